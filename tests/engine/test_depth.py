"""Local depth: the map against independent computations, its histogram, and its wiring.

Independent references: pixel-disk overlap areas by adaptive quadrature of the
chord length (not the closed form of glaciar.engine.depth), aperture sums by
direct loops over pixels (not FFTs), and the demo fields' known noise factors.
"""
import functools
import json
import math
import warnings

import numpy as np
import pytest
from scipy.integrate import quad

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.engine.depth import depth_area_histogram, depth_at, disk_pixel_weights, local_depth_map
from glaciar.execute import simulate
from glaciar.fieldprep import build_field_context
from glaciar.manifest import prepare_run_dir
from glaciar.store import read_results
from glaciar.rundir import read_manifest
from glaciar.survey import Survey

ZP = 25.946


@functools.lru_cache(maxsize=None)
def _overlap_quad(ix, iy, r):
    """Area of pixel (ix, iy) (centred on integers) inside the disk of radius r at 0, by quadrature."""
    def chord(x):
        h = math.sqrt(max(r * r - x * x, 0.0))
        return max(0.0, min(iy + 0.5, h) - max(iy - 0.5, -h))
    a, b = max(ix - 0.5, -r), min(ix + 0.5, r)
    if a >= b:
        return 0.0
    return quad(chord, a, b, epsabs=1e-13, epsrel=1e-13, limit=200)[0]


def _brute_depth(rms, valid, y, x, r, zp=ZP, nsigma=C.DEPTH_NSIGMA):
    """The documented definition, by a loop over the pixels of the aperture."""
    h = int(math.ceil(r)) + 1
    w_all = num = den = 0.0
    for dy in range(-h, h + 1):
        for dx in range(-h, h + 1):
            w = _overlap_quad(dx, dy, r)
            if w == 0.0:
                continue
            w_all += w
            yy, xx = y + dy, x + dx
            if 0 <= yy < rms.shape[0] and 0 <= xx < rms.shape[1] and valid[yy, xx]:
                num += w * rms[yy, xx] ** 2
                den += w
    return zp - 2.5 * math.log10(nsigma * math.sqrt(w_all * num / den))


@pytest.mark.parametrize("r", [0.4, 1.0, 2.5, 3.3])
def test_disk_weights_are_the_exact_overlap_areas(r):
    w = disk_pixel_weights(r)
    h = w.shape[0] // 2
    ref = np.array([[_overlap_quad(ix, iy, r) for ix in range(-h, h + 1)] for iy in range(-h, h + 1)])
    np.testing.assert_allclose(w, ref, atol=1e-11)
    assert w.sum() == pytest.approx(math.pi * r * r, rel=1e-12)
    # The kernel's outer ring is needed (else it would be one pixel too big).
    assert w[0].max() > 0


def test_uniform_rms_gives_the_analytic_depth():
    """sigma_ap = sigma sqrt(pi r^2) everywhere, edges and holes included.

    The weights are exact, so the only error is the float32 output: 1e-5 mag.
    """
    sigma, r = 0.0123, 2.7
    valid = np.ones((60, 70), bool)
    valid[20:30, 25:40] = False            # a hole: the mean of rms^2 over valid pixels is unchanged
    rms = np.where(valid, sigma, np.inf)
    d = local_depth_map(rms, valid, ZP, r)
    assert d.dtype == np.float32
    expect = ZP - 2.5 * math.log10(C.DEPTH_NSIGMA * sigma * math.sqrt(math.pi * r * r))
    np.testing.assert_allclose(d[valid], expect, atol=1e-5)
    assert np.isnan(d[~valid]).all()


def test_random_rms_matches_direct_aperture_sums():
    rng = np.random.default_rng(1)
    shape, r = (50, 61), 2.3
    rms = np.exp(rng.normal(-3.0, 0.5, shape))
    valid = np.ones(shape, bool)
    d = local_depth_map(rms, valid, ZP, r)
    ys, xs = rng.integers(0, shape[0], 20), rng.integers(0, shape[1], 20)
    ys[:2], xs[:2] = (0, shape[0] - 1), (0, shape[1] - 1)   # image corners: aperture cut by the edge
    for y, x in zip(ys, xs):
        assert d[y, x] == pytest.approx(_brute_depth(rms, valid, y, x, r), abs=1e-5)


def test_masked_pixels_are_not_data():
    rng = np.random.default_rng(2)
    shape, r = (45, 52), 3.1
    rms = np.exp(rng.normal(-2.0, 0.7, shape))
    valid = rng.uniform(size=shape) > 0.2
    valid[10:25, 30:] = False
    # What lies under the mask must not matter: garbage there (inf, NaN, 0, huge).
    garbage = rms.copy()
    garbage[~valid] = rng.choice([np.inf, np.nan, 0.0, 1e30], size=(~valid).sum())
    d = local_depth_map(garbage, valid, ZP, r)
    assert np.isnan(d[~valid]).all() and np.isfinite(d[valid]).all()
    ys, xs = np.nonzero(valid)
    pick = rng.choice(ys.size, 20, replace=False)
    # Include pixels right next to the masked block.
    near = np.flatnonzero(valid[9] & (np.arange(shape[1]) >= 30))[:3]
    for y, x in list(zip(ys[pick], xs[pick])) + [(9, int(x)) for x in near]:
        assert d[y, x] == pytest.approx(_brute_depth(rms, valid, y, x, r), abs=1e-5)


def test_bad_inputs_are_refused_and_empty_footprint_is_nan():
    rms = np.ones((8, 8))
    with pytest.raises(ValueError, match="non-finite or non-positive"):
        local_depth_map(np.where(np.eye(8, dtype=bool), 0.0, 1.0), np.ones((8, 8), bool), ZP, 1.0)
    with pytest.raises(ValueError, match="radius"):
        local_depth_map(rms, np.ones((8, 8), bool), ZP, 0.0)
    assert np.isnan(local_depth_map(rms, np.zeros((8, 8), bool), ZP, 1.0)).all()


@pytest.mark.parametrize("r", [2.3, 12.2])     # direct sums; FFT per tile (625 weights > 441)
def test_row_tiles_give_the_documented_map_at_their_seams(r):
    """Tiles of 1, 3 or 7 rows (halo = aperture half-width): the brute-force depth at the
    pixels next to every seam; with the direct sums, the same map bit for bit whatever the tiling."""
    rng = np.random.default_rng(4)
    shape = (41, 37)
    rms = np.exp(rng.normal(-2.5, 0.6, shape)).astype(np.float32)
    valid = rng.uniform(size=shape) > 0.15
    rms[~valid] = np.inf
    whole = local_depth_map(rms, valid, ZP, r, tile_rows=shape[0])
    # None: the footprint is where the rms is finite and positive.
    assert np.array_equal(local_depth_map(rms, None, ZP, r), whole, equal_nan=True)
    for rows in (1, 3, 7):
        d = local_depth_map(rms, valid, ZP, r, tile_rows=rows)
        if r < 10:
            assert np.array_equal(d, whole, equal_nan=True)
        assert np.array_equal(np.isnan(d), ~valid)
        seams = np.arange(rows, shape[0], rows)
        for y in np.unique(np.concatenate([seams, seams - 1]))[:8]:
            for x in np.flatnonzero(valid[y])[::9]:
                expect = _brute_depth(rms.astype(np.float64), valid, int(y), int(x), r)
                assert d[y, x] == pytest.approx(expect, abs=1e-5), (rows, y, x)
    with pytest.raises(ValueError, match="tile_rows"):
        local_depth_map(rms, valid, ZP, r, tile_rows=0)


def test_histogram_adds_up_to_the_footprint_on_the_lattice():
    rng = np.random.default_rng(3)
    d = rng.normal(27.0, 0.4, (80, 90)).astype(np.float32)
    d[rng.uniform(size=d.shape) < 0.3] = np.nan
    scale = 0.06
    edges, area = depth_area_histogram(d, scale)
    pix = (scale / 60.0) ** 2
    assert area.sum() == pytest.approx(np.isfinite(d).sum() * pix, rel=1e-12)
    assert edges.size == area.size + 1
    k = edges / C.DEPTH_BIN_MAG
    np.testing.assert_allclose(k, np.round(k), atol=1e-9)
    np.testing.assert_allclose(np.diff(edges), C.DEPTH_BIN_MAG, atol=1e-9)
    assert edges[0] <= np.nanmin(d) and np.nanmax(d) < edges[-1]
    counts, _ = np.histogram(d[np.isfinite(d)], bins=edges)
    np.testing.assert_allclose(area, counts * pix, rtol=1e-12)
    # Another field's histogram lies on the same lattice (shifted by whole bins).
    edges2, _ = depth_area_histogram(d + 0.731, scale)
    k2 = edges2 / C.DEPTH_BIN_MAG
    np.testing.assert_allclose(k2, np.round(k2), atol=1e-9)
    e0, a0 = depth_area_histogram(np.full((3, 3), np.nan), scale)
    assert e0.size == 0 and a0.size == 0


def test_depth_at_takes_the_pixel_containing_the_position():
    d = np.arange(12, dtype=np.float32).reshape(3, 4)
    x = np.array([0.0, 0.49, 0.5, 1.5, 3.49, -0.5, 3.5, 1.0])
    y = np.array([0.0, 0.0, 0.0, 2.4, 1.0, 1.0, 0.0, -0.51])
    np.testing.assert_array_equal(depth_at(d, x, y), [0, 0, 1, 10, 7, 4, np.nan, np.nan])


# --------------------------------------------------------------------------
# Wiring: field context, per-source column, manifest
# --------------------------------------------------------------------------
def _pixel_of(rows):
    """(row, col) of the pixel containing each source's input position: floor(v + 1/2)."""
    return (np.floor(rows[C.COL_Y].to_numpy() + 0.5).astype(int),
            np.floor(rows[C.COL_X].to_numpy() + 0.5).astype(int))


@pytest.fixture(scope="module")
def small_run(small_survey, tmp_path_factory):
    cfg = load_config(small_survey)
    out = tmp_path_factory.mktemp("depth_small")
    simulate(cfg, out, workers=1, progress=False, max_tasks=3)
    ctx = build_field_context(cfg, Survey.from_config(cfg), cfg.survey.fields[0])
    return cfg, out, ctx


def test_field_depth_is_the_documented_map(small_run):
    from glaciar.galaxy.psf import measure_fwhm, prepare_psf

    cfg, _, ctx = small_run
    det = cfg.survey.detection_band
    b = cfg.survey.band(det)
    psf = prepare_psf(b.psf, ctx.pixel_scale_arcsec, base_dir=cfg.base_dir,
                      psf_pixel_scale_arcsec=b.psf_pixel_scale_arcsec)
    r = C.DEPTH_APERTURE_RADIUS_FWHM * measure_fwhm(psf, 1.0)
    # The demo's detection noise map is 1/sqrt(weight), read independently here.
    from astropy.io import fits
    s = cfg.survey
    wht = fits.getdata(s.image_dir / s.noise.format(field=ctx.field, band=det)).astype(np.float64)
    valid = ctx.footprint
    rms = np.where(valid, 1.0 / np.sqrt(np.where(valid, wht, 1.0)), np.inf)
    np.testing.assert_array_equal(np.isfinite(ctx.depth), valid)
    rng = np.random.default_rng(4)
    ys, xs = np.nonzero(valid)
    for i in rng.choice(ys.size, 8, replace=False):
        assert ctx.depth[ys[i], xs[i]] == pytest.approx(
            _brute_depth(rms, valid, ys[i], xs[i], r, zp=b.zeropoint), abs=1e-4)


def test_every_source_carries_the_depth_under_it(small_run):
    cfg, out, ctx = small_run
    rows = read_results(out)
    assert len(rows) == 3 * cfg.simulation.n_galaxies
    iy, ix = _pixel_of(rows)
    np.testing.assert_array_equal(rows[C.COL_DEPTH].to_numpy(), ctx.depth[iy, ix].astype(np.float64))
    assert np.isfinite(rows[C.COL_DEPTH]).all()


def test_manifest_depth_area(small_run):
    cfg, out, ctx = small_run
    m = read_manifest(out)
    da = m["depth_area"][ctx.field]
    assert da["band"] == cfg.survey.detection_band and da["nsigma"] == C.DEPTH_NSIGMA
    assert da["rms_source"] == "noise_map"
    # The manifest's map and the workers' map are the same: same histogram.
    edges, area = np.array(da["bin_edges_mag"]), np.array(da["area_arcmin2"])
    counts, _ = np.histogram(ctx.depth[np.isfinite(ctx.depth)], bins=edges)
    np.testing.assert_allclose(area, counts * (ctx.pixel_scale_arcsec / 60) ** 2, rtol=1e-12)
    assert area.sum() == pytest.approx(m["area_arcmin2"][ctx.field], rel=1e-12)
    # r = 1 FWHM of the demo's 0.20" F160W Moffat (measure_fwhm: within a few %).
    assert da["aperture_radius_arcsec"] == pytest.approx(0.20 * C.DEPTH_APERTURE_RADIUS_FWHM, rel=0.05)


def test_old_manifest_gains_depth_area_without_refusal(small_run, tmp_path):
    import shutil

    cfg, out, _ = small_run
    run = tmp_path / "old"
    shutil.copytree(out, run)
    old = read_manifest(run)
    del old["depth_area"]
    old["glaciar_version"] = "0.0.old"
    (run / C.MANIFEST_NAME).write_text(json.dumps(old))
    stats = simulate(cfg, run, workers=1, progress=False, max_tasks=1)
    assert stats["n_done_before"] == 3 and stats["n_run"] == 1
    new = read_manifest(run)
    assert new["depth_area"] == read_manifest(out)["depth_area"]
    assert new["glaciar_version"] == "0.0.old"        # what the old manifest said stays


def _without_noise_map(config_path, tmp_path):
    import yaml

    d = yaml.safe_load(config_path.read_text())
    d["survey"]["noise"] = None
    d["survey"]["image_dir"] = str(config_path.parent / d["survey"]["image_dir"])
    for b in d["survey"]["bands"].values():
        b["psf"] = str(config_path.parent / b["psf"])
    p = tmp_path / "no_noise.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return load_config(p)


def _depth_warnings(record):
    return [w for w in record if "background RMS" in str(w.message)]


def test_background_rms_fallback_warns_once_per_run_and_field(small_survey, small_run, tmp_path):
    cfg = _without_noise_map(small_survey, tmp_path)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        # workers=1: every task's field context is built in this process too.
        simulate(cfg, tmp_path / "run", workers=1, progress=False, max_tasks=3)
    got = _depth_warnings(rec)
    assert len(got) == 1 and repr(cfg.survey.fields[0]) in str(got[0].message)
    m = read_manifest(tmp_path / "run")
    assert m["depth_area"][cfg.survey.fields[0]]["rms_source"] == "background"
    # sep's background RMS is the per-pixel RMS the weight map states: same depth to ~0.1 mag.
    rows = read_results(tmp_path / "run")
    ref = read_results(small_run[1])
    assert np.median(rows[C.COL_DEPTH]) == pytest.approx(np.median(ref[C.COL_DEPTH]), abs=0.1)


def test_background_rms_fallback_names_each_field(two_depth_survey, tmp_path):
    cfg = _without_noise_map(two_depth_survey, tmp_path)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        prepare_run_dir(cfg, tmp_path / "run", cfg.simulation.seed)
    got = [str(w.message) for w in _depth_warnings(rec)]
    assert len(got) == 2
    assert "'shallow'" in got[0] and "'deep'" in got[1]


def test_noise_map_gives_no_warning(small_survey, tmp_path):
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        prepare_run_dir(load_config(small_survey), tmp_path, 11)
    assert not _depth_warnings(rec)


# --------------------------------------------------------------------------
# The fixtures with depth contrasts
# --------------------------------------------------------------------------
def test_demo_noise_scale():
    from glaciar.demo import make_demo_images

    base = make_demo_images((96, 100), seed=5, n_galaxies=0, n_stars=0)
    same = make_demo_images((96, 100), seed=5, n_galaxies=0, n_stars=0, noise_scale=np.ones((96, 100)))
    for b in base["science"]:
        assert np.array_equal(base["science"][b], same["science"][b])
        assert np.array_equal(base["weight"][b], same["weight"][b])
    deep = make_demo_images((96, 100), seed=5, n_galaxies=0, n_stars=0, noise_scale=2.5)
    for b in base["science"]:
        np.testing.assert_allclose(deep["weight"][b], base["weight"][b] / 6.25, rtol=1e-6)
        # No sources: the science image is the sky noise alone, scaled exactly.
        np.testing.assert_allclose(deep["science"][b], 2.5 * base["science"][b], rtol=1e-6, atol=1e-12)
    with pytest.raises(ValueError, match="noise_scale"):
        make_demo_images((96, 100), noise_scale=np.ones((10, 10)))
    with pytest.raises(ValueError, match="noise_scale"):
        make_demo_images((96, 100), noise_scale=0.0)


def test_two_depth_fields_differ_by_one_magnitude(two_depth_survey, tmp_path):
    cfg = load_config(two_depth_survey)
    survey = Survey.from_config(cfg)
    assert cfg.survey.fields == ("shallow", "deep")
    area = {f: survey.footprint(f).sum() for f in cfg.survey.fields}
    assert area["deep"] / area["shallow"] == pytest.approx(4.0, rel=0.05)
    m = prepare_run_dir(cfg, tmp_path, cfg.simulation.seed)
    med = {}
    for f, da in m["depth_area"].items():
        edges, a = np.array(da["bin_edges_mag"]), np.array(da["area_arcmin2"])
        cum = np.cumsum(a) / a.sum()
        med[f] = np.interp(0.5, cum, edges[1:])
    # Noise x2.5: 2.5 log10(2.5) = 0.995 mag, to the bin width and the fields' own exposure maps.
    assert med["deep"] - med["shallow"] == pytest.approx(2.5 * math.log10(2.5), abs=0.06)


def test_two_depth_run_columns(two_depth_run):
    cfg, out = two_depth_run
    rows = read_results(out)
    assert 6000 <= len(rows) <= 9000          # 300 tasks of at most 30 sources
    med = rows.groupby(C.COL_FIELD)[C.COL_DEPTH].median()
    assert med["deep"] - med["shallow"] == pytest.approx(2.5 * math.log10(2.5), abs=0.06)
    # Completeness runs from ~1 to 0 in both fields, and the deep one is more complete.
    c = rows.groupby([C.COL_FIELD, C.COL_MAG])[C.COL_RECOVERED].mean()
    for f in ("shallow", "deep"):
        assert c[f].iloc[0] > 0.85 and c[f].iloc[-1] < 0.02
    assert (c["deep"] >= c["shallow"] - 0.05).all()


def test_deep_corner_quadrant_is_1p31_mag_deeper(deep_corner_run, deep_corner_quadrant):
    (qy, qx), factor = deep_corner_quadrant
    cfg, out = deep_corner_run
    field = cfg.survey.fields[0]
    ctx = build_field_context(cfg, Survey.from_config(cfg), field)
    q = np.zeros(ctx.shape, bool)
    q[qy, qx] = True
    expect = 2.5 * math.log10(1.0 / factor)          # 1.307 mag
    # The demo's exposure map varies by a few % between quadrants: 0.05 mag.
    assert np.nanmedian(ctx.depth[q]) - np.nanmedian(ctx.depth[~q]) == pytest.approx(expect, abs=0.05)
    rows = read_results(out)
    iy, ix = _pixel_of(rows)
    in_q = q[iy, ix]
    assert 0.15 < in_q.mean() < 0.35
    d = rows[C.COL_DEPTH].to_numpy()
    assert np.median(d[in_q]) - np.median(d[~in_q]) == pytest.approx(expect, abs=0.05)
