"""Run a plan's tasks on any executor, write their results, resume: :func:`simulate`.

This is the edge of the package: it owns parallelism and progress bars.
The science happens in :func:`glaciar.engine.task.task_columns` (the rows of
:func:`~glaciar.engine.task.run_task` as column arrays), a pure function of a prepared
:class:`~glaciar.engine.context.FieldContext` and a :class:`~glaciar.engine.task.TaskSpec`.
"""
from __future__ import annotations

import concurrent.futures as cf
import math
import os
import time
from pathlib import Path

import numpy as np

from . import constants as C
from .config import Config, config_hash, config_to_dict
from .contexts import (clear_contexts, fields_measured, finish_context_cache,
                       prepare_context_cache, worker_context)
from .engine import fieldcache
from .engine.task import TaskSpec, task_columns
from .manifest import open_run
from .memory import drop_file_pages
from .plan import (INTERLOPER_DIRNAME, finished_specs, interloper_model, plan_tasks,
                   spec_filename, spec_key, spec_store)
from .shards import check_shard, shard_scope
from .store import COMPACT_EVERY, compact, write_task_table
from .workers import process_cpu_seconds, single_thread_libraries, terminate_workers, worker_init


def _run_chunk(cfg_dict: dict, base_dir: str, cfg_hash: str, run_dir: str, seed: int,
               specs: list[TaskSpec], mode: str = "windowed") -> list[tuple[str, int, float]]:
    """Run a chunk of tasks of one field and write each task's file; return (name, rows, seconds)."""
    done = []
    ctx = None
    interlopers = interloper_model(cfg_dict)     # None without an interlopers: section
    try:
        for spec in specs:
            t0 = time.process_time()
            ctx = worker_context(cfg_dict, base_dir, cfg_hash, spec.field, run_dir)
            # Image pages the tasks touch stay resident while mapped: dropped past a budget.
            fieldcache.trim(ctx, watch=True)
            # The rows as column arrays, written without a DataFrame: no pandas in the tasks.
            table = task_columns(ctx, spec, seed, mode=mode, interlopers=interlopers)
            name = spec_filename(spec)
            # The task's counts go in its file's footer, keyed on the fit's magnitude covariate.
            # (Interlopers have no M_UV: their counts are per apparent magnitude.)
            mag_column = (C.COL_M_UV if ctx.magnitude_type == "absolute" and not spec.population
                          else C.COL_MAG_INPUT)
            # And the histograms of the measured detection-band magnitude (transfer matrices).
            write_task_table(spec_store(run_dir, spec), name, table, key=spec_key(spec),
                             mag_column=mag_column,
                             obs_column=C.band_column(C.OBS_MAG_QUANTITY, ctx.detection_band))
            done.append((name, len(table[C.COL_SOURCE]), time.process_time() - t0))
    finally:
        if ctx is not None:
            fieldcache.trim(ctx, watch=False)
    return done


#: :func:`glaciar.contexts.fields_measured` when this process last dropped the code pages of
#: its imports and set-up (:func:`glaciar.memory.drop_file_pages`); None: never.
_DROPPED_AT: list = [None]

#: Guided scheduling: each chunk holds 1 / (this x workers) of the tasks not yet chunked.
_GUIDED_CHUNK_DIVISOR = 4


def _chunks(specs: list[TaskSpec], n_workers: int) -> list[list[TaskSpec]]:
    """Cut the ordered tasks into chunks of one (field, z) each, large ones first.

    Guided self-scheduling: a chunk takes ``1 / (4 x n_workers)`` of the tasks
    not yet chunked, so the first chunks are large (few submissions) and the
    last ones single tasks, which the workers share as they free up: the run's
    tail is about one task, not one chunk.  A chunk never spans two (field, z)
    pairs, so a worker renders a chunk's templates once (a process caches them
    across chunks too), and the plan's field order is kept (one field's
    context per process at a time).
    """
    groups: dict = {}
    for s in specs:
        groups.setdefault((s.field_index, s.z_index), []).append(s)
    divisor = _GUIDED_CHUNK_DIVISOR * max(1, n_workers)
    remaining = len(specs)
    out = []
    for g in groups.values():
        i = 0
        while i < len(g):
            chunk = g[i:i + max(1, math.ceil(remaining / divisor))]
            out.append(chunk)
            i += len(chunk)
            remaining -= len(chunk)
    return out


def _run_chunk_measured(*args) -> tuple[list[tuple[str, int, float]], int, float]:
    """:func:`_run_chunk`, and the worker's pid and process CPU [s] it used (set-up included)."""
    c0 = process_cpu_seconds(children=False)
    done = _run_chunk(*args)
    return done, os.getpid(), process_cpu_seconds(children=False) - c0


def _check_count(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {value!r}")
    return int(value)


def simulate(cfg: Config, run_dir, *, workers: int = 1, seed: int | None = None,
             executor: cf.Executor | None = None, progress: bool = True, mode: str = "windowed",
             max_tasks: int | None = None, shard: tuple[int, int] | None = None) -> dict:
    """Run (or resume) the injection-recovery simulation of a configuration.

    Parameters
    ----------
    cfg : Config
        Loaded configuration.
    run_dir : path
        Output directory (results store); finished tasks found there are skipped.
        While the run writes, it holds the directory's lock: a second run into
        the same directory is refused.
    workers : int
        Number of worker processes (>= 1; 1: run in this process).  Workers die
        with this process.  With ``executor``: how many of its workers to have
        import glaciar while this process checks the inputs (default 1).
    seed : int, optional
        Overrides ``simulation.seed`` (>= 0).
    executor : concurrent.futures.Executor, optional
        Any executor (e.g. a Dask ``Client.get_executor()``): it runs the tasks instead of a
        pool of ``workers`` processes.
    progress : bool
        Show a progress bar with ETA.
    mode : {"windowed", "full"}
        Detection mode.
    max_tasks : int, optional
        Run at most this many of the pending tasks (the rest stay pending for a resume).
    shard : (int, int), optional
        ``(k, n)``: run only shard k of n of the plan (:func:`glaciar.shards.shard_tasks`),
        beside the other shards' processes into the same ``run_dir`` (``glaciar simulate
        --shard K/N``; docs/scale-out.md).  The same k twice, or another n than the run's
        shards were started with, is refused.

    Returns
    -------
    dict
        ``n_tasks`` (of the shard, with ``shard``), ``n_done_before``, ``n_run``, ``n_sources``;
        ``cpu_seconds`` [s]: inside
        the tasks (a worker's field set-up counted in its first task); ``process_cpu_seconds``
        [s]: this process and its pool workers, set-up, scheduling and compaction included (with
        ``executor``: this process plus its workers' CPU during their chunks, their imports
        excepted); ``wall_seconds`` [s]: the whole call, of which ``setup_seconds`` (inputs
        checked, field measured, manifest written: before the first task is submitted) and
        ``task_seconds`` (first submission to last result; the rest is the final compaction);
        ``remote_cpu_seconds`` [s]: the part of ``process_cpu_seconds`` measured in the
        workers of ``executor`` (0 without one).

    Raises
    ------
    ValueError
        Bad arguments or input files (:class:`glaciar.inputs.InputError`), checked before anything is written.
    StoreMismatchError
        The run directory holds tasks made differently.
    glaciar.rundir.RunLockedError
        Another run is writing into ``run_dir``.
    """
    # The bar's module only when a bar is shown: tqdm.auto (notebook or console) also imports
    # asyncio (~2.5 MB resident for the rest of a one-worker run); the disabled bar is std's.
    if progress:
        from tqdm.auto import tqdm
    else:
        from tqdm.std import tqdm

    run_dir = Path(run_dir)
    seed = _check_count("seed", cfg.simulation.seed if seed is None else seed, 0)
    if seed != cfg.simulation.seed:
        # The override is the run's seed everywhere, the box's points included (and the
        # run's stored config.yaml says so).
        cfg = cfg.model_copy(update={"simulation": cfg.simulation.model_copy(
            update={"seed": seed})})
    workers = _check_count("workers", workers, 1)
    if mode not in ("windowed", "full"):
        raise ValueError(f"mode: expected 'windowed' or 'full', got {mode!r}")
    if max_tasks is not None:
        max_tasks = _check_count("max_tasks", max_tasks, 0)
    if shard is not None:
        shard = check_shard(shard)
    # This process is a worker too (the set-up's serial part; every task with one worker):
    # one BLAS/OpenMP thread while it runs, the caller's limits back afterwards.
    with single_thread_libraries():
        return _simulate_one_thread(cfg, run_dir, seed, workers, executor, progress, mode,
                                    max_tasks, shard, tqdm)


def _simulate_one_thread(cfg, run_dir, seed, workers, executor, progress, mode, max_tasks,
                         shard, tqdm) -> dict:
    c0, t0 = process_cpu_seconds(), time.perf_counter()
    # With workers, the pool exists from the start: its workers measure the fields (one job
    # per field, glaciar.contexts.measure_field), then run the tasks, mapping the caches.
    # (Forked at its first job, the z limit, submitted before the input checks: the workers
    # inherit no image; those checks are this process's serial share of the set-up.)
    pool = None
    if executor is None and workers > 1:
        pool = cf.ProcessPoolExecutor(max_workers=workers, initializer=worker_init,
                                      initargs=(os.getpid(),))
    try:
        setup = _setup_executor(executor) or pool
        _, lock = open_run(cfg, run_dir, seed, parallel=setup, warm=workers, shard=shard,
                           measure_on=setup)
        try:
            stats = _simulate_locked(cfg, run_dir, seed, workers, executor or pool, progress,
                                     mode, max_tasks, tqdm, t0, lock, own=pool is not None)
        finally:
            lock.release()
    except KeyboardInterrupt:
        if pool is not None:
            terminate_workers(pool)
        raise
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    # Whole-process CPU: this process (checks, manifest, scheduling) and its pool workers
    # (reaped at the pool's shutdown, field set-up included); with another executor its
    # workers' CPU inside the chunks (tasks and field set-up; not their imports).
    stats["process_cpu_seconds"] = process_cpu_seconds() - c0 + stats["remote_cpu_seconds"]
    stats["wall_seconds"] = time.perf_counter() - t0
    return stats


def _setup_executor(executor: cf.Executor | None) -> cf.Executor | None:
    """The caller's executor whose workers do the run's set-up jobs (the fields' measurement,
    the detection z limit: :func:`glaciar.manifest.open_run`), if any: not a thread pool
    (the jobs would share this process's memory and interpreter)."""
    if isinstance(executor, cf.ThreadPoolExecutor):
        return None
    return executor


def _simulate_locked(cfg, run_dir, seed, workers, executor, progress, mode, max_tasks, tqdm,
                     t_start, lock, own=False):
    # ---- sharded runs (glaciar.shards): this process's part of the plan, its own files ----
    plan = plan_tasks(cfg)
    specs, own_files = shard_scope(plan, lock.shard)
    # ----
    # Each population's tasks in its own store (glaciar.plan.spec_store).
    finished = finished_specs(run_dir, specs, quarantine=True)
    pending = [s for s in specs if s not in finished]
    n_done_before = len(specs) - len(pending)
    if max_tasks is not None:
        pending = pending[:max_tasks]
    cfg_dict = config_to_dict(cfg)
    base_dir = str(cfg.base_dir)
    cfg_hash = config_hash(cfg)
    if lock.shard is None:    # a shard prepared them in its set-up (glaciar.manifest.open_run)
        prepare_context_cache(run_dir, cfg, cfg_hash, {s.field for s in pending})
    n_workers = 1 if executor is None and workers <= 1 else max(1, workers)
    chunks = _chunks(pending, n_workers)
    stats = {"n_tasks": len(specs), "n_done_before": n_done_before, "n_run": 0, "n_sources": 0,
             "cpu_seconds": 0.0, "remote_cpu_seconds": 0.0, "shard": lock.shard}
    bar = tqdm(total=len(pending), unit="task", disable=not progress, desc="simulate")

    def account(result):
        for _name, rows, cpu in result:
            stats["n_run"] += 1
            stats["n_sources"] += rows
            stats["cpu_seconds"] += cpu
        bar.update(len(result))
        # Bound the number of loose task files of a long run (glaciar.store: Compaction).
        if stats["n_run"] // COMPACT_EVERY > account.compactions:
            account.compactions = stats["n_run"] // COMPACT_EVERY
            for store in stores:
                compact(store, min_tasks=COMPACT_EVERY, **own_files)
    account.compactions = 0
    stores = [run_dir] + ([run_dir / INTERLOPER_DIRNAME] if any(s.population for s in specs)
                          else [])

    t0 = time.perf_counter()
    try:
        if executor is None and n_workers == 1:
            # This process imported glaciar, measured the field and now runs every task: the
            # code pages only the imports and the set-up ran go back before the first task,
            # and once more after it (its own first-time code), so they do not add to the
            # tasks' peak RSS (glaciar.memory; ~30 ms each).  Once per process, and again
            # after a field is measured here (not for a context kept from an earlier call).
            if chunks and _DROPPED_AT[0] != fields_measured():
                drop_file_pages()
                # the first task alone, then the drop of what it ran for the first time
                first, chunks = chunks[0][:1], [chunks[0][1:], *chunks[1:]]
                account(_run_chunk(cfg_dict, base_dir, cfg_hash, str(run_dir), seed, first, mode))
                drop_file_pages()
                _DROPPED_AT[0] = fields_measured()
            for ch in chunks:
                if ch:
                    account(_run_chunk(cfg_dict, base_dir, cfg_hash, str(run_dir), seed, ch,
                                       mode))
        elif chunks:
            ex = executor
            try:
                futs = [ex.submit(_run_chunk_measured, cfg_dict, base_dir, cfg_hash, str(run_dir),
                                  seed, ch, mode) for ch in chunks]
                # A context measured here (a thread pool's run) is in the workers' hands
                # now: this process runs no task, so it lets its copy go.
                clear_contexts()
                for fut in cf.as_completed(futs):
                    done, pid, cpu = fut.result()
                    # Our own pool's workers are reaped (RUSAGE_CHILDREN) and a thread's CPU
                    # is this process's: only other executors' processes are added.
                    if not own and pid != os.getpid():
                        stats["remote_cpu_seconds"] += cpu
                    account(done)
            except KeyboardInterrupt:
                if own:
                    terminate_workers(ex)
                raise
            finally:
                if own:     # the workers' CPU is reaped into this process's before it is read
                    ex.shutdown(wait=True, cancel_futures=True)
    finally:
        bar.close()
    stats["setup_seconds"] = t0 - t_start
    stats["task_seconds"] = time.perf_counter() - t0
    for store in stores:
        if store.is_dir():
            compact(store, min_tasks=COMPACT_EVERY, **own_files)
    if lock.shard is None:
        finish_context_cache(run_dir, n_done_before + stats["n_run"] == len(specs))
    else:
        # The field caches go once the whole plan is done, whichever shard sees it last.
        with lock.setup():
            finish_context_cache(run_dir, len(finished_specs(run_dir, plan, verify=False))
                                 == len(plan))
    return stats
