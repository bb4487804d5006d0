"""The run directory's own files: atomic writes, the manifest, input fingerprints, the lock.

Everything glaciar writes goes through :func:`atomic_write_bytes` (a temporary name in
the same directory, then a rename), so an interrupted run never leaves a half-written
file.  ``RUN_DIR/manifest.json`` records the run's settings, inputs and store format
(:func:`read_manifest`, :func:`write_manifest`); :func:`file_fingerprint` hashes the
input files it names; :class:`RunLock` (``RUN_DIR/.lock``) lets one process write a run
directory at a time.  The task files and parts under ``results/`` are
:mod:`glaciar.store`'s.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import tempfile
from pathlib import Path

from .constants import LOCK_NAME, MANIFEST_NAME
from .paths import UnsafePathError, allocate, disk_full

__all__ = ["process_umask", "atomic_write_bytes", "atomic_write_text", "StoreMismatchError",
           "RunLockedError", "read_manifest", "manifest_text", "write_manifest", "store_format",
           "file_fingerprint", "RunLock"]


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


class RunLock:
    """Advisory, exclusive lock on a run directory (``fcntl.flock`` on ``RUN_DIR/.lock``).

    Only the holder writes the manifest, the stored config and task files,
    and removes stale temporary files.  The lock file holds the holder's pid
    (for the refusal message); it is never deleted, so that two processes
    always lock the same inode.
    """

    def __init__(self, run_dir: str | os.PathLike):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self._fd: int | None = None

    @staticmethod
    def _holder(fd: int) -> str:
        try:
            text = os.pread(fd, 64, 0).decode("ascii", "replace").strip()
        except OSError:
            text = ""
        return text if text.isdigit() else "unknown"

    def _link_or(self, exc: OSError) -> Exception:
        """A refusal naming a lock file that is a symbolic link, else ``exc`` itself."""
        if exc.errno == errno.ELOOP or self.path.is_symlink():
            return UnsafePathError(f"{self.path}: is a symbolic link; glaciar writes only inside "
                                   "the run directory: remove it")
        return exc

    def _refuse(self, fd: int):
        pid = self._holder(fd)
        return RunLockedError(f"{self.run_dir}: another glaciar run is writing here (pid {pid})")

    def check_free(self) -> None:
        """Raise :class:`RunLockedError` if another process holds the lock (creates nothing)."""
        import fcntl

        try:
            fd = os.open(self.path, os.O_RDONLY | _NOFOLLOW)
        except FileNotFoundError:
            return
        except OSError as exc:
            raise self._link_or(exc) from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except OSError as exc:
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise self._refuse(fd) from None
                raise
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    def acquire(self) -> "RunLock":
        """Take the lock (creating the lock file) or raise :class:`RunLockedError`."""
        import fcntl

        try:
            # Not through a symbolic link: the pid written below would land outside the run.
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | _NOFOLLOW, 0o666 & ~process_umask())
        except OSError as exc:
            raise self._link_or(exc) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            try:
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise self._refuse(fd) from None
                raise
            finally:
                os.close(fd)
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as exc:
            # The pid only names the holder in refusals: on a full disk the lock holds
            # without it, and the run's first real write says which file has no room.
            if disk_full(self.path, exc) is None:
                os.close(fd)
                raise
        self._fd = fd
        return self

    def release(self) -> None:
        """Release the lock (the file stays)."""
        import fcntl

        if self._fd is not None:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_UN)
            finally:
                os.close(self._fd)
                self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
