"""Results store: an append-only Parquet dataset, one file per finished task.

Layout of a run directory::

    RUN_DIR/config.yaml        the resolved configuration of the run
    RUN_DIR/manifest.json      store format, settings, input fingerprints, seed, glaciar version
    RUN_DIR/results/task_*.parquet  one file per finished task (rows; counts and m_obs
                               histograms in its footer, :func:`glaciar.counting.task_counts`,
                               :func:`glaciar.counting.task_histogram`)
    RUN_DIR/results/compact/field=<name>-<hash>/z=<z>/part-<hash>.parquet
                               compacted tasks of one (field, z): their rows, and in the
                               footer their task list, counts and histograms (:func:`compact`)
    RUN_DIR/results/corrupt/   task files and parts found corrupt, set aside by the run
                               that found them (their tasks run again; :func:`set_aside`)
    RUN_DIR/.lock              advisory lock held by the run writing here (its pid inside)
    RUN_DIR/.input_fingerprints.json   cache of input-file hashes by (path, size, mtime)

Every file is written to a temporary name in the same directory and then
renamed, so an interrupted run never leaves a half-written file behind; a
resumed run skips the tasks whose file exists and is an intact Parquet file
of the right task (:func:`verified_task_names`).  Task files and parts are
written with Parquet page checksums and footer digests of their pages, columns
and row count, and footer tables (:func:`unit_problem`): a corrupt one is set
aside and redone, and readers name it.

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
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from .constants import COL_FIELD, COL_ITERATION, COL_MAG, COL_Z, LOCK_NAME, MANIFEST_NAME, RESULTS_DIRNAME
from .counting import (COUNT_DEPTH_KEY, COUNT_K_REC, COUNT_K_SEL, COUNT_MAG_KEY, COUNT_N, HIST_MIN_KEY,
                       HIST_MOBS_BIN, group_sums, has_hist_columns, task_counts, task_histogram)
from .paths import UnsafePathError, allocate, disk_full, readable, run_subdir

__all__ = ["atomic_write_bytes", "atomic_write_text", "task_key", "task_filename",
           "field_file_prefix", "write_task_table", "finished_task_names", "verified_task_names",
           "read_results", "read_current_results", "read_manifest", "write_manifest",
           "file_fingerprint", "RunLock", "StoreMismatchError", "RunLockedError", "StoreWarning",
           "read_current_counts", "store_columns", "write_part", "compact", "COMPACT_EVERY",
           "read_current_histograms", "unit_problem", "set_aside",
           "CORRUPT_DIRNAME", "process_umask"]

#: Key-value metadata of every task file: the exact task key and the number of rows.
_META_TASK = b"glaciar.task"
_META_ROWS = b"glaciar.n_rows"
#: Footer metadata of the counts: an Arrow IPC stream, and the magnitude covariate they key on.
_META_COUNTS = b"glaciar.counts"
_META_COUNTS_MAG = b"glaciar.counts_mag_column"
#: Footer metadata of the histograms of the measured magnitude (:func:`glaciar.counting.task_histogram`): an
#: Arrow IPC stream, and the measured-magnitude column they bin.
_META_HIST = b"glaciar.mobs_hist"
_META_HIST_OBS = b"glaciar.mobs_hist_column"
#: Suffix of the key of a footer table's BLAKE2b digest (checked on resume, :func:`_task_file_problem`).
_DIGEST_SUFFIX = b".blake2b"
#: Footer metadata: BLAKE2b of the rows' column names, types and row count
#: (:func:`_schema_digest`).  Parquet checksums its data pages (written with
#: ``write_page_checksum``) but not its footer: a garbled footer that still parses
#: (a renamed column, another row count) is caught by this digest.
_META_SCHEMA = b"glaciar.schema.blake2b"
#: Footer metadata: BLAKE2b of every byte before the footer (pages and page headers,
#: :func:`_parquet_bytes`).
_META_PAGES = b"glaciar.pages.blake2b"
#: Footer metadata of a compacted part: JSON list of [task file name, task key, n_rows].
_META_PART_TASKS = b"glaciar.part_tasks"
#: Characters of the field name kept in the readable part of a task file name.
_READABLE_FIELD_CHARS = 40
#: Sub-directory of results/ holding the compacted parts.
COMPACT_DIRNAME = "compact"
#: Compact when at least this many task files are loose (end of simulate, and during a run).
COMPACT_EVERY = 1024


class StoreMismatchError(RuntimeError):
    """The run directory was made with a different configuration, inputs or format."""


class RunLockedError(RuntimeError):
    """Another process holds the run directory's lock."""


class StoreWarning(UserWarning):
    """Something in a run directory is ignored or redone (stale rows, a corrupt task file)."""


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
    return readable(name, _READABLE_FIELD_CHARS)


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
                     key: str | None = None, mag_column: str | None = None,
                     obs_column: str | None = None) -> Path:
    """Write one task's per-source rows atomically as ``results/<name>``.

    ``key`` (:func:`task_key`) and the row count are stored in the file's
    metadata, so that :func:`verified_task_names` can tell a complete file of
    the right task from a truncated or foreign one without reading the rows.
    With ``mag_column`` (the fit's magnitude covariate, ``mag_input`` or
    ``M_uv``), the task's :func:`glaciar.counting.task_counts` are stored in the footer too;
    with ``obs_column`` (the measured detection-band magnitude) its
    :func:`glaciar.counting.task_histogram` as well (when the table has that column and
    ``mag_input``).
    """
    import pyarrow as pa

    path = Path(run_dir) / RESULTS_DIRNAME / name
    t = pa.Table.from_pandas(table, preserve_index=False)
    meta = dict(t.schema.metadata or {})
    meta[_META_ROWS] = str(len(table)).encode()
    if key is not None:
        meta[_META_TASK] = key.encode("utf-8")
    if mag_column is not None:
        meta[_META_COUNTS] = _ipc_bytes(task_counts(table, mag_column))
        meta[_META_COUNTS_MAG] = mag_column.encode("utf-8")
    if obs_column is not None and has_hist_columns(table.columns, obs_column):
        meta[_META_HIST] = _ipc_bytes(task_histogram(table, obs_column))
        meta[_META_HIST_OBS] = obs_column.encode("utf-8")
    for k in (_META_COUNTS, _META_HIST):
        if k in meta:
            meta[k + _DIGEST_SUFFIX] = _digest(meta[k])
    meta[_META_SCHEMA] = _schema_digest(t.schema, t.num_rows)
    data = _parquet_bytes(t.replace_schema_metadata(meta))
    atomic_write_bytes(run_subdir(run_dir, RESULTS_DIRNAME) / name, data)
    return path


def _parquet_bytes(table) -> bytes:
    """``table`` as Parquet bytes with page checksums and, in its footer, a digest of its pages.

    Parquet's page checksums cover a page's data, not its header; a digest of every
    byte before the footer (:data:`_META_PAGES`) covers both, and checking it costs one
    hash of the file (:func:`unit_problem`).  The key-value metadata lives only in the
    footer, so the file is written once to learn the bytes of its pages and once more
    with their digest added: the pages come out the same (checked; if they ever did not,
    the file keeps its page checksums only).
    """
    import io

    import pyarrow.parquet as pq

    def write(t) -> bytes:
        buf = io.BytesIO()
        pq.write_table(t, buf, write_page_checksum=True)
        return buf.getvalue()

    first = write(table)
    pages = first[:_pages_end(first)]
    meta = dict(table.schema.metadata or {})
    meta[_META_PAGES] = _digest(pages)
    second = write(table.replace_schema_metadata(meta))
    return second if second[:len(pages)] == pages else first


def _pages_end(data: bytes) -> int:
    """Offset of the footer of complete Parquet bytes (the pages end there)."""
    return len(data) - 8 - int.from_bytes(data[-8:-4], "little")


def _ipc_bytes(df: pd.DataFrame) -> bytes:
    import pyarrow as pa

    t = pa.Table.from_pandas(df, preserve_index=False).replace_schema_metadata(None)
    sink = pa.BufferOutputStream()
    # zstd: counts repeat their keys and are mostly small integers (~10x smaller footers).
    opts = pa.ipc.IpcWriteOptions(compression="zstd")
    with pa.ipc.new_stream(sink, t.schema, options=opts) as w:
        w.write_table(t)
    return sink.getvalue().to_pybytes()


def _ipc_table(data: bytes):
    import pyarrow as pa

    return pa.ipc.open_stream(pa.py_buffer(data)).read_all()


# --------------------------------------------------------------------------
# Units of the store: loose task files and compacted parts
# --------------------------------------------------------------------------
def _loose_files(run_dir) -> list[Path]:
    d = Path(run_dir) / RESULTS_DIRNAME
    return sorted(d.glob("task_*.parquet")) if d.is_dir() else []


def _part_files(run_dir) -> list[Path]:
    d = Path(run_dir) / RESULTS_DIRNAME / COMPACT_DIRNAME
    return sorted(d.glob("field=*/z=*/part-*.parquet")) if d.is_dir() else []


def _footer(path: Path):
    """(key-value metadata dict, None) of a Parquet file, or (None, why not)."""
    import pyarrow.parquet as pq

    try:
        meta = pq.read_metadata(path).metadata or {}
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad files
        return None, f"not a complete Parquet file ({type(exc).__name__}: {exc})"
    return meta, None


def _part_tasks(path: Path, meta: dict | None = None):
    """([(name, key, n_rows)], footer) of a compacted part, or (None, why not)."""
    if meta is None:
        meta, problem = _footer(path)
        if meta is None:
            return None, problem
    if _META_PART_TASKS not in meta:
        return None, "not a glaciar part (no task list in its metadata)"
    try:
        tasks = [(str(n), str(k), int(r)) for n, k, r in json.loads(meta[_META_PART_TASKS])]
    except (ValueError, TypeError) as exc:
        return None, f"unreadable task list ({exc})"
    return tasks, meta


def _valid_parts(run_dir, warn: bool, names: bool):
    """Yield ``(path, footer, task names or None)`` of each valid part, one footer at a time.

    A part is valid when its footer parses and holds a task list; the list is
    parsed only when ``names`` is asked for.  An invalid part is skipped with
    a :class:`StoreWarning` naming it (``warn``).
    """
    for p in _part_files(run_dir):
        meta, problem = _footer(p)
        if meta is not None and _META_PART_TASKS not in meta:
            meta, problem = None, "not a glaciar part (no task list in its metadata)"
        got = None
        if meta is not None and names:
            tasks, problem = _part_tasks(p, meta)
            meta = None if tasks is None else meta
            got = None if tasks is None else {n for n, _, _ in tasks}
        if meta is None:
            if warn:
                warnings.warn(f"{p}: {problem}; its tasks are not counted and will be run again",
                              StoreWarning, stacklevel=4)
            continue
        yield p, meta, got


def _store_units(run_dir, warn: bool = True):
    """Valid parts and the loose task files that no valid part holds.

    Returns ``(parts, loose)``, two lists of paths.  A task file whose name a
    valid part lists is left out (the window between a part's rename and the
    deletion of its task files: counted once).  An invalid part is left out
    with a :class:`StoreWarning` naming it (``warn``).  Footers are parsed
    one at a time and not kept (memory bounded by one part's footer).
    """
    loose_all = _loose_files(run_dir)
    parts, in_parts = [], set()
    for p, _, names in _valid_parts(run_dir, warn, bool(loose_all)):
        parts.append(p)
        in_parts.update(names or ())
    loose = [f for f in loose_all if f.name not in in_parts]
    return parts, loose


def finished_task_names(run_dir: str | os.PathLike) -> set[str]:
    """Names of the finished tasks' files: loose task files and tasks listed by valid parts.

    Temporary files excluded; loose files not validated (:func:`verified_task_names` does).
    """
    parts, loose = _store_units(run_dir, warn=False)
    names = {f.name for f in loose}
    for p in parts:
        tasks, _ = _part_tasks(p)
        names.update(n for n, _, _ in tasks or ())
    return names


def _task_file_problem(path: Path, key: str) -> str | None:
    """Why ``path`` is not a complete task file of ``key`` (None if it is).

    A footer-level check that reads ~the footer's bytes and parses nothing
    (~0.1 ms per file, where parsing the ~45 kB footer with pyarrow costs
    ~1.5 ms): the file starts and ends with Parquet's magic bytes, the footer
    length fits the file, and the footer holds this task's key (written by
    :func:`write_task_table`).  Parquet writes its footer last and task files
    are renamed into place only when complete, so a cut or partly copied file
    fails the check; a file of another task fails the key test; counts or
    histograms whose bytes no longer match their stored digest fail too
    (:func:`_footer_table_problem`).
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
    for meta_key in (_META_COUNTS, _META_HIST):
        problem = _footer_table_problem(footer, meta_key)
        if problem is not None:
            return problem
    return None


def _footer_table_problem(footer: bytes, meta_key: bytes) -> str | None:
    """Why the IPC table stored under ``meta_key`` in a raw Parquet footer is unreadable.

    None when it is absent, or has no digest (a file written before digests),
    or matches its BLAKE2b digest (``meta_key + _DIGEST_SUFFIX``, written
    beside it by :func:`write_task_table`): hashing the few kB costs ~µs
    where decoding the table costs ~1 ms.
    """
    digest = _raw_meta_value(footer, meta_key + _DIGEST_SUFFIX)
    if digest is None:
        return None
    value = _raw_meta_value(footer, meta_key)
    if value is None or _digest(value) != digest:
        return f"unreadable {meta_key.decode()} metadata (digest mismatch)"
    return None


def _schema_digest(schema, n_rows: int) -> bytes:
    """BLAKE2b of an Arrow schema's column names and types and a row count (metadata ignored)."""
    text = json.dumps([[f.name, str(f.type)] for f in schema] + [int(n_rows)],
                      ensure_ascii=False, separators=(",", ":"))
    return _digest(text.encode("utf-8"))


def _digest(data: bytes) -> bytes:
    return hashlib.blake2b(data, digest_size=16).hexdigest().encode("ascii")


def _raw_meta_value(footer: bytes, meta_key: bytes) -> bytes | None:
    """The value of key-value metadata ``meta_key`` found in a raw (unparsed) Parquet footer.

    Thrift's compact protocol writes an entry as field header 0x18, varint
    length, key bytes, 0x18, varint length, value bytes; None if the key is
    absent (or the value runs past the footer).
    """
    head = b"\x18" + _varint(len(meta_key)) + meta_key + b"\x18"
    at = footer.find(head)
    if at < 0:
        return None
    i, n, shift = at + len(head), 0, 0
    while i < len(footer):
        byte = footer[i]
        n |= (byte & 0x7F) << shift
        shift += 7
        i += 1
        if not byte & 0x80:
            break
    value = footer[i:i + n]
    return value if len(value) == n else None


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        out.append((n & 0x7F) | (0x80 if n > 0x7F else 0))
        n >>= 7
        if not n:
            return bytes(out)



def unit_problem(path: str | os.PathLike) -> str | None:
    """Why a task file or compacted part is not intact (None if it is): every byte checked.

    Parses the footer (a garbled one fails, or no longer matches the digests
    glaciar wrote into it: row count, column names and types, counts,
    histograms, a part's task list), then checks every byte before the footer
    against its recorded digest (pages and page headers: one hash of the file).
    A file written before page digests has every page of every row group
    decoded instead, with Parquet's page checksums verified where it has them
    (without: pages that no longer decode).  Detection of random in-page
    garbage: benchmarks/corruption.py.
    """
    import pyarrow.parquet as pq

    path = Path(path)
    try:
        pf = pq.ParquetFile(path, page_checksum_verification=True)
        md = pf.metadata
        meta = md.metadata or {}
        rows = meta.get(_META_ROWS)
        if rows is not None and int(rows) != md.num_rows:
            return (f"corrupt footer ({md.num_rows} rows where its metadata records "
                    f"{int(rows)})")
        want = meta.get(_META_SCHEMA)
        if want is not None and _schema_digest(pf.schema_arrow, md.num_rows) != want:
            return "corrupt footer (columns or row count differ from its recorded digest)"
        for k in (_META_COUNTS, _META_HIST, _META_PART_TASKS):
            digest = meta.get(k + _DIGEST_SUFFIX)
            if digest is not None and (k not in meta or _digest(meta[k]) != digest):
                return f"corrupt footer (unreadable {k.decode()} metadata: digest mismatch)"
        pages = meta.get(_META_PAGES)
        if pages is not None:
            if _file_pages_digest(path) != pages:
                return "corrupt data pages (digest mismatch)"
        else:       # a file from before page digests: decode every page (checksums if any)
            for _ in pf.iter_batches(batch_size=_VERIFY_BATCH_ROWS, use_threads=False):
                pass
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad bytes
        text = str(exc).strip().splitlines()
        return f"corrupt ({type(exc).__name__}: {text[0] if text else 'unreadable'})"
    return None


def _file_pages_digest(path: Path) -> bytes:
    """BLAKE2b of the bytes of a Parquet file before its footer, read in blocks."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        size = fh.seek(0, os.SEEK_END)
        fh.seek(max(size - 8, 0))
        tail = fh.read(8)
        left = size - 8 - int.from_bytes(tail[:4], "little") if size >= 12 else 0
        fh.seek(0)
        while left > 0:
            block = fh.read(min(left, 1 << 22))
            if not block:
                break
            h.update(block)
            left -= len(block)
    return h.hexdigest().encode("ascii")


#: Rows decoded at a time when a unit's pages are verified (memory: one batch of columns).
_VERIFY_BATCH_ROWS = 1 << 16
#: Sub-directory of results/ where corrupt task files and parts are set aside.
CORRUPT_DIRNAME = "corrupt"


def set_aside(run_dir: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Move a corrupt unit of the store to ``results/corrupt/`` (inside the run); return where.

    Only the holder of the run's lock may call this.  The new name keeps the
    unit's path below ``results/`` (``/`` as ``__``); an earlier file of that
    name is kept (``.1``, ``.2``, ... appended).
    """
    run_dir, path = Path(run_dir), Path(path)
    results = run_dir / RESULTS_DIRNAME
    try:
        rel = path.relative_to(results)
    except ValueError:
        rel = Path(path.name)
    dest_dir = run_subdir(run_dir, RESULTS_DIRNAME, CORRUPT_DIRNAME)
    base = "__".join(rel.parts)
    dest, k = dest_dir / base, 0
    while dest.exists():
        k += 1
        dest = dest_dir / f"{base}.{k}"
    os.replace(path, dest)
    return dest


def verified_task_names(run_dir: str | os.PathLike, wanted: dict[str, str],
                        quarantine: bool = False) -> set[str]:
    """The names among ``wanted`` whose task is stored completely, as the right task.

    Every compacted part and every wanted loose task file is checked whole
    (:func:`unit_problem`: footer, recorded digests, every page's checksum), so
    that a task counted as done here is one every reader can read.

    Parameters
    ----------
    run_dir : path
    wanted : dict
        ``{file name: task key}`` of the tasks to look for.
    quarantine : bool
        Move each corrupt part or task file to ``results/corrupt/``
        (:func:`set_aside`) so that readers stop meeting it and its tasks are
        run again (only the holder of the run's lock may).

    Returns
    -------
    set of str
        Names listed with the expected key by an intact compacted part, or
        whose loose file is an intact task file of the expected key.  Each
        other existing file gets one :class:`StoreWarning` naming it (its tasks
        will be run again).
    """
    run_dir = Path(run_dir)
    d = run_dir / RESULTS_DIRNAME
    good = set()

    def bad(path, problem, what):
        where = ""
        if quarantine:
            where = f"; set aside as {set_aside(run_dir, path)}"
        warnings.warn(f"{path}: {problem}{where}; {what} will be run again", StoreWarning,
                      stacklevel=3)

    for p in _part_files(run_dir):
        tasks, meta = _part_tasks(p)
        problem = meta if tasks is None else unit_problem(p)
        if problem is not None:
            bad(p, problem, "its tasks")
            continue
        good.update(n for n, k, _ in tasks if wanted.get(n) == k)
    for f in _loose_files(run_dir):
        name = f.name
        if name not in wanted or name in good:
            continue
        problem = _task_file_problem(d / name, wanted[name]) or unit_problem(d / name)
        if problem is None:
            good.add(name)
        else:
            bad(d / name, problem, "the task")
    return good


# --------------------------------------------------------------------------
# Reading rows
# --------------------------------------------------------------------------
def _unreadable(path: Path, why: str) -> ValueError:
    """The one-line error of a reader that met a corrupt or unreadable unit of the store.

    ``glaciar simulate`` checks every unit whole before it counts a task as done
    (:func:`verified_task_names`), so the advice holds: it sets the file aside
    and redoes its tasks.
    """
    return ValueError(f"{path}: unreadable task file ({why}); `glaciar simulate` into this run "
                      f"directory sets it aside in {RESULTS_DIRNAME}/{CORRUPT_DIRNAME}/ and "
                      "redoes its tasks")


def _footer_problem(path: Path) -> str | None:
    """Why a unit's footer is not intact (parse, row count, recorded digests), or None.

    Reads and parses the footer only (no data page): what readers check before
    they decode rows, whose pages they then read with checksums verified.
    """
    import pyarrow.parquet as pq

    try:
        md = pq.read_metadata(path)
        meta = md.metadata or {}
        rows = meta.get(_META_ROWS)
        if rows is not None and int(rows) != md.num_rows:
            return f"corrupt footer ({md.num_rows} rows where its metadata records {int(rows)})"
        want = meta.get(_META_SCHEMA)
        if want is not None and _schema_digest(md.schema.to_arrow_schema(), md.num_rows) != want:
            return "corrupt footer (columns or row count differ from its recorded digest)"
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad bytes
        text = str(exc).strip().splitlines()
        return f"{type(exc).__name__}: {text[0] if text else 'unreadable'}"
    return None


def _read_task_file(path: Path, columns):
    problem = _footer_problem(path)
    if problem is not None:
        raise _unreadable(path, problem) from None
    try:
        return pd.read_parquet(path, columns=columns, page_checksum_verification=True)
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad files
        text = str(exc).strip().splitlines()
        raise _unreadable(path, f"{type(exc).__name__}: {text[0] if text else exc!r}") from None


def store_columns(run_dir: str | os.PathLike) -> set[str]:
    """Names of the per-source columns the store's rows have (from one file's schema)."""
    import pyarrow.parquet as pq

    parts, loose = _store_units(run_dir, warn=False)
    first = parts[0] if parts else (loose[0] if loose else None)
    if first is None:
        return set()
    problem = _footer_problem(first)
    if problem is not None:
        raise _unreadable(first, problem)
    return set(pq.read_schema(first).names)


def read_results(run_dir: str | os.PathLike, columns: list[str] | None = None) -> pd.DataFrame:
    """Every per-source row in the store, current or not, as one DataFrame.

    Compacted parts first (sorted by path), then loose task files (sorted by
    name); a task is read once even while both its part and its file exist.
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
    parts, loose = _store_units(run_dir)
    files = parts + loose
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


def _keep_current(df: pd.DataFrame, manifest: dict, run_dir: Path, what: str) -> pd.DataFrame:
    """``df`` restricted by :func:`current_rows_mask`, warning once about what is left out."""
    keep = current_rows_mask(df, manifest)
    if bool(keep.all()):
        return df
    out = df.loc[~keep]
    key_cols = [c for c in (COL_FIELD, COL_Z, COL_MAG, COL_ITERATION) if c in df.columns]
    n_tasks = len(out[key_cols].drop_duplicates())
    n_out = int(out["n"].sum()) if what == "counts" else len(out)
    gone = sorted(set(map(str, out[COL_FIELD])) - set(map(str, manifest["fields"]))) \
        if COL_FIELD in df.columns and manifest.get("fields") is not None else []
    extra = f" (fields no longer listed: {gone})" if gone else ""
    warnings.warn(f"{run_dir}: ignoring {n_out} rows of {n_tasks} task(s) whose field, z, "
                  f"magnitude or iteration the run's configuration no longer lists{extra}",
                  StoreWarning, stacklevel=3)
    return df[keep].reset_index(drop=True)


def read_current_results(run_dir: str | os.PathLike,
                         columns: list[str] | None = None) -> pd.DataFrame:
    """The per-source rows of the tasks the run's manifest lists now.

    The single rule that ``glaciar report`` and ``glaciar fit`` share: rows of
    fields, z or magnitude values, or iterations that the configuration no
    longer lists (a run directory grows and shrinks with its configuration)
    are left out, with one :class:`StoreWarning` saying how many.  The
    manifest's areas cover exactly the fields kept.  Without a manifest
    (a hand-made store) every row counts.  Counts follow the same rule
    (:func:`read_current_counts`).

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
    run_dir = Path(run_dir)
    manifest = read_manifest(run_dir) or {}
    d = run_dir / RESULTS_DIRNAME
    read_cols = None
    if columns is not None:
        have = store_columns(run_dir)
        keys = [c for c in (COL_FIELD, COL_Z, COL_MAG, COL_ITERATION) if c in have]
        read_cols = list(dict.fromkeys(list(columns) + keys))
    rows = _keep_current(read_results(run_dir, columns=read_cols), manifest, run_dir, "rows")
    if rows.empty:
        raise FileNotFoundError(f"{d}: no finished task of the fields and grid the run's "
                                "configuration lists; run `glaciar simulate` first")
    if columns is not None:
        rows = rows[list(columns)]
    return rows


def _unit_tables(run_dir, meta_key: bytes, tag_key: bytes):
    """Per store unit (valid part, or loose task file no part holds): (footer table, tag).

    The table stored under ``meta_key`` (counts or histograms) and the
    covariate or column named under ``tag_key``.  Yields ``None`` for a unit
    without it (a task file written before it) or whose stored table cannot
    be decoded (a :class:`StoreWarning` names the file: the caller falls
    back to the rows).  One footer read per part; task lists are parsed only
    when loose task files exist (to skip those a part already holds).
    """
    def table(path, meta):
        if meta is None or meta_key not in meta:
            return None
        digest = meta.get(meta_key + _DIGEST_SUFFIX)
        if digest is not None and _digest(meta[meta_key]) != digest:
            # Garbled bytes that may still decode: the rows say which file is corrupt.
            warnings.warn(f"{path}: unreadable {meta_key.decode()} metadata (digest mismatch); "
                          "reading rows instead", StoreWarning, stacklevel=4)
            return None
        try:
            return _ipc_table(meta[meta_key]), meta.get(tag_key)
        except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad bytes
            warnings.warn(f"{path}: unreadable {meta_key.decode()} metadata "
                          f"({type(exc).__name__}); reading rows instead", StoreWarning,
                          stacklevel=4)
            return None

    loose_all = _loose_files(run_dir)
    in_parts = set()
    for p, meta, names in _valid_parts(run_dir, True, bool(loose_all)):
        in_parts.update(names or ())
        yield table(p, meta)
    for f in loose_all:
        if f.name in in_parts:
            continue
        meta, _ = _footer(f)
        yield table(f, meta)


def _unit_counts(run_dir):
    """:func:`_unit_tables` of the counts."""
    return _unit_tables(run_dir, _META_COUNTS, _META_COUNTS_MAG)


def _merge_counts(df: pd.DataFrame) -> pd.DataFrame:
    """Counts summed over iterations: one row per (field, z, mag, mag key, depth key)."""
    keys = [c for c in (COL_FIELD, COL_Z, COL_MAG) if c in df.columns] + [COUNT_MAG_KEY,
                                                                          COUNT_DEPTH_KEY]
    return group_sums(df.drop(columns=[COL_ITERATION], errors="ignore"), keys)


def read_current_counts(run_dir: str | os.PathLike, merge_iterations: bool = True):
    """The stored counts of the tasks the run's manifest lists now.

    The same rule as the rows (:func:`current_rows_mask` on the counts'
    identity columns, one :class:`StoreWarning` about what is left out), read
    from footers only (no row data).

    Parameters
    ----------
    run_dir : path
    merge_iterations : bool
        Sum the counts over iterations (and tasks) as units are read, so that
        memory scales with the cells, not the tasks.

    Returns
    -------
    (pandas.DataFrame, str) or None
        The counts (:func:`glaciar.counting.task_counts` columns; without ``iteration`` when
        merged) and the magnitude covariate they are keyed on; ``None`` when
        some task has no counts (a store written before them: read the rows)
        or tasks disagree on the covariate.

    Raises
    ------
    FileNotFoundError
        No task, or none of a listed task.
    """
    got = _read_current_tables(run_dir, _unit_counts(run_dir),
                               _merge_counts if merge_iterations else None, warn=True)
    if got is None:
        return None
    counts, mags = got
    if merge_iterations and counts.attrs.get("n_batches", 1) > 1:
        counts = _merge_counts(counts)
    counts.attrs.pop("n_batches", None)
    return counts, mags.pop().decode("utf-8")


def _read_current_tables(run_dir, units, merge, warn: bool):
    """Footer tables of every unit, restricted to the current tasks and merged per batch.

    Returns ``(DataFrame, {tag})`` (the frame's ``attrs["n_batches"]`` says
    how many merged batches were concatenated) or None when a unit has no
    table or units disagree on the tag.
    """
    import pyarrow as pa

    run_dir = Path(run_dir)
    manifest = read_manifest(run_dir) or {}
    mags, batch, merged = set(), [], []
    n_out, tasks_out, gone = 0, 0, set()
    n_batch = 0

    def flush():
        nonlocal n_out, tasks_out
        df = pa.concat_tables(batch, promote_options="permissive").to_pandas()
        batch.clear()
        keep = current_rows_mask(df, manifest)
        if not bool(keep.all()):
            out = df.loc[~keep]
            n_out += int(out[COUNT_N].sum())
            ids = [c for c in (COL_FIELD, COL_Z, COL_MAG, COL_ITERATION) if c in df.columns]
            tasks_out += len(out[ids].drop_duplicates())
            if COL_FIELD in df.columns and manifest.get("fields") is not None:
                gone.update(set(map(str, out[COL_FIELD])) - set(map(str, manifest["fields"])))
            df = df[keep]
        merged.append(merge(df) if merge is not None else df)

    for unit in units:
        if unit is None:
            return None
        batch.append(unit[0])
        mags.add(unit[1])
        n_batch += unit[0].num_rows
        if n_batch >= 1_000_000:
            flush()
            n_batch = 0
    if batch:
        flush()
    if not merged:
        raise FileNotFoundError(f"{run_dir / RESULTS_DIRNAME}: no finished task files; run "
                                "`glaciar simulate` first")
    if len(mags) != 1 or None in mags:
        return None
    if n_out and warn:
        extra = f" (fields no longer listed: {sorted(gone)})" if gone else ""
        warnings.warn(f"{run_dir}: ignoring {n_out} rows of {tasks_out} task(s) whose field, z, "
                      f"magnitude or iteration the run's configuration no longer lists{extra}",
                      StoreWarning, stacklevel=3)
    out = pd.concat(merged, ignore_index=True)
    if out.empty:
        raise FileNotFoundError(f"{run_dir / RESULTS_DIRNAME}: no finished task of the fields "
                                "and grid the run's configuration lists; run `glaciar simulate` "
                                "first")
    out.attrs["n_batches"] = len(merged)
    return out, mags


def _merge_histograms(df: pd.DataFrame) -> pd.DataFrame:
    """Histograms summed over iterations and nominal magnitudes: per (field, z, m_in key, bin).

    Arrow's hash aggregation (single-threaded: the same order every run), ~2x faster
    than pandas' groupby on these ~1e6-row batches; NaN keys form their own group.
    """
    import pyarrow as pa

    keys = [c for c in (COL_FIELD, COL_Z) if c in df.columns] + [HIST_MIN_KEY, HIST_MOBS_BIN]
    sums = [COUNT_N, COUNT_K_REC, COUNT_K_SEL]
    t = pa.Table.from_pandas(df[keys + sums], preserve_index=False)
    out = t.group_by(keys, use_threads=False).aggregate([(c, "sum") for c in sums])
    names = [c[:-len("_sum")] if c.endswith("_sum") else c for c in out.column_names]
    return out.rename_columns(names).to_pandas()


def read_current_histograms(run_dir: str | os.PathLike):
    """The stored m_obs histograms (:func:`glaciar.counting.task_histogram`) of the current tasks, merged.

    The tasks are those :func:`read_current_counts` keeps (same rule, read
    from footers only, no row data; it warns about the rest, this does not).

    Returns
    -------
    (pandas.DataFrame, str) or None
        Columns ``field`` and ``z`` (when stored), ``m_in_key``, ``mobs_bin``,
        ``n``, ``k_recovered``, ``k_selected``, summed over iterations and
        nominal magnitudes; and the measured-magnitude column they bin.
        ``None`` when some task has no (readable) histograms or tasks disagree
        on the column: read the rows.

    Raises
    ------
    FileNotFoundError
        No task, or none of a listed task.
    """
    got = _read_current_tables(run_dir, _unit_tables(run_dir, _META_HIST, _META_HIST_OBS),
                               _merge_histograms, warn=False)
    if got is None:
        return None
    hist, cols = got
    if hist.attrs.pop("n_batches", 1) > 1:
        hist = _merge_histograms(hist)
    return hist, cols.pop().decode("utf-8")


# --------------------------------------------------------------------------
# Compaction
# --------------------------------------------------------------------------
def _partition_dir(run_dir: Path, field: str, z: float) -> Path:
    return (run_dir / RESULTS_DIRNAME / COMPACT_DIRNAME / f"field={_readable(field)}-"
            f"{_short_hash(str(field), 8)}" / f"z={float(z)!r}")


def write_part(run_dir, field: str, z: float, table, tasks: list, counts: pd.DataFrame | None,
               mag_column: str | None, extra_meta: dict | None = None,
               hist: pd.DataFrame | None = None, obs_column: str | None = None) -> Path:
    """Write one compacted part of (field, z) atomically; return its path.

    Parameters
    ----------
    table : pyarrow.Table
        The tasks' per-source rows.
    tasks : list of [name, key, n_rows]
        The task files it replaces (name, :func:`task_key`, row count).
    counts : pandas.DataFrame or None
        The tasks' :func:`glaciar.counting.task_counts` (None: a part without counts).
    mag_column : str or None
        The covariate the counts are keyed on.
    hist : pandas.DataFrame or None
        The tasks' :func:`glaciar.counting.task_histogram` (None: a part without histograms).
    obs_column : str or None
        The measured-magnitude column the histograms bin.
    """
    meta = {**(extra_meta or {}),
            _META_PART_TASKS: json.dumps(tasks, ensure_ascii=False).encode("utf-8"),
            _META_ROWS: str(table.num_rows).encode()}
    if counts is not None:
        meta[_META_COUNTS] = _ipc_bytes(counts)
        meta[_META_COUNTS_MAG] = mag_column.encode("utf-8")
    if hist is not None:
        meta[_META_HIST] = _ipc_bytes(hist)
        meta[_META_HIST_OBS] = obs_column.encode("utf-8")
    for k in (_META_COUNTS, _META_HIST, _META_PART_TASKS):
        if k in meta:
            meta[k + _DIGEST_SUFFIX] = _digest(meta[k])
    meta[_META_SCHEMA] = _schema_digest(table.schema, table.num_rows)
    data = _parquet_bytes(table.replace_schema_metadata(meta))
    name = "part-" + _short_hash("\n".join(sorted(str(t[1]) for t in tasks)), 16) + ".parquet"
    part_dir = _partition_dir(Path(run_dir), field, float(z))
    run_subdir(run_dir, *part_dir.relative_to(Path(run_dir)).parts)
    path = part_dir / name
    atomic_write_bytes(path, data)
    return path


def compact(run_dir: str | os.PathLike, min_tasks: int = 0) -> int:
    """Merge loose task files into one part per (field, z); return the tasks compacted.

    Only the holder of the run's lock may call this.  Nothing happens when
    fewer than ``min_tasks`` task files are loose.  Per partition: the rows
    of its tasks are concatenated into ``part-<hash of the task keys>.parquet``
    (footer: the task list and the tasks' counts), written to a temporary
    name, fsynced and renamed; then the task files are deleted.  Task files
    that a valid part already lists (a kill after a rename) are deleted;
    task files that fail the footer check are left for resume to redo; task
    files whose footer digests or page checksums fail are set aside in
    ``results/corrupt/`` (:func:`set_aside`), never copied into a part.
    Parts are written with page checksums like task files.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    run_dir = Path(run_dir)
    # Temporary parts of a compaction that was killed (the caller holds the lock).
    for stale in (run_dir / RESULTS_DIRNAME / COMPACT_DIRNAME).glob("field=*/z=*/.part-*.tmp"):
        stale.unlink(missing_ok=True)
    parts, loose = _store_units(run_dir, warn=False)
    for f in set(_loose_files(run_dir)) - set(loose):
        f.unlink(missing_ok=True)            # already in a renamed part: a kill left it behind
    if len(loose) < max(1, int(min_tasks)):
        return 0
    groups: dict = {}
    for f in loose:
        meta, _ = _footer(f)
        if meta is None or _META_TASK not in meta:
            continue
        key = meta[_META_TASK].decode("utf-8")
        if _task_file_problem(f, key) is not None:
            continue
        field, z, _, _ = json.loads(key)
        groups.setdefault((field, z), []).append((f, key, meta))
    n_done = 0
    for (field, z), items in sorted(groups.items()):
        tables, counts, tasks, mags, hists, obs = [], [], [], set(), [], set()
        pandas_meta = {}
        intact = []
        for f, key, meta in items:
            # Pages verified as they are read: a corrupt task file is set aside (and its
            # task redone by the next simulate), never copied into a part.
            problem = _footer_problem(f)
            try:
                t = None if problem else pq.read_table(f, page_checksum_verification=True)
            except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad bytes
                problem = f"corrupt ({type(exc).__name__}: {str(exc).strip()[:200]})"
            if problem is not None:
                warnings.warn(f"{f}: {problem}; set aside as {set_aside(run_dir, f)}; the task "
                              "will be run again", StoreWarning, stacklevel=2)
                continue
            intact.append((f, key, meta))
            if b"pandas" in meta and not pandas_meta:
                pandas_meta = {b"pandas": meta[b"pandas"]}
            tables.append(t.replace_schema_metadata(None))
            tasks.append([f.name, key, t.num_rows])
            for got, tags, mk, tk in ((counts, mags, _META_COUNTS, _META_COUNTS_MAG),
                                      (hists, obs, _META_HIST, _META_HIST_OBS)):
                if mk in meta:
                    try:
                        got.append(_ipc_table(meta[mk]))
                        tags.add(meta.get(tk))
                    except Exception:  # noqa: BLE001 - a file from before digests, garbled:
                        pass           # the part goes without; readers then use the rows
        items = intact
        if not items:
            continue
        table = pa.concat_tables(tables, promote_options="permissive")
        cnt = (pa.concat_tables(counts, promote_options="permissive").to_pandas()
               if counts and len(counts) == len(items) and len(mags) == 1 else None)
        # Histograms kept per task (iteration included), as the counts: readers filter
        # current tasks before summing, and each task is in exactly one unit.
        hst = (pa.concat_tables(hists, promote_options="permissive").to_pandas()
               if hists and len(hists) == len(items) and len(obs) == 1 else None)
        write_part(run_dir, field, float(z), table, tasks, cnt,
                   mags.pop().decode("utf-8") if cnt is not None else None, pandas_meta,
                   hist=hst, obs_column=obs.pop().decode("utf-8") if hst is not None else None)
        for f, _, _ in items:                # only after the part is in place
            f.unlink(missing_ok=True)
        n_done += len(items)
    return n_done


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
