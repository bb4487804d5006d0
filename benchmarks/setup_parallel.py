"""1 -> 2 workers on a whole run, field set-up included (issue 24, point 2).

A demo survey of ``--fields`` fields (4 bands, ``--size``^2 each, written once into
``--dir`` or a temporary directory) and a grid of ``--tasks`` tasks spread evenly over
the fields (3 redshifts x 5 magnitudes x iterations, ``--n`` sources each) are simulated
through :func:`glaciar.execute.simulate`, each run in a fresh child interpreter and a
fresh run directory, with ``workers=1`` (everything in one process: each field measured
in turn, then the tasks) and ``workers=2`` (a process pool whose workers measure the
fields, one job per field, then run the tasks; :func:`glaciar.contexts.measure_field`).

Printed per worker count: the wall time of the whole ``simulate`` call [s] and of the
child (imports included), of which the set-up (inputs checked, fields measured,
manifest written: ``setup_seconds``) and its share of the call, the task phase
(``task_seconds``), peak RSS of the main process and of the largest pool worker,
and CPU seconds by stage: the set-up (a second child runs the
set-up alone, ``max_tasks=0``, its pool reaped: main process + workers), inside the
tasks (``cpu_seconds``) and the whole call (``process_cpu_seconds``).  Then the
speed-ups 1 -> 2 workers of the call's wall time (acceptance: >= 1.8x), of the set-up
and of the task phase, and the same from CPU seconds alone: the main process's plus
its busiest pool worker's (each worker's own CPU, written as it exits), i.e. the
critical path on two free cores -- the figure to read on a loaded machine.  The load average before and after each run is printed; over
1.5 (the machine shared with other work) the wall times and speed-ups are marked as
measured under load: the CPU seconds are the figures to trust then.

Usage::

    python benchmarks/setup_parallel.py [--fields 4] [--size 1000] [--tasks 120] [--n 50]
                                        [--dir DIR] [--repeat 1]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _child import spawn  # noqa: E402

Z_VALUES = (8.0, 9.0, 10.0)
MAG_VALUES = (25.0, 25.5, 26.0, 26.5, 27.0)
LOADED = 1.5        #: load average above which wall times are marked as measured under load


def _survey(opt) -> Path:
    """The benchmark's survey config in ``opt.dir`` (written unless there already)."""
    import yaml

    from glaciar.demo import build_demo_survey

    d = Path(opt.dir)
    config = d / f"setup_parallel_{opt.fields}x{opt.size}_{opt.tasks}_{opt.n}.yaml"
    if config.exists():
        return config
    names = [f"f{i:02d}" for i in range(opt.fields)]
    demo = None
    for i, name in enumerate(names):
        demo = build_demo_survey(d, shape=(opt.size, opt.size), seed=100 + i, field=name)
    data = yaml.safe_load(demo.read_text())
    data["survey"]["fields"] = names
    data["grid"]["z"] = {"values": list(Z_VALUES)}
    data["grid"]["mag"] = {"values": list(MAG_VALUES)}
    per_field = len(Z_VALUES) * len(MAG_VALUES)
    data["simulation"].update(n_galaxies=opt.n, n_iterations=opt.tasks // (opt.fields * per_field))
    config.write_text(yaml.safe_dump(data, sort_keys=False))
    return config


def _child(opt) -> dict:
    """One ``simulate`` call (this child's imports timed too); its stats as JSON."""
    t_start = time.perf_counter()
    import resource

    from glaciar.config import load_config
    from glaciar.execute import simulate
    from glaciar.workers import process_cpu_seconds

    t_imported = time.perf_counter()
    cfg = load_config(opt.config)
    log = Path(opt.out).with_suffix(".workers")
    _account_workers(log)
    load0 = os.getloadavg()[0]
    c0, m0 = process_cpu_seconds(), process_cpu_seconds(children=False)
    stats = simulate(cfg, opt.out, workers=opt.workers, progress=False,
                     max_tasks=0 if opt.setup_only else None)
    # Peak resident sets [MB]: this process's, and the largest of its reaped pool workers'.
    own, kids = (resource.getrusage(who).ru_maxrss / 1024.0
                 for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    workers = [float(line.split()[1]) for line in log.read_text().splitlines()] \
        if log.exists() else []
    log.unlink(missing_ok=True)
    return {"main_rss_mb": own, "worker_rss_mb": kids, "worker_cpu_s": workers,
            "main_cpu_s": process_cpu_seconds(children=False) - m0,"wall_s": stats["wall_seconds"], "setup_s": stats["setup_seconds"],
            "task_s": stats["task_seconds"], "task_cpu_s": stats["cpu_seconds"],
            "cpu_s": process_cpu_seconds() - c0, "n_run": stats["n_run"],
            "n_sources": stats["n_sources"], "import_s": t_imported - t_start,
            "child_wall_s": time.perf_counter() - t_start,
            "load": [load0, os.getloadavg()[0]]}


def _account_workers(log: Path) -> None:
    """Have each pool worker of :func:`glaciar.execute.simulate` append its own CPU seconds
    to ``log`` when it exits (forked workers inherit the patched initializer)."""
    import multiprocessing.util

    import glaciar.execute as execute

    init = execute.worker_init

    def init_and_account(parent_pid):
        init(parent_pid)

        def write():
            t = os.times()
            with open(log, "a") as fh:
                fh.write(f"{os.getpid()} {t.user + t.system}\n")

        # Run by multiprocessing when the worker process ends normally (pool shut down).
        multiprocessing.util.Finalize(None, write, exitpriority=100)

    execute.worker_init = init_and_account


def _critical_cpu(r: dict) -> float:
    """CPU seconds on the run's critical path if each process had a core of its own: the main
    process's, plus its busiest worker's (an upper bound: part of the main process's CPU
    overlaps the workers')."""
    return r["main_cpu_s"] + max(r["worker_cpu_s"], default=0.0)


def _run(opt, config: Path, workers: int, setup_only: bool, scratch: Path) -> dict:
    out = scratch / f"run_w{workers}{'_setup' if setup_only else ''}"
    shutil.rmtree(out, ignore_errors=True)
    try:
        return spawn(__file__, ["--child", "--config", str(config), "--out", str(out),
                                "--workers", str(workers)] + (["--setup-only"] if setup_only else []))
    finally:
        shutil.rmtree(out, ignore_errors=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fields", type=int, default=4, help="fields of the survey (default 4)")
    ap.add_argument("--size", type=int, default=1000, help="side of each field [px] (default 1000)")
    ap.add_argument("--tasks", type=int, default=120, help="tasks of the run (default 120)")
    ap.add_argument("--n", type=int, default=50, help="sources per task (default 50)")
    ap.add_argument("--dir", default=None, help="survey directory (kept; default a temporary one)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="runs per worker count, interleaved (the fastest kept)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--config", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--workers", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--setup-only", action="store_true", help=argparse.SUPPRESS)
    opt = ap.parse_args(argv)
    if opt.child:
        print(json.dumps(_child(opt)))
        return 0
    per_field = len(Z_VALUES) * len(MAG_VALUES)
    if opt.tasks % (opt.fields * per_field):
        ap.error(f"--tasks must be a multiple of --fields x {per_field}")
    own_dir = opt.dir is None
    opt.dir = tempfile.mkdtemp(prefix="glaciar_setup_parallel_") if own_dir else opt.dir
    Path(opt.dir).mkdir(parents=True, exist_ok=True)
    scratch = None
    try:
        config = _survey(opt)
        scratch = Path(tempfile.mkdtemp(prefix="runs_", dir=opt.dir))
        print(f"glaciar setup_parallel: {opt.fields} demo fields of {opt.size}^2 (4 bands), "
              f"{opt.tasks} tasks x {opt.n} sources; {os.cpu_count()} CPUs; load average "
              f"{os.getloadavg()[0]:.2f}")
        runs = {(w, alone): [] for w in (1, 2) for alone in (False, True)}
        for _ in range(opt.repeat):     # interleaved: a change of the load hits both counts
            for w in (1, 2):
                for alone in (False, True):
                    runs[w, alone].append(_run(opt, config, w, alone, scratch))
        res = {}
        for w in (1, 2):
            full, setup = (min(runs[w, alone], key=lambda r: r["wall_s"]) for alone in (False, True))
            res[w] = full, setup
            assert full["n_run"] == opt.tasks, full
            print(f"workers={w}: simulate {full['wall_s']:.1f} s wall (child {full['child_wall_s']:.1f} s, "
                  f"imports {full['import_s']:.1f} s) = set-up {full['setup_s']:.1f} s "
                  f"({100 * full['setup_s'] / full['wall_s']:.0f} %) + tasks {full['task_s']:.1f} s "
                  f"+ rest {full['wall_s'] - full['setup_s'] - full['task_s']:.1f} s; CPU: set-up "
                  f"{setup['cpu_s']:.1f} s (alone: {setup['wall_s']:.1f} s wall), inside tasks "
                  f"{full['task_cpu_s']:.1f} s, whole call {full['cpu_s']:.1f} s; peak RSS main "
                  f"{full['main_rss_mb']:.0f} MB, largest worker {full['worker_rss_mb']:.0f} MB; "
                  f"load {full['load'][0]:.2f} -> {full['load'][1]:.2f}")
        (f1, s1), (f2, s2) = res[1], res[2]
        loads = [x for f, s in res.values() for x in (*f["load"], *s["load"])]
        print(f"speed-up 1 -> 2 workers: whole call {f1['wall_s'] / f2['wall_s']:.2f}x "
              f"(>= 1.8x aimed for), child incl. imports {f1['child_wall_s'] / f2['child_wall_s']:.2f}x, "
              f"set-up alone {s1['wall_s'] / s2['wall_s']:.2f}x, task phase "
              f"{f1['task_s'] / f2['task_s']:.2f}x")
        print(f"CPU on the critical path (main process + its busiest worker; load-independent): "
              f"1 worker {_critical_cpu(f1):.1f} s, 2 workers {_critical_cpu(f2):.1f} s "
              f"(workers {', '.join(f'{c:.1f}' for c in f2['worker_cpu_s'])} s), i.e. "
              f"{_critical_cpu(f1) / _critical_cpu(f2):.2f}x on two free cores; set-up alone "
              f"{_critical_cpu(s1) / _critical_cpu(s2):.2f}x")
        if max(loads) > LOADED:
            print(f"MEASURED UNDER LOAD: load average up to {max(loads):.2f} (> {LOADED}) on "
                  f"{os.cpu_count()} CPUs during the runs; the wall times and speed-ups above "
                  "depend on the other work; the CPU seconds do not")
    finally:
        if own_dir:
            shutil.rmtree(opt.dir, ignore_errors=True)
        elif scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
