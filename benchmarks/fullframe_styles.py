"""Windowed against full-frame measurement for every detection style (issue 22, point 2).

Builds the 4-band demo field (``--size`` square, F160W detection) once, and for each
combination of ``CLEAN_STYLE`` x ``THRESHOLD_RMS`` x ``FILTER_TYPE`` asked for builds
the field context (its reference extraction depends on them), draws ``--tasks`` tasks
of ``--n`` injected sources at magnitude ``--mag`` through
:func:`glaciar.engine.task.run_task`, and measures each task's injected scenes
twice with :func:`glaciar.engine.measure.measure_injected`: ``mode="windowed"`` and
``mode="full"``.  It prints, per combination, CPU milliseconds per injected source
(``time.process_time``) of each mode, their ratio full / windowed, and whether the
per-source rows are bit-identical and equal to 1e-9 relative (the tests' criterion;
every column but ``detection_id``, whose labels are per extraction; NaN equal to NaN).

Usage::

    python benchmarks/fullframe_styles.py [--size 1000] [--tasks 3] [--n 100] [--mag 26]
        [--styles region,sextractor,sep,sep-merge] [--thresholds pixel,filtered]
        [--filters conv,matched]
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import tempfile
import time

import numpy as np
import yaml

import glaciar.engine.task as task_module
from glaciar.config import load_config
from glaciar.demo import build_demo_survey
from glaciar.engine.measure import measure_injected
from glaciar.fieldprep import build_field_context
from glaciar.plan import plan_tasks
from glaciar.survey import Survey


def _compare_rows(a: dict, b: dict) -> tuple[bool, bool]:
    """(bit-identical, equal to 1e-9 relative) over every column but detection_id, NaN where
    NaN (the second is the tests' criterion: ``tests/conftest.py::_assert_same_outputs``)."""
    bits = close = True
    for k in a:
        if k == "detection_id":
            continue
        x, y = np.asarray(a[k]), np.asarray(b[k])
        if x.dtype.kind == "f":
            bits &= bool(np.array_equal(x, y, equal_nan=True))
            with np.errstate(invalid="ignore"):
                close &= bool(np.all((np.isnan(x) & np.isnan(y)) | (np.abs(x - y) <= 1e-9 * np.abs(y))))
        else:
            same = bool(np.array_equal(x, y))
            bits &= same
            close &= same
    return bits, close


def _captured_calls(cfg, ctx, tasks):
    """The measure_injected arguments of the first ``tasks`` tasks (run once, windowed)."""
    real = task_module.measure_injected
    calls = []

    def recording(*args, **kwargs):
        calls.append((args, kwargs))
        return real(*args, **kwargs)

    task_module.measure_injected = recording
    try:
        for spec in plan_tasks(cfg)[:tasks]:
            task_module.run_task(ctx, spec, cfg.simulation.seed)
    finally:
        task_module.measure_injected = real
    return calls


def run_combo(path, style, threshold, filt, tasks):
    raw = yaml.safe_load(open(path))
    det = raw.setdefault("detection", {})
    det["CLEAN_STYLE"], det["THRESHOLD_RMS"], det["FILTER_TYPE"] = style, threshold, filt
    combo = path.parent / f"combo_{style}_{threshold}_{filt}.yaml"
    with open(combo, "w") as fh:
        yaml.safe_dump(raw, fh)
    cfg = load_config(combo)
    ctx = build_field_context(cfg, Survey.from_config(cfg), cfg.survey.fields[0])
    calls = _captured_calls(cfg, ctx, tasks)
    sig = inspect.signature(measure_injected)
    t = {"windowed": 0.0, "full": 0.0}
    n_src, bits, close = 0, True, True
    for args, kwargs in calls:
        b = sig.bind(*args, **kwargs)
        b.arguments.pop("mode", None)
        out = {}
        for mode in ("windowed", "full"):
            t0 = time.process_time()
            out[mode] = measure_injected(*b.args, **b.kwargs, mode=mode)
            t[mode] += time.process_time() - t0
        n_src += len(out["full"]["status"])
        b_, c_ = _compare_rows(out["windowed"], out["full"])
        bits, close = bits and b_, close and c_
    return {"n": n_src, "t_win": t["windowed"], "t_full": t["full"], "bits": bits, "close": close}


def _yn(flag):
    return "yes" if flag else "NO"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=1000, help="image side [pixels] (default 1000)")
    ap.add_argument("--tasks", type=int, default=3, help="tasks per combination (default 3)")
    ap.add_argument("--n", type=int, default=100, help="injected sources per task (default 100)")
    ap.add_argument("--mag", type=float, default=26.0, help="F160W magnitude [AB] (default 26)")
    ap.add_argument("--z", type=float, default=8.0, help="redshift (default 8)")
    ap.add_argument("--seed", type=int, default=3, help="seed of the demo images (default 3)")
    ap.add_argument("--styles", default="region,sextractor,sep,sep-merge", help="CLEAN_STYLE values")
    ap.add_argument("--thresholds", default="pixel,filtered", help="THRESHOLD_RMS values")
    ap.add_argument("--filters", default="conv,matched", help="FILTER_TYPE values")
    opt = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="glaciar-ffstyles-") as tmp:
        path = build_demo_survey(tmp, shape=(opt.size, opt.size), seed=opt.seed, n_galaxies=opt.n,
                                 n_iterations=opt.tasks, z_values=(opt.z,), mag_values=(opt.mag,))
        rows = []
        for style in opt.styles.split(","):
            for thr in opt.thresholds.split(","):
                for filt in opt.filters.split(","):
                    r = run_combo(path, style, thr, filt, opt.tasks)
                    rows.append((style, thr, filt, r))
                    ms = lambda s: 1e3 * s / r["n"]  # noqa: E731
                    print(f"{style:>10s} {thr:>8s} {filt:>7s} windowed {ms(r['t_win']):7.3f} ms  "
                          f"full {ms(r['t_full']):7.3f} ms  full/windowed {r['t_full'] / r['t_win']:5.2f}  "
                          f"rows bit-identical {_yn(r['bits'])}, to 1e-9 {_yn(r['close'])}", flush=True)
    print()
    print(f"demo field {opt.size}x{opt.size} px, 4 bands, {opt.tasks} tasks x {opt.n} sources at "
          f"m = {opt.mag:g}, z = {opt.z:g}; CPU ms per injected source (time.process_time)")
    print(f"{'CLEAN_STYLE':>11s} {'THRESH_RMS':>10s} {'FILTER':>7s} {'windowed':>9s} {'full':>8s} "
          f"{'full/win':>8s} {'bits':>5s} {'1e-9':>5s}")
    for style, thr, filt, r in rows:
        ms = lambda s: 1e3 * s / r["n"]  # noqa: E731
        print(f"{style:>11s} {thr:>10s} {filt:>7s} {ms(r['t_win']):9.3f} {ms(r['t_full']):8.3f} "
              f"{r['t_full'] / r['t_win']:8.2f} {_yn(r['bits']):>5s} {_yn(r['close']):>5s}")


if __name__ == "__main__":
    main()
