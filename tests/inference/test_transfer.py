"""The transfer function anywhere in the box (glaciar.inference.transfer) against exact normal scatter."""
import numpy as np
import pytest
from scipy.stats import norm

from glaciar.inference.products import InjectionSED, kcorrection
from glaciar.inference.transfer import (row_magnitudes, transfer_function,
                                        transfer_probability_muv)
from glaciar.tables import TransferMatrix, slice_edges, transfer_matrix

GRID = np.arange(24.0, 28.01, 0.5)        # injected magnitudes [AB mag]
ZS = np.array([6.0, 7.0, 8.0])
SHIFT = 0.15                              # m_obs - m_in, mean [mag]


def sigma(m):
    """Scatter growing to the faint end: 0.1 mag at 24, 0.5 mag at 28."""
    return 0.1 + 0.1 * (np.asarray(m, float) - 24.0)


def mu(m, z):
    """Mean measured magnitude: a shift, drifting slightly with z."""
    return m + SHIFT + 0.02 * (z - 7.0)


def exact_matrix(grid=GRID, zs=ZS, sig=sigma, mean=mu, step=0.2, n_draws=1):
    """A TransferMatrix whose rows are the exact normal bin probabilities (no sampling noise)."""
    zs = np.asarray(zs, float)
    me = slice_edges(grid, 0.25)
    ze = slice_edges(zs, 0.25)
    inner = np.round(np.arange(np.floor(grid[0] - 1.5), grid[-1] + 1.51, step), 6)
    oe = np.concatenate([[-np.inf], inner, [np.inf]])
    mat = np.zeros((2, len(zs), len(grid), len(oe)))
    for i, z in enumerate(zs):
        for j, g in enumerate(grid):
            mat[:, i, j, 1:] = np.diff(norm.cdf(oe, mean(g, z), sig(g)))
    return TransferMatrix(kinds=("recovered", "selected"), z_edges=ze, z_mean=zs, m_in_edges=me,
                          m_obs_edges=oe, counts=np.rint(mat * 1e6).astype(np.int64),
                          matrix=mat, draws=np.repeat(mat[None], n_draws, axis=0), alpha=0.01)


def test_row_magnitudes_are_the_grid_values():
    np.testing.assert_allclose(row_magnitudes(slice_edges(GRID, 0.25)), GRID, atol=1e-12)
    uneven = np.array([24.0, 24.5, 25.5, 26.0])
    np.testing.assert_allclose(row_magnitudes(slice_edges(uneven, 0.25)), uneven, atol=1e-12)
    # Uniform bins of sources injected continuously: the centres.
    np.testing.assert_allclose(row_magnitudes([24.0, 24.25, 24.5]), [24.125, 24.375])


def test_off_grid_bins_match_the_exact_normal():
    tf = transfer_function(exact_matrix())
    edges = np.round(np.arange(22.0, 30.01, 0.2), 6)
    worst = {}
    for m, z in [(25.3, 6.6), (26.7, 7.4), (24.2, 7.9), (27.9, 6.2), (25.0, 7.0), (27.85, 7.5),
                 (24.1, 7.0)]:
        p = tf.probability(m, z, edges)
        exact = np.diff(norm.cdf(edges, mu(m, z), sigma(m)))
        worst[m] = np.abs(p - exact).max()
    # The error is the 0.2 mag histogram's (read smoothly by PCHIP), largest for the
    # narrowest scatter; a mixture of the neighbouring rows would be off by ~0.1 at 25.3.
    assert worst[24.2] < 0.012                         # sigma = 0.12
    assert max(worst[25.3], worst[26.7], worst[27.9], worst[27.85]) < 5e-3   # sigma >= 0.2
    assert worst[25.0] < 2e-3                          # a row's own magnitude and slice
    # Beyond the rows (m_in < 24): the end row's offsets, unchanged (sigma 0.1, shift 0.15).
    np.testing.assert_allclose(tf.probability(22.7, 7.0, edges), tf.probability(24.0, 7.0,
                                                                               edges + 1.3),
                               atol=1e-9)
    # sigma = 0.11: narrower than the bins, the histogram does not resolve it (documented).
    assert worst[24.1] < 0.08
    ms = np.linspace(24.0, 24.5, 201)
    avg = tf.probability(ms, 7.0, edges).mean(axis=0)
    exact = np.mean([np.diff(norm.cdf(edges, mu(m, 7.0), sigma(m))) for m in ms], axis=0)
    assert np.abs(avg - exact).max() < 0.016


def test_sampled_matrix_agrees_within_its_noise():
    rng = np.random.default_rng(3)
    n = 4000
    z = np.repeat(ZS, n * len(GRID))
    m_in = np.tile(np.repeat(GRID, n), len(ZS))
    m_obs = mu(m_in, z) + sigma(m_in) * rng.standard_normal(z.size)
    sel = np.ones(z.size, bool)
    tm = transfer_matrix(z, m_in, m_obs, sel, sel, n_draws=8, seed=1)
    edges = np.round(np.arange(23.0, 29.01, 0.2), 6)
    p = transfer_function(tm).probability(26.3, 7.3, edges)
    exact = np.diff(norm.cdf(edges, mu(26.3, 7.3), sigma(26.3)))
    # Noise of one bin of ~4000 sources: sqrt(p / n) <~ 0.007 (two rows and slices mixed).
    assert np.abs(p - exact).max() < 0.02
    per_draw = transfer_function(tm, draws=True).probability(26.3, 7.3, edges)
    assert per_draw.shape == (8, len(edges) - 1)
    assert np.abs(per_draw.mean(axis=0) - p).max() < 0.01
    assert 0 < per_draw.std(axis=0).max() < 0.02


def test_empty_and_thin_rows_borrow_a_neighbour_and_open_bins_stay_apart():
    tm = exact_matrix()
    counts = tm.counts.copy()
    matrix = tm.matrix.copy()
    counts[1, 1, -1] = 0                          # faintest row of z = 7: no source at all
    matrix[1, 1, -1] = np.nan
    counts[1, 1, -2, 1:] = 0                      # next row: 3 selected sources only
    counts[1, 1, -2, 10] = 3
    thin = TransferMatrix(tm.kinds, tm.z_edges, tm.z_mean, tm.m_in_edges, tm.m_obs_edges,
                          counts, matrix, matrix[None], tm.alpha)
    tf = transfer_function(thin, "selected")
    assert tf.filled[1, -1] and tf.filled[1, -2] and not tf.filled[1, :-2].any()
    np.testing.assert_allclose(tf.source[1, -2:], GRID[-3])
    p = tf.probability([27.8, 28.0], 7.0, [-np.inf, 26.0, 30.0, np.inf])
    assert np.all(np.isfinite(p))
    np.testing.assert_allclose(p.sum(axis=-1), 1.0, atol=1e-9)
    # 1 % of the sources in the open faint bin (e.g. no positive flux): only an open bin gets them.
    mat = tm.matrix.copy()
    mat[..., 1:] *= 0.99
    mat[..., -1] += 0.01
    leak = TransferMatrix(tm.kinds, tm.z_edges, tm.z_mean, tm.m_in_edges, tm.m_obs_edges,
                          np.rint(mat * 1e6).astype(np.int64), mat, mat[None], tm.alpha)
    tfl = transfer_function(leak)
    closed = tfl.probability(26.0, 7.0, np.arange(20.0, 33.01, 0.5)).sum()
    opened = tfl.probability(26.0, 7.0, [-np.inf, 26.0, np.inf]).sum()
    assert closed == pytest.approx(0.99, abs=1e-6) and opened == pytest.approx(1.0, abs=1e-9)
    with pytest.raises(ValueError, match="kind must be one of"):
        transfer_function(tm, "detected")


def test_transfer_in_muv_is_the_beta_average_at_m_in_of_each_beta():
    from glaciar.galaxy.filters import get_filter

    tf = transfer_function(exact_matrix())
    sed = InjectionSED(get_filter("wfc3_ir_f160w"), beta_mean=-2.0, beta_sd=0.3)
    M, z = np.array([-20.3]), np.array([7.2])
    edges = np.round(np.arange(25.0, 29.01, 0.2), 6)
    got = transfer_probability_muv(tf, M, z, edges, sed, n_beta=5)[0, 0]
    x, w = np.polynomial.hermite_e.hermegauss(5)
    betas, w = -2.0 + 0.3 * x, w / w.sum()
    k = kcorrection(z, betas, sed.detection_filter)[0]
    want = sum(wi * tf.probability(M[0] + ki, z[0], edges) for wi, ki in zip(w, k))
    np.testing.assert_allclose(got, want, atol=1e-12)
