"""Luminosity-function models, likelihood and sampler (glaciar.lf)."""
import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import poisson

from glaciar.inference.sampling import SamplerSettings
from glaciar.lf import (LFPosterior, default_window, double_power_law, fit_lf, get_model,
                        parse_fix, schechter, stepwise)
from glaciar.lf.fit import Marginalisation

from analytic_sf import TRUE, lf_sf, mock_candidates


WINDOW = np.round(np.arange(24.4, 29.01, 0.2), 6)      # faint end where P is ~0.1


def test_models_against_hand_values():
    # Schechter at M = M*: 0.4 ln10 phi* e^-1; one magnitude fainter: x = 10^-0.4.
    ln = 0.4 * np.log(10)
    assert schechter(-21.0, -3.0, -21.0, -2.0) == pytest.approx(ln * 1e-3 * np.exp(-1), rel=1e-12)
    x = 10 ** -0.4
    assert schechter(-20.0, -3.0, -21.0, -2.0) == pytest.approx(ln * 1e-3 * x ** -1 * np.exp(-x),
                                                                rel=1e-12)
    # Double power law: phi*/2 at M*; far faint -> slope alpha, far bright -> beta.
    assert double_power_law(-21.0, -3.0, -21.0, -2.0, -4.5) == pytest.approx(5e-4, rel=1e-12)
    d = 2.0
    want = 1e-3 / (10 ** (0.4 * (-1.0) * d) + 10 ** (0.4 * (-3.5) * d))
    assert double_power_law(-19.0, -3.0, -21.0, -2.0, -4.5) == pytest.approx(want, rel=1e-12)
    np.testing.assert_allclose(stepwise([-22.0, -21.2, -20.5, -19.0], [-4.0, -3.0],
                                        [-21.5, -21.0, -20.0]), [0.0, 1e-4, 1e-3, 0.0])
    mdl = get_model("dpl")
    assert mdl.param_names == ("log_phi_star", "M_star", "alpha", "beta")
    # beta < alpha (the slopes are otherwise interchangeable) and the uniform box.
    assert mdl.log_prior([-3.0, -21.0, -2.0, -4.0]) == 0.0
    assert mdl.log_prior([-3.0, -21.0, -4.0, -2.0]) == -np.inf
    assert get_model("schechter").log_prior([-3.0, -21.0, -4.0]) == -np.inf


def test_fix_parsing_names_the_allowed_parameters():
    assert parse_fix(["alpha=-2", "M_star = -21.5"]) == {"alpha": -2.0, "M_star": -21.5}
    with pytest.raises(ValueError, match="allowed: log_phi_star, M_star, alpha$"):
        parse_fix(["apha=-2"])
    with pytest.raises(ValueError, match="allowed: log_phi_star, M_star, alpha, beta"):
        parse_fix(["gamma=1"], "dpl")
    with pytest.raises(ValueError, match="NAME=VALUE"):
        parse_fix(["alpha"])
    with pytest.raises(ValueError, match="not a number"):
        parse_fix(["alpha=steep"])
    with pytest.raises(ValueError, match="given twice"):
        parse_fix(["alpha=-2", "alpha=-1.9"])
    assert parse_fix(["log_phi_3=-4"], "stepwise") == {"log_phi_3": -4.0}
    with pytest.raises(ValueError, match="unknown luminosity-function model"):
        parse_fix([], "gaussian")
    # fit_lf refuses an unknown name before computing anything (no SED needed to get there).
    with pytest.raises(ValueError, match="allowed: log_phi_star, M_star, alpha"):
        fit_lf(lf_sf(), [25.0], fix={"Mstar": -21.0})
    with pytest.raises(ValueError, match="every parameter"):
        get_model("schechter").check_fix({"log_phi_star": -3, "M_star": -21, "alpha": -2})


def test_likelihood_is_the_log_mean_exp_of_poisson_over_draws():
    rng = np.random.default_rng(0)
    K = rng.uniform(0.0, 50.0, (6, 3, 5))                 # (cells, draws, bins)
    n = np.array([3, 0, 7, 1, 12])
    M = np.linspace(-22, -19.5, 6)
    post = LFPosterior(get_model("schechter"), K, n, {}, M=M)
    th = np.array([[-3.0, -21.0, -1.8], [-2.5, -20.5, -2.2]])
    lam = np.einsum("wm,mdk->wdk", schechter(M[None, :], *(th.T[:, :, None])), K)
    per = poisson.logpmf(n, lam).sum(axis=-1)             # with ln n! (a constant)
    from scipy.special import gammaln
    want = logsumexp(per, axis=1) - np.log(3) + gammaln(n + 1).sum()
    np.testing.assert_allclose(post.log_like(th), want, rtol=1e-12)
    assert post(np.array([[-3.0, -21.0, 1.0]]))[0] == -np.inf      # alpha outside its prior


def test_schechter_recovered_from_the_forward_model():
    sf = lf_sf()
    m = mock_candidates(sf, lambda M: schechter(M, **TRUE), WINDOW, seed=11)
    assert 2000 < len(m) < 5000
    res = fit_lf(sf, m, m_obs_edges=WINDOW, sampler=SamplerSettings(seed=3, max_steps=3000))
    assert res.convergence["converged"] and res.n_candidates == len(m)
    # The mixture: every draw's posterior sampled on its own and weighed 1/D.
    assert res.convergence["sf_draw_ess"] == pytest.approx(sf.n_draws)
    assert res.convergence["n_importance"] + res.convergence["n_chains"] == sf.n_draws
    for name, truth in TRUE.items():
        p = res.parameters[name]
        sd = 0.5 * (p["hi68"] - p["lo68"])
        assert abs(p["median"] - truth) < 2.5 * sd, (name, p, truth)
    # Observed vs expected per bin: the predictive mean follows the data.
    c = res.counts
    chi2 = np.sum((c["n_obs"] - c["n_exp"]) ** 2 / np.maximum(c["n_exp"], 1.0))
    assert chi2 < 2.0 * len(c["n_obs"])
    # The binned phi where the data are: within a few sigma of the truth.
    b = res.binned_phi
    good = b["n_obs"] > 100
    truth = np.array([schechter(np.linspace(lo, hi, 11), **TRUE).mean()
                      for lo, hi in zip(b["M_lo"][good], b["M_hi"][good])])
    sig = 0.5 * (b["phi_hi68"][good] - b["phi_lo68"][good])
    assert np.all(np.abs(b["phi"][good] - truth) < 4 * sig + 0.05 * truth)
    # A fixed parameter stays fixed; the others follow (here with one emcee chain on the
    # likelihood averaged over the draws).
    fx = fit_lf(sf, m, m_obs_edges=WINDOW, sampler=SamplerSettings(seed=4, max_steps=2000),
                fix={"alpha": -2.0}, marginalisation=Marginalisation("likelihood"))
    assert fx.convergence["converged"] and fx.convergence["n_chains"] == 1
    assert fx.fixed == {"alpha": -2.0} and fx.parameters["alpha"]["lo68"] == -2.0
    assert fx.chain.shape[-1] == 2 and fx.samples.shape[-1] == 3
    p = fx.parameters["M_star"]
    assert abs(p["median"] - TRUE["M_star"]) < 2.5 * 0.5 * (p["hi68"] - p["lo68"])


def test_stepwise_recovers_a_stepwise_truth():
    sf = lf_sf()
    bins = [-22.5, -21.5, -20.5, -19.5, -18.5]
    truth = np.array([-5.0, -3.9, -3.2, -2.6])
    m = mock_candidates(sf, lambda M: stepwise(M, truth, bins), WINDOW, seed=12)
    res = fit_lf(sf, m, model="stepwise", m_obs_edges=WINDOW,
                 sampler=SamplerSettings(seed=5, max_steps=3000), bins=bins)
    assert res.param_names == ("log_phi_0", "log_phi_1", "log_phi_2", "log_phi_3")
    assert res.muv_range == (-22.5, -18.5)
    for k, t in enumerate(truth):
        p = res.parameters[f"log_phi_{k}"]
        assert abs(p["median"] - t) < 2.5 * 0.5 * (p["hi68"] - p["lo68"]), (k, p, t)
    np.testing.assert_allclose(res.binned_phi["phi"],
                               [10 ** res.parameters[f"log_phi_{k}"]["median"] for k in range(4)],
                               rtol=0.05)


def test_default_window_is_inside_the_simulated_range_on_the_lattice():
    from glaciar.lf import expected_counts

    sf = lf_sf()
    by_name = expected_counts(sf, "schechter", WINDOW, params=TRUE, draws=1, warn=False)
    by_phi = sf.expected_counts(lambda M, z: schechter(M, **TRUE) + 0 * z, WINDOW, draws=1,
                                warn=False)
    np.testing.assert_allclose(by_name.median, by_phi.median, rtol=1e-12)
    with pytest.raises(ValueError, match="needs alpha"):
        expected_counts(sf, "schechter", WINDOW, params={"log_phi_star": -3, "M_star": -21})
    w = default_window(sf)
    assert w[0] == pytest.approx(24.4) and w[-1] == pytest.approx(30.0)
    np.testing.assert_allclose(np.diff(w), 0.2)
    with pytest.raises(ValueError, match="no candidate"):
        fit_lf(lf_sf(), [10.0, 40.0], m_obs_edges=WINDOW)


# ----------------------------------------------------------------------------- glaciar lf
def _run(tmp_path, *, chash="c0ffee", band="F160W"):
    """A run directory with a manifest and a selection-function file (no store needed)."""
    import json

    run = tmp_path / "run"
    run.mkdir()
    (run / "manifest.json").write_text(json.dumps({"config_hash": chash, "detection_band": band}))
    sf = lf_sf()
    sf.meta["config_hash"] = chash
    sf.write(run / "selection_function.fits")
    return run, sf


def _catalog(path, sf, *, chash="c0ffee", columns=None, n_junk=5, seed=21):
    from glaciar.pipeline.catalog import write_catalog
    import pandas as pd

    m = mock_candidates(sf, lambda M: schechter(M, **TRUE), default_window(sf), seed=seed)
    mag = np.concatenate([m, np.full(n_junk, np.nan), np.full(n_junk, 26.0)])
    sel = np.concatenate([np.ones(len(m) + n_junk, bool), np.zeros(n_junk, bool)])
    table = pd.DataFrame({"field": "f1", "id": np.arange(len(mag)), "selected": sel,
                          "mag_auto_f160w": mag})
    if columns is not None:
        table = table[columns]
    meta = {} if chash is None else {"config_hash": chash}
    write_catalog(table, path, meta)
    return len(m)


def test_run_lf_writes_the_products(tmp_path):
    import json

    from glaciar.pipeline.lf import run_lf

    run, sf = _run(tmp_path)
    n = _catalog(run / "catalog.parquet", sf)
    out = run_lf(run, model="schechter", fix={"alpha": -2.0}, seed=1)
    assert out == run / "lf"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["model"] == "schechter" and summary["fixed"] == {"alpha": -2.0}
    # Selected rows with a finite magnitude (the NaN ones and the unselected left out),
    # minus those outside the default window.
    assert summary["n_candidates"] + summary["n_outside_window"] == n
    assert summary["n_selected_without_magnitude"] == 5
    assert set(summary["parameters"]) == {"log_phi_star", "M_star", "alpha"}
    assert set(summary["parameters"]["M_star"]) == {"median", "lo68", "hi68"}
    from astropy.table import Table
    t = Table.read(out / "binned_phi.ecsv")
    assert {"M", "phi", "phi_lo68", "phi_hi68", "n_obs"} <= set(t.colnames)
    import astropy.units as u
    assert t["phi"].unit == u.Mpc ** -3 / u.mag
    assert (out / "lf.png").stat().st_size > 10000 and (out / "counts.ecsv").is_file()


def test_run_lf_refuses_bad_inputs_before_writing(tmp_path):
    from glaciar.pipeline.lf import run_lf

    run, sf = _run(tmp_path)
    other = tmp_path / "other.parquet"
    _catalog(other, sf, chash="deadbeef")
    with pytest.raises(ValueError, match=r"config_hash deadbeef.*config_hash c0ffee"):
        run_lf(run, other)
    ecsv = tmp_path / "cat.ecsv"
    _catalog(ecsv, sf, chash="deadbeef")
    with pytest.raises(ValueError, match=r"cat.ecsv \(config_hash deadbeef\)"):
        run_lf(run, ecsv)
    anon = tmp_path / "anon.parquet"
    _catalog(anon, sf, chash=None)
    with pytest.raises(ValueError, match="no config_hash"):
        run_lf(run, anon)
    nocol = tmp_path / "nocol.fits"
    _catalog(nocol, sf, columns=["field", "id", "selected"])
    with pytest.raises(ValueError, match="missing column.*mag_auto_f160w"):
        run_lf(run, nocol)
    good = tmp_path / "good.parquet"
    _catalog(good, sf)
    with pytest.raises(ValueError, match="allowed: log_phi_star, M_star, alpha$"):
        run_lf(run, good, fix={"Mstar": -21.0})
    with pytest.raises(ValueError, match="unknown luminosity-function model"):
        run_lf(run, good, model="gauss")
    with pytest.raises(ValueError, match="muv_range"):
        run_lf(run, good, muv_range=(-18.0, -22.0))
    with pytest.raises(FileNotFoundError, match="catalogue not found"):
        run_lf(run, tmp_path / "none.parquet")
    # The identity `glaciar catalog` records (settings, input files, fields, band) decides
    # when present: the run's stored config.yaml hashes differently from its source file.
    import json

    from glaciar.pipeline.catalog import catalog_identity, read_catalog, write_catalog
    from glaciar.pipeline.lf import read_candidates
    manifest = {"config_hash": "c0ffee", "detection_band": "F160W", "store_hash": "5e77",
                "inputs": {}, "fields": ["f1"]}
    (run / "manifest.json").write_text(json.dumps(manifest))
    same = tmp_path / "same.parquet"
    _catalog(same, sf, chash="other")
    t, meta = read_catalog(same)
    write_catalog(t, same, {**meta, **catalog_identity("5e77", {}, ["f1"], "F160W")})
    m_obs, info = read_candidates(run, same)
    assert info["identity"] == "store_hash" and len(m_obs) > 100
    write_catalog(t, same, {**meta, **catalog_identity("0bad", {}, ["f1"], "F160W")})
    with pytest.raises(ValueError, match="other measurement settings"):
        read_candidates(run, same)
    (run / "selection_function.fits").unlink()
    with pytest.raises(FileNotFoundError, match="glaciar fit"):
        run_lf(run, good)
    assert not (run / "lf").exists()
