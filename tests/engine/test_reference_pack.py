"""glaciar.engine.reference: the split regions' replay packed into few columns.

``pack_columns``' rules are checked directly (power-of-two column ranges, distance to the
edges and between regions, completion order of regions ending on one row); that the packed
replay gives sep's whole-frame answer is checked against one ``sep.extract`` call on a wide
image crowded with blended pairs in every column range (an independent computation).
"""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import sep
from scipy import ndimage

from glaciar.engine.detect import DetectionParams
from glaciar.engine.reference import pack_columns, strip_extract

HF = 2                                   # the default 5 x 5 filter's half-width


def _layout(seed, ny=400, nx=3000, n=900, edge_boxes=True):
    """Random disjoint boxes (y0, y1, x0, x1), 2 px apart at least, in sep's emission order
    (last row, then first column)."""
    rng = np.random.default_rng(seed)
    taken = np.zeros((ny, nx), dtype=bool)
    boxes = []
    for _ in range(n):
        h, w = rng.integers(2, 20, 2)
        y, x = int(rng.integers(0, ny - h)), int(rng.integers(0, nx - w))
        if not taken[max(0, y - 2):y + h + 2, max(0, x - 2):x + w + 2].any():
            taken[y:y + h, x:x + w] = True
            boxes.append((y, y + h, x, x + w))
    if edge_boxes:
        for y, x, h, w in ((5, 0, 4, 3), (50, nx - 3, 6, 3), (120, 1020, 5, 9)):   # edges, straddling 1024
            if not taken[max(0, y - 2):y + h + 2, max(0, x - 2):x + w + 2].any():
                boxes.append((y, y + h, x, x + w))
    b = np.array(boxes, dtype=np.int64)
    return b[np.lexsort((b[:, 2], b[:, 1]))]


def _check_rules(boxes, shift, nx, hf):
    y0, y1, x0, x1 = boxes.T
    n0, n1 = x0 + shift, x1 + shift
    moved = shift != 0
    # a moved region's columns stay in the power-of-two range of its own, away from the edges
    for a, b in ((x0[moved], n0[moved]), (x1[moved] - 1, n1[moved] - 1)):
        np.testing.assert_array_equal(np.floor(np.log2(b)), np.floor(np.log2(a)))
    assert (n0[moved] >= 2 * hf + 1).all() and (n1[moved] <= nx - 2 * hf - 1).all()
    # a region whose columns span two ranges, or near an edge, stays
    spans = np.floor(np.log2(np.maximum(x0, 1))) != np.floor(np.log2(x1 - 1))
    assert not moved[spans | (x0 < 2 * hf + 1) | (x1 > nx - 2 * hf - 1)].any()
    # boxes grown by hf + 1 are disjoint (paint them: no pixel twice) unless both stayed
    g = hf + 1
    paint = np.zeros((int(y1.max()) + g, int(n1.max()) + g), dtype=np.int32)
    for i in np.flatnonzero(moved):
        paint[max(0, y0[i] - g):y1[i] + g, max(0, n0[i] - g):n1[i] + g] += 1
    assert paint.max() <= 1
    for i in np.flatnonzero(~moved):
        assert not paint[max(0, y0[i] - g):y1[i] + g, max(0, n0[i] - g):n1[i] + g].any()
    # regions ending on one row: left to right in emission order
    for y in np.unique(y1):
        on = np.flatnonzero(y1 == y)
        assert (np.diff(n0[on]) > 0).all() and (n0[on][1:] >= n1[on][:-1]).all()


def test_pack_columns_rules_and_gain():
    boxes = _layout(1)
    nx = 3000
    shift = pack_columns(boxes, nx, HF)
    assert shift is not None and shift.shape == (len(boxes),)
    _check_rules(boxes, shift, nx, HF)
    assert np.count_nonzero(shift) > 0.9 * len(boxes)

    # the gain: memory pages (256 float32 columns here) the grown boxes touch, row by row
    def pages(x0, x1):
        g = 2 * HF + 1
        return len({(r, p) for (a, b), c, d in zip(boxes[:, :2], x0, x1)
                    for r in range(a - g, b + g) for p in range((c - g) // 256, (d + g - 1) // 256 + 1)})
    assert pages(boxes[:, 2] + shift, boxes[:, 3] + shift) < 0.8 * pages(boxes[:, 2], boxes[:, 3])


def test_pack_columns_keeps_nested_regions_in_completion_order():
    # a small region inside a larger one's box, both ending on row 40: sep completes the
    # inner one first here (its emission order is given), so it must stay left of the other
    boxes = np.array([(10, 30, 1500, 1510), (5, 41, 1200, 1240), (30, 41, 1210, 1220),
                      (20, 41, 1300, 1330)], dtype=np.int64)[[0, 2, 1, 3]]
    shift = pack_columns(boxes, 2000, HF)
    assert shift is not None
    new0 = boxes[:, 2] + shift
    assert new0[1] + 10 <= new0[2] and new0[2] + 40 <= new0[3]
    _check_rules(boxes, shift, 2000, HF)


def _crowded(ny, nx, n, seed):
    """Noise and n blended pairs of galaxies spread over every column range (written here)."""
    rng = np.random.default_rng(seed)
    img = rng.normal(0.0, 1.0, (ny, nx)).astype(np.float32)
    for _ in range(n):
        y, x = rng.uniform(6, ny - 6), np.exp(rng.uniform(np.log(8.0), np.log(nx - 8.0)))
        for dy, dx, f in ((0.0, 0.0, 1.0), tuple(rng.normal(0, 2.5, 2)) + (0.6,)):
            s = rng.uniform(0.9, 2.2)
            cy, cx = y + dy, x + dx
            a, b = int(max(0, cy - 5 * s)), int(min(ny, cy + 5 * s + 1))
            c, d = int(max(0, cx - 5 * s)), int(min(nx, cx + 5 * s + 1))
            yy, xx = np.mgrid[a:b, c:d]
            amp = f * 10 ** rng.uniform(1.3, 2.5) / (2 * np.pi * s * s)
            img[a:b, c:d] += (amp * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * s * s))).astype(np.float32)
    rms = np.ones((ny, nx), dtype=np.float32)
    rms[:, nx // 3:] = 1.2
    return img, rms


@pytest.fixture(scope="module")
def crowded():
    params = DetectionParams(detect_thresh=1.5)
    img, rms = _crowded(160, 2300, 1400, 5)
    sep.set_extract_pixstack(img.size + 1024)
    cat, seg = sep.extract(img, params.detect_thresh, err=rms, minarea=params.detect_minarea,
                           filter_kernel=params.filter_kernel, filter_type="conv",
                           deblend_nthresh=params.deblend_nthresh, deblend_cont=params.deblend_mincont,
                           clean=False, segmentation_map=True)
    return img, rms, params, cat, seg


@pytest.mark.parametrize("rows", [9, 40])
def test_packed_replay_equals_the_whole_frame(crowded, rows):
    img, rms, params, cat, seg = crowded
    assert np.count_nonzero(cat["flag"] & sep.OBJ_MERGED) > 200     # many split regions
    # the split regions (8-connected footprints holding 2+ objects), in sep's order: most move
    lab, _ = ndimage.label(seg > 0, structure=np.ones((3, 3), dtype=bool))
    region = np.zeros(len(cat) + 1, dtype=np.int64)
    region[seg[seg > 0]] = lab[seg > 0]
    labels, first, count = np.unique(region[1:], return_index=True, return_counts=True)
    split = labels[count > 1][np.argsort(first[count > 1])]
    boxes = np.array([(s[0].start, s[0].stop, s[1].start, s[1].stop)
                      for s in (ndimage.find_objects(lab)[k - 1] for k in split)])
    shift = pack_columns(boxes, img.shape[1], HF)
    moved = np.floor(np.log2(boxes[shift != 0, 2]))
    assert np.count_nonzero(shift) > 0.5 * len(boxes) and len(np.unique(moved)) >= 4
    with warnings.catch_warnings():
        warnings.simplefilter("error")     # the packed replay falls back to true columns with one
        cat_s, seg_s = strip_extract(img, rms, None, params, strip_rows=rows, halo=4)
    assert len(cat_s) == len(cat)
    for name in cat.dtype.names:
        np.testing.assert_array_equal(cat_s[name], cat[name], err_msg=name)
    np.testing.assert_array_equal(seg_s, seg)

