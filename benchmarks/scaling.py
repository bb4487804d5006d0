"""Mosaic independence, memory and parallel efficiency (issue 11, points 4-6).

For each image side in ``--sizes`` the embedded 4-band demo survey is generated
(in a child process, into a temporary directory on disk) and the same tasks
(``--tasks`` x ``--n`` sources at ``--z``, ``--mag``) are simulated through
:func:`glaciar.execute.simulate` in another child process, with a one-worker
process pool so that the worker's memory is seen apart from the main
process's (manifest, input checks, noise record).  Printed per size:

* whole-process CPU per injected source: :func:`glaciar.workers.process_cpu_seconds`
  (the child's own CPU plus its reaped pool worker, field set-up included), and
  its ratio to the smallest size (target: within 1.3x);
* CPU per source inside the tasks (``simulate``'s ``cpu_seconds``) and its ratio
  to the smallest size (target: within 1.3x);
* peak RSS of the pool worker (``RUSAGE_CHILDREN.ru_maxrss``: the largest
  reaped descendant, i.e. *per worker*, not summed) and of the main process
  (``RUSAGE_SELF``) [MB]; target <= 400 MB per worker on a 1200^2 field and
  <= 2 GB on 16000^2;
* peak RSS and wall time of the demo generation.  Up to
  ``glaciar.demo.strips.STRIP_MIN_PIXELS`` (2048^2) the generator builds the field
  in memory (~200 bytes per pixel); above, it streams it into the FITS files by
  strips of rows (~1.4 GB at any size: 1.2 GB at 4000^2, 1.3 GB at 8000^2,
  1.4 GB at 16000^2, measured).  A size whose generation would not fit in the
  available memory, or whose files would not fit on disk, is skipped with a message.

Then the 2-worker speed-up on ``--parallel-size``, through the process pool
(``workers=1`` runs in-process) and through a Dask ``LocalCluster`` (1 vs 2
worker processes, 1 thread each; cluster start-up not timed): the wall time
of the whole ``simulate`` call (target >= 1.8x on an otherwise idle machine),
separately its task phase (first submission to last result, from the stats
``simulate`` returns) and its serial seconds (the rest: input checks, field
measurement and manifest before, compaction after), and the Amdahl bound that
the 1-worker run's serial seconds allow.  The load average before and after
each run is printed: on a shared machine the wall times mean little.

Ratios are from one run; absolute times are noisy on a shared machine.

Usage::

    python benchmarks/scaling.py [--sizes 1000,4000[,16000]] [--tasks 30] [--n 100]
                                 [--z 8] [--mag 26] [--parallel-size 1000] [--no-parallel]
                                 [--tmp DIR] [--map-budget-mb MB] [--no-tiles] [--mmap-tiles]
                                 [--no-clean]

``--map-budget-mb`` sets the resident budget of a worker's memory-mapped field
cache (:data:`glaciar.engine.fieldcache.RESIDENT_BUDGET_BYTES`): with a budget
below the field's maps (e.g. 256 MB at 4000^2), pages are dropped during the
run as on a 16000^2 mosaic, which shows what the bound costs in task CPU.  A field
whose maps exceed that budget is cached as 64 x 64 tiles, which workers read with
positional reads (the rows of the tiles under a window; nothing mapped, nothing
dropped); ``--mmap-tiles`` memory-maps the tiles instead (the page cache's large
folios are then mapped whole and dropped past the budget) and ``--no-tiles`` keeps
the cache row-major (mapped), for comparison.  A second table gives the worker's user and
system CPU and its minor/major page faults per source.  ``--no-clean`` turns CLEAN off in the generated config: sep's CLEAN
of the full-frame reference extraction is quadratic in the number of objects and
takes ~30 min at 16000^2, so this is how the rest of a 16000^2 run is measured.
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

from _child import spawn

MB = 1024.0 ** 2
#: Peak memory of the whole-image demo generation per pixel [bytes] (measured: 3.2 GB at 4000^2).
GEN_BYTES_PER_PIXEL = 200
#: Peak memory of the strip-by-strip generation [bytes] (measured 1.2-1.4 GB, 4000^2-16000^2).
GEN_STRIP_BYTES = 1.6e9


def _generation_memory(size: int) -> float:
    """Expected peak memory [bytes] of generating the size^2 demo survey."""
    from glaciar.demo.strips import STRIP_MIN_PIXELS

    if size * size > STRIP_MIN_PIXELS:
        return GEN_STRIP_BYTES
    return GEN_BYTES_PER_PIXEL * size * size


def _available_memory() -> float | None:
    """MemAvailable of /proc/meminfo [bytes], None where there is none."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return 1024.0 * float(line.split()[1])
    except OSError:
        pass
    return None


# --------------------------------------------------------------------------
# Child processes (each measures its own peak RSS)
# --------------------------------------------------------------------------
def _maxrss_bytes(who) -> float:
    import resource

    # Linux reports ru_maxrss in KiB (macOS in bytes).
    k = 1 if sys.platform == "darwin" else 1024
    return float(resource.getrusage(who).ru_maxrss) * k


def _child_build(opt) -> dict:
    import resource

    from glaciar.demo import build_demo_survey

    t0 = time.perf_counter()
    path = build_demo_survey(opt.out, shape=(opt.size, opt.size), seed=opt.seed, n_galaxies=opt.n,
                             n_iterations=opt.tasks, z_values=(opt.z,), mag_values=(opt.mag,))
    if opt.no_clean:
        # sep's CLEAN of the full-frame reference extraction is quadratic in the number of
        # objects (~30 min at 16000^2): this measures the rest of the set-up and the tasks.
        import yaml

        cfg = yaml.safe_load(path.read_text())
        cfg["detection"]["CLEAN"] = False
        path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return {"config": str(path), "wall_s": time.perf_counter() - t0,
            "rss_mb": _maxrss_bytes(resource.RUSAGE_SELF) / MB}


def _child_run(opt) -> dict:
    import concurrent.futures as cf
    import resource

    from glaciar.config import load_config
    from glaciar.execute import simulate
    from glaciar.workers import process_cpu_seconds

    cfg = load_config(opt.config)
    if opt.map_budget_mb is not None:
        from glaciar.engine import fieldcache

        # Set before simulate opens the field cache: forked workers inherit it.
        fieldcache.RESIDENT_BUDGET_BYTES = int(opt.map_budget_mb * MB)
    if opt.no_tiles:
        from glaciar.engine import fieldcache

        fieldcache.TILED_CACHE = False
    if opt.mmap_tiles:
        from glaciar.engine import fieldcache

        # Tiles memory-mapped (pages trimmed by the budget) instead of read with preadv.
        fieldcache.READ_TILES = False
    out = {}
    c0 = process_cpu_seconds()
    t0 = time.perf_counter()
    if opt.executor == "pool1":
        # A one-worker pool: the worker's peak RSS is measured apart from this process's.
        ex = cf.ProcessPoolExecutor(max_workers=1)
        try:
            stats = simulate(cfg, opt.out, executor=ex, progress=False)
        finally:
            ex.shutdown(wait=True)
    elif opt.executor.startswith("dask"):
        import distributed

        nw = int(opt.executor[4:])
        with distributed.LocalCluster(n_workers=nw, threads_per_worker=1, processes=True,
                                      dashboard_address=None) as lc, \
                distributed.Client(lc) as client:
            client.run(lambda: None)               # every worker is up before timing
            t0 = time.perf_counter()
            stats = simulate(cfg, opt.out, executor=client.get_executor(), workers=nw,
                             progress=False)
            out["wall_s"] = time.perf_counter() - t0
    else:
        stats = simulate(cfg, opt.out, workers=int(opt.executor), progress=False)
    out.setdefault("wall_s", time.perf_counter() - t0)
    out["cpu_s"] = process_cpu_seconds() - c0
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    out["main_cpu_s"] = own.ru_utime + own.ru_stime
    out["worker_cpu_s"] = kids.ru_utime + kids.ru_stime
    # The reaped pool worker's user and system CPU and page faults (minor: a page mapped from
    # the page cache or a fresh anonymous page; major: read from disk).
    out["worker_user_s"], out["worker_sys_s"] = kids.ru_utime, kids.ru_stime
    out["worker_minflt"], out["worker_majflt"] = kids.ru_minflt, kids.ru_majflt
    out["task_cpu_s"] = float(stats["cpu_seconds"])     # inside run_task + writing, all workers
    out["n_sources"] = int(stats["n_sources"])
    out["setup_s"] = float(stats["setup_seconds"])      # inputs checked, field measured, manifest
    out["task_s"] = float(stats["task_seconds"])        # first submission to last result
    out["stats_cpu_s"] = float(stats["process_cpu_seconds"])
    out["n_run"] = int(stats["n_run"])
    out["main_rss_mb"] = _maxrss_bytes(resource.RUSAGE_SELF) / MB
    out["worker_rss_mb"] = _maxrss_bytes(resource.RUSAGE_CHILDREN) / MB
    return out


def _spawn(args: list[str]) -> dict:
    """Run this script as a child with ``args``; return the JSON it prints last."""
    return spawn(__file__, args)


# --------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="1000,4000",
                    help="comma-separated image sides [pixels] (default 1000,4000; add 16000)")
    ap.add_argument("--tasks", type=int, default=30, help="tasks per size (default 30)")
    ap.add_argument("--n", type=int, default=100, help="sources per task (default 100)")
    ap.add_argument("--z", type=float, default=8.0, help="redshift (default 8)")
    ap.add_argument("--mag", type=float, default=26.0, help="F160W magnitude [AB] (default 26)")
    ap.add_argument("--seed", type=int, default=3, help="seed of the demo images (default 3)")
    ap.add_argument("--parallel-size", type=int, default=1000,
                    help="image side of the 1 vs 2 worker comparison (default 1000)")
    ap.add_argument("--no-parallel", action="store_true", help="skip the 1 vs 2 worker comparison")
    ap.add_argument("--no-dask", action="store_true", help="skip the Dask LocalCluster comparison")
    ap.add_argument("--tmp", default=None, help="directory for the surveys (default: system temp)")
    ap.add_argument("--map-budget-mb", type=float, default=None,
                    help="resident budget of a worker's mapped field cache [MB] (default: "
                         "glaciar.engine.fieldcache.RESIDENT_BUDGET_BYTES)")
    ap.add_argument("--no-clean", action="store_true",
                    help="CLEAN off in the generated config (sep's full-frame CLEAN of the "
                         "reference extraction is quadratic in the number of objects)")
    ap.add_argument("--no-tiles", action="store_true",
                    help="keep the field cache row-major on large fields (no tiles; for comparison)")
    ap.add_argument("--mmap-tiles", action="store_true",
                    help="memory-map the tiles (pages trimmed by the budget) instead of reading "
                         "them with positional reads (for comparison)")
    # internal: child-process modes
    ap.add_argument("--child", choices=("build", "run"), help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--config", help=argparse.SUPPRESS)
    ap.add_argument("--executor", default="pool1", help=argparse.SUPPRESS)
    opt = ap.parse_args(argv)

    if opt.child == "build":
        print(json.dumps(_child_build(opt)))
        return
    if opt.child == "run":
        print(json.dumps(_child_run(opt)))
        return

    sizes = [int(s) for s in opt.sizes.split(",") if s.strip()]
    common = ["--tasks", str(opt.tasks), "--n", str(opt.n), "--z", str(opt.z), "--mag", str(opt.mag),
              "--seed", str(opt.seed)] + (["--no-clean"] if opt.no_clean else [])
    load = os.getloadavg()
    print(f"glaciar scaling: demo survey (4 bands{', CLEAN off' if opt.no_clean else ''}), {opt.tasks} tasks x {opt.n} sources at "
          f"z = {opt.z:g}, m = {opt.mag:g}; load average at start {load[0]:.1f} "
          f"on {os.cpu_count()} CPUs")
    if opt.tmp is not None:
        os.makedirs(opt.tmp, exist_ok=True)
    tmp_root = tempfile.mkdtemp(prefix="glaciar-scaling-", dir=opt.tmp)
    try:
        rows = []
        for size in sizes:
            sdir = Path(tmp_root) / f"s{size}"
            free = shutil.disk_usage(tmp_root).free
            need = 2 * 4 * 4 * size * size            # science + weight, 4 bands, float32
            if need > 0.8 * free:
                print(f"{size}^2: skipped, needs ~{need / 1e9:.1f} GB on disk, "
                      f"{free / 1e9:.1f} GB free in {tmp_root}")
                continue
            # Small fields are built in memory (~200 bytes per pixel), large ones by strips.
            gen = _generation_memory(size)
            avail = _available_memory()
            if avail is not None and gen > 0.8 * avail:
                print(f"{size}^2: skipped, generating the demo field needs ~{gen / 1e9:.1f} GB "
                      f"of memory, {avail / 1e9:.1f} GB available")
                continue
            b = _spawn(["--child", "build", "--size", str(size), "--out", str(sdir / "survey"),
                        *common])
            print(f"  {size}^2 generated: {b['wall_s']:.0f} s wall, peak RSS {b['rss_mb']:.0f} MB",
                  flush=True)
            budget = [] if opt.map_budget_mb is None else ["--map-budget-mb", str(opt.map_budget_mb)]
            if opt.no_tiles:
                budget.append("--no-tiles")
            if opt.mmap_tiles:
                budget.append("--mmap-tiles")
            r = _spawn(["--child", "run", "--config", b["config"], "--out", str(sdir / "run"),
                        "--executor", "pool1", *budget, *common])
            rows.append((size, b, r))
            shutil.rmtree(sdir / "run", ignore_errors=True)
            if size != opt.parallel_size:
                shutil.rmtree(sdir, ignore_errors=True)
            print(f"  {size}^2 done: {1e3 * r['cpu_s'] / max(r['n_sources'], 1):.2f} ms CPU/source, "
                  f"worker {r['worker_rss_mb']:.0f} MB", flush=True)

        print()
        print(f"{'side':>7s} {'sources':>8s} {'ms CPU/src':>11s} {'ratio':>6s} {'main ms':>8s} "
              f"{'worker ms':>10s} {'ratio':>6s} {'task ms':>8s} {'ratio':>6s} "
              f"{'worker RSS MB':>14s} {'main RSS MB':>12s} {'gen RSS MB':>11s} {'gen wall s':>11s}")
        base = base_w = base_t = None
        for size, b, r in rows:
            n = max(r["n_sources"], 1)
            ms, ms_main, ms_w, ms_t = (1e3 * r[k] / n for k in
                                       ("cpu_s", "main_cpu_s", "worker_cpu_s", "task_cpu_s"))
            base, base_w, base_t = base or ms, base_w or ms_w, base_t or ms_t
            print(f"{size:>7d} {r['n_sources']:>8d} {ms:>11.2f} {ms / base:>6.2f} {ms_main:>8.2f} "
                  f"{ms_w:>10.2f} {ms_w / base_w:>6.2f} {ms_t:>8.2f} {ms_t / base_t:>6.2f} "
                  f"{r['worker_rss_mb']:>14.0f} {r['main_rss_mb']:>12.0f} {b['rss_mb']:>11.0f} "
                  f"{b['wall_s']:>11.1f}")
        print("(ms CPU/src: glaciar.workers.process_cpu_seconds of simulate per injected source, main "
              "process + its 1-worker pool, set-up included, and its ratio to the first size "
              "(target <= 1.3); main ms / worker ms: the two parts (the main process checks the "
              "inputs, measures the field for the manifest and writes its field cache; the forked "
              "worker maps that cache and runs the tasks); task ms: CPU inside the tasks (run_task "
              "and the task file), target within 1.3x of the first size; worker RSS: peak of the pool worker, target <= 400 MB at "
              "1200^2, <= 2 GB at 16000^2; main RSS: peak of the main process)")
        print()
        print(f"{'side':>7s} {'worker user ms/src':>19s} {'sys ms/src':>11s} {'minor faults/src':>17s} "
              f"{'major faults/src':>17s}")
        for size, b, r in rows:
            n = max(r["n_sources"], 1)
            print(f"{size:>7d} {1e3 * r['worker_user_s'] / n:>19.3f} {1e3 * r['worker_sys_s'] / n:>11.3f} "
                  f"{r['worker_minflt'] / n:>17.1f} {r['worker_majflt'] / n:>17.2f}")
        print("(the pool worker: opening the field cache and every task; system time and minor "
              "faults grow when mapped pages are dropped and faulted in again)")

        if not opt.no_parallel:
            size = opt.parallel_size
            sdir = Path(tmp_root) / f"s{size}"
            cfg_path = sdir / "survey" / "demo.yaml"
            if not cfg_path.exists():
                _spawn(["--child", "build", "--size", str(size), "--out", str(sdir / "survey"),
                        *common])
            print()
            print(f"1 vs 2 workers on {size}^2 (wall time of simulate, same tasks, fresh run "
                  f"directory each; load average now {os.getloadavg()[0]:.1f}):")
            kinds = [("process pool", "1", "2")]
            if not opt.no_dask:
                try:
                    import distributed  # noqa: F401
                    kinds.append(("Dask LocalCluster", "dask1", "dask2"))
                except ImportError:
                    print("  (distributed not installed: Dask comparison skipped)")
            for name, one, two in kinds:
                runs = []
                for ex in (one, two):
                    run_dir = sdir / f"run_{ex}"
                    load0 = os.getloadavg()[0]
                    r = _spawn(["--child", "run", "--config", str(cfg_path), "--out", str(run_dir),
                                "--executor", ex, *common])
                    shutil.rmtree(run_dir, ignore_errors=True)
                    r["load"] = (load0, os.getloadavg()[0])
                    runs.append(r)
                a, b = runs
                # Serial part: everything of the call outside the task phase (set-up before the
                # first submission, compaction after the last result).
                serial = [r["wall_s"] - r["task_s"] for r in runs]
                # Amdahl: the 1-worker run's serial seconds stay, its task phase halves.
                bound = a["wall_s"] / (serial[0] + a["task_s"] / 2)
                print(f"  {name}:")
                print(f"    whole simulate wall   1 worker {a['wall_s']:7.2f} s   2 workers "
                      f"{b['wall_s']:7.2f} s   speed-up {a['wall_s'] / b['wall_s']:5.2f}x  "
                      f"(target >= 1.8)")
                print(f"    task phase wall       1 worker {a['task_s']:7.2f} s   2 workers "
                      f"{b['task_s']:7.2f} s   speed-up {a['task_s'] / b['task_s']:5.2f}x")
                print(f"    serial (set-up + end) 1 worker {serial[0]:7.2f} s   2 workers "
                      f"{serial[1]:7.2f} s   (set-up {a['setup_s']:.2f} / {b['setup_s']:.2f} s)")
                # simulate's own figure: this process, its reaped pool workers, and a Dask
                # cluster's workers during their chunks (not the cluster's start or idle time).
                print(f"    Amdahl bound from the 1-worker run's serial share: {bound:5.2f}x; "
                      f"simulate's whole-process CPU per source "
                      f"{1e3 * a['stats_cpu_s'] / max(a['n_sources'], 1):.2f} / "
                      f"{1e3 * b['stats_cpu_s'] / max(b['n_sources'], 1):.2f} ms; load average "
                      f"{a['load'][0]:.1f}-{a['load'][1]:.1f} / {b['load'][0]:.1f}-{b['load'][1]:.1f}")
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)


if __name__ == "__main__":
    main()
