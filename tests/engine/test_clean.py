"""Full-frame sep CLEAN in linear time (``segmentation.sep_extract_clean``) against sep's own.

The reference is ``sep.extract(..., clean=True)`` itself (through glaciar's thin
wrapper ``sep_extract``, which only sets sep's buffer sizes): the emulation
must return the same catalogue rows (every field) and the same segmentation map,
on fields where CLEAN removes many objects across and inside deblended regions,
with masked pixels.  The linear CLEAN_ZONE pair search is checked against a
brute-force O(N^2) loop over sep's scalar zone test.
"""
import numpy as np
import pytest

from glaciar.engine import clean as cl
from glaciar.engine import sepscan
from glaciar.engine import segmentation as sg
from glaciar.engine.detect import SEP_OBJ_MERGED, DetectionParams, sep_extract, detection_rms, sanitize
from glaciar.engine.measure import reference_extraction

from toy_images import exponential_galaxy

N = 300


def _field(seed):
    """Bright extended galaxies with faint neighbours (CLEAN), close pairs (deblending), a
    masked rectangle and scattered masked pixels, a varying RMS."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:N, :N]
    img = np.zeros((N, N))

    def galaxy(*args):
        return exponential_galaxy(xx, yy, *args)

    for x0, y0, f, r in [(80, 80, 3000, 5.0), (220, 100, 1500, 4.0), (100, 220, 2500, 6.0), (230, 230, 800, 3.0)]:
        img += galaxy(x0, y0, f, r)
        for ang, d in zip(rng.uniform(0, 2 * np.pi, 6), (10, 15, 21, 28, 36, 45)):
            img += galaxy(x0 + d * np.cos(ang), y0 + d * np.sin(ang), 10 ** rng.uniform(0.8, 1.8), 1.2)
    for _ in range(25):                                    # close pairs: deblended regions
        x0, y0 = rng.uniform(10, N - 10, 2)
        img += galaxy(x0, y0, 10 ** rng.uniform(1.3, 2.3), rng.uniform(1.0, 2.0))
        img += galaxy(x0 + rng.uniform(3, 6), y0 + rng.uniform(-3, 3), 10 ** rng.uniform(1.0, 2.0), 1.0)
    for _ in range(60):
        x0, y0 = rng.uniform(0, N, 2)
        img += galaxy(x0, y0, 10 ** rng.uniform(0.7, 2.3), rng.lognormal(np.log(1.5), 0.4),
                      rng.uniform(0.4, 1.0), rng.uniform(0, np.pi))
    rms = 1.0 + 0.2 * np.sin(xx / 50.0) * np.cos(yy / 40.0)
    img = img + rng.normal(size=(N, N)) * rms
    mask = np.zeros((N, N), dtype=bool)
    mask[140:170, 10:60] = True                            # a masked rectangle cutting objects
    mask[rng.integers(0, N, 300), rng.integers(0, N, 300)] = True
    return img, rms.astype(np.float32), mask


@pytest.fixture(scope="module")
def field():
    return _field(5)


def _inputs(field, params):
    img, rms, mask = field
    data, err, nodata = sanitize(img, rms, mask)
    return data, detection_rms(err, nodata, params), nodata


@pytest.mark.parametrize("seed, mincont, beta, minarea, thresh, threshold_rms", [
    (5, 0.005, 1.0, 5, 0.5, "pixel"),
    (5, 0.005, 0.5, 9, 0.5, "pixel"),
    (5, 0.001, 2.0, 3, 0.7, "filtered"),
    (5, 0.001, 1.0, 3, 0.8, "filtered"),
    (5, 1.0, 1.0, 5, 0.5, "pixel"),
    # a deblended child whose brightest pixel came from another branch (its core is elsewhere)
    (3, 0.002, 1.0, 9, 0.6, "pixel"),
    (28, 0.005, 1.0, 5, 0.4, "pixel"),
    # an object holding a masked pixel of the first rows (sep does not mask them)
    (16, 0.005, 1.0, 5, 0.4, "pixel"),
])
def test_emulated_clean_is_seps(field, monkeypatch, seed, mincont, beta, minarea, thresh, threshold_rms):
    """Catalogue rows and segmentation map equal sep's clean=True, with both exact-mthresh
    paths (whole-region objects and deblended children) exercised."""
    field = field if seed == 5 else _field(seed)
    params = DetectionParams(detect_thresh=thresh, detect_minarea=minarea, deblend_mincont=mincont,
                             clean=True, clean_param=beta, threshold_rms=threshold_rms)
    data, err, nodata = _inputs(field, params)
    cat0, _ = sep_extract(data, err, nodata, params, False)
    cat_s, seg_s = sep_extract(data, err, nodata, params, True)
    calls = {"object": 0, "region": 0}
    obj_fn, reg_fn = sg._object_mthresh, sg._region_mthresh

    def count(name, fn):
        def wrapped(*a, **k):
            calls[name] += 1
            return fn(*a, **k)
        return wrapped

    monkeypatch.setattr(sg, "_object_mthresh", count("object", obj_fn))
    monkeypatch.setattr(sg, "_region_mthresh", count("region", reg_fn))
    cat_e, seg_e = sg.sep_extract_clean(data, err, nodata, params, min_objects=0)
    assert len(cat0) - len(cat_s) >= 20                   # CLEAN removes many objects here
    assert cat_e.dtype == cat_s.dtype
    for f in cat_s.dtype.names:
        assert np.array_equal(cat_e[f], cat_s[f]), f
    assert seg_e.dtype == seg_s.dtype and np.array_equal(seg_e, seg_s)
    assert calls["object"] >= 1
    if mincont < 1.0:
        assert np.count_nonzero(cat0["flag"] & SEP_OBJ_MERGED) >= 10
        assert calls["region"] >= 1


def test_below_crossover_is_seps_own_call(field):
    """Below the crossover sep's own CLEAN runs: same answer (and no emulation)."""
    params = DetectionParams(detect_thresh=0.6, detect_minarea=5, clean=True)
    data, err, nodata = _inputs(field, params)
    cat_s, seg_s = sep_extract(data, err, nodata, params, True)
    cat_e, seg_e = sg.sep_extract_clean(data, err, nodata, params, min_objects=10 ** 9)
    assert np.array_equal(cat_e, cat_s) and np.array_equal(seg_e, seg_s)


def _objects(rng, n):
    x, y = rng.uniform(0, 400, n), rng.uniform(0, 400, n)
    a = rng.lognormal(np.log(1.0), 0.5, n).astype(np.float32)
    a[rng.choice(n, 4, replace=False)] = np.float32([15.0, 25.0, 40.0, 40.0])   # a few huge ones (a tie)
    a[:3] = a[3]                                           # more ties
    z32 = np.zeros(n, dtype=np.float32)
    return cl.CleanObjects(x=x, y=y, a=a, b=a, cxx=z32, cyy=z32, cxy=z32, fdflux=z32, thresh=z32,
                           npix=np.ones(n, dtype=np.int64), abcor=z32, mthresh=z32, tmin=z32)


@pytest.mark.parametrize("seed", [0, 1])
def test_zone_pairs_equal_brute_force(seed):
    """Every pair (i < j) passing sep's scalar zone test, no other, sorted by (i, j)."""
    rng = np.random.default_rng(seed)
    o = _objects(rng, 300)
    # pairs on the zone's edge: j at distance CLEAN_ZONE (a_i + a_j) from i, along x or y
    for i in range(10, 20, 2):
        d = cl.CLEAN_ZONE * (float(o.a[i]) + float(o.a[i + 1]))
        o.x[i], o.y[i] = (o.x[i + 1] + d, o.y[i + 1]) if i % 4 else (o.x[i + 1], o.y[i + 1] - d)
    bi, bj = [], []
    for i in range(len(o)):
        for j in range(i + 1, len(o)):
            if cl.in_zone(o.x[i], o.y[i], o.a[i], o.x[j], o.y[j], o.a[j]):
                bi.append(i)
                bj.append(j)
    pi, pj = cl.zone_pairs(o, chunk=37)
    assert np.array_equal(pi, bi) and np.array_equal(pj, bj)
    big = set(np.flatnonzero(o.a >= 15).tolist())
    assert sum(1 for i, j in zip(bi, bj) if i in big or j in big) > 100   # the huge ones pair widely


def test_reference_extraction_same_either_side_of_crossover(field, monkeypatch):
    """reference_extraction (clean_style "region") gives the same reference with the
    emulation forced on as with sep's own CLEAN."""
    img, rms, mask = field
    params = DetectionParams(detect_thresh=0.6, detect_minarea=5, deblend_mincont=0.005, clean=True)
    assert params.clean_style == "region"
    monkeypatch.setattr(sg, "EMULATED_CLEAN_MIN_OBJECTS", 10 ** 9)
    ref_s = reference_extraction(img, rms, params, 25.0, mask=mask)
    monkeypatch.setattr(sg, "EMULATED_CLEAN_MIN_OBJECTS", 0)
    ref_e = reference_extraction(img, rms, params, 25.0, mask=mask)
    assert np.array_equal(ref_e.segmap, ref_s.segmap)
    assert np.array_equal(ref_e.catalog, ref_s.catalog)
    assert np.array_equal(ref_e.flux, ref_s.flux) and np.array_equal(ref_e.mag, ref_s.mag, equal_nan=True)
    assert np.array_equal(ref_e.objects.region, ref_s.objects.region)
    assert np.array_equal(ref_e.objects.need, ref_s.objects.need)


def _sep_loop(o, beta):
    """sep's clean() loop written out (extract.c): i skipped if already removed when its turn
    comes, not if removed during it.  Also counts removals by an object removed earlier in its turn."""
    n = len(o)
    surv = np.ones(n, dtype=bool)
    late = 0
    for i in range(n):
        if not surv[i]:
            continue
        for j in range(i + 1, n):
            if not surv[j]:
                continue
            if o.fdflux[j] < o.fdflux[i]:
                if cl.eats(o, i, o, j, beta):
                    late += not surv[i]
                    surv[j] = False
            elif cl.eats(o, j, o, i, beta):
                surv[i] = False
    return surv, late


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bounded_clean_replays_seps_loop(seed):
    """Tests decided from random bounds of mthresh (exact values asked only when needed)
    remove exactly the objects sep's loop removes with the exact values."""
    rng = np.random.default_rng(seed)
    n = 400
    f32 = np.float32
    a = rng.uniform(0.8, 3.0, n).astype(f32)
    b = (a * rng.uniform(0.4, 1.0, n)).astype(f32)
    cxx, cyy = (1 / a ** 2).astype(f32), (1 / b ** 2).astype(f32)
    o = cl.CleanObjects(x=rng.uniform(0, 120, n), y=rng.uniform(0, 120, n), a=a, b=b, cxx=cxx, cyy=cyy,
                        cxy=rng.uniform(-0.1, 0.1, n).astype(f32),
                        fdflux=(10 ** rng.uniform(0.5, 3.5, n)).astype(f32), thresh=f32(1.0) + f32(0) * a,
                        npix=rng.integers(5, 200, n), abcor=f32(1.0) + f32(0) * a,
                        mthresh=(10 ** rng.uniform(-1, 1.5, n)).astype(f32), tmin=f32(0) * a)
    beta = 1.0
    ref, late = _sep_loop(o, beta)
    assert (~ref).sum() > 50 and late >= 1
    lo = np.where(rng.random(n) < 0.5, o.mthresh * f32(0.3), o.mthresh).astype(f32)
    hi = np.where(rng.random(n) < 0.5, o.mthresh * f32(3.0), o.mthresh).astype(f32)
    asked = []

    def mthresh_of(idx):
        asked.extend(np.asarray(idx).tolist())
        return o.mthresh[idx]

    surv, eater = cl.sep_clean_bounded(o, beta, lo, hi, mthresh_of)
    assert np.array_equal(surv, ref)
    assert 0 < len(asked) < n and all(lo[k] < hi[k] for k in asked)
    assert np.array_equal(cl.sep_clean(o, beta)[0], ref)


def test_exact_mthresh_paths_equal_full_frame_scan(field):
    """The cut-out computations of mthresh (whole-region objects gathered by row tiles;
    deblended children by region) equal the full-frame route: sep's Lutz scan of the
    whole detection mask, children's orders in it, heap_mthresh -- for exactly the
    objects asked."""
    params = DetectionParams(detect_thresh=0.5, detect_minarea=5, deblend_mincont=0.005, clean=True)
    data, err, nodata = _inputs(field, params)
    cat0, seg0 = sep_extract(data, err, nodata, params, False)
    mask, filt, thr = sepscan.detection_mask(data, err, nodata, params)
    sf = seg0.ravel()
    tp = (filt - thr).astype(np.float32).ravel()
    full = {}
    for pix, _, _ in sepscan.lutz_regions(mask, params.detect_minarea):
        labs = np.unique(sf[pix][sf[pix] > 0])
        if labs.size == 1:
            full[int(labs[0]) - 1] = sepscan.heap_mthresh(tp[pix], params.detect_minarea)
        elif labs.size > 1:
            for lab, o in sepscan.child_pixel_orders(pix, data.shape[1], sf, filt.ravel(), labs.tolist(),
                                                cat0["thresh"][labs[0] - 1], params.deblend_nthresh).items():
                full[lab - 1] = sepscan.heap_mthresh(tp[o], params.detect_minarea)
    merged = (cat0["flag"] & SEP_OBJ_MERGED) != 0
    single = np.flatnonzero(~merged)
    asked = single[::3]                                   # a subset: nothing else may be returned
    got = sg._object_mthresh(asked, len(cat0), data, err, nodata, seg0, params)
    assert set(got) == set(asked.tolist())
    assert all(got[k] == full[k] for k in got)
    kids = np.flatnonzero(merged)
    assert kids.size >= 10
    for k in kids.tolist():
        got = sg._region_mthresh(k, data, err, nodata, seg0, cat0, params)
        assert k in got and all(got[j] == full[j] for j in got), k


@pytest.mark.parametrize("kernel", ["gauss_2.0_3x3", "gauss_2.0_5x5", "gauss_3.0_7x7"])
def test_sep_leaves_first_rows_unmasked(kernel):
    """sep's detections on a noisy image with a fifth of the pixels masked are exactly the
    pixels sepscan.detection_mask finds above threshold given the image row y0: masked pixels never detected, except in
    the first filter_halfwidth rows, where those above the RMS passed are (the case exists here)."""
    from glaciar.engine.detect import builtin_filter

    rng = np.random.default_rng(2)
    p = DetectionParams(detect_thresh=0.4, detect_minarea=1, deblend_mincont=1.0, clean=False,
                        filter_kernel=builtin_filter(kernel))
    d = rng.normal(size=(80, 90)).astype(np.float32)
    d[:12, 20:50] += 3.0                                  # bright on the first rows and lower down
    nodata = rng.random(d.shape) < 0.2
    d[nodata] = 0.0
    err = np.ones_like(d)
    _, seg = sep_extract(d, err, nodata, p, False)
    above = sepscan.detection_mask(d, err, nodata, p, y0=0)[0]   # the one "above threshold"
    assert np.array_equal(seg > 0, above)
    hw = p.filter_halfwidth
    assert (above & nodata)[:hw].any() and not (above & nodata)[hw:].any()
    # the same rows of a tile starting lower down are masked
    assert np.array_equal(sepscan.threshold_map(err[5:], nodata[5:], p, y0=5),
                          sepscan.threshold_map(err[5:], nodata[5:], p))
