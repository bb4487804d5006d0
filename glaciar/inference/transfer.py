"""The photometric transfer function p(m_obs | m_in, z) anywhere inside the simulated box.

:func:`glaciar.tables.transfer_matrix` counts, per redshift slice ``i`` and input-magnitude
bin ``j``, where the measured detection-band magnitude m_obs of the injected sources fell
(0.2 mag bins, the first and last open).  A luminosity-function code needs it at every
(m_in, z), per posterior draw, on its own m_obs bins.  :func:`transfer_function` turns
the matrix into a :class:`TransferFunction` that does this:

* **Rows as offsets.**  Row (i, j), conditional on the source being selected (or
  recovered: columns 1.. renormalised), is read as the distribution of the offset
  delta = m_obs - u_j, with u_j the row's input magnitude (the grid magnitude the bin was
  built around, :func:`row_magnitudes`), uniform inside each m_obs bin.  The two open
  bins are kept apart as masses f_lo (brighter than every finite edge) and f_hi (fainter,
  including measured fluxes <= 0): they enter only an asked-for bin that is open on
  that side.
* **Smooth rows.**  Each row's cumulative distribution, known at the 0.2 mag bin edges, is
  interpolated between them by a monotone cubic (PCHIP: every bin keeps its probability,
  an empty bin stays empty) and sampled at ``REFINE`` sub-bins per bin; read as piecewise
  uniform in the 0.2 mag bins instead, a narrow scatter (sigma ~ 0.1 mag) shifted by half
  a bin is off by up to 0.16 in a bin's probability, with PCHIP by < 0.08 (< 5e-3 for
  sigma >= 0.2 mag): the 0.2 mag histogram does not resolve a narrower scatter better.
* **Between input magnitudes: displacement interpolation.**  Each row's offset
  distribution is stored as its quantile function Q_j(p) at ``N_LEVELS`` fixed levels
  (normal scores: p = Phi(x), x uniform over +-4, plus 0 and 1), read as piecewise
  uniform between them.  At u_j <= m <= u_(j+1), t = (m - u_j) / (u_(j+1) - u_j), the
  quantile function is (1 - t) Q_j + t Q_(j+1) (McCann's displacement interpolation)
  and f_lo, f_hi mix linearly.  A shift or a widening of the scatter with magnitude (the
  faint end) is then followed exactly (a location-scale family whose location and
  scale vary linearly is reproduced), where a mixture of the two rows would give a
  two-humped distribution.
* **Between redshift slices: a mixture**, linear in z between the slices' mean input
  redshifts (``TransferMatrix.z_mean``).
* **Outside the rows** (m brighter than the first row or fainter than the last, z
  outside the slices' means) the nearest row's offset distribution (nearest slice)
  is used unchanged.  Such m lie outside the simulated magnitude range: callers flag
  them (:func:`glaciar.inference.counts.count_kernel`).
* **Thin rows.**  A row with fewer than ``min_count`` sources in finite m_obs bins (empty
  rows, NaN in the matrix, included: faint rows with hardly any selected source) gives
  no usable shape; it borrows the offset distribution of the nearest usable row of its
  slice, and a slice without any usable row is left out.

Accuracy (tests/inference/test_transfer.py): for a Gaussian scatter m_obs = m_in + 0.15 +
N(0, sigma(m_in)), sigma growing linearly from 0.1 mag (m_in = 24) to 0.5 mag (28),
tabulated exactly on a 0.5 mag grid of input magnitudes in 0.2 mag m_obs bins, the
probabilities of 0.2 mag bins at off-grid (m_in, z) agree with the exact normal ones to
< 5e-3 where sigma >= 0.2 mag, < 0.01 at sigma = 0.12, and at a row's own magnitude to
< 4e-3 (1e-3 at sigma = 0.2: the quantile representation).  A scatter narrower than the
bins is not resolved by the histogram: at sigma ~ 0.1 a bin's probability can be off by
up to 0.07 at one input magnitude (0.015 averaged over 0.5 mag of input magnitude, which
is what counts integrate over).  This is the 0.2 mag histogram's limit, not the
interpolation's (exact for this family).  Finer m_obs bins in the stored histograms
(``TRANSFER_MOBS_STEP``) would lift it.

Arrays in, arrays out; no file I/O.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .products import beta_nodes, kcorrection

__all__ = ["TransferFunction", "transfer_function", "row_magnitudes", "quantile_levels",
           "transfer_probability_muv", "MIN_ROW_COUNT", "REFINE", "N_LEVELS"]

#: A transfer-matrix row needs at least this many sources in finite m_obs bins to describe
#: a distribution of its own; thinner rows borrow the nearest usable row's (module docstring).
MIN_ROW_COUNT = 10
#: Sub-bins per m_obs bin: each row's cumulative distribution is interpolated between the
#: matrix's bin edges by a monotone cubic (PCHIP; bin probabilities kept exactly) and read as
#: piecewise uniform on the sub-bins (module docstring).
REFINE = 4
#: Levels of the stored quantile functions (:func:`quantile_levels`).
N_LEVELS = 129
#: Stand-in for an infinite m_obs edge inside the interpolation (clamped anyway) [mag].
_BIG = 1.0e6


def row_magnitudes(m_in_edges) -> np.ndarray:
    """The input magnitude each transfer-matrix row describes [mag].

    :func:`glaciar.tables.slice_edges` puts the edges of a grid of injected magnitudes
    halfway between grid values (the outer ones half a spacing out), so the grid values
    follow from the edges: u_0 = (e_0 + e_1) / 2, u_k = 2 e_k - u_(k-1).  For uniform
    bins (sources injected continuously) that gives the bin centres.  When the edges were
    not built that way (the recursion leaves a bin or misses the last edge by > 1e-6 mag),
    the bin centres.

    Parameters
    ----------
    m_in_edges : array_like (n + 1,)

    Returns
    -------
    ndarray (n,)
    """
    e = np.asarray(m_in_edges, float)
    centres = 0.5 * (e[:-1] + e[1:])
    if len(e) < 3:
        return centres
    u = np.empty(len(e) - 1)
    u[0] = centres[0]
    for k in range(1, len(u)):
        u[k] = 2 * e[k] - u[k - 1]
    ok = (np.all((u > e[:-1]) & (u < e[1:]))
          and abs(2 * u[-1] - e[-2] - e[-1]) < 1e-6)
    return u if ok else centres


def _refine(edges, cdf, n: int):
    """``n`` sub-bins per bin: the CDF (last axis, at ``edges``) by PCHIP at the sub-bin edges.

    PCHIP keeps the CDF monotone and equal to the given values at the edges (so every
    bin keeps its probability, and an empty bin stays empty), and its density is smooth
    where the histogram's is.
    """
    from scipy.interpolate import PchipInterpolator

    fine = np.concatenate([edges[:-1, None] + np.diff(edges)[:, None] * np.arange(n) / n,
                           edges[-1:, None]], axis=None)
    out = PchipInterpolator(edges, cdf, axis=-1)(fine)
    out = np.maximum.accumulate(np.clip(out, 0.0, 1.0), axis=-1)
    return fine, out


def _interp_rows(x, xp, fp, side: str = "right"):
    """Piecewise-linear interpolation row by row, clamped at the ends.

    ``x`` (B, nx), ``xp`` (B, n) non-decreasing per row, ``fp`` (B, n).  At a repeated
    abscissa (a jump) ``side="right"`` takes the last value and ``side="left"`` the
    first.  One ``searchsorted`` over all rows: row r is offset by r times the span of
    all abscissae, so the rows follow each other in one increasing array.
    """
    B, n = xp.shape
    xc = np.clip(x, xp[:, :1], xp[:, -1:])
    lo, hi = float(xp.min()), float(xp.max())
    span = (hi - lo) + 1.0
    off = (np.arange(B, dtype=float) * span)[:, None]
    flat = (xp - lo + off).ravel()
    pos = np.searchsorted(flat, (xc - lo + off).ravel(), side=side).reshape(xc.shape)
    idx = pos - (np.arange(B) * n)[:, None]
    idx = np.clip(idx - 1, 0, n - 2)
    x0 = np.take_along_axis(xp, idx, axis=1)
    x1 = np.take_along_axis(xp, idx + 1, axis=1)
    f0 = np.take_along_axis(fp, idx, axis=1)
    f1 = np.take_along_axis(fp, idx + 1, axis=1)
    dx = x1 - x0
    # dx = 0 only where the index was clamped at an end: the end's value on that side.
    t = np.where(dx > 0, (xc - x0) / np.where(dx > 0, dx, 1.0), 1.0 if side == "right" else 0.0)
    return f0 + np.clip(t, 0.0, 1.0) * (f1 - f0)


def quantile_levels(n: int) -> np.ndarray:
    """``n`` cumulative levels: 0, Phi(x) for ``n - 2`` x uniform over [-4, 4], 1.

    Dense in the tails (normal scores), so that a Gaussian-like offset distribution is
    sampled about evenly in magnitude.
    """
    from scipy.special import ndtr

    return np.concatenate([[0.0], ndtr(np.linspace(-4.0, 4.0, int(n) - 2)), [1.0]])


def _quantiles(levels, cdf, knots):
    """Q(p) of piecewise-uniform laws (CDF ``cdf`` at ``knots``, (B, n)) at ``levels`` (L,).

    Q(0) is where the support starts and Q(1) where it ends (an empty first or last bin
    is not part of it); in between the right-continuous inverse.
    """
    B = len(cdf)
    lv = np.broadcast_to(levels, (B, len(levels)))
    q = _interp_rows(lv, cdf, knots, "right")
    q[:, -1] = _interp_rows(lv[:, -1:], cdf, knots, "left")[:, 0]
    return q


@dataclass(frozen=True)
class TransferFunction:
    """p(m_obs in bin k | m_in, z, selected) (or recovered) at any (m_in, z), per draw.

    Built by :func:`transfer_function`; the method is in the module docstring.

    Attributes
    ----------
    kind : str
        "selected" or "recovered": what the distribution is conditional on.
    z_nodes : ndarray (n_s,)
        Mean input redshift of each usable slice, increasing.
    m_nodes : ndarray (n_in,)
        Input magnitude of each row [mag] (:func:`row_magnitudes`).
    source : ndarray (n_s, n_in)
        Input magnitude the row's offsets are measured from [mag]: its own, or that of
        the row it borrowed from.
    levels : ndarray (L,)
        Cumulative levels of the stored quantiles (:func:`quantile_levels`).
    quantiles : ndarray (n_d, n_s, n_in, L)
        Offset m_obs - source [mag] at each level, of the finite part of the row.
    f_lo, f_hi : ndarray (n_d, n_s, n_in)
        Probability of the open bright and faint bins.
    n_sources : ndarray (n_s, n_in)
        Sources of the row in finite m_obs bins (kind).
    filled : ndarray of bool (n_s, n_in)
        Rows that borrowed another row's distribution (fewer than ``min_count`` sources).
    per_draw : bool
        True: the leading axis holds the matrix's posterior draws; False: one entry,
        the counts' estimate.
    """

    kind: str
    z_nodes: np.ndarray
    m_nodes: np.ndarray
    source: np.ndarray
    levels: np.ndarray
    quantiles: np.ndarray
    f_lo: np.ndarray
    f_hi: np.ndarray
    n_sources: np.ndarray
    filled: np.ndarray
    per_draw: bool

    @property
    def n_draws(self) -> int:
        return int(self.quantiles.shape[0])

    @property
    def m_range(self) -> tuple[float, float]:
        """Input magnitudes covered by rows [mag]; outside, the end rows are used."""
        return float(self.m_nodes[0]), float(self.m_nodes[-1])

    def _row_pairs(self, m):
        """(j, t): rows j, j + 1 and the weight of j + 1 for each magnitude (clamped)."""
        u = self.m_nodes
        if len(u) == 1:
            return np.zeros(np.shape(m), int), np.zeros(np.shape(m))
        j = np.clip(np.searchsorted(u, m, side="right") - 1, 0, len(u) - 2)
        t = np.clip((m - u[j]) / (u[j + 1] - u[j]), 0.0, 1.0)
        return j, t

    def _z_pairs(self, z):
        """(i, s): slices i, i + 1 and the weight of i + 1 for each redshift (clamped)."""
        zn = self.z_nodes
        z = np.asarray(z, float)
        if len(zn) == 1:
            return np.zeros(z.shape, int), np.zeros(z.shape)
        i = np.clip(np.searchsorted(zn, z, side="right") - 1, 0, len(zn) - 2)
        s = np.clip((z - zn[i]) / (zn[i + 1] - zn[i]), 0.0, 1.0)
        return i, s

    def _rows_at(self, d, i, m, m_obs_edges):
        """p(bin k | m, slice i) for draw indices d, slices i and magnitudes m (all (B,))."""
        E = np.asarray(m_obs_edges, float)
        m = np.asarray(m, float)
        j, t = self._row_pairs(m)
        j2 = np.minimum(j + 1, len(self.m_nodes) - 1)
        tt = t[:, None]
        # Displacement interpolation: the quantiles of the offset mix linearly, and
        # m_obs = m + offset (between rows (1 - t) u_j + t u_j+1 = m, so this is the mix
        # of the rows' m_obs quantiles; beyond the end rows, their offsets unchanged).
        q = m[:, None] + (1 - tt) * self.quantiles[d, i, j] + tt * self.quantiles[d, i, j2]
        x = np.broadcast_to(np.clip(E, -_BIG, _BIG), (len(m), len(E)))
        G = _interp_rows(x, q, np.broadcast_to(self.levels, q.shape), "right")
        flo = (1 - t) * self.f_lo[d, i, j] + t * self.f_lo[d, i, j2]
        fhi = (1 - t) * self.f_hi[d, i, j] + t * self.f_hi[d, i, j2]
        p = (1.0 - flo - fhi)[:, None] * np.diff(G, axis=1)
        if E[0] == -np.inf:
            p[:, 0] += flo
        if E[-1] == np.inf:
            p[:, -1] += fhi
        return p

    def slice_table(self, m, m_obs_edges, draws=None) -> np.ndarray:
        """p(bin k | m, slice) for every usable slice at magnitudes ``m``.

        Parameters
        ----------
        m : array_like (n_m,)
            Input detection-band magnitudes [AB mag].
        m_obs_edges : array_like (n_k + 1,)
            Increasing bin edges of the measured magnitude [AB mag]; may start at -inf
            and end at +inf (the open bins' masses go there).
        draws : array_like of int, optional
            Which draws (default all).

        Returns
        -------
        ndarray (n_sel_draws, n_s, n_m, n_k)
        """
        m = np.atleast_1d(np.asarray(m, float))
        d = np.arange(self.n_draws) if draws is None else np.asarray(draws, int)
        n_s = len(self.z_nodes)
        dd, ii, mm = np.meshgrid(d, np.arange(n_s), np.arange(m.size), indexing="ij")
        p = self._rows_at(dd.ravel(), ii.ravel(), m[mm.ravel()], m_obs_edges)
        return p.reshape(len(d), n_s, m.size, -1)

    def probability(self, m_in, z, m_obs_edges) -> np.ndarray:
        """p(m_obs in bin k | m_in, z) at any input magnitude and redshift.

        Parameters
        ----------
        m_in : array_like
            Input detection-band magnitude [AB mag].
        z : array_like
            Redshift, broadcast against ``m_in``.
        m_obs_edges : array_like (n_k + 1,)
            As :meth:`slice_table`.

        Returns
        -------
        ndarray
            ``shape + (n_k,)`` for a counts' estimate, ``(n_d,) + shape + (n_k,)`` per draw.
            Rows sum to the probability of the asked-for range (1 for open ends).
        """
        m, z = np.broadcast_arrays(np.asarray(m_in, float), np.asarray(z, float))
        shape = m.shape
        m, z = m.ravel(), z.ravel()
        i, s = self._z_pairs(z)
        i2 = np.minimum(i + 1, len(self.z_nodes) - 1)
        out = []
        for d in range(self.n_draws):
            dv = np.full(m.size, d)
            p = ((1 - s)[:, None] * self._rows_at(dv, i, m, m_obs_edges)
                 + s[:, None] * self._rows_at(dv, i2, m, m_obs_edges))
            out.append(p.reshape(shape + (-1,)))
        out = np.stack(out)
        return out if self.per_draw else out[0]


def transfer_function(tm, kind: str = "selected", *, draws: bool = False,
                      min_count: int = MIN_ROW_COUNT, refine: int = REFINE,
                      n_levels: int = N_LEVELS) -> TransferFunction:
    """The interpolable transfer function of a :class:`glaciar.tables.TransferMatrix`.

    Parameters
    ----------
    tm : glaciar.tables.TransferMatrix
    kind : {"selected", "recovered"}
        Condition on the source being selected (what a luminosity function counts) or
        recovered.
    draws : bool
        Use the matrix's Dirichlet posterior draws (one distribution per draw) instead of
        the counts' estimate.  A draw's row conditional on kind is Dirichlet in its own
        right (counts + alpha): its small prior mass is spread over every m_obs bin.
    min_count : int
        Rows with fewer sources in finite m_obs bins borrow the nearest usable row's
        distribution (module docstring).
    refine : int
        Sub-bins per m_obs bin of the rows' cumulative distributions, interpolated
        monotonically (PCHIP) between the bin edges (module docstring); 1: piecewise
        uniform in the matrix's bins.
    n_levels : int
        Levels at which each row's quantile function is stored (:func:`quantile_levels`).

    Returns
    -------
    TransferFunction

    Raises
    ------
    ValueError
        A bad ``kind``, or no row with ``min_count`` sources.
    """
    if kind not in tm.kinds:
        raise ValueError(f"transfer_function: kind must be one of {tm.kinds}, not {kind!r}")
    k = tm.kinds.index(kind)
    counts = np.asarray(tm.counts[k], float)                                # (n_z, n_in, 1+n_obs)
    rows = np.asarray(tm.draws[:, k] if draws else tm.matrix[k][None], float)
    cond = rows[..., 1:]                                                   # (n_d, n_z, n_in, n_obs)
    n_fin = counts[..., 2:-1].sum(axis=-1)                                 # (n_z, n_in)
    usable = n_fin >= max(int(min_count), 1)
    zm = np.asarray(tm.z_mean, float)
    slices = np.flatnonzero(usable.any(axis=1) & np.isfinite(zm))
    if not slices.size:
        raise ValueError(f"transfer_function: no row of the transfer matrix has {min_count} "
                         f"{kind} sources with a finite measured magnitude")
    slices = slices[np.argsort(zm[slices], kind="stable")]
    u = row_magnitudes(tm.m_in_edges)
    fe = np.asarray(tm.m_obs_edges[1:-1], float)
    with np.errstate(invalid="ignore", divide="ignore"):
        tot = cond.sum(axis=-1)
        fin = cond[..., 1:-1]
        ftot = fin.sum(axis=-1)
        cdf = np.concatenate([np.zeros(fin.shape[:-1] + (1,)), np.cumsum(fin, axis=-1)],
                             axis=-1) / ftot[..., None]
        f_lo, f_hi = cond[..., 0] / tot, cond[..., -1] / tot
    cdf = np.clip(cdf, 0.0, 1.0)
    cdf[..., -1] = 1.0
    levels = quantile_levels(n_levels)
    n_s, n_in = len(slices), len(u)
    source = np.empty((n_s, n_in))
    donor = np.empty((n_s, n_in), int)
    for a, i in enumerate(slices):
        good = np.flatnonzero(usable[i])
        # Nearest usable row in input magnitude (argmin: the brighter one on a tie).
        pick = good[np.argmin(np.abs(u[good][None, :] - u[:, None]), axis=1)]
        donor[a] = pick
        source[a] = u[pick]
    take = (slice(None), slices[:, None], donor)
    out_cdf, out_lo, out_hi = cdf[take], f_lo[take], f_hi[take]
    if not (np.all(np.isfinite(out_cdf)) and np.all(np.isfinite(out_lo))
            and np.all(np.isfinite(out_hi))):
        raise ValueError("transfer_function: a usable row has no finite probabilities")
    if int(refine) > 1:
        fe, out_cdf = _refine(fe, out_cdf, int(refine))
    shape = out_cdf.shape[:-1]
    flat = out_cdf.reshape(-1, out_cdf.shape[-1])
    knots = np.broadcast_to(fe, flat.shape)
    q = _quantiles(levels, flat, knots).reshape(shape + (len(levels),))
    q = q - source[None, :, :, None]                       # offsets from the row's magnitude
    return TransferFunction(kind=kind, z_nodes=zm[slices], m_nodes=u, source=source,
                            levels=levels, quantiles=q, f_lo=out_lo, f_hi=out_hi,
                            n_sources=n_fin[slices].astype(np.int64),
                            filled=~usable[slices], per_draw=bool(draws))


def transfer_probability_muv(tf: TransferFunction, M_uv, z, m_obs_edges, sed, *,
                             cosmology=None, n_beta: int = 7, weight=None) -> np.ndarray:
    """p(m_obs in bin k | M_UV, z): the transfer function of a source of absolute magnitude M_UV.

    m_in = M_UV + K(z, beta) (:func:`glaciar.inference.products.kcorrection`,
    the map the injections used), averaged over beta ~ N(sed.beta_mean, sed.beta_sd) by
    Gauss-Hermite quadrature (``n_beta`` nodes).  Beta nodes for which the band receives
    no flux are left out (weights renormalised over the others; all zero if none has flux).

    Parameters
    ----------
    tf : TransferFunction
    M_uv : array_like (n_M,)
        Absolute UV magnitudes at rest 1600 A [AB mag].
    z : array_like (n_z,)
        Redshifts (> 0).
    m_obs_edges : array_like (n_k + 1,)
        Measured-magnitude bin edges [AB mag].
    sed : glaciar.inference.products.InjectionSED
    cosmology : astropy Cosmology or str, optional
        Default the sed's.
    n_beta : int
    weight : callable, optional
        ``weight(z, m)`` (arrays (n_z, n_M, n_beta)) multiplying each beta node's weight,
        e.g. the selection probability, to condition on the source being selected at
        every beta (then normalised over beta).

    Returns
    -------
    ndarray
        ``(n_z, n_M, n_k)`` for a counts' estimate, ``(n_d, n_z, n_M, n_k)`` per draw.
    """
    M = np.atleast_1d(np.asarray(M_uv, float))
    z = np.atleast_1d(np.asarray(z, float))
    b, w = beta_nodes(sed.beta_mean, sed.beta_sd, n_beta)
    K = kcorrection(z, b, sed.detection_filter, igm=sed.igm,
                    cosmology=sed.cosmology if cosmology is None else cosmology)   # (n_z, n_b)
    flux = np.isfinite(K)
    m = M[None, :, None] + np.where(flux, K, 0.0)[:, None, :]                     # (n_z, n_M, n_b)
    wt = np.broadcast_to(np.where(flux, w[None, :], 0.0)[:, None, :], m.shape).copy()
    if weight is not None:
        wt = wt * np.asarray(weight(np.broadcast_to(z[:, None, None], m.shape), m), float)
    norm = wt.sum(axis=-1, keepdims=True)
    wt = np.where(norm > 0, wt / np.where(norm > 0, norm, 1.0), 0.0)
    zz = np.broadcast_to(z[:, None, None], m.shape)
    p = tf.probability(m, zz, m_obs_edges)                                        # (..., n_b, n_k)
    out = np.einsum("...zmbk,zmb->...zmk", p, wt)
    return out
