"""Windowed detection equals a full-frame extraction: 2000 injected sources.

A 600x600 synthetic field (exponential-disk galaxies of a wide range of
sizes and fluxes, Gaussian noise with a varying RMS map) receives 20 x 100
non-overlapping Gaussian stamps; every per-source column from
``mode="windowed"`` must equal ``mode="full"`` (floats to 1e-9 relative).
"""
import dataclasses

import numpy as np
import pytest

from glaciar.constants import STATUS_CODES, STATUS_NOT_DETECTED
from glaciar.engine.classify import ClassificationParams
from glaciar.engine.detect import DetectionParams, measure_background
from glaciar.engine.measure import MeasureSetup, measure_injected, output_columns, reference_extraction
from glaciar.engine.scene import Scene
from glaciar.engine import scene as scene_module

from toy_images import crowded_field, gaussian_stamps


@pytest.fixture(scope="module")
def field():
    img = crowded_field()
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
        xs, ys, flux, st = gaussian_stamps(rng)
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
    xs, ys, flux, st = gaussian_stamps(np.random.default_rng(1), nsrc=20)
    det = Scene(sub, st)
    setup = MeasureSetup(band_rms={"h": rms}, reference=ref, params=bad, classification=ClassificationParams(),
                         zeropoints={"h": 25.0}, gains={"h": None}, detection_band="h")
    out = measure_injected(setup, det, rms, {"h": det}, xs, ys, flux, 25 - 2.5 * np.log10(flux))
    err = (out[COL_FLAGS] & FLAG_SEP_ERROR) > 0
    assert err.any()
    assert np.all(out["status"][err] == STATUS_NOT_DETECTED) and np.all(np.isnan(out["flux_iso_h"][err]))


# ------------------------------------------------------------------------------
# The batching shortcuts of windowed detection change speed, never answers.
#
# * ``Scene.paste_windows`` (all windows of a canvas in one pass) writes exactly
#   the pixels ``Scene.window`` returns, bit for bit, with overlapping, clipped
#   and flux-scaled stamps;
# * a stamp given as (template, flux) equals the pre-multiplied stamp bit for bit;
# * ``measure_injected`` gives the same per-source results whatever the first
#   window size (a speed-only setting), and the same as a full-frame extraction;
#   its diagnostics report windows that hold each source.
# ------------------------------------------------------------------------------
def _random_scene(rng, shape=(60, 80), n=12, scaled=False):
    base = rng.normal(size=shape).astype(np.float32)
    stamps, premult = [], []
    for _ in range(n):
        h, w = rng.integers(3, 25, 2)
        y0 = int(rng.integers(-h + 1, shape[0]))
        x0 = int(rng.integers(-w + 1, shape[1]))
        t = rng.normal(size=(h, w))
        f = float(rng.uniform(0.1, 50.0))
        stamps.append((y0, x0, t, f) if scaled else (y0, x0, t * f))
        premult.append((y0, x0, t * f))
    return base, stamps, premult


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled kernel", "numpy"])
@pytest.mark.parametrize("scaled", [False, True])
def test_paste_windows_equals_window_bit_for_bit(scaled, compiled, monkeypatch):
    if compiled and scene_module.KERNEL is None:
        pytest.skip("glaciar.engine.kernels is not built here (no C compiler at install)")
    if not compiled:
        monkeypatch.setattr(scene_module, "KERNEL", None)
    rng = np.random.default_rng(11)
    base, stamps, premult = _random_scene(rng, scaled=scaled)
    sc = Scene(base, stamps)
    ref = Scene(base, premult)
    ny, nx = base.shape
    rects, oy, ox, off = [], [], [], 0
    for _ in range(15):
        y0, x0 = int(rng.integers(0, ny - 1)), int(rng.integers(0, nx - 1))
        y1, x1 = int(rng.integers(y0 + 1, ny + 1)), int(rng.integers(x0 + 1, nx + 1))
        rects.append((y0, y1, x0, x1))
        oy.append(2)
        ox.append(off)
        off += x1 - x0 + 3
    canvas = np.full((ny + 4, off), -7.0)
    sc.paste_windows(canvas, np.array(rects), np.array(oy), np.array(ox))
    for (y0, y1, x0, x1), cy, cx in zip(rects, oy, ox):
        got = canvas[cy:cy + y1 - y0, cx:cx + x1 - x0]
        assert got.tobytes() == sc.window(y0, y1, x0, x1).tobytes()
        # a (template, flux) stamp is the pre-multiplied stamp, bit for bit
        assert got.tobytes() == ref.window(y0, y1, x0, x1).tobytes()
    # nothing written outside the windows
    mask = np.ones(canvas.shape, dtype=bool)
    for (y0, y1, x0, x1), cy, cx in zip(rects, oy, ox):
        mask[cy:cy + y1 - y0, cx:cx + x1 - x0] = False
    assert np.all(canvas[mask] == -7.0)
    with pytest.raises(ValueError):         # a window that does not fit the canvas
        sc.paste_windows(np.zeros((ny, nx - 1)), np.array([(0, ny, 0, nx)]), np.array([0]), np.array([0]))


def test_scene_rejects_malformed_stamp():
    with pytest.raises(ValueError, match="stamp 0"):
        Scene(np.zeros((5, 5)), [(0, 0)])
    with pytest.raises(ValueError, match="stamp 0"):
        Scene(np.zeros((5, 5)), [(0, 0, np.ones((2, 2)), "bright")])


N_BATCH = 240


@pytest.fixture(scope="module")
def small_field():
    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[:N_BATCH, :N_BATCH]
    img = rng.normal(size=(N_BATCH, N_BATCH)) * 0.05
    for _ in range(40):
        x0, y0 = rng.uniform(0, N_BATCH, 2)
        r = rng.lognormal(np.log(2.0), 0.5)
        f = 10 ** rng.uniform(0.5, 2.5)
        img += f * np.exp(-np.hypot(xx - x0, yy - y0) / r) / (2 * np.pi * r * r)
    params = DetectionParams()
    back, rms = measure_background(img, None, params)
    sub = img - back
    ref = reference_extraction(sub, rms, params, 25.0)
    # 36 Gaussian sources on a grid (never overlapping), fluxes from faint to bright
    h = 10
    py, px = np.mgrid[-h:h + 1, -h:h + 1]
    cells = np.arange(6) * (N_BATCH / 6.0) + N_BATCH / 12.0
    xs = (cells[None, :] + rng.uniform(-5, 5, (6, 6))).ravel()
    ys = (cells[:, None] + rng.uniform(-5, 5, (6, 6))).ravel()
    flux = 10 ** rng.uniform(-0.3, 1.7, xs.size)
    stamps = []
    for x, y, f in zip(xs, ys, flux):
        ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        s = rng.uniform(0.8, 2.5)
        p = np.exp(-((px - (x - ix)) ** 2 + (py - (y - iy)) ** 2) / (2 * s * s))
        stamps.append((iy - h, ix - h, p / p.sum(), f))
    return sub, rms, params, ref, xs, ys, flux, stamps


def test_results_do_not_depend_on_first_window_size(small_field, assert_same_outputs):
    sub, rms, params, ref, xs, ys, flux, stamps = small_field
    det = Scene(sub, stamps)
    bands = {"h": det, "j": Scene(0.6 * sub, [(a, b, t, 0.4 * f) for a, b, t, f in stamps])}
    setup = MeasureSetup(band_rms={"h": rms, "j": 1.2 * rms}, reference=ref, params=params,
                         classification=ClassificationParams(), zeropoints={"h": 25.0, "j": 26.0},
                         gains={"h": None, "j": 3.0}, detection_band="h")
    kw = dict(det_rms=rms, band_scenes=bands, x=xs, y=ys, input_flux_det=flux,
              input_mag_det=25.0 - 2.5 * np.log10(flux))
    full = measure_injected(setup, det, mode="full", **kw)
    seen_rounds = set()
    for first in (9, 33, 65):
        diag = {}
        p = dataclasses.replace(params, initial_window=first)
        w = measure_injected(dataclasses.replace(setup, params=p), det, diagnostics=diag, **kw)
        assert_same_outputs(w, full, first)
        win = diag["window"]
        ix, iy = np.floor(xs + 0.5), np.floor(ys + 0.5)
        assert win.shape == (xs.size, 4)
        assert np.all((win[:, 0] <= iy) & (iy < win[:, 1]) & (win[:, 2] <= ix) & (ix < win[:, 3]))
        assert np.all((win[:, 0] >= 0) & (win[:, 1] <= N_BATCH) & (win[:, 2] >= 0) & (win[:, 3] <= N_BATCH))
        # no window is smaller than the first one unless clipped by the image edge, or the
        # source was found undetectable before any extraction (early exit): its window is
        # then the search box plus the filter's reach, and it is not detected
        side = np.minimum(win[:, 1] - win[:, 0], win[:, 3] - win[:, 2])
        inner = (win[:, 0] > 0) & (win[:, 1] < N_BATCH) & (win[:, 2] > 0) & (win[:, 3] < N_BATCH)
        early = side == ClassificationParams().search_box + 2 * (params.filter_halfwidth + 1)
        assert np.all(w["status"][early] == STATUS_NOT_DETECTED)
        inner &= ~early
        assert np.all(side[inner] >= first)
        seen_rounds.add(diag["rounds"])
    # a 9-pixel first window cannot hold these sources: windows really grew
    assert max(seen_rounds) > 1
    assert np.any(full["status"] >= 0)


def test_early_exit_is_exact_and_only_skips_sources_without_above_threshold_pixels(small_field,
                                                                                   assert_same_outputs):
    """Skipping undetectable sources changes no value; skipped sources really have no
    above-threshold pixel in their search box according to plain sep on the whole image."""
    import sep

    sub, rms, params, ref, xs, ys, flux, stamps = small_field
    # faint sources (many are below threshold everywhere) beside the fixture's
    faint = [(y0, x0, t, 0.02 * f) for y0, x0, t, f in stamps]
    det = Scene(sub, faint)
    setup = MeasureSetup(band_rms={"h": rms}, reference=ref, params=params,
                         classification=ClassificationParams(), zeropoints={"h": 25.0}, gains={"h": None},
                         detection_band="h")
    kw = dict(det_rms=rms, band_scenes={"h": det}, x=xs, y=ys, input_flux_det=0.02 * flux,
              input_mag_det=25.0 - 2.5 * np.log10(0.02 * flux))
    d_on, d_off = {}, {}
    on = measure_injected(setup, det, early_exit=True, diagnostics=d_on, **kw)
    off = measure_injected(setup, det, early_exit=False, diagnostics=d_off, **kw)
    assert_same_outputs(on, off, "early exit")
    side = d_on["window"][:, 1] - d_on["window"][:, 0]
    skipped = side == ClassificationParams().search_box + 2 * (params.filter_halfwidth + 1)
    assert 0 < skipped.sum() < xs.size          # the test exercises both branches
    # independent: sep's segmentation of the whole injected image, every region kept
    # (minarea 1, no deblending), marks exactly its above-threshold pixels
    img = det.full().astype(np.float32)
    sep.set_extract_pixstack(img.size + 1024)
    _, seg = sep.extract(img, params.detect_thresh, err=rms.astype(np.float32), minarea=1,
                         filter_kernel=params.filter_kernel, filter_type=params.filter_type, deblend_cont=1.0,
                         clean=False, segmentation_map=True)
    h = ClassificationParams().search_box // 2
    ix, iy = np.floor(xs + 0.5).astype(int), np.floor(ys + 0.5).astype(int)
    for i in range(xs.size):
        box = seg[max(iy[i] - h, 0):iy[i] + h + 1, max(ix[i] - h, 0):ix[i] + h + 1]
        if skipped[i]:
            assert not box.any(), i
            assert on["status"][i] == STATUS_NOT_DETECTED
    # and sources with such a pixel were not skipped
    assert all(seg[max(iy[i] - h, 0):iy[i] + h + 1, max(ix[i] - h, 0):ix[i] + h + 1].any()
               for i in np.flatnonzero(~skipped))


def test_initial_windows_hold_the_neighbours_a_source_may_touch():
    from glaciar.engine.canvas import ObjectBoxes
    from glaciar.engine.windows import _OWN_HALF, initial_windows

    params = DetectionParams()
    margin = params.filter_halfwidth + 1
    pad = margin + 4
    r = params.initial_window // 2
    x = np.array([100.2, 300.0, 500.0, 700.0])
    y = np.array([100.0, 300.0, 500.0, 700.0])
    # object 0: its region box meets source 0's own box (not its search box): the region must fit
    # object 1: its region box covers source 1's search box: its Kron/AUTO box must fit
    # object 2: far from everything
    region = np.array([[100 + _OWN_HALF - 2, 160, 90, 110],
                       [290, 310, 295, 305],
                       [900, 910, 900, 910]])
    need = np.array([[95, 170, 80, 120],
                     [200, 380, 250, 330],
                     [880, 930, 880, 930]])
    win = initial_windows(x, y, (1000, 1000), params, 3, margin, ObjectBoxes.build(region, need, (1000, 1000)))
    sq = lambda c: (c - r, c + r + 1)  # noqa: E731
    np.testing.assert_array_equal(win[0], [sq(100)[0], 160 + pad, sq(100)[0], sq(100)[1]])
    np.testing.assert_array_equal(win[1], [200 - pad, 380 + pad, 250 - pad, 330 + pad])
    np.testing.assert_array_equal(win[2], [*sq(500), *sq(500)])
    np.testing.assert_array_equal(win[3], [*sq(700), *sq(700)])
    # without the reference boxes: the squares; clipped to the image; capped at max_window
    plain = initial_windows(np.array([3.0]), np.array([998.0]), (1000, 1000), params, 3, margin)
    np.testing.assert_array_equal(plain[0], [998 - r, 1000, 0, 3 + r + 1])
    huge = initial_windows(x[1:2], y[1:2], (5000, 5000), dataclasses.replace(params, max_window=101), 3, margin,
                           ObjectBoxes.build(region[1:2], [[0, 4000, 0, 4000]], (5000, 5000)))
    assert huge[0, 1] - huge[0, 0] == 101 and huge[0, 3] - huge[0, 2] == 101


def test_object_boxes_candidates_hold_every_meeting_box():
    """The grid index returns every object whose box meets a query box (brute force)."""
    from glaciar.engine.canvas import ObjectBoxes

    rng = np.random.default_rng(5)
    shape = (700, 900)
    y0, x0 = rng.integers(-20, 700, 300), rng.integers(-20, 900, 300)
    region = np.stack([y0, y0 + rng.integers(1, 200, 300), x0, x0 + rng.integers(1, 120, 300)], axis=1)
    ob = ObjectBoxes.build(region, region, shape, cell=50)
    qy, qx = rng.integers(0, 700, 400), rng.integers(0, 900, 400)
    q = np.stack([qy - 10, qy + 11, qx - 3, qx + 4], axis=1)
    si, oi = ob.candidates(q)
    got = set(zip(si.tolist(), oi.tolist()))
    meet = ((region[None, :, 0] < q[:, None, 1]) & (region[None, :, 1] > q[:, None, 0])
            & (region[None, :, 2] < q[:, None, 3]) & (region[None, :, 3] > q[:, None, 2]))
    want = set(zip(*[v.tolist() for v in np.nonzero(meet)]))
    assert want <= got
    assert len(got) < 0.2 * q.shape[0] * region.shape[0]       # an index, not all pairs


# ------------------------------------------------------------------------------
# Fast kernels of the windowed measurement against independent computations.
# ------------------------------------------------------------------------------
def _stamp_ctx(templates, x, y, rms=1.0, shape=(200, 200)):
    from types import SimpleNamespace

    from glaciar.engine.detect import DetectionParams
    return SimpleNamespace(x=np.asarray(x, float), y=np.asarray(y, float), shape=shape,
                           det_rms=np.full(shape, rms), params=DetectionParams(), templates=templates,
                           margin=DetectionParams().filter_halfwidth + 1)


def test_stamp_half_sizes_follow_the_gaussian_width():
    """A bright circular Gaussian of sigma s: the above-threshold second moments give a -> s
    (the part below threshold carries a negligible share of the weight), so the
    predicted half-size is ceil(6 s + slack) + margin."""
    from glaciar.engine import windows as W

    h = 40
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    out = []
    for s in (1.5, 3.0, 5.0):
        g = np.exp(-(xx ** 2 + yy ** 2) / (2 * s * s))
        g /= g.sum()
        out.append((100 - h, 100 - h, g, 1e9))
    ctx = _stamp_ctx(out + [None, (100 - h, 100 - h, g, 1e-9)], [100.0] * 5, [100.0] * 5)
    half = W.stamp_half_sizes(ctx)
    for k, s in enumerate((1.5, 3.0, 5.0)):
        lo = int(np.ceil(6 * 0.99 * s + W._STAMP_SLACK)) + ctx.margin
        hi = int(np.ceil(6 * s + W._STAMP_SLACK)) + ctx.margin
        assert lo <= half[k] <= hi
    assert half[3] == 0 and half[4] == 0          # no template; nothing above threshold


def test_initial_windows_hold_the_predicted_half_size():
    from glaciar.engine.detect import DetectionParams
    from glaciar.engine.windows import initial_windows

    params = DetectionParams()
    x = np.array([100.0, 100.0, 3.0])
    y = np.array([100.0, 150.0, 3.0])
    win = initial_windows(x, y, (400, 400), params, 3, 3, own_half=np.array([0, 35, 35]))
    r = params.initial_window // 2
    assert tuple(win[0]) == (100 - r, 101 + r, 100 - r, 101 + r)
    assert tuple(win[1]) == (150 - 35, 186, 100 - 35, 136)
    assert tuple(win[2]) == (0, 39, 0, 39)         # clipped to the image


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
