"""``glaciar lf``: fit a luminosity function to a run's catalogue through its selection function.

:func:`run_lf` is the edge around :func:`glaciar.lf.fit_lf`: it reads
``RUN_DIR/selection_function.fits`` and the catalogue (Parquet, or ECSV / FITS by
extension), checks that the catalogue was measured as the run's injections were
(:func:`read_candidates`: the identity ``glaciar catalog`` records, else the
``config_hash``) and holds the columns it needs -- all before anything is written --
fits, and writes

- ``RUN_DIR/lf/summary.json``: model, candidates, parameters (median and 68 % interval),
  fixed parameters, ranges, convergence, the files it came from;
- ``RUN_DIR/lf/binned_phi.ecsv``: phi(M_UV) in bins with 68 % intervals;
- ``RUN_DIR/lf/counts.ecsv``: observed vs expected candidates per m_obs bin;
- ``RUN_DIR/lf/lf.png``: both, against the model (:mod:`glaciar.pipeline.lf_figures`).

Candidates are the catalogue's rows with ``selected`` true and a finite measured
magnitude in the detection band (``mag_auto_<band>``, the quantity the transfer
function was built from).
"""
from __future__ import annotations

import dataclasses

import io
import json
from pathlib import Path

import numpy as np

from .. import constants as C
from ..inference.counts import SurveyVolume
from ..inference.sampling import SamplerSettings
from ..lf.fit import fit_lf
from ..lf.models import get_model, parse_fix

__all__ = ["run_lf", "read_candidates", "LF_DIRNAME"]

#: Output directory of ``glaciar lf`` inside the run.
LF_DIRNAME = "lf"

_PHI_COLUMNS = {
    "M_lo": ("mag", "bright edge of the M_UV bin (AB, rest 1600 A)"),
    "M_hi": ("mag", "faint edge of the M_UV bin"),
    "M": ("mag", "bin centre"),
    "phi": ("Mpc-3 mag-1", "binned phi: the step's posterior median (stepwise) or "
                           "phi_model * n_obs / n_exp (parametric)"),
    "phi_lo68": ("Mpc-3 mag-1", "16th percentile (stepwise) or Gehrels 1-sigma lower limit"),
    "phi_hi68": ("Mpc-3 mag-1", "84th percentile (stepwise) or Gehrels 1-sigma upper limit"),
    "phi_model": ("Mpc-3 mag-1", "the model averaged over the bin, at the median parameters"),
    "n_obs": ("", "candidates apportioned to the bin by the model's expected contributions"),
    "n_exp": ("", "candidates the model expects from the bin"),
}
_COUNT_COLUMNS = {
    "m_lo": ("mag", "bright edge of the measured-magnitude bin (detection band, AB)"),
    "m_hi": ("mag", "faint edge of the measured-magnitude bin"),
    "n_obs": ("", "candidates in the bin"),
    "n_exp": ("", "expected candidates: posterior-predictive median"),
    "n_exp_lo68": ("", "16th percentile of the expected candidates"),
    "n_exp_hi68": ("", "84th percentile of the expected candidates"),
}
#: With a contamination in the selection function (docs/contamination.md).
_INTERLOPER_COLUMN = {"n_interlopers": ("", "expected interlopers in the bin (included in n_exp): "
                                            "area x number counts x passing fraction")}


def _meta_value(meta: dict, key: str):
    """A metadata value by key, case-insensitively (FITS headers upper-case their keys)."""
    for k, v in meta.items():
        if str(k).lower() == key.lower():
            if isinstance(v, str):
                try:
                    return json.loads(v)        # FITS cards hold JSON strings
                except ValueError:
                    return v
            return v
    return None


def _read_catalog(path: Path):
    """(DataFrame, metadata) of a catalogue file; ``glaciar.pipeline.catalog``'s reader."""
    from .catalog import read_catalog

    table, meta = read_catalog(path)
    if path.suffix.lower() == ".fits" and _meta_value(meta, "config_hash") is None:
        # A FITS table written elsewhere: the identity in its header (HIERARCH CONFIG_HASH).
        from astropy.table import Table
        try:
            meta = {**dict(Table.read(path, hdu=1).meta), **meta}
        except (OSError, ValueError):
            pass
    return table, meta


def read_candidates(run_dir, catalog, manifest: dict | None = None):
    """The candidates' measured magnitudes, after checking the catalogue against the run.

    Parameters
    ----------
    run_dir : path-like
        The run (its ``manifest.json`` gives the identity and the detection band).
    catalog : path-like
        Catalogue file: ``.parquet`` (default), ``.ecsv`` or ``.fits``.
    manifest : dict, optional
        The run's manifest (read if not given).

    Returns
    -------
    m_obs : ndarray
        Measured detection-band magnitudes [AB mag] of the selected rows with a finite one.
    info : dict
        ``n_rows``, ``n_selected``, ``n_no_magnitude``, ``column``, ``config_hash``.

    Raises
    ------
    FileNotFoundError
        No run manifest or no catalogue.
    ValueError
        The catalogue's identity differs from the run's, it carries none, or it lacks the
        ``selected`` or magnitude column (named).  The identity is the one ``glaciar
        catalog`` records (measurement settings, input files, fields, band:
        :func:`glaciar.pipeline.catalog.check_identity`) when present, else the
        ``config_hash`` (both hashes and files named on a mismatch).
    """
    from ..rundir import read_manifest

    run_dir, catalog = Path(run_dir), Path(catalog)
    manifest = read_manifest(run_dir) if manifest is None else manifest
    if manifest is None:
        raise FileNotFoundError(f"{run_dir}: no {C.MANIFEST_NAME} (not a glaciar run directory)")
    table, meta = _read_catalog(catalog)
    run_hash = manifest.get("config_hash")
    cat_hash = _meta_value(meta, "config_hash")
    if "store_hash" in meta:
        # The identity `glaciar catalog` records: measurement settings, input-file
        # fingerprints, fields, detection band -- what fixes the selection.  It decides:
        # config_hash also covers the grid, the iterations and where the files sit (a run's
        # stored config.yaml hashes differently from the file it was made from).
        from .catalog import check_identity
        check_identity(meta, manifest, catalog, run_dir)
    elif cat_hash is None:
        raise ValueError(f"{catalog}: no config_hash in its metadata, so it cannot be matched to "
                         f"the run {run_dir} (config_hash {run_hash}); catalogue the run with "
                         f"`glaciar catalog {run_dir}`")
    elif str(cat_hash) != str(run_hash):
        raise ValueError(f"{catalog} (config_hash {cat_hash}) was not made with the configuration "
                         f"of the run {run_dir} ({C.MANIFEST_NAME} config_hash {run_hash}); its "
                         "selection is not the one the selection function describes")
    det = manifest.get("detection_band")
    if not det:
        raise ValueError(f"{run_dir}/{C.MANIFEST_NAME}: no detection_band recorded")
    col = C.band_column(C.OBS_MAG_QUANTITY, det)
    missing = [c for c in (C.COL_SELECTED, col) if c not in table.columns]
    if missing:
        raise ValueError(f"{catalog}: missing column(s) {', '.join(missing)} (the detection band "
                         f"of the run is {det}); has {', '.join(map(str, table.columns[:12]))}"
                         f"{' ...' if len(table.columns) > 12 else ''}")
    sel = np.asarray(table[C.COL_SELECTED]).astype(bool)
    mag = np.asarray(table[col], float)
    fin = np.isfinite(mag)
    info = {"n_rows": int(len(table)), "n_selected": int(sel.sum()),
            "n_no_magnitude": int((sel & ~fin).sum()), "column": col,
            "config_hash": None if cat_hash is None else str(cat_hash),
            "identity": "store_hash" if "store_hash" in meta else "config_hash"}
    return mag[sel & fin], info


def _read_selection_function(run_dir: Path):
    """The run's fit(s): the pooled one ("all") if present, else every per-field fit."""
    from ..inference import SelectionFunction

    path = run_dir / C.SELECTION_FUNCTION_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no selection function; run `glaciar fit {run_dir}` first")
    fits_ = SelectionFunction.read_all(path)
    if "all" in fits_:
        return [fits_["all"]], path
    return list(fits_.values()), path


def _interlopers_summary(sfs, res) -> dict:
    """What ``summary.json`` says about interlopers: whether and how many were added."""
    if "n_interlopers" not in res.counts:
        return {"added": False, "why": "the selection function holds no contamination (no "
                                       "interlopers: section in the run)"}
    c = sfs[0].interlopers
    return {"added": True, "expected_total": float(np.sum(res.counts["n_interlopers"])),
            "z_range": list(c.z_range), "number_counts": dict(zip(("a", "b", "m0"), c.counts)),
            "note": "expected interlopers per m_obs bin are in counts.ecsv (n_interlopers), "
                    "included in n_exp and in the likelihood"}


def _ecsv(columns: dict, data: dict, meta: dict) -> str:
    from astropy.table import Table

    t = Table()
    for name, (unit, desc) in columns.items():
        t[name] = np.asarray(data[name])
        if unit:
            t[name].unit = unit
        t[name].description = desc
    t.meta.update(meta)
    buf = io.StringIO()
    t.write(buf, format="ascii.ecsv")
    return buf.getvalue()


def run_lf(run_dir, catalog=None, *, model: str = "schechter", fix: dict | None = None,
           muv_range=None, z_range=None, seed: int = 0, progress: bool = False,
           return_result: bool = False):
    """Fit a luminosity function to a run's catalogue and write ``RUN_DIR/lf/``.

    Parameters
    ----------
    run_dir : path-like
        A run with ``selection_function.fits`` (``glaciar fit``).
    catalog : path-like, optional
        The candidates (``glaciar catalog RUN``); default ``RUN_DIR/catalog.parquet``.
    model : {"schechter", "double_power_law" (or "dpl"), "stepwise"}
    fix : dict, optional
        ``{name: value}`` fixed parameters (:func:`glaciar.lf.parse_fix` makes it from
        ``--fix NAME=VALUE``).
    muv_range : (float, float), optional
        M_UV range of phi [AB mag].
    z_range : (float, float), optional
        Redshift range (at most the simulated one).
    seed : int
        Seed of the sampler.
    progress : bool
        Show the sampler's progress.

    return_result : bool
        Return the :class:`glaciar.lf.LFResult` (with the directory as ``result.path``)
        instead of the directory; ``glaciar.lf(run, catalog, ...)`` does.

    Returns
    -------
    Path or LFResult
        ``RUN_DIR/lf``.

    Raises
    ------
    FileNotFoundError
        No run, selection function or catalogue.
    ValueError
        Bad model or ``fix`` (the allowed parameters named), bad ranges, a catalogue of
        another configuration (both hashes named) or without the needed columns, no
        candidates; nothing is written then.
    """
    from ..plots import save_png
    from ..rundir import atomic_write_text, read_manifest
    from .lf_figures import FIGURE_DPI, lf_figure

    run_dir = Path(run_dir)
    # Arguments first: nothing is read on a bad model, --fix or range.
    probe = get_model(model, edges=[0.0, 1.0])
    fix = dict(fix or {})
    if probe.name == "stepwise":
        parse_fix([f"{k}={v}" for k, v in fix.items()], "stepwise")
    else:
        probe.check_fix(fix)
    for name, r in (("muv_range", muv_range), ("z_range", z_range)):
        if r is not None:
            lo, hi = map(float, r)
            if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
                raise ValueError(f"{name} must be (lo, hi) with lo < hi, not {tuple(r)}")
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: no such run directory")
    manifest = read_manifest(run_dir)
    if manifest is None:
        raise FileNotFoundError(f"{run_dir}: no {C.MANIFEST_NAME} (not a glaciar run directory)")
    catalog = Path(catalog) if catalog is not None else run_dir / "catalog.parquet"
    m_obs, info = read_candidates(run_dir, catalog, manifest)
    sfs, sf_path = _read_selection_function(run_dir)
    if sfs[0].meta.get("config_hash") not in (None, manifest.get("config_hash")):
        raise ValueError(f"{sf_path} (config_hash {sfs[0].meta.get('config_hash')}) was not fitted "
                         f"to this run's configuration ({C.MANIFEST_NAME} config_hash "
                         f"{manifest.get('config_hash')}); re-run `glaciar fit {run_dir}`")
    for s in sfs:
        # The run records where the detection band stops receiving flux (edge checks).
        if manifest.get("detection_z_limit") is not None:
            s.meta.setdefault("detection_z_limit", manifest["detection_z_limit"])
    if not m_obs.size:
        raise ValueError(f"{catalog}: no selected candidate with a finite {info['column']} "
                         f"({info['n_rows']} rows, {info['n_selected']} selected)")
    z_min, z_max = (None, None) if z_range is None else z_range
    res = fit_lf(sfs if len(sfs) > 1 else sfs[0], m_obs, model=model, fix=fix,
                 muv_range=muv_range, volume=SurveyVolume(z_min=z_min, z_max=z_max),
                 sampler=SamplerSettings(seed=seed, progress=progress))

    # Everything fitted: now write.
    from ..paths import run_subdir
    out = run_subdir(run_dir, LF_DIRNAME)     # refused if a symbolic link (writes stay in the run)
    summary = {
        "model": res.model, "n_candidates": res.n_candidates,
        "parameters": res.parameters, "fixed": res.fixed,
        "n_outside_window": res.n_outside, "n_selected_without_magnitude": info["n_no_magnitude"],
        "m_obs_column": info["column"],
        "m_obs_range": [float(res.counts["m_lo"][0]), float(res.counts["m_hi"][-1])],
        "muv_range": list(res.muv_range), "z_range": list(res.z_range),
        "transfer": res.transfer, "seed": int(seed), "convergence": res.convergence,
        "interlopers": _interlopers_summary(sfs, res),
        "catalog": str(catalog), "catalog_identity": info["identity"],
        "selection_function": str(sf_path),
        "fields": [s.field for s in sfs], "config_hash": manifest.get("config_hash"),
        "units": {"phi": "Mpc-3 mag-1", "log_phi_star": "log10 Mpc-3 (Schechter) or "
                  "log10 Mpc-3 mag-1 (double power law)", "M_star": "AB mag (M_UV, 1600 A)",
                  "log_phi_k": "log10 Mpc-3 mag-1"},
    }
    meta = {"model": res.model, "config_hash": manifest.get("config_hash"),
            "catalog": str(catalog), "z_range": list(res.z_range)}
    atomic_write_text(out / "binned_phi.ecsv", _ecsv(_PHI_COLUMNS, res.binned_phi, meta))
    columns = {**_COUNT_COLUMNS, **(_INTERLOPER_COLUMN if "n_interlopers" in res.counts else {})}
    atomic_write_text(out / "counts.ecsv", _ecsv(columns, res.counts, meta))
    save_png(lf_figure(res), out / "lf.png", dpi=FIGURE_DPI)
    # The summary last: its presence says the rest was written.
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    if return_result:
        return dataclasses.replace(res, path=out)
    return out
