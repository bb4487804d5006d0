"""Cost of a user selection function against the expression selection (issue 23, speed).

Builds the embedded 4-band demo field in a temporary directory, measures it once, then
runs the same tasks (:func:`glaciar.engine.task.run_task`, ``n`` sources each) with each
selection on the same field context, interleaved task by task so that a shared machine's
load falls on all of them alike, and prints CPU time per injected source
(``time.process_time``):

* ``expression``: the default BoRG J125-dropout expressions (glaciar's interpreter);
* ``function (boolean)``: the same cuts as a vectorised numpy function;
* ``function (probability)``: a vectorised logistic P(selected) in S/N, ``selected``
  drawn from it;
* ``example photo-z``: ``examples/photoz_selection.py`` (templates x 150 z per source).

and, separately, the selection step alone on the tasks' tables (the call that differs).
Acceptance (issue 23): a vectorised function costs <= 10 % more per source than the
expression.

Usage::

    python benchmarks/user_selection.py [--size 600] [--tasks 6] [--n 60] [--repeat 200]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from glaciar.config import load_config
from glaciar.demo import build_demo_survey
from glaciar.engine.selection import DEFAULT_JDROPOUT, compile_selection
from glaciar.engine.task import run_task
from glaciar.engine.user_selection import (BOOLEAN, PROBABILITY, SelectionFunction,
                                           apply_selection, function_columns)
from glaciar.fieldprep import build_field_context
from glaciar.plan import plan_tasks
from glaciar.survey import Survey

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import photoz_selection  # noqa: E402  (the example lives outside the package)


def jdropout(t):
    """DEFAULT_JDROPOUT as numpy (NaN compares False, as in the interpreter)."""
    with np.errstate(invalid="ignore"):
        return ((t["sn_f160w"] >= 8) & (t["sn_f606w"] < 1.5) & (t["sn_f098m"] < 1.5)
                & (t["maglim_f125w"] - t["mag_f160w"] > 1.5))


def logistic(t):
    sn = np.nan_to_num(t["sn_f160w"], nan=-100.0)
    return 1.0 / (1.0 + np.exp(-(sn - 8.0) / 2.0))


def _selections(cfg):
    cols = function_columns(cfg.survey.band_names, len(cfg.detection.phot_apertures))
    photoz_kw = {"filters": {b.name: b.filter for b in cfg.survey.bands},
                 "zeropoints": {b.name: b.zeropoint for b in cfg.survey.bands},
                 "z_cut": 7.0, "p_min": 0.7, "sn_band": "f160w", "min_sn": 8.0}

    def fn(name, func, kind, kwargs=None):
        return SelectionFunction(spec=f"benchmark:{name}", version="1", kind=kind, columns=cols,
                                 kwargs=kwargs or {}, func=func)
    return {"expression": compile_selection(DEFAULT_JDROPOUT),
            "function (boolean)": fn("jdropout", jdropout, BOOLEAN),
            "function (probability)": fn("logistic", logistic, PROBABILITY),
            "example photo-z": fn("photoz", photoz_selection.select, BOOLEAN, photoz_kw)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=600, help="field side [pixels]")
    ap.add_argument("--tasks", type=int, default=6, help="timed tasks per selection")
    ap.add_argument("--n", type=int, default=60, help="sources per task")
    ap.add_argument("--repeat", type=int, default=200, help="repetitions of the step alone")
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        path = build_demo_survey(Path(tmp), shape=(args.size, args.size), seed=5,
                                 n_galaxies=args.n, n_iterations=args.tasks + 1,
                                 z_values=(9.0,), mag_values=(26.0,))
        cfg = load_config(path)
        survey = Survey.from_config(cfg)
        field = cfg.survey.fields[0]
        ctx = build_field_context(cfg, survey, field)
        selections = _selections(cfg)
        specs = [s for s in plan_tasks(cfg) if s.field == field][:args.tasks + 1]
        cpu = {k: 0.0 for k in selections}
        n_src = {k: 0 for k in selections}
        tables = []
        names = list(selections)
        for i, spec in enumerate(specs):
            ctx.selection = selections["expression"]
            run_task(ctx, spec, seed=1)      # untimed: the task's stamps enter the caches
            # Rotate the order, so that no selection always runs first after the warm-up.
            for name in names[i % len(names):] + names[:i % len(names)]:
                ctx.selection = selections[name]
                t0 = time.process_time()
                table = run_task(ctx, spec, seed=1)
                dt = time.process_time() - t0
                if i == 0:               # warm-up: caches, the photo-z templates
                    continue
                cpu[name] += dt
                n_src[name] += len(table)
                if name == "expression":
                    tables.append(table)
        step = {}
        for name, sel in selections.items():
            rows = sum(len(t) for t in tables)
            t0 = time.process_time()
            for _ in range(args.repeat):
                for t in tables:
                    apply_selection(sel, t, (1,))
            step[name] = (time.process_time() - t0) / (args.repeat * rows) * 1e6
    base = cpu["expression"] / n_src["expression"] * 1e3
    print(f"demo field {args.size}^2 px, {args.tasks} tasks x {args.n} sources "
          f"(z = 9, m = 26), CPU per injected source")
    print(f"{'selection':<26}{'whole task [ms]':>16}{'vs expression':>15}"
          f"{'selection step [us]':>21}")
    for name in selections:
        ms = cpu[name] / n_src[name] * 1e3
        print(f"{name:<26}{ms:>16.3f}{ms / base - 1:>+15.1%}{step[name]:>21.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
