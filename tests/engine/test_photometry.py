"""Dual-mode photometry against direct numpy sums and analytic values."""
import numpy as np
import pytest

from glaciar.engine import photometry as phot


def test_iso_matches_numpy_sums_with_and_without_gain():
    rng = np.random.default_rng(1)
    img = rng.normal(size=(30, 40))
    rms = rng.uniform(0.5, 2.0, size=(30, 40))
    seg = np.zeros((30, 40), dtype=np.int32)
    seg[5:10, 5:12] = 3
    seg[20:28, 30:35] = 1
    f, e = phot.iso_photometry(img, rms, seg, np.array([1, 3, 0]))
    for k, lab in enumerate([1, 3]):
        m = seg == lab
        assert np.isclose(f[k], img[m].sum(), rtol=1e-12)
        assert np.isclose(e[k], np.sqrt((rms[m] ** 2).sum()), rtol=1e-12)
    assert np.isnan(f[2]) and np.isnan(e[2])
    f, e = phot.iso_photometry(img, rms, seg, np.array([3]), gain=2.5)
    m = seg == 3
    assert np.isclose(e[0], np.sqrt((rms[m] ** 2).sum() + np.clip(img[m], 0, None).sum() / 2.5), rtol=1e-12)


def test_aperture_on_constant_image_is_area():
    img = np.full((60, 60), 2.0)
    rms = np.full((60, 60), 0.5)
    f, e = phot.aperture_photometry(img, rms, [30.3], [29.6], (4.0, 10.0))
    area = np.pi * np.array([2.0, 5.0]) ** 2
    # exact pixel overlap: only float rounding
    np.testing.assert_allclose(f[:, 0], 2.0 * area, rtol=1e-9)
    np.testing.assert_allclose(e[:, 0], 0.5 * np.sqrt(area), rtol=1e-9)


def test_auto_on_constant_image_is_ellipse_area_and_masks_neighbours():
    img = np.full((80, 80), 1.0)
    rms = np.ones((80, 80))
    a, b, th = 3.0, 1.5, 0.4
    scale = phot.auto_scale(np.array([2.0]), (2.5, 3.5))
    assert scale[0] == 5.0
    f, _ = phot.auto_photometry(img, rms, phot.Ellipses([40.0], [40.0], [a], [b], [th], scale))
    np.testing.assert_allclose(f, np.pi * a * b * 25.0, rtol=1e-6)
    # R_min applies when k * kron is smaller
    assert phot.auto_scale(np.array([1.0, np.nan]), (2.5, 3.5)).tolist() == [3.5, 3.5]


def test_kron_radius_of_uniform_disk():
    # uniform ellipse profile: <r> over r <= 6 is 2/3 * 6 = 4 (in units of a, b)
    img = np.ones((101, 101))
    kr = phot.kron_radius(img, [50.0], [50.0], [5.0], [5.0], [0.0])
    np.testing.assert_allclose(kr, 4.0, rtol=5e-3)


def test_magnitudes_and_limits():
    mag, magerr, sn = phot.magnitudes(np.array([100.0, -5.0, 0.0]), np.array([10.0, 2.0, 1.0]), 25.0)
    assert np.isclose(mag[0], 20.0) and np.isnan(mag[1]) and np.isnan(mag[2])
    assert np.isclose(magerr[0], 2.5 / np.log(10) * 0.1)
    np.testing.assert_allclose(sn, [10.0, -2.5, 0.0])
    lim = phot.limiting_magnitude(np.array([100.0, -5.0, np.nan]), np.array([10.0, 2.0, np.nan]), 25.0)
    assert np.isclose(lim[0], 20.0)
    assert np.isclose(lim[1], 25.0 - 2.5 * np.log10(2.0))   # 1-sigma limit for a negative flux
    assert np.isnan(lim[2])


def test_auto_excludes_neighbour_segments():
    img = np.ones((80, 80))
    seg = np.zeros((80, 80), dtype=np.int32)
    seg[38:43, 38:43] = 1
    img[40:44, 46:50] = 100.0          # a bright neighbour inside the aperture
    seg[40:44, 46:50] = 2
    ell = phot.Ellipses([40.0], [40.0], [3.0], [3.0], [0.0], np.array([4.0]))
    f, _ = phot.auto_photometry(img, np.ones_like(img), ell, segmap=seg, seg_id=np.array([1]))
    # the 16 neighbour pixels (all inside the r = 12 ellipse) are excluded, not replaced
    np.testing.assert_allclose(f, np.pi * 12.0 ** 2 - 16.0, rtol=1e-9)
    # no-data pixels (mask) are excluded and compensated by the area ratio, as in sep
    m = seg == 2
    h, _ = phot.auto_photometry(np.ones_like(img), np.ones_like(img), ell, mask=m)
    np.testing.assert_allclose(h, np.pi * 12.0 ** 2, rtol=1e-9)
    g, _ = phot.auto_photometry(img, np.ones_like(img), ell)
    assert g[0] > f[0] + 1000


def test_correlated_noise_scales_only_the_background_variance():
    from glaciar.engine.noise import CorrelatedNoise
    from glaciar.engine.photometry import aperture_photometry, iso_photometry

    rng = np.random.default_rng(0)
    img = rng.normal(size=(40, 40)) + 5.0
    rms = np.full(img.shape, 2.0)
    seg = np.zeros(img.shape, dtype=np.int32)
    seg[10:14, 10:15] = 1                       # 20 pixels
    seg[20:30, 20:30] = 2                       # 100 pixels
    model = CorrelatedNoise.fit([10.0, 100.0], [1.5, 3.0])      # r = 1.5 at 10 px, 3 at 100 px
    _, err = iso_photometry(img, rms, seg, [1, 2], noise=model)
    for lab, n in ((1, 20), (2, 100)):
        expected = np.sqrt(model.variance_factor(n) * n * 4.0)   # hand: f(N) * N * rms^2
        assert err[lab - 1] == pytest.approx(expected, rel=1e-12)
    # With a gain the Poisson part is not scaled.
    gain = 3.0
    _, e_plain = iso_photometry(img, rms, seg, [2], gain=gain)
    _, e_corr = iso_photometry(img, rms, seg, [2], gain=gain, noise=model)
    poisson = np.clip(img[20:30, 20:30], 0, None).sum() / gain
    assert e_corr[0] ** 2 == pytest.approx(model.variance_factor(100) * 400.0 + poisson, rel=1e-12)
    assert e_plain[0] ** 2 == pytest.approx(400.0 + poisson, rel=1e-12)
    # Apertures: background variance sum(w rms^2) = pi r^2 rms^2 scaled by f(pi r^2).
    _, ea = aperture_photometry(img, rms, [20.0], [20.0], [6.0], noise=model)
    area = np.pi * 9.0
    assert ea[0, 0] == pytest.approx(np.sqrt(model.variance_factor(area) * area * 4.0), rel=1e-6)
    _, eg = aperture_photometry(img, rms, [20.0], [20.0], [6.0], gain=gain, noise=model)
    _, eg0 = aperture_photometry(img, rms, [20.0], [20.0], [6.0], gain=gain)
    assert eg[0, 0] ** 2 - eg0[0, 0] ** 2 == pytest.approx((model.variance_factor(area) - 1) * area * 4.0,
                                                            rel=1e-6)


# ------------------------------------------------------------------------------
# Field set-up with bounded memory gives the same answers.
#
# Lean field set-up: row tiles and in-place work against whole-frame definitions
# ------------------------------------------------------------------------------
def _aperture_inputs(seed=4, shape=(90, 110), n=60):
    rng = np.random.default_rng(seed)
    img = (rng.standard_normal(shape) * 2.0 + rng.uniform(0.0, 4.0, shape)).astype(np.float32)
    rms = rng.uniform(0.5, 2.0, shape).astype(np.float32)
    seg = rng.integers(0, 4, shape).astype(np.int32)
    nodata = rng.uniform(size=shape) < 0.05
    x, y = rng.uniform(-3, shape[1] + 3, n), rng.uniform(-3, shape[0] + 3, n)
    a = rng.uniform(1.0, 6.0, n)
    b = a * rng.uniform(0.2, 1.0, n)
    th = rng.uniform(-1.5, 1.5, n)
    return img, rms, seg, nodata, x, y, a, b, th, rng.integers(1, 4, n).astype(np.int32)


@pytest.mark.parametrize("gain", [None, 2.5])
def test_sep_photometry_of_float32_images_is_that_of_their_float64_copies(gain):
    """kron_radius, auto_photometry and aperture_photometry no longer copy a float32 image to
    float64 (8 bytes per pixel on a field's reference photometry): sep on the float64 copies,
    called directly, is the reference, bit for bit; a read-only map is accepted."""
    import sep

    from glaciar.engine import photometry as phot

    img, rms, seg, nodata, x, y, a, b, th, ids = _aperture_inputs()
    i64, r64 = img.astype(np.float64), rms.astype(np.float64)
    ro = img.copy()
    ro.setflags(write=False)
    for data in (img, ro):
        kr = phot.kron_radius(data, x, y, a, b, th, segmap=seg, seg_id=ids, mask=nodata)
        want = sep.kron_radius(i64, x, y, a, b, th, 6.0, mask=nodata, segmap=seg, seg_id=ids)[0]
        assert np.array_equal(kr, want, equal_nan=True)
        scale = phot.auto_scale(kr, (2.5, 3.5))
        f, fe = phot.auto_photometry(data, rms, phot.Ellipses(x, y, a, b, th, scale), gain=gain, segmap=seg,
                                     seg_id=ids, mask=nodata)
        wf, wfe, _ = sep.sum_ellipse(i64, x, y, a, b, th, scale, err=r64, mask=nodata, gain=gain,
                                     subpix=0, segmap=seg, seg_id=ids)
        assert np.array_equal(f, wf, equal_nan=True) and np.array_equal(fe, wfe, equal_nan=True)
        fa, fea = phot.aperture_photometry(data, rms, x, y, (4.0, 8.0), gain=gain, mask=nodata)
        for k, d in enumerate((4.0, 8.0)):
            wf, wfe, _ = sep.sum_circle(i64, x, y, d / 2, err=r64, mask=nodata, gain=gain, subpix=0)
            assert np.array_equal(fa[k], wf, equal_nan=True)
            assert np.array_equal(fea[k], wfe, equal_nan=True)
    assert np.isfinite(f).sum() > 30
