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


def test_empty_aperture_scatter_unchanged_by_the_capped_map():
    rng = np.random.default_rng(3)
    usable = _mask((120, 110), seed=2)
    img = rng.standard_normal(usable.shape).astype(np.float32)
    rms = np.full(usable.shape, 1.0, np.float32)
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
    want_cat, want_seg = detect._sep_extract(img, err, nodata, params, True)
    stacks = []
    real = sep.set_extract_pixstack
    monkeypatch.setattr(detect.sep, "set_extract_pixstack", lambda n: (stacks.append(n), real(n)))
    monkeypatch.setattr(detect, "PIXSTACK_START", 64)
    cat, seg = detect._sep_extract(img, err, nodata, params, True)
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

    from glaciar.engine import clean, measure
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
    dmask = clean.detection_mask(data, detection_rms(err, nodata, params), nodata, params)[0] \
        | (ref.segmap > 0)
    comp, _ = ndimage.label(dmask, structure=np.ones((3, 3), bool))
    boxes = ndimage.find_objects(comp)
    n = int(ref.segmap.max())
    assert n >= 4
    for rows in (1, 2, 7):
        monkeypatch.setattr(measure, "REFERENCE_TILE_PIXELS", rows * img.shape[1])
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
