"""Field preparation (glaciar.fieldprep): a field's pixels read and measured once, as defined."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from glaciar.engine.noise import empty_aperture_scatter, empty_sky_distance

from toy_images import fits_survey


def test_noise_rms_follows_weight_type():
    from glaciar.fieldprep import noise_rms

    noise = np.full((4, 4), 0.5, np.float32)       # the map's RMS
    nodata = np.zeros((4, 4), bool)
    nodata[0, 0] = True
    measured = np.full((4, 4), 2.0, np.float32)     # sep's background RMS
    measured[0, 0] = 100.0                          # no data there: left out of the factor
    calls = []

    def background():
        calls.append(1)
        return measured

    # An absolute map (no WEIGHT_TYPE, MAP_RMS) is used as it is; the background is not measured.
    for weight_type in (None, "map_rms"):
        rms, from_background = noise_rms(noise, weight_type, background, nodata)
        assert rms is noise and not from_background
    assert calls == []
    # MAP_WEIGHT: one factor, median(2.0 / 0.5) = 4 over the pixels with data.
    rms, from_background = noise_rms(noise, "map_weight", background, nodata)
    np.testing.assert_array_equal(rms, np.full((4, 4), 2.0, np.float32))
    assert not from_background
    # BACKGROUND, or no map: sep's background RMS.
    for args in ((noise, "background"), (None, None), (None, "map_weight")):
        rms, from_background = noise_rms(*args, background, nodata)
        assert rms is measured and from_background


# ------------------------------------------------------------------------------
# Field set-up with bounded memory gives the same answers.
# ------------------------------------------------------------------------------


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
    s = fits_survey(tmp_path, sci.astype(dtype), wht.astype(">f4"))
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


def test_correlated_noise_by_tiles_is_the_whole_frame_measurement(monkeypatch, tmp_path, small_survey):
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
    sky, released, kept = {}, [], []

    def keep(a):                            # what a large field does: the source mask on disk
        m = np.lib.format.open_memmap(tmp_path / "sources.npy", mode="w+", dtype=a.dtype, shape=a.shape)
        m[...] = a
        kept.append(m)
        return m

    for b, (base, rms, _) in pix.items():
        got = fieldprep.correlated_noise(cfg, field, b, base, rms, seg, sky, release=lambda: released.append(b),
                                         keep=keep)
        usable = np.isfinite(rms) & ~grown
        seq = np.random.SeedSequence([field_key(field), field_key(b)])
        npix, ratio, n = empty_aperture_scatter(base, rms, usable, radii, cfg.noise.n_empty_apertures,
                                                np.random.default_rng(seq),
                                                distance=empty_sky_distance(usable))
        want = CorrelatedNoise.fit(npix, ratio, n)
        assert got == want, b
        assert len(npix) >= 5
    assert set(released) == set(pix) and len(released) > 2 * len(pix)    # block by block
    assert len(kept) == 1 and sky["sources"] is kept[0]                 # spilled once, read from disk
    np.testing.assert_array_equal(kept[0], grown)


def test_large_field_reference_by_strips_equals_whole_frame(small_survey, monkeypatch, assert_same_outputs):
    """By default a large (spilled) field's reference extraction runs by row strips (a few
    rows each here; CLEAN off): the context's reference, depth and noise models, and a task's
    rows, equal the whole-frame build's."""
    from glaciar import fieldprep
    from glaciar.config import load_config
    from glaciar.engine import reference
    from glaciar.engine.task import TaskSpec, run_task
    from glaciar.survey import Survey

    cfg = load_config(small_survey)
    cfg = cfg.model_copy(update={"detection": cfg.detection.model_copy(update={"clean": False})})
    field = cfg.survey.fields[0]
    whole = fieldprep.build_field_context(cfg, Survey.from_config(cfg), field)
    calls = []
    monkeypatch.setattr(fieldprep, "SPILL_MIN_BYTES", 0)
    monkeypatch.setattr(reference, "STRIP_PIXELS", 7 * 320)
    monkeypatch.setattr(fieldprep, "strip_reference",
                        lambda *a, **k: calls.append(1) or reference.strip_reference(*a, **k))
    strips = fieldprep.build_field_context(cfg, Survey.from_config(cfg), field)
    assert calls == [1]
    a, b = whole.reference, strips.reference
    np.testing.assert_array_equal(np.asarray(b.segmap), a.segmap)
    for name in a.catalog.dtype.names:
        np.testing.assert_array_equal(b.catalog[name], a.catalog[name], err_msg=name)
    np.testing.assert_array_equal(b.flux, a.flux)
    np.testing.assert_array_equal(b.mag, a.mag)
    np.testing.assert_array_equal(b.objects.need, a.objects.need)
    np.testing.assert_array_equal(np.asarray(strips.depth), whole.depth)
    assert strips.measured_noise == whole.measured_noise
    spec = TaskSpec(field=field, field_index=0, z_index=0, mag_index=0, iteration=0, z=8.0, mag=26.0)
    assert_same_outputs(run_task(strips, spec, 3), run_task(whole, spec, 3), "strips")
