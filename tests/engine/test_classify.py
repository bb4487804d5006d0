"""Recovery classes on small synthetic segmentation maps with known answers."""
import math

import numpy as np
import pytest
from scipy.special import erf

from glaciar.constants import (STATUS_BLENDED_FAILED, STATUS_BLENDED_FAINTER, STATUS_BLENDED_PASSED,
                               STATUS_ISOLATED, STATUS_LOW_SN, STATUS_NOT_DETECTED)
from glaciar.engine.classify import (ClassificationParams, classify, flux_test, footprint_overlap,
                                     select_detection)
from glaciar.engine.detect import DetectionParams
from glaciar.engine.measure import FieldReference, MeasureSetup, measure_injected
from glaciar.engine.scene import Scene

P = ClassificationParams()


def _scene():
    """20x40 maps: new detections 1..5 and original sources 1..3 (mag 24, 28, 22)."""
    new = np.zeros((20, 40), dtype=np.int32)
    ref = np.zeros((20, 40), dtype=np.int32)
    new[2:7, 2:7] = 1                 # isolated: no original pixel under it
    new[2:7, 10:15] = 2               # on a faint original source (id 2, mag 28)
    ref[4:7, 12:15] = 2               # 9 of 25 pixels
    new[10:18, 2:12] = 3              # on a bright original (id 3): 8 of 80 px overlap
    ref[16:18, 8:12] = 3
    new[10:18, 20:30] = 4             # on a bright original (id 1): 40 of 80 px overlap
    ref[10:14, 20:30] = 1
    new[2:7, 30:35] = 5               # detected, low S/N
    ref_mag = np.array([24.0, 28.0, 22.0])
    return new, ref, ref_mag


def test_each_status_on_a_synthetic_scene():
    new, ref, ref_mag = _scene()
    #            iso  fainter  pass  fail  undetected  low-sn
    x = np.array([4.0, 12.0, 6.0, 25.0, 20.0, 32.0])
    y = np.array([4.0, 4.0, 14.0, 14.0, 4.0, 4.0])
    flux = np.bincount(new.ravel(), minlength=6).astype(float)
    lab = select_detection(new, x, y, flux, 3)
    np.testing.assert_array_equal(lab, [1, 2, 3, 4, 0, 5])
    n_fp, n_ov, blend = footprint_overlap(new, lab, ref, ref_mag)
    np.testing.assert_array_equal(n_fp, [25, 25, 80, 80, 0, 25])
    np.testing.assert_array_equal(n_ov, [0, 9, 8, 40, 0, 0])
    np.testing.assert_array_equal(blend, [0, 2, 3, 1, 0, 0])
    sn = np.array([20.0, 20.0, 20.0, 20.0, np.nan, 3.0])
    input_mag = np.full(6, 26.0)
    template = np.full(6, 100.0)     # the injected template's AUTO flux in the same ellipse
    recovered = np.array([100.0, 90.0, 110.0, 110.0, np.nan, 50.0])
    bmag = np.where(blend > 0, ref_mag[np.maximum(blend - 1, 0)], np.nan)
    st = classify(lab, sn, n_fp, n_ov, bmag, input_mag, recovered, template, P)
    np.testing.assert_array_equal(st, [STATUS_ISOLATED, STATUS_BLENDED_FAINTER, STATUS_BLENDED_PASSED,
                                       STATUS_BLENDED_FAILED, STATUS_NOT_DETECTED, STATUS_LOW_SN])


def test_brighter_blend_fails_on_flux_alone():
    # overlap 10 % passes, but recovered flux 30 % high fails
    st = classify(np.array([1]), np.array([50.0]), np.array([100]), np.array([10]), np.array([22.0]),
                  np.array([26.0]), np.array([130.0]), np.array([100.0]), P)
    assert st[0] == STATUS_BLENDED_FAILED
    st = classify(np.array([1]), np.array([50.0]), np.array([100]), np.array([25]), np.array([22.0]),
                  np.array([26.0]), np.array([125.0]), np.array([100.0]), P)
    assert st[0] == STATUS_BLENDED_PASSED          # both limits are inclusive


def test_equal_magnitude_counts_as_brighter_and_nan_as_fainter():
    args = (np.array([1, 1]), np.array([50.0, 50.0]), np.array([100, 100]), np.array([60, 60]),
            np.array([26.0, np.nan]), np.array([26.0, 26.0]), np.array([100.0, 100.0]), np.array([100.0, 100.0]))
    np.testing.assert_array_equal(classify(*args, P), [STATUS_BLENDED_FAILED, STATUS_BLENDED_FAINTER])


def test_select_detection_rules():
    seg = np.zeros((9, 9), dtype=np.int32)
    seg[4, 4] = 7                      # central pixel wins even if a minority
    seg[3, 3:6] = 2
    seg[5, 3:6] = 2
    assert select_detection(seg, [4.0], [4.0], np.ones(8), 3)[0] == 7
    seg[4, 4] = 0                      # then the majority
    seg[4, 3] = 3
    assert select_detection(seg, [4.0], [4.0], np.ones(8), 3)[0] == 2
    # tie on pixel count -> brightest
    seg = np.zeros((9, 9), dtype=np.int32)
    seg[3, 3:6] = 1
    seg[5, 3:6] = 2
    flux = np.array([0.0, 5.0, 9.0])
    assert select_detection(seg, [4.0], [4.0], flux, 3)[0] == 2
    flux = np.array([0.0, 9.0, 5.0])
    assert select_detection(seg, [4.0], [4.0], flux, 3)[0] == 1
    # the box is centred: a segment 2 px away is outside a 3x3 box, inside a 5x5 box
    seg = np.zeros((9, 9), dtype=np.int32)
    seg[6, 4] = 4
    assert select_detection(seg, [4.0], [4.0], np.ones(5), 3)[0] == 0
    assert select_detection(seg, [4.0], [4.0], np.ones(5), 5)[0] == 4
    # rounding half up: x = 3.5 is pixel 4
    seg = np.zeros((9, 9), dtype=np.int32)
    seg[4, 5] = 1
    assert select_detection(seg, [3.5], [4.0], np.ones(2), 1)[0] == 0
    assert select_detection(seg, [4.5], [4.0], np.ones(2), 1)[0] == 1


def test_blend_is_the_most_overlapping_not_the_max_id():
    new = np.zeros((5, 10), dtype=np.int32)
    new[:, :] = 1
    ref = np.zeros((5, 10), dtype=np.int32)
    ref[:, :6] = 1      # 30 px
    ref[:, 8:] = 9      # 10 px
    _, n_ov, blend = footprint_overlap(new, np.array([1]), ref)
    assert blend[0] == 1 and n_ov[0] == 40


def test_params_validation():
    with pytest.raises(ValueError, match="search_box"):
        ClassificationParams(search_box=4)
    with pytest.raises(ValueError, match="sn_definition"):
        ClassificationParams(sn_definition="peak")
    with pytest.raises(ValueError, match="max_overlap_fraction"):
        ClassificationParams(max_overlap_fraction=1.5)


def test_flux_test_hand_cases():
    rec = np.array([125.0, 75.0, 125.01, 74.99, 5.0, 0.0, np.nan, 100.0, 100.0])
    tpl = np.array([100.0, 100.0, 100.0, 100.0, 0.0, 0.0, 100.0, np.nan, -100.0])
    np.testing.assert_array_equal(flux_test(rec, tpl, 0.25),
                                  [True, True, False, False, False, False, False, False, False])
    # tolerance 0: only the exact template flux passes
    np.testing.assert_array_equal(flux_test([100.0, 100.1], [100.0, 100.0], 0.0), [True, False])


# ---------------------------------------------------------------------------
# The status-2 flux test through the whole measurement, for every S/N definition
# ---------------------------------------------------------------------------
SIGMA = 2.0            # Gaussian source [pixels]
FLUX = 200.0           # its input flux [image units]
CENTRE = (40.0, 40.0)  # (y, x), a pixel centre


def _gaussian_stamp(half=15):
    """Pixel integrals (exact, erf) of a unit-flux round Gaussian centred on the central pixel."""
    edges = np.arange(-half - 0.5, half + 1.0)
    cdf = 0.5 * (1 + erf(edges / (SIGMA * math.sqrt(2))))
    p = np.diff(cdf)
    return np.outer(p, p), half


def _measure(k_neighbour, sn_definition, mode="windowed", seed=3):
    """One source injected on a noiseless-ish 80x80 field.

    The original image holds ``k_neighbour`` x the source's own profile under
    it: light of a neighbour that adds exactly that fraction of the source's
    flux through *any* aperture (so the expected excess is known by
    construction, whatever Kron ellipse sep finds).  The original
    segmentation marks a brighter original source (mag 15) on 9 pixels of
    the source's footprint (well under 25 %), so the flux test alone decides
    between status 2 and -1.
    """
    rng = np.random.default_rng(seed)
    rms = np.full((80, 80), 0.01)
    stamp, h = _gaussian_stamp()
    y0, x0 = int(CENTRE[0]) - h, int(CENTRE[1]) - h
    base = rng.normal(size=(80, 80)) * rms
    base[y0:y0 + stamp.shape[0], x0:x0 + stamp.shape[1]] += k_neighbour * FLUX * stamp
    ref_seg = np.zeros((80, 80), dtype=np.int32)
    ref_seg[41:44, 41:44] = 1
    reference = FieldReference(ref_seg, np.array([1e4]), np.array([15.0]))
    scene = Scene(base, [(y0, x0, stamp, FLUX)])
    cls = ClassificationParams(sn_definition=sn_definition)
    setup = MeasureSetup(band_rms={"h": rms}, reference=reference, params=DetectionParams(),
                         classification=cls, zeropoints={"h": 25.0}, gains={"h": None}, detection_band="h")
    return measure_injected(setup, scene, rms, {"h": scene}, np.array([CENTRE[1]]),
                            np.array([CENTRE[0]]), np.array([FLUX]),
                            np.array([25.0 - 2.5 * math.log10(FLUX)]), mode=mode)


@pytest.mark.parametrize("sn_definition", ["iso", "aper", "auto"])
def test_isolated_source_passes_the_flux_test_whatever_the_sn_definition(sn_definition):
    out = _measure(0.0, sn_definition)
    assert out["sn_h"][0] > 100                            # noiseless-ish
    assert 0 < out["overlap_fraction"][0] <= 0.25          # brighter blend by overlap only
    # The template's AUTO flux is the input flux times the Kron ellipse's enclosed fraction:
    # a Kron aperture holds more than 90 % of a Gaussian's light.
    assert 0.9 * FLUX < out["flux_auto_template"][0] <= FLUX
    assert out["status"][0] == STATUS_BLENDED_PASSED
    # The old rule (S/N flux against the total input flux) fails it with aperture S/N: a
    # 4-px-diameter aperture holds 1 - exp(-r^2 / 2 sigma^2) = 39 % of a sigma = 2 px Gaussian.
    frac = 1 - math.exp(-2.0 ** 2 / (2 * SIGMA ** 2))
    assert abs(frac * FLUX - FLUX) > 0.25 * FLUX
    np.testing.assert_allclose(out["flux_aper0_h"][0], frac * FLUX, rtol=0.05)


@pytest.mark.parametrize("sn_definition", ["iso", "aper", "auto"])
@pytest.mark.parametrize("k, expected", [(0.10, STATUS_BLENDED_PASSED), (0.18, STATUS_BLENDED_PASSED),
                                         (0.32, STATUS_BLENDED_FAILED), (0.45, STATUS_BLENDED_FAILED)])
def test_neighbour_adding_more_than_the_tolerance_fails(sn_definition, k, expected):
    out = _measure(k, sn_definition)
    assert 0 < out["overlap_fraction"][0] <= 0.25
    # the measured AUTO flux is the template's plus the neighbour's k of it (by construction)
    np.testing.assert_allclose(out["flux_auto_h"][0] / out["flux_auto_template"][0], 1 + k, atol=0.01)
    assert out["status"][0] == expected


def test_flux_test_same_in_windowed_and_full_frame():
    for k in (0.0, 0.4):
        w, f = _measure(k, "iso", "windowed"), _measure(k, "iso", "full")
        assert w["status"][0] == f["status"][0]
        np.testing.assert_allclose(w["flux_auto_template"], f["flux_auto_template"], rtol=1e-12)
