"""Depth-aware selection functions on surveys simulated through the engine.

* Two fields of areas ~1 : 4 and depths 1 mag apart: the pooled, area-weighted
  P = C*S matches the area-weighted binned fractions, and V_eff matches the
  area-weighted brute-force integral of those fractions; the injection-weighted
  pooling of the previous release (a fit without depth) fails the same checks.
* One field with a deep corner (noise x0.3 over a quarter): the depth-aware fit
  is adequate by the posterior-predictive check, and its completeness at each
  depth matches the binned fractions of the sources at that depth.
"""
import json
import shutil
import warnings

import astropy.units as u
import numpy as np
import pytest
from astropy.cosmology import Planck18
from scipy import stats

from glaciar import constants as C
from glaciar.inference import SelectionFunction
from glaciar.inference.sampling import SamplerSettings
from glaciar.pipeline import run_fit
from glaciar.store import read_results
from glaciar.rundir import read_manifest


def _fit(run_dir, out_name, **kw):
    """Fit a copy of the run's store (fixtures are shared) and return the SelectionFunction."""
    dst = run_dir.parent / out_name
    if not dst.exists():
        shutil.copytree(run_dir, dst, ignore=shutil.ignore_patterns("fit", "selection_function.fits"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")       # z-edge warnings: the grid is inside the window
            run_fit(dst, model="logistic", plots=False, max_draws=600, **kw)
    return SelectionFunction.read(dst / C.SELECTION_FUNCTION_NAME), dst


def _area_weighted_binned(df, areas, zs, ms, rng, n_draws=2000):
    """Area-weighted binned P and C per (z, m), with Beta(k+1, n-k+1) draws of P."""
    tot = sum(areas.values())
    p = np.zeros((len(zs), len(ms)))
    c = np.zeros_like(p)
    pd_ = np.zeros((n_draws, len(zs), len(ms)))
    for (f, z, m), d in df.groupby([C.COL_FIELD, C.COL_Z, C.COL_MAG]):
        i, j = np.searchsorted(zs, z), np.searchsorted(ms, m)
        n, k, kr = len(d), int(d[C.COL_SELECTED].sum()), int(d[C.COL_RECOVERED].sum())
        w = areas[f] / tot
        p[i, j] += w * k / n
        c[i, j] += w * kr / n
        pd_[:, i, j] += w * rng.beta(k + 1, n - k + 1, n_draws)
    return p, c, pd_


@pytest.fixture(scope="module")
def two_depth(two_depth_run):
    cfg, run = two_depth_run
    df = read_results(run)
    areas = read_manifest(run)["area_arcmin2"]
    return run, df, areas


def test_two_fields_area_weighted_selection_and_veff(two_depth):
    run, df, areas = two_depth
    assert 3.5 < areas["deep"] / areas["shallow"] < 4.5
    zs, ms = np.unique(df[C.COL_Z]), np.unique(df[C.COL_MAG])
    rng = np.random.default_rng(0)
    p_bin, c_bin, p_draws = _area_weighted_binned(df, areas, zs, ms, rng)
    dvdz = Planck18.differential_comoving_volume(zs).to_value(u.Mpc ** 3 / u.sr)
    sr = (sum(areas.values()) * u.arcmin ** 2).to_value(u.sr)
    # brute force: trapezoid over the simulated z of the area-weighted binned fractions
    v_bf = np.trapezoid(p_draws * dvdz[None, :, None], zs, axis=1) * sr       # (draws, n_m)
    c_mean = c_bin.mean(axis=0)
    mid = (c_mean >= 0.1) & (c_mean <= 0.9)
    assert mid.sum() >= 3

    results = {}
    for name, depth in (("depth_aware", "auto"), ("injection_weighted", "off")):
        sf, _ = _fit(run, f"fit_{name}", depth=depth)
        assert sf.model.depth_aware == (depth == "auto")
        P = sf.selection_probability(zs[:, None], ms[None, :])
        v = sf.effective_volume(ms[mid])
        med, lo, hi = (q.to_value(u.Mpc ** 3) for q in (v.median, v.lower, v.upper))
        bf_med = np.median(v_bf[:, mid], axis=0)
        # combined 68 % half-widths of the model's and the brute force's intervals
        bf_lo, bf_hi = np.quantile(v_bf[:, mid], [0.16, 0.84], axis=0)
        sig = np.hypot(0.5 * (hi - lo), 0.5 * (bf_hi - bf_lo))
        results[name] = (np.mean(np.abs(P - p_bin)), (med - bf_med) / sig, med / bf_med)
        print(f"{name}: mean |P - P_binned| = {results[name][0]:.3f}; V_eff / brute force at "
              f"m = {ms[mid]}: {np.round(med / bf_med, 3)}; (V - V_bf) / sigma = "
              f"{np.round(results[name][1], 2)}")
    dp, z_score, ratio = results["depth_aware"]
    assert dp <= 0.03
    # no bias: each within 2 combined sigma, and the mean offset within 1 sigma
    assert np.all(np.abs(z_score) <= 2.0) and abs(np.mean(z_score)) <= 1.0
    # the previous release's pooling (by injections) fails the same test by far
    dp_old, z_old, ratio_old = results["injection_weighted"]
    assert dp_old > dp and np.max(np.abs(z_old)) > 4.0 and np.min(ratio_old) < 0.8


def test_two_fields_per_field_volumes_add_up_to_the_survey(two_depth):
    run, df, areas = two_depth
    sf, _ = _fit(run, "fit_depth_aware", depth="auto")
    m = [25.5, 26.0, 26.5]
    parts = [sf.effective_volume(m, field=f).draws.value for f in ("shallow", "deep")]
    # equal up to the merging of depth bins into <= 12 nodes (per field vs survey): 3e-3
    np.testing.assert_allclose(parts[0] + parts[1], sf.effective_volume(m).draws.value, rtol=3e-3)
    assert sf.area_arcmin2("shallow") == pytest.approx(areas["shallow"], rel=1e-9)
    # the shallow field is ~1 mag shallower: its V_eff per area falls at brighter m
    per_area = [p.mean(axis=0) / areas[f] for p, f in zip(parts, ("shallow", "deep"))]
    assert per_area[0][-1] < 0.5 * per_area[1][-1]


def test_deep_corner_adequate_and_per_depth_completeness(deep_corner_run):
    cfg, run = deep_corner_run
    # Two redshifts leave S's high-z edge to its prior: its chain mixes slowly (tau ~ 500
    # steps for logit_s_max), and 50 tau need more than the default 20 000 steps.
    sf, dst = _fit(run, "fit_corner", depth="auto", sampler=SamplerSettings(max_steps=60000))
    summ = json.loads((dst / "fit" / "summary.json").read_text())["fits"]["all"]
    ppc = summ["ppc"]
    print(f"deep corner: {ppc['n_extreme']} of {ppc['n_cells']} PPC cells extreme "
          f"({ppc['fraction_extreme']:.1%}), converged {summ['converged']}")
    assert summ["converged"] and summ["adequate"]
    assert ppc["fraction_extreme"] <= 0.10
    # per-depth completeness: model mean over the sources of a depth group vs binned fraction
    df = read_results(dst)
    deep = df[C.COL_DEPTH] > np.median(df[C.COL_DEPTH]) + 0.6
    assert 0.15 < deep.mean() < 0.35                       # the quarter with noise x 0.3
    rows = []
    for group in (deep, ~deep):
        for (z, m), d in df[group].groupby([C.COL_Z, C.COL_MAG]):
            c = sf.completeness(d[C.COL_MAG_INPUT].to_numpy(), d[C.COL_Z].to_numpy(),
                                d[C.COL_DEPTH].to_numpy(), draws=True).mean(axis=1)
            n, k = len(d), int(d[C.COL_RECOVERED].sum())
            q = np.median(c)
            # two-sided binomial p value of the observed count under the model's completeness
            pval = min(1.0, 2 * min(stats.binom.cdf(k, n, q), stats.binom.sf(k - 1, n, q)))
            rows.append((bool(group is deep), z, m, n, k / n, q, pval))
    pvals = np.array([r[-1] for r in rows])
    # the model curve agrees with the binned fraction of each depth group in (almost) every
    # cell: at most what chance gives at the 1 % level (binomial 99 % quantile)
    allowed = stats.binom.isf(0.01, len(pvals), 0.01)
    assert np.sum(pvals < 0.01) <= allowed, [r for r in rows if r[-1] < 0.01]
    # and the deep corner's completeness is shifted faint by its extra depth (~1.3 mag)
    d50 = [sf.magnitude_at(0.5, 9.0).median[0]]
    shift = np.median(df.loc[deep, C.COL_DEPTH]) - np.median(df.loc[~deep, C.COL_DEPTH])
    c_deep = sf.completeness(27.0, 9.0, np.median(df.loc[deep, C.COL_DEPTH]))
    c_shallow = sf.completeness(27.0, 9.0, np.median(df.loc[~deep, C.COL_DEPTH]))
    assert shift == pytest.approx(1.31, abs=0.1) and c_deep > 0.8 > 0.2 > c_shallow and np.isfinite(d50[0])


def test_deep_corner_documented_reader_averages_depth_bins(deep_corner_run):
    """The stand-alone reader (every 0.05 mag bin) agrees with glaciar's <= 24 merged nodes."""
    import pathlib
    import re
    cfg, run = deep_corner_run
    sf, dst = _fit(run, "fit_corner", depth="auto", sampler=SamplerSettings(max_steps=60000))
    doc = pathlib.Path(__file__).parents[1] / "docs" / "selection-function-file.md"
    code = re.findall(r"```python\n(.*?)```", doc.read_text(), re.S)[1]
    ns = {}
    exec(code.replace('"selection_function.fits"', repr(str(dst / C.SELECTION_FUNCTION_NAME))), ns)
    z, m = np.array([8.5, 9.0, 9.7]), np.array([26.0, 26.8, 27.5])
    got = sf.selection_probability(z, m, draws=True)
    np.testing.assert_allclose(ns["P"](z, m), got, atol=2e-3)
