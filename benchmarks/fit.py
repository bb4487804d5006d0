"""Wall time and autocorrelation time of the depth-aware fit; stock emcee against the former override.

Target: the 1e6-source fit (MAP + sampling to 50 tau) in <= 60 s on one core.

Flags are drawn from known depth-aware surfaces (``SurfaceModel.for_data(...,
depth_ref=...)``; both selection edges inside the simulated z range) on a 13
(z) x 25 (m) grid with a continuous mag_input (0.1 mag scatter, as a varying
UV slope gives).  Every source has a local depth: a third lie in a shallow
field (depth 28.2 mag), two thirds in a deep one (29.2 mag), each with 0.1 mag
of scatter within the field; the flags follow C(m, z | d) and S(z, m | d), and
the cells are aggregated with ``depth_ref`` (the median depth, as `glaciar fit`
does without a depth-area table) at the default 0.01 mag resolution of the
depth-relative magnitude.

Table 1 (the fit as glaciar runs it): sources, aggregated cells, aggregation
time, MAP time, sampling time (Laplace, pilot, emcee to convergence), total fit
time (MAP + sampling), chain length and largest tau of the completeness /
selection blocks, acceptance fractions, whether both blocks reached 50 tau,
and the effective number of independent draws of the worst parameter
(walkers x (steps - burn-in) / tau_max).

Table 2 (why the sampler uses emcee's stock moves and ``emcee.autocorr``):
the sampling step alone (same MAP, same seed) with the stock
``emcee.moves.DEMove`` / ``StretchMove`` and ``emcee.autocorr.integrated_time``
against the private override glaciar used before (red-blue ``propose`` with a
vectorised accept step, and a vectorised copy of ``integrated_time``; both
kept below as the reference).  The override draws the same random numbers in
the same order, so the chains are bit-identical (checked: tau and ESS are
the same in both columns, "at equal accuracy" by construction) and only the
time differs.  Times are CPU seconds of this process (``time.process_time``,
robust to other load on the machine), the minimum of ``--repeats`` interleaved
runs; the ratio is from one run of this script.  A small data set (300
sources, the size of the SBC test's data sets, where the log posterior is
cheapest and per-step overhead matters most) is always included.

Table 3 (the cost of the convergence checks of a long chain): every check
estimates tau on the whole chain so far, so checking every 100 steps costs
O(length^2); the sampler now checks every 100 steps up to 2000 and every ~10 %
of the chain beyond (``glaciar.inference.sampling.CHECK_FRACTION``), which
leaves every chain of <= 2000 steps (all of Table 2) as it was.  CPU of all
checks along a 10000-step chain that never converges, both estimators.

    python benchmarks/fit.py [--repeats R] [N ...]
"""
from __future__ import annotations

import argparse
import time
import warnings
from unittest import mock

import emcee
import numpy as np
import pandas as pd

import glaciar.inference.sampling as sampling
from glaciar.inference import SurfaceModel, aggregate_cells, find_map, fit_surfaces

TARGET_1E6_S = 60.0
SMALL_N = 300
Z_GRID = np.arange(6.0, 9.01, 0.25)
M_GRID = np.arange(24.0, 30.01, 0.25)
DEPTHS = ((28.2, 1 / 3), (29.2, 2 / 3))      # (field depth [mag], fraction of sources)
DEPTH_SCATTER = 0.1                          # within a field [mag]
DEPTH_TRUTH_REF = 28.9                       # reference depth of the truth's parameters
# In the truth model's normalisation (z_ref 7.5, z_scale 1.5; m_ref 27, m_scale 3):
# lower selection edge at z = 6.8 (dz 0.15), upper at 8.4 (dz 0.2), both inside.
TRUTH = dict(logit_c_max_0=2.5, logit_c_max_1=-0.2, m50_0=27.4, m50_1=-0.3, m50_2=0.05,
             log_w_0=np.log(0.3), log_w_1=0.1, logit_s_max=3.0,
             eta_lo_0=-0.8 / 0.15, eta_lo_1=-0.5, log_dz_lo_0=np.log(0.15), log_dz_lo_1=0.1,
             eta_hi_0=-0.6 / 0.2, eta_hi_1=0.3, log_dz_hi_0=np.log(0.2), log_dz_hi_1=0.0)


# ------------------------------------------------- the former private override (reference)
class _VectorisedRedBlue:
    """emcee's red-blue ``propose`` with the accept/reject loop vectorised (private API).

    emcee draws one uniform per walker in a Python loop; ``random.rand(n)``
    draws the same numbers from the same stream in the same order, so the
    chains are bit-identical to emcee's own move.
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


def _tau_vectorised(chain, c: float = sampling.SOKAL_C) -> np.ndarray:
    """emcee.autocorr.integrated_time (tol=0), one FFT per parameter instead of per walker."""
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


def _override():
    return mock.patch.multiple(sampling, _red_blue_moves=lambda: [_DEMove(), _StretchMove()],
                               autocorr_time=_tau_vectorised)


# ---------------------------------------------------------------------------------- data
def make(n, rng):
    """Per-source table: z, mag_input, depth_local and the flags."""
    mdl = SurfaceModel.for_data(Z_GRID, M_GRID, depth_ref=DEPTH_TRUTH_REF)
    th = np.array([TRUTH[p] for p in mdl.param_names])
    z = rng.choice(Z_GRID, n)
    m = rng.choice(M_GRID, n) + 0.1 * rng.standard_normal(n)
    field = rng.choice(len(DEPTHS), n, p=[f for _, f in DEPTHS])
    d = np.array([dd for dd, _ in DEPTHS])[field] + DEPTH_SCATTER * rng.standard_normal(n)
    rec = rng.random(n) < mdl.completeness(th, m, z, depth=d)
    sel = rec & (rng.random(n) < mdl.selection_given_recovered(th, z, m, depth=d))
    return pd.DataFrame({"z": z, "mag_input": m, "depth_local": d, "recovered": rec,
                         "selected": sel})


def _cells(n):
    df = make(n, np.random.default_rng(n))
    depth_ref = round(float(np.median(df["depth_local"])), 2)
    t0 = time.perf_counter()
    cells = aggregate_cells(df, depth_ref=depth_ref)
    t_agg = time.perf_counter() - t0
    return cells, SurfaceModel.for_data(cells.z, cells.mag, depth_ref=depth_ref), t_agg


def _sample(cells, mdl, theta_map):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c0, w0 = time.process_time(), time.perf_counter()
        res = fit_surfaces(cells, mdl, seed=0, theta_map=theta_map)
        return res, time.process_time() - c0, time.perf_counter() - w0


def _ess(b):
    return b.chain.shape[1] * (b.n_steps - b.burn) / max(b.tau)


# -------------------------------------------------------------------------------- tables
def fit_table(sizes):
    print(f"Depth-aware fit; target: 1e6 sources fitted (MAP + sampling) in <= {TARGET_1E6_S:.0f} s")
    print(f"{'N':>9} {'cells':>6} {'agg s':>6} {'map s':>6} {'mcmc s':>6} {'fit s':>6} "
          f"{'steps c/s':>10} {'tau_max c/s':>12} {'acc c/s':>10} {'conv':>5} {'ESS c/s':>11}")
    for n in sizes:
        cells, mdl, t_agg = _cells(n)
        t1 = time.perf_counter()
        theta_map = find_map(mdl, cells)
        t2 = time.perf_counter()
        res, _, t_mcmc = _sample(cells, mdl, theta_map)
        b = res.blocks
        flag = ""
        if n == 1_000_000:
            flag = (f"  {'meets' if t2 - t1 + t_mcmc <= TARGET_1E6_S else 'MISSES'} the "
                    f"{TARGET_1E6_S:.0f} s target")
        print(f"{n:>9d} {len(cells):>6d} {t_agg:>6.2f} {t2 - t1:>6.2f} {t_mcmc:>6.2f} "
              f"{t2 - t1 + t_mcmc:>6.2f} {b[0].n_steps:>4d}/{b[1].n_steps:<5d} "
              f"{max(b[0].tau):>5.1f}/{max(b[1].tau):<6.1f} "
              f"{np.mean(b[0].acceptance_fraction):>4.2f}/{np.mean(b[1].acceptance_fraction):<5.2f} "
              f"{str(res.converged):>5} {_ess(b[0]):>5.0f}/{_ess(b[1]):<5.0f}{flag}", flush=True)


def moves_table(sizes, repeats):
    print(f"\nSampling only (same MAP and seed): stock emcee moves + emcee.autocorr against the "
          f"former private override;\nCPU s of this process, min of {repeats} interleaved runs; "
          "tau_max and ESS of the worst parameter, blocks c/s")
    print(f"{'N':>9} {'cells':>6} {'stock s':>8} {'override s':>10} {'ratio':>6} "
          f"{'tau_max c/s':>12} {'ESS c/s':>11} {'same chains':>11}")
    for n in sizes:
        cells, mdl, _ = _cells(n)
        theta_map = find_map(mdl, cells)
        cpu = {"stock": [], "override": []}
        res = {}
        for _ in range(repeats):
            res["stock"], c, _ = _sample(cells, mdl, theta_map)
            cpu["stock"].append(c)
            with _override():
                res["override"], c, _ = _sample(cells, mdl, theta_map)
            cpu["override"].append(c)
        same = all(np.array_equal(a.chain, b.chain) and np.allclose(a.tau, b.tau, rtol=1e-9)
                   for a, b in zip(res["stock"].blocks, res["override"].blocks))
        s, o = min(cpu["stock"]), min(cpu["override"])
        b = res["stock"].blocks
        print(f"{n:>9d} {len(cells):>6d} {s:>8.2f} {o:>10.2f} {s / o:>6.2f} "
              f"{max(b[0].tau):>5.1f}/{max(b[1].tau):<6.1f} {_ess(b[0]):>5.0f}/{_ess(b[1]):<5.0f} "
              f"{'yes' if same else 'NO':>11}", flush=True)


def _schedule(n_steps, block, growing):
    """Chain lengths at which sample_block checks convergence, up to ``n_steps``."""
    out, done = [], block
    while done <= n_steps:
        out.append(done)
        step = max(block, int(sampling.CHECK_FRACTION * done) // block * block) if growing else block
        done += step
    return out


def checks_table(n_steps=10_000, walkers=32, n_params=9, block=100):
    """CPU of all convergence checks along a chain that runs to max_steps without converging."""
    rng = np.random.default_rng(1)
    phi = 0.96                                   # AR(1): tau = (1 + phi) / (1 - phi) = 49
    x = np.empty((n_steps, walkers, n_params))
    x[0] = rng.standard_normal((walkers, n_params))
    for i in range(1, n_steps):
        x[i] = phi * x[i - 1] + np.sqrt(1 - phi ** 2) * rng.standard_normal((walkers, n_params))
    print(f"\nConvergence checks along a {n_steps}-step chain that never converges ({walkers} "
          f"walkers, {n_params} parameters, tau {(1 + phi) / (1 - phi):.0f}): CPU s of all checks")
    print(f"{'schedule':>28} {'checks':>6} {'emcee.autocorr s':>16} {'vectorised s':>12} {'ratio':>6}")
    for label, growing in ((f"every {block} steps (before)", False),
                           (f"every {block}, then ~{sampling.CHECK_FRACTION:.0%} (now)", True)):
        sched = _schedule(n_steps, block, growing)
        cpu = {}
        for name, fn in (("stock", sampling.autocorr_time), ("vectorised", _tau_vectorised)):
            t = time.process_time()
            for n in sched:
                fn(x[:n])
            cpu[name] = time.process_time() - t
        print(f"{label:>28} {len(sched):>6d} {cpu['stock']:>16.2f} {cpu['vectorised']:>12.2f} "
              f"{cpu['stock'] / cpu['vectorised']:>6.2f}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sizes", nargs="*", type=lambda a: int(float(a)),
                    default=[10_000, 100_000, 1_000_000], help="numbers of sources")
    ap.add_argument("--repeats", type=int, default=3, help="interleaved runs per variant")
    args = ap.parse_args(argv)
    fit_table(args.sizes)
    moves_table([SMALL_N] + [n for n in args.sizes if n != SMALL_N], args.repeats)
    checks_table()


if __name__ == "__main__":
    main()
