"""Field set-up with bounded memory gives the same answers.

* the empty-sky distance map by tiles (glaciar.engine.noise.empty_sky_distance):
  against the whole-image Euclidean distance transform (scipy, one call) and the
  brute-force nearest unusable pixel;
* sep's pixel stack started small: against the whole-area stack;
* the reference extraction sanitizing after the segmentation: against the
  segmentation of pre-sanitized inputs (sanitize is idempotent).
"""
import numpy as np
import pytest
from scipy import ndimage

from glaciar.engine.noise import (DEFAULT_EMPTY_APERTURE_RADII_PIX, distance_cap,
                                  empty_aperture_scatter, empty_sky_distance)


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


def test_sep_extraction_with_a_small_first_pixel_stack_is_unchanged(monkeypatch):
    """A pixel stack too small for the image's objects retries with the image area:
    the catalogue and segmentation are those of the whole-area stack."""
    import sep

    from glaciar.engine import detect
    from glaciar.engine.detect import DetectionParams

    rng = np.random.default_rng(1)
    img = rng.standard_normal((150, 140)).astype(np.float32)
    yy, xx = np.mgrid[:150, :140]
    for y, x, f in ((40, 30, 60.0), (100, 90, 200.0), (70, 120, 30.0)):
        img += f * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * 4.0 ** 2))
    err = np.ones_like(img)
    nodata = np.zeros(img.shape, bool)
    params = DetectionParams()
    want_cat, want_seg = detect.sep_extract(img, err, nodata, params, True)
    stacks = []
    real = sep.set_extract_pixstack
    monkeypatch.setattr(detect.sep, "set_extract_pixstack", lambda n: (stacks.append(n), real(n)))
    monkeypatch.setattr(detect, "PIXSTACK_START", 64)
    cat, seg = detect.sep_extract(img, err, nodata, params, True)
    assert stacks == [64, img.size + 1024]           # overflowed, retried with the image area
    assert np.array_equal(seg, want_seg) and len(want_cat) >= 3
    for name in ("x", "y", "flux", "a", "b", "theta", "npix"):
        assert np.array_equal(cat[name], want_cat[name])


def test_sanitize_is_idempotent_and_the_reference_extraction_unchanged():
    from glaciar.engine.detect import DetectionParams, sanitize
    from glaciar.engine.measure import reference_extraction
    from glaciar.engine.segmentation import sep_segmentation

    rng = np.random.default_rng(2)
    img = rng.standard_normal((120, 130)).astype(np.float32)
    yy, xx = np.mgrid[:120, :130]
    for y, x, f in ((30, 30, 40.0), (34, 40, 25.0), (90, 100, 80.0)):     # a blend and a single
        img += f * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * 3.0 ** 2))
    img[5, 7] = np.nan
    rms = np.full(img.shape, 1.0, np.float32)
    rms[60, 61] = np.inf
    mask = np.zeros(img.shape, bool)
    mask[:, :4] = True
    once = sanitize(img, rms, mask)
    twice = sanitize(*once)
    for a, b in zip(once, twice):
        assert np.array_equal(a, b)
    params = DetectionParams()
    ref = reference_extraction(img, rms, params, 25.0, mask=mask)
    # The former order: segmentation of the sanitized arrays (so, by idempotence, this call).
    former = reference_extraction(once[0], once[1], params, 25.0, mask=once[2])
    assert np.array_equal(sep_segmentation(*once[:2], params, mask=once[2]).seg,
                          sep_segmentation(img, rms, params, mask=mask).seg)
    assert ref.segmap.max() >= 3
    assert np.array_equal(ref.segmap, former.segmap)
    assert np.array_equal(ref.flux, former.flux) and np.array_equal(ref.mag, former.mag, equal_nan=True)


@pytest.mark.parametrize("filter_type,threshold_rms", [("conv", "pixel"), ("matched", "pixel"),
                                                       ("conv", "filtered")])
def test_reference_boxes_by_row_tiles_equal_the_full_frame_definition(monkeypatch, filter_type,
                                                                      threshold_rms):
    """Region boxes: bounding boxes of the 8-connected components of (sep's detection mask |
    segmentation), taken here on the whole frame at once as the reference."""
    import dataclasses

    from glaciar.engine import blocks, sepscan
    from glaciar.engine.detect import DetectionParams, builtin_filter, detection_rms, sanitize
    from glaciar.engine.measure import reference_extraction

    rng = np.random.default_rng(6)
    img = rng.standard_normal((90, 75)).astype(np.float32)
    yy, xx = np.mgrid[:90, :75]
    for y, x, f in ((20, 20, 30.0), (24, 27, 20.0), (45, 60, 50.0), (70, 15, 9.0), (44, 40, 6.0)):
        img += f * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * 2.5 ** 2))
    rms = np.full(img.shape, 1.0, np.float32)
    rms[30:40, :] = 1.7
    params = dataclasses.replace(DetectionParams(), filter_kernel=builtin_filter("gauss_2.0_5x5"),
                                 filter_type=filter_type, threshold_rms=threshold_rms)
    ref = reference_extraction(img, rms, params, 25.0)
    data, err, nodata = sanitize(img, rms, None)
    dmask = sepscan.detection_mask(data, detection_rms(err, nodata, params), nodata, params)[0] \
        | (ref.segmap > 0)
    comp, _ = ndimage.label(dmask, structure=np.ones((3, 3), bool))
    boxes = ndimage.find_objects(comp)
    n = int(ref.segmap.max())
    assert n >= 4
    for rows in (1, 2, 7):
        monkeypatch.setattr(blocks, "REFERENCE_TILE_PIXELS", rows * img.shape[1])
        tiled = reference_extraction(img, rms, params, 25.0)
        assert np.array_equal(tiled.segmap, ref.segmap)
        for i in range(1, n + 1):
            c = np.unique(comp[ref.segmap == i])
            assert c.size == 1
            sl = boxes[c[0] - 1]
            want = (sl[0].start, sl[0].stop, sl[1].start, sl[1].stop)
            got = tuple(int(v) for v in tiled.objects.region[i - 1])
            assert got == want, (rows, i)
        assert np.array_equal(tiled.objects.need, ref.objects.need)


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


# ---------------------------------------------------------------------------
# Lean field set-up: row tiles and in-place work against whole-frame definitions
# ---------------------------------------------------------------------------
def _aperture_inputs(seed=4, shape=(90, 110), n=60):
    rng = np.random.default_rng(seed)
    img = (rng.standard_normal(shape) * 2.0 + rng.uniform(0.0, 4.0, shape)).astype(np.float32)
    rms = rng.uniform(0.5, 2.0, shape).astype(np.float32)
    seg = rng.integers(0, 4, shape).astype(np.int32)
    nodata = rng.uniform(size=shape) < 0.05
    x, y = rng.uniform(-3, shape[1] + 3, n), rng.uniform(-3, shape[0] + 3, n)
    a = rng.uniform(1.0, 6.0, n)
    b = a * rng.uniform(0.2, 1.0, n)
    th = rng.uniform(-1.5, 1.5, n)
    return img, rms, seg, nodata, x, y, a, b, th, rng.integers(1, 4, n).astype(np.int32)


@pytest.mark.parametrize("gain", [None, 2.5])
def test_sep_photometry_of_float32_images_is_that_of_their_float64_copies(gain):
    """kron_radius, auto_photometry and aperture_photometry no longer copy a float32 image to
    float64 (8 bytes per pixel on a field's reference photometry): sep on the float64 copies,
    called directly, is the reference, bit for bit; a read-only map is accepted."""
    import sep

    from glaciar.engine import photometry as phot

    img, rms, seg, nodata, x, y, a, b, th, ids = _aperture_inputs()
    i64, r64 = img.astype(np.float64), rms.astype(np.float64)
    ro = img.copy()
    ro.setflags(write=False)
    for data in (img, ro):
        kr = phot.kron_radius(data, x, y, a, b, th, segmap=seg, seg_id=ids, mask=nodata)
        want = sep.kron_radius(i64, x, y, a, b, th, 6.0, mask=nodata, segmap=seg, seg_id=ids)[0]
        assert np.array_equal(kr, want, equal_nan=True)
        scale = phot.auto_scale(kr, (2.5, 3.5))
        f, fe = phot.auto_photometry(data, rms, phot.Ellipses(x, y, a, b, th, scale), gain=gain, segmap=seg,
                                     seg_id=ids, mask=nodata)
        wf, wfe, _ = sep.sum_ellipse(i64, x, y, a, b, th, scale, err=r64, mask=nodata, gain=gain,
                                     subpix=0, segmap=seg, seg_id=ids)
        assert np.array_equal(f, wf, equal_nan=True) and np.array_equal(fe, wfe, equal_nan=True)
        fa, fea = phot.aperture_photometry(data, rms, x, y, (4.0, 8.0), gain=gain, mask=nodata)
        for k, d in enumerate((4.0, 8.0)):
            wf, wfe, _ = sep.sum_circle(i64, x, y, d / 2, err=r64, mask=nodata, gain=gain, subpix=0)
            assert np.array_equal(fa[k], wf, equal_nan=True)
            assert np.array_equal(fea[k], wfe, equal_nan=True)
    assert np.isfinite(f).sum() > 30


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


def test_sanitize_by_blocks_and_from_a_map_is_the_elementwise_definition(monkeypatch, tmp_path):
    from glaciar.engine import detect

    rng = np.random.default_rng(9)
    img = rng.standard_normal((37, 29)).astype(np.float64)
    img[3, 4], img[10, 1] = np.nan, np.inf
    err = rng.uniform(0.5, 2.0, img.shape).astype(np.float32)
    err[5, 5], err[6, 6], err[7, 7] = 0.0, -1.0, np.nan
    mask = rng.uniform(size=img.shape) < 0.1
    # The definition, elementwise on whole arrays.
    i32 = img.astype(np.float32)
    with np.errstate(invalid="ignore"):
        nodata = ~np.isfinite(i32) | mask | ~(np.isfinite(err) & (err > 0))
    want = (np.where(nodata, 0, i32).astype(np.float32), np.where(nodata, 1, err).astype(np.float32),
            nodata)
    np.save(tmp_path / "img.npy", i32)
    mapped = np.load(tmp_path / "img.npy", mmap_mode="r")
    for pixels in (1 << 22, 29, 60):                     # one block; one row; two rows
        monkeypatch.setattr(detect, "SANITIZE_BLOCK_PIXELS", pixels)
        for image in (img, mapped):
            got = detect.sanitize(image, err, mask)
            for g, w in zip(got, want):
                assert g.dtype == w.dtype and np.array_equal(g, w)
    assert np.array_equal(detect.sanitize(img)[0], np.where(~np.isfinite(i32), 0, i32))


def _fits_survey(tmp_path, sci, wht, noise_type="weight", negative="mask"):
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


@pytest.mark.parametrize("dtype", [">f4", ">f8", ">i2"])
def test_survey_reads_by_row_blocks_are_the_whole_image(monkeypatch, tmp_path, dtype):
    """Science, RMS and footprint read by blocks of 3 rows equal astropy's whole-image data
    turned into them elementwise (1/sqrt(weight), inf without weight)."""
    from astropy.io import fits

    from glaciar import survey as sv

    rng = np.random.default_rng(2)
    sci = (rng.standard_normal((23, 17)) * 50).astype(dtype)
    sci[0, 0] = 0
    wht = rng.uniform(0.1, 4.0, sci.shape).astype(">f4")
    wht[2, 3], wht[4, 5], wht[6, 7] = 0.0, np.nan, np.inf
    if dtype != ">i2":
        sci[8, 9] = np.nan
    s = _fits_survey(tmp_path, sci, wht)
    monkeypatch.setattr(sv, "ROW_BLOCK_PIXELS", 3 * 17)
    sv.clear_cache()
    whole = fits.getdata(tmp_path / "f_b_drz.fits")
    native = np.float32 if dtype != ">f8" else np.float64
    got = s.science("f", "b", cache=False)
    assert got.dtype == native and got.flags.writeable
    assert np.array_equal(got, whole.astype(native), equal_nan=True)
    w = fits.getdata(tmp_path / "f_b_wht.fits").astype(np.float32)
    good = np.isfinite(w) & (w > 0)
    with np.errstate(divide="ignore"):
        want_rms = np.where(good, np.float32(1) / np.sqrt(w), np.float32(np.inf))
    assert np.array_equal(s.rms("f", "b"), want_rms)
    assert np.array_equal(s.rms("f", "b", cache=False), want_rms)
    sci_n = whole.astype(native)
    want_fp = np.isfinite(sci_n) & (sci_n != 0) & good
    assert np.array_equal(s.footprint("f"), want_fp) and not want_fp.all()
    assert np.array_equal(s.band_valid("f", "b"), want_fp)


def test_negative_weights_are_counted_over_every_block(monkeypatch, tmp_path):
    from glaciar import survey as sv

    sci = np.ones((20, 10), ">f4")
    wht = np.ones((20, 10), ">f4")
    wht[1, 1] = wht[12, 3] = wht[19, 9] = -1.0           # in three different blocks
    s = _fits_survey(tmp_path, sci, wht, negative="error")
    monkeypatch.setattr(sv, "ROW_BLOCK_PIXELS", 40)
    sv.clear_cache()
    for call in (lambda: s.rms("f", "b"), lambda: s.footprint("f")):
        with pytest.raises(ValueError, match=r"3 negative weight pixel\(s\)"):
            call()


@pytest.mark.parametrize("weight_type", [None, "map_weight", "background"])
@pytest.mark.parametrize("dtype", [">f4", ">f8"])
def test_band_pixels_is_the_elementwise_definition(tmp_path, weight_type, dtype):
    """band_pixels (in place on new arrays, background subtracted by sep's subfrom where it
    can) against the definition on whole arrays: sep's background of the sanitized image,
    base = image - background (float32 for a float32 image), 0 and inf off the valid pixels."""
    import sep

    from glaciar.engine.detect import DetectionParams
    from glaciar.engine.noise import weight_rescale_factor
    from glaciar.fieldprep import band_pixels

    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[:130, :120]
    sci = rng.standard_normal((130, 120)) + 0.01 * xx + 30 * np.exp(-((yy - 60) ** 2 + (xx - 50) ** 2) / 18.0)
    sci[:, :6] = 0.0                                    # uncovered
    sci[40, 41] = np.nan
    wht = np.full(sci.shape, 0.8)
    wht[100:, 100:] = 0.0
    s = _fits_survey(tmp_path, sci.astype(dtype), wht.astype(">f4"))
    params = DetectionParams(back_size=32)
    fp = s.footprint("f")
    bkg_out = {}
    base, rms, from_bkg = band_pixels(s, "f", "b", fp, params, weight_type, background=bkg_out)
    img = sci.astype(dtype).astype(np.float32 if dtype == ">f4" else np.float64)
    with np.errstate(divide="ignore"):
        noise = np.where(wht.astype(np.float32) > 0, np.float32(1) / np.sqrt(wht.astype(np.float32)),
                         np.inf)
    valid = fp & np.isfinite(img) & np.isfinite(noise)
    data = np.where(valid, img, 0).astype(np.float32)
    model = sep.Background(data, mask=~valid, bw=32, bh=32, fw=3, fh=3)
    back, brms = model.back(dtype=np.float32), model.rms(dtype=np.float32)
    want_base = np.where(valid, img - back, 0).astype(np.float32)
    if weight_type == "background":
        want_rms = brms
    elif weight_type == "map_weight":
        want_rms = noise.astype(np.float32) * weight_rescale_factor(brms, noise.astype(np.float32), valid)
    else:
        want_rms = noise
    want_rms = np.where(valid, want_rms.astype(np.float32), np.float32(np.inf))
    assert base.dtype == rms.dtype == np.float32
    assert np.array_equal(base, want_base) and np.array_equal(rms, want_rms)
    assert np.array_equal(bkg_out["b"], back) and from_bkg == (weight_type == "background")
    assert (~valid).sum() > 100 and np.abs(base).max() > 10


def test_correlated_noise_by_tiles_is_the_whole_frame_measurement(monkeypatch, small_survey):
    """The field's empty-aperture models, with every tiled step in tiles of a few rows, against
    the whole-frame recipe: scipy's dilation of the segmentation, the uncapped whole-image
    distance transform and empty_aperture_scatter on that map."""
    from glaciar import fieldprep
    from glaciar.config import load_config
    from glaciar.engine import noise as nz
    from glaciar.engine.noise import CorrelatedNoise
    from glaciar.engine.measure import reference_extraction
    from glaciar.engine.task import field_key
    from glaciar.survey import Survey

    cfg = load_config(small_survey)
    survey = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    params = fieldprep.detection_params(cfg)
    fp = survey.footprint(field)
    pix = {b.name: fieldprep.band_pixels(survey, field, b.name, fp, params) for b in cfg.survey.bands}
    det = cfg.survey.detection_band
    seg = reference_extraction(pix[det][0], pix[det][1], params, 25.0, mask=~fp).segmap
    radii = cfg.noise.empty_aperture_radii_pix
    grown = ndimage.binary_dilation(seg > 0, iterations=fieldprep._EMPTY_SKY_MARGIN_PIX)
    nx = seg.shape[1]
    monkeypatch.setattr(nz, "DISTANCE_TILE_PIXELS", 5 * nx)
    monkeypatch.setattr(fieldprep, "ROW_BLOCK_PIXELS", 3 * nx)
    sky, released = {}, []
    for b, (base, rms, _) in pix.items():
        got = fieldprep.correlated_noise(cfg, field, b, base, rms, seg, sky, release=lambda: released.append(b))
        usable = np.isfinite(rms) & ~grown
        seq = np.random.SeedSequence([field_key(field), field_key(b)])
        npix, ratio, n = empty_aperture_scatter(base, rms, usable, radii, cfg.noise.n_empty_apertures,
                                                np.random.default_rng(seq),
                                                distance=empty_sky_distance(usable))
        want = CorrelatedNoise.fit(npix, ratio, n)
        assert got == want, b
        assert len(npix) >= 5
    assert set(released) == set(pix) and len(released) > 2 * len(pix)    # block by block


@pytest.mark.parametrize("method", ["ivw", "chi2"])
def test_coadd_by_row_blocks_is_the_pixelwise_stack(monkeypatch, tmp_path, method):
    """The stack of a large image by blocks of 2 rows (inputs memory-mapped, float32 output)
    against its definition on whole arrays: inverse-variance mean and 1/sqrt(sum w), or the
    Gaussianised chi-square deviate of the bands with data."""
    from scipy import special

    from glaciar.engine import coadd as co

    rng = np.random.default_rng(12)
    shape = (41, 23)
    images = [rng.standard_normal(shape).astype(np.float32) * s for s in (1.0, 2.0, 0.5)]
    rms = [np.full(shape, s, np.float32) for s in (1.0, 2.0, 0.5)]
    rms[0][3:9, 4:6] = np.inf
    rms[1][3:7, 4:5] = 0.0
    rms[2][3:5, 4:5] = np.nan                            # (3..4, 4): no band has data
    images[1][10, 10] = 1e3                              # a bright pixel: large chi2
    maps = []
    for k, a in enumerate(images + rms):
        np.save(tmp_path / f"{k}.npy", a)
        maps.append(np.load(tmp_path / f"{k}.npy", mmap_mode="r"))
    with np.errstate(divide="ignore"):
        w = [np.where(np.isfinite(r) & (r > 0), 1.0 / np.square(r.astype(np.float64)), 0.0)
             for r in rms]
    wsum = sum(w)
    has = wsum > 0
    if method == "ivw":
        with np.errstate(divide="ignore", invalid="ignore"):
            want = (np.where(has, sum(wi * np.where(wi > 0, im, 0.0) for wi, im in zip(w, images)) / wsum, 0),
                    np.where(has, 1.0 / np.sqrt(wsum), np.inf))
    else:
        x = sum(wi * np.where(wi > 0, im.astype(np.float64), 0.0) ** 2 for wi, im in zip(w, images))
        k = sum((wi > 0).astype(int) for wi in w)
        z = np.zeros(shape)
        z[has] = np.clip(-special.ndtri(np.clip(special.chdtrc(k[has], x[has]), 1e-300, 1)), -37, 37)
        want = (z, np.where(has, 1.0, np.inf))
    monkeypatch.setattr(co, "COADD_BLOCK_PIXELS", 2 * shape[1])
    got = co.coadd(maps[:3], maps[3:], method)
    got32 = co.coadd(maps[:3], maps[3:], method, dtype=np.float32)
    for g, g32, wnt in zip(got, got32, want):
        assert g.dtype == np.float64 and g32.dtype == np.float32
        assert np.allclose(g, wnt, rtol=1e-12, atol=0) or np.array_equal(g, wnt)
        assert np.array_equal(g32, g.astype(np.float32))
    monkeypatch.setattr(co, "COADD_BLOCK_PIXELS", 1 << 20)
    for g, whole in zip(got, co.coadd(images, rms, method)):
        assert np.array_equal(g, whole)                  # bit for bit: the same pixelwise ops
    assert (~has).sum() == 2 and np.isinf(got[1][~has]).all()


def test_gzipped_image_by_row_blocks_is_the_whole_image(monkeypatch, tmp_path):
    """A .fits.gz image (decompressed once, then cut in blocks) reads as astropy's whole data."""
    from astropy.io import fits

    from glaciar import survey as sv

    data = np.random.default_rng(3).standard_normal((1, 31, 19)).astype(">f4")   # NAXIS3 = 1
    path = tmp_path / "img.fits.gz"
    fits.writeto(path, data)
    monkeypatch.setattr(sv, "ROW_BLOCK_PIXELS", 4 * 19)
    got = sv.read_array(path)
    assert got.dtype == np.float32 and got.shape == (31, 19)
    assert np.array_equal(got, fits.getdata(path)[0].astype(np.float32))
