"""Toy images and surveys shared by tests (not collected: no ``test_`` prefix)."""
from __future__ import annotations

import numpy as np
from astropy.io import fits

from glaciar.config import config_from_dict
from glaciar.survey import Survey


def exponential_galaxy(xx, yy, x0, y0, flux, r, q=1.0, pa=0.0):
    """An exponential profile of total ``flux`` (before pixelisation), scale length ``r``
    [pixels], axis ratio ``q`` and position angle ``pa`` [rad], on the grids ``xx``, ``yy``."""
    dx, dy = xx - x0, yy - y0
    u = dx * np.cos(pa) + dy * np.sin(pa)
    v = (-dx * np.sin(pa) + dy * np.cos(pa)) / q
    return flux * np.exp(-np.hypot(u, v) / r) / (2 * np.pi * r * r * q)


def fits_survey(tmp_path, sci, wht, noise_type="weight", negative="mask"):
    """A one-field, one-band survey of the given arrays (FITS written as given)."""
    from astropy.io import fits

    from glaciar.config import config_from_dict

    fits.writeto(tmp_path / "f_b_drz.fits", sci, overwrite=True)
    if wht is not None:
        fits.writeto(tmp_path / "f_b_wht.fits", wht, overwrite=True)
    cfg = {"survey": {"fields": ["f"], "image_dir": str(tmp_path), "science": "{field}_{band}_drz.fits",
                      "noise": None if wht is None else "{field}_{band}_wht.fits",
                      "noise_type": noise_type, "negative_weights": negative,
                      "pixel_scale_arcsec": 0.1, "detection_band": "b",
                      "bands": {"b": {"filter": "wfc3_ir_f160w", "zeropoint": 25.0,
                                      "psf": {"profile": "moffat", "fwhm_arcsec": 0.2, "beta": 2.5}}}},
           "grid": {"z": {"values": [8.0]}, "mag": {"values": [26.0]}}}
    from glaciar.survey import Survey
    return Survey.from_config(config_from_dict(cfg, base_dir=tmp_path))
