"""The Dask path (issue 10, point 7): ``simulate(..., executor=Client.get_executor())``
and ``glaciar simulate --scheduler ADDR`` on a real ``distributed.LocalCluster``
(2 worker processes, 1 thread each).

* The per-source table equals the serial run's and a 2-process pool's, row for
  row and column for column (every task draws from its own SeedSequence, so
  neither the scheduler nor the worker a task lands on may change a value).
* Nothing large travels through the scheduler: every submission (function,
  config dict, seed, a chunk of task specs) and every result (names, row counts,
  CPU seconds), as Dask's own serialiser pickles them, stays below
  MAX_MESSAGE_BYTES, which is under the size of one image of the field.
* Workers read the images themselves: one worker measures the field in the run's
  set-up (reading each image file once, issue 24) and keeps its context; the others'
  first task maps the cache it wrote, their later tasks reuse it
  (``glaciar.contexts.worker_context``'s per-process cache); nothing else reads an image.

The cluster and one survey (``small_survey``: 8 tasks, 4 chunks) are shared by
the module; ~15 s on an idle 2-core machine, most of it the three runs.
"""
from __future__ import annotations

import concurrent.futures as cf
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.execute import simulate
from glaciar.plan import plan_tasks
from glaciar.store import read_results

distributed = pytest.importorskip("distributed")
cloudpickle = pytest.importorskip("cloudpickle")
from distributed.protocol.pickle import dumps as dask_dumps  # noqa: E402  (Dask's serialiser)

N_WORKERS = 2
#: Upper bound on one submission or result as Dask pickles it [bytes].
MAX_MESSAGE_BYTES = 100_000
TASK_KEYS = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]


def _sorted(df: pd.DataFrame) -> pd.DataFrame:
    return df.sort_values(TASK_KEYS).reset_index(drop=True)


# --------------------------------------------------------------------------
# Worker-side probes (sent by value: the workers cannot import this test module)
# --------------------------------------------------------------------------
def _install_probes(dask_worker):
    """Count, in this worker process, field-context builds, image reads and tasks run."""
    import glaciar.contexts as contexts
    import glaciar.execute as execute
    import glaciar.survey as survey

    counts = {"contexts": 0, "opened": 0, "reads": {}, "tasks": 0, "cached_before": len(survey._CACHE),
              "contexts_before": len(contexts._CONTEXTS)}
    build, read, task = contexts.build_field_context, survey.read_array, execute.task_columns
    opener = contexts.open_field_context

    def counting_build(*args, **kwargs):
        counts["contexts"] += 1
        return build(*args, **kwargs)

    def counting_open(*args, **kwargs):
        counts["opened"] += 1
        return opener(*args, **kwargs)

    contexts.open_field_context = counting_open

    def counting_read(path):
        counts["reads"][str(path)] = counts["reads"].get(str(path), 0) + 1
        return read(path)

    def counting_task(*args, **kwargs):
        counts["tasks"] += 1
        return task(*args, **kwargs)

    contexts.build_field_context, survey.read_array, execute.task_columns = counting_build, counting_read, counting_task
    dask_worker.glaciar_probe = counts
    return os.getpid()


def _read_probes(dask_worker):
    return dict(dask_worker.glaciar_probe, pid=os.getpid())


class RecordingExecutor(cf.Executor):
    """Passes every submission to a Dask executor, keeping its serialised size."""

    def __init__(self, inner: cf.Executor):
        self.inner = inner
        self.submitted: list[int] = []
        self.futures: list[cf.Future] = []

    def submit(self, fn, /, *args, **kwargs):
        self.submitted.append(len(dask_dumps((fn, args, kwargs))))
        fut = self.inner.submit(fn, *args, **kwargs)
        self.futures.append(fut)
        return fut

    def shutdown(self, wait=True, *, cancel_futures=False):
        self.inner.shutdown(wait=wait)


# --------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cluster():
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        with distributed.LocalCluster(n_workers=N_WORKERS, threads_per_worker=1, processes=True,
                                      dashboard_address=None) as lc, distributed.Client(lc) as client:
            yield lc, client
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="module")
def reference_runs(small_run, tmp_path_factory):
    """The serial run's table (the session's shared ``small_run``) and a 2-process pool's,
    of ``small_survey``."""
    cfg, serial = small_run
    pool = tmp_path_factory.mktemp("dask_pool")
    simulate(cfg, pool, workers=2, progress=False)
    return cfg, _sorted(read_results(serial)), _sorted(read_results(pool))


@pytest.fixture(scope="module")
def dask_run(cluster, reference_runs, tmp_path_factory):
    """``small_survey`` run through the cluster's executor, with probes in the workers."""
    _, client = cluster
    cfg = reference_runs[0]
    out = tmp_path_factory.mktemp("dask_run")
    pids = client.run(_install_probes)
    ex = RecordingExecutor(client.get_executor())
    stats = simulate(cfg, out, executor=ex, progress=False)
    probes = client.run(_read_probes)
    return out, stats, ex, pids, probes


# --------------------------------------------------------------------------
# Tests
# --------------------------------------------------------------------------
def test_dask_table_equals_serial_and_process_pool(reference_runs, dask_run):
    cfg, serial, pool = reference_runs
    out, stats, _, _, _ = dask_run
    assert stats["n_run"] == len(plan_tasks(cfg)) == stats["n_tasks"]
    got = _sorted(read_results(out))
    assert len(got) == len(plan_tasks(cfg)) * cfg.simulation.n_galaxies
    pd.testing.assert_frame_equal(got, serial)
    pd.testing.assert_frame_equal(got, pool)


def test_nothing_large_goes_through_the_scheduler(dask_run, small_survey):
    from glaciar.survey import Survey

    _, _, ex, _, _ = dask_run
    cfg = load_config(small_survey)
    field = cfg.survey.fields[0]
    one_image = Survey.from_config(cfg).science(field, cfg.survey.detection_band).nbytes
    assert MAX_MESSAGE_BYTES < one_image          # the bound would catch a single image
    assert len(ex.submitted) >= N_WORKERS         # more than one chunk: real distribution
    assert max(ex.submitted) < MAX_MESSAGE_BYTES
    results = [len(dask_dumps(f.result())) for f in ex.futures]
    assert max(results) < MAX_MESSAGE_BYTES


def test_workers_open_the_field_cache_once_per_process(dask_run, small_survey):
    """One worker measures the field (issue 24: set-up in the workers), reading each image
    once, and keeps its context; the others map the cache it wrote (glaciar.engine.fieldcache)."""
    _, stats, ex, pids, probes = dask_run
    assert len(probes) == N_WORKERS
    assert sorted(p["pid"] for p in probes.values()) == sorted(pids.values())
    assert os.getpid() not in {p["pid"] for p in probes.values()}   # separate processes
    assert sum(p["tasks"] for p in probes.values()) == stats["n_run"]
    used = [p for p in probes.values() if p["tasks"]]
    assert used, "no worker ran a task"
    assert any(p["tasks"] > 1 for p in used)        # some worker reused its context
    assert sum(p["contexts"] for p in probes.values()) == 1       # measured once
    for p in probes.values():
        assert p["cached_before"] == 0 and p["contexts_before"] == 0   # nothing read in advance
        if p["contexts"]:
            assert p["reads"] and set(p["reads"].values()) == {1} and p["opened"] == 0
        else:                                            # no image read; one field: one opening
            assert not p["reads"] and p["opened"] == (1 if p["tasks"] else 0)


def test_cli_scheduler_option(cluster, reference_runs, dask_run, small_survey, tmp_path):
    """``glaciar simulate --scheduler ADDR`` connects to the cluster and writes the same table.

    (``dask_run`` first: its probes need workers that have read nothing yet.)
    """
    lc, _ = cluster
    _, serial, _ = reference_runs
    out = tmp_path / "cli"
    proc = subprocess.run([sys.executable, "-m", "glaciar.cli", "simulate", str(small_survey),
                           "--out", str(out), "--scheduler", lc.scheduler_address, "--quiet"],
                          capture_output=True, text=True, timeout=300,
                          env={**os.environ, "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr
    assert f"{len(plan_tasks(load_config(small_survey)))} tasks run" in proc.stdout
    pd.testing.assert_frame_equal(_sorted(read_results(Path(out))), serial)
