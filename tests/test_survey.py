"""Survey access on small FITS files: weight/RMS, footprint, byte order, WCS scale, errors."""
import os
import pickle

import numpy as np
import pytest
from astropy.io import fits

from glaciar.config import config_from_dict
from glaciar.survey import Survey, clear_cache

from toy_images import fits_survey


@pytest.fixture(autouse=True)
def _fresh_cache():
    clear_cache()
    yield
    clear_cache()


def make_survey(tmp_path, *, noise_type="weight", noise=True, pixel_scale=None,
                bands=("f160w", "f125w"), fields=("a",), selection=(), **survey_keys):
    (tmp_path / "img").mkdir(exist_ok=True)
    data = {"survey": {"fields": list(fields), "image_dir": "img",
                       "science": "{field}_{band}_sci.fits",
                       "noise": "{field}_{band}_noise.fits" if noise else None,
                       "noise_type": noise_type, "pixel_scale_arcsec": pixel_scale,
                       "detection_band": "f160w",
                       "bands": {b: {"filter": f"wfc3_ir_{b}", "zeropoint": 25.0,
                                     "psf": {"profile": "gaussian", "fwhm_arcsec": 0.2}} for b in bands},
                       **survey_keys},
            "selection": list(selection)}
    return Survey.from_config(config_from_dict(data, tmp_path, "test.yaml"))


def write(path, data, header=None, primary_empty=False):
    if primary_empty:
        fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(data, header)]).writeto(path, overwrite=True)
    else:
        fits.PrimaryHDU(data, header).writeto(path, overwrite=True)


def celestial_header(cd=None, cdelt=None):
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRVAL1"], h["CRVAL2"] = 150.0, 2.0
    h["CRPIX1"], h["CRPIX2"] = 5.0, 5.0
    if cd is not None:
        h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = cd[0][0], cd[0][1], cd[1][0], cd[1][1]
    if cdelt is not None:
        h["CDELT1"], h["CDELT2"] = cdelt
    return h


def test_paths_follow_templates(tmp_path):
    s = make_survey(tmp_path, fields=("f1", "f2"))
    assert s.fields == ("f1", "f2") and s.bands == ("f160w", "f125w")
    assert s.science_path("f2", "f125w") == (tmp_path / "img" / "f2_f125w_sci.fits").resolve()
    assert s.noise_path("f1", "f160w") == (tmp_path / "img" / "f1_f160w_noise.fits").resolve()
    assert make_survey(tmp_path, noise=False).noise_path("a", "f160w") is None
    with pytest.raises(KeyError, match="unknown band"):
        s.science_path("f1", "f999w")


def test_weight_to_rms_and_footprint(tmp_path):
    s = make_survey(tmp_path, negative_weights="mask")
    sci = np.ones((3, 4), dtype=np.float32)
    sci[0, 3] = 0.0          # uncovered (drizzle fills with 0)
    sci[1, 0] = np.nan
    wht = np.array([[4.0, 0.25, 1e6, 1.0],
                    [1.0, 0.0, -2.0, np.nan],
                    [np.inf, 100.0, 1.0, 1.0]], dtype=np.float32)
    for b in s.bands:
        write(s.science_path("a", b), sci)
        write(s.noise_path("a", b), wht)
    rms = s.rms("a", "f160w")
    valid = np.isfinite(wht) & (wht > 0)
    expected = np.where(valid, 1.0 / np.sqrt(np.where(valid, wht.astype(float), 1.0)), np.inf)
    np.testing.assert_allclose(rms[valid], expected[valid], rtol=1e-6)
    assert np.all(np.isinf(rms[~valid])) and np.all(rms[~valid] > 0)
    assert rms.dtype == np.float32
    fp = s.footprint("a")
    expected_fp = np.isfinite(sci) & (sci != 0) & valid
    np.testing.assert_array_equal(fp, expected_fp)
    assert fp.dtype == bool and fp.sum() == 6


def test_rms_map_and_no_noise(tmp_path):
    s = make_survey(tmp_path, noise_type="rms")
    sci = np.arange(1, 7, dtype=np.float64).reshape(2, 3)
    rms_in = np.array([[0.5, 0.0, np.nan], [-1.0, 2.0, 3.0]])
    for b in s.bands:
        write(s.science_path("a", b), sci)
        write(s.noise_path("a", b), rms_in)
    rms = s.rms("a", "f125w")
    np.testing.assert_array_equal(rms, [[0.5, np.inf, np.inf], [np.inf, 2.0, 3.0]])
    np.testing.assert_array_equal(s.footprint("a"), [[True, False, False], [False, True, True]])

    (tmp_path / "x").mkdir()
    s2 = make_survey(tmp_path / "x", noise=False)
    for b in s2.bands:
        write(s2.science_path("a", b), sci)
    assert s2.rms("a", "f160w") is None
    assert s2.footprint("a").all()


def test_big_endian_and_integer_data(tmp_path):
    s = make_survey(tmp_path, noise=False)
    rng = np.random.default_rng(0)
    be = rng.normal(size=(5, 6)).astype(">f8")
    write(s.science_path("a", "f160w"), be)
    ints = rng.integers(-1000, 1000, size=(5, 6)).astype(">i2")
    hdu = fits.PrimaryHDU(ints)
    hdu.writeto(s.science_path("a", "f125w"))
    a = s.science("a", "f160w")
    assert a.dtype == np.float64 and a.dtype.isnative
    np.testing.assert_array_equal(a, be.astype(np.float64))
    b = s.science("a", "f125w")
    assert b.dtype == np.float32 and b.dtype.isnative
    np.testing.assert_array_equal(b, ints.astype(np.float32))
    # Native arrays work with numpy reductions without byte swapping surprises.
    assert a.sum() == pytest.approx(float(be.astype(float).sum()), rel=1e-12)


def test_image_in_extension_and_degenerate_axes(tmp_path):
    s = make_survey(tmp_path, noise=False)
    data = np.arange(12, dtype=np.float32).reshape(3, 4)
    write(s.science_path("a", "f160w"), data, primary_empty=True)
    write(s.science_path("a", "f125w"), data.reshape(1, 3, 4))
    assert s.shape("a") == (3, 4)
    np.testing.assert_array_equal(s.science("a", "f160w"), data)
    np.testing.assert_array_equal(s.science("a", "f125w"), data)


def test_non_2d_image_error(tmp_path):
    s = make_survey(tmp_path, noise=False)
    write(s.science_path("a", "f160w"), np.zeros((2, 3, 4), dtype=np.float32))
    write(s.science_path("a", "f125w"), np.zeros((3, 4), dtype=np.float32))
    with pytest.raises(ValueError, match=r"a_f160w_sci\.fits.*3-D image.*expected a 2-D image"):
        s.shape("a")


def test_shape_mismatch_names_files(tmp_path):
    s = make_survey(tmp_path)
    write(s.science_path("a", "f160w"), np.zeros((10, 10), dtype=np.float32))
    write(s.noise_path("a", "f160w"), np.ones((10, 10), dtype=np.float32))
    write(s.science_path("a", "f125w"), np.zeros((10, 12), dtype=np.float32))
    write(s.noise_path("a", "f125w"), np.ones((10, 12), dtype=np.float32))
    with pytest.raises(ValueError, match="differ in shape") as info:
        s.science("a", "f160w")
    msg = str(info.value)
    assert "a_f160w_sci.fits: 10x10" in msg and "a_f125w_sci.fits: 10x12" in msg


def test_missing_file_error_names_key(tmp_path):
    s = make_survey(tmp_path)
    write(s.science_path("a", "f160w"), np.zeros((4, 4), dtype=np.float32))
    with pytest.raises(FileNotFoundError, match=r"survey\.noise \(field 'a', band 'f160w'\)"):
        s.rms("a", "f160w")
    with pytest.raises(FileNotFoundError, match=r"survey\.science.*a_f125w_sci\.fits"):
        s.header("a", "f125w")


def test_pixel_scale_from_cdelt_and_cd(tmp_path):
    s = make_survey(tmp_path, noise=False, bands=("f160w",))
    data = np.ones((8, 8), dtype=np.float32)
    scale = 0.08
    write(s.science_path("a", "f160w"), data,
          celestial_header(cdelt=(-scale / 3600, scale / 3600)))
    assert s.pixel_scale_arcsec("a") == pytest.approx(scale, rel=1e-9)

    (tmp_path / "cd").mkdir()
    s2 = make_survey(tmp_path / "cd", noise=False, bands=("f160w",))
    theta, scale2 = np.radians(30.0), 0.06 / 3600
    cd = [[-scale2 * np.cos(theta), scale2 * np.sin(theta)],
          [scale2 * np.sin(theta), scale2 * np.cos(theta)]]
    write(s2.science_path("a", "f160w"), data, celestial_header(cd=cd))
    assert s2.pixel_scale_arcsec("a") == pytest.approx(0.06, rel=1e-9)

    # The config value wins over the header.
    s3 = make_survey(tmp_path, noise=False, bands=("f160w",), pixel_scale=0.1)
    assert s3.pixel_scale_arcsec("a") == 0.1


def test_pixel_scale_errors(tmp_path):
    s = make_survey(tmp_path, noise=False, bands=("f160w",))
    write(s.science_path("a", "f160w"), np.ones((8, 8), dtype=np.float32))
    with pytest.raises(ValueError, match="pixel_scale_arcsec"):
        s.pixel_scale_arcsec("a")
    clear_cache()
    s = make_survey(tmp_path, noise=False, bands=("f160w",))
    write(s.science_path("a", "f160w"), np.ones((8, 8), dtype=np.float32),
          celestial_header(cdelt=(-0.08 / 3600, 0.1 / 3600)))
    with pytest.raises(ValueError, match="not square"):
        s.pixel_scale_arcsec("a")


def test_cache_reuse_invalidation_readonly_and_pickle(tmp_path):
    s = make_survey(tmp_path, noise=False, bands=("f160w",))
    path = s.science_path("a", "f160w")
    write(path, np.full((4, 4), 1.0, dtype=np.float32))
    a1 = s.science("a", "f160w")
    assert s.science("a", "f160w") is a1                      # cached
    assert Survey.from_config(s.config).science("a", "f160w") is a1   # shared per process
    with pytest.raises(ValueError):
        a1[0, 0] = 5.0                                        # read-only: no silent corruption
    write(path, np.full((4, 4), 2.0, dtype=np.float32))
    st = os.stat(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert s.science("a", "f160w")[0, 0] == 2.0              # rewritten file is re-read
    blob = pickle.dumps(s)
    assert len(blob) < 20000                                  # images are not pickled
    assert pickle.loads(blob).science("a", "f160w")[0, 0] == 2.0


# --------------------------------------------------------------------------
# Masks, coverage and negative weights (issue 9, point 3)
# --------------------------------------------------------------------------
def _filled(s, field="a", shape=(40, 60), holes=None):
    for b in s.bands:
        sci = np.ones(shape, dtype=np.float32)
        wht = np.ones(shape, dtype=np.float32)
        if holes and b in holes:
            sci[holes[b]] = 0.0
            wht[holes[b]] = 0.0
        write(s.science_path(field, b), sci, celestial_header(cdelt=(-0.08 / 3600, 0.08 / 3600)))
        write(s.noise_path(field, b), wht)


def test_negative_weights_are_an_error_unless_masked(tmp_path):
    s = make_survey(tmp_path)
    _filled(s)
    wht = np.ones((40, 60), dtype=np.float32)
    wht[3:5, 7:10] = -1.0
    write(s.noise_path("a", "f125w"), wht)
    with pytest.raises(ValueError, match=r"6 negative weight pixel\(s\).*f125w.*negative_weights"):
        s.rms("a", "f125w")
    clear_cache()
    s2 = make_survey(tmp_path, negative_weights="mask", coverage="all_bands")
    assert s2.footprint("a").sum() == 40 * 60 - 6


def test_coverage_follows_the_selection_bands(tmp_path):
    holes = {"f125w": (slice(0, 40), slice(0, 15)), "f098m": (slice(0, 10), slice(0, 60))}
    bands = ("f160w", "f125w", "f098m")
    # The selection reads f125w only: its hole (a quarter) leaves the footprint, f098m's does not.
    s = make_survey(tmp_path, bands=bands, selection=["sn_f160w > 5", "sn_f125w < 2"])
    _filled(s, holes=holes)
    assert s.coverage_bands() == ("f160w", "f125w")
    assert s.footprint("a").sum() == 40 * 60 * 3 // 4
    clear_cache()
    s = make_survey(tmp_path, bands=bands, selection=["sn_f160w > 5"], coverage="all_bands")
    assert s.footprint("a").sum() == 40 * 45 - 10 * 45
    clear_cache()
    s = make_survey(tmp_path, bands=bands, selection=["sn_f125w < 2"], coverage="detection_band")
    assert s.footprint("a").sum() == 40 * 60


def test_fits_and_region_masks(tmp_path):
    s = make_survey(tmp_path, mask="{field}_mask.fits")
    _filled(s)
    m = np.zeros((40, 60), dtype=np.int16)
    m[:, :20] = 4                                   # a third of the field
    write(tmp_path / "img" / "a_mask.fits", m)
    assert s.footprint("a").sum() == 40 * 40
    clear_cache()
    # DS9: an image-coordinate box (1-based, centre 30.5,20.5, 10x20 px) and a sky circle.
    reg = tmp_path / "img" / "a.reg"
    reg.write_text("# Region file format: DS9\nimage\nbox(30.5,20.5,10,20,0)\n"
                   "icrs\ncircle(150.0,2.0,0.42\")\n")
    s = make_survey(tmp_path, mask="{field}.reg")
    masked = ~s.footprint("a")
    assert masked[10:30, 25:35].all()        # the box: 0-based centre (29.5, 19.5), 10 x 20 px
    yy, xx = np.mgrid[:40, :60]
    # celestial_header: CRPIX (5, 5) -> 0-based (4, 4) is at (150, 2); 0.42" = 5.25 px
    circle = (xx - 4) ** 2 + (yy - 4) ** 2 < 5.25 ** 2
    assert masked[circle].all()
    box = np.zeros((40, 60), bool)
    box[10:30, 25:35] = True
    assert masked.sum() == (box | circle).sum()
    clear_cache()
    s = make_survey(tmp_path, mask="{field}_nothere.reg")
    with pytest.raises(FileNotFoundError, match="survey.mask"):
        s.footprint("a")


def test_gzipped_and_plain_images_mix(tmp_path):
    """A layout where some images are .fits.gz and the template says .fits (or back) still runs."""
    import gzip
    import shutil

    s = make_survey(tmp_path)
    _filled(s)
    plain = s.science_path("a", "f125w")
    with open(plain, "rb") as src, gzip.open(str(plain) + ".gz", "wb") as dst:
        shutil.copyfileobj(src, dst)
    plain.unlink()
    assert s.science_path("a", "f125w").name.endswith(".fits.gz")
    np.testing.assert_array_equal(s.science("a", "f125w"), np.ones((40, 60), np.float32))
    assert s.science_path("a", "f160w").name.endswith("_sci.fits")


# ------------------------------------------------------------------------------
# Field set-up with bounded memory gives the same answers.
# ------------------------------------------------------------------------------
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
    s = fits_survey(tmp_path, sci, wht)
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
    s = fits_survey(tmp_path, sci, wht, negative="error")
    monkeypatch.setattr(sv, "ROW_BLOCK_PIXELS", 40)
    sv.clear_cache()
    for call in (lambda: s.rms("f", "b"), lambda: s.footprint("f")):
        with pytest.raises(ValueError, match=r"3 negative weight pixel\(s\)"):
            call()


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
