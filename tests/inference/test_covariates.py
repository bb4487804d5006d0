"""Size- and beta-aware selection functions (glaciar.inference.covariates), issue 23 point 2.

Injections with known truth, drawn here: C depends on log r_e (m50 moves 1.5 mag per dex,
bigger is harder) and sizes follow a size-luminosity law with 0.3 dex scatter, as
``source:`` draws them.  The per-source flags are Bernoulli draws of the truth (no
images: the engine's size dependence is not what is tested, the fit's is).
"""
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.special import expit
from scipy.integrate import trapezoid
from scipy.stats import beta as beta_dist
from scipy.stats import chi2

from glaciar.inference import (BetaDistribution, SelectionFunction, SizeRelation, SurfaceModel,
                               aggregate_cells, fit_surfaces)
from glaciar.inference.covariates import fit_covariate_nodes, hat_weights

AREA = 100.0
ZS = np.array([7.0, 8.0, 9.0])
MS = np.arange(-21.0, -17.0 + 1e-9, 0.25)
WIDE = SizeRelation(r_eff_kpc_z6=0.8, size_evolution=-1.0, size_luminosity_slope=0.25,
                    r_eff_scatter_dex=0.3)
NARROW = SizeRelation(r_eff_kpc_z6=0.8, size_evolution=-1.0, size_luminosity_slope=0.25,
                      r_eff_scatter_dex=0.1)
STEPS = 400


def truth_c(M, z, logr):
    return 0.95 * expit(-(M - (-19.0 - 1.5 * (logr - np.log10(0.12)))) / 0.25)


def truth_s(z, M):
    return 0.9 * expit((z - 7.4) / 0.1) * expit((8.6 - z) / 0.1)


def injections(law, n_per, seed):
    rng = np.random.default_rng(seed)
    z, M = [a.ravel() for a in np.meshgrid(ZS, MS, indexing="ij")]
    z, M = np.repeat(z, n_per), np.repeat(M, n_per)
    logr = law.log_r_arcsec(M, z) + law.r_eff_scatter_dex * rng.standard_normal(z.size)
    rec = rng.random(z.size) < truth_c(M, z, logr)
    sel = rec & (rng.random(z.size) < truth_s(z, M))
    return pd.DataFrame({"z": z, "M_uv": M, "mag": M, "recovered": rec, "selected": sel,
                         "r_eff_arcsec": 10 ** logr})


def pooled(df, seed):
    cells = aggregate_cells(df, 0.01, None, "M_uv")
    mdl = SurfaceModel.for_data(cells.z, cells.mag, shape="logistic")
    res = fit_surfaces(cells, mdl, seed=seed, max_steps=STEPS)
    return SelectionFunction(mdl, res.draws(400), meta={"area_arcmin2": AREA,
                                                         "magnitude_type": "absolute"},
                             domain={"z": (ZS[0], ZS[-1]), "mag": (MS[0], MS[-1])})


@pytest.fixture(scope="module")
def fits():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")            # short chains: ConvergenceWarning
        wide = injections(WIDE, 50, 1)
        sf = pooled(wide, 0)
        sf.covariates = {"r_eff": fit_covariate_nodes(
            wide, "r_eff", sf.model, n_bins=4, max_draws=400, mag_col="M_uv",
            fit=lambda c, m, s: fit_surfaces(c, m, seed=s, max_steps=STEPS))}
        narrow = pooled(injections(NARROW, 50, 2), 1)
    return wide, sf, narrow


def test_completeness_given_size_matches_binned_fractions_per_size_bin(fits):
    wide, sf, _ = fits
    x = np.log10(wide["r_eff_arcsec"].to_numpy())
    q = np.quantile(x, [0, 0.25, 0.5, 0.75, 1])
    k = np.clip(np.searchsorted(q, x, side="right") - 1, 0, 3)
    z, M, rec = wide["z"].to_numpy(), wide["M_uv"].to_numpy(), wide["recovered"].to_numpy()
    c_src = sf.completeness(M, z, r_eff_arcsec=wide["r_eff_arcsec"].to_numpy())
    c_pool = sf.completeness(M, z)

    def chi2_p(c):                                     # per size bin, over the magnitudes (z pooled)
        out = []
        for b in range(4):
            x2 = 0.0
            for Mi in MS:
                i = (k == b) & (M == Mi)
                kk, nn, pp = rec[i].sum(), i.sum(), np.clip(c[i].mean(), 1e-3, 1 - 1e-3)
                x2 += (kk - nn * pp) ** 2 / (nn * pp * (1 - pp))
            out.append(chi2.sf(x2, len(MS)))
        return np.array(out)

    # The size-aware C reproduces the binned fractions of every size bin (measured: p = 0.39,
    # 1.0, 0.34, 0.94); the pooled C (marginalised over the injected sizes) misses the small
    # and the large bins (p = 1e-28, 0.03, 8e-5, 8e-16).
    assert np.all(chi2_p(c_src) > 0.01), chi2_p(c_src)
    assert np.min(chi2_p(c_pool)) < 1e-6, chi2_p(c_pool)
    assert sf.covariates["r_eff"].adequate.all()


def test_completeness_at_the_nodes_follows_the_truth(fits):
    _, sf, _ = fits
    nodes = sf.covariates["r_eff"]
    inside = []
    for x in nodes.centres:
        M = -19.0 - 1.5 * (x - np.log10(0.12))                # the true m50 at this size
        c = sf.completeness(M, 8.0, r_eff_arcsec=10 ** x, draws=True)
        lo, hi = np.quantile(c, [0.005, 0.995])
        inside.append(lo <= truth_c(M, 8.0, x) <= hi)
    # each node's C is that of its mean size (not of the bin's mixture of sizes); one of
    # four 99 % intervals may miss by chance (the bins have ~640 sources over 17 magnitudes)
    assert sum(inside) >= 3, inside


def test_size_aware_c_averaged_over_the_injected_sizes_gives_the_binned_fraction(fits):
    wide, sf, _ = fits
    z, M = wide["z"].to_numpy(), wide["M_uv"].to_numpy()
    r, rec = wide["r_eff_arcsec"].to_numpy(), wide["recovered"].to_numpy()
    for Mi in (-19.5, -19.0, -18.5):
        i = (M == Mi) & (z == 8.0)
        avg = np.mean(sf.completeness(M[i], 8.0, r_eff_arcsec=r[i]))
        lo, hi = beta_dist.ppf([0.003, 0.997], rec[i].sum() + 1, (~rec[i]).sum() + 1)
        assert lo <= avg <= hi


def test_reweighted_veff_matches_a_run_injected_with_the_narrower_law(fits):
    _, sf, narrow = fits
    M = np.array([-19.5, -19.0, -18.5, -18.0, -17.75])
    rw = sf.effective_volume(M, size_relation=NARROW)
    ref = narrow.effective_volume(M)
    plain = sf.effective_volume(M)
    half = 0.5 * (ref.upper - ref.lower)
    assert np.all(np.abs(rw.median - ref.median) <= half + 0.5 * (rw.upper - rw.lower)), \
        (rw.median, ref.median, half)
    # the re-weighting matters: at the faint end the injected (wider) law's V_eff is
    # several times the narrow run's, far outside its interval
    assert plain.median[-1] > ref.upper[-1] + 2 * half[-1], (plain.median, ref.median, half)


def test_reweighting_outside_the_injected_sizes_warns(fits):
    _, sf, _ = fits
    far = SizeRelation(r_eff_kpc_z6=40.0, r_eff_scatter_dex=0.1, size_luminosity_slope=0.25)
    with pytest.warns(UserWarning, match="outside the injected range"):
        sf.effective_volume([-19.0], size_relation=far, n_z=101)


def test_outside_the_injected_sizes_is_nan_and_unfitted_covariates_are_refused(fits):
    _, sf, _ = fits
    lo, hi = sf.covariates["r_eff"].covered
    assert np.isnan(sf.completeness(-19.0, 8.0, r_eff_arcsec=10 ** (hi + 0.1)))
    assert np.isfinite(sf.completeness(-19.0, 8.0, r_eff_arcsec=10 ** (hi + 0.1),
                                       outside="extrapolate"))
    with pytest.raises(ValueError, match="without the 'beta' covariate"):
        sf.selection_probability(8.0, -19.0, beta=-2.0)
    with pytest.raises(ValueError, match="beta"):
        sf.effective_volume([-19.0], beta_distribution=BetaDistribution(-2.0, 0.3))


def test_file_round_trip_keeps_the_covariates(fits, tmp_path):
    _, sf, narrow = fits
    sf.write(tmp_path / "sf.fits")
    back = SelectionFunction.read(tmp_path / "sf.fits")
    r = np.array([0.05, 0.1, 0.2])
    np.testing.assert_array_equal(back.completeness(-19.0, 8.0, r_eff_arcsec=r, draws=True),
                                  sf.completeness(-19.0, 8.0, r_eff_arcsec=r, draws=True))
    np.testing.assert_array_equal(back.covariates["r_eff"].edges, sf.covariates["r_eff"].edges)
    from astropy.io import fits as afits
    with afits.open(tmp_path / "sf.fits") as h:
        assert h["CV_R_EFF", 1].header["COVCOL"] == "r_eff_arcsec"
        assert h["CV_R_EFF", 1].header["COVMIN"] == pytest.approx(sf.covariates["r_eff"].covered[0])
    # a file without covariates has no CV_* extension and reads with none
    narrow.write(tmp_path / "plain.fits")
    with afits.open(tmp_path / "plain.fits") as h:
        assert not any(x.name.startswith("CV_") for x in h)
    assert SelectionFunction.read(tmp_path / "plain.fits").covariates == {}


def test_a_run_of_one_size_is_refused():
    df = injections(WIDE, 2, 5)
    df["r_eff_arcsec"] = 0.1
    mdl = SurfaceModel.for_data(df["z"], df["M_uv"])
    with pytest.raises(ValueError, match="span no range of r_eff_arcsec.*r_eff_scatter_dex"):
        fit_covariate_nodes(df, "r_eff", mdl, mag_col="M_uv")


def test_hat_weights_integrate_piecewise_linear_functions_exactly():
    nodes = np.linspace(-1.5, -0.5, 9)
    f = np.sin(3 * nodes)                      # the piecewise-linear interpolant of these values
    xs = np.linspace(-4, 3, 200001)
    for mu, sd in ((-1.0, 0.2), (-1.4, 0.05), (-0.3, 0.3), (-1.0, 0.0)):
        w, out = hat_weights(nodes, mu, sd)
        assert w.sum() == pytest.approx(1.0)
        if sd == 0:
            assert w @ f == pytest.approx(np.interp(mu, nodes, f))
            continue
        pdf = np.exp(-0.5 * ((xs - mu) / sd) ** 2) / (sd * np.sqrt(2 * np.pi))
        ref = trapezoid(np.interp(xs, nodes, f) * pdf, xs)   # np.interp clamps like the end nodes
        assert w @ f == pytest.approx(ref, abs=1e-6)
        from scipy.special import ndtr
        assert out == pytest.approx(ndtr((nodes[0] - mu) / sd) + ndtr((mu - nodes[-1]) / sd))


def test_size_moves_c_and_beta_moves_s_by_linear_interpolation_of_the_draws():
    from analytic_sf import lf_sf
    from glaciar.inference.covariates import CovariateNodes

    sf = lf_sf(n_draws=4)
    names = sf.model.param_names

    def nodes(name, x, col, step):
        d = np.stack([sf.draws.copy() for _ in x])
        d[:, :, names.index(col)] += (step * np.arange(len(x)))[:, None]
        return CovariateNodes(name=name, centres=np.asarray(x, float),
                              edges=np.linspace(x[0] - 0.2, x[-1] + 0.2, len(x) + 1), draws=d,
                              n_sources=np.ones(len(x), int), n_cells=np.ones(len(x), int),
                              n_extreme=np.zeros(len(x), int), adequate=np.ones(len(x), bool))

    sf.covariates = {"r_eff": nodes("r_eff", [-1.4, -1.0, -0.6], "m50_0", -0.6),
                     "beta": nodes("beta", [-2.6, -2.0, -1.4], "eta_lo_0", 1.0)}
    th_c = sf.draws.copy()
    th_c[:, names.index("m50_0")] += -0.6 * 0.25          # x = -1.3: a quarter of the way to node 2
    th_s = sf.draws.copy()
    th_s[:, names.index("eta_lo_0")] += 1.0 * 1.5         # beta = -1.7: halfway from node 2 to 3
    m, z = np.array([27.0, 27.6, 28.0]), np.array([6.4, 7.0, 7.6])
    c = sf.completeness(m, z, r_eff_arcsec=10 ** -1.3, draws=True)
    s = sf.selection_given_recovered(z, m, beta=-1.7, draws=True)
    np.testing.assert_allclose(c, sf.model.completeness(th_c, m, z), rtol=1e-12)
    np.testing.assert_allclose(s, sf.model.selection_given_recovered(th_s, z, m), rtol=1e-12)
    # the size leaves S alone, beta leaves C alone; P = C(r_e) S(beta)
    np.testing.assert_allclose(sf.selection_given_recovered(z, m, draws=True),
                               sf.model.selection_given_recovered(sf.draws, z, m), rtol=1e-12)
    np.testing.assert_allclose(sf.selection_probability(z, m, r_eff_arcsec=10 ** -1.3, beta=-1.7,
                                                        draws=True), c * s, rtol=1e-12)
    with pytest.warns(UserWarning, match="beta law lies outside"):
        sf.effective_volume([27.0], beta_distribution=BetaDistribution(0.0, 0.2), n_z=51)
