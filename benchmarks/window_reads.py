"""Window reads from a field cache: row-major map, mapped tiles, tiles read by preadv (issue 11, point 4).

A task reads windows of the field's images (``base[y0:y1, x0:x1]``).  From a
memory map, a fault maps the page-cache folio around it (64 kB fault-around,
and with large folios -- Linux 6.x -- up to 2 MB at once), a whole row of a
16000-pixel float32 image; tiles (:class:`glaciar.engine.fieldcache.TiledArray`)
put the pixels of a window close together in the file, and reading them with
positional reads (``os.preadv``, what workers do) copies the rows of the tiles
under the window and maps nothing.  For one ``--side``^2 float32 image, written
row-major and tiled (``--tile`` px) into ``--tmp`` (and read from the page cache),
this prints per window size and layout:

* microseconds per read with the pages already mapped (``warm``) and with the
  process's pages dropped before every read (``dropped``: what a worker pays
  once its resident budget made it release the maps; the page cache keeps the
  file, so these are minor faults; nothing to drop for ``tiles read``);
* the file-backed resident memory each read adds [kB] (``/proc/self/statm``, over 50 reads
  from nothing mapped).

Usage::

    python benchmarks/window_reads.py [--side 16000] [--windows 64,200] [--reads 2000] [--tile 64]
                                      [--tmp DIR]
"""
from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from glaciar.engine import fieldcache


def _write_images(directory: Path, side: int, tile: int) -> tuple[Path, Path]:
    """Write a side^2 float32 image as a plain .npy and as a tiled cache, by blocks of rows."""
    rng = np.random.default_rng(1)
    plain = directory / "plain.npy"
    out = np.lib.format.open_memmap(plain, mode="w+", dtype=np.float32, shape=(side, side))
    step = max(1, (64 << 20) // (4 * side))
    for y in range(0, side, step):
        out[y:y + step] = rng.normal(size=(min(step, side - y), side)).astype(np.float32)
    out.flush()
    del out
    img = np.load(plain, mmap_mode="r")
    tiled = fieldcache.save({"img": fieldcache.Tiled(img, tile)}, directory / "tiled")
    return plain, tiled


def _reads(arr, windows, release) -> tuple[float, float]:
    """Mean [us] per read and resident kB added per read."""
    r0 = fieldcache._file_resident_bytes()
    t0 = time.perf_counter()
    for y0, x0, w in windows:
        if release is not None:
            release()
        np.array(arr[y0:y0 + w, x0:x0 + w], dtype=np.float64)
    dt = time.perf_counter() - t0
    grown = (fieldcache._file_resident_bytes() - r0) / 1024.0
    return 1e6 * dt / len(windows), grown / len(windows)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--side", type=int, default=16000)
    ap.add_argument("--windows", default="64,200", help="window sides [pixels]")
    ap.add_argument("--reads", type=int, default=2000)
    ap.add_argument("--tile", type=int, default=fieldcache.TILE, help="tile side [pixels]")
    ap.add_argument("--tmp", default=None)
    opt = ap.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="glaciar-windows-", dir=opt.tmp))
    try:
        plain_path, tiled_path = _write_images(root, opt.side, opt.tile)
        rng = np.random.default_rng(2)
        print(f"{opt.side}^2 float32 ({4 * opt.side ** 2 / 2 ** 20:.0f} MB), {opt.tile} px tiles, "
              f"{opt.reads} random windows per figure, page cache warm")
        print(f"{'window':>7s} {'layout':>12s} {'warm us':>9s} {'dropped us':>11s} "
              f"{'resident kB/read':>17s}")
        for w in (int(s) for s in opt.windows.split(",")):
            windows = [(int(y), int(x), w) for y, x in
                       rng.integers(0, opt.side - w, size=(opt.reads, 2))]
            for layout in ("row-major", "tiles mapped", "tiles read"):
                if layout == "row-major":
                    arr = np.load(plain_path, mmap_mode="r")
                    maps = (arr._mmap,)
                else:
                    read = fieldcache.READ_TILES
                    fieldcache.READ_TILES = layout == "tiles read"
                    try:
                        items, maps = fieldcache.load(tiled_path)
                    finally:
                        fieldcache.READ_TILES = read
                    arr = items["img"]
                # resident growth from nothing mapped (few windows: the map does not fill
                # up), then all windows twice (the second pass warm)
                fieldcache.release(maps)
                _, kb = _reads(arr, windows[:50], None)
                _reads(arr, windows, None)
                warm, _ = _reads(arr, windows, None)
                dropped, _ = _reads(arr, windows, lambda: fieldcache.release(maps))
                print(f"{w:>7d} {layout:>12s} {warm:>9.1f} {dropped:>11.1f} {kb:>17.0f}")
                fieldcache.release(maps)
                del arr, maps
    finally:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
