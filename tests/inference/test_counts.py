"""Expected counts per measured-magnitude bin (SelectionFunction.expected_counts) and the z-edge check."""
import warnings

import astropy.units as u
import numpy as np
import pytest
from astropy.cosmology import Planck18
from scipy.integrate import quad
from scipy.stats import norm

from glaciar.galaxy.filters import get_filter
from glaciar.inference import SelectionFunction, SurfaceModel
from glaciar.inference.counts import Quadrature, SurveyVolume, expected_counts
from glaciar.inference.products import InjectionSED

from analytic_sf import gauss_matrix

M_LIM = 27.5          # step of the synthetic selection [AB mag]
AREA = 10.0           # [arcmin^2]
F160W = "wfc3_ir_f160w"


def step_sf(sed=None, *, domain_mag=(23.0, 30.0), m_lim=M_LIM, magnitude_type="apparent",
            n_draws=2, z=(6.0, 8.0)):
    """P = 1 for m < m_lim, 0 beyond (logistic of width 1e-4 mag), S = 1 over z."""
    mdl = SurfaceModel(shape="logistic", z_ref=0.5 * (z[0] + z[1]), z_scale=0.5 * (z[1] - z[0]),
                       m_ref=0.5 * sum(domain_mag), m_scale=2.0, m50_degree=0, log_w_degree=0,
                       edge_degree=0, c_max_degree=0)
    th = dict(logit_c_max_0=40.0, m50_0=m_lim, log_w_0=np.log(1e-4), logit_s_max=40.0,
              eta_lo_0=40.0, log_dz_lo_0=0.0, eta_hi_0=40.0, log_dz_hi_0=0.0)
    draws = np.tile([th[n] for n in mdl.param_names], (n_draws, 1))
    sed = sed or InjectionSED(get_filter(F160W), beta_mean=-2.0, beta_sd=0.0)
    return SelectionFunction(mdl, draws, meta={"area_arcmin2": AREA, "magnitude_type": magnitude_type},
                             domain={"z": z, "mag": domain_mag}, sed=sed)


def volume(z0=6.0, z1=8.0):
    """Comoving volume of the area between z0 and z1 [Mpc^3]."""
    omega = (AREA * u.arcmin ** 2).to_value(u.sr)
    return ((Planck18.comoving_volume(z1) - Planck18.comoving_volume(z0)).to_value(u.Mpc ** 3)
            * omega / (4 * np.pi))


def one(M, z):
    return np.ones(np.broadcast(M, z).shape)


EDGES = np.round(np.arange(25.0, 28.01, 0.2), 6)


def test_step_selection_without_transfer_counts_the_comoving_volume():
    ec = step_sf().expected_counts(one, EDGES, transfer=False)
    # phi = 1 per Mpc^3 per mag: every M maps one to one onto m at each z, so a bin of
    # 0.2 mag wholly bright of the step holds 0.2 V; the bin holding the step half of it.
    full = EDGES[1:] <= M_LIM
    np.testing.assert_allclose(ec.median[full], 0.2 * volume(), rtol=1e-4)
    k = np.flatnonzero((EDGES[:-1] < M_LIM) & (EDGES[1:] > M_LIM))[0]
    assert ec.median[k] == pytest.approx(0.1 * volume(), rel=2e-3)
    assert np.all(ec.median[EDGES[:-1] >= M_LIM + 0.01] < 1e-6 * volume())
    assert ec.draws.shape == (2, len(EDGES) - 1) and not ec.transfer
    np.testing.assert_array_equal(ec.extrapolated_fraction, 0.0)


def test_volume_and_quadrature_options_reach_the_counts():
    """The grouped options (issue 22): a SurveyVolume of z 6.5-7.5 over twice the fit's area
    counts that volume, and the method's z_min/z_max/area keywords are the same volume."""
    vol = SurveyVolume(z_min=6.5, z_max=7.5, area=2 * AREA)
    quad_grid = Quadrature(n_z=31, n_beta=3, dM=0.1)
    ec = expected_counts(step_sf(), one, EDGES, volume=vol, quadrature=quad_grid,
                         transfer=False)
    full = EDGES[1:] <= M_LIM
    np.testing.assert_allclose(ec.median[full], 0.2 * 2 * volume(6.5, 7.5), rtol=1e-4)
    by_keywords = step_sf().expected_counts(one, EDGES, z_min=6.5, z_max=7.5, area=2 * AREA,
                                            quadrature=quad_grid, transfer=False)
    np.testing.assert_array_equal(by_keywords.median, ec.median)
    with pytest.raises(TypeError):          # options are keyword-only
        expected_counts(step_sf(), one, EDGES, vol)


def test_gaussian_transfer_gives_the_analytic_convolution():
    sf = step_sf()
    sf.transfer_matrix = gauss_matrix(np.arange(23.0, 30.01, 0.5), [6.0, 7.0, 8.0], n_draws=3)
    ec = sf.expected_counts(one, EDGES)
    # phi constant: N_k = V * ∫^{M_LIM} dm p(k | m), the same at every z.
    want = np.array([quad(lambda m: norm.cdf(b, m + 0.15, 0.2) - norm.cdf(a, m + 0.15, 0.2),
                          M_LIM - 12, M_LIM, points=[a - 0.15, b - 0.15], limit=200)[0]
                     for a, b in zip(EDGES[:-1], EDGES[1:])]) * volume()
    bright = EDGES[1:] <= M_LIM - 0.5
    np.testing.assert_allclose(ec.median[bright], want[bright], rtol=2e-4)
    near = (EDGES[1:] > M_LIM - 0.5) & (EDGES[:-1] < M_LIM + 0.2)
    np.testing.assert_allclose(ec.median[near], want[near], rtol=6e-3)
    # Beyond: the tail of the scatter, a few per cent of a small number; everywhere within
    # 0.5 % of a full bin's counts.
    np.testing.assert_allclose(ec.median, want, atol=0.005 * 0.2 * volume())
    assert ec.draws.shape == (2, len(EDGES) - 1)


def test_redshift_evolving_phi_and_absolute_magnitude_fit():
    # phi = (z - 6): the counts weigh the volume by it.
    ec = step_sf().expected_counts(lambda M, z: (z - 6.0) + 0 * M, EDGES, transfer=False,
                                   draws=False)
    omega = (AREA * u.arcmin ** 2).to_value(u.sr)
    want = quad(lambda z: (z - 6.0) * Planck18.differential_comoving_volume(z).to_value(
        u.Mpc ** 3 / u.sr), 6.0, 8.0)[0] * omega * 0.2
    assert ec.median[0] == pytest.approx(want, rel=1e-5) and ec.draws is None
    # An absolute-magnitude fit: P = 1 for M_UV < -19.5; a bin of m_obs holds 0.2 V where
    # every M it maps to at every z is brighter than that (m < 26.7 at z = 6-8, beta = -2).
    sf = step_sf(domain_mag=(-23.0, -17.0), m_lim=-19.5, magnitude_type="absolute")
    ec = sf.expected_counts(one, EDGES, transfer=False)
    full = EDGES[1:] <= 26.7 - 0.2
    np.testing.assert_allclose(ec.median[full], 0.2 * volume(), rtol=1e-4)
    assert np.all(ec.median[EDGES[:-1] > 27.6] < 1e-6 * volume())
    # With a transfer function (read at m = M + K): the same where the scatter (0.15 +- 0.2
    # mag) stays inside the selected range; in all, 0.15 mag of sources more (the shift
    # brings them in across the bright edge, P depending on M only).  Beyond the
    # transfer matrix's rows (m_in < 23) their offsets apply unchanged.
    sf.transfer_matrix = gauss_matrix(np.arange(23.0, 30.01, 0.5), [6.0, 7.0, 8.0])
    wide = np.round(np.arange(22.0, 30.01, 0.2), 6)
    with pytest.warns(UserWarning, match="outside the simulated range"):   # M_UV < -23
        et = sf.expected_counts(one, wide)
    with pytest.warns(UserWarning, match="outside the simulated range"):
        eb = sf.expected_counts(one, wide, transfer=False)
    inner = (wide[:-1] >= 25.0) & (wide[1:] <= 25.6)
    np.testing.assert_allclose(et.median[inner], 0.2 * volume(), rtol=2e-3)
    assert et.median.sum() == pytest.approx(eb.median.sum() + 0.15 * volume(), rel=1e-3)


def test_magnitudes_outside_the_simulated_range_are_flagged_not_zeroed():
    sf = step_sf(domain_mag=(23.0, 27.2))          # the step at 27.5 lies beyond the box
    with pytest.warns(UserWarning, match="outside the simulated range"):
        ec = sf.expected_counts(one, EDGES, transfer=False)
    k = np.flatnonzero(EDGES[:-1] >= 27.2 - 1e-9)[0]
    # (by M cell centre: the cell straddling 27.2 counts as inside)
    assert ec.extrapolated_fraction[k] == pytest.approx(1.0, abs=0.05)
    assert ec.median[k] == pytest.approx(0.2 * volume(), rel=1e-4)     # the surface, not 0
    assert np.all(ec.extrapolated_fraction[EDGES[1:] <= 27.0 + 1e-9] == 0)
    assert ec.extrapolated_fraction[k - 1] < 0.05


def test_bad_inputs_are_refused():
    sf = step_sf()
    with pytest.raises(ValueError, match="no transfer matrix"):
        sf.expected_counts(one, EDGES)
    with pytest.raises(ValueError, match="increasing"):
        sf.expected_counts(one, EDGES[::-1], transfer=False)
    nosed = step_sf()
    nosed.sed = None
    with pytest.raises(ValueError, match="no injection SED"):
        nosed.expected_counts(one, EDGES, transfer=False)


def _dropout_sf(z_top, sed):
    """P = 1 bright of 27.5 from z ~ 9.3 up to z_top (S rises at the low end, flat at the top)."""
    mdl = SurfaceModel(shape="logistic", z_ref=0.5 * (9.0 + z_top), z_scale=0.5 * (z_top - 9.0),
                       m_ref=27.0, m_scale=2.0, m50_degree=0, log_w_degree=0, edge_degree=0,
                       c_max_degree=0)
    th = dict(logit_c_max_0=40.0, m50_0=27.5, log_w_0=np.log(0.2), logit_s_max=40.0,
              eta_lo_0=-8.0, log_dz_lo_0=np.log(0.05), eta_hi_0=40.0, log_dz_hi_0=0.0)
    draws = np.tile([th[n] for n in mdl.param_names], (2, 1))
    return SelectionFunction(mdl, draws, meta={"area_arcmin2": 1.0}, sed=sed,
                             domain={"z": (9.0, z_top), "mag": (25.0, 30.0)})


def test_z_edge_warning_is_silent_at_the_detection_bands_flux_limit():
    sed = InjectionSED(get_filter("wfc3_ir_f098m"), -2.0, 0.0)
    z_lim = _dropout_sf(10.0, sed).detection_z_limit
    # F098M receives no flux of a beta = -2 source from z ~ 13 (the Lyman limit leaves it).
    assert 12.5 < z_lim < 13.5
    with pytest.warns(UserWarning, match="at an end of the simulated z range"):
        _dropout_sf(11.0, sed).effective_volume(np.array([26.0]))       # the top cuts volume
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _dropout_sf(z_lim, sed).effective_volume(np.array([26.0]))     # nothing beyond it
        _dropout_sf(z_lim - 0.05, sed).effective_volume(np.array([26.0]))
    # The limit recorded in the metadata (as the run's manifest has it) is used as is.
    sf = _dropout_sf(11.0, sed)
    sf.meta["detection_z_limit"] = 11.05
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sf.effective_volume(np.array([26.0]))
