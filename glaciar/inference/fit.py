"""Fit the surfaces: aggregate the flags, find the MAP, sample with emcee.

Sampler design
--------------
The posterior is sampled with :class:`emcee.EnsembleSampler` (vectorised
log-probability) using a mixture of three Metropolis-Hastings moves that all
leave the posterior invariant:

- an *independence* move (30 %) whose proposal is a multivariate Student t
  (5 degrees of freedom), started from the MAP and the Laplace covariance
  (the inverse Hessian of the log posterior) and re-fitted to the stages of
  a discarded pilot run until it is stable (:data:`PILOT_STAGES`).  With
  thousands of sources the posterior is close to Gaussian, acceptance is
  high and the integrated autocorrelation time tau is a few steps;
- emcee's differential-evolution move (30 %) and stretch move (40 %), which
  keep the ensemble mixing where the posterior is far from Gaussian (small
  data sets, parameters bounded by the data on one side only, such as a
  selection edge outside the simulated z range).  Against the earlier
  60/20/20 weights they cut tau of such an edge from ~290 to ~70 steps, at
  the price of tau ~7 instead of ~3 steps where the posterior is Gaussian.

Convergence: the chain is extended in blocks until it is at least 50 tau long
(tau the largest per-parameter integrated autocorrelation time, estimated as
:func:`emcee.autocorr.integrated_time` does, vectorised in :func:`_tau`) and
that largest tau changed by less than 10 % since the previous block, or until
``max_steps``; a :class:`ConvergenceWarning` is issued otherwise.  Burn-in is
2 tau, thinning tau / 2.

Cost per step: the log posterior of a block is :class:`BlockPosterior`
(terms shared by cells evaluated once, one log1p and one log per cell), and
emcee's red-blue moves run with a vectorised accept step (bit-identical
chains).  More weight on the independence move (80 %) lowers tau at 1e6
sources, but lets walkers stick in a heavy tail (logit
S_max of a sharp, nearly complete selection: tau 75 instead of 11 steps on
the 2800-source test data).

Aggregation (exact, or with a stated resolution)
------------------------------------------------
Sources with identical (z, mag_input) give identical Bernoulli terms; summing
them into binomial counts is exact.  When ``mag_input`` is continuous (it
varies with the UV slope), sources are grouped by z and by ``mag_input``
rounded to ``mag_resolution`` (default 0.01 mag), and each group is evaluated
at its mean ``mag_input``.  This is a Berkson-type grouping: the fit sees the
true step convolved with the within-group scatter (variance <= res^2 / 12),
which leaves m50 unbiased to first order and widens w by a relative
0.15 * res^2 / (12 w^2) = 1.3e-4 (0.1 mag / w)^2 at res = 0.01 mag -- far
below the posterior width of w for any realistic run (tested against the
exact per-source likelihood).
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import emcee
import numpy as np
import pandas as pd
from scipy import optimize

from ..constants import COL_DEPTH, COL_MAG_INPUT, COL_RECOVERED, COL_SELECTED, COL_Z
from .models import Cells, SurfaceModel

__all__ = ["ConvergenceWarning", "aggregate_cells", "find_map", "laplace_covariance",
           "FitResult", "fit_surfaces", "DEFAULT_MAG_RESOLUTION"]

DEFAULT_MAG_RESOLUTION = 0.01    #: [mag] grouping resolution for continuous mag_input
_T_DOF = 5.0                      # Student-t proposal degrees of freedom
_MOVE_WEIGHTS = (0.3, 0.3, 0.4)   # independence, differential evolution, stretch
#: Stages of the discarded pilot run that sets the independence proposal [steps];
#: it stops after the second stage once the proposal is stable.  A single 50-step
#: pilot left tau underestimated by 30-50 % where an edge lies outside the data.
PILOT_STAGES = (50, 150, 400, 1000, 2500)
#: Default cap on each block's chain length per call [steps].
DEFAULT_MAX_STEPS = 20000


class ConvergenceWarning(UserWarning):
    """The chain stopped at ``max_steps`` before reaching 50 autocorrelation times."""


# --------------------------------------------------------------------------
# Aggregation
# --------------------------------------------------------------------------
def _flags(df: pd.DataFrame, col: str) -> np.ndarray:
    """A recovered/selected column as bool; NaN or values other than 0/1/True/False are an error."""
    v = df[col].to_numpy()
    if v.dtype == bool:
        return v
    bad = None
    try:
        f = np.asarray(v, dtype=float)
        bad = ~np.isin(f, (0.0, 1.0))          # NaN is not in {0, 1}
    except (TypeError, ValueError):
        bad = np.ones(len(v), bool)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"column {col!r} must be boolean: {int(bad.sum())} of {len(v)} values "
                         f"are not True/False (first: row {i}, value {v[i]!r})")
    return f.astype(bool)


def aggregate_cells(df: pd.DataFrame, mag_resolution: float | None = DEFAULT_MAG_RESOLUTION,
                    depth_ref: float | None = None, mag_column: str = COL_MAG_INPUT) -> Cells:
    """Sum per-source flags into binomial counts per (z, magnitude) cell.

    Parameters
    ----------
    df : pandas.DataFrame
        Per-source rows with columns ``z``, ``mag_column`` [mag], ``recovered``
        and ``selected`` (booleans; selected implies recovered) and, for a
        depth-aware fit, ``depth_local`` [AB mag].
    mag_resolution : float or None
        Magnitude grouping resolution [mag]; ``None`` or 0 groups identical
        values only (exact).  See the module docstring for its accuracy.
    depth_ref : float, optional
        Reference depth [AB mag] of a depth-aware model: the cells' magnitude
        is then ``m - (depth_local - depth_ref)``.
    mag_column : str
        The magnitude covariate: ``mag_input`` (apparent, detection band) or
        ``M_uv`` for an absolute-magnitude run.

    Returns
    -------
    Cells

    Raises
    ------
    ValueError
        A column is missing, a flag is NaN or not boolean, a selected source
        is not recovered, or nothing is left to fit.
    """
    need = [COL_Z, mag_column, COL_RECOVERED, COL_SELECTED] + ([COL_DEPTH] if depth_ref is not None else [])
    for col in need:
        if col not in df.columns:
            raise ValueError(f"per-source table lacks column {col!r} (have {list(df.columns)})")
    z = df[COL_Z].to_numpy(float)
    m = df[mag_column].to_numpy(float)
    if depth_ref is not None:
        m = m - (df[COL_DEPTH].to_numpy(float) - float(depth_ref))
    rec = _flags(df, COL_RECOVERED)
    sel = _flags(df, COL_SELECTED)
    good = np.isfinite(z) & np.isfinite(m)
    if not good.all():
        what = "z, magnitude or depth" if depth_ref is not None else "z or magnitude"
        warnings.warn(f"aggregate_cells: dropping {np.sum(~good)} sources with non-finite {what}")
        z, m, rec, sel = z[good], m[good], rec[good], sel[good]
    if np.any(sel & ~rec):
        raise ValueError(f"{np.sum(sel & ~rec)} sources are selected but not recovered; "
                         "'selected' must imply 'recovered'")
    if z.size == 0:
        raise ValueError("aggregate_cells: no sources to fit")
    mkey = np.round(m / mag_resolution) if mag_resolution else m
    _, zi = np.unique(z, return_inverse=True)
    _, mi = np.unique(mkey, return_inverse=True)
    key = zi.astype(np.int64) * (int(mi.max()) + 1) + mi
    ukey, inv = np.unique(key, return_inverse=True)
    nc = len(ukey)
    n = np.bincount(inv, minlength=nc)
    return Cells(z=np.bincount(inv, weights=z, minlength=nc) / n,
                 mag=np.bincount(inv, weights=m, minlength=nc) / n,
                 n=n.astype(np.int64),
                 k_rec=np.bincount(inv, weights=rec, minlength=nc).astype(np.int64),
                 k_sel=np.bincount(inv, weights=sel, minlength=nc).astype(np.int64))


# --------------------------------------------------------------------------
# MAP and Laplace approximation
# --------------------------------------------------------------------------
def _heuristic_start(model: SurfaceModel, cells: Cells) -> np.ndarray:
    """A data-driven starting point: m50 where the pooled recovered fraction halves."""
    theta = model.prior_mean.copy()
    names = model.param_names
    order = np.argsort(cells.mag)
    n = np.cumsum(cells.n[order])
    k = np.cumsum(cells.k_rec[order])
    frac_bright = k / n                                # recovered fraction brighter than m
    # Where the fraction of recovered sources among those fainter than m drops below half
    # of the overall bright-end fraction.
    nf = n[-1] - n + cells.n[order]
    kf = k[-1] - k + cells.k_rec[order]
    with np.errstate(invalid="ignore", divide="ignore"):
        f_faint = kf / nf
    top = np.nanmax(frac_bright[: max(1, len(order) // 10)])
    below = np.nonzero(f_faint < 0.5 * top)[0]
    if len(below) and 0 < top < 1 + 1e-12:
        theta[names.index("m50_0")] = cells.mag[order][below[0]]
        theta[names.index("logit_c_max_0")] = np.log((top + 0.01) / (1.01 - top))
    return theta


def _neg_log_post_and_grad(lp_fn, h):
    def fg(x):
        # Central differences, all 2P+1 points in one vectorised call.
        P = len(x)
        pts = np.repeat(x[None, :], 2 * P + 1, axis=0)
        idx = np.arange(P)
        pts[1 + idx, idx] += h
        pts[1 + P + idx, idx] -= h
        lp = lp_fn(pts)
        if not np.isfinite(lp[0]):
            return np.inf, np.zeros(P)
        g = (lp[1:P + 1] - lp[P + 1:]) / (2 * h)
        g = np.where(np.isfinite(g), g, 0.0)
        return -lp[0], -g
    return fg


def find_map(model: SurfaceModel, cells: Cells, starts=None) -> np.ndarray:
    """Maximum a posteriori parameters (BFGS from several starts).

    The posterior factorises into the completeness and the selection blocks
    (:meth:`SurfaceModel.block_indices`), so each block is maximised on its
    own (smaller problems, fewer iterations); the best start is kept per block.

    Parameters
    ----------
    model : SurfaceModel
    cells : Cells
    starts : sequence of ndarray, optional
        Starting points (full parameter vectors); default the prior mean and
        a data-driven guess.

    Returns
    -------
    ndarray, shape (P,)
    """
    if starts is None:
        starts = [_heuristic_start(model, cells), model.prior_mean]
    starts = [np.asarray(x0, float) for x0 in starts]
    out = np.array(starts[0], float)
    for part in ("c", "s"):
        lp_fn = model.block_log_posterior(cells, part)
        idx = lp_fn.index
        fg = _neg_log_post_and_grad(lp_fn, 1e-5 * model.prior_sd[idx])
        best, tried = None, []
        for x0 in starts:
            xb = x0[idx]
            if any(np.array_equal(xb, t) for t in tried):
                continue                      # same start for this block: same optimum
            tried.append(xb)
            # BFGS: for <= 20 parameters its dense update is cheaper than L-BFGS-B's overhead.
            res = optimize.minimize(fg, xb, jac=True, method="BFGS",
                                    options={"maxiter": 2000, "gtol": 1e-6})
            if np.isfinite(res.fun) and (best is None or res.fun < best.fun):
                best = res
        if best is None:
            raise RuntimeError("MAP search failed: the log posterior is not finite at any start")
        out[idx] = best.x
    return out


def laplace_covariance(model: SurfaceModel, cells: Cells, theta_map, part: str = "both") -> np.ndarray:
    """Inverse of minus the Hessian of the log posterior at ``theta_map``.

    The Hessian is taken by central differences (one vectorised call) with
    steps of 0.1 posterior sigma, refined once; eigenvalues are floored so the
    result is positive definite.  With ``part`` "c" or "s" only that block of
    parameters (:meth:`SurfaceModel.block_indices`) is returned.
    """
    full = np.asarray(theta_map, float)
    idx = np.arange(model.n_params) if part == "both" else model.block_indices(part)
    x = full[idx]
    P = len(x)
    sd = model.prior_sd[idx]
    h = 1e-3 * sd

    if part == "both":
        def lp(pts):
            return model.log_posterior(pts, cells, part)
    else:
        lp = model.block_log_posterior(cells, part)

    for _ in range(2):
        H = _hessian(lp, x, h)
        w, V = np.linalg.eigh(-H)
        w = np.maximum(w, 1e-8 * max(w.max(), 1e-300) + 1e-12)
        cov = (V / w) @ V.T
        h = np.clip(0.1 * np.sqrt(np.diag(cov)), 1e-7 * sd, sd)
    cov = 0.5 * (cov + cov.T)
    return cov + 1e-12 * np.eye(P) * np.max(np.diag(cov))


def _hessian(lp_fn, x, h):
    P = len(x)
    I, J = np.triu_indices(P)
    E = np.eye(P)
    d1, d2 = E[I] * h[I][:, None], E[J] * h[J][:, None]
    pts = np.concatenate([x + d1 + d2, x + d1 - d2, x - d1 + d2, x - d1 - d2])
    lp = lp_fn(pts)
    k = len(I)
    f_pp, f_pm, f_mp, f_mm = lp[:k], lp[k:2 * k], lp[2 * k:3 * k], lp[3 * k:]
    H = np.empty((P, P))
    off = (f_pp - f_pm - f_mp + f_mm) / (4 * h[I] * h[J])
    # On the diagonal d1 = d2, so f_pm = f_mp = f0 and the formula is f(x+2h)-2f+f(x-2h) over 4h^2.
    H[I, J] = off
    H[J, I] = off
    return H


# --------------------------------------------------------------------------
# Sampler
# --------------------------------------------------------------------------
class _StudentT:
    """Multivariate Student t proposal: draws and log density (up to a constant)."""

    def __init__(self, mean, cov, dof=_T_DOF):
        self.mean = np.asarray(mean, float)
        self.cov = np.asarray(cov, float)
        self.L = np.linalg.cholesky(cov)
        self.Linv = np.linalg.inv(self.L)
        self.dof = dof

    def draw(self, n, rng):
        P = len(self.mean)
        g = rng.standard_normal((n, P)) @ self.L.T
        chi2 = rng.chisquare(self.dof, size=n)
        return self.mean + g * np.sqrt(self.dof / chi2)[:, None]

    def logpdf(self, x):
        d = (np.asarray(x) - self.mean) @ self.Linv.T
        return -0.5 * (self.dof + len(self.mean)) * np.log1p(np.sum(d * d, axis=-1) / self.dof)

    def proposal(self, coords, rng):
        new = self.draw(len(coords), rng)
        return new, self.logpdf(coords) - self.logpdf(new)


class _VectorisedRedBlue:
    """Mixin: emcee's red-blue ``propose`` with the accept/reject loop vectorised.

    emcee draws one uniform per walker in a Python loop; ``random.rand(n)``
    draws the same numbers from the same stream in the same order, so the
    chains are bit-identical to emcee's own move (tested), at a fraction of
    the per-step cost when the log-probability is cheap.
    """

    def propose(self, model, state):
        nwalkers, ndim = state.coords.shape
        if nwalkers < 2 * ndim and not self.live_dangerously:
            raise RuntimeError("a red-blue move needs at least twice as many walkers as dimensions")
        self.setup(state.coords)
        accepted = np.zeros(nwalkers, dtype=bool)
        inds = np.arange(nwalkers) % self.nsplits
        if self.randomize_split:
            model.random.shuffle(inds)
        for split in range(self.nsplits):
            S1 = inds == split
            sets = [state.coords[inds == j] for j in range(self.nsplits)]
            q, factors = self.get_proposal(sets[split], sets[:split] + sets[split + 1:], model.random)
            new_log_probs, new_blobs = model.compute_log_prob_fn(q)
            lnpdiff = factors + new_log_probs - state.log_prob[S1]
            accepted[S1] = lnpdiff > np.log(model.random.rand(len(lnpdiff)))
            state = self.update(state, emcee.State(q, log_prob=new_log_probs, blobs=new_blobs),
                                accepted, S1)
        return state, accepted


class _DEMove(_VectorisedRedBlue, emcee.moves.DEMove):
    pass


class _StretchMove(_VectorisedRedBlue, emcee.moves.StretchMove):
    pass


@dataclass
class BlockChain:
    """The emcee chain of one parameter block ("c": completeness, "s": selection).

    Attributes
    ----------
    part : str
    index : ndarray of int
        Positions of the block's parameters in the full parameter vector.
    chain : ndarray (n_steps, n_walkers, n_block)
    log_prob : ndarray (n_steps, n_walkers)
    n_accepted : ndarray (n_walkers,)
        Accepted proposals per walker over the whole chain.
    tau : ndarray (n_block,)
        Integrated autocorrelation time per parameter [steps].
    burn, thin : int
    converged : bool
    random_state : tuple
        State of the block sampler's random generator at the end (for resuming).
    laplace_cov : ndarray (n_block, n_block)
        Covariance of the independence proposal (Laplace, re-estimated by the pilot).
    proposal_mean : ndarray (n_block,)
        Centre of the independence proposal.
    """

    part: str
    index: np.ndarray
    chain: np.ndarray
    log_prob: np.ndarray
    n_accepted: np.ndarray
    tau: np.ndarray
    burn: int
    thin: int
    converged: bool
    random_state: tuple
    laplace_cov: np.ndarray
    proposal_mean: np.ndarray

    @property
    def n_steps(self) -> int:
        return self.chain.shape[0]

    @property
    def acceptance_fraction(self) -> np.ndarray:
        return self.n_accepted / max(self.n_steps, 1)

    def flat(self) -> np.ndarray:
        return self.chain[self.burn::self.thin].reshape(-1, self.chain.shape[-1])

    @property
    def ess(self) -> np.ndarray:
        """Effective sample size per parameter: walkers x (steps - burn-in) / tau."""
        return self.chain.shape[1] * (self.n_steps - self.burn) / np.maximum(self.tau, 1.0)

    @property
    def split_rhat(self) -> np.ndarray:
        """Split R-hat per parameter (Gelman et al. 2013), each walker's post-burn-in
        chain split in halves and treated as a chain; ~1 when the walkers agree."""
        return split_rhat(self.chain[self.burn:])


@dataclass
class FitResult:
    """The outcome of :func:`fit_surfaces`.

    The posterior factorises into the completeness parameters (recovered
    flags) and the selection parameters (selected-given-recovered flags), so
    each block is sampled by its own ensemble; a joint draw pairs the i-th
    draws of the two blocks, which are independent.

    Attributes
    ----------
    model : SurfaceModel
    theta_map : ndarray (P,)
    blocks : list of BlockChain
    wall_time : float
        Seconds spent in this call (MAP + sampling).
    info : dict
    """

    model: SurfaceModel
    theta_map: np.ndarray
    blocks: list
    wall_time: float = 0.0
    info: dict = field(default_factory=dict)

    def _per_param(self, attr):
        out = np.empty(self.model.n_params)
        for b in self.blocks:
            out[b.index] = getattr(b, attr) if np.ndim(getattr(b, attr)) else getattr(b, attr)
        return out

    @property
    def tau(self) -> np.ndarray:
        """Integrated autocorrelation time per parameter [steps of its block's chain]."""
        return self._per_param("tau")

    @property
    def converged(self) -> bool:
        return all(b.converged for b in self.blocks)

    @property
    def ess(self) -> np.ndarray:
        """Effective sample size per parameter (see :attr:`BlockChain.ess`)."""
        return self._per_param("ess")

    @property
    def split_rhat(self) -> np.ndarray:
        """Split R-hat per parameter (see :func:`split_rhat`)."""
        return self._per_param("split_rhat")

    @property
    def acceptance_fraction(self) -> np.ndarray:
        """Mean acceptance fraction of each block's walkers, per parameter."""
        out = np.empty(self.model.n_params)
        for b in self.blocks:
            out[b.index] = np.mean(b.acceptance_fraction)
        return out

    @property
    def n_steps(self) -> np.ndarray:
        return self._per_param("n_steps")

    def draws(self, max_draws: int | None = 4000) -> np.ndarray:
        """Joint posterior draws (after burn-in and thinning), shape (n, P).

        ``n`` is the smaller of the blocks' draw counts and ``max_draws``;
        each block's draws are taken evenly spaced along its thinned chain.
        """
        flats = [b.flat() for b in self.blocks]
        n = min(len(f) for f in flats)
        if max_draws is not None:
            n = min(n, int(max_draws))
        out = np.empty((n, self.model.n_params))
        for b, f in zip(self.blocks, flats):
            out[:, b.index] = f[np.linspace(0, len(f) - 1, n).round().astype(int)]
        return out


def _tau(chain, c: float = 5.0) -> np.ndarray:
    """Integrated autocorrelation time per parameter of an ensemble chain [steps].

    The estimator of :func:`emcee.autocorr.integrated_time` (tol=0): the
    normalised autocorrelation function of each walker, averaged over the
    walkers, summed up to Sokal's window M >= c tau.  Vectorised over walkers
    (one FFT per parameter instead of one per walker and parameter); equal to
    emcee's to rounding (tested to 1e-10).

    Parameters
    ----------
    chain : ndarray (n_steps, n_walkers, n_params)

    Returns
    -------
    ndarray (n_params,)
    """
    x = np.asarray(chain, float)
    n = x.shape[0]
    nfft = 2 * (1 << max(0, int(n - 1).bit_length()))          # emcee: 2 * next power of two
    out = np.empty(x.shape[2])
    steps = np.arange(n)
    for d in range(x.shape[2]):
        y = x[:, :, d]
        f = np.fft.rfft(y - y.mean(axis=0), n=nfft, axis=0)
        acf = np.fft.irfft(f.real ** 2 + f.imag ** 2, n=nfft, axis=0)[:n]
        with np.errstate(invalid="ignore", divide="ignore"):
            rho = np.mean(acf / acf[0], axis=1)
        taus = 2.0 * np.cumsum(rho) - 1.0
        m = steps < c * taus
        out[d] = taus[int(np.argmin(m)) if np.any(m) else n - 1]
    return out


def split_rhat(chain) -> np.ndarray:
    """Split R-hat of an ensemble chain (n_steps, n_walkers, n_params), per parameter.

    Every walker's chain is split in two halves; with m = 2 W chains of n
    steps, R-hat = sqrt(((n - 1)/n W_within + B/n) / W_within) (Gelman et al.
    2013, BDA3 eq. 11.4 with split chains).
    """
    x = np.asarray(chain, float)
    n = x.shape[0] // 2
    if n < 2:
        return np.full(x.shape[-1], np.nan)
    halves = np.concatenate([x[:n], x[-n:]], axis=1)          # (n, 2W, P)
    means = halves.mean(axis=0)
    within = halves.var(axis=0, ddof=1).mean(axis=0)
    between = n * means.var(axis=0, ddof=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(((n - 1) / n * within + between / n) / within)


def _sample_block(model, cells, part, theta_map, cov, seed, n_walkers, max_steps, min_steps,
                  block, callback, resume: BlockChain | None):
    idx = model.block_indices(part)
    P = len(idx)
    base = np.asarray(theta_map, float)

    log_prob = model.block_log_posterior(cells, part)

    if n_walkers is None:
        n_walkers = max(32, 2 * P + 2)
    n_walkers = int(n_walkers) + int(n_walkers) % 2
    if n_walkers < 2 * P:
        raise ValueError(f"n_walkers={n_walkers} must be at least 2 * n_params = {2 * P}")
    if resume is not None:
        cov = resume.laplace_cov
        n_walkers = resume.chain.shape[1]
    prop = _StudentT(base[idx], cov) if resume is None else _StudentT(resume.proposal_mean, cov)
    moves = [(mv, w) for mv, w in zip((emcee.moves.MHMove(prop.proposal), _DEMove(),
                                       _StretchMove()), _MOVE_WEIGHTS) if w > 0]
    # emcee converts the returned log-probabilities one walker at a time; a list of
    # Python floats makes that loop several times cheaper than an ndarray.
    sampler = emcee.EnsembleSampler(n_walkers, P, lambda x: log_prob(x).tolist(), moves=moves,
                                    vectorize=True)
    if resume is None:
        rs = np.random.RandomState(seed.generate_state(8))
        # Walkers start from the (over-dispersed) t proposal: near stationarity already.
        p0 = prop.draw(n_walkers, rs)
        lp0 = log_prob(p0)
        for _ in range(100):
            bad = ~np.isfinite(lp0)
            if not bad.any():
                break
            p0[bad] = prop.draw(int(bad.sum()), rs)
            lp0[bad] = log_prob(p0[bad])
        if not np.all(np.isfinite(lp0)):
            raise RuntimeError("could not place walkers where the posterior is finite")
        state = emcee.State(p0, log_prob=lp0, random_state=rs.get_state())
        # Pilot run, discarded: re-centre and re-scale the independence proposal on
        # the pilot's second half, which follows skewed posteriors (a C_max or S_max
        # near 1, an edge outside the data) far better than the Laplace approximation.
        # Stages of growing length, each re-fitting the proposal to the second half of
        # its chain, until the proposal's centre and spread stop changing: a posterior
        # bounded on one side only (an edge outside the simulated range, an edge
        # between two simulated redshifts) is explored by the differential-evolution
        # and stretch moves, and the proposal widens to it.  The chain proper then
        # runs with a fixed proposal (no adaptation), so it is a valid MCMC.
        for stage in PILOT_STAGES:
            sampler.reset()
            state = sampler.run_mcmc(state, stage, progress=False, skip_initial_state_check=True)
            pil = sampler.get_chain()[stage // 2:].reshape(-1, P)
            pcov = np.cov(pil, rowvar=False)
            old_mean, old_sd = prop.mean.copy(), np.sqrt(np.diag(prop.cov))
            try:
                prop.__init__(pil.mean(axis=0),
                              0.5 * (pcov + pcov.T) + 1e-12 * np.diag(np.diag(cov)))
                cov = prop.cov
            except np.linalg.LinAlgError:
                continue
            sd = np.sqrt(np.diag(prop.cov))
            if (stage >= PILOT_STAGES[1] and np.all(np.abs(prop.mean - old_mean) < 0.2 * sd)
                    and np.all(np.abs(np.log(sd / old_sd)) < 0.2)):
                break
        sampler.reset()
        chains, lps, n_acc = [], [], np.zeros(n_walkers)
    else:
        state = emcee.State(resume.chain[-1].copy(), log_prob=resume.log_prob[-1].copy(),
                            random_state=resume.random_state)
        chains, lps, n_acc = [resume.chain], [resume.log_prob], resume.n_accepted.copy()

    done = sum(c.shape[0] for c in chains)
    # max_steps counts the steps of this call, so a re-run continues past an earlier cap.
    limit = done + int(max_steps)
    tau_prev, tau = None, None
    converged = False
    while True:
        if done >= min_steps:
            tau = _tau(np.concatenate(chains))
            # The 50-tau rule is on the largest tau; its stability is judged on the same
            # number (per-parameter estimates of short chains scatter by ~10 % each).
            tmax_now = float(np.max(tau))
            converged = (done >= 50 * tmax_now and tau_prev is not None
                         and abs(tmax_now - float(np.max(tau_prev))) < 0.1 * tmax_now)
            tau_prev = tau
            if converged or done >= limit:
                break
        nb = min(block, limit - done)
        if nb <= 0:
            break
        sampler.reset()
        state = sampler.run_mcmc(state, nb, progress=False, skip_initial_state_check=True)
        chains.append(sampler.get_chain())
        lps.append(sampler.get_log_prob())
        n_acc = n_acc + sampler.backend.accepted
        done += nb
        if callback is not None:
            callback(nb)
    chain = np.concatenate(chains)
    if tau is None:
        tau = _tau(chain)
    tmax = float(np.max(tau))
    if not converged:
        warnings.warn(f"emcee chain ({part} block) of {done} steps is shorter than 50 "
                      f"autocorrelation times (tau = {tmax:.1f} steps) or tau is still changing; "
                      f"raise max_steps (this call ran {max_steps}) or re-run the fit to extend it",
                      ConvergenceWarning, stacklevel=3)
    return BlockChain(part=part, index=idx, chain=chain, log_prob=np.concatenate(lps),
                      n_accepted=n_acc, tau=tau, burn=min(int(math.ceil(2 * tmax)), done // 2),
                      thin=max(1, int(0.5 * float(np.min(tau)))), converged=bool(converged),
                      random_state=state.random_state, laplace_cov=cov,
                      proposal_mean=prop.mean)


def fit_surfaces(cells: Cells, model: SurfaceModel, *, seed=0, n_walkers: int | None = None,
                 max_steps: int = DEFAULT_MAX_STEPS, min_steps: int = 100, block: int = 100,
                 callback=None, resume: FitResult | None = None,
                 theta_map=None) -> FitResult:
    """MAP start, then emcee until 50 autocorrelation times or ``max_steps``.

    Parameters
    ----------
    cells : Cells
        Aggregated counts (:func:`aggregate_cells`).
    model : SurfaceModel
    seed : int or sequence of int
        Seed of the samplers' random streams; same seed, same chains.
    n_walkers : int, optional
        Walkers per block; default ``max(32, 2 * P_block + 2)``.
    max_steps : int
        Cap on the steps each block runs in this call (a resumed chain may
        grow by this much past its earlier length).
    min_steps : int
        Shortest chain considered for convergence [steps].
    block : int
        Steps between convergence checks.
    callback : callable, optional
        Called with the number of steps just run (for a progress bar at the edge).
    resume : FitResult, optional
        A previous result of the same model and data to extend: sampling
        continues from its last state and random state (bit-identical to an
        uninterrupted run with the same ``block`` schedule).
    theta_map : ndarray, optional
        Skip the MAP search.

    Returns
    -------
    FitResult
    """
    t0 = time.perf_counter()
    if resume is not None:
        theta_map = resume.theta_map
    if theta_map is None:
        theta_map = find_map(model, cells)
    seeds = np.random.SeedSequence(seed).spawn(2)
    blocks = []
    for i, part in enumerate(("c", "s")):
        prev = None if resume is None else resume.blocks[i]
        cov = None if prev is not None else laplace_covariance(model, cells, theta_map, part)
        blocks.append(_sample_block(model, cells, part, theta_map, cov, seeds[i], n_walkers,
                                    max_steps, min_steps, block, callback, prev))
    return FitResult(model=model, theta_map=np.asarray(theta_map, float), blocks=blocks,
                     wall_time=time.perf_counter() - t0,
                     info={"n_cells": len(cells), "n_sources": cells.n_sources})




def fit_and_choose(cells: Cells, shapes=None, *, depth_ref=None, seed=0, n_walkers=None,
                   max_steps: int = DEFAULT_MAX_STEPS, loo_draws: int = 400, fit=None):
    """Fit every completeness step in ``shapes`` and keep one by PSIS-LOO.

    The selection block is the same for every step; the steps are compared on
    the recovered flags alone (leave-one-cell-out, :func:`psis_loo` over the
    aggregated cells), and the simplest step within 2 standard errors of the
    best elpd is kept (:func:`compare_models`; ``shapes`` in order of simplicity).

    Parameters
    ----------
    cells : Cells
    shapes : sequence of str, optional
        Default :data:`COMPLETENESS_SHAPES` (logistic, erf, fleming, sas).
    depth_ref : float, optional
        Reference depth of a depth-aware model (the cells must be depth-relative).
    seed, n_walkers, max_steps
        As :func:`fit_surfaces`.
    loo_draws : int
        Posterior draws used for PSIS-LOO.
    fit : callable, optional
        ``fit(cells, model) -> FitResult`` replacing :func:`fit_surfaces` (the
        pipeline passes one that resumes saved chains and shows progress).

    Returns
    -------
    chosen : str
    results : dict
        ``{shape: FitResult}``.
    comparison : list of dict
        :func:`compare_models` table (empty for a single shape).
    """
    from .diagnostics import compare_models, psis_loo
    from .models import COMPLETENESS_SHAPES

    shapes = list(COMPLETENESS_SHAPES if shapes is None else shapes)
    if fit is None:
        def fit(c, mdl):
            return fit_surfaces(c, mdl, seed=seed, n_walkers=n_walkers, max_steps=max_steps)
    results, loos = {}, {}
    for shape in shapes:
        mdl = SurfaceModel.for_data(cells.z, cells.mag, shape=shape, depth_ref=depth_ref)
        results[shape] = fit(cells, mdl)
        if len(shapes) > 1:
            d = results[shape].draws(loo_draws)
            loos[shape] = psis_loo(mdl.cell_log_likelihood(d, cells, part="c"))
    if len(shapes) == 1:
        return shapes[0], results, []
    chosen, table = compare_models(loos)
    return chosen, results, table
