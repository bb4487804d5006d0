"""Drizzle-like correlated noise of the demo images."""
from __future__ import annotations

import math

import numpy as np

from .bands import DEMO_PIXEL_SCALE_ARCSEC, DEPTH_APERTURE_RADIUS_ARCSEC, DemoBand


# --------------------------------------------------------------------------
# Noise
# --------------------------------------------------------------------------
def drizzle_kernel_1d(native_pixel_arcsec: float, pixfrac: float,
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
    k1 = drizzle_kernel_1d(native_pixel_arcsec, pixfrac, pixel_scale_arcsec)
    return np.outer(k1, k1)


def correlated_unit_noise(rng: np.random.Generator, shape: tuple[int, int],
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


def pixel_rms_for_depth(band: DemoBand, psf_image: np.ndarray, kernel: np.ndarray,
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


