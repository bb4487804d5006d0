"""Noise models: weight rescaling and correlated noise against a field of known covariance.

The reference field is white Gaussian noise convolved with a known kernel K,
so the variance of any pixel sum is known exactly: for a sum over the pixel
set D, Var = sigma_w^2 * sum_j ((1_D correlated with K)_j)^2. The tests compare
glaciar's empirical measurements with that number, never with glaciar itself.
"""
import numpy as np
import pytest
from scipy import ndimage, signal

from glaciar.engine.detect import DetectionParams, measure_background
from glaciar.engine.noise import (CorrelatedNoise, empty_aperture_scatter,
                                  weight_rescale_factor)

KERNEL = np.outer([1, 2, 1], [1, 2, 1]) / 16.0 + 0.0     # a drizzle-like 3x3 smoothing kernel


def correlated_field(shape=(900, 900), seed=1):
    rng = np.random.default_rng(seed)
    white = rng.normal(size=(shape[0] + 2, shape[1] + 2))
    return signal.convolve2d(white, KERNEL, mode="valid")


def disk(r):
    """Pixel-centre-in-circle indicator centred on a pixel (what subpix=1 sums)."""
    k = int(np.ceil(r)) + 1
    yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
    return (xx ** 2 + yy ** 2 < r * r).astype(float)


def exact_sum_variance(indicator):
    """Var(sum over the pixel set) of white noise (sigma 1) convolved with KERNEL."""
    w = signal.correlate2d(indicator, KERNEL, mode="full")
    return float(np.sum(w ** 2))


SIGMA_PIX = float(np.sqrt(np.sum(KERNEL ** 2)))


def test_pixel_noise_of_the_reference_field():
    # Sanity of the reference itself: pixel sigma = sqrt(sum K^2) = 0.375 for this kernel.
    img = correlated_field()
    assert SIGMA_PIX == pytest.approx(0.375)
    assert img.std() == pytest.approx(SIGMA_PIX, rel=0.01)


def test_empty_aperture_scatter_matches_the_known_covariance():
    img = correlated_field()
    overestimate = 2.3
    rms = np.full(img.shape, overestimate * SIGMA_PIX)
    usable = np.ones(img.shape, bool)
    npix, ratio, n = empty_aperture_scatter(img, rms, usable, radii_pix=(1.2, 2.2, 4.2, 8.2),
                                            n_per_radius=1000, rng=np.random.default_rng(3))
    assert len(npix) == 4
    for r, N, got, k in zip((1.2, 2.2, 4.2, 8.2), npix, ratio, n):
        d = disk(r)
        assert N == d.sum()
        expected = np.sqrt(exact_sum_variance(d) / (d.sum() * (overestimate * SIGMA_PIX) ** 2))
        # clipped scatter from k (partly overlapping) apertures: ~1/sqrt(2k) relative error
        tol = 4 / np.sqrt(2 * k)
        assert got == pytest.approx(expected, rel=tol), (r, got, expected)
    # correlated noise: the ratio grows with the area
    assert np.all(np.diff(ratio) > 0)


def test_white_noise_with_a_true_map_is_the_identity():
    rng = np.random.default_rng(7)
    img = rng.normal(scale=2.0, size=(700, 700))
    npix, ratio, n = empty_aperture_scatter(img, np.full(img.shape, 2.0), np.ones(img.shape, bool),
                                            rng=np.random.default_rng(1))
    model = CorrelatedNoise.fit(npix, ratio, n)
    assert model.is_identity(0.05)
    # 1000 apertures per radius: each ratio within 4 standard errors (1/sqrt(2000)) of 1
    assert np.all(np.abs(ratio - 1) < 4 / np.sqrt(2 * n))


def test_apertures_stay_on_usable_sky():
    img = correlated_field((400, 400))
    usable = np.ones(img.shape, bool)
    usable[:, 200:] = False
    img[:, 200:] = 1e6          # anything touching the unusable half would dominate
    npix, ratio, _ = empty_aperture_scatter(img, np.full(img.shape, SIGMA_PIX), usable,
                                            radii_pix=(2.0, 6.0), rng=np.random.default_rng(0))
    assert np.all(ratio < 5)


def test_weight_rescale_factor_recovers_the_overestimate():
    img = correlated_field()
    map_rms = np.full(img.shape, 2.3 * SIGMA_PIX)
    _, bkg_rms = measure_background(img, None, DetectionParams())
    f = weight_rescale_factor(bkg_rms, map_rms, np.ones(img.shape, bool))
    assert f == pytest.approx(1 / 2.3, rel=0.03)


def test_table_interpolation_and_clamping():
    npix = np.array([12.0, 3.0, 50.0, 200.0])
    ratio = np.array([1.3, 1.1, 1.5, 1.6])
    model = CorrelatedNoise.fit(npix, ratio)
    assert model.npix == (3.0, 12.0, 50.0, 200.0)                 # sorted by area
    assert model.ratio_at(12.0) == pytest.approx(1.3)
    assert model.ratio_at(6.0) == pytest.approx(1.2)              # halfway in log N
    assert model.ratio_at(1.0) == pytest.approx(1.1)              # held at the range's ends
    assert model.ratio_at(1e4) == pytest.approx(1.6)
    assert model.variance_factor(50.0) == pytest.approx(1.5 ** 2)
    assert not model.is_identity()
    # 1 within tolerance + 3 standard errors of each measurement
    assert CorrelatedNoise.fit([5, 50], [1.06, 0.95], [1000, 1000]).is_identity(0.05)
    assert not CorrelatedNoise.fit([5, 50], [1.0, 1.13], [1000, 1000]).is_identity(0.05)
    with pytest.raises(ValueError, match=">= 2 areas"):
        CorrelatedNoise.fit([3.0], [1.0])


def _reference_aperture_sums(image, rms, usable, radii, n, seed):
    """The textbook procedure, written out plainly: full-frame float64 copies, one distance
    transform, one scan of the whole frame per radius (issue 11: the engine avoids all three)."""
    rng = np.random.default_rng(seed)
    var = np.where(usable, np.asarray(rms, np.float64) ** 2, 0.0)
    data = np.where(usable, np.asarray(image, np.float64), 0.0)
    dist = ndimage.distance_transform_edt(np.pad(usable, 1))[1:-1, 1:-1]
    out = []
    for r in radii:
        k = int(np.ceil(r))
        dy, dx = np.mgrid[-k:k + 1, -k:k + 1]
        inside = dy ** 2 + dx ** 2 < r * r
        yy, xx = np.nonzero(dist > r + 1.0)
        pick = rng.choice(yy.size, size=min(n, yy.size), replace=False)
        iy = yy[pick][:, None] + dy[inside][None, :]
        ix = xx[pick][:, None] + dx[inside][None, :]
        s, v = data[iy, ix].sum(axis=1), var[iy, ix].sum(axis=1)
        out.append(_robust_sigma_plain(s / np.sqrt(v)))
    return np.array(out)


def _robust_sigma_plain(x):
    keep = np.ones(x.size, bool)
    center, sigma = np.median(x), 1.482602218505602 * np.median(np.abs(x - np.median(x)))
    for _ in range(10):
        new = np.abs(x - center) <= 3.0 * sigma
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
        center, sigma = np.mean(x[keep]), np.std(x[keep], ddof=1) / 0.986659
    return sigma


def test_empty_aperture_scatter_equals_the_plain_procedure_bit_for_bit():
    # float32 inputs and an irregular usable mask (holes, a border strip), radii in any order:
    # the gathered, subset-filtered computation must give exactly the plain full-frame one's
    # numbers, with and without a shared distance map.
    from glaciar.engine.noise import empty_sky_distance

    rng = np.random.default_rng(7)
    img = correlated_field((300, 340), seed=3).astype(np.float32)
    rms = (0.3 + 0.1 * rng.random(img.shape)).astype(np.float32)
    usable = np.ones(img.shape, bool)
    usable[:, :20] = False
    usable[rng.integers(0, 300, 40), rng.integers(0, 340, 40)] = False
    usable = ~ndimage.binary_dilation(~usable, iterations=2)
    radii = (4.2, 0.5, 2.2, 8.2)
    want = _reference_aperture_sums(img, rms, usable, radii, 200, seed=11)
    for dist in (None, empty_sky_distance(usable)):
        _, ratio, n = empty_aperture_scatter(img, rms, usable, radii, 200,
                                             np.random.default_rng(11), distance=dist)
        assert np.array_equal(ratio, want)
        assert np.all(n == 200)
