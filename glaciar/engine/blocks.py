"""Full-frame images by blocks of rows: how a field's set-up bounds its memory.

Every set-up step that works pixel by pixel, or with a kernel a few rows tall,
goes through the image in blocks of consecutive rows (:func:`row_blocks`), each
read with the rows the kernel needs beyond it (its halo), so that the step's
result is, row for row, the whole-image result (each step's test holds it to
that with blocks of a few rows).
"""
from __future__ import annotations

import math

__all__ = ["row_blocks", "row_tiles", "REFERENCE_TILE_PIXELS"]

#: Pixels per row tile of the full-frame mask work on a field's detection image (the
#: reference's region boxes, :mod:`glaciar.engine.measure`; the emulated CLEAN's
#: thresholds, :mod:`glaciar.engine.segmentation`): ~16 MB of float32 per tile.
REFERENCE_TILE_PIXELS = 1 << 22


def row_blocks(shape, pixels: int, halo: int = 0, rows: int | None = None):
    """Blocks of rows of an image, with a halo.

    Parameters
    ----------
    shape : tuple of int
        Image shape, rows first (further axes make up a row).
    pixels : int
        Pixels per block: ``pixels // row size`` rows, at least one.
    halo : int
        Rows read beyond each side of a block (clipped to the image) [pixels].
    rows : int, optional
        Rows per block instead of ``pixels``' (>= 1).

    Yields
    ------
    y0, y1, a, b : int
        The block's rows ``[y0, y1)`` and the rows ``[a, b)`` read for it.

    Raises
    ------
    ValueError
        If ``rows`` < 1 (raised when the first block is asked for).
    """
    ny = int(shape[0])
    width = math.prod(int(n) for n in shape[1:])
    step = max(1, int(pixels) // max(width, 1)) if rows is None else int(rows)
    if step < 1:
        raise ValueError(f"tile_rows must be >= 1, got {rows!r}")
    for y0 in range(0, ny, step):
        y1 = min(y0 + step, ny)
        yield y0, y1, max(y0 - halo, 0), min(y1 + halo, ny)


def row_tiles(shape, halo: int = 0):
    """Row tiles of :data:`REFERENCE_TILE_PIXELS` pixels with ``halo`` rows around each.

    The one tiling the detection image's full-frame mask work shares (a leaf, so that
    both :mod:`~glaciar.engine.measure` and :mod:`~glaciar.engine.segmentation` use it
    without importing each other).  The tile size is read at each call (tests shrink it).

    Yields
    ------
    y0, y1, a, b : int
        As :func:`row_blocks`.
    """
    return row_blocks(shape, REFERENCE_TILE_PIXELS, halo)
