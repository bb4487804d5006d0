"""Results store: an append-only Parquet dataset, one file per finished task.

Layout of a run directory::

    RUN_DIR/config.yaml        the resolved configuration of the run
    RUN_DIR/manifest.json      store format, settings, input fingerprints, seed, glaciar version
    RUN_DIR/results/*.parquet  one file per finished task
    RUN_DIR/.lock              advisory lock held by the run writing here (its pid inside)
    RUN_DIR/.input_fingerprints.json   cache of input-file hashes by (path, size, mtime)

Every file is written to a temporary name in the same directory and then
renamed, so an interrupted run never leaves a half-written file behind; a
resumed run skips the tasks whose file exists and is a complete Parquet file
of the right task (:func:`verified_task_names`).

Task files are named by :func:`task_filename`: a readable part plus a hash of
the exact task key (field name, z and magnitude as ``repr(float)``,
iteration), so two different tasks never share a file.  Which rows count is
decided in one place, :func:`read_current_results`: the rows of the fields,
grid values and iterations that the run's manifest lists now.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from .constants import (COL_FIELD, COL_ITERATION, COL_MAG, COL_Z, LOCK_NAME, MANIFEST_NAME,
                        RESULTS_DIRNAME)

__all__ = ["atomic_write_bytes", "atomic_write_text", "task_key", "task_filename",
           "field_file_prefix", "write_task_table", "finished_task_names", "verified_task_names",
           "read_results", "read_current_results", "read_manifest", "write_manifest",
           "file_fingerprint", "RunLock", "StoreMismatchError", "RunLockedError", "StoreWarning"]

#: Key-value metadata of every task file: the exact task key and the number of rows.
_META_TASK = b"glaciar.task"
_META_ROWS = b"glaciar.n_rows"
#: Characters of the field name kept in the readable part of a task file name.
_READABLE_FIELD_CHARS = 40


class StoreMismatchError(RuntimeError):
    """The run directory was made with a different configuration, inputs or format."""


class RunLockedError(RuntimeError):
    """Another process holds the run directory's lock."""


class StoreWarning(UserWarning):
    """Something in a run directory is ignored or redone (stale rows, a corrupt task file)."""


# --------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------
def _umask() -> int:
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
    the umask (``mkstemp`` alone would leave it 0600).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fchmod(fh.fileno(), 0o666 & ~_umask())
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Text version of :func:`atomic_write_bytes` (UTF-8)."""
    atomic_write_bytes(path, text.encode("utf-8"))


# --------------------------------------------------------------------------
# Task identity
# --------------------------------------------------------------------------
def task_key(field: str, z: float, mag: float, iteration: int) -> str:
    """The exact identity of a task as a string (JSON of field, repr(z), repr(mag), iteration).

    Two tasks have the same key only if their field names are equal, their z
    and magnitude are the same floats and their iterations are equal.
    """
    return json.dumps([str(field), repr(float(z)), repr(float(mag)), int(iteration)],
                      ensure_ascii=False, separators=(",", ":"))


def _readable(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", str(name))[:_READABLE_FIELD_CHARS]


def _short_hash(text: str, n: int) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:n]


def field_file_prefix(field: str) -> str:
    """The start of the name of every task file of ``field`` (readable name + field hash)."""
    return f"task_{_readable(field)}-{_short_hash(str(field), 8)}_"


def task_filename(field: str, z: float, mag: float, iteration: int) -> str:
    """File name (inside ``results/``) of one task's rows.

    A readable part (field name with unsafe characters replaced, z and
    magnitude to 4 decimals, iteration) for people, then the first 16 hex
    digits of the SHA-256 of :func:`task_key` for uniqueness: fields ``a b``
    and ``a_b``, or z = 9.0 and 9.00004, get different files.  Named by
    values, not grid indices, so extending the grid of a run leaves the
    names (and the rows) of its finished tasks unchanged.
    """
    key = task_key(field, z, mag, iteration)
    return (f"{field_file_prefix(field)}z{float(z):+09.4f}_m{float(mag):+09.4f}_"
            f"i{int(iteration):04d}_{_short_hash(key, 16)}.parquet")


def write_task_table(run_dir: str | os.PathLike, name: str, table: pd.DataFrame,
                     key: str | None = None) -> Path:
    """Write one task's per-source rows atomically as ``results/<name>``.

    ``key`` (:func:`task_key`) and the row count are stored in the file's
    metadata, so that :func:`verified_task_names` can tell a complete file of
    the right task from a truncated or foreign one without reading the rows.
    """
    import io

    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(run_dir) / RESULTS_DIRNAME / name
    t = pa.Table.from_pandas(table, preserve_index=False)
    meta = dict(t.schema.metadata or {})
    meta[_META_ROWS] = str(len(table)).encode()
    if key is not None:
        meta[_META_TASK] = key.encode("utf-8")
    t = t.replace_schema_metadata(meta)
    buf = io.BytesIO()
    pq.write_table(t, buf)
    atomic_write_bytes(path, buf.getvalue())
    return path


def finished_task_names(run_dir: str | os.PathLike) -> set[str]:
    """Names of the task files present (temporary files excluded; not validated)."""
    d = Path(run_dir) / RESULTS_DIRNAME
    if not d.is_dir():
        return set()
    return {p.name for p in d.glob("task_*.parquet")}


def _task_file_problem(path: Path, key: str) -> str | None:
    """Why ``path`` is not a complete task file of ``key`` (None if it is).

    A footer-level check that reads ~the footer's bytes and parses nothing
    (~0.1 ms per file, where parsing the ~45 kB footer with pyarrow costs
    ~1.5 ms): the file starts and ends with Parquet's magic bytes, the footer
    length fits the file, and the footer holds this task's key (written by
    :func:`write_task_table`).  Parquet writes its footer last and task files
    are renamed into place only when complete, so a cut or partly copied file
    fails the check; a file of another task fails the key test.
    """
    magic = b"PAR1"
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
            size = fh.seek(0, os.SEEK_END)
            if size < 12:
                return f"not a complete Parquet file ({size} bytes)"
            fh.seek(size - 8)
            tail = fh.read(8)
            n = int.from_bytes(tail[:4], "little")
            if head != magic or tail[4:] != magic or n <= 0 or n > size - 12:
                return "not a complete Parquet file (no footer: truncated or not Parquet)"
            fh.seek(size - 8 - n)
            footer = fh.read(n)
    except OSError as exc:
        return f"unreadable ({exc.strerror or exc})"
    if _META_TASK not in footer:
        return "not a glaciar task file (no task key in its metadata)"
    if key.encode("utf-8") not in footer:
        return f"holds another task than {key}"
    return None


def verified_task_names(run_dir: str | os.PathLike, wanted: dict[str, str]) -> set[str]:
    """The names among ``wanted`` whose file is a complete task file of the right task.

    Parameters
    ----------
    run_dir : path
    wanted : dict
        ``{file name: task key}`` of the tasks to look for.

    Returns
    -------
    set of str
        Names whose file exists and passes :func:`_task_file_problem` (complete
        Parquet footer holding the expected task key).  Each other existing
        file gets a :class:`StoreWarning` naming it (its task will be run again).
    """
    d = Path(run_dir) / RESULTS_DIRNAME
    good = set()
    for name in sorted(finished_task_names(run_dir) & set(wanted)):
        problem = _task_file_problem(d / name, wanted[name])
        if problem is None:
            good.add(name)
        else:
            warnings.warn(f"{d / name}: {problem}; the task will be run again", StoreWarning,
                          stacklevel=2)
    return good


# --------------------------------------------------------------------------
# Reading rows
# --------------------------------------------------------------------------
def _read_task_file(path: Path, columns):
    try:
        return pd.read_parquet(path, columns=columns)
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad files
        raise ValueError(f"{path}: unreadable task file ({type(exc).__name__}: {exc}); run "
                         "`glaciar simulate` again to redo it") from None


def read_results(run_dir: str | os.PathLike, columns: list[str] | None = None) -> pd.DataFrame:
    """Every per-source row in the store, current or not, as one DataFrame (sorted by file).

    Most callers want :func:`read_current_results`, which keeps only the rows
    of the tasks the run's configuration lists now.

    Raises
    ------
    FileNotFoundError
        If the run directory holds no finished task.
    ValueError
        A task file that cannot be read (named).
    """
    d = Path(run_dir) / RESULTS_DIRNAME
    files = sorted(d.glob("task_*.parquet")) if d.is_dir() else []
    if not files:
        raise FileNotFoundError(f"{d}: no finished task files (task_*.parquet); "
                                "run `glaciar simulate` first")
    frames = [_read_task_file(f, columns) for f in files]
    return pd.concat(frames, ignore_index=True)


def current_rows_mask(rows: pd.DataFrame, manifest: dict) -> "pd.Series":
    """True for rows of a field, z, magnitude and iteration that ``manifest`` lists.

    Grid values are compared exactly (the manifest stores them as JSON floats,
    which round-trip).  A manifest key or a row column that is absent does not
    restrict.
    """
    keep = pd.Series(True, index=rows.index)
    checks = ((COL_FIELD, "fields", lambda col, v: col.astype(str).isin([str(x) for x in v])),
              (COL_Z, "z_values", lambda col, v: col.astype(float).isin([float(x) for x in v])),
              (COL_MAG, "mag_values", lambda col, v: col.astype(float).isin([float(x) for x in v])),
              (COL_ITERATION, "n_iterations", lambda col, v: col.astype(int) < int(v)))
    for col, key, test in checks:
        if col in rows.columns and manifest.get(key) is not None:
            keep &= test(rows[col], manifest[key])
    cells = manifest.get("cells") or []
    if cells and all(c in rows.columns for c in (COL_FIELD, COL_Z, COL_MAG, COL_ITERATION)):
        # Explicit cells (grid.cells, adaptive rounds): a row of (field, z, mag) with an
        # iteration below the cell's count is current too. Exact float comparison, as above.
        listed = pd.DataFrame(
            [(str(f), float(c["z"]), float(c["mag"]), int(c["n_iterations"]))
             for c in cells for f in c["fields"]],
            columns=["_f", "_z", "_m", "_n"]).groupby(["_f", "_z", "_m"], as_index=False).max()
        key = pd.DataFrame({"_f": rows[COL_FIELD].astype(str).to_numpy(),
                            "_z": rows[COL_Z].astype(float).to_numpy(),
                            "_m": rows[COL_MAG].astype(float).to_numpy()})
        n_it = key.merge(listed, on=["_f", "_z", "_m"], how="left")["_n"].to_numpy()
        with np.errstate(invalid="ignore"):
            in_cell = rows[COL_ITERATION].astype(int).to_numpy() < np.nan_to_num(n_it, nan=0)
        keep |= pd.Series(in_cell, index=rows.index)
    return keep


def read_current_results(run_dir: str | os.PathLike,
                         columns: list[str] | None = None) -> pd.DataFrame:
    """The per-source rows of the tasks the run's manifest lists now.

    The single rule that ``glaciar report`` and ``glaciar fit`` share: rows of
    fields, z or magnitude values, or iterations that the configuration no
    longer lists (a run directory grows and shrinks with its configuration)
    are left out, with one :class:`StoreWarning` saying how many.  The
    manifest's areas cover exactly the fields kept.  Without a manifest
    (a hand-made store) every row counts.

    Parameters
    ----------
    run_dir : path
    columns : list of str, optional
        Columns to return (all by default).

    Raises
    ------
    FileNotFoundError
        No task file, or no row of a listed task.
    ValueError
        A task file that cannot be read (named).
    """
    import pyarrow.parquet as pq

    run_dir = Path(run_dir)
    manifest = read_manifest(run_dir) or {}
    d = run_dir / RESULTS_DIRNAME
    files = sorted(d.glob("task_*.parquet")) if d.is_dir() else []
    read_cols = None
    if columns is not None and files:
        try:
            have = set(pq.read_schema(files[0]).names)
        except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad files
            raise ValueError(f"{files[0]}: unreadable task file ({type(exc).__name__}: {exc}); "
                             "run `glaciar simulate` again to redo it") from None
        keys = [c for c in (COL_FIELD, COL_Z, COL_MAG, COL_ITERATION) if c in have]
        read_cols = list(dict.fromkeys(list(columns) + keys))
    rows = read_results(run_dir, columns=read_cols)
    keep = current_rows_mask(rows, manifest)
    n_out = int((~keep).sum())
    if n_out:
        key_cols = [c for c in (COL_FIELD, COL_Z, COL_MAG, COL_ITERATION) if c in rows.columns]
        n_tasks = len(rows.loc[~keep, key_cols].drop_duplicates())
        gone = sorted(set(map(str, rows.loc[~keep, COL_FIELD])) - set(map(str, manifest["fields"]))) \
            if COL_FIELD in rows.columns and manifest.get("fields") is not None else []
        what = f" (fields no longer listed: {gone})" if gone else ""
        warnings.warn(f"{run_dir}: ignoring {n_out} rows of {n_tasks} task(s) whose field, z, "
                      f"magnitude or iteration the run's configuration no longer lists{what}",
                      StoreWarning, stacklevel=2)
        rows = rows[keep].reset_index(drop=True)
    if rows.empty:
        raise FileNotFoundError(f"{d}: no finished task of the fields and grid the run's "
                                "configuration lists; run `glaciar simulate` first")
    if columns is not None:
        rows = rows[list(columns)]
    return rows


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

    def _refuse(self, fd: int):
        pid = self._holder(fd)
        return RunLockedError(f"{self.run_dir}: another glaciar run is writing here (pid {pid})")

    def check_free(self) -> None:
        """Raise :class:`RunLockedError` if another process holds the lock (creates nothing)."""
        import fcntl

        try:
            fd = os.open(self.path, os.O_RDONLY)
        except FileNotFoundError:
            return
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

        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666 & ~_umask())
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            try:
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise self._refuse(fd) from None
                raise
            finally:
                os.close(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
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
