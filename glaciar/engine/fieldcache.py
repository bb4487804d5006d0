"""Field contexts on disk: measured arrays as ``.npy`` files that workers map or read by window.

A field's context (:class:`glaciar.engine.context.FieldContext`) holds full-frame
arrays -- background-subtracted images and RMS maps of every band, masks, the
local depth map, the reference segmentation -- about 45 bytes per pixel for 4
bands, 11 GB on a 16000² mosaic.  The process that measures the field writes
its measured part once (:func:`save`) as a directory of native-endian ``.npy``
files plus a JSON description of how they nest (dataclasses, dicts, tuples,
scalars); no pickle.  Workers open it (:func:`load`): arrays of at least
:data:`MMAP_MIN_BYTES` are read-only memory maps (pages read on first touch
and shared between processes through the page cache), smaller ones are read
into memory, tiled ones (below) are read by window from the file.  A task
reads windows of the maps, so what it costs in memory is the pages under its
windows.

Mapped pages count in a process's resident set while mapped and would
accumulate over a long run until the whole files were resident;
:func:`trim` drops them (``madvise(MADV_DONTNEED)``: the page cache keeps
them, the next touch is a minor fault) once more than
:data:`RESIDENT_BUDGET_BYTES` of file-backed pages have accumulated.

On a field whose maps exceed that budget, glaciar.contexts stores the images the
engine reads by window (images, RMS maps, mask, reference segmentation) as
square tiles (:class:`Tiled` on writing, :class:`TiledArray` on reading: a 4-d
``.npy`` ``[ty, tx, 64, 64]``), and workers read them with positional reads
(``os.preadv``, one per row of tiles under a window) into private memory,
not through a memory map.  Why: the page cache holds a file in large folios
(Linux 6.x: up to 2 MB), and a fault on a mapped file maps the whole folio
into the process -- measured on an 8000^2 field, a task's windows (~14 per
source, 10-150 px) made ~1 GB of maps resident, 85-550 times the bytes they
read, so that a worker under the budget dropped its pages every ~20 sources
and faulted them in again (1.41-1.94x the task CPU per source of a 1000^2
field at 16000^2, much of it system time).  A positional read copies the
bytes of the tile rows it needs: the resident set does not grow with the
windows read, nothing is dropped, and the tile size (not the folio size) sets
the granularity.  Task CPU per source on an 8000^2 demo field with a 192 MB
budget (the 16000^2 pressure scaled by area; scratch harness, 20 tasks x 100
sources, medians of 3-12 alternating rounds on a loaded machine): 1.26 ms with
tiles read, 1.33 ms from mapped 128 px tiles the budget dropped, 0.99 ms with
every array in memory (1000^2: 0.96 ms): what is left is the cost of ~14
window reads per source (~10 us each against 2 us from memory).  Reads that
miss the page cache go to disk whichever way the file is read: on an 8000^2
cache whose pages were evicted, ~750 kB read per source and 0.6-0.8 ms of
system CPU per source (POSIX_FADV_RANDOM made no difference); a 16000^2 run
right after its set-up (13 GB peak on a 24 GB machine) starts that way.
Small fields stay row-major and mapped (their pages stay resident, a plain
slice is cheapest).

:func:`spill` moves a finished array of a field being measured to an unnamed
temporary file (memory-mapped), so that measuring a large field does not
hold the whole context in memory.

The directory is written under a temporary name and renamed into place, so a
reader sees a complete cache or none; when two processes write the same cache,
the first rename wins and the other copy is removed.
"""
from __future__ import annotations

import atexit
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

__all__ = ["save", "load", "exists", "UnreadableCache", "release", "Trimmer", "trim", "TiledArray", "Tiled", "spill", "FORMAT",
           "MMAP_MIN_BYTES", "RESIDENT_BUDGET_BYTES", "TILE"]

#: Version of the on-disk layout and of what it holds (part of a cache's key: a new layout
#: never reads an old one). 2: r(N) measured about local backgrounds where the mesh leaves
#: residuals (issue 21), so a cache holding the mesh-only r(N) is not reused.  3: the
#: reference's ObjectBoxes live in glaciar.engine.canvas (issue 22), the name a cache stores.
#: 4: the reference holds no segmentation product (task-wide CLEAN runs full frame, issue 22).
FORMAT = 4
#: Arrays at least this large [bytes] are memory-mapped; smaller ones (catalogues) are read.
MMAP_MIN_BYTES = 1 << 20
#: File-backed resident pages [bytes] a worker lets accumulate before they are dropped: with
#: ~300 MB of code and working memory a worker stays near 1.1 GB (target: 2 GB on 16000^2),
#: while a 4000^2 4-band field (~0.9 GB of maps) is seldom trimmed (each trim costs refaults).
RESIDENT_BUDGET_BYTES = 768 << 20
#: Store the windowed images of a field larger than the resident budget as tiles
#: (glaciar.contexts' field cache); False keeps every array row-major (for comparisons).
TILED_CACHE = True
#: Side [pixels] of the square tiles of a tiled 2-d array (:class:`TiledArray`): a window
#: reads the rows it needs of the tiles under it (16 kB per float32 tile, 4 kB per bool one).
#: Task CPU per source on an 8000^2 field (scratch harness, alternating rounds): 32 and 64
#: the same within the noise, 128 ~20 % more (a window copies more bytes of wider tiles).
TILE = 64
#: Tiles start at a multiple of this file offset [bytes] (the .npy header is padded to it):
#: page-aligned tiles for the memory-mapped fallback (no ``os.preadv``).
TILE_ALIGN = 1 << 16
#: Read tiled arrays with positional reads (:meth:`TiledArray.open`) rather than through a
#: memory map (False, or a platform without ``os.preadv``: mapped, pages trimmed by budget).
READ_TILES = hasattr(os, "preadv")
#: Largest .npy header np.load is allowed to read for a tiled file (its padding included).
_MAX_HEADER = 1 << 17
#: Rows copied at a time [bytes] when a cache array is written (mapped pages dropped after each).
COPY_BLOCK_BYTES = 64 << 20
#: Directory of :func:`spill`'s temporary files (None: the system temp directory).
SCRATCH_DIR = None
#: Name of the JSON description inside a cache directory.
INDEX_NAME = "index.json"

#: Classes a cache may rebuild (by "module:qualname"); nothing else is instantiated on load.
_CLASSES = frozenset({
    "glaciar.engine.measure:FieldReference",
    "glaciar.engine.canvas:ObjectBoxes",
    "glaciar.engine.noise:CorrelatedNoise",
})


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------
def _maps_of(*arrays) -> list:
    """The mmap objects behind memory-mapped arrays (views of np.load/np.memmap maps)."""
    out = []
    for a in arrays:
        while a is not None:
            m = getattr(a, "_mmap", None)
            if m is not None:
                out.append(m)
                break
            a = getattr(a, "base", None)
    return out


def _copy_rows(src: np.ndarray, out: np.ndarray) -> None:
    """``out[...] = src`` by blocks of rows (~:data:`COPY_BLOCK_BYTES`), dropping the mapped
    pages of both after each block: copying a mapped 16000^2 image does not make it resident."""
    if not src.size:
        getattr(out, "flush", lambda: None)()     # an empty array is not mapped
        return
    if src.ndim == 0:
        out[...] = src
        out.flush()
        return
    row = max(1, src[0].nbytes if src.ndim > 1 else src.itemsize)
    step = max(1, COPY_BLOCK_BYTES // row)
    maps = _maps_of(src, out)
    for i in range(0, src.shape[0], step):
        out[i:i + step] = src[i:i + step]
        if maps:
            out.flush()
            release(maps)
    out.flush()


def _allocated_npy(path, dtype, shape) -> np.memmap:
    """A new ``.npy`` at ``path`` opened as a writable memory map, its blocks allocated first.

    ``np.lib.format.open_memmap(mode="w+")`` makes a sparse file and maps it: on a
    full disk the first write to a page without a block kills the process with
    ``SIGBUS``.  Here the header is written and the data's blocks reserved
    (:func:`glaciar.paths.allocate`) before the map exists, so a full disk is a
    :class:`glaciar.paths.DiskFullError` naming ``path``.  Same bytes as
    ``open_memmap`` (format 1.0 header, or 2.0 when it does not fit).
    """
    from ..paths import allocate, disk_full

    dtype = np.dtype(dtype)
    shape = tuple(int(n) for n in shape)
    header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
              "shape": shape}
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    try:
        with open(path, "wb") as fh:
            try:
                np.lib.format.write_array_header_1_0(fh, header)
            except ValueError:                     # header too long for format 1.0
                fh.seek(0)
                fh.truncate()
                np.lib.format.write_array_header_2_0(fh, header)
            offset = fh.tell()
            allocate(fh.fileno(), offset + nbytes, path)
            if nbytes == 0:
                return np.zeros(shape, dtype)      # nothing to map (np.memmap refuses 0 bytes)
        return np.memmap(path, dtype=dtype, mode="r+", offset=offset, shape=shape)
    except OSError as exc:
        full = disk_full(path, exc)
        if full is not None:
            raise full from None
        raise


def spill(arr: np.ndarray, directory=None) -> np.ndarray:
    """``arr`` moved to an unnamed file: a read-only memory map of a copy written to a temporary
    ``.npy`` in ``directory`` (default :data:`SCRATCH_DIR`, else the system temp directory).

    The file is unlinked once mapped (POSIX: its space is freed when the map closes; elsewhere
    it is removed at exit), so nothing is left behind.  Lets a process that measures a large
    field keep each finished full-frame array on disk rather than in memory.
    """
    arr = np.asarray(arr)

    def write_and_map(name):
        dtype = arr.dtype if arr.dtype.isnative else arr.dtype.newbyteorder("=")
        out = _allocated_npy(name, dtype, arr.shape)
        _copy_rows(arr, out)
        del out
        return np.load(name, mmap_mode="r", allow_pickle=False)

    return _unnamed_npy(write_and_map, directory)


def scratch_array(shape, dtype, directory=None) -> np.ndarray:
    """A zero-filled, writable memory map of an unnamed temporary ``.npy`` (as :func:`spill`'s,
    in ``directory``, default :data:`SCRATCH_DIR`): for a full-frame result written piece by
    piece (a large field's reference segmentation) without holding it in memory."""
    return _unnamed_npy(lambda name: _allocated_npy(name, np.dtype(dtype), tuple(shape)), directory)


def _unnamed_npy(make, directory=None):
    """``make(name)`` on a new temporary ``.npy`` name, the file unlinked afterwards (at exit
    where a mapped file cannot be), or at once if ``make`` fails."""
    fd, name = tempfile.mkstemp(prefix="glaciar-spill-", suffix=".npy",
                                dir=directory if directory is not None else SCRATCH_DIR)
    os.close(fd)
    try:
        out = make(name)
    except BaseException:
        os.unlink(name)
        raise
    try:
        os.unlink(name)
    except OSError:                     # pragma: no cover - platforms that keep mapped files
        atexit.register(lambda: os.path.exists(name) and os.unlink(name))
    return out


def _write_tiled(arr: np.ndarray, path: Path, tile: int) -> None:
    """Write a 2-d array as a 4-d .npy ``[ty, tx, tile, tile]`` (edge tiles zero-padded),
    its data at a multiple of :data:`TILE_ALIGN`; one row of tiles in memory at a time."""
    ny, nx = arr.shape
    nty, ntx = -(-ny // tile), -(-nx // tile)
    dtype = arr.dtype if arr.dtype.isnative else arr.dtype.newbyteorder("=")
    shape = (nty, ntx, tile, tile)
    header = repr({"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
                   "shape": shape})
    # Format 2.0: magic (6) + version (2) + uint32 length (4) + header ending in "\n".
    total = -(-(12 + len(header) + 1) // TILE_ALIGN) * TILE_ALIGN
    header = header + " " * (total - 12 - len(header) - 1) + "\n"
    from ..paths import allocate

    with open(path, "wb") as fh:
        # The whole file reserved first: a full disk fails here, not half-way.
        allocate(fh.fileno(), total + nty * ntx * tile * tile * dtype.itemsize, path)
        fh.write(np.lib.format.magic(2, 0))
        fh.write(np.uint32(len(header)).astype("<u4").tobytes())
        fh.write(header.encode("latin1"))
        row = np.zeros((tile, ntx * tile), dtype=dtype)
        src_maps = _maps_of(arr)          # a mapped source: its pages dropped row by row
        for ty in range(nty):
            y0, y1 = ty * tile, min((ty + 1) * tile, ny)
            row[:y1 - y0, :nx] = arr[y0:y1]
            if y1 - y0 < tile:
                row[y1 - y0:] = 0
            fh.write(np.ascontiguousarray(
                row.reshape(tile, ntx, tile).transpose(1, 0, 2)).tobytes())
            if src_maps:
                release(src_maps)


class Tiled:
    """Marks a 2-d array that :func:`save` stores as tiles (read back as a :class:`TiledArray`)."""

    __slots__ = ("array", "tile")

    def __init__(self, array, tile: int = TILE):
        self.array = array
        self.tile = int(tile)


def _encode(obj, directory: Path, names: list) -> dict:
    if isinstance(obj, Tiled):
        arr = obj.array
        if isinstance(arr, TiledArray):
            arr = np.asarray(arr)
        if arr.ndim != 2 or arr.dtype.hasobject:
            raise TypeError(f"field cache: only 2-d numeric arrays are tiled (got {arr.dtype}, "
                            f"{arr.ndim}-d)")
        name = f"a{len(names):04d}.npy"
        names.append(name)
        _write_tiled(arr, directory / name, obj.tile)
        return {"tiled": name, "shape": [int(n) for n in arr.shape]}
    if isinstance(obj, TiledArray):
        return _encode(Tiled(obj, obj.tile), directory, names)
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            raise TypeError(f"field cache: arrays of Python objects are not stored (dtype {obj.dtype})")
        name = f"a{len(names):04d}.npy"
        names.append(name)
        dtype = obj.dtype if obj.dtype.isnative else obj.dtype.newbyteorder("=")
        out = _allocated_npy(directory / name, dtype, obj.shape)
        _copy_rows(obj, out)
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
    Every array file's blocks are allocated before it is mapped or written: a full
    disk raises :class:`glaciar.paths.DiskFullError` naming ``directory`` (nothing
    left behind), never ``SIGBUS``.
    """
    from ..paths import disk_full

    directory = Path(directory)
    tmp = None
    try:
        directory.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{directory.name}.", suffix=".tmp",
                                    dir=directory.parent))
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
    except BaseException as exc:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        # Named by the cache directory (the temporary copy that ran out of space is gone).
        full = disk_full(directory, OSError(exc.errno, str(exc))) \
            if isinstance(exc, OSError) else None
        if full is not None:
            raise full from None
        raise
    return directory


# --------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------
def _decode(node: dict, directory: Path, maps: list):
    if "tiled" in node:
        if READ_TILES:
            return TiledArray.open(directory / node["tiled"], tuple(node["shape"]))
        tiles = np.load(directory / node["tiled"], mmap_mode="r", allow_pickle=False,
                        max_header_size=_MAX_HEADER)
        if isinstance(tiles, np.memmap):
            maps.append(tiles._mmap)
        return TiledArray(tiles, tuple(node["shape"]))
    if "npy" in node:
        path = directory / node["npy"]
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
        if arr.nbytes >= MMAP_MIN_BYTES and isinstance(arr, np.memmap):
            maps.append(arr._mmap)
            # A plain ndarray over the same map: np.memmap's Python-level __getitem__ and
            # __array_finalize__ cost ~2 us on every window slice a task takes (~1 % of a
            # task's CPU); the map stays alive as the view's base (and in ``maps``).
            return arr.view(np.ndarray)
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
    try:
        index = json.loads((directory / INDEX_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise UnreadableCache(directory / INDEX_NAME, str(exc)) from None
    if not isinstance(index, dict) or index.get("format") != FORMAT:
        raise ValueError(f"{directory / INDEX_NAME}: field cache format "
                         f"{index.get('format') if isinstance(index, dict) else None!r}, "
                         f"expected {FORMAT}")
    maps: list = []
    try:
        items = _decode(index["items"], directory, maps)
    except (OSError, ValueError, KeyError, TypeError, EOFError) as exc:
        # e.g. a truncated .npy: named, with the fix (the cache is a copy of measurements).
        text = str(exc).strip().splitlines()
        raise UnreadableCache(directory, f"{type(exc).__name__}: {text[0] if text else ''}") \
            from None
    return items, tuple(maps)


class UnreadableCache(ValueError):
    """A field cache that cannot be read (e.g. a truncated file): ``path`` and ``why``.

    The cache is a copy of measurements: removing it makes the field be measured again
    (glaciar.contexts does so on its own when it opens a run's caches).
    """

    def __init__(self, path, why: str):
        self.path, self.why = Path(path), why
        super().__init__(f"{path}: unreadable field cache ({why}); remove it and the field is "
                         "measured again")


def exists(directory) -> bool:
    """A complete cache is at ``directory``."""
    return (Path(directory) / INDEX_NAME).is_file()


# --------------------------------------------------------------------------
# Tiled arrays
# --------------------------------------------------------------------------
class TiledArray:
    """Read-only 2-d array stored as square tiles ``[ty, tx, row, col]``.

    Indexing returns what the same index of the plain array returns (always a
    new array, never a view): ``a[y0:y1, x0:x1]`` (steps of 1, negative and
    out-of-range bounds as numpy clips them) copies the tiles under the window
    only; ``a[iy, ix]`` with integer arrays (any broadcastable shapes) or
    integers gathers single pixels; a row ``a[i]`` or ``a[i, x0:x1]`` too.
    ``np.asarray(a)`` assembles the whole frame (rare full-frame users such as
    ``mode="full"``); any other index goes through it.

    The tiles are a 4-d array (in memory or memory-mapped: :attr:`tiles`), or,
    for a cache file opened with :meth:`open`, read from the file with
    positional reads (``os.preadv``) into private memory: one read per row of
    tiles under a window, of the rows it needs.  Why not a memory map: the
    page cache holds a file in large folios (up to 2 MB on Linux 6.x), and a
    fault maps the whole folio into the process, so a window of a few kB of a
    mapped file made up to MBs resident, which the resident budget then had
    to drop and fault in again (system time); a positional read copies the
    bytes it asks for and leaves nothing mapped: the process's resident set
    does not grow with the windows it reads, and no page is ever dropped.
    """

    __array_priority__ = 10.0

    def __init__(self, tiles: np.ndarray | None, shape: tuple[int, int], *, _file=None):
        if _file is not None:
            # (path, fd, data offset [bytes], 4-d shape, dtype): positional reads of the file
            self.path, self._fd, self._offset, tshape, dtype = _file
            weakref.finalize(self, os.close, self._fd)
        else:
            tshape, dtype, self._fd, self.path = tiles.shape, tiles.dtype, None, None
        if len(tshape) != 4 or tshape[2] != tshape[3]:
            raise ValueError(f"tiles must have shape (ty, tx, t, t), got {tuple(tshape)}")
        self.tiles = tiles
        self.tile = int(tshape[2])
        self._ntx = int(tshape[1])
        self.shape = (int(shape[0]), int(shape[1]))
        if tshape[0] * self.tile < self.shape[0] or tshape[1] * self.tile < self.shape[1]:
            raise ValueError(f"tiles {tuple(tshape)} do not cover shape {self.shape}")
        self.dtype = np.dtype(dtype)
        self.ndim = 2
        self.size = self.shape[0] * self.shape[1]
        self.itemsize = self.dtype.itemsize
        self.nbytes = self.size * self.itemsize
        self._row_bytes = self.tile * self.itemsize             # one row of a tile
        self._tile_bytes = self.tile * self._row_bytes

    @classmethod
    def open(cls, path, shape: tuple[int, int]) -> "TiledArray":
        """The tiled ``.npy`` at ``path`` (written by :func:`save`), read with positional reads.

        The file stays open (read-only) until the array is garbage-collected; a
        forked process shares the descriptor (positional reads move no file offset)."""
        path = str(path)
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
        try:
            with os.fdopen(os.dup(fd), "rb") as fh:
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    tshape, fortran, dtype = np.lib.format.read_array_header_1_0(
                        fh, max_header_size=_MAX_HEADER)
                else:
                    tshape, fortran, dtype = np.lib.format.read_array_header_2_0(
                        fh, max_header_size=_MAX_HEADER)
                offset = fh.tell()
            if fortran or dtype.hasobject or not dtype.isnative:
                raise ValueError(f"{path}: not a tiled field-cache array ({dtype}, "
                                 f"fortran_order={fortran})")
            size = os.fstat(fd).st_size
            if offset + int(np.prod(tshape)) * dtype.itemsize > size:
                raise ValueError(f"{path}: truncated ({size} bytes)")
        except BaseException:
            os.close(fd)
            raise
        return cls(None, shape, _file=(path, fd, offset, tuple(tshape), dtype))

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        return f"TiledArray(shape={self.shape}, dtype={self.dtype}, tile={self.tile})"

    def __reduce__(self):
        # A file-backed array is sent to another process as its path (reopened there).
        if self.tiles is None:
            return (_open_tiled, (self.path, self.shape))
        return (TiledArray, (np.asarray(self.tiles), self.shape))

    def _window(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        if y1 <= y0 or x1 <= x0:
            return np.empty((max(y1 - y0, 0), max(x1 - x0, 0)), dtype=self.dtype)
        t = self.tile
        ty0, tx0 = y0 // t, x0 // t
        nty, nw = (y1 - 1) // t + 1 - ty0, (x1 - 1) // t + 1 - tx0
        r0, c0 = y0 - ty0 * t, x0 - tx0 * t
        if nty == 1 and nw == 1 and self.tiles is None:
            # Inside one tile (small windows often are): its rows r0:r0 + h, in one read.
            h = y1 - y0
            rows = np.empty((h, t), dtype=self.dtype)
            size = h * self._row_bytes
            if os.preadv(self._fd, (rows,), self._offset + (ty0 * self._ntx + tx0)
                         * self._tile_bytes + r0 * self._row_bytes) != size:
                raise OSError(f"{self.path}: short read")
            return rows[:, c0:c0 + x1 - x0].copy()
        # Row of tiles by row of tiles (a whole frame never holds more than one extra row of
        # tiles): the rows of the tiles under the window, then the window's columns of them.
        out = np.empty((y1 - y0, x1 - x0), dtype=self.dtype)
        w = x1 - x0
        last = y1 - (ty0 + nty - 1) * t
        buf = np.empty((nw, t, t), dtype=self.dtype) if self.tiles is None else None
        for k in range(nty):
            a, b = (r0 if k == 0 else 0), (last if k == nty - 1 else t)
            if buf is None:
                block = self.tiles[ty0 + k, tx0:tx0 + nw, a:b]
            else:
                self._read_tile_row(buf, ty0 + k, tx0, a, b)
                block = buf[:, a:b]
            dst = out[k * t + a - r0:k * t + b - r0]
            if nw == 1:
                dst[...] = block[0, :, c0:c0 + w]
            else:
                # (tiles, rows, cols) -> (rows, tiles x cols)
                dst[...] = block.transpose(1, 0, 2).reshape(b - a, nw * t)[:, c0:c0 + w]
        return out

    def _read_tile_row(self, buf: np.ndarray, ty: int, tx0: int, a: int, b: int) -> None:
        """Rows ``a:b`` of the tiles ``tx0:tx0 + len(buf)`` of tile row ``ty`` into ``buf``.

        One read of the file's contiguous bytes from the first tile's row ``a`` to the
        last tile's row ``b``: the other rows of the tiles between come along (cheaper
        than one read per tile) and are not used."""
        row, tile_bytes = self._row_bytes, self._tile_bytes
        lo, hi = a * row, (len(buf) - 1) * tile_bytes + b * row
        raw = memoryview(buf).cast("B")
        if os.preadv(self._fd, (raw[lo:hi],),
                     self._offset + (ty * self._ntx + tx0) * tile_bytes + lo) != hi - lo:
            raise OSError(f"{self.path}: short read")

    def _points(self, iy, ix) -> np.ndarray:
        iy, ix = np.broadcast_arrays(np.asarray(iy), np.asarray(ix))
        ny, nx = self.shape
        if iy.size and (iy.min() < -ny or iy.max() >= ny or ix.min() < -nx or ix.max() >= nx):
            raise IndexError(f"index out of bounds for an array of shape {self.shape}")
        iy = np.where(iy < 0, iy + ny, iy)
        ix = np.where(ix < 0, ix + nx, ix)
        t = self.tile
        if self.tiles is not None:
            return np.array(self.tiles[iy // t, ix // t, iy % t, ix % t])
        # element index in the file: ((ty * ntx + tx) * t + row) * t + col
        pos = (((iy // t) * self._ntx + ix // t) * t + iy % t) * t + ix % t
        out = np.empty(pos.shape, dtype=self.dtype)
        if not out.size:
            return out
        n = self.itemsize
        raw = memoryview(out.reshape(-1).view(np.uint8))
        base, fd = self._offset, self._fd
        for k, p in enumerate((pos.reshape(-1) * n).tolist()):
            if os.preadv(fd, [raw[k * n:(k + 1) * n]], base + p) != n:
                raise OSError(f"{self.path}: short read")
        return out

    def __getitem__(self, key):
        if type(key) is tuple and len(key) == 2:
            ky, kx = key
            if type(ky) is slice and type(kx) is slice and ky.step is None and kx.step is None:
                # the common case first: a window
                y0, y1, _ = ky.indices(self.shape[0])
                x0, x1, _ = kx.indices(self.shape[1])
                return self._window(y0, y1, x0, x1)
        if type(key) is not tuple:
            key = (key,)
        if len(key) == 1:
            key = (key[0], slice(None))
        if len(key) == 2:
            ky, kx = key
            sy, sx = isinstance(ky, slice), isinstance(kx, slice)
            if (sy and sx and ky.step in (None, 1) and kx.step in (None, 1)):
                y0, y1, _ = ky.indices(self.shape[0])
                x0, x1, _ = kx.indices(self.shape[1])
                return self._window(y0, y1, x0, x1)
            iy_int = isinstance(ky, (int, np.integer))
            ix_int = isinstance(kx, (int, np.integer))
            if iy_int and ix_int:
                return self._points(ky, kx)[()]
            if (iy_int and sx and kx.step in (None, 1)) or (ix_int and sy and ky.step in (None, 1)):
                n = self.shape[0] if iy_int else self.shape[1]
                i = int(ky if iy_int else kx)
                if not -n <= i < n:
                    raise IndexError(f"index {i} out of bounds for an array of shape {self.shape}")
                i += n if i < 0 else 0
                if iy_int:
                    x0, x1, _ = kx.indices(self.shape[1])
                    return self._window(i, i + 1, x0, x1)[0]
                y0, y1, _ = ky.indices(self.shape[0])
                return self._window(y0, y1, i, i + 1)[:, 0]
            if not (sy or sx or ky is None or kx is None or ky is Ellipsis or kx is Ellipsis):
                ay, ax = np.asarray(ky), np.asarray(kx)
                if ay.dtype.kind in "iu" and ax.dtype.kind in "iu":
                    return self._points(ay, ax)
        return np.asarray(self)[key]

    def __array__(self, dtype=None, copy=None):
        out = self._window(0, self.shape[0], 0, self.shape[1])
        return out if dtype is None else out.astype(dtype, copy=False)

    def astype(self, dtype, copy: bool = True):
        return np.asarray(self).astype(dtype, copy=copy)


def _open_tiled(path, shape) -> TiledArray:
    return TiledArray.open(path, shape)


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
    fault maps a whole page-cache folio (64 kB fault-around, up to 2 MB with
    large folios), many image rows at 16000 pixels of float32 (the tiled
    images, read with positional reads, are not mapped and not counted).
    When the maps are larger than the budget,
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
