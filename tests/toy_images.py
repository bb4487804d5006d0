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



CROWDED_SIDE = 600      #: side [px] of the crowded field of the windowed-equals-full-frame tests


def crowded_field(seed=0, ngal=150):
    """``ngal`` exponential-disk galaxies of a wide range of sizes and fluxes, on Gaussian noise
    whose RMS varies across the CROWDED_SIDE^2 field."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:CROWDED_SIDE, :CROWDED_SIDE]
    img = np.zeros((CROWDED_SIDE, CROWDED_SIDE))
    for _ in range(ngal):
        x0, y0 = rng.uniform(0, CROWDED_SIDE, 2)
        r = rng.lognormal(np.log(2.0), 0.5)
        q, pa = rng.uniform(0.4, 1.0), rng.uniform(0, np.pi)
        f = 10 ** rng.uniform(0.5, 3.0)
        s = int(min(12 * r + 5, 60))
        ya, yb = max(int(y0) - s, 0), min(int(y0) + s + 1, CROWDED_SIDE)
        xa, xb = max(int(x0) - s, 0), min(int(x0) + s + 1, CROWDED_SIDE)
        dx, dy = xx[ya:yb, xa:xb] - x0, yy[ya:yb, xa:xb] - y0
        u = dx * np.cos(pa) + dy * np.sin(pa)
        v = (-dx * np.sin(pa) + dy * np.cos(pa)) / q
        img[ya:yb, xa:xb] += f * np.exp(-np.hypot(u, v) / r) / (2 * np.pi * r * r * q)
    rms = 0.05 * (1 + 0.5 * np.sin(xx / 90.0) * np.cos(yy / 70.0))
    return img + rng.normal(size=(CROWDED_SIDE, CROWDED_SIDE)) * rms


def gaussian_stamps(rng, nsrc=100, size=21):
    """``nsrc`` non-overlapping Gaussian stamps (one per cell of a grid over the crowded field):
    (x, y, flux, [(row0, col0, stamp)])."""
    h = size // 2
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    g = int(np.ceil(np.sqrt(nsrc)))
    cell = (CROWDED_SIDE - 2 * h) / g
    cells = rng.permutation(g * g)[:nsrc]         # one per cell: stamps never overlap
    xs = np.clip(((cells % g) + rng.uniform(0.2, 0.8, nsrc)) * cell + h / 2, 1, CROWDED_SIDE - 2)
    ys = np.clip(((cells // g) + rng.uniform(0.2, 0.8, nsrc)) * cell + h / 2, 1, CROWDED_SIDE - 2)
    flux = 10 ** rng.uniform(-0.3, 1.7, nsrc)
    out = []
    for x, y, f in zip(xs, ys, flux):
        ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        s = rng.uniform(0.8, 2.5)
        p = np.exp(-((xx - (x - ix)) ** 2 + (yy - (y - iy)) ** 2) / (2 * s * s))
        out.append((iy - h, ix - h, f * p / p.sum()))
    return xs, ys, flux, out
