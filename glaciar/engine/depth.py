"""Local depth: the limiting magnitude under every pixel of a field, from its noise map.

The depth at pixel (y, x) is the ``nsigma``-sigma limiting AB magnitude in a
circular aperture of radius ``r`` [pixels] centred on the pixel::

    m_lim = zeropoint - 2.5 log10(nsigma * sigma_ap)
    sigma_ap^2 = sum_i w_i rms_i^2

with ``w_i`` the exact fraction of pixel *i*'s area inside the disk (so
``sum w_i = pi r^2``) and ``rms`` the per-pixel noise map.  The weights enter
linearly, as for the noise of uncorrelated pixels in an aperture of area
pi r^2 (the usual ``rms * sqrt(N_pix)``); correlated (e.g. drizzled) noise
makes the true aperture noise larger, which this definition does not model.

Pixels outside the valid footprint carry no noise estimate.  The variance of
an aperture that straddles the footprint's edge is the full aperture area
times the weighted mean of rms^2 over its valid pixels, so the depth near an
edge is that of the data next to it rather than an artificially deep value;
outside the footprint the depth is NaN.

Everything here is pure numpy/scipy on arrays: no I/O.
"""
from __future__ import annotations

import math

import numpy as np

from .. import constants as C
from .blocks import row_blocks
from .classify import input_pixel

__all__ = ["disk_pixel_weights", "local_depth_map", "depth_area_histogram", "depth_at"]


def _disk_quadrant_area(x, y, r: float):
    """Area of the disk of radius ``r`` inside [0, x] x [0, y], signed like x * y.

    For x, y >= 0 (clipped at r) this is ``integral_0^x min(y, sqrt(r^2 - t^2)) dt``
    in closed form; the sign makes inclusion-exclusion over a pixel's corners
    give the area of any axis-aligned rectangle, by the disk's symmetry.
    """
    sign = np.sign(x) * np.sign(y)
    a = np.minimum(np.abs(x), r)
    b = np.minimum(np.abs(y), r)
    # Up to t0 the chord reaches above b (height b); beyond it, the circle (height sqrt(r^2 - t^2)).
    t0 = np.minimum(a, np.sqrt(np.maximum(r * r - b * b, 0.0)))

    def arc(t):   # integral_0^t sqrt(r^2 - s^2) ds
        return 0.5 * (t * np.sqrt(np.maximum(r * r - t * t, 0.0)) + r * r * np.arcsin(np.clip(t / r, -1.0, 1.0)))

    return sign * (t0 * b + arc(a) - arc(t0))


def disk_pixel_weights(radius_pix: float) -> np.ndarray:
    """Exact fraction of each pixel's area inside a disk centred on the central pixel.

    Parameters
    ----------
    radius_pix : float
        Disk radius [pixels], > 0.

    Returns
    -------
    weights : ndarray, float64, shape (2h + 1, 2h + 1), h = ceil(radius_pix - 0.5)
        Fraction in [0, 1] of each pixel (pixel *i* spans [i - 1/2, i + 1/2]
        around the centre) inside the disk; the sum is pi r^2 to rounding.
    """
    r = float(radius_pix)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"aperture radius must be a finite number of pixels > 0, got {radius_pix!r}")
    h = max(0, math.ceil(r - 0.5))
    lo = np.arange(-h, h + 1, dtype=np.float64) - 0.5
    hi = lo + 1.0
    x0, x1 = lo[None, :], hi[None, :]
    y0, y1 = lo[:, None], hi[:, None]
    w = (_disk_quadrant_area(x1, y1, r) - _disk_quadrant_area(x0, y1, r)
         - _disk_quadrant_area(x1, y0, r) + _disk_quadrant_area(x0, y0, r))
    return np.clip(w, 0.0, 1.0)


#: Pixels per row tile of :func:`local_depth_map` (~60 bytes of work arrays per tile pixel).
DEPTH_TILE_PIXELS = 1 << 21
#: Largest aperture footprint [pixels of the weight array] summed directly; larger ones by FFT.
_DIRECT_MAX_TAPS = 441


def local_depth_map(rms, valid, zeropoint: float, aperture_radius_pix: float,
                    nsigma: float = C.DEPTH_NSIGMA, tile_rows: int | None = None) -> np.ndarray:
    """Limiting magnitude in a circular aperture centred on every pixel.

    Parameters
    ----------
    rms : ndarray, shape (ny, nx)
        Per-pixel noise RMS [image units]; read only where ``valid`` (it may be
        inf or NaN elsewhere).  Any float dtype; read by row tiles (a memory map is fine).
    valid : ndarray of bool, shape (ny, nx), or None
        The footprint: pixels with data and a finite, positive RMS.  None: the
        pixels whose ``rms`` is finite and > 0.
    zeropoint : float
        AB zeropoint of the image units [mag].
    aperture_radius_pix : float
        Aperture radius [pixels].
    nsigma : float
        The limit is ``nsigma`` times the aperture noise.
    tile_rows : int, optional
        Rows per tile (default: :data:`DEPTH_TILE_PIXELS` / nx, at least 1).

    Returns
    -------
    depth : ndarray, float32, shape (ny, nx)
        ``zeropoint - 2.5 log10(nsigma * sigma_ap)`` [AB mag], with
        ``sigma_ap^2 = (sum of the aperture weights) x (weighted mean of rms^2
        over the valid pixels in the aperture)``; NaN where not ``valid``.

    Notes
    -----
    The two weighted sums are taken by row tiles that carry the aperture's
    half-width ``h`` of rows beyond them (zero beyond the image edge: no data),
    so memory is bounded by the tile, not the image.  For apertures of up to
    :data:`_DIRECT_MAX_TAPS` weights (radius <= 10 pixels) each pixel's sums are
    direct float64 sums of its own (2h + 1)^2 products, in one order: the map is
    the same bit for bit whatever the tiling, with relative rounding ~1e-15.
    Larger apertures are summed by FFT per tile (relative rounding ~1e-13 of the
    largest rms^2 of the tile).
    """
    rms_in = rms if hasattr(rms, "shape") else np.asarray(rms)
    valid_in = None if valid is None else (valid if hasattr(valid, "shape") else np.asarray(valid))
    if rms_in.ndim != 2 or (valid_in is not None and valid_in.shape != rms_in.shape):
        raise ValueError(f"rms and valid must be 2-D arrays of one shape, got {rms_in.shape} and "
                         f"{None if valid_in is None else valid_in.shape}")
    if not (float(nsigma) > 0 and math.isfinite(float(zeropoint))):
        raise ValueError(f"need nsigma > 0 and a finite zeropoint, got {nsigma!r}, {zeropoint!r}")
    w = disk_pixel_weights(aperture_radius_pix)
    h = w.shape[0] // 2
    depth = np.full(rms_in.shape, np.nan, dtype=np.float32)
    w_sum, n_bad = w.sum(), 0
    from .detect import release_mapped

    for y0, y1, a, b in row_blocks(rms_in.shape, DEPTH_TILE_PIXELS, h, rows=tile_rows):
        r = np.asarray(rms_in[a:b], dtype=np.float64)
        ok = np.isfinite(r) & (r > 0)
        v = ok if valid_in is None else np.asarray(valid_in[a:b], dtype=bool)
        # A spilled (memory-mapped) rms or footprint, read once: its pages go as the tiles
        # pass (they would pile up in the process: 1 GB at 16000^2).
        release_mapped(rms_in, valid_in)
        inner = slice(y0 - a, y1 - a)
        n_bad += int(np.count_nonzero(v[inner] & ~ok[inner]))
        if n_bad or not v[inner].any():
            continue
        var = np.where(v, r * r, 0.0)
        num = _aperture_sum(var, w)[inner]
        den = _aperture_sum(v.astype(np.float64), w)[inner]
        vi = v[inner]
        # A valid pixel has den >= its own weight (1 for r >= 1/sqrt(2)), far above rounding.
        sigma2 = w_sum * num[vi] / den[vi]
        tile = depth[y0:y1]
        tile[vi] = zeropoint - 2.5 * np.log10(float(nsigma) * np.sqrt(sigma2))
    if n_bad:
        raise ValueError(f"{n_bad} valid pixels have a non-finite or non-positive rms")
    return depth


def _aperture_sum(values: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``sum_k w_k values[p + k]`` at every pixel p (w centred), zero beyond the array.

    Beyond the array is the image edge, or rows of a tile's halo whose own sums are not used.
    """
    if w.size <= _DIRECT_MAX_TAPS:
        from scipy.ndimage import correlate

        return correlate(values, w, mode="constant", cval=0.0)
    from ..fftconv import fftconvolve     # scipy.signal's, without importing it

    # The disk is symmetric: convolution = correlation.
    return fftconvolve(values, w, mode="same")


def depth_area_histogram(depth_map, pixel_scale_arcsec: float,
                         bin_mag: float = C.DEPTH_BIN_MAG) -> tuple[np.ndarray, np.ndarray]:
    """Footprint area per bin of local depth.

    Parameters
    ----------
    depth_map : ndarray
        Local depth [AB mag], NaN outside the footprint (:func:`local_depth_map`).
    pixel_scale_arcsec : float
        Pixel scale [arcsec / pixel].
    bin_mag : float
        Bin width [mag].  Edges are integer multiples of ``bin_mag``, so the
        histograms of different fields share their edges.

    Returns
    -------
    bin_edges_mag : ndarray, float64, shape (n + 1,)
        Bin *k* is [edge_k, edge_k+1) [AB mag]; empty (shape (0,)) if the
        footprint is empty.
    area_arcmin2 : ndarray, float64, shape (n,)
        Footprint area in each bin [arcmin^2]; it sums to the number of
        finite-depth pixels times the pixel area.
    """
    if not (float(bin_mag) > 0 and float(pixel_scale_arcsec) > 0):
        raise ValueError(f"need bin_mag > 0 and pixel_scale_arcsec > 0, got {bin_mag!r}, {pixel_scale_arcsec!r}")
    d = np.asarray(depth_map, dtype=np.float64)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return np.zeros(0), np.zeros(0)
    # Counting by the integer lattice index (not by comparing with float edges) puts every
    # pixel in exactly one bin, so the areas add up to the footprint.
    k = np.floor(d / bin_mag).astype(np.int64)
    k0 = int(k.min())
    counts = np.bincount(k - k0)
    edges = (k0 + np.arange(counts.size + 1)) * float(bin_mag)
    pixel_area_arcmin2 = (float(pixel_scale_arcsec) / 60.0) ** 2
    return edges, counts * pixel_area_arcmin2


def depth_at(depth_map, x, y) -> np.ndarray:
    """Local depth at positions, from the pixel containing each one.

    Parameters
    ----------
    depth_map : ndarray, shape (ny, nx)
        Local depth [AB mag].
    x, y : array_like
        0-based pixel positions (x along axis 1, y along axis 0); pixel *i*
        spans [i - 1/2, i + 1/2], so the pixel is ``floor(v + 1/2)``.

    Returns
    -------
    ndarray, float64
        Depth [AB mag] of each position's pixel; NaN off the image.
    """
    d = np.asarray(depth_map)
    ix, iy = input_pixel(x, y)
    inside = (ix >= 0) & (ix < d.shape[1]) & (iy >= 0) & (iy < d.shape[0])
    out = np.full(ix.shape, np.nan)
    out[inside] = d[iy[inside], ix[inside]]
    return out
