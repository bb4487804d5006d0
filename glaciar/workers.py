"""Worker processes: they die with the parent and leave interrupts to it; CPU accounting."""
from __future__ import annotations

import concurrent.futures as cf
import os
import signal
import sys
import threading
import time

_PR_SET_PDEATHSIG = 1


def _watch_parent(parent_pid: int, period: float = 0.5) -> None:
    while True:
        time.sleep(period)
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), signal.SIGKILL)


def single_thread_libraries():
    """Limit this process's BLAS and OpenMP thread pools to one thread each.

    A worker is one core: OpenBLAS otherwise starts a thread per core in every process,
    and on 2 cores its threads spin for ~45 % of a field's set-up CPU (the empty
    apertures' plane fits), so ``--workers 2`` ran four busy threads.  Applied at once;
    the returned object restores the previous limits when used as a context manager
    (``with single_thread_libraries(): ...``) or by its ``restore_original_limits()``.
    """
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1)


def worker_init(parent_pid: int) -> None:
    """Initializer of the process pool's workers.

    SIGINT is ignored (the parent handles Ctrl-C and terminates the workers),
    SIGTERM kills; on Linux the kernel sends SIGKILL when the parent dies
    (``PR_SET_PDEATHSIG``), and a watchdog thread checking the parent pid
    does the same elsewhere or if that call fails.  BLAS/OpenMP run one thread
    (:func:`single_thread_libraries`) for the worker's life.
    """
    single_thread_libraries()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - no libc prctl
            pass
    if os.getppid() != parent_pid:        # the parent died before prctl took effect
        os.kill(os.getpid(), signal.SIGKILL)
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True,
                     name="glaciar-parent-watchdog").start()


def terminate_workers(ex: cf.ProcessPoolExecutor) -> None:
    """Stop a process pool's workers now (on an interrupt: their tasks are redone on resume)."""
    stop = getattr(ex, "terminate_workers", None)        # Python >= 3.14
    if stop is not None:
        stop()
        return
    for p in list((getattr(ex, "_processes", None) or {}).values()):
        try:
            p.terminate()
        except (OSError, ValueError, AttributeError):    # already gone
            pass


def process_cpu_seconds(children: bool = True) -> float:
    """CPU [s] used so far by this process and (``children``) its terminated (reaped) child processes."""
    import resource

    own = resource.getrusage(resource.RUSAGE_SELF)
    if not children:
        return own.ru_utime + own.ru_stime
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def default_workers() -> int:
    """Worker processes to use by default: the CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)
