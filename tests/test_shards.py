"""Sharded runs (issue 24, point 1): ``glaciar simulate --shard K/N``, ``glaciar status``.

* The assignment: every task in exactly one shard for several N, shard costs within the
  bound :func:`glaciar.shards.shard_bounds` states, (field, z) groups kept whole where a
  cut can move to their boundary cheaply.
* ``--shard 1/2`` and ``--shard 2/2`` started at the same time (two processes) into one
  directory, shard 2 killed by SIGKILL after its first task file and run again, store
  rows equal, bit for bit, to the serial run's (``small_run``); the field is measured
  once in all (the other shard and the resume map its cache).  While shard 2 is down,
  ``glaciar status`` counts its tasks missing, and running while its lock is held.
* An unsharded run afterwards completes what the shards left.
* Refusals, one line and exit 2: bad ``--shard`` text; another shard count (nothing
  written); the same shard twice; an unsharded run while a shard runs.
* A shard compacts, deletes and cleans only its own files.
* The dask-jobqueue example of docs/scale-out.md, on a ``LocalCluster``.

``small_survey``: 8 tasks, 4 per shard; ~25 s in all on a shared 2-core machine.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import types
from pathlib import Path

import pandas as pd
import pytest

from glaciar import constants as C
from glaciar import contexts
from glaciar.cli import main
from glaciar.config import load_config
from glaciar.contexts import clear_contexts
from glaciar.engine.task import TaskSpec
from glaciar.execute import simulate
from glaciar.rundir import RunLock
from glaciar.shards import SHARD_SNAP_FRACTION, run_status, shard_task_names, shard_tasks
from glaciar.store import compact, read_results

ROOT = Path(__file__).resolve().parent.parent
KEYS = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]


def _rows(run) -> pd.DataFrame:
    return read_results(run).sort_values(KEYS).reset_index(drop=True)


def _assert_same_rows(run, reference):
    got, want = _rows(run), _rows(reference)
    assert len(got) == len(want) > 0
    pd.testing.assert_frame_equal(got, want, check_exact=True)


def _snapshot(root: Path) -> dict:
    """Every path and file content below ``root``, lock files' content (a holder's pid) aside."""
    return {p.relative_to(root).as_posix():
            (p.read_bytes() if p.is_file() and not p.name.endswith(".lock") else None)
            for p in sorted(root.rglob("*"))}


def _task_files(run: Path) -> list[str]:
    return sorted(p.name for p in (run / C.RESULTS_DIRNAME).glob("task_*.parquet"))


def _plan(fields=("a", "b"), zs=(8.0, 9.0, 10.0), mags=(24.0, 25.0, 26.0, 27.0), n_it=3):
    return [TaskSpec(field=f, field_index=i, z_index=j, mag_index=k, iteration=it, z=z, mag=m)
            for i, f in enumerate(fields) for j, z in enumerate(zs)
            for k, m in enumerate(mags) for it in range(n_it)]


# --------------------------------------------------------------------------
# The assignment
# --------------------------------------------------------------------------
@pytest.mark.parametrize("costs_of", [None, "by_mag"])
def test_every_task_in_exactly_one_shard_with_balanced_costs(costs_of):
    plan = _plan()                                          # 72 tasks, 6 (field, z) groups
    cost = {s: 1.0 if costs_of is None else 1.0 + 0.5 * s.mag_index for s in plan}
    total, biggest = sum(cost.values()), max(cost.values())
    for n in range(1, 10):
        shards = [shard_tasks(plan, k, n, costs=None if costs_of is None else
                              [cost[s] for s in plan]) for k in range(1, n + 1)]
        # Every task once, in plan order: the shards are contiguous pieces of the plan.
        assert [s for sh in shards for s in sh] == plan
        bound = 2 * max(SHARD_SNAP_FRACTION * total / n, biggest / 2)
        for sh in shards:
            assert abs(sum(cost[s] for s in sh) - total / n) <= bound + 1e-9, (n, len(sh))
        # At most n - 1 (field, z) groups are split between two shards.
        owners = {}
        for k, sh in enumerate(shards):
            for s in sh:
                owners.setdefault((s.field, s.z), set()).add(k)
        assert sum(len(o) > 1 for o in owners.values()) <= n - 1
        # Deterministic: the same plan and n give the same shards.
        assert shards == [shard_tasks(list(plan), k, n, costs=None if costs_of is None else
                                      [cost[s] for s in plan]) for k in range(1, n + 1)]


def test_cuts_move_to_group_boundaries_when_cheap():
    # Three (field, z) groups of 11, 9 and 10 tasks, 3 shards: the equal-cost cuts (10, 20)
    # move to the group boundaries (11, 20), 1 task = a tenth of a shard away.
    plan = [s for s in _plan(fields=("a",), zs=(8.0, 9.0, 10.0), mags=(24.0,), n_it=11)
            if not (s.z == 9.0 and s.iteration >= 9) and not (s.z == 10.0 and s.iteration >= 10)]
    sizes = [len(shard_tasks(plan, k, 3)) for k in (1, 2, 3)]
    assert sizes == [11, 9, 10]
    assert [{s.z for s in shard_tasks(plan, k, 3)} for k in (1, 2, 3)] == [{8.0}, {9.0}, {10.0}]


@pytest.mark.parametrize("text", ["0/2", "3/2", "1/0", "a/b", "1", "1/2/3"])
def test_bad_shard_text_is_refused_in_one_line(small_survey, tmp_path, capsys, text):
    out = tmp_path / "run"
    assert main(["simulate", str(small_survey), "--out", str(out), "--shard", text,
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--shard" in err and text in err and "K/N" in err
    assert not out.exists()


def test_bad_shard_tuple_is_refused_by_the_api(small_survey, tmp_path):
    for shard in [(0, 2), (3, 2), (1, 0), ("1", "2"), (1,)]:
        with pytest.raises(ValueError, match="shard"):
            simulate(load_config(small_survey), tmp_path / "run", shard=shard, progress=False)
    assert not (tmp_path / "run").exists()


# --------------------------------------------------------------------------
# Two shards at the same time, one killed mid-run and resumed
# --------------------------------------------------------------------------
def _shard_command(config, out, shard, builds: Path, slow: float = 0.0) -> list[str]:
    """``glaciar simulate --shard`` in a new interpreter; ``slow`` [s] is slept before each
    task (so that a kill lands between tasks of a shard this small); each field measurement
    (``glaciar.contexts.build_field_context``) adds a line to ``builds``."""
    argv = ["simulate", str(config), "--out", str(out), "--workers", "1", "--quiet",
            "--shard", shard]
    code = textwrap.dedent(f"""
        import sys, time
        import glaciar.contexts as contexts
        import glaciar.execute as execute
        build = contexts.build_field_context
        def counted(*a, **k):
            with open({str(builds)!r}, "a") as fh:
                fh.write({shard!r} + "\\n")
            return build(*a, **k)
        contexts.build_field_context = counted
        if {slow!r}:
            run_task = execute.task_columns
            def slowed(*a, **k):
                time.sleep({slow!r})
                return run_task(*a, **k)
            execute.task_columns = slowed
        from glaciar.cli import main
        sys.exit(main({argv!r}))
    """)
    return [sys.executable, "-c", code]


@pytest.fixture(scope="module")
def two_shards(small_survey, tmp_path_factory):
    """``--shard 1/2`` and ``--shard 2/2`` started at the same time into one directory;
    shard 2 (0.5 s more per task) killed by SIGKILL once its first task file is there.

    Returns (run directory, shard 1's stdout, number of shard 2's tasks done).
    """
    run = tmp_path_factory.mktemp("shards") / "run"
    builds = run.parent / "builds.txt"
    second = shard_task_names(load_config(small_survey), (2, 2))
    procs = [subprocess.Popen(_shard_command(small_survey, run, f"{k}/2", builds, slow=slow),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for k, slow in ((1, 0.0), (2, 0.5))]
    deadline = time.monotonic() + 180
    while not (run / C.RESULTS_DIRNAME).is_dir() or not second & set(_task_files(run)):
        assert procs[1].poll() is None, procs[1].communicate()
        assert time.monotonic() < deadline
        time.sleep(0.02)
    os.kill(procs[1].pid, signal.SIGKILL)
    procs[1].communicate(timeout=60)
    out, err = procs[0].communicate(timeout=180)
    assert procs[0].returncode == 0, err
    done = len(second & set(_task_files(run)))
    assert 1 <= done < 4            # killed mid-run
    # The field was measured once, by one shard; the other mapped its cache.
    assert len(builds.read_text().splitlines()) == 1
    return run, out, done


def _no_measuring(*args, **kwargs):
    raise AssertionError("the field was measured again: its cache is in the run")


def test_two_shards_at_once_and_a_killed_one_resumed_give_the_serial_rows(
        small_survey, small_run, two_shards, tmp_path, monkeypatch):
    run = tmp_path / "run"
    shutil.copytree(two_shards[0], run)
    # Shard 1 ran its own half beside shard 2: not refused, nothing of shard 2's run by it.
    assert two_shards[1].startswith("4 tasks run (0 already done of 4)"), two_shards[1]
    assert (run / C.CONTEXT_DIRNAME).is_dir()       # shard 2's tasks still need the field cache
    cfg = load_config(small_survey)
    # Temporaries of a task in flight, of each shard: shard 2 removes only its own.
    own, sibling = (sorted(shard_task_names(cfg, (k, 2)))[-1] for k in (2, 1))
    for name in (own, sibling):
        (run / C.RESULTS_DIRNAME / f".{name}.x1y2z3.tmp").write_bytes(b"half")
    clear_contexts()
    monkeypatch.setattr(contexts, "build_field_context", _no_measuring)
    with RunLock(run, shard=(1, 2)):                # as if shard 1 were still running
        stats = simulate(cfg, run, shard=(2, 2), progress=False)
    assert (stats["n_tasks"], stats["n_done_before"]) == (4, two_shards[2])
    assert not (run / C.RESULTS_DIRNAME / f".{own}.x1y2z3.tmp").exists()
    assert (run / C.RESULTS_DIRNAME / f".{sibling}.x1y2z3.tmp").exists()
    _assert_same_rows(run, small_run[1])
    # The whole plan is done: the field caches went, and status says all done.
    assert not (run / C.CONTEXT_DIRNAME).exists()
    assert [(r["shard"], r["done"], r["running"], r["missing"]) for r in run_status(run)] == \
        [(1, 4, 0, 0), (2, 4, 0, 0)]


def test_an_unsharded_run_completes_what_the_shards_left(small_survey, small_run, two_shards,
                                                         tmp_path):
    # The merge job of docs/scale-out.md: shard 2 died; one unsharded pass does the rest.
    run = tmp_path / "run"
    shutil.copytree(two_shards[0], run)
    stats = simulate(load_config(small_survey), run, progress=False)
    assert (stats["n_tasks"], stats["n_run"]) == (8, 4 - two_shards[2])
    _assert_same_rows(run, small_run[1])
    assert not (run / C.CONTEXT_DIRNAME).exists()


def test_status_counts_done_running_and_missing(two_shards, capsys):
    run, _, _ = two_shards
    done = len(_task_files(run)) - 4                # shard 1 finished its 4
    assert main(["status", str(run)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["shard 1/2: 4 tasks: 4 done, 0 running, 0 missing",
                     f"shard 2/2: 4 tasks: {done} done, 0 running, {4 - done} missing",
                     f"{run}: 8 tasks in 2 shards: {4 + done} done, 0 running, {4 - done} missing"]
    # While shard 2's lock is held (a live shard), its tasks not done are running.
    lock = RunLock(run, shard=(2, 2)).acquire()
    try:
        rows = run_status(run)
    finally:
        lock.release()
    assert [(r["done"], r["running"], r["missing"]) for r in rows] == \
        [(4, 0, 0), (done, 4 - done, 0)]
    assert rows[1]["pid"] == str(os.getpid())


def test_changed_shard_count_is_refused_and_nothing_written(small_survey, two_shards, capsys):
    run = two_shards[0]
    before = _snapshot(run)
    assert main(["simulate", str(small_survey), "--out", str(run), "--shard", "1/3",
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "2 shards" in err and "--shard 1/3" in err
    assert _snapshot(run) == before


def test_same_shard_twice_and_unsharded_runs_are_refused(small_survey, two_shards, capsys):
    run = two_shards[0]
    before = _snapshot(run)
    lock = RunLock(run, shard=(2, 2)).acquire()          # shard 2 is running
    try:
        assert main(["simulate", str(small_survey), "--out", str(run), "--shard", "2/2",
                     "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "shard 2/2 is already running" in err
        assert main(["simulate", str(small_survey), "--out", str(run), "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"pid {os.getpid()}" in err and "shard" in err
        assert main(["report", str(run)]) == 2           # as today: the run is being written
        err = capsys.readouterr().err.strip()            # ... by shard 2, named as such
        assert len(err.splitlines()) == 1 and f"shard 2/2 (pid {os.getpid()})" in err
    finally:
        lock.release()
    assert _snapshot(run) == before
    # An unsharded run holds the lock: no shard starts.
    with RunLock(run):
        assert main(["simulate", str(small_survey), "--out", str(run), "--shard", "1/2",
                     "--quiet"]) == 2
        assert "unsharded" in capsys.readouterr().err
    assert _snapshot(run) == before


# --------------------------------------------------------------------------
# Compaction keeps to a shard's own files
# --------------------------------------------------------------------------
def test_shard_compaction_touches_only_its_own_files(small_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(small_run[1], run, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    loose = _task_files(run)
    assert len(loose) == 8
    mine = set(loose[:4])
    part_dir = run / C.RESULTS_DIRNAME / "compact" / "field=x" / "z=8.0"
    part_dir.mkdir(parents=True)
    (part_dir / ".part-s1-abc.parquet.tmp1.tmp").write_bytes(b"stale, mine")
    (part_dir / ".part-s2-abc.parquet.tmp2.tmp").write_bytes(b"a sibling's, in flight")
    assert compact(run, tasks=mine, tag="s1") == 4
    assert set(_task_files(run)) == set(loose) - mine          # the sibling's stay loose
    parts = sorted(p.name for p in (run / C.RESULTS_DIRNAME / "compact").rglob("*.parquet"))
    assert parts and all(re.fullmatch(r"part-s1-[0-9a-f]{16}\.parquet", p) for p in parts)
    assert not (part_dir / ".part-s1-abc.parquet.tmp1.tmp").exists()
    assert (part_dir / ".part-s2-abc.parquet.tmp2.tmp").exists()
    _assert_same_rows(run, small_run[1])                        # every task once


def test_status_of_an_unsharded_run(small_run, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(small_run[1], run, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    for name in _task_files(run)[:3]:
        (run / C.RESULTS_DIRNAME / name).unlink()
    assert main(["status", str(run)]) == 0
    assert capsys.readouterr().out == f"{run}: 8 tasks: 5 done, 0 running, 3 missing\n"
    with RunLock(run):
        assert main(["status", str(run)]) == 0
    assert capsys.readouterr().out == \
        f"{run}: 8 tasks: 5 done, 3 running (pid {os.getpid()}), 0 missing\n"


# --------------------------------------------------------------------------
# docs/scale-out.md's dask-jobqueue example
# --------------------------------------------------------------------------
def test_dask_jobqueue_example_runs_on_a_local_cluster(small_survey, small_run, tmp_path,
                                                        monkeypatch):
    distributed = pytest.importorskip("distributed")
    page = (ROOT / "docs" / "scale-out.md").read_text(encoding="utf-8")
    code = re.search(r"<!-- tests/test_shards.py runs this block[^>]*-->\n```python\n(.*?)^```",
                     page, re.S | re.M).group(1)
    assert "SLURMCluster(" in code and "executor=client.get_executor()" in code
    run = tmp_path / "run"
    code = code.replace('"survey.yaml"', repr(str(small_survey))).replace('"run"', repr(str(run)))

    class SLURMCluster(distributed.LocalCluster):
        """dask_jobqueue.SLURMCluster's interface on this machine: no worker until scaled."""

        def __init__(self, **job_settings):
            super().__init__(n_workers=0, processes=False, threads_per_worker=1,
                             dashboard_address=None)

        def scale(self, n=None, jobs=0, **kwargs):
            return super().scale(min(max(n or 0, jobs), 2))

    monkeypatch.setitem(sys.modules, "dask_jobqueue",
                        types.SimpleNamespace(SLURMCluster=SLURMCluster))
    exec(compile(code, "docs/scale-out.md", "exec"), {"__name__": "scale_out_example"})
    _assert_same_rows(run, small_run[1])
