"""Sample one parameter block's posterior with emcee; chains, convergence, diagnostics.

Arrays in, results out: a log-posterior callable and a starting point in, a
:class:`BlockChain` out.  Nothing here reads or writes files (saving chains to
resume a fit is :mod:`glaciar.pipeline.chains`' job).

Sampler design
--------------
Each block is sampled with :class:`emcee.EnsembleSampler` (vectorised
log-probability) using a mixture of three of emcee's stock moves, all of
which leave the posterior invariant:

- an *independence* move (30 %): :class:`emcee.moves.MHMove` whose proposal
  is a multivariate Student t (5 degrees of freedom), started from the MAP and
  the Laplace covariance (the inverse Hessian of the log posterior) and
  re-fitted to the stages of a discarded pilot run until it is stable
  (:data:`PILOT_STAGES`).  With thousands of sources the posterior is close
  to Gaussian, acceptance is high and the integrated autocorrelation time tau
  is a few steps;
- :class:`emcee.moves.DEMove` (30 %) and :class:`emcee.moves.StretchMove`
  (40 %), which keep the ensemble mixing where the posterior is far from
  Gaussian (small data sets, parameters bounded by the data on one side only,
  such as a selection edge outside the simulated z range).  Against 60/20/20
  weights they cut tau of such an edge from ~290 to ~70 steps, at the price of
  tau ~7 instead of ~3 steps where the posterior is Gaussian.  More weight on
  the independence move (80 %) lowers tau at 1e6 sources but lets walkers
  stick in a heavy tail (logit S_max of a sharp, nearly complete selection:
  tau 75 instead of 11 steps on 2800 sources).

Convergence: the chain is extended in blocks until it is at least 50 tau long
(tau the largest per-parameter integrated autocorrelation time,
:func:`emcee.autocorr.integrated_time` with Sokal's window c = 5) and that
largest tau changed by less than 10 % since the previous check, or until
``max_steps``; a :class:`ConvergenceWarning` is issued otherwise.  Checks
come every ``block`` (100) steps, and every ~10 % of the chain beyond 2000
steps (:data:`CHECK_FRACTION`), so that the checks of a long chain cost in
proportion to its length.  Burn-in is 2 tau, thinning tau / 2.

Speed: the per-step cost is the log posterior (:class:`BlockPosterior`).  The
private override glaciar used before -- emcee's red-blue ``propose`` with a
vectorised accept step, and a vectorised copy of ``integrated_time``, both
giving bit-identical chains -- saved 0-3 % of the sampling time at 1e4-1e6
sources and ~15 % at 300 (``benchmarks/fit.py`` prints the comparison), so
the stock moves and estimator are used.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import emcee
import numpy as np

__all__ = ["ConvergenceWarning", "BlockChain", "FitResult", "StudentT", "autocorr_time",
           "split_rhat", "sample_block", "PILOT_STAGES", "MOVE_WEIGHTS", "T_DOF", "SOKAL_C",
           "CHECK_FRACTION", "DEFAULT_MAX_STEPS"]

T_DOF = 5.0                       #: Student-t proposal degrees of freedom
MOVE_WEIGHTS = (0.3, 0.3, 0.4)    #: independence, differential evolution, stretch
SOKAL_C = 5.0                     #: Sokal's window: tau summed up to M >= SOKAL_C tau
#: Convergence is checked every ``block`` steps, or every this fraction of the
#: chain once that is longer (rounded down to a multiple of ``block``).
CHECK_FRACTION = 0.1
#: Stages of the discarded pilot run that sets the independence proposal [steps];
#: it stops after the second stage once the proposal is stable.  A single 50-step
#: pilot left tau underestimated by 30-50 % where an edge lies outside the data.
PILOT_STAGES = (50, 150, 400, 1000, 2500)
#: Default cap on each block's chain length per call [steps].
DEFAULT_MAX_STEPS = 20000


@dataclass(frozen=True)
class SamplerSettings:
    """How long and how wide the emcee chains run, and from which seed (fit and LF fit).

    Attributes
    ----------
    n_walkers : int, optional
        Walkers per parameter block; default the caller's (``glaciar fit``: its
        per-block rule; :func:`glaciar.lf.fit_lf`: max(32, 2 n_free + 2)).
    max_steps : int, optional
        Cap on each chain's steps in this call [steps] (it stops earlier once
        converged); default the caller's (``glaciar fit``: :data:`DEFAULT_MAX_STEPS`;
        :func:`glaciar.lf.fit_lf`: :data:`glaciar.lf.fit.LF_MAX_STEPS`).
    seed : int
        Sampler seed; the same seed and data give identical chains.
    progress : bool
        Show a progress bar of the sampling.
    """

    n_walkers: int | None = None
    max_steps: int | None = None
    seed: int = 0
    progress: bool = False


class ConvergenceWarning(UserWarning):
    """The chain stopped at ``max_steps`` before reaching 50 autocorrelation times."""


class StudentT:
    """Multivariate Student t: draws and log density (up to a constant).

    Parameters
    ----------
    mean : ndarray (P,)
    cov : ndarray (P, P)
        Scale matrix (positive definite).
    dof : float
        Degrees of freedom.
    """

    def __init__(self, mean, cov, dof: float = T_DOF):
        self.mean = np.asarray(mean, float)
        self.cov = np.asarray(cov, float)
        self.L = np.linalg.cholesky(self.cov)
        self.Linv = np.linalg.inv(self.L)
        self.dof = float(dof)

    def draw(self, n: int, rng) -> np.ndarray:
        """``n`` draws, shape (n, P), from a legacy ``numpy.random.RandomState``."""
        g = rng.standard_normal((n, len(self.mean))) @ self.L.T
        chi2 = rng.chisquare(self.dof, size=n)
        return self.mean + g * np.sqrt(self.dof / chi2)[:, None]

    def logpdf(self, x) -> np.ndarray:
        d = (np.asarray(x) - self.mean) @ self.Linv.T
        return -0.5 * (self.dof + len(self.mean)) * np.log1p(np.sum(d * d, axis=-1) / self.dof)


class _Independence:
    """The proposal function of :class:`emcee.moves.MHMove`: independent t draws.

    Holds the current :class:`StudentT`, which the pilot replaces between its
    stages (the move keeps calling this object).
    """

    def __init__(self, dist: StudentT):
        self.dist = dist

    def __call__(self, coords, rng):
        new = self.dist.draw(len(coords), rng)
        return new, self.dist.logpdf(coords) - self.dist.logpdf(new)


def _red_blue_moves() -> list:
    """emcee's differential-evolution and stretch moves (weights :data:`MOVE_WEIGHTS`)."""
    return [emcee.moves.DEMove(), emcee.moves.StretchMove()]


def autocorr_time(chain) -> np.ndarray:
    """Integrated autocorrelation time per parameter of an ensemble chain [steps].

    :func:`emcee.autocorr.integrated_time` with Sokal's window ``c =``
    :data:`SOKAL_C` and no length check (the 50-tau rule is applied by the
    caller): each walker's normalised autocorrelation function, averaged over
    the walkers, summed up to the window.

    Parameters
    ----------
    chain : ndarray (n_steps, n_walkers, n_params)

    Returns
    -------
    ndarray (n_params,)
        Where no estimate exists -- a parameter no walker has moved yet (0/0 in the
        normalised autocorrelation), as in a chain of a few steps -- the chain's length:
        the largest time such a chain can show, so the caller's 50-tau rule calls it
        unconverged and burn-in and thinning stay finite.
    """
    chain = np.asarray(chain, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        tau = emcee.autocorr.integrated_time(chain, c=SOKAL_C, tol=0, quiet=True)
    return np.where(np.isfinite(tau), tau, float(chain.shape[0]))


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


@dataclass(frozen=True)
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
        Burn-in and thinning [steps].
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
        """Draws after burn-in and thinning, shape (n, n_block)."""
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


@dataclass(frozen=True)
class FitResult:
    """The outcome of :func:`glaciar.inference.fit_surfaces`.

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
        Seconds spent in this call (MAP + sampling) [s].
    info : dict
    """

    model: object
    theta_map: np.ndarray
    blocks: list
    wall_time: float = 0.0
    info: dict = field(default_factory=dict)

    def _per_param(self, attr):
        out = np.empty(self.model.n_params)
        for b in self.blocks:
            out[b.index] = getattr(b, attr)
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


def _start(prop: StudentT, log_prob, n_walkers: int, rs) -> tuple[np.ndarray, np.ndarray]:
    """Walkers drawn from the (over-dispersed) t proposal where the posterior is finite."""
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
    return p0, lp0


def _pilot(sampler, state, proposal: _Independence, cov):
    """Discarded pilot: re-centre and re-scale the independence proposal, stage by stage.

    Each stage re-fits the proposal to the second half of its chain, which
    follows skewed posteriors (a C_max or S_max near 1, an edge outside the
    data) far better than the Laplace approximation; stages grow until the
    proposal's centre and spread stop changing (from the second stage on): a
    posterior bounded on one side only is explored by the differential-
    evolution and stretch moves, and the proposal widens to it.  The chain
    proper then runs with a fixed proposal (no adaptation), so it is a valid MCMC.
    """
    P = len(proposal.dist.mean)
    for stage in PILOT_STAGES:
        sampler.reset()
        state = sampler.run_mcmc(state, stage, progress=False, skip_initial_state_check=True)
        pil = sampler.get_chain()[stage // 2:].reshape(-1, P)
        pcov = np.cov(pil, rowvar=False)
        old = proposal.dist
        try:
            proposal.dist = StudentT(pil.mean(axis=0),
                                     0.5 * (pcov + pcov.T) + 1e-12 * np.diag(np.diag(cov)))
        except np.linalg.LinAlgError:
            continue
        cov = proposal.dist.cov
        sd, old_sd = np.sqrt(np.diag(proposal.dist.cov)), np.sqrt(np.diag(old.cov))
        if (stage >= PILOT_STAGES[1] and np.all(np.abs(proposal.dist.mean - old.mean) < 0.2 * sd)
                and np.all(np.abs(np.log(sd / old_sd)) < 0.2)):
            break
    sampler.reset()
    return state, cov


def sample_block(log_prob, index, start, cov, seed, *, part: str = "c",
                 n_walkers: int | None = None, max_steps: int = DEFAULT_MAX_STEPS,
                 min_steps: int = 100, block: int = 100, callback=None,
                 resume: BlockChain | None = None) -> BlockChain:
    """Sample one block's posterior until 50 autocorrelation times or ``max_steps``.

    Parameters
    ----------
    log_prob : callable
        Log posterior of the block: ``log_prob(x)`` with ``x`` of shape
        (W, P_block) returns an ndarray (W,) (e.g. :class:`BlockPosterior`).
    index : ndarray of int
        Positions of the block's parameters in the full vector (recorded in the result).
    start : ndarray (P_block,)
        Centre of the first independence proposal (the MAP).
    cov : ndarray (P_block, P_block) or None
        Its covariance (the Laplace approximation); ignored when resuming.
    seed : numpy.random.SeedSequence
        Seed of the walkers' start and of the sampler's random stream.
    part : str
        Block label ("c" or "s"), for the result and the warning.
    n_walkers : int, optional
        Walkers; default ``max(32, 2 P_block + 2)``, rounded up to even.
    max_steps : int
        Cap on the steps of this call [steps].
    min_steps : int
        Shortest chain considered for convergence [steps].
    block : int
        Steps between convergence checks, or a multiple of it: every
        :data:`CHECK_FRACTION` of the chain once that is longer [steps].
    callback : callable, optional
        Called with the number of steps just run.
    resume : BlockChain, optional
        A previous chain of the same block to extend (same random stream).

    Returns
    -------
    BlockChain

    Warns
    -----
    ConvergenceWarning
        The chain is shorter than 50 tau, or tau is still changing, at ``max_steps``.
    """
    idx = np.asarray(index)
    P = len(idx)
    if n_walkers is None:
        n_walkers = max(32, 2 * P + 2)
    n_walkers = int(n_walkers) + int(n_walkers) % 2
    if n_walkers < 2 * P:
        raise ValueError(f"n_walkers={n_walkers} must be at least 2 * n_params = {2 * P}")
    if resume is not None:
        cov = resume.laplace_cov
        n_walkers = resume.chain.shape[1]
        start = resume.proposal_mean
    proposal = _Independence(StudentT(np.asarray(start, float), cov))
    moves = [(mv, w) for mv, w in zip([emcee.moves.MHMove(proposal)] + _red_blue_moves(),
                                      MOVE_WEIGHTS) if w > 0]
    # emcee converts the returned log-probabilities one walker at a time; a list of
    # Python floats makes that loop several times cheaper than an ndarray.
    sampler = emcee.EnsembleSampler(n_walkers, P, lambda x: log_prob(x).tolist(), moves=moves,
                                    vectorize=True)
    if resume is None:
        rs = np.random.RandomState(seed.generate_state(8))
        p0, lp0 = _start(proposal.dist, log_prob, n_walkers, rs)
        state = emcee.State(p0, log_prob=lp0, random_state=rs.get_state())
        state, cov = _pilot(sampler, state, proposal, cov)
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
            tau = autocorr_time(np.concatenate(chains))
            # The 50-tau rule is on the largest tau; its stability is judged on the same
            # number (per-parameter estimates of short chains scatter by ~10 % each).
            tmax_now = float(np.max(tau))
            converged = (done >= 50 * tmax_now and tau_prev is not None
                         and abs(tmax_now - float(np.max(tau_prev))) < 0.1 * tmax_now)
            tau_prev = tau
            if converged or done >= limit:
                break
        # Every `block` steps, then every ~CHECK_FRACTION of the chain (a multiple of
        # `block`): a check costs in proportion to the chain's length, so the checks of
        # a long chain cost O(length) in all instead of O(length^2 / block).
        nb = min(max(block, int(CHECK_FRACTION * done) // block * block), limit - done)
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
        tau = autocorr_time(chain)
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
                      proposal_mean=proposal.dist.mean)
