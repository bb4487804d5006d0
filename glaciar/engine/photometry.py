"""Dual-mode photometry: fluxes in any band inside detection-band apertures.

All functions take whole arrays and many sources at once (sep's array calls,
``np.bincount`` over segment labels), so a batch of windows costs one call per
band and aperture type.  Fluxes are in image units of the measured band;
magnitudes are AB through the band's zeropoint.  A non-positive flux has no
magnitude (NaN), never a 99: non-detections stay fluxes.
"""
from __future__ import annotations

import numpy as np
import sep

__all__ = ["iso_photometry", "aperture_photometry", "kron_radius", "auto_photometry",
           "magnitudes", "limiting_magnitude"]

#: ln(10)/2.5, so magerr = 2.5/ln(10) * err/flux = err/(flux * _K)
_K = np.log(10.0) / 2.5


def iso_photometry(image, rms, segmap, labels, gain=None, pixels=None, noise=None):
    """Isophotal flux of detection segments measured in a band.

    Parameters
    ----------
    image : ndarray
        Background-subtracted band image (injected) [image units].
    rms : ndarray
        Per-pixel RMS of the band [image units].
    segmap : ndarray of int
        Detection-band segmentation (same shape).
    labels : array of int
        Segment labels to measure; 0 or negative -> NaN.
    gain : float or None
        Electrons per image unit for the source Poisson term; None = no term.
    pixels : ndarray of int, optional
        ``np.flatnonzero(segmap)``, to reuse across bands.
    noise : glaciar.engine.noise.CorrelatedNoise, optional
        Correlated-noise model: the background variance of a segment of N
        pixels is multiplied by ``noise.variance_factor(N)``.

    Returns
    -------
    flux, fluxerr : ndarray
        ``flux = sum(image)`` over the segment; ``fluxerr = sqrt(f(N) sum(rms^2) +
        sum(max(image, 0))/gain)`` with ``f = 1`` without a noise model.  Sums are in row-major pixel order, so the
        same segment in a cut-out and in the full frame gives bit-identical
        results.
    """
    labels = np.asarray(labels, dtype=np.int64)
    if pixels is None:
        pixels = np.flatnonzero(segmap)
    lab = np.asarray(segmap).ravel()[pixels]
    n = int(max(lab.max(initial=0), labels.max(initial=0))) + 1
    val = np.asarray(image, dtype=np.float64).ravel()[pixels]
    var = np.asarray(rms, dtype=np.float64).ravel()[pixels] ** 2
    fsum = np.bincount(lab, weights=val, minlength=n)
    vsum = np.bincount(lab, weights=var, minlength=n)
    if noise is not None:
        vsum = vsum * noise.variance_factor(np.maximum(np.bincount(lab, minlength=n), 1))
    if gain is not None:
        if not gain > 0:
            raise ValueError(f"gain must be positive or None, got {gain!r}")
        vsum = vsum + np.bincount(lab, weights=np.maximum(val, 0.0), minlength=n) / gain
    ok = labels > 0
    flux = np.full(labels.shape, np.nan)
    err = np.full(labels.shape, np.nan)
    flux[ok] = fsum[labels[ok]]
    err[ok] = np.sqrt(vsum[labels[ok]])
    return flux, err


def _f64(a):
    return np.ascontiguousarray(a, dtype=np.float64)


def _mask(m):
    return None if m is None else np.ascontiguousarray(m, dtype=bool)


def _scaled_error(err_bkg, err_total, factor):
    """Error with its background variance scaled by ``factor`` and its Poisson part kept."""
    poisson = np.maximum(np.square(err_total) - np.square(err_bkg), 0.0)
    return np.sqrt(np.square(err_bkg) * factor + poisson)


def aperture_photometry(image, rms, x, y, diameters, gain=None, mask=None, noise=None):
    """Fluxes in circular apertures (SExtractor FLUX_APER).

    Parameters
    ----------
    image, rms : ndarray
        Band image and RMS [image units].
    x, y : array
        Centres, 0-based pixel coordinates (x along numpy axis 1).
    diameters : sequence of float
        Aperture diameters [pixels] (SExtractor's PHOT_APERTURES convention).
    gain : float or None
        For the Poisson term of the error.
    mask : ndarray of bool, optional
        Pixels without data, excluded from the sums, which sep scales up by
        total/unmasked area.
    noise : glaciar.engine.noise.CorrelatedNoise, optional
        Scales the background variance of each aperture by
        ``noise.variance_factor(pi r^2)``.

    Returns
    -------
    flux, fluxerr : ndarray, shape (len(diameters), len(x))
        Sums weighted by the exact pixel/circle overlap (sep, ``subpix=0``).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    flux = np.full((len(diameters), x.size), np.nan)
    err = np.full((len(diameters), x.size), np.nan)
    if x.size == 0:
        return flux, err
    data = _f64(image)
    e = _f64(rms)
    for k, d in enumerate(diameters):
        f, fe, _ = sep.sum_circle(data, x, y, 0.5 * float(d), err=e, mask=_mask(mask),
                                  gain=gain, subpix=0)
        if noise is not None:
            fb = fe if gain is None else sep.sum_circle(data, x, y, 0.5 * float(d), err=e,
                                                        mask=_mask(mask), subpix=0)[1]
            fe = _scaled_error(fb, fe, noise.variance_factor(np.pi * (0.5 * float(d)) ** 2))
        flux[k], err[k] = f, fe
    return flux, err


def kron_radius(det_image, x, y, a, b, theta, segmap=None, seg_id=None, mask=None):
    """Kron radius (first moment within 6 isophotal radii) in units of (a, b).

    Neighbouring segments (``segmap`` != 0 and != ``seg_id``) are excluded, as
    SExtractor does.  Returns NaN where sep flags a failure.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return np.zeros(0)
    kw = {}
    if segmap is not None:
        kw = dict(segmap=np.ascontiguousarray(segmap, dtype=np.int32),
                  seg_id=np.asarray(seg_id, dtype=np.int32))
    kr, flag = sep.kron_radius(_f64(det_image), x, _f64(y), _f64(a), _f64(b), _f64(theta),
                               6.0, mask=_mask(mask), **kw)
    kr = np.asarray(kr, dtype=np.float64)
    return kr


def auto_scale(kron, autoparams):
    """AUTO aperture scale in units of (a, b): ``max(k * kron, R_min)``.

    SExtractor's PHOT_AUTOPARAMS (k, R_min): the elliptical aperture has
    semi-axes ``scale * a`` and ``scale * b``; an invalid Kron radius gives
    ``R_min``.
    """
    k, rmin = autoparams
    s = k * np.asarray(kron, dtype=np.float64)
    return np.where(np.isfinite(s) & (s > rmin), s, rmin)


def auto_photometry(image, rms, x, y, a, b, theta, scale, gain=None,
                    segmap=None, seg_id=None, mask=None, noise=None):
    """Flux in the AUTO (Kron) ellipse of semi-axes ``scale*a``, ``scale*b``.

    Pixels of other segments (``segmap``, ``seg_id``) are excluded; pixels
    flagged in ``mask`` (no data) are excluded and, as sep does, compensated
    by scaling the sum by total/unmasked area.  Pixel weights are the exact
    pixel/ellipse overlap (``subpix=0``). With a correlated-noise model
    (``noise``) the background variance is scaled by
    ``noise.variance_factor(pi a b scale^2)``.

    Returns
    -------
    flux, fluxerr : ndarray
    """
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return np.zeros(0), np.zeros(0)
    kw = {}
    if segmap is not None:
        kw = dict(segmap=np.ascontiguousarray(segmap, dtype=np.int32),
                  seg_id=np.asarray(seg_id, dtype=np.int32))
    args = (_f64(image), x, _f64(y), _f64(a), _f64(b), _f64(theta), _f64(scale))
    f, fe, _ = sep.sum_ellipse(*args, err=_f64(rms), mask=_mask(mask), gain=gain, subpix=0, **kw)
    fe = np.asarray(fe, dtype=np.float64)
    if noise is not None:
        fb = fe if gain is None else np.asarray(
            sep.sum_ellipse(*args, err=_f64(rms), mask=_mask(mask), subpix=0, **kw)[1])
        area = np.pi * np.asarray(a, float) * np.asarray(b, float) * np.asarray(scale, float) ** 2
        fe = _scaled_error(fb, fe, noise.variance_factor(area))
    return np.asarray(f, dtype=np.float64), fe


def magnitudes(flux, fluxerr, zeropoint):
    """AB magnitude, its error and S/N from a flux.

    Returns
    -------
    mag, magerr, sn : ndarray
        ``mag = zp - 2.5 log10(flux)`` and ``magerr = 2.5/ln(10) err/flux``
        for flux > 0, NaN otherwise; ``sn = flux / err``.
    """
    flux = np.asarray(flux, dtype=np.float64)
    fluxerr = np.asarray(fluxerr, dtype=np.float64)
    pos = flux > 0
    safe = np.where(pos, flux, 1.0)
    mag = np.where(pos, zeropoint - 2.5 * np.log10(safe), np.nan)
    magerr = np.where(pos, fluxerr / (safe * _K), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        sn = flux / fluxerr
    return mag, magerr, sn


def limiting_magnitude(flux, fluxerr, zeropoint):
    """Magnitude of ``max(flux, 1-sigma error)``: a 1-sigma limit for non-detections."""
    f = np.fmax(np.asarray(flux, dtype=np.float64), np.asarray(fluxerr, dtype=np.float64))
    pos = f > 0
    return np.where(pos, zeropoint - 2.5 * np.log10(np.where(pos, f, 1.0)), np.nan)
