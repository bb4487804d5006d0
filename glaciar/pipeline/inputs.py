"""What the fit reads from a run directory: the flag columns and the manifest's areas."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .. import constants as C

__all__ = ["read_columns", "manifest_areas", "depth_area"]


def read_columns(run_dir, want):
    """The wanted columns that the store has (column projection), current rows only.

    The rows are :func:`glaciar.store.read_current_results`'; a column the
    task files lack is left out rather than an error.
    """
    import pyarrow.parquet as pq

    from ..store import read_current_results

    files = sorted((Path(run_dir) / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    have = set(pq.read_schema(files[0]).names) if files else set(want)
    return read_current_results(run_dir, columns=[c for c in want if c in have])


def manifest_areas(manifest: dict, run_dir) -> dict:
    """{field: area [arcmin^2]} from the manifest (per-field mapping), or {}.

    Raises
    ------
    ValueError
        ``area_arcmin2`` is a mapping whose values are not all finite numbers > 0.
    """
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


def depth_area(manifest: dict, fields) -> dict:
    """{field: (bin edges [AB mag], areas [arcmin^2])} from the manifest's ``depth_area``."""
    da = manifest.get("depth_area") or {}
    out = {}
    for f in fields:
        if f in da:
            e = np.asarray(da[f]["bin_edges_mag"], float)
            a = np.asarray(da[f]["area_arcmin2"], float)
            if len(e) == len(a) + 1 and len(a):
                out[f] = (e, a)
    return out
