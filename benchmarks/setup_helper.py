"""Does the forked set-up helper pay for itself? (issue 22 point 1)

A run's start (:func:`glaciar.manifest.open_run`) checks every input file, runs
the placement preflight and bisects the detection z limit; where
``glaciar.execute._setup_parallelism`` says ``"fork"`` (>= 2 worker processes and
the fork start method) those three run in a forked helper process
(``glaciar.manifest._SetupJobs``) while this process measures the field for the
manifest; otherwise they run here, one after the other, before it.

This script generates the demo survey once (``glaciar demo``'s survey,
1000^2, 4 bands; ``--size`` for another side) and times the start of a fresh
run -- ``simulate(..., max_tasks=0)``: inputs checked, field measured, manifest
and field cache written, no task -- with the helper forced on (``fork``) and
off (``serial``), for ``workers`` = 1 and 2.  Each start runs in its own child
process (cold caches, as a real run), ``--repeat`` times, the two variants
alternating (and which goes first); the median wall time and whole-process CPU (this child and its
reaped helper) are printed, and the load average before and after: on a shared
machine the wall times mean little beyond their ratio.

Measured (2 shared cores, load average 4-5 from other jobs; wall [s], median)::

    demo 1000^2, --repeat 4 (order alternated)   serial   fork   serial/fork
      workers 1                                    6.37    7.08   0.90x
      workers 2                                    6.51    7.23   0.90x
    demo 1000^2, --repeat 3 (serial always first)  7.87    6.57   1.20x  (w=1)
                                                   4.93    4.06   1.21x  (w=2)
    demo 400^2, --repeat 3 (serial always first)   3.28    3.17   1.03x  (w=1)
                                                   4.48    5.34   0.84x  (w=2)

Once the order is alternated the helper gains nothing (issue 11's note: "no gain
at idle" either): removed in the next commit (issue 22 point 1).

Usage::

    python benchmarks/setup_helper.py [--size 1000] [--repeat 3] [--tmp DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

_CHILD = r"""
import json, sys
from glaciar import execute
from glaciar.config import load_config
from glaciar.workers import process_cpu_seconds
cfg_path, out, workers, where = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
# The helper forced on or off; an executor is never passed here.
execute._setup_parallelism = lambda w, ex: "fork" if where == "fork" else None
cfg = load_config(cfg_path)
stats = execute.simulate(cfg, out, workers=workers, progress=False, max_tasks=0)
print(json.dumps({"wall": stats["wall_seconds"], "setup": stats["setup_seconds"],
                  "cpu": process_cpu_seconds()}))
"""


def _start(cfg_path: Path, out: Path, workers: int, where: str) -> dict:
    res = subprocess.run([sys.executable, "-c", _CHILD, str(cfg_path), str(out), str(workers), where],
                         check=True, capture_output=True, text=True, env=os.environ.copy())
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1000, help="demo image side [pixels] (default 1000)")
    ap.add_argument("--repeat", type=int, default=3, help="starts per variant (default 3)")
    ap.add_argument("--tmp", help="directory for the survey and runs (default a new temporary one)")
    opt = ap.parse_args(argv)

    from glaciar.demo import build_demo_survey

    root = Path(opt.tmp or tempfile.mkdtemp(prefix="glaciar-setuphelper-"))
    cfg_path = build_demo_survey(root / "survey", shape=(opt.size, opt.size))
    print(f"demo {opt.size}^2, load average before: {os.getloadavg()[0]:.2f}")
    print(f"{'workers':>7} {'set-up':>7} {'wall [s]':>9} {'CPU [s]':>8}   (median of {opt.repeat})")
    results = {}
    n = 0
    for workers in (1, 2):
        runs: dict = {"serial": [], "fork": []}
        for k in range(opt.repeat):
            # Alternating which goes first: neither gains from the other's warmed page cache.
            for where in (("serial", "fork") if k % 2 == 0 else ("fork", "serial")):
                n += 1
                runs[where].append(_start(cfg_path, root / f"run{n}", workers, where))
        for where, rs in runs.items():
            wall = statistics.median(r["wall"] for r in rs)
            cpu = statistics.median(r["cpu"] for r in rs)
            results[(workers, where)] = wall
            print(f"{workers:>7} {where:>7} {wall:9.2f} {cpu:8.2f}")
        print(f"{workers:>7} serial/fork wall: {results[(workers, 'serial')] / results[(workers, 'fork')]:.2f}x")
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
