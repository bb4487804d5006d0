"""The full simulation-based calibration of the depth-aware surfaces.

Runs ``tests/inference/test_fit_sbc.py``'s full check (the suite runs its first 64
data sets by default; the full one is marked ``slow``): N data sets drawn from
the prior, each refitted with the production ``fit_surfaces``; prints the
coverage of the central 68 % and 95 % credible intervals of C and S at the 18
(z, m, depth) points, averaged over data sets, with its cluster Monte Carlo
standard error, the coverage of intervals shrunk by 25 % (the power check) and
the time, and checks them against the full test's tolerances (5 points at 68 %,
3 at 95 %; every MC s.e. at most half of them).  Exit status 1 if a check fails.

    python benchmarks/sbc.py [N_SETS [WORKERS]]     (default 220, 2)

Data set k is seeded by k, as in the test, so the test's sets are the first N
here.  ``GLACIAR_SBC_PILOT=full`` runs the production pilot.  Cost: ~0.37 s of
CPU per data set (220 sets: 82 s of CPU, ~45 s on 2 free cores).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "inference"))

import test_fit_sbc as sbc  # noqa: E402


def main(n_sets=sbc.N_SETS, workers=sbc.N_WORKERS) -> int:
    t0 = time.perf_counter()
    try:
        sbc.check_sbc(n_sets, sbc.TOL, workers=workers)
    except AssertionError as exc:
        print(f"FAILED: {exc}")
        return 1
    finally:
        print(f"{n_sets} data sets, {workers} workers, {time.perf_counter() - t0:.0f} s wall")
    print("all coverages within tolerance, every MC s.e. <= tolerance / 2, "
          "25 %-narrow intervals caught")
    return 0


if __name__ == "__main__":
    args = [int(a) for a in sys.argv[1:]]
    sys.exit(main(*args))
