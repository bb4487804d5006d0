"""Summaries of a run: GLACiAR's Table 1 per field, binned C, S and C·S, DS9 regions.

Columns of the summary (the paper's Table 1, with headers that match the data):

====================  =====================================================
``z``                 input redshift of the task grid
``mag``               nominal magnitude of the task grid (apparent in the
                      detection band, or M_UV, as configured)
``n_input``           artificial sources injected (all iterations)
``n_status_0``        detected and isolated
``n_status_1``        blended with a fainter original source (recovered)
``n_status_2``        blended with a brighter source, passing the overlap and
                      flux tests (recovered)
``n_status_m1``       blended with a brighter source, failing them
``n_status_m2``       detected below the S/N threshold
``n_status_m3``       not detected
``n_recovered``       statuses 0, 1 and 2
``n_selected``        recovered and passing the selection criteria
``completeness``      C = n_recovered / n_input
``selection_total``   C·S = n_selected / n_input
``selection``         S = n_selected / n_recovered (NaN where nothing was recovered)
====================  =====================================================
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd
from astropy.table import Table

from . import constants as C
from .store import atomic_write_bytes, atomic_write_text, field_file_prefix

__all__ = ["summary_table", "write_summaries", "region_file", "STATUS_COLUMNS"]

#: summary column of each status code
STATUS_COLUMNS = {code: f"n_status_{code}" if code >= 0 else f"n_status_m{-code}"
                  for code in C.STATUS_CODES}


def summary_table(rows: pd.DataFrame) -> pd.DataFrame:
    """Counts per (z, mag) cell from per-source rows (one field, or several pooled).

    Parameters
    ----------
    rows : pandas.DataFrame
        Per-source rows with at least ``z``, ``mag``, ``status``, ``recovered``,
        ``selected``; or stored counts (:func:`glaciar.store.task_counts`
        columns, recognised by their ``n`` column), summed per cell.

    Returns
    -------
    pandas.DataFrame
        One row per (z, mag) cell, columns as in the module docstring.
    """
    from .store import COUNT_K_REC, COUNT_K_SEL, COUNT_N
    if COUNT_N in rows.columns:
        cols = [COUNT_N, *STATUS_COLUMNS.values(), COUNT_K_REC, COUNT_K_SEL]
        out = rows.groupby([C.COL_Z, C.COL_MAG], sort=True)[cols].sum()
        out = out.rename(columns={COUNT_N: "n_input", COUNT_K_REC: "n_recovered",
                                  COUNT_K_SEL: "n_selected"})
        return _fractions(out)
    g = rows.groupby([C.COL_Z, C.COL_MAG], sort=True)
    out = g.size().rename("n_input").to_frame()
    counts = rows.groupby([C.COL_Z, C.COL_MAG, C.COL_STATUS]).size().unstack(fill_value=0)
    for code, col in STATUS_COLUMNS.items():
        out[col] = counts[code] if code in counts.columns else 0
    out["n_recovered"] = g[C.COL_RECOVERED].sum().astype(np.int64)
    out["n_selected"] = g[C.COL_SELECTED].sum().astype(np.int64)
    return _fractions(out)


def _fractions(out: pd.DataFrame) -> pd.DataFrame:
    """The fraction columns beside the counts of a (z, mag)-indexed summary; the index reset."""
    out["completeness"] = out["n_recovered"] / out["n_input"]
    out["selection_total"] = out["n_selected"] / out["n_input"]
    with np.errstate(invalid="ignore", divide="ignore"):
        out["selection"] = np.where(out["n_recovered"] > 0,
                                    out["n_selected"] / out["n_recovered"].where(out["n_recovered"] > 0, 1),
                                    np.nan)
    out = out.reset_index()
    for col in list(STATUS_COLUMNS.values()) + ["n_input", "n_recovered", "n_selected"]:
        out[col] = out[col].astype(np.int64)
    return out


_DESCRIPTIONS = {
    "z": "input redshift", "mag": "nominal magnitude of the grid cell",
    "n_input": "artificial sources injected",
    "n_status_0": "status 0: detected, isolated", "n_status_1": "status 1: blended with a fainter source",
    "n_status_2": "status 2: blended with a brighter source, passing overlap and flux tests",
    "n_status_m1": "status -1: blended with a brighter source, failing them",
    "n_status_m2": "status -2: detected below the S/N threshold", "n_status_m3": "status -3: not detected",
    "n_recovered": "recovered (status 0, 1, 2)", "n_selected": "recovered and selected",
    "completeness": "C = n_recovered / n_input", "selection_total": "C*S = n_selected / n_input",
    "selection": "S = n_selected / n_recovered",
}


def _ecsv_bytes(df: pd.DataFrame, meta: dict) -> bytes:
    t = Table.from_pandas(df)
    for name, desc in _DESCRIPTIONS.items():
        if name in t.colnames:
            t[name].description = desc
    t.meta.update(meta)
    buf = io.StringIO()
    t.write(buf, format="ascii.ecsv")
    return buf.getvalue().encode()


def write_summaries(rows: pd.DataFrame, out_dir, meta: dict | None = None) -> list[Path]:
    """Write one ECSV summary per field, plus ``summary_all.ecsv`` pooled over fields."""
    out_dir = Path(out_dir)
    paths = []
    for field, sub in rows.groupby(C.COL_FIELD, sort=True):
        p = out_dir / f"summary_{field}.ecsv"
        atomic_write_bytes(p, _ecsv_bytes(summary_table(sub), {**(meta or {}), "field": str(field)}))
        paths.append(p)
    p = out_dir / "summary_all.ecsv"
    atomic_write_bytes(p, _ecsv_bytes(summary_table(rows), {**(meta or {}), "field": "all"}))
    paths.append(p)
    return paths


#: DS9 colours by status
_REGION_COLOURS = {C.STATUS_ISOLATED: "green", C.STATUS_BLENDED_FAINTER: "cyan",
                   C.STATUS_BLENDED_PASSED: "blue", C.STATUS_BLENDED_FAILED: "magenta",
                   C.STATUS_LOW_SN: "yellow", C.STATUS_NOT_DETECTED: "red"}


def region_file(rows: pd.DataFrame, radius_pix: float = 5.0) -> str:
    """DS9 region text (image coordinates, 1-based) of injected sources coloured by status."""
    lines = ["# Region file format: DS9", "# glaciar injected sources; colour = status", "image"]
    for x, y, st, zz, m in zip(rows[C.COL_X], rows[C.COL_Y], rows[C.COL_STATUS], rows[C.COL_Z], rows[C.COL_MAG]):
        lines.append(f"circle({x + 1:.3f},{y + 1:.3f},{radius_pix:.1f}) # color={_REGION_COLOURS[int(st)]} "
                     f"text={{{int(st)}}} tag={{z={zz:g} m={m:g}}}")
    return "\n".join(lines) + "\n"


def write_regions(rows: pd.DataFrame, out_dir) -> list[Path]:
    """One DS9 region file per field, written atomically (sources of every task of the field).

    Sources are in task order (z, mag, iteration, then source order), each
    tagged with its task's z and magnitude.  Named by the field's file prefix
    (:func:`glaciar.store.field_file_prefix`: readable name + hash), so that
    two fields never share a region file (``a b`` / ``a_b``).
    """
    out_dir = Path(out_dir)
    paths = []
    order = [c for c in (C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE) if c in rows.columns]
    for f, sub in rows.groupby(C.COL_FIELD, sort=True):
        prefix = field_file_prefix(str(f))
        p = out_dir / f"regions_{prefix[len('task_'):-1]}.reg"
        atomic_write_text(p, region_file(sub.sort_values(order, kind="stable")))
        paths.append(p)
    return paths
