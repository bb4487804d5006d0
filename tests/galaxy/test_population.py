"""Per-source draws: Sérsic mix, shapes, sizes, UV slopes; model validation."""
from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest
from hypothesis import given, strategies as st
from scipy import stats

from glaciar.galaxy.population import (SourceModel, Z_MIN_DISTANCE, draw_beta, draw_shapes,
                                       get_cosmology, kpc_to_arcsec, r_eff_kpc)

from renderer_box import CHEAP_SETTINGS, magnitude, redshift


def test_defaults_match_config_schema():
    m = SourceModel()
    assert (m.r_eff_kpc_z6, m.size_evolution, m.r_eff_scatter_dex, m.size_luminosity_slope) == \
        (1.075, -1.0, 0.0, 0.0)
    assert m.sersic_indices == (1.0, 4.0) and m.sersic_fractions == (0.5, 0.5)
    assert (m.ellipticity_bins, m.position_angle_bins, m.round_de_vaucouleurs) == (1, 1, False)
    assert (m.beta_mean, m.beta_sd, m.beta_per, m.igm, m.cosmology) == \
        (-2.2, 0.4, "source", "inoue14", "Planck18")
    assert m.stamp_flux_fraction == 0.995


def test_sersic_fractions_respected():
    """Chi-square goodness of fit of the index counts to the fractions."""
    model = SourceModel(sersic_indices=[1.0, 2.5, 4.0], sersic_fractions=[0.2, 0.3, 0.5])
    n = 60000
    shapes = draw_shapes(np.random.default_rng(42), n, model)
    counts = np.array([(shapes["sersic_n"] == v).sum() for v in model.sersic_indices])
    assert counts.sum() == n
    p = stats.chisquare(counts, n * np.array(model.sersic_fractions)).pvalue
    assert p > 1e-3
    # small n: no systematic truncation (GLACiAR's int(N f) would give 0 of a 0.3 class for n=3)
    per_draw = [draw_shapes(np.random.default_rng(s), 3, model)["sersic_n"] for s in range(3000)]
    frac = np.mean([(d == 2.5).mean() for d in per_draw])
    assert abs(frac - 0.3) < 0.02


def test_single_ellipticity_bin_is_round():
    shapes = draw_shapes(np.random.default_rng(1), 500, SourceModel())
    np.testing.assert_array_equal(shapes["axis_ratio"], 1.0)
    np.testing.assert_array_equal(shapes["position_angle_deg"], 0.0)


def test_bins_take_the_specified_values():
    model = SourceModel(ellipticity_bins=4, position_angle_bins=6)
    shapes = draw_shapes(np.random.default_rng(7), 20000, model)
    assert set(np.unique(shapes["axis_ratio"])) == {1.0, 0.75, 0.5, 0.25}
    assert set(np.unique(shapes["position_angle_deg"])) == {0.0, 30.0, 60.0, 90.0, 120.0, 150.0}
    assert np.all((shapes["position_angle_deg"] >= 0) & (shapes["position_angle_deg"] < 180))
    # uniform over the bins
    _, counts = np.unique(shapes["axis_ratio"], return_counts=True)
    assert stats.chisquare(counts).pvalue > 1e-3


def test_round_de_vaucouleurs():
    model = SourceModel(ellipticity_bins=5, position_angle_bins=4, round_de_vaucouleurs=True)
    s = draw_shapes(np.random.default_rng(3), 4000, model)
    dev = s["sersic_n"] == 4.0
    assert 0 < dev.sum() < 4000
    np.testing.assert_array_equal(s["axis_ratio"][dev], 1.0)
    np.testing.assert_array_equal(s["position_angle_deg"][dev], 0.0)
    assert np.any(s["axis_ratio"][~dev] < 1.0)


def test_draws_are_reproducible():
    model = SourceModel(ellipticity_bins=3, position_angle_bins=3)
    a = draw_shapes(np.random.default_rng(99), 50, model)
    b = draw_shapes(np.random.default_rng(99), 50, model)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_size_evolution():
    model = SourceModel(size_evolution=-1.0)
    z = np.array([6.0, 8.0, 10.0, 13.0])
    np.testing.assert_allclose(r_eff_kpc(z, model), 1.075 * 7.0 / (1 + z), rtol=1e-14)
    model = SourceModel(r_eff_kpc_z6=0.8, size_evolution=-1.5)
    np.testing.assert_allclose(r_eff_kpc(9.0, model), 0.8 * (10 / 7) ** -1.5, rtol=1e-14)


def test_size_luminosity_relation():
    model = SourceModel(size_luminosity_slope=0.25)
    M = np.array([-21.0, -18.5])
    r = r_eff_kpc(6.0, model, M_uv=M)
    # 2.5 mag fainter = 10x less luminous -> r smaller by 10^0.25
    np.testing.assert_allclose(r, [1.075, 1.075 * 10 ** -0.25], rtol=1e-14)
    with pytest.raises(ValueError, match="M_uv is required"):
        r_eff_kpc(6.0, model)


def test_size_scatter_width():
    model = SourceModel(r_eff_scatter_dex=0.2)
    rng = np.random.default_rng(5)
    r = r_eff_kpc(np.full(40000, 7.0), model, rng=rng)
    logr = np.log10(r / (1.075 * 7 / 8))
    assert abs(np.std(logr) - 0.2) < 0.005
    assert abs(np.mean(logr)) < 0.005
    with pytest.raises(ValueError, match="rng is required"):
        r_eff_kpc(7.0, model)


def test_kpc_to_arcsec_against_angular_diameter_distance():
    from astropy.cosmology import Planck18, WMAP9

    z = np.array([6.0, 9.0, 12.0])
    for name, cosmo in [("Planck18", Planck18), ("WMAP9", WMAP9)]:
        d_a_kpc = cosmo.angular_diameter_distance(z).to_value("kpc")
        expected = 1.3 / d_a_kpc * (180.0 / np.pi) * 3600.0
        np.testing.assert_allclose(kpc_to_arcsec(1.3, z, name), expected, rtol=1e-10)
        np.testing.assert_allclose(kpc_to_arcsec(1.3, z, cosmo), expected, rtol=1e-10)
    # about 0.18" per kpc at z = 6 in Planck18
    assert 0.17 < kpc_to_arcsec(1.0, 6.0) < 0.19


def test_beta_per_source_and_per_iteration():
    rng = np.random.default_rng(11)
    b = draw_beta(rng, 50000, SourceModel(beta_mean=-2.0, beta_sd=0.3))
    assert abs(b.mean() + 2.0) < 0.01 and abs(b.std() - 0.3) < 0.01
    it = SourceModel(beta_per="iteration")
    draws = [draw_beta(np.random.default_rng(s), 20, it) for s in range(400)]
    for d in draws:
        assert d.shape == (20,) and np.all(d == d[0])
    firsts = np.array([d[0] for d in draws])
    assert abs(firsts.std() - 0.4) < 0.05          # still random between iterations
    np.testing.assert_array_equal(draw_beta(rng, 5, SourceModel(beta_sd=0.0)), -2.2)


@pytest.mark.parametrize("kwargs, field", [
    (dict(sersic_fractions=[0.5, 0.6]), "sersic_fractions"),
    (dict(sersic_fractions=[1.0]), "sersic_fractions"),
    (dict(sersic_indices=[1.0, -4.0]), "sersic_indices"),
    (dict(ellipticity_bins=0), "ellipticity_bins"),
    (dict(position_angle_bins=2.5), "position_angle_bins"),
    (dict(beta_per="galaxy"), "beta_per"),
    (dict(igm="inoue"), "igm"),
    (dict(cosmology="Planck99"), "cosmology"),
    (dict(r_eff_kpc_z6=0.0), "r_eff_kpc_z6"),
    (dict(r_eff_scatter_dex=-0.1), "r_eff_scatter_dex"),
    (dict(beta_sd=-1), "beta_sd"),
    (dict(stamp_flux_fraction=1.0), "stamp_flux_fraction"),
    (dict(round_de_vaucouleurs="yes"), "round_de_vaucouleurs"),
])
def test_validation_names_the_field(kwargs, field):
    with pytest.raises(ValueError, match=f"source.{field}"):
        SourceModel(**kwargs)


def test_from_mapping():
    m = SourceModel.from_mapping({"sersic_indices": [1, 4], "sersic_fractions": [0.7, 0.3],
                                  "ellipticity_bins": 2})
    assert m.sersic_fractions == (0.7, 0.3) and m.ellipticity_bins == 2
    assert isinstance(m.sersic_indices, tuple)
    with pytest.raises(ValueError, match="unknown key.*r_eff"):
        SourceModel.from_mapping({"r_eff": 1.0})
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.beta_mean = 0.0


def test_get_cosmology():
    from astropy.cosmology import Planck18

    assert get_cosmology("Planck18") is Planck18
    assert get_cosmology(None) is Planck18
    assert get_cosmology(Planck18) is Planck18
    with pytest.raises(ValueError, match="Planck18"):
        get_cosmology("planck2018")


# ------------------------------------------------------------------------------
# Property-based stress of the source renderer (issue 10, point 8): hypothesis draws over
# the parameter box of tests/renderer_box.py, against its independent references.
#
# Sizes
# ------------------------------------------------------------------------------
@CHEAP_SETTINGS
@given(z=redshift, m=magnitude, slope=st.floats(-0.5, 0.5), scatter=st.floats(0.0, 0.5),
       seed=st.integers(0, 2**32 - 1))
def test_sizes_are_finite_and_follow_the_angular_diameter_distance(z, m, slope, scatter, seed):
    """r_e [kpc] finite and > 0 at any z in the box; in arcsec r_e / D_A(z)
    (astropy's angular-diameter distance); at z = 0 (below Z_MIN_DISTANCE) there is
    no angular size and kpc_to_arcsec says so."""
    model = SourceModel(size_luminosity_slope=slope, r_eff_scatter_dex=scatter)
    rng = np.random.default_rng(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r_kpc = r_eff_kpc(z, model, M_uv=np.full(3, m - 47.0), rng=rng)
        assert np.all(np.isfinite(r_kpc)) and np.all(r_kpc > 0)
        if z < Z_MIN_DISTANCE:
            with pytest.raises(ValueError, match="z must be > 0"):
                kpc_to_arcsec(r_kpc, z)
            return
        arcsec = kpc_to_arcsec(r_kpc, z)
    d_a_kpc = get_cosmology("Planck18").angular_diameter_distance(z).to_value("kpc")
    np.testing.assert_allclose(arcsec, r_kpc / d_a_kpc * (180 / math.pi * 3600), rtol=1e-9)
