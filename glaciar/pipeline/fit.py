"""``glaciar fit``: read a run, fit, check, write the selection-function file.

:func:`run_fit` reads the run's stored counts (or, for stores written before
counts, only the columns the fit needs: :func:`glaciar.pipeline.inputs.fit_inputs`),
decides the model (depth-aware whenever the local depth varies;
``model="auto"`` picks the completeness step by PSIS-LOO), samples with
:func:`glaciar.inference.fit_and_choose`, runs the posterior-predictive check
and the redshift-edge check (:mod:`glaciar.inference.diagnostics`), and
writes every output only after all of that succeeded, as one unit (built in
``RUN_DIR/.fit.new/`` and swapped in, :mod:`glaciar.pipeline.fitdir`), holding the
run's lock throughout.  Degenerate runs (nothing recovered or nothing selected, in
the run or a field) are refused before anything is sampled
(:func:`check_not_degenerate`); a detection-only run fits C alone (S = 1 exactly):

``RUN_DIR/selection_function.fits``
    :meth:`glaciar.SelectionFunction.to_bytes` (layout: :mod:`glaciar.inference.selection_format`),
    with the LF products of :mod:`glaciar.pipeline.selection_file`.
``RUN_DIR/fit/``
    ``summary.json`` and ``summary.txt`` (:mod:`glaciar.pipeline.summary`),
    ``parameters_<field>.ecsv``, ``ppc_<field>.ecsv``, the saved chains
    (:mod:`glaciar.pipeline.chains`) and the PNG figures
    (:mod:`glaciar.pipeline.figures`).
"""
from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import time
import warnings
from pathlib import Path

import numpy as np

from .. import constants as C
from ..inference.diagnostics import edge_report, ppc_cells, ppc_verdict
from ..inference.fit import DEFAULT_MAG_RESOLUTION, fit_and_choose, fit_surfaces
from ..inference.models import COMPLETENESS_SHAPES
from ..inference.counts import SurveyVolume
from ..inference.sampling import DEFAULT_MAX_STEPS, SamplerSettings
from ..inference.selection_function import SelectionFunction
from .chains import chains_key, file_tag, load_chains, save_chains
from .fitdir import FitStage, hold_run
from .inputs import depth_area as _depth_area
from .inputs import fit_inputs, manifest_areas
from .contamination import add_contamination
from .covariate_fit import covariate_summary
from .lens_covariate import fit_magnification, magnification_rows
from .selection_file import add_lf_products, lens_nodes_from_manifest
from .summary import (cmax_summary, format_summary, json_default, m50_summary, param_summary,
                      param_table, veff_summary)

__all__ = ["run_fit", "FitWarning", "MODEL_CHOICES", "check_not_degenerate", "kept_reason"]

MODEL_CHOICES = COMPLETENESS_SHAPES + ("auto",)
#: Posterior draws used for the PPC, the model comparison and the summary's V_eff.
_DIAG_DRAWS = 400
#: Draws of the extrapolated surface in the redshift-edge check.
_EDGE_DRAWS = 100
#: Step of the file's z and magnitude grids [z, mag] (at most 81 points each).
_GRID_STEP = 0.05


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


def _one_fit(cells, mdl, fit_dir, tag, seed, n_walkers, max_steps, resume, bar):
    """fit_surfaces, continuing saved chains of the same data and settings; steps on ``bar``."""
    key = chains_key(cells, mdl, seed, n_walkers)
    prev = load_chains(fit_dir, tag, mdl, key) if resume else None
    bar.set_postfix_str(tag, refresh=False)
    res = fit_surfaces(cells, mdl, seed=seed, n_walkers=n_walkers, max_steps=max_steps,
                       callback=bar.update, resume=prev)
    return res, key


def _physical_edges(edges, z_limit):
    """Drop or redirect high-z edges that stop at the detection band's flux limit.

    With an apparent-magnitude grid no source exists where the detection band
    receives no flux (``manifest["detection_z_limit"]``): C*S is 0 beyond it,
    whatever the fitted surface extrapolates. An edge within 0.1 of that limit
    loses nothing worth a warning; farther, the grid can only be extended up to it.
    """
    if z_limit is None:
        return edges
    out = []
    for e in edges:
        if e["end"] == "high":
            if e["z"] >= z_limit - 0.1:
                continue
            target = e["z"] + e["extend_dz"] if np.isfinite(e["extend_dz"]) else np.inf
            if target > z_limit:
                e = {**e, "extend_dz": float(z_limit - 0.05 - e["z"]), "z_limit": float(z_limit)}
        out.append(e)
    return out


def _warn_checks(name, chosen, verdict, edges):
    if not verdict["adequate"]:
        warnings.warn(f"fit {name!r}, model {chosen} (kept): {verdict['n_extreme']} of {verdict['n_cells']} "
                      f"cells are extreme in the posterior-predictive check (chance allows "
                      f"{verdict['max_allowed']}); the model does not describe the data there "
                      f"(cells flagged 'extreme' in fit/ppc_{file_tag(name)}.ecsv)", FitWarning)
    for e in edges:
        side = "above" if e["end"] == "high" else "below"
        how = (f"the detection band receives no flux from z = {e['z_limit']:.3g}: extend the z "
               f"grid up to z = {e['z'] + e['extend_dz']:.4g}" if "z_limit" in e else
               f"the fitted surface extrapolates to ~0 about {e['extend_dz']:.2g} {side} it: "
               f"extend the z grid to z = {e['z'] + (1 if side == 'above' else -1) * e['extend_dz']:.4g}"
               if np.isfinite(e["extend_dz"]) else
               f"it has hardly started to fall there: extend the z grid {side} {e['z']:g} "
               "until it has")
        warnings.warn(f"fit {name!r}, model {chosen} (kept): C*S has not fallen to ~0 at z = {e['z']:g} (still "
                      f"{e['ratio']:.0%} of its peak at m = {e['mag']:.2f}), so V_eff misses "
                      f"the volume {side} it; {how}", FitWarning)


def run_fit(run_dir, *, model: str = "auto", per_field: bool = False,
            sampler: SamplerSettings = SamplerSettings(), cosmology=None,
            area_arcmin2: float | None = None,
            mag_resolution: float | None = DEFAULT_MAG_RESOLUTION, resume: bool = True,
            max_draws: int = 1000, plots: bool = True, depth: str = "auto",
            write: bool = True):
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
    sampler : SamplerSettings
        emcee walkers per parameter block (default the fit's own rule); cap on the
        steps each chain runs in this call (default :data:`DEFAULT_MAX_STEPS`; a
        re-run extends unconverged saved chains by up to this many steps); the seed
        (the same seed and data give identical files); one progress bar (sampler
        steps of every model and field).
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
    write : bool
        False: write nothing and skip the summaries (edges, m50, V_eff); return
        the fitted :class:`SelectionFunction` objects (the adaptive loop's
        intermediate rounds).

    Returns
    -------
    pathlib.Path
        ``RUN_DIR/selection_function.fits``.  The summary (also in
        ``fit/summary.json``) is :func:`format_summary`'s input.  With
        ``write=False``, the list of fits instead.

    Raises
    ------
    ValueError
        Bad arguments (checked before anything is read or sampled), a bad
        per-source table or manifest, or a degenerate run (:func:`check_not_degenerate`:
        nothing recovered, or nothing selected, in the run or in a field).
    glaciar.rundir.RunLockedError
        ``glaciar simulate`` (or another fit) is writing the run.

    Notes
    -----
    The fit holds the run's lock from before it reads until it has written, and
    writes ``fit/`` and the file as one unit (:mod:`glaciar.pipeline.fitdir`).
    A detection-only run (``selection: []`` in its manifest) has S = 1 exactly:
    only C is fitted, and there is no selection figure and no redshift-edge advice.
    A lensed run (manifest ``lens``) also gets the ``magnification`` covariate (C as a
    function of |mu|, :mod:`glaciar.pipeline.lens_covariate`), which V_eff and the count
    tables behind the lens use.
    """
    t_start = time.perf_counter()
    # Arguments first: nothing is read, sampled or written on bad input.
    if model not in MODEL_CHOICES:
        raise ValueError(f"--model {model!r}: expected one of {MODEL_CHOICES}")
    if depth not in ("auto", "on", "off"):
        raise ValueError(f"depth must be 'auto', 'on' or 'off', not {depth!r}")
    area_arcmin2 = _check_positive("--area-arcmin2", area_arcmin2)
    max_steps = DEFAULT_MAX_STEPS if sampler.max_steps is None else sampler.max_steps
    if int(max_steps) < 1 or int(max_draws) < 1:
        raise ValueError(f"--max-steps ({max_steps}) and max_draws ({max_draws}) must be >= 1")
    run_dir = Path(run_dir)
    with hold_run(run_dir, "fit"):
        return _run_fit_locked(run_dir, t_start, model=model, per_field=per_field,
                               sampler=dataclasses.replace(sampler, max_steps=max_steps),
                               volume=SurveyVolume(area=area_arcmin2, cosmology=cosmology),
                               mag_resolution=mag_resolution, resume=resume,
                               max_draws=max_draws, plots=plots, depth=depth, write=write)


def check_not_degenerate(run_dir, data, detection_only: bool) -> None:
    """Refuse a run whose outcome is not a fit: nothing recovered, or nothing selected.

    A surface fitted to all-zero flags is its prior: it would print m50 values
    and 'converged' for a run that measured nothing (e.g. a mis-declared noise map
    giving C = 0 everywhere).  Checked for the whole run and for every field.

    Raises
    ------
    ValueError
        One line naming the run, the field(s) and what is missing.
    """
    fields = np.asarray(data.field).astype(str)
    k_rec = np.asarray(data.k_rec)
    k_sel = np.asarray(data.k_sel)
    n = np.asarray(data.n)
    where = f"{run_dir}"
    if int(k_rec.sum()) == 0:
        raise ValueError(f"{where}: none of the {int(n.sum())} injected sources was recovered; "
                         "there is no completeness to fit (check the noise map type and "
                         "zeropoints, or simulate brighter magnitudes)")
    if not detection_only and int(k_sel.sum()) == 0:
        raise ValueError(f"{where}: none of the {int(k_rec.sum())} recovered sources passes the "
                         "selection; there is no selection function to fit (check the "
                         "selection expressions and the redshift grid)")
    names = sorted(set(fields))
    none_rec = [f for f in names if int(k_rec[fields == f].sum()) == 0]
    if none_rec:
        raise ValueError(f"{where}: no injected source was recovered in field(s) "
                         f"{', '.join(map(repr, none_rec))}; fix or remove them from "
                         "survey.fields before fitting")
    if not detection_only:
        none_sel = [f for f in names if int(k_sel[fields == f].sum()) == 0]
        if none_sel:
            raise ValueError(f"{where}: no recovered source passes the selection in field(s) "
                             f"{', '.join(map(repr, none_sel))}; fix or remove them from "
                             "survey.fields before fitting")


def kept_reason(chosen: str, comparison: list, requested: str) -> str:
    """Why ``chosen`` is the model in the file, in one sentence (for the summary)."""
    if not comparison:
        return f"the only model fitted (--model {requested})"
    best = max(comparison, key=lambda r: r["delta_elpd"])["model"]
    if chosen == best:
        return "the highest PSIS-LOO elpd, and no simpler model within 2 s.e. of it"
    return (f"the simplest model whose PSIS-LOO elpd is within 2 s.e. of the best "
            f"({best})")


def _run_fit_locked(run_dir, t_start, *, model, per_field, sampler, volume, mag_resolution,
                    resume, max_draws, plots, depth, write):
    """:func:`run_fit` once the arguments are checked and the run's lock is held
    (``sampler.max_steps`` resolved; ``volume``: the survey area [arcmin^2] and the
    cosmology of the V_eff entries, no redshift range)."""
    seed, n_walkers, max_steps = sampler.seed, sampler.n_walkers, sampler.max_steps
    progress = sampler.progress
    area_arcmin2, cosmology = volume.area, volume.cosmology
    from ..rundir import atomic_write_bytes, atomic_write_text, read_manifest

    manifest = read_manifest(run_dir) or {}
    magnitude_type = str(manifest.get("magnitude_type", "apparent"))
    mag_col = C.COL_M_UV if magnitude_type == "absolute" else C.COL_MAG_INPUT
    # Counts when the store has them (column projection of rows otherwise): :mod:`.inputs`.
    data = fit_inputs(run_dir, mag_col, mag_resolution)
    fields = sorted(set(map(str, data.field)))
    # Only the fields the manifest lists now count: rows of removed fields are ignored.
    listed = manifest.get("fields")
    if listed:
        dropped = sorted(set(fields) - set(map(str, listed)))
        if dropped:
            warnings.warn(f"{run_dir}: ignoring rows of field(s) {dropped}, which the run's "
                          "configuration no longer lists", FitWarning)
            data = data.subset(np.isin(data.field, list(map(str, listed))))
            fields = sorted(set(map(str, data.field)))
    # A detection-only run (an empty selection list) has S = 1 exactly: nothing to fit.
    detection_only = "selection" in manifest and not manifest.get("selection")
    check_not_degenerate(run_dir, data, detection_only)
    if detection_only and np.any(np.asarray(data.k_sel) != np.asarray(data.k_rec)):
        raise ValueError(f"{run_dir}: the manifest has no selection criteria, but the stored "
                         "'selected' flags differ from 'recovered'; the run's files disagree "
                         "(simulate it again into a new directory)")
    field_area = manifest_areas(manifest, run_dir)
    depth_area = _depth_area(manifest, fields)
    lens_nodes = {f: per for f, per in lens_nodes_from_manifest(manifest).items() if f in fields}
    # Behind a lens C depends on |mu| at fixed observed magnitude: a lensed run's fit has the
    # magnification covariate (:mod:`.lens_covariate`); an unlensed run's is unchanged.
    mu_rows = (magnification_rows(run_dir, mag_col, fields)
               if manifest.get("lens") and lens_nodes else None)

    # Depth-aware?
    has_depth = bool(np.isfinite(data.depth).all())
    if depth == "on" and not has_depth:
        raise ValueError(f"{run_dir}: the per-source table has no finite {C.COL_DEPTH!r} "
                         "column; the depth-aware model needs a run made with local depths")
    spread = float(np.max(data.depth_hi) - np.min(data.depth_lo)) if has_depth else 0.0
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
            depth_ref = round(data.depth_median(), 2)
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
                likelihood=("recovered ~ Bernoulli(C); detection only: S = 1" if detection_only
                            else "recovered ~ Bernoulli(C); selected | recovered ~ Bernoulli(S)"),
                magnitude_column=mag_col)
    # Per-field areas: the depth histograms' when known, else the manifest's footprints.
    per_field_area = ({f: float(np.sum(a)) for f, (_, a) in depth_area.items()} if depth_area
                      else {f: field_area[f] for f in fields if f in field_area})
    if per_field_area:
        meta["area_arcmin2_field"] = per_field_area
        meta["area_arcmin2"] = float(sum(per_field_area.values()))

    # Saved chains are read from the current fit/ (resume); nothing is written there. A fit/
    # that is a symbolic link is refused rather than read.
    from ..paths import run_subdir
    fit_dir = run_subdir(run_dir, "fit", create=False)
    cells_all = data.cells(mag_resolution, depth_ref, mag_col)
    domain = {"z": (float(data.z.min()), float(data.z.max())),
              "mag": (float(np.min(data.mag_lo)), float(np.max(data.mag_hi)))}
    if depth_aware:
        domain["depth"] = (float(np.min(data.depth_lo)), float(np.max(data.depth_hi)))
    zg = _grid(*domain["z"], _GRID_STEP)
    mg = _grid(*domain["mag"], _GRID_STEP)
    groups = ([(f, data.subset(data.field == f)) for f in fields] if per_field
              else [("all", data)])
    shapes = list(COMPLETENESS_SHAPES) if model == "auto" else [model]

    outputs = []
    summary = {"model": model, "seed": seed, "magnitude_type": magnitude_type,
               "depth_aware": bool(depth_aware), "depth_ref": depth_ref,
               "detection_only": bool(detection_only), "fits": {}}
    from tqdm.auto import tqdm

    # One progress bar for the job (every model and field), named by the fit it is on.
    bar = tqdm(desc="fit", unit="step", disable=not progress, leave=False)
    for i, (name, d) in enumerate(groups):
        t_group = time.perf_counter()
        cells = cells_all if not per_field else d.cells(mag_resolution, depth_ref, mag_col)
        fseed = [int(seed), i] if per_field else int(seed)
        keys = {}

        def fit(c, mdl, name=name, fseed=fseed, keys=keys):
            tag = file_tag(f"{name}_{mdl.shape}")
            res, keys[mdl.shape] = _one_fit(c, mdl, fit_dir, tag, fseed, n_walkers, max_steps,
                                            resume, bar)
            return res

        chosen, results, comparison = fit_and_choose(cells, shapes, depth_ref=depth_ref,
                                                     loo_draws=_DIAG_DRAWS, fit=fit,
                                                     selection=not detection_only,
                                                     label=f"fit {name!r}")
        res, key, tag = results[chosen], keys[chosen], file_tag(f"{name}_{chosen}")
        mdl = res.model
        draws = res.draws(max_draws)
        # This fit's areas: its field's depth distribution (per field) or all of them.
        own_depth = {name: depth_area[name]} if per_field and name in depth_area else (
            {} if per_field else depth_area)
        own_depth = own_depth if depth_aware else {}
        fmeta = (dict(meta, area_arcmin2_field={name: field_area[name]})
                 if not depth_aware and per_field and name in field_area else meta)
        # Posterior-predictive check on a subset of draws.
        sub = SelectionFunction(mdl, res.draws(_DIAG_DRAWS), meta=fmeta, field=name,
                                depth_area=own_depth, domain=domain)
        sub.lens_nodes = {f: per for f, per in lens_nodes.items() if name in ("all", f)} or None
        mu_cov = {}
        if mu_rows is not None and sub.lens_nodes:
            mu_cov = {"magnification": fit_magnification(
                mu_rows, name, i, mdl, seed=seed, n_walkers=n_walkers, max_steps=max_steps,
                max_draws=max_draws, mag_col=mag_col, mag_resolution=mag_resolution)}
            sub.covariates = mu_cov
        zz, mm, mnom = d.z, d.mag, d.mag_nominal
        dd = d.depth if depth_aware else None

        def c_fn(idx, zz=zz, mm=mm, dd=dd, sub=sub):
            return sub.model.completeness(sub.draws, mm[idx], zz[idx], None if dd is None else dd[idx])

        def s_fn(idx, zz=zz, mm=mm, dd=dd, sub=sub):
            return sub.model.selection_given_recovered(sub.draws, zz[idx], mm[idx],
                                                       None if dd is None else dd[idx])

        # Cells are split by depth whenever depths are known, also for a fit without
        # depth: that is where such a fit fails.
        # (From counts, an entry is a group of n sources evaluated at its mean covariates.)
        ppc = ppc_cells(zz, mnom, mdl.relative_magnitude(mm, dd), d.k_rec, d.k_sel, c_fn, s_fn,
                        depth=d.depth_bin if has_depth else None,
                        counts=None if not d.from_counts else d.n)
        verdict = ppc_verdict(ppc)
        fit_info = {"nsources": cells.n_sources, "ncells": len(cells), "converge": res.converged,
                    "taumax": float(np.max(res.tau)), "essmin": float(np.min(res.ess)),
                    "rhatmax": float(np.nanmax(res.split_rhat)),
                    "adequate": verdict["adequate"], "ppcext": verdict["fraction_extreme"]}
        sf = SelectionFunction(mdl, draws, zg, mg, meta=fmeta, field=name, ppc=ppc, fit_info=fit_info,
                               depth_area=own_depth, domain=domain,
                               diagnostics={"tau": res.tau, "ess": res.ess, "rhat": res.split_rhat})
        sf.covariates = dict(mu_cov)
        if not write:
            outputs.append((name, tag, res, key, draws, sf))
            continue
        gd = sub.grid_draws(zg, mg)
        few = SelectionFunction(mdl, sub.draws[:_EDGE_DRAWS], meta=fmeta, depth_area=own_depth)
        # Detection only: no selection, so no redshift edge of it to advise on.
        edges = edge_report(gd["P"], zg, mg, extrapolate=lambda z, few=few: few.grid_draws(z, mg)["P"]) \
            if len(zg) > 1 and not detection_only else []
        edges = _physical_edges(edges, manifest.get("detection_z_limit"))
        entry = {
            "n_sources": cells.n_sources, "n_cells": len(cells), "model": chosen,
            "model_kept_because": kept_reason(chosen, comparison, model),
            "converged": res.converged, "adequate": verdict["adequate"], "ppc": verdict,
            # the sampler time of the kept model alone; wall_time_s (set below) is the whole fit's
            "sampler_time_s": res.wall_time, "model_comparison": comparison,
            "blocks": {b.part: {"n_steps": b.n_steps, "n_walkers": b.chain.shape[1],
                                "burn": b.burn, "thin": b.thin, "tau": b.tau.tolist(),
                                "acceptance_fraction": float(np.mean(b.acceptance_fraction)),
                                "converged": b.converged} for b in res.blocks},
            "parameters": param_summary(res, draws), "z_edges": edges,
            "m50": m50_summary(sub, zg),
            "c_max": cmax_summary(sub, zg),
        }
        if mu_cov:
            entry["covariates"] = covariate_summary(name, mu_cov)
        _warn_checks(name, chosen, verdict, edges)
        try:
            entry["effective_volume"] = veff_summary(sub, mg, zg, cosmology)
        except ValueError as exc:         # no area, or a single redshift
            entry["effective_volume"] = None
            entry["effective_volume_note"] = str(exc)
        # This fit's real wall time: every model compared, the checks and summaries.
        entry["wall_time_s"] = time.perf_counter() - t_group
        summary["fits"][name] = entry
        outputs.append((name, tag, res, key, draws, sf))

    bar.close()
    if not write:
        return [sf for *_, sf in outputs]
    # V_eff(M_UV) and the transfer matrices (issue 8.4), also before anything is written.
    add_lf_products(run_dir, manifest, [sf for *_, sf in outputs], cosmology=cosmology, seed=seed)
    # And the interlopers' passing fraction, when the run injected them (CONTAM).
    add_contamination(run_dir, manifest, [sf for *_, sf in outputs], seed=seed)
    if outputs and outputs[0][-1].interlopers is not None:
        c = outputs[0][-1].interlopers
        summary["interlopers"] = {"m_obs_edges": c.m_edges.tolist(), "fraction": c.fraction.tolist(),
                                  "lo68": c.lower.tolist(), "hi68": c.upper.tolist(),
                                  "n_injected": c.n_injected.tolist(),
                                  "n_selected": c.n_selected.tolist()}

    # Everything sampled and checked: now write, into a stage swapped in as one unit.
    from astropy.table import Table
    with FitStage(run_dir) as stage:
        new_dir = stage.fit_dir
        for name, tag, res, key, draws, sf in outputs:
            save_chains(new_dir, tag, res, key)
            for kind, tab in (("parameters", Table(param_table(res, draws))), ("ppc", Table(sf.ppc))):
                buf = io.StringIO()
                tab.write(buf, format="ascii.ecsv")
                atomic_write_text(new_dir / f"{kind}_{file_tag(name)}.ecsv", buf.getvalue())
            if plots:
                from ..plots import save_png
                from .figures import FIGURE_DPI, completeness_figure, selection_figure
                save_png(completeness_figure(sf), new_dir / f"completeness_{file_tag(name)}.png",
                         dpi=FIGURE_DPI)
                if sf.model.selection:            # detection only: S = 1, nothing to draw
                    save_png(selection_figure(sf), new_dir / f"selection_{file_tag(name)}.png",
                             dpi=FIGURE_DPI)
        _keep_other_chains(fit_dir, new_dir)
        atomic_write_bytes(stage.selection_file,
                           SelectionFunction.to_bytes([sf for *_, sf in outputs], meta))
        # The whole command's wall time, up to the commit (what `glaciar report` shows).
        summary["wall_time_s"] = time.perf_counter() - t_start
        atomic_write_text(new_dir / "summary.json",
                          json.dumps(summary, indent=2, default=json_default))
        atomic_write_text(new_dir / "summary.txt", format_summary(summary))
        return stage.commit()


def _keep_other_chains(old_dir: Path, new_dir: Path) -> None:
    """Saved chains of other models or settings in the previous fit/, kept for a later resume.

    They are keyed by data, model, seed and walkers (:func:`chains_key`), so a
    stale one is never resumed; hard links (copies where links fail) cost no space.
    """
    import shutil

    if not old_dir.is_dir() or old_dir.is_symlink():
        return
    for p in old_dir.iterdir():
        if (p.name.startswith(("chain_", "log_prob_", "state_")) and p.is_file()
                and not p.is_symlink() and not (new_dir / p.name).exists()):
            try:
                os.link(p, new_dir / p.name)
            except OSError:
                shutil.copy2(p, new_dir / p.name)
