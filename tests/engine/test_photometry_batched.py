"""SExtractor-style photometry of objects that need no masking, batched (issue 24).

``sextractor_photometry`` measured every object on its own masked cut-out (two or
more sep calls per object and band).  An object whose cut-out lies inside its bounds
and holds no pixel to mask is now summed with the others like it in one sep call on
the whole array.  The fluxes must stay bit-identical to sums on each object's cut-out,
written out here from MASK_TYPE's definition.
"""
import numpy as np
import pytest
import sep

from glaciar.engine import photometry as phot
from glaciar.engine.noise import CorrelatedNoise

DIAMETERS = (2.0, 4.0, 6.0)
#: x, y, size [px]: 1-2 touch (masked), 3 sits by the no-data patch, 4 by the image edge,
#: 5-8 stand alone (clean).
OBJECTS = [(20.3, 25.7, 2.5), (27.1, 31.4, 2.0), (60.45, 20.7, 1.5), (3.2, 70.9, 1.8),
           (80.77, 60.13, 2.2), (45.5, 75.25, 1.7), (101.31, 33.9, 2.0), (70.02, 88.61, 1.4)]


def _scene(seed=11):
    rng = np.random.default_rng(seed)
    ny, nx = 100, 120
    yy, xx = np.mgrid[:ny, :nx]
    img = rng.normal(0.0, 0.05, (ny, nx))
    seg = np.zeros((ny, nx), dtype=np.int32)
    for k, (x, y, s) in enumerate(OBJECTS, start=1):
        r2 = (xx - x) ** 2 + (yy - y) ** 2
        img += 5.0 * np.exp(-0.5 * r2 / s ** 2)
        seg[(r2 < (2.2 * s) ** 2) & (seg == 0)] = k
    nodata = np.zeros((ny, nx), dtype=bool)
    nodata[14:18, 64:67] = True
    rms = 0.05 * (1.0 + 0.1 * rng.random((ny, nx)))
    x = np.array([o[0] for o in OBJECTS])
    y = np.array([o[1] for o in OBJECTS])
    k = len(OBJECTS)
    ell = phot.Ellipses(x, y, np.linspace(1.6, 2.4, k), np.linspace(1.2, 1.6, k),
                        np.linspace(-1.2, 1.3, k), np.linspace(2.0, 3.0, k))
    return img, rms, seg, nodata, ell


def _cutout(image, rms, seg, seg_id, nodata, x, y, box, bounds):
    """MASK_TYPE correct, pixel by pixel (neighbours and no data mirrored, else 0)."""
    by0, by1, bx0, bx1 = bounds
    y0, y1, x0, x1 = max(box[0], by0), min(box[1], by1), max(box[2], bx0), min(box[3], bx1)
    data = np.array(image[y0:y1, x0:x1], dtype=np.float64)
    err = np.array(rms[y0:y1, x0:x1], dtype=np.float64)

    def invalid(j, i):
        return bool(nodata[j, i]) or (seg[j, i] != 0 and seg[j, i] != seg_id)

    for j in range(y0, y1):
        for i in range(x0, x1):
            if invalid(j, i):
                v = e = 0.0
                i2, j2 = int(2.0 * x + 0.49999 - i), int(2.0 * y + 0.49999 - j)
                if bx0 <= i2 < bx1 and by0 <= j2 < by1 and not invalid(j2, i2):
                    v, e = image[j2, i2], rms[j2, i2]
                data[j - y0, i - x0], err[j - y0, i - x0] = v, e
    return data, err, (y0, x0)


def _by_object(img, rms, seg, nodata, ell, gain, noise, bounds):
    """Each object on its own cut-out, one sep call per aperture (the numbers to keep)."""
    xs, ys, a, b, th, sc = ell
    k = xs.size
    fa, fea = np.full((len(DIAMETERS), k), np.nan), np.full((len(DIAMETERS), k), np.nan)
    fau, feau = np.full(k, np.nan), np.full(k, np.nan)
    for i in range(k):
        c, s_ = np.cos(th[i]), np.sin(th[i])
        hy = max(sc[i] * np.sqrt((a[i] * s_) ** 2 + (b[i] * c) ** 2), 0.5 * max(DIAMETERS))
        hx = max(sc[i] * np.sqrt((a[i] * c) ** 2 + (b[i] * s_) ** 2), 0.5 * max(DIAMETERS))
        box = (int(np.floor(ys[i] - hy)) - 1, int(np.ceil(ys[i] + hy)) + 2,
               int(np.floor(xs[i] - hx)) - 1, int(np.ceil(xs[i] + hx)) + 2)
        d, e, (oy, ox) = _cutout(img, rms, seg, i + 1, nodata, xs[i], ys[i], box, bounds[i])
        cx, cy = np.array([xs[i] - ox]), np.array([ys[i] - oy])
        for j, dia in enumerate(DIAMETERS):
            f, fe, _ = sep.sum_circle(d, cx, cy, 0.5 * dia, err=e, gain=gain, subpix=0)
            if noise is not None:
                fb = sep.sum_circle(d, cx, cy, 0.5 * dia, err=e, subpix=0)[1]
                factor = noise.variance_factor(np.pi * (0.5 * dia) ** 2)
                fe = np.sqrt(np.square(fb) * factor + np.maximum(np.square(fe) - np.square(fb), 0.0))
            fa[j, i], fea[j, i] = f[0], fe[0]
        args = (cx, cy, a[i:i + 1], b[i:i + 1], th[i:i + 1], sc[i:i + 1])
        f, fe, _ = sep.sum_ellipse(d, *args, err=e, gain=gain, subpix=0)
        if noise is not None:
            fb = sep.sum_ellipse(d, *args, err=e, subpix=0)[1]
            factor = noise.variance_factor(np.pi * a[i] * b[i] * sc[i] ** 2)
            fe = np.sqrt(np.square(fb) * factor + np.maximum(np.square(fe) - np.square(fb), 0.0))
        fau[i], feau[i] = f[0], fe[0]
    return fa, fea, fau, feau


@pytest.mark.parametrize("gain, with_noise, narrow", [(None, False, False), (1500.0, True, False),
                                                      (1500.0, False, True)])
def test_bit_identical_to_sums_on_each_cutout(gain, with_noise, narrow):
    img, rms, seg, nodata, ell = _scene()
    k = ell.x.size
    bounds = np.tile([0, img.shape[0], 0, img.shape[1]], (k, 1))
    if narrow:          # objects 5 and 6 stand for images whose edge cuts their cut-outs
        bounds[4] = (52, 69, 72, 90)
        bounds[5] = (70, 100, 0, 49)
    noise = CorrelatedNoise.fit([1.0, 10.0, 100.0], [1.0, 1.3, 1.8]) if with_noise else None
    got = phot.sextractor_photometry(img, rms, seg, np.arange(1, k + 1), nodata, ell, DIAMETERS,
                                     "correct", gain=gain, bounds=bounds, noise=noise)
    want = _by_object(img, rms, seg, nodata, ell, gain, noise, bounds)
    for g, w in zip(got, want):
        assert np.all(np.isfinite(g))
        assert g.tobytes() == w.tobytes()


def test_clean_objects_share_one_sep_call(monkeypatch):
    img, rms, seg, nodata, ell = _scene()
    k = ell.x.size
    calls = {"circle": [], "ellipse": []}
    real_circle, real_ellipse = sep.sum_circle, sep.sum_ellipse
    monkeypatch.setattr(sep, "sum_circle",
                        lambda *a, **kw: calls["circle"].append(np.size(a[1])) or real_circle(*a, **kw))
    monkeypatch.setattr(sep, "sum_ellipse",
                        lambda *a, **kw: calls["ellipse"].append(np.size(a[1])) or real_ellipse(*a, **kw))
    phot.sextractor_photometry(img, rms, seg, np.arange(1, k + 1), nodata, ell, DIAMETERS, "correct")
    # Objects 1-4 are measured on their own cut-outs; 5-8 (4 objects x 3 apertures) together.
    assert sorted(calls["circle"]) == [3, 3, 3, 3, 12]       # 8 calls of 3 before issue 24
    assert sorted(calls["ellipse"]) == [1, 1, 1, 1, 4]


def test_cutout_plan_once_for_every_band():
    """Which cut-outs hold no neighbour depends on the segmentation only: planned once, the
    plan serves every band (here two images on one segmentation) with the same fluxes."""
    img, rms, seg, nodata, ell = _scene()
    k = ell.x.size
    labels = np.arange(1, k + 1)
    plan = phot.CutoutPlan.of(seg, labels, ell, DIAMETERS, "correct")
    # 1-2 touch each other, 4's cut-out crosses the image edge; 3 (by the no-data patch: not a
    # neighbour) and 5-8 are clear.  Without a mask type only the edge counts.
    assert plan.clear.tolist() == [False, False, True, False, True, True, True, True]
    assert phot.CutoutPlan.of(seg, labels, ell, DIAMETERS, "none").clear.tolist() == \
        [True, True, True, False, True, True, True, True]
    bounds = np.tile([0, img.shape[0], 0, img.shape[1]], (k, 1))
    for band_img in (img, 0.5 * img[::-1, ::-1].copy() + 0.01):
        got = plan.measure(band_img, rms, nodata, gain=1500.0)
        want = _by_object(band_img, rms, seg, nodata, ell, 1500.0, None, bounds)
        for g, w in zip(got, want):
            assert g.tobytes() == w.tobytes()
