"""Issue 21, bullets 1 and 2: a noise model that is right or says so; noise maps checked against the pixels.

* Synthetic (CI): one large de Vaucouleurs galaxy in a small image with noise of a
  known correlation (white noise convolved with a 3x3 binomial kernel) and a 64-pixel
  background mesh: sums about the mesh read the galaxy's background residuals as
  correlated noise. r(N) must match the exact value of the injected kernel.
* Real (local only): the HFF A2744 dwarf-galaxy F105W cutout with the template's
  defaults; BACK_SIZE 64 and 32 agree, and the noise model's 5-sigma depth agrees
  with an independent empty-aperture depth computed with plain ``sep``.
"""
import importlib.util
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from scipy import signal

from glaciar.config import config_from_dict
from glaciar.engine import noise as N
from glaciar.fieldprep import field_noise_record
from glaciar.survey import Survey, clear_cache

_BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "hff_noise.py"
_SPEC = importlib.util.spec_from_file_location("hff_noise_benchmark", _BENCH)
hff = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(hff)

SIGMA = 0.01            #: pixel noise of the synthetic image [image units]
#: Tolerance of the measured r(N) against the exact one, for N <= 213 pixels (radius 8.2):
#: on a 256^2 image the apertures of one radius overlap, so each ratio scatters by
#: ~5 % (seeds 3-6: worst +12.6 %); larger apertures have too few independent positions.
R_TOLERANCE = 0.15


def binomial_kernel() -> np.ndarray:
    """3x3 binomial smoothing kernel scaled to sum(K^2) = 1 (unit pixel variance)."""
    k = np.outer([1.0, 2.0, 1.0], [1.0, 2.0, 1.0])
    return k / math.sqrt((k ** 2).sum())


def exact_ratio(radius: float, kernel: np.ndarray) -> float:
    """r(N) of noise ``K * white`` for the whole-pixel aperture of ``radius`` (pixel centres inside)."""
    k = int(math.ceil(radius))
    dy, dx = np.mgrid[-k:k + 1, -k:k + 1]
    w = (dy ** 2 + dx ** 2 < radius * radius).astype(float)
    return math.sqrt(np.sum(signal.convolve(w, kernel) ** 2) / w.sum())


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


def _record(cfg_dict, root):
    clear_cache()
    cfg = config_from_dict(cfg_dict, base_dir=root)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = field_noise_record(cfg, Survey.from_config(cfg), "f")["b"]
    return cfg, rec, [str(w.message) for w in caught]


# --------------------------------------------------------------------------
# Synthetic: the failure mode of the HFF cutout, with a known answer
# --------------------------------------------------------------------------
def test_background_residuals_are_not_read_as_correlated_noise(tmp_path):
    cfg, rec, said = _record(big_galaxy_survey(tmp_path), tmp_path)
    table = rec["correlated"]
    radii = cfg.noise.empty_aperture_radii_pix
    exact = np.array([exact_ratio(r, binomial_kernel()) for r in radii])
    got = np.array(table["ratio"])
    small = np.array(table["npix"]) <= 213
    assert np.all(np.abs(got[small] / exact[small] - 1) <= R_TOLERANCE), (got, exact)
    # Before issue 21 the sums about the 64-pixel mesh were the model: 1.9x the exact
    # r(213) here (4.89 against 2.53); they are kept in the record, and said once.
    mesh = np.array(table["mesh_ratio"])
    assert mesh[small][-1] / exact[small][-1] > 1.4
    assert rec["applied"] is True
    assert len(said) == 1 and "'f', band 'b'" in said[0] and "BACK_SIZE 64" in said[0]
    assert "about the background mesh" in said[0]


def test_a_flat_background_keeps_the_mesh_table(tmp_path):
    """No galaxy: the mesh leaves no residual; the table is the one measured about the
    mesh, as before issue 21 (no mesh_ratio, no warning): fixtures and the demo keep
    their r(N) bit for bit."""
    cfg, rec, said = _record(big_galaxy_survey(tmp_path, amp=0.0, n=200), tmp_path)
    table = rec["correlated"]
    assert "mesh_ratio" not in table and said == []
    assert rec["applied"] is True and table["ratio"][-1] > 1.1      # correlated, and said so


def test_a_background_varying_across_the_apertures_is_refused(tmp_path):
    """A background with structure between the mesh's and the annuli's scales (a 96-pixel
    sinusoidal egg-crate of 3 sigma under a 64-pixel mesh) is neither noise nor removed:
    r(N) rises like N^0.41 to 5.5 at N = 401. One line, naming the settings to change."""
    cfg = big_galaxy_survey(tmp_path, amp=0.0, n=192, back_size=64)
    sci = fits.getdata(tmp_path / "img" / "f_b.fits").astype(np.float32)
    y, x = np.mgrid[:192, :192]
    sci += (3.0 * SIGMA * np.sin(2 * np.pi * x / 96) * np.sin(2 * np.pi * y / 96)).astype(np.float32)
    fits.writeto(tmp_path / "img" / "f_b.fits", sci, overwrite=True)
    with pytest.raises(ValueError) as info:
        _record(cfg, tmp_path)
    msg = str(info.value)
    assert "\n" not in msg and "field 'f', band 'b'" in msg and "rises like N^" in msg
    assert "detection.BACK_SIZE" in msg and "noise.correlated: 'off'" in msg
    # noise.correlated: off is the documented way past it: measured, recorded, not applied.
    cfg["noise"] = {"correlated": "off"}
    _, rec, _ = _record(cfg, tmp_path)
    assert rec["applied"] is False


def test_background_excess_and_rise_exponent():
    n = [1000] * 4
    assert not N.background_excess([1.0, 1.5, 2.0, 2.1], [1.0, 1.49, 2.02, 2.05], n).any()
    assert N.background_excess([1.0, 1.5, 3.0, 5.0], [1.0, 1.5, 2.0, 6.0], n).tolist() == \
        [False, False, True, False]           # only an excess of the mesh's scatter counts
    # Fewer apertures, wider allowance: 1.4x from 10 apertures is within noise (3/sqrt(10)).
    assert not N.background_excess([1.4], [1.0], [10]).any()
    assert not N.background_excess([3.0], [np.nan], [1000]).any()
    npix = [1, 9, 37, 121, 401]
    assert N.rise_exponent(npix, [1, 2, 2.4, 2.5, 2.5]) == pytest.approx(0.0, abs=0.05)
    assert N.rise_exponent(npix, np.sqrt(npix)) == pytest.approx(0.5)
    assert N.rise_exponent(npix, [1, 2, 2.4, 2.5, 2.5]) < N.MAX_RISE_EXPONENT < 0.5


def test_local_ratio_is_one_for_white_noise_under_a_gradient():
    """White noise + a steep plane: the local (plane-fitted) ratio is 1, the mesh-free sum is not."""
    rng = np.random.default_rng(1)
    y, x = np.mgrid[:200, :200]
    img = rng.normal(0, 1.0, (200, 200)) + 0.05 * x + 0.03 * y
    rms = np.ones((200, 200))
    usable = np.ones((200, 200), bool)
    npix, ratio, k, local = N.empty_aperture_scatter(img, rms, usable, (0.5, 2.2, 6.2), 600,
                                                     np.random.default_rng(2), local=True)
    assert np.all(np.abs(local - 1) < 0.1), local
    assert ratio[-1] > 3              # the gradient dominates sums about zero


# --------------------------------------------------------------------------
# Bullet 2: the map type against the pixels
# --------------------------------------------------------------------------
def test_map_type_problem_names_the_fix():
    rng = np.random.default_rng(0)
    sci = rng.normal(0, 0.002, (300, 300))
    rms = np.full(sci.shape, 0.002)
    weight = 1.0 / rms ** 2
    assert N.map_type_problem(sci, rms, "rms") is None
    assert N.map_type_problem(sci, weight, "weight") is None
    # A factor 2 (what MAP_WEIGHT / a drizzle's r(1) is about) is not refused.
    assert N.map_type_problem(sci, 2 * rms, "rms") is None
    assert N.map_type_problem(sci, weight / 4, "weight") is None
    msg = N.map_type_problem(sci, rms, "weight")
    assert "looks like an RMS map" in msg and "set survey.noise_type: rms" in msg and "\n" not in msg
    msg = N.map_type_problem(sci, weight, "rms")
    assert "looks like a weight" in msg and "set survey.noise_type: weight" in msg
    msg = N.map_type_problem(sci, 1000 * rms, "rms")
    assert "units" in msg and "noise_type: weight" not in msg
    # Nothing to compare (a constant image): no verdict.
    assert N.map_type_problem(np.ones((50, 50)), rms[:50, :50], "weight") is None


# --------------------------------------------------------------------------
# The real HFF cutout (not in CI: the data are local)
# --------------------------------------------------------------------------
@pytest.mark.skipif(not (hff.DATA / "abell_2744_dwarf_galaxy_f105w_rms.fits.gz").is_file(),
                    reason=f"HFF A2744 cutouts not present at {hff.DATA}")
def test_hff_dwarf_cutout_does_not_depend_on_the_mesh(tmp_path):
    rows = {r["back_size"]: r for r in hff.run(hff.DATA, back_sizes=(64, 32), n_galaxies=10,
                                                  n_iterations=4, root=tmp_path)}
    for r in rows.values():
        assert r["error"] is None, r["error"]
    # Before issue 21: m50 25.74 (64) and 27.10 (32), r(401) = 7.17 and 2.23.
    assert abs(rows[64]["m50"] - rows[32]["m50"]) <= 0.3
    # The noise model's 5-sigma depth in glaciar's depth aperture (radius = PSF FWHM),
    # r(N) x the map's aperture noise, against plain sep's empty apertures with local
    # annulus backgrounds (29.48 here): before, 28.69 (64) and 29.21 (32).
    # sep_depth is computed here with plain sep (benchmark's function, no glaciar code).
    sep_depth = hff.sep_depth(fits.getdata(hff.DATA / "abell_2744_dwarf_galaxy_f105w.fits.gz"),
                              hff.depth_radius_pix(hff.DATA), hff.ZEROPOINT)
    assert 29.1 <= sep_depth <= 29.7                   # the issue's 29.1-29.5
    for bs, r in rows.items():
        assert abs(r["depth_model"] - sep_depth) <= 0.3, (bs, r["depth_model"], sep_depth)
        assert max(r["ratio"]) < 2.5            # before: 7.17 (64)
        # m50 against sep's depth: 1.9 mag brighter (S/N >= 8 in isophotes of extended
        # sources; completeness levelling at ~0.65), the same for both meshes (module docstring
        # of benchmarks/hff_noise.py): bounded here, not equal.
        assert 1.0 <= sep_depth - r["m50"] <= 2.5
