"""Field contexts on disk: measured arrays as ``.npy`` files that workers memory-map.

A field's context (:class:`glaciar.engine.context.FieldContext`) holds full-frame
arrays -- background-subtracted images and RMS maps of every band, masks, the
local depth map, the reference segmentation -- about 45 bytes per pixel for 4
bands, 11 GB on a 16000² mosaic.  The process that measures the field writes
its measured part once (:func:`save`) as a directory of native-endian ``.npy``
files plus a JSON description of how they nest (dataclasses, dicts, tuples,
scalars); no pickle.  Workers open it (:func:`load`): arrays of at least
:data:`MMAP_MIN_BYTES` are read-only memory maps (pages read on first touch
and shared between processes through the page cache), smaller ones are read
into memory.  A task reads windows of the maps, so what it costs in memory is
the pages under its windows.

Mapped pages count in a process's resident set while mapped and would
accumulate over a long run until the whole files were resident;
:func:`trim` drops them (``madvise(MADV_DONTNEED)``: the page cache keeps
them, the next touch is a minor fault) once more than
:data:`RESIDENT_BUDGET_BYTES` of file-backed pages have accumulated.

The directory is written under a temporary name and renamed into place, so a
reader sees a complete cache or none; when two processes write the same cache,
the first rename wins and the other copy is removed.
"""
from __future__ import annotations

import dataclasses
import importlib
import json
import mmap
import os
import shutil
import tempfile
import threading
import weakref
from pathlib import Path

import numpy as np

__all__ = ["save", "load", "exists", "release", "Trimmer", "trim", "FORMAT", "MMAP_MIN_BYTES",
           "RESIDENT_BUDGET_BYTES"]

#: Version of the on-disk layout (part of a cache's key: a new layout never reads an old one).
FORMAT = 1
#: Arrays at least this large [bytes] are memory-mapped; smaller ones (catalogues) are read.
MMAP_MIN_BYTES = 1 << 20
#: File-backed resident pages [bytes] a worker lets accumulate before they are dropped: with
#: ~300 MB of code and working memory a worker stays near 1.1 GB (target: 2 GB on 16000^2),
#: while a 4000^2 4-band field (~0.9 GB of maps) is seldom trimmed (each trim costs refaults).
RESIDENT_BUDGET_BYTES = 768 << 20
#: Name of the JSON description inside a cache directory.
INDEX_NAME = "index.json"

#: Classes a cache may rebuild (by "module:qualname"); nothing else is instantiated on load.
_CLASSES = frozenset({
    "glaciar.engine.measure:FieldReference",
    "glaciar.engine.segmentation:Segmentation",
    "glaciar.engine.clean:CleanObjects",
    "glaciar.engine.windows:ObjectBoxes",
    "glaciar.engine.noise:CorrelatedNoise",
})


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------
def _encode(obj, directory: Path, names: list) -> dict:
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            raise TypeError(f"field cache: arrays of Python objects are not stored (dtype {obj.dtype})")
        name = f"a{len(names):04d}.npy"
        names.append(name)
        dtype = obj.dtype if obj.dtype.isnative else obj.dtype.newbyteorder("=")
        out = np.lib.format.open_memmap(directory / name, mode="w+", dtype=dtype, shape=obj.shape)
        if obj.size:
            out[...] = obj
        out.flush()
        del out
        return {"npy": name}
    if isinstance(obj, np.generic):
        return {"value": obj.item()}
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return {"value": obj}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        cls = type(obj)
        qual = f"{cls.__module__}:{cls.__qualname__}"
        if qual not in _CLASSES:
            raise TypeError(f"field cache: {qual} is not a class it stores")
        # Fields starting with "_" are lazily built caches (e.g. a k-d tree): rebuilt on use.
        return {"dataclass": qual, "fields": {f.name: _encode(getattr(obj, f.name), directory, names)
                                              for f in dataclasses.fields(obj)
                                              if not f.name.startswith("_")}}
    if isinstance(obj, dict):
        if not all(isinstance(k, str) for k in obj):
            raise TypeError("field cache: dict keys must be strings")
        return {"dict": {k: _encode(v, directory, names) for k, v in obj.items()}}
    if isinstance(obj, (tuple, list)):
        return {type(obj).__name__: [_encode(v, directory, names) for v in obj]}
    raise TypeError(f"field cache: cannot store a {type(obj).__name__}")


def save(items: dict, directory) -> Path:
    """Write ``items`` (str -> arrays, scalars, dicts, tuples, known dataclasses) to ``directory``.

    Written to a temporary sibling and renamed: an existing ``directory`` (another
    process was faster) is kept and the new copy removed.  Returns ``directory``.
    """
    directory = Path(directory)
    directory.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{directory.name}.", suffix=".tmp", dir=directory.parent))
    try:
        names: list = []
        index = {"format": FORMAT, "items": _encode(dict(items), tmp, names)}
        (tmp / INDEX_NAME).write_text(json.dumps(index, indent=1, allow_nan=True), encoding="utf-8")
        os.chmod(tmp, 0o755)
        try:
            os.rename(tmp, directory)
        except OSError:
            if not (directory / INDEX_NAME).is_file():
                raise
            shutil.rmtree(tmp, ignore_errors=True)      # the same cache is already there
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return directory


# --------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------
def _decode(node: dict, directory: Path, maps: list):
    if "npy" in node:
        path = directory / node["npy"]
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
        if arr.nbytes >= MMAP_MIN_BYTES and isinstance(arr, np.memmap):
            maps.append(arr._mmap)
            return arr
        return np.array(arr)           # small: a private in-memory copy, the map closed
    if "value" in node:
        return node["value"]
    if "dataclass" in node:
        qual = node["dataclass"]
        if qual not in _CLASSES:
            raise ValueError(f"{directory / INDEX_NAME}: unknown class {qual!r}")
        module, name = qual.split(":")
        cls = getattr(importlib.import_module(module), name)
        return cls(**{k: _decode(v, directory, maps) for k, v in node["fields"].items()})
    if "dict" in node:
        return {k: _decode(v, directory, maps) for k, v in node["dict"].items()}
    if "tuple" in node:
        return tuple(_decode(v, directory, maps) for v in node["tuple"])
    if "list" in node:
        return [_decode(v, directory, maps) for v in node["list"]]
    raise ValueError(f"{directory / INDEX_NAME}: unreadable entry {sorted(node)}")


def load(directory) -> tuple[dict, tuple]:
    """Open a cache written by :func:`save`: ``(items, maps)``.

    ``maps``: the ``mmap`` objects behind the memory-mapped arrays (for
    :func:`trim` / :func:`release`).
    """
    directory = Path(directory)
    index = json.loads((directory / INDEX_NAME).read_text(encoding="utf-8"))
    if index.get("format") != FORMAT:
        raise ValueError(f"{directory / INDEX_NAME}: field cache format {index.get('format')!r}, "
                         f"expected {FORMAT}")
    maps: list = []
    items = _decode(index["items"], directory, maps)
    return items, tuple(maps)


def exists(directory) -> bool:
    """A complete cache is at ``directory``."""
    return (Path(directory) / INDEX_NAME).is_file()


# --------------------------------------------------------------------------
# Resident pages
# --------------------------------------------------------------------------
_PAGE = mmap.PAGESIZE
_STATM = "/proc/self/statm"


def _file_resident_bytes() -> int | None:
    """Resident shared (file-backed) bytes of this process, or None where unknown."""
    try:
        with open(_STATM, "rb") as fh:
            return int(fh.read().split()[2]) * _PAGE
    except (OSError, IndexError, ValueError):
        return None


def release(maps) -> None:
    """Drop the resident pages of ``maps`` from this process (they stay in the page cache)."""
    advice = getattr(mmap, "MADV_DONTNEED", None)
    if advice is None:          # pragma: no cover - platforms without madvise
        return
    for m in maps:
        try:
            m.madvise(advice)
        except (OSError, ValueError):       # closed map
            pass


class Trimmer:
    """Calls :func:`release` when file-backed resident pages grew by more than a budget.

    The baseline is the resident size when the maps were opened or last
    released (shared libraries' pages are file-backed too).  Where the resident
    size cannot be read, every call releases.

    A task on a large mosaic can touch more than the budget by itself: each
    window row faults in a whole 64 kB block ("fault-around"), a full image row
    at 16000 pixels of float32.  When the maps are larger than the budget,
    :meth:`watch` also checks from a daemon thread every ``period`` seconds, so
    that the resident set stays bounded during a task (dropping pages under a
    reader is safe: read-only file pages are read again on the next touch).
    """

    def __init__(self, maps, budget: int | None = None, period: float = 0.01):
        self.maps = tuple(maps)
        self.budget = int(RESIDENT_BUDGET_BYTES if budget is None else budget)
        self.period = float(period)
        self.mapped = sum(len(m) for m in self.maps)
        self.baseline = _file_resident_bytes()
        self.releases = 0
        self._pid = os.getpid()
        self._lock = threading.Lock()
        self._watcher: tuple | None = None          # (pid, thread, stop event)

    def _forked(self) -> None:
        """In a child forked after the maps were opened: its own lock and baseline."""
        if os.getpid() != self._pid:
            self._pid = os.getpid()
            self._lock = threading.Lock()           # a lock copied by fork may be held
            self._watcher = None                    # threads do not survive a fork
            self.baseline = _file_resident_bytes()

    def __call__(self) -> bool:
        if not self.maps:
            return False
        self._forked()
        with self._lock:
            now = _file_resident_bytes()
            if now is not None and self.baseline is not None and now - self.baseline <= self.budget:
                return False
            release(self.maps)
            self.releases += 1
            self.baseline = _file_resident_bytes()      # libraries' pages grow too: re-based here
            return True

    def watch(self) -> bool:
        """Start the checking thread in this process (a forked child starts its own) when the
        maps exceed the budget; True if one runs.  :meth:`unwatch` stops it."""
        if self.mapped <= self.budget or _file_resident_bytes() is None:
            return False
        self._forked()
        pid = os.getpid()
        if self._watcher is not None and self._watcher[1].is_alive():
            return True
        stop = threading.Event()
        thread = threading.Thread(target=_watch, args=(weakref.ref(self), stop, self.period),
                                  daemon=True, name="glaciar-fieldcache-trim")
        self._watcher = (pid, thread, stop)
        thread.start()
        return True

    def unwatch(self) -> None:
        """Stop this process's checking thread (if any)."""
        if self._watcher is not None and self._watcher[0] == os.getpid():
            self._watcher[2].set()
            self._watcher[1].join()
        self._watcher = None


def _watch(ref, stop: threading.Event, period: float) -> None:
    while not stop.wait(period):
        trimmer = ref()
        if trimmer is None:             # the context is gone
            return
        trimmer()
        del trimmer


def trim(ctx, watch: bool | None = None) -> bool:
    """Drop a context's mapped pages if more than the budget accumulated (True if it did).

    ``watch``: True starts this process's checking thread (:meth:`Trimmer.watch`) for the
    tasks that follow, False stops it, None leaves it as it is.
    """
    trimmer = getattr(ctx, "_trimmer", None)
    if trimmer is None:
        return False
    if watch is True:
        trimmer.watch()
    elif watch is False:
        trimmer.unwatch()
    return trimmer()
