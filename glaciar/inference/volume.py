"""The effective-volume integrals of the selection function
(:class:`~glaciar.inference.selection_function.SelectionFunction`) on arrays: pure
functions of the surface model, its posterior draws and the nodes of the integral (depth
nodes and their solid angles, redshift nodes and dV/dz/dΩ).

The selection function resolves its defaults (area, cosmology, SED, integration range)
and calls these; they touch no file and no global state.
"""
from __future__ import annotations

import numpy as np

from .products import EffectiveVolume

__all__ = ["merge_depth_nodes", "group_linearly", "volume_draws", "muv_magnitudes", "muv_volume_draws",
           "summarise_volume", "warn_if_cut", "detection_z_limit"]

#: Posterior draws evaluated at a time in V_eff(m) (memory: draws x n_z x n_m floats).
M_BATCH = 64
#: Posterior draws evaluated at a time in V_eff(M_UV).
MUV_BATCH = 256


def merge_depth_nodes(edges, area, max_nodes: int):
    """Merge an area-by-depth histogram into <= ``max_nodes`` (depth [mag], area) nodes,
    each at the area-weighted mean depth of its bins (the bins' centres where they are few).
    """
    edges, area = np.asarray(edges, float), np.asarray(area, float)
    centre = 0.5 * (edges[:-1] + edges[1:])
    keep = area > 0
    centre, area = centre[keep], area[keep]
    if len(centre) <= max_nodes:
        return centre, area
    _, means, weights = group_linearly(centre, area, max_nodes)
    return means, weights


def group_linearly(values, weights, n_max: int):
    """Group ``values`` into at most ``n_max`` equal-width bins between their extremes.

    Returns
    -------
    index : ndarray of int
        Each value's group, numbered 0.. over the non-empty bins in increasing order.
    means, totals : ndarray
        Per group: the weighted mean of its values and the sum of its weights.
    """
    values, weights = np.asarray(values, float), np.asarray(weights, float)
    lo, hi = float(values.min()), float(values.max())
    k = (np.zeros(values.size, np.int64) if hi <= lo else
         np.minimum(((values - lo) / (hi - lo) * n_max).astype(np.int64), n_max - 1))
    _, index = np.unique(k, return_inverse=True)
    totals = np.bincount(index, weights=weights)
    return index, np.bincount(index, weights=weights * values) / totals, totals


def volume_draws(model, draws, nodes, node_sr, zz, dvdz, mm):
    """V_eff(m) per posterior draw, and the median C*S at the ends of the z range.

    Parameters
    ----------
    model : SurfaceModel
    draws : ndarray, shape (n_draws, n_params)
    nodes, node_sr : ndarray
        Depth nodes [mag] and their solid angles [sr].
    zz : ndarray
        Simpson nodes in redshift (odd count).
    dvdz : ndarray
        dV/dz/dΩ at ``zz`` [Mpc^3 / sr].
    mm : ndarray, 1-d
        Input magnitudes [mag].

    Returns
    -------
    out : ndarray, shape (n_draws, len(mm))
        V_eff [Mpc^3].
    ends : ndarray, shape (3, len(mm))
        Area-weighted median C*S of the first draws (``M_BATCH``) at the low and high z
        end and at its peak in z (for the warning that V_eff misses volume).
    """
    from scipy.integrate import simpson

    n_draws = len(draws)
    out = np.zeros((n_draws, mm.size))
    ends = np.zeros((3, mm.size))
    for dj, sr in zip(nodes, node_sr):
        mrel = model.relative_magnitude(mm, dj)
        for i in range(0, n_draws, M_BATCH):
            c, s = model.surfaces_on_grid(draws[i:i + M_BATCH], zz, mrel)
            out[i:i + M_BATCH] += simpson(c * s * dvdz[None, :, None], x=zz, axis=1) * sr
            if i == 0:
                p = np.median(c * s, axis=0)                          # (n_z, n_m)
                ends += sr * np.stack([p[0], p[-1], p.max(axis=0)])
    return out, ends


def muv_magnitudes(MM, K, k0, mag_range):
    """Apparent magnitudes of absolute magnitudes ``MM`` through the K-corrections.

    Parameters
    ----------
    MM : ndarray, 1-d
        M_UV [AB mag].
    K : ndarray, shape (n_z, n_beta)
        m_det - M_UV per redshift and UV slope [mag]; not finite where the band
        receives no flux.
    k0 : ndarray, shape (n_z,)
        The same at the central slope [mag].
    mag_range : (float, float) or None
        The simulated magnitude range [mag], if recorded.

    Returns
    -------
    m : ndarray, shape (n_z, n_beta, n_M)
        Apparent magnitudes (0 where there is no flux).
    flux : ndarray of bool, shape (n_z, n_beta, 1)
        Where the band receives flux.
    ext : ndarray of bool, shape (n_z, n_M)
        Where the central slope's magnitude is outside ``mag_range`` (extrapolated).
    """
    flux = np.isfinite(K)[:, :, None]
    m = np.where(flux, MM[None, None, :] + np.where(np.isfinite(K), K, 0.0)[:, :, None], 0.0)
    if mag_range is not None:
        lo, hi = mag_range
        tol = 1e-9 * max(1.0, abs(hi))
        mc = MM[None, :] + k0[:, None]
        ext = np.isfinite(mc) & ((mc < lo - tol) | (mc > hi + tol))
    else:
        ext = np.zeros((len(k0), MM.size), bool)
    return m, flux, ext


def muv_volume_draws(model, draws, nodes, node_sr, zz, dvdz, m, flux, bw, ext, tolerance):
    """V_eff(M_UV) per posterior draw, averaged over the UV slope.

    Parameters
    ----------
    model, draws, nodes, node_sr, zz, dvdz
        As :func:`volume_draws`.
    m, flux, ext
        From :func:`muv_magnitudes`.
    bw : ndarray, shape (n_beta,)
        Weights of the slope nodes (sum 1).
    tolerance : float or None
        NaN for an M_UV drawing more than this fraction of its median V_eff from
        extrapolated magnitudes (``ext``); None keeps the extrapolation.

    Returns
    -------
    ndarray, shape (n_draws, n_M)
        V_eff [Mpc^3].
    """
    from scipy.integrate import simpson

    n_draws, n_b, n_m = len(draws), m.shape[1], m.shape[2]
    out = np.zeros((n_draws, n_m))
    out_ext = np.zeros_like(out)
    for i in range(0, n_draws, MUV_BATCH):
        th = draws[i:i + MUV_BATCH]
        p = np.zeros((len(th), len(zz), n_m))
        for dj, sr in zip(nodes, node_sr):
            mrel = model.relative_magnitude(m, dj if model.depth_aware else None)
            # One z at a time on the grid path (z terms once per z): ~40x faster than
            # evaluating every (z, beta, M) point on its own.
            for iz in range(len(zz)):
                c, sel = model.surfaces_on_grid(th, zz[iz:iz + 1], mrel[iz].ravel())
                pz = (c * sel)[:, 0].reshape(len(th), n_b, n_m)
                p[:, iz] += sr * np.einsum("dbm,b->dm", np.where(flux[iz][None], pz, 0.0), bw)
        out[i:i + MUV_BATCH] = simpson(p * dvdz[None, :, None], x=zz, axis=1)
        if ext.any():
            out_ext[i:i + MUV_BATCH] = simpson(np.where(ext[None], p, 0.0) * dvdz[None, :, None],
                                               x=zz, axis=1)
    if tolerance is not None and ext.any():
        tot, part = np.median(out, axis=0), np.median(out_ext, axis=0)
        # 0 of 0 (no volume at all): nothing extrapolated matters.
        frac = np.where(tot > 0, part / np.where(tot > 0, tot, 1.0), 0.0)
        out[:, ~(frac <= tolerance) & ext.any(axis=0)] = np.nan
    return out


def summarise_volume(out, interval: float) -> EffectiveVolume:
    """:class:`EffectiveVolume` of V_eff draws ``out`` [Mpc^3]: median and central interval."""
    import astropy.units as u

    lo, hi = 0.5 - 0.5 * interval, 0.5 + 0.5 * interval
    q = np.quantile(out, [0.5, lo, hi], axis=0)
    unit = u.Mpc ** 3
    return EffectiveVolume(median=q[0] * unit, lower=q[1] * unit, upper=q[2] * unit,
                           draws=out * unit)


def warn_if_cut(ends, z_range, top_is_physical: bool, mm) -> None:
    """Warn that V_eff misses volume where C*S is not ~0 at an end of the simulated z range.

    ``ends`` as :func:`volume_draws` returns it; a top that reaches the z where the
    detection band receives no flux (``top_is_physical``) selects nothing beyond it,
    whatever the surface extrapolates.
    """
    top = np.zeros_like(ends[1]) if top_is_physical else ends[1]
    worst = np.maximum(ends[0], top)
    cut = (ends[2] > 0) & (worst > 0.05 * ends[2])
    if cut.any():
        import warnings
        warnings.warn(f"effective_volume: C*S is still {np.max(worst[cut] / ends[2][cut]):.0%} "
                      f"of its peak at an end of the simulated z range {z_range[0]:g}-"
                      f"{z_range[1]:g} (m = {mm[cut][0]:g}...): V_eff misses the volume beyond it",
                      stacklevel=3)


def detection_z_limit(sed, lo_z: float, hi_z: float, z_stop: float = 30.0):
    """Lowest redshift [to 0.005] at which the detection band receives no flux from a source
    of the central beta of ``sed`` (an InjectionSED), searched from the range [lo_z, hi_z]
    upward to ``z_stop``; None when it receives flux up to there.  ``lo_z`` itself when the
    band already receives none there."""
    from ..galaxy.population import get_cosmology
    from .products import band_colour

    cosmo = get_cosmology(sed.cosmology)

    def flux(z):
        return bool(np.isfinite(band_colour(z, np.array([sed.beta_mean]), sed.detection_filter,
                                            sed.igm, cosmo)).all())

    if flux(hi_z):
        lo, hi = hi_z, hi_z + 0.25
        while flux(hi):
            lo, hi = hi, hi + 0.25
            if hi > z_stop:
                return None
    elif not flux(lo_z):
        return float(lo_z)
    else:
        lo, hi = lo_z, hi_z
    while hi - lo > 0.005:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if flux(mid) else (lo, mid)
    return round(hi, 3)
