"""The ``source-extractor`` backend, checked against the SExtractor binary itself.

* The product is SExtractor's: FLUX_ISO in its catalogue is the sum of the
  measurement image over the check-image segment of the same NUMBER, and for
  objects whose pixel sets glaciar's sep backend reproduces, SExtractor's
  X_IMAGE - 1, Y_IMAGE - 1, A_IMAGE, B_IMAGE and THETA_IMAGE (in radians)
  are sep's barycentre and ellipse (so the 1-based and degree conventions are
  converted right).
* With SExtractor's semantics (``threshold_rms="filtered"``,
  ``clean_style="sextractor"``) and no deblending, glaciar's segmentation is
  SExtractor's pixel for pixel, also where the RMS varies and near pixels
  without data.
* CLEAN: SExtractor cleans as it extracts and gives a cleaned object's pixels
  to the object that absorbs it; glaciar's sep product with
  ``clean_style="sextractor"`` reproduces SExtractor's segmentation object
  by object wherever the detection itself agrees; sep's decisions with the
  hand-over (``"sep-merge"``) get part of the way, sep's CLEAN (``"sep"``)
  least.
* ``measure_injected(mode="source-extractor")`` classifies injected sources
  with glaciar's code on SExtractor's full-frame dual-image segmentation;
  without deblending (whose random pixel hand-out differs between any two
  runs) it agrees with the windowed sep engine on every recovered flag.

Skipped, with a message, where the binary is absent (``apt-get install
source-extractor``; ``.ci/run`` installs it when it can).
"""
import numpy as np
import pytest

from glaciar.engine.classify import ClassificationParams
from glaciar.engine.detect import DetectionParams
from glaciar.engine.measure import MeasureSetup, measure_injected, reference_extraction
from glaciar.engine.scene import Scene
from glaciar.engine.segmentation import sep_segmentation
from glaciar.engine.sextractor_backend import SExtractorError, find_sextractor, run_sextractor, \
    sextractor_segmentation

pytestmark = pytest.mark.skipif(find_sextractor() is None,
                                reason="SExtractor binary not found (apt-get install source-extractor, "
                                       "or set $GLACIAR_SEXTRACTOR)")

N = 300


def _field(seed=7):
    """Bright galaxies with faint neighbours and noise peaks around them (CLEAN's prey).

    The RMS map is constant (SExtractor thresholds the *filtered* variance, sep
    the pixel's: the two agree where the RMS is flat) and 20 % below the
    noise, so noise peaks pass the low threshold, as in deep-field settings."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:N, :N]
    img = 1.2 * rng.normal(size=(N, N))

    def add(x0, y0, f, r):
        img[...] += f * np.exp(-np.hypot(xx - x0, yy - y0) / r) / (2 * np.pi * r * r)

    for _ in range(6):
        x0, y0 = rng.uniform(30, N - 30, 2)
        add(x0, y0, 10 ** rng.uniform(3.0, 3.7), rng.uniform(3.5, 6.0))
        for _ in range(3):
            d, t = rng.uniform(8, 30), rng.uniform(0, 2 * np.pi)
            add(x0 + d * np.cos(t), y0 + d * np.sin(t), 10 ** rng.uniform(1.0, 1.8), rng.uniform(0.8, 1.5))
    for _ in range(30):
        x0, y0 = rng.uniform(0, N, 2)
        add(x0, y0, 10 ** rng.uniform(1.3, 2.8), rng.lognormal(np.log(1.8), 0.5))
    return img.astype(np.float32), np.ones((N, N), dtype=np.float32)


def _params(**kw):
    """SExtractor's semantics (its threshold with a filter and a weight map, its CLEAN), no deblending."""
    base = dict(detect_thresh=0.8, detect_minarea=9, deblend_mincont=1.0, clean=True, clean_param=1.0,
                phot_apertures=(4.0,), threshold_rms="filtered", clean_style="sextractor")
    base.update(kw)
    return DetectionParams(**base)


def _pixel_sets(seg):
    flat = seg.ravel()
    nz = np.flatnonzero(flat)
    order = np.argsort(flat[nz], kind="stable")
    labs, start = np.unique(flat[nz][order], return_index=True)
    return {int(lab): frozenset(nz[order][s:e].tolist()) for lab, s, e in zip(labs, start, list(start[1:]) + [nz.size])}


def _matching(a_seg, b_seg):
    """Labels of a whose pixel set is exactly one of b's: {a label: b label}."""
    sa, sb = _pixel_sets(a_seg), _pixel_sets(b_seg)
    inv = {v: k for k, v in sb.items()}
    return {k: inv[v] for k, v in sa.items() if v in inv}


def test_matched_filter_is_refused():
    with pytest.raises(ValueError, match="matched"):
        run_sextractor(np.zeros((20, 20)), np.ones((20, 20)), DetectionParams(filter_type="matched"))


def test_product_is_sextractors_catalogue_and_check_image():
    img, rms = _field()
    p = _params()
    S = sextractor_segmentation(img, rms, p)
    assert len(S) >= 20
    # FLUX_ISO = sum of the image over the check-image segment (absorbed fragments included)
    iso = np.bincount(S.seg.ravel(), weights=img.astype(np.float64).ravel(), minlength=len(S) + 1)[1:]
    np.testing.assert_allclose(iso, S.flux_iso, rtol=1e-6)
    # geometry in glaciar's conventions: sep's values for the objects both segment alike
    G = sep_segmentation(img, rms, p)
    match = _matching(S.seg, G.seg)
    assert len(match) >= 0.9 * len(S)
    k = np.array(sorted(match)) - 1
    g = np.array([match[i + 1] for i in k]) - 1
    for f, tol in (("x", 1e-3), ("y", 1e-3), ("a", 1e-3), ("b", 1e-3)):
        np.testing.assert_allclose(getattr(S, f)[k], getattr(G, f)[g], atol=tol, err_msg=f)
    dth = np.angle(np.exp(2j * (S.theta[k] - G.theta[g]))) / 2           # angles modulo pi
    round_ = np.abs(G.a[g] - G.b[g]) < 0.05 * G.a[g]
    assert np.all(np.abs(dth[~round_]) < 1e-3)


def test_sextractor_clean_style_reproduces_sextractors_clean():
    img, rms = _field()
    S_off = sextractor_segmentation(img, rms, _params(clean=False))
    S = sextractor_segmentation(img, rms, _params(clean=True))
    assert len(S_off) - len(S) >= 5                     # CLEAN acts on this field
    G_off = sep_segmentation(img, rms, _params(clean=False))
    same_off = len(_matching(S_off.seg, G_off.seg))     # detection alone: all but threshold roundings
    assert same_off >= len(S_off) - 3
    same = {style: len(_matching(S.seg, sep_segmentation(img, rms, _params(clean=True, clean_style=style)).seg))
            for style in ("sextractor", "sep-merge", "sep")}
    # SExtractor's CLEAN, emulated: every object the detection itself agrees on
    assert same["sextractor"] >= len(S) - (len(S_off) - same_off)
    # the hand-over of absorbed pixels alone gets part of the way; sep's CLEAN least
    assert same["sep"] < same["sep-merge"] < same["sextractor"]


def _varying_field(seed=9):
    """As :func:`_field`, but an RMS map that varies by a factor 2 and a hole without data."""
    img, _ = _field(seed)
    yy, xx = np.mgrid[:N, :N]
    rms = (1.0 + 0.5 * np.sin(xx / 37.0) * np.cos(yy / 23.0)).astype(np.float32)
    rng = np.random.default_rng(seed + 1)
    img = (img + (rms - 1.0) * rng.normal(size=(N, N))).astype(np.float32)
    mask = np.zeros((N, N), dtype=bool)
    mask[140:170, 60:110] = True
    return img, rms, mask


@pytest.mark.parametrize("clean", [False, True])
def test_sextractor_semantics_reproduce_sextractor_exactly(clean):
    """threshold_rms="filtered" (SExtractor's threshold with a filter and a weight map) and
    clean_style="sextractor": glaciar's segmentation is SExtractor's, object for object and pixel
    for pixel, on a field whose RMS varies and which has a hole without data.  (No deblending:
    both programs hand a split region's faint pixels out at random.)"""
    img, rms, mask = _varying_field()
    p = _params(clean=clean, threshold_rms="filtered", clean_style="sextractor")
    S = sextractor_segmentation(img, rms, p, mask=mask)
    G = sep_segmentation(img, rms, p, mask=mask)
    assert len(S) >= 40
    assert len(G) == len(S)
    assert len(_matching(S.seg, G.seg)) == len(S)
    assert np.array_equal(S.seg > 0, G.seg > 0)
    # and sep's own threshold (each pixel's RMS) does not
    Gp = sep_segmentation(img, rms, _params(clean=clean, threshold_rms="pixel", clean_style="sextractor"),
                          mask=mask)
    assert not np.array_equal(S.seg > 0, Gp.seg > 0)


def _inject(img, rng, n=60, h=7):
    xs = rng.uniform(5, N - 5, n)
    ys = rng.uniform(5, N - 5, n)
    flux = 10 ** rng.uniform(1.3, 2.6, n)
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    st = []
    for x, y, f in zip(xs, ys, flux):
        ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        p = np.exp(-((xx - (x - ix)) ** 2 + (yy - (y - iy)) ** 2) / (2 * 1.4 ** 2))
        st.append((iy - h, ix - h, f * p / p.sum()))
    return xs, ys, flux, Scene(img, st)


@pytest.mark.parametrize("clean", [False, True])
def test_source_extractor_mode_agrees_with_windowed_sep(clean):
    img, rms = _field(seed=8)
    p = _params(clean=clean)
    xs, ys, flux, scene = _inject(img.astype(np.float64), np.random.default_rng(3))
    kw = dict(band_scenes={"h": scene}, x=xs, y=ys, input_flux_det=flux, input_mag_det=25 - 2.5 * np.log10(flux))
    setup = dict(band_rms={"h": rms}, params=p, classification=ClassificationParams(min_sn=8.0),
                 zeropoints={"h": 25.0}, gains={"h": None}, detection_band="h")
    ref_se = reference_extraction(img, rms, p, 25.0, backend="source-extractor")
    ref_sep = reference_extraction(img, rms, p, 25.0)
    se = measure_injected(MeasureSetup(reference=ref_se, **setup), scene, rms, mode="source-extractor", **kw)
    win = measure_injected(MeasureSetup(reference=ref_sep, **setup), scene, rms, mode="windowed", **kw)
    rec_se = se["status"] >= 0
    rec_w = win["status"] >= 0
    assert 10 <= rec_se.sum() <= len(xs) - 10
    assert np.array_equal(rec_se, rec_w), np.flatnonzero(rec_se != rec_w)
    both = np.isfinite(se["flux_iso_h"]) & np.isfinite(win["flux_iso_h"])
    rel = np.abs(se["flux_iso_h"][both] - win["flux_iso_h"][both]) / np.abs(win["flux_iso_h"][both])
    assert np.mean(rel < 1e-6) >= 0.95              # the same segments, to float32 image precision


def test_missing_binary_is_a_clear_error(monkeypatch):
    monkeypatch.setenv("PATH", "/nonexistent")
    monkeypatch.delenv("GLACIAR_SEXTRACTOR", raising=False)
    with pytest.raises(SExtractorError, match="source-extractor"):
        run_sextractor(np.zeros((20, 20)), np.ones((20, 20)), DetectionParams())
