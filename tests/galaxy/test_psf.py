"""Tests for glaciar.galaxy.psf: analytic PSFs, FITS reading, resampling, FWHM, convolution."""
import math

import numpy as np
import pytest
from astropy.io import fits
from scipy import integrate
from scipy.special import erf, j1

from glaciar.galaxy.psf import (airy_psf, gaussian_psf, measure_fwhm, moffat_psf,
                                prepare_psf, read_psf, resample_psf, shift_psf)

SIG_PER_FWHM = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


def erf_gaussian(fwhm_pix, size, cx=0.0, cy=0.0):
    """Exact pixel integrals of a Gaussian (product of erf differences), sum 1."""
    s = fwhm_pix * SIG_PER_FWHM
    h = (size - 1) // 2
    e = np.arange(-h - 0.5, h + 1.5)
    gx = np.diff(0.5 * erf((e - cx) / (math.sqrt(2) * s)))
    gy = np.diff(0.5 * erf((e - cy) / (math.sqrt(2) * s)))
    out = np.outer(gy, gx)
    return out / out.sum()


def centroid(a):
    yy, xx = np.indices(a.shape)
    return (a * yy).sum() / a.sum(), (a * xx).sum() / a.sum()


# ---------------------------------------------------------------- analytic PSFs
@pytest.mark.parametrize("fwhm_pix", [0.5, 1.0, 1.4, 2.25, 6.0])
def test_gaussian_matches_erf_product(fwhm_pix):
    psf = gaussian_psf(fwhm_pix * 0.08, 0.08)
    assert psf.shape[0] % 2 == 1 and psf.shape[0] == psf.shape[1]
    ref = erf_gaussian(fwhm_pix, psf.shape[0])
    assert np.abs(psf - ref).max() < 1e-7 * ref.max()
    assert psf.sum() == pytest.approx(1.0, abs=1e-14)


def test_moffat_pixel_integrals_match_adaptive_quadrature():
    fwhm, scale, beta = 0.18, 0.08, 2.5
    psf = moffat_psf(fwhm, scale, beta=beta, size=41)
    alpha = fwhm / (2 * math.sqrt(2 ** (1 / beta) - 1)) / scale    # pixels
    f = lambda y, x: (1 + (x * x + y * y) / alpha ** 2) ** -beta
    # Normalisation over the same 41x41 box, separately computed.
    ref = {}
    for (iy, ix) in [(0, 0), (0, 1), (1, 2), (5, -3)]:
        ref[(iy, ix)] = integrate.dblquad(f, ix - 0.5, ix + 0.5, iy - 0.5, iy + 0.5,
                                          epsabs=1e-13, epsrel=1e-11)[0]
    total = integrate.dblquad(f, -20.5, 20.5, -20.5, 20.5, epsabs=1e-12, epsrel=1e-11)[0]
    for (iy, ix), v in ref.items():
        assert psf[20 + iy, 20 + ix] == pytest.approx(v / total, abs=1e-7 * psf.max())


def test_airy_pixel_integral_and_unobscured_fwhm():
    wav, scale = 16000.0, 0.08
    lod = wav * 1e-10 / 2.4 * 206264.80624709636          # lambda / D [arcsec]
    eps = 0.33
    psf = airy_psf(wav, scale, obscuration=eps, size=21)

    def prof(y, x):
        xx = math.pi * math.hypot(x, y) * scale / lod
        if xx == 0:
            return 1.0
        return (2 * j1(xx) / xx - eps ** 2 * 2 * j1(eps * xx) / (eps * xx)) ** 2

    num = [integrate.dblquad(prof, ix - .5, ix + .5, iy - .5, iy + .5, epsabs=1e-12)[0]
           for iy, ix in [(0, 0), (0, 2)]]
    # ratio of two pixels is independent of the box normalisation
    assert psf[10, 10] / psf[10, 12] == pytest.approx(num[0] / num[1], rel=1e-6)
    # Unobscured Airy: FWHM = 1.029 lambda/D (finely sampled so pixels do not matter).
    fine = airy_psf(wav, 0.01, obscuration=0.0, size=81)
    assert measure_fwhm(fine, 0.01) == pytest.approx(1.029 * lod, rel=0.01)


def test_analytic_psfs_are_centred_and_odd():
    for psf in (gaussian_psf(0.2, 0.06), moffat_psf(0.2, 0.06, beta=3.0), airy_psf(12000, 0.06)):
        n = psf.shape[0]
        assert n % 2 == 1 and psf.shape == (n, n)
        cy, cx = centroid(psf)
        assert abs(cy - (n - 1) / 2) < 1e-10 and abs(cx - (n - 1) / 2) < 1e-10
        assert psf.sum() == pytest.approx(1.0, abs=1e-13)
    assert gaussian_psf(0.2, 0.06, size=9).shape == (9, 9)


def test_analytic_psf_errors():
    with pytest.raises(ValueError, match="odd"):
        gaussian_psf(0.2, 0.06, size=10)
    with pytest.raises(ValueError, match="beta"):
        moffat_psf(0.2, 0.06, beta=1.0)
    with pytest.raises(ValueError, match="fwhm_arcsec"):
        gaussian_psf(-1, 0.06)
    with pytest.raises(ValueError, match="obscuration"):
        airy_psf(10000, 0.06, obscuration=1.2)


# ---------------------------------------------------------------- FITS
def test_read_psf_big_endian_header_scales_and_negative_wings(tmp_path):
    data = erf_gaussian(2.0, 15) * 3.0
    data[0, 0] = -1e-3                                   # negative wing: kept
    be = data.astype(">f8")
    p1 = tmp_path / "pixscale.fits"
    h = fits.Header()
    h["PIXSCALE"] = 0.13
    fits.PrimaryHDU(be, header=h).writeto(p1)
    psf, scale = read_psf(p1)
    assert scale == 0.13
    assert psf.dtype == np.float64 and psf.dtype.isnative
    assert psf.sum() == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(psf, data / data.sum(), rtol=1e-14, atol=1e-17)
    assert psf[0, 0] < 0

    # CDELT x PC in degrees (drizzle style: CDELT = 1, scale in PC)
    p2 = tmp_path / "pc.fits"
    h = fits.Header()
    for k, v in dict(CDELT1=1.0, CDELT2=1.0, PC1_1=-0.06 / 3600, PC2_2=0.06 / 3600,
                     PC1_2=0.0, PC2_1=0.0, CUNIT1="deg").items():
        h[k] = v
    fits.PrimaryHDU(data.astype(">f4"), header=h).writeto(p2)
    assert read_psf(p2)[1] == pytest.approx(0.06, rel=1e-6)

    # CD matrix, and the explicit argument wins over the header
    p3 = tmp_path / "cd.fits"
    h = fits.Header()
    h["CD1_1"], h["CD2_2"] = -0.03 / 3600, 0.03 / 3600
    fits.PrimaryHDU(data, header=h).writeto(p3)
    assert read_psf(p3)[1] == pytest.approx(0.03, rel=1e-9)
    assert read_psf(p3, psf_pixel_scale_arcsec=0.1)[1] == 0.1


def test_read_psf_errors(tmp_path):
    p = tmp_path / "noscale.fits"
    fits.PrimaryHDU(np.ones((5, 5))).writeto(p)
    with pytest.raises(ValueError, match="noscale.fits.*pixel scale"):
        read_psf(p)
    q = tmp_path / "nan.fits"
    d = np.ones((5, 5))
    d[2, 2] = np.nan
    h = fits.Header()
    h["PIXSCALE"] = 0.1
    fits.PrimaryHDU(d, header=h).writeto(q)
    with pytest.raises(ValueError, match="nan.fits.*NaN"):
        read_psf(q)
    with pytest.raises(FileNotFoundError, match="missing.fits"):
        read_psf(tmp_path / "missing.fits")


# ---------------------------------------------------------------- resampling
@pytest.mark.parametrize("make,fwhm,s_in,s_out", [
    (gaussian_psf, 0.18, 0.13, 0.08),       # WFC3/IR Tiny Tim scale -> BoRG (coarser -> finer)
    (gaussian_psf, 0.18, 0.0495, 0.08),     # ACS scale -> BoRG (finer -> coarser)
    (moffat_psf, 0.18, 0.0495, 0.08),
    (gaussian_psf, 0.18, 0.08, 0.13),
    (moffat_psf, 0.24, 0.08, 0.03),
])
def test_resample_keeps_fwhm_flux_and_centre(make, fwhm, s_in, s_out):
    src = make(fwhm, s_in)
    out = resample_psf(src, s_in, s_out)
    direct = make(fwhm, s_out)
    n = out.shape[0]
    assert n % 2 == 1 and out.shape == (n, n)
    assert out.sum() == pytest.approx(1.0, abs=1e-12)
    cy, cx = centroid(out)
    assert abs(cy - (n - 1) / 2) < 0.01 and abs(cx - (n - 1) / 2) < 0.01
    assert measure_fwhm(out, s_out) == pytest.approx(measure_fwhm(direct, s_out), rel=0.02)
    # Output covers the input extent (no light thrown away by the grid).
    assert n * s_out >= src.shape[0] * s_in - 1e-9


def test_resample_conserves_flux_in_apertures():
    """Light in a box whose edges are new-pixel edges equals the exact erf integral."""
    fwhm, s_in, s_out = 0.3, 0.05, 0.08
    out = resample_psf(gaussian_psf(fwhm, s_in, size=61), s_in, s_out)
    h = (out.shape[0] - 1) // 2
    sig = fwhm * SIG_PER_FWHM
    for k in (0, 1, 2, 4):
        a = (k + 0.5) * s_out                            # half-side [arcsec]
        exact = erf(a / (math.sqrt(2) * sig)) ** 2
        assert out[h - k:h + k + 1, h - k:h + k + 1].sum() == pytest.approx(exact, abs=2e-3)


def test_resample_recentres_offcentre_even_input():
    # even-sized, source centred at (11.8, 12.3) in a 24x26 array at 0.05"/px
    ny, nx = 24, 26
    s = 0.12 * SIG_PER_FWHM / 0.05
    ey, ex = np.arange(ny + 1) - 0.5, np.arange(nx + 1) - 0.5
    gy = np.diff(0.5 * erf((ey - 11.8) / (math.sqrt(2) * s)))
    gx = np.diff(0.5 * erf((ex - 12.3) / (math.sqrt(2) * s)))
    out = resample_psf(np.outer(gy, gx), 0.05, 0.06)
    n = out.shape[0]
    cy, cx = centroid(out)
    assert n % 2 == 1 and abs(cy - (n - 1) / 2) < 0.01 and abs(cx - (n - 1) / 2) < 0.01
    ref = erf_gaussian(0.12 / 0.06, n)     # input FWHM 2.4 px: stated accuracy 2 % of peak
    assert np.abs(out - ref).max() < 0.02 * ref.max()


def test_shift_psf_moves_centroid_and_matches_exact_shift():
    psf = gaussian_psf(0.24, 0.08)          # 3 px FWHM
    out = shift_psf(psf, 0.25, -0.375)
    n = psf.shape[0]
    cy, cx = centroid(out)
    assert cx - (n - 1) / 2 == pytest.approx(0.25, abs=1e-4)
    assert cy - (n - 1) / 2 == pytest.approx(-0.375, abs=1e-4)
    ref = erf_gaussian(3.0, n, cx=0.25, cy=-0.375)
    assert np.abs(out - ref).max() < 0.01 * ref.max()


@pytest.mark.parametrize("make", [gaussian_psf, moffat_psf])
@pytest.mark.parametrize("fwhm_pix", [2.5, 4.0, 8.0])
def test_measure_fwhm_matches_analytic(make, fwhm_pix):
    psf = make(fwhm_pix * 0.05, 0.05)
    assert measure_fwhm(psf, 0.05) == pytest.approx(fwhm_pix * 0.05, rel=0.015)


# ---------------------------------------------------------------- prepare_psf
def test_prepare_psf_profiles_and_fits(tmp_path):
    np.testing.assert_array_equal(prepare_psf({"profile": "Gaussian", "fwhm_arcsec": 0.2}, 0.08),
                                  gaussian_psf(0.2, 0.08))
    np.testing.assert_array_equal(
        prepare_psf({"profile": "moffat", "fwhm_arcsec": 0.2, "beta": 3.0}, 0.08),
        moffat_psf(0.2, 0.08, beta=3.0))
    np.testing.assert_array_equal(
        prepare_psf({"profile": "airy", "wavelength_angstrom": 15000.0, "diameter_m": 6.5}, 0.03),
        airy_psf(15000.0, 0.03, diameter_m=6.5))
    # FITS path relative to base_dir, resampled 0.04 -> 0.08
    h = fits.Header()
    h["PIXSCALE"] = 0.04
    fits.PrimaryHDU(gaussian_psf(0.2, 0.04).astype(">f4"), header=h).writeto(tmp_path / "p.fits")
    out = prepare_psf("p.fits", 0.08, base_dir=tmp_path)
    assert out.sum() == pytest.approx(1.0, abs=1e-12)
    assert measure_fwhm(out, 0.08) == pytest.approx(0.2, rel=0.02)


def test_prepare_psf_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown PSF profile 'sersic'"):
        prepare_psf({"profile": "sersic", "fwhm_arcsec": 0.2}, 0.08)
    with pytest.raises(ValueError, match=r"needs key\(s\) \['fwhm_arcsec'\]"):
        prepare_psf({"profile": "moffat", "beta": 2.5}, 0.08)
    with pytest.raises(ValueError, match=r"\['fwhm'\]"):
        prepare_psf({"profile": "gaussian", "fwhm_arcsec": 0.2, "fwhm": 0.2}, 0.08)
    with pytest.raises(ValueError, match="no 'profile'"):
        prepare_psf({"fwhm_arcsec": 0.2}, 0.08)
    with pytest.raises(FileNotFoundError, match="nope.fits"):
        prepare_psf("nope.fits", 0.08, base_dir=tmp_path)


# ------------------------------------------------------------------------------
# Fast kernels of the windowed measurement against independent computations.
# ------------------------------------------------------------------------------
def test_resample_matrix_equals_a_fresh_spline_through_the_cumulative():
    """The cached spline per input size gives the matrix a spline built on the spot gives."""
    from scipy.interpolate import CubicSpline

    from glaciar.galaxy.psf import _resample_matrix

    rng = np.random.default_rng(3)
    for n in (5, 17, 41, 17):
        new_edges = np.sort(rng.uniform(-3.0, n + 3.0, n + 1))
        edges = np.arange(-2.5, n + 2.5)
        cum = np.zeros((edges.size, n))
        cum[3:3 + n] = np.tril(np.ones((n, n)))
        cum[3 + n:] = 1.0
        ref = np.diff(CubicSpline(edges, cum, axis=0, bc_type="clamped")(np.clip(new_edges, edges[0], edges[-1])),
                      axis=0)
        assert np.array_equal(_resample_matrix(n, new_edges), ref)
