"""Canvases of windows (glaciar.engine.canvas) against independent computations.

Box helpers against scipy, and the packing of windows into one array.
"""
import numpy as np
from scipy import ndimage

from glaciar.engine.canvas import label_boxes


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


def test_pack_windows_places_disjoint_rectangles_with_gaps():
    from glaciar.engine.canvas import pack_windows

    rng = np.random.default_rng(7)
    for k, gap in ((1, 3), (7, 2), (100, 3), (60, 4)):
        h = rng.integers(5, 80, k)
        w = rng.integers(5, 80, k)
        oy, ox, shape = pack_windows(h, w, gap)
        # every rectangle, grown by the gap, inside the canvas and disjoint from the others
        occ = np.zeros(shape, dtype=np.int64)
        for i in range(k):
            assert oy[i] >= gap and ox[i] >= gap
            assert oy[i] + h[i] + gap <= shape[0] and ox[i] + w[i] + gap <= shape[1]
            occ[oy[i]:oy[i] + h[i] + gap, ox[i]:ox[i] + w[i] + gap] += 1
        assert occ.max() == 1
        # no worse than one shelf row of the widest width per rectangle
        assert shape[0] * shape[1] <= ((h + gap).max() + gap) * (np.sum(w + gap) + gap)
