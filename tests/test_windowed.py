"""Windowed detection equals a full-frame extraction: 2000 injected sources.

A 600x600 synthetic field (exponential-disk galaxies of a wide range of
sizes and fluxes, Gaussian noise with a varying RMS map) receives 20 x 100
non-overlapping Gaussian stamps; every per-source column from
``mode="windowed"`` must equal ``mode="full"`` (floats to 1e-9 relative).
"""
import numpy as np
import pytest

from glaciar.constants import STATUS_CODES
from glaciar.engine.classify import ClassificationParams
from glaciar.engine.detect import DetectionParams, measure_background
from glaciar.engine.measure import MeasureSetup, measure_injected, output_columns, reference_extraction
from glaciar.engine.scene import Scene

N = 600


def _field(seed=0, ngal=150):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:N, :N]
    img = np.zeros((N, N))
    for _ in range(ngal):
        x0, y0 = rng.uniform(0, N, 2)
        r = rng.lognormal(np.log(2.0), 0.5)
        q, pa = rng.uniform(0.4, 1.0), rng.uniform(0, np.pi)
        f = 10 ** rng.uniform(0.5, 3.0)
        s = int(min(12 * r + 5, 60))
        ya, yb, xa, xb = max(int(y0) - s, 0), min(int(y0) + s + 1, N), max(int(x0) - s, 0), min(int(x0) + s + 1, N)
        dx, dy = xx[ya:yb, xa:xb] - x0, yy[ya:yb, xa:xb] - y0
        u = dx * np.cos(pa) + dy * np.sin(pa)
        v = (-dx * np.sin(pa) + dy * np.cos(pa)) / q
        img[ya:yb, xa:xb] += f * np.exp(-np.hypot(u, v) / r) / (2 * np.pi * r * r * q)
    rms = 0.05 * (1 + 0.5 * np.sin(xx / 90.0) * np.cos(yy / 70.0))
    return img + rng.normal(size=(N, N)) * rms


def _stamps(rng, nsrc=100, size=21):
    h = size // 2
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    g = int(np.ceil(np.sqrt(nsrc)))
    cell = (N - 2 * h) / g
    cells = rng.permutation(g * g)[:nsrc]         # one per cell: stamps never overlap
    xs = np.clip(((cells % g) + rng.uniform(0.2, 0.8, nsrc)) * cell + h / 2, 1, N - 2)
    ys = np.clip(((cells // g) + rng.uniform(0.2, 0.8, nsrc)) * cell + h / 2, 1, N - 2)
    flux = 10 ** rng.uniform(-0.3, 1.7, nsrc)
    out = []
    for x, y, f in zip(xs, ys, flux):
        ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        s = rng.uniform(0.8, 2.5)
        p = np.exp(-((xx - (x - ix)) ** 2 + (yy - (y - iy)) ** 2) / (2 * s * s))
        out.append((iy - h, ix - h, f * p / p.sum()))
    return xs, ys, flux, out


@pytest.fixture(scope="module")
def field():
    img = _field()
    params = DetectionParams()
    back, rms = measure_background(img, None, params)
    sub = img - back
    return sub, rms, params, reference_extraction(sub, rms, params, 25.0)


def test_windowed_equals_full_frame(field, assert_same_outputs):
    sub, rms, params, ref = field
    cls = ClassificationParams()
    rng = np.random.default_rng(5)
    statuses = []
    n_checked = 0
    for it in range(20):
        xs, ys, flux, st = _stamps(rng)
        det = Scene(sub, st)
        bands = {"h": det, "j": Scene(0.7 * sub, [(a, b, 0.5 * d) for a, b, d in st])}
        setup = MeasureSetup(band_rms={"h": rms, "j": 1.3 * rms}, reference=ref, params=params,
                             classification=cls, zeropoints={"h": 25.0, "j": 26.0},
                             gains={"h": None, "j": 2.0}, detection_band="h")
        kw = dict(det_rms=rms, band_scenes=bands, x=xs, y=ys, input_flux_det=flux,
                  input_mag_det=25.0 - 2.5 * np.log10(flux))
        w = measure_injected(setup, det, mode="windowed", **kw)
        f = measure_injected(setup, det, mode="full", **kw)
        assert set(w) == set(output_columns(["h", "j"], 2))
        assert_same_outputs(w, f, it)
        statuses.append(w["status"])
        n_checked += xs.size
    s = np.concatenate(statuses)
    assert n_checked >= 2000
    # the comparison covers every class, deblended blends included
    counts = {c: int((s == c).sum()) for c in STATUS_CODES}
    assert all(v > 0 for v in counts.values()), counts


def test_scene_adds_and_clips_stamps():
    base = np.arange(50.0).reshape(5, 10)
    st = np.ones((3, 3))
    sc = Scene(base, [(-1, -1, st), (0, 0, 2 * st), (3, 8, st)])
    full = sc.full()
    expected = base.copy()
    expected[0:2, 0:2] += 1          # first stamp, clipped at the corner
    expected[0:3, 0:3] += 2          # overlapping stamps add, never overwrite
    expected[3:5, 8:10] += 1
    np.testing.assert_array_equal(full, expected)
    np.testing.assert_array_equal(sc.window(1, 4, 1, 9), expected[1:4, 1:9])
    np.testing.assert_array_equal(sc.window(-5, 2, 8, 20), expected[0:2, 8:10])
    np.testing.assert_array_equal(sc.clipped(), [True, False, True])
    assert base[0, 0] == 0.0         # the base image is never modified


def test_sep_errors_are_flagged_not_raised(field):
    from glaciar.constants import COL_FLAGS, FLAG_SEP_ERROR, STATUS_NOT_DETECTED
    sub, rms, _, ref = field
    bad = DetectionParams(sub_object_limit=1, deblend_mincont=0.0)
    xs, ys, flux, st = _stamps(np.random.default_rng(1), nsrc=20)
    det = Scene(sub, st)
    setup = MeasureSetup(band_rms={"h": rms}, reference=ref, params=bad, classification=ClassificationParams(),
                         zeropoints={"h": 25.0}, gains={"h": None}, detection_band="h")
    out = measure_injected(setup, det, rms, {"h": det}, xs, ys, flux, 25 - 2.5 * np.log10(flux))
    err = (out[COL_FLAGS] & FLAG_SEP_ERROR) > 0
    assert err.any()
    assert np.all(out["status"][err] == STATUS_NOT_DETECTED) and np.all(np.isnan(out["flux_iso_h"][err]))


def test_matched_filter_objects_without_a_positive_moment_matrix_are_measured():
    """sep's catalogue gives b = NaN (and a = NaN) for objects whose second-moment matrix is
    not positive, which its matched filter (noise-aware) detects in noise of varying RMS;
    the engine passed them to sep's aperture calls, which refused ("invalid aperture
    parameters").  They are measured as degenerate ellipses in both modes, which are one
    path (the matched filter runs full frame)."""
    from glaciar.engine.detect import sep_extract

    rng = np.random.default_rng(0)
    n = 64
    rms = np.exp(0.5 * rng.normal(size=(n, n))).astype(np.float32)
    img = rng.normal(size=(n, n)) * rms
    params = DetectionParams(filter_type="matched")
    cat, _ = sep_extract(img.astype(np.float32), rms, np.zeros((n, n), dtype=bool), params, False)
    nan = ~np.isfinite(cat["b"])
    assert nan.sum() >= 2                      # the case exists on this image
    xs, ys = np.asarray(cat["x"][nan], dtype=np.float64), np.asarray(cat["y"][nan], dtype=np.float64)
    ref = reference_extraction(img, rms, params, 25.0)
    det = Scene(img, [])
    setup = MeasureSetup(band_rms={"h": rms}, reference=ref, params=params, classification=ClassificationParams(),
                         zeropoints={"h": 25.0}, gains={"h": None}, detection_band="h")
    flux = np.ones(xs.size)
    kw = dict(input_templates=[None] * xs.size)
    w = measure_injected(setup, det, rms, {"h": det}, xs, ys, flux, 25.0 + 0 * flux, mode="windowed", **kw)
    f = measure_injected(setup, det, rms, {"h": det}, xs, ys, flux, 25.0 + 0 * flux, mode="full", **kw)
    det_ = w["detection_id"] > 0
    assert det_.sum() >= 3
    assert np.all(np.isfinite(w["flux_auto_h"][det_])) and np.all(np.isfinite(w["flux_aper0_h"][det_]))
    for c in w:
        np.testing.assert_array_equal(w[c], f[c], err_msg=c)
