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
renamed (:func:`glaciar.rundir.atomic_write_bytes`), so an interrupted run never leaves a
half-written file behind; a
resumed run skips the tasks whose file exists and is an intact Parquet file
of the right task (:func:`verified_task_names`).  Task files and parts are
written with Parquet page checksums and footer digests of their pages, columns
and row count, and footer tables (:func:`unit_problem`): a corrupt one is set
aside and redone, and readers name it.

Task files are named by :func:`task_filename`: a readable part plus a hash of
the exact task key (field name, z and magnitude as ``repr(float)``,
iteration), so two different tasks never share a file.  Which rows count is
decided in one place, :func:`read_current_results`: the rows of the fields,
grid values and iterations that the run's manifest lists now.  The manifest, the
lock, input fingerprints and atomic writes are :mod:`glaciar.rundir`'s.
"""
from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .constants import COL_FIELD, COL_ITERATION, COL_MAG, COL_Z, RESULTS_DIRNAME
from .counting import (COUNT_DEPTH_KEY, COUNT_K_REC, COUNT_K_SEL, COUNT_MAG_KEY, COUNT_N, HIST_MIN_KEY,
                       HIST_MOBS_BIN, group_sums, has_hist_columns, task_count_arrays,
                       task_counts, task_histogram, task_histogram_arrays)
from .paths import readable, run_subdir
from .rundir import atomic_write_bytes, read_manifest
from .taskfile import (DIGEST_SUFFIX, META_COUNTS, META_COUNTS_MAG, META_HIST, META_HIST_OBS,
                       META_PART_TASKS, META_ROWS, META_SCHEMA, META_TASK, arrow_table,
                       blake2b_digest, footer_metadata, ipc_bytes, ipc_table, parquet_bytes,
                       schema_digest, task_file_problem, unit_problem)

if TYPE_CHECKING:   # the readers import it; a run's tasks write their files without it
    import pandas as pd

__all__ = ["task_key", "task_filename", "field_file_prefix", "write_task_table",
           "finished_task_names", "verified_task_names", "read_results", "read_current_results",
           "StoreWarning", "read_current_counts", "store_columns", "write_part", "compact",
           "COMPACT_EVERY", "read_current_histograms", "set_aside", "CORRUPT_DIRNAME"]

#: Characters of the field name kept in the readable part of a task file name.
_READABLE_FIELD_CHARS = 40
#: Sub-directory of results/ holding the compacted parts.
COMPACT_DIRNAME = "compact"
#: Compact when at least this many task files are loose (end of simulate, and during a run).
COMPACT_EVERY = 1024


class StoreWarning(UserWarning):
    """Something in a run directory is ignored or redone (stale rows, a corrupt task file)."""


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


def write_task_table(run_dir: str | os.PathLike, name: str, table,
                     key: str | None = None, mag_column: str | None = None,
                     obs_column: str | None = None) -> Path:
    """Write one task's per-source rows atomically as ``results/<name>``.

    ``table``: a DataFrame, or its columns as a dict of arrays
    (:func:`glaciar.engine.task.task_columns`; the same file, written without pandas).

    ``key`` (:func:`task_key`) and the row count are stored in the file's
    metadata, so that :func:`verified_task_names` can tell a complete file of
    the right task from a truncated or foreign one without reading the rows.
    With ``mag_column`` (the fit's magnitude covariate, ``mag_input`` or
    ``M_uv``), the task's :func:`glaciar.counting.task_counts` are stored in the footer too;
    with ``obs_column`` (the measured detection-band magnitude) its
    :func:`glaciar.counting.task_histogram` as well (when the table has that column and
    ``mag_input``).
    """
    path = Path(run_dir) / RESULTS_DIRNAME / name
    t = arrow_table(table)
    meta = dict(t.schema.metadata or {})
    meta[META_ROWS] = str(t.num_rows).encode()
    if key is not None:
        meta[META_TASK] = key.encode("utf-8")
    if mag_column is not None:
        meta[META_COUNTS] = ipc_bytes(task_count_arrays(table, mag_column))
        meta[META_COUNTS_MAG] = mag_column.encode("utf-8")
    if obs_column is not None and has_hist_columns(getattr(table, "columns", table), obs_column):
        meta[META_HIST] = ipc_bytes(task_histogram_arrays(table, obs_column))
        meta[META_HIST_OBS] = obs_column.encode("utf-8")
    for k in (META_COUNTS, META_HIST):
        if k in meta:
            meta[k + DIGEST_SUFFIX] = blake2b_digest(meta[k])
    meta[META_SCHEMA] = schema_digest(t.schema, t.num_rows)
    # Plain pages, no statistics: a task's rows hold mostly distinct values (parquet_bytes).
    data = parquet_bytes(t.replace_schema_metadata(meta), small=True)
    atomic_write_bytes(run_subdir(run_dir, RESULTS_DIRNAME) / name, data)
    return path


# --------------------------------------------------------------------------
# Units of the store: loose task files and compacted parts
# --------------------------------------------------------------------------
def _loose_files(run_dir) -> list[Path]:
    d = Path(run_dir) / RESULTS_DIRNAME
    return sorted(d.glob("task_*.parquet")) if d.is_dir() else []


def _part_files(run_dir) -> list[Path]:
    d = Path(run_dir) / RESULTS_DIRNAME / COMPACT_DIRNAME
    return sorted(d.glob("field=*/z=*/part-*.parquet")) if d.is_dir() else []


def _part_tasks(path: Path, meta: dict | None = None):
    """([(name, key, n_rows)], footer) of a compacted part, or (None, why not)."""
    if meta is None:
        meta, problem = footer_metadata(path)
        if meta is None:
            return None, problem
    if META_PART_TASKS not in meta:
        return None, "not a glaciar part (no task list in its metadata)"
    try:
        tasks = [(str(n), str(k), int(r)) for n, k, r in json.loads(meta[META_PART_TASKS])]
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
        meta, problem = footer_metadata(p)
        if meta is not None and META_PART_TASKS not in meta:
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
        problem = task_file_problem(d / name, wanted[name]) or unit_problem(d / name)
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
        rows = meta.get(META_ROWS)
        if rows is not None and int(rows) != md.num_rows:
            return f"corrupt footer ({md.num_rows} rows where its metadata records {int(rows)})"
        want = meta.get(META_SCHEMA)
        if want is not None and schema_digest(md.schema.to_arrow_schema(), md.num_rows) != want:
            return "corrupt footer (columns or row count differ from its recorded digest)"
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad bytes
        text = str(exc).strip().splitlines()
        return f"{type(exc).__name__}: {text[0] if text else 'unreadable'}"
    return None


def _read_task_file(path: Path, columns):
    problem = _footer_problem(path)
    if problem is not None:
        raise _unreadable(path, problem) from None
    import pandas as pd

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
    import pandas as pd

    frames = [_read_task_file(f, columns) for f in files]
    return pd.concat(frames, ignore_index=True)


def current_rows_mask(rows: pd.DataFrame, manifest: dict) -> "pd.Series":
    """True for rows of a field, z, magnitude and iteration that ``manifest`` lists.

    Grid values are compared exactly (the manifest stores them as JSON floats,
    which round-trip).  A manifest key or a row column that is absent does not
    restrict.
    """
    import pandas as pd

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
        digest = meta.get(meta_key + DIGEST_SUFFIX)
        if digest is not None and blake2b_digest(meta[meta_key]) != digest:
            # Garbled bytes that may still decode: the rows say which file is corrupt.
            warnings.warn(f"{path}: unreadable {meta_key.decode()} metadata (digest mismatch); "
                          "reading rows instead", StoreWarning, stacklevel=4)
            return None
        try:
            return ipc_table(meta[meta_key]), meta.get(tag_key)
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
        meta, _ = footer_metadata(f)
        yield table(f, meta)


def _unit_counts(run_dir):
    """:func:`_unit_tables` of the counts."""
    return _unit_tables(run_dir, META_COUNTS, META_COUNTS_MAG)


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
    import pandas as pd
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
    got = _read_current_tables(run_dir, _unit_tables(run_dir, META_HIST, META_HIST_OBS),
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


def write_part(run_dir, field: str, z: float, table, tasks: list, counts,
               mag_column: str | None, extra_meta: dict | None = None,
               hist=None, obs_column: str | None = None,
               tag: str | None = None) -> Path:
    """Write one compacted part of (field, z) atomically; return its path.

    Parameters
    ----------
    table : pyarrow.Table
        The tasks' per-source rows.
    tasks : list of [name, key, n_rows]
        The task files it replaces (name, :func:`task_key`, row count).
    counts : pandas.DataFrame, pyarrow.Table or None
        The tasks' :func:`glaciar.counting.task_counts` (None: a part without counts).
    mag_column : str or None
        The covariate the counts are keyed on.
    hist : pandas.DataFrame, pyarrow.Table or None
        The tasks' :func:`glaciar.counting.task_histogram` (None: a part without histograms).
    obs_column : str or None
        The measured-magnitude column the histograms bin.
    tag : str, optional
        Put in the part's name (``part-<tag>-<hash>.parquet``): a shard's parts and their
        temporaries are told from its siblings' by it (:func:`compact`).
    """
    meta = {**(extra_meta or {}),
            META_PART_TASKS: json.dumps(tasks, ensure_ascii=False).encode("utf-8"),
            META_ROWS: str(table.num_rows).encode()}
    if counts is not None:
        meta[META_COUNTS] = ipc_bytes(counts)
        meta[META_COUNTS_MAG] = mag_column.encode("utf-8")
    if hist is not None:
        meta[META_HIST] = ipc_bytes(hist)
        meta[META_HIST_OBS] = obs_column.encode("utf-8")
    for k in (META_COUNTS, META_HIST, META_PART_TASKS):
        if k in meta:
            meta[k + DIGEST_SUFFIX] = blake2b_digest(meta[k])
    meta[META_SCHEMA] = schema_digest(table.schema, table.num_rows)
    data = parquet_bytes(table.replace_schema_metadata(meta))
    name = ("part-" + (f"{tag}-" if tag else "")
            + _short_hash("\n".join(sorted(str(t[1]) for t in tasks)), 16) + ".parquet")
    part_dir = _partition_dir(Path(run_dir), field, float(z))
    run_subdir(run_dir, *part_dir.relative_to(Path(run_dir)).parts)
    path = part_dir / name
    atomic_write_bytes(path, data)
    return path


def _footer_tables(tables: list):
    """The tasks' footer tables (counts or histograms) of a part, concatenated.

    One Arrow table when they share a schema (every task of a run: no pandas, which a
    compaction in the middle of a one-worker run would otherwise import for good; the same
    table in the part's footer, written as one batch where the DataFrame's text column kept
    one chunk per task: ~18x fewer bytes); otherwise (files of another version, missing
    columns promoted to nulls) the DataFrame, as before.
    """
    import pyarrow as pa

    t = pa.concat_tables(tables, promote_options="permissive")
    if all(x.schema.equals(tables[0].schema) for x in tables[1:]):
        return t.combine_chunks()
    return t.to_pandas()


def compact(run_dir: str | os.PathLike, min_tasks: int = 0, tasks=None,
            tag: str | None = None) -> int:
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

    A shard of a run (:mod:`glaciar.shards`) passes ``tasks``, the file names of its
    own tasks, and ``tag`` (e.g. ``s2``): it compacts, deletes and sets aside only its own
    task files, names its parts ``part-<tag>-...`` and removes only its own stale part
    temporaries, so that it never touches a file a sibling shard is writing.  Each task
    is in one shard, so its loose file and its part are written by one process, and
    readers see it once (:func:`_store_units`).  Without them (an unsharded run, which
    excludes every shard): every loose file and stale temporary.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    run_dir = Path(run_dir)
    # Temporary parts of a compaction that was killed (the caller holds the lock).
    stale_pattern = "field=*/z=*/.part-*.tmp" if not tag else f"field=*/z=*/.part-{tag}-*.tmp"
    for stale in (run_dir / RESULTS_DIRNAME / COMPACT_DIRNAME).glob(stale_pattern):
        stale.unlink(missing_ok=True)
    # Listed before the units: a file listed here and not loose there is in a part.  (A
    # second listing after them would also hold task files written meanwhile -- by this
    # run's pool workers, or a sibling shard -- which no part holds yet.)
    listed = set(_loose_files(run_dir))
    parts, loose = _store_units(run_dir, warn=False)
    own = set(tasks) if tasks is not None else None
    for f in listed - set(loose):
        if own is None or f.name in own:
            f.unlink(missing_ok=True)        # already in a renamed part: a kill left it behind
    if own is not None:
        loose = [f for f in loose if f.name in own]
    if len(loose) < max(1, int(min_tasks)):
        return 0
    groups: dict = {}
    for f in loose:
        meta, _ = footer_metadata(f)
        if meta is None or META_TASK not in meta:
            continue
        key = meta[META_TASK].decode("utf-8")
        if task_file_problem(f, key) is not None:
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
                # (ParquetFile, not read_table: its dataset layer imports pandas)
                t = None if problem else pq.ParquetFile(f, page_checksum_verification=True).read()
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
            for got, tags, mk, tk in ((counts, mags, META_COUNTS, META_COUNTS_MAG),
                                      (hists, obs, META_HIST, META_HIST_OBS)):
                if mk in meta:
                    try:
                        got.append(ipc_table(meta[mk]))
                        tags.add(meta.get(tk))
                    except Exception:  # noqa: BLE001 - a file from before digests, garbled:
                        pass           # the part goes without; readers then use the rows
        items = intact
        if not items:
            continue
        table = pa.concat_tables(tables, promote_options="permissive")
        cnt = (_footer_tables(counts)
               if counts and len(counts) == len(items) and len(mags) == 1 else None)
        # Histograms kept per task (iteration included), as the counts: readers filter
        # current tasks before summing, and each task is in exactly one unit.
        hst = (_footer_tables(hists)
               if hists and len(hists) == len(items) and len(obs) == 1 else None)
        write_part(run_dir, field, float(z), table, tasks, cnt,
                   mags.pop().decode("utf-8") if cnt is not None else None, pandas_meta,
                   hist=hst, obs_column=obs.pop().decode("utf-8") if hst is not None else None,
                   tag=tag)
        for f, _, _ in items:                # only after the part is in place
            f.unlink(missing_ok=True)
        n_done += len(items)
    return n_done
