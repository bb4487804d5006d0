"""Tests of the embedded demo survey (glaciar.demo)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from glaciar.config import template_yaml
from astropy.io import fits
from astropy.wcs import WCS

from glaciar.demo import sky as demo_sky
from glaciar.demo import strips as demo_strips
from glaciar.demo import survey as demo_survey
from glaciar.demo import (DEMO_BANDS, DEMO_BANDS_SPEC, DEMO_FIELD, build_demo_survey,
                          drizzle_noise_kernel, make_demo_images)
from glaciar.galaxy.psf import moffat_psf, read_psf

SHAPE = (300, 300)
SCHEMA = Path(__file__).resolve().parents[2] / "docs" / "config-schema.yaml"


@pytest.fixture(scope="module")
def scene():
    return make_demo_images(SHAPE, seed=7)


@pytest.fixture(scope="module")
def noise_only():
    """Source-free realisation: science is pure background noise."""
    return make_demo_images(SHAPE, seed=11, source_density_arcmin2=0.0, n_stars=0)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    path = build_demo_survey(out, shape=SHAPE, seed=5, n_galaxies=20, n_iterations=3)
    return path


def _normalised_noise(images, band):
    """science * sqrt(weight): unit per-pixel variance if the weight map is right."""
    w = images["weight"][band].astype(np.float64)
    s = images["science"][band].astype(np.float64)
    z = np.where(w > 0, s * np.sqrt(np.where(w > 0, w, 1.0)), 0.0)
    return z, w > 0


# --------------------------------------------------------------------------
# determinism
# --------------------------------------------------------------------------
def test_same_seed_identical_different_seed_different(scene):
    again = make_demo_images(SHAPE, seed=7)
    other = make_demo_images(SHAPE, seed=8)
    for b in DEMO_BANDS:
        assert np.array_equal(scene["science"][b], again["science"][b])
        assert np.array_equal(scene["weight"][b], again["weight"][b])
        assert not np.array_equal(scene["science"][b], other["science"][b])
    for col in scene["truth"].colnames:
        a, b = np.asarray(scene["truth"][col]), np.asarray(again["truth"][col])
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    assert not np.array_equal(np.asarray(scene["truth"]["x"]), np.asarray(other["truth"]["x"]))


def test_output_types(scene):
    for b in DEMO_BANDS:
        assert scene["science"][b].dtype == np.float32 and scene["science"][b].shape == SHAPE
        assert scene["weight"][b].dtype == np.float32 and scene["weight"][b].shape == SHAPE
        assert scene["psf"][b].dtype == np.float64
        assert scene["psf"][b].sum() == pytest.approx(1.0, abs=1e-12)
        assert scene["psf_pixel_scale_arcsec"][b] == DEMO_BANDS_SPEC[b].psf_pixel_scale_arcsec


# --------------------------------------------------------------------------
# noise and weights
# --------------------------------------------------------------------------
@pytest.mark.parametrize("band", DEMO_BANDS)
def test_weight_map_gives_per_pixel_variance(noise_only, band):
    z, valid = _normalised_noise(noise_only, band)
    assert np.std(z[valid]) == pytest.approx(1.0, rel=0.03)
    # Also in the low-weight parts alone (dithered edges, stripe, blobs): the weight
    # map must follow the exposure, not just be right on average.
    w = noise_only["weight"][band]
    low = valid & (w < 0.75 * np.median(w[valid]))
    assert low.sum() > 2000
    assert np.std(z[low]) == pytest.approx(1.0, rel=0.05)


@pytest.mark.parametrize("band", ["f160w", "f098m", "f125w"])
def test_ir_noise_is_correlated_like_drizzle(noise_only, band):
    z, valid = _normalised_noise(noise_only, band)
    spec = DEMO_BANDS_SPEC[band]
    # Independent expectation: drop side d (output pixels) overlaps each neighbour by
    # t = (d - 1) / 2, so the 1-D kernel is (t, 1, t) and rho(1) = 2t / (1 + 2t^2).
    d = spec.pixfrac * spec.native_pixel_arcsec / 0.08
    t = (d - 1.0) / 2.0
    rho = 2 * t / (1 + 2 * t * t)
    both_x = valid[:, 1:] & valid[:, :-1]
    both_y = valid[1:, :] & valid[:-1, :]
    rho_x = np.mean((z[:, 1:] * z[:, :-1])[both_x])
    rho_y = np.mean((z[1:, :] * z[:-1, :])[both_y])
    assert rho > 0.2
    assert rho_x == pytest.approx(rho, abs=0.02)
    assert rho_y == pytest.approx(rho, abs=0.02)


def test_uvis_noise_nearly_white(noise_only):
    z, valid = _normalised_noise(noise_only, "f606w")
    both = valid[:, 1:] & valid[:, :-1]
    assert abs(np.mean((z[:, 1:] * z[:, :-1])[both])) < 0.02


def test_drizzle_kernel_unit_power():
    k = drizzle_noise_kernel(0.1283, 0.8, 0.08)
    assert np.sum(k ** 2) == pytest.approx(1.0, rel=1e-12)
    assert k.shape == (3, 3) and np.allclose(k, k.T) and np.allclose(k, k[::-1, ::-1])
    assert drizzle_noise_kernel(0.0396, 0.8, 0.08).shape == (1, 1)
    with pytest.raises(ValueError, match="pixfrac"):
        drizzle_noise_kernel(0.13, 1.5)


@pytest.mark.parametrize("band", DEMO_BANDS)
def test_stated_depth_holds_in_apertures(noise_only, band):
    """A point source at depth_5sigma has S/N = 5 in an r = 0.2" aperture at exposure 1."""
    import sep

    z, valid = _normalised_noise(noise_only, band)
    r = 0.2 / 0.08
    yc, xc = np.mgrid[8:SHAPE[0] - 8:6, 8:SHAPE[1] - 8:6]
    yc, xc = yc.ravel(), xc.ravel()
    # Keep apertures whose whole box has data.
    ok = np.array([valid[y - 3:y + 4, x - 3:x + 4].all() for y, x in zip(yc, xc)])
    assert ok.sum() > 1500
    sums, _, _ = sep.sum_circle(z, xc[ok].astype(float), yc[ok].astype(float), r)
    noise_factor = np.std(sums)       # aperture noise in units of the per-pixel RMS
    if band != "f606w":
        # Correlated noise: apertures are noisier than sqrt(N_pix) independent pixels.
        assert noise_factor > 1.25 * math.sqrt(math.pi * r * r)
    spec = DEMO_BANDS_SPEC[band]
    psf = moffat_psf(spec.psf_fwhm_arcsec, 0.08, beta=2.5, size=61)
    ee, _, _ = sep.sum_circle(psf, np.array([30.0]), np.array([30.0]), r)
    sigma_ap = noise_factor * noise_only["rms_nominal"][band]
    m_lim = spec.zeropoint - 2.5 * math.log10(5 * sigma_ap / ee[0])
    assert m_lim == pytest.approx(spec.depth_5sigma, abs=0.05)
    # The nominal exposure is the typical one: the weight at full coverage is within
    # the +-~15 % exposure gradient of 1 / rms_nominal^2.
    w = noise_only["weight"][band]
    central = w[SHAPE[0] // 3:2 * SHAPE[0] // 3, SHAPE[1] // 3:2 * SHAPE[1] // 3]
    ratio = np.median(central) * noise_only["rms_nominal"][band] ** 2
    assert 0.85 < ratio < 1.15


def test_zero_weight_border_and_varying_weights(scene):
    masks = [scene["weight"][b] > 0 for b in DEMO_BANDS]
    for b, valid in zip(DEMO_BANDS, masks):
        w, s = scene["weight"][b], scene["science"][b]
        assert np.all(s[~valid] == 0.0)
        assert np.all(w >= 0)
        # No data along the image edges and in the corners (tilted footprint).
        assert not valid[0].any() and not valid[-1].any()
        assert not valid[:, 0].any() and not valid[:, -1].any()
        assert not valid[:10, :10].any() and not valid[-10:, -10:].any()
        assert 0.7 < valid.mean() < 0.95
        # Weights vary inside the footprint: gradient, dithered edges (1/3, 2/3 depth).
        wv = w[valid]
        assert np.percentile(wv, 99) / np.percentile(wv, 1) > 2.0
        assert np.std(wv) / np.mean(wv) > 0.08
        # Science is noisy where there are data.
        assert np.all(np.isfinite(s)) and np.count_nonzero(s[valid]) == valid.sum()
    # One footprint for all bands (the detection band's).
    for m in masks[1:]:
        assert np.array_equal(m, masks[0])


def test_f606w_chip_gap_stripe_is_half_depth(scene):
    ratio = scene["weight"]["f606w"] / np.where(scene["weight"]["f160w"] > 0,
                                                  scene["weight"]["f160w"], np.inf)
    valid = scene["weight"]["f160w"] > 0
    # The stripe is a 4 %-high band: its pixels have half the F606W/F160W weight ratio.
    r = ratio[valid]
    hi = np.median(r)
    lo = r < 0.7 * hi
    assert 0.02 < lo.mean() < 0.08
    assert np.median(r[lo]) / hi == pytest.approx(0.5, rel=0.15)


# --------------------------------------------------------------------------
# sources
# --------------------------------------------------------------------------
def test_requested_numbers_of_galaxies_and_stars():
    images = make_demo_images(SHAPE, seed=3, n_galaxies=37, n_stars=5)
    truth = images["truth"]
    assert len(truth) == 42
    assert int(np.sum(truth["is_star"])) == 5
    # Everything sits inside the footprint.
    valid = images["weight"]["f160w"] > 0
    iy = np.rint(np.asarray(truth["y"])).astype(int)
    ix = np.rint(np.asarray(truth["x"])).astype(int)
    assert valid[iy, ix].all()
    gal = ~np.asarray(truth["is_star"])
    assert np.all((truth["sersic_n"][gal] >= 0.5) & (truth["sersic_n"][gal] <= 4.0))
    assert np.all((truth["axis_ratio"][gal] > 0) & (truth["axis_ratio"][gal] <= 1))
    assert np.all(truth["r_eff_pix"][gal] == pytest.approx(truth["r_eff_arcsec"][gal] / 0.08))


def test_default_density(scene):
    valid = scene["weight"]["f160w"] > 0
    area_arcmin2 = valid.sum() * (0.08 / 60) ** 2
    n_gal = int(np.sum(~np.asarray(scene["truth"]["is_star"])))
    assert n_gal == round(250.0 * area_arcmin2)
    with pytest.raises(ValueError, match="confusion"):
        make_demo_images(SHAPE, source_density_arcmin2=5000.0)


def test_number_counts_follow_broken_power_law():
    mag = demo_sky._sample_counts_magnitudes(np.random.default_rng(0), 200_000)
    assert mag.min() >= 19.0 and mag.max() <= 29.0
    # Independent CDF: trapezoidal integral of 10^(0.3(m-25)) / 10^(0.15(m-25)).
    grid = np.linspace(19.0, 29.0, 100_001)
    dndm = np.where(grid < 25.0, 10 ** (0.3 * (grid - 25)), 10 ** (0.15 * (grid - 25)))
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dndm[1:] + dndm[:-1]) * np.diff(grid))])
    cdf /= cdf[-1]
    for m in (21.0, 24.0, 25.0, 26.5, 28.0):
        assert np.mean(mag < m) == pytest.approx(np.interp(m, grid, cdf), abs=0.004)


def test_colours_make_some_galaxies_bright_in_f606w(scene):
    t = scene["truth"]
    gal = ~np.asarray(t["is_star"])
    v_minus_h = np.asarray(t["mag_f606w"] - t["mag_f160w"])[gal]
    assert np.any(v_minus_h < 0.6) and np.any(v_minus_h > 2.0)


def test_stars_are_the_psf_with_the_catalogue_flux():
    """Each band's star = flux x that band's PSF sampled at the pixel centre (zeropoints, PSFs)."""
    images = make_demo_images(SHAPE, seed=4, n_galaxies=0, n_stars=3)
    t = images["truth"]
    for b in DEMO_BANDS:
        spec = DEMO_BANDS_SPEC[b]
        psf = moffat_psf(spec.psf_fwhm_arcsec, 0.08, beta=2.5, size=61)
        for row in t:
            flux = 10 ** (-0.4 * (row[f"mag_{b}"] - spec.zeropoint))
            peak = images["model"][b][int(row["y"]), int(row["x"])]
            assert peak == pytest.approx(flux * psf[30, 30], rel=2e-3)


def test_background_sersic_renderer():
    # Round n = 1 profile: half the flux inside r_e (truncation at 5 r_e drops 0.04 %).
    y0, x0, img = demo_sky.sersic_stamp_fast(50.0, 50.0, 8.0, 1.0, 1.0, 0.0, (101, 101))
    assert img.sum() == pytest.approx(1.0, rel=1e-12)
    yy, xx = np.mgrid[y0:y0 + img.shape[0], x0:x0 + img.shape[1]]
    rr = np.hypot(xx - 50.0, yy - 50.0)
    assert img[rr < 8.0].sum() == pytest.approx(0.5, abs=0.02)
    # q = 0.4 at PA 0: elongated along x; at PA 90: along y.
    for pa, axis in ((0.0, "x"), (90.0, "y")):
        y0, x0, img = demo_sky.sersic_stamp_fast(50.0, 50.0, 6.0, 1.0, 0.4, pa, (101, 101))
        yy, xx = np.mgrid[y0:y0 + img.shape[0], x0:x0 + img.shape[1]]
        vx = np.sum(img * (xx - 50.0) ** 2)
        vy = np.sum(img * (yy - 50.0) ** 2)
        assert (vx > 4 * vy) if axis == "x" else (vy > 4 * vx)
    # A stamp at the image edge is clipped, a stamp off the image is dropped.
    assert demo_sky.sersic_stamp_fast(-500.0, 50.0, 2.0, 1.0, 1.0, 0.0, (101, 101)) is None


def test_bad_arguments():
    with pytest.raises(ValueError, match="64"):
        make_demo_images((20, 300))
    with pytest.raises(ValueError, match=">= 0"):
        make_demo_images(SHAPE, n_stars=-1)


# --------------------------------------------------------------------------
# files and config
# --------------------------------------------------------------------------
def _keys_follow_schema(cfg, schema, where=""):
    """Every key of the demo config is documented in docs/config-schema.yaml."""
    for key, value in cfg.items():
        entry = schema.get(key)
        assert entry is not None, f"{where}{key} is not in docs/config-schema.yaml"
        keys = entry.get("keys") or entry.get("each band") or entry.get("axis keys")
        if isinstance(value, dict) and keys is not None and key != "bands":
            _keys_follow_schema(value, keys, f"{where}{key}.")


def test_config_follows_schema_and_references_existing_files(survey):
    cfg = yaml.safe_load(survey.read_text())
    schema = yaml.safe_load(SCHEMA.read_text())
    _keys_follow_schema(cfg, schema)
    band_keys = set(schema["survey"]["keys"]["bands"]["each band"])
    base = survey.parent
    sv = cfg["survey"]
    assert sv["fields"] == [DEMO_FIELD]
    assert sv["detection_band"] == "f160w" and sv["noise_type"] == "weight"
    assert list(sv["bands"]) == list(DEMO_BANDS)
    for b, bcfg in sv["bands"].items():
        assert set(bcfg) <= band_keys
        assert bcfg["filter"] == DEMO_BANDS_SPEC[b].filter
        assert bcfg["zeropoint"] == DEMO_BANDS_SPEC[b].zeropoint
        assert 2000 <= bcfg["gain"] <= 5000
        for template in (sv["science"], sv["noise"]):
            assert (base / sv["image_dir"] / template.format(field=DEMO_FIELD, band=b)).is_file()
        assert (base / bcfg["psf"]).is_file()
    assert cfg["grid"]["z"]["values"] == pytest.approx(list(np.arange(7.8, 12.61, 0.4)) + [12.9])
    assert cfg["grid"]["mag"]["values"] == pytest.approx(list(np.arange(24.5, 28.51, 0.5)))
    assert cfg["simulation"] == {"n_galaxies": 20, "n_iterations": 3, "seed": 5}
    assert cfg["classification"]["min_sn"] == 8.0
    # The demo states the documented defaults explicitly.
    template = yaml.safe_load(template_yaml())
    assert cfg["selection"] == template["selection"]
    for section in ("detection", "source"):
        for key, value in cfg[section].items():
            assert value == schema[section]["keys"][key]["default"], (section, key)
    assert survey.read_text().startswith("#")
    # Atomic writes leave no temporary files behind.
    assert not list(base.rglob("*.tmp"))


def test_fits_files_round_trip_with_wcs(survey):
    base = survey.parent
    images = make_demo_images(SHAPE, seed=5)
    for b in DEMO_BANDS:
        with fits.open(base / "images" / f"{DEMO_FIELD}_{b}_drz.fits") as hdul:
            data, hdr = hdul[0].data, hdul[0].header
            assert data.dtype.kind == "f" and data.dtype.itemsize == 4
            assert np.array_equal(data, images["science"][b])
            assert hdr["BUNIT"] == "ELECTRONS/S"
            assert hdr["MAGZPT"] == DEMO_BANDS_SPEC[b].zeropoint
            wcs = WCS(hdr)
            assert wcs.wcs.ctype[0] == "RA---TAN" and wcs.wcs.ctype[1] == "DEC--TAN"
            scales = wcs.proj_plane_pixel_scales()
            assert [s.to_value("arcsec") for s in scales] == pytest.approx([0.08, 0.08], rel=1e-9)
        with fits.open(base / "images" / f"{DEMO_FIELD}_{b}_wht.fits") as hdul:
            assert np.array_equal(hdul[0].data, images["weight"][b])


def test_psf_files_carry_their_pixel_scale(survey):
    base = survey.parent
    cfg = yaml.safe_load(survey.read_text())
    for b in DEMO_BANDS:
        path = base / cfg["survey"]["bands"][b]["psf"]
        psf, scale = read_psf(path)                 # scale from the header
        expected = 0.04 if b == "f606w" else 0.13
        assert scale == expected != 0.08
        assert fits.getheader(path)["PIXSCALE"] == expected
        assert cfg["survey"]["bands"][b]["psf_pixel_scale_arcsec"] == expected
        spec = DEMO_BANDS_SPEC[b]
        assert np.allclose(psf, moffat_psf(spec.psf_fwhm_arcsec, expected, beta=2.5,
                                           size=spec.psf_size), rtol=0, atol=1e-12)


# --------------------------------------------------------------------------
# the strip path (large mosaics), forced on small fields
# --------------------------------------------------------------------------
STRIP_SHAPE = (230, 200)
STRIP_ROWS = 23                    # 10 strips: galaxies, PSF wings and noise cross their seams


def _assemble(strips, shape=STRIP_SHAPE):
    """Whole images from iter_demo_strips' strips, checking they tile the rows once, in order."""
    science, weight, edges = {b: [] for b in DEMO_BANDS}, {b: [] for b in DEMO_BANDS}, []
    for y0, y1, s, w in strips:
        edges.append((y0, y1))
        for b in DEMO_BANDS:
            assert s[b].dtype == np.float32 and s[b].shape == (y1 - y0, shape[1])
            science[b].append(s[b])
            weight[b].append(w[b])
    assert edges[0][0] == 0 and edges[-1][1] == shape[0]
    assert all(a[1] == b[0] for a, b in zip(edges, edges[1:]))
    return ({b: np.concatenate(v) for b, v in science.items()},
            {b: np.concatenate(v) for b, v in weight.items()})


@pytest.fixture(scope="module")
def strip_noise_survey(tmp_path_factory, request):
    """A source-free survey written by build_demo_survey through the strip path."""
    mp = pytest.MonkeyPatch()
    request.addfinalizer(mp.undo)
    mp.setattr(demo_strips, "STRIP_MIN_PIXELS", 0)
    mp.setattr(demo_strips, "STRIP_PIXELS", STRIP_ROWS * STRIP_SHAPE[1])
    out = tmp_path_factory.mktemp("strips")
    path = build_demo_survey(out, shape=STRIP_SHAPE, seed=21, source_density_arcmin2=0.0, n_stars=0)
    images = {"science": {}, "weight": {}}
    for b in DEMO_BANDS:
        for kind, name in (("science", "drz"), ("weight", "wht")):
            images[kind][b] = fits.getdata(out / "images" / f"{DEMO_FIELD}_{b}_{name}.fits")
    return path, images


@pytest.mark.parametrize("band", DEMO_BANDS)
def test_strip_path_noise_matches_weight_maps(strip_noise_survey, band):
    path, images = strip_noise_survey
    z, valid = _normalised_noise(images, band)
    assert valid.sum() > 30000
    assert np.std(z[valid]) == pytest.approx(1.0, rel=0.03)
    # Drizzle correlation along y also across the strip seams (rows y0 - 1, y0): the
    # independent expectation rho(1) = 2t / (1 + 2t^2) of test_ir_noise_is_correlated_like_drizzle.
    spec = DEMO_BANDS_SPEC[band]
    d = spec.pixfrac * spec.native_pixel_arcsec / 0.08
    t = max(d - 1.0, 0.0) / 2.0
    rho = 2 * t / (1 + 2 * t * t)
    both_y = valid[1:, :] & valid[:-1, :]
    assert np.mean((z[1:, :] * z[:-1, :])[both_y]) == pytest.approx(rho, abs=0.03)
    seams = np.arange(STRIP_ROWS, STRIP_SHAPE[0], STRIP_ROWS)
    pairs = (z[seams] * z[seams - 1])[valid[seams] & valid[seams - 1]]
    assert pairs.size > 1000
    assert np.mean(pairs) == pytest.approx(rho, abs=4.0 / math.sqrt(pairs.size))


def test_strip_path_files_and_config(strip_noise_survey):
    path, images = strip_noise_survey
    base = path.parent
    assert not list(base.rglob("*.tmp"))
    cfg = yaml.safe_load(path.read_text())
    assert cfg["simulation"]["seed"] == 21
    for b in DEMO_BANDS:
        with fits.open(base / "images" / f"{DEMO_FIELD}_{b}_drz.fits") as hdul:
            assert len(hdul) == 1 and hdul[0].data.shape == STRIP_SHAPE
            assert hdul[0].header["MAGZPT"] == DEMO_BANDS_SPEC[b].zeropoint
            assert WCS(hdul[0].header).pixel_shape == (STRIP_SHAPE[1], STRIP_SHAPE[0])
        assert (base / "psf" / f"psf_{b}.fits").is_file()
    # The same weights as the whole-image generator (elementwise maps, bit for bit).
    whole = make_demo_images(STRIP_SHAPE, seed=21, source_density_arcmin2=0.0, n_stars=0)
    for b in DEMO_BANDS:
        assert np.array_equal(images["weight"][b], whole["weight"][b])


def test_strip_writer_bytes_equal_whole_image_writer(tmp_path):
    """The streamed FITS file is the file the whole-image writer produces."""
    data = np.random.default_rng(0).standard_normal((97, 61)).astype(np.float32)
    header = demo_survey._image_header(data.shape, "f125w", 0.08, "science")
    w = demo_survey._FitsRowWriter(tmp_path / "x.fits", data.shape, header)
    for y0 in range(0, 97, 10):
        w.write(data[y0:y0 + 10])
    w.commit()
    assert (tmp_path / "x.fits").read_bytes() == demo_survey._fits_bytes(data, header)
    # An interrupted write leaves nothing behind.
    w = demo_survey._FitsRowWriter(tmp_path / "y.fits", data.shape, header)
    w.write(data[:10])
    w.discard()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.fits"]


def test_strip_path_source_fluxes_match_truth():
    """Box sums of isolated sources in the strip-built images = catalogue flux (zeropoints)."""
    shape = (360, 340)
    info, strips = demo_strips.iter_demo_strips(shape, seed=9, n_galaxies=6, n_stars=3,
                                                noise_scale=1e-4, strip_rows=STRIP_ROWS)
    science, weight = _assemble(strips, shape)
    t = info["truth"]
    x, y = np.asarray(t["x"]), np.asarray(t["y"])
    # Box: the 5 r_e truncated profile (+ rounding) plus the 61-px rendering PSF's half-width.
    half = np.ceil(5.0 * np.asarray(t["r_eff_pix"])).astype(int) + 2 + 30
    valid = weight["f160w"] > 0
    checked = 0
    for i in range(len(t)):
        ya, yb = int(round(y[i])) - half[i], int(round(y[i])) + half[i] + 1
        xa, xb = int(round(x[i])) - half[i], int(round(x[i])) + half[i] + 1
        if ya < 0 or xa < 0 or yb > shape[0] or xb > shape[1] or not valid[ya:yb, xa:xb].all():
            continue
        others = np.delete(np.arange(len(t)), i)
        near = (np.abs(x[others] - x[i]) < half[i] + half[others]) & \
               (np.abs(y[others] - y[i]) < half[i] + half[others])
        if near.any():
            continue
        for b in DEMO_BANDS:
            spec = DEMO_BANDS_SPEC[b]
            flux = 10 ** (-0.4 * (t[f"mag_{b}"][i] - spec.zeropoint))
            measured = float(np.sum(science[b][ya:yb, xa:xb], dtype=np.float64))
            # Shot noise of the box sum (exposure >= 1/3 of nominal), and the Moffat wing
            # beyond the 61-px rendering PSF's normalisation (< 1e-3).
            tol = 5.0 * math.sqrt(flux / (spec.exptime_s / 3.0)) + 1e-3 * flux
            assert measured == pytest.approx(flux, abs=tol), (i, b)
        checked += 1
    assert checked >= 2


def test_strip_path_is_the_whole_image_field():
    """Same catalogue and weights bit for bit, science within float32 rounding (FFT order)."""
    kw = dict(seed=9, n_galaxies=25, n_stars=4, noise_scale=np.linspace(0.5, 2.0, 230 * 200).reshape(230, 200))
    whole = make_demo_images(STRIP_SHAPE, **kw)
    info, strips = demo_strips.iter_demo_strips(STRIP_SHAPE, strip_rows=STRIP_ROWS, **kw)
    science, weight = _assemble(strips)
    for col in whole["truth"].colnames:
        a, b = np.asarray(whole["truth"][col]), np.asarray(info["truth"][col])
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), col
    for b in DEMO_BANDS:
        assert np.array_equal(weight[b], whole["weight"][b])
        assert info["rms_nominal"][b] == whole["rms_nominal"][b]
        assert np.allclose(science[b], whole["science"][b], rtol=2e-7, atol=1e-7 * whole["model"][b].max())
    with pytest.raises(ValueError, match="strip_rows"):
        demo_strips.iter_demo_strips(STRIP_SHAPE, strip_rows=0)
