"""sep backend in SExtractor vocabulary: filters, config files, background, extraction."""
import numpy as np
import pytest
from scipy import integrate

from glaciar.engine.detect import (DetectionError, DetectionParams, builtin_filter, builtin_filter_names,
                                   extract, measure_background, read_conv_file)


def test_builtin_gaussian_matches_numerical_pixel_integrals():
    k = builtin_filter("gauss_2.0_5x5")
    sig = 2.0 / 2.354820045
    g = lambda v: np.exp(-0.5 * (v / sig) ** 2)  # noqa: E731
    p = np.array([integrate.quad(g, c - 0.5, c + 0.5)[0] for c in range(-2, 3)])
    ref = np.outer(p, p)
    np.testing.assert_allclose(k, ref / ref.sum(), rtol=1e-10)
    for name in ("gauss_2.5_5x5", "gauss_3.0_7x7", "tophat_3.0_3x3", "default"):
        kk = builtin_filter(name)
        assert np.isclose(kk.sum(), 1.0) and np.allclose(kk, kk.T) and np.allclose(kk, kk[::-1])
    assert builtin_filter("gauss_3.0_7x7").shape == (7, 7)
    assert set(("gauss_2.0_5x5", "gauss_2.5_5x5", "gauss_3.0_7x7", "tophat_3.0_3x3", "default")) <= set(builtin_filter_names())


def test_tophat_is_disk_area_fraction():
    k = builtin_filter("tophat_3.0_3x3")
    total = np.pi * 1.5 ** 2                 # the whole disk lies inside the 3x3 box
    # corner pixel [0.5, 1.5]^2: area inside r = 1.5, by quadrature (101^2 sub-sampling: < 2e-3)
    corner = integrate.quad(lambda x: max(np.sqrt(2.25 - x * x) - 0.5, 0.0), 0.5, 1.5)[0]
    np.testing.assert_allclose(k[0, 0] * total, corner, rtol=2e-2)
    np.testing.assert_allclose(k[1, 1] * total, 1.0, rtol=2e-3)   # centre pixel fully inside


def test_builtin_default_is_pyramid():
    np.testing.assert_allclose(builtin_filter("default.conv") * 16, [[1, 2, 1], [2, 4, 2], [1, 2, 1]])
    with pytest.raises(ValueError, match="unknown built-in filter"):
        builtin_filter("gauss_9.9_3x3")


def test_read_conv_file(tmp_path):
    p = tmp_path / "k.conv"
    p.write_text("CONV NORM\n# 3x3 kernel\n1 2 1\n2 4 2\n1 2 1\n")
    np.testing.assert_array_equal(read_conv_file(p), [[1, 2, 1], [2, 4, 2], [1, 2, 1]])
    p.write_text("1 2 1\n")
    with pytest.raises(ValueError, match="CONV NORM"):
        read_conv_file(p)
    p.write_text("CONV NONORM\n1 2\n1 2 3\n")
    with pytest.raises(ValueError, match="different lengths"):
        read_conv_file(p)
    with pytest.raises(FileNotFoundError):
        read_conv_file(tmp_path / "missing.conv")


def _blob(n=64, x0=32.0, y0=32.0, amp=5.0, s=2.0):
    yy, xx = np.mgrid[:n, :n]
    return amp * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * s * s))


def test_threshold_is_relative_to_the_rms_map():
    # no filter: a flat 4x4 plateau is detected iff it exceeds DETECT_THRESH * rms of its pixels
    p = DetectionParams(detect_thresh=2.0, detect_minarea=4, filter_kernel=None)
    img = np.zeros((40, 40))
    img[10:14, 10:14] = 1.0
    img[25:29, 25:29] = 1.0
    rms = np.full((40, 40), 0.45)       # 1.0 > 0.9: both detected
    rms[20:, 20:] = 0.55                # 1.0 < 1.1: the second is not
    cat, seg = extract(img, rms, p)
    assert len(cat) == 1 and np.isclose(cat["x"][0], 11.5) and seg[11, 11] == 1 and seg[26, 26] == 0


def test_pixels_without_data_are_never_detected():
    p = DetectionParams()
    img = _blob() + _blob(x0=12, y0=12)
    rms = np.full(img.shape, 0.1)
    mask = np.zeros(img.shape, bool)
    mask[20:45, 20:45] = True           # masks the first blob
    rms[:25, :25] = np.inf              # infinite RMS hides the second
    cat, seg = extract(img, rms, p, mask=mask)
    assert len(cat) == 0 and not seg.any()
    img2 = img.copy()
    img2[20:45, 20:45] = np.nan         # NaN data are no data too
    cat, _ = extract(img2, np.full(img.shape, 0.1), p)
    assert len(cat) == 1 and np.hypot(cat["x"][0] - 12, cat["y"][0] - 12) < 0.1


def test_background_rms_and_big_endian_input():
    rng = np.random.default_rng(3)
    img = (10.0 + rng.normal(0, 0.2, (256, 256))).astype(">f4")
    p = DetectionParams()
    back, rms = measure_background(img, None, p)
    assert abs(np.median(back) - 10.0) < 0.01
    assert abs(np.median(rms) - 0.2) / 0.2 < 0.03
    cat, seg = extract((img - back) + _blob(256, 128, 128, 3.0, 2.5), rms, p)
    assert seg[128, 128] > 0 and seg.dtype == np.int32


def test_background_mesh_larger_than_the_image_is_one_mesh_of_the_whole_image():
    """BACK_SIZE beyond the image: the result of a mesh cut to the image (sep allocated
    BACK_SIZE^2 pixels first: MemoryError with an empty message at 1e9)."""
    import sep

    rng = np.random.default_rng(4)
    img = (rng.normal(0, 1, (120, 90)) + np.linspace(0, 3, 90)[None, :]).astype(np.float32)
    mask = np.zeros(img.shape, bool)
    mask[:7] = True
    back, rms = measure_background(img, mask, DetectionParams(back_size=10 ** 9))
    # Independent: sep itself with the mesh cut to the image (one mesh: a constant map).
    ref = sep.Background(img, mask=mask, bw=90, bh=120, fw=3, fh=3)
    np.testing.assert_array_equal(back, ref.back(dtype=np.float32))
    np.testing.assert_array_equal(rms, ref.rms(dtype=np.float32))
    good = img[~mask]
    assert np.ptp(back) == 0 and abs(back[0, 0] - np.median(good)) < 0.2


def test_sep_failure_becomes_detection_error():
    p = DetectionParams(detect_thresh=0.1, detect_minarea=1, deblend_nthresh=64, deblend_mincont=0.0,
                        sub_object_limit=1, filter_kernel=None)
    rng = np.random.default_rng(0)
    img = _blob(64, 32, 32, 50.0, 8.0) + rng.normal(0, 1, (64, 64))
    with pytest.raises(DetectionError):
        extract(img, np.ones((64, 64)), p)


def test_params_validation():
    with pytest.raises(ValueError, match="detect_thresh"):
        DetectionParams(detect_thresh=-1)
    with pytest.raises(ValueError, match="phot_apertures"):
        DetectionParams(phot_apertures=())
    with pytest.raises(ValueError, match="filter_type"):
        DetectionParams(filter_type="gauss")


# ------------------------------------------------------------------------------
# Field set-up with bounded memory gives the same answers.
# ------------------------------------------------------------------------------
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
