"""Calibration at fixed truths with more replicates than the test runs.

The three truths of ``tests/inference/test_fit_calibration.py`` (logistic with both
selection edges inside the simulated z range; the upper edge just beyond it,
as in the demo; an erf step fitted with ``fit_and_choose`` over every step),
each fitted to ``N`` replicate data sets of 2800 sources with the production
sampler; prints the coverage of the central 68 % and 95 % credible intervals
of C, S and P = C S at the truth's 4 x 4 (z, m) points, averaged over
replicates and points, with its cluster Monte Carlo standard error, the worst
single point, the steps picked by PSIS-LOO, convergence, tau and time.

    python benchmarks/calibration.py [N_REPLICATES [WORKERS]]     (default 200, 2)

The replicates are seeded exactly as in the test (replicate r of a truth is
the same data set and chain), so the test's replicates are the first 100 here.
Cost: ~1.5 s of CPU per replicate of the first truth, ~15 s (mean; 11 % of the
replicates run to max_steps at ~60 s each) of the second and ~12 s (four steps
fitted) of the third: 200 replicates take ~50 minutes on 2 free cores.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "inference"))

import test_fit_calibration as cal  # noqa: E402


def main(n_reps=200, workers=2):
    t0 = time.perf_counter()
    jobs = [(name, rep) for name in cal.TRUTHS for rep in range(n_reps)]
    jobs.sort(key=lambda j: j[0] not in cal.AUTO)
    results = cal.run_replicates(jobs, workers=workers)
    summary, table = cal.coverage_table(results)
    print(f"Calibration at fixed truths: {n_reps} replicates x {len(cal.TRUTHS)} truths, "
          f"{workers} workers, {time.perf_counter() - t0:.0f} s wall")
    print(table)
    bad = [(name, q, p) for name, s in summary.items() for i, q in enumerate(cal.QUANTITIES)
           for j, p in enumerate(cal.LEVELS) if abs(s["cov"][i, j] - p) > cal.TOL[p]]
    noisy = [(name, q, p) for name, s in summary.items() for i, q in enumerate(cal.QUANTITIES)
             for j, p in enumerate(cal.LEVELS) if s["se"][i, j] > cal.TOL[p] / 2]
    print("all coverages within tolerance" if not bad else f"outside tolerance: {bad}")
    print("every MC s.e. <= tolerance / 2" if not noisy else f"MC s.e. > tolerance / 2: {noisy}")


if __name__ == "__main__":
    args = [int(a) for a in sys.argv[1:]]
    main(*args)
