"""A task's counts: what the store keeps in each task file's footer instead of its rows.

Binomial counts per group of identical covariates (:func:`task_counts`), histograms of
the measured magnitude on the global m_obs lattice (:func:`task_histogram`,
:func:`mobs_lattice_index`; the transfer matrices are rebuilt from them by
:func:`glaciar.tables.transfer_from_histograms`), their column names and the names of
the per-status counts.  A leaf (numpy, pandas and :mod:`glaciar.constants` only), so
that ``store`` (which writes and merges the counts) and ``tables`` (which reads them and
writes files through ``store``) do not import each other.  The ``*_arrays`` functions
take a DataFrame or a mapping of column arrays and import no pandas on a task's few rows
(a worker's tasks write their footers without it; it is imported where a DataFrame is
returned, and to group many rows).
"""
from __future__ import annotations

import numpy as np

from . import constants as C
from .constants import (COL_DEPTH, COL_FIELD, COL_ITERATION, COL_MAG, COL_MAG_INPUT, COL_RECOVERED,
                        COL_SELECTED, COL_STATUS, COL_Z, DEPTH_BIN_MAG)

__all__ = ["STATUS_COLUMNS", "TRANSFER_MOBS_STEP", "MOBS_BIN_FAINT", "MOBS_BIN_BRIGHT",
           "mobs_lattice_edge", "mobs_lattice_index", "COUNTS_MAG_RESOLUTION", "COUNT_COLUMNS",
           "HIST_COLUMNS", "task_counts", "task_count_arrays", "task_histogram",
           "task_histogram_arrays", "group_sums", "group_sum_arrays", "hist_sums", "hist_sum_arrays",
           "has_hist_columns"]

#: Magnitude key resolution of the counts [mag]: the fit's default grouping resolution, so the
#: fit's (z, magnitude) cells are unions of count groups (identical partition) at that default.
COUNTS_MAG_RESOLUTION = 0.01
#: Counts columns (beside the identity columns field, z, mag, iteration).
COUNT_MAG_KEY = "mag_key"          #: round(covariate / COUNTS_MAG_RESOLUTION), float (NaN if non-finite)
COUNT_DEPTH_KEY = "depth_key"      #: floor(depth_local / DEPTH_BIN_MAG), float (NaN if unknown)
COUNT_N = "n"
COUNT_K_REC = "k_recovered"
COUNT_K_SEL = "k_selected"
COUNT_SUM_MAG = "sum_mag"          #: sum of the magnitude covariate over the group [mag]
COUNT_SUM_DEPTH = "sum_depth"      #: sum of depth_local over the group [AB mag]
COUNT_MAG_MIN, COUNT_MAG_MAX = "mag_min", "mag_max"
COUNT_DEPTH_MIN, COUNT_DEPTH_MAX = "depth_min", "depth_max"
#: Histogram columns (beside the identity columns and COUNT_N, COUNT_K_REC, COUNT_K_SEL).
HIST_MIN_KEY = "m_in_key"          #: round(mag_input / COUNTS_MAG_RESOLUTION), float (NaN if non-finite)
HIST_MOBS_BIN = "mobs_bin"         #: m_obs lattice index (mobs_lattice_index), int32
HIST_COLUMNS = (HIST_MIN_KEY, HIST_MOBS_BIN, COUNT_N, COUNT_K_REC, COUNT_K_SEL)

#: summary column of each status code
STATUS_COLUMNS = {code: f"n_status_{code}" if code >= 0 else f"n_status_m{-code}"
                  for code in C.STATUS_CODES}

#: Width of a bin of the m_obs lattice [mag] (anchored at 0 mag).
TRANSFER_MOBS_STEP = C.TRANSFER_MOBS_STEP
#: Overflow bins of the m_obs lattice (int32 extremes): NaN or +inf measured magnitude (flux
#: <= 0) and sources not recovered in the faint one, -inf in the bright one.
MOBS_BIN_FAINT = np.iinfo(np.int32).max
MOBS_BIN_BRIGHT = np.iinfo(np.int32).min


def mobs_lattice_edge(b) -> np.ndarray:
    """Lower edge [mag] of lattice bin ``b`` of the measured magnitude: ``b * TRANSFER_MOBS_STEP``
    rounded to 1e-6 mag, as :func:`glaciar.tables.transfer_matrix` rounds its default edges."""
    return np.round(np.asarray(b, float) * TRANSFER_MOBS_STEP, 6)


def mobs_lattice_index(m_obs) -> np.ndarray:
    """Index ``b`` of the lattice bin [edge(b), edge(b + 1)) holding each measured magnitude.

    The global lattice of ``TRANSFER_MOBS_STEP`` anchored at 0 mag (:func:`mobs_lattice_edge`);
    NaN and +inf give ``MOBS_BIN_FAINT``, -inf ``MOBS_BIN_BRIGHT`` (int32).
    """
    m = np.asarray(m_obs, float)
    fin = np.isfinite(m)
    lim = float(MOBS_BIN_FAINT - 2)
    b = np.floor(np.clip(np.where(fin, m, 0.0) / TRANSFER_MOBS_STEP, -lim, lim))
    # floor(m / step) can miss by one against the rounded edges: correct both ways.
    b = np.where(m < mobs_lattice_edge(b), b - 1, b)
    b = np.where(m >= mobs_lattice_edge(b + 1), b + 1, b)
    out = np.where(fin, b, np.where(m == -np.inf, MOBS_BIN_BRIGHT, MOBS_BIN_FAINT))
    return out.astype(np.int32)


# --------------------------------------------------------------------------
# Counts and histograms of a task
# --------------------------------------------------------------------------
def task_counts(rows, mag_column: str):
    """Binomial counts of per-source rows per group of identical covariates.

    Groups are (field, z, mag, iteration, magnitude key, depth key): the
    identity columns of the task, ``round(rows[mag_column] /
    COUNTS_MAG_RESOLUTION)`` and ``floor(depth_local / DEPTH_BIN_MAG)`` (NaN
    keys, e.g. unknown depth, form their own group).

    Parameters
    ----------
    rows : pandas.DataFrame
        Per-source rows (one or several tasks) with ``recovered``, ``selected``,
        ``status``, ``mag_column`` and the identity columns that exist.
    mag_column : str
        The fit's magnitude covariate (``mag_input`` [AB mag] or ``M_uv``).

    Returns
    -------
    pandas.DataFrame
        One row per group: the identity columns present, ``mag_key``,
        ``depth_key``, ``n``, ``k_recovered``, ``k_selected``, one
        ``n_status_*`` column per status code, ``sum_mag``, ``mag_min``,
        ``mag_max`` [mag], ``sum_depth``, ``depth_min``, ``depth_max`` [AB mag].
    """
    import pandas as pd

    return pd.DataFrame(task_count_arrays(rows, mag_column))


def task_count_arrays(rows, mag_column: str) -> dict:
    """:func:`task_counts` as a dict of column arrays (in its column order), without the
    DataFrame: what a task file's footer stores (:func:`glaciar.taskfile.ipc_bytes`).
    ``rows``: a DataFrame or a mapping of column arrays (:func:`glaciar.engine.task.task_columns`)."""
    return group_sum_arrays(*_count_columns(rows, mag_column))


def _has(rows, column: str) -> bool:
    """Whether a DataFrame or a mapping of column arrays has ``column``."""
    return column in (rows.columns if hasattr(rows, "columns") else rows)


def _values(rows, column: str, dtype=None) -> np.ndarray:
    """A column of a DataFrame (``to_numpy``, as before) or of a mapping, as a numpy array."""
    v = rows[column]
    return v.to_numpy(dtype) if hasattr(v, "to_numpy") else np.asarray(v, dtype)


def _count_columns(rows, mag_column: str) -> tuple[dict, list]:
    """The grouped columns of :func:`task_counts` (a dict of arrays) and its keys."""

    ids = [c for c in (COL_FIELD, COL_Z, COL_MAG, COL_ITERATION) if _has(rows, c)]
    m = _values(rows, mag_column, float)
    n = m.size
    dep = _values(rows, COL_DEPTH, float) if _has(rows, COL_DEPTH) else np.full(n, np.nan)
    g = {c: _values(rows, c) for c in ids}     # a dict: column-wise DataFrame building is slow
    g[COUNT_MAG_KEY] = np.where(np.isfinite(m), np.round(m / COUNTS_MAG_RESOLUTION), np.nan)
    g[COUNT_DEPTH_KEY] = np.where(np.isfinite(dep), np.floor(dep / DEPTH_BIN_MAG), np.nan)
    g[COUNT_N] = np.ones(n, np.int64)
    g[COUNT_K_REC] = _values(rows, COL_RECOVERED).astype(np.int64)
    g[COUNT_K_SEL] = _values(rows, COL_SELECTED).astype(np.int64)
    st = _values(rows, COL_STATUS) if _has(rows, COL_STATUS) else None
    for code, col in STATUS_COLUMNS.items():
        g[col] = (st == code).astype(np.int64) if st is not None else np.zeros(n, np.int64)
    g[COUNT_SUM_MAG] = m
    g[COUNT_MAG_MIN] = m
    g[COUNT_MAG_MAX] = m
    g[COUNT_SUM_DEPTH] = dep
    g[COUNT_DEPTH_MIN] = dep
    g[COUNT_DEPTH_MAX] = dep
    keys = ids + [COUNT_MAG_KEY, COUNT_DEPTH_KEY]
    return g, keys


def _groups(g, keys: list):
    """Group of each row by ``keys`` (sorted as pandas' groupby(sort=True, dropna=False):
    lexicographic, NaN last) and one row of each group.

    Hash-based (``pandas.factorize``) codes per key, combined into one integer, so a
    task's few rows skip pandas' groupby set-up (~10 ms) and millions of merged counts
    never sort strings; a task's few numeric rows are coded by ``numpy.unique`` (the same
    codes, without importing pandas: :func:`_factorize`)."""
    n = len(np.asarray(g[keys[0]]))        # callers always group by at least one key
    combined = np.zeros(n, dtype=np.int64)
    span = 1
    for k in keys:
        v = np.asarray(g[k])
        if n and _constant(v):
            continue        # one value (not NaN): code 0 for every row, nothing to combine
        codes, card = _factorize(v)
        card = max(card, 1)
        if span * card >= 2 ** 62:       # would overflow: re-code what is combined so far
            combined = _factorize(combined)[0]
            span = int(combined.max(initial=0)) + 1
        combined = combined * card + codes
        span *= card
    inverse = _factorize(combined)[0]
    first = np.empty(int(inverse.max(initial=-1)) + 1, dtype=np.int64)
    first[inverse[::-1]] = np.arange(n - 1, -1, -1)      # the first row of each group
    return inverse, first


#: Rows up to which :func:`_factorize` codes numbers with numpy (sorting) rather than pandas
#: (hashing, faster on many rows): a task's rows, not a merge's.
_NUMPY_FACTORIZE_MAX = 1 << 14


def _factorize(v: np.ndarray) -> tuple[np.ndarray, int]:
    """``pandas.factorize(v, sort=True, use_na_sentinel=False)``: int64 codes in sorted order of
    the distinct values (NaN one value, last), and the number of distinct values."""
    if v.dtype.kind in "biuf" and v.size <= _NUMPY_FACTORIZE_MAX:
        uniq, codes = np.unique(v, return_inverse=True)     # NaNs equal, sorted last
        return codes.reshape(-1).astype(np.int64, copy=False), len(uniq)
    import pandas as pd

    codes, uniq = pd.factorize(v, sort=True, use_na_sentinel=False)
    return codes.astype(np.int64, copy=False), len(uniq)


def _constant(v: np.ndarray) -> bool:
    """Every element of ``v`` equals the first (a NaN first never does): a task's identity
    columns (field, z, mag, iteration) are, and factorizing each costs ~50 us."""
    first = v[0]
    try:
        return bool(np.all(v == first))
    except (TypeError, ValueError):         # uncomparable objects: let pandas group them
        return False


def group_sums(g, keys: list):
    """Counts summed per ``keys``: ints and sums added, extremes kept; an all-NaN sum stays NaN.

    ``g``: a DataFrame or a dict of column arrays."""
    import pandas as pd

    return pd.DataFrame(group_sum_arrays(g, keys))


def group_sum_arrays(g, keys: list) -> dict:
    """:func:`group_sums` as a dict of column arrays (its column order)."""
    grp, first = _groups(g, keys)
    ng = first.size
    out = {k: np.asarray(g[k])[first] for k in keys}
    sums = [c for c in g if c not in keys and (c == COUNT_N or c.startswith(("k_", "n_status_", "sum_")))]
    for c in sums:
        v = np.asarray(g[c])
        if v.dtype.kind in "iub":
            out[c] = np.bincount(grp, weights=v, minlength=ng).astype(np.int64)
        else:       # NaN skipped, as pandas' sum
            out[c] = np.bincount(grp, weights=np.nan_to_num(v.astype(float), nan=0.0), minlength=ng)
    for c, lo, hi in ((COUNT_SUM_MAG, COUNT_MAG_MIN, COUNT_MAG_MAX),
                      (COUNT_SUM_DEPTH, COUNT_DEPTH_MIN, COUNT_DEPTH_MAX)):
        vlo, vhi = np.asarray(g[lo], dtype=float), np.asarray(g[hi], dtype=float)
        mn, mx = np.full(ng, np.nan), np.full(ng, np.nan)
        np.fmin.at(mn, grp, vlo)          # fmin/fmax skip NaN; an all-NaN group stays NaN
        np.fmax.at(mx, grp, vhi)
        out[lo], out[hi] = mn, mx
        # Unknown depth (NaN) in every source of a group: the sum stays NaN, not 0.
        out[c] = np.where(np.isnan(mn), np.nan, out[c])
    return out


def has_hist_columns(columns, obs_column: str) -> bool:
    return all(c in columns for c in (obs_column, COL_MAG_INPUT, COL_RECOVERED, COL_SELECTED))


def task_histogram(rows, obs_column: str):
    """Histograms of the measured magnitude of recovered and selected sources.

    What the photometric transfer matrices need (:func:`glaciar.tables.
    transfer_from_histograms`), without the rows: per group of identity
    columns (field, z, mag, iteration), input-magnitude key
    ``round(mag_input / COUNTS_MAG_RESOLUTION)`` and measured-magnitude bin
    on the global lattice of ``TRANSFER_MOBS_STEP`` anchored at 0
    (:func:`glaciar.counting.mobs_lattice_index`; integer indices, so any edges
    that are unions of lattice bins are rebuilt exactly), the number of
    sources and of recovered and selected ones.  Sources not recovered, and
    recovered ones whose measured magnitude is NaN or +inf (flux <= 0), are
    in the faint overflow bin ``MOBS_BIN_FAINT``; -inf in ``MOBS_BIN_BRIGHT``.
    Only non-empty groups are stored (sparse).

    Parameters
    ----------
    rows : pandas.DataFrame
        Per-source rows with ``mag_input`` [AB mag], ``obs_column`` [AB mag],
        ``recovered``, ``selected`` and the identity columns that exist.
    obs_column : str
        The measured detection-band magnitude column, e.g. ``mag_f160w``.

    Returns
    -------
    pandas.DataFrame
        The identity columns present, ``m_in_key``, ``mobs_bin``, ``n``,
        ``k_recovered``, ``k_selected``.
    """
    import pandas as pd

    return pd.DataFrame(task_histogram_arrays(rows, obs_column))


def task_histogram_arrays(rows, obs_column: str) -> dict:
    """:func:`task_histogram` as a dict of column arrays (its column order); ``rows`` a
    DataFrame or a mapping of column arrays."""
    return hist_sum_arrays(*_histogram_columns(rows, obs_column))


def _histogram_columns(rows, obs_column: str) -> tuple[dict, list]:
    """The grouped columns of :func:`task_histogram` (a dict of arrays) and its keys."""
    ids = [c for c in (COL_FIELD, COL_Z, COL_MAG, COL_ITERATION) if _has(rows, c)]
    m_in = _values(rows, COL_MAG_INPUT, float)
    rec = _values(rows, COL_RECOVERED).astype(bool)
    g = {c: _values(rows, c) for c in ids}
    g[HIST_MIN_KEY] = np.where(np.isfinite(m_in), np.round(m_in / COUNTS_MAG_RESOLUTION), np.nan)
    b = mobs_lattice_index(_values(rows, obs_column, float))
    g[HIST_MOBS_BIN] = np.where(rec, b, MOBS_BIN_FAINT).astype(np.int32)
    g[COUNT_N] = np.ones(m_in.size, np.int64)
    g[COUNT_K_REC] = rec.astype(np.int64)
    g[COUNT_K_SEL] = _values(rows, COL_SELECTED).astype(np.int64)
    return g, ids


def hist_sums(g, ids: list):
    """Histogram rows summed per (ids, m_in key, m_obs bin), a DataFrame; ``g`` a DataFrame
    or dict of arrays."""
    import pandas as pd

    return pd.DataFrame(hist_sum_arrays(g, ids))


def hist_sum_arrays(g, ids: list) -> dict:
    """:func:`hist_sums` as a dict of column arrays (its column order)."""
    keys = list(ids) + [HIST_MIN_KEY, HIST_MOBS_BIN]
    grp, first = _groups(g, keys)
    out = {k: np.asarray(g[k])[first] for k in keys}
    for c in (COUNT_N, COUNT_K_REC, COUNT_K_SEL):
        out[c] = np.bincount(grp, weights=np.asarray(g[c]), minlength=first.size).astype(np.int64)
    return out


#: Counts columns in the order :func:`task_counts` writes them (after the identity columns).
COUNT_COLUMNS = (COUNT_MAG_KEY, COUNT_DEPTH_KEY, COUNT_N, COUNT_K_REC, COUNT_K_SEL,
                 COUNT_SUM_MAG, COUNT_MAG_MIN, COUNT_MAG_MAX, COUNT_SUM_DEPTH, COUNT_DEPTH_MIN,
                 COUNT_DEPTH_MAX)
