"""Cost of lensed injections: CPU per source behind the demo's lens against unlensed.

Builds the demo field (1000 x 1000 px, or ``--size``) once, measures it once, and runs the
same tasks (z, mag, iteration) on its context without a lens and with the lens of
``glaciar demo --lensed`` (glaciar.demo.lensed.DEMO_LENS), in this process, timing each
task's process CPU.  The difference is the lensed path's own work: the placement by
rejection (the lens, the intrinsic size and the lensed box at each candidate), and stamps
rendered per source (a lensed shape is continuous, so the template cache rarely hits).

    PYTHONPATH=. python benchmarks/lensed.py [--size 1000] [--tasks 6] [--out /tmp/bench]

Prints a table and, last, a JSON line.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def _cpu():
    return time.process_time()


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1000)
    ap.add_argument("--tasks", type=int, default=6, help="tasks per (z, mag) setting")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    from glaciar.config import load_config
    from glaciar.demo import build_demo_survey
    from glaciar.demo.lensed import write_lensed_demo_config
    from glaciar.engine.task import TaskSpec, run_task
    from glaciar.fieldprep import build_field_context
    from glaciar.lensmaps import LazyFieldLens
    from glaciar.survey import Survey

    out = Path(args.out or tempfile.mkdtemp(prefix="glaciar-lensed-bench-"))
    path = build_demo_survey(out / "survey", shape=(args.size, args.size))
    cfg = load_config(write_lensed_demo_config(path))
    survey = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    lensed = build_field_context(cfg, survey, field)
    plain = dataclasses.replace(lensed, lens=None)
    lensed = dataclasses.replace(lensed, lens=LazyFieldLens(cfg, survey, field))
    settings = [(8.2, 25.0), (9.8, 26.5), (11.4, 28.0)]
    rows = []
    for z, mag in settings:
        for name, ctx in (("unlensed", plain), ("lensed", lensed)):
            ctx.cache.clear()
            cpu, n, mus = 0.0, 0, []
            for it in range(args.tasks):
                spec = TaskSpec(field, 0, 0, 0, it, z, mag)
                t0 = _cpu()
                table = run_task(ctx, spec, cfg.simulation.seed)
                cpu += _cpu() - t0
                n += len(table)
                if "magnification" in table:
                    mus.append(np.abs(table["magnification"].to_numpy()))
            med = float(np.median(np.concatenate(mus))) if mus else 1.0
            rows.append({"z": z, "mag": mag, "path": name, "sources": n,
                         "cpu_ms_per_source": 1e3 * cpu / max(n, 1), "median_abs_mu": med})
    print(f"{'z':>5} {'mag':>5} {'path':>9} {'sources':>8} {'CPU ms/source':>14} {'median |mu|':>12}")
    for r in rows:
        print(f"{r['z']:5.1f} {r['mag']:5.1f} {r['path']:>9} {r['sources']:8d} "
              f"{r['cpu_ms_per_source']:14.1f} {r['median_abs_mu']:12.2f}")
    tot = {p: sum(r["cpu_ms_per_source"] * r["sources"] for r in rows if r["path"] == p)
           / sum(r["sources"] for r in rows if r["path"] == p) for p in ("unlensed", "lensed")}
    print(f"all: unlensed {tot['unlensed']:.1f} ms/source, lensed {tot['lensed']:.1f} ms/source "
          f"(x{tot['lensed'] / tot['unlensed']:.2f})")
    result = {"size": args.size, "rows": rows, "ms_per_source": tot}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
