"""V_eff behind a lens: against analytic source-plane volumes and a direct per-node sum."""
import math

import astropy.units as u
import numpy as np
import pytest
from astropy.cosmology import Planck18
from scipy.integrate import quad

from glaciar.galaxy.filters import get_filter
from glaciar.galaxy.lensing import SISLens, distance_ratio, lens_area_nodes
from glaciar.inference import SelectionFunction, SurfaceModel
from glaciar.inference.lensed import LensNodes, lensed_table
from glaciar.inference.products import InjectionSED
from lens_maps import put_mass_sheet

Z_LENS = 0.308
SED = InjectionSED(get_filter("wfc3_ir_f160w"), beta_mean=-2.0, beta_sd=0.3)


def _sf(params, depth_ref=None, n_draws=3, seed=0, z=(6.0, 8.0)):
    mdl = SurfaceModel(shape="logistic", z_ref=sum(z) / 2, z_scale=(z[1] - z[0]) / 2, m_ref=27.0,
                       m_scale=2.0, depth_ref=depth_ref)
    base = dict.fromkeys(mdl.param_names, 0.0)
    base.update(params)
    th = np.array([base[n] for n in mdl.param_names])
    draws = th + 0.01 * np.random.default_rng(seed).standard_normal((n_draws, len(th)))
    return SelectionFunction(mdl, draws, meta={"area_arcmin2": 1.0}, sed=SED,
                             domain={"z": z, "mag": (24.0, 30.0)})


#: P = 1 to 1e-12 for every m < 40 and z in the range: a step selection.
STEP = dict(logit_c_max_0=40.0, m50_0=60.0, log_w_0=0.0, logit_s_max=40.0,
            eta_lo_0=40.0, log_dz_lo_0=0.0, eta_hi_0=40.0, log_dz_hi_0=0.0)
#: A realistic selection: m50 = 27.4, w = 0.25, z edges of 0.15 inside the range.
SMOOTH = dict(logit_c_max_0=3.0, m50_0=27.4, m50_1=0.1, log_w_0=np.log(0.25), logit_s_max=3.0,
              eta_lo_0=-1.0, log_dz_lo_0=np.log(0.15), eta_hi_0=-1.0, log_dz_hi_0=np.log(0.15))


def _sis_field(theta_e=6.0, half=40.0, h=0.1, depth=None):
    """Pixel samples (arcsec) of a square field centred on an SIS (+ its nodes, 1 depth)."""
    lens = SISLens(theta_e=theta_e, x0=0.01, y0=-0.02)
    g = np.arange(-half, half, h) + h / 2
    xx, yy = np.meshgrid(g, g)
    k, g1, g2 = lens.convergence_shear(xx, yy)
    d = np.full(xx.shape, 27.5) if depth is None else depth(xx, yy)
    r = distance_ratio(Z_LENS, [6.0, 8.0], Planck18)
    nodes = lens_area_nodes(d, k, g1, g2, h * h / 3600, depth_bin_mag=0.05,
                            ratio_range=(r[0], r[1]))
    return LensNodes.from_dict("cl", "sis", Z_LENS, nodes), (k, g1, g2)


def _dvdz_sr(z):
    return Planck18.differential_comoving_volume(z).to_value(u.Mpc ** 3 / u.sr)


def test_step_selection_volume_is_the_source_plane_comoving_volume():
    """V_eff of a step selection behind an SIS = integral of dV/dz times the analytic
    source-plane area, 4 L^2 - 8 L theta_E(z) asinh(1) + 2 pi theta_E(z)^2 with
    theta_E(z) = theta_E D_ls/D_s: to 1 % (pixelisation of the square; the pixel sum
    itself to 1e-4)."""
    theta_e, half = 6.0, 40.0
    nodes, (k, g1, g2) = _sis_field(theta_e, half, h=0.2)
    sf = _sf(STEP)
    sf.lens_nodes = {"cl": {"sis": nodes}}
    v = sf.effective_volume([25.0, 28.0], cosmology=Planck18)
    arcsec2_sr = (1 * u.arcsec ** 2).to_value(u.sr)

    def analytic(z):
        te = theta_e * distance_ratio(Z_LENS, z, Planck18)
        return (4 * half ** 2 - 8 * half * te * math.asinh(1) + 2 * math.pi * te ** 2) * arcsec2_sr

    def pixels(z):
        r = distance_ratio(Z_LENS, z, Planck18)
        return np.abs(1 - 2 * r * k + r * r * (k * k - g1 ** 2 - g2 ** 2)).sum() * 0.04 * arcsec2_sr

    x, w = np.polynomial.legendre.leggauss(16)          # smooth integrands: exact to < 1e-8
    zq = 7.0 + x
    want = np.sum(w * _dvdz_sr(zq) * analytic(zq))
    exact = np.sum(w * _dvdz_sr(zq) * np.array([pixels(z) for z in zq]))
    got = v.median.to_value(u.Mpc ** 3)
    np.testing.assert_allclose(got, exact, rtol=1e-4)
    np.testing.assert_allclose(got, want, rtol=0.01)
    # M_UV: a step selection does not depend on the magnitude either.
    vm = sf.effective_volume_muv([-20.0, -18.0], cosmology=Planck18)
    np.testing.assert_allclose(vm.median.to_value(u.Mpc ** 3), exact, rtol=1e-4)


def test_two_mass_sheets_give_the_analytic_volume_ratio_and_spread():
    """Lens models kappa = 0.2 and 0.4 (no shear): the source-plane area is (1 - r kappa)^2 of
    the image plane, so V_eff per model, their mean and spread follow in closed form."""
    d = np.full((20, 20), 27.5)
    zero = np.zeros_like(d)
    lens = {}
    for name, kap in (("a", 0.2), ("b", 0.4)):
        nodes = lens_area_nodes(d, zero + kap, zero, zero, 0.01, depth_bin_mag=0.05,
                                ratio_range=(0.8, 0.9))
        lens[name] = LensNodes.from_dict("cl", name, Z_LENS, nodes)
    sf = _sf(STEP)
    sf.lens_nodes = {"cl": lens}
    got = sf.lens_model_volumes([26.0], cosmology=Planck18)
    sr = (4.0 * u.arcmin ** 2).to_value(u.sr)

    def vol(kap):
        return quad(lambda z: _dvdz_sr(z) * sr * (1 - distance_ratio(Z_LENS, z, Planck18) * kap) ** 2,
                    6.0, 8.0, epsrel=1e-9)[0]
    va, vb = vol(0.2), vol(0.4)
    np.testing.assert_allclose(got.per_model["a"].median.to_value(u.Mpc ** 3), va, rtol=1e-6)
    np.testing.assert_allclose(got.per_model["b"].median.to_value(u.Mpc ** 3), vb, rtol=1e-6)
    np.testing.assert_allclose(got.average.median.to_value(u.Mpc ** 3), (va + vb) / 2, rtol=1e-6)
    np.testing.assert_allclose(got.spread.to_value(u.Mpc ** 3), abs(va - vb) / 2, rtol=1e-5)
    # The default V_eff is the models' average.
    np.testing.assert_allclose(sf.effective_volume([26.0], cosmology=Planck18).median.value,
                               (va + vb) / 2, rtol=1e-6)


def test_lensed_table_matches_a_direct_sum_over_nodes():
    """A depth-aware smooth selection behind an SIS with two depths: the lattice/FFT table
    equals sum_n Omega_n |det_n| P(z, m + 2.5 log10|det_n| - (d_n - d_ref)) evaluated node
    by node, to 2e-4 of its value (the stated h^2/8 P'' accuracy)."""
    nodes, _ = _sis_field(theta_e=4.0, half=12.0, h=0.2,
                          depth=lambda x, y: np.where(x < 0, 27.2, 27.9))
    sf = _sf(SMOOTH, depth_ref=27.5, n_draws=2)
    zz = np.array([6.3, 7.0, 7.6])
    m = np.array([25.3, 26.9, 27.55, 28.4, 29.7])
    got = lensed_table(sf.model, sf.draws, zz, m, [nodes], Planck18)
    sr = (nodes.area_arcmin2 * u.arcmin ** 2).to_value(u.sr)
    det = nodes.inverse_magnification(zz, Planck18)                      # (n_z, n)
    want = np.zeros_like(got)
    for iz, z in enumerate(zz):
        for n in range(len(sr)):
            shift = 2.5 * np.log10(abs(det[iz, n])) - (nodes.depth[n] - 27.5)
            c, s = sf.model.surfaces_on_grid(sf.draws, np.array([z]), m + min(max(shift, -6), 6))
            want[:, iz] += sr[n] * abs(det[iz, n]) * (c * s)[:, 0]
    np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-4 * want.max())


def test_file_keeps_the_lens_nodes():
    nodes, _ = _sis_field(theta_e=3.0, half=6.0, h=0.3)
    sf = _sf(SMOOTH)
    sf.lens_nodes = {"cl": {"sis": nodes}}
    back = SelectionFunction.from_bytes(SelectionFunction.to_bytes([sf]))["all"]
    got = back.lens_nodes["cl"]["sis"]
    assert got.z_lens == Z_LENS and back.lens_models == ["sis"]
    for key in ("depth", "kappa", "gamma", "kappa2_minus_gamma2", "area_arcmin2"):
        np.testing.assert_array_equal(getattr(got, key), getattr(nodes, key))
    np.testing.assert_allclose(back.effective_volume([27.0], cosmology=Planck18, n_z=201).draws.value,
                               sf.effective_volume([27.0], cosmology=Planck18, n_z=201).draws.value,
                               rtol=1e-12)
    # A file without lensed fields reads as before: no lens nodes.
    plain = SelectionFunction.from_bytes(SelectionFunction.to_bytes([_sf(SMOOTH)]))["all"]
    assert plain.lens_nodes is None
    with pytest.raises(ValueError, match="no lens model 'x'"):
        sf.for_lens_model("x")


def test_expected_counts_behind_a_mass_sheet_are_the_unlensed_ones_magnified():
    """A mass sheet magnifies every source by mu(z) = 1 / (1 - r kappa)^2: the expected counts
    per measured-magnitude bin are the unlensed counts of phi(M + 2.5 log10 mu), times the
    source-plane area fraction 1/mu (z = 7.9-8.0, where mu varies by < 0.1 %): to 1e-3 of
    the largest bin, with the transfer function, and the same through the lensed tables
    for kappa = 0."""
    from analytic_sf import lf_sf

    def phi(M, z):
        return 1e-3 * 10 ** (-0.4 * 1.0 * (M + 20.0)) * np.exp(-10 ** (-0.4 * (M + 21.0))) + 0 * z

    edges = np.arange(25.0, 30.01, 0.25)
    kw = dict(z_min=7.9, z_max=8.0, draws=2, warn=False)
    plain = lf_sf(n_draws=3).expected_counts(phi, edges, **kw).draws
    none = put_mass_sheet(lf_sf(n_draws=3), Z_LENS, 0.0).expected_counts(phi, edges, **kw).draws
    np.testing.assert_allclose(none, plain, atol=1e-3 * plain.max())
    kappa = 0.25
    r = float(distance_ratio(Z_LENS, 7.95, Planck18))
    mu = 1 / (1 - r * kappa) ** 2
    lensed = put_mass_sheet(lf_sf(n_draws=3), Z_LENS, kappa).expected_counts(phi, edges, **kw).draws
    shifted = lf_sf(n_draws=3).expected_counts(lambda M, z: phi(M + 2.5 * np.log10(mu), z),
                                               edges, **kw).draws / mu
    np.testing.assert_allclose(lensed, shifted, atol=1e-3 * shifted.max())
    assert abs(lensed.sum() - plain.sum()) > 0.2 * plain.sum()     # lensing matters here
    # Without the transfer function the counts sit at the magnified input magnitude.
    raw = put_mass_sheet(lf_sf(n_draws=3), Z_LENS, kappa).expected_counts(phi, edges, transfer=False,
                                                                         **kw).draws
    raw_shifted = lf_sf(n_draws=3).expected_counts(
        lambda M, z: phi(M + 2.5 * np.log10(mu), z), edges, transfer=False, **kw).draws / mu
    np.testing.assert_allclose(raw.sum(axis=-1), raw_shifted.sum(axis=-1), rtol=2e-3)


def test_completeness_of_a_magnified_source_is_read_at_its_observed_magnitude():
    sf = _sf(SMOOTH)
    m = np.array([27.0, 28.5, 30.0])
    np.testing.assert_array_equal(sf.completeness_lensed(m, 7.0, [10.0, -10.0, 1.0]),
                                  sf.completeness(m - 2.5 * np.log10([10.0, 10.0, 1.0]), 7.0))
    np.testing.assert_array_equal(sf.selection_probability_lensed(7.0, m, 2.0),
                                  sf.selection_probability(7.0, m - 2.5 * np.log10(2.0)))
    with pytest.raises(ValueError, match="non-zero"):
        sf.completeness_lensed(m, 7.0, 0.0)
