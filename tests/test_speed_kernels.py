"""Fast kernels of the windowed measurement against independent computations.

Each vectorised replacement of a per-object Python loop is compared here with
the straightforward computation it replaced (scipy, or a loop written out).
"""
import numpy as np
from scipy import ndimage

from glaciar.engine.windows import label_boxes


def test_label_boxes_equal_find_objects():
    rng = np.random.default_rng(1)
    for shape, frac in (((157, 211), 0.08), ((40, 3), 0.5), ((1, 50), 0.3), ((64, 64), 0.0)):
        mask = rng.random(shape) < frac
        comp, n = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
        cb = label_boxes(comp, n)
        assert cb.shape == (n + 1, 4) and cb.dtype == np.int64
        assert np.all(cb[0] == 0)
        for c, sl in enumerate(ndimage.find_objects(comp), start=1):
            assert tuple(cb[c]) == (sl[0].start, sl[0].stop, sl[1].start, sl[1].stop)
