"""The embedded demo survey: a synthetic 4-band BoRG-like field, written as FITS plus a config.

``glaciar demo`` needs no downloads.  :func:`make_demo_images` builds, in
memory and in a few seconds, one HST WFC3 pure-parallel-like pointing in the
four BoRG[z8] bands (F160W detection, F098M, F125W, F606W; Carrasco et al.
2018, Sect. 4) drizzled to 0.08"/px, and :func:`build_demo_survey` writes it
to disk with a configuration following ``docs/config-schema.yaml``.

What is in the field
--------------------
* **Noise.** Drizzle-like correlated noise: white Gaussian noise convolved
  with the separable overlap kernel of a square drop (side pixfrac x native
  pixel) with the output pixel, normalised so that the *per-pixel* variance
  is exactly ``1 / weight``.  As in real drizzled data the noise in an
  aperture is then larger than ``rms_pixel * sqrt(N_pix)`` (by 1.39x in an
  r = 0.2" aperture for the IR bands at pixfrac 0.8, 0.128" -> 0.08"); F606W (UVIS, 0.04" -> 0.08")
  drops are smaller than an output pixel, so its noise is white.
* **Weights.** Inverse variance maps built from a relative-exposure map: a
  smooth exposure gradient, three dithered exposures of a tilted detector
  footprint (so 1/3 and 2/3 depth along the edges and zero weight -- and
  science = 0 -- in the corners and border where there are no data), two
  slightly shallower IR "blob" patches and, in F606W, a half-depth chip-gap
  stripe.
* **Depths.** ``DEMO_BANDS_SPEC[band].depth_5sigma``: total AB magnitude of
  a point source whose flux inside an r = 0.2" circular aperture is 5 times
  the (correlated) aperture noise, at relative exposure 1 (BoRG quotes this
  quantity; typical 26.7 in F160W, Carrasco et al. 2018 Sect. 4).
  F160W 26.7, F125W 26.8, F098M 26.5, F606W 27.0.
* **Sources.** Background galaxies with dN/dm ~ 10^(0.3 m) in 19 < H < 25,
  flattening to 10^(0.15 m) for 25 < H < 29 (deep near-IR counts); 250 per
  arcmin^2 by default (not confusion-limited; ~65 per arcmin^2 at H < 26, about
  half of a real deep field), Sersic n 0.5-4 tied to three SED types (blue
  star-forming, dusty/intermediate, passive red) that set the colours, sizes from a magnitude-size relation with 0.2 dex scatter,
  random axis ratio and position angle; plus a few stars (two bright).  Each
  band is convolved with its own Moffat (beta = 2.5) PSF.  Source Poisson
  noise uses the band's exposure time (the config's ``gain``).
* **PSF files** are written at a different pixel scale from the images
  (IR at 0.13"/px like Tiny Tim, F606W at 0.04"/px) with a ``PIXSCALE``
  header, so the pipeline exercises PSF resampling.

Conventions: pixel ``(iy, ix)`` covers ``[ix - 1/2, ix + 1/2] x [iy - 1/2,
iy + 1/2]`` (0-based, as :mod:`glaciar.galaxy.psf`); image units are
electrons / s; position angles are counter-clockwise from the +x pixel axis;
``r_eff`` is the half-light semi-major axis.
"""
from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .constants import COL_AXIS_RATIO, COL_PA, COL_R_EFF_ARCSEC, COL_R_EFF_PIX, COL_SERSIC_N, COL_X, COL_Y

__all__ = ["DEMO_FIELD", "DEMO_BANDS", "DEMO_BANDS_SPEC", "DEMO_CONFIG_NAME", "DemoBand",
           "drizzle_noise_kernel", "make_demo_images", "build_demo_survey"]

DEMO_FIELD = "demo01"
DEMO_BANDS = ("f160w", "f098m", "f125w", "f606w")
DEMO_CONFIG_NAME = "demo.yaml"
DEMO_PIXEL_SCALE_ARCSEC = 0.08
DEMO_MOFFAT_BETA = 2.5
DEPTH_APERTURE_RADIUS_ARCSEC = 0.2

# An arbitrary high-latitude pointing; only there so the images carry a real celestial WCS.
_CRVAL_DEG = (219.21135, 50.72650)


@dataclass(frozen=True)
class DemoBand:
    """One band of the demo survey.

    Attributes
    ----------
    filter : str
        Built-in filter-curve name.
    zeropoint : float
        AB zeropoint of the image units (electrons / s).
    depth_5sigma : float
        5-sigma total point-source AB limit in an r = 0.2" aperture, at relative exposure 1.
    psf_fwhm_arcsec : float
        FWHM of the Moffat (beta = 2.5) PSF [arcsec].
    psf_pixel_scale_arcsec : float
        Pixel scale of the PSF file [arcsec / pixel] (differs from the image on purpose).
    psf_size : int
        Side of the PSF file array [pixels, odd].
    exptime_s : float
        Exposure time [s]: electrons per image unit, written as the config's ``gain``.
    native_pixel_arcsec : float
        Detector pixel scale [arcsec], sets the drizzle drop size.
    pixfrac : float
        Drizzle pixfrac (drop side / native pixel side).
    """

    filter: str
    zeropoint: float
    depth_5sigma: float
    psf_fwhm_arcsec: float
    psf_pixel_scale_arcsec: float
    psf_size: int
    exptime_s: float
    native_pixel_arcsec: float
    pixfrac: float


DEMO_BANDS_SPEC: dict[str, DemoBand] = {
    "f160w": DemoBand("wfc3_ir_f160w", 25.946, 26.7, 0.20, 0.13, 47, 2800.0, 0.1283, 0.8),
    "f098m": DemoBand("wfc3_ir_f098m", 25.667, 26.5, 0.18, 0.13, 47, 4200.0, 0.1283, 0.8),
    "f125w": DemoBand("wfc3_ir_f125w", 26.230, 26.8, 0.19, 0.13, 47, 2600.0, 0.1283, 0.8),
    "f606w": DemoBand("wfc3_uvis_f606w", 26.08, 27.0, 0.10, 0.04, 101, 3200.0, 0.0396, 0.8),
}

# SED types of the background population: (fraction, m_band - m_F160W per band,
# Sersic-n range, axis-ratio range, size offset [dex]).  Blue star-forming galaxies are
# nearly flat in f_nu, so they are bright in F606W -- they are what the optical veto of a
# dropout selection has to reject.
_SED_TYPES = (
    ("sf_blue", 0.55, {"f098m": 0.10, "f125w": 0.05, "f606w": 0.35}, (0.5, 1.5), (0.2, 1.0), 0.0),
    ("sf_dusty", 0.30, {"f098m": 0.45, "f125w": 0.20, "f606w": 1.20}, (1.0, 2.5), (0.3, 1.0), 0.0),
    ("passive", 0.15, {"f098m": 1.00, "f125w": 0.40, "f606w": 2.60}, (2.5, 4.0), (0.5, 1.0), -0.1),
)
_COLOUR_SCATTER_MAG = 0.15
_MAG_RANGE_F160W = (19.0, 29.0)
_COUNT_SLOPE_BRIGHT = 0.3          # dN/dm ~ 10^(0.3 m) for H < 25 ...
_COUNT_SLOPE_FAINT = 0.15          # ... and ~ 10^(0.15 m) for H > 25
_COUNT_BREAK_MAG = 25.0
_MAX_DENSITY_ARCMIN2 = 400.0       # beyond this the field becomes confusion-limited
_SUPERSAMPLE = 4
_TRUNCATION_R_EFF = 5.0
_RENDER_PSF_SIZE = 61              # 4.9": encloses all but ~4e-4 of an IR beta=2.5 Moffat


# --------------------------------------------------------------------------
# Noise
# --------------------------------------------------------------------------
def _drizzle_kernel_1d(native_pixel_arcsec: float, pixfrac: float,
                       pixel_scale_arcsec: float) -> np.ndarray:
    """1-D factor of :func:`drizzle_noise_kernel`, normalised to unit sum of squares."""
    if not (native_pixel_arcsec > 0 and pixel_scale_arcsec > 0 and 0 < pixfrac <= 1):
        raise ValueError("drizzle noise kernel needs native_pixel_arcsec > 0, pixel_scale_arcsec > 0 "
                         f"and 0 < pixfrac <= 1, got {native_pixel_arcsec}, {pixel_scale_arcsec}, "
                         f"{pixfrac}")
    drop = pixfrac * native_pixel_arcsec / pixel_scale_arcsec
    m = int(math.ceil(0.5 * drop + 0.5))
    k = np.arange(-m, m + 1, dtype=np.float64)
    overlap = np.clip(np.minimum(k + 0.5 * drop, 0.5) - np.maximum(k - 0.5 * drop, -0.5), 0.0, None)
    overlap = overlap[overlap > 0]          # symmetric, so the centre stays in the middle
    return overlap / math.sqrt(np.sum(overlap ** 2))


def drizzle_noise_kernel(native_pixel_arcsec: float, pixfrac: float,
                         pixel_scale_arcsec: float = DEMO_PIXEL_SCALE_ARCSEC) -> np.ndarray:
    """Kernel that turns white noise into drizzle-like correlated noise.

    Each output pixel receives a drop of side ``d = pixfrac * native / output``
    [output pixels]; the 1-D weight of a drop centred ``k`` pixels away is its
    overlap length with the output pixel.  The 2-D kernel is the outer product,
    normalised so that the sum of its squares is 1: convolving unit white noise
    with it gives unit per-pixel variance with neighbour correlations like
    drizzled data (0.27 for the WFC3/IR defaults; none when ``d <= 1``, e.g.
    UVIS 0.04" -> 0.08").

    Parameters
    ----------
    native_pixel_arcsec : float
        Detector pixel scale [arcsec].
    pixfrac : float
        Drizzle pixfrac (0 < pixfrac <= 1).
    pixel_scale_arcsec : float
        Output (drizzled) pixel scale [arcsec].

    Returns
    -------
    kernel : ndarray, float64, shape (2m + 1, 2m + 1), with ``sum(kernel**2) == 1``.
    """
    k1 = _drizzle_kernel_1d(native_pixel_arcsec, pixfrac, pixel_scale_arcsec)
    return np.outer(k1, k1)


def _correlated_unit_noise(rng: np.random.Generator, shape: tuple[int, int],
                           kernel_1d: np.ndarray) -> np.ndarray:
    """Unit-variance correlated noise: white noise convolved with ``outer(kernel_1d, kernel_1d)``.

    The convolution wraps around the image edges so the noise is exactly
    stationary (a reflecting edge would change the variance of border pixels).
    """
    from scipy.ndimage import convolve1d

    white = rng.standard_normal(shape)
    return convolve1d(convolve1d(white, kernel_1d, axis=0, mode="wrap"), kernel_1d, axis=1,
                      mode="wrap")


def _aperture_weights(radius_pix: float, supersample: int = 15) -> np.ndarray:
    """Fraction of each pixel inside a centred circle (``supersample^2`` sub-pixels per pixel)."""
    half = int(math.ceil(radius_pix))
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    c = (np.arange(-half, half + 1)[:, None] + sub[None, :]).ravel()
    inside = (c[:, None] ** 2 + c[None, :] ** 2) <= radius_pix ** 2
    n = 2 * half + 1
    return inside.reshape(n, supersample, n, supersample).mean(axis=(1, 3))


def _pixel_rms_for_depth(band: DemoBand, psf_image: np.ndarray, kernel: np.ndarray,
                         pixel_scale_arcsec: float) -> float:
    """Per-pixel noise RMS [e-/s] that gives ``band.depth_5sigma``.

    For noise ``sigma * (K * white)`` the sum over aperture weights ``A`` has
    variance ``sigma^2 * sum((A corr K)^2)`` exactly, which includes the
    drizzle correlation.  The point-source aperture flux is ``EE * F`` with EE
    the PSF's encircled energy in the same aperture.
    """
    from scipy.signal import correlate

    aperture = _aperture_weights(DEPTH_APERTURE_RADIUS_ARCSEC / pixel_scale_arcsec)
    noise_factor = math.sqrt(np.sum(correlate(aperture, kernel, mode="full") ** 2))
    ny, nx = psf_image.shape
    h = aperture.shape[0] // 2
    encircled = float(np.sum(psf_image[ny // 2 - h:ny // 2 + h + 1, nx // 2 - h:nx // 2 + h + 1]
                             * aperture))
    total_flux = 10.0 ** (-0.4 * (band.depth_5sigma - band.zeropoint))
    return encircled * total_flux / 5.0 / noise_factor


# --------------------------------------------------------------------------
# Exposure and footprint
# --------------------------------------------------------------------------
_TILT_DEG = 4.0          # detector footprint tilted against the north-up drizzle grid


def _coverage(shape: tuple[int, int]) -> np.ndarray:
    """Fraction of the three dithered exposures covering each pixel (0, 1/3, 2/3, 1)."""
    ny, nx = shape
    yy = np.arange(ny, dtype=np.float64)[:, None] - 0.5 * (ny - 1)
    xx = np.arange(nx, dtype=np.float64)[None, :] - 0.5 * (nx - 1)
    c, s = math.cos(math.radians(_TILT_DEG)), math.sin(math.radians(_TILT_DEG))
    dither = 0.015 * np.array([[0.0, 0.0], [1.0, 0.5], [-0.5, 1.0]]) * min(ny, nx)
    margin = 0.01 * min(ny, nx)
    # Half sides such that every tilted exposure fits inside the image with the margin.
    half_x = (0.5 * nx - margin - np.abs(dither[:, 0]).max()) / (c + s)
    half_y = (0.5 * ny - margin - np.abs(dither[:, 1]).max()) / (c + s)
    coverage = np.zeros(shape)
    for dx, dy in dither:
        u = (xx - dx) * c + (yy - dy) * s
        v = -(xx - dx) * s + (yy - dy) * c
        coverage += (np.abs(u) <= half_x) & (np.abs(v) <= half_y)
    return coverage / len(dither)


def _relative_exposure(coverage: np.ndarray, band: str) -> np.ndarray:
    """Relative exposure map of ``band`` (1 = the nominal depth; 0 = no data), deterministic."""
    ny, nx = coverage.shape
    yy = np.arange(ny, dtype=np.float64)[:, None] - 0.5 * (ny - 1)
    xx = np.arange(nx, dtype=np.float64)[None, :] - 0.5 * (nx - 1)
    # Smooth exposure gradient (flat-field / pixel-area / pointing differences), +-~12 %.
    xh, yh = xx / (0.5 * nx), yy / (0.5 * ny)
    tilt = {"f160w": (0.12, -0.08), "f098m": (-0.10, 0.06), "f125w": (0.08, 0.10),
            "f606w": (-0.06, -0.12)}[band]
    exposure = coverage * (1.0 + tilt[0] * xh + tilt[1] * yh + 0.04 * (xh ** 2 + yh ** 2 - 2.0 / 3.0))
    if band == "f606w":
        # UVIS chip gap, partly filled by the dithers: a half-depth stripe across the field.
        c, s = math.cos(math.radians(_TILT_DEG)), math.sin(math.radians(_TILT_DEG))
        v = -xx * s + yy * c
        exposure *= np.where(np.abs(v - 0.12 * ny) <= 0.02 * ny, 0.5, 1.0)
    else:
        # IR "blobs": small patches of lowered sensitivity.
        for fy, fx in ((-0.20, 0.20), (0.22, -0.15)):
            blob = (yy - fy * ny) ** 2 + (xx - fx * nx) ** 2 <= (0.03 * min(ny, nx)) ** 2
            exposure = np.where(blob, 0.8 * exposure, exposure)
    return exposure


# --------------------------------------------------------------------------
# Sources
# --------------------------------------------------------------------------
def _sample_counts_magnitudes(rng: np.random.Generator, n: int) -> np.ndarray:
    """F160W magnitudes from the broken power-law counts on [19, 29] (exact inverse CDF).

    dN/dm ~ 10^(0.3 m) up to H = 25 and ~ 10^(0.15 m) beyond, continuous at the
    break: the flattening of deep near-IR counts.  A single 0.3 slope normalised
    to a non-confused total would leave 3-4x too few galaxies at the magnitudes
    that are detected (H < 27), hence too little blending with real sources.
    """
    lo, hi = _MAG_RANGE_F160W
    a1, a2 = _COUNT_SLOPE_BRIGHT * math.log(10.0), _COUNT_SLOPE_FAINT * math.log(10.0)
    # Counts per magnitude are exp(a1 (m - mb)) below the break, exp(a2 (m - mb)) above.
    n1 = (1.0 - math.exp(-a1 * (_COUNT_BREAK_MAG - lo))) / a1
    n2 = (math.exp(a2 * (hi - _COUNT_BREAK_MAG)) - 1.0) / a2
    u = rng.uniform(size=n) * (n1 + n2)
    bright = u < n1
    mag = np.empty(n)
    mag[bright] = _COUNT_BREAK_MAG + np.log(np.exp(-a1 * (_COUNT_BREAK_MAG - lo)) + a1 * u[bright]) / a1
    mag[~bright] = _COUNT_BREAK_MAG + np.log1p(a2 * (u[~bright] - n1)) / a2
    return mag


def _draw_population(rng: np.random.Generator, footprint: np.ndarray, n_galaxies: int,
                     n_stars: int, pixel_scale_arcsec: float):
    """Catalogue of the injected real population (galaxies first, then stars)."""
    from astropy.table import Table

    fy, fx = np.nonzero(footprint)
    if fy.size == 0:
        raise ValueError("demo field has an empty footprint; use a larger shape")
    # Galaxies: uniform inside the footprint, continuous sub-pixel positions.
    pick = rng.integers(0, fy.size, size=n_galaxies)
    gx = fx[pick] + rng.uniform(-0.5, 0.5, size=n_galaxies)
    gy = fy[pick] + rng.uniform(-0.5, 0.5, size=n_galaxies)
    mag_h = _sample_counts_magnitudes(rng, n_galaxies)
    fractions = np.array([t[1] for t in _SED_TYPES])
    sed = rng.choice(len(_SED_TYPES), size=n_galaxies, p=fractions / fractions.sum())
    sersic_n = np.empty(n_galaxies)
    q = np.empty(n_galaxies)
    size_offset = np.empty(n_galaxies)
    mags = {"f160w": mag_h}
    for b in DEMO_BANDS[1:]:
        mags[b] = np.empty(n_galaxies)
    for k, (_, _, colours, n_range, q_range, dlogr) in enumerate(_SED_TYPES):
        sel = sed == k
        m = int(sel.sum())
        sersic_n[sel] = rng.uniform(*n_range, size=m)
        q[sel] = rng.uniform(*q_range, size=m)
        size_offset[sel] = dlogr
        for b in DEMO_BANDS[1:]:
            mags[b][sel] = mag_h[sel] + colours[b] + rng.normal(0.0, _COLOUR_SCATTER_MAG, size=m)
    # Magnitude-size relation: r_e = 0.28" at H = 24, shrinking by 0.08 dex per magnitude,
    # 0.2 dex log-normal scatter (roughly the CANDELS H-band relation of faint galaxies).
    log_re = -0.55 - 0.08 * (mag_h - 24.0) + size_offset + rng.normal(0.0, 0.2, size=n_galaxies)
    r_eff_arcsec = np.clip(10.0 ** log_re, 0.04, 1.5)
    pa = rng.uniform(0.0, 180.0, size=n_galaxies)

    # Stars: on pixel centres (so a star is exactly the PSF sampled on the grid), the first
    # two bright, the rest faint; colours of G-M dwarfs.
    keep = np.flatnonzero((fy > 2) & (fx > 2))
    pick = rng.choice(keep, size=n_stars, replace=False) if n_stars else np.zeros(0, int)
    sx, sy = fx[pick].astype(float), fy[pick].astype(float)
    n_bright = min(2, n_stars)
    star_h = np.concatenate([rng.uniform(18.0, 19.5, n_bright), rng.uniform(20.0, 24.5, n_stars - n_bright)])
    v_minus_h = rng.uniform(0.6, 2.5, n_stars)
    star_mags = {"f160w": star_h, "f098m": star_h + 0.1 + 0.2 * v_minus_h,
                 "f125w": star_h + 0.05 + 0.1 * v_minus_h, "f606w": star_h + v_minus_h}

    ntot = n_galaxies + n_stars
    table = Table()
    table["id"] = np.arange(1, ntot + 1)
    table[COL_X] = np.concatenate([gx, sx])
    table[COL_Y] = np.concatenate([gy, sy])
    for b in DEMO_BANDS:
        table[f"mag_{b}"] = np.concatenate([mags[b], star_mags[b]])
    table[COL_R_EFF_ARCSEC] = np.concatenate([r_eff_arcsec, np.zeros(n_stars)])
    table[COL_R_EFF_PIX] = table[COL_R_EFF_ARCSEC] / pixel_scale_arcsec
    table[COL_SERSIC_N] = np.concatenate([sersic_n, np.full(n_stars, np.nan)])
    table[COL_AXIS_RATIO] = np.concatenate([q, np.ones(n_stars)])
    table[COL_PA] = np.concatenate([pa, np.zeros(n_stars)])
    table["is_star"] = np.concatenate([np.zeros(n_galaxies, bool), np.ones(n_stars, bool)])
    table["sed_type"] = [_SED_TYPES[k][0] for k in sed] + ["star"] * n_stars
    return table


def _sersic_stamp_fast(x: float, y: float, r_eff_pix: float, n: float, q: float, pa_deg: float,
                       shape: tuple[int, int]):
    """Unit-flux Sersic stamp for the *background scene*, clipped to the image.

    Scene realism, not injection accuracy, is the goal here: a 4x4 supersampled
    analytic profile on the pixel grid, truncated at 5 r_e and normalised to
    unit sum over the truncated profile (so the catalogue flux is all inside
    5 r_e; for n = 4 the untruncated profile would have ~15 % outside).  Errors
    are ~10 % on the central pixel of sub-pixel galaxies.  Injected sources use
    :mod:`glaciar.galaxy.sersic`, which integrates the profile accurately.

    Returns
    -------
    (y0, x0, stamp) or None if the stamp misses the image.
    """
    from scipy.special import gammaincinv

    b_n = gammaincinv(2.0 * n, 0.5)
    r_max = _TRUNCATION_R_EFF * r_eff_pix
    half = max(2, int(math.ceil(r_max + 1.0)))
    ix, iy = int(round(x)), int(round(y))
    ss = _SUPERSAMPLE
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    gx = (np.arange(ix - half, ix + half + 1)[:, None] + sub[None, :]).ravel() - x
    gy = (np.arange(iy - half, iy + half + 1)[:, None] + sub[None, :]).ravel() - y
    c, s = math.cos(math.radians(pa_deg)), math.sin(math.radians(pa_deg))
    u = gx[None, :] * c + gy[:, None] * s
    v = -gx[None, :] * s + gy[:, None] * c
    r = np.sqrt(u ** 2 + (v / q) ** 2)
    img = np.where(r <= r_max, np.exp(-b_n * (r / r_eff_pix) ** (1.0 / n)), 0.0)
    size = 2 * half + 1
    img = img.reshape(size, ss, size, ss).sum(axis=(1, 3))
    img /= img.sum()
    ny, nx = shape
    y0, x0 = iy - half, ix - half
    ya, xa = max(y0, 0), max(x0, 0)
    yb, xb = min(y0 + size, ny), min(x0 + size, nx)
    if ya >= yb or xa >= xb:
        return None
    return ya, xa, img[ya - y0:yb - y0, xa - x0:xb - x0]


# --------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------
def make_demo_images(shape: tuple[int, int] = (1000, 1000), *, seed: int = 2018,
                     pixel_scale_arcsec: float = DEMO_PIXEL_SCALE_ARCSEC,
                     source_density_arcmin2: float = 250.0, n_galaxies: int | None = None,
                     n_stars: int = 6, field: str = DEMO_FIELD, noise_scale=1.0) -> dict:
    """Build the demo field in memory (no files written).

    Parameters
    ----------
    shape : (int, int)
        Image shape (ny, nx) [pixels]; >= 64 on each side.
    seed : int
        Seed of every random draw: the same seed gives identical arrays.
    pixel_scale_arcsec : float
        Image pixel scale [arcsec / pixel].
    source_density_arcmin2 : float
        Background galaxies per arcmin^2 of footprint (19 < H < 29), used when
        ``n_galaxies`` is None; at most 400 so the field is not confusion-limited.
    n_galaxies : int, optional
        Exact number of background galaxies (overrides the density).
    n_stars : int
        Number of stars (the first two are bright, H = 18-19.5).
    field : str
        Field name (returned as ``"field"``; :func:`build_demo_survey` names files after it).
    noise_scale : float or ndarray of shape ``shape``
        Multiplier (> 0) of the sky-noise RMS of every pixel in every band: the
        weight maps are divided by ``noise_scale**2`` and the sky noise added to the
        science images is scaled by it (source shot noise is not).  2.5 makes a
        field ~1 mag shallower; an array makes depth vary across it (e.g. 0.3 over
        one quadrant: that quadrant 2.5 log10(1 / 0.3) = 1.31 mag deeper).  The
        random draws do not depend on it.

    Returns
    -------
    dict with keys
        ``"science"``: {band: float32 (ny, nx) [e-/s]}, 0 where there are no data;
        ``"weight"``: {band: float32 (ny, nx) inverse variance [(e-/s)^-2]}, 0 where no data;
        ``"model"``: {band: float64 noiseless scene [e-/s]};
        ``"psf"``: {band: float64 PSF at its own pixel scale, as written to the PSF file};
        ``"psf_pixel_scale_arcsec"``: {band: float};
        ``"rms_nominal"``: {band: per-pixel noise RMS at relative exposure 1 and
        ``noise_scale`` 1 [e-/s]};
        ``"field"``: the field name;
        ``"truth"``: astropy Table of the real population (id, x, y, mag_<band>,
        r_eff_arcsec, r_eff_pix, sersic_n, axis_ratio, position_angle_deg,
        is_star, sed_type), galaxies first, then stars.
    """
    from scipy.signal import fftconvolve

    from .galaxy.psf import moffat_psf

    ny, nx = (int(v) for v in shape)
    if ny < 64 or nx < 64:
        raise ValueError(f"demo shape must be at least 64 x 64 pixels, got {shape!r}")
    if not pixel_scale_arcsec > 0:
        raise ValueError(f"pixel_scale_arcsec must be > 0, got {pixel_scale_arcsec!r}")
    if n_stars < 0 or (n_galaxies is not None and n_galaxies < 0):
        raise ValueError("n_galaxies and n_stars must be >= 0")
    if not 0 <= source_density_arcmin2 <= _MAX_DENSITY_ARCMIN2:
        raise ValueError(f"source_density_arcmin2 must be in [0, {_MAX_DENSITY_ARCMIN2:g}] "
                         f"(denser fields are confusion-limited), got {source_density_arcmin2!r}")
    shape = (ny, nx)
    noise_scale = _check_noise_scale(noise_scale, shape)
    streams = np.random.SeedSequence(int(seed)).spawn(1 + 2 * len(DEMO_BANDS))
    rng_pop = np.random.default_rng(streams[0])

    coverage = _coverage(shape)
    exposure = {b: _relative_exposure(coverage, b) for b in DEMO_BANDS}
    footprint = exposure[DEMO_BANDS[0]] > 0
    if n_galaxies is None:
        area_arcmin2 = footprint.sum() * (pixel_scale_arcsec / 60.0) ** 2
        n_galaxies = int(round(source_density_arcmin2 * area_arcmin2))
    truth = _draw_population(rng_pop, footprint, int(n_galaxies), int(n_stars), pixel_scale_arcsec)

    # Render the unit-flux morphology once, add it to every band with that band's flux.
    intrinsic = {b: np.zeros(shape) for b in DEMO_BANDS}
    flux = {b: 10.0 ** (-0.4 * (np.asarray(truth[f"mag_{b}"]) - DEMO_BANDS_SPEC[b].zeropoint))
            for b in DEMO_BANDS}
    cols = [np.asarray(truth[c], dtype=np.float64)
            for c in (COL_X, COL_Y, COL_R_EFF_PIX, COL_SERSIC_N, COL_AXIS_RATIO, COL_PA)]
    for i in np.flatnonzero(~np.asarray(truth["is_star"])):
        stamp = _sersic_stamp_fast(*(float(c[i]) for c in cols), shape)
        if stamp is None:
            continue
        y0, x0, img = stamp
        for b in DEMO_BANDS:
            intrinsic[b][y0:y0 + img.shape[0], x0:x0 + img.shape[1]] += flux[b][i] * img
    for i in np.flatnonzero(np.asarray(truth["is_star"])):
        for b in DEMO_BANDS:
            intrinsic[b][int(truth[COL_Y][i]), int(truth[COL_X][i])] += flux[b][i]

    out = {"science": {}, "weight": {}, "model": {}, "psf": {}, "psf_pixel_scale_arcsec": {},
           "rms_nominal": {}, "truth": truth, "field": str(field)}
    for k, b in enumerate(DEMO_BANDS):
        spec = DEMO_BANDS_SPEC[b]
        rng_noise = np.random.default_rng(streams[1 + 2 * k])
        rng_poisson = np.random.default_rng(streams[2 + 2 * k])
        psf_image = moffat_psf(spec.psf_fwhm_arcsec, pixel_scale_arcsec, beta=DEMO_MOFFAT_BETA,
                               size=_RENDER_PSF_SIZE)
        model = fftconvolve(intrinsic[b], psf_image, mode="same")
        kernel_1d = _drizzle_kernel_1d(spec.native_pixel_arcsec, spec.pixfrac, pixel_scale_arcsec)
        kernel = np.outer(kernel_1d, kernel_1d)
        rms_nominal = _pixel_rms_for_depth(spec, psf_image, kernel, pixel_scale_arcsec)
        e = exposure[b]
        has_data = e > 0
        weight = np.zeros(shape)
        # Scaling after the nominal expressions keeps noise_scale = 1 bit-identical to no scale.
        weight[has_data] = e[has_data] / rms_nominal ** 2 / noise_scale[has_data] ** 2
        rms = np.zeros(shape)
        rms[has_data] = rms_nominal / np.sqrt(e[has_data]) * noise_scale[has_data]
        science = model + rms * _correlated_unit_noise(rng_noise, shape, kernel_1d)
        # Source shot noise with the local exposure time (white: a simplification).
        shot_var = np.zeros(shape)
        shot_var[has_data] = np.clip(model[has_data], 0.0, None) / (spec.exptime_s * e[has_data])
        science += np.sqrt(shot_var) * rng_poisson.standard_normal(shape)
        science[~has_data] = 0.0
        out["science"][b] = science.astype(np.float32)
        out["weight"][b] = weight.astype(np.float32)
        out["model"][b] = model
        out["rms_nominal"][b] = float(rms_nominal)
        out["psf"][b] = moffat_psf(spec.psf_fwhm_arcsec, spec.psf_pixel_scale_arcsec,
                                   beta=DEMO_MOFFAT_BETA, size=spec.psf_size)
        out["psf_pixel_scale_arcsec"][b] = spec.psf_pixel_scale_arcsec
    return out


def _check_noise_scale(noise_scale, shape: tuple[int, int]) -> np.ndarray:
    """``noise_scale`` as a float64 array of the image shape; finite and > 0 everywhere."""
    a = np.asarray(noise_scale, dtype=np.float64)
    if a.ndim not in (0, 2) or (a.ndim == 2 and a.shape != shape):
        raise ValueError(f"noise_scale must be a number or an array of the image shape {shape}, "
                         f"got shape {a.shape}")
    if not (np.all(np.isfinite(a)) and np.all(a > 0)):
        raise ValueError("noise_scale must be finite and > 0 everywhere")
    return np.broadcast_to(a, shape)


def _image_header(shape: tuple[int, int], band: str, pixel_scale_arcsec: float, kind: str,
                  field: str = DEMO_FIELD):
    from astropy.io import fits

    spec = DEMO_BANDS_SPEC[band]
    ny, nx = shape
    h = fits.Header()
    h["TELESCOP"] = "HST"
    h["INSTRUME"] = "WFC3"
    h["DETECTOR"] = "UVIS" if "uvis" in spec.filter else "IR"
    h["FILTER"] = band.upper()
    h["OBJECT"] = field
    h["ORIGIN"] = ("glaciar demo", "synthetic BoRG-like field")
    h["WCSAXES"] = 2
    h["CTYPE1"] = "RA---TAN"
    h["CTYPE2"] = "DEC--TAN"
    h["CUNIT1"] = "deg"
    h["CUNIT2"] = "deg"
    h["CRPIX1"] = 0.5 * (nx + 1)
    h["CRPIX2"] = 0.5 * (ny + 1)
    h["CRVAL1"] = _CRVAL_DEG[0]
    h["CRVAL2"] = _CRVAL_DEG[1]
    h["CD1_1"] = -pixel_scale_arcsec / 3600.0
    h["CD1_2"] = 0.0
    h["CD2_1"] = 0.0
    h["CD2_2"] = pixel_scale_arcsec / 3600.0
    h["RADESYS"] = "ICRS"
    h["EXPTIME"] = (spec.exptime_s, "[s] nominal exposure time")
    if kind == "science":
        h["BUNIT"] = "ELECTRONS/S"
        h["MAGZPT"] = (spec.zeropoint, "AB zeropoint of ELECTRONS/S")
        h["DEPTH5S"] = (spec.depth_5sigma, "5 sigma point source AB, r=0.2 arcsec aperture")
    else:
        h["BUNIT"] = "(ELECTRONS/S)**-2"
        h["WHTTYPE"] = ("IVM", "inverse variance of the sky noise per pixel")
    return h


def _fits_bytes(data: np.ndarray, header) -> bytes:
    from astropy.io import fits

    buf = io.BytesIO()
    fits.PrimaryHDU(data=data, header=header).writeto(buf)
    return buf.getvalue()


def _config_dumper():
    """A SafeDumper (no Python tags) writing mappings as blocks and scalar lists inline."""
    import yaml

    class _Dumper(yaml.SafeDumper):
        pass

    def _list(dumper, value):
        flow = all(not isinstance(v, (list, dict)) for v in value)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", value, flow_style=flow)

    _Dumper.add_representer(list, _list)
    return _Dumper


def _grid_values(values) -> list[float]:
    vals = [float(round(float(v), 6)) for v in np.atleast_1d(np.asarray(values, dtype=float))]
    if not vals or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"grid values must be a non-empty list of finite numbers, got {values!r}")
    return vals


def build_demo_survey(out_dir, *, shape: tuple[int, int] = (1000, 1000), seed: int = 2018,
                      n_galaxies: int = 50, n_iterations: int = 2,
                      z_values=tuple(np.round(np.arange(7.8, 12.6 + 1e-9, 0.4), 6)) + (12.9,),
                      mag_values=tuple(np.round(np.arange(24.5, 28.5 + 1e-9, 0.5), 6)),
                      source_density_arcmin2: float = 250.0, n_stars: int = 6,
                      field: str = DEMO_FIELD, noise_scale=1.0) -> Path:
    """Write the demo survey (FITS images, weight maps, PSFs and a config) to ``out_dir``.

    Layout: ``out_dir/demo.yaml``, ``out_dir/images/<field>_<band>_drz.fits``
    (float32, e-/s, TAN WCS at 0.08"/px), ``out_dir/images/<field>_<band>_wht.fits``
    (inverse variance), ``out_dir/psf/psf_<band>.fits`` (with ``PIXSCALE``).
    Every file is written atomically.  Fields of other names (and the same
    pixel scale and PSFs) can be written into one directory; the config
    ``demo.yaml`` then describes the last one written.

    Parameters
    ----------
    out_dir : str or path-like
        Directory to write into (created if needed; existing demo files are replaced).
    shape : (int, int)
        Image shape (ny, nx) [pixels].
    seed : int
        Seed of the images; also written as the simulation seed of the config.
    n_galaxies : int
        Artificial sources injected per iteration (config ``simulation.n_galaxies``).
    n_iterations : int
        Iterations per (field, z, mag) (config ``simulation.n_iterations``).
    z_values, mag_values : sequence of float
        Redshift grid and apparent F160W magnitude grid [AB] of the config.
        Defaults 7.8-12.6 step 0.4 and 12.9 (the J125-dropout's lower edge inside; F160W,
        the detection band, receives no flux from z = 12.99, where Lyman-alpha leaves it,
        so the selection ends there) and 24.5-28.5 step 0.5: 252 tasks, about a minute
        on 2 cores.
    source_density_arcmin2, n_stars, noise_scale : see :func:`make_demo_images`.
    field : str
        Field name, used in the file names and the config (default ``demo01``).

    Returns
    -------
    pathlib.Path
        Path of the config file.
    """
    import yaml
    from astropy.io import fits

    from .store import atomic_write_bytes, atomic_write_text

    if int(n_galaxies) < 1 or int(n_iterations) < 1:
        raise ValueError(f"n_galaxies and n_iterations must be >= 1, got {n_galaxies}, {n_iterations}")
    out_dir = Path(out_dir)
    demo = make_demo_images(shape, seed=seed, source_density_arcmin2=source_density_arcmin2,
                            n_stars=n_stars, field=field, noise_scale=noise_scale)
    image_shape = demo["science"][DEMO_BANDS[0]].shape

    for b in DEMO_BANDS:
        for kind, name in (("science", "drz"), ("weight", "wht")):
            atomic_write_bytes(out_dir / "images" / f"{field}_{b}_{name}.fits",
                               _fits_bytes(demo[kind][b], _image_header(image_shape, b,
                                                                        DEMO_PIXEL_SCALE_ARCSEC, kind,
                                                                        field)))
        ph = fits.Header()
        ph["PIXSCALE"] = (demo["psf_pixel_scale_arcsec"][b], "[arcsec/pixel]")
        ph["FILTER"] = b.upper()
        ph["PSFMODEL"] = ("MOFFAT", "analytic, pixel-integrated")
        ph["FWHM"] = (DEMO_BANDS_SPEC[b].psf_fwhm_arcsec, "[arcsec]")
        ph["BETA"] = DEMO_MOFFAT_BETA
        atomic_write_bytes(out_dir / "psf" / f"psf_{b}.fits", _fits_bytes(demo["psf"][b], ph))

    config = {
        "survey": {
            "fields": [field],
            "image_dir": "images",
            "science": "{field}_{band}_drz.fits",
            "noise": "{field}_{band}_wht.fits",
            "noise_type": "weight",
            "pixel_scale_arcsec": None,
            "detection_band": DEMO_BANDS[0],
            "bands": {b: {"filter": DEMO_BANDS_SPEC[b].filter,
                          "zeropoint": DEMO_BANDS_SPEC[b].zeropoint,
                          "gain": DEMO_BANDS_SPEC[b].exptime_s,
                          "psf": f"psf/psf_{b}.fits",
                          "psf_pixel_scale_arcsec": DEMO_BANDS_SPEC[b].psf_pixel_scale_arcsec}
                      for b in DEMO_BANDS},
        },
        "grid": {"z": {"values": _grid_values(z_values)},
                 "mag": {"values": _grid_values(mag_values)},
                 "magnitude_type": "apparent"},
        "simulation": {"n_galaxies": int(n_galaxies), "n_iterations": int(n_iterations),
                       "seed": int(seed)},
        "source": {"r_eff_kpc_z6": 1.075, "size_evolution": -1.0, "r_eff_scatter_dex": 0.0,
                   "size_luminosity_slope": 0.0, "sersic_indices": [1.0, 4.0],
                   "sersic_fractions": [0.5, 0.5], "ellipticity_bins": 1,
                   "position_angle_bins": 1, "round_de_vaucouleurs": False, "beta_mean": -2.2,
                   "beta_sd": 0.4, "beta_per": "source", "igm": "inoue14",
                   "cosmology": "Planck18", "stamp_flux_fraction": 0.995},
        "detection": {"sex_file": None, "DETECT_THRESH": 0.7, "DETECT_MINAREA": 9,
                      "FILTER": True, "FILTER_NAME": "gauss_2.0_5x5", "DEBLEND_NTHRESH": 32,
                      "DEBLEND_MINCONT": 0.005, "CLEAN": True, "CLEAN_PARAM": 1.0,
                      "BACK_SIZE": 64, "BACK_FILTERSIZE": 3, "PHOT_APERTURES": [4.0, 8.0],
                      "PHOT_AUTOPARAMS": [2.5, 3.5]},
        "classification": {"min_sn": 8.0, "sn_definition": "iso", "sn_aperture_index": 0,
                           "search_box": 3, "max_overlap_fraction": 0.25, "flux_tolerance": 0.25},
        "selection": ["sn_f160w >= 8", "sn_f606w < 1.5", "sn_f098m < 1.5",
                      "maglim_f125w - mag_f160w > 1.5"],
        "output": {"regions": False},
    }
    depths = ", ".join(f"{b.upper()} {DEMO_BANDS_SPEC[b].depth_5sigma}" for b in DEMO_BANDS)
    header = (
        "# glaciar demo survey: a synthetic BoRG-like field (written by glaciar.demo).\n"
        f"# Field {field}, {image_shape[1]} x {image_shape[0]} px at "
        f"{DEMO_PIXEL_SCALE_ARCSEC}\"/px, image seed {seed}; drizzle-like correlated noise,\n"
        "# inverse-variance weight maps, Moffat PSFs written at 0.13\"/px (IR) and 0.04\"/px (F606W).\n"
        f"# 5-sigma point-source depths (r = 0.2\" aperture, full exposure): {depths}.\n"
        "# gain = exposure time [s] (electrons per e-/s). Selection: BoRG J125-dropouts.\n"
        "# Paths are relative to this file. Schema: docs/config-schema.yaml.\n"
    )
    scale = np.asarray(noise_scale, dtype=np.float64)
    if np.any(scale != 1.0):
        header += (f"# Sky noise RMS scaled by noise_scale = {float(scale.min()):g}"
                   + (f" to {float(scale.max()):g} across the field" if np.ptp(scale) > 0 else "")
                   + " (the depths above are for 1).\n")
    path = out_dir / DEMO_CONFIG_NAME
    atomic_write_text(path, header + yaml.dump(config, Dumper=_config_dumper(), sort_keys=False,
                                               default_flow_style=False, width=100))
    return path
