"""SExtractor keys honoured (issue 9, point 2): BACKPHOTO_TYPE/BACKPHOTO_THICK, MASK_TYPE, SATUR_LEVEL.

Every expected value is computed by hand from the synthetic scene: a pixel-sampled
Gaussian of known flux centred on a pixel, on a known pedestal plus a linear slope
(the slope cancels in any region symmetric about the centre), neighbours made of
known pixels, and SExtractor's rules (annulus geometry, mirrored pixels) written out.
"""
import copy
import dataclasses
import shutil
import subprocess
import textwrap

import numpy as np
import pytest

from glaciar.config import ConfigError, config_from_dict, store_hash
from glaciar.constants import FLAG_NO_DATA, FLAG_SATURATED, FLAG_SEP_ERROR, FLAG_STAMP_CLIPPED, \
    FLAG_WINDOW_AT_LIMIT
from glaciar.engine import photometry as phot
from glaciar.engine.classify import ClassificationParams
from glaciar.engine.detect import DetectionParams
from glaciar.engine.measure import MeasureSetup, measure_injected, reference_extraction
from glaciar.engine.scene import Scene
from glaciar.fieldprep import detection_params

from config_dicts import base, error_of, load

MOFFAT = {"profile": "moffat", "fwhm_arcsec": 0.18}
BASE = {"survey": {
    "fields": ["f1"], "image_dir": "images", "science": "{field}_{band}_drz.fits",
    "noise": "{field}_{band}_wht.fits", "detection_band": "f160w",
    "bands": {"f160w": {"filter": "wfc3_ir_f160w", "zeropoint": 25.0, "psf": MOFFAT}}}}


def _cfg(tmp_path, sex_text=None, **detection):
    d = copy.deepcopy(BASE)
    if sex_text is not None:
        (tmp_path / "k.sex").write_text(sex_text)
        detection["sex_file"] = "k.sex"
    if detection:
        d["detection"] = detection
    return config_from_dict(d, tmp_path, "config.yaml")


# ---------------------------------------------------------------------------
# Configuration: typed keys, mapped from .sex, in the store identity
# ---------------------------------------------------------------------------
def test_flag_bits_are_distinct_powers_of_two():
    bits = [FLAG_SEP_ERROR, FLAG_WINDOW_AT_LIMIT, FLAG_STAMP_CLIPPED, FLAG_NO_DATA, FLAG_SATURATED]
    assert all(b > 0 and b & (b - 1) == 0 for b in bits) and len(set(bits)) == len(bits)


def test_defaults_and_sex_mapping(tmp_path):
    d = _cfg(tmp_path).detection
    # SExtractor's defaults for BACKPHOTO_* and SATUR_LEVEL; MASK_TYPE null keeps sep's masking
    assert (d.backphoto_type, d.backphoto_thick, d.mask_type, d.satur_level) == ("global", 24, None, 50000.0)
    sex = "BACKPHOTO_TYPE LOCAL\nBACKPHOTO_THICK 12\nMASK_TYPE BLANK\nSATUR_LEVEL 3000.5\nSATUR_KEY SATURATE\n"
    cfg = _cfg(tmp_path, sex)
    d = cfg.detection
    assert (d.backphoto_type, d.backphoto_thick, d.mask_type, d.satur_level) == ("local", 12, "blank", 3000.5)
    p = detection_params(cfg)
    assert (p.backphoto_type, p.backphoto_thick, p.mask_type, p.satur_level) == ("local", 12, "blank", 3000.5)
    # keys given in the YAML win over the .sex file
    d = _cfg(tmp_path, sex, MASK_TYPE="correct").detection
    assert d.mask_type == "correct" and d.backphoto_type == "local"


@pytest.mark.parametrize("line, needle", [
    ("BACKPHOTO_TYPE NEARBY", "detection.BACKPHOTO_TYPE: expected one of global, local"),
    ("BACKPHOTO_THICK 0", "detection.BACKPHOTO_THICK"),
    ("MASK_TYPE SOMETIMES", "detection.MASK_TYPE: expected one of none, blank, correct"),
    ("SATUR_LEVEL -5", "detection.SATUR_LEVEL"),
])
def test_bad_values_are_refused_naming_key_and_file(tmp_path, line, needle):
    with pytest.raises(ConfigError) as info:
        _cfg(tmp_path, line + "\n")
    msg = str(info.value)
    assert needle in msg and "k.sex" in msg and "\n" not in msg.strip(), msg


@pytest.mark.parametrize("key, value", [("BACKPHOTO_TYPE", "local"), ("BACKPHOTO_THICK", 30),
                                        ("MASK_TYPE", "correct"), ("MASK_TYPE", "none"),
                                        ("SATUR_LEVEL", 1000.0)])
def test_each_key_changes_the_store_identity(tmp_path, key, value):
    assert store_hash(_cfg(tmp_path, **{key: value})) != store_hash(_cfg(tmp_path))


def test_engine_parameters_are_checked():
    for kw in (dict(backphoto_type="auto"), dict(backphoto_thick=0), dict(mask_type="CORRECT"),
               dict(satur_level=-1.0)):
        with pytest.raises(ValueError, match=next(iter(kw))):
            DetectionParams(**kw)


# ---------------------------------------------------------------------------
# BACKPHOTO_TYPE LOCAL
# ---------------------------------------------------------------------------
def test_background_mode_of_symmetric_and_contaminated_samples():
    # symmetric sample: mean = median, so SExtractor's mode is the centre
    v = 3.25 + np.array([-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0] * 10)
    assert phot.sextractor_background_mode(v) == pytest.approx(3.25, abs=1e-12)
    assert phot.sextractor_background_mode(np.full(50, -0.75)) == -0.75
    # Gaussian sky with 5 % of bright outliers: clipping keeps the estimate on the sky
    rng = np.random.default_rng(1)
    v = np.concatenate([rng.normal(10.0, 2.0, 40000), np.full(2000, 500.0)])
    assert phot.sextractor_background_mode(v) == pytest.approx(10.0, abs=0.05)


def test_annulus_geometry_is_sextractors():
    # object box y 10..17 (8 rows -> widened by 8//4 = 2), x 20..23 (4 cols -> by 1)
    inner, outer = phot.local_background_boxes([[10, 17, 20, 23]], 5, (100, 100))
    assert inner.tolist() == [[8, 20, 19, 25]] and outer.tolist() == [[3, 25, 14, 30]]
    # an object larger than half the image is widened by (image size - size) // 4
    inner, _ = phot.local_background_boxes([[0, 59, 0, 9]], 5, (100, 100))
    assert inner.tolist() == [[0 - 10, 60 + 10, 0 - 2, 10 + 2]]


def test_local_background_uses_annulus_pixels_of_no_object():
    img = np.full((60, 60), 100.0)          # inside the inner box and outside the outer box
    img[3:25, 14:30] = 3.0                  # the annulus (outer box)
    img[8:20, 19:25] = 100.0                # the inner box
    seg = np.zeros((60, 60), dtype=np.int32)
    seg[10:18, 20:24] = 1
    img[4:7, 15:18] = 1e4                   # another object in the annulus: ignored
    seg[4:7, 15:18] = 2
    nodata = np.zeros((60, 60), dtype=bool)
    img[22, 26] = -1e4                      # a pixel without data: ignored
    nodata[22, 26] = True
    boxes = [[10, 17, 20, 23]]
    assert phot.local_background(img, seg, nodata, boxes, 5).tolist() == [3.0]
    # the outer box must lie inside the image, its upper sides one pixel inside: else 0
    assert phot.local_background(img[:25], seg[:25], nodata[:25], boxes, 5).tolist() == [0.0]
    assert phot.local_background(img[:26], seg[:26], nodata[:26], boxes, 5).tolist() == [3.0]


N = 121
C = 60                                      # source centre: a pixel centre
F = 2000.0                                  # source flux [image units]
SIGMA = 1.5
B0, GX, GY = 0.3, 0.002, -0.0015            # pedestal and slope left by the global background


def _gauss(size=41, flux=F, sigma=SIGMA):
    h = size // 2
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    g = np.exp(-(xx ** 2 + yy ** 2) / (2 * sigma ** 2))
    return C - h, C - h, flux * g / g.sum()


def _measure(params, background=None, det_background=None, mode="windowed"):
    yy, xx = np.mgrid[:N, :N]
    base = (B0 + GX * (xx - C) + GY * (yy - C)) if background is None else background
    base = base.astype(np.float32)
    rms = np.ones((N, N), dtype=np.float32)
    ref = reference_extraction(base, rms, params, 25.0)
    if background is None:
        assert ref.segmap.max() == 0                  # the pedestal alone is not detected
    y0, x0, stamp = _gauss()
    scene = Scene(base, [(y0, x0, stamp)])
    setup = MeasureSetup(band_rms={"h": rms}, reference=ref, params=params,
                         classification=ClassificationParams(), zeropoints={"h": 25.0}, gains={"h": None},
                         detection_band="h", det_background=det_background)
    out = measure_injected(setup, scene, rms, {"h": scene}, np.array([float(C)]), np.array([float(C)]),
                           np.array([F]), np.array([25.0 - 2.5 * np.log10(F)]), mode=mode)
    return out, base, stamp


@pytest.mark.parametrize("mask_type", [None, "correct"])
def test_local_background_recovers_the_flux_global_misses(tmp_path, mask_type):
    """End to end: .sex keys -> config -> engine; LOCAL removes exactly the pedestal."""
    sex = "DETECT_THRESH 1.5\nPHOT_APERTURES 16\nBACKPHOTO_TYPE LOCAL\nBACKPHOTO_THICK 24\n"
    p_local = detection_params(_cfg(tmp_path, sex, MASK_TYPE=mask_type))
    assert p_local.backphoto_type == "local" and p_local.mask_type == mask_type
    p_global = dataclasses.replace(p_local, backphoto_type="global")
    loc, _, _ = _measure(p_local)
    glo, _, _ = _measure(p_global)
    assert loc["status"][0] == 0 and glo["status"][0] == 0
    # aperture of radius 8 px (holds the Gaussian to 1e-6): the slope cancels by symmetry
    assert loc["flux_aper0_h"][0] == pytest.approx(F, rel=1e-5)
    assert glo["flux_aper0_h"][0] - loc["flux_aper0_h"][0] == pytest.approx(B0 * np.pi * 8 ** 2, rel=1e-5)
    # ISO: GLOBAL - LOCAL = (number of segment pixels) x pedestal
    npix = (glo["flux_iso_h"][0] - loc["flux_iso_h"][0]) / B0
    assert npix > 20 and npix == pytest.approx(round(npix), abs=1e-3)
    # AUTO: the Kron ellipse holds the Gaussian; LOCAL leaves its flux alone
    assert loc["flux_auto_h"][0] == pytest.approx(F, rel=1e-3)
    assert glo["flux_auto_h"][0] - loc["flux_auto_h"][0] > 0.3 * B0 * npix
    # the errors do not change (SExtractor adds no term for the local background)
    assert loc["fluxerr_aper0_h"][0] == pytest.approx(glo["fluxerr_aper0_h"][0], rel=1e-12)
    # a pure slope (no pedestal) has a local background of 0: LOCAL = GLOBAL
    yy, xx = np.mgrid[:N, :N]
    slope_only = GX * (xx - C) + GY * (yy - C)
    a, _, _ = _measure(p_local, background=slope_only)
    b, _, _ = _measure(p_global, background=slope_only)
    assert a["flux_aper0_h"][0] == pytest.approx(b["flux_aper0_h"][0], rel=1e-6)


# ---------------------------------------------------------------------------
# MASK_TYPE
# ---------------------------------------------------------------------------
def _neighbour_scene():
    """Source 1 (Gaussian, flux F at pixel centre (30, 30)) and a neighbour block, label 2."""
    img = np.zeros((61, 61))
    y0, x0, g = _gauss()
    img += np.pad(g, ((30 - 20, 61 - 30 - 21), (30 - 20, 61 - 30 - 21)))
    seg = np.zeros((61, 61), dtype=np.int32)
    yy, xx = np.mgrid[:61, :61]
    seg[(xx - 30) ** 2 + (yy - 30) ** 2 < 16] = 1
    block = (slice(36, 38), slice(33, 36))             # 6 pixels, all inside r = 10 with weight 1
    img[block] += 7.0
    seg[block] = 2
    return img, seg, block


def _aper(img, seg, nodata, mask_type, r=10.0):
    fa, fea, _, _ = phot.sextractor_photometry(img, np.ones_like(img), seg, [1], nodata,
                                               phot.Ellipses([30.0], [30.0], [1.0], [1.0], [0.0], [3.5]),
                                               [2 * r], mask_type)
    return fa[0, 0], fea[0, 0]


def test_mask_types_give_the_analytic_aperture_sums():
    img, seg, block = _neighbour_scene()
    g = img.copy()
    g[block] -= 7.0                                     # the source's own light
    under = g[block].sum()                              # its light under the neighbour's pixels
    f, e = _aper(img, seg, None, "none")
    assert f == pytest.approx(F + 6 * 7.0, rel=1e-8)
    assert e ** 2 == pytest.approx(np.pi * 100, rel=1e-8)
    f, e = _aper(img, seg, None, "blank")
    assert f == pytest.approx(F - under, rel=1e-8)
    assert e ** 2 == pytest.approx(np.pi * 100 - 6, rel=1e-8)          # blanked pixels: no variance
    f, e = _aper(img, seg, None, "correct")
    assert f == pytest.approx(F, rel=1e-8)                             # mirror pixels hold the same light
    assert e ** 2 == pytest.approx(np.pi * 100, rel=1e-8)
    # mirrors that are themselves without data give 0, and so do those pixels
    nodata = np.zeros_like(seg, dtype=bool)
    mirror = (slice(60 - 37, 60 - 35), slice(60 - 35, 60 - 32))      # (2*30 - y, 2*30 - x)
    nodata[mirror] = True
    f, _ = _aper(img, seg, nodata, "correct")
    assert f == pytest.approx(F - under - g[mirror].sum(), rel=1e-8)
    # sep's masking (the default, MASK_TYPE null) is none of these for apertures: no neighbour mask
    sep_f, _ = phot.aperture_photometry(img, np.ones_like(img), [30.0], [30.0], [20.0])
    assert sep_f[0, 0] == pytest.approx(F + 6 * 7.0, rel=1e-8)


def test_mask_type_through_the_engine():
    """measure_injected with a detected neighbour (6 pixels of 40) in the original image."""
    base = np.zeros((N, N))
    base[C + 7:C + 9, C + 3:C + 6] = 40.0                  # inside r = 11 with weight 1
    params = DetectionParams(detect_thresh=1.5, phot_apertures=(22.0,))
    res = {}
    for m in ("none", "blank", "correct"):
        for mode in ("windowed", "full"):
            res[m, mode], _, _ = _measure(dataclasses.replace(params, mask_type=m), background=base,
                                          mode=mode)
            assert res[m, mode]["detection_id"][0] > 0
    for mode in ("windowed", "full"):
        f = {m: res[m, mode]["flux_aper0_h"][0] for m in ("none", "blank", "correct")}
        assert f["none"] == pytest.approx(F + 6 * 40.0, rel=1e-6)    # neighbour kept
        assert f["correct"] == pytest.approx(F, rel=1e-4)            # its pixels mirrored: source only
        assert F - 20.0 < f["blank"] < F                           # its pixels (and the source's light there) 0


# ---------------------------------------------------------------------------
# SATUR_LEVEL
# ---------------------------------------------------------------------------
def test_saturated_peak_rule():
    img = np.array([[0.0, 5.0, 9.0], [1.0, 2.0, 3.0]])
    seg = np.array([[1, 1, 2], [1, 0, 2]])
    pix = np.flatnonzero(seg)
    lab = seg.ravel()[pix]
    assert phot.saturated(img, pix, lab, [np.inf, 5.0, 9.5], 3).tolist() == [False, True, False]


def test_saturation_flag_above_and_below_the_level():
    params = DetectionParams(detect_thresh=1.5)
    bkg = np.full((N, N), 100.0, dtype=np.float32)
    out, base, stamp = _measure(params, det_background=bkg)
    peak = float(base[C, C]) + stamp.max()            # the brightest pixel, background-subtracted
    for level, flagged in ((peak + 100.0 - 1e-3, True), (peak + 100.0 + 1e-3, False)):
        for mode in ("windowed", "full"):
            out, _, _ = _measure(dataclasses.replace(params, satur_level=level), det_background=bkg, mode=mode)
            assert bool(out["source_flags"][0] & FLAG_SATURATED) is flagged, (level, mode)
            assert out["status"][0] == 0


# ---------------------------------------------------------------------------
# Against SExtractor itself (skipped where the binary is absent)
# ---------------------------------------------------------------------------
_SEX = shutil.which("source-extractor") or shutil.which("sex")
_SEX_PARAMS = ["NUMBER", "X_IMAGE", "Y_IMAGE", "XMIN_IMAGE", "XMAX_IMAGE", "YMIN_IMAGE", "YMAX_IMAGE",
               "FLUX_ISO", "FLUX_APER(1)", "FLAGS", "FLUX_MAX"]


def _run_sextractor(tmp_path, img, **keys):
    from astropy.io import fits

    fits.writeto(tmp_path / "img.fits", img, overwrite=True)
    (tmp_path / "p.param").write_text("\n".join(_SEX_PARAMS) + "\n")
    args = dict(CATALOG_NAME="c.cat", CATALOG_TYPE="ASCII", PARAMETERS_NAME="p.param", BACK_TYPE="MANUAL",
                BACK_VALUE="0", THRESH_TYPE="ABSOLUTE", DETECT_THRESH="1.5", ANALYSIS_THRESH="1.5",
                DETECT_MINAREA="5", FILTER="N", CLEAN="N", PHOT_APERTURES="16", GAIN="0",
                CHECKIMAGE_TYPE="SEGMENTATION", CHECKIMAGE_NAME="seg.fits", VERBOSE_TYPE="QUIET")
    args.update({k: str(v) for k, v in keys.items()})
    cmd = [_SEX, "img.fits", "-c", "/dev/null"]
    for k, v in args.items():
        cmd += ["-" + k, v]
    subprocess.run(cmd, check=True, cwd=tmp_path, capture_output=True)
    cat = np.atleast_2d(np.loadtxt(tmp_path / "c.cat"))
    return cat[np.argsort(cat[:, 0])], fits.getdata(tmp_path / "seg.fits").astype(np.int32)


@pytest.mark.skipif(_SEX is None, reason="SExtractor binary (Debian package source-extractor) not installed")
def test_against_sextractor(tmp_path):
    """Same image, SExtractor's own segmentation and centres: glaciar's rules give its numbers.

    An isolated Gaussian, and a bright Gaussian with a deblended neighbour, on a pedestal +
    slope + noise (sigma 0.05), global background fixed at 0 (BACK_TYPE MANUAL).
    """
    n = 201
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:n, :n]

    def gauss(x0, y0, f, s):
        g = np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * s * s))
        return f * g / g.sum()

    img = 0.3 + 0.002 * (xx - 100) - 0.0015 * (yy - 100) + rng.normal(0, 0.05, (n, n))
    img = (img + gauss(100, 100, 2000, 1.5) + gauss(107, 104, 300, 1.2) + gauss(150, 60, 500, 1.0)
           ).astype(np.float32)
    glo, seg = _run_sextractor(tmp_path, img, BACKPHOTO_TYPE="GLOBAL", MASK_TYPE="NONE")
    loc, seg_l = _run_sextractor(tmp_path, img, BACKPHOTO_TYPE="LOCAL", BACKPHOTO_THICK=24, MASK_TYPE="NONE")
    assert len(glo) == 3 and np.array_equal(seg, seg_l)
    iso = int(np.argmin(np.hypot(glo[:, 1] - 151, glo[:, 2] - 61)))     # the isolated object
    boxes = np.stack([glo[:, 5], glo[:, 6], glo[:, 3], glo[:, 4]], axis=1).astype(int) - 1
    dbkg = phot.local_background(img, seg, None, boxes, 24)
    npix = np.bincount(seg.ravel())[glo[:, 0].astype(int)]
    # ISO of the isolated object: SExtractor subtracts npix x its local background; same
    # value to 1 % of the pixel noise (SExtractor's median is from a quantised histogram)
    assert (glo[iso, 7] - loc[iso, 7]) / npix[iso] == pytest.approx(dbkg[iso], abs=0.01 * 0.05)
    # apertures of every object lose dbkg x area (SExtractor's 5x5-subsampled area: 0.1 %)
    assert np.allclose((glo[:, 8] - loc[:, 8]) / (np.pi * 8 ** 2), dbkg, rtol=2e-3)
    # MASK_TYPE: aperture fluxes from glaciar's rules with SExtractor's centres and
    # segmentation (its deblended objects own slightly different pixels internally: 1.5 %)
    for m in ("NONE", "BLANK", "CORRECT"):
        cat, _ = _run_sextractor(tmp_path, img, BACKPHOTO_TYPE="GLOBAL", MASK_TYPE=m)
        fa, _, _, _ = phot.sextractor_photometry(img, np.full(img.shape, 0.05), seg, cat[:, 0].astype(int), None,
                                                 phot.Ellipses(cat[:, 1] - 1, cat[:, 2] - 1, 1.0, 1.0, 0.0, 3.5),
                                                 [16.0], m.lower())
        assert fa[0, iso] == pytest.approx(cat[iso, 8], rel=1e-3), m
        assert np.allclose(fa[0], cat[:, 8], rtol=1.5e-2), (m, fa[0], cat[:, 8])
    # SATUR_LEVEL: FLAGS bit 4 exactly where the peak reaches the level
    pix = np.flatnonzero(seg)
    for level in (0.99 * glo[:, 10].min(), 0.5 * (glo[:, 10].min() + glo[:, 10].max()), 1.01 * glo[:, 10].max()):
        cat, _ = _run_sextractor(tmp_path, img, SATUR_LEVEL=level)
        ours = phot.saturated(img, pix, seg.ravel()[pix], np.r_[np.inf, np.full(len(cat), level)], len(cat) + 1)
        assert ((cat[:, 9].astype(int) & 4) > 0).tolist() == ours[cat[:, 0].astype(int)].tolist()


# ---------------------------------------------------------------------------
# Windowed detection stays exact with the new keys
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("keys", [dict(backphoto_type="local", mask_type="correct"),
                                  dict(backphoto_type="local", backphoto_thick=8, mask_type="blank",
                                       satur_level=5.0)])
def test_windowed_equals_full_frame_with_the_keys(keys):
    """100 sources on the crowded field of tests/engine/test_windows.py (toy_images.crowded_field):
    every column identical in both modes.

    The windows must hold each annulus and every region touching it (LOCAL), and the
    mirrored pixels (CORRECT), as the full frame sees them.
    """
    from glaciar.engine.detect import measure_background

    from toy_images import crowded_field, gaussian_stamps

    img = crowded_field(seed=2, ngal=120)
    params = dataclasses.replace(DetectionParams(), **keys)
    back, rms = measure_background(img, None, params)
    sub = img - back
    ref = reference_extraction(sub, rms, params, 25.0)
    xs, ys, flux, st = gaussian_stamps(np.random.default_rng(8))
    det = Scene(sub, st)
    bands = {"h": det, "j": Scene(0.7 * sub, [(a, b, 0.5 * d) for a, b, d in st])}
    setup = MeasureSetup(band_rms={"h": rms, "j": 1.3 * rms}, reference=ref, params=params,
                         classification=ClassificationParams(), zeropoints={"h": 25.0, "j": 26.0},
                         gains={"h": None, "j": 2.0}, detection_band="h", det_background=back)
    kw = dict(det_rms=rms, band_scenes=bands, x=xs, y=ys, input_flux_det=flux,
              input_mag_det=25.0 - 2.5 * np.log10(flux))
    w = measure_injected(setup, det, mode="windowed", **kw)
    f = measure_injected(setup, det, mode="full", **kw)
    assert (w["detection_id"] > 0).sum() > 50
    for c in w:
        if c == "detection_id":
            continue
        np.testing.assert_allclose(np.asarray(w[c], float), np.asarray(f[c], float), rtol=1e-9, atol=1e-12,
                                   err_msg=c)
    if "satur_level" in keys:
        assert 0 < int(((w["source_flags"] & FLAG_SATURATED) > 0).sum()) < (w["detection_id"] > 0).sum()


def test_sex_file_merge(tmp_path):
    sexdir = tmp_path / "sex"
    sexdir.mkdir()
    (sexdir / "my.conv").write_text("CONV NORM\n1 2 1\n2 4 2\n1 2 1\n")
    (sexdir / "default.sex").write_text(textwrap.dedent("""\
        # SExtractor config
        CATALOG_NAME     test.cat       # ignored
        DETECT_MINAREA   5
        DETECT_THRESH    1.5,25.0       # sigma first
        FILTER           Y
        FILTER_NAME      my.conv
        DEBLEND_NTHRESH  64
        CLEAN            N
        PHOT_APERTURES   2,4,6          # diameters
        PHOT_AUTOPARAMS  2.5, 3.5
        BACK_SIZE        128
        """))
    d = base()
    d["detection"] = {"sex_file": "sex/default.sex", "DEBLEND_NTHRESH": 16}
    det = load(d, tmp_path).detection
    assert det.sex_file == str((sexdir / "default.sex").resolve())
    assert det.detect_minarea == 5 and det.detect_thresh == 1.5      # from the .sex file
    assert det.deblend_nthresh == 16                                     # explicit key wins
    assert det.clean is False and det.phot_apertures == (2.0, 4.0, 6.0)
    assert det.phot_autoparams == (2.5, 3.5) and det.back_size == 128
    assert det.filter_name == str((sexdir / "my.conv").resolve())       # next to the .sex
    assert det.deblend_mincont == 0.005                                  # default kept
    (sexdir / "abs.sex").write_text("THRESH_TYPE ABSOLUTE\nDETECT_THRESH 0.01\n")
    d["detection"] = {"sex_file": "sex/abs.sex"}
    assert "THRESH_TYPE: only RELATIVE" in error_of(d, tmp_path)
    d["detection"] = {"sex_file": "sex/none.sex"}
    assert "detection.sex_file: file not found" in error_of(d, tmp_path)


# ---------------------------------------------------------------------------
# SExtractor keys -> the engine's DetectionParams (one reader, one validator)
# ---------------------------------------------------------------------------
def test_sex_file_reader_and_detection_params(tmp_path):
    from glaciar.config import read_sex_file
    from glaciar.engine.detect import DetectionParams
    from glaciar.fieldprep import detection_params

    (tmp_path / "my.conv").write_text("CONV NORM\n0 1 0\n1 4 1\n0 1 0\n")
    sex = tmp_path / "det.sex"
    sex.write_text("# comment\nDETECT_THRESH   1.5   # sigma\nDETECT_MINAREA 5\n"
                   "PHOT_APERTURES 2,4,6\nFILTER_NAME my.conv\nCATALOG_NAME out.cat\nCLEAN N\n")
    raw = read_sex_file(sex)
    assert raw["DETECT_THRESH"] == "1.5" and raw["PHOT_APERTURES"] == ["2", "4", "6"]
    d = base()
    d["detection"] = {"sex_file": "det.sex", "DETECT_MINAREA": 12}
    p = detection_params(load(d, tmp_path))
    assert p.detect_thresh == 1.5 and p.detect_minarea == 12          # explicit key wins
    assert p.phot_apertures == (2.0, 4.0, 6.0) and p.clean is False
    np.testing.assert_array_equal(p.filter_kernel, [[0, 1, 0], [1, 4, 1], [0, 1, 0]])
    d["detection"] = {"FILTER": False}
    q = detection_params(load(d, tmp_path))
    assert q.filter_kernel is None and q.filter_halfwidth == 0
    d["detection"] = {"FILTER_NAME": "gauss_3.0_7x7"}
    assert detection_params(load(d, tmp_path)).filter_halfwidth == 3
    # The config's defaults are the engine's defaults (one place).
    assert detection_params(load(base(), tmp_path)) == DetectionParams()


@pytest.mark.parametrize("key,value,expected", [
    ("DETECT_THRESH", "abc", "expected a number"), ("DETECT_MINAREA", 2.5, "expected an integer"),
    ("CLEAN", "maybe", "expected true/false"), ("PHOT_APERTURES", [1, "x"], "expected a number"),
    ("DEBLEND_MINCONT", 2.0, "must be <= 1"), ("FILTER_NAME", "nofilter", "unknown built-in filter"),
    ("FILTER_TYPE", "gauss", "expected one of conv, matched")])
def test_detection_errors_name_the_key(tmp_path, key, value, expected):
    d = base()
    d["detection"] = {key: value}
    msg = error_of(d, tmp_path)
    assert msg.startswith(f"config.yaml: detection.{key}") and expected in msg, msg


def test_sex_file_values_are_checked_and_named(tmp_path):
    (tmp_path / "bad.sex").write_text("DETECT_MINAREA 2.5\n")
    d = base()
    d["detection"] = {"sex_file": "bad.sex"}
    msg = error_of(d, tmp_path)
    assert "detection.DETECT_MINAREA: expected an integer" in msg
    assert str((tmp_path / "bad.sex").resolve()) in msg        # where the value came from


# ---------------------------------------------------------------------------
# Every SExtractor key honoured or refused (issue 9, point 2)
# ---------------------------------------------------------------------------
SEX_DEFAULTS = """\
CATALOG_NAME     test.cat
CATALOG_TYPE     ASCII_HEAD
PARAMETERS_NAME  default.param
DETECT_TYPE      CCD
DETECT_MINAREA   3
DETECT_THRESH    1.5
ANALYSIS_THRESH  1.5
FILTER           Y
FILTER_NAME      gauss_2.0_5x5.conv
DEBLEND_NTHRESH  32
DEBLEND_MINCONT  0.005
CLEAN            Y
CLEAN_PARAM      1.0
MASK_TYPE        CORRECT
WEIGHT_TYPE      NONE
WEIGHT_IMAGE     weight.fits
FLAG_IMAGE       flag.fits
FLAG_TYPE        OR
PHOT_APERTURES   5
PHOT_AUTOPARAMS  2.5, 3.5
PHOT_PETROPARAMS 2.0, 3.5
PHOT_AUTOAPERS   0.0,0.0
SATUR_LEVEL      50000.0
SATUR_KEY        SATURATE
MAG_ZEROPOINT    0.0
GAIN             0.0
GAIN_KEY         GAIN
PIXEL_SCALE      1.0
SEEING_FWHM      1.2
BACK_TYPE        AUTO
BACK_VALUE       0.0
BACK_SIZE        64
BACK_FILTERSIZE  3
BACKPHOTO_TYPE   GLOBAL
CHECKIMAGE_TYPE  NONE
MEMORY_OBJSTACK  3000
VERBOSE_TYPE     NORMAL
"""


def test_sextractor_default_file_is_accepted(tmp_path):
    (tmp_path / "default.sex").write_text(SEX_DEFAULTS)
    d = base()
    d["detection"] = {"sex_file": "default.sex"}
    cfg = load(d, tmp_path)
    det = cfg.detection
    assert (det.detect_thresh, det.detect_minarea, det.phot_apertures) == (1.5, 3, (5.0,))
    assert det.filter_name == "gauss_2.0_5x5" and det.weight_type is None
    assert any("WEIGHT_TYPE NONE" in w for w in cfg.warnings)


@pytest.mark.parametrize("line, needle", [
    ("BACK_TYPE MANUAL", "BACK_TYPE MANUAL: not supported"),
    ("GAIN 2.5", "GAIN 2.5: not supported"),
    ("INTERP_TYPE ALL", "INTERP_TYPE ALL: not supported"),
    ("DETECT_TYPE PHOTO", "DETECT_TYPE PHOTO"),
    ("FANCY_NEW_KEY 3", "FANCY_NEW_KEY: SExtractor key not supported"),
    ("WEIGHT_TYPE MAP_WEIGHT,MAP_RMS", "different types for detection and measurement"),
])
def test_sextractor_keys_that_would_change_the_answer_are_refused(tmp_path, line, needle):
    (tmp_path / "x.sex").write_text(SEX_DEFAULTS.replace("WEIGHT_TYPE      NONE\n", "") + line + "\n")
    d = base()
    d["detection"] = {"sex_file": "x.sex"}
    msg = error_of(d, tmp_path)
    assert msg.startswith("config.yaml: detection.sex_file: ") and needle in msg, msg
    assert str(tmp_path / "x.sex") in msg


def test_weight_type_from_sex_and_consistency(tmp_path):
    (tmp_path / "w.sex").write_text("WEIGHT_TYPE MAP_WEIGHT,MAP_WEIGHT\nWEIGHT_GAIN Y\n")
    d = base()
    d["detection"] = {"sex_file": "w.sex"}
    cfg = load(d, tmp_path)
    assert cfg.detection.weight_type == "map_weight" and cfg.detection.weight_gain is True
    d["survey"]["noise_type"] = "rms"
    assert "detection.WEIGHT_TYPE: MAP_WEIGHT needs survey.noise_type: weight" in error_of(d, tmp_path)
    d = base()
    d["detection"] = {"WEIGHT_GAIN": True}
    d["survey"]["bands"]["f160w"]["gain"] = 2000.0
    assert "detection.WEIGHT_GAIN: WEIGHT_GAIN Y" in error_of(d, tmp_path)
    d = base()
    del d["survey"]["noise"]
    d["detection"] = {"WEIGHT_TYPE": "MAP_WEIGHT"}
    assert "needs a noise map" in error_of(d, tmp_path)
