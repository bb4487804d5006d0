"""The run directory's own files (glaciar.rundir): input fingerprints, the run lock, atomic writes under the umask."""
import hashlib
import os
import subprocess
import sys

import pytest

from glaciar import constants as C
from glaciar.cli import main
from glaciar.execute import simulate
from glaciar.rundir import (RunLock, RunLockedError, StoreMismatchError, atomic_temporary_target,
                            atomic_write_text, file_fingerprint)

from tiny_runs import file_snapshot, load_dict


def test_fingerprint_cache_skips_unchanged_files(tmp_path):
    p = tmp_path / "f.bin"
    p.write_bytes(b"abc")
    cache = {}
    fp = file_fingerprint(p, cache)
    assert fp == {"size": 3, "blake2b": hashlib.blake2b(b"abc", digest_size=16).hexdigest()}
    entry = cache[str(p.resolve())]
    # A cache entry with the same size and mtime is trusted (the file is not read again) ...
    cache[str(p.resolve())] = {**entry, "blake2b": "cached"}
    from glaciar import rundir
    rundir._FINGERPRINTS.clear()
    assert file_fingerprint(p, cache)["blake2b"] == "cached"
    # ... a new mtime is not.
    os.utime(p, ns=(entry["mtime_ns"] + 10**9, entry["mtime_ns"] + 10**9))
    assert file_fingerprint(p, cache)["blake2b"] == fp["blake2b"]


# --------------------------------------------------------------------------
# The run lock
# --------------------------------------------------------------------------
def test_second_writer_is_refused_and_live_temp_files_survive(run_copy, tmp_path):
    d, run = run_copy
    cfg = load_dict(d, tmp_path / "c.yaml")
    tmp_file = run / C.RESULTS_DIRNAME / ".task_inflight.parquet.abc.tmp"
    tmp_file.write_bytes(b"half a task")
    code = ("import sys; from glaciar.rundir import RunLock; RunLock(sys.argv[1]).acquire(); "
            "print('locked', flush=True); sys.stdin.read()")
    holder = subprocess.Popen([sys.executable, "-c", code, str(run)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = file_snapshot(run)
        with pytest.raises(RunLockedError) as exc:
            simulate(cfg, run, workers=1, progress=False)
        assert str(exc.value) == f"{run}: another glaciar run is writing here (pid {holder.pid})"
        assert file_snapshot(run) == before                    # the live run's temp file too
        # The CLI says the same in one line, exit 2.
        assert main(["simulate", str(tmp_path / "c.yaml"), "--out", str(run), "--quiet"]) == 2
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)
        holder.stdout.close()
    # Once the holder is gone the lock is free, and the stale temp file is cleaned up.
    assert simulate(cfg, run, workers=1, progress=False)["n_run"] == 0
    assert not tmp_file.exists()


def test_lock_is_released_after_a_run_and_after_a_failure(run_copy, tmp_path):
    d, run = run_copy
    simulate(load_dict(d, tmp_path / "c.yaml"), run, workers=1, progress=False)
    with RunLock(run):                                     # free again
        pass
    bad = {**d, "simulation": {**d["simulation"], "seed": 12}}
    with pytest.raises(StoreMismatchError):
        simulate(load_dict(bad, tmp_path / "bad.yaml"), run, workers=1, progress=False)
    with RunLock(run):
        pass


def test_a_temporary_names_the_file_it_was_written_for(tmp_path):
    """A killed atomic write's temporary names its target (a shard removes only its own)."""
    import tempfile

    for name in ("task_f_z+008.0000_m+024.0000_i0000_0123456789abcdef.parquet", "manifest.json"):
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=tmp_path)
        os.close(fd)
        assert atomic_temporary_target(tmp) == name
    for other in ("task_a.parquet", ".part-s1.tmp", "x.tmp", ".lock"):
        assert atomic_temporary_target(tmp_path / other) == ""


# --------------------------------------------------------------------------
# Outputs honour the umask
# --------------------------------------------------------------------------
@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_atomic_writes_honour_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == mode


def test_run_files_are_readable_by_the_group_with_umask_022(one_task_run, tmp_path):
    d, _ = one_task_run
    cfg = load_dict(d, tmp_path / "c.yaml")
    old = os.umask(0o022)
    try:
        simulate(cfg, tmp_path / "run", workers=1, progress=False)
    finally:
        os.umask(old)
    modes = {p.name: p.stat().st_mode & 0o777 for p in (tmp_path / "run").rglob("*") if p.is_file()}
    assert modes and set(modes.values()) == {0o644}, modes
