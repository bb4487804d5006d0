"""The demo survey's bands, constants and background-population settings."""
from __future__ import annotations

from dataclasses import dataclass


DEMO_FIELD = "demo01"
DEMO_BANDS = ("f160w", "f098m", "f125w", "f606w")
DEMO_CONFIG_NAME = "demo.yaml"
DEMO_PIXEL_SCALE_ARCSEC = 0.08
DEMO_MOFFAT_BETA = 2.5
DEPTH_APERTURE_RADIUS_ARCSEC = 0.2

# An arbitrary high-latitude pointing; only there so the images carry a real celestial WCS.
CRVAL_DEG = (219.21135, 50.72650)


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
SED_TYPES = (
    ("sf_blue", 0.55, {"f098m": 0.10, "f125w": 0.05, "f606w": 0.35}, (0.5, 1.5), (0.2, 1.0), 0.0),
    ("sf_dusty", 0.30, {"f098m": 0.45, "f125w": 0.20, "f606w": 1.20}, (1.0, 2.5), (0.3, 1.0), 0.0),
    ("passive", 0.15, {"f098m": 1.00, "f125w": 0.40, "f606w": 2.60}, (2.5, 4.0), (0.5, 1.0), -0.1),
)
COLOUR_SCATTER_MAG = 0.15
MAG_RANGE_F160W = (19.0, 29.0)
COUNT_SLOPE_BRIGHT = 0.3          # dN/dm ~ 10^(0.3 m) for H < 25 ...
COUNT_SLOPE_FAINT = 0.15          # ... and ~ 10^(0.15 m) for H > 25
COUNT_BREAK_MAG = 25.0
MAX_DENSITY_ARCMIN2 = 400.0       # beyond this the field becomes confusion-limited
SUPERSAMPLE = 4
TRUNCATION_R_EFF = 5.0
RENDER_PSF_SIZE = 61              # 4.9": encloses all but ~4e-4 of an IR beta=2.5 Moffat


