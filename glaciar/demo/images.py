"""The demo field's images in memory (:func:`make_demo_images`)."""
from __future__ import annotations

import numpy as np

from ..constants import COL_AXIS_RATIO, COL_PA, COL_R_EFF_PIX, COL_SERSIC_N, COL_X, COL_Y

from .bands import (DEMO_BANDS, DEMO_BANDS_SPEC, DEMO_FIELD, DEMO_MOFFAT_BETA,
                    DEMO_PIXEL_SCALE_ARCSEC, MAX_DENSITY_ARCMIN2, RENDER_PSF_SIZE)
from .noise import correlated_unit_noise, drizzle_kernel_1d, pixel_rms_for_depth
from .sky import dither_coverage, draw_population, relative_exposure, sersic_stamp_fast


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

    shape = check_arguments(shape, pixel_scale_arcsec, source_density_arcmin2, n_galaxies, n_stars)
    noise_scale = check_noise_scale(noise_scale, shape)
    streams = np.random.SeedSequence(int(seed)).spawn(1 + 2 * len(DEMO_BANDS))
    rng_pop = np.random.default_rng(streams[0])

    coverage = dither_coverage(shape)
    exposure = {b: relative_exposure(coverage, b) for b in DEMO_BANDS}
    footprint = exposure[DEMO_BANDS[0]] > 0
    if n_galaxies is None:
        area_arcmin2 = footprint.sum() * (pixel_scale_arcsec / 60.0) ** 2
        n_galaxies = int(round(source_density_arcmin2 * area_arcmin2))
    truth = draw_population(rng_pop, footprint, int(n_galaxies), int(n_stars), pixel_scale_arcsec)

    # Render the unit-flux morphology once, add it to every band with that band's flux.
    intrinsic = {b: np.zeros(shape) for b in DEMO_BANDS}
    flux = {b: 10.0 ** (-0.4 * (np.asarray(truth[f"mag_{b}"]) - DEMO_BANDS_SPEC[b].zeropoint))
            for b in DEMO_BANDS}
    cols = [np.asarray(truth[c], dtype=np.float64)
            for c in (COL_X, COL_Y, COL_R_EFF_PIX, COL_SERSIC_N, COL_AXIS_RATIO, COL_PA)]
    for i in np.flatnonzero(~np.asarray(truth["is_star"])):
        stamp = sersic_stamp_fast(*(float(c[i]) for c in cols), shape)
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
        psf_image, kernel_1d, rms_nominal = band_setup(b, pixel_scale_arcsec)
        model = fftconvolve(intrinsic[b], psf_image, mode="same")
        science, weight = band_science_weight(model, exposure[b], rms_nominal, noise_scale,
                                       correlated_unit_noise(rng_noise, shape, kernel_1d),
                                       rng_poisson, spec.exptime_s)
        out["science"][b] = science
        out["weight"][b] = weight
        out["model"][b] = model
        out["rms_nominal"][b] = float(rms_nominal)
        out["psf"][b] = psf_file_image(b)
        out["psf_pixel_scale_arcsec"][b] = spec.psf_pixel_scale_arcsec
    return out


def band_setup(band: str, pixel_scale_arcsec: float):
    """A band's rendering PSF (at the image scale), 1-D drizzle kernel and nominal pixel RMS."""
    from ..galaxy.psf import moffat_psf

    spec = DEMO_BANDS_SPEC[band]
    psf_image = moffat_psf(spec.psf_fwhm_arcsec, pixel_scale_arcsec, beta=DEMO_MOFFAT_BETA,
                           size=RENDER_PSF_SIZE)
    kernel_1d = drizzle_kernel_1d(spec.native_pixel_arcsec, spec.pixfrac, pixel_scale_arcsec)
    rms_nominal = pixel_rms_for_depth(spec, psf_image, np.outer(kernel_1d, kernel_1d),
                                       pixel_scale_arcsec)
    return psf_image, kernel_1d, rms_nominal


def psf_file_image(band: str) -> np.ndarray:
    """The PSF written to the band's PSF file (at its own pixel scale)."""
    from ..galaxy.psf import moffat_psf

    spec = DEMO_BANDS_SPEC[band]
    return moffat_psf(spec.psf_fwhm_arcsec, spec.psf_pixel_scale_arcsec, beta=DEMO_MOFFAT_BETA,
                      size=spec.psf_size)


def check_arguments(shape, pixel_scale_arcsec, source_density_arcmin2, n_galaxies,
                     n_stars) -> tuple[int, int]:
    """Validate :func:`make_demo_images`' arguments; the shape as a tuple of ints."""
    ny, nx = (int(v) for v in shape)
    if ny < 64 or nx < 64:
        raise ValueError(f"demo shape must be at least 64 x 64 pixels, got {shape!r}")
    if not pixel_scale_arcsec > 0:
        raise ValueError(f"pixel_scale_arcsec must be > 0, got {pixel_scale_arcsec!r}")
    if n_stars < 0 or (n_galaxies is not None and n_galaxies < 0):
        raise ValueError("n_galaxies and n_stars must be >= 0")
    if not 0 <= source_density_arcmin2 <= MAX_DENSITY_ARCMIN2:
        raise ValueError(f"source_density_arcmin2 must be in [0, {MAX_DENSITY_ARCMIN2:g}] "
                         f"(denser fields are confusion-limited), got {source_density_arcmin2!r}")
    return ny, nx


def band_science_weight(model: np.ndarray, exposure: np.ndarray, rms_nominal: float,
                 noise_scale: np.ndarray, unit_noise: np.ndarray, rng_poisson: np.random.Generator,
                 exptime_s: float) -> tuple[np.ndarray, np.ndarray]:
    """One band's science and weight pixels from its noiseless scene (whole image or a strip).

    Parameters
    ----------
    model : ndarray, float64
        Noiseless PSF-convolved scene [e-/s].
    exposure : ndarray
        Relative exposure (0 = no data), same shape.
    rms_nominal : float
        Per-pixel sky RMS at relative exposure 1 [e-/s].
    noise_scale : ndarray
        Sky-RMS multiplier, same shape.
    unit_noise : ndarray
        Unit-variance (correlated) sky noise, same shape.
    rng_poisson : numpy.random.Generator
        Draws the source shot noise (``model.size`` normals, row-major).
    exptime_s : float
        Exposure time at relative exposure 1 [s].

    Returns
    -------
    science, weight : float32 ndarrays [e-/s], [(e-/s)^-2]; 0 where there are no data.
    """
    shape = model.shape
    e = exposure
    has_data = e > 0
    weight = np.zeros(shape)
    # Scaling after the nominal expressions keeps noise_scale = 1 bit-identical to no scale.
    weight[has_data] = e[has_data] / rms_nominal ** 2 / noise_scale[has_data] ** 2
    rms = np.zeros(shape)
    rms[has_data] = rms_nominal / np.sqrt(e[has_data]) * noise_scale[has_data]
    science = model + rms * unit_noise
    # Source shot noise with the local exposure time (white: a simplification).
    shot_var = np.zeros(shape)
    shot_var[has_data] = np.clip(model[has_data], 0.0, None) / (exptime_s * e[has_data])
    science += np.sqrt(shot_var) * rng_poisson.standard_normal(shape)
    science[~has_data] = 0.0
    return science.astype(np.float32), weight.astype(np.float32)


def check_noise_scale(noise_scale, shape: tuple[int, int]) -> np.ndarray:
    """``noise_scale`` as a float64 array of the image shape; finite and > 0 everywhere."""
    a = np.asarray(noise_scale, dtype=np.float64)
    if a.ndim not in (0, 2) or (a.ndim == 2 and a.shape != shape):
        raise ValueError(f"noise_scale must be a number or an array of the image shape {shape}, "
                         f"got shape {a.shape}")
    if not (np.all(np.isfinite(a)) and np.all(a > 0)):
        raise ValueError("noise_scale must be finite and > 0 everywhere")
    return np.broadcast_to(a, shape)

