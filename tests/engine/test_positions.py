"""Placement of injected sources (glaciar.engine.positions) against references written here.

The documented distribution: sources are placed in index order; source k's centre
pixel is uniform over the footprint pixels where its box meets none of the boxes
already placed, its offset inside the pixel uniform; placement stops at the first
source with no such pixel.  The references below compute those valid pixels by
brute force from the box-intersection condition (no code of the module is used),
and the uniformity checks are probability-integral transforms that are exactly
U(0, 1) under the documented distribution, tested with Kolmogorov-Smirnov at
p > 1e-3 (fixed seeds: deterministic; a correct sampler fails a fresh seed with
probability 1e-3).  Each uniformity test has a control: a sampler biased in the way
the test should catch, which must fail it.
"""
import time
import tracemalloc

import numpy as np
import pytest
from scipy import stats

from glaciar.engine import positions
from glaciar.engine.positions import draw_positions, placement_capacity

P_MIN = 1e-3


# ---------------------------------------------------------------- references
def _boxes_disjoint(x, y, hh, hw):
    """Brute force over pairs: inclusive pixel intervals [c - h, c + h] overlap on both axes."""
    iy, ix = np.rint(y).astype(int), np.rint(x).astype(int)
    for i in range(x.size):
        for j in range(i + 1, x.size):
            rows = max(iy[i] - hh[i], iy[j] - hh[j]) <= min(iy[i] + hh[i], iy[j] + hh[j])
            cols = max(ix[i] - hw[i], ix[j] - hw[j]) <= min(ix[i] + hw[i], ix[j] + hw[j])
            if rows and cols:
                return False
    return True


def _valid_pixels(fp, iy, ix, phh, phw, h, w):
    """(row, col) of the footprint pixels, in row-major order, where a box (h, w) meets none
    of the boxes centred at (iy, ix) with half sizes (phh, phw)."""
    yy, xx = np.nonzero(fp)
    ok = np.ones(yy.size, bool)
    for cy, cx, a, b in zip(iy, ix, phh, phw):
        ok &= ~((np.abs(yy - cy) <= a + h) & (np.abs(xx - cx) <= b + w))
    return yy[ok], xx[ok]


def _pit(fp, x, y, hh, hw, n_requested):
    """Probability-integral transforms of each placed source under the documented law.

    Row-major: (rank of the pixel among the valid ones in row-major order + x fraction) /
    number valid; column-major likewise with the y fraction.  Both are U(0, 1) exactly when
    the pixel is uniform over the valid ones and the offset uniform inside it.  Also checks
    that every chosen pixel was valid and that placement stopped only when nothing fitted.
    """
    iy, ix = np.rint(y).astype(int), np.rint(x).astype(int)
    fx, fy = x - ix + 0.5, y - iy + 0.5
    ny, nx = fp.shape
    u_row, u_col = [], []
    for k in range(x.size + (x.size < n_requested)):
        vy, vx = _valid_pixels(fp, iy[:k], ix[:k], hh[:k], hw[:k], hh[k], hw[k])
        if k == x.size:                      # the source placement stopped at
            assert vy.size == 0, f"stopped at source {k} with {vy.size} valid pixels left"
            break
        row_major = vy * nx + vx
        col_major = np.sort(vx * ny + vy)
        r = np.searchsorted(row_major, iy[k] * nx + ix[k])
        c = np.searchsorted(col_major, ix[k] * ny + iy[k])
        assert r < row_major.size and row_major[r] == iy[k] * nx + ix[k], f"source {k} not valid"
        u_row.append((r + fx[k]) / row_major.size)
        u_col.append((c + fy[k]) / col_major.size)
    return np.array(u_row), np.array(u_col)


def _irregular_footprint():
    fp = np.zeros((48, 64), bool)
    fp[2:46, 3:62] = True
    fp[20:24, :] = False            # a chip gap
    fp[30:40, 40:52] = False        # a masked star
    return fp


def _sizes(seed, n):
    r = np.random.default_rng(10_000 + seed)
    return r.integers(1, 6, n), r.integers(1, 6, n)


def _column_biased_sampler(rng, fp, hh, hw):
    """Control: valid pixels chosen with weight 1 + column (right-leaning), offsets uniform."""
    iy, ix = [], []
    for k in range(hh.size):
        vy, vx = _valid_pixels(fp, iy, ix, hh[:k], hw[:k], hh[k], hw[k])
        if vy.size == 0:
            break
        wgt = 1.0 + vx
        j = rng.choice(vy.size, p=wgt / wgt.sum())
        iy.append(vy[j])
        ix.append(vx[j])
    iy, ix = np.array(iy), np.array(ix)
    return ix + rng.uniform(-0.5, 0.5, ix.size), iy + rng.uniform(-0.5, 0.5, iy.size)


# ---------------------------------------------------------------- tests
def test_positions_inside_footprint_and_disjoint():
    rng = np.random.default_rng(1)
    fp = np.zeros((300, 400), bool)
    fp[50:250, 20:380] = True
    fp[100:120, :] = False           # a chip gap
    hh = rng.integers(2, 12, 60)
    hw = rng.integers(2, 12, 60)
    x, y = draw_positions(rng, fp, hh, hw)
    assert x.size == 60
    assert fp[np.rint(y).astype(int), np.rint(x).astype(int)].all()
    assert _boxes_disjoint(x, y, hh, hw)


@pytest.mark.parametrize("path", ["as shipped", "exact enumeration only"])
def test_positions_follow_the_documented_sequential_law(path, monkeypatch):
    """Every source's pixel is uniform over its valid pixels (brute-force reference) and its
    offset uniform in the pixel: row- and column-major PITs are U(0, 1) (KS p > 1e-3).

    The sampler draws by rejection and falls back to enumerating the valid pixels after
    a number of rejections; with that number set to 0 every source goes through the
    enumeration, so both ways of drawing are checked against the law."""
    if path != "as shipped":
        monkeypatch.setattr(positions, "_max_tries", lambda n_pixels: 0)
    fp = _irregular_footprint()
    u_row, u_col, stopped = [], [], 0
    for seed in range(100):
        hh, hw = _sizes(seed, 35)
        x, y = draw_positions(np.random.default_rng(seed), fp, hh, hw)
        assert _boxes_disjoint(x, y, hh, hw)
        stopped += x.size < hh.size
        a, b = _pit(fp, x, y, hh, hw, hh.size)
        u_row.append(a)
        u_col.append(b)
    u_row, u_col = np.concatenate(u_row), np.concatenate(u_col)
    assert u_row.size > 3000
    assert stopped > 10              # the stopping rule was exercised (checked inside _pit)
    assert stats.kstest(u_row, "uniform").pvalue > P_MIN
    assert stats.kstest(u_col, "uniform").pvalue > P_MIN


def test_sequential_law_check_catches_a_biased_sampler():
    """Control for the test above: a sampler leaning to the right fails it."""
    fp = _irregular_footprint()
    u_col = []
    for seed in range(40):
        hh, hw = _sizes(seed, 30)
        x, y = _column_biased_sampler(np.random.default_rng(seed), fp, hh, hw)
        u_col.append(_pit(fp, x, y, hh, hw, hh.size)[1])
    assert stats.kstest(np.concatenate(u_col), "uniform").pvalue < 1e-6


def test_first_source_uniform_over_footprint():
    """The first source of a task is uniform over the footprint: a chi-square over regions
    of known area, and a KS of x against the analytic uniform on the continuous interval."""
    fp = np.zeros((200, 200), bool)
    fp[:, 20:150] = True            # 200 x 130
    fp[:50, 170:190] = True         # 50 x 20, disjoint
    fp[90:100, :] = False           # a chip gap
    areas = np.array([fp[:, :100].sum(), fp[:, 100:160].sum(), fp[:, 160:].sum()], float)
    xs, ys = [], []
    for seed in range(3000):
        x, y = draw_positions(np.random.default_rng(seed), fp, [7], [5])
        xs.append(x[0])
        ys.append(y[0])
    xs, ys = np.array(xs), np.array(ys)
    counts = np.array([np.sum(xs < 99.5), np.sum((xs >= 99.5) & (xs < 159.5)), np.sum(xs >= 159.5)])
    assert stats.chisquare(counts, areas / areas.sum() * xs.size).pvalue > P_MIN
    assert not np.any((ys > 89.5) & (ys < 99.5))
    main = xs < 159.5               # x uniform on [19.5, 149.5) there
    assert stats.kstest(xs[main], stats.uniform(19.5, 130.0).cdf).pvalue > P_MIN


def test_subpixel_offsets_uniform_and_clipping_cannot_fake_it():
    """Fractional parts of x and y are U[0, 1) (KS p > 1e-3); a sampler whose offsets are
    a clipped normal (sigma 0.2 pixel) keeps every centre inside its pixel (all the old
    test checked) and fails the same KS test."""
    fp = np.ones((400, 400), bool)
    x, y = draw_positions(np.random.default_rng(3), fp, np.full(1500, 2), np.full(1500, 3))
    assert x.size == 1500
    fx, fy = x - np.rint(x) + 0.5, y - np.rint(y) + 0.5
    assert stats.kstest(fx, "uniform").pvalue > P_MIN
    assert stats.kstest(fy, "uniform").pvalue > P_MIN
    # Control: centre pixels as drawn, offsets N(0, 0.2) clipped into the pixel.
    rng = np.random.default_rng(4)
    xb = np.rint(x) + np.clip(rng.normal(0, 0.2, x.size), -0.5 + 1e-9, 0.5 - 1e-9)
    fb = xb - np.rint(xb) + 0.5
    assert np.all((fb > 0) & (fb < 1))
    assert stats.kstest(fb, "uniform").pvalue < 1e-6


def test_positions_deterministic_for_a_seed():
    fp = _irregular_footprint()
    hh, hw = _sizes(0, 25)
    a = draw_positions(np.random.default_rng(3), fp, hh, hw)
    b = draw_positions(np.random.default_rng(3), fp, hh, hw)
    c = draw_positions(np.random.default_rng(4), fp, hh, hw)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0][:c[0].size], c[0][:a[0].size])


@pytest.mark.parametrize("masked_half", [False, True])
def test_capacity_exact_on_a_hand_countable_field(masked_half):
    """A 90 x 90 footprint of 9 x 9 boxes (half size 4) holds 10 x 10 = 100 of them: the
    lattice below places 100, and 101 cannot fit (9 x 9 cells from the corner: two centres
    in one cell are < 9 apart on both axes).  Masking the right half leaves 10 x 5 = 50."""
    fp = np.zeros((120, 130), bool)
    fp[10:100, 20:110] = True
    if masked_half:
        fp[:, 65:] = False
    expect = 50 if masked_half else 100
    lattice_y, lattice_x = np.meshgrid(np.arange(14, 100, 9), np.arange(24, 110, 9), indexing="ij")
    inside = fp[lattice_y, lattice_x]
    assert inside.sum() == expect and _boxes_disjoint(lattice_x[inside], lattice_y[inside],
                                                      np.full(expect, 4), np.full(expect, 4))
    cap = placement_capacity(fp, 4, 4)
    assert cap.upper_bound == expect
    assert 0 < cap.random_fill <= expect


def test_capacity_rectangle_with_unequal_sides():
    # rows 7..56 (50), cols 3..79 (77); boxes 5 x 7: ceil(50/5) * ceil(77/7) = 10 * 11
    fp = np.zeros((60, 90), bool)
    fp[7:57, 3:80] = True
    assert placement_capacity(fp, 2, 3).upper_bound == 110
    # mixed sizes: the bound is that of the smallest box
    assert placement_capacity(fp, [2, 5, 9], [3, 8, 4]).upper_bound == 110


def test_upper_bound_never_exceeded():
    """On irregular footprints, no fill (random or greedy raster, written here) beats the bound."""
    rng = np.random.default_rng(5)
    for trial in range(6):
        fp = rng.random((40, 50)) < 0.9
        fp[rng.integers(0, 40):, rng.integers(0, 50):] = False
        h, w = int(rng.integers(0, 3)), int(rng.integers(0, 3))
        ub = placement_capacity(fp, h, w).upper_bound
        # greedy raster fill (a reference placement)
        placed = []
        for py, px in zip(*np.nonzero(fp)):
            if all(abs(py - qy) > 2 * h or abs(px - qx) > 2 * w for qy, qx in placed):
                placed.append((py, px))
        assert len(placed) <= ub
        x, _ = draw_positions(rng, fp, np.full(ub + 5, h), np.full(ub + 5, w))
        assert x.size <= ub


def test_million_requested_on_a_small_field_returns_what_fits_quickly():
    fp = np.ones((200, 200), bool)
    fp[60:80, 100:200] = False
    n = 10**6
    rng = np.random.default_rng(6)
    hh, hw = rng.integers(3, 7, n), rng.integers(3, 7, n)
    t0 = time.perf_counter()
    x, y = draw_positions(np.random.default_rng(7), fp, hh, hw)
    elapsed = time.perf_counter() - t0
    assert elapsed < 2.0
    m = x.size
    assert 0 < m <= placement_capacity(fp, hh, hw).upper_bound
    assert fp[np.rint(y).astype(int), np.rint(x).astype(int)].all()
    assert _boxes_disjoint(x, y, hh[:m], hw[:m])
    # it stopped because source m has no valid pixel left (brute force)
    vy, _ = _valid_pixels(fp, np.rint(y).astype(int), np.rint(x).astype(int), hh[:m], hw[:m],
                          hh[m], hw[m])
    assert vy.size == 0


def test_empty_footprint_and_bad_sizes():
    x, y = draw_positions(np.random.default_rng(0), np.zeros((10, 10), bool), [1, 1], [1, 1])
    assert x.size == 0 and y.size == 0
    assert placement_capacity(np.zeros((10, 10), bool), 1, 1) == (0, 0)
    with pytest.raises(ValueError):
        draw_positions(np.random.default_rng(0), np.ones((10, 10), bool), [1, 1], [1])
    with pytest.raises(ValueError):
        draw_positions(np.random.default_rng(0), np.ones((10, 10), bool), [-1], [1])


# ------------------------------------------------------------------------------
# Sparse placement (glaciar.engine.positions._Sparse): same positions, no full-frame arrays.
#
# The sparse path must reproduce the two-map path exactly (same centre pixels, same
# random stream consumed) on sparse and crowded fields, through every hand-over to
# the maps (bound failing mid-task, exact enumeration, footprint under a quarter of
# the grid); on a field where it stays sparse, its draws follow the documented law
# (a brute-force reference written here); and it allocates no frame-sized array.
# ------------------------------------------------------------------------------
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
