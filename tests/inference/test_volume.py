"""V_eff as a function of M_UV (SelectionFunction.effective_volume_muv) against independent computations."""
import astropy.units as u
import numpy as np
import pytest
from astropy.cosmology import FlatLambdaCDM, Planck18
from scipy.optimize import brentq

from glaciar.galaxy.filters import get_filter
from glaciar.inference import SelectionFunction, SurfaceModel
from glaciar.inference.products import InjectionSED, beta_nodes, kcorrection

M_LIM = 27.5          # the step of the synthetic selection [AB mag]
AREA = 10.0           # [arcmin^2]
F160W = "wfc3_ir_f160w"


def _step_sf(sed=None, magnitude_type="apparent", domain_mag=(25.0, 30.0), n_draws=2):
    """P = 1 for m < M_LIM, 0 beyond (logistic of width 1e-4 mag), S = 1 over z 6-8."""
    mdl = SurfaceModel(shape="logistic", z_ref=7.0, z_scale=1.0, m_ref=27.0, m_scale=2.0,
                       m50_degree=0, log_w_degree=0, edge_degree=0, c_max_degree=0)
    th = dict(logit_c_max_0=40.0, m50_0=M_LIM, log_w_0=np.log(1e-4), logit_s_max=40.0,
              eta_lo_0=40.0, log_dz_lo_0=0.0, eta_hi_0=40.0, log_dz_hi_0=0.0)
    draws = np.tile([th[n] for n in mdl.param_names], (n_draws, 1))
    return SelectionFunction(mdl, draws, meta={"area_arcmin2": AREA, "magnitude_type": magnitude_type},
                             domain={"z": (6.0, 8.0), "mag": domain_mag}, sed=sed)


def _flat_fnu_mag(M, z, cosmo):
    """Independent K-correction of a flat-f_nu source (beta = -2).

    m = M + 5 log10(D_L / 10 pc) - 2.5 log10(1 + z).
    """
    dl_pc = cosmo.luminosity_distance(z).to_value(u.pc)
    return M + 5 * np.log10(dl_pc / 10.0) - 2.5 * np.log10(1 + z)


def test_kcorrection_of_flat_fnu_matches_the_textbook_formula():
    # F160W at z = 6-8 lies redward of Lyman-alpha: no IGM, and a flat f_nu has no colour.
    z = np.linspace(6.0, 8.0, 9)
    k = kcorrection(z, [-2.0], F160W, cosmology=Planck18)[:, 0]
    np.testing.assert_allclose(k, _flat_fnu_mag(0.0, z, Planck18), atol=2e-4)
    # The spline between exact colours (dz = 0.05) agrees with the exact colour at every z.
    zf = np.linspace(6.0, 8.0, 81)
    np.testing.assert_allclose(kcorrection(zf, [-2.5, -1.5], F160W, dz=0.05),
                               kcorrection(zf, [-2.5, -1.5], F160W, dz=None), atol=1e-6)
    # A range starting on a node multiple (8.2 = 164 x 0.05, whose float quotient is
    # 163.999...) once put two equal nodes into the spline ("x must be strictly increasing").
    zs = np.linspace(8.2, 10.0, 61)
    np.testing.assert_allclose(kcorrection(zs, [-2.0], F160W, dz=0.05),
                               kcorrection(zs, [-2.0], F160W, dz=None), atol=3e-4)
    # Another cosmology moves it by the difference of the distance moduli.
    other = FlatLambdaCDM(H0=70, Om0=0.3)
    np.testing.assert_allclose(kcorrection(z, [-2.0], F160W, cosmology=other)[:, 0],
                               _flat_fnu_mag(0.0, z, other), atol=2e-4)


def test_band_without_flux_maps_to_infinity():
    # F098M (0.9-1.1 um) lies below the Lyman limit from z ~ 11: at z = 13 a source of
    # M_UV = 0 would be fainter than 50 mag there, glaciar's rule for "no flux" (as the
    # injections'), and the band is not used; the spline stops at the last finite node.
    k = kcorrection([7.0, 13.0], [-2.0], "wfc3_ir_f098m", dz=None)
    assert np.isfinite(k[0, 0]) and k[1, 0] == np.inf
    zf = np.linspace(11.0, 14.0, 100)
    spl = kcorrection(zf, [-2.0], "wfc3_ir_f098m")[:, 0]
    assert np.all(np.isfinite(spl[zf < 12.0])) and np.all(np.isinf(spl[zf >= 13.0]))


def test_step_selection_gives_the_analytic_comoving_volume():
    sed = InjectionSED(get_filter(F160W), beta_mean=-2.0, beta_sd=0.0, igm="inoue14",
                       cosmology="Planck18")
    sf = _step_sf(sed)
    M = np.array([-21.0, -19.9, -19.6, -19.45])
    v = sf.effective_volume_muv(M, n_z=2001)
    omega = (AREA * u.arcmin ** 2).to_value(u.sr)
    for Mi, vi in zip(M, v.median.to_value(u.Mpc ** 3)):
        # Selected out to the z where m(M, z) = M_LIM (or to the end of the box).
        f = lambda z: _flat_fnu_mag(Mi, z, Planck18) - M_LIM
        zs = 8.0 if f(8.0) < 0 else brentq(f, 6.0, 8.0)
        exact = ((Planck18.comoving_volume(zs) - Planck18.comoving_volume(6.0)).to_value(u.Mpc ** 3)
                 * omega / (4 * np.pi))
        # Simpson with dz = 1e-3 over a step: error < dz dV/dz / V ~ 2e-3 at the faintest.
        assert vi == pytest.approx(exact, rel=2.5e-3), (Mi, zs)
    assert v.draws.shape == (2, 4)


def test_beta_average_uses_gauss_hermite_of_the_injected_distribution():
    x, w = beta_nodes(-2.0, 0.4, 7)
    assert w.sum() == pytest.approx(1.0)
    assert np.sum(w * x) == pytest.approx(-2.0)
    assert np.sum(w * (x + 2.0) ** 2) == pytest.approx(0.16)
    # A beta spread at fixed M_UV spreads m: V_eff near the step is the beta-average of
    # the single-beta volumes (independent: each beta node evaluated on its own).
    filt = get_filter(F160W)
    sf = _step_sf(InjectionSED(filt, -2.0, 0.4))
    M = np.array([-19.7])
    mixed = sf.effective_volume_muv(M, n_z=801, n_beta=7).median.value
    per_beta = [_step_sf(InjectionSED(filt, b, 0.0)).effective_volume_muv(M, n_z=801).median.value[0]
                for b in x]
    assert mixed[0] == pytest.approx(np.sum(w * np.array(per_beta)), rel=1e-9)


def test_outside_the_simulated_magnitudes_is_nan_unless_extrapolated():
    sed = InjectionSED(get_filter(F160W), -2.0, 0.0)
    sf = _step_sf(sed, domain_mag=(26.0, 30.0))
    # M = -22 maps to m ~ 24.9-25.4 over z 6-8: brighter than the box, P = 1 there.
    v = sf.effective_volume_muv([-22.0, -19.6], n_z=401)
    assert np.isnan(v.median[0].value) and np.isfinite(v.median[1].value)
    ve = sf.effective_volume_muv([-22.0], n_z=401, outside="extrapolate")
    assert ve.median[0].value > 0
    grid = sf.muv_grid(0.1)
    assert np.isfinite(sf.effective_volume_muv(grid, n_z=201).median.value).all()


@pytest.mark.filterwarnings("ignore:effective_volume. C.S is still")   # S = 1 at the z ends, by design
def test_absolute_magnitude_fit_is_its_own_veff_and_needs_no_sed():
    sf = _step_sf(None, magnitude_type="absolute", domain_mag=(-23.0, -17.0))
    sf_m = _step_sf(None, magnitude_type="absolute", domain_mag=(-23.0, -17.0))
    v = sf.effective_volume_muv(np.array([-19.0]))
    np.testing.assert_allclose(v.median.value, sf_m.effective_volume(np.array([-19.0])).median.value)
    with pytest.raises(ValueError, match="records no injection SED"):
        _step_sf(None).effective_volume_muv([-20.0])


def test_veff_muv_file_round_trip_is_exact(tmp_path):
    from glaciar.inference.products import VeffTable

    filt = get_filter(F160W)
    sed = InjectionSED(filt, -2.2, 0.4, "madau95", "Planck18")
    sf = _step_sf(sed)
    grid = sf.muv_grid(0.5)
    vol = sf.effective_volume_muv(grid, n_z=101)
    sf.veff_muv = VeffTable(grid, vol, 0.68, AREA, "Planck18")
    path = tmp_path / "sf.fits"
    sf.write(path)
    back = SelectionFunction.read(path)
    np.testing.assert_array_equal(back.veff_muv.M_uv, grid)
    for name in ("median", "lower", "upper", "draws"):
        np.testing.assert_array_equal(getattr(back.veff_muv.volume, name).value,
                                      getattr(vol, name).value)
    assert back.sed.beta_mean == -2.2 and back.sed.igm == "madau95"
    np.testing.assert_array_equal(back.sed.detection_filter.throughput, filt.throughput)
    # The read-back SED reproduces the volume.
    np.testing.assert_array_equal(back.effective_volume_muv(grid, n_z=101).median.value,
                                  vol.median.value)


def test_group_linearly_bins_and_weights_independently():
    """Equal-width bins between the extremes, empty ones dropped, weighted means per group."""
    from glaciar.inference.volume import group_linearly

    v = np.array([0.0, 0.1, 0.95, 1.0, 3.9, 4.0])
    w = np.array([1.0, 3.0, 2.0, 2.0, 1.0, 1.0])
    index, means, totals = group_linearly(v, w, 4)     # bins of width 1: [0,1) [1,2) [2,3) [3,4]
    np.testing.assert_array_equal(index, [0, 0, 0, 1, 2, 2])
    np.testing.assert_allclose(means, [(0.3 + 1.9) / 6, 1.0, 3.95])
    np.testing.assert_allclose(totals, [6.0, 2.0, 2.0])
    index, means, totals = group_linearly(np.full(3, 2.5), [1.0, 1.0, 2.0], 4)
    np.testing.assert_array_equal(index, [0, 0, 0])
    np.testing.assert_allclose((means, totals), ([2.5], [4.0]))
