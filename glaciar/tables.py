"""Summaries of a run: GLACiAR's Table 1 per field, binned C, S and C·S, DS9 regions,
and the photometric transfer matrices p(m_obs | m_in, z) (:func:`transfer_matrix`).

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

A run with ``grid.box`` also gets ``box_summary_*.ecsv``: the same columns for the
box's points binned on a grid over the box (:func:`box_summary_table`), with the
bin edges ``z_lo``, ``z_hi``, ``mag_lo``, ``mag_hi`` and ``n_points``.
"""
from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from astropy.table import Table

from . import constants as C
from .paths import file_stem, run_subdir
from .counting import (COUNT_K_REC, COUNT_K_SEL, COUNT_N, COUNTS_MAG_RESOLUTION, STATUS_COLUMNS,
                       TRANSFER_MOBS_STEP, mobs_lattice_edge)
from .store import field_file_prefix
from .rundir import atomic_write_bytes, atomic_write_text

__all__ = ["summary_table", "box_summary_table", "write_summaries", "summary_stem", "region_file",
           "TransferMatrix", "transfer_matrix", "slice_edges", "TRANSFER_KINDS",
           "transfer_from_histograms"]

def summary_table(rows: pd.DataFrame) -> pd.DataFrame:
    """Counts per (z, mag) cell from per-source rows (one field, or several pooled).

    Parameters
    ----------
    rows : pandas.DataFrame
        Per-source rows with at least ``z``, ``mag``, ``status``, ``recovered``,
        ``selected``; or stored counts (:func:`glaciar.counting.task_counts`
        columns, recognised by their ``n`` column), summed per cell.

    Returns
    -------
    pandas.DataFrame
        One row per (z, mag) cell, columns as in the module docstring.
    """
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


def box_summary_table(rows: pd.DataFrame, points, z_edges, mag_edges) -> pd.DataFrame:
    """Counts of the ``grid.box`` points binned on a (z, mag) grid over the box.

    A box point is one (z, m) cell of a few tasks: a table of its own per point
    says little.  The box's points (and only them: grid cells and ``grid.cells``
    inside the box are not mixed in) are summed per bin.

    Parameters
    ----------
    rows : pandas.DataFrame
        As :func:`summary_table` (rows or stored counts).
    points : sequence of (float, float)
        The box's (z, mag) points (:func:`glaciar.box.box_points`), matched exactly.
    z_edges, mag_edges : array_like
        Bin edges (:func:`glaciar.box.box_bin_edges`); the last bin includes its upper edge.

    Returns
    -------
    pandas.DataFrame
        :func:`summary_table`'s columns, ``z`` and ``mag`` being the bin centres, plus
        ``z_lo``, ``z_hi``, ``mag_lo``, ``mag_hi`` and ``n_points`` (box points with rows
        in the bin).  Empty bins are left out.
    """
    ze, me = np.asarray(z_edges, float), np.asarray(mag_edges, float)
    pts = pd.DataFrame(list(points), columns=["_z", "_m"]).drop_duplicates()
    key = pd.DataFrame({"_z": rows[C.COL_Z].astype(float).to_numpy(),
                        "_m": rows[C.COL_MAG].astype(float).to_numpy()})
    on_box = key.merge(pts.assign(_in=True), on=["_z", "_m"], how="left")["_in"]
    sub = rows.loc[on_box.fillna(False).astype(bool).to_numpy()].copy()
    iz = np.clip(np.searchsorted(ze, sub[C.COL_Z].to_numpy(float), side="right") - 1, 0, ze.size - 2)
    im = np.clip(np.searchsorted(me, sub[C.COL_MAG].to_numpy(float), side="right") - 1, 0,
                 me.size - 2)
    n_points = (pd.DataFrame({"iz": iz, "im": im, "z": sub[C.COL_Z].to_numpy(float),
                              "m": sub[C.COL_MAG].to_numpy(float)})
                .drop_duplicates().groupby(["iz", "im"]).size())
    # Centres without binary noise (8.674999999999999): they name the rows.
    sub[C.COL_Z] = np.round(0.5 * (ze[iz] + ze[iz + 1]), 10)
    sub[C.COL_MAG] = np.round(0.5 * (me[im] + me[im + 1]), 10)
    if sub.empty:
        return summary_table(rows.iloc[:0]).assign(z_lo=[], z_hi=[], mag_lo=[], mag_hi=[],
                                                   n_points=[])
    out = summary_table(sub)
    jz = np.clip(np.searchsorted(ze, out[C.COL_Z].to_numpy(), side="right") - 1, 0, ze.size - 2)
    jm = np.clip(np.searchsorted(me, out[C.COL_MAG].to_numpy(), side="right") - 1, 0, me.size - 2)
    out.insert(2, "z_lo", ze[jz])
    out.insert(3, "z_hi", ze[jz + 1])
    out.insert(4, "mag_lo", me[jm])
    out.insert(5, "mag_hi", me[jm + 1])
    out.insert(6, "n_points", n_points.reindex(list(zip(jz, jm))).to_numpy(np.int64))
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
    "z_lo": "lower redshift edge of the box bin", "z_hi": "upper redshift edge of the box bin",
    "mag_lo": "lower magnitude edge of the box bin", "mag_hi": "upper magnitude edge of the box bin",
    "n_points": "box points (each a (z, mag) of its own) in the bin",
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


#: Stem of the summaries pooled over fields (``summary_all.ecsv``): a field of that name is
#: escaped (:func:`summary_stem`).
POOLED_STEM = "all"


def summary_stem(field) -> str:
    """The file-name part of a field's summaries (``summary_<stem>.ecsv``, maps ``*_<stem>.png``).

    :func:`glaciar.paths.file_stem` with the pooled name ``all`` reserved: an
    ordinary field name is kept as it is; ``../x``, ``a/b`` or a field called
    ``all`` get an escaped name with a hash, inside the summary directory.
    """
    return file_stem(str(field), reserved=(POOLED_STEM,))


def _own_dir(out_dir) -> Path:
    """``out_dir`` created if missing and refused if it is a symbolic link (one line)."""
    out_dir = Path(out_dir)
    return run_subdir(out_dir.parent, out_dir.name)


def write_summaries(rows: pd.DataFrame, out_dir, meta: dict | None = None,
                    box: dict | None = None) -> list[Path]:
    """Write one ECSV summary per field, plus ``summary_all.ecsv`` pooled over fields.

    Per-field files are named by :func:`summary_stem` (``summary_<stem>.ecsv``):
    never outside ``out_dir``, never shared by two fields or with the pooled file.

    With ``box`` (``{"points", "z_edges", "mag_edges"}``, a run with ``grid.box``),
    also ``box_summary_<field>.ecsv`` and ``box_summary_all.ecsv``: the box's points
    binned (:func:`box_summary_table`).  The per-cell tables list every point as it is.
    """
    out_dir = _own_dir(out_dir)
    paths = []
    tables = [("summary", summary_table)]
    if box is not None:
        def binned(df):
            return box_summary_table(df, box["points"], box["z_edges"], box["mag_edges"])
        tables.append(("box_summary", binned))
    for prefix, make in tables:
        for field, sub in rows.groupby(C.COL_FIELD, sort=True):
            p = out_dir / f"{prefix}_{summary_stem(field)}.ecsv"
            atomic_write_bytes(p, _ecsv_bytes(make(sub), {**(meta or {}), "field": str(field)}))
            paths.append(p)
        p = out_dir / f"{prefix}_all.ecsv"
        atomic_write_bytes(p, _ecsv_bytes(make(rows), {**(meta or {}), "field": "all"}))
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
    out_dir = _own_dir(out_dir)
    paths = []
    order = [c for c in (C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE) if c in rows.columns]
    for f, sub in rows.groupby(C.COL_FIELD, sort=True):
        prefix = field_file_prefix(str(f))
        p = out_dir / f"regions_{prefix[len('task_'):-1]}.reg"
        atomic_write_text(p, region_file(sub.sort_values(order, kind="stable")))
        paths.append(p)
    return paths


# --------------------------------------------------------------------------
# Photometric transfer function p(m_obs | m_in, z)
# --------------------------------------------------------------------------
#: Width of the input-magnitude (and redshift) slices when the injections are not on a
#: grid (more distinct values than TRANSFER_MAX_UNIQUE) [mag, z].
TRANSFER_MIN_STEP = 0.25
TRANSFER_Z_STEP = 0.25
TRANSFER_MAX_UNIQUE = 200
#: Measured magnitudes are binned from (min input edge - margin) to (max input edge + margin),
#: with one open bin on either side [mag].
TRANSFER_MOBS_MARGIN = 1.5
#: Posterior draws of each transfer matrix written to the selection-function file.
TRANSFER_DRAWS = 100
#: The two matrices: entry 0 of the last axis is "not recovered" or "not selected".
TRANSFER_KINDS = ("recovered", "selected")
@dataclass(frozen=True)
class TransferMatrix:
    """The photometric transfer function p(m_obs | m_in, z) as row-normalised matrices.

    For every redshift slice ``i`` and input-magnitude bin ``j``, entry ``[k, i, j, 0]``
    is the fraction of injected sources that were *not* recovered (kind 0) or not
    selected (kind 1), and entry ``[k, i, j, 1 + b]`` the fraction that were, with a
    measured detection-band magnitude in bin ``b`` of ``m_obs_edges``; each row sums
    to 1.  The first and last m_obs bins are open (edges -inf and +inf); a recovered
    source whose measured flux is not positive (measured magnitude NaN) counts in
    the last (faintest) bin.

    Attributes
    ----------
    kinds : tuple of str
        ``TRANSFER_KINDS``: what the first axis holds.
    z_edges : ndarray (n_z + 1,)
        Redshift slices [lo, hi).
    z_mean : ndarray (n_z,)
        Mean input redshift of the sources in each slice (NaN if empty).
    m_in_edges : ndarray (n_in + 1,)
        Input-magnitude bins [lo, hi) [mag].
    m_obs_edges : ndarray (n_obs + 1,)
        Measured-magnitude bins [mag]; first -inf, last +inf.
    counts : ndarray int64 (2, n_z, n_in, 1 + n_obs)
        Source counts per entry.
    matrix : ndarray (2, n_z, n_in, 1 + n_obs)
        ``counts / counts.sum(-1)`` (NaN for a row without sources).
    draws : ndarray (n_draws, 2, n_z, n_in, 1 + n_obs)
        Posterior draws of each row, Dirichlet(counts + alpha) (NaN for empty rows).
    alpha : float
        Dirichlet prior concentration per entry (Perks: 1 / (1 + n_obs), one
        pseudo-source per row).
    """

    kinds: tuple
    z_edges: np.ndarray
    z_mean: np.ndarray
    m_in_edges: np.ndarray
    m_obs_edges: np.ndarray
    counts: np.ndarray
    matrix: np.ndarray
    draws: np.ndarray
    alpha: float


def slice_edges(values, step: float, max_unique: int = TRANSFER_MAX_UNIQUE) -> np.ndarray:
    """Bin edges for sources injected on a grid (one bin per value) or continuously.

    With at most ``max_unique`` distinct values (rounded to 1e-6) the edges are the
    midpoints between them, the outer ones half a spacing beyond (``step / 2`` for a
    single value); otherwise uniform bins of width ``step`` from the minimum.
    """
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        raise ValueError("slice_edges: no finite values")
    u = np.unique(np.round(v, 6))
    if len(u) == 1:
        return np.array([u[0] - step / 2, u[0] + step / 2])
    if len(u) <= max_unique:
        mid = 0.5 * (u[1:] + u[:-1])
        return np.concatenate([[u[0] - (mid[0] - u[0])], mid, [u[-1] + (u[-1] - mid[-1])]])
    n = max(1, int(np.ceil((u[-1] - u[0]) / step + 1e-9)))
    edges = u[0] + step * np.arange(n + 1)
    edges[-1] = max(edges[-1], np.nextafter(u[-1], np.inf))
    return edges


def transfer_matrix(z, m_in, m_obs, recovered, selected, *, z_edges=None, m_in_edges=None,
                    m_obs_edges=None, n_draws: int = TRANSFER_DRAWS, seed=0) -> TransferMatrix:
    """p(m_obs | m_in, z) of recovered and of selected sources, with Dirichlet draws.

    Parameters
    ----------
    z, m_in : array_like (N,)
        Input redshift and total input detection-band magnitude [AB mag] per source.
    m_obs : array_like (N,)
        Measured detection-band magnitude [AB mag] (NaN for non-positive flux; only
        used where recovered / selected).
    recovered, selected : array_like of bool (N,)
    z_edges, m_in_edges : array_like, optional
        Slices; default :func:`slice_edges` of the data (``TRANSFER_Z_STEP``,
        ``TRANSFER_MIN_STEP``).  Sources outside them are left out.
    m_obs_edges : array_like, optional
        Finite inner edges of the measured-magnitude bins, increasing; -inf and +inf
        are added at the ends.  Default: steps of ``TRANSFER_MOBS_STEP`` over the
        input range widened by ``TRANSFER_MOBS_MARGIN``.
    n_draws : int
        Posterior draws per row.
    seed : int or sequence of int
        Seed of the draws (the same seed and data give the same draws).

    Returns
    -------
    TransferMatrix
    """
    z = np.asarray(z, float)
    m_in = np.asarray(m_in, float)
    m_obs = np.asarray(m_obs, float)
    rec = np.asarray(recovered, bool)
    sel = np.asarray(selected, bool)
    n = len(z)
    if not (len(m_in) == len(m_obs) == len(rec) == len(sel) == n):
        raise ValueError("transfer_matrix: z, m_in, m_obs, recovered and selected must have "
                         "the same length")
    if n == 0:
        raise ValueError("transfer_matrix: no sources")
    if np.any(sel & ~rec):
        raise ValueError("transfer_matrix: a selected source must be recovered")
    ze, me, inner = _transfer_edges(z, m_in, z_edges, m_in_edges, m_obs_edges)
    oe = np.concatenate([[-np.inf], inner, [np.inf]])
    n_z, n_in, n_obs = len(ze) - 1, len(me) - 1, len(oe) - 1
    iz = np.searchsorted(ze, z, side="right") - 1
    im = np.searchsorted(me, m_in, side="right") - 1
    inside = (iz >= 0) & (iz < n_z) & (im >= 0) & (im < n_in)
    # NaN measured magnitude (flux <= 0) goes to the faintest, open bin.
    io = np.where(np.isnan(m_obs), n_obs - 1, np.searchsorted(oe, m_obs, side="right") - 1)
    io = np.clip(io, 0, n_obs - 1)
    counts = np.zeros((len(TRANSFER_KINDS), n_z, n_in, 1 + n_obs), np.int64)
    for k, flag in enumerate((rec, sel)):
        entry = np.where(flag, 1 + io, 0)
        flat = np.ravel_multi_index((iz[inside], im[inside], entry[inside]), (n_z, n_in, 1 + n_obs))
        counts[k] = np.bincount(flat, minlength=n_z * n_in * (1 + n_obs)).reshape(n_z, n_in, 1 + n_obs)
    zsum = np.bincount(iz[inside], weights=z[inside], minlength=n_z)
    zn = np.bincount(iz[inside], minlength=n_z)
    return _transfer_result(counts, ze, me, oe, zsum, zn, n_draws, seed)


def _transfer_edges(z, m_in, z_edges, m_in_edges, m_obs_edges):
    """(z, m_in, finite inner m_obs) edges: given, or the defaults of :func:`transfer_matrix`."""
    ze = slice_edges(z, TRANSFER_Z_STEP) if z_edges is None else np.asarray(z_edges, float)
    me = slice_edges(m_in, TRANSFER_MIN_STEP) if m_in_edges is None else np.asarray(m_in_edges, float)
    if m_obs_edges is None:
        lo = np.floor((me[0] - TRANSFER_MOBS_MARGIN) / TRANSFER_MOBS_STEP) * TRANSFER_MOBS_STEP
        hi = np.ceil((me[-1] + TRANSFER_MOBS_MARGIN) / TRANSFER_MOBS_STEP) * TRANSFER_MOBS_STEP
        inner = np.round(np.arange(lo, hi + TRANSFER_MOBS_STEP / 2, TRANSFER_MOBS_STEP), 6)
    else:
        inner = np.asarray(m_obs_edges, float)
    for name, e in (("z_edges", ze), ("m_in_edges", me), ("m_obs_edges", inner)):
        if e.ndim != 1 or len(e) < 2 or not np.all(np.isfinite(e)) or np.any(np.diff(e) <= 0):
            raise ValueError(f"transfer_matrix: {name} must be >= 2 finite increasing values")
    return ze, me, inner


def _transfer_result(counts, ze, me, oe, zsum, zn, n_draws, seed) -> TransferMatrix:
    """The :class:`TransferMatrix` of ``counts``: normalised rows, draws, mean z per slice."""
    n_obs = len(oe) - 1
    tot = counts.sum(axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        matrix = np.where(tot > 0, counts / np.maximum(tot, 1), np.nan)
    # Dirichlet(counts + alpha) per row, from independent Gamma variates.
    alpha = 1.0 / (1 + n_obs)
    rng = np.random.default_rng(seed)
    g = rng.standard_gamma(counts[None] + alpha, size=(int(n_draws),) + counts.shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        draws = g / g.sum(axis=-1, keepdims=True)
    draws[:, tot[..., 0] == 0] = np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        z_mean = np.where(zn > 0, zsum / np.maximum(zn, 1), np.nan)
    return TransferMatrix(kinds=TRANSFER_KINDS, z_edges=ze, z_mean=z_mean, m_in_edges=me,
                          m_obs_edges=oe, counts=counts, matrix=matrix, draws=draws, alpha=alpha)


def transfer_from_histograms(z, m_in_key, mobs_bin, n, k_recovered, k_selected, *, z_edges=None,
                             m_in_edges=None, m_obs_edges=None, n_draws: int = TRANSFER_DRAWS,
                             seed=0) -> TransferMatrix:
    """:func:`transfer_matrix` from stored histograms of the measured magnitude (no rows).

    The histograms are :func:`glaciar.counting.task_histogram` rows (any sum of
    them): per (z, input-magnitude key, m_obs lattice bin) the number of
    sources and of recovered and selected ones.  The result equals
    :func:`transfer_matrix` on the rows (same counts; same draws for the
    same seed) when each input magnitude is its key's value
    (``m_in_key * COUNTS_MAG_RESOLUTION``, true for a magnitude grid on that
    resolution) or the ``m_in_edges`` fall between keys, and the m_obs edges
    are lattice edges (:func:`glaciar.counting.mobs_lattice_edge`; the defaults are); the mean z
    of a slice agrees to rounding.  Otherwise an input magnitude is binned
    by its key's value (to ``COUNTS_MAG_RESOLUTION``).

    Parameters
    ----------
    z : array_like (K,)
        Input redshift of each histogram row.
    m_in_key : array_like (K,)
        ``round(mag_input / COUNTS_MAG_RESOLUTION)`` (NaN: non-finite input magnitude).
    mobs_bin : array_like of int (K,)
        :func:`glaciar.counting.mobs_lattice_index` of the measured magnitude (``MOBS_BIN_FAINT`` for
        sources not recovered).
    n, k_recovered, k_selected : array_like of int (K,)
        Sources, recovered, selected.
    z_edges, m_in_edges, m_obs_edges, n_draws, seed
        As :func:`transfer_matrix`; ``m_obs_edges`` must be lattice edges.

    Returns
    -------
    TransferMatrix

    Raises
    ------
    ValueError
        No sources, a selected count above the recovered one, or m_obs edges off the lattice.
    """

    z = np.asarray(z, float)
    key = np.asarray(m_in_key, float)
    b = np.asarray(mobs_bin, np.int64)
    n = np.asarray(n, np.int64)
    k_rec = np.asarray(k_recovered, np.int64)
    k_sel = np.asarray(k_selected, np.int64)
    if not (len(key) == len(b) == len(n) == len(k_rec) == len(k_sel) == len(z)):
        raise ValueError("transfer_from_histograms: z, m_in_key, mobs_bin, n, k_recovered and "
                         "k_selected must have the same length")
    if n.sum() == 0:
        raise ValueError("transfer_matrix: no sources")
    if np.any(k_sel > k_rec) or np.any(k_rec > n):
        raise ValueError("transfer_matrix: a selected source must be recovered")
    # The key's value rounded as slice_edges rounds the rows' values (grid values agree exactly).
    m_in = np.round(key * COUNTS_MAG_RESOLUTION, 6)
    ze, me, inner = _transfer_edges(z, m_in, z_edges, m_in_edges, m_obs_edges)
    lat = np.round(inner / TRANSFER_MOBS_STEP)
    if np.any(np.abs(mobs_lattice_edge(lat) - inner) > 1e-9):
        raise ValueError(f"transfer_from_histograms: m_obs_edges must be multiples of "
                         f"{TRANSFER_MOBS_STEP} mag (the stored lattice)")
    oe = np.concatenate([[-np.inf], inner, [np.inf]])
    n_z, n_in, n_obs = len(ze) - 1, len(me) - 1, len(oe) - 1
    iz = np.searchsorted(ze, z, side="right") - 1
    im = np.searchsorted(me, m_in, side="right") - 1
    inside = (iz >= 0) & (iz < n_z) & (im >= 0) & (im < n_in) & np.isfinite(m_in)
    # Lattice bin b lies wholly in output bin searchsorted(lattice edges, b): the overflow
    # sentinels land in the open end bins.
    io = np.searchsorted(lat.astype(np.int64), b, side="right")
    counts = np.zeros((len(TRANSFER_KINDS), n_z, n_in, 1 + n_obs), np.int64)
    size = n_z * n_in * (1 + n_obs)
    iz, im, io = iz[inside], im[inside], io[inside]
    for k, kk in enumerate((k_rec[inside], k_sel[inside])):
        hit = np.ravel_multi_index((iz, im, 1 + io), (n_z, n_in, 1 + n_obs))
        miss = np.ravel_multi_index((iz, im, np.zeros_like(io)), (n_z, n_in, 1 + n_obs))
        # Integer sums as float64 are exact below 2**53 sources.
        flat = (np.bincount(hit, weights=kk, minlength=size)
                + np.bincount(miss, weights=n[inside] - kk, minlength=size))
        counts[k] = np.rint(flat).astype(np.int64).reshape(n_z, n_in, 1 + n_obs)
    zsum = np.bincount(iz, weights=z[inside] * n[inside], minlength=n_z)
    zn = np.bincount(iz, weights=n[inside], minlength=n_z)
    return _transfer_result(counts, ze, me, oe, zsum, zn, n_draws, seed)
