"""The photometric transfer function p(m_obs | m_in, z): glaciar.tables.transfer_matrix, the file."""
import numpy as np
import pytest

from glaciar.inference import SelectionFunction, SurfaceModel
from glaciar.pipeline import selection_file
from glaciar.tables import slice_edges, transfer_matrix


def _synthetic(n=400, delta=0.3, seed=1):
    """Sources on a (z, m_in) grid; recovered with probability 0.75, m_obs = m_in + delta."""
    rng = np.random.default_rng(seed)
    z = np.repeat([7.0, 8.0], 3 * n)
    m_in = np.tile(np.repeat([25.0, 26.0, 27.0], n), 2)
    rec = rng.random(z.size) < 0.75
    sel = rec & (rng.random(z.size) < 0.5)
    return z, m_in, m_in + delta, rec, sel


def test_rows_sum_to_one_and_known_shift_lands_on_the_shifted_bin():
    z, m_in, m_obs, rec, sel = _synthetic(delta=0.3)
    edges = np.arange(23.0, 29.01, 0.2)
    tm = transfer_matrix(z, m_in, m_obs, rec, sel, m_obs_edges=edges, n_draws=50, seed=3)
    np.testing.assert_allclose(tm.matrix.sum(axis=-1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.nansum(tm.draws, axis=-1), 1.0, rtol=0, atol=1e-9)
    assert tm.m_obs_edges[0] == -np.inf and tm.m_obs_edges[-1] == np.inf
    np.testing.assert_allclose(slice_edges([7.0, 8.0], 0.25), [6.5, 7.5, 8.5])
    np.testing.assert_allclose(tm.z_mean, [7.0, 8.0])
    for k, flag in enumerate((rec, sel)):
        for i, zi in enumerate((7.0, 8.0)):
            for j, mj in enumerate((25.0, 26.0, 27.0)):
                cell = (z == zi) & (m_in == mj)
                row = tm.counts[k, i, j]
                # Not recovered / not selected in entry 0; every other source in the one bin
                # holding m_in + 0.3 (independent: np.digitize on the finite edges).
                b = np.digitize(mj + 0.3, edges)          # index into [-inf, e0, ..., +inf] bins
                assert row[0] == np.sum(cell & ~flag)
                assert row[1 + b] == np.sum(cell & flag)
                assert row.sum() == cell.sum()


def test_non_positive_flux_goes_to_the_faintest_bin_and_outside_sources_are_dropped():
    z = np.array([7.0, 7.0, 7.0, 9.9])
    m_in = np.array([26.0, 26.0, 26.0, 26.0])
    m_obs = np.array([np.nan, 40.0, 26.1, 26.0])
    rec = np.array([True, True, True, True])
    tm = transfer_matrix(z, m_in, m_obs, rec, rec, z_edges=[6.5, 7.5], m_in_edges=[25.5, 26.5],
                         m_obs_edges=[25.0, 26.0, 27.0], n_draws=4)
    assert tm.counts[0, 0, 0].tolist() == [0, 0, 0, 1, 2]     # missed, <25, 25-26, 26-27, >=27
    assert tm.counts.sum() == 2 * 3


def test_draws_spread_matches_the_multinomial_expectation():
    rng = np.random.default_rng(5)
    n = 400
    p = np.array([0.25, 0.05, 0.4, 0.3])          # missed, three m_obs bins
    entry = rng.choice(4, size=n, p=p)
    rec = entry > 0
    m_obs = np.array([np.nan, 25.5, 26.5, 27.5])[entry]
    tm = transfer_matrix(np.full(n, 7.0), np.full(n, 26.0), m_obs, rec, np.zeros(n, bool),
                         m_obs_edges=[25.0, 26.0, 27.0, 28.0], n_draws=4000, seed=7)
    counts = tm.counts[0, 0, 0]
    phat = counts / n
    d = tm.draws[:, 0, 0, 0]
    # Dirichlet(counts + alpha): mean (n_k + alpha) / A, var = m (1 - m) / (A + 1), A = n + K alpha.
    a = counts + tm.alpha
    mean = a / a.sum()
    sd = np.sqrt(mean * (1 - mean) / (a.sum() + 1))
    np.testing.assert_allclose(d.mean(axis=0), mean, atol=4 * sd.max() / np.sqrt(4000))
    np.testing.assert_allclose(d.std(axis=0), sd, rtol=0.06)
    # ... which is the multinomial (binomial per entry) sd of the estimate, sqrt(p (1 - p) / n).
    occupied = counts > 0
    np.testing.assert_allclose(d.std(axis=0)[occupied], np.sqrt(phat * (1 - phat) / n)[occupied],
                               rtol=0.08)
    # Same seed, same draws.
    again = transfer_matrix(np.full(n, 7.0), np.full(n, 26.0), m_obs, rec, np.zeros(n, bool),
                            m_obs_edges=[25.0, 26.0, 27.0, 28.0], n_draws=4000, seed=7)
    np.testing.assert_array_equal(again.draws, tm.draws)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="selected source must be recovered"):
        transfer_matrix([7.0], [26.0], [26.0], [False], [True])
    with pytest.raises(ValueError, match="m_obs_edges"):
        transfer_matrix([7.0], [26.0], [26.0], [True], [True], m_obs_edges=[27.0, 26.0])


def test_file_round_trip_is_exact(tmp_path):
    z, m_in, m_obs, rec, sel = _synthetic(n=50)
    tm = transfer_matrix(z, m_in, m_obs, rec, sel, n_draws=20, seed=2)
    mdl = SurfaceModel.for_data(np.array([7.0, 8.0]), np.array([25.0, 27.0]))
    sf = SelectionFunction(mdl, mdl.sample_prior(3, np.random.default_rng(0)),
                           meta={"area_arcmin2": 2.0})
    sf.transfer_matrix = tm
    path = tmp_path / "sf.fits"
    sf.write(path)
    back = SelectionFunction.read(path).transfer_matrix
    for name in ("z_edges", "z_mean", "m_in_edges", "m_obs_edges", "counts", "matrix"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tm, name), err_msg=name)
    np.testing.assert_array_equal(back.draws, tm.draws.astype(np.float32))
    assert back.kinds == tm.kinds and back.alpha == tm.alpha
    one = SelectionFunction.read(path).transfer(8.2, kind="selected")
    np.testing.assert_array_equal(one.matrix, tm.matrix[1, 1])
    assert (one.z_lo, one.z_hi) == (7.5, 8.5)
    with pytest.raises(ValueError, match="outside the slices"):
        SelectionFunction.read(path).transfer(9.0)


def test_glaciar_fit_products_from_a_run(small_run):
    """add_lf_products on a simulated run: counts against an independent histogram of its rows."""
    import json

    from glaciar import constants as C
    from glaciar.store import read_current_histograms, read_current_results

    cfg, run = small_run
    # The simulated run stores m_obs histograms: the matrices below come from them, not rows.
    assert read_current_histograms(run) is not None
    manifest = json.loads((run / C.MANIFEST_NAME).read_text())
    rows = read_current_results(run)
    mdl = SurfaceModel.for_data(rows[C.COL_Z], rows[C.COL_MAG_INPUT])
    sf = SelectionFunction(mdl, mdl.sample_prior(4, np.random.default_rng(0)),
                           meta={"area_arcmin2": 1.0}, field="all",
                           domain={"z": (8.0, 10.4), "mag": (24.0, 27.5)})
    selection_file.add_lf_products(run, manifest, [sf], seed=3)
    assert sf.sed.beta_mean == cfg.source.beta_mean and sf.sed.igm == cfg.source.igm
    assert sf.sed.detection_filter.name.endswith(cfg.survey.detection_band.lower())
    tm = sf.transfer_matrix
    det = C.band_column(C.OBS_MAG_QUANTITY, cfg.survey.detection_band)
    for k, flag in enumerate((C.COL_RECOVERED, C.COL_SELECTED)):
        for i, zi in enumerate(sorted(rows[C.COL_Z].unique())):
            for j, mj in enumerate(sorted(rows[C.COL_MAG_INPUT].round(6).unique())):
                cell = rows[(rows[C.COL_Z] == zi) & (rows[C.COL_MAG_INPUT].round(6) == mj)]
                hit = cell[cell[flag].astype(bool)]
                mobs = hit[det].fillna(np.inf).to_numpy(float)
                want = np.histogram(mobs, bins=tm.m_obs_edges)[0]
                want[-1] += np.sum(mobs == np.inf)        # histogram leaves out +inf itself
                assert tm.counts[k, i, j, 0] == len(cell) - len(hit)
                np.testing.assert_array_equal(tm.counts[k, i, j, 1:], want)
