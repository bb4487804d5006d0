"""The edge of the inference: read a run, fit, check, write the selection-function file.

:func:`run_fit` is what ``glaciar fit`` calls.  It reads only the columns the
fit needs from the run's store, decides the model (depth-aware whenever the
local depth varies; ``model="auto"`` picks the completeness step by PSIS-LOO),
samples with :func:`glaciar.inference.fit_surfaces`, runs the posterior-
predictive check and the redshift-edge check, and writes every output only
after all of that succeeded (each file atomically).
"""
from __future__ import annotations

import io
import json
import math
import warnings
from pathlib import Path

import numpy as np

from . import constants as C
from .inference.diagnostics import edge_report, ppc_cells, ppc_verdict
from .inference.fit import (DEFAULT_MAG_RESOLUTION, DEFAULT_MAX_STEPS, BlockChain, FitResult,
                            aggregate_cells, fit_and_choose, fit_surfaces)
from .inference.models import COMPLETENESS_SHAPES, Cells, SurfaceModel
from .inference.selection_function import SelectionFunction

__all__ = ["run_fit", "FitWarning", "format_summary", "MODEL_CHOICES"]

MODEL_CHOICES = COMPLETENESS_SHAPES + ("auto",)
#: Posterior draws used for the PPC, the model comparison and the summary's V_eff.
_DIAG_DRAWS = 400
#: V_eff is quoted in the printed summary at these completeness levels' magnitudes.
_SUMMARY_LEVELS = (0.9, 0.5, 0.2)


class FitWarning(UserWarning):
    """The fit is not adequate (PPC), or the simulated box misses part of the selection."""


def _check_positive(name, value):
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive finite number, not {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number, not {value!r}")
    return v


def _manifest_areas(manifest: dict, run_dir) -> dict:
    """{field: area [arcmin^2]} from the manifest (per-field mapping), or {}."""
    per = manifest.get("area_arcmin2")
    if not isinstance(per, dict):
        return {}
    try:
        out = {str(k): float(v) for k, v in per.items()}
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{run_dir}/manifest.json: 'area_arcmin2' must map fields to areas "
                         f"in arcmin^2 ({exc})") from exc
    bad = [k for k, v in out.items() if not (math.isfinite(v) and v > 0)]
    if bad:
        raise ValueError(f"{run_dir}/manifest.json: area of field(s) {bad} is not > 0")
    return out


def _depth_area(manifest: dict, fields) -> dict:
    """{field: (edges, areas)} from the manifest's ``depth_area`` for the given fields."""
    da = manifest.get("depth_area") or {}
    out = {}
    for f in fields:
        if f in da:
            e = np.asarray(da[f]["bin_edges_mag"], float)
            a = np.asarray(da[f]["area_arcmin2"], float)
            if len(e) == len(a) + 1 and len(a):
                out[f] = (e, a)
    return out


def _weighted_median(values, weights):
    o = np.argsort(values)
    cw = np.cumsum(np.asarray(weights, float)[o])
    return float(np.asarray(values)[o][np.searchsorted(cw, 0.5 * cw[-1])])


def _grid(lo, hi, step, max_n=81):
    """A uniform grid over [lo, hi]; a single value when lo == hi (no zero step)."""
    if not hi > lo:
        return np.array([lo])
    n = int(min(max_n, max(2, round((hi - lo) / step) + 1)))
    return np.linspace(lo, hi, n)


def _cells_hash(cells: Cells, model: SurfaceModel, seed, n_walkers) -> str:
    import hashlib
    h = hashlib.sha256()
    for a in (cells.z, cells.mag, cells.n, cells.k_rec, cells.k_sel):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(json.dumps([model.to_header_dict(), repr(seed), n_walkers], default=str).encode())
    return h.hexdigest()[:16]


def _save_chains(fit_dir, tag, res: FitResult, key: str):
    """Chains as .npy (no pickle) + a JSON with what is needed to resume."""
    from .store import atomic_write_bytes, atomic_write_text
    state = {"key": key, "theta_map": res.theta_map.tolist(), "blocks": []}
    for b in res.blocks:
        for name, arr in (("chain", b.chain), ("log_prob", b.log_prob)):
            buf = io.BytesIO()
            np.save(buf, arr, allow_pickle=False)
            atomic_write_bytes(fit_dir / f"{name}_{tag}_{b.part}.npy", buf.getvalue())
        rs = b.random_state
        state["blocks"].append({
            "part": b.part, "n_accepted": b.n_accepted.tolist(),
            "laplace_cov": np.asarray(b.laplace_cov).tolist(),
            "proposal_mean": np.asarray(b.proposal_mean).tolist(),
            "random_state": [rs[0], np.asarray(rs[1]).tolist(), int(rs[2]), int(rs[3]), float(rs[4])]})
    atomic_write_text(fit_dir / f"state_{tag}.json", json.dumps(state))


def _load_chains(fit_dir, tag, model: SurfaceModel, key: str) -> FitResult | None:
    p = fit_dir / f"state_{tag}.json"
    if not p.exists():
        return None
    try:
        state = json.loads(p.read_text())
        if state.get("key") != key:
            return None
        blocks = []
        for b in state["blocks"]:
            chain = np.load(fit_dir / f"chain_{tag}_{b['part']}.npy", allow_pickle=False)
            lp = np.load(fit_dir / f"log_prob_{tag}_{b['part']}.npy", allow_pickle=False)
            rs = b["random_state"]
            blocks.append(BlockChain(
                part=b["part"], index=model.block_indices(b["part"]), chain=chain, log_prob=lp,
                n_accepted=np.asarray(b["n_accepted"]), tau=None, burn=0, thin=1, converged=False,
                random_state=(rs[0], np.asarray(rs[1], dtype=np.uint32), rs[2], rs[3], rs[4]),
                laplace_cov=np.asarray(b["laplace_cov"]), proposal_mean=np.asarray(b["proposal_mean"])))
        return FitResult(model=model, theta_map=np.asarray(state["theta_map"]), blocks=blocks)
    except (OSError, ValueError, KeyError) as exc:
        warnings.warn(f"{p}: cannot resume from the saved chains ({exc}); starting afresh")
        return None


def _tag(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _one_fit(cells, mdl, fit_dir, tag, seed, n_walkers, max_steps, resume, progress):
    from tqdm.auto import tqdm

    key = _cells_hash(cells, mdl, seed, n_walkers)
    prev = _load_chains(fit_dir, tag, mdl, key) if resume else None
    bar = tqdm(desc=f"fit {tag}", unit="step", disable=not progress, leave=False)
    try:
        res = fit_surfaces(cells, mdl, seed=seed, n_walkers=n_walkers, max_steps=max_steps,
                           callback=bar.update, resume=prev)
    finally:
        bar.close()
    return res, key


def run_fit(run_dir, *, model: str = "auto", per_field: bool = False, seed=0,
            n_walkers: int | None = None, max_steps: int = DEFAULT_MAX_STEPS,
            progress: bool = False, cosmology=None, area_arcmin2: float | None = None,
            mag_resolution: float | None = DEFAULT_MAG_RESOLUTION, resume: bool = True,
            max_draws: int = 1000, plots: bool = True, depth: str = "auto"):
    """Fit C and S to a run's per-source flags and write the selection-function file.

    Parameters
    ----------
    run_dir : path-like
        Run directory of ``glaciar simulate`` (``results/*.parquet``, ``manifest.json``).
    model : {"auto", "logistic", "erf", "fleming", "sas"}
        Completeness step shape; "auto" fits all four and keeps the simplest
        one whose PSIS-LOO elpd is within 2 s.e. of the best.
    per_field : bool
        Fit every field separately (one fit per field in the file) instead of pooled.
    seed : int
        Sampler seed; the same seed and data give identical files.
    n_walkers : int, optional
        emcee walkers per parameter block.
    max_steps : int
        Cap on the steps each chain runs in this call; a re-run extends
        unconverged saved chains by up to this many steps.
    progress : bool
        One progress bar per fit.
    cosmology : astropy Cosmology, optional
        Cosmology of the V_eff entries (default Planck18).
    area_arcmin2 : float, optional
        Survey area [arcmin^2]; rescales the fields' area-by-depth distributions
        to this total (default: the footprint areas in the run manifest).
    mag_resolution : float or None
        Grouping resolution of the magnitude covariate [mag] (:func:`aggregate_cells`).
    resume : bool
        Continue the chains saved under ``RUN_DIR/fit/`` when model, data, seed
        and walkers match.
    max_draws : int
        Posterior draws stored in the file.
    plots : bool
        Write PNG plots under ``RUN_DIR/fit/``.
    depth : {"auto", "on", "off"}
        Depth-aware model: "auto" whenever the local depth varies by more than
        one 0.05 mag bin.

    Returns
    -------
    pathlib.Path
        ``RUN_DIR/selection_function.fits``.  The summary (also in
        ``fit/summary.json``) is :func:`format_summary`'s input.

    Raises
    ------
    ValueError
        Bad arguments (checked before anything is read or sampled), a bad
        per-source table or manifest.
    """
    from .store import atomic_write_bytes, atomic_write_text, read_manifest

    # Arguments first: nothing is read, sampled or written on bad input.
    if model not in MODEL_CHOICES:
        raise ValueError(f"--model {model!r}: expected one of {MODEL_CHOICES}")
    if depth not in ("auto", "on", "off"):
        raise ValueError(f"depth must be 'auto', 'on' or 'off', not {depth!r}")
    area_arcmin2 = _check_positive("--area-arcmin2", area_arcmin2)
    max_steps = DEFAULT_MAX_STEPS if max_steps is None else max_steps
    if int(max_steps) < 1 or int(max_draws) < 1:
        raise ValueError(f"--max-steps ({max_steps}) and max_draws ({max_draws}) must be >= 1")
    run_dir = Path(run_dir)
    manifest = read_manifest(run_dir) or {}
    magnitude_type = str(manifest.get("magnitude_type", "apparent"))
    mag_col = C.COL_M_UV if magnitude_type == "absolute" else C.COL_MAG_INPUT
    want = [C.COL_FIELD, C.COL_Z, C.COL_MAG, mag_col, C.COL_RECOVERED, C.COL_SELECTED, C.COL_DEPTH]
    df = _read_columns(run_dir, want)
    if C.COL_FIELD not in df.columns:
        df[C.COL_FIELD] = "all"
    fields = sorted(map(str, df[C.COL_FIELD].unique()))
    # Only the fields the manifest lists now count: rows of removed fields are ignored.
    listed = manifest.get("fields")
    if listed:
        dropped = sorted(set(fields) - set(map(str, listed)))
        if dropped:
            warnings.warn(f"{run_dir}: ignoring rows of field(s) {dropped}, which the run's "
                          "configuration no longer lists", FitWarning)
            df = df[df[C.COL_FIELD].astype(str).isin(list(map(str, listed)))]
            fields = sorted(map(str, df[C.COL_FIELD].unique()))
    field_area = _manifest_areas(manifest, run_dir)
    depth_area = _depth_area(manifest, fields)

    # Depth-aware?
    has_depth = C.COL_DEPTH in df.columns and np.isfinite(df[C.COL_DEPTH].to_numpy(float)).all()
    if depth == "on" and not has_depth:
        raise ValueError(f"{run_dir}: the per-source table has no finite {C.COL_DEPTH!r} "
                         "column; the depth-aware model needs a run made with local depths")
    spread = float(np.ptp(df[C.COL_DEPTH].to_numpy(float))) if has_depth else 0.0
    depth_aware = has_depth and (depth == "on" or (depth == "auto" and spread > C.DEPTH_BIN_MAG))
    if not has_depth and depth == "auto":
        warnings.warn(f"{run_dir}: no local depths in the per-source table (a run made before "
                      f"glaciar recorded {C.COL_DEPTH!r}); fitting without "
                      "depth, so fields are pooled by injections and V_eff assumes each field's "
                      "completeness is the same everywhere in it", FitWarning)
    depth_ref = None
    if depth_aware:
        if depth_area:
            cen = np.concatenate([0.5 * (e[:-1] + e[1:]) for e, _ in depth_area.values()])
            wts = np.concatenate([a for _, a in depth_area.values()])
            depth_ref = round(_weighted_median(cen, wts), 2)
        else:
            depth_ref = round(float(np.median(df[C.COL_DEPTH])), 2)
    if area_arcmin2 is not None:
        # Rescale the fields' areas (and depth distributions) to the given total.
        tot = sum(np.sum(a) for _, a in depth_area.values()) if depth_area else sum(
            field_area.get(f, 0.0) for f in fields)
        if depth_area and tot > 0:
            depth_area = {f: (e, a * area_arcmin2 / tot) for f, (e, a) in depth_area.items()}
        field_area = ({f: field_area[f] * area_arcmin2 / tot for f in fields if f in field_area}
                      if tot > 0 else {})
        if not field_area and not depth_area:
            field_area = {f: area_arcmin2 / len(fields) for f in fields}

    meta = {k: manifest[k] for k in ("bands", "detection_band", "selection", "config_hash")
            if k in manifest}
    meta.update(fields=fields, magnitude_type=magnitude_type, mag_resolution=mag_resolution,
                pooled=not per_field, depth_aware=bool(depth_aware), depth_ref=depth_ref,
                likelihood="recovered ~ Bernoulli(C); selected | recovered ~ Bernoulli(S)",
                magnitude_column=mag_col)
    # Per-field areas: the depth histograms' when known, else the manifest's footprints.
    per_field_area = ({f: float(np.sum(a)) for f, (_, a) in depth_area.items()} if depth_area
                      else {f: field_area[f] for f in fields if f in field_area})
    if per_field_area:
        meta["area_arcmin2_field"] = per_field_area
        meta["area_arcmin2"] = float(sum(per_field_area.values()))

    fit_dir = run_dir / "fit"
    fit_dir.mkdir(exist_ok=True)
    cells_all = aggregate_cells(df, mag_resolution, depth_ref, mag_col)
    zall = df[C.COL_Z].to_numpy(float)
    mall = df[mag_col].to_numpy(float)
    domain = {"z": (float(zall.min()), float(zall.max())), "mag": (float(mall.min()), float(mall.max()))}
    if depth_aware:
        dall = df[C.COL_DEPTH].to_numpy(float)
        domain["depth"] = (float(dall.min()), float(dall.max()))
    zg = _grid(*domain["z"], 0.05)
    mg = _grid(*domain["mag"], 0.05)
    groups = ([(f, df[df[C.COL_FIELD].astype(str) == f]) for f in fields] if per_field
              else [("all", df)])
    shapes = list(COMPLETENESS_SHAPES) if model == "auto" else [model]

    sfs, outputs = [], []
    summary = {"model": model, "seed": seed, "magnitude_type": magnitude_type,
               "depth_aware": bool(depth_aware), "depth_ref": depth_ref, "fits": {}}
    for i, (name, d) in enumerate(groups):
        cells = cells_all if not per_field else aggregate_cells(d, mag_resolution, depth_ref, mag_col)
        fseed = [int(seed), i] if per_field else int(seed)
        keys = {}

        def fit(c, mdl, name=name, fseed=fseed, keys=keys):
            tag = _tag(f"{name}_{mdl.shape}")
            res, keys[mdl.shape] = _one_fit(c, mdl, fit_dir, tag, fseed, n_walkers, max_steps,
                                            resume, progress)
            return res

        chosen, results, comparison = fit_and_choose(cells, shapes, depth_ref=depth_ref,
                                                     loo_draws=_DIAG_DRAWS, fit=fit)
        res, key, tag = results[chosen], keys[chosen], _tag(f"{name}_{chosen}")
        mdl = res.model
        draws = res.draws(max_draws)
        info = {"nsources": cells.n_sources, "ncells": len(cells), "converge": res.converged,
                "taumax": float(np.max(res.tau)), "essmin": float(np.min(res.ess)),
                "rhatmax": float(np.nanmax(res.split_rhat))}
        own_depth = {name: depth_area[name]} if per_field and name in depth_area else (
            {} if per_field else depth_area)
        sf = SelectionFunction(mdl, draws, zg, mg, meta, name, fit_info=info,
                               depth_area=own_depth if depth_aware else {},
                               domain=domain,
                               diagnostics={"tau": res.tau, "ess": res.ess, "rhat": res.split_rhat})
        if not depth_aware and per_field and name in field_area:
            sf.meta = dict(sf.meta, area_arcmin2_field={name: field_area[name]})
        # Posterior-predictive check on a subset of draws.
        sub = SelectionFunction(mdl, res.draws(_DIAG_DRAWS), meta=sf.meta, field=name,
                                depth_area=sf.depth_area, domain=domain)
        zz = d[C.COL_Z].to_numpy(float)
        mm = d[mag_col].to_numpy(float)
        dd = d[C.COL_DEPTH].to_numpy(float) if depth_aware else None
        mnom = d[C.COL_MAG].to_numpy(float) if C.COL_MAG in d.columns else np.round(mm / 0.25) * 0.25

        def c_fn(idx, zz=zz, mm=mm, dd=dd, sub=sub):
            return sub.model.completeness(sub.draws, mm[idx], zz[idx], None if dd is None else dd[idx])

        def s_fn(idx, zz=zz, mm=mm, dd=dd, sub=sub):
            return sub.model.selection_given_recovered(sub.draws, zz[idx], mm[idx],
                                                       None if dd is None else dd[idx])

        # Cells are split by depth whenever depths are known, also for a fit without
        # depth: that is where such a fit fails.
        sf.ppc = ppc_cells(zz, mnom, mdl.relative_magnitude(mm, dd), d[C.COL_RECOVERED].to_numpy(bool),
                           d[C.COL_SELECTED].to_numpy(bool), c_fn, s_fn,
                           depth=d[C.COL_DEPTH].to_numpy(float) if has_depth else None)
        verdict = ppc_verdict(sf.ppc)
        sf.fit_info["adequate"] = verdict["adequate"]
        sf.fit_info["ppcext"] = verdict["fraction_extreme"]
        gd = sub.grid_draws(zg, mg)
        few = SelectionFunction(mdl, sub.draws[:100], meta=sf.meta, depth_area=sf.depth_area)
        edges = edge_report(gd["P"], zg, mg, extrapolate=lambda z, few=few: few.grid_draws(z, mg)["P"]) \
            if len(zg) > 1 else []
        entry = {
            "n_sources": cells.n_sources, "n_cells": len(cells), "model": chosen,
            "converged": res.converged, "adequate": verdict["adequate"], "ppc": verdict,
            "wall_time_s": res.wall_time, "model_comparison": comparison,
            "blocks": {b.part: {"n_steps": b.n_steps, "n_walkers": b.chain.shape[1],
                                "burn": b.burn, "thin": b.thin, "tau": b.tau.tolist(),
                                "acceptance_fraction": float(np.mean(b.acceptance_fraction)),
                                "converged": b.converged} for b in res.blocks},
            "parameters": _param_summary(res, draws), "z_edges": edges,
            "m50": _m50_summary(sub, zg),
            "c_max": _cmax_summary(sub, zg),
        }
        if not verdict["adequate"]:
            warnings.warn(f"fit {name!r} ({chosen}): {verdict['n_extreme']} of {verdict['n_cells']} "
                          f"cells are extreme in the posterior-predictive check (chance allows "
                          f"{verdict['max_allowed']}); the model does not describe the data there "
                          f"(cells flagged 'extreme' in fit/ppc_{_tag(name)}.ecsv)", FitWarning)
        for e in edges:
            side = "above" if e["end"] == "high" else "below"
            how = (f"the fitted surface extrapolates to ~0 about {e['extend_dz']:.2g} {side} it: "
                   f"extend the z grid to z = {e['z'] + (1 if side == 'above' else -1) * e['extend_dz']:.4g}"
                   if np.isfinite(e["extend_dz"]) else
                   f"it has hardly started to fall there: extend the z grid {side} {e['z']:g} "
                   "until it has")
            warnings.warn(f"fit {name!r}: C*S has not fallen to ~0 at z = {e['z']:g} (still "
                          f"{e['ratio']:.0%} of its peak at m = {e['mag']:.2f}), so V_eff misses "
                          f"the volume {side} it; {how}", FitWarning)
        try:
            entry["effective_volume"] = _veff_summary(mdl, sub, sf, name, domain, mg, zg, cosmology)
        except ValueError as exc:         # no area, or a single redshift
            entry["effective_volume"] = None
            entry["effective_volume_note"] = str(exc)
        summary["fits"][name] = entry
        sfs.append(sf)
        outputs.append((name, tag, res, key, draws, sf))

    # Everything sampled and checked: now write.
    from astropy.table import Table
    for name, tag, res, key, draws, sf in outputs:
        _save_chains(fit_dir, tag, res, key)
        for kind, tab in (("parameters", Table(_param_table(res, draws))), ("ppc", Table(sf.ppc))):
            buf = io.StringIO()
            tab.write(buf, format="ascii.ecsv")
            atomic_write_text(fit_dir / f"{kind}_{_tag(name)}.ecsv", buf.getvalue())
        if plots:
            from .inference.plotting import plot_completeness, plot_selection
            plot_completeness(sf, fit_dir / f"completeness_{_tag(name)}.png")
            plot_selection(sf, fit_dir / f"selection_{_tag(name)}.png")
    atomic_write_text(fit_dir / "summary.json", json.dumps(summary, indent=2, default=_json))
    atomic_write_text(fit_dir / "summary.txt", format_summary(summary))
    out = run_dir / C.SELECTION_FUNCTION_NAME
    atomic_write_bytes(out, SelectionFunction.to_bytes(sfs, meta))
    return out


def _veff_summary(mdl, sub, sf, name, domain, mg, zg, cosmology) -> dict:
    """V_eff on the file's magnitude grid, and at three magnitudes around m50, for the summary."""
    with warnings.catch_warnings():
        # the z-edge warning of the fit already covers V_eff's truncation
        warnings.filterwarnings("ignore", message="effective_volume: C\\*S is still")
        # the full magnitude grid with 200 draws (its median to ~1/15 of the 68 % width)
        ve = SelectionFunction(mdl, sub.draws[:200], meta=sf.meta, field=name,
                               depth_area=sf.depth_area, domain=domain
                               ).effective_volume(mg, cosmology=cosmology, n_z=201)
        lev = sub.magnitude_at(0.5, [np.median(zg)])
        quote = ([float(x) for x in np.round(lev.median[0] + np.array([-1.0, 0.0, 0.5]), 2)]
                 if np.isfinite(lev.median[0]) else [float(x) for x in mg[[0, len(mg) // 2, -1]]])
        vq = sub.effective_volume(quote, cosmology=cosmology, n_z=401)
    return {"area_arcmin2": sub.area_arcmin2(), "z_range": list(domain["z"]),
            "cosmology": getattr(cosmology, "name", None) or "Planck18",
            "mag": mg.tolist(), "median_mpc3": ve.median.value.tolist(),
            "lower_mpc3": ve.lower.value.tolist(), "upper_mpc3": ve.upper.value.tolist(),
            "quoted": {"mag": quote, "median_mpc3": vq.median.value.tolist(),
                       "lower_mpc3": vq.lower.value.tolist(), "upper_mpc3": vq.upper.value.tolist()}}


def _read_columns(run_dir, want):
    """The wanted columns that the store has (column projection)."""
    import pyarrow.parquet as pq

    from .store import read_current_results

    files = sorted((Path(run_dir) / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    have = set(pq.read_schema(files[0]).names) if files else set(want)
    return read_current_results(run_dir, columns=[c for c in want if c in have])


def _json(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _param_table(res: FitResult, draws) -> dict:
    mdl = res.model
    q = np.quantile(draws, [0.5, 0.16, 0.84, 0.025, 0.975], axis=0)
    return {"name": mdl.param_names, "map": res.theta_map, "median": q[0], "q16": q[1],
            "q84": q[2], "q025": q[3], "q975": q[4], "tau": res.tau, "ess": res.ess,
            "rhat": res.split_rhat, "acceptance_fraction": res.acceptance_fraction,
            "n_steps": res.n_steps, "prior_mean": mdl.prior_mean, "prior_sd": mdl.prior_sd}


def _param_summary(res: FitResult, draws) -> dict:
    t = _param_table(res, draws)
    return {n: {"map": float(t["map"][j]), "median": float(t["median"][j]),
                "ci68": [float(t["q16"][j]), float(t["q84"][j])],
                "ci95": [float(t["q025"][j]), float(t["q975"][j])], "tau": float(t["tau"][j]),
                "ess": float(t["ess"][j]), "rhat": float(t["rhat"][j])}
            for j, n in enumerate(res.model.param_names)}


def _m50_summary(sf: SelectionFunction, zg) -> list:
    zs = np.unique(np.round(np.linspace(zg[0], zg[-1], min(len(zg), 5)), 3))
    r = sf.magnitude_at(0.5, zs)
    return [{"z": float(z), "m50": float(a), "ci68": [float(b), float(c)]}
            for z, a, b, c in zip(zs, r.median, r.lower, r.upper)]


def _cmax_summary(sf: SelectionFunction, zg) -> dict:
    from scipy.special import expit
    s = sf.model._slices["logit_c_max"]
    zc = (np.median(zg) - sf.model.z_ref) / sf.model.z_scale
    v = expit(sf.draws[:, s] @ zc ** np.arange(s.stop - s.start))
    q = np.quantile(v, [0.5, 0.16, 0.84])
    return {"z": float(np.median(zg)), "median": float(q[0]), "ci68": [float(q[1]), float(q[2])]}


def format_summary(summary: dict) -> str:
    """The few lines ``glaciar fit`` prints: per fit, the verdicts, m50(z), C_max, V_eff."""
    lines = []
    mlabel = "M_UV" if summary.get("magnitude_type") == "absolute" else "m"
    for name, e in summary["fits"].items():
        depth = (f"depth-aware (d_ref = {summary['depth_ref']:.2f})" if summary.get("depth_aware")
                 else "no depth")
        ppc = e["ppc"]
        lines.append(f"fit {name}: {e['model']}, {depth}, {e['n_sources']} sources; "
                     f"converged: {'yes' if e['converged'] else 'NO'}; adequate: "
                     f"{'yes' if e['adequate'] else 'NO'} ({ppc['n_extreme']}/{ppc['n_cells']} "
                     f"PPC cells extreme, chance allows {ppc['max_allowed']})")
        if e.get("model_comparison"):
            lines.append("  PSIS-LOO: " + ", ".join(
                f"{r['model']} {r['delta_elpd']:+.1f}±{r['se_delta']:.1f}" for r in e["model_comparison"]))
        lines.append(f"  {mlabel} at C = 0.5: " + "; ".join(
            f"z {r['z']:g}: {r['m50']:.2f} [{r['ci68'][0]:.2f}, {r['ci68'][1]:.2f}]" for r in e["m50"]))
        cm = e["c_max"]
        lines.append(f"  C_max(z = {cm['z']:g}) = {cm['median']:.3f} [{cm['ci68'][0]:.3f}, "
                     f"{cm['ci68'][1]:.3f}]")
        ve = e.get("effective_volume")
        if ve:
            q = ve["quoted"]
            lines.append(f"  V_eff ({ve['area_arcmin2']:.2f} arcmin², z {ve['z_range'][0]:g}–"
                         f"{ve['z_range'][1]:g}): " + "; ".join(
                             f"{mlabel} {m:.2f}: {v:.3g} [{lo:.3g}, {hi:.3g}] Mpc³" for m, v, lo, hi in
                             zip(q["mag"], q["median_mpc3"], q["lower_mpc3"], q["upper_mpc3"])))
        elif e.get("effective_volume_note"):
            lines.append(f"  V_eff: not computed ({e['effective_volume_note']})")
    return "\n".join(lines) + "\n"
