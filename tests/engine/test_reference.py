"""glaciar.engine.reference: the row-strip extraction equals one sep.extract call on the whole image.

The expected values come from ``sep.extract`` itself, called once on the whole image (an
independent computation); strips of a few rows force every hard case: regions taller than
a strip (re-read with more rows above), regions cut below DETECT_MINAREA by a strip's edge,
split (deblended) regions whose faint pixels sep hands out with its per-call random stream,
masked pixels in the first rows (sep's line-buffer quirk) and next to objects.
"""
from __future__ import annotations

import numpy as np
import pytest
import sep

from glaciar.engine.detect import DetectionParams
from glaciar.engine.reference import strip_extract, strips_apply


def _field(ny, nx, n, seed):
    """Noise, round and elongated galaxies (40 % with a blended companion), two large
    bright ones, masked rows and a NaN."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:ny, 0:nx].astype(np.float32)
    img = rng.normal(0.0, 1.0, (ny, nx)).astype(np.float32)

    def add(y, x, flux, s, q=1.0):
        r2 = (yy - y) ** 2 / (q * q) + (xx - x) ** 2
        img[...] += (flux / (2 * np.pi * s * s * q) * np.exp(-r2 / (2 * s * s))).astype(np.float32)

    for _ in range(n):
        y, x, s, f = rng.uniform(0, ny), rng.uniform(0, nx), rng.uniform(0.8, 5.0), 10 ** rng.uniform(0.5, 3)
        add(y, x, f, s, rng.uniform(0.4, 1.0))
        if rng.uniform() < 0.4:
            add(y + rng.normal(0, 3), x + rng.normal(0, 3), 0.6 * f, s)
    add(ny * 0.45, nx * 0.5, 3e4, 9.0, 0.5)           # large: taller than any strip below
    add(ny * 0.47, nx * 0.56, 1e4, 4.0)               # ... blended with a bright neighbour
    rms = np.full((ny, nx), rng.uniform(0.8, 1.2), dtype=np.float32)
    rms[:, nx // 2:] *= 1.3
    mask = np.zeros((ny, nx), dtype=bool)
    mask[ny // 3:ny // 3 + 4, 10:50] = True
    mask[:2, :30] = True                               # no-data in sep's preloaded first rows
    img[6, 9] = np.nan
    return img, rms, mask


def _whole_frame(img, rms, mask, params):
    """One sep.extract call on the whole image, sanitized as glaciar passes it (written here)."""
    data = np.nan_to_num(img.astype(np.float32), nan=0.0)
    nodata = mask | ~np.isfinite(img)
    data[nodata] = 0.0
    err = rms.astype(np.float32).copy()
    err[nodata] = 1.0
    sep.set_extract_pixstack(img.size + 1024)
    return sep.extract(data, params.detect_thresh, err=err, mask=nodata, minarea=params.detect_minarea,
                       filter_kernel=params.filter_kernel, filter_type="conv",
                       deblend_nthresh=params.deblend_nthresh,
                       deblend_cont=params.deblend_mincont, clean=False, segmentation_map=True)


@pytest.fixture(scope="module")
def case():
    params = DetectionParams(detect_thresh=1.0)
    img, rms, mask = _field(240, 200, 160, 3)
    cat, seg = _whole_frame(img, rms, mask, params)
    return img, rms, mask, params, cat, seg


def _assert_same(cat, seg, cat_s, seg_s):
    assert len(cat_s) == len(cat)
    for name in cat.dtype.names:
        np.testing.assert_array_equal(cat_s[name], cat[name], err_msg=name)
    np.testing.assert_array_equal(seg_s, seg)


@pytest.mark.parametrize("rows, halo", [(4, 3), (11, 5), (29, 4)])
def test_strips_equal_whole_frame(case, rows, halo):
    img, rms, mask, params, cat, seg = case
    # the field holds what makes strips hard: split regions, regions taller than a strip
    assert np.count_nonzero(cat["flag"] & sep.OBJ_MERGED) >= 10
    assert (cat["ymax"] - cat["ymin"] + 1).max() > rows + halo
    cat_s, seg_s = strip_extract(img, rms, mask, params, strip_rows=rows, halo=halo)
    _assert_same(cat, seg, cat_s, seg_s)


def test_strips_without_filter_and_into_given_array(case):
    img, rms, mask, _, _, _ = case
    params = DetectionParams(detect_thresh=2.0, filter_kernel=None, deblend_mincont=0.001)
    cat, seg = _whole_frame(img, rms, mask, params)
    out = np.zeros(img.shape, dtype=np.int32)
    cat_s, seg_s = strip_extract(img, rms, mask, params, strip_rows=6, halo=1, out=out)
    assert seg_s is out
    _assert_same(cat, seg, cat_s, seg_s)


def test_split_regions_need_the_frame_random_stream(case):
    """Strips extracted on their own (no replay of the split regions) would hand faint
    pixels out differently: the case does exercise sep's random stream."""
    img, rms, mask, params, cat, seg = case
    data = np.nan_to_num(img, nan=0.0)
    nodata = mask | ~np.isfinite(img)
    data[nodata] = 0.0
    err = rms.copy()
    err[nodata] = 1.0
    half = img.shape[0] // 2
    rows = np.flatnonzero((cat["flag"] & sep.OBJ_MERGED) & (cat["ymin"] > half + 10))
    sub, subseg = sep.extract(np.ascontiguousarray(data[half:]), params.detect_thresh,
                              err=np.ascontiguousarray(err[half:]), mask=np.ascontiguousarray(nodata[half:]),
                              minarea=params.detect_minarea, filter_kernel=params.filter_kernel,
                              filter_type="conv",
                              clean=False, segmentation_map=True)
    same = [np.array_equal(seg[half:] == k + 1, subseg == j + 1)
            for k in rows for j in np.flatnonzero((sub["xmin"] == cat["xmin"][k])
                                                  & (sub["ymin"] == cat["ymin"][k] - half))]
    assert not all(same)


def test_unhandled_settings_refused():
    assert strips_apply(DetectionParams())
    p = DetectionParams(threshold_rms="filtered")
    assert not strips_apply(p)
    with pytest.raises(ValueError, match="threshold_rms"):
        strip_extract(np.zeros((8, 8)), np.ones((8, 8)), None, p)


@pytest.mark.parametrize("clean", [False, True])
def test_strip_reference_equals_the_whole_frame_reference(case, monkeypatch, clean):
    """Segmentation, catalogue, AUTO photometry (detection band and another band) and object
    boxes equal the whole-frame reference extraction's (sep's own CLEAN with CLEAN on), with
    strips and bands of a few rows."""
    from glaciar.engine import reference
    from glaciar.engine.measure import reference_extraction

    img, rms, mask, _, _, _ = case
    params = DetectionParams(detect_thresh=1.0, clean=clean, clean_param=0.6)
    monkeypatch.setattr(reference, "STRIP_PIXELS", 9 * img.shape[1])
    other = (img * np.float32(1.1) + np.float32(0.2), rms * np.float32(1.2))
    for phot in ((None, other) if not clean else (None,)):
        whole = reference_extraction(img, rms, params, 25.0, mask=mask, photometry=phot)
        strips = reference.strip_reference(img, rms, params, 25.0, mask=mask, photometry=phot,
                                           seg_out=np.zeros(img.shape, dtype=np.int32))
        _assert_same(whole.catalog, whole.segmap, strips.catalog, strips.segmap)
        np.testing.assert_array_equal(strips.flux, whole.flux)
        np.testing.assert_array_equal(strips.mag, whole.mag)
        for name in ("region", "need", "cell", "start", "ids"):
            np.testing.assert_array_equal(getattr(strips.objects, name), getattr(whole.objects, name))
        if clean:        # CLEAN removed objects here: the case tests the emulation on strips
            assert len(whole.catalog) < len(_whole_frame(img, rms, mask, params)[0])
    with pytest.raises(ValueError, match="clean_style"):
        reference.strip_reference(img, rms, DetectionParams(clean_style="sep"), 25.0, mask=mask)
