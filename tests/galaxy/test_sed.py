"""Band magnitudes of UV power laws: normalisations, colours, speed, edge cases."""
from __future__ import annotations

import time
import warnings

import numpy as np
import pytest
from hypothesis import given, strategies as st

from glaciar.constants import AB_ZEROPOINT_FNU, C_ANGSTROM_PER_S, FAINT_MAG_LIMIT, UV_REST_ANGSTROM
from glaciar.galaxy.filters import Filter, ab_magnitude, builtin_filter_names, get_filter
from glaciar.galaxy.igm import IGM_MODELS, igm_transmission
from glaciar.galaxy.population import Z_MIN_DISTANCE
from glaciar.galaxy.sed import (_BETA_GRID, _band_table, absolute_magnitude, band_magnitudes,
                                bands_to_skip, flux_to_mag, mag_to_flux, uv_flambda)

from renderer_box import (BANDS, FAINT_EDGE_MAG, PROPERTY_SETTINGS, ZEROPOINT, beta, distance_term,
                          mag_tol, magnitude, redshift, ref_colour)

HST = ["wfc3_uvis_f606w", "wfc3_ir_f098m", "wfc3_ir_f105w", "wfc3_ir_f125w", "wfc3_ir_f140w",
       "wfc3_ir_f160w"]
JWST = ["nircam_f090w", "nircam_f115w", "nircam_f150w", "nircam_f200w", "nircam_f277w",
        "nircam_f444w"]
ALL_BUILTIN = [n for n in builtin_filter_names() if n != "wfc3_uvis_f600lp"]


def _reference_mags(z, beta, filters, m_1600, igm="inoue14"):
    """Independent path: an explicit f_lambda on a fine grid, normalised so that
    f_nu at rest 1600 A has AB magnitude m_1600, integrated by ab_magnitude.
    Nodes are placed either side of the Lyman alpha-delta and Lyman-limit
    onsets so the trapezoid rule does not straddle the IGM's jumps."""
    lam_ref = UV_REST_ANGSTROM * (1 + z)
    wave = np.exp(np.arange(np.log(5000.0), np.log(53000.0), 2e-5))
    edges = np.array([1215.67, 1025.72, 972.537, 949.743, 911.8]) * (1 + z)
    wave = np.union1d(wave, np.concatenate([edges * (1 - 1e-9), edges * (1 + 1e-9)]))
    fnu_ref = 10 ** (-0.4 * (m_1600 - AB_ZEROPOINT_FNU))
    flam = (fnu_ref * C_ANGSTROM_PER_S / lam_ref**2 * (wave / lam_ref) ** beta
            * igm_transmission(wave, z, igm))
    return np.array([ab_magnitude(wave, flam, f) for f in filters])


def _distance_modulus(z, cosmo):
    # independent of astropy's distmod: from the luminosity distance
    return 5 * np.log10(cosmo.luminosity_distance(z).to_value("pc") / 10.0)


def test_flat_fnu_equal_magnitudes_in_all_bands():
    """beta = -2 is flat in f_nu: with no IGM effect in any band (z = 0.5, all
    bands redward of 1.5 x 1216 A) every band has the same AB magnitude."""
    mags = band_magnitudes(0.5, -2.0, ALL_BUILTIN, mag=25.0, detection_index=0)
    np.testing.assert_allclose(mags, 25.0, atol=1e-4, rtol=0)
    mags = band_magnitudes(0.5, [-2.0, -2.0], ALL_BUILTIN, M_uv=-20.0, cosmology="Planck18")
    assert np.ptp(mags) < 1e-4


@pytest.mark.parametrize("z", [6.0, 9.0, 12.0])
def test_detection_magnitude_reproduced(z):
    """The spectrum band_magnitudes describes, rebuilt explicitly from the
    M_UV it implies, has the requested apparent magnitude in the detection
    band (to 1e-4 mag) and the returned magnitudes in every other band."""
    from astropy.cosmology import Planck18

    filters = HST + JWST
    det = filters.index("wfc3_ir_f160w") if z < 10 else filters.index("nircam_f200w")
    betas = np.array([-3.0, -2.2, -1.0])
    mags = band_magnitudes(z, betas, filters, mag=26.3, detection_index=det)
    np.testing.assert_allclose(mags[:, det], 26.3, atol=1e-12, rtol=0)
    M_uv = absolute_magnitude(26.3, z, betas, filters[det])
    for k, beta in enumerate(betas):
        m_1600 = M_uv[k] + _distance_modulus(z, Planck18) - 2.5 * np.log10(1 + z)
        ref = _reference_mags(z, beta, filters, m_1600)
        assert abs(ref[det] - 26.3) < 1e-4
        ok = ref < 40          # bands with non-negligible flux
        assert ok.sum() >= 4
        np.testing.assert_allclose(mags[k, ok], ref[ok], atol=1e-4, rtol=0)
        assert np.all(np.isinf(mags[k, ~ok]) | (mags[k, ~ok] > 39))


@pytest.mark.parametrize("cosmo_name", ["Planck18", "WMAP9"])
def test_absolute_normalisation_against_astropy(cosmo_name):
    """M_UV normalisation: m at observed 1600 (1+z) A equals M + DM - 2.5 log(1+z),
    with DM from astropy's luminosity distance, to 1e-4 mag in every band."""
    from astropy.cosmology import realizations

    cosmo = getattr(realizations, cosmo_name)
    z, M_uv = 7.5, np.array([-21.0, -19.3])
    betas = np.array([-2.5, -1.7])
    mags = band_magnitudes(z, betas, HST + JWST, M_uv=M_uv, cosmology=cosmo_name)
    for k in range(2):
        m_1600 = M_uv[k] + _distance_modulus(z, cosmo) - 2.5 * np.log10(1 + z)
        ref = _reference_mags(z, betas[k], HST + JWST, m_1600)
        ok = ref < 40
        np.testing.assert_allclose(mags[k, ok], ref[ok], atol=1e-4, rtol=0)
    # a cosmology object is accepted too
    np.testing.assert_array_equal(band_magnitudes(z, betas, HST, M_uv=M_uv, cosmology=cosmo),
                                  mags[:, :len(HST)])


def test_absolute_magnitude_inverts_band_magnitudes():
    betas = np.linspace(-3, -1, 7)
    mags = band_magnitudes(8.0, betas, HST, mag=27.0, detection_index=5)
    M = absolute_magnitude(27.0, 8.0, betas, "f160w")
    np.testing.assert_allclose(band_magnitudes(8.0, betas, HST, M_uv=M), mags, atol=1e-10)
    assert isinstance(absolute_magnitude(27.0, 8.0, -2.0, "f160w"), float)


def test_beta_colour_for_narrow_bands():
    """m1 - m2 = -2.5 (beta + 2) log10(lam1 / lam2) for narrow bands (here 1 %-wide
    top hats, where the pivot-wavelength approximation is good to < 1e-3 mag)."""
    def tophat(name, centre):
        w = np.linspace(centre * 0.99, centre * 1.01, 201)
        t = np.ones_like(w)
        t[[0, -1]] = 0.0
        return Filter(name, w, t)

    f1, f2 = tophat("n1", 12000.0), tophat("n2", 20000.0)
    betas = np.array([-3.0, -2.2, -2.0, -1.0, 0.5])
    mags = band_magnitudes(3.0, betas, [f1, f2], mag=25.0, detection_index=1)
    expected = -2.5 * (betas + 2) * np.log10(f1.pivot_wavelength_angstrom
                                            / f2.pivot_wavelength_angstrom)
    np.testing.assert_allclose(mags[:, 0] - mags[:, 1], expected, atol=1e-3, rtol=0)


def test_beta_interpolation_accuracy():
    """The cubic-Hermite table in beta matches direct summation to 1e-6 mag,
    and beta outside the table is summed directly."""
    rng = np.random.default_rng(3)
    beta = np.concatenate([rng.uniform(_BETA_GRID[0], _BETA_GRID[-1], 400), [-12.0, 7.5]])
    for name, z in [("wfc3_ir_f140w", 11.0), ("wfc3_uvis_f606w", 4.0), ("nircam_f115w", 9.2)]:
        table = _band_table(z, get_filter(name), "inoue14")
        a = beta[:, None] * table.x[None, :] + table.log_u[None, :]
        amax = a.max(axis=1)
        direct = -2.5 / np.log(10) * (np.log(np.exp(a - amax[:, None]).sum(axis=1)) + amax
                                      - table.log_norm)
        np.testing.assert_allclose(table.colour(beta), direct, atol=1e-6, rtol=0)


def test_scalar_and_array_inputs_broadcast():
    one = band_magnitudes(9.0, -2.2, HST, mag=26.0, detection_index=5)
    assert one.shape == (1, len(HST))
    many = band_magnitudes(9.0, [-2.2] * 4, HST, mag=[26.0, 26.0, 27.0, 28.0], detection_index=5)
    assert many.shape == (4, len(HST))
    np.testing.assert_allclose(many[0], one[0])
    np.testing.assert_allclose(many[3, 1:] - many[0, 1:], 2.0, atol=1e-12)
    assert np.isinf(many[3, 0])         # F606W is blueward of the break at z = 9
    # negative detection index counts from the end
    np.testing.assert_array_equal(band_magnitudes(9.0, -2.2, HST, mag=26.0, detection_index=-1), one)


def test_zero_flux_bands_and_faint_limit():
    # z = 9: F606W is entirely blueward of the break
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mags = band_magnitudes(9.0, [-2.0, -2.5], HST, mag=26.0, detection_index=5, igm="sharp")
    assert np.all(np.isinf(mags[:, 0]))
    mags = band_magnitudes(9.0, [-2.0], HST, mag=26.0, detection_index=5, faint_limit=None)
    assert 50 < mags[0, 0] < np.inf          # Inoue+14 leaves a trace of flux
    assert np.isinf(band_magnitudes(9.0, [-2.0], HST, mag=26.0, detection_index=5)[0, 0])
    skip = bands_to_skip(mags)
    np.testing.assert_array_equal(skip[0], [True, False, False, False, False, False])
    np.testing.assert_array_equal(bands_to_skip([[np.inf, np.nan, 49.9, 50.0]]),
                                  [[True, True, False, True]])


def test_errors():
    with pytest.raises(ValueError, match="receives no flux"):
        band_magnitudes(13.5, -2.0, HST, mag=26.0, detection_index=5, igm="sharp")
    with pytest.raises(ValueError, match="exactly one"):
        band_magnitudes(9.0, -2.0, HST)
    with pytest.raises(ValueError, match="exactly one"):
        band_magnitudes(9.0, -2.0, HST, mag=26.0, detection_index=0, M_uv=-20)
    with pytest.raises(ValueError, match="detection_index"):
        band_magnitudes(9.0, -2.0, HST, mag=26.0)
    with pytest.raises(ValueError, match="out of range"):
        band_magnitudes(9.0, -2.0, HST, mag=26.0, detection_index=6)
    with pytest.raises(ValueError, match="unknown IGM"):
        band_magnitudes(9.0, -2.0, HST, mag=26.0, detection_index=5, igm="foo")
    with pytest.raises(ValueError, match="z > 0"):
        band_magnitudes(0.0, -2.0, HST, M_uv=-20.0)


def test_speed_thousands_of_sources_per_millisecond():
    betas = np.random.default_rng(0).normal(-2.2, 0.4, 20000)
    band_magnitudes(9.4, betas[:2], HST, mag=26.0, detection_index=5)      # builds the tables
    t0 = time.perf_counter()
    band_magnitudes(9.4, betas, HST, mag=26.0, detection_index=5)
    elapsed = time.perf_counter() - t0
    assert elapsed < 0.1    # measured ~8 ms for 20 000 sources x 6 bands


def test_uv_flambda():
    z = 7.0
    lam_ref = UV_REST_ANGSTROM * (1 + z)
    f = uv_flambda([lam_ref, 2 * lam_ref], z, [-2.0, -1.0])
    assert f.shape == (2, 2)
    np.testing.assert_allclose(f, [[1.0, 0.25], [1.0, 0.5]])
    wave = np.array([1000.0, 1300.0]) * (1 + z)
    np.testing.assert_allclose(uv_flambda(wave, z, -2.0, igm="sharp"),
                               [0.0, (1300.0 / 1600.0) ** -2])


def test_mag_flux_round_trip():
    mags = np.array([20.0, 25.5, np.inf])
    flux = mag_to_flux(mags, 25.0)
    np.testing.assert_allclose(flux[:2], [10 ** 2, 10 ** -0.2])
    assert flux[2] == 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = flux_to_mag(flux, 25.0)
        assert np.isnan(flux_to_mag(-1.0, 25.0))
    np.testing.assert_allclose(back[:2], mags[:2], rtol=1e-14)
    assert back[2] == np.inf
    assert isinstance(mag_to_flux(25.0, 25.0), float) and mag_to_flux(25.0, 25.0) == 1.0


# ------------------------------------------------------------------------------
# Property-based stress of the source renderer (issue 10, point 8): hypothesis draws over
# the parameter box of tests/renderer_box.py, against its independent references.
#
# Spectra and band magnitudes
# ------------------------------------------------------------------------------
def _check_against_reference(mags, expected, z):
    """Band by band: +inf exactly where the reference is beyond the faint limit,
    else within MAG_TOL, or MAG_TOL_OFF_LATTICE at a z off sed's lattice (bands
    within FAINT_EDGE_MAG of the limit may go either way)."""
    assert not np.any(np.isnan(mags)) and not np.any(np.isneginf(mags))
    clear = np.abs(expected - FAINT_MAG_LIMIT) > FAINT_EDGE_MAG
    np.testing.assert_array_equal(np.isinf(mags)[clear], (expected > FAINT_MAG_LIMIT)[clear])
    ok = clear & (expected < FAINT_MAG_LIMIT)
    np.testing.assert_allclose(mags[ok], expected[ok], atol=mag_tol(z), rtol=0)


@PROPERTY_SETTINGS
@given(z=redshift, b=beta, m=magnitude, det=st.integers(0, len(BANDS) - 1),
       igm=st.sampled_from(IGM_MODELS))
def test_apparent_band_magnitudes(z, b, m, det, igm):
    """Normalised to m in a detection band: that band is exactly m, the others match
    the reference colours, every flux is finite; or the detection band receives no
    flux at this z (< 1e-20 of the 1600 A flux: the faint-limit rule) and the call
    says so."""
    colours = np.array([ref_colour(z, b, band, igm) for band in BANDS])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            mags = band_magnitudes(z, b, BANDS, mag=m, detection_index=det, igm=igm)[0]
        except ValueError as e:
            assert "receives no flux" in str(e)
            assert colours[det] > FAINT_MAG_LIMIT - FAINT_EDGE_MAG
            return
        flux = mag_to_flux(mags, ZEROPOINT)
        m_uv = absolute_magnitude(m, z, b, BANDS[det], igm=igm) if z >= Z_MIN_DISTANCE else None
    assert colours[det] <= FAINT_MAG_LIMIT + FAINT_EDGE_MAG
    assert mags[det] == m
    _check_against_reference(mags, m + colours - colours[det], z)
    assert np.all(np.isfinite(flux)) and np.all(flux >= 0)
    np.testing.assert_array_equal(flux == 0, np.isinf(mags))
    if m_uv is not None:       # the inverse normalisation, through the distance term
        assert np.isfinite(m_uv)
        assert m_uv == pytest.approx(m - colours[det] - distance_term(z), abs=mag_tol(z))


@PROPERTY_SETTINGS
@given(z=redshift, b=beta, m=magnitude, igm=st.sampled_from(IGM_MODELS))
def test_absolute_band_magnitudes(z, b, m, igm):
    """Normalised to M_UV (here m - 47, i.e. -37 ... -7): m_band = M_UV + DM(z) -
    2.5 log10(1+z) + colour; at z = 0 (below Z_MIN_DISTANCE) there is no distance
    and the call says so."""
    M_uv = m - 47.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        if z < Z_MIN_DISTANCE:
            with pytest.raises(ValueError, match="need z > 0"):
                band_magnitudes(z, b, BANDS, M_uv=M_uv, igm=igm)
            return
        mags = band_magnitudes(z, b, BANDS, M_uv=M_uv, igm=igm)[0]
        flux = mag_to_flux(mags, ZEROPOINT)
    colours = np.array([ref_colour(z, b, band, igm) for band in BANDS])
    _check_against_reference(mags, M_uv + distance_term(z) + colours, z)
    assert np.all(np.isfinite(flux)) and np.all(flux >= 0)


def test_draw_spectra_apparent_and_absolute_cells():
    from glaciar.galaxy.population import SourceModel, draw_beta
    from glaciar.galaxy.sed import draw_spectra

    model = SourceModel(beta_mean=-2.0, beta_sd=0.3)
    filters = ["f098m", "f125w", "f160w"]
    beta, mag_in, M_uv = draw_spectra(np.random.default_rng(4), 50, 8.0, 26.5, model, filters,
                                      detection_index=2)
    # The beta law's own draws, from the same stream; the cell's magnitude in the
    # detection band; a Lyman-break colour (F098M lies blue of Lya at z = 8).
    assert np.array_equal(beta, draw_beta(np.random.default_rng(4), 50, model))
    assert mag_in.shape == (50, 3) and np.allclose(mag_in[:, 2], 26.5, atol=1e-9)
    assert np.all(mag_in[:, 0] > mag_in[:, 1] + 1.0)
    # An absolute cell at those M_UV gives back the same magnitudes in every band.
    for k in range(3):
        _, mag_abs, M_abs = draw_spectra(np.random.default_rng(4), 50, 8.0, M_uv[k], model,
                                         filters, detection_index=2, absolute=True)
        assert np.all(M_abs == M_uv[k])
        assert np.allclose(mag_abs[k], mag_in[k], atol=1e-6)
