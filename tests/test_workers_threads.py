"""One BLAS/OpenMP thread per worker (glaciar.workers.single_thread_libraries, worker_init).

OpenBLAS starts a thread per core in every process; with a pool of N workers on N cores
that made N x cores busy threads.  Fails before: neither function limited anything.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

from glaciar.workers import single_thread_libraries


def _threads() -> list[int]:
    return [pool["num_threads"] for pool in threadpool_info()]


def test_limits_inside_and_restores_after():
    np.dot(np.ones((64, 64)), np.ones((64, 64)))        # numpy's BLAS loaded and started
    with threadpool_limits(limits=2):                   # a caller's own setting, kept
        before = _threads()
        with single_thread_libraries():
            assert _threads() and all(n == 1 for n in _threads())
        assert _threads() == before


def test_a_pool_worker_runs_one_thread():
    # A fresh interpreter (no limit inherited from this test process), as a pool worker.
    code = ("import json, os, numpy as np; from threadpoolctl import threadpool_info;"
            "np.dot(np.ones((8, 8)), np.ones((8, 8)));"
            "from glaciar.workers import worker_init; worker_init(os.getppid());"
            "print(json.dumps([p['num_threads'] for p in threadpool_info()]))")
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=120, check=True).stdout
    threads = json.loads(out.strip().splitlines()[-1])
    assert threads and all(n == 1 for n in threads)
