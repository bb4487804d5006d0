"""Fit a luminosity function to observed candidates through the selection function.

The data are the measured detection-band magnitudes m_obs of the candidates (recovered,
selected, finite m_obs), binned in fine bins of m_obs (the transfer matrix's 0.2 mag by
default, over :func:`default_window`).  The model predicts, per selection-function draw d,

    lambda_dk(theta) = Σ_M phi(M; theta) K_d[M, k]

with K_d the count kernel (:func:`glaciar.inference.counts.count_kernel`: P = C S, the
transfer function, the beta average, dV/dz, the area by depth), computed once: a
likelihood evaluation is one matrix product, whatever the number of candidates.

Likelihood: Poisson in every bin, ln L_d = Σ_k [n_k ln lambda_dk - lambda_dk] (ln n_k!
dropped).

**Selection-function uncertainty** (:class:`Marginalisation`), over D posterior draws of the
selection function (``max_sf_draws``, evenly spaced; draw i paired with transfer draw
i mod n_t):

* ``"mixture"`` (default): the posterior is the average of the posteriors given each
  draw, p(theta | data) = (1/D) Σ_d p(theta | data, draw d) -- the selection function's
  uncertainty propagated into the luminosity function, the catalogue not being allowed
  to re-calibrate the selection function (a "cut" of that feedback).  Each draw's
  posterior is sampled on its own: its mode (Newton steps with its own Laplace
  curvature) and Laplace covariance, then importance
  sampling from a Student t (5 degrees of freedom, 1.2 x the Laplace scale) around the
  mode, 2000 proposals resampled to 200 samples (:func:`_importance`); where the weights'
  effective sample size is below 200, again from that draw's own L-BFGS mode and Laplace
  covariance with 8000 proposals and a 1.8 x scale; where still below (a posterior unlike
  the proposal, e.g. pinned at a prior bound), an emcee chain (~1-2 s each).  The same
  number of samples from every draw.
* ``"likelihood"``: the likelihood averaged over the draws, ln L = ln((1/D) Σ_d L_d):
  the Monte Carlo estimate of the likelihood marginalised over the selection function,
  i.e. the joint posterior in which the catalogue also weighs the draws.  With many
  candidates the draws' likelihoods differ by many units and one or two draws carry it:
  it would need far more draws than a file holds, hence not the default.

Measured on a fitted demo run with a poorly constrained selection function (5 z x 9
magnitudes, 3 x 30 sources per cell, 1000 draws) and 1.1e4 mock candidates drawn from its
median prediction of a Schechter function (log phi* = -3.3, M* = -20.9, alpha = -2),
distances in units of the 68 % half-interval on the truth's side: the likelihood average
collapsed onto 1.5 effective draws and missed by 4.3 (log phi*), 6.7 (M*) and 8.5 sigma
(alpha); the mixture, with intervals 3-20 x wider, by 1.0, 1.3 and 1.0 sigma.  About half
of its 100 draws had posteriors pinned at alpha's prior bound and needed an emcee chain
(~3 min in all); with a well-constrained selection function every draw is
importance-sampled (seconds in all).

``LFResult.convergence["sf_draw_ess"]`` is the effective number of draws carrying the
posterior (1 / Σ w_d^2 of the draws' mean posterior weights over the samples): D for
the mixture by construction, often ~1 for "likelihood" with many candidates.

Priors: uniform (:mod:`glaciar.lf.models`).  Sampling: MAP (L-BFGS-B), its Laplace
covariance, then (importance sampling per draw, above, or) emcee with the independence,
differential-evolution and stretch moves of :func:`glaciar.inference.sampling.sample_block`,
until 50 autocorrelation times or ``sampler.max_steps`` (per chain); burn-in 2 tau,
thinning tau / 2.

phi is 0 outside ``muv_range`` (sources outside it are assumed absent: choose it to
cover every M_UV that contributes to the measured-magnitude window; the default does),
and constant in z over the redshift range (``volume``).

Arrays in, results out; no file I/O (``glaciar lf``, :func:`glaciar.pipeline.lf.run_lf`,
reads and writes the files).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..inference.counts import (COUNTS_EXTRAPOLATION_TOLERANCE, M_STEP, SurveyVolume, count_kernel,
                                default_M_edges)
from ..inference.sampling import SamplerSettings
from .models import LFModel, get_model
from .predict import expected_counts, interloper_background

__all__ = ["LFResult", "LFPosterior", "fit_lf", "expected_counts", "default_window", "step_width",
           "gehrels_limits",
           "STEP_WIDTH", "WINDOW_BRIGHT_MARGIN", "MAX_SF_DRAWS", "MAX_TRANSFER_DRAWS",
           "STEP_MIN_SENSITIVITY", "LF_MAX_STEPS", "Marginalisation"]

#: Default width of the stepwise bins and of the binned-phi table [mag].
STEP_WIDTH = 0.5
#: The default measured-magnitude window starts this far inside the simulated range's bright
#: end [mag], so that sources brighter than the simulations scatter into it negligibly.
WINDOW_BRIGHT_MARGIN = 0.4
#: Default cap on the emcee steps of the LF fit (it stops earlier at 50 autocorrelation times).
LF_MAX_STEPS = 5000
#: Selection-function draws the likelihood is averaged over (evenly spaced), at most.
MAX_SF_DRAWS = 100
#: Transfer-matrix draws used by default: its rows hold hundreds to thousands of sources
#: each and move counts only between neighbouring m_obs bins, so a few tens of draws carry
#: its uncertainty (each costs a table of the transfer function, ~0.05 s).
MAX_TRANSFER_DRAWS = 20
#: Default stepwise bins cover the M_UV where the kernel's counts per unit phi reach this
#: fraction of their maximum (bins beyond would be constrained by the prior alone).
STEP_MIN_SENSITIVITY = 0.01
#: Importance sampling of one draw's posterior (mixture): proposals, samples kept
#: (resampled), the smallest effective sample size accepted (else an emcee chain), the
#: Student t's degrees of freedom and its scale over the Laplace covariance.
IS_PROPOSALS = 2000
IS_SAMPLES = 200
IS_MIN_ESS = 200
T_DOF = 5.0
IS_SCALE = 1.2
#: Posterior samples used for the predictive counts and the binned phi.
_N_PRED = 200


@dataclass(frozen=True)
class Marginalisation:
    """How the selection function's uncertainty enters the LF fit (module docstring)."""

    #: "mixture": the average of the posteriors given each draw; "likelihood": the
    #: likelihood averaged over the draws.
    method: str = "mixture"
    #: Selection-function draws marginalised over (evenly spaced), at most.
    max_sf_draws: int = MAX_SF_DRAWS
    #: Transfer-matrix draws used (selection-function draw i with transfer draw i mod this).
    max_transfer_draws: int = MAX_TRANSFER_DRAWS


@dataclass(frozen=True)
class LFResult:
    """A fitted luminosity function.

    Attributes
    ----------
    model : str
    param_names : tuple of str
        Every parameter of the model (fixed ones included).
    parameters : dict
        ``{name: {"median", "lo68", "hi68"}}`` (16th and 84th percentiles; a fixed
        parameter has its value in all three).
    fixed : dict
        ``{name: value}`` of the fixed parameters.
    samples : ndarray (n_samples, n_params)
        Posterior samples after burn-in and thinning (fixed parameters included).
    chain : ndarray (n_samples, n_free)
        The free parameters' samples (emcee: after burn-in and thinning), draw by draw for
        the mixture (``n_samples / n_sf_draws`` from each, in draw order).
    n_candidates : int
        Candidates inside the measured-magnitude window (what was fitted).
    n_outside : int
        Candidates with a finite m_obs outside the window (left out).
    counts : dict of ndarray
        Observed vs expected per m_obs bin: ``m_lo``, ``m_hi`` [AB mag], ``n_obs``,
        ``n_exp`` (posterior-predictive mean: median over posterior samples, each with a
        selection-function draw drawn from its posterior weights), ``n_exp_lo68``,
        ``n_exp_hi68``.
    binned_phi : dict of ndarray
        ``M_lo``, ``M_hi``, ``M`` [AB mag]; ``phi``, ``phi_lo68``, ``phi_hi68`` [Mpc^-3 mag^-1];
        ``phi_model`` (the model averaged over the bin at the median parameters);
        ``n_obs`` (candidates apportioned to the bin: each m_obs bin's count split in
        proportion to the bins' expected contributions), ``n_exp``.  For the stepwise
        model phi is the step's posterior median and 68 % interval; for a parametric
        model it is the data's: phi_model * n_obs / n_exp, with Gehrels (1986) 1-sigma
        Poisson limits on n_obs.
    muv_range, z_range : tuple of float
        M_UV range of phi [AB mag] and redshift range integrated over.
    transfer : bool
        Whether the transfer function was used.
    convergence : dict
        ``n_importance`` (draws sampled by importance sampling), ``importance_ess_min``,
        ``n_chains`` (emcee chains), ``tau`` (per free parameter, the largest over the
        chains, steps; None without a chain), ``n_steps`` (longest chain), ``n_walkers``,
        ``converged`` (every chain), ``acceptance``, ``n_sf_draws``, ``marginalise``,
        ``sf_draw_ess``, ``extrapolated_fraction_max``.
    path : Path or None
        Where :func:`glaciar.pipeline.lf.run_lf` wrote it.
    """

    model: str
    param_names: tuple
    parameters: dict
    fixed: dict
    samples: np.ndarray
    chain: np.ndarray
    n_candidates: int
    n_outside: int
    counts: dict
    binned_phi: dict
    muv_range: tuple
    z_range: tuple
    transfer: bool
    convergence: dict = field(default_factory=dict)
    #: Directory the result was written to (``RUN_DIR/lf``), when it was.
    path: object = None

    def phi(self, M, which: str = "median") -> np.ndarray:
        """phi(M) [Mpc^-3 mag^-1] at the median parameters (``which="median"``), or per sample."""
        mdl = get_model(self.model, edges=self.binned_phi["edges"] if self.model == "stepwise"
                        else None)
        if which == "median":
            return mdl.phi(M, np.array([self.parameters[n]["median"] for n in self.param_names]))
        return mdl.phi(M, self.samples)


class LFPosterior:
    """Vectorised log posterior of the free parameters: uniform prior, Poisson log-mean-exp likelihood.

    Parameters
    ----------
    model : LFModel
    basis : ndarray (n_basis, n_d, n_k)
        Kernel in the model's basis: per M cell (parametric models, phi at the cell
        centres ``M``) or per step (stepwise: the cells of each bin summed).
    n_obs : ndarray (n_k,)
        Observed counts per m_obs bin.
    fixed : dict
    M : ndarray (n_basis,), optional
        Cell centres [AB mag] (parametric models).
    """

    def __init__(self, model: LFModel, basis, n_obs, fixed, M=None, offsets=None, background=None):
        self.model = model
        self.M = None if M is None else np.asarray(M, float)
        self.n_obs = np.asarray(n_obs, float)
        # Counts phi does not set (interlopers, (n_d, n_k)): one more basis row, its phi 1.
        self.background, self._n_bg = background, int(background is not None)
        b = np.asarray(basis, float)
        if background is not None:
            b = np.concatenate([b, np.broadcast_to(background, b.shape[1:])[None]])
        self.n_d = b.shape[1]
        nz = self.n_obs > 0
        self._nz = self.n_obs[nz]
        self._Kall = b.reshape(b.shape[0], -1)                          # (n_b, D n_k)
        self._Knz = b[:, :, nz].reshape(b.shape[0], -1)                 # (n_b, D n_nz)
        self._Ksum = b.sum(axis=2)                                       # (n_b, D)
        self.fixed = dict(fixed)
        self.basis = b
        self.offsets = np.zeros(self.n_d) if offsets is None else np.asarray(offsets, float)
        self.free = [i for i, n in enumerate(model.param_names) if n not in self.fixed]
        self._full0 = np.array([self.fixed.get(n, np.nan) for n in model.param_names])

    @property
    def free_names(self) -> list[str]:
        return [self.model.param_names[i] for i in self.free]

    def full(self, x) -> np.ndarray:
        """Free parameters (W, n_free) -> every parameter (W, n_params)."""
        x = np.atleast_2d(np.asarray(x, float))
        th = np.tile(self._full0, (len(x), 1))
        th[:, self.free] = x
        return th

    def basis_phi(self, theta) -> np.ndarray:
        """phi on the basis (W, n_basis): at the cell centres, or 10^step."""
        th = np.atleast_2d(theta)
        f = 10.0 ** th if self.model.name == "stepwise" else self.model.phi(self.M, th)
        return np.concatenate([f, np.ones((len(f), self._n_bg))], axis=1) if self._n_bg else f

    def grad_log_like(self, theta) -> np.ndarray:
        """d ln L / d (free parameters) at one full parameter vector ``theta``, (n_free,).

        d ln L_d / d phi_b = Σ_k (n_k / lambda_dk - 1) K_d[b, k], weighed over the draws
        by their posterior weights, times d phi_b / d theta (exact for the steps, central
        differences of phi for the parametric models).
        """
        th = np.asarray(theta, float).reshape(1, -1)
        f = self.basis_phi(th)[0]
        lam = (f @ self._Kall).reshape(self.n_d, -1)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(lam > 0, self.n_obs / np.where(lam > 0, lam, 1.0), 0.0) - 1.0
        g_phi = np.einsum("d,bdk,dk->b", self.responsibilities(th)[0], self.basis, r)
        free = self.free
        if self.model.name == "stepwise":
            return np.log(10.0) * f[free] * g_phi[free]
        h = 1e-6 * np.maximum(1.0, np.abs(th[0, free]))
        pts = np.repeat(th, 2 * len(free), axis=0)
        for i, (j, hj) in enumerate(zip(free, h)):
            pts[2 * i, j] += hj
            pts[2 * i + 1, j] -= hj
        fp = self.basis_phi(pts)
        J = (fp[0::2] - fp[1::2]) / (2 * h[:, None])                      # (n_free, n_b)
        return J @ g_phi

    def expected(self, theta) -> np.ndarray:
        """lambda (W, n_d, n_k) for full parameter vectors ``theta``."""
        f = self.basis_phi(theta)
        return (f @ self._Kall).reshape(len(f), self.n_d, -1)

    def log_like_draws(self, theta) -> np.ndarray:
        """ln L_d (W, n_d) for full parameter vectors ``theta`` (ln n_k! dropped)."""
        f = self.basis_phi(theta)
        lam_nz = (f @ self._Knz).reshape(len(f), self.n_d, -1)
        with np.errstate(divide="ignore"):
            ll = (np.log(np.maximum(lam_nz, 1e-300)) * self._nz).sum(axis=2)
        return ll - f @ self._Ksum

    def log_like(self, theta) -> np.ndarray:
        """ln (1/D) Σ_d L_d / Z_d (W,): Z_d = exp(offsets[d]) (1 for the plain average)."""
        ll = self.log_like_draws(theta) - self.offsets
        if self.n_d == 1:
            return ll[:, 0]
        top = ll.max(axis=1, keepdims=True)
        top = np.where(np.isfinite(top), top, 0.0)
        with np.errstate(divide="ignore"):
            return np.log(np.exp(ll - top).sum(axis=1)) + top[:, 0] - np.log(self.n_d)

    def responsibilities(self, theta) -> np.ndarray:
        """Posterior weight of each draw given the parameters, (W, n_d)."""
        ll = self.log_like_draws(theta) - self.offsets
        w = np.exp(ll - ll.max(axis=1, keepdims=True))
        return w / w.sum(axis=1, keepdims=True)

    def draw(self, d: int) -> "LFPosterior":
        """The posterior given selection-function draw ``d`` alone."""
        bg = None if self.background is None else self.background[d:d + 1]
        return LFPosterior(self.model, self.basis[:len(self.basis) - self._n_bg, d:d + 1],
                           self.n_obs, self.fixed, self.M, background=bg)

    def __call__(self, x) -> np.ndarray:
        th = self.full(x)
        lp = self.model.log_prior(th)
        out = np.full(len(th), -np.inf)
        ok = np.isfinite(lp)
        if ok.any():
            out[ok] = self.log_like(th[ok]) + lp[ok]
        return out


def default_window(sf, transfer: bool = True, step: float | None = None) -> np.ndarray:
    """Measured-magnitude bins [AB mag] fitted by default: the simulated range on the transfer lattice.

    From ``WINDOW_BRIGHT_MARGIN`` inside the bright end of the simulated input magnitudes
    (those of the transfer matrix's rows for an absolute-magnitude fit) to their faint
    end, in bins of ``step`` (default the transfer matrix's, 0.2 mag) on its lattice.
    """
    from .. import constants as C
    from ..inference.transfer import row_magnitudes

    step = float(step or C.TRANSFER_MOBS_STEP)
    tm = sf.transfer_matrix
    if sf.magnitude_type == "absolute" or "mag" not in sf.domain:
        if tm is None:
            raise ValueError("fit_lf: give m_obs_edges (no transfer matrix to take the "
                             "measured-magnitude range from)")
        u = row_magnitudes(tm.m_in_edges)
        lo, hi = float(u[0]), float(u[-1])
    else:
        lo, hi = sf.domain["mag"]
    a = np.ceil((lo + WINDOW_BRIGHT_MARGIN) / step - 1e-9)
    b = np.floor(hi / step + 1e-9)
    if b - a < 1:
        raise ValueError(f"fit_lf: the simulated magnitude range {lo:g}-{hi:g} is too narrow "
                         "for a measured-magnitude window; give m_obs_edges")
    return np.round(np.arange(a, b + 1) * step, 6)


def step_width(kernel, m_centres) -> float:
    """Default stepwise bin width [mag]: the spread in m_obs of one M_UV, in multiples of STEP_WIDTH.

    The full width at half maximum (2.355 sigma) of the measured magnitudes of sources of
    one M_UV (the redshift range through the distance modulus, beta, the photometric
    scatter), the median over M_UV weighted by their counts per unit phi, rounded up to
    a multiple of ``STEP_WIDTH``.  Narrower bins are not resolved by the data: adjacent
    bins anticorrelate, the posterior zigzags and the sampler mixes poorly.

    Parameters
    ----------
    kernel : ndarray (n_M, n_k)
        Counts per unit phi of each M_UV cell in each m_obs bin.
    m_centres : ndarray (n_k,)
        Centres of the m_obs bins [AB mag].
    """
    v = np.asarray(kernel, float)
    tot = v.sum(axis=1)
    ok = tot > 0
    if not ok.any():
        return STEP_WIDTH
    w = v[ok] / tot[ok, None]
    mean = w @ m_centres
    sd = np.sqrt(np.maximum(w @ m_centres ** 2 - mean ** 2, 0.0))
    order = np.argsort(sd)
    cw = np.cumsum(tot[ok][order])
    s = sd[order][np.searchsorted(cw, 0.5 * cw[-1])]
    return float(STEP_WIDTH * max(1, np.ceil(2.355 * s / STEP_WIDTH - 1e-9)))


def _as_list(sf):
    from ..inference.selection_function import SelectionFunction
    if isinstance(sf, SelectionFunction):
        return [sf]
    if isinstance(sf, dict):
        return list(sf.values())
    out = list(sf)
    if not out or not all(isinstance(s, SelectionFunction) for s in out):
        raise ValueError("fit_lf: sf must be a SelectionFunction or a list of them (one per field)")
    return out


def gehrels_limits(n):
    """1-sigma Poisson limits (Gehrels 1986, eqs. 7 and 11 with S = 1) of counts ``n``:
    (lower, upper), also for non-integer (apportioned) counts."""
    n = np.asarray(n, float)
    up = n + np.sqrt(n + 0.75) + 1.0
    nn = np.maximum(n, 1.0)            # the lower limit of n < 1 (apportioned counts) is ~0
    lo = np.where(n >= 1.0, nn * (1 - 1 / (9 * nn) - 1 / (3 * np.sqrt(nn))) ** 3, 0.0)
    return np.maximum(lo, 0.0), up


def _laplace_cov(lp, x, bounds):
    """Inverse of minus the Hessian of ``lp`` at ``x`` (central differences), made positive.

    At a prior bound (a step with an upper limit only) the differences are taken just
    inside it, so that the other directions keep their curvature.
    """
    P = len(x)
    width = bounds[:, 1] - bounds[:, 0]
    h = 1e-3 * width
    for _ in range(2):
        I, J = np.triu_indices(P)
        E = np.eye(P)
        d1, d2 = E[I] * h[I][:, None], E[J] * h[J][:, None]
        xe = np.clip(x, bounds[:, 0] + 2.5 * h, bounds[:, 1] - 2.5 * h)
        pts = np.concatenate([xe + d1 + d2, xe + d1 - d2, xe - d1 + d2, xe - d1 - d2])
        v = lp(pts)
        k = len(I)
        H = np.zeros((P, P))
        if np.all(np.isfinite(v)):
            off = (v[:k] - v[k:2 * k] - v[2 * k:3 * k] + v[3 * k:]) / (4 * h[I] * h[J])
            H[I, J] = off
            H[J, I] = off
        w, V = np.linalg.eigh(-H)
        # A direction the data do not constrain gets the prior's spread.
        w = np.maximum(w, 12.0 / np.min(width) ** 2)
        cov = (V / w) @ V.T
        h = np.clip(0.1 * np.sqrt(np.diag(cov)), 1e-6 * width, 0.05 * width)
    return 0.5 * (cov + cov.T)


def _map(post: LFPosterior, x0, bounds):
    """Maximum of the posterior by L-BFGS-B inside the prior box (analytic gradient).

    The double power law's beta < alpha is a smooth penalty for the optimiser (the
    sampler sees -inf beyond it).
    """
    from scipy.optimize import minimize

    names = post.free_names
    dpl = post.model.name == "double_power_law"
    ia = names.index("alpha") if dpl and "alpha" in names else None
    ib = names.index("beta") if dpl and "beta" in names else None

    def f(x):
        th = post.full(x)
        pen, gpen = 0.0, np.zeros(len(x))
        if dpl:
            gap = th[0, 3] - th[0, 2] + 1e-3
            if gap > 0:
                pen = 1e4 * gap ** 2
                if ib is not None:
                    gpen[ib] += 2e4 * gap
                if ia is not None:
                    gpen[ia] -= 2e4 * gap
                th = th.copy()
                th[0, 3] = th[0, 2] - 1e-3
        v = post.log_like(th)[0]
        if not np.isfinite(v):
            return 1e300, np.zeros(len(x))
        return -v + pen, -post.grad_log_like(th[0]) + gpen

    res = minimize(f, x0, jac=True, method="L-BFGS-B", bounds=[tuple(b) for b in bounds],
                   options={"maxiter": 2000})
    x = np.clip(res.x, bounds[:, 0], bounds[:, 1])
    if not np.isfinite(post(x[None])[0]):
        raise RuntimeError(f"fit_lf: no finite posterior found for {names}")
    return x


def _start(post: LFPosterior, n_obs_total):
    """A starting point: typical shape, normalisation matched to the observed total."""
    mdl = post.model
    guess = {"log_phi_star": 0.0, "M_star": -21.0, "alpha": -2.0, "beta": -4.5}
    if mdl.name == "stepwise":
        th = np.zeros(mdl.n_params)
    else:
        th = np.array([guess[n] for n in mdl.param_names])
    for n, v in post.fixed.items():
        th[mdl.param_names.index(n)] = v
    lam = post.expected(th[None])[0].sum(axis=1).mean()
    shift = np.log10(max(n_obs_total, 1.0) / lam) if lam > 0 else 0.0
    norm = ["log_phi_star"] if mdl.name != "stepwise" else list(mdl.param_names)
    for n in norm:
        if n not in post.fixed:
            i = mdl.param_names.index(n)
            th[i] = th[i] + shift
    x = th[post.free]
    b = mdl.bounds[post.free]
    return np.clip(x, b[:, 0] + 1e-6 * (b[:, 1] - b[:, 0]), b[:, 1] - 1e-6 * (b[:, 1] - b[:, 0]))


def _newton(target: LFPosterior, x, cov, bounds, n_iter: int = 6):
    """Ascend ``target`` from ``x`` by steps cov @ gradient (halved until the posterior rises)."""
    x = np.asarray(x, float)
    lp = target(x[None])[0]
    sd = np.sqrt(np.diag(cov))
    for _ in range(n_iter):
        step = cov @ target.grad_log_like(target.full(x)[0])
        for _ in range(8):
            xn = np.clip(x + step, bounds[:, 0], bounds[:, 1])
            lpn = target(xn[None])[0]
            if np.isfinite(lpn) and lpn >= lp:
                break
            step = 0.5 * step
        else:
            return x
        x, lp = xn, lpn
        if np.all(np.abs(step) < 1e-2 * sd):
            break
    return x


def _importance(target: LFPosterior, x0, cov, n, rng, bounds, n_prop: int = None,
                scale: float = None):
    """Samples of one draw's posterior by importance sampling from a Student t around its mode.

    Proposal: ``n_prop`` (default ``IS_PROPOSALS``) draws of a multivariate t (``T_DOF``
    degrees of freedom) centred on the mode, scaled by ``scale`` (default ``IS_SCALE``)
    times the Laplace covariance; weights posterior / proposal (0 outside the prior).

    Returns
    -------
    samples : ndarray (n, n_free) or None
        ``n`` samples resampled by the weights (systematic resampling); None when no
        proposal has a finite posterior.
    ess : float
        The weights' effective sample size, 1 / Σ w^2.
    """
    P = len(x0)
    n_prop = IS_PROPOSALS if n_prop is None else int(n_prop)
    scale = IS_SCALE if scale is None else float(scale)
    L = np.linalg.cholesky(scale ** 2 * cov + 1e-12 * np.eye(P))
    z = rng.standard_normal((n_prop, P))
    g = rng.chisquare(T_DOF, n_prop) / T_DOF
    u = z / np.sqrt(g)[:, None]
    x = x0 + u @ L.T
    # log t density up to its constant (the same for every point: it cancels)
    logq = -0.5 * (T_DOF + P) * np.log1p(np.sum(u * u, axis=1) / T_DOF)
    inside = np.all((x >= bounds[:, 0]) & (x <= bounds[:, 1]), axis=1)
    logp = np.full(len(x), -np.inf)
    if inside.any():
        logp[inside] = target(x[inside])
    lw = logp - logq
    if not np.isfinite(lw).any():
        return None, 0.0
    w = np.exp(lw - lw[np.isfinite(lw)].max())
    w[~np.isfinite(w)] = 0.0
    w /= w.sum()
    ess = float(1.0 / np.sum(w ** 2))
    pos = (rng.random() + np.arange(n)) / n
    idx = np.minimum(np.searchsorted(np.cumsum(w), pos), len(w) - 1)
    return x[idx], ess


def _sample(post: LFPosterior, x_map, bounds, n_walkers, n_steps, seed, marginalise,
            progress, name):
    """Posterior samples of the free parameters: (flat (N, n_free), draw of each or None, info).

    ``"mixture"``: per selection-function draw, that draw's own mode and Laplace
    covariance, then importance sampling from a Student t around it (:func:`_importance`);
    where the weights' effective sample size falls below ``IS_MIN_ESS`` (a posterior
    far from the proposal's shape, e.g. a step with an upper limit only), an emcee chain
    (:func:`glaciar.inference.sampling.sample_block`) instead.  The same number of
    samples from each draw, so that every draw weighs 1/D.
    ``"likelihood"``: one emcee chain on the likelihood averaged over the draws.
    """
    from ..inference.sampling import ConvergenceWarning, sample_block

    P = len(post.free)
    bar = None
    n_targets = post.n_d if marginalise == "mixture" else 1
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(desc=f"lf {name}", unit="draw", total=n_targets, leave=False)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1]))
    flats, taus, steps, conv_ok, acc, ess_is = [], [], [], [], [], []
    cov_all = _laplace_cov(post, x_map, bounds)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        for d in range(n_targets):
            target = post.draw(d) if marginalise == "mixture" else post
            x0, cov = x_map, cov_all
            if marginalise == "mixture":
                # This draw's mode by Newton steps with its own curvature (the pooled one
                # also holds the spread between draws), then importance sampling; its
                # L-BFGS mode and a wider proposal if the weights say it was off.
                cov = _laplace_cov(target, x_map, bounds)
                x0 = _newton(target, x_map, cov, bounds)
                cov = _laplace_cov(target, x0, bounds)
                x0 = _newton(target, x0, cov, bounds, n_iter=2)
                got, ess = _importance(target, x0, cov, IS_SAMPLES, rng, bounds)
                if got is None or ess < IS_MIN_ESS:
                    x0 = _map(target, x0, bounds)
                    cov = _laplace_cov(target, x0, bounds)
                    got, ess = _importance(target, x0, cov, IS_SAMPLES, rng, bounds,
                                           n_prop=4 * IS_PROPOSALS, scale=1.5 * IS_SCALE)
                if got is not None and ess >= IS_MIN_ESS:
                    flats.append(got)
                    ess_is.append(ess)
                    if bar is not None:
                        bar.update(1)
                    continue
            ss = np.random.SeedSequence([int(seed), 0 if marginalise != "mixture" else d + 2])
            ch = sample_block(target, np.arange(P), x0, cov, ss, part="lf", n_walkers=n_walkers,
                              max_steps=n_steps)
            flats.append(ch.flat())
            taus.append(np.atleast_1d(ch.tau))
            steps.append(ch.n_steps)
            conv_ok.append(bool(ch.converged))
            acc.append(float(np.mean(ch.acceptance_fraction)))
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    for w in caught:
        if not issubclass(w.category, ConvergenceWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if not all(conv_ok):
        warnings.warn(f"fit_lf ({name}): {len(conv_ok) - sum(conv_ok)} of {len(conv_ok)} emcee "
                      f"chain(s) of up to {max(steps)} steps are shorter than 50 autocorrelation "
                      f"times (tau up to {np.max(np.concatenate(taus)):.0f} steps) or tau is "
                      "still changing; raise SamplerSettings.max_steps", ConvergenceWarning,
                      stacklevel=3)
    if marginalise == "mixture":
        # Every draw weighs the same: as many samples from each.
        n_per = min(len(f) for f in flats)
        keep = [f[np.linspace(0, len(f) - 1, n_per).round().astype(int)] for f in flats]
        flat = np.concatenate(keep)
        draw_of = np.repeat(np.arange(post.n_d), n_per)
    else:
        flat, draw_of = flats[0], None
    info = {"n_importance": len(ess_is), "n_chains": len(conv_ok),
            "importance_ess_min": float(min(ess_is)) if ess_is else None,
            "tau": [float(t) for t in np.max(np.array(taus), axis=0)] if taus else None,
            "n_steps": int(max(steps)) if steps else 0, "n_walkers": int(n_walkers),
            "converged": bool(all(conv_ok)),
            "acceptance": float(np.mean(acc)) if acc else None}
    return flat, draw_of, info


def fit_lf(sf, m_obs, *, model: str = "schechter", fix=None, muv_range=None,
           volume: SurveyVolume = SurveyVolume(), m_obs_edges=None, transfer: bool = True,
           bins=None, sampler: SamplerSettings = SamplerSettings(),
           marginalisation: Marginalisation = Marginalisation(), interlopers=None) -> LFResult:
    """Fit a luminosity function phi(M_UV) to the measured magnitudes of observed candidates.

    Method, likelihood, priors and sampling: module docstring.

    Parameters
    ----------
    sf : SelectionFunction, or a list (dict) of them
        The fitted selection function with its injection SED and transfer matrix; several
        (one per field) add their expected counts.
    m_obs : array_like
        Measured detection-band magnitudes of the candidates [AB mag] (the quantity the
        transfer matrix was built from; non-finite values are left out).
    model : {"schechter", "double_power_law" (or "dpl"), "stepwise"}
    fix : dict, optional
        ``{name: value}`` parameters held fixed (:func:`glaciar.lf.models.parse_fix`).
    muv_range : (float, float), optional
        M_UV range of phi [AB mag]; default every M_UV whose image can land in the window
        (stepwise: where the counts per unit phi reach ``STEP_MIN_SENSITIVITY`` of their
        maximum).
    volume : SurveyVolume
        Redshift range (default and at most the simulated one), area and cosmology of
        the counts, as :meth:`SelectionFunction.expected_counts`.
    m_obs_edges : array_like, optional
        Measured-magnitude bins [AB mag]; default :func:`default_window`.
    transfer : bool
        Use the transfer function (else measured magnitude := input magnitude).
    bins : array_like, optional
        Stepwise bin edges [AB mag]; default bins of :func:`step_width` over ``muv_range``.
    sampler : SamplerSettings
        Walkers (default max(32, 2 n_free + 2)), cap on the emcee steps (default
        :data:`LF_MAX_STEPS`; it stops earlier at 50 autocorrelation times), seed and
        progress bar.
    marginalisation : Marginalisation
        How the selection function's draws enter, and how many are used.
    interlopers : bool, optional
        Add the expected interlopers to lambda (:func:`glaciar.lf.predict.interloper_background`;
        default: when the file holds a contamination); ``counts["n_interlopers"]`` then.

    Returns
    -------
    LFResult

    Raises
    ------
    ValueError
        Bad model, ``fix`` naming an unknown parameter (the allowed ones are listed),
        bad ranges, no candidate in the window.
    """
    from ..inference.products import beta_nodes, kcorrection

    sfs = _as_list(sf)
    marginalise = marginalisation.method
    max_sf_draws, max_transfer_draws = (marginalisation.max_sf_draws,
                                        marginalisation.max_transfer_draws)
    n_walkers, seed, progress = sampler.n_walkers, sampler.seed, sampler.progress
    n_steps = LF_MAX_STEPS if sampler.max_steps is None else sampler.max_steps
    area, cosmology = volume.area, volume.cosmology
    if marginalise not in ("mixture", "likelihood"):
        raise ValueError(f"fit_lf: marginalise must be 'mixture' or 'likelihood', not {marginalise!r}")
    # Arguments first: a bad model or --fix fails before anything is computed.
    probe = get_model(model, edges=[0.0, 1.0])
    if probe.name == "stepwise":
        from .models import parse_fix
        parse_fix([f"{k}=0" for k in (fix or {})], "stepwise")
    else:
        probe.check_fix(fix)
    m = np.asarray(m_obs, float).ravel()
    m = m[np.isfinite(m)]
    E = default_window(sfs[0], transfer) if m_obs_edges is None else np.asarray(m_obs_edges, float)
    if E.ndim != 1 or len(E) < 2 or np.any(np.diff(E) <= 0) or not np.all(np.isfinite(E)):
        raise ValueError("fit_lf: m_obs_edges must be >= 2 finite increasing values")
    n_obs = np.histogram(m, E)[0].astype(float)
    inside = (m >= E[0]) & (m <= E[-1])
    n_cand, n_out = int(inside.sum()), int((~inside).sum())
    if n_cand == 0:
        raise ValueError(f"fit_lf: no candidate with m_obs in the window {E[0]:g}-{E[-1]:g} "
                         f"({m.size} with a finite m_obs)")
    z_min, z_max = (None if z is None else float(z) for z in (volume.z_min, volume.z_max))
    s0 = sfs[0]
    zr = s0._z_limits(z_min, z_max, "fit_lf")
    sed = s0.sed
    if sed is None:
        raise ValueError("fit_lf: the selection function records no injection SED")
    # The M_UV cells: M_STEP wide, aligned with the stepwise bins.
    if muv_range is None:
        zz = np.linspace(zr[0], zr[1], 61)
        b, _ = beta_nodes(sed.beta_mean, sed.beta_sd, 7)
        K = kcorrection(zz, b, sed.detection_filter, igm=sed.igm, cosmology=sed.cosmology)
        Me = default_M_edges(s0, E, K, transfer, M_STEP)
        # Outward to the STEP_WIDTH lattice: whole bins for the steps and the binned phi.
        lo = float(np.floor(Me[0] / STEP_WIDTH + 1e-9) * STEP_WIDTH)
        hi = float(np.ceil(Me[-1] / STEP_WIDTH - 1e-9) * STEP_WIDTH)
    else:
        lo, hi = map(float, muv_range)
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            raise ValueError(f"fit_lf: muv_range must be (lo, hi) with hi > lo, not {muv_range}")
    n_draws = min(min(s.n_draws for s in sfs), int(max_sf_draws))

    def kernel(a, b_, n_cells, draws=n_draws):
        Me = np.linspace(a, b_, n_cells + 1)
        vals = 0.0
        ext = 0.0
        for s in sfs:
            vol = SurveyVolume(z_min=z_min, z_max=z_max, area=area, cosmology=cosmology)
            k = count_kernel(s, E, Me, volume=vol, transfer=transfer, draws=draws,
                             transfer_draws=max_transfer_draws, who="fit_lf")
            vals = vals + k.values
            ext = ext + k.extrapolated
        return Me, vals, ext

    edges = None
    if probe.name == "stepwise":
        if bins is None:
            # A look at the kernel (a few draws): where the data say something, and how far
            # one M_UV spreads in m_obs.
            n_c = max(1, int(np.ceil((hi - lo) / M_STEP - 1e-9)))
            Me0, v0, _ = kernel(lo, lo + n_c * M_STEP, n_c, draws=min(4, n_draws))
            v0 = v0.mean(axis=0)
            width = step_width(v0, 0.5 * (E[:-1] + E[1:]))
            if muv_range is None:
                # Bins where the counts per unit phi reach a fraction of their maximum.
                sens = v0.sum(axis=1)
                ok = np.flatnonzero(sens >= STEP_MIN_SENSITIVITY * sens.max())
                lo = float(np.floor(Me0[ok[0]] / STEP_WIDTH + 1e-9) * STEP_WIDTH)
                hi = float(np.ceil(Me0[ok[-1] + 1] / STEP_WIDTH - 1e-9) * STEP_WIDTH)
            n_b = max(1, int(np.ceil((hi - lo) / width - 1e-6)))
            if muv_range is None:
                hi = lo + n_b * width
            edges = np.linspace(lo, hi, n_b + 1)
        else:
            edges = np.asarray(bins, float)
            lo, hi = float(edges[0]), float(edges[-1])
    mdl = get_model(model, edges=edges)
    fixed = mdl.check_fix(fix)
    per = 1 if edges is None else len(edges) - 1
    n_cells = per * max(1, int(np.ceil((hi - lo) / per / M_STEP - 1e-9)))
    Me, vals, ext = kernel(lo, hi, n_cells)
    Mc = 0.5 * (Me[:-1] + Me[1:])
    bg = interloper_background(sfs, E, len(vals), area, interlopers)
    if mdl.name == "stepwise":
        cell_bin = np.clip(np.searchsorted(edges, Mc, side="right") - 1, 0, per - 1)
        basis = np.stack([vals[:, cell_bin == j].sum(axis=1) for j in range(per)])
        post = LFPosterior(mdl, basis, n_obs, fixed, background=bg)
    else:
        post = LFPosterior(mdl, np.moveaxis(vals, 1, 0), n_obs, fixed, M=Mc, background=bg)

    free_b = mdl.bounds[post.free]
    x0 = _start(post, n_obs.sum())
    x_map = _map(post, x0, free_b)
    P = len(post.free)
    nw = max(32, 2 * P + 2) if n_walkers is None else int(n_walkers)
    flat, draw_of, conv = _sample(post, x_map, free_b, nw, int(n_steps), seed, marginalise,
                                  progress, mdl.name)
    samples = post.full(flat)
    q = np.quantile(samples, [0.5, 0.16, 0.84], axis=0)
    params = {n: {"median": float(q[0, i]), "lo68": float(q[1, i]), "hi68": float(q[2, i])}
              for i, n in enumerate(mdl.param_names)}

    # Posterior predictive: each sample with its draw (mixture), or a draw from its
    # posterior weights over the draws (likelihood average).
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(1)[0])
    sel = np.unique(np.linspace(0, len(samples) - 1, min(_N_PRED, len(samples))).round().astype(int))
    pick = samples[sel]
    w = post.responsibilities(pick)
    if draw_of is not None:
        d_pick = draw_of[sel]
    else:
        d_pick = np.array([rng.choice(post.n_d, p=wi) for wi in w])
    lam = post.expected(pick)[np.arange(len(pick)), d_pick]                  # (S, n_k)
    lq = np.quantile(lam, [0.5, 0.16, 0.84], axis=0)
    counts = {"m_lo": E[:-1].copy(), "m_hi": E[1:].copy(), "n_obs": n_obs.astype(np.int64),
              "n_exp": lq[0], "n_exp_lo68": lq[1], "n_exp_hi68": lq[2],
              **({} if bg is None else {"n_interlopers": np.median(bg, axis=0)})}
    # Draws that carry the posterior: 1 / Σ w^2 of the draws' mean weights over the samples.
    wbar = (np.bincount(d_pick, minlength=post.n_d) / len(d_pick) if draw_of is not None
            else w.mean(axis=0))
    conv["sf_draw_ess"] = float(1.0 / np.sum(wbar ** 2))

    # Binned phi: M bins (the steps, or STEP_WIDTH bins over muv_range).
    th_med = q[0]
    # The kernel of the draws as the posterior weighs them.
    wd = wbar if draw_of is not None else post.responsibilities(th_med[None])[0]
    Kbar = np.einsum("d,dmk->mk", wd, vals)                                   # (n_cells, n_k)
    phi_cells = mdl.phi(Mc, th_med)
    if edges is None:
        n_b = max(1, int(round((hi - lo) / STEP_WIDTH)))
        bedges = np.linspace(lo, hi, n_b + 1)
    else:
        bedges = edges
    cb = np.clip(np.searchsorted(bedges, Mc, side="right") - 1, 0, len(bedges) - 2)
    contrib = np.stack([(phi_cells[cb == j, None] * Kbar[cb == j]).sum(axis=0)
                        for j in range(len(bedges) - 1)])                     # (n_b, n_k)
    lam_med = contrib.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(lam_med > 0, contrib / np.where(lam_med > 0, lam_med, 1.0), 0.0)
    nb_obs = share @ n_obs
    nb_exp = contrib.sum(axis=1)
    phi_bar = np.array([phi_cells[cb == j].mean() for j in range(len(bedges) - 1)])
    if mdl.name == "stepwise":
        sq = np.quantile(10.0 ** samples, [0.5, 0.16, 0.84], axis=0)
        phi, plo, phi_hi = sq[0], sq[1], sq[2]
    else:
        glo, ghi = gehrels_limits(nb_obs)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.where(nb_exp > 0, phi_bar / np.where(nb_exp > 0, nb_exp, 1.0), np.nan)
        phi, plo, phi_hi = r * nb_obs, r * glo, r * ghi
    binned = {"M_lo": bedges[:-1].copy(), "M_hi": bedges[1:].copy(),
              "M": 0.5 * (bedges[:-1] + bedges[1:]), "phi": phi, "phi_lo68": plo,
              "phi_hi68": phi_hi, "phi_model": phi_bar, "n_obs": nb_obs, "n_exp": nb_exp,
              "edges": bedges}
    lam_mean = phi_cells @ vals.mean(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac_ext = np.where(lam_mean > 0, (phi_cells @ ext) / np.where(lam_mean > 0, lam_mean, 1.0),
                            0.0)
    frac_ext = np.clip(frac_ext, 0.0, 1.0)
    bad = (frac_ext > COUNTS_EXTRAPOLATION_TOLERANCE) & \
        (frac_ext * lam_med > 0.1 * np.sqrt(np.maximum(lam_med, 1.0)))
    if bad.any():
        k = np.flatnonzero(bad)
        warnings.warn(f"fit_lf: {len(k)} m_obs bin(s) ({E[k[0]]:g}-{E[k[0] + 1]:g} ...) draw up "
                      f"to {frac_ext[bad].max():.0%} of their expected counts from magnitudes "
                      "outside the simulated range (P and the transfer function extrapolated)",
                      stacklevel=2)
    conv.update(n_sf_draws=int(post.n_d), marginalise=marginalise,
                extrapolated_fraction_max=float(frac_ext.max()))
    return LFResult(model=mdl.name, param_names=tuple(mdl.param_names), parameters=params,
                    fixed=dict(fixed), samples=samples, chain=flat, n_candidates=n_cand,
                    n_outside=n_out, counts=counts, binned_phi=binned,
                    muv_range=(float(lo), float(hi)), z_range=(float(zr[0]), float(zr[1])),
                    transfer=bool(transfer), convergence=conv)
