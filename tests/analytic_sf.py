"""Analytic selection functions and transfer matrices shared by the inference, LF and pipeline tests.

Built from closed forms (no simulation): a transfer matrix whose rows are exact normal bin
probabilities, and a smooth selection function with a Gaussian transfer for the
luminosity-function fits (``lf_sf``, its truth ``TRUE`` and candidates drawn from it).
"""
import numpy as np
from scipy.stats import norm

from glaciar.galaxy.filters import get_filter
from glaciar.inference import SelectionFunction, SurfaceModel
from glaciar.inference.products import InjectionSED
from glaciar.tables import TransferMatrix, slice_edges


def gauss_matrix(grid, zs, *, shift=0.15, sigma=0.2, step=0.2, n_draws=1):
    """TransferMatrix whose selected rows are exactly m_obs = m_in + shift + N(0, sigma)."""
    zs = np.asarray(zs, float)
    sig = sigma if callable(sigma) else (lambda m: sigma + 0 * m)
    inner = np.round(np.arange(np.floor(grid[0] - 1.5), grid[-1] + 1.51, step), 6)
    oe = np.concatenate([[-np.inf], inner, [np.inf]])
    mat = np.zeros((2, len(zs), len(grid), len(oe)))
    for j, g in enumerate(grid):
        mat[:, :, j, 1:] = np.diff(norm.cdf(oe, g + shift, sig(g)))
    return TransferMatrix(kinds=("recovered", "selected"), z_edges=slice_edges(zs, 0.25),
                          z_mean=zs, m_in_edges=slice_edges(grid, 0.25), m_obs_edges=oe,
                          counts=np.rint(mat * 1e6).astype(np.int64), matrix=mat,
                          draws=np.repeat(mat[None], n_draws, axis=0), alpha=0.01)


TRUE = {"log_phi_star": -3.3, "M_star": -20.9, "alpha": -2.0}


def lf_sf(n_draws=4, area=800.0, seed=0):
    """A smooth selection (m50 = 27.6, w = 0.25, z edges of 0.15) over z 6-8, m 24-30.

    Draws scatter by 0.02 in every parameter; the transfer function is m_obs = m_in + 0.15
    + N(0, 0.1 + 0.1 (m_in - 24)).
    """
    mdl = SurfaceModel(shape="logistic", z_ref=7.0, z_scale=1.0, m_ref=27.0, m_scale=2.0)
    base = dict.fromkeys(mdl.param_names, 0.0)
    base.update(logit_c_max_0=3.0, m50_0=27.6, m50_1=0.1, log_w_0=np.log(0.25), logit_s_max=3.0,
                eta_lo_0=-1.0, log_dz_lo_0=np.log(0.15), eta_hi_0=-1.0, log_dz_hi_0=np.log(0.15))
    th = np.array([base[n] for n in mdl.param_names])
    draws = th + 0.02 * np.random.default_rng(seed).standard_normal((n_draws, len(th)))
    sed = InjectionSED(get_filter("wfc3_ir_f160w"), beta_mean=-2.0, beta_sd=0.4)
    sf = SelectionFunction(mdl, draws, meta={"area_arcmin2": area}, sed=sed,
                           domain={"z": (6.0, 8.0), "mag": (24.0, 30.0)})
    sf.transfer_matrix = gauss_matrix(np.arange(24.0, 30.01, 0.5), [6.0, 6.5, 7.0, 7.5, 8.0],
                                      sigma=lambda m: 0.1 + 0.1 * (m - 24.0))
    return sf


def mock_candidates(sf, phi, edges, seed):
    """Candidates drawn from the forward model: Poisson counts per bin, uniform inside it."""
    ec = sf.expected_counts(lambda M, z: phi(M) + 0 * z, edges, draws=1, warn=False)
    rng = np.random.default_rng(seed)
    n = rng.poisson(ec.median)
    return np.concatenate([rng.uniform(a, b, k) for a, b, k in zip(edges[:-1], edges[1:], n)])
