"""The magnification covariate behind a lens (issue 25 point 3): C(m_obs, z | |mu|).

Behind a lens the injections are made at the observed magnitude; at fixed observed flux a
more magnified source is more stretched and less often recovered.  With the covariate,
V_eff and the count tables read each lens node's C at its own |mu| (glaciar.inference.lensed).
The reference values here are computed independently: P at the parameters interpolated
linearly in log10|mu| by hand, integrated over z with scipy.
"""
import warnings

import astropy.units as u
import numpy as np
import pandas as pd
import pytest
from astropy.cosmology import Planck18
from scipy.integrate import quad
from scipy.special import expit

from glaciar.galaxy.lensing import distance_ratio, lens_area_nodes
from glaciar.inference import SelectionFunction, SurfaceModel, aggregate_cells, fit_surfaces
from glaciar.inference.covariates import (MAGNIFICATION_QUANTILES, CovariateNodes,
                                          fit_covariate_nodes)
from glaciar.inference.lensed import LensNodes, lensed_count_tables
from lens_maps import put_mass_sheet

Z_LENS = 0.308
#: m50 of the hand-built nodes: 27.4 at |mu| = 1, 1 mag brighter per dex of |mu|.
M50_0, K_MU = 27.4, -1.0
SMOOTH = dict(logit_c_max_0=3.0, m50_0=M50_0, log_w_0=np.log(0.25), logit_s_max=3.0,
              eta_lo_0=-1.0, log_dz_lo_0=np.log(0.15), eta_hi_0=-1.0, log_dz_hi_0=np.log(0.15))
X_NODES = np.array([0.0, 0.25, 0.5, 0.75, 1.0])


def _params(mdl, **over):
    base = dict.fromkeys(mdl.param_names, 0.0)
    base.update(SMOOTH, **over)
    return np.array([base[n] for n in mdl.param_names])


def _synthetic():
    """A selection function whose magnification nodes differ: m50 = 27.4 - x (x = log10|mu|)."""
    mdl = SurfaceModel(shape="logistic", z_ref=7.0, z_scale=1.0, m_ref=27.0, m_scale=2.0)
    pooled = _params(mdl)[None, :] + np.zeros((2, 1))
    draws = np.stack([_params(mdl, m50_0=M50_0 + K_MU * x)[None, :] + np.zeros((2, 1))
                      for x in X_NODES])
    k = len(X_NODES)
    cov = CovariateNodes(name="magnification", centres=X_NODES,
                         edges=np.concatenate([[-0.1], 0.5 * (X_NODES[1:] + X_NODES[:-1]), [1.1]]),
                         draws=draws, n_sources=np.full(k, 100), n_cells=np.full(k, 10),
                         n_extreme=np.zeros(k, int), adequate=np.ones(k, bool))
    sf = SelectionFunction(mdl, pooled, meta={"area_arcmin2": 1.0},
                           domain={"z": (6.0, 8.0), "mag": (24.0, 30.0)})
    return sf, cov


def _p_at_mu(sf, z, m_obs, x):
    """P at observed magnitude m_obs with the parameters interpolated by hand at x = log10|mu|."""
    th = _params(sf.model, m50_0=M50_0 + K_MU * float(np.clip(x, X_NODES[0], X_NODES[-1])))
    c, s = sf.model.surfaces_on_grid(th, np.array([z]), np.array([m_obs]))
    return float(c[0, 0] * s[0, 0])


def _sheet_volume(sf, m, kappa, area, with_mu=True):
    sr = (area * u.arcmin ** 2).to_value(u.sr)

    def integrand(z):
        det = (1 - distance_ratio(Z_LENS, z, Planck18) * kappa) ** 2
        x = -np.log10(det) if with_mu else 0.0
        dvdz = Planck18.differential_comoving_volume(z).to_value(u.Mpc ** 3 / u.sr)
        return dvdz * sr * det * _p_at_mu(sf, z, m + 2.5 * np.log10(det), x)
    return quad(integrand, 6.0, 8.0, epsrel=1e-8)[0]


def test_volume_behind_a_mass_sheet_uses_p_at_its_magnification():
    """kappa = 0.3: |mu| = 1.95-1.99 over z = 6-8 (x ~ 0.29, between nodes).  V_eff equals the
    integral of dV/dz A/mu P(z, m - 2.5 log10 mu | theta(log10 mu)) to 3e-3 (P interpolated
    linearly between nodes 0.1 dex apart: ~ dx^2/8 |dm50/dx|^2 P''); without the covariate
    (the pooled draws, m50 of |mu| = 1) it is 1 % off at 26.8 (C ~ C_max) and 26-82 % at
    27.6 and 28.0."""
    sf, cov = _synthetic()
    m = np.array([26.8, 27.6, 28.0])
    put_mass_sheet(sf, Z_LENS, 0.3)
    without = sf.effective_volume(m, cosmology=Planck18, n_z=201).median.to_value(u.Mpc ** 3)
    sf.covariates = {"magnification": cov}
    got = sf.effective_volume(m, cosmology=Planck18, n_z=201).median.to_value(u.Mpc ** 3)
    want = np.array([_sheet_volume(sf, mi, 0.3, 800.0) for mi in m])
    np.testing.assert_allclose(got, want, rtol=3e-3)
    assert np.all(np.abs(without[1:] / want[1:] - 1) > 0.2)


def test_count_tables_behind_a_mass_sheet_use_p_at_its_magnification():
    """The count kernels' table (one class per covariate node) at draw 0: Omega |det A| P(z,
    m + 2.5 log10|det A| | theta(x)) per z, against the per-z value computed here."""
    sf, cov = _synthetic()
    sf.covariates = {"magnification": cov}
    put_mass_sheet(sf, Z_LENS, 0.3, area=4.0)
    zz = np.array([6.2, 7.0, 7.9])
    m_tab = 26.0 + 0.02 * np.arange(150)
    (a, table), = lensed_count_tables(sf, np.array([0]), zz, m_tab, None, Planck18)
    sr = (4.0 * u.arcmin ** 2).to_value(u.sr)
    for iz, z in enumerate(zz):
        det = (1 - distance_ratio(Z_LENS, z, Planck18) * 0.3) ** 2
        want = [sr * det * _p_at_mu(sf, z, mi + 2.5 * np.log10(det), -np.log10(det))
                for mi in m_tab[::10]]
        np.testing.assert_allclose(table[iz, ::10], want, rtol=3e-3, atol=1e-3 * max(want))


def test_outside_the_injected_range_is_clamped_and_warned_about():
    """kappa = 0.55: |mu| ~ 5-6 (x ~ 0.7-0.8) inside; an injected range ending at x = 0.5
    (|mu| 3.2) takes the end node's P for every node and warns once."""
    sf, cov = _synthetic()
    short = CovariateNodes(name="magnification", centres=cov.centres[:3],
                           edges=np.array([-0.1, 0.125, 0.375, 0.5]), draws=cov.draws[:3],
                           n_sources=cov.n_sources[:3], n_cells=cov.n_cells[:3],
                           n_extreme=cov.n_extreme[:3], adequate=cov.adequate[:3])
    sf.covariates = {"magnification": short}
    put_mass_sheet(sf, Z_LENS, 0.55)
    with pytest.warns(UserWarning, match="outside the injected range"):
        got = sf.effective_volume([27.0], cosmology=Planck18, n_z=201).median.to_value(u.Mpc ** 3)
    sr = (800.0 * u.arcmin ** 2).to_value(u.sr)

    def integrand(z):
        det = (1 - distance_ratio(Z_LENS, z, Planck18) * 0.55) ** 2
        dvdz = Planck18.differential_comoving_volume(z).to_value(u.Mpc ** 3 / u.sr)
        return dvdz * sr * det * _p_at_mu(sf, z, 27.0 + 2.5 * np.log10(det), 0.5)
    np.testing.assert_allclose(got, quad(integrand, 6.0, 8.0, epsrel=1e-8)[0], rtol=1e-3)


def test_completeness_lensed_reads_c_at_the_magnification():
    sf, cov = _synthetic()
    sf.covariates = {"magnification": cov}
    mu = np.array([1.0, -3.0, 10.0])                # signed: |mu| is used
    m_int = np.array([27.5, 28.0, 29.0])
    got = sf.completeness_lensed(m_int, 7.0, mu)
    m_obs = m_int - 2.5 * np.log10(np.abs(mu))
    want = [sf.model.completeness(_params(sf.model, m50_0=M50_0 + K_MU * np.log10(abs(u_))),
                                  mo, 7.0) for mo, u_ in zip(m_obs, mu)]
    np.testing.assert_allclose(got, want, rtol=1e-9)


# ---------------------------------------------------------------- fitting it
ZS = np.array([7.0, 8.0, 9.0])
MS = np.arange(24.5, 27.01, 0.25)


def truth_c(m, x):
    """Recovered fraction at observed magnitude m and x = log10|mu|: flat up to |mu| = 1.6,
    then 2.5 mag brighter per dex (lower surface brightness of the stretched image)."""
    return 0.95 * expit(-(m - (25.7 - 2.5 * np.maximum(x - 0.2, 0.0))) / 0.15)


@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(3)
    z, m = [a.ravel() for a in np.meshgrid(ZS, MS, indexing="ij")]
    n = 80
    z, m = np.repeat(z, n), np.repeat(m, n)
    # An image-plane |mu| distribution like a cluster field's: most weakly magnified, a tail.
    x = 0.05 + rng.exponential(0.12, z.size)
    mu = 10 ** x * np.where(rng.random(z.size) < 0.1, -1.0, 1.0)
    rec = rng.random(z.size) < truth_c(m, x)
    sel = rec & (rng.random(z.size) < 0.9)
    df = pd.DataFrame({"z": z, "mag": m, "mag_input": m, "recovered": rec, "selected": sel,
                       "magnification": mu})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")            # short chains: ConvergenceWarning
        cells = aggregate_cells(df, 0.01, None, "mag_input")
        mdl = SurfaceModel.for_data(cells.z, cells.mag, shape="logistic")
        res = fit_surfaces(cells, mdl, seed=0, max_steps=200)
        sf = SelectionFunction(mdl, res.draws(300), meta={"area_arcmin2": 1.0},
                               domain={"z": (7.0, 9.0), "mag": (24.5, 27.0)})
        sf.covariates = {"magnification": fit_covariate_nodes(
            df, "magnification", mdl, quantiles=MAGNIFICATION_QUANTILES, max_draws=300,
            fit=lambda c, mm, s: fit_surfaces(c, mm, seed=s, max_steps=200))}
    return df, sf


def test_fitted_magnification_bins_are_adequate_and_c_falls_with_mu_as_the_data(fitted):
    """Every bin passes its PPC, and at observed m = 25.25-25.75 the predicted recovered
    counts of the weakest- and strongest-magnified bins match the counts (3 sigma), which
    differ by > 0.3 in fraction; the pooled fit (C marginalised over the injected |mu|)
    misses the strongly magnified bin's count by > 3 sigma (5.3 here)."""
    df, sf = fitted
    cov = sf.covariates["magnification"]
    assert cov.adequate.all() and len(cov.centres) == len(MAGNIFICATION_QUANTILES) - 1
    x = np.log10(np.abs(df["magnification"].to_numpy()))
    k = np.clip(np.searchsorted(cov.edges, x, side="right") - 1, 0, len(cov.centres) - 1)
    near = np.abs(df["mag"].to_numpy() - 25.5) < 0.3
    frac = []
    for b in (0, len(cov.centres) - 1):
        s = near & (k == b)
        d = df[s]
        mu = d["magnification"].to_numpy()
        m_int = d["mag"].to_numpy() + 2.5 * np.log10(np.abs(mu))      # intrinsic magnitude
        p = sf.completeness_lensed(m_int, d["z"].to_numpy(), mu)
        n_rec = d["recovered"].sum()
        assert abs(n_rec - p.sum()) < 3 * np.sqrt(np.sum(p * (1 - p))) + 1
        pooled = sf.completeness(d["mag"].to_numpy(), d["z"].to_numpy())
        frac.append((n_rec / len(d), p.mean(), abs(n_rec - pooled.sum()) / np.sqrt(
            np.sum(pooled * (1 - pooled)))))
    (f_lo, p_lo, _), (f_hi, p_hi, pooled_sigma) = frac
    assert f_lo - f_hi > 0.3 and p_lo - p_hi > 0.3 and pooled_sigma > 3


def test_volume_over_a_range_of_magnifications_with_few_redshifts():
    """A convergence gradient (kappa 0-0.6, |mu| 1-5: a lensing-shift range wider than the
    21 redshift nodes, which once made the lattice too short): V_eff equals the per-node sum
    of Omega_n |det A_n| P(z, m + 2.5 log10|det A_n| | theta(x_n)) integrated here by
    Simpson's rule over the same z, to 5e-3."""
    from scipy.integrate import simpson

    sf, cov = _synthetic()
    sf.covariates = {"magnification": cov}
    kap = np.broadcast_to(np.linspace(0.0, 0.6, 30)[None, :], (4, 30))
    zero = np.zeros_like(kap)
    nodes = lens_area_nodes(np.full(kap.shape, 27.5), kap, zero, zero, 800.0 / kap.size,
                            depth_bin_mag=0.05, ratio_range=(0.8, 0.9))
    ln = LensNodes.from_dict("cl", "grad", Z_LENS, nodes)
    sf.lens_nodes = {"cl": {"grad": ln}}
    m = np.array([27.0, 27.8])
    got = sf.effective_volume(m, cosmology=Planck18, n_z=21).median.to_value(u.Mpc ** 3)
    zz = np.linspace(6.0, 8.0, 21)
    sr = (ln.area_arcmin2 * u.arcmin ** 2).to_value(u.sr)
    dvdz = Planck18.differential_comoving_volume(zz).to_value(u.Mpc ** 3 / u.sr)
    want = []
    for mi in m:
        f = np.zeros(len(zz))
        for iz, z in enumerate(zz):
            r = distance_ratio(Z_LENS, z, Planck18)
            det = np.abs(1 - 2 * r * ln.kappa + r * r * ln.kappa2_minus_gamma2)
            f[iz] = sum(s * d * _p_at_mu(sf, z, mi + 2.5 * np.log10(d), -np.log10(d))
                        for s, d in zip(sr, det))
        want.append(simpson(f * dvdz, x=zz))
    np.testing.assert_allclose(got, want, rtol=5e-3)
