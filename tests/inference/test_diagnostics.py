"""Diagnostics and honest inputs/outputs of the inference: PSIS-LOO, R-hat, edge and
domain checks, magnitude_at, depth shifts, bad flags, bad arguments, single-z runs."""
import json
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy import special, stats

from glaciar.inference import SelectionFunction, SurfaceModel, aggregate_cells
from glaciar.inference.diagnostics import compare_models, edge_report, psis_loo
from glaciar.inference.sampling import SamplerSettings, split_rhat
from glaciar.pipeline import run_fit
from glaciar.store import write_task_table


# ------------------------------------------------------------------ PSIS-LOO
def test_psis_loo_matches_exact_beta_binomial_loo():
    """Conjugate model: exact leave-one-cell-out predictive densities are analytic."""
    rng = np.random.default_rng(1)
    n = rng.integers(5, 40, size=30)
    k = rng.binomial(n, 0.3)
    a, b = 1 + k.sum(), 1 + (n - k).sum()
    p = rng.beta(a, b, size=8000)
    ll = stats.binom.logpmf(k[None, :], n[None, :], p[:, None])
    # exact: p(k_i | others) is beta-binomial with the posterior without cell i
    exact = stats.betabinom.logpmf(k, n, a - k, b - (n - k))
    r = psis_loo(ll)
    np.testing.assert_allclose(r["pointwise"], exact, atol=0.01)
    assert np.all(r["k_hat"] < 0.5)
    assert 0.5 < r["p_loo"] < 1.5            # one parameter


def test_psis_loo_flags_influential_cells_and_compare_prefers_simpler_when_tied():
    rng = np.random.default_rng(2)
    k = np.r_[rng.binomial(40, 0.05, size=20), 40]           # the last cell is an outlier
    p = rng.beta(1 + k.sum(), 1 + 40 * len(k) - k.sum(), size=4000)
    r = psis_loo(stats.binom.logpmf(k[None, :], 40, p[:, None]))
    assert r["k_hat"][-1] > 0.7 and np.all(r["k_hat"][:-1] < 0.5)   # the outlier is influential
    base = {"elpd": -10.0, "se": 1.0, "pointwise": np.full(10, -1.0), "k_hat": np.zeros(10)}
    tied = dict(base, elpd=-9.9, pointwise=np.r_[np.full(9, -1.0), -0.9])
    better = dict(base, elpd=-5.0, pointwise=np.full(10, -0.5))
    assert compare_models({"simple": base, "flexible": tied})[0] == "simple"
    assert compare_models({"simple": base, "flexible": better})[0] == "flexible"


def test_split_rhat_one_for_mixed_chains_and_large_for_stuck_walkers():
    rng = np.random.default_rng(3)
    good = rng.standard_normal((400, 16, 2))
    assert np.all(np.abs(split_rhat(good) - 1) < 0.02)
    bad = good.copy()
    bad[:, :8, 0] += 3.0                       # half the walkers elsewhere
    bad[200:, :, 1] += 2.0                     # a drift within the chain
    r = split_rhat(bad)
    assert r[0] > 1.5 and r[1] > 1.2
    # the BDA3 formula, written out for one parameter
    x = good[:, :, 0]
    h = np.concatenate([x[:200], x[200:]], axis=1)
    W = h.var(axis=0, ddof=1).mean()
    B = 200 * h.mean(axis=0).var(ddof=1)
    assert split_rhat(good)[0] == pytest.approx(np.sqrt((199 / 200 * W + B / 200) / W), rel=1e-12)


# ------------------------------------------------------------- z-edge report
def test_edge_report_finds_truncated_edge_and_extrapolates_extent():
    z = np.linspace(6.0, 8.0, 21)
    m = np.array([26.0, 27.0])
    # P falls as exp(-(8.5 - z) / 0.2) near the upper end: still high at z = 8
    p = special.expit((8.5 - z) / 0.2)[:, None] * special.expit((z - 6.3) / 0.1)[:, None] * np.ones(2)
    def surface(zz):
        return (special.expit((8.5 - zz) / 0.2) * special.expit((zz - 6.3) / 0.1))[None, :, None] * np.ones(2)

    rep = edge_report(p[None], z, m, extrapolate=surface)
    assert [r["end"] for r in rep] == ["high"]
    # where the falling edge reaches 5 % of the peak: (8.5 - z) / 0.2 = logit(0.05 * peak)
    target = 8.5 - 0.2 * special.logit(0.05 * p.max()) - 8.0
    assert rep[0]["extend_dz"] == pytest.approx(target, abs=0.021)     # the 1 % search step
    assert np.isnan(edge_report(p[None], z, m)[0]["extend_dz"])           # nothing to extrapolate
    assert edge_report((p * special.expit((7.5 - z) / 0.1)[:, None])[None], z, m) == []


# ------------------------------------------------------ model and file facts
def _toy_model(depth_ref=None, n=4):
    mdl = SurfaceModel.for_data(np.array([7.0, 8.0, 9.0]), np.array([25.0, 27.0, 29.0]),
                                depth_ref=depth_ref)
    th = np.tile(mdl.prior_mean, (n, 1))
    th[:, mdl.param_names.index("m50_0")] = 27.0 + 0.05 * np.arange(n)
    th[:, mdl.param_names.index("logit_c_max_0")] = 3.0
    return mdl, th


def test_depth_shift_and_uniform_depth_reduces_to_plain_model():
    mdl_d, th = _toy_model(depth_ref=27.0)
    mdl, _ = _toy_model()
    m, z = np.linspace(25, 29, 9), 8.0
    # C(m, z | d) = C(m - (d - d_ref), z), and at d_ref the plain model
    np.testing.assert_allclose(mdl_d.completeness(th, m, z, 28.0), mdl.completeness(th, m - 1.0, z),
                               rtol=1e-12)
    np.testing.assert_allclose(mdl_d.completeness(th, m, z, 27.0), mdl.completeness(th, m, z), rtol=1e-12)
    np.testing.assert_allclose(mdl_d.selection_given_recovered(th, z, m, 26.5),
                               mdl.selection_given_recovered(th, z, m + 0.5), rtol=1e-12)
    # one depth bin at d_ref: the survey average is the plain surface
    sf = SelectionFunction(mdl_d, th, depth_area={"f": (np.array([26.95, 27.05]), np.array([2.0]))},
                           domain={"z": (7, 9), "mag": (25, 29)})
    np.testing.assert_allclose(sf.completeness(m, z, draws=True), mdl.completeness(th, m, z), rtol=1e-12)


def test_area_weighted_average_and_per_field_volumes_add_up():
    mdl, th = _toy_model(depth_ref=27.0)
    da = {"a": (np.array([26.0, 26.05]), np.array([1.0])),          # shallow, 1 arcmin^2
          "b": (np.array([27.0, 27.05]), np.array([4.0]))}          # deep, 4 arcmin^2
    sf = SelectionFunction(mdl, th, depth_area=da, domain={"z": (7, 9), "mag": (25, 29)})
    m, z = 26.5, 8.0
    ca = mdl.completeness(th, m, z, 26.025)
    cb = mdl.completeness(th, m, z, 27.025)
    np.testing.assert_allclose(sf.completeness(m, z, draws=True), (1 * ca + 4 * cb) / 5, rtol=1e-12)
    p = sf.selection_probability(z, m, draws=True)
    s = sf.selection_given_recovered(z, m, draws=True)
    np.testing.assert_allclose(sf.completeness(m, z, draws=True) * s, p, rtol=1e-12)
    va, vb, v = (sf.effective_volume([26.0, 27.0], field=f) for f in ("a", "b", None))
    np.testing.assert_allclose((va.draws + vb.draws).value, v.draws.value, rtol=1e-12)
    assert sf.area_arcmin2() == 5.0 and sf.area_arcmin2("a") == 1.0


def test_effective_volume_warns_when_the_z_range_truncates_the_selection():
    mdl, th = _toy_model()
    sf = SelectionFunction(mdl, th, meta={"area_arcmin2": 1.0}, domain={"z": (7.0, 9.0), "mag": (25, 29)})
    with pytest.warns(UserWarning, match="misses the volume beyond"):
        sf.effective_volume(26.0)                 # prior-mean edges sit at the range's ends
    inside = th.copy()
    for k, v in (("eta_lo_0", -5.0), ("eta_hi_0", -5.0), ("log_dz_lo_0", np.log(0.1)),
                 ("log_dz_hi_0", np.log(0.1))):
        inside[:, mdl.param_names.index(k)] = v   # edges at 7.5 and 8.5, width 0.1
    sf = SelectionFunction(mdl, inside, meta={"area_arcmin2": 1.0}, domain={"z": (7.0, 9.0), "mag": (25, 29)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert sf.effective_volume(26.0).median.value > 0


def test_domain_outside_is_nan_unless_extrapolating():
    mdl, th = _toy_model()
    sf = SelectionFunction(mdl, th, domain={"z": (7.0, 9.0), "mag": (25.0, 29.0)})
    c = sf.completeness(np.array([24.0, 26.0, 30.0]), np.array([8.0, 9.5, 8.0]))
    assert np.isnan(c[0]) and np.isnan(c[1]) and np.isnan(c[2])
    assert np.isfinite(sf.completeness(26.0, 8.0))
    assert np.isfinite(sf.completeness(30.0, 8.0, outside="extrapolate"))
    with pytest.raises(ValueError, match="outside"):
        sf.completeness(26.0, 8.0, outside="clip")


def test_magnitude_at_matches_analytic_logistic_inverse():
    mdl, th = _toy_model()
    sf = SelectionFunction(mdl, th, domain={"z": (7.0, 9.0), "mag": (25.0, 29.0)})
    z = 8.0
    zc = (z - mdl.z_ref) / mdl.z_scale
    s = mdl._slices
    cmax = special.expit(th[:, s["logit_c_max"]] @ zc ** np.arange(2))
    m50 = th[:, s["m50"]] @ zc ** np.arange(3)
    w = np.exp(th[:, s["log_w"]] @ zc ** np.arange(2))
    # C_max / (1 + exp(u)) = 0.5  ->  u = ln(2 C_max - 1)
    expect = m50 + w * np.log(2 * cmax - 1)
    r = sf.magnitude_at(0.5, z)
    np.testing.assert_allclose(r.draws[:, 0], expect, atol=1e-4)
    assert r.median[0] == pytest.approx(np.median(expect), abs=1e-4)
    assert np.isnan(sf.magnitude_at(0.99, z).draws).all()         # above C_max: never reached


# ------------------------------------------------------------------ inputs
def _flags_frame(n=200, seed=0):
    rng = np.random.default_rng(seed)
    z = rng.choice([7.0, 8.0, 9.0], n)
    m = rng.choice(np.arange(25.0, 29.1, 0.5), n)
    rec = rng.random(n) < special.expit(27.0 - m)
    return pd.DataFrame({"field": "f", "z": z, "mag": m, "mag_input": m, "recovered": rec,
                         "selected": rec & (rng.random(n) < 0.7)})


def test_nan_or_non_boolean_flags_are_errors():
    df = _flags_frame()
    bad = df.astype({"recovered": float})
    bad.loc[3, "recovered"] = np.nan
    with pytest.raises(ValueError, match=r"'recovered' must be boolean.*row 3"):
        aggregate_cells(bad)
    bad = df.astype({"selected": object})
    bad.loc[5, "selected"] = "yes"
    with pytest.raises(ValueError, match="'selected' must be boolean"):
        aggregate_cells(bad)
    ok = df.astype({"recovered": int, "selected": float})       # 0/1 numbers are fine
    assert aggregate_cells(ok).k_rec.sum() == df.recovered.sum()


def _run(tmp_path, df, manifest):
    run = tmp_path / "run"
    write_task_table(run, "task_a.parquet", df)
    (run / "manifest.json").write_text(json.dumps(manifest))
    return run


@pytest.mark.parametrize("area", [-1.0, 0.0, float("nan"), float("inf"), "abc"])
def test_bad_area_refused_before_anything_is_written(tmp_path, area):
    run = _run(tmp_path, _flags_frame(), {"fields": ["f"], "area_arcmin2": {"f": 1.0}})
    (run / "selection_function.fits").write_bytes(b"previous")
    with pytest.raises(ValueError, match="area-arcmin2 must be a positive finite number"):
        run_fit(run, area_arcmin2=area)
    assert (run / "selection_function.fits").read_bytes() == b"previous"
    assert not (run / "fit").exists()


def test_cli_bad_area_exit_2(tmp_path, capsys):
    from glaciar.cli import main
    run = _run(tmp_path, _flags_frame(), {"fields": ["f"], "area_arcmin2": {"f": 1.0}})
    assert main(["fit", str(run), "--area-arcmin2", "-1"]) == 2
    assert "--area-arcmin2: expected a finite number > 0" in capsys.readouterr().err
    assert main(["fit", str(run), "--max-steps", "0"]) == 2
    assert not (run / "fit").exists()


def test_single_redshift_run_has_no_zero_volume_or_zero_step(tmp_path):
    from astropy.io import fits
    df = _flags_frame(600)
    df["z"] = 8.0
    run = _run(tmp_path, df, {"fields": ["f"], "area_arcmin2": {"f": 2.0}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # one z leaves the selection's z edges to their prior: cap the chains (test speed)
        path = run_fit(run, model="logistic", plots=False, max_draws=200,
                           sampler=SamplerSettings(max_steps=1500))
    with fits.open(path) as h:
        assert h["C_GRID", 1].header["CDELT2"] != 0 and h["C_GRID", 1].header["CDELT1"] != 0
        assert h["C_GRID", 1].data.shape[1] == 1
    summ = json.loads((run / "fit" / "summary.json").read_text())["fits"]["all"]
    assert summ["effective_volume"] is None and "redshift range" in summ["effective_volume_note"]
    sf = SelectionFunction.read(path)
    with pytest.raises(ValueError, match="no redshift range"):
        sf.effective_volume(26.0)


def test_absolute_magnitude_run_fits_m_uv(tmp_path):
    df = _flags_frame(900, seed=4)
    df["M_uv"] = df["mag"] - 47.0                   # M_UV grid; mag_input varies with beta
    df["mag_input"] = df["mag"] + np.random.default_rng(5).normal(0, 0.2, len(df))
    run = _run(tmp_path, df, {"fields": ["f"], "area_arcmin2": {"f": 2.0},
                              "magnitude_type": "absolute"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        path = run_fit(run, model="logistic", plots=False, max_draws=200)
    sf = SelectionFunction.read(path)
    assert sf.magnitude_type == "absolute" and sf.meta["magnitude_column"] == "M_uv"
    assert sf.domain["mag"] == pytest.approx((df.M_uv.min(), df.M_uv.max()))
    # flags were drawn with 50 % at mag 27 - ln(C_max...) ~ M_UV = -20
    assert sf.magnitude_at(0.5, 8.0).median[0] == pytest.approx(-20.0, abs=0.4)
