"""The run directory's own files: atomic writes, the manifest, input fingerprints, the lock.

Everything glaciar writes goes through :func:`atomic_write_bytes` (a temporary name in
the same directory, then a rename), so an interrupted run never leaves a half-written
file.  ``RUN_DIR/manifest.json`` records the run's settings, inputs and store format
(:func:`read_manifest`, :func:`write_manifest`); :func:`file_fingerprint` hashes the
input files it names; :class:`RunLock` (``RUN_DIR/.lock``) lets one process write a run
directory at a time, or the N shards of a sharded run together (``RUN_DIR/.shards/``:
per-shard locks and records of the shard count, the set-up lock; :mod:`glaciar.shards`).
The task files and parts under ``results/`` are :mod:`glaciar.store`'s.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import tempfile
import time
from pathlib import Path

from .constants import LOCK_NAME, MANIFEST_NAME, SHARDS_DIRNAME
from .paths import UnsafePathError, allocate, disk_full, run_subdir

__all__ = ["process_umask", "atomic_write_bytes", "atomic_temporary_target", "atomic_write_text",
           "StoreMismatchError", "RunLockedError", "read_manifest", "manifest_text", "write_manifest", "store_format",
           "file_fingerprint", "RunLock", "read_shard_counts", "check_shard_count",
           "write_shard_record", "shard_holder", "run_holder", "running_shards"]


class StoreMismatchError(RuntimeError):
    """The run directory was made with a different configuration, inputs or format."""


class RunLockedError(RuntimeError):
    """Another process holds the run directory's lock."""


# --------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------
def process_umask() -> int:
    """The process umask, read without changing it where the OS allows."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    old = os.umask(0o022)          # pragma: no cover - non-Linux
    os.umask(old)
    return old


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and an atomic rename.

    The file gets the permissions of a plain ``open(path, "w")``: 0666 minus
    the umask (``mkstemp`` alone would leave it 0600).  A full disk (or quota)
    raises :class:`glaciar.paths.DiskFullError` naming ``path`` (the temporary
    file removed, ``path`` unchanged).
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as fh:
            # Blocks reserved first: a full disk fails here, before any byte is written.
            allocate(fh.fileno(), len(data), path)
            fh.write(data)
            fh.flush()
            os.fchmod(fh.fileno(), 0o666 & ~process_umask())
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
        full = disk_full(path, exc)
        if full is not None:
            raise full from None
        raise


def atomic_temporary_target(tmp: str | os.PathLike) -> str:
    """The file name :func:`atomic_write_bytes` was writing when it left temporary ``tmp``
    (``.<name>.<random>.tmp``) behind, e.g. a killed run's; "" for another file."""
    name = Path(tmp).name
    if not (name.startswith(".") and name.endswith(".tmp")):
        return ""
    target, dot, _ = name[1:-len(".tmp")].rpartition(".")
    return target if dot else ""


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Text version of :func:`atomic_write_bytes` (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"))


# --------------------------------------------------------------------------
# Manifest
# --------------------------------------------------------------------------
def read_manifest(run_dir: str | os.PathLike) -> dict | None:
    """The run's manifest, or None if there is none yet."""
    p = Path(run_dir) / MANIFEST_NAME
    if not p.exists():
        return None
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StoreMismatchError(f"{p}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise StoreMismatchError(f"{p}: expected a JSON object, got {type(data).__name__}")
    return data


def manifest_text(manifest: dict) -> str:
    """The manifest as written to disk (stable: sorted keys, 2-space indent)."""
    return json.dumps(manifest, indent=2, sort_keys=True, ensure_ascii=False)


def write_manifest(run_dir: str | os.PathLike, manifest: dict) -> None:
    """Write the manifest atomically."""
    atomic_write_text(Path(run_dir) / MANIFEST_NAME, manifest_text(manifest))


def store_format(manifest: dict) -> int:
    """The store format of a manifest (1 for manifests from before formats were recorded)."""
    return int(manifest.get("store_format", 1))


# --------------------------------------------------------------------------
# Input fingerprints
# --------------------------------------------------------------------------
_FINGERPRINTS: dict = {}     # (path, size, mtime_ns) -> hex digest, this process


def file_fingerprint(path: str | os.PathLike, cache: dict | None = None) -> dict:
    """Size and BLAKE2b-128 digest of a file's bytes.

    Parameters
    ----------
    path : path
    cache : dict, optional
        ``{path: {"size", "mtime_ns", "blake2b", ...}}`` (e.g. a run directory's
        cache file): a file whose size and mtime are unchanged is not read
        again.  Updated in place; the entry of a new or changed file is
        replaced, so other facts recorded in it (e.g. "checked") are dropped.

    Returns
    -------
    dict
        ``{"size": bytes, "blake2b": hex}``.
    """
    p = Path(path).resolve()
    st = p.stat()
    mem_key = (str(p), st.st_size, st.st_mtime_ns)
    entry = None if cache is None else cache.get(str(p))
    if not (isinstance(entry, dict) and entry.get("size") == st.st_size
            and entry.get("mtime_ns") == st.st_mtime_ns and isinstance(entry.get("blake2b"), str)):
        entry = None
    digest = entry["blake2b"] if entry is not None else _FINGERPRINTS.get(mem_key)
    if digest is None:
        h = hashlib.blake2b(digest_size=16)
        with open(p, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 22), b""):
                h.update(block)
        digest = h.hexdigest()
    _FINGERPRINTS[mem_key] = digest
    if cache is not None and entry is None:
        # A new or changed file: a fresh entry (whatever else was recorded about it is void).
        cache[str(p)] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "blake2b": digest}
    return {"size": st.st_size, "blake2b": digest}


# --------------------------------------------------------------------------
# Run-directory lock
# --------------------------------------------------------------------------
#: ``os.open`` flag that refuses a symbolic link as the last component (0 where unknown).
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
#: A shard lock found held is tried again this many times, this far apart [s], before the
#: shard is refused: another process's probe (:func:`shard_holder`, a joining shard's check)
#: holds it for microseconds.
_SHARD_LOCK_TRIES, _SHARD_LOCK_PAUSE = 5, 0.05
_BUSY = (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)


def _shard_lock_path(run_dir, k: int) -> Path:
    return Path(run_dir) / SHARDS_DIRNAME / f"shard-{int(k)}.lock"


def _shard_record_path(run_dir, k: int) -> Path:
    return Path(run_dir) / SHARDS_DIRNAME / f"shard-{int(k)}.json"


def _pid_text(fd: int) -> str:
    try:
        text = os.pread(fd, 64, 0).decode("ascii", "replace").strip()
    except OSError:
        text = ""
    return text if text.isdigit() else "unknown"


def _probe(path: Path, how: int) -> str | None:
    """The pid text of the holder of a conflicting flock on ``path`` (``how``: LOCK_SH or
    LOCK_EX), or None when it is free or missing (creates nothing, holds nothing)."""
    import fcntl

    try:
        fd = os.open(path, os.O_RDONLY | _NOFOLLOW)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, how | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno in _BUSY:
                return _pid_text(fd)
            raise
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def shard_holder(run_dir, k: int) -> str | None:
    """Pid text of the process running shard ``k`` in ``run_dir`` (its shard lock), or None."""
    import fcntl

    return _probe(_shard_lock_path(run_dir, k), fcntl.LOCK_SH)


def run_holder(run_dir) -> str | None:
    """Pid text of the unsharded run, fit or report holding ``run_dir``'s lock, or None."""
    import fcntl

    return _probe(Path(run_dir) / LOCK_NAME, fcntl.LOCK_SH)


def running_shards(run_dir, exclude: int | None = None) -> dict[int, str]:
    """``{k: pid text}`` of the shards whose lock is held in ``run_dir`` (not ``exclude``'s)."""
    d = Path(run_dir) / SHARDS_DIRNAME
    out = {}
    for p in sorted(d.glob("shard-*.lock")) if d.is_dir() else ():
        try:
            k = int(p.name[len("shard-"):-len(".lock")])
        except ValueError:
            continue
        pid = None if k == exclude else shard_holder(run_dir, k)
        if pid is not None:
            out[k] = pid
    return dict(sorted(out.items()))


def read_shard_counts(run_dir) -> dict[int, int]:
    """``{k: n}`` from the records of the shards that have started in ``run_dir``."""
    d = Path(run_dir) / SHARDS_DIRNAME
    out = {}
    for p in sorted(d.glob("shard-*.json")) if d.is_dir() else ():
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
            out[int(data["shard"])] = int(data["shards"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise StoreMismatchError(f"{p}: unreadable shard record ({exc}); expected "
                                     '{"shard": K, "shards": N}') from None
    return out


def check_shard_count(run_dir, shard: tuple[int, int]) -> None:
    """Refuse (:class:`StoreMismatchError`, one line naming both counts) shard ``(k, n)`` of a run
    directory whose shards were started with another count."""
    k, n = shard
    other = sorted({m for m in read_shard_counts(run_dir).values() if m != n})
    if other:
        m = other[0]
        raise StoreMismatchError(
            f"{run_dir}: its shards were started as {m} shards (--shard K/{m}); --shard {k}/{n} "
            f"asks for {n}: a run's shard count cannot change; use --shard K/{m}, no --shard once "
            "every shard has finished, or another --out")


def write_shard_record(run_dir, shard: tuple[int, int]) -> None:
    """Record shard ``(k, n)``'s count in ``RUN/.shards/shard-K.json`` (by that shard only)."""
    k, n = shard
    p = _shard_record_path(run_dir, k)
    text = json.dumps({"shard": int(k), "shards": int(n)}, sort_keys=True) + "\n"
    try:
        if p.read_text(encoding="utf-8") == text:
            return
    except OSError:
        pass
    atomic_write_text(p, text)


class RunLock:
    """Advisory lock on a run directory (``fcntl.flock`` on ``RUN_DIR/.lock``).

    Unsharded (``shard=None``): exclusive on ``.lock``; only the holder writes the
    manifest, the stored config and task files, and removes stale temporary files.

    Shard ``(k, n)``: shared on ``.lock`` and exclusive on ``RUN_DIR/.shards/shard-K.lock``.
    Shards with different K hold it together; the same K twice is refused, and so is an
    unsharded run (or a fit/report, which take ``.lock`` exclusively) while any shard
    holds it, and a shard while one of those does.  A shard writes only its own task
    files, parts and shard record; the shared files (manifest, stored config,
    fingerprint cache, field caches) only while it also holds the set-up lock
    (:meth:`setup`, exclusive on ``RUN_DIR/.shards/setup.lock``), which shards take in
    turn.

    The lock file of an exclusive holder holds its pid (for the refusal message); lock
    files are never deleted, so that two processes always lock the same inode.
    """

    def __init__(self, run_dir: str | os.PathLike, shard: tuple[int, int] | None = None):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self.shard = None if shard is None else (int(shard[0]), int(shard[1]))
        self._fd: int | None = None
        self._shard_fd: int | None = None
        self._setup_fd: int | None = None

    def _link_or(self, exc: OSError, path: Path | None = None) -> Exception:
        """A refusal naming a lock file that is a symbolic link, else ``exc`` itself."""
        path = self.path if path is None else path
        if exc.errno == errno.ELOOP or path.is_symlink():
            return UnsafePathError(f"{path}: is a symbolic link; glaciar writes only inside "
                                   "the run directory: remove it")
        return exc

    def _refuse(self, fd: int | None = None, shards: dict | None = None):
        shards = running_shards(self.run_dir) if shards is None else shards
        if shards and self.shard is None:
            n = (read_shard_counts(self.run_dir) or {}).values()
            of = f"/{max(n)}" if n else ""
            who = ", ".join(f"{k}{of} (pid {pid})" for k, pid in shards.items())
            return RunLockedError(f"{self.run_dir}: shards of a sharded run are writing here "
                                  f"(shard {who}); run again once they have finished")
        pid = "unknown" if fd is None else _pid_text(fd)
        if self.shard is not None:
            return RunLockedError(f"{self.run_dir}: an unsharded glaciar run (or a fit/report) is "
                                  f"writing here (pid {pid}); a shard starts once it has finished")
        return RunLockedError(f"{self.run_dir}: another glaciar run is writing here (pid {pid})")

    def _refuse_shard(self, pid: str):
        k, n = self.shard
        return RunLockedError(f"{self.run_dir}: shard {k}/{n} is already running here (pid {pid}); "
                              "each shard runs once at a time")

    def check_free(self) -> None:
        """Raise :class:`RunLockedError` if a process holds what :meth:`acquire` would take
        (creates nothing)."""
        import fcntl

        try:
            fd = os.open(self.path, os.O_RDONLY | _NOFOLLOW)
        except FileNotFoundError:
            fd = None
        except OSError as exc:
            raise self._link_or(exc) from None
        if fd is not None:
            try:
                try:
                    fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
                except OSError as exc:
                    if exc.errno in _BUSY:
                        raise self._refuse(fd, shards={}) from None
                    raise
                fcntl.flock(fd, fcntl.LOCK_UN)
            finally:
                os.close(fd)
        if self.shard is None:
            shards = running_shards(self.run_dir)
            if shards:
                raise self._refuse(shards=shards)
        else:
            pid = shard_holder(self.run_dir, self.shard[0])
            if pid is not None:
                raise self._refuse_shard(pid)

    def _open(self, path: Path) -> int:
        try:
            # Not through a symbolic link: the pid written below would land outside the run.
            return os.open(path, os.O_RDWR | os.O_CREAT | _NOFOLLOW, 0o666 & ~process_umask())
        except OSError as exc:
            raise self._link_or(exc, path) from None

    def _write_pid(self, fd: int, path: Path) -> None:
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as exc:
            # The pid only names the holder in refusals: on a full disk the lock holds
            # without it, and the run's first real write says which file has no room.
            if disk_full(path, exc) is None:
                os.close(fd)
                raise

    def acquire(self) -> "RunLock":
        """Take the lock (creating the lock files) or raise :class:`RunLockedError`."""
        import fcntl

        fd = self._open(self.path)
        how = fcntl.LOCK_EX if self.shard is None else fcntl.LOCK_SH
        try:
            fcntl.flock(fd, how | fcntl.LOCK_NB)
        except OSError as exc:
            try:
                if exc.errno in _BUSY:
                    raise self._refuse(fd, shards=None if self.shard is None else {}) from None
                raise
            finally:
                os.close(fd)
        if self.shard is None:
            self._write_pid(fd, self.path)
            self._fd = fd
            return self
        # A shard: .lock shared (never written: other shards hold it too), its own lock exclusive.
        self._fd = fd
        try:
            run_subdir(self.run_dir, SHARDS_DIRNAME)
            path = _shard_lock_path(self.run_dir, self.shard[0])
            sfd = self._open(path)
            for attempt in range(_SHARD_LOCK_TRIES):
                try:
                    fcntl.flock(sfd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as exc:
                    if exc.errno not in _BUSY:
                        os.close(sfd)
                        raise
                    if attempt == _SHARD_LOCK_TRIES - 1:
                        pid = _pid_text(sfd)
                        os.close(sfd)
                        raise self._refuse_shard(pid) from None
                    time.sleep(_SHARD_LOCK_PAUSE)
            self._write_pid(sfd, path)
            self._shard_fd = sfd
        except BaseException:
            self.release()
            raise
        return self

    def begin_setup(self) -> None:
        """A shard: wait for, then take, the set-up lock (no-op when unsharded or held)."""
        import fcntl

        if self.shard is None or self._setup_fd is not None:
            return
        fd = self._open(Path(self.run_dir) / SHARDS_DIRNAME / "setup.lock")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except BaseException:
            os.close(fd)
            raise
        self._setup_fd = fd

    def end_setup(self) -> None:
        """Release the set-up lock (no-op when not held)."""
        import fcntl

        if self._setup_fd is not None:
            try:
                fcntl.flock(self._setup_fd, fcntl.LOCK_UN)
            finally:
                os.close(self._setup_fd)
                self._setup_fd = None

    def setup(self):
        """Context manager: the set-up lock held inside (a shard; nothing unsharded)."""
        import contextlib

        @contextlib.contextmanager
        def held():
            self.begin_setup()
            try:
                yield self
            finally:
                self.end_setup()
        return held()

    def release(self) -> None:
        """Release every lock held (the files stay)."""
        import fcntl

        self.end_setup()
        for attr in ("_shard_fd", "_fd"):
            fd = getattr(self, attr)
            if fd is not None:
                try:
                    fcntl.flock(fd, fcntl.LOCK_UN)
                finally:
                    os.close(fd)
                    setattr(self, attr, None)

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
