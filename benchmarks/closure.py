"""End-to-end luminosity-function closure test: a mock universe in, its LF back out.

A mock universe with a known UV luminosity function (Schechter, non-evolving over
z = 7.8-12.9) is rendered into several demo fields with source shot noise
(:mod:`glaciar.demo.mock`); then the user's path runs on those images, through
the public API only::

    glaciar.simulate(config, run)   # injection-recovery on the fields (with the mock galaxies in)
    glaciar.catalog(run, out)       # the survey's own detections, measured and selected
    glaciar.fit(run)                # the selection function P = C S and its transfer function
    glaciar.lf(run, catalog)        # the LF: Poisson forward model through P and the transfer

and the recovered parameters are compared with the input ones.  Printed (markdown):

* parameters: truth, median and 68 % interval, pull = (median - truth) / half-width of
  the 68 % interval, for the forward model with the transfer function (the pipeline),
  (a) the same model in input magnitude only (``transfer=False``: m_obs taken as m_in),
  and (b) binned 1/V_eff in observed magnitude (M_UV from one mean redshift, V_eff from
  ``sf.effective_volume_muv``), whose binned counts are fitted by a Poisson likelihood;
* observed vs expected counts per observed-magnitude bin (the truth LF through the
  selection function, transfer included; and through the input-magnitude-only model),
  with a Poisson likelihood-ratio (G) test p-value;
* the binned 1/V_eff phi against the truth (chi^2);
* the candidates matched to the mock galaxies (real / contaminants) and run times.

``--ensemble N`` runs N realisations (seeds seed, seed+1, ...: new images, new mock
universe, new injections -- the selection function is simulated again for each) and
reports the coverage of the 68 % intervals of alpha and log phi* and the mean pulls.

The mock universe (stated, with the reasons):

* LF: log phi* = -3.5 + boost, default boost 0.8 dex (log phi* = -2.7), M* = -20.5,
  alpha = -2.0, non-evolving over z = 7.8-12.9 (the simulated range: no galaxy lies where
  the selection function was not measured), M_UV from -22.5 to -19.0: ~35 high-z galaxies
  per arcmin^2 (<= 40 asked).  Redshifts are drawn on the 0.01 lattice of the band tables
  (``z_step``; each cell with its comoving volume's probability), so that their
  magnitudes come from exact cached tables (glaciar.demo.mock: ~1e-5 on any count).
* Fields (``--deeper``, default 1.75 mag): the demo fields with their sky noise scaled
  by 10^(-0.4 x 1.75) = 0.2 (``noise_scale``; 5-sigma F160W ~28.4).  At the demo's own
  depth the J125-dropout selection (S/N_iso >= 8, F125W 1.5 mag fainter than F160W,
  F098M and F606W undetected) reaches only m ~ 26 at z ~ 10, i.e. M_UV ~ -21.6, 1.1 mag
  brighter than M*: ~0.03 candidates per arcmin^2 at the 40 per arcmin^2 cap.  Deeper
  by 1.75 mag, P falls to 50 % at m ~ 27.3 and to ~0 at 28.3 (M_UV ~ -19.2 at z ~ 10):
  ~1.3 candidates per arcmin^2.  M_UV = -19.0, the faint end of the mock, is where
  V_eff is 2e-4 of its bright-end value: beyond the detection limit.  The simulated
  magnitudes are 24.5-29.0 (step 0.5; the demo's z grid), 50 sources x 2 iterations
  per field and cell.
* 4 fields of 2000^2 px (``--fields``, ``--size``): ~23.5 arcmin^2, ~35 candidates.

M* is fixed at its true value in the default fits (``--free-mstar`` adds fits with it
free): M* = -20.5 lies 0.7 mag brighter than the 50 % limit, and ~25 arcmin^2 hold a few
galaxies brighter than it, so the data constrain it weakly; alpha and phi* are the
closure test's parameters.

    python benchmarks/closure.py [--fields 4] [--size 2000] [--seed 1] [--ensemble N]
                                 [--workers 2] [--out DIR] [--keep] [--boost 0.8]
                                 [--deeper 1.75] [--iterations 2] [--n-galaxies 50]
                                 [--free-mstar]

Measured (2026-11-27, ``--ensemble 10 --seed 1``, 4 fields of 2000^2 px, 23.48 arcmin^2; shared
2-core machine; ~5 min per realisation: simulate 165 s, fit 45 s, catalog ~20 s, lf 6 s):

| method | M* | parameter | coverage of 68 % | mean pull (s.e.) | median pull | mean median - truth |
|---|---|---|---|---|---|---|
| forward model + transfer (glaciar.lf) | fixed | log_phi_star | 7/10 = 0.70 | +0.09 (0.35) | +0.29 | -0.001 |
| forward model + transfer (glaciar.lf) | fixed | alpha | 6/10 = 0.60 | -0.06 (0.40) | +0.08 | -0.011 |
| (a) input magnitude only (transfer=False) | fixed | log_phi_star | 7/10 = 0.70 | +0.15 (0.37) | +0.26 | +0.003 |
| (a) input magnitude only (transfer=False) | fixed | alpha | 5/10 = 0.50 | -1.15 (0.47) | -0.93 | -0.431 |
| (b) binned 1/V_eff, M_UV at mean z | fixed | log_phi_star | 9/10 = 0.90 | -0.52 (0.36) | -0.50 | -0.049 |
| (b) binned 1/V_eff, M_UV at mean z | fixed | alpha | 2/10 = 0.20 | -2.29 (0.50) | -2.17 | -0.737 |

| counts test | mean G / bins | p < 0.01 | p < 0.05 | median p |
|---|---|---|---|---|
| truth, transfer | 7.7 / 7.2 | 0/10 | 1/10 | 0.51 |
| truth, input-only | 10.5 / 7.2 | 1/10 | 3/10 | 0.24 |
| fitted median, transfer | 5.6 / 7.2 | 0/10 | 0/10 | 0.67 |
| 1/V_eff binned phi vs truth (chi^2) | 11.7 / 7.0 | 1/10 | 3/10 | 0.15 |

Summed over the realisations: 332 candidates selected against 307.5 expected from the truth
LF through the selection function (+1.40 sigma); 326 of them mock galaxies against the sum
over the mock galaxies of P(z_i, m_i) = 318.9 (+0.40 sigma); 0.6 contaminants per realisation.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from glaciar.demo import mock  # noqa: E402

LOG_PHI_STAR_0 = -3.5
M_STAR = -20.5
ALPHA = -2.0
Z_RANGE = (7.8, 12.9)
M_RANGE = (-22.5, -19.0)
PARAMS = ("log_phi_star", "M_star", "alpha")
MAG_GRID = [float(v) for v in np.round(np.arange(24.5, 29.0 + 1e-9, 0.5), 6)]
MATCH_RADIUS_PIX = 4.0
OBS_BIN = 0.5


# --------------------------------------------------------------------------------------
# The public API (each with the lower-level call it stands for, as a fallback)
# --------------------------------------------------------------------------------------
def _api(name):
    import glaciar

    try:
        return getattr(glaciar, name)
    except AttributeError:
        return None


def api_simulate(cfg_path, run_dir, *, workers, seed):
    f = _api("simulate")
    if f is not None:
        return f(cfg_path, run_dir, workers=workers, seed=seed, progress=False)
    from glaciar.config import load_config
    from glaciar.execute import simulate

    return simulate(load_config(cfg_path), run_dir, workers=workers, seed=seed, progress=False)


def api_catalog(run_dir, out):
    f = _api("catalog")
    if f is not None:
        return f(run_dir, out, progress=False)
    from glaciar.pipeline.catalog import run_catalog

    return run_catalog(run_dir, out, progress=False)


def api_fit(run_dir, seed):
    f = _api("fit")
    if f is not None and callable(f):
        return f(run_dir, seed=seed, plots=False)
    from glaciar.inference.sampling import SamplerSettings
    from glaciar.inference.selection_function import SelectionFunction
    from glaciar.pipeline import run_fit

    path = run_fit(run_dir, sampler=SamplerSettings(seed=seed), plots=False)
    return SelectionFunction.read(path)


def api_lf(run_dir, catalog_path, *, fix, seed):
    """glaciar.lf(run, catalogue): {name: {median, lo68, hi68}}, and the result (or summary)."""
    import glaciar

    f = glaciar.lf
    if callable(f):
        res = f(run_dir, catalog_path, model="schechter", fix=fix, muv_range=M_RANGE,
                z_range=Z_RANGE, seed=seed)
        return res.parameters, res
    from glaciar.pipeline.lf import run_lf      # the package is not callable (yet): its writer

    out = run_lf(run_dir, catalog_path, model="schechter", fix=fix, muv_range=M_RANGE,
                 z_range=Z_RANGE, seed=seed)
    summary = json.loads((Path(out) / "summary.json").read_text())
    return summary["parameters"], summary


def lf_module():
    import importlib

    return importlib.import_module("glaciar.lf")


# --------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------
def pull(summary: dict, truth: float) -> float:
    """(median - truth) / half-width of the 68 % interval."""
    med, lo, hi = (float(summary[k]) for k in ("median", "lo68", "hi68"))
    half = 0.5 * (hi - lo)
    return (med - truth) / half if half > 0 else float("nan")


def g_test(observed, expected) -> tuple[float, int, float]:
    """Poisson likelihood-ratio statistic G = 2 sum(mu - n + n ln(n / mu)), dof, p-value."""
    from scipy import stats

    n = np.asarray(observed, float)
    mu = np.asarray(expected, float)
    ok = mu > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(n > 0, n * np.log(n / mu), 0.0)
    g = float(2.0 * np.sum((mu - n + t)[ok]))
    dof = int(ok.sum())
    return g, dof, float(stats.chi2.sf(g, dof)) if dof else float("nan")


def truth_params(boost: float) -> dict:
    return {"log_phi_star": LOG_PHI_STAR_0 + boost, "M_star": M_STAR, "alpha": ALPHA}


def match_truth(cat, truth, radius=MATCH_RADIUS_PIX):
    """Index into ``truth`` of the nearest mock galaxy within ``radius`` of each row (-1: none)."""
    from scipy.spatial import cKDTree

    out = np.full(len(cat), -1, dtype=np.int64)
    for f in np.unique(np.asarray(cat["field"])):
        ci = np.flatnonzero(np.asarray(cat["field"]) == f)
        ti = np.flatnonzero(np.asarray(truth["field"]) == f)
        if not (ci.size and ti.size):
            continue
        tree = cKDTree(np.c_[truth["x"].to_numpy()[ti], truth["y"].to_numpy()[ti]])
        d, k = tree.query(np.c_[cat["x"].to_numpy()[ci], cat["y"].to_numpy()[ci]])
        out[ci] = np.where(d <= radius, ti[np.minimum(k, ti.size - 1)], -1)
    return out


# --------------------------------------------------------------------------------------
# One realisation
# --------------------------------------------------------------------------------------
class Timer:
    def __init__(self):
        self.t = {}

    def __call__(self, name):
        timer = self

        class _T:
            def __enter__(self):
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                timer.t[name] = timer.t.get(name, 0.0) + time.perf_counter() - self.t0
        return _T()


def make_universe(work: Path, args, seed: int, timer: Timer):
    """Build the fields, draw and render the mock universe; (config path, truth DataFrame)."""
    with timer("build fields"):
        cfg_path = mock.build_mock_survey(
            work / "survey", n_fields=args.fields, shape=(args.size, args.size),
            seed=1000 * seed + 1, noise_scale=10.0 ** (-0.4 * args.deeper),
            config_updates={"simulation": {"n_iterations": args.iterations,
                                           "n_galaxies": args.n_galaxies, "seed": seed},
                            "grid": {"mag": {"values": MAG_GRID}}})
    from glaciar.config import load_config

    cfg = load_config(cfg_path)
    with timer("draw mock"):
        fps = mock.field_footprints(cfg)
        areas = {f: float(fp.sum()) * s ** 2 / 3600.0 for f, (fp, s) in fps.items()}
        scale = next(iter(fps.values()))[1]
        lf = mock.Schechter(**truth_params(args.boost))
        truth = mock.draw_mock_population(np.random.default_rng([seed, 1]), lf, Z_RANGE, M_RANGE,
                                          areas, cfg, pixel_scale_arcsec=scale, z_step=0.01)
    with timer("render mock"):
        tpath = mock.render_mock_universe(cfg_path, truth, seed=seed)
    return cfg_path, mock.read_truth(tpath)


def run_pipeline(work: Path, cfg_path: Path, args, seed: int, timer: Timer):
    """simulate -> catalog -> fit; (run dir, catalogue path, catalogue, selection function, stats)."""
    run_dir = work / "run"
    with timer("simulate"):
        stats = api_simulate(cfg_path, run_dir, workers=args.workers, seed=seed)
    cat_path = run_dir / "catalog.parquet"
    with timer("catalog"):
        cat = api_catalog(run_dir, cat_path)
    with timer("fit"):
        sf = api_fit(run_dir, seed)
    return run_dir, cat_path, cat, sf, stats


# --------------------------------------------------------------------------------------
# The comparisons
# --------------------------------------------------------------------------------------
def phi_truth(boost):
    lf = mock.Schechter(**truth_params(boost))
    return lambda M, z: lf(M) + 0.0 * np.asarray(z, float)


def merged_edges(sf, phi, m_obs, min_expected=3.0):
    """m_obs bins (open ends) merged until each expects >= ``min_expected`` under ``phi``."""
    lo, hi = sf.domain["mag"]
    fine = np.round(np.arange(lo, hi + 1e-9, 0.1), 6)
    edges = np.r_[-np.inf, fine, np.inf]
    ec = sf.expected_counts(phi, edges, z_min=Z_RANGE[0], z_max=Z_RANGE[1], M_uv_range=M_RANGE,
                            draws=False, warn=False)
    mu = ec.median
    out = [edges[0]]
    acc = 0.0
    for k in range(len(mu)):
        acc += mu[k]
        if acc >= min_expected and mu[k + 1:].sum() >= min_expected:
            out.append(edges[k + 1])
            acc = 0.0
    out.append(edges[-1])
    return np.asarray(out)


def counts_table(sf, boost, m_obs, lf_params=None):
    """Observed vs expected per m_obs bin: truth with transfer, truth input-only, fitted median."""
    phi = phi_truth(boost)
    edges = merged_edges(sf, phi, m_obs)
    kw = dict(z_min=Z_RANGE[0], z_max=Z_RANGE[1], M_uv_range=M_RANGE, draws=100, warn=False)
    rows = {"edges": edges, "n_obs": np.histogram(m_obs, edges)[0]}
    ec = sf.expected_counts(phi, edges, transfer=True, **kw)
    rows["truth"] = ec.median
    rows["truth_lo"], rows["truth_hi"] = ec.lower, ec.upper
    rows["truth_input_only"] = sf.expected_counts(phi, edges, transfer=False, **kw).median
    if lf_params is not None:
        lf = mock.Schechter(**{k: lf_params[k]["median"] for k in PARAMS})
        rows["fit"] = sf.expected_counts(lambda M, z: lf(M) + 0.0 * z, edges, transfer=True,
                                         **kw).median
    return rows


def mean_redshift(sf, M_ref):
    """The selection-weighted mean redshift of sources of M_UV = M_ref: sum z P dV / sum P dV."""
    import astropy.units as u

    from glaciar.galaxy.population import get_cosmology
    from glaciar.inference.products import kcorrection

    sed = sf.sed
    cosmo = get_cosmology(sed.cosmology)
    zz = np.linspace(Z_RANGE[0], Z_RANGE[1], 256)
    K = kcorrection(zz, [sed.beta_mean], sed.detection_filter, igm=sed.igm, cosmology=cosmo)[:, 0]
    ok = np.isfinite(K)
    p = np.zeros_like(zz)
    p[ok] = np.median(sf.selection_probability(zz[ok], M_ref + K[ok], draws=True,
                                               outside="extrapolate"), axis=0)
    w = p * cosmo.differential_comoving_volume(zz).to_value(u.Mpc ** 3 / u.sr)
    return float(np.sum(zz * w) / np.sum(w))


def veff_binned(sf, boost, m_obs):
    """(b) Binned 1/V_eff in observed magnitude, M_UV from one mean redshift; a binned fit."""
    from glaciar.inference.products import kcorrection

    sed = sf.sed
    kc = lambda z: float(kcorrection([z], [sed.beta_mean], sed.detection_filter, igm=sed.igm,
                                     cosmology=sed.cosmology)[0, 0])
    zbar = 10.0
    for _ in range(2):
        zbar = mean_redshift(sf, float(np.median(m_obs)) - kc(zbar))
    M = np.asarray(m_obs, float) - kc(zbar)
    dM = 0.5
    edges = np.arange(M_RANGE[0], M_RANGE[1] + 1e-9, dM)
    fine = np.arange(M_RANGE[0] + 0.05, M_RANGE[1], 0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        vf = sf.effective_volume_muv(fine, outside="extrapolate", n_z=101).median.value
    vbin = np.array([vf[(fine >= a) & (fine < b)].mean() for a, b in zip(edges[:-1], edges[1:])])
    n = np.histogram(M, edges)[0]
    truth = mock.Schechter(**truth_params(boost))
    phibar_true = np.array([truth(fine[(fine >= a) & (fine < b)]).mean()
                            for a, b in zip(edges[:-1], edges[1:])])
    mu = phibar_true * vbin * dM
    use = mu > 0.1
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = n / (vbin * dM)
        sig_true = np.sqrt(mu) / (vbin * dM)
    chi2 = float(np.sum(((phi - phibar_true) / sig_true)[use] ** 2))
    from scipy import stats
    dof = int(use.sum())
    p = float(stats.chi2.sf(chi2, dof)) if dof else float("nan")
    return {"zbar": zbar, "edges": edges, "n": n, "veff": vbin, "phi": phi, "phi_true": phibar_true,
            "sig_true": sig_true, "use": use, "chi2": chi2, "dof": dof, "p": p, "fine": fine,
            "dM": dM}


def _binned_fit(edges, n, vbin, dM, fine, fix_mstar, seed):
    """Poisson likelihood of the binned counts, mu_k = <phi>_k V_eff,k dM; emcee, uniform priors."""
    import emcee

    from glaciar.lf.models import PRIORS

    pri = PRIORS["schechter"]
    names = ["log_phi_star", "alpha"] + ([] if fix_mstar else ["M_star"])
    lo = np.array([pri[k][0] for k in names])
    hi = np.array([pri[k][1] for k in names])
    cell = np.clip(np.searchsorted(edges, fine, side="right") - 1, 0, len(n) - 1)
    counts = np.bincount(cell, minlength=len(n)).astype(float)

    def logp(x):
        x = np.atleast_2d(x)
        out = np.full(len(x), -np.inf)
        ok = np.all((x > lo) & (x < hi), axis=1)
        for i in np.flatnonzero(ok):
            ms = M_STAR if fix_mstar else x[i, 2]
            f = mock.Schechter(x[i, 0], ms, x[i, 1])(fine)
            phib = np.bincount(cell, weights=f, minlength=len(n)) / counts
            mu = phib * vbin * dM
            if not np.all(np.isfinite(mu)):
                continue
            out[i] = float(np.sum(n * np.log(np.maximum(mu, 1e-300)) - mu))
        return out

    rng = np.random.default_rng(seed)
    x0 = np.array([-2.7, -2.0] + ([] if fix_mstar else [-20.5]))
    nw = 32
    p0 = x0 + 0.05 * rng.standard_normal((nw, len(names)))
    sampler = emcee.EnsembleSampler(nw, len(names), logp, vectorize=True)
    sampler._random = np.random.RandomState(int(rng.integers(2 ** 31)))
    sampler.run_mcmc(p0, 3000, progress=False)
    chain = sampler.get_chain(discard=1000, flat=True)
    q = np.quantile(chain, [0.5, 0.16, 0.84], axis=0)
    out = {k: {"median": float(q[0, i]), "lo68": float(q[1, i]), "hi68": float(q[2, i])}
           for i, k in enumerate(names)}
    if fix_mstar:
        out["M_star"] = {"median": M_STAR, "lo68": M_STAR, "hi68": M_STAR}
    return out


def selected_truth(sf, truth):
    """Expected number of mock galaxies selected, sum_i P(z_i, m_i) (P averaged over depth)."""
    det = sf.meta.get("detection_band", "f160w")
    m = truth[f"mag_in_{det}"].to_numpy(float)
    z = truth["z"].to_numpy(float)
    ok = np.isfinite(m)
    p = np.zeros(len(m))
    p[ok] = sf.selection_probability(z[ok], m[ok], outside="extrapolate")
    return float(np.nansum(p))


# --------------------------------------------------------------------------------------
# One realisation, end to end
# --------------------------------------------------------------------------------------
def realisation(args, seed: int, work: Path) -> dict:
    from glaciar.inference.counts import SurveyVolume
    from glaciar.inference.sampling import SamplerSettings
    from glaciar.lf import fit_lf

    timer = Timer()
    t0 = time.perf_counter()
    cfg_path, truth = make_universe(work, args, seed, timer)
    run_dir, cat_path, cat, sf, stats = run_pipeline(work, cfg_path, args, seed, timer)
    det = sf.meta.get("detection_band", "f160w")
    sel = cat[np.asarray(cat["selected"], bool)]
    m_obs = sel[f"mag_auto_{det}"].to_numpy(float)
    m_obs = m_obs[np.isfinite(m_obs)]
    match = match_truth(sel, truth)
    res = {"seed": seed, "n_mock": len(truth), "area_arcmin2": sf.area_arcmin2(),
           "n_expected_mock": float(sum(truth.attrs["n_expected"].values())),
           "n_selected": int(len(sel)), "n_matched": int((match >= 0).sum()),
           "n_contaminants": int((match < 0).sum()), "sim_stats": {k: stats.get(k) for k in (
               "n_tasks", "n_sources", "cpu_seconds", "wall_seconds")}}
    with timer("sum P over the mock"):
        res["n_selected_expected_truth"] = selected_truth(sf, truth)
    tp = truth_params(args.boost)
    variants = [("fixed", {"M_star": M_STAR})] + ([("free", None)] if args.free_mstar else [])
    res["fits"] = {}
    with timer("1/V_eff table"):
        vb = veff_binned(sf, args.boost, m_obs)
    res["veff"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in vb.items()
                   if k != "fine"}
    for vname, fix in variants:
        with timer(f"lf ({vname} M*)"):
            params, _ = api_lf(run_dir, cat_path, fix=fix, seed=seed)
        res["fits"][f"transfer/{vname}"] = params
        with timer(f"lf input-only ({vname} M*)"):
            r = fit_lf(sf, m_obs, model="schechter", fix=fix, muv_range=M_RANGE,
                       volume=SurveyVolume(z_min=Z_RANGE[0], z_max=Z_RANGE[1]),
                       transfer=False, sampler=SamplerSettings(seed=seed))
        res["fits"][f"input_only/{vname}"] = r.parameters
        with timer(f"1/V_eff fit ({vname} M*)"):
            res["fits"][f"veff/{vname}"] = _binned_fit(vb["edges"], vb["n"], vb["veff"], vb["dM"],
                                                       vb["fine"], fix is not None, seed)
    with timer("expected counts"):
        ct = counts_table(sf, args.boost, m_obs, res["fits"]["transfer/fixed"])
    res["counts"] = {k: np.asarray(v).tolist() for k, v in ct.items()}
    for key in ("truth", "truth_input_only", "fit"):
        if key in ct:
            res[f"G_{key}"] = g_test(ct["n_obs"], ct[key])
    res["pulls"] = {f: {k: pull(p[k], tp[k]) for k in PARAMS if p[k]["hi68"] > p[k]["lo68"]}
                    for f, p in res["fits"].items()}
    res["times"] = dict(timer.t)
    res["times"]["total"] = time.perf_counter() - t0
    return res


# --------------------------------------------------------------------------------------
# Printing
# --------------------------------------------------------------------------------------
METHODS = {"transfer": "forward model + transfer (glaciar.lf)",
           "input_only": "(a) input magnitude only (transfer=False)",
           "veff": "(b) binned 1/V_eff, M_UV at mean z"}


def _fmt(x, nd=3):
    return "nan" if x is None or not np.isfinite(x) else f"{x:.{nd}f}"


def print_realisation(res: dict, args) -> None:
    tp = truth_params(args.boost)
    t = res["times"]
    print(f"\n## Realisation seed {res['seed']}: {args.fields} fields of {args.size}^2 px, "
          f"{res['area_arcmin2']:.2f} arcmin^2 (total {t['total']:.0f} s)\n")
    print(f"Truth: log phi* = {tp['log_phi_star']:.2f} (-3.5 + boost {args.boost:g} dex), "
          f"M* = {M_STAR}, alpha = {ALPHA}; z {Z_RANGE[0]}-{Z_RANGE[1]}, M_UV {M_RANGE[0]} to "
          f"{M_RANGE[1]}: {res['n_mock']} mock galaxies (expected {res['n_expected_mock']:.1f}; "
          f"{res['n_mock'] / res['area_arcmin2']:.1f} per arcmin^2).")
    print(f"Candidates: {res['n_selected']} selected; {res['n_matched']} matched to a mock galaxy "
          f"(< {MATCH_RADIUS_PIX:g} px), {res['n_contaminants']} not; sum of P(z_i, m_i) over the "
          f"mock galaxies: {res['n_selected_expected_truth']:.1f}.\n")
    print("| method | M* | parameter | truth | median | 68 % interval | pull |")
    print("|---|---|---|---|---|---|---|")
    for key, p in res["fits"].items():
        meth, var = key.split("/")
        for k in PARAMS:
            if var == "fixed" and k == "M_star":
                continue
            pl = res["pulls"][key].get(k, float("nan"))
            print(f"| {METHODS[meth]} | {var} | {k} | {tp[k]:.2f} | {_fmt(p[k]['median'])} | "
                  f"[{_fmt(p[k]['lo68'])}, {_fmt(p[k]['hi68'])}] | {_fmt(pl, 2)} |")
    lf_t = sum(v for k, v in t.items() if k.startswith("lf ("))
    print(f"\n(lf: {lf_t:.0f} s; input-only: "
          f"{sum(v for k, v in t.items() if k.startswith('lf input')):.0f} s; 1/V_eff: "
          f"{sum(v for k, v in t.items() if k.startswith('1/V_eff')):.0f} s)\n")
    c = res["counts"]
    e = c["edges"]
    has_fit = "fit" in c
    print("| m_obs bin | N_obs | N_exp truth (transfer) [68 %] | N_exp truth (input-only) |"
          + (" N_exp fitted (transfer) |" if has_fit else ""))
    print("|---|---|---|---|" + ("---|" if has_fit else ""))
    for k in range(len(c["n_obs"])):
        print(f"| {e[k]:.1f} - {e[k + 1]:.1f} | {c['n_obs'][k]} | {c['truth'][k]:.2f} "
              f"[{c['truth_lo'][k]:.2f}, {c['truth_hi'][k]:.2f}] | {c['truth_input_only'][k]:.2f} |"
              + (f" {c['fit'][k]:.2f} |" if has_fit else ""))
    tot = [f"{sum(c['n_obs'])}", f"{sum(c['truth']):.2f}", f"{sum(c['truth_input_only']):.2f}"] + (
        [f"{sum(c['fit']):.2f}"] if has_fit else [])
    print(f"| total | " + " | ".join(tot) + " |")
    for key, name in (("truth", "truth, transfer"), ("truth_input_only", "truth, input-only"),
                      ("fit", "fitted, transfer")):
        if f"G_{key}" in res:
            g, dof, p = res[f"G_{key}"]
            print(f"\nG-test ({name}): G = {g:.2f}, {dof} bins, p = {p:.3f}", end="")
    print(f"\n\n(expected counts: {t.get('expected counts', 0):.0f} s)\n")
    v = res["veff"]
    print(f"1/V_eff: M_UV = m_obs - K(z_bar = {v['zbar']:.2f}, beta = mean); V_eff from "
          "sf.effective_volume_muv (bin mean); sigma from the truth's expected counts.\n")
    print("| M_UV bin | N | V_eff [Mpc^3] | phi [Mpc^-3 mag^-1] | phi_true (bin mean) | "
          "(phi - phi_true) / sigma |")
    print("|---|---|---|---|---|---|")
    for k in range(len(v["n"])):
        dev = (v["phi"][k] - v["phi_true"][k]) / v["sig_true"][k] if v["use"][k] else float("nan")
        print(f"| {v['edges'][k]:.1f} - {v['edges'][k + 1]:.1f} | {v['n'][k]} | {v['veff'][k]:.4g} | "
              f"{v['phi'][k]:.3g} | {v['phi_true'][k]:.3g} | {_fmt(dev, 2)} |")
    print(f"\nchi^2 of binned phi vs truth = {v['chi2']:.2f} ({v['dof']} bins, p = {v['p']:.3g})\n")
    print("| step | time [s] |")
    print("|---|---|")
    for k, val in t.items():
        print(f"| {k} | {val:.1f} |")
    s = res["sim_stats"]
    print(f"\n(simulation: {s['n_tasks']} tasks, {s['n_sources']} sources, "
          f"{s['cpu_seconds']:.0f} s of task CPU)")


def print_ensemble(results: list[dict], args) -> None:
    tp = truth_params(args.boost)
    n = len(results)
    print(f"\n## Ensemble: {n} realisations (seeds {results[0]['seed']}..{results[-1]['seed']}), "
          f"each simulated, catalogued and fitted anew\n")
    print("| method | M* | parameter | coverage of 68 % | mean pull (s.e.) | median pull | "
          "mean median - truth | mean of (median - forward model's) (s.e.) |")
    print("|---|---|---|---|---|---|---|---|")
    for key in results[0]["fits"]:
        meth, var = key.split("/")
        for k in ("log_phi_star", "alpha", "M_star"):
            if var == "fixed" and k == "M_star":
                continue
            ps = [r["fits"][key][k] for r in results]
            inside = [p["lo68"] <= tp[k] <= p["hi68"] for p in ps]
            pulls = np.array([r["pulls"][key].get(k, np.nan) for r in results], float)
            bias = np.mean([p["median"] - tp[k] for p in ps])
            se = np.nanstd(pulls, ddof=1) / math.sqrt(max(np.isfinite(pulls).sum(), 1)) \
                if np.isfinite(pulls).sum() > 1 else float("nan")
            ref = f"transfer/{var}"
            diff = np.array([r["fits"][key][k]["median"] - r["fits"][ref][k]["median"]
                             for r in results if ref in r["fits"]])
            paired = "" if meth == "transfer" or not diff.size else (
                f"{diff.mean():+.3f} ({diff.std(ddof=1) / math.sqrt(diff.size):.3f})"
                if diff.size > 1 else f"{diff.mean():+.3f}")
            print(f"| {METHODS[meth]} | {var} | {k} | {sum(inside)}/{n} = {np.mean(inside):.2f} | "
                  f"{np.nanmean(pulls):+.2f} ({_fmt(se, 2)}) | {np.nanmedian(pulls):+.2f} | "
                  f"{bias:+.3f} | {paired} |")
    print("\n| counts test | mean G / bins | p < 0.01 | p < 0.05 | median p |")
    print("|---|---|---|---|---|")
    for key, name in (("truth", "truth, transfer"), ("truth_input_only", "truth, input-only"),
                      ("fit", "fitted median, transfer")):
        gs = [r[f"G_{key}"] for r in results if f"G_{key}" in r]
        if gs:
            p = np.array([g[2] for g in gs])
            print(f"| {name} | {np.mean([g[0] for g in gs]):.1f} / {np.mean([g[1] for g in gs]):.1f} | "
                  f"{np.sum(p < 0.01)}/{len(p)} | {np.sum(p < 0.05)}/{len(p)} | {np.median(p):.2f} |")
    chi = np.array([r["veff"]["chi2"] for r in results])
    dof = np.array([r["veff"]["dof"] for r in results])
    pv = np.array([r["veff"]["p"] for r in results])
    print(f"| 1/V_eff binned phi vs truth (chi^2) | {chi.mean():.1f} / {dof.mean():.1f} | "
          f"{np.sum(pv < 0.01)}/{n} | {np.sum(pv < 0.05)}/{n} | {np.median(pv):.2f} |")
    ns = np.array([r["n_selected"] for r in results])
    nexp = np.array([sum(r["counts"]["truth"]) for r in results])
    nmt = np.array([r["n_matched"] for r in results])
    sp = np.array([r["n_selected_expected_truth"] for r in results])
    print(f"\nSummed over the realisations: {ns.sum()} candidates selected vs {nexp.sum():.1f} expected "
          f"from the truth LF through the selection function ((N - mu) / sqrt(mu) = "
          f"{(ns.sum() - nexp.sum()) / math.sqrt(nexp.sum()):+.2f}); {nmt.sum()} of them mock "
          f"galaxies vs sum over the mock galaxies of P(z_i, m_i) = {sp.sum():.1f} "
          f"({(nmt.sum() - sp.sum()) / math.sqrt(sp.sum()):+.2f}).")
    nm = np.array([r["n_matched"] for r in results])
    ne = np.array([r["n_selected_expected_truth"] for r in results])
    print(f"\nCandidates per realisation: mean {ns.mean():.1f} (matched to mock galaxies "
          f"{nm.mean():.1f}, sum P over the mock {ne.mean():.1f}; contaminants "
          f"{(ns - nm).mean():.2f}); run time per realisation: mean "
          f"{np.mean([r['times']['total'] for r in results]):.0f} s "
          f"(simulate {np.mean([r['times']['simulate'] for r in results]):.0f} s, "
          f"fit {np.mean([r['times']['fit'] for r in results]):.0f} s).")


# --------------------------------------------------------------------------------------
def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return _jsonable(o.tolist())
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    return o


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fields", type=int, default=4, help="demo fields (default 4)")
    ap.add_argument("--size", type=int, default=2000, help="pixels per side (default 2000)")
    ap.add_argument("--seed", type=int, default=1, help="first realisation's seed (default 1)")
    ap.add_argument("--ensemble", type=int, default=1, help="realisations (default 1)")
    ap.add_argument("--workers", type=int, default=2, help="simulation workers (default 2)")
    ap.add_argument("--out", type=Path, default=None,
                    help="work directory (default: a temporary one); realisations already in its "
                         "closure_results.jsonl are not run again")
    ap.add_argument("--keep", action="store_true", help="keep the realisations' files")
    ap.add_argument("--boost", type=float, default=0.8,
                    help="log phi* = -3.5 + boost [dex] (default 0.8: ~35 galaxies per arcmin^2)")
    ap.add_argument("--deeper", type=float, default=1.75,
                    help="fields this many mag deeper than the demo's (sky RMS x 10^(-0.4 x); "
                         "default 1.75)")
    ap.add_argument("--iterations", type=int, default=2, help="simulation.n_iterations (default 2)")
    ap.add_argument("--n-galaxies", type=int, default=50, help="simulation.n_galaxies (default 50)")
    ap.add_argument("--free-mstar", action="store_true",
                    help="also fit with M* free (default: M* fixed at its true value only)")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    out = args.out or Path(tempfile.mkdtemp(prefix="glaciar-closure-"))
    out.mkdir(parents=True, exist_ok=True)
    results = []
    log = out / "closure_results.jsonl"
    done = {}
    if log.exists():             # a resumed ensemble: the realisations already finished count
        for line in log.read_text().splitlines():
            try:
                r = json.loads(line)
            except ValueError:
                continue
            done[r["seed"]] = r
    for i in range(args.ensemble):
        seed = args.seed + i
        if seed in done:
            results.append(done[seed])
            print(f"(seed {seed}: finished before, read from {log})")
            continue
        work = out / f"r{seed:03d}"
        if work.exists():
            shutil.rmtree(work)
        res = realisation(args, seed, work)
        results.append(res)
        with open(log, "a") as fh:
            fh.write(json.dumps(_jsonable(res)) + "\n")
        print_realisation(res, args)
        sys.stdout.flush()
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    if args.ensemble > 1:
        print_ensemble(results, args)
    if not args.keep and args.out is None:
        shutil.rmtree(out, ignore_errors=True)
    else:
        print(f"\n(per-realisation results, JSON lines: {log})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
