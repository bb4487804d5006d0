"""Sparse placement (glaciar.engine.positions._Sparse): same positions, no full-frame arrays.

The sparse path must reproduce the two-map path exactly (same centre pixels, same
random stream consumed) on sparse and crowded fields, through every hand-over to
the maps (bound failing mid-task, exact enumeration, footprint under a quarter of
the grid); on a field where it stays sparse, its draws follow the documented law
(a brute-force reference written here); and it allocates no frame-sized array.
"""
import tracemalloc

import numpy as np
import pytest

from glaciar.engine import positions
from glaciar.engine.positions import draw_positions


def _valid(fp, placed, h, w):
    """Flat indices (row-major) of footprint pixels where a box (h, w) meets none of the
    placed boxes (y, x, h_k, w_k): brute force over the whole grid."""
    yy, xx = np.nonzero(fp)
    ok = np.ones(yy.size, bool)
    for cy, cx, a, b in placed:
        ok &= ~((np.abs(yy - cy) <= a + h) & (np.abs(xx - cx) <= b + w))
    return yy[ok] * fp.shape[1] + xx[ok]


def _count_dense(monkeypatch):
    calls = []
    real = positions._Sparse.dense

    def counting(self):
        calls.append(len(self.boxes))
        return real(self)

    monkeypatch.setattr(positions._Sparse, "dense", counting)
    return calls


def _both(fp, hh, hw, seed, n_footprint=None):
    out = []
    for sparse in (True, False):
        rng = np.random.default_rng(seed)
        pix = positions._place(rng, fp, np.asarray(hh), np.asarray(hw), n_footprint, sparse=sparse)
        out.append((pix, rng.bit_generator.state))
    return out


def _field(kind):
    rng = np.random.default_rng(11)
    if kind == "sparse":          # large field, few sources: stays sparse
        fp = np.ones((600, 700), bool)
        fp[200:230, :] = False
        fp[:, 500:520] = False
        return fp, rng.integers(3, 15, 40), rng.integers(3, 15, 40)
    if kind == "crowded":         # fills up: the bound fails mid-task, then compaction, then stop
        fp = np.ones((120, 150), bool)
        fp[40:50, 30:140] = False
        return fp, rng.integers(2, 9, 400), rng.integers(2, 9, 400)
    if kind == "small footprint":  # under a quarter of the grid: the maps from the start
        fp = np.zeros((200, 200), bool)
        fp[10:90, 20:100] = True
        return fp, rng.integers(2, 6, 60), rng.integers(2, 6, 60)
    raise ValueError(kind)


@pytest.mark.parametrize("kind", ["sparse", "crowded", "small footprint"])
def test_sparse_path_gives_the_maps_positions(kind, monkeypatch):
    fp, hh, hw = _field(kind)
    handovers = _count_dense(monkeypatch)
    for seed in range(6):
        (a, sa), (b, sb) = _both(fp, hh, hw, seed)
        np.testing.assert_array_equal(a, b)
        assert sa == sb                       # the same random numbers were consumed
    if kind == "sparse":
        assert handovers == [] and a.size == hh.size
    elif kind == "crowded":
        assert handovers and min(handovers) > 0 and a.size < hh.size   # sparse first, then maps
    else:
        assert handovers == [0] * 6


def test_sparse_path_gives_the_maps_positions_with_enumeration(monkeypatch):
    """Every source through the exact enumeration (no rejection tolerated): the hand-over
    happens at the first source and the stream stays the maps' one."""
    monkeypatch.setattr(positions, "_max_tries", lambda n_pixels: 0)
    fp, hh, hw = _field("sparse")
    for seed in range(3):
        (a, sa), (b, sb) = _both(fp, hh, hw, seed)
        np.testing.assert_array_equal(a, b)
        assert sa == sb


def test_given_footprint_count_is_the_counted_one():
    fp, hh, hw = _field("crowded")
    x1, y1 = draw_positions(np.random.default_rng(5), fp, hh, hw)
    x2, y2 = draw_positions(np.random.default_rng(5), fp, hh, hw, n_footprint=int(fp.sum()))
    np.testing.assert_array_equal(x1, x2)
    np.testing.assert_array_equal(y1, y2)


def test_sparse_draws_are_valid_and_uniform_against_brute_force(monkeypatch):
    """On a field where the placement stays sparse: each centre pixel is one of its valid
    pixels (brute force) and its rank among them is uniform (chi-square on deciles)."""
    from scipy import stats

    handovers = _count_dense(monkeypatch)
    fp = np.ones((90, 110), bool)
    fp[30:36, :] = False
    fp[60:80, 70:100] = False
    hh = np.array([4, 2, 6, 3, 5, 2, 3, 4])
    hw = np.array([3, 5, 2, 4, 2, 3, 6, 2])
    ranks = []
    for seed in range(400):
        pix = positions._place(np.random.default_rng(seed), fp, hh, hw, None)
        assert pix.size == hh.size
        placed = []
        for k, p in enumerate(pix):
            valid = _valid(fp, placed, hh[k], hw[k])
            r = np.searchsorted(valid, p)
            assert r < valid.size and valid[r] == p
            ranks.append(r / valid.size)
            placed.append((p // fp.shape[1], p % fp.shape[1], hh[k], hw[k]))
    assert handovers == []
    counts = np.histogram(ranks, bins=10, range=(0, 1))[0]
    assert stats.chisquare(counts).pvalue > 1e-3


def test_no_frame_sized_allocation():
    """100 sources on a 3000 x 3000 footprint (9 MB of bool): the placement allocates
    well under one frame (the maps would allocate two)."""
    fp = np.ones((3000, 3000), bool)
    n_fp = fp.size
    rng = np.random.default_rng(2)
    hh, hw = rng.integers(5, 30, 100), rng.integers(5, 30, 100)
    tracemalloc.start()
    try:
        x, _ = draw_positions(np.random.default_rng(3), fp, hh, hw, n_footprint=n_fp)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert x.size == 100
    assert peak < fp.nbytes / 20
