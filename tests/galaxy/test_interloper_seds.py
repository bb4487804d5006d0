"""The built-in interloper spectra: the Calzetti law, the D4000 break, their band magnitudes."""
import numpy as np
import pytest

from glaciar.galaxy.filters import ab_magnitude
from glaciar.galaxy.igm import igm_transmission
from glaciar.galaxy.interloper_seds import (CALZETTI_RV, InterloperParams, calzetti_k,
                                            interloper_band_magnitudes, rest_flambda)

BANDS = ["wfc3_uvis_f606w", "wfc3_ir_f098m", "wfc3_ir_f125w", "wfc3_ir_f160w"]


def calzetti_published(lam_um):
    """Calzetti et al. (2000), eq. 4, typed in from the paper."""
    x = 1.0 / lam_um
    if lam_um < 0.63:
        return 2.659 * (-2.156 + 1.509 * x - 0.198 * x ** 2 + 0.011 * x ** 3) + 4.05
    return 2.659 * (-1.857 + 1.040 * x) + 4.05


@pytest.mark.parametrize("lam_um", [0.125, 0.16, 0.25, 0.44, 0.55, 0.62, 0.65, 1.0, 1.6, 2.19])
def test_calzetti_curve_is_the_published_formula(lam_um):
    assert calzetti_k(lam_um * 1e4) == pytest.approx(calzetti_published(lam_um), rel=1e-12)


def test_calzetti_curve_defines_rv_and_ebv():
    # k(V) = R_V and k(B) - k(V) = 1: what A_V = R_V E(B-V) means.
    k_b, k_v = calzetti_k([4400.0, 5500.0])
    assert k_v == pytest.approx(CALZETTI_RV, rel=1e-3)
    assert k_b - k_v == pytest.approx(1.0, rel=0.02)


def test_calzetti_curve_continues_smoothly_beyond_its_range():
    # Linear in 1/lambda outside 0.12-2.2 micron, continuous with the formula at both edges.
    lo = calzetti_k([1199.0, 1200.0, 1201.0])
    assert lo[0] - lo[1] == pytest.approx(lo[1] - lo[2], rel=0.02)
    hi = calzetti_k([21990.0, 22000.0, 22010.0])
    assert hi[0] - hi[1] == pytest.approx(hi[1] - hi[2], rel=0.02)
    assert np.all(np.diff(calzetti_k(np.linspace(900, 30000, 500))) < 0)   # attenuation falls
    assert np.all(calzetti_k([50000.0, 1e5]) >= 0)


def balmer(d4000, beta_blue=2.0, beta_red=-1.0, a_v=0.0):
    n = np.size(d4000)
    return InterloperParams(family=np.array(["balmer"] * n), beta=np.full(n, beta_blue),
                            beta_red=np.full(n, beta_red), a_v=np.full(n, a_v),
                            d4000=np.atleast_1d(np.asarray(d4000, float)))


@pytest.mark.parametrize("d,bb,br,av", [(1.3, 2.0, -1.0, 0.0), (1.8, 0.0, 0.5, 0.3),
                                        (2.5, 3.0, -2.0, 1.0)])
def test_d4000_measured_on_the_template_is_the_configured_value(d, bb, br, av):
    # Bruzual (1983): <f_nu> over 4050-4250 A / <f_nu> over 3750-3950 A, integrated here
    # on a grid of its own.
    lam = np.linspace(3700.0, 4300.0, 60001)
    f_nu = rest_flambda(lam, balmer(d, bb, br, av))[0] * lam ** 2
    red = (lam >= 4050) & (lam <= 4250)
    blue = (lam >= 3750) & (lam <= 3950)
    measured = np.trapezoid(f_nu[red], lam[red]) / np.trapezoid(f_nu[blue], lam[blue])
    assert measured == pytest.approx(d, rel=0.01)
    assert measured == pytest.approx(d, rel=1e-5)


def test_templates_have_no_ionising_flux():
    p = InterloperParams(family=np.array(["dusty", "balmer"]), beta=np.array([-2.0, 2.0]),
                         beta_red=np.array([0.0, -1.0]), a_v=np.array([1.0, 0.0]),
                         d4000=np.array([np.nan, 1.5]))
    f = rest_flambda([800.0, 900.0, 1000.0], p)
    assert np.all(f[:, :2] == 0) and np.all(f[:, 2] > 0)


@pytest.mark.parametrize("z", [1.0, 2.5, 4.2])
def test_band_magnitudes_against_direct_integration(z):
    p = InterloperParams(family=np.array(["dusty", "balmer"]), beta=np.array([-1.8, 2.0]),
                         beta_red=np.array([0.0, -1.0]), a_v=np.array([2.5, 0.4]),
                         d4000=np.array([np.nan, 1.9]))
    mags = interloper_band_magnitudes(z, p, BANDS, np.array([26.0, 27.0]), 3)
    wave = np.geomspace(2500.0, 25000.0, 120001)
    flam = rest_flambda(wave / (1 + z), p) * igm_transmission(wave, z)
    for i, m_det in enumerate([26.0, 27.0]):
        direct = np.array([ab_magnitude(wave, flam[i], b) for b in BANDS])
        want = direct - direct[3] + m_det
        assert mags[i, 3] == m_det
        assert np.allclose(mags[i], want, atol=2e-3), (mags[i], want)


def test_dust_reddens_a_dusty_interloper_by_the_calzetti_colour():
    # Two dusty sources differing only in A_V: their F098M - F160W colours differ by
    # ~ delta A_V (k(lambda_98) - k(lambda_160)) / R_V at the bands' rest wavelengths.
    z = 2.0
    p = InterloperParams(family=np.array(["dusty", "dusty"]), beta=np.array([-2.0, -2.0]),
                         beta_red=np.zeros(2), a_v=np.array([0.0, 2.0]), d4000=np.full(2, np.nan))
    m = interloper_band_magnitudes(z, p, BANDS, np.array([26.0, 26.0]), 3)
    d_colour = (m[1, 1] - m[1, 3]) - (m[0, 1] - m[0, 3])
    k98, k160 = calzetti_k([9860.0 / (1 + z), 15370.0 / (1 + z)])
    assert d_colour == pytest.approx(2.0 * (k98 - k160) / CALZETTI_RV, rel=0.1)


def test_a_detection_band_without_flux_is_refused():
    p = balmer(1.5)
    with pytest.raises(ValueError, match="receives no flux"):
        interloper_band_magnitudes(12.0, p, ["wfc3_uvis_f606w"], np.array([26.0]), 0)


@pytest.mark.parametrize("counts", [(-1.2, 0.35, 25.0), (0.3, 0.0, 24.0), (-2.0, -0.1, 26.5)])
def test_number_counts_integral_is_the_integral_of_the_counts(counts):
    """The closed form against adaptive quadrature of the power law, to 1e-10."""
    from scipy.integrate import quad

    from glaciar.galaxy.interloper_seds import number_counts, number_counts_integral

    for lo, hi in ((22.0, 23.5), (25.0, 29.0)):
        want = quad(lambda m: float(number_counts(counts, m)), lo, hi, epsabs=0, epsrel=1e-12)[0]
        assert float(number_counts_integral(counts, lo, hi)) == pytest.approx(want, rel=1e-10)
    assert float(number_counts(counts, counts[2])) == pytest.approx(10 ** counts[0], rel=1e-15)
