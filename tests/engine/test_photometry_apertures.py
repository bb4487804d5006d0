"""SExtractor-style aperture photometry: one sep call for all apertures, same numbers (issue 24).

``sextractor_photometry`` measures each object on its own masked cut-out.  It
now sums all PHOT_APERTURES of an object in one ``sep.sum_circle`` call (it
made one per aperture), and ``masked_cutout`` finds a cut-out's invalid pixels
from slices.  The fluxes must stay bit-identical to one call per aperture on
the cut-out written out here by hand from MASK_TYPE's definition.
"""
import numpy as np
import pytest
import sep

from glaciar.engine import photometry as phot
from glaciar.engine.noise import CorrelatedNoise

DIAMETERS = (2.0, 4.0, 6.0, 8.0, 10.0)


def _scene(seed=5):
    """A 60x70 image with 3 objects (labels 1-3) touching each other, and a no-data patch."""
    rng = np.random.default_rng(seed)
    ny, nx = 60, 70
    yy, xx = np.mgrid[:ny, :nx]
    img = rng.normal(0.0, 0.05, (ny, nx))
    seg = np.zeros((ny, nx), dtype=np.int32)
    objs = [(20.3, 25.7, 2.5), (27.1, 31.4, 2.0), (44.6, 40.2, 3.0)]    # x, y, size [px]
    for k, (x, y, s) in enumerate(objs, start=1):
        r2 = (xx - x) ** 2 + (yy - y) ** 2
        img += 5.0 * np.exp(-0.5 * r2 / s ** 2)
        seg[(r2 < (2.2 * s) ** 2) & (seg == 0)] = k
    nodata = np.zeros((ny, nx), dtype=bool)
    nodata[30:34, 14:19] = True
    rms = np.full((ny, nx), 0.05) * (1.0 + 0.1 * rng.random((ny, nx)))
    x = np.array([o[0] for o in objs])
    y = np.array([o[1] for o in objs])
    return img, rms, seg, nodata, x, y


def _cutout_by_hand(image, rms, seg, seg_id, nodata, x, y, box, mask_type):
    """MASK_TYPE applied pixel by pixel, as the docstring of masked_cutout defines it."""
    y0, y1, x0, x1 = box
    y0, y1, x0, x1 = max(y0, 0), min(y1, image.shape[0]), max(x0, 0), min(x1, image.shape[1])
    data = np.array(image[y0:y1, x0:x1], dtype=np.float64)
    err = np.array(rms[y0:y1, x0:x1], dtype=np.float64)

    def invalid(j, i):
        other = seg[j, i] != 0 and seg[j, i] != seg_id
        return bool(nodata[j, i]) or (mask_type != "none" and other)

    for j in range(y0, y1):
        for i in range(x0, x1):
            if not invalid(j, i):
                continue
            v = e = 0.0
            if mask_type == "correct":
                i2, j2 = int(2.0 * x + 0.49999 - i), int(2.0 * y + 0.49999 - j)
                if 0 <= i2 < image.shape[1] and 0 <= j2 < image.shape[0] and not invalid(j2, i2):
                    v, e = image[j2, i2], rms[j2, i2]
            data[j - y0, i - x0], err[j - y0, i - x0] = v, e
    return data, err, (y0, x0)


@pytest.mark.parametrize("mask_type", ["none", "blank", "correct"])
def test_masked_cutout_equals_the_definition(mask_type):
    img, rms, seg, nodata, x, y = _scene()
    for k in range(3):
        box = (int(y[k]) - 12, int(y[k]) + 13, int(x[k]) - 12, int(x[k]) + 14)
        got = phot.masked_cutout(img, rms, seg, k + 1, nodata, x[k], y[k], box, mask_type)
        want = _cutout_by_hand(img, rms, seg, k + 1, nodata, x[k], y[k], box, mask_type)
        assert got[2] == want[2]
        assert got[0].tobytes() == want[0].tobytes()
        assert got[1].tobytes() == want[1].tobytes()


def _per_aperture(img, rms, seg, nodata, x, y, ell, gain, dbkg, noise):
    """One sep call per aperture on each object's cut-out (the figures to keep)."""
    xs, ys, a, b, th, sc = ell
    fa = np.full((len(DIAMETERS), x.size), np.nan)
    fea = fa.copy()
    for i in range(x.size):
        c, s_ = np.cos(th[i]), np.sin(th[i])
        hy = max(sc[i] * np.sqrt((a[i] * s_) ** 2 + (b[i] * c) ** 2), 5.0)
        hx = max(sc[i] * np.sqrt((a[i] * c) ** 2 + (b[i] * s_) ** 2), 5.0)
        box = (int(np.floor(y[i] - hy)) - 1, int(np.ceil(y[i] + hy)) + 2,
               int(np.floor(x[i] - hx)) - 1, int(np.ceil(x[i] + hx)) + 2)
        d, e, (oy, ox) = _cutout_by_hand(img, rms, seg, i + 1, nodata, x[i], y[i], box, "correct")
        cx, cy = np.array([x[i] - ox]), np.array([y[i] - oy])
        for j, dia in enumerate(DIAMETERS):
            r = 0.5 * dia
            f, fe, _ = sep.sum_circle(d, cx, cy, r, err=e, gain=gain, subpix=0)
            if noise is not None:
                fb = sep.sum_circle(d, cx, cy, r, err=e, subpix=0)[1]
                factor = noise.variance_factor(np.pi * r * r)
                fe = np.sqrt(np.square(fb) * factor + np.maximum(np.square(fe) - np.square(fb), 0.0))
            if dbkg[i] != 0.0:
                f = f - dbkg[i] * sep.sum_circle(np.ones_like(d), cx, cy, r, subpix=0)[0]
            fa[j, i], fea[j, i] = f[0], fe[0]
    return fa, fea


@pytest.mark.parametrize("with_noise", [False, True])
def test_aperture_fluxes_bit_identical_to_one_call_per_aperture(with_noise):
    img, rms, seg, nodata, x, y = _scene()
    ell = phot.Ellipses(x, y, np.array([2.0, 1.6, 2.4]), np.array([1.5, 1.2, 2.0]),
                        np.array([0.3, -0.7, 1.2]), np.array([2.5, 3.0, 2.2]))
    dbkg = np.array([0.0, 0.01, -0.02])
    noise = CorrelatedNoise.fit([1.0, 10.0, 100.0], [1.0, 1.3, 1.8]) if with_noise else None
    fa, fea, fau, feau = phot.sextractor_photometry(img, rms, seg, [1, 2, 3], nodata, ell, DIAMETERS,
                                                    "correct", gain=1500.0, dbkg=dbkg, noise=noise)
    want_fa, want_fea = _per_aperture(img, rms, seg, nodata, x, y, ell, 1500.0, dbkg, noise)
    assert fa.tobytes() == want_fa.tobytes()
    assert fea.tobytes() == want_fea.tobytes()
    assert np.all(np.isfinite(fau)) and np.all(np.isfinite(feau))


def test_one_sum_circle_call_per_object(monkeypatch):
    img, rms, seg, nodata, x, y = _scene()
    ell = phot.Ellipses(x, y, np.full(3, 2.0), np.full(3, 1.5), np.zeros(3), np.full(3, 2.5))
    calls = []
    real = sep.sum_circle
    monkeypatch.setattr(sep, "sum_circle", lambda *a, **k: calls.append(1) or real(*a, **k))
    phot.sextractor_photometry(img, rms, seg, [1, 2, 3], nodata, ell, DIAMETERS, "correct", gain=1500.0)
    assert len(calls) == 3          # one per object, not one per object and aperture (15)
