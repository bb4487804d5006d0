"""Dual-mode photometry: fluxes in any band inside detection-band apertures.

All functions take whole arrays and many sources at once (sep's array calls,
``np.bincount`` over segment labels), so a batch of windows costs one call per
band and aperture type.  Fluxes are in image units of the measured band;
magnitudes are AB through the band's zeropoint.  A non-positive flux has no
magnitude (NaN), never a 99: non-detections stay fluxes.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import sep

__all__ = ["Ellipses", "iso_photometry", "aperture_photometry", "kron_radius", "auto_photometry",
           "sextractor_photometry", "CutoutPlan", "masked_cutout",
           "magnitudes", "limiting_magnitude"]


class Ellipses(NamedTuple):
    """AUTO (Kron) ellipses of K sources, each field an array of shape (K,) (or a scalar).

    The aperture has semi-axes ``scale * a`` and ``scale * b`` about (x, y).
    """

    x: np.ndarray          #: centre, 0-based column [pixels]
    y: np.ndarray          #: centre, 0-based row [pixels]
    a: np.ndarray          #: isophotal semi-major axis [pixels]
    b: np.ndarray          #: isophotal semi-minor axis [pixels]
    theta: np.ndarray      #: position angle [radians, counter-clockwise from +x]
    scale: np.ndarray      #: Kron factor x radius (:func:`auto_scale`) [units of a, b]

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


def _pixels(a):
    """An image for sep's aperture sums: float32 and float64 kept, anything else as float64.

    sep reads every pixel into a C ``float`` before summing, so a float32 image gives
    the very sums of its float64 copy: a writable, C-contiguous float32 or float64
    array is passed as it is (no full-frame copy, 8 bytes per pixel, for a field's
    reference photometry); another float32 one is copied as float32 (sep takes only
    writable buffers).
    """
    a = np.asarray(a)
    if a.dtype in (np.float32, np.float64) and a.dtype.isnative:
        if a.flags.c_contiguous and a.flags.writeable:
            return a
        return np.array(a, dtype=a.dtype, order="C")
    return _f64(a)


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
    data = _pixels(image)
    e = _pixels(rms)
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
    kr, flag = sep.kron_radius(_pixels(det_image), x, _f64(y), _f64(a), _f64(b), _f64(theta),
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


def auto_photometry(image, rms, ellipses: Ellipses, *, gain=None, segmap=None, seg_id=None, mask=None,
                    noise=None):
    """Flux in the AUTO (Kron) ellipse of semi-axes ``scale*a``, ``scale*b`` (``ellipses``).

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
    x, y, a, b, theta, scale = ellipses
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return np.zeros(0), np.zeros(0)
    kw = {}
    if segmap is not None:
        kw = dict(segmap=np.ascontiguousarray(segmap, dtype=np.int32),
                  seg_id=np.asarray(seg_id, dtype=np.int32))
    args = (_pixels(image), x, _f64(y), _f64(a), _f64(b), _f64(theta), _f64(scale))
    err = _pixels(rms)
    f, fe, _ = sep.sum_ellipse(*args, err=err, mask=_mask(mask), gain=gain, subpix=0, **kw)
    fe = np.asarray(fe, dtype=np.float64)
    if noise is not None:
        fb = fe if gain is None else np.asarray(
            sep.sum_ellipse(*args, err=err, mask=_mask(mask), subpix=0, **kw)[1])
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


# --------------------------------------------------------------------------
# SExtractor's BACKPHOTO_TYPE LOCAL, MASK_TYPE and SATUR_LEVEL
# --------------------------------------------------------------------------
def sextractor_background_mode(values):
    """SExtractor's background estimate of a pixel sample (``backstat`` + ``backguess``).

    The sample is clipped once to mean +- 2 sigma, then iteratively to
    median +- 3 sigma until sigma converges; the estimate is the mode
    ``2.5 median - 1.5 mean`` when ``|mean - median| < 0.3 sigma``, else the
    median (the mean when sigma is 0).  SExtractor computes the median from a
    histogram of quantised values; here it is the exact median of the
    clipped sample.

    Parameters
    ----------
    values : array
        Pixel values [image units]; non-finite values are ignored.

    Returns
    -------
    float
        Background level [image units]; 0 for an empty sample.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0
    m, s = v.mean(), v.std()
    v = v[(v >= m - 2.0 * s) & (v <= m + 2.0 * s)]
    if v.size == 0:
        return float(m)
    lo, hi, sig1 = -np.inf, np.inf, None
    mea, sig, med = v.mean(), v.std(), np.median(v)
    for _ in range(100):
        w = v[(v >= lo) & (v <= hi)]
        if w.size == 0:
            break
        mea, sig, med = w.mean(), w.std(), np.median(w)
        if sig == 0.0 or (sig1 is not None and abs(sig / sig1 - 1.0) <= 1e-4):
            break
        sig1 = sig
        lo, hi = med - 3.0 * sig, med + 3.0 * sig
    if sig == 0.0:
        return float(mea)
    return float(2.5 * med - 1.5 * mea if abs(mea - med) / sig < 0.3 else med)


def segment_boxes(pixels, labels, width, n):
    """Bounding boxes of segments from their flat pixel indices.

    Parameters
    ----------
    pixels, labels : array of int
        Flat (row-major) indices of segment pixels and their labels.
    width : int
        Row length of the array the indices refer to [pixels].
    n : int
        Number of labels (boxes are returned for labels 0 .. n-1).

    Returns
    -------
    ndarray of int, shape (n, 4)
        ``ymin, ymax, xmin, xmax`` (inclusive, SExtractor's X/YMIN, X/YMAX);
        labels without pixels get ``ymin > ymax``.
    """
    big = np.iinfo(np.int64).max // 4
    out = np.empty((n, 4), dtype=np.int64)
    out[:, 0] = out[:, 2] = big
    out[:, 1] = out[:, 3] = -big
    rows, cols = np.divmod(np.asarray(pixels, dtype=np.int64), int(width))
    lab = np.asarray(labels, dtype=np.int64)
    np.minimum.at(out[:, 0], lab, rows)
    np.maximum.at(out[:, 1], lab, rows)
    np.minimum.at(out[:, 2], lab, cols)
    np.maximum.at(out[:, 3], lab, cols)
    return out


def local_background_boxes(boxes, thick, shape):
    """SExtractor's rectangular annulus of each object (BACKPHOTO_TYPE LOCAL).

    The inner rectangle is the object's isophotal box widened by a quarter of
    its size on each side (``(size)//4``, or ``(image size - size)//4`` for an
    object larger than half the image); the outer one is the inner one
    widened by ``thick`` pixels.

    Parameters
    ----------
    boxes : ndarray of int, shape (K, 4)
        ``ymin, ymax, xmin, xmax`` (inclusive) of each object's pixels, in
        the coordinates of the image of size ``shape``.
    thick : int
        BACKPHOTO_THICK [pixels].
    shape : (int, int)
        Image size (rows, columns) [pixels].

    Returns
    -------
    inner, outer : ndarray of int, shape (K, 4)
        ``y0, y1, x0, x1`` with exclusive upper ends.
    """
    b = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    h, w = int(shape[0]), int(shape[1])
    oy = b[:, 1] - b[:, 0] + 1
    ox = b[:, 3] - b[:, 2] + 1
    ny = np.where(oy < h // 2, oy // 4, (h - oy) // 4)
    nx = np.where(ox < w // 2, ox // 4, (w - ox) // 4)
    inner = np.stack([b[:, 0] - ny, b[:, 1] + 1 + ny, b[:, 2] - nx, b[:, 3] + 1 + nx], axis=1)
    t = int(thick)
    outer = inner + np.array([-t, t, -t, t], dtype=np.int64)
    return inner, outer


def local_background(image, segmap, nodata, boxes, thick, shape=None, bounds=None):
    """Local background of each object (SExtractor's BACKPHOTO_TYPE LOCAL).

    Estimated with :func:`sextractor_background_mode` from the pixels of the
    rectangular annulus (:func:`local_background_boxes`) that belong to no
    object (``segmap == 0``) and have data; 0 when the annulus leaves the
    image (as SExtractor: its outer rectangle must lie inside, the upper
    sides at least one pixel inside) or holds no such pixel.

    Parameters
    ----------
    image : ndarray
        Background-subtracted band image [image units].
    segmap : ndarray of int
        Segmentation (0 = no object).
    nodata : ndarray of bool or None
        Pixels without data.
    boxes : ndarray of int, shape (K, 4)
        Object boxes ``ymin, ymax, xmin, xmax`` (inclusive, array coordinates).
    thick : int
        BACKPHOTO_THICK [pixels].
    shape : (int, int), optional
        Size of the whole image when ``image`` is a cut-out or a canvas of
        windows (it sets the quarter-size widening rule); default
        ``image.shape``.
    bounds : ndarray of int, shape (K, 4), optional
        ``y0, y1, x0, x1`` (array coordinates) of the part of the array that
        stands for each object's image; default the whole array.

    Returns
    -------
    ndarray, shape (K,)
        Background level to subtract per pixel [image units].
    """
    boxes = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    k = boxes.shape[0]
    out = np.zeros(k)
    if k == 0:
        return out
    img = np.asarray(image)
    if shape is None:
        shape = img.shape
    if bounds is None:
        bounds = np.tile(np.array([0, img.shape[0], 0, img.shape[1]], dtype=np.int64), (k, 1))
    bounds = np.asarray(bounds, dtype=np.int64).reshape(-1, 4)
    inner, outer = local_background_boxes(boxes, thick, shape)
    inside = ((outer[:, 0] >= bounds[:, 0]) & (outer[:, 1] < bounds[:, 1])
              & (outer[:, 2] >= bounds[:, 2]) & (outer[:, 3] < bounds[:, 3])
              & (boxes[:, 0] <= boxes[:, 1]))
    for i in np.flatnonzero(inside).tolist():
        y0, y1, x0, x1 = outer[i].tolist()
        iy0, iy1, ix0, ix1 = inner[i].tolist()
        ok = np.asarray(segmap[y0:y1, x0:x1]) == 0
        if nodata is not None:
            ok &= ~np.asarray(nodata[y0:y1, x0:x1], dtype=bool)
        ok[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0] = False
        if ok.any():
            out[i] = sextractor_background_mode(img[y0:y1, x0:x1][ok])
    return out


def masked_cutout(image, rms, segmap, seg_id, nodata, x, y, box, mask_type, bounds=None):
    """A cut-out of a band with the neighbours treated as SExtractor's MASK_TYPE.

    SExtractor gives pixels of other objects and pixels without data no
    value; before aperture and AUTO photometry they become

    * ``none``: neighbours kept; pixels without data 0;
    * ``blank``: 0 (with no variance);
    * ``correct``: the pixel symmetric about the object's centre,
      ``(int(2 x + 0.49999 - i), int(2 y + 0.49999 - j))``, with its variance,
      when that pixel is inside the image and neither a neighbour's nor
      without data; else 0 (no variance).

    Parameters
    ----------
    image, rms : ndarray
        Band image and RMS [image units].
    segmap : ndarray of int
        Segmentation; pixels != 0 and != ``seg_id`` are neighbours.
    seg_id : int
        The object's label.
    nodata : ndarray of bool or None
    x, y : float
        Object centre (0-based pixels, x along axis 1).
    box : (int, int, int, int)
        ``y0, y1, x0, x1`` of the cut-out (array coordinates, clipped to bounds).
    mask_type : {"none", "blank", "correct"}
    bounds : (int, int, int, int), optional
        ``y0, y1, x0, x1`` of the part of the array standing for the image
        (mirrored pixels outside it do not exist); default the whole array.

    Returns
    -------
    data, err : ndarray
        Cut-outs [image units] to sum without a mask.
    origin : (int, int)
        Row and column of the cut-out's first pixel in the array.
    """
    if bounds is None:
        bounds = (0, image.shape[0], 0, image.shape[1])
    by0, by1, bx0, bx1 = (int(v) for v in bounds)
    y0, y1, x0, x1 = (int(v) for v in box)
    y0, y1, x0, x1 = max(y0, by0), min(y1, by1), max(x0, bx0), min(x1, bx1)
    y1, x1 = max(y1, y0), max(x1, x0)
    data = np.array(image[y0:y1, x0:x1], dtype=np.float64)
    err = np.array(rms[y0:y1, x0:x1], dtype=np.float64)

    def invalid(ys, xs):
        bad = np.zeros(np.shape(ys), dtype=bool)
        if nodata is not None:
            bad |= np.asarray(nodata, dtype=bool)[ys, xs]
        if mask_type != "none":
            s = np.asarray(segmap)[ys, xs]
            bad |= (s != 0) & (s != seg_id)
        return bad

    # The cut-out's invalid pixels from slices (no index arrays: this runs once per object
    # and band); np.nonzero lists them in row-major order, as the mirror step expects.
    bad = np.zeros((y1 - y0, x1 - x0), dtype=bool)
    if nodata is not None:
        bad |= np.asarray(nodata[y0:y1, x0:x1], dtype=bool)
    if mask_type != "none":
        s = np.asarray(segmap[y0:y1, x0:x1])
        bad |= (s != 0) & (s != seg_id)
    if not bad.any():
        return data, err, (y0, x0)
    jb, ib = np.nonzero(bad)
    if mask_type == "correct":
        # C's (int) truncates toward zero
        x2 = np.trunc(2.0 * x + 0.49999 - (ib + x0)).astype(np.int64)
        y2 = np.trunc(2.0 * y + 0.49999 - (jb + y0)).astype(np.int64)
        ok = (x2 >= bx0) & (x2 < bx1) & (y2 >= by0) & (y2 < by1)
        ok[ok] = ~invalid(y2[ok], x2[ok])
        data[jb, ib] = 0.0
        err[jb, ib] = 0.0
        data[jb[ok], ib[ok]] = np.asarray(image)[y2[ok], x2[ok]]
        err[jb[ok], ib[ok]] = np.asarray(rms)[y2[ok], x2[ok]]
    else:
        data[jb, ib] = 0.0
        err[jb, ib] = 0.0
    return data, err, (y0, x0)


def sextractor_photometry(image, rms, segmap, labels, nodata, ellipses: Ellipses, diameters, mask_type, *,
                          gain=None, dbkg=None, bounds=None, noise=None):
    """Aperture and AUTO fluxes with neighbours treated by SExtractor's MASK_TYPE.

    Each object is measured on its own cut-out from :func:`masked_cutout`
    (the box holding its largest aperture and its AUTO ellipse), summed with
    the exact pixel/aperture overlap (sep, ``subpix=0``) and no further
    mask.  With a local background ``dbkg`` (BACKPHOTO_TYPE LOCAL) the
    flux of each aperture loses ``dbkg`` times its area inside the image,
    as SExtractor subtracts it.

    Parameters
    ----------
    image, rms : ndarray
        Band image and RMS [image units].
    segmap : ndarray of int
    labels : array of int, shape (K,)
        Each object's label in ``segmap``.
    nodata : ndarray of bool or None
    ellipses : Ellipses
        Centres [pixels], isophotal shape and AUTO scale of the K objects.
    diameters : sequence of float
        PHOT_APERTURES [pixels].
    mask_type : {"none", "blank", "correct"}
    gain : float or None
    dbkg : array, shape (K,), optional
        Local background per pixel [image units].
    bounds : ndarray of int, shape (K, 4), optional
        Part of the array standing for each object's image (y0, y1, x0, x1).
    noise : glaciar.engine.noise.CorrelatedNoise, optional

    Returns
    -------
    flux_aper, fluxerr_aper : ndarray, shape (len(diameters), K)
    flux_auto, fluxerr_auto : ndarray, shape (K,)
    """
    plan = CutoutPlan.of(segmap, labels, ellipses, diameters, mask_type, bounds=bounds,
                         shape=np.shape(image))
    return plan.measure(image, rms, nodata, gain=gain, dbkg=dbkg, noise=noise)


class CutoutPlan(NamedTuple):
    """The band-independent part of :func:`sextractor_photometry` for K objects of one
    segmentation: their cut-out boxes and which of them hold no neighbour (:meth:`of`).

    A caller measuring several bands of one extraction makes it once and calls
    :meth:`measure` per band: the same numbers as :func:`sextractor_photometry` on each.
    """

    segmap: np.ndarray
    labels: np.ndarray       #: (K,) int64
    ellipses: Ellipses       #: arrays of shape (K,), float64
    radii: np.ndarray        #: PHOT_APERTURES / 2 [pixels]
    mask_type: str
    bounds: np.ndarray       #: (K, 4) y0, y1, x0, x1
    boxes: np.ndarray        #: (K, 4) each object's cut-out (:func:`_cutout_boxes`)
    clear: np.ndarray        #: (K,) bool: cut-out inside its bounds and free of neighbours

    @classmethod
    def of(cls, segmap, labels, ellipses: Ellipses, diameters, mask_type, *, bounds=None,
           shape=None) -> "CutoutPlan":
        """Plan of :func:`sextractor_photometry`'s arguments of the same names (``shape``:
        the band arrays', default the segmentation's; used when ``bounds`` is None)."""
        x, y, a, b, theta, scale = ellipses
        x = np.atleast_1d(np.asarray(x, dtype=np.float64))
        y = np.atleast_1d(np.asarray(y, dtype=np.float64))
        k = x.size
        a, b, theta, scale = (np.broadcast_to(np.asarray(v, dtype=np.float64), (k,))
                              for v in (a, b, theta, scale))
        labels = np.broadcast_to(np.asarray(labels, dtype=np.int64), (k,))
        if bounds is None:
            ny, nx = np.shape(segmap) if shape is None else shape
            bounds = np.tile(np.array([0, ny, 0, nx]), (k, 1))
        bounds = np.asarray(bounds, dtype=np.int64).reshape(-1, 4)
        radii = np.array([0.5 * float(d) for d in diameters], dtype=np.float64)
        dya, dxa = _half_extent(a, b, theta, scale)
        boxes = _cutout_boxes(x, y, dya, dxa, float(radii.max()))
        clear = _clear_cutouts(boxes, bounds, segmap, labels, mask_type)
        return cls(segmap, labels, Ellipses(x, y, a, b, theta, scale), radii, mask_type, bounds,
                   boxes, clear)

    def measure(self, image, rms, nodata, *, gain=None, dbkg=None, noise=None):
        """Aperture and AUTO fluxes of the planned objects in one band: as
        :func:`sextractor_photometry` (same parameters and returns)."""
        segmap, labels, mask_type, bounds, boxes = (self.segmap, self.labels, self.mask_type,
                                                    self.bounds, self.boxes)
        x, y, a, b, theta, scale = self.ellipses
        radii = self.radii
        k, nd = x.size, radii.size
        dbkg = np.zeros(k) if dbkg is None else np.broadcast_to(np.asarray(dbkg, float), (k,))
        fa = np.full((nd, k), np.nan)
        fea = fa.copy()
        fau = np.full(k, np.nan)
        feau = fau.copy()
        factors = None if noise is None else [noise.variance_factor(np.pi * r * r) for r in radii]
        clean = _without_nodata(self.clear & (dbkg == 0.0), boxes, nodata)
        if clean.any():
            c = np.flatnonzero(clean)
            fa[:, c], fea[:, c], fau[c], feau[c] = _unmasked_sums(
                image, rms, x[c], y[c], a[c], b[c], theta[c], scale[c], radii, gain, noise, factors)
        for i in np.flatnonzero(~clean).tolist():
            box = tuple(boxes[i].tolist())
            d, e, (oy, ox) = masked_cutout(image, rms, segmap, int(labels[i]), nodata, x[i], y[i], box,
                                           mask_type, bounds=bounds[i])
            if d.size == 0:
                continue
            # All apertures of the object in one sep call (sep sums each (x, y, r) on its own:
            # the same numbers as one call per radius, at a fifth of the calls for 5 apertures).
            cxs, cys = np.full(nd, x[i] - ox), np.full(nd, y[i] - oy)
            f, fe, _ = sep.sum_circle(d, cxs, cys, radii, err=e, gain=gain, subpix=0)
            if noise is not None:
                fb = fe if gain is None else sep.sum_circle(d, cxs, cys, radii, err=e, subpix=0)[1]
                fe = np.array([_scaled_error(fb[j:j + 1], fe[j:j + 1], factors[j])[0] for j in range(nd)])
            one = np.ones_like(d) if dbkg[i] != 0.0 else None      # the area under each aperture
            if one is not None:
                f = f - dbkg[i] * sep.sum_circle(one, cxs, cys, radii, subpix=0)[0]
            fa[:, i], fea[:, i] = f, fe
            cx, cy = cxs[:1], cys[:1]
            args = (cx, cy, a[i:i + 1], b[i:i + 1], theta[i:i + 1], scale[i:i + 1])
            f, fe, _ = sep.sum_ellipse(d, *args, err=e, gain=gain, subpix=0)
            fe = np.asarray(fe, dtype=np.float64)
            if noise is not None:
                fb = fe if gain is None else np.asarray(sep.sum_ellipse(d, *args, err=e, subpix=0)[1])
                area = np.pi * a[i] * b[i] * scale[i] ** 2
                fe = _scaled_error(fb, fe, noise.variance_factor(area))
            if one is not None:
                f = f - dbkg[i] * sep.sum_ellipse(one, *args, subpix=0)[0]
            fau[i], feau[i] = f[0], fe[0]
        return fa, fea, fau, feau


def _cutout_boxes(x, y, dya, dxa, rap):
    """``y0, y1, x0, x1`` (array coordinates, exclusive ends) of each object's cut-out: its
    largest aperture (radius ``rap``) and AUTO ellipse (half extents ``dya``, ``dxa``) with
    a margin of 1-2 pixels, so that sep's box of either aperture lies inside it."""
    hy, hx = np.maximum(dya, rap), np.maximum(dxa, rap)
    out = np.zeros((x.size, 4), dtype=np.int64)
    ok = np.isfinite(hy) & np.isfinite(hx) & np.isfinite(x) & np.isfinite(y)
    out[ok, 0] = np.floor(y[ok] - hy[ok]).astype(np.int64) - 1
    out[ok, 1] = np.ceil(y[ok] + hy[ok]).astype(np.int64) + 2
    out[ok, 2] = np.floor(x[ok] - hx[ok]).astype(np.int64) - 1
    out[ok, 3] = np.ceil(x[ok] + hx[ok]).astype(np.int64) + 2
    out[~ok] = (0, -1, 0, -1)       # never clean: such objects take the per-object path
    return out


def _clear_cutouts(boxes, bounds, segmap, labels, mask_type) -> np.ndarray:
    """True for objects whose cut-out lies inside their bounds and holds no neighbour pixel
    that :func:`masked_cutout` would change under a MASK_TYPE other than none."""
    inside = ((boxes[:, 0] >= bounds[:, 0]) & (boxes[:, 1] <= bounds[:, 1])
              & (boxes[:, 2] >= bounds[:, 2]) & (boxes[:, 3] <= bounds[:, 3])
              & (boxes[:, 0] < boxes[:, 1]) & (boxes[:, 2] < boxes[:, 3]))
    if mask_type == "none":
        return inside
    seg = np.asarray(segmap)
    for i in np.flatnonzero(inside).tolist():
        y0, y1, x0, x1 = boxes[i].tolist()
        s = seg[y0:y1, x0:x1]
        inside[i] = not ((s != 0) & (s != labels[i])).any()
    return inside


def _without_nodata(clear, boxes, nodata) -> np.ndarray:
    """``clear`` (a new array) made False where the object's cut-out holds a pixel without
    data: with no neighbour and no such pixel, the cut-out is a plain slice of the arrays."""
    clean = np.array(clear, dtype=bool)
    if nodata is not None:
        for i in np.flatnonzero(clean).tolist():
            y0, y1, x0, x1 = boxes[i].tolist()
            clean[i] = not nodata[y0:y1, x0:x1].any()
    return clean


def _unmasked_sums(image, rms, x, y, a, b, theta, scale, radii, gain, noise, factors):
    """Aperture and AUTO sums of objects whose cut-outs need no masking, in one sep call
    per kind on the whole arrays.

    The same numbers as on each object's cut-out: sep's box of each aperture lies inside
    the cut-out (:func:`_cutout_boxes`), every pixel offset ``ix - x`` is exact in either
    frame (an integer minus a centre of the same binade or a smaller one), so the same
    pixels get the same overlaps and are summed in the same order.
    """
    nd, k = radii.size, x.size
    img = np.ascontiguousarray(image)
    err = np.ascontiguousarray(rms)
    xs, ys, rs = np.repeat(x, nd), np.repeat(y, nd), np.tile(radii, k)
    f, fe, _ = sep.sum_circle(img, xs, ys, rs, err=err, gain=gain, subpix=0)
    fe = np.asarray(fe, dtype=np.float64)
    if noise is not None:
        fb = fe if gain is None else np.asarray(sep.sum_circle(img, xs, ys, rs, err=err, subpix=0)[1])
        fe = _scaled_error(fb, fe, np.tile(np.asarray(factors, dtype=np.float64), k))
    fa, fea = np.asarray(f).reshape(k, nd).T, fe.reshape(k, nd).T
    f, feu, _ = sep.sum_ellipse(img, x, y, a, b, theta, scale, err=err, gain=gain, subpix=0)
    feu = np.asarray(feu, dtype=np.float64)
    if noise is not None:
        fb = feu if gain is None else np.asarray(
            sep.sum_ellipse(img, x, y, a, b, theta, scale, err=err, subpix=0)[1])
        # The factor per object as the per-object path computes it (scalar area).
        area_factor = np.array([noise.variance_factor(np.pi * a[i] * b[i] * scale[i] ** 2)
                                for i in range(k)], dtype=np.float64)
        feu = _scaled_error(fb, feu, area_factor)
    return fa, fea, np.asarray(f, dtype=np.float64), feu


def _half_extent(a, b, theta, r):
    c, s = np.cos(theta), np.sin(theta)
    return r * np.sqrt((a * s) ** 2 + (b * c) ** 2), r * np.sqrt((a * c) ** 2 + (b * s) ** 2)


def aperture_area(shape, x, y, diameters, a=None, b=None, theta=None, scale=None, bounds=None):
    """Area of each circular (and, with a/b/theta/scale, AUTO) aperture inside the image [pixels].

    The pixel/aperture overlap summed over the pixels of the array (or of
    ``bounds``, y0, y1, x0, x1 per object): the area times which SExtractor
    subtracts a local background from an aperture flux.

    Returns
    -------
    circle : ndarray, shape (len(diameters), K)
    ellipse : ndarray, shape (K,) or None
    """
    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    y = np.atleast_1d(np.asarray(y, dtype=np.float64))
    k = x.size
    if bounds is None:
        bounds = np.tile(np.array([0, shape[0], 0, shape[1]]), (k, 1))
    bounds = np.asarray(bounds, dtype=np.int64).reshape(-1, 4)
    circ = np.zeros((len(diameters), k))
    ell = None if a is None else np.zeros(k)
    for i in range(k):
        y0, y1, x0, x1 = bounds[i].tolist()
        one = np.ones((y1 - y0, x1 - x0))
        cx, cy = np.array([x[i] - x0]), np.array([y[i] - y0])
        for j, d in enumerate(diameters):
            circ[j, i] = sep.sum_circle(one, cx, cy, 0.5 * float(d), subpix=0)[0][0]
        if ell is not None:
            ell[i] = sep.sum_ellipse(one, cx, cy, np.atleast_1d(a)[i:i + 1], np.atleast_1d(b)[i:i + 1],
                                     np.atleast_1d(theta)[i:i + 1], np.atleast_1d(scale)[i:i + 1],
                                     subpix=0)[0][0]
    return circ, ell


def saturated(image, pixels, labels, threshold, n):
    """SExtractor's FLAGS saturation bit (value 4): the object has a pixel at SATUR_LEVEL.

    SExtractor flags an object when its peak (the largest background-
    subtracted value over its isophotal pixels in the measurement image)
    plus the background at its centre reaches SATUR_LEVEL.

    Parameters
    ----------
    image : ndarray
        Background-subtracted measurement image [image units].
    pixels, labels : array of int
        Flat indices of the segment pixels and their labels.
    threshold : array, shape (n,)
        Per label: SATUR_LEVEL minus the background at the object's centre
        [image units].
    n : int
        Number of labels.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    peak = np.full(n, -np.inf)
    np.maximum.at(peak, np.asarray(labels, dtype=np.int64),
                  np.asarray(image, dtype=np.float64).ravel()[pixels])
    return peak >= np.asarray(threshold, dtype=np.float64)
