"""Uniform against adaptive injection designs: error of C*S versus injections and CPU.

Surrogate part (fast, no images).  The "simulation" draws missed /
recovered-not-selected / selected outcomes from a KNOWN surface

    C(m, z) = C_max / (1 + exp((m - m50(z)) / w(z))),
    S(z, m) = S_max * expit((z - z_lo(m)) / dz_lo) * expit((z_hi(m) - z) / dz_hi),

with demo-like numbers (m50 ~ 27.2 mag drifting brighter with z, w ~ 0.22 mag,
a selection window z ~ 8.6-11.6 whose edges move with m) over the demo's box
z = 7.8-12.6, m = 24.5-28.5 mag.  Both designs are fitted by glaciar's own
inference (``glaciar.inference.fit_surfaces`` on ``SurfaceModel.for_data``,
logistic step, ``--max-steps`` per block), and the error is that of the
posterior median of C*S against the known surface on a dense 49 x 41 grid
over the box (max and RMS of |error|).

* uniform: the demo's 13 (z) x 9 (m) grid with n sources per cell, n = 10,
  20, 40, 80 (``--uniform-n``), one fit per budget;
* adaptive: a coarse 5 x 5 grid over the box (``--initial-n`` per cell),
  then rounds of ``--round-size`` sources (fit -> candidate grid from the
  simulated values, refine 2 -> expected information gain -> allocation ->
  simulate) up to ``--adaptive-budget``, with
  :func:`glaciar.inference.adaptive.run_design`; the error is measured after
  every round.

The ratio printed per seed is (uniform design's final budget) / (injections
the adaptive design needed to reach the uniform design's final error); ">" when
it did not reach it within its budget (then budget-limited, a lower bound).
CPU is ``time.process_time`` of this process (fits dominate); the machine was
shared, so compare the columns of one run, not absolute seconds.

The loop takes its simulation as a callable ``simulate(request, seed) ->
Cells``, so a ``--demo`` part (injections into the demo survey, error against a
long reference run) can reuse :func:`compare_designs` with another simulator
and reference surface.

    python benchmarks/adaptive.py [--seeds 0 1 2] [--max-steps 1500] [--criterion information]

Measured (2026-11-24, seeds 0 1 2, defaults, on a shared and loaded 2-core
machine; injections needed to reach the uniform 9360-source design's final
value, from the seed-averaged curves):

    criterion     max sd of C*S   max |err|   rms |err|   CPU (process, whole script)
    information   3.5x            2.6x        1.7x        119 s user
    variance      3.9x            1.4x        1.4x        167 s user

At 9360 injections the adaptive design (information) has max |err| 0.031,
rms 0.0077, max sd 0.017 against the uniform grid's 0.051, 0.0100, 0.037
(means over the seeds).  The >= 5x target of issue 8 is not reached on this
surrogate: the max sd falls 3.5-3.9x faster, the error 1.4-2.6x.  The
adaptive design also costs more CPU here (a fit per 300-source round, 31
fits against the uniform design's 4; in this surrogate the fits are all the
CPU, while in a real run the injections dominate at ~1 ms of CPU per source).
"""
from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from scipy.special import expit

from glaciar.inference import SelectionFunction, SurfaceModel, fit_surfaces
from glaciar.inference.adaptive import (REQUEST_DTYPE, candidate_grid, max_posterior_sd,
                                        merge_cells, plan_round, round_seed, run_design)
from glaciar.inference.models import Cells

BOX = ((7.8, 12.6), (24.5, 28.5))                  #: the demo's (z, m) box
UNIFORM_Z = np.linspace(7.8, 12.6, 13)             #: the demo's grid
UNIFORM_M = np.linspace(24.5, 28.5, 9)
COARSE_Z = np.linspace(7.8, 12.6, 5)
COARSE_M = np.linspace(24.5, 28.5, 5)
EVAL_Z = np.linspace(7.8, 12.6, 49)                #: where the error is measured
EVAL_M = np.linspace(24.5, 28.5, 41)
VR_Z = np.linspace(7.8, 12.6, 25)                  #: the "variance" rule's objective grid
VR_M = np.linspace(24.5, 28.5, 17)
MIN_STEP = (0.05, 0.05)                            #: finest candidate spacing (dz, dm [mag])
N_DRAWS = 400                                      #: posterior draws kept per fit


# --------------------------------------------------------------------------
# The known surface and its simulator
# --------------------------------------------------------------------------
def true_c(m, z):
    """Known completeness C(m, z)."""
    dz = np.asarray(z, float) - 10.0
    m50 = 27.2 - 0.15 * dz - 0.03 * dz ** 2
    w = 0.22 + 0.02 * dz
    return 0.95 * expit(-(np.asarray(m, float) - m50) / w)


def true_s(z, m):
    """Known selection given recovery S(z, m)."""
    dm = np.asarray(m, float) - 26.5
    z_lo, z_hi = 8.6 + 0.05 * dm, 11.6 - 0.10 * dm
    z = np.asarray(z, float)
    return 0.9 * expit((z - z_lo) / 0.12) * expit((z_hi - z) / 0.15)


def true_p_grid(z, m):
    zz, mm = np.meshgrid(z, m, indexing="ij")
    return true_c(mm, zz) * true_s(zz, mm)


def surrogate_simulate(request, seed) -> Cells:
    """Binomial outcomes of ``request["n"]`` sources per cell from the known surface."""
    rng = np.random.default_rng(seed)
    z, m, n = request["z"], request["mag"], request["n"].astype(np.int64)
    k_rec = rng.binomial(n, true_c(m, z))
    k_sel = rng.binomial(k_rec, true_s(z, m))
    return Cells(z=z.astype(float), mag=m.astype(float), n=n, k_rec=k_rec, k_sel=k_sel)


def grid_request(z, m, n) -> np.ndarray:
    zz, mm = np.meshgrid(z, m, indexing="ij")
    out = np.empty(zz.size, dtype=REQUEST_DTYPE)
    out["z"], out["mag"], out["n"] = zz.ravel(), mm.ravel(), n
    return out


# --------------------------------------------------------------------------
# Fit, error, proposal
# --------------------------------------------------------------------------
def make_fit(max_steps: int):
    """``fit(cells, seed) -> SelectionFunction`` with glaciar's inference (no I/O)."""
    def fit(cells, seed):
        mdl = SurfaceModel.for_data(cells.z, cells.mag, shape="logistic")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")          # short chains: ConvergenceWarning
            res = fit_surfaces(cells, mdl, seed=int(seed.generate_state(1)[0]), max_steps=max_steps)
        return SelectionFunction(mdl, res.draws(N_DRAWS))
    return fit


def error(sf, reference=true_p_grid) -> tuple[float, float]:
    """(max, RMS) of |median C*S - reference| over the evaluation grid."""
    p = np.median(sf.grid_draws(EVAL_Z, EVAL_M)["P"], axis=0)
    d = np.abs(p - reference(EVAL_Z, EVAL_M))
    return float(d.max()), float(np.sqrt(np.mean(d ** 2)))


def sd_statistic(sf) -> float:
    """The stopping statistic on the evaluation grid (whole box)."""
    return max_posterior_sd(sf.grid_draws(EVAL_Z, EVAL_M)["P"], EVAL_Z, EVAL_M, BOX)


def make_propose(box=BOX, min_per_cell: int = 10, outcomes: str = "selected",
                 criterion: str = "information"):
    """``propose(posterior, cells, k, seed)``: candidate grid + information gain + allocation."""
    def propose(sf, cells, k, seed):
        zc, mc = candidate_grid(cells.z, cells.mag, box=box, refine=2, min_step=MIN_STEP)
        g = sf.grid_draws(zc, mc)
        # The batch rule's objective: the variance of C*S on a fixed grid over the box.
        p_eval = sf.grid_draws(VR_Z, VR_M)["P"] if criterion == "variance" else None
        return plan_round(g["C"], g["S"], (zc, mc), k, criterion=criterion, outcomes=outcomes,
                          min_per_cell=min_per_cell, p_eval=p_eval)
    return propose


# --------------------------------------------------------------------------
# The comparison
# --------------------------------------------------------------------------
def uniform_curve(simulate, fit, uniform_n, seed, reference=true_p_grid):
    """Rows (injections, cpu_s, max_err, rms_err, max_sd) of the uniform grid at each n per cell.

    Nested: each budget adds sources to the previous one (as a user raising
    the iterations would); CPU is cumulative (simulate + fit).
    """
    rows, cells, cpu, done = [], None, 0.0, 0
    for i, n in enumerate(uniform_n):
        t0 = time.process_time()
        s_sim, s_fit = round_seed(seed, i).spawn(2)
        cells = merge_cells(cells, simulate(grid_request(UNIFORM_Z, UNIFORM_M, n - done), s_sim))
        done = n
        sf = fit(cells, s_fit)
        cpu += time.process_time() - t0
        rows.append((cells.n_sources, cpu, *error(sf, reference), sd_statistic(sf)))
    return rows


def adaptive_curve(simulate, fit, propose, initial_n, budget, round_size, seed,
                   reference=true_p_grid):
    """Rows (injections, cpu_s, max_err, rms_err, max_sd) after every round of the loop.

    CPU is cumulative over rounds (simulate + fit + propose + the stopping
    statistic, as :func:`run_design` logs it); measuring the error is not counted.
    """
    posteriors = []

    def fit_kept(cells, s):
        posteriors.append(fit(cells, s))
        return posteriors[-1]

    result = run_design(simulate, fit_kept, propose, grid_request(COARSE_Z, COARSE_M, initial_n),
                        budget=budget, round_size=round_size, seed=seed, statistic=sd_statistic)
    rows, cpu = [], 0.0
    for rec, sf in zip(result.rounds, posteriors):
        cpu += rec.cpu_s
        rows.append((rec.n_total, cpu, *error(sf, reference), rec.max_sd))
    return rows, result


def injections_to_reach(rows, target, col=2, sustained=True):
    """Injections after which the error (column ``col``) is <= target (and, with
    ``sustained``, stays so to the end of the run); None if never."""
    ok = np.array([r[col] <= target for r in rows])
    if sustained:
        ok = np.logical_and.accumulate(ok[::-1])[::-1]
    return rows[int(np.argmax(ok))][0] if ok.any() else None


def compare_designs(simulate, fit, propose, seeds, *, uniform_n=(10, 20, 40, 80), initial_n=12,
                    adaptive_budget=9360, round_size=300, reference=true_p_grid, out=print):
    """Run both designs for every seed; print the tables and the ratios; return them.

    The ratio is (uniform final injections) / (injections after which the
    adaptive error stays <= the uniform final error to the end of its run);
    the first crossing (noisier, more flattering) is printed beside it.
    """
    summary, curves_u, curves_a = [], [], []
    head = f"{'injections':>10} {'CPU s':>7} {'max|err|':>9} {'rms|err|':>9} {'max sd':>8}"
    for seed in seeds:
        u = uniform_curve(simulate, fit, uniform_n, seed, reference)
        a, _ = adaptive_curve(simulate, fit, propose, initial_n, adaptive_budget, round_size,
                              seed, reference)
        out(f"\n# seed {seed}: uniform ({UNIFORM_Z.size} x {UNIFORM_M.size} grid)")
        out(head)
        for r in u:
            out(f"{r[0]:>10d} {r[1]:>7.1f} {r[2]:>9.4f} {r[3]:>9.4f} {r[4]:>8.4f}")
        out(f"# seed {seed}: adaptive ({COARSE_Z.size} x {COARSE_M.size} x {initial_n}, "
            f"then rounds of {round_size})")
        out(head)
        for r in a:
            out(f"{r[0]:>10d} {r[1]:>7.1f} {r[2]:>9.4f} {r[3]:>9.4f} {r[4]:>8.4f}")
        curves_u.append(u)
        curves_a.append(a)
        row = {"seed": seed, "uniform_final": u[-1][0], "uniform_cpu": u[-1][1],
               "adaptive_final": a[-1][0]}
        for name, col in (("max", 2), ("rms", 3), ("sd", 4)):
            for kind, sus in (("", True), ("_first", False)):
                need = injections_to_reach(a, u[-1][col], col, sustained=sus)
                row[f"need_{name}{kind}"] = need
                row[f"ratio_{name}{kind}"] = u[-1][0] / (need or a[-1][0])
                row[f"reached_{name}{kind}"] = need is not None
            k = next((i for i, r in enumerate(a) if r[0] == row[f"need_{name}"]), len(a) - 1)
            row[f"cpu_{name}"] = a[k][1]
        summary.append(row)

    def fmt(r, key):
        return f"{'' if r['reached_' + key] else '>'}{r['ratio_' + key]:.1f}x"

    out("\n# injections the adaptive design needs to reach the uniform design's final value "
        "(stays below to the end; first crossing in brackets; '>' = not reached, lower bound)")
    out(f"{'seed':>4} {'uniform':>8} {'max|err|':>16} {'rms|err|':>16} {'max sd':>16} "
        f"{'CPU a/u (max)':>14}")
    for r in summary:
        cols = [f"{fmt(r, k):>6} ({fmt(r, k + '_first'):>6})" for k in ("max", "rms", "sd")]
        out(f"{r['seed']:>4} {r['uniform_final']:>8d} {cols[0]:>16} {cols[1]:>16} {cols[2]:>16} "
            f"{r['cpu_max'] / max(r['uniform_cpu'], 1e-9):>13.1f}x")
    # The same on the curves averaged over seeds (budgets are the same for every seed).
    mu, ma = np.mean(np.array(curves_u, float), axis=0), np.mean(np.array(curves_a, float), axis=0)
    out(f"\n# mean over {len(seeds)} seeds")
    out(f"{'design':>8} " + head)
    for name, rows in (("uniform", mu), ("adaptive", ma)):
        for r in rows:
            out(f"{name:>8} {int(r[0]):>10d} {r[1]:>7.1f} {r[2]:>9.4f} {r[3]:>9.4f} {r[4]:>8.4f}")
    mean_ratio = {}
    for name, col in (("max", 2), ("rms", 3), ("sd", 4)):
        need = injections_to_reach([tuple(r) for r in ma], mu[-1][col], col)
        mean_ratio[name] = (mu[-1][0] / need, True) if need else (mu[-1][0] / ma[-1][0], False)
        out(f"# mean {name:>3}: uniform's final {mu[-1][col]:.4f} at {int(mu[-1][0])} injections; "
            f"adaptive reaches it at {int(need) if need else '>' + str(int(ma[-1][0]))}: "
            f"{'' if need else '>'}{mean_ratio[name][0]:.1f}x fewer injections")
    for name in ("max", "rms", "sd"):
        ratios = [r[f"ratio_{name}"] for r in summary]
        out(f"# {name:>3}: median ratio {np.median(ratios):.1f}x over {len(ratios)} seeds "
            f"(min {min(ratios):.1f}x, max {max(ratios):.1f}x); reached in "
            f"{sum(r[f'reached_{name}'] for r in summary)} of {len(summary)}")
    return summary, mean_ratio


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--max-steps", type=int, default=1500)
    ap.add_argument("--uniform-n", type=int, nargs="+", default=[10, 20, 40, 80])
    ap.add_argument("--initial-n", type=int, default=12)
    ap.add_argument("--round-size", type=int, default=300)
    ap.add_argument("--adaptive-budget", type=int, default=None,
                    help="default: the uniform design's final budget")
    ap.add_argument("--min-per-cell", type=int, default=10)
    ap.add_argument("--outcomes", choices=("selected", "all"), default="selected")
    ap.add_argument("--criterion", choices=("information", "sd", "variance"),
                    default="information")
    a = ap.parse_args(argv)
    budget = a.adaptive_budget or UNIFORM_Z.size * UNIFORM_M.size * max(a.uniform_n)
    print(f"surrogate: known C*S, box z {BOX[0]}, m {BOX[1]}; fit max_steps {a.max_steps}; "
          f"acquisition: {a.criterion} ({a.outcomes}), min {a.min_per_cell} per cell")
    compare_designs(surrogate_simulate, make_fit(a.max_steps),
                    make_propose(min_per_cell=a.min_per_cell, outcomes=a.outcomes,
                                 criterion=a.criterion), a.seeds,
                    uniform_n=a.uniform_n, initial_n=a.initial_n, adaptive_budget=budget,
                    round_size=a.round_size)


if __name__ == "__main__":
    main()
