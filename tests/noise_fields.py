"""Synthetic noise fields shared by the noise-model tests and the hostile-noise CLI tests.

A large de Vaucouleurs galaxy on noise of a known correlation (white noise convolved with
a 3x3 binomial kernel) in a small image; and the HFF A2744 cutout benchmark
(``benchmarks/hff_noise.py``, loaded as ``hff``), whose data are local only.
"""
import importlib.util
import math
from pathlib import Path

import numpy as np
from astropy.io import fits
from scipy import signal

#: benchmarks/hff_noise.py, the real-data check (its cutouts are local only)
_BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "hff_noise.py"
_SPEC = importlib.util.spec_from_file_location("hff_noise_benchmark", _BENCH)
hff = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(hff)

SIGMA = 0.01            #: pixel noise of the synthetic image [image units]


def binomial_kernel() -> np.ndarray:
    """3x3 binomial smoothing kernel scaled to sum(K^2) = 1 (unit pixel variance)."""
    k = np.outer([1.0, 2.0, 1.0], [1.0, 2.0, 1.0])
    return k / math.sqrt((k ** 2).sum())


def big_galaxy_survey(root: Path, *, n: int = 256, seed: int = 3, amp: float = 1000.0,
                      r_e: float = 12.0, back_size: int = 64, noise_type: str = "rms",
                      noise_map=None, correlated: str = "auto"):
    """One field: a de Vaucouleurs galaxy (peak ~amp x e^7.67 sigma) off centre on correlated noise."""
    rng = np.random.default_rng(seed)
    noise = SIGMA * signal.convolve(rng.standard_normal((n + 2, n + 2)), binomial_kernel(), mode="valid")
    y, x = np.mgrid[:n, :n]
    rr = np.hypot(x - n / 2 + 10, y - n / 2 + 10)
    galaxy = amp * SIGMA * np.exp(-7.669 * ((rr / r_e) ** 0.25 - 1.0))
    img = root / "img"
    img.mkdir(parents=True, exist_ok=True)
    fits.writeto(img / "f_b.fits", (noise + galaxy).astype(np.float32), overwrite=True)
    nmap = np.full((n, n), SIGMA, np.float32) if noise_map is None else noise_map
    fits.writeto(img / "f_b_noise.fits", np.asarray(nmap, np.float32), overwrite=True)
    cfg = {"survey": {"fields": ["f"], "image_dir": str(img), "science": "{field}_{band}.fits",
                      "noise": "{field}_{band}_noise.fits", "noise_type": noise_type,
                      "pixel_scale_arcsec": 0.06, "detection_band": "b",
                      "bands": {"b": {"filter": "wfc3_ir_f160w", "zeropoint": 25.0,
                                      "psf": {"profile": "gaussian", "fwhm_arcsec": 0.15}}}},
           "grid": {"z": {"values": [8.0]}, "mag": {"values": [26.0]}},
           "simulation": {"n_galaxies": 3, "n_iterations": 1, "seed": 1},
           "detection": {"BACK_SIZE": back_size}, "noise": {"correlated": correlated},
           "selection": []}
    return cfg
