"""Tests of glaciar.inference: models, priors, fit, file round-trip, V_eff, PPC."""
import json
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy import integrate, special, stats

from glaciar.inference import (Cells, SelectionFunction, SurfaceModel, aggregate_cells,
                               find_map, fit_surfaces, propose_cells)
from glaciar.inference.fit import ConvergenceWarning
from glaciar.inference.sampling import SamplerSettings
from glaciar.pipeline import run_fit
from glaciar.store import write_task_table

Z_GRID = np.array([6.0, 6.5, 7.0, 7.5, 8.0, 8.5, 9.0])
M_GRID = np.arange(25.0, 29.51, 0.5)
# Edges: rising 50 % point at z_min - eta_lo dz_lo = 6.8 (+ slope), falling at 8.4.
TRUTH = dict(logit_c_max_0=2.5, logit_c_max_1=0.2, m50_0=27.4, m50_1=-0.3, m50_2=0.05,
             log_w_0=np.log(0.3), log_w_1=0.1, logit_s_max=3.0, eta_lo_0=-0.8 / 0.15,
             eta_lo_1=0.3, log_dz_lo_0=np.log(0.15), log_dz_lo_1=0.1, eta_hi_0=-0.6 / 0.2,
             eta_hi_1=0.5, log_dz_hi_0=np.log(0.2), log_dz_hi_1=0.0, sas_eps=0.3,
             sas_log_delta=-0.2)


def truth_model(shape="logistic", depth_ref=None):
    mdl = SurfaceModel.for_data(Z_GRID, M_GRID, shape=shape, depth_ref=depth_ref)
    th = mdl.prior_mean.copy()
    for k, v in TRUTH.items():
        if k in mdl.param_names:
            th[mdl.param_names.index(k)] = v
    return mdl, th


def simulate(mdl, th, n_per_cell, rng, scatter=0.05, fields=("f1",)):
    z = np.repeat(Z_GRID, len(M_GRID) * n_per_cell)
    mnom = np.tile(np.repeat(M_GRID, n_per_cell), len(Z_GRID))
    mi = mnom + scatter * rng.standard_normal(z.size)
    rec = rng.random(z.size) < mdl.completeness(th, mi, z)
    sel = rec & (rng.random(z.size) < mdl.selection_given_recovered(th, z, mi))
    return pd.DataFrame({"field": rng.choice(list(fields), z.size), "z": z, "mag": mnom,
                         "mag_input": mi, "recovered": rec, "selected": sel})


# ----------------------------------------------------------------- models
@pytest.mark.parametrize("shape", ["logistic", "erf", "fleming", "sas"])
def test_completeness_analytic_values_and_limits(shape):
    mdl, th = truth_model(shape)
    z = 7.0
    zc = (z - mdl.z_ref) / mdl.z_scale
    cmax = special.expit(2.5 + 0.2 * zc)
    m50 = 27.4 - 0.3 * zc + 0.05 * zc ** 2
    w = np.exp(np.log(0.3) + 0.1 * zc)
    m = m50 + w * np.array([-1.0, 0.0, 1.0, 2.0])
    u = (m - m50) / w
    t = np.sinh(np.exp(-0.2) * np.arcsinh(u) - 0.3)
    expect = {"logistic": 1 / (1 + np.exp(u)), "erf": 0.5 * special.erfc(u / np.sqrt(2)),
              "fleming": 0.5 * (1 - u / np.sqrt(1 + u ** 2)),
              "sas": 0.5 * special.erfc(t / np.sqrt(2))}[shape]
    np.testing.assert_allclose(mdl.completeness(th, m, z), cmax * expect, rtol=1e-12)
    # limits: C -> C_max bright, -> 0 faint; monotone decreasing in m
    mm = np.linspace(15, 45, 500)
    c = mdl.completeness(th, mm, z)
    assert abs(c[0] - cmax) < 3e-3 and c[-1] < 3e-3
    assert np.all(np.diff(c) <= 0)
    # ln(1 - C) stays finite and exact where 1 - C is tiny / C underflows
    ll = mdl.log_likelihood(th, Cells(z=np.array([7.0, 7.0]), mag=np.array([5.0, 80.0]),
                                      n=np.array([3, 3]), k_rec=np.array([2, 1]), k_sel=np.array([0, 0])))
    assert np.isfinite(ll)


def test_selection_analytic_and_likelihood_against_bernoulli():
    mdl, th = truth_model()
    z, m = np.array([6.3, 7.6, 8.9]), np.array([25.5, 27.0, 29.0])
    mc = (m - mdl.m_ref) / mdl.m_scale
    dlo, dhi = np.exp(np.log(0.15) + 0.1 * mc), np.full(3, 0.2)
    # 50 % points of the edges from their logits at the ends of the simulated range 6..9
    zlo = 6.0 - (-0.8 / 0.15 + 0.3 * mc) * dlo
    zhi = 9.0 + (-3.0 + 0.5 * mc) * dhi
    s = special.expit(3.0) * special.expit((z - zlo) / dlo) * special.expit((zhi - z) / dhi)
    np.testing.assert_allclose(mdl.selection_given_recovered(th, z, m), s, rtol=1e-12)
    assert np.all(mdl.selection_given_recovered(th, z, m) < special.expit(3.0))
    # aggregated binomial likelihood == sum of per-source Bernoulli terms (exact aggregation)
    rng = np.random.default_rng(3)
    df = simulate(mdl, th, 5, rng, scatter=0.0)
    cells = aggregate_cells(df, mag_resolution=None)
    assert len(cells) == len(Z_GRID) * len(M_GRID)
    C = mdl.completeness(th, df.mag_input, df.z)
    S = mdl.selection_given_recovered(th, df.z, df.mag_input)
    r, sl = df.recovered.to_numpy(), df.selected.to_numpy()
    direct = np.sum(np.where(r, np.log(C), np.log1p(-C))) + np.sum(
        np.where(r, np.where(sl, np.log(S), np.log1p(-S)), 0.0))
    np.testing.assert_allclose(mdl.log_likelihood(th, cells), direct, rtol=1e-10)


def test_grouped_magnitudes_match_exact_likelihood():
    """mag_resolution grouping: likelihood differences agree with the exact ones."""
    mdl, th = truth_model()
    rng = np.random.default_rng(4)
    df = simulate(mdl, th, 200, rng, scatter=0.1)
    exact, grouped = aggregate_cells(df, None), aggregate_cells(df, 0.01)
    assert len(grouped) < len(exact) / 3
    th2 = th.copy()
    th2[mdl.param_names.index("log_w_0")] += 0.05   # a 5 % change of the width
    d_exact = mdl.log_likelihood(th2, exact) - mdl.log_likelihood(th, exact)
    d_group = mdl.log_likelihood(th2, grouped) - mdl.log_likelihood(th, grouped)
    assert abs(d_group - d_exact) < 0.02 * abs(d_exact) + 0.05


# ----------------------------------------------------------------- priors
@pytest.mark.parametrize("outcome", ["all", "none"])
def test_separable_data_finite_map_and_proper_posterior(outcome):
    mdl, th = truth_model()
    rng = np.random.default_rng(5)
    df = simulate(mdl, th, 3, rng)
    df["recovered"] = outcome == "all"
    df["selected"] = outcome == "all"
    cells = aggregate_cells(df)
    # log-likelihood <= 0 everywhere => posterior <= prior, which is normalisable
    pts = mdl.sample_prior(2000, rng) * 3.0 - 2.0 * mdl.prior_mean
    assert np.all(mdl.log_likelihood(pts, cells) <= 1e-12)
    tmap = find_map(mdl, cells)
    assert np.all(np.isfinite(tmap))
    assert np.all(np.abs((tmap - mdl.prior_mean) / mdl.prior_sd) < 6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = fit_surfaces(cells, mdl, seed=1, max_steps=400)
    d = res.draws()
    # posterior spread bounded by the prior's (proper, not drifting away)
    assert np.all(np.std(d, axis=0) < 3 * mdl.prior_sd)


# -------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def fitted_run(tmp_path_factory):
    mdl, th = truth_model()
    rng = np.random.default_rng(7)
    df = simulate(mdl, th, 40, rng, fields=("f1", "f2"))
    run = tmp_path_factory.mktemp("run")
    for i, (z, d) in enumerate(df.groupby("z")):
        write_task_table(run, f"task_f_z{i:03d}_m000_i0000.parquet", d)
    (run / "manifest.json").write_text(json.dumps({"fields": ["f1", "f2"],
                                                   "area_arcmin2": {"f1": 3.0, "f2": 1.5},
                                                   "bands": ["f125w", "f160w"], "config_hash": "abc"}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")      # no local depths in this hand-made run
        path = run_fit(run, sampler=SamplerSettings(seed=3), model="logistic")
    return run, path, df, mdl, th


def test_run_fit_recovers_truth_and_writes_outputs(fitted_run):
    run, path, df, mdl, th = fitted_run
    sf = SelectionFunction.read(path)
    summ = json.loads((run / "fit" / "summary.json").read_text())["fits"]["all"]
    assert summ["n_sources"] == len(df)
    for name in ("completeness_all.png", "selection_all.png", "ppc_all.ecsv", "parameters_all.ecsv"):
        assert (run / "fit" / name).stat().st_size > 1000
    # truth inside the 99.7 % band of the surfaces at a few points
    zz, mm = np.array([6.5, 7.5, 8.0]), np.array([27.0, 27.5, 26.0])
    for f, tf in ((sf.completeness(mm, zz, draws=True), mdl.completeness(th, mm, zz)),
                  (sf.selection_given_recovered(zz, mm, draws=True),
                   mdl.selection_given_recovered(th, zz, mm))):
        lo, hi = np.quantile(f, [0.0015, 0.9985], axis=0)
        assert np.all((lo <= tf) & (tf <= hi))


def test_file_round_trip_and_determinism(fitted_run, tmp_path):
    run, path, df, mdl, th = fitted_run
    from astropy.io import fits
    sf = SelectionFunction.read(path)
    with fits.open(path) as h:
        assert h[0].header["MODEL"] == "logistic" and h[0].header["CONFHASH"] == "abc"
        grid = h["C_GRID", 1].data
        assert grid.shape == (5, len(sf.z_grid), len(sf.m_grid))
        names = {x.name for x in h}
        assert {"DRAWS", "PARAMS", "C_GRID", "SR_GRID", "P_GRID", "PPC", "META"} <= names
        assert h[0].header["MAGTYPE"] == "apparent" and h[0].header["DEPTHAW"] is False
        # grids: C * SR = P draw by draw, so the medians agree where C is not ~0
        assert np.all(h["PARAMS", 1].data["rhat"] < 1.1) and np.all(h["PARAMS", 1].data["ess"] > 400)
    assert sf.meta["area_arcmin2"] == 4.5 and sf.meta["bands"] == ["f125w", "f160w"]
    # tables come back in native byte order
    assert sf.ppc.dtype["n"].isnative and sf.ppc.dtype["c_binned"].isnative
    # the stored grid equals quantiles of the stored draws (independent recomputation)
    c = sf.model.completeness(sf.draws, sf.m_grid[None, :], sf.z_grid[:, None])
    np.testing.assert_allclose(grid[0], np.median(c, axis=0), atol=1e-6)
    # write -> read: identical draws and grids
    p2 = tmp_path / "copy.fits"
    sf.write(p2)
    sf2 = SelectionFunction.read(p2)
    np.testing.assert_array_equal(sf2.draws, sf.draws)
    np.testing.assert_array_equal(sf2.z_grid, sf.z_grid)
    with fits.open(p2) as h2:
        np.testing.assert_array_equal(h2["C_GRID", 1].data, grid)
    # same seed, same data: identical chains; a resumed chain equals an uninterrupted one
    cells = aggregate_cells(df[df.z.isin([6.5, 7.5, 8.5])])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        a = fit_surfaces(cells, sf.model, seed=11, max_steps=200, min_steps=1000)
        b = fit_surfaces(cells, sf.model, seed=11, max_steps=200, min_steps=1000)
        half = fit_surfaces(cells, sf.model, seed=11, max_steps=100, min_steps=1000)
        # a re-run with the same cap continues past it (max_steps counts this call's steps)
        resumed = fit_surfaces(cells, sf.model, seed=11, max_steps=100, min_steps=1000, resume=half)
    for x, y in ((a, b), (a, resumed)):
        for bx, by in zip(x.blocks, y.blocks):
            np.testing.assert_array_equal(bx.chain, by.chain)


def test_ppc_table_is_beta_binomial_posterior_mean(fitted_run):
    run, path, df, mdl, th = fitted_run
    sf = SelectionFunction.read(path)
    t = sf.ppc
    for row in t[::7]:
        d = df[(df.z == row["z"]) & (df.mag == row["mag"])]
        n, k, ks = len(d), int(d.recovered.sum()), int(d.selected.sum())
        assert (row["n"], row["k_rec"], row["k_sel"]) == (n, k, ks)
        assert row["c_binned"] == pytest.approx((k + 1) / (n + 2), rel=1e-12)
        assert row["p_binned"] == pytest.approx((ks + 1) / (n + 2), rel=1e-12)
        assert row["c_binned_q16"] == pytest.approx(stats.beta(k + 1, n - k + 1).ppf(0.16))
        # the model column is the cell mean of C over its sources, posterior median
        c = sf.model.completeness(sf.draws, d.mag_input.to_numpy(), d.z.to_numpy()).mean(axis=1)
        assert row["c_model"] == pytest.approx(np.median(c), abs=0.02)
    # a well-specified model: mid-p values are not piled up at 0 or 1, verdict adequate
    assert np.mean(t["extreme"]) < 0.05
    summ = json.loads((run / "fit" / "summary.json").read_text())["fits"]["all"]
    assert summ["adequate"] and summ["converged"]


def test_ppc_flags_a_misfit():
    """Data from two depths fitted without depth: the PPC says 'not adequate'."""
    from glaciar.inference.diagnostics import ppc_cells, ppc_verdict
    mdl, th = truth_model()
    rng = np.random.default_rng(21)
    df = simulate(mdl, th, 60, rng, scatter=0.0)
    shift = np.where(rng.random(len(df)) < 0.5, 0.0, 1.2)     # half the sources 1.2 mag deeper
    df["recovered"] = rng.random(len(df)) < mdl.completeness(th, df.mag_input - shift, df.z)
    df["selected"] = df.recovered & (rng.random(len(df)) < 0.8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        res = fit_surfaces(aggregate_cells(df), mdl, seed=2, max_steps=1500)
    d = res.draws(300)
    z, m = df.z.to_numpy(), df.mag_input.to_numpy()
    t = ppc_cells(z, df.mag.to_numpy(), m, df.recovered, df.selected,
                  lambda i: mdl.completeness(d, m[i], z[i]),
                  lambda i: mdl.selection_given_recovered(d, z[i], m[i]), depth=27.0 + shift)
    v = ppc_verdict(t)
    assert not v["adequate"] and v["n_extreme"] > v["max_allowed"]


def test_effective_volume_against_quad(fitted_run):
    import astropy.units as u
    from astropy.cosmology import Planck18, FlatLambdaCDM
    run, path, df, mdl, th = fitted_run
    sf = SelectionFunction.read(path)
    cosmo = FlatLambdaCDM(H0=70, Om0=0.3)
    m = 27.0
    v = sf.effective_volume([m], area=4.5 * u.arcmin ** 2, cosmology=cosmo)
    area_sr = (4.5 * u.arcmin ** 2).to_value(u.sr)
    for i in (0, 17):
        t = sf.draws[i]
        f = lambda z: (sf.model.completeness(t, m, z) * sf.model.selection_given_recovered(t, z, m)
                       * cosmo.differential_comoving_volume(z).to_value(u.Mpc ** 3 / u.sr))
        ref = integrate.quad(f, sf.z_grid[0], sf.z_grid[-1], epsabs=0, epsrel=1e-8, limit=200)[0]
        assert v.draws[i, 0].to_value(u.Mpc ** 3) == pytest.approx(ref * area_sr, rel=1e-3)
    assert v.lower[0] < v.median[0] < v.upper[0]
    # float area means arcmin^2; default area from the metadata; default cosmology Planck18
    v2 = sf.effective_volume(m)
    v3 = sf.effective_volume(m, area=4.5, cosmology=Planck18)
    assert v2.median == v3.median
    # per-field volumes (no depth: the field's share of the area) add up to the survey's
    va, vb = (sf.effective_volume(m, field=f, cosmology=cosmo) for f in ("f1", "f2"))
    np.testing.assert_allclose((va.draws + vb.draws).value, sf.effective_volume(m, cosmology=cosmo).draws.value,
                               rtol=1e-12)


def test_per_field_fits_and_sample(fitted_run, tmp_path):
    run, path, df, mdl, th = fitted_run
    sub = df[df.z.isin([6.5, 7.5, 8.5])]
    r2 = tmp_path / "r2"
    write_task_table(r2, "task_x_z000_m000_i0000.parquet", sub)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        p = run_fit(r2, per_field=True, model="erf", sampler=SamplerSettings(max_steps=300),
                    plots=False)
    fits_ = SelectionFunction.read_all(p)
    assert sorted(fits_) == ["f1", "f2"] and fits_["f1"].model.shape == "erf"
    with pytest.raises(ValueError, match="pass field="):
        SelectionFunction.read(p)
    one = SelectionFunction.read(p, field="f2").sample(3, seed=1)
    assert len(one) == 3 and one[0].n_draws == 1
    assert one[0].completeness(27.0, 7.0) == pytest.approx(
        one[0].model.completeness(one[0].draws[0], 27.0, 7.0))


def test_propose_cells_picks_widest_interval():
    rng = np.random.default_rng(0)
    z, m = np.array([6.0, 7.0]), np.array([26.0, 27.0, 28.0])
    draws = 0.5 + 0.01 * rng.standard_normal((400, 2, 3))
    draws[:, 1, 2] = 0.5 + 0.2 * rng.standard_normal(400)   # the uncertain cell
    draws[:, 0, 0] = 0.5 + 0.1 * rng.standard_normal(400)
    out = propose_cells(draws, z, m, 2)
    assert (out["z"][0], out["mag"][0]) == (7.0, 28.0)
    assert (out["z"][1], out["mag"][1]) == (6.0, 26.0)
    assert out["width"][0] == pytest.approx(np.subtract(*np.quantile(draws[:, 1, 2], [0.84, 0.16])))


def test_documented_reader_without_glaciar_matches(fitted_run):
    """The stand-alone reader in docs/selection-function-file.md reproduces selection_probability."""
    import pathlib
    import re
    run, path, df, mdl, th = fitted_run
    doc = pathlib.Path(__file__).parents[2] / "docs" / "selection-function-file.md"
    code = re.findall(r"```python\n(.*?)```", doc.read_text(), re.S)[1]
    ns = {}
    exec(code.replace('"selection_function.fits"', repr(str(path))), ns)
    z, m = np.array([6.5, 7.2, 8.1]), np.array([26.0, 27.3, 28.0])
    np.testing.assert_allclose(ns["P"](z, m),
                               SelectionFunction.read(path).selection_probability(z, m, draws=True),
                               rtol=1e-10, atol=1e-14)


# ------------------------------------------------------- speed-path identities
@pytest.mark.parametrize("shape", ["logistic", "erf", "fleming", "sas"])
def test_block_posterior_equals_model_log_posterior(shape):
    """The sampler's BlockPosterior is the model's log posterior (other block's prior aside)."""
    mdl, th = truth_model(shape)
    rng = np.random.default_rng(11)
    for scatter in (0.0, 0.1):           # grid magnitudes (shared terms) and continuous ones
        cells = aggregate_cells(simulate(mdl, th, 6, rng, scatter=scatter))
        pts = mdl.sample_prior(40, rng)
        pts[0] = th
        pts[1, mdl.param_names.index("logit_c_max_0")] = 40.0   # C_max = 1 to double precision
        pts[2, mdl.param_names.index("logit_s_max")] = 40.0
        pts[3, mdl.param_names.index("log_w_0")] = -8.0         # a near-perfect step
        for part in ("c", "s"):
            bp = mdl.block_log_posterior(cells, part)
            other = np.setdiff1d(np.arange(mdl.n_params), bp.index)
            t = (pts[:, other] - mdl.prior_mean[other]) / mdl.prior_sd[other]
            other_prior = (-0.5 * np.sum(t * t, axis=1) - np.sum(np.log(mdl.prior_sd[other]))
                           - 0.5 * len(other) * np.log(2 * np.pi))
            ref = mdl.log_posterior(pts, cells, part) - other_prior
            got = bp(pts[:, bp.index])
            assert np.all(np.isfinite(got))
            np.testing.assert_allclose(got, ref, rtol=1e-10)
            assert bp(pts[0, bp.index]) == pytest.approx(ref[0], rel=1e-10)


def test_autocorr_time_of_ar1_walkers_matches_analytic_tau():
    """AR(1) walkers with phi = 0.5, 0.8, 0.9 per parameter: tau = (1 + phi) / (1 - phi)."""
    from glaciar.inference.sampling import autocorr_time
    rng = np.random.default_rng(12)
    phi = np.array([0.5, 0.8, 0.9])
    n, walkers = 4000, 24
    x = np.empty((n, walkers, 3))                 # (steps, walkers, parameters), as emcee's chains
    x[0] = rng.standard_normal((walkers, 3))
    for i in range(1, n):
        x[i] = phi * x[i - 1] + np.sqrt(1 - phi ** 2) * rng.standard_normal((walkers, 3))
    # relative sd of the windowed estimate ~ sqrt(2 (2M + 1) / (n W)) <= 6 % here (M = 5 tau)
    np.testing.assert_allclose(autocorr_time(x), (1 + phi) / (1 - phi), rtol=0.15)
    # one walker's chain (a single walker is a valid ensemble): same tau, wider tolerance
    np.testing.assert_allclose(autocorr_time(x[:, :1]), (1 + phi) / (1 - phi), rtol=0.5)
    # A parameter no walker has moved (a chain of a few steps): no estimate (0/0), reported
    # as the chain's length, so burn-in and thinning stay finite (it was NaN -> int error).
    stuck = x[:20].copy()
    stuck[:, :, 1] = 0.5 * np.arange(walkers)       # each walker where it started
    tau = autocorr_time(stuck)
    assert tau[1] == 20.0 and np.all(np.isfinite(tau))


def test_sample_block_reproduces_a_known_posterior():
    """sample_block on a correlated Gaussian (and a skewed, bounded-on-one-side density):
    posterior means, sds and correlation against the analytic values, within Monte Carlo error."""
    from glaciar.inference.sampling import sample_block
    mean = np.array([1.0, -2.0, 0.5])
    sd = np.array([0.5, 2.0, 0.1])
    corr = np.array([[1.0, 0.8, 0.0], [0.8, 1.0, -0.3], [0.0, -0.3, 1.0]])
    cov = corr * np.outer(sd, sd)
    icov = np.linalg.inv(cov)

    def log_prob(x):
        d = np.atleast_2d(x) - mean
        return -0.5 * np.einsum("ij,jk,ik->i", d, icov, d)

    # A poor starting proposal: off-centre and 3x too narrow, no correlation.
    res = sample_block(log_prob, np.arange(3), mean + sd, np.diag((sd / 3) ** 2),
                       np.random.SeedSequence(5), max_steps=5000)
    assert res.converged and res.n_steps >= 50 * np.max(res.tau)
    d = res.flat()
    ess = np.min(res.ess)
    assert ess > 1000
    np.testing.assert_array_less(np.abs(d.mean(axis=0) - mean), 4 * sd / np.sqrt(ess))
    np.testing.assert_allclose(d.std(axis=0), sd, rtol=4 / np.sqrt(2 * ess) + 0.01)
    assert abs(np.corrcoef(d.T)[0, 1] - 0.8) < 0.05
    # Gamma(2) in log space is skewed; x = log g: density exp(2 x - e^x), mean digamma(2).
    res = sample_block(lambda x: (2 * np.atleast_2d(x)[:, 0] - np.exp(np.atleast_2d(x)[:, 0])),
                       np.arange(1), np.array([0.0]), np.array([[1.0]]),
                       np.random.SeedSequence(6), max_steps=5000)
    d = res.flat()[:, 0]
    ess = float(np.min(res.ess))
    assert abs(d.mean() - special.digamma(2.0)) < 4 * np.sqrt(special.polygamma(1, 2.0) / ess)
    assert abs(d.var() - special.polygamma(1, 2.0)) < 0.05 * special.polygamma(1, 2.0) + 0.02


# -------------------------------------------------------- V_eff in the summary
def test_run_fit_summary_effective_volume_from_run_manifest(fitted_run, tmp_path):
    """glaciar.manifest's manifest (per-field areas): V_eff(m) in summary.json, pooled and per field."""
    import astropy.units as u
    from astropy.cosmology import FlatLambdaCDM
    from astropy.io import fits
    run, path, df, mdl, th = fitted_run
    sub = df[df.z.isin([6.5, 7.0, 7.5, 8.0, 8.5])]
    r3 = tmp_path / "r3"
    write_task_table(r3, "task_x_z000_m000_i0000.parquet", sub)
    areas = {"f1": 3.0, "f2": 1.5}
    (r3 / "manifest.json").write_text(json.dumps({"fields": ["f1", "f2"], "area_arcmin2": areas}))
    cosmo = FlatLambdaCDM(H0=70, Om0=0.3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = run_fit(r3, model="logistic", plots=False, cosmology=cosmo, max_draws=400)
    with fits.open(p) as h:
        assert h[0].header["AREA"] == 4.5
    sf = SelectionFunction.read(p)
    assert sf.meta["area_arcmin2"] == 4.5 and sf.meta["area_arcmin2_field"] == areas
    e = json.loads((r3 / "fit" / "summary.json").read_text())["fits"]["all"]["effective_volume"]
    assert e["area_arcmin2"] == 4.5
    np.testing.assert_allclose(e["mag"], sf.m_grid, rtol=0, atol=1e-9)
    ref = sf.effective_volume(sf.m_grid[::8], area=4.5 * u.arcmin ** 2, cosmology=cosmo)
    # the summary uses 200 of the chain's draws and 201 Simpson nodes: the same posterior,
    # medians within a fraction of the 68 % width
    width = (ref.upper - ref.lower).to_value(u.Mpc ** 3)
    assert np.all(np.abs(np.array(e["median_mpc3"][::8]) - ref.median.to_value(u.Mpc ** 3))
                  <= 0.25 * width)
    assert np.all(np.array(e["lower_mpc3"]) < np.array(e["median_mpc3"]))
    assert np.all(np.array(e["median_mpc3"]) < np.array(e["upper_mpc3"]))
    assert e["median_mpc3"][0] > 10 * e["median_mpc3"][-1]      # falls with C at faint m
    q = e["quoted"]
    assert len(q["mag"]) == 3 and q["median_mpc3"][0] > q["median_mpc3"][2]
    # per field: each field's own area, Planck18 by default
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pf = run_fit(r3, model="logistic", plots=False, per_field=True, max_draws=300)
    summ = json.loads((r3 / "fit" / "summary.json").read_text())["fits"]
    for f, a in areas.items():
        ef = summ[f]["effective_volume"]
        assert ef["area_arcmin2"] == a and ef["cosmology"] == "Planck18"
        v = SelectionFunction.read(pf, field=f).effective_volume(np.array(ef["mag"][::40]))
        # different draw subsets of one posterior: medians agree to a fraction of the 68 % width
        width = (v.upper - v.lower).to_value(u.Mpc ** 3)
        assert np.all(np.abs(np.array(ef["median_mpc3"][::40]) - v.median.to_value(u.Mpc ** 3))
                      <= 0.25 * width)


@pytest.mark.parametrize("shape", ["logistic", "erf", "fleming", "sas"])
def test_surfaces_on_grid_equal_pointwise_surfaces(shape):
    mdl, th = truth_model(shape)
    draws = mdl.sample_prior(5, np.random.default_rng(14))
    draws[0] = th
    z, m = np.linspace(5.5, 9.5, 9), np.linspace(24.0, 31.0, 11)
    c, s = mdl.surfaces_on_grid(draws, z, m)
    assert c.shape == s.shape == (5, 9, 11)
    np.testing.assert_allclose(c, mdl.completeness(draws, m[None, :], z[:, None]), rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(s, mdl.selection_given_recovered(draws, z[:, None], m[None, :]),
                               rtol=1e-12, atol=1e-300)
    c1, s1 = mdl.surfaces_on_grid(th, z, m)
    np.testing.assert_array_equal(c1, c[0])
