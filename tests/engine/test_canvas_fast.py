"""The detection canvas against an independent construction, bit for bit.

``Canvas`` tiles the detection windows into one array (injected pixels, RMS,
no-data mask, gaps, reference segmentation); its per-window loop now slices
with precomputed canvas boxes.  Here every window of the canvas is rebuilt
directly from the inputs (base + stamps in order, float32 RMS, mask, reference
segmentation) and compared exactly, gaps included.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from glaciar.engine.canvas import Canvas
from glaciar.engine.scene import Scene


@pytest.fixture(scope="module")
def canvas_case():
    rng = np.random.default_rng(24)
    ny, nx = 40, 50
    base = rng.normal(0.0, 1.0, (ny, nx)).astype(np.float32)
    rms = rng.uniform(0.5, 2.0, (ny, nx)).astype(np.float32)
    rms[5, 7] = np.nan                   # no data through the RMS
    rms[30, 40] = 0.0
    base[12, 20] = np.nan                # no data through the image
    mask = np.zeros((ny, nx), dtype=bool)
    mask[20:23, 3:6] = True
    ref = rng.integers(0, 4, (ny, nx)).astype(np.int32)
    stamps = [(y0, x0, rng.uniform(0.0, 3.0, (h, w)))
              for y0, x0, h, w in ((2, 3, 9, 11), (6, 8, 7, 7), (-3, 40, 10, 14), (25, 10, 12, 9))]
    scene = Scene(base, stamps)
    params = SimpleNamespace(threshold_rms="pixel", filter_kernel=None)
    ctx = SimpleNamespace(det_scene=scene, det_rms=rms, mask=mask, ref_segmap=ref, gap=3,
                          params=params, shape=(ny, nx))
    rects = np.array([[0, 12, 0, 15], [4, 16, 5, 20], [0, 8, 36, 50], [22, 40, 0, 30], [30, 40, 38, 50]],
                     dtype=np.int64)
    return ctx, base, rms, mask, ref, stamps, rects, Canvas(ctx, rects)


def _injected(base, stamps, y0, y1, x0, x1):
    """The injected window, stamp by stamp in order, from a padded float64 copy of the base."""
    pad = 20
    img = np.full((base.shape[0] + 2 * pad, base.shape[1] + 2 * pad), np.nan)
    img[pad:-pad, pad:-pad] = base.astype(np.float64)
    for sy, sx, d in stamps:
        img[pad + sy:pad + sy + d.shape[0], pad + sx:pad + sx + d.shape[1]] += d
    return img[pad + y0:pad + y1, pad + x0:pad + x1]


def test_every_window_is_the_inputs_bit_for_bit(canvas_case):
    ctx, base, rms, mask, ref, stamps, rects, cv = canvas_case
    for k, (y0, y1, x0, x1) in enumerate(rects.tolist()):
        sl = (slice(cv.oy[k], cv.oy[k] + y1 - y0), slice(cv.ox[k], cv.ox[k] + x1 - x0))
        det = _injected(base, stamps, y0, y1, x0, x1)
        err = rms[y0:y1, x0:x1].astype(np.float32)
        bad = mask[y0:y1, x0:x1] | ~np.isfinite(det) | ~(np.isfinite(err) & (err > 0))
        det = np.where(bad, 0.0, det)
        err = np.where(bad, np.float32(1.0), err)
        assert cv.det[sl].tobytes() == det.tobytes()
        assert cv.det32[sl].tobytes() == det.astype(np.float32).tobytes()
        assert cv.err[sl].tobytes() == err.tobytes()
        assert np.array_equal(cv.nodata[sl], bad)
        assert np.array_equal(cv.ref[sl], ref[y0:y1, x0:x1])
    # threshold RMS "pixel": the RMS sep's threshold multiplies is the canvas RMS itself
    assert cv.derr is cv.err


def test_gaps_are_blank_no_data(canvas_case):
    ctx, base, rms, mask, ref, stamps, rects, cv = canvas_case
    inside = np.zeros(cv.shape, dtype=bool)
    for k, (y0, y1, x0, x1) in enumerate(rects.tolist()):
        inside[cv.oy[k]:cv.oy[k] + y1 - y0, cv.ox[k]:cv.ox[k] + x1 - x0] = True
    gap = ~inside
    assert gap.any()
    assert np.all(cv.det[gap] == 0.0) and np.all(cv.err[gap] == 1.0)
    assert np.all(cv.nodata[gap]) and np.all(cv.ref[gap] == 0)
