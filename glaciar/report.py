"""``glaciar report RUN --html``: one self-contained HTML page of a run.

Sections: a summary in plain words (what was simulated, depth, m50 per field with
its 68 % interval, the model kept and why, the fit's wall time), configuration,
run statistics (with the definitions of grid cells, likelihood groups and PPC
cells), status breakdown, C and S with credible bands, posterior-predictive
check (PPC), depth map of completeness, adaptive rounds, selection-function
summary.

Everything shown is read from files the run already holds; nothing is refitted
or resampled.  Two things are evaluated from them for display: the credible
bands at a simulated value between two rows of the file's grid (linear), and
the m50 of each field of a pooled depth-aware fit (the file's draws, averaged
over that field's depths):

==================================  ==================================================
``RUN/config.yaml``                 the configuration, verbatim
``RUN/manifest.json``               grid, fields, areas, area by depth, seed, versions
``RUN/summary/summary_*.ecsv``      counts per (z, m) cell and status (``glaciar report``)
``RUN/selection_function.fits``     headers, ``PARAMS``, the ``C_GRID``/``SR_GRID``/
                                    ``P_GRID`` posterior quantiles, the ``PPC`` table
``RUN/fit/summary.json``            verdicts, m50(z), C_max, PSIS-LOO, V_eff(m)
``RUN/adaptive_rounds.json``        the adaptive loop's log, one object per round
                                    (or the manifest's ``adaptive_rounds``); "none"
                                    when the run has neither
==================================  ==================================================

The page is self-contained: figures are PNG (matplotlib) embedded as base64
``data:`` URIs, the style sheet is inline, and there is no script and no
external URL.  Every number in a table carries its exact value in a
``data-value`` attribute (``repr`` of the float), so that tests and scripts
can read the page back; :mod:`glaciar.html_page` holds these page pieces.

:func:`load_report_data` reads (the I/O edge), :func:`render_html` turns that
into the page, :func:`write_html_report` writes ``RUN/report.html``.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from . import constants as C
from .html_page import STYLE, esc, figure, kv_table, note, section, table

__all__ = ["load_report_data", "render_html", "write_html_report", "write_summary_files", "REPORT_NAME",
           "ADAPTIVE_ROUNDS_NAME"]

#: file name of the page inside the run directory
REPORT_NAME = "report.html"
#: the adaptive loop's log inside the run directory (a JSON list of objects, one per round)
ADAPTIVE_ROUNDS_NAME = C.ADAPTIVE_ROUNDS_NAME
#: quantile planes of the file's grids, in the order the figures want them
_PLANE_ORDER = (0.5, 0.16, 0.84, 0.025, 0.975)
#: per-field per-cell tables are shown up to this many fields (the pooled one always)
_MAX_FIELD_TABLES = 20
#: structural FITS keywords left out of the header tables
_STRUCTURAL = ("XTENSION", "BITPIX", "NAXIS", "PCOUNT", "GCOUNT", "TFIELDS", "TTYPE", "TFORM",
               "TUNIT", "TDIM", "EXTNAME", "EXTVER", "SIMPLE", "EXTEND", "TNULL", "TDISP")


# ------------------------------------------------------------------------------- reading
def _read_ecsv(path):
    from astropy.table import Table

    return Table.read(path, format="ascii.ecsv").to_pandas()


def _header_dict(header) -> dict:
    return {k: header[k] for k in header
            if k and k not in ("COMMENT", "HISTORY") and not any(k.startswith(s) for s in _STRUCTURAL)}


def _grid_axes(header, shape):
    n_z, n_m = shape[1], shape[2]
    m = header["CRVAL1"] + (np.arange(n_m) + 1 - header["CRPIX1"]) * header["CDELT1"]
    z = header["CRVAL2"] + (np.arange(n_z) + 1 - header["CRPIX2"]) * header["CDELT2"]
    return z, m


def _detection_only(manifest: dict) -> bool:
    """A run without selection criteria (``selection: []``): S = 1 exactly, nothing to plot."""
    return "selection" in manifest and not manifest.get("selection")


def _read_selection_function(path: Path) -> dict:
    """Headers, parameter table, grids (planes in ``_PLANE_ORDER``), PPC and DEPTH per fit."""
    from astropy.io import fits
    from astropy.table import Table

    out = {"path": str(path), "fits": []}
    with fits.open(path) as h:
        out["primary"] = _header_dict(h[0].header)
        names = {(x.name, x.ver) for x in h}
        n = int(out["primary"].get("NFITS", 1))
        for i in range(1, n + 1):
            fit = {"extver": i}
            d = h["DRAWS", i]
            fit["draws_header"] = _header_dict(d.header)
            fit["field"] = str(d.header.get("FIELD", "all"))
            fit["n_draws"] = int(d.header.get("NAXIS2", len(d.data)))
            fit["params"] = Table(h["PARAMS", i].data).to_pandas()
            for ext in ("C_GRID", "SR_GRID", "P_GRID"):
                if (ext, i) not in names:
                    continue
                img = h[ext, i]
                data = np.asarray(img.data, float)
                planes = [float(img.header.get(f"QUANT{k + 1}", q)) for k, q in enumerate(_PLANE_ORDER)]
                order = [int(np.argmin(np.abs(np.asarray(planes) - q))) for q in _PLANE_ORDER]
                z, m = _grid_axes(img.header, data.shape)
                fit[ext] = {"q": data[order], "z": z, "m": m}
            for ext in ("PPC", "DEPTH"):
                fit[ext] = Table(h[ext, i].data).to_pandas() if (ext, i) in names else None
            out["fits"].append(fit)
    return out


def _adaptive_rounds(run_dir: Path, manifest: dict) -> list:
    p = run_dir / ADAPTIVE_ROUNDS_NAME
    if p.exists():
        rounds = json.loads(p.read_text(encoding="utf-8"))
    else:
        rounds = manifest.get("adaptive_rounds") or []
    if not isinstance(rounds, list) or not all(isinstance(r, dict) for r in rounds):
        raise ValueError(f"{p if p.exists() else run_dir / C.MANIFEST_NAME}: adaptive rounds "
                         "must be a list of objects, one per round")
    return rounds


def load_report_data(run_dir) -> dict:
    """Everything the page shows, read from the run directory's files.

    Raises
    ------
    FileNotFoundError
        No manifest, or no summary tables (run ``glaciar report RUN`` first, which
        ``glaciar report RUN --html`` does).
    """
    from .rundir import read_manifest
    from .tables import summary_stem

    run_dir = Path(run_dir)
    manifest = read_manifest(run_dir)
    if manifest is None:
        raise FileNotFoundError(f"{run_dir}: no {C.MANIFEST_NAME}; not a glaciar run directory")
    sdir = run_dir / C.SUMMARY_DIRNAME
    if not (sdir / "summary_all.ecsv").exists():
        raise FileNotFoundError(f"{sdir / 'summary_all.ecsv'}: missing; run `glaciar report "
                                f"{run_dir}` first")
    fields = [str(f) for f in manifest.get("fields") or []]
    summaries = {"all": _read_ecsv(sdir / "summary_all.ecsv")}
    for f in fields:
        p = sdir / f"summary_{summary_stem(f)}.ecsv"
        if p.exists():
            summaries[f] = _read_ecsv(p)
    cfg_path = run_dir / C.RUN_CONFIG_NAME
    data = {
        "run_dir": str(run_dir.resolve()),
        "manifest": manifest,
        "config_text": cfg_path.read_text(encoding="utf-8") if cfg_path.exists() else None,
        "summaries": summaries,
        "adaptive_rounds": _adaptive_rounds(run_dir, manifest),
        "selection_function": None,
        "fit_summary": None,
    }
    sf_path = run_dir / C.SELECTION_FUNCTION_NAME
    if sf_path.exists():
        data["selection_function"] = _read_selection_function(sf_path)
    fs = run_dir / "fit" / "summary.json"
    if fs.exists():
        data["fit_summary"] = json.loads(fs.read_text(encoding="utf-8"))
    data["field_m50"] = _pooled_field_m50(sf_path, data, fields)
    return data


def _pooled_field_m50(sf_path: Path, data: dict, fields: list) -> dict:
    """m50 per field of a pooled, depth-aware fit of several fields, from the file's draws.

    ``fit/summary.json`` holds the survey-averaged m50 only; each field's differs with its
    depths (C(m | d) = C(m − (d − d_ref))).  Evaluated, not refitted: the file's posterior
    draws averaged over that field's area-by-depth distribution
    (:meth:`glaciar.SelectionFunction.magnitude_at` with ``field=``), at the redshifts of
    the summary's m50.  Empty when not needed (one field, per-field fits, no depth).
    """
    sf, fs = data["selection_function"], data["fit_summary"]
    if (sf is None or not fs or len(fields) < 2 or not sf["primary"].get("DEPTHAW")
            or not ((fs.get("fits") or {}).get("all") or {}).get("m50")):
        return {}
    from .inference import SelectionFunction

    pooled = SelectionFunction.read(sf_path, "all")
    zs = [r["z"] for r in fs["fits"]["all"]["m50"]]
    out = {}
    for f in fields:
        if f not in pooled.depth_area:
            continue
        r = pooled.magnitude_at(0.5, zs, field=f)
        out[f] = [{"z": float(z), "m50": float(a), "ci68": [float(b), float(c)]}
                  for z, a, b, c in zip(zs, r.median, r.lower, r.upper)]
    return out


# ------------------------------------------------------------------------------ helpers
def _mag_label(manifest: dict) -> str:
    if manifest.get("magnitude_type") == "absolute":
        return "M_UV"
    return f"m ({manifest.get('detection_band', 'detection band')}, AB)"


def _beta_interval(k, n):
    """((k+1)/(n+2), 16 %, 84 %) of binned fractions: Beta(k+1, n-k+1) mean and quantiles."""
    from scipy import stats

    k = np.asarray(k, float)
    n = np.asarray(n, float)
    return (k + 1) / (n + 2), stats.beta.ppf(0.16, k + 1, n - k + 1), stats.beta.ppf(0.84, k + 1, n - k + 1)


def _simulated(values, max_n):
    """At most ``max_n`` of the distinct simulated ``values``, evenly spread, ends included."""
    v = np.unique(np.asarray(values, float))
    if v.size > max_n:
        v = v[np.linspace(0, v.size - 1, max_n).round().astype(int)]
    return v


def _planes_at(axis, q, value, dim):
    """The quantile planes ``q`` at ``value`` of the grid ``axis`` (dimension ``dim`` of q).

    Linear between the two grid rows around ``value`` (the file's grid is uniform and
    need not hold the simulated values; the rows are <= 0.05 in z or mag apart for a
    small run, so the interpolation is far inside the bands); the row itself when
    ``value`` is on the grid.
    """
    axis = np.asarray(axis, float)
    if axis.size == 1:
        return np.take(q, 0, axis=dim)
    j = int(np.clip(np.searchsorted(axis, value) - 1, 0, axis.size - 2))
    w = float(np.clip((value - axis[j]) / (axis[j + 1] - axis[j]), 0.0, 1.0))
    lo, hi = np.take(q, j, axis=dim), np.take(q, j + 1, axis=dim)
    return lo if w == 0.0 else hi if w == 1.0 else (1.0 - w) * lo + w * hi


def _points(sub, k: str, n: str, x: str):
    """Binned fractions of the summary rows ``sub`` with data (``n`` > 0) for a curve.

    A cell without injected (``n_input``) or recovered (``n_recovered``) sources has no
    fraction: its Beta(1, 1) mean 0.50 ± 0.34 would only show the prior, so it is left out.
    """
    sub = sub[sub[n].to_numpy(float) > 0]
    y, lo, hi = _beta_interval(sub[k], sub[n])
    return sub[x].to_numpy(float), y, lo, hi


# ----------------------------------------------------------------------------- sections
#: what each count of "cells" on the page is (one fact, one place: the page's definitions)
CELL_TERMS = (
    ("grid cells", "the simulated (z, m) pairs: one row of a summary table each"),
    ("likelihood groups", "the fit's binomial terms: sources with the same redshift and the same "
                          "magnitude covariate (input magnitude rounded to the fit's resolution, "
                          "0.01 mag by default; relative to the local depth in a depth-aware fit) "
                          "summed into one count; the file's NCELLS"),
    ("PPC cells", "the posterior-predictive check's cells: simulated (z, m) pairs split into "
                  "0.25 mag bins of local depth when depths are known; the file's PPC table rows"),
)


def _range_text(values, max_listed: int = 6) -> str:
    """'8, 10' (the distinct values, up to ``max_listed``) or '40 values from 6 to 8'."""
    v = np.unique(np.asarray(values, float))
    if not v.size:
        return "none"
    if v.size <= max_listed:
        return ", ".join(f"{x:g}" for x in v)
    return f"{v.size} values from {v[0]:g} to {v[-1]:g}"


def _pm(median, lower, upper) -> str:
    """'27.31 +0.05/−0.04' (a 68 % interval in plain words); '—' when not reached."""
    if median is None or not all(math.isfinite(float(v)) for v in (median, lower, upper)):
        return "—"
    return f"{median:.2f} +{upper - median:.2f}/−{median - lower:.2f}"


def _field_m50(d: dict) -> list:
    """Rows (field, z, m50, lower_68, upper_68, fit) of m50 per field, from the fit's files.

    At the simulated redshifts among the summary's (all of them if none is simulated).
    A per-field fit's own m50 (``fit/summary.json``); one pooled fit describes a single
    field as it stands, and every field alike when it is not depth-aware; several fields
    of a depth-aware pooled fit each have their own (``load_report_data``'s
    ``field_m50``, from the file's draws).
    """
    fs = (d["fit_summary"] or {}).get("fits", {})
    fields = [str(f) for f in d["manifest"].get("fields", [])]
    simulated = np.unique(d["summaries"]["all"]["z"].to_numpy(float))
    rows = []
    for f in fields:
        if f in fs:
            src, name = fs[f].get("m50") or [], f
        elif "all" in fs and f in (d.get("field_m50") or {}):
            src, name = d["field_m50"][f], "all"
        elif "all" in fs:
            src, name = fs["all"].get("m50") or [], "all"
        else:
            continue
        # at the simulated redshifts when the summary has them (it spreads up to 5 over the range)
        at_sim = [r for r in src if np.isclose(simulated, r["z"], rtol=0, atol=1e-6).any()]
        rows += [(f, r["z"], r["m50"], r["ci68"][0], r["ci68"][1], name) for r in at_sim or src]
    return rows


def _summary_section(d: dict) -> str:
    """The run in plain words: what was simulated, depth, m50, the model kept, the fit time."""
    m = d["manifest"]
    s = d["summaries"]["all"]
    fields = [str(f) for f in m.get("fields", [])]
    n_in, n_rec, n_sel = (int(s[c].sum()) for c in ("n_input", "n_recovered", "n_selected"))
    sel = m.get("selection")
    mag_word = "absolute magnitude M_UV =" if m.get("magnitude_type") == "absolute" else \
        f"{m.get('detection_band', 'detection-band')} magnitude m ="
    area = m.get("area_arcmin2_total")
    where = ", ".join(fields) + (f"; {area:.3g} arcmin² in all" if area else "")
    what = (f"{n_in} artificial galaxies were injected into {len(fields)} "
            f"field{'s' if len(fields) != 1 else ''} ({where}), at {len(s)} grid cells: "
            f"redshift z = {_range_text(s['z'])} × {mag_word} {_range_text(s['mag'])}")
    if m.get("n_iterations") and m.get("n_galaxies"):
        what += f", {m['n_iterations']} iterations of {m['n_galaxies']} sources per field and cell"
    what += f". {n_rec} ({n_rec / max(n_in, 1):.1%}) were recovered"
    if sel is not None and not sel:
        what += "; there are no selection criteria (detection only)."
    else:
        what += (f", and {n_sel} ({n_sel / max(n_in, 1):.1%}) of them also passed the "
                 f"{len(sel or [])} selection criteria.")
    body = f'<p id="summary-simulated">{esc(what)}</p>'
    rows = []
    for f in fields:
        lo, hi, med = _depth_range(m, f)
        rows.append((f, (m.get("area_arcmin2") or {}).get(f), med, lo, hi))
    body += table(["field", "area_arcmin2", "depth_median", "depth_min", "depth_max"], rows,
                   table_id="summary-depth",
                   formats={"area_arcmin2": ".4g", "depth_median": ".2f", "depth_min": ".2f",
                            "depth_max": ".2f"},
                   headers={"area_arcmin2": "area [arcmin²]",
                            "depth_median": "depth: area median [AB]",
                            "depth_min": "shallowest", "depth_max": "deepest"})
    body += note("Depth: the local 5σ limit in a 1-FWHM aperture, over the field's footprint.")
    fs = d["fit_summary"]
    if not fs or d["selection_function"] is None:
        return section("summary", "Summary", body + _not_fitted(d))
    mrows = _field_m50(d)
    if mrows:
        if "all" in fs.get("fits", {}) and len(fields) > 1 and not d.get("field_m50"):
            body += note("One pooled fit that is not depth-aware: C(m, z) is the same for every "
                          "field, and so is m50.")
        mname = "M_UV" if m.get("magnitude_type") == "absolute" else "m"
        body += f"<h3>50 % completeness {esc(mname)}50 per field (68 % interval)</h3>"
        body += table(["field", "z", "m50", "lower_68", "upper_68", "m50_text"],
                       [r[:5] + (_pm(*r[2:5]),) for r in mrows], table_id="summary-m50",
                       formats={"z": "g", "m50": ".2f", "lower_68": ".2f", "upper_68": ".2f"},
                       headers={"m50": f"{mname}50", "lower_68": "68 % lower",
                                "upper_68": "68 % upper", "m50_text": "in words"})
    sentences = []
    for name, e in fs.get("fits", {}).items():
        if not e.get("model"):
            continue
        ok = ("converged" if e.get("converged") else "NOT converged") + ", " + \
             ("adequate by the posterior-predictive check" if e.get("adequate")
              else "NOT adequate by the posterior-predictive check")
        sentences.append(f"Fit {name}: the {e['model']} completeness step was kept — "
                         f"{e.get('model_kept_because') or 'no reason recorded'} ({ok}).")
    if fs.get("wall_time_s") is not None:
        sentences.append(f"The fit took {float(fs['wall_time_s']):.1f} s of wall-clock time "
                         "(the whole `glaciar fit`: every model compared, the checks and the files).")
    else:
        sentences.append("The fit's wall-clock time was not recorded by the glaciar that wrote it.")
    body += '<p id="summary-fit">' + " ".join(esc(t) for t in sentences) + "</p>"
    return section("summary", "Summary", body)


def _config_section(d: dict) -> str:
    m = d["manifest"]
    items = [("detection band", m.get("detection_band")),
             ("bands", ", ".join(map(str, m.get("bands", [])))),
             ("fields", ", ".join(map(str, m.get("fields", [])))),
             ("magnitude type", m.get("magnitude_type")),
             ("z grid", ", ".join(f"{v:g}" for v in m.get("z_values", []))),
             ("magnitude grid", ", ".join(f"{v:g}" for v in m.get("mag_values", []))),
             ("sources per task (n_galaxies)", m.get("n_galaxies")),
             ("iterations per cell", m.get("n_iterations")),
             ("seed", m.get("seed")),
             ("config hash", m.get("config_hash")),
             ("glaciar version", m.get("glaciar_version")),
             ("store format", m.get("store_format"))]
    sel = m.get("selection") or []
    body = kv_table([(k, v) for k, v in items if v is not None], "config-facts")
    body += "<h3>Selection criteria</h3>" + ("<ul>" + "".join(f"<li><code>{esc(s)}</code></li>" for s in sel)
                                             + "</ul>" if sel else note("none"))
    if d["config_text"] is not None:
        body += (f"<details><summary>{esc(C.RUN_CONFIG_NAME)} (the resolved configuration of the "
                 f"run)</summary><pre>{esc(d['config_text'])}</pre></details>")
    else:
        body += note(f"no {C.RUN_CONFIG_NAME} in the run directory")
    return section("configuration", "Configuration", body)


def _depth_range(manifest: dict, field: str):
    da = (manifest.get("depth_area") or {}).get(field)
    if not da:
        return None, None, None
    e = np.asarray(da["bin_edges_mag"], float)
    a = np.asarray(da["area_arcmin2"], float)
    if a.size == 0 or a.sum() <= 0:
        return None, None, None
    nz = np.flatnonzero(a > 0)
    cen = 0.5 * (e[:-1] + e[1:])
    cw = np.cumsum(a)
    return float(e[nz[0]]), float(e[nz[-1] + 1]), float(cen[np.searchsorted(cw, 0.5 * cw[-1])])


def _statistics_section(d: dict) -> str:
    m = d["manifest"]
    s = d["summaries"]["all"]
    fields = [str(f) for f in m.get("fields", [])]
    n_tasks = (len(fields) * len(m.get("z_values", [])) * len(m.get("mag_values", []))
               * int(m.get("n_iterations") or 0))
    n_in, n_rec, n_sel = (int(s[c].sum()) for c in ("n_input", "n_recovered", "n_selected"))
    items = [("fields", len(fields)), ("grid cells (simulated z, m pairs)", len(s)),
             ("tasks (fields × z × m × iterations)", n_tasks),
             ("sources injected", n_in), ("recovered (status 0, 1, 2)", n_rec),
             ("recovered and selected", n_sel),
             ("recovered fraction", n_rec / n_in if n_in else None),
             ("selected fraction", n_sel / n_in if n_in else None),
             ("survey area [arcmin²]", m.get("area_arcmin2_total"))]
    body = kv_table(items, "run-statistics")
    body += ('<dl id="cell-terms">' + "".join(f"<dt>{esc(k)}</dt><dd>{esc(v)}</dd>" for k, v in CELL_TERMS)
             + "</dl>")
    areas = m.get("area_arcmin2") or {}
    scales = m.get("pixel_scale_arcsec") or {}
    rows = []
    for f in fields:
        sf = d["summaries"].get(f)
        lo, hi, med = _depth_range(m, f)
        rows.append((f, areas.get(f), scales.get(f),
                     int(sf["n_input"].sum()) if sf is not None else None,
                     int(sf["n_recovered"].sum()) if sf is not None else None,
                     int(sf["n_selected"].sum()) if sf is not None else None, lo, med, hi))
    body += "<h3>Fields</h3>" + table(
        ["field", "area_arcmin2", "pixel_scale_arcsec", "n_input", "n_recovered", "n_selected",
         "depth_min", "depth_median", "depth_max"], rows, table_id="fields",
        formats={"area_arcmin2": ".4g", "pixel_scale_arcsec": ".4g", "depth_min": ".2f",
                 "depth_median": ".2f", "depth_max": ".2f"},
        headers={"area_arcmin2": "area [arcmin²]", "pixel_scale_arcsec": "pixel [arcsec]",
                 "depth_min": "depth min", "depth_median": "depth median (by area)",
                 "depth_max": "depth max"})
    fs = d["fit_summary"]
    if fs:
        rows = []
        for name, e in fs.get("fits", {}).items():
            steps = ", ".join(f"{p}: {b['n_steps']}×{b['n_walkers']}" for p, b in
                              (e.get("blocks") or {}).items())
            rows.append((name, e.get("model"), e.get("model_kept_because"), e.get("n_sources"),
                         e.get("n_cells"), e.get("wall_time_s"), steps))
        # summary.json's "n_cells" is len(Cells): the likelihood groups (CELL_TERMS)
        body += "<h3>Fit</h3>" + table(["fit", "model", "kept_because", "n_sources",
                                         "n_likelihood_groups", "wall_time_s", "steps × walkers"],
                                        rows, table_id="fit-statistics",
                                        formats={"wall_time_s": ".1f"},
                                        headers={"wall_time_s": "wall time [s]",
                                                 "kept_because": "kept because",
                                                 "n_sources": "sources",
                                                 "n_likelihood_groups": "likelihood groups"})
        if fs.get("wall_time_s") is not None:
            # The command's own clock (every model compared, checks, V_eff, files); a fit's
            # row is its share, without reading the run and writing the outputs.
            body += note(f"Fit wall time: {float(fs['wall_time_s']):.1f} s for the whole "
                          "`glaciar fit` (every model compared, the checks and the outputs).")
        else:
            body += note("Fit wall time: not recorded by the glaciar that wrote this fit (its "
                          "per-fit times count one model's sampler only).")
    return section("statistics", "Run statistics", body)


def _status_section(d: dict) -> str:
    from .plots import plot_status_fractions
    from .counting import STATUS_COLUMNS
    from .tables import summary_stem

    labels = {code: (STATUS_COLUMNS[code], C.STATUS_LABELS[code]) for code in C.STATUS_CODES}
    cols = [STATUS_COLUMNS[c] for c in C.STATUS_CODES]
    rows = []
    for name, s in d["summaries"].items():
        n = int(s["n_input"].sum())
        rows.append([name, n] + [int(s[c].sum()) for c in cols]
                    + [int(s["n_recovered"].sum()), int(s["n_selected"].sum())])
    heads = {STATUS_COLUMNS[c]: f"{c}: {C.STATUS_LABELS[c]}" for c in C.STATUS_CODES}
    body = note("Counts of injected sources by status (GLACiAR's codes: 0, 1, 2 recovered; "
                 "−1 blended with a brighter source and failing the overlap or flux test; "
                 "−2 detected below the S/N threshold; −3 not detected).")
    body += table(["field", "n_input"] + cols + ["n_recovered", "n_selected"], rows,
                   table_id="status-totals", headers=heads)
    body += figure(plot_status_fractions(d["summaries"]["all"], labels, _mag_label(d["manifest"])),
                    "Fraction of injected sources in each status per magnitude", "fig-status")
    sum_cols = (["z", "mag", "n_input"] + cols + ["n_recovered", "n_selected", "completeness",
                                                   "selection_total", "selection"])
    shown = d["summaries"] if len(d["summaries"]) <= _MAX_FIELD_TABLES + 1 else \
        {"all": d["summaries"]["all"]}
    if len(shown) < len(d["summaries"]):
        body += note(f"{len(d['summaries']) - 1} fields: their per-cell tables are in "
                      f"{C.SUMMARY_DIRNAME}/summary_<field>.ecsv")
    for name, s in shown.items():
        src = "summary_all.ecsv" if name == "all" else f"summary_{summary_stem(name)}.ecsv"
        rows = [[r[c] for c in sum_cols] for r in s[sum_cols].to_dict("records")]
        body += (f"<details><summary>Per (z, m) cell: {esc(name)} ({esc(src)})</summary>"
                 + table(sum_cols, rows, table_id=f"summary-{name}",
                          formats={"completeness": ".4f", "selection_total": ".4f",
                                   "selection": ".4f", "z": "g", "mag": "g"})
                 + "</details>")
    return section("status", "Status breakdown", body)


def _not_fitted(d: dict) -> str:
    return note(f"not fitted: no {C.SELECTION_FUNCTION_NAME} in the run directory; run "
                 f"`glaciar fit {d['run_dir']}` and then `glaciar report {d['run_dir']} --html` again",
                 "missing")


def _points_for(d: dict, field: str):
    return d["summaries"].get(field, d["summaries"]["all"])


def _curves_section(d: dict) -> str:
    from .plots import plot_grid_map, plot_quantile_curves

    sf = d["selection_function"]
    if sf is None:
        return section("curves", "Completeness C and selection S", _not_fitted(d))
    m = d["manifest"]
    mlabel = _mag_label(m)
    body = note("Curves at simulated redshifts and magnitudes only. Lines: posterior median; "
                 "bands: 68 % and 95 % credible intervals (the quantile planes of the file's C_GRID "
                 "and SR_GRID: survey averages, weighted by area over fields and depths; "
                 "interpolated linearly between the two grid rows around a simulated value). "
                 "Points: binned fractions of the summary table, (k+1)/(n+2) with Beta(k+1, n−k+1) "
                 "68 % intervals (pooled by injections, so fields of unequal depth or area can pull "
                 "them off the area-weighted curve); a cell with no injected source (C) or no "
                 "recovered one (S) has no point.")
    for fit in sf["fits"]:
        name = fit["field"]
        pts = _points_for(d, name)
        if "C_GRID" not in fit:
            body += note(f"fit {name}: the file holds no grids")
            continue
        g = fit["C_GRID"]
        curves, points = [], []
        # Only simulated redshifts: those of the fit's summary table with injected sources.
        for z in _simulated(pts.loc[pts["n_input"] > 0, "z"], 6):
            curves.append((f"z = {z:g}", _planes_at(g["z"], g["q"], z, 1)))
            points.append(_points(pts[np.isclose(pts["z"], z, atol=1e-6)], "n_recovered", "n_input",
                                  "mag"))
        body += figure(plot_quantile_curves(g["m"], curves, xlabel=mlabel, ylabel="completeness C(m)",
                                             title=f"C(m) at the simulated z — fit {name}",
                                             points=points),
                        f"Completeness C(m, z) with 68 % and 95 % credible bands (fit {name})",
                        f"fig-completeness-{name}")
        if fit["draws_header"].get("SELFIT", True) is False:
            body += note(f"fit {name}: detection only (no selection criteria), so S = 1 "
                          "exactly and P = C; there is no S to show.")
            continue
        g = fit["SR_GRID"]
        curves, points = [], []
        for mv in _simulated(pts.loc[pts["n_input"] > 0, "mag"], 4):
            curves.append((f"m = {mv:g}", _planes_at(g["m"], g["q"], mv, 2)))
            points.append(_points(pts[np.isclose(pts["mag"], mv, atol=1e-6)], "n_selected",
                                  "n_recovered", "z"))
        body += figure(plot_quantile_curves(g["z"], curves, xlabel="redshift z",
                                             ylabel="S(z, m) = P(selected | recovered)",
                                             title=f"S(z) at simulated magnitudes — fit {name}",
                                             points=points),
                        f"Selection given recovery S(z, m) with 68 % and 95 % credible bands (fit {name})",
                        f"fig-selection-{name}")
        g = fit["P_GRID"]
        body += figure(plot_grid_map(g["m"], g["z"], g["q"][0], xlabel=mlabel, ylabel="redshift z",
                                      label="median P = C·S", title=f"P(z, m) = C·S — fit {name}"),
                        f"Median selection probability P = C·S (fit {name})", f"fig-p-{name}")
    return section("curves", "Completeness C and selection S", body)


def _ppc_section(d: dict) -> str:
    from .plots import plot_ppc

    sf = d["selection_function"]
    if sf is None:
        return section("ppc", "Posterior-predictive check", _not_fitted(d))
    fits_summary = (d["fit_summary"] or {}).get("fits", {})
    body = note("Per simulated (z, m, depth bin) cell: the observed counts against the posterior "
                 "predictive distribution (mid-p values); a cell is extreme when either mid-p is "
                 "below 0.01 or above 0.99. The fit is adequate unless more cells are extreme "
                 "than chance allows (99 % quantile of Binomial(PPC cells, 0.04)).")
    rows = []
    for fit in sf["fits"]:
        v = (fits_summary.get(fit["field"]) or {}).get("ppc") or {}
        ppc = fit["PPC"]
        n_ext = int(np.sum(ppc["extreme"])) if ppc is not None else v.get("n_extreme")
        rows.append((fit["field"], len(ppc) if ppc is not None else v.get("n_cells"), n_ext,
                     v.get("max_allowed"), v.get("adequate", fit["draws_header"].get("ADEQUATE"))))
    body += table(["fit", "n_ppc_cells", "n_extreme", "max_allowed", "adequate"], rows,
                   table_id="ppc-verdict",
                   headers={"n_ppc_cells": "PPC cells", "n_extreme": "extreme cells",
                            "max_allowed": "most extreme cells allowed"})
    for fit in sf["fits"]:
        ppc = fit["PPC"]
        if ppc is None or not len(ppc):
            body += note(f"fit {fit['field']}: the file holds no PPC table")
            continue
        body += figure(plot_ppc(ppc), f"Binned fractions against the model per cell (fit {fit['field']})",
                        f"fig-ppc-{fit['field']}")
        ext = ppc[ppc["extreme"].astype(bool)]
        cols = ["z", "mag", "depth_lo", "n", "k_rec", "k_sel", "c_binned", "c_model", "s_binned",
                "s_model", "ppc_p_rec", "ppc_p_sel"]
        if len(ext):
            body += f"<h3>Extreme cells (fit {esc(fit['field'])})</h3>" + table(
                cols, ext[cols].itertuples(index=False), table_id=f"ppc-extreme-{fit['field']}",
                formats={"z": "g", "mag": "g", "depth_lo": ".2f"})
        else:
            body += note(f"fit {fit['field']}: no extreme cells")
    return section("ppc", "Posterior-predictive check", body)


def _depth_section(d: dict) -> str:
    from .plots import plot_area_by_depth, plot_depth_completeness

    m = d["manifest"]
    body = ""
    da = {f: (v["bin_edges_mag"], v["area_arcmin2"]) for f, v in (m.get("depth_area") or {}).items()
          if len(v.get("area_arcmin2", [])) and len(v["bin_edges_mag"]) == len(v["area_arcmin2"]) + 1}
    if da:
        body += figure(plot_area_by_depth(da), "Footprint area per local-depth bin (manifest depth_area)",
                        "fig-area-by-depth")
    else:
        body += note("the manifest holds no area-by-depth distribution")
    sf = d["selection_function"]
    if sf is None:
        return section("depth", "Depth map of completeness", body + _not_fitted(d))
    depth_aware = bool(sf["primary"].get("DEPTHAW", False))
    body = note("Completeness against magnitude and the local depth under each source "
                 "(5σ limit in a 1-FWHM aperture), from the file's PPC table: counts summed over "
                 "redshift per (m, 0.25 mag depth bin) cell; the model map is the posterior median "
                 "of the cell means, averaged over redshift with the cells' source counts as "
                 "weights. " + ("The fit is depth-aware: C(m, z | d) = C(m − (d − d_ref), z)."
                                if depth_aware else "The fit is not depth-aware.")) + body
    for fit in sf["fits"]:
        ppc = fit["PPC"]
        if ppc is None or not len(ppc) or not np.isfinite(ppc["depth_lo"].to_numpy(float)).any():
            body += note(f"fit {fit['field']}: no local depths in the PPC table")
            continue
        p = ppc[np.isfinite(ppc["depth_lo"].to_numpy(float))].copy()
        p["c_model_n"] = p["c_model"] * p["n"]
        g = p.groupby(["depth_lo", "mag"], sort=True)[["n", "k_rec", "c_model_n"]].sum()
        dl = np.unique(p["depth_lo"].to_numpy(float))
        step = float(np.min(np.diff(dl))) if dl.size > 1 else 0.25
        # every depth bin from the shallowest to the deepest (empty ones blank)
        dl = dl[0] + step * np.arange(int(round((dl[-1] - dl[0]) / step)) + 1)
        mags = np.unique(p["mag"].to_numpy(float))
        obs = np.full((dl.size, mags.size), np.nan)
        mod = np.full_like(obs, np.nan)
        idl = np.rint((g.index.get_level_values(0).to_numpy(float) - dl[0]) / step).astype(int)
        im = np.searchsorted(mags, g.index.get_level_values(1).to_numpy(float))
        n = g["n"].to_numpy(float)
        obs[idl, im] = g["k_rec"].to_numpy(float) / n
        mod[idl, im] = g["c_model_n"].to_numpy(float) / n
        body += figure(plot_depth_completeness(mags, dl, step, obs, mod, mag_label=_mag_label(m)),
                        f"Completeness by magnitude and local depth, all z (fit {fit['field']})",
                        f"fig-depth-{fit['field']}")
    return section("depth", "Depth map of completeness", body)


def _round_value(column: str, value):
    """One cell of the rounds table: a round's cells and task counts summarised."""
    if column == "cells" and isinstance(value, list) and value and all(
            isinstance(c, dict) and {"z", "mag"} <= set(c) for c in value):
        z = [float(c["z"]) for c in value]
        m = [float(c["mag"]) for c in value]
        return f"{len(value)} cells, z {min(z):g}–{max(z):g}, m {min(m):g}–{max(m):g}"
    if column == "simulated" and isinstance(value, dict):
        return f"{value.get('n_tasks_run', '?')} tasks, {value.get('cpu_seconds', '?')} s CPU"
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    return value


def _adaptive_section(d: dict) -> str:
    rounds = d["adaptive_rounds"]
    if not rounds:
        body = '<p id="adaptive-none">none — this run has no adaptive rounds.</p>'
    else:
        cols = list(dict.fromkeys(k for r in rounds for k in r))
        rows = [[_round_value(c, r.get(c)) for c in cols] for r in rounds]
        body = table(cols, rows, table_id="adaptive-rounds")
    return section("adaptive", "Adaptive rounds", body)


def _sf_section(d: dict) -> str:
    sf = d["selection_function"]
    if sf is None:
        return section("selection-function", "Selection-function summary", _not_fitted(d))
    from .plots import plot_effective_volume

    m = d["manifest"]
    fs = d["fit_summary"] or {}
    mlabel = "M_UV" if m.get("magnitude_type") == "absolute" else "m"
    body = note(f"{sf['path']}: read it with glaciar.SelectionFunction.read(path), or without "
                 "glaciar as docs/selection-function-file.md describes.")
    # Is the file current?  (It describes the rows that were fitted.)
    n_now = int(d["summaries"]["all"]["n_input"].sum())
    if sf["primary"].get("CONFHASH") and m.get("config_hash") and \
            sf["primary"]["CONFHASH"] != m["config_hash"]:
        body += note("the file was fitted to another configuration than the run's: fit again",
                      "warning")
    fsum = fs.get("fits", {})
    for fit in sf["fits"]:
        name = fit["field"]
        e = fsum.get(name) or {}
        dh = fit["draws_header"]
        body += f"<h3>Fit {esc(name)}</h3>"
        if name == "all" and dh.get("NSOURCES") is not None and int(dh["NSOURCES"]) != n_now:
            body += note(f"the fit used {int(dh['NSOURCES'])} sources, the run's summary tables now "
                          f"hold {n_now}: run `glaciar fit` again", "warning")
        facts = [("model", dh.get("MODEL")), ("posterior draws", fit["n_draws"]),
                 ("sources", dh.get("NSOURCES")), ("likelihood groups", dh.get("NCELLS")),
                 ("converged (every chain ≥ 50 τ)", dh.get("CONVERGE")),
                 ("adequate (PPC)", dh.get("ADEQUATE")), ("max τ", dh.get("TAUMAX")),
                 ("min ESS", dh.get("ESSMIN")), ("max split R-hat", dh.get("RHATMAX")),
                 ("depth reference d_ref", dh.get("DEPTHREF")),
                 ("simulated z", f"{dh.get('ZMIN')} – {dh.get('ZMAX')}"),
                 ("simulated m", f"{dh.get('MMIN')} – {dh.get('MMAX')}")]
        body += kv_table(facts, f"sf-fit-{name}")
        if e.get("m50"):
            body += f"<h4>{esc(mlabel)} at C = 0.5</h4>" + table(
                ["z", "m50", "lower_68", "upper_68"],
                [(r["z"], r["m50"], r["ci68"][0], r["ci68"][1]) for r in e["m50"]],
                table_id=f"m50-{name}", formats={"z": "g", "m50": ".3f", "lower_68": ".3f",
                                                 "upper_68": ".3f"})
        if e.get("c_max"):
            cm = e["c_max"]
            body += kv_table([(f"C_max(z = {cm['z']:g}) median", cm["median"]),
                               ("C_max 68 % lower", cm["ci68"][0]), ("C_max 68 % upper", cm["ci68"][1])],
                              f"cmax-{name}")
        if e.get("model_comparison"):
            body += "<h4>PSIS-LOO comparison of completeness steps</h4>" + table(
                ["model", "delta_elpd", "se_delta"],
                [(r["model"], r["delta_elpd"], r["se_delta"]) for r in e["model_comparison"]],
                table_id=f"loo-{name}", formats={"delta_elpd": "+.2f", "se_delta": ".2f"})
        ve = e.get("effective_volume")
        if ve:
            q = ve["quoted"]
            what = (f"{ve['area_arcmin2']:.4g} arcmin², z {ve['z_range'][0]:g}–{ve['z_range'][1]:g}, "
                    f"{ve.get('cosmology')}")
            body += f"<h4>Effective volume ({esc(what)})</h4>"
            body += table(["mag", "median_mpc3", "lower_mpc3", "upper_mpc3"],
                           zip(q["mag"], q["median_mpc3"], q["lower_mpc3"], q["upper_mpc3"]),
                           table_id=f"veff-{name}", formats={"mag": ".2f"},
                           headers={"median_mpc3": "V_eff median [Mpc³]", "lower_mpc3": "68 % lower",
                                    "upper_mpc3": "68 % upper"})
            body += figure(plot_effective_volume(ve["mag"], ve["median_mpc3"], ve["lower_mpc3"],
                                                  ve["upper_mpc3"], mag_label=_mag_label(m),
                                                  title=f"V_eff(m), fit {name}"),
                            f"Effective volume V_eff(m) with its 68 % interval (fit {name})",
                            f"fig-veff-{name}")
        elif e.get("effective_volume_note"):
            body += note(f"V_eff: not computed ({e['effective_volume_note']})")
        p = fit["params"]
        cols = [c for c in ("name", "median", "q16", "q84", "prior_mean", "prior_sd", "tau", "ess", "rhat")
                if c in p.columns]
        body += (f"<details><summary>Parameters (PARAMS, fit {esc(name)})</summary>"
                 + table(cols, p[cols].itertuples(index=False), table_id=f"params-{name}") + "</details>")
    # The raw keywords, for whoever reads the file by hand: the summary above says it in words.
    body += ("<details><summary>The file's primary header (FITS keywords)</summary>"
             + kv_table(sorted(sf["primary"].items()), "sf-primary") + "</details>")
    return section("selection-function", "Selection-function summary", body)


_SECTIONS = (("summary", "Summary", _summary_section),
             ("configuration", "Configuration", _config_section),
             ("statistics", "Run statistics", _statistics_section),
             ("status", "Status breakdown", _status_section),
             ("curves", "C and S", _curves_section),
             ("ppc", "PPC", _ppc_section),
             ("depth", "Depth map", _depth_section),
             ("adaptive", "Adaptive rounds", _adaptive_section),
             ("selection-function", "Selection function", _sf_section))


def render_html(data: dict) -> str:
    """The page for :func:`load_report_data`'s output (a complete HTML document)."""
    from .version import __version__

    title = f"glaciar report — {Path(data['run_dir']).name}"
    nav = "".join(f'<a href="#{sid}">{esc(label)}</a>' for sid, label, _ in _SECTIONS)
    body = "".join(fn(data) for _, _, fn in _SECTIONS)
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            '<link rel="icon" href="data:,">'
            f"<title>{esc(title)}</title><style>{STYLE}</style></head><body>"
            f"<header><h1>{esc(title)}</h1><p class=\"note\">{esc(data['run_dir'])} · written by "
            f"glaciar {esc(__version__)}</p><nav>{nav}</nav></header>"
            f"<main>{body}</main></body></html>\n")


def write_html_report(run_dir, path=None) -> Path:
    """Write the run's HTML report (default ``RUN/report.html``, atomically); return its path."""
    from .rundir import atomic_write_text

    from .pipeline.fitdir import hold_run

    run_dir = Path(run_dir)
    # Under the run's lock: never a half-written run, nor a fit/ from another fit than the file.
    with hold_run(run_dir, "report"):
        page = render_html(load_report_data(run_dir))
        out = Path(path) if path is not None else run_dir / REPORT_NAME
        atomic_write_text(out, page)
    return out


def write_summary_files(run_dir, *, regions: bool = False) -> list[Path]:
    """The summary tables (ECSV), maps (PNG) and optionally DS9 regions of a run
    (``glaciar report``); returns the paths written.  Store warnings are issued as
    :class:`glaciar.store.StoreWarning` (once each).

    Raises
    ------
    glaciar.rundir.RunLockedError
        ``glaciar simulate`` (or a fit) is writing the run.
    """
    from .pipeline.fitdir import hold_run

    run_dir = Path(run_dir)
    # Under the run's lock: a run that `glaciar simulate` is writing is refused.
    with hold_run(run_dir, "report"):
        return _write_summary_files(run_dir, regions)


def _write_summary_files(run_dir: Path, regions: bool) -> list[Path]:
    import warnings

    from .plots import plot_summary_maps
    from .store import StoreWarning, read_current_counts, read_current_results, store_columns
    from .rundir import read_manifest
    from .tables import summary_table, write_regions, write_summaries

    # What fit uses too: the tasks the run's configuration lists now; their stored counts
    # (footers only), or the rows of a store written before counts.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", StoreWarning)
        got = read_current_counts(run_dir)
        have = store_columns(run_dir)
        rows = got[0] if got is not None else read_current_results(run_dir, columns=[
            c for c in (C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_STATUS, C.COL_RECOVERED,
                        C.COL_SELECTED) if c in have])
    seen = set()
    for w in caught:
        if str(w.message) not in seen:
            seen.add(str(w.message))
            warnings.warn(w.message, stacklevel=2)
    manifest = read_manifest(run_dir) or {}
    out_dir = run_dir / C.SUMMARY_DIRNAME
    meta = {k: manifest[k] for k in ("config_hash", "seed", "detection_band", "selection") if k in manifest}
    box = None
    if manifest.get("box"):
        from .box import box_bin_edges, box_points

        b = manifest["box"]
        ze, me = box_bin_edges(b["z"], b["mag"], b["n_points"])
        box = {"points": box_points(b["z"], b["mag"], b["n_points"], manifest["seed"]),
               "z_edges": ze, "mag_edges": me}
    paths = write_summaries(rows, out_dir, meta, box=box)
    mag_label = "M_UV" if manifest.get("magnitude_type") == "absolute" else \
        f"m ({manifest.get('detection_band', 'detection band')}, AB)"
    for field, sub in rows.groupby(C.COL_FIELD):
        paths += plot_summary_maps(summary_table(sub), out_dir, str(field), mag_label,
                                   selection=not _detection_only(manifest))
    if regions:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", StoreWarning)     # printed above
            src = read_current_results(run_dir, columns=[
                c for c in (C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE,
                            C.COL_X, C.COL_Y, C.COL_STATUS) if c in have])
        paths += write_regions(src, out_dir / "regions")
    return paths
