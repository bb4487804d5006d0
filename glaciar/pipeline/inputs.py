"""What the fit reads from a run directory: counts (or the flag columns), the manifest's areas.

:func:`fit_inputs` gives the fit one view of a store, :class:`FitInputs`:
entries with a source count ``n`` each.  From the stored counts
(:func:`glaciar.store.read_current_counts`) an entry is a group of sources of
one (field, z, mag, magnitude key, depth bin of ``DEPTH_BIN_MAG``) summed
over iterations; from the rows (stores written before counts, or a
magnitude resolution other than the counts') an entry is one source.

Counts and the fit's cells
--------------------------
Without depth, the fit's cells (z, round(m / 0.01)) are unions of count
groups (same magnitude key): :func:`cells_from_counts` gives the same cells
as :func:`glaciar.inference.fit.aggregate_cells` on the rows (integer counts
identical, means equal to rounding).  With depth, a source's covariate is
``m - (depth - depth_ref)``; a count group (depth bin 0.05 mag) is placed in
the cell of its mean covariate, so a cell may hold sources up to
0.05 + 0.01 mag apart instead of 0.01: the Berkson-type grouping of
:mod:`glaciar.inference.fit` with variance <= (0.01^2 + 0.05^2) / 12 mag^2,
which widens w by a relative ~0.15 * 2.2e-4 / w^2 (4e-4 at w = 0.3 mag).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, fields

import numpy as np

from .. import constants as C

__all__ = ["read_columns", "manifest_areas", "depth_area", "FitInputs", "fit_inputs",
           "cells_from_counts"]


def read_columns(run_dir, want):
    """The wanted per-source columns that the store has (column projection), current rows only.

    The projection entry point for whatever needs per-source values (e.g.
    measured magnitudes): the rows are
    :func:`glaciar.store.read_current_results`' (loose task files and
    compacted parts alike); a column the store lacks is left out rather than
    an error.
    """
    from ..store import read_current_results, store_columns

    have = store_columns(run_dir) or set(want)
    return read_current_results(run_dir, columns=[c for c in want if c in have])


@dataclass(frozen=True)
class FitInputs:
    """The fit's view of a store: entries of ``n`` sources each (arrays of equal length).

    Attributes
    ----------
    field : ndarray of str
    z, mag_nominal : ndarray
        Redshift and the task's nominal magnitude.
    mag : ndarray
        Mean magnitude covariate of the entry [mag].
    depth : ndarray
        Mean local depth [AB mag] (NaN where unknown).
    depth_bin : ndarray
        A depth inside the entry's depth bin (the depth itself for a source,
        the bin centre for a count group), for the posterior-predictive check's bins.
    mag_lo, mag_hi, depth_lo, depth_hi : ndarray
        Extremes of the covariate and depth over the entry's sources.
    n, k_rec, k_sel : ndarray of int
        Sources, recovered, selected.
    rows : pandas.DataFrame or None
        The per-source rows when read from rows (the fit's cells are then
        :func:`aggregate_cells` of them, exactly as before counts existed).
    """
    field: np.ndarray
    z: np.ndarray
    mag_nominal: np.ndarray
    mag: np.ndarray
    depth: np.ndarray
    depth_bin: np.ndarray
    mag_lo: np.ndarray
    mag_hi: np.ndarray
    depth_lo: np.ndarray
    depth_hi: np.ndarray
    n: np.ndarray
    k_rec: np.ndarray
    k_sel: np.ndarray
    rows: object = None

    @property
    def from_counts(self) -> bool:
        return self.rows is None

    def subset(self, mask) -> "FitInputs":
        """The entries where ``mask`` is True."""
        mask = np.asarray(mask, bool)
        kw = {f.name: getattr(self, f.name)[mask] for f in fields(self) if f.name != "rows"}
        rows = None if self.rows is None else self.rows[mask].reset_index(drop=True)
        return FitInputs(**kw, rows=rows)

    def depth_median(self) -> float:
        """Median depth over sources (weighted median of the entries' mean depths for counts)."""
        if self.rows is not None:
            return float(np.median(self.depth))
        o = np.argsort(self.depth)
        cw = np.cumsum(self.n[o])
        return float(self.depth[o][np.searchsorted(cw, 0.5 * cw[-1])])

    def cells(self, mag_resolution, depth_ref, mag_col):
        """The fit's binomial cells (:func:`aggregate_cells` or :func:`cells_from_counts`)."""
        from ..inference.fit import aggregate_cells

        if self.rows is not None:
            return aggregate_cells(self.rows, mag_resolution, depth_ref, mag_col)
        return cells_from_counts(self.z, self.mag, self.depth, self.n, self.k_rec, self.k_sel,
                                 mag_resolution, depth_ref)


def cells_from_counts(z, mag, depth, n, k_rec, k_sel, mag_resolution, depth_ref=None):
    """The fit's binomial cells from count groups (the counterpart of :func:`aggregate_cells`).

    Parameters
    ----------
    z, mag, depth : array_like (G,)
        Per group: redshift, mean magnitude covariate [mag], mean local depth [AB mag].
    n, k_rec, k_sel : array_like of int (G,)
    mag_resolution : float
        Cells group ``round(m / mag_resolution)``; a group falls in the cell of
        its mean covariate ``m = mag - (depth - depth_ref)`` (or ``mag``).
    depth_ref : float, optional

    Returns
    -------
    Cells
        Ordered by (z, magnitude key), like :func:`aggregate_cells`.
    """
    from ..inference.models import Cells

    z = np.asarray(z, float)
    n = np.asarray(n, np.int64)
    m = np.asarray(mag, float)
    if depth_ref is not None:
        m = m - (np.asarray(depth, float) - float(depth_ref))
    kr, ks = np.asarray(k_rec, np.int64), np.asarray(k_sel, np.int64)
    good = np.isfinite(z) & np.isfinite(m)
    if not good.all():
        what = "z, magnitude or depth" if depth_ref is not None else "z or magnitude"
        warnings.warn(f"cells_from_counts: dropping {int(n[~good].sum())} sources with "
                      f"non-finite {what}")
        z, m, n, kr, ks = z[good], m[good], n[good], kr[good], ks[good]
    if np.any(ks > kr):
        raise ValueError(f"{int(np.sum(ks > kr))} count groups have more selected than "
                         "recovered sources; 'selected' must imply 'recovered'")
    if n.sum() == 0:
        raise ValueError("cells_from_counts: no sources to fit")
    mkey = np.round(m / mag_resolution)
    _, zi = np.unique(z, return_inverse=True)
    _, mi = np.unique(mkey, return_inverse=True)
    key = zi.astype(np.int64) * (int(mi.max()) + 1) + mi
    ukey, inv = np.unique(key, return_inverse=True)
    nc = len(ukey)
    nn = np.bincount(inv, weights=n, minlength=nc)
    return Cells(z=np.bincount(inv, weights=z * n, minlength=nc) / nn,
                 mag=np.bincount(inv, weights=m * n, minlength=nc) / nn,
                 n=nn.astype(np.int64),
                 k_rec=np.bincount(inv, weights=kr, minlength=nc).astype(np.int64),
                 k_sel=np.bincount(inv, weights=ks, minlength=nc).astype(np.int64))


def fit_inputs(run_dir, mag_col: str, mag_resolution) -> FitInputs:
    """The fit's view of a run: from the stored counts whenever they serve, else the rows.

    Counts serve when every task has them, keyed on ``mag_col``, and
    ``mag_resolution`` is :data:`glaciar.counting.COUNTS_MAG_RESOLUTION` (their
    key); otherwise the rows' columns the fit needs are read (projection).
    """
    from .. import counting as K
    from .. import store as S

    got = None
    if mag_resolution is not None and float(mag_resolution) == K.COUNTS_MAG_RESOLUTION:
        got = S.read_current_counts(run_dir)
    if got is not None and got[1] == mag_col:
        c = got[0]
        n = c[K.COUNT_N].to_numpy(np.int64)
        dkey = c[K.COUNT_DEPTH_KEY].to_numpy(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            return FitInputs(
                field=(c[C.COL_FIELD].astype(str).to_numpy() if C.COL_FIELD in c.columns
                       else np.full(len(c), "all")),
                z=c[C.COL_Z].to_numpy(float), mag_nominal=c[C.COL_MAG].to_numpy(float),
                mag=c[K.COUNT_SUM_MAG].to_numpy(float) / n,
                depth=c[K.COUNT_SUM_DEPTH].to_numpy(float) / n,
                depth_bin=(dkey + 0.5) * C.DEPTH_BIN_MAG,
                mag_lo=c[K.COUNT_MAG_MIN].to_numpy(float), mag_hi=c[K.COUNT_MAG_MAX].to_numpy(float),
                depth_lo=c[K.COUNT_DEPTH_MIN].to_numpy(float),
                depth_hi=c[K.COUNT_DEPTH_MAX].to_numpy(float),
                n=n, k_rec=c[K.COUNT_K_REC].to_numpy(np.int64),
                k_sel=c[K.COUNT_K_SEL].to_numpy(np.int64))
    want = [C.COL_FIELD, C.COL_Z, C.COL_MAG, mag_col, C.COL_RECOVERED, C.COL_SELECTED, C.COL_DEPTH]
    df = read_columns(run_dir, want)
    if C.COL_FIELD not in df.columns:
        df[C.COL_FIELD] = "all"
    m = df[mag_col].to_numpy(float)
    d = df[C.COL_DEPTH].to_numpy(float) if C.COL_DEPTH in df.columns else np.full(len(df), np.nan)
    mnom = df[C.COL_MAG].to_numpy(float) if C.COL_MAG in df.columns else np.round(m / 0.25) * 0.25
    rec = df[C.COL_RECOVERED].to_numpy()
    sel = df[C.COL_SELECTED].to_numpy()
    return FitInputs(field=df[C.COL_FIELD].astype(str).to_numpy(), z=df[C.COL_Z].to_numpy(float),
                     mag_nominal=mnom, mag=m, depth=d, depth_bin=d, mag_lo=m, mag_hi=m,
                     depth_lo=d, depth_hi=d, n=np.ones(len(df), np.int64),
                     k_rec=np.asarray(rec).astype(bool).astype(np.int64),
                     k_sel=np.asarray(sel).astype(bool).astype(np.int64),
                     rows=df)


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
