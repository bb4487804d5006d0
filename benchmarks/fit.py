"""Wall time and autocorrelation time of `glaciar fit` for 1e4, 1e5 and 1e6 sources.

Flags are drawn from known surfaces on a 13 (z) x 25 (m) grid with a
continuous mag_input (0.1 mag scatter, as a varying UV slope gives), so the
aggregation runs at its default 0.01 mag resolution.  Columns: sources,
aggregated cells, aggregation time, MAP time, sampling time (Laplace, pilot,
emcee to convergence), total fit time (MAP + sampling), chain length and
largest tau of the completeness / selection blocks, acceptance fractions,
whether both blocks reached 50 tau, and the effective number of independent
draws of the worst parameter (walkers x (steps - burn-in) / tau_max).

    python benchmarks/fit.py [N ...]
"""
from __future__ import annotations

import sys
import time
import warnings

import numpy as np
import pandas as pd

from glaciar.inference import SurfaceModel, aggregate_cells, find_map, fit_surfaces

TRUTH = dict(logit_c_max=2.5, m50_0=27.4, m50_1=-0.3, m50_2=0.05, log_w_0=np.log(0.3),
             log_w_1=0.1, logit_s_max=3.0, z_lo_0=6.8, z_lo_1=0.1, log_dz_lo_0=np.log(0.15),
             log_dz_lo_1=0.1, z_hi_0=8.4, z_hi_1=-0.1, log_dz_hi_0=np.log(0.2), log_dz_hi_1=0.0)


def make(n, rng):
    zg, mg = np.arange(6.0, 9.01, 0.25), np.arange(24.0, 30.01, 0.25)
    mdl = SurfaceModel.for_data(zg, mg)
    th = mdl.prior_mean.copy()
    for k, v in TRUTH.items():
        th[mdl.param_names.index(k)] = v
    z = rng.choice(zg, n)
    m = rng.choice(mg, n) + 0.1 * rng.standard_normal(n)
    rec = rng.random(n) < mdl.completeness(th, m, z)
    sel = rec & (rng.random(n) < mdl.selection(th, z, m))
    return pd.DataFrame({"z": z, "mag_input": m, "recovered": rec, "selected": sel})


def main(sizes):
    print(f"{'N':>9} {'cells':>6} {'agg s':>6} {'map s':>6} {'mcmc s':>6} {'fit s':>6} "
          f"{'steps c/s':>10} {'tau_max c/s':>12} {'acc c/s':>10} {'conv':>5} {'ESS c/s':>11}")
    for n in sizes:
        df = make(n, np.random.default_rng(n))
        t0 = time.perf_counter()
        cells = aggregate_cells(df)
        t1 = time.perf_counter()
        mdl = SurfaceModel.for_data(cells.z, cells.mag)
        theta_map = find_map(mdl, cells)
        t2 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = fit_surfaces(cells, mdl, seed=0, theta_map=theta_map)
        t3 = time.perf_counter()
        b = res.blocks
        ess = [bb.chain.shape[1] * (bb.n_steps - bb.burn) / max(bb.tau) for bb in b]
        print(f"{n:>9d} {len(cells):>6d} {t1 - t0:>6.2f} {t2 - t1:>6.2f} {t3 - t2:>6.2f} "
              f"{t3 - t1:>6.2f} {b[0].n_steps:>4d}/{b[1].n_steps:<5d} "
              f"{max(b[0].tau):>5.1f}/{max(b[1].tau):<6.1f} "
              f"{np.mean(b[0].acceptance_fraction):>4.2f}/{np.mean(b[1].acceptance_fraction):<5.2f} "
              f"{str(res.converged):>5} {ess[0]:>5.0f}/{ess[1]:<5.0f}", flush=True)


if __name__ == "__main__":
    main([int(float(a)) for a in sys.argv[1:]] or [10_000, 100_000, 1_000_000])
