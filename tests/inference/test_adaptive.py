"""The adaptive loop's acquisition rule, allocation, candidates, stopping statistic, driver."""
import math

import numpy as np
import pytest
from scipy import stats

from glaciar.inference.adaptive import (REQUEST_DTYPE, acquisition_score, allocate_sources,
                                        allocate_variance_reduction,
                                        candidate_grid, information_gain, max_posterior_sd,
                                        merge_cells, misfit_on_candidates, plan_round,
                                        propose_cells, run_design)
from glaciar.inference.models import Cells


def _h(ps):
    """Entropy [nats] written out by hand."""
    return -sum(p * math.log(p) for p in ps if p > 0)


# --------------------------------------------------------------------------
# Information gain
# --------------------------------------------------------------------------
def test_information_gain_of_a_two_draw_posterior_is_the_hand_value():
    # Binary outcome, P = 0.2 or 0.6 with equal weight.
    hand = _h([0.4, 0.6]) - 0.5 * (_h([0.2, 0.8]) + _h([0.6, 0.4]))
    assert information_gain(np.array([0.2, 0.6])) == pytest.approx(hand, rel=1e-12)
    # Three outcomes: (C, S) = (0.5, 0.2) or (0.9, 0.8):
    # (selected, recovered-not-selected, missed) = (0.1, 0.4, 0.5) or (0.72, 0.18, 0.1).
    d1, d2 = (0.1, 0.4, 0.5), (0.72, 0.18, 0.1)
    mean = [(a + b) / 2 for a, b in zip(d1, d2)]
    hand3 = _h(mean) - 0.5 * (_h(d1) + _h(d2))
    # Independently: mutual information = mean KL(per-draw || mean predictive).
    kl = 0.5 * sum(sum(p * math.log(p / q) for p, q in zip(d, mean)) for d in (d1, d2))
    assert hand3 == pytest.approx(kl, rel=1e-12)
    got = information_gain(np.array([0.5, 0.9]), np.array([0.2, 0.8]), outcomes="all")
    assert got == pytest.approx(hand3, rel=1e-12)
    # Binary "selected" outcome of the same posterior: P = 0.1 or 0.72.
    hand_sel = _h([0.41, 0.59]) - 0.5 * (_h([0.1, 0.9]) + _h([0.72, 0.28]))
    assert information_gain(np.array([0.5, 0.9]), np.array([0.2, 0.8])) == pytest.approx(hand_sel)
    # The chain rule: three outcomes carry at least the binary one's information.
    assert hand3 >= hand_sel


def test_information_gain_is_zero_where_draws_agree_and_bounded():
    rng = np.random.default_rng(1)
    c = np.repeat(rng.uniform(0, 1, (1, 4, 3)), 50, axis=0)
    s = np.repeat(rng.uniform(0, 1, (1, 4, 3)), 50, axis=0)
    # Zero up to the rounding of a mean of equal numbers.
    assert np.all(np.abs(information_gain(c, s, "all")) < 1e-14)
    assert np.all(np.abs(information_gain(c * s)) < 1e-14)
    # Certain outcomes (0 or 1) and S = NaN where C = 0 are handled.
    assert information_gain(np.array([0.0, 0.0]), np.array([np.nan, np.nan]), "all") == 0.0
    # The maximum: draws split evenly between certain outcomes.
    assert information_gain(np.array([0.0, 1.0])) == pytest.approx(math.log(2))
    three = information_gain(np.array([0.0, 1.0, 1.0]), np.array([0.0, 0.0, 1.0]), "all")
    assert three == pytest.approx(math.log(3))


def test_width_and_information_rank_the_same_cells():
    # P near 0.5 with a spread that varies cell to cell: both criteria follow the spread.
    rng = np.random.default_rng(2)
    nz, nm, nd = 8, 6, 2000
    mu = rng.uniform(0.3, 0.7, (nz, nm))
    sd = rng.uniform(0.005, 0.1, (nz, nm))
    draws = np.clip(mu + sd * rng.standard_normal((nd, nz, nm)), 0, 1)
    z, m = np.arange(nz, dtype=float), np.arange(nm, dtype=float)
    w = propose_cells(draws, z, m, nz * nm)
    i = propose_cells(draws, z, m, nz * nm, criterion="information")
    key = lambda a: list(zip(a["z"], a["mag"]))                                # noqa: E731
    assert len(set(key(w[:10])) & set(key(i[:10]))) >= 8
    rank_w = {c: r for r, c in enumerate(key(w))}
    rank_i = [rank_w[c] for c in key(i)]
    assert stats.spearmanr(np.arange(nz * nm), rank_i)[0] > 0.9
    # Fields of the extended output: info is the score, sd is numpy's sd of the draws.
    assert np.allclose(i["score"], i["info"])
    assert i["sd"][0] == pytest.approx(draws[:, int(i["z"][0]), int(i["mag"][0])].std())


def test_misfit_and_weight_terms():
    gain = np.array([[0.3, 0.1], [0.2, 0.05]])
    misfit = np.array([[False, False], [False, True]])
    s = acquisition_score(gain, misfit=misfit, misfit_weight=1.0)
    assert s[1, 1] == pytest.approx(0.05 + 0.3)                      # + max gain
    assert np.array_equal(s[~misfit], gain[~misfit])
    w = np.array([[0.0, 1.0], [2.0, 1.0]])
    sw = acquisition_score(gain, misfit=misfit, weight=w)
    assert np.allclose(sw, w * s)
    with pytest.raises(ValueError, match="misfit"):
        acquisition_score(gain, misfit=np.full((2, 2), 2.0))
    with pytest.raises(ValueError, match="weight"):
        acquisition_score(gain, weight=-w)


def test_misfit_on_candidates_marks_the_cell_and_its_neighbours():
    zc, mc = candidate_grid([8.0, 9.0, 10.0], [25.0, 26.0, 27.0])      # 5 x 5
    ppc = np.array([(9.0, 27.0, True), (8.0, 25.0, False)],
                   dtype=[("z", float), ("mag", float), ("extreme", bool)])
    mask = misfit_on_candidates(ppc, zc, mc)
    expect = np.zeros((5, 5), bool)
    expect[1:4, 3:5] = True                                # z 8.5-9.5, m 26.5-27
    assert np.array_equal(mask, expect)


# --------------------------------------------------------------------------
# Allocation
# --------------------------------------------------------------------------
def test_allocation_hand_example():
    # 3 positive cells get 1 each; 9 more shared 3:1:2 -> 4.5, 1.5, 3 -> 4, 1, 3 and one
    # left over, whose equal remainders (0.5) go to the better-ranked cell.
    got = allocate_sources(np.array([3.0, 1.0, 0.0, 2.0]), 12)
    assert got.tolist() == [6, 2, 0, 4]


def test_allocation_sums_to_k_and_is_deterministic():
    rng = np.random.default_rng(3)
    for trial in range(50):
        scores = rng.exponential(size=(7, 5)) * (rng.uniform(size=(7, 5)) > 0.2)
        k = int(rng.integers(0, 500))
        mpc = int(rng.integers(1, 20))
        n_cells = int(rng.integers(1, 40))
        a = allocate_sources(scores, k, n_cells=n_cells, min_per_cell=mpc)
        assert a.shape == scores.shape and a.dtype == np.int64
        assert a.sum() == k
        assert np.array_equal(a, allocate_sources(scores.copy(), k, n_cells=n_cells,
                                                  min_per_cell=mpc))
        used = a > 0
        assert used.sum() <= n_cells
        if k >= mpc:
            assert np.all(a[used] >= mpc)
            assert np.all(scores[used] > 0)
            # No unused cell outscores a used one.
            if (~used).any():
                assert scores[~used].max() <= scores[used].min()
    # Ties are broken by flat index: equal scores, two cells of three get the sources.
    assert allocate_sources(np.ones(3), 4, min_per_cell=2).tolist() == [2, 2, 0]
    with pytest.raises(ValueError, match="k must be"):
        allocate_sources(np.ones(3), 2.5)


# --------------------------------------------------------------------------
# Candidates and stopping
# --------------------------------------------------------------------------
def test_candidate_grid_on_non_uniform_values_stays_inside_the_box():
    z = [9.4, 7.8, 8.2, 10.6, 9.0, 9.0]                  # unsorted, repeated, non-uniform
    m = [24.5, 26.0, 25.0, 28.5]
    box = ((8.0, 10.0), (24.5, 27.0))
    zc, mc = candidate_grid(z, m, box=box)
    # Values in the box plus midpoints of consecutive values in the box, nothing else.
    assert np.allclose(zc, [8.0, 8.2, 8.6, 9.0, 9.2, 9.4, 10.0])
    assert np.allclose(mc, [24.5, 24.75, 25.0, 25.5, 26.0])
    zs = np.unique(z)
    allowed = np.concatenate([zs, 0.5 * (zs[1:] + zs[:-1])])
    assert all(np.min(np.abs(allowed - v)) < 1e-12 for v in zc)
    assert np.all((zc >= 8.0) & (zc <= 10.0)) and np.all((mc >= 24.5) & (mc <= 27.0))
    # refine=3 splits each interval in thirds; refine=1 returns the values.
    z3, _ = candidate_grid([1.0, 2.0, 5.0], [0.0], refine=3)
    assert np.allclose(z3, [1.0, 4 / 3, 5 / 3, 2.0, 3.0, 4.0, 5.0])
    assert np.allclose(candidate_grid(z, m, refine=1)[0], zs)
    # min_step: only intervals whose halves are >= 0.3 wide are split (7.8-8.2 and 9.0-9.4 are not).
    zm, _ = candidate_grid(z, m, min_step=(0.3, 0.0))
    assert np.allclose(zm, [7.8, 8.2, 8.6, 9.0, 9.4, 10.0, 10.6])
    with pytest.raises(ValueError, match="inside the box"):
        candidate_grid(z, m, box=((20, 21), (24, 25)))
    with pytest.raises(ValueError, match="refine"):
        candidate_grid(z, m, refine=0)


def test_max_posterior_sd_is_numpys_sd_over_the_box():
    rng = np.random.default_rng(4)
    z, m = np.array([7.0, 8.0, 9.0]), np.array([25.0, 26.0, 27.0, 28.0])
    d = rng.uniform(size=(300, 3, 4)) * np.linspace(0.1, 1, 12).reshape(3, 4)
    assert max_posterior_sd(d) == pytest.approx(max(np.std(d[:, i, j])
                                                     for i in range(3) for j in range(4)))
    box = ((7.5, 9.0), (25.0, 26.5))
    inside = [(i, j) for i in range(3) for j in range(4)
              if 7.5 <= z[i] <= 9.0 and 25.0 <= m[j] <= 26.5]
    assert max_posterior_sd(d, z, m, box) == pytest.approx(max(np.std(d[:, i, j]) for i, j in inside))


# --------------------------------------------------------------------------
# Rounds
# --------------------------------------------------------------------------
def test_merge_cells_sums_counts_of_the_same_cell():
    a = Cells(z=np.array([8.0, 9.0]), mag=np.array([26.0, 26.0]), n=np.array([10, 10]),
              k_rec=np.array([5, 6]), k_sel=np.array([1, 2]))
    b = Cells(z=np.array([9.0, 8.5]), mag=np.array([26.0, 27.0]), n=np.array([4, 3]),
              k_rec=np.array([4, 0]), k_sel=np.array([3, 0]))
    c = merge_cells(a, b)
    got = {(z, m): (n, r, s) for z, m, n, r, s in zip(c.z, c.mag, c.n, c.k_rec, c.k_sel)}
    assert got == {(8.0, 26.0): (10, 5, 1), (9.0, 26.0): (14, 10, 5), (8.5, 27.0): (3, 0, 0)}


def test_plan_round_requests_the_best_cells():
    zc, mc = np.array([8.0, 9.0]), np.array([26.0, 27.0, 28.0])
    p = np.full((2, 2, 3), 0.5)
    p[:, 1, 2] = [0.1, 0.9]                              # the only uncertain cell
    req = plan_round(p, None, (zc, mc), 25)
    assert req.dtype == np.dtype(REQUEST_DTYPE)
    assert req.tolist() == [(9.0, 28.0, 25)]
    # The sd criterion on C and S draws: P = C S is uncertain only at (8, 26).
    c, s = np.full((2, 2, 3), 0.8), np.full((2, 2, 3), 0.5)
    s[:, 0, 0] = [0.2, 0.7]
    assert plan_round(c, s, (zc, mc), 7, criterion="sd").tolist() == [(8.0, 26.0, 7)]


def _toy_loop(seed, budget=130, target_sd=None):
    """A loop whose 'posterior' is the counts: sd ~ 1 / sqrt(n) of the worst cell."""
    def simulate(req, s):
        rng = np.random.default_rng(s)
        k = rng.binomial(req["n"], 0.5)
        return Cells(z=req["z"], mag=req["mag"], n=req["n"], k_rec=k, k_sel=k)

    def fit(cells, s):
        return cells

    def propose(cells, _cells, k, s):
        zc, mc = candidate_grid(cells.z, cells.mag)
        n = np.zeros((zc.size, mc.size))
        for z, m, nn in zip(cells.z, cells.mag, cells.n):
            n[np.argmin(abs(zc - z)), np.argmin(abs(mc - m))] += nn
        alloc = allocate_sources(1 / np.sqrt(n + 1), k, n_cells=3)
        i, j = np.nonzero(alloc)
        out = np.empty(i.size, dtype=REQUEST_DTYPE)
        out["z"], out["mag"], out["n"] = zc[i], mc[j], alloc[i, j]
        return out

    def stat(cells):
        return 0.5 / math.sqrt(cells.n_sources)

    init = np.array([(8.0, 26.0, 10), (9.0, 27.0, 10)], dtype=REQUEST_DTYPE)
    return run_design(simulate, fit, propose, init, budget=budget, round_size=25, seed=seed,
                      target_sd=target_sd, statistic=stat)


def test_run_design_spends_the_budget_exactly_and_is_deterministic():
    r1, r2 = _toy_loop(7), _toy_loop(7)
    assert r1.stopped == "budget" and r1.cells.n_sources == 130
    assert [r.n_sources for r in r1.rounds] == [20, 25, 25, 25, 25, 10]
    assert np.array_equal(r1.cells.k_rec, r2.cells.k_rec)
    assert all(np.array_equal(a.request, b.request) for a, b in zip(r1.rounds, r2.rounds))
    assert not np.array_equal(r1.cells.k_rec, _toy_loop(8).cells.k_rec)
    t = _toy_loop(7, budget=10_000, target_sd=0.02)          # reached at 625 sources
    assert t.stopped == "target" and t.rounds[-1].max_sd < 0.02
    assert all(r.max_sd >= 0.02 for r in t.rounds[:-1])
    assert t.cells.n_sources == 20 + 25 * math.ceil((625 - 20) / 25)
    with pytest.raises(ValueError, match="budget"):
        _toy_loop(7, budget=5)


def test_variance_reduction_follows_the_explicit_kalman_update():
    # Independent computation: the covariance matrix of the draws, the greedy gain
    # sum_e w_e Cov(e, x)^2 / (Var x + pbar (1 - pbar) / n), and the rank-one update.
    rng = np.random.default_rng(5)
    d, n_cells, chunk = 60, 9, 5
    p = rng.uniform(0.1, 0.9, (d, 1)) * rng.uniform(0.5, 1.0, (1, n_cells)) \
        + 0.05 * rng.standard_normal((d, n_cells))
    p = np.clip(p, 0, 1)
    w = rng.uniform(0, 1, n_cells)
    cov = np.cov(p.T, bias=True)
    r = p.mean(0) * (1 - p.mean(0)) / chunk
    picks = []
    for _ in range(4):
        gain = np.array([np.sum(w * cov[:, x] ** 2) / (cov[x, x] + r[x]) for x in range(n_cells)])
        x = int(np.argmax(gain))
        picks.append(x)
        cov = cov - np.outer(cov[:, x], cov[x, :]) / (cov[x, x] + r[x])
    expect = np.bincount(picks, minlength=n_cells) * chunk
    got = allocate_variance_reduction(p, 4 * chunk, eval_weight=w, min_per_cell=chunk)
    assert got.tolist() == expect.tolist()
    # Sums to k with a remainder, is deterministic, and misfit cells come first.
    a = allocate_variance_reduction(p, 23, eval_weight=w, min_per_cell=chunk)
    assert a.sum() == 23 and np.array_equal(a, allocate_variance_reduction(p, 23, eval_weight=w,
                                                                          min_per_cell=chunk))
    never = int(np.argmin(a))
    flag = np.zeros(n_cells, bool)
    flag[never] = True
    assert allocate_variance_reduction(p, 23, eval_weight=w, misfit=flag, min_per_cell=chunk)[never] > 0
    # Certain cells (no posterior spread anywhere) still get the sources, deterministically.
    assert allocate_variance_reduction(np.full((10, 3), 0.5), 7).sum() == 7
