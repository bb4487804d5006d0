"""The mock universe of the closure test (glaciar.demo.mock): numbers, fluxes, shot noise."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy import integrate, stats

from glaciar.demo import mock

ARCMIN2_SR = (math.pi / 10800.0) ** 2
LF = mock.Schechter(log_phi_star=-2.5, M_star=-20.5, alpha=-2.0)
Z_RANGE = (8.0, 8.3)          # narrow: few band tables to compute (each ~15 ms per band)
M_RANGE = (-22.5, -19.0)


def _phi(M):
    """Schechter phi(M), written out here independently of glaciar.demo.mock."""
    x = 10 ** (-0.4 * (M - LF.M_star))
    return 0.4 * math.log(10) * 10 ** LF.log_phi_star * x ** (LF.alpha + 1) * math.exp(-x)


def _dvdz(z):
    from astropy.cosmology import Planck18
    import astropy.units as u

    return Planck18.differential_comoving_volume(z).to_value(u.Mpc ** 3 / u.sr)


@pytest.fixture(scope="module")
def cfg(tmp_path_factory):
    from glaciar.config import load_config

    d = tmp_path_factory.mktemp("mock_survey")
    return load_config(mock.build_mock_survey(d, n_fields=1, shape=(128, 128), seed=5,
                                              n_stars=0, source_density_arcmin2=0.0))


def test_expected_number_matches_quad():
    area = 3.7
    v = integrate.quad(_dvdz, *Z_RANGE, epsrel=1e-10)[0]
    n = integrate.quad(_phi, *M_RANGE, epsrel=1e-10)[0]
    want = area * ARCMIN2_SR * v * n
    got = mock.expected_number(LF, Z_RANGE, M_RANGE, area)
    assert got == pytest.approx(want, rel=1e-6)
    assert mock.comoving_volume_arcmin2(Z_RANGE) == pytest.approx(v * ARCMIN2_SR, rel=1e-6)


def test_drawn_population_number_and_distributions(cfg):
    area = {"a": 24.0, "b": 12.0}
    rng = np.random.default_rng(11)
    t = mock.draw_mock_population(rng, LF, Z_RANGE, M_RANGE, area, cfg, pixel_scale_arcsec=0.08)
    v = integrate.quad(_dvdz, *Z_RANGE, epsrel=1e-10)[0]
    n = integrate.quad(_phi, *M_RANGE, epsrel=1e-10)[0]
    for f, a in area.items():
        mu = a * ARCMIN2_SR * v * n
        assert t.attrs["n_expected"][f] == pytest.approx(mu, rel=1e-6)
        k = int((t["field"] == f).sum())
        assert abs(k - mu) < 4.5 * math.sqrt(mu), (f, k, mu)
    assert len(t) > 100
    # z ~ dV/dz and M ~ phi(M): KS against CDFs integrated by quad.
    zcdf = np.vectorize(lambda z: integrate.quad(_dvdz, Z_RANGE[0], z)[0] / v)
    mcdf = np.vectorize(lambda M: integrate.quad(_phi, M_RANGE[0], M)[0] / n)
    assert stats.kstest(t["z"], zcdf).pvalue > 1e-3
    assert stats.kstest(t["M_uv"], mcdf).pvalue > 1e-3
    # The injections' population model: beta ~ N(-2.2, 0.4), n in {1, 4}, sizes on the lattice.
    assert abs(t["beta"].mean() + 2.2) < 5 * 0.4 / math.sqrt(len(t))
    assert set(np.unique(t["sersic_n"])) <= {1.0, 4.0}
    assert np.allclose(t["r_eff_arcsec"], t["r_eff_pix"] * 0.08)
    # M_UV -> the detection band: m = M + DM - 2.5 log(1 + z) + colour (F160W at z ~ 8: ~0).
    from astropy.cosmology import Planck18
    dm = Planck18.distmod(t["z"].to_numpy()).value - 2.5 * np.log10(1 + t["z"].to_numpy())
    assert np.all(np.abs(t["mag_in_f160w"] - t["M_uv"] - dm) < 0.3)
    assert np.all(np.isinf(t["mag_in_f606w"]))          # blueward of the break: no flux


def _stamp_sources(n=3):
    return pd.DataFrame({"x": [40.3, 90.0, 61.7][:n], "y": [50.2, 70.6, 100.1][:n],
                         "sersic_n": [1.0, 4.0, 1.0][:n], "axis_ratio": [1.0, 0.6, 0.8][:n],
                         "position_angle_deg": [0.0, 30.0, 120.0][:n],
                         "r_eff_pix": [2.0, 1.5, 3.0][:n], "mag_in_h": [22.0, 23.0, 22.5][:n]})


def _cache():
    from glaciar.galaxy.psf import moffat_psf
    from glaciar.galaxy.templates import TemplateCache

    return TemplateCache({"h": moffat_psf(0.2, 0.08, beta=2.5, size=41)})


def test_render_sources_adds_the_rendered_flux():
    cache, src, zp = _cache(), _stamp_sources(), 25.0
    base = np.random.default_rng(0).normal(0, 1e-3, (160, 160))
    img, added = mock.render_sources(base, cache, "h", src, zp, None, np.random.default_rng(1))
    flux = 10 ** (-0.4 * (src["mag_in_h"].to_numpy() - zp))
    frac = np.array([cache.stamp("h", *r).in_stamp_fraction for r in
                     src[["sersic_n", "axis_ratio", "position_angle_deg", "r_eff_pix", "x", "y"]]
                     .itertuples(index=False)])
    assert np.allclose(added, flux * frac, rtol=1e-12)
    assert (img - base).sum() == pytest.approx(added.sum(), rel=1e-12)
    assert np.all(base == np.random.default_rng(0).normal(0, 1e-3, (160, 160)))   # not modified
    # A huge gain: the same to shot-noise precision.
    img2, added2 = mock.render_sources(base, cache, "h", src, zp, 1e9, np.random.default_rng(2))
    assert np.array_equal(added2, added)
    assert (img2 - base).sum() == pytest.approx(added.sum(), abs=5 * math.sqrt(added.sum() / 1e9))
    # Pixels without data receive nothing.
    valid = np.ones(base.shape, bool)
    valid[:, :60] = False
    img3, added3 = mock.render_sources(base, cache, "h", src, zp, None, np.random.default_rng(1),
                                       valid=valid)
    assert np.all(img3[:, :60] == base[:, :60])
    assert added3[0] < 1e-3 * added[0] and 0.99 * added[1] < added3[1] < added[1]


def test_shot_noise_variance_is_flux_over_gain():
    cache, zp, gain = _cache(), 25.0, 20.0
    src = _stamp_sources(1).assign(mag_in_h=20.0, r_eff_pix=6.0)
    model, _ = mock.render_sources(np.zeros((160, 160)), cache, "h", src, zp, None, None)
    dev = np.concatenate([
        (mock.render_sources(np.zeros((160, 160)), cache, "h", src, zp, gain,
                             np.random.default_rng(s))[0] - model).ravel() for s in range(4)])
    m = np.tile(model.ravel(), 4)
    use = m > 0.05                         # >= 1 electron expected: variance = mean
    chi2 = np.sum(dev[use] ** 2 / (m[use] / gain))
    k = int(use.sum())
    assert k > 1500
    assert abs(chi2 - k) < 5 * math.sqrt(2 * k), (chi2, k)
    assert abs(dev[use].sum()) < 5 * math.sqrt(m[use].sum() / gain)


def test_render_mock_universe_writes_images_and_truth(cfg, tmp_path):
    from astropy.io import fits

    from glaciar.survey import Survey

    cfg_path = cfg.path if getattr(cfg, "path", None) else None
    cfg_path = cfg_path or next(iter(cfg.base_dir.glob("mock.yaml")))
    survey = Survey.from_config(cfg)
    field = survey.fields[0]
    before = {b: fits.getdata(survey.science_path(field, b)).astype(float) for b in survey.bands}
    truth = mock.draw_mock_population(np.random.default_rng(3), LF, Z_RANGE, (-22.5, -21.5),
                                      {field: 0.0}, cfg, pixel_scale_arcsec=0.08)
    # Two bright galaxies placed by hand, well inside the 128^2 footprint.
    rows = mock.draw_mock_population(np.random.default_rng(4), LF, Z_RANGE, (-22.5, -21.5),
                                     {field: 400.0}, cfg, pixel_scale_arcsec=0.08).iloc[:2]
    assert len(truth) == 0 and len(rows) == 2
    rows = rows.assign(x=[45.0, 80.0], y=[50.0, 75.0])
    out = mock.render_mock_universe(cfg_path, rows, seed=9, truth_path=tmp_path / "t.parquet")
    got = mock.read_truth(out)
    assert got.attrs["seed"] == 9 and len(got) == 2
    for b in survey.bands:
        after = fits.getdata(survey.science_path(field, b)).astype(float)
        gain = cfg.survey.band(b).gain
        diff = (after - before[b]).sum()
        want = got[f"flux_added_{b}"].sum()
        # float32 images: rounding of ~1e4 pixels adds ~1e-7 relative of the pixel values.
        tol = 5 * math.sqrt(max(want, 0) / gain) + 1e-4
        assert abs(diff - want) < tol, (b, diff, want)
        assert np.all(got[f"flux_added_{b}"] <= got[f"flux_in_{b}"] * (1 + 1e-12))
        assert fits.getheader(survey.science_path(field, b))["MOCKSEED"] == 9
    with pytest.raises(ValueError, match="already holds a mock universe"):
        mock.render_mock_universe(cfg_path, rows, seed=10, truth_path=tmp_path / "t2.parquet")


def test_redshift_lattice(cfg):
    """z_step: redshifts on the lattice, each cell with its comoving volume's probability."""
    rng = np.random.default_rng(5)
    t = mock.draw_mock_population(rng, LF, (8.0, 8.05), M_RANGE, {"a": 400.0}, cfg,
                                  pixel_scale_arcsec=0.08, z_step=0.01)
    z = t["z"].to_numpy()
    assert np.all(np.abs(z * 100 - np.round(z * 100)) < 1e-9)
    nodes = np.round(np.arange(8.0, 8.0501, 0.01), 10)
    assert set(np.unique(z)) <= set(nodes)
    # Cell k holds [z_k - 0.005, z_k + 0.005] (half cells at the ends).
    edges = np.clip(np.r_[nodes - 0.005, nodes[-1] + 0.005], 8.0, 8.05)
    p = np.array([integrate.quad(_dvdz, a, b)[0] for a, b in zip(edges[:-1], edges[1:])])
    p /= p.sum()
    k = np.array([(z == v).sum() for v in nodes])
    assert stats.chisquare(k, p * k.sum()).pvalue > 1e-3
