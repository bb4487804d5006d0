"""Worker processes (glaciar.workers) die with their parent; SIGTERM stops a run cleanly and it resumes.

The two subprocess tests run ~18 tasks of the small survey with 2 workers.
"""
import os
import signal
import subprocess
import sys
import time

import pytest

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.execute import simulate
from glaciar.plan import plan_tasks
from glaciar.store import read_results

from tiny_runs import tiny_config, write_yaml


# --------------------------------------------------------------------------
# Process hygiene
# --------------------------------------------------------------------------
def _children(pid):
    psutil = pytest.importorskip("psutil")
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _gone(procs, timeout):
    psutil = pytest.importorskip("psutil")
    deadline = time.time() + timeout
    while time.time() < deadline:
        alive = []
        for p in procs:
            try:
                if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                    alive.append(p)
            except psutil.NoSuchProcess:
                pass
        if not alive:
            return True
        time.sleep(0.05)
    return False


def _start_cli_run(small_survey_dict, tmp_path):
    d = tiny_config(small_survey_dict, z=(8.0, 10.4), mag=(24.0, 26.0, 27.5), n_iter=3, n_gal=6)
    cfg_path = write_yaml(d, tmp_path / "c.yaml")
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "glaciar.cli", "simulate", str(cfg_path),
                             "--out", str(run), "--workers", "2", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    results = run / C.RESULTS_DIRNAME
    deadline = time.time() + 120
    workers = []
    while time.time() < deadline and proc.poll() is None:
        workers = _children(proc.pid)
        if len(workers) >= 2 and results.is_dir() and any(results.glob("task_*.parquet")):
            break
        time.sleep(0.05)
    assert proc.poll() is None and len(workers) >= 2, "the run ended before it could be killed"
    return proc, workers, cfg_path, run


def _kill_all(procs):
    for p in procs:
        try:
            p.kill()
        except Exception:  # noqa: BLE001 - already gone
            pass


def test_workers_die_with_a_killed_parent(small_survey_dict, tmp_path):
    proc, workers, _, run = _start_cli_run(small_survey_dict, tmp_path)
    try:
        os.kill(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=30)          # reaps it and closes its pipes
        assert _gone(workers, timeout=5), [p.pid for p in workers]
    finally:
        _kill_all(workers)


def test_sigterm_stops_cleanly_and_resumes(small_survey_dict, tmp_path):
    proc, workers, cfg_path, run = _start_cli_run(small_survey_dict, tmp_path)
    try:
        os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 128 + signal.SIGTERM
        assert err.strip().splitlines() == ["glaciar simulate: terminated (SIGTERM); finished "
                                            "tasks are kept, run the same command to resume"]
        assert _gone(workers, timeout=5)
    finally:
        _kill_all(workers)
    cfg = load_config(cfg_path)
    stats = simulate(cfg, run, workers=1, progress=False)
    assert stats["n_done_before"] >= 1 and stats["n_done_before"] + stats["n_run"] == len(plan_tasks(cfg))
    assert not list((run / C.RESULTS_DIRNAME).glob(".*.tmp"))
    rows = read_results(run)
    assert (rows.groupby([C.COL_Z, C.COL_MAG, C.COL_ITERATION]).size() == 6).all()
