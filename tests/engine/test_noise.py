"""Noise models: weight rescaling and correlated noise against a field of known covariance.

The reference field is white Gaussian noise convolved with a known kernel K,
so the variance of any pixel sum is known exactly: for a sum over the pixel
set D, Var = sigma_w^2 * sum_j ((1_D correlated with K)_j)^2. The tests compare
glaciar's empirical measurements with that number, never with glaciar itself.
"""
import importlib.util
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from scipy import ndimage, signal

from glaciar.config import config_from_dict
from glaciar.engine import noise as N
from glaciar.engine.detect import DetectionParams, measure_background
from glaciar.engine.noise import (CorrelatedNoise, DEFAULT_EMPTY_APERTURE_RADII_PIX, distance_cap,
                                  empty_aperture_scatter, empty_sky_distance, weight_rescale_factor)
from glaciar.fieldprep import field_noise_record
from glaciar.survey import Survey, clear_cache

from noise_fields import SIGMA, big_galaxy_survey, binomial_kernel, hff

KERNEL = np.outer([1, 2, 1], [1, 2, 1]) / 16.0 + 0.0     # a drizzle-like 3x3 smoothing kernel


def correlated_field(shape=(900, 900), seed=1):
    rng = np.random.default_rng(seed)
    white = rng.normal(size=(shape[0] + 2, shape[1] + 2))
    return signal.convolve2d(white, KERNEL, mode="valid")


def disk(r):
    """Pixel-centre-in-circle indicator centred on a pixel (what subpix=1 sums)."""
    k = int(np.ceil(r)) + 1
    yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
    return (xx ** 2 + yy ** 2 < r * r).astype(float)


def exact_sum_variance(indicator):
    """Var(sum over the pixel set) of white noise (sigma 1) convolved with KERNEL."""
    w = signal.correlate2d(indicator, KERNEL, mode="full")
    return float(np.sum(w ** 2))


SIGMA_PIX = float(np.sqrt(np.sum(KERNEL ** 2)))


def test_pixel_noise_of_the_reference_field():
    # Sanity of the reference itself: pixel sigma = sqrt(sum K^2) = 0.375 for this kernel.
    img = correlated_field()
    assert SIGMA_PIX == pytest.approx(0.375)
    assert img.std() == pytest.approx(SIGMA_PIX, rel=0.01)


def test_empty_aperture_scatter_matches_the_known_covariance():
    img = correlated_field()
    overestimate = 2.3
    rms = np.full(img.shape, overestimate * SIGMA_PIX)
    usable = np.ones(img.shape, bool)
    npix, ratio, n = empty_aperture_scatter(img, rms, usable, radii_pix=(1.2, 2.2, 4.2, 8.2),
                                            n_per_radius=1000, rng=np.random.default_rng(3))
    assert len(npix) == 4
    for r, N, got, k in zip((1.2, 2.2, 4.2, 8.2), npix, ratio, n):
        d = disk(r)
        assert N == d.sum()
        expected = np.sqrt(exact_sum_variance(d) / (d.sum() * (overestimate * SIGMA_PIX) ** 2))
        # clipped scatter from k (partly overlapping) apertures: ~1/sqrt(2k) relative error
        tol = 4 / np.sqrt(2 * k)
        assert got == pytest.approx(expected, rel=tol), (r, got, expected)
    # correlated noise: the ratio grows with the area
    assert np.all(np.diff(ratio) > 0)


def test_white_noise_with_a_true_map_is_the_identity():
    rng = np.random.default_rng(7)
    img = rng.normal(scale=2.0, size=(700, 700))
    npix, ratio, n = empty_aperture_scatter(img, np.full(img.shape, 2.0), np.ones(img.shape, bool),
                                            rng=np.random.default_rng(1))
    model = CorrelatedNoise.fit(npix, ratio, n)
    assert model.is_identity(0.05)
    # 1000 apertures per radius: each ratio within 4 standard errors (1/sqrt(2000)) of 1
    assert np.all(np.abs(ratio - 1) < 4 / np.sqrt(2 * n))


def test_apertures_stay_on_usable_sky():
    img = correlated_field((400, 400))
    usable = np.ones(img.shape, bool)
    usable[:, 200:] = False
    img[:, 200:] = 1e6          # anything touching the unusable half would dominate
    npix, ratio, _ = empty_aperture_scatter(img, np.full(img.shape, SIGMA_PIX), usable,
                                            radii_pix=(2.0, 6.0), rng=np.random.default_rng(0))
    assert np.all(ratio < 5)


def test_weight_rescale_factor_recovers_the_overestimate():
    img = correlated_field()
    map_rms = np.full(img.shape, 2.3 * SIGMA_PIX)
    _, bkg_rms = measure_background(img, None, DetectionParams())
    f = weight_rescale_factor(bkg_rms, map_rms, np.ones(img.shape, bool))
    assert f == pytest.approx(1 / 2.3, rel=0.03)


def test_table_interpolation_and_clamping():
    npix = np.array([12.0, 3.0, 50.0, 200.0])
    ratio = np.array([1.3, 1.1, 1.5, 1.6])
    model = CorrelatedNoise.fit(npix, ratio)
    assert model.npix == (3.0, 12.0, 50.0, 200.0)                 # sorted by area
    assert model.ratio_at(12.0) == pytest.approx(1.3)
    assert model.ratio_at(6.0) == pytest.approx(1.2)              # halfway in log N
    assert model.ratio_at(1.0) == pytest.approx(1.1)              # held at the range's ends
    assert model.ratio_at(1e4) == pytest.approx(1.6)
    assert model.variance_factor(50.0) == pytest.approx(1.5 ** 2)
    assert not model.is_identity()
    # 1 within tolerance + 3 standard errors of each measurement
    assert CorrelatedNoise.fit([5, 50], [1.06, 0.95], [1000, 1000]).is_identity(0.05)
    assert not CorrelatedNoise.fit([5, 50], [1.0, 1.13], [1000, 1000]).is_identity(0.05)
    with pytest.raises(ValueError, match=">= 2 areas"):
        CorrelatedNoise.fit([3.0], [1.0])


def _reference_aperture_sums(image, rms, usable, radii, n, seed):
    """The textbook procedure, written out plainly: full-frame float64 copies, one distance
    transform, one scan of the whole frame per radius (issue 11: the engine avoids all three)."""
    rng = np.random.default_rng(seed)
    var = np.where(usable, np.asarray(rms, np.float64) ** 2, 0.0)
    data = np.where(usable, np.asarray(image, np.float64), 0.0)
    dist = ndimage.distance_transform_edt(np.pad(usable, 1))[1:-1, 1:-1]
    out = []
    for r in radii:
        k = int(np.ceil(r))
        dy, dx = np.mgrid[-k:k + 1, -k:k + 1]
        inside = dy ** 2 + dx ** 2 < r * r
        yy, xx = np.nonzero(dist > r + 1.0)
        pick = rng.choice(yy.size, size=min(n, yy.size), replace=False)
        iy = yy[pick][:, None] + dy[inside][None, :]
        ix = xx[pick][:, None] + dx[inside][None, :]
        s, v = data[iy, ix].sum(axis=1), var[iy, ix].sum(axis=1)
        out.append(_robust_sigma_plain(s / np.sqrt(v)))
    return np.array(out)


def _robust_sigma_plain(x):
    keep = np.ones(x.size, bool)
    center, sigma = np.median(x), 1.482602218505602 * np.median(np.abs(x - np.median(x)))
    for _ in range(10):
        new = np.abs(x - center) <= 3.0 * sigma
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
        center, sigma = np.mean(x[keep]), np.std(x[keep], ddof=1) / 0.986659
    return sigma


def test_empty_aperture_scatter_equals_the_plain_procedure_bit_for_bit():
    # float32 inputs and an irregular usable mask (holes, a border strip), radii in any order:
    # the gathered, subset-filtered computation must give exactly the plain full-frame one's
    # numbers, with and without a shared distance map.
    from glaciar.engine.noise import empty_sky_distance

    rng = np.random.default_rng(7)
    img = correlated_field((300, 340), seed=3).astype(np.float32)
    rms = (0.3 + 0.1 * rng.random(img.shape)).astype(np.float32)
    usable = np.ones(img.shape, bool)
    usable[:, :20] = False
    usable[rng.integers(0, 300, 40), rng.integers(0, 340, 40)] = False
    usable = ~ndimage.binary_dilation(~usable, iterations=2)
    radii = (4.2, 0.5, 2.2, 8.2)
    want = _reference_aperture_sums(img, rms, usable, radii, 200, seed=11)
    for dist in (None, empty_sky_distance(usable)):
        _, ratio, n = empty_aperture_scatter(img, rms, usable, radii, 200,
                                             np.random.default_rng(11), distance=dist)
        assert np.array_equal(ratio, want)
        assert np.all(n == 200)


# ------------------------------------------------------------------------------
# Acceptance of issue 9, point 1 on a drizzle-like field whose noise map is 2.3x too high.
#
# References independent of glaciar: the exact noise of an aperture on noise
# ``sigma_pix (K * white)`` with the demo's drizzle kernel K, and m50 from a
# maximum-likelihood logistic fit of the recovered flags (benchmarks/correlated_noise.py
# holds both, with more sources and the table of all variants).
# ------------------------------------------------------------------------------
_SPEC = importlib.util.spec_from_file_location(
    "correlated_noise_benchmark", Path(__file__).resolve().parents[2] / "benchmarks" / "correlated_noise.py")
bench = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bench)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("corrnoise")


@pytest.fixture(scope="module")
def rows(root):
    return {r["variant"]: r for r in bench.run(
        n_galaxies=40, n_iterations=2, workers=2, root=root,
        mags=tuple(np.round(np.arange(24.75, 27.01, 0.25), 2)),
        only=("true map", "2.3x map, MAP_WEIGHT", "true map, no r(N)"))}


def test_map_weight_recovers_the_true_map_completeness(rows):
    assert abs(rows["2.3x map, MAP_WEIGHT"]["dm50"]) <= 0.15


def test_errors_match_the_exact_aperture_noise(rows):
    for name in ("true map", "2.3x map, MAP_WEIGHT"):
        assert rows[name]["n_isolated"] >= 50
        assert rows[name]["err_ratio"] == pytest.approx(1.0, abs=0.10), name
    # Control: without the correlated-noise model the errors are too small on this field.
    assert rows["true map, no r(N)"]["err_ratio"] < 0.9


def test_the_noise_model_is_recorded_in_the_run(rows, root):
    import json

    manifest = json.loads((root / "run1" / "manifest.json").read_text())   # the MAP_WEIGHT run
    rec = manifest["noise"]["demo01"]["f160w"]
    assert rec["weight_type"] == "map_weight" and rec["applied"] is True
    # The map was made 2.3x too high: MAP_WEIGHT scales it back by ~1/2.3.
    assert rec["weight_scale"] == pytest.approx(1 / 2.3, rel=0.05)
    table = rec["correlated"]
    # r(1): pixel scatter over the rescaled map. sep's sigma-clipped background RMS, which
    # MAP_WEIGHT matches (as SExtractor does), still holds faint sources: ~5 % high here.
    assert table["npix"][0] == 1 and table["ratio"][0] == pytest.approx(1.0, abs=0.1)
    assert table["ratio"][-1] > 1.2            # drizzle-correlated: sums are noisier than the map says


# ------------------------------------------------------------------------------
# Issue 21, bullets 1 and 2: a noise model that is right or says so; noise maps checked against the pixels.
#
# * Synthetic (CI): one large de Vaucouleurs galaxy in a small image with noise of a
#   known correlation (white noise convolved with a 3x3 binomial kernel) and a 64-pixel
#   background mesh: sums about the mesh read the galaxy's background residuals as
#   correlated noise. r(N) must match the exact value of the injected kernel.
# * Real (local only): the HFF A2744 dwarf-galaxy F105W cutout with the template's
#   defaults; BACK_SIZE 64 and 32 agree, and the noise model's 5-sigma depth agrees
#   with an independent empty-aperture depth computed with plain ``sep``.
# ------------------------------------------------------------------------------
#: Tolerance of the measured r(N) against the exact one, for N <= 213 pixels (radius 8.2):
#: on a 256^2 image the apertures of one radius overlap, so each ratio scatters by
#: ~5 % (seeds 3-6: worst +12.6 %); larger apertures have too few independent positions.
R_TOLERANCE = 0.15


def exact_ratio(radius: float, kernel: np.ndarray) -> float:
    """r(N) of noise ``K * white`` for the whole-pixel aperture of ``radius`` (pixel centres inside)."""
    k = int(math.ceil(radius))
    dy, dx = np.mgrid[-k:k + 1, -k:k + 1]
    w = (dy ** 2 + dx ** 2 < radius * radius).astype(float)
    return math.sqrt(np.sum(signal.convolve(w, kernel) ** 2) / w.sum())


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
    assert 29.1 <= sep_depth <= 29.7                   # the 29.1-29.5
    for bs, r in rows.items():
        assert abs(r["depth_model"] - sep_depth) <= 0.3, (bs, r["depth_model"], sep_depth)
        assert max(r["ratio"]) < 2.5            # before: 7.17 (64)
        # m50 against sep's depth: 1.9 mag brighter (S/N >= 8 in isophotes of extended
        # sources; completeness levelling at ~0.65), the same for both meshes (module docstring
        # of benchmarks/hff_noise.py): bounded here, not equal.
        assert 1.0 <= sep_depth - r["m50"] <= 2.5


# ------------------------------------------------------------------------------
# Field set-up with bounded memory gives the same answers.
# ------------------------------------------------------------------------------
def _mask(shape=(97, 83), seed=0):
    rng = np.random.default_rng(seed)
    usable = rng.uniform(size=shape) > 0.004
    usable[40:60, 10:30] = False                     # a large hole: distances up to ~40 px
    usable = ~ndimage.binary_dilation(~usable, iterations=1)
    return usable


@pytest.mark.parametrize("rows", [1, 4, 13, 200])
def test_capped_tiled_distance_is_the_capped_whole_image_one(rows):
    usable = _mask()
    whole = ndimage.distance_transform_edt(np.pad(usable, 1))[1:-1, 1:-1]
    for cap in (3.7, 13.2):
        d = empty_sky_distance(usable, cap=cap, tile_rows=rows)
        assert np.array_equal(d, np.minimum(whole, cap))
        assert d.max() == cap                        # some pixels are farther than the cap
    # Independent: brute-force distance to the nearest unusable pixel (the border counts).
    ys, xs = np.nonzero(usable)
    pad = np.pad(usable, 1)
    zy, zx = np.nonzero(~pad)
    d = empty_sky_distance(usable, cap=13.2, tile_rows=rows)
    for y, x in zip(ys[::701], xs[::701]):
        brute = np.sqrt(np.min((zy - 1 - y) ** 2 + (zx - 1 - x) ** 2))
        assert d[y, x] == min(brute, 13.2)


def _sky_field():
    """A noise image, unit RMS and a usable-sky mask with holes, for the empty apertures."""
    rng = np.random.default_rng(3)
    usable = _mask((120, 110), seed=2)
    img = rng.standard_normal(usable.shape).astype(np.float32)
    return img, np.full(usable.shape, 1.0, np.float32), usable


def test_empty_aperture_scatter_unchanged_by_the_capped_map():
    img, rms, usable = _sky_field()
    radii = DEFAULT_EMPTY_APERTURE_RADII_PIX
    uncapped = empty_sky_distance(usable)
    capped = empty_sky_distance(usable, cap=distance_cap(radii), tile_rows=7)
    outs = [empty_aperture_scatter(img, rms, usable, radii, 150, np.random.default_rng(5), distance=d)
            for d in (uncapped, capped, None)]
    for out in outs[1:]:
        for a, b in zip(outs[0], out):
            assert np.array_equal(a, b)
    assert outs[0][0].size >= 5                      # several radii measured
    with pytest.raises(ValueError, match="cap"):
        empty_sky_distance(usable, cap=0.0)


def test_empty_aperture_centres_by_chunks_are_unchanged(monkeypatch):
    """Candidate centres taken by chunks of 37 pixels (int32): the same apertures as at once."""
    from glaciar.engine import noise

    rng = np.random.default_rng(8)
    usable = _mask((80, 90), seed=4)
    img = rng.standard_normal(usable.shape).astype(np.float32)
    rms = np.full(usable.shape, 1.0, np.float32)
    radii = (0.5, 2.2, 4.2, 8.2)
    whole = noise.empty_aperture_scatter(img, rms, usable, radii, 120, np.random.default_rng(1))
    flat = empty_sky_distance(usable).ravel()
    monkeypatch.setattr(noise, "_CHUNK", 37)
    got = noise._indices_beyond(flat, 3.2, np.int32)
    assert got.dtype == np.int32 and np.array_equal(got, np.flatnonzero(flat > 3.2))
    assert np.array_equal(noise._keep_beyond(flat, got, 5.2), np.flatnonzero(flat > 5.2))
    chunked = noise.empty_aperture_scatter(img, rms, usable, radii, 120, np.random.default_rng(1))
    for a, b in zip(whole, chunked):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("rows", [1, 2, 5, 500])
def test_source_margin_by_tiles_is_the_whole_frame_dilation(rows):
    from glaciar.engine.noise import source_margin

    rng = np.random.default_rng(5)
    seg = np.zeros((70, 64), np.int32)
    seg[rng.uniform(size=seg.shape) < 0.01] = 7
    seg[30:33, 0:5] = 2
    seg[0, 63] = seg[69, 0] = 3                        # sources at the image's corners
    for margin in (1, 3):
        want = ndimage.binary_dilation(seg > 0, iterations=margin)
        assert np.array_equal(source_margin(seg, margin, tile_rows=rows), want)
    with pytest.raises(ValueError, match="margin"):
        source_margin(seg, 0)


@pytest.mark.parametrize("rows", [1, 3, 11, 400])
def test_empty_sky_centres_are_the_whole_image_distance_comparisons(rows):
    """EmptySky.beyond(limit): the pixels whose whole-image (uncapped, scipy in one call)
    distance to an unusable pixel exceeds the limit, ascending."""
    from glaciar.engine.noise import empty_sky

    usable = _mask()
    whole = ndimage.distance_transform_edt(np.pad(usable, 1))[1:-1, 1:-1].ravel()
    limits = [r + 1.0 for r in DEFAULT_EMPTY_APERTURE_RADII_PIX]
    sky = empty_sky(usable, limits, tile_rows=rows)
    assert sky.indices.dtype == np.int32
    for lim in limits:
        want = np.flatnonzero(whole > lim)
        assert np.array_equal(sky.beyond(lim), want), lim
    assert sky.beyond(limits[-1]).size > 0              # the hole's middle is far from all


def test_empty_aperture_scatter_with_empty_sky_centres_is_unchanged():
    from glaciar.engine.noise import empty_sky

    img, rms, usable = _sky_field()
    radii = DEFAULT_EMPTY_APERTURE_RADII_PIX
    want = empty_aperture_scatter(img, rms, usable, radii, 150, np.random.default_rng(5),
                                  distance=empty_sky_distance(usable))
    sky = empty_sky(usable, [r + 1.0 for r in radii], tile_rows=7)
    got = empty_aperture_scatter(img, rms, usable, radii, 150, np.random.default_rng(5), sky=sky)
    for a, b in zip(want, got):
        assert np.array_equal(a, b)
    assert want[0].size >= 5
