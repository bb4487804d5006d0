"""Fit a luminosity function to observed candidates through the selection function.

The data are the measured detection-band magnitudes m_obs of the candidates (recovered,
selected, finite m_obs), binned in fine bins of m_obs (the transfer matrix's 0.2 mag by
default, over :func:`default_window`).  The model predicts, per selection-function draw d,

    lambda_dk(theta) = Σ_M phi(M; theta) K_d[M, k]

with K_d the count kernel (:func:`glaciar.inference.counts.count_kernel`: P = C S, the
transfer function, the beta average, dV/dz, the area by depth), computed once: a
likelihood evaluation is one matrix product, whatever the number of candidates.

Likelihood: Poisson in every bin, ln L_d = Σ_k [n_k ln lambda_dk - lambda_dk] (ln n_k!
dropped).  **Selection-function uncertainty**: the likelihood is averaged over the
selection function's posterior draws, ln L = ln( (1/D) Σ_d L_d ) (log-mean-exp): the
Monte Carlo estimate, with D draws, of the likelihood marginalised over the selection
function's posterior (the simulations and the catalogue are independent data).  With many
candidates the draws' likelihoods can differ by more than a few units, and then a few
draws carry the average: ``LFResult.convergence["sf_draw_ess"]`` is the effective number
of draws at the posterior median (1 / Σ w_d^2 of the draws' posterior weights); when it
is small, use more draws (``max_sf_draws``).

Priors: uniform (:mod:`glaciar.lf.models`).  Sampling: MAP (L-BFGS-B), its Laplace
covariance, then emcee with the independence, differential-evolution and stretch moves
of :func:`glaciar.inference.sampling.sample_block`, until 50 autocorrelation times or
``n_steps``; burn-in 2 tau, thinning tau / 2.

phi is 0 outside ``muv_range`` (sources outside it are assumed absent: choose it to
cover every M_UV that contributes to the measured-magnitude window; the default does),
and constant in z over ``z_range``.

Arrays in, results out; no file I/O (``glaciar lf``, :func:`glaciar.pipeline.lf.run_lf`,
reads and writes the files).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..inference.counts import (COUNTS_EXTRAPOLATION_TOLERANCE, M_STEP, count_kernel,
                                default_M_edges)
from .models import LFModel, get_model

__all__ = ["LFResult", "LFPosterior", "fit_lf", "expected_counts", "default_window", "step_width",
           "STEP_WIDTH", "WINDOW_BRIGHT_MARGIN", "MAX_SF_DRAWS", "STEP_MIN_SENSITIVITY"]

#: Default width of the stepwise bins and of the binned-phi table [mag].
STEP_WIDTH = 0.5
#: The default measured-magnitude window starts this far inside the simulated range's bright
#: end [mag], so that sources brighter than the simulations scatter into it negligibly.
WINDOW_BRIGHT_MARGIN = 0.4
#: Selection-function draws the likelihood is averaged over (evenly spaced), at most.
MAX_SF_DRAWS = 100
#: Default stepwise bins cover the M_UV where the kernel's counts per unit phi reach this
#: fraction of their maximum (bins beyond would be constrained by the prior alone).
STEP_MIN_SENSITIVITY = 0.01
#: Posterior samples used for the predictive counts and the binned phi.
_N_PRED = 200


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
    chain : ndarray (n_steps, n_walkers, n_free)
        The emcee chain of the free parameters.
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
        ``tau`` (per free parameter, steps), ``burn``, ``thin``, ``n_steps``, ``n_walkers``,
        ``converged``, ``acceptance``, ``n_sf_draws``, ``sf_draw_ess``,
        ``extrapolated_fraction_max``.
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

    def __init__(self, model: LFModel, basis, n_obs, fixed, M=None):
        self.model = model
        self.M = None if M is None else np.asarray(M, float)
        self.n_obs = np.asarray(n_obs, float)
        b = np.asarray(basis, float)
        self.n_d = b.shape[1]
        nz = self.n_obs > 0
        self._nz = self.n_obs[nz]
        self._Kall = b.reshape(b.shape[0], -1)                          # (n_b, D n_k)
        self._Knz = b[:, :, nz].reshape(b.shape[0], -1)                 # (n_b, D n_nz)
        self._Ksum = b.sum(axis=2)                                       # (n_b, D)
        self.fixed = dict(fixed)
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
        if self.model.name == "stepwise":
            return 10.0 ** th
        return self.model.phi(self.M, th)

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
        """Log-mean-exp over the draws (W,)."""
        from scipy.special import logsumexp
        return logsumexp(self.log_like_draws(theta), axis=1) - np.log(self.n_d)

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


def _gehrels(n):
    """1-sigma Poisson limits (Gehrels 1986, eqs. 7 and 11 with S = 1)."""
    n = np.asarray(n, float)
    up = n + np.sqrt(n + 0.75) + 1.0
    nn = np.maximum(n, 1.0)            # the lower limit of n < 1 (apportioned counts) is ~0
    lo = np.where(n >= 1.0, nn * (1 - 1 / (9 * nn) - 1 / (3 * np.sqrt(nn))) ** 3, 0.0)
    return np.maximum(lo, 0.0), up


def _laplace_cov(lp, x, bounds):
    """Inverse of minus the Hessian of ``lp`` at ``x`` (central differences), made positive."""
    P = len(x)
    width = bounds[:, 1] - bounds[:, 0]
    h = 1e-3 * width
    for _ in range(2):
        I, J = np.triu_indices(P)
        E = np.eye(P)
        d1, d2 = E[I] * h[I][:, None], E[J] * h[J][:, None]
        pts = np.concatenate([x + d1 + d2, x + d1 - d2, x - d1 + d2, x - d1 - d2])
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
    """Maximum of the posterior by L-BFGS-B inside the prior box (constraints as penalties)."""
    from scipy.optimize import minimize

    names = post.free_names

    def f(x):
        th = post.full(x)
        pen = 0.0
        if post.model.name == "double_power_law":
            # beta < alpha: a smooth wall for the optimiser (the sampler sees -inf).
            pen = 1e4 * max(0.0, th[0, 3] - th[0, 2] + 1e-3) ** 2
            th = th.copy()
            th[0, 3] = min(th[0, 3], th[0, 2] - 1e-3)
        v = post.log_like(th)[0]
        return -(v if np.isfinite(v) else -1e300) + pen

    res = minimize(f, x0, method="L-BFGS-B", bounds=[tuple(b) for b in bounds],
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


def fit_lf(sf, m_obs, *, model: str = "schechter", fix=None, muv_range=None, z_range=None,
           m_obs_edges=None, transfer: bool = True, bins=None, n_walkers: int | None = None,
           n_steps: int = 5000, seed=0, progress: bool = False, max_sf_draws: int = MAX_SF_DRAWS,
           area=None, cosmology=None) -> LFResult:
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
    z_range : (float, float), optional
        Redshift range; default (and at most) the simulated one.
    m_obs_edges : array_like, optional
        Measured-magnitude bins [AB mag]; default :func:`default_window`.
    transfer : bool
        Use the transfer function (else measured magnitude := input magnitude).
    bins : array_like, optional
        Stepwise bin edges [AB mag]; default bins of :func:`step_width` over ``muv_range``.
    n_walkers : int, optional
        Default max(32, 2 n_free + 2).
    n_steps : int
        Cap on the emcee steps (it stops earlier at 50 autocorrelation times).
    seed : int
    progress : bool
        Show a progress bar of the sampling.
    max_sf_draws : int
        Selection-function draws the likelihood averages over (evenly spaced).
    area, cosmology
        As :meth:`SelectionFunction.expected_counts`.

    Returns
    -------
    LFResult

    Raises
    ------
    ValueError
        Bad model, ``fix`` naming an unknown parameter (the allowed ones are listed),
        bad ranges, no candidate in the window.
    """
    from ..inference.sampling import ConvergenceWarning, sample_block
    from ..inference.selection_function import beta_nodes, kcorrection

    sfs = _as_list(sf)
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
    z_min, z_max = (None, None) if z_range is None else map(float, z_range)
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
            k = count_kernel(s, E, Me, z_min=z_min, z_max=z_max, transfer=transfer,
                             draws=draws, area=area, cosmology=cosmology, who="fit_lf")
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
    if mdl.name == "stepwise":
        cell_bin = np.clip(np.searchsorted(edges, Mc, side="right") - 1, 0, per - 1)
        basis = np.stack([vals[:, cell_bin == j].sum(axis=1) for j in range(per)])
        post = LFPosterior(mdl, basis, n_obs, fixed)
    else:
        post = LFPosterior(mdl, np.moveaxis(vals, 1, 0), n_obs, fixed, M=Mc)

    free_b = mdl.bounds[post.free]
    x0 = _start(post, n_obs.sum())
    x_map = _map(post, x0, free_b)
    cov = _laplace_cov(post, x_map, free_b)
    P = len(post.free)
    nw = max(32, 2 * P + 2) if n_walkers is None else int(n_walkers)
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(desc=f"lf {mdl.name}", unit="step", total=int(n_steps), leave=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        ch = sample_block(post, np.arange(P), x_map, cov, np.random.SeedSequence(seed),
                          part="lf", n_walkers=nw, max_steps=int(n_steps),
                          callback=None if bar is None else bar.update)
    if bar is not None:
        bar.close()
    if not ch.converged:
        warnings.warn(f"fit_lf ({mdl.name}): the emcee chain of {ch.chain.shape[0]} steps is "
                      f"shorter than 50 autocorrelation times (tau = {np.max(ch.tau):.0f} steps) "
                      "or tau is still changing; raise n_steps", ConvergenceWarning, stacklevel=2)
    for w in caught:
        if not issubclass(w.category, ConvergenceWarning):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    flat = ch.chain[ch.burn::ch.thin].reshape(-1, P)
    samples = post.full(flat)
    q = np.quantile(samples, [0.5, 0.16, 0.84], axis=0)
    params = {n: {"median": float(q[0, i]), "lo68": float(q[1, i]), "hi68": float(q[2, i])}
              for i, n in enumerate(mdl.param_names)}

    # Posterior predictive: each sample with a draw from its posterior weights over draws.
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(1)[0])
    pick = samples[np.unique(np.linspace(0, len(samples) - 1, min(_N_PRED, len(samples)))
                             .round().astype(int))]
    lld = post.log_like_draws(pick)
    w = np.exp(lld - lld.max(axis=1, keepdims=True))
    w /= w.sum(axis=1, keepdims=True)
    d_pick = np.array([rng.choice(post.n_d, p=wi) for wi in w])
    lam = post.expected(pick)[np.arange(len(pick)), d_pick]                  # (S, n_k)
    lq = np.quantile(lam, [0.5, 0.16, 0.84], axis=0)
    counts = {"m_lo": E[:-1].copy(), "m_hi": E[1:].copy(), "n_obs": n_obs.astype(np.int64),
              "n_exp": lq[0], "n_exp_lo68": lq[1], "n_exp_hi68": lq[2]}

    # Binned phi: M bins (the steps, or STEP_WIDTH bins over muv_range).
    th_med = q[0]
    lld_med = post.log_like_draws(th_med[None])[0]
    wd = np.exp(lld_med - lld_med.max())
    wd /= wd.sum()
    ess = float(1.0 / np.sum(wd ** 2))
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
        glo, ghi = _gehrels(nb_obs)
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
    acc = float(np.mean(ch.acceptance_fraction))
    conv = {"tau": [float(t) for t in np.atleast_1d(ch.tau)], "burn": int(ch.burn),
            "thin": int(ch.thin), "n_steps": int(ch.chain.shape[0]), "n_walkers": int(nw),
            "converged": bool(ch.converged), "acceptance": acc, "n_sf_draws": int(post.n_d),
            "sf_draw_ess": ess, "extrapolated_fraction_max": float(frac_ext.max())}
    return LFResult(model=mdl.name, param_names=tuple(mdl.param_names), parameters=params,
                    fixed=dict(fixed), samples=samples, chain=ch.chain, n_candidates=n_cand,
                    n_outside=n_out, counts=counts, binned_phi=binned,
                    muv_range=(float(lo), float(hi)), z_range=(float(zr[0]), float(zr[1])),
                    transfer=bool(transfer), convergence=conv)


def expected_counts(sf, phi, m_obs_edges, *, params=None, **kw):
    """Expected counts per measured-magnitude bin for a luminosity function.

    Parameters
    ----------
    sf : SelectionFunction
    phi : callable or str
        ``phi(M, z)`` [Mpc^-3 mag^-1], or a model name ("schechter", "double_power_law")
        evaluated at ``params``.
    m_obs_edges : array_like
        Measured-magnitude bins [AB mag].
    params : dict, optional
        The model's parameters, by name (with a model name).
    **kw
        :meth:`glaciar.inference.SelectionFunction.expected_counts`'s keywords.

    Returns
    -------
    glaciar.inference.counts.ExpectedCounts
    """
    if isinstance(phi, str):
        mdl = get_model(phi)
        missing = [n for n in mdl.param_names if n not in (params or {})]
        if missing:
            raise ValueError(f"expected_counts: model {mdl.name!r} needs {', '.join(missing)}")
        th = np.array([float(params[n]) for n in mdl.param_names])

        def phi(M, z, th=th, mdl=mdl):
            return mdl.phi(np.asarray(M, float) + 0 * np.asarray(z, float), th)
    return sf.expected_counts(phi, m_obs_edges, **kw)
