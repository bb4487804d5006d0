"""Results store: an append-only Parquet dataset, one file per finished task.

Layout of a run directory::

    RUN_DIR/config.yaml        the resolved configuration of the run
    RUN_DIR/manifest.json      config hash, seed, bands, glaciar version
    RUN_DIR/results/*.parquet  one file per finished task

Every file is written to a temporary name in the same directory and then
renamed, so an interrupted run never leaves a half-written file behind; a
resumed run skips the tasks whose file exists.
"""
from __future__ import annotations

import json
import os
import re
import tempfile
from pathlib import Path

import pandas as pd

from .constants import MANIFEST_NAME, RESULTS_DIRNAME

__all__ = ["atomic_write_bytes", "atomic_write_text", "task_filename", "write_task_table",
           "finished_task_names", "read_results", "read_manifest", "write_manifest",
           "StoreMismatchError"]


class StoreMismatchError(RuntimeError):
    """The run directory was made with a different configuration."""


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
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


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", str(name))


def task_filename(field: str, z: float, mag: float, iteration: int) -> str:
    """File name (inside ``results/``) of one task's rows.

    Named by values, not grid indices, so that extending the grid of a run
    leaves the names (and the rows) of its finished tasks unchanged.
    """
    return f"task_{_safe(field)}_z{z:+09.4f}_m{mag:+09.4f}_i{iteration:04d}.parquet"


def write_task_table(run_dir: str | os.PathLike, name: str, table: pd.DataFrame) -> Path:
    """Write one task's per-source rows atomically as ``results/<name>``."""
    import io

    path = Path(run_dir) / RESULTS_DIRNAME / name
    buf = io.BytesIO()
    table.to_parquet(buf, index=False)
    atomic_write_bytes(path, buf.getvalue())
    return path


def finished_task_names(run_dir: str | os.PathLike) -> set[str]:
    """Names of the task files already written (temporary files excluded)."""
    d = Path(run_dir) / RESULTS_DIRNAME
    if not d.is_dir():
        return set()
    return {p.name for p in d.glob("task_*.parquet")}


def read_results(run_dir: str | os.PathLike, columns: list[str] | None = None) -> pd.DataFrame:
    """All per-source rows of a run as one DataFrame (sorted by task, then source).

    Raises
    ------
    FileNotFoundError
        If the run directory holds no finished task.
    """
    d = Path(run_dir) / RESULTS_DIRNAME
    files = sorted(d.glob("task_*.parquet")) if d.is_dir() else []
    if not files:
        raise FileNotFoundError(f"{d}: no finished task files (task_*.parquet); "
                                "run `glaciar simulate` first")
    frames = [pd.read_parquet(f, columns=columns) for f in files]
    return pd.concat(frames, ignore_index=True)


def read_manifest(run_dir: str | os.PathLike) -> dict | None:
    """The run's manifest, or None if there is none yet."""
    p = Path(run_dir) / MANIFEST_NAME
    if not p.exists():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise StoreMismatchError(f"{p}: not valid JSON ({exc})") from exc


def write_manifest(run_dir: str | os.PathLike, manifest: dict) -> None:
    """Write the manifest atomically."""
    atomic_write_text(Path(run_dir) / MANIFEST_NAME, json.dumps(manifest, indent=2, sort_keys=True))
