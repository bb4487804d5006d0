"""Random positions for injected sources: uniform inside the footprint, isolation boxes never overlapping.

GLACiAR started every galaxy at a hard-coded pixel, forced galaxy 0 to a fixed
position and kept only a 5 r_e centre separation, so about 13 % of its stamps
overwrote each other (reference/glaciar-algorithm.md Sect. 6-7).  Here each
source owns a rectangular isolation box; boxes of two sources never intersect.

The distribution (random sequential placement)
----------------------------------------------
Sources are placed one after the other in index order.  The box of source k
covers rows ``iy - half_height[k] .. iy + half_height[k]`` and columns
``ix - half_width[k] .. ix + half_width[k]`` (inclusive) around its centre
pixel ``(iy, ix)``; it may extend beyond the image.  Source k's centre pixel is
uniform over its *valid* pixels: footprint pixels where its box intersects none
of the boxes of sources 0 .. k-1.  Its position inside that pixel is uniform
(pixel i spans [i - 0.5, i + 0.5]).  Placement stops at the first source that
has no valid pixel, so the placed sources are always the first m of the n
requested (m < n only when the field is full for source m).

Algorithm
---------
Two boolean maps on the pixel grid are kept up to date *locally* after each
placement (work proportional to the box area):

* ``occupied``: pixels covered by a placed box (clipped to the image).  Two boxes
  whose centres lie in the image intersect if and only if they share a pixel
  of the image (along each axis both intervals contain their own centre, which
  lies in the image), so a box fits at a pixel exactly when its window of
  ``occupied`` is empty.
* ``free``: footprint pixels where a box of the *smallest* half sizes among the
  n sources fits.  Every source's valid pixels are a subset of ``free``.

A candidate is drawn uniformly from a list of pixels holding every ``free``
pixel (the whole grid at first, compacted to the ``free`` pixels when fewer than
a quarter of its entries are still free) and accepted when it is ``free`` and the
source's box fits there: rejection sampling, so the accepted pixel is exactly
uniform over the valid pixels.  After a bounded number of rejections
(:func:`_max_tries`) the valid pixels of that source are enumerated exactly with
``occupied`` dilated by the source's box (O(image) once) and one is drawn
uniformly from them -- the same distribution again; when there are none,
placement stops.
No loop is unbounded: asking for 10^6 sources on a field that holds 100 costs
about 100 placements and one enumeration.

Sparse placement (no full-frame array per task)
-----------------------------------------------
The two maps cost O(image) memory and time per task (two boolean frames), which
on a large mosaic dwarfs the placement itself.  :func:`draw_positions` therefore
runs the same algorithm without them while it provably makes the same decisions
(:class:`_Sparse`): the placed boxes are kept as a list, indexed by a coarse grid
of cells, and a candidate pixel is accepted when it lies in the footprint and no
placed box is within the source's box (the same box-intersection rule, which for
a box at least as large as the smallest also implies ``free``).  The only other
decisions the maps take part in are the compaction of the candidate list
(``n_free * 4 < pool_size``) and the ``n_free == 0`` stop.  ``n_free`` is at least
the footprint's pixel count minus the areas (clipped to the image) of the
placed boxes widened by the smallest half sizes; while that bound times 4 is at
least the grid's pixel count, neither decision can be taken, so the candidate
sequence, the accepted pixels and the random stream are those of the maps.
As soon as the bound fails, or a source needs the exact enumeration, the maps
are built from the placed boxes (they are a function of them) and the
placement continues with them: the positions are identical for the same
generator state in every case.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import ndimage

__all__ = ["draw_positions", "placement_capacity", "PlacementCapacity"]

#: Random indices are drawn in batches of this many (a performance setting only:
#: it changes which positions a seed gives, never their distribution).
_BATCH = 256


def _max_tries(n_pixels: int) -> int:
    """Rejections tolerated for one source before its valid pixels are enumerated.

    An enumeration costs ~10 ns per image pixel and a rejected candidate ~3 us, so
    this balances the two.
    """
    return 64 + n_pixels // 256


class _Grid:
    """Occupancy and free-centre maps of one placement (see the module docstring)."""

    def __init__(self, footprint: np.ndarray, min_half_height: int, min_half_width: int):
        self.ny, self.nx = footprint.shape
        self.hmin = int(min_half_height)
        self.wmin = int(min_half_width)
        self.occupied = np.zeros(footprint.shape, dtype=bool)
        self.free = footprint.copy()
        self.n_free = int(np.count_nonzero(self.free))
        self.pool: np.ndarray | None = None      # None: the whole grid, entry i is pixel i
        self.pool_size = self.ny * self.nx
        self.batch = np.empty(0, dtype=np.int64)
        self.cursor = 0
        self.max_tries = _max_tries(self.ny * self.nx)

    # -- candidates --------------------------------------------------------
    def _compact(self) -> None:
        self.pool = np.flatnonzero(self.free.ravel())
        self.pool_size = self.pool.size
        self.batch = np.empty(0, dtype=np.int64)     # drawn for the old pool size
        self.cursor = 0

    def _candidate(self, rng: np.random.Generator) -> int:
        if self.n_free * 4 < self.pool_size:
            self._compact()
        if self.cursor == self.batch.size:
            self.batch = rng.integers(0, self.pool_size, size=_BATCH)
            self.cursor = 0
        i = int(self.batch[self.cursor])
        self.cursor += 1
        return i if self.pool is None else int(self.pool[i])

    def _fits(self, p: int, h: int, w: int) -> bool:
        y, x = divmod(p, self.nx)
        return not self.occupied[max(0, y - h):y + h + 1, max(0, x - w):x + w + 1].any()

    def _enumerate(self, rng: np.random.Generator, h: int, w: int) -> int:
        """Draw uniformly from all valid pixels of a box (h, w), found exactly; -1 when none.

        Valid = free and no occupied pixel in the box: ``occupied`` dilated by the box
        (two running maxima, O(image) whatever the box size).  The r-th valid pixel in
        row-major order is found from per-row counts, without listing them all.
        """
        valid = self.free
        if (h, w) != (self.hmin, self.wmin):
            near = ndimage.maximum_filter1d(self.occupied.view(np.uint8), 2 * h + 1, axis=0,
                                            mode="constant", cval=0)
            near = ndimage.maximum_filter1d(near, 2 * w + 1, axis=1, mode="constant", cval=0)
            valid = valid & (near == 0)
        per_row = np.cumsum(np.count_nonzero(valid, axis=1))
        if per_row[-1] == 0:
            return -1
        r = int(rng.integers(0, per_row[-1]))
        row = int(np.searchsorted(per_row, r, side="right"))
        before = int(per_row[row - 1]) if row else 0
        return row * self.nx + int(np.flatnonzero(valid[row])[r - before])

    def draw(self, rng: np.random.Generator, h: int, w: int) -> int:
        """A pixel (flat index) uniform over the valid pixels of a box (h, w); -1 when none."""
        smallest = h == self.hmin and w == self.wmin     # free already means "fits"
        free = self.free.ravel()
        for _ in range(self.max_tries):
            if self.n_free == 0:
                return -1
            p = self._candidate(rng)
            if free[p] and (smallest or self._fits(p, h, w)):
                return p
        return self._enumerate(rng, h, w)

    # -- bookkeeping -------------------------------------------------------
    def occupy(self, p: int, h: int, w: int) -> None:
        y, x = divmod(p, self.nx)
        self.occupied[max(0, y - h):y + h + 1, max(0, x - w):x + w + 1] = True
        hb, wb = h + self.hmin, w + self.wmin
        blocked = self.free[max(0, y - hb):y + hb + 1, max(0, x - wb):x + wb + 1]
        self.n_free -= int(np.count_nonzero(blocked))
        blocked[...] = False


class _Sparse:
    """The placement of :class:`_Grid` without its two maps, while provably identical.

    Placed boxes are kept in lists and indexed by a grid of square cells of side
    ``cell`` (at least the widest box, so a box or a query window meets at most
    2 x 2 cells).  ``removed`` bounds from above the pixels :class:`_Grid` would
    have cleared from ``free``: while ``n_footprint - removed`` is at least a
    quarter of the grid, ``_Grid`` would neither compact its candidate list nor
    find ``free`` empty (see the module docstring), so :meth:`exact` holds and
    the candidates, acceptances and random draws are the same.
    """

    def __init__(self, footprint: np.ndarray, n_footprint: int, min_half_height: int,
                 min_half_width: int, cell: int):
        self.footprint = footprint
        self.flat = footprint.reshape(-1)
        self.ny, self.nx = footprint.shape
        self.hmin = int(min_half_height)
        self.wmin = int(min_half_width)
        self.n_footprint = int(n_footprint)
        self.removed = 0
        self.cell = int(cell)
        self.ncx = -(-self.nx // self.cell)
        self.cells: dict[int, list[int]] = {}
        self.boxes: list[tuple[int, int, int, int]] = []      # (y, x, h, w) in placement order
        self.pool_size = self.ny * self.nx
        self.batch = np.empty(0, dtype=np.int64)
        self.cursor = 0
        self.max_tries = _max_tries(self.ny * self.nx)

    def exact(self) -> bool:
        """True while :class:`_Grid` provably neither compacts nor runs out of free pixels."""
        return (self.n_footprint - self.removed) * 4 >= self.pool_size > 0

    def _cell_range(self, lo: int, hi: int, n: int) -> range:
        return range(max(lo, 0) // self.cell, min(hi, n - 1) // self.cell + 1)

    def _clear(self, y: int, x: int, h: int, w: int) -> bool:
        """No placed box meets the box (h, w) at (y, x): |dy| <= h + h_k and |dx| <= w + w_k."""
        cells = self.cells
        for cy in self._cell_range(y - h, y + h, self.ny):
            row = cy * self.ncx
            for cx in self._cell_range(x - w, x + w, self.nx):
                for k in cells.get(row + cx, ()):
                    by, bx, bh, bw = self.boxes[k]
                    if abs(y - by) <= h + bh and abs(x - bx) <= w + bw:
                        return False
        return True

    def draw(self, rng: np.random.Generator, h: int, w: int) -> int:
        """As :meth:`_Grid.draw` while :meth:`exact`; -2 after ``max_tries`` rejections (the
        caller then enumerates on the maps)."""
        flat, nx = self.flat, self.nx
        for _ in range(self.max_tries):
            if self.cursor == self.batch.size:
                self.batch = rng.integers(0, self.pool_size, size=_BATCH)
                self.cursor = 0
            p = int(self.batch[self.cursor])
            self.cursor += 1
            # (h, w) >= the smallest half sizes, so a clear box also means "free".
            if flat[p] and self._clear(*divmod(p, nx), h, w):
                return p
        return -2

    def occupy(self, p: int, h: int, w: int) -> None:
        y, x = divmod(p, self.nx)
        k = len(self.boxes)
        self.boxes.append((y, x, h, w))
        for cy in self._cell_range(y - h, y + h, self.ny):
            for cx in self._cell_range(x - w, x + w, self.nx):
                self.cells.setdefault(cy * self.ncx + cx, []).append(k)
        hb, wb = h + self.hmin, w + self.wmin
        self.removed += ((min(y + hb, self.ny - 1) - max(y - hb, 0) + 1)
                         * (min(x + wb, self.nx - 1) - max(x - wb, 0) + 1))

    def dense(self) -> _Grid:
        """The maps of the same placement (its boxes replayed), with the same candidate batch."""
        grid = _Grid(self.footprint, self.hmin, self.wmin)
        for y, x, h, w in self.boxes:
            grid.occupy(y * self.nx + x, h, w)
        grid.batch, grid.cursor = self.batch, self.cursor
        return grid


def _half_sizes(footprint, half_height, half_width) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    footprint = np.asarray(footprint, dtype=bool)
    if footprint.ndim != 2:
        raise ValueError(f"footprint must be a 2-d array, got shape {footprint.shape}")
    hh = np.atleast_1d(np.asarray(half_height)).astype(np.int64, casting="same_kind").ravel()
    hw = np.atleast_1d(np.asarray(half_width)).astype(np.int64, casting="same_kind").ravel()
    if hh.shape != hw.shape:
        raise ValueError(f"half_height and half_width differ in length ({hh.size} vs {hw.size})")
    if hh.size and (hh.min() < 0 or hw.min() < 0):
        raise ValueError("half sizes must be >= 0 pixels")
    return footprint, hh, hw


def draw_positions(rng: np.random.Generator, footprint: np.ndarray, half_height: np.ndarray,
                   half_width: np.ndarray, n_footprint: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Draw source centres uniformly inside a footprint, isolation boxes never intersecting.

    Parameters
    ----------
    rng : numpy.random.Generator
        The task's random stream (the result is a deterministic function of its state).
    footprint : ndarray of bool, shape (ny, nx)
        True where a centre may lie (the detection band has valid data).
    half_height, half_width : array_like of int, shape (n,)
        Half sizes [pixels] of each source's isolation box; the box of source i
        covers rows ``round(y_i) - half_height[i] .. round(y_i) + half_height[i]``
        and likewise columns (inclusive; it may extend beyond the image).
    n_footprint : int, optional
        Number of True pixels of ``footprint``, if known (e.g. a field context's
        ``footprint_count``): saves counting them, the one full-frame pass left
        (the placement is otherwise sparse; see the module docstring).

    Returns
    -------
    x, y : ndarray of float, shape (m,)
        Centres in 0-based pixel coordinates [pixels] (``x`` along axis 1; pixel i
        spans [i - 0.5, i + 0.5]; ``round(x_i)`` is the centre pixel), of the first
        m <= n sources.  Source k's centre pixel is uniform over the footprint
        pixels where its box meets none of the boxes of sources 0 .. k-1, and its
        offset inside the pixel uniform on [-0.5, 0.5) along each axis.  m < n
        exactly when source m has no such pixel: the caller must keep the first m
        sources and can report how many were placed.  The work is bounded by the
        number of sources that fit (at most ``placement_capacity(...).upper_bound``
        placements), whatever n is.
    """
    footprint, hh, hw = _half_sizes(footprint, half_height, half_width)
    n = hh.size
    if n == 0:
        return np.empty(0), np.empty(0)
    pix = _place(rng, footprint, hh, hw, n_footprint)
    m = pix.size
    iy, ix = np.divmod(pix, footprint.shape[1])
    u = rng.random((2, m)) - 0.5
    return _inside_pixel(ix + u[0], ix), _inside_pixel(iy + u[1], iy)


def _place(rng: np.random.Generator, footprint: np.ndarray, hh: np.ndarray, hw: np.ndarray,
           n_footprint: int | None, sparse: bool = True) -> np.ndarray:
    """Centre pixels (flat indices) of the first m sources; sparse while provably exact."""
    n = hh.size
    hmin, wmin = int(hh.min()), int(hw.min())
    grid = None
    if sparse:
        if n_footprint is None:
            n_footprint = int(np.count_nonzero(footprint))
        cell = max(16, 2 * int(max(hh.max(), hw.max())) + 1)
        grid = _Sparse(footprint, n_footprint, hmin, wmin, cell)
        if not grid.exact():
            grid = grid.dense()
    else:
        grid = _Grid(footprint, hmin, wmin)
    pix = np.empty(n, dtype=np.int64)
    m = 0
    for k in range(n):
        h, w = int(hh[k]), int(hw[k])
        p = grid.draw(rng, h, w)
        if p == -2:                         # sparse: max_tries rejections, enumerate exactly
            grid = grid.dense()
            p = grid._enumerate(rng, h, w)
        if p < 0:
            break
        grid.occupy(p, h, w)
        if isinstance(grid, _Sparse) and not grid.exact():
            grid = grid.dense()
        pix[m] = p
        m += 1
    return pix[:m]


def _inside_pixel(v: np.ndarray, i: np.ndarray) -> np.ndarray:
    """``v`` with ``round(v) == i`` kept: i - 0.5 exactly, or i + u rounded up to i + 0.5 in
    floating point (probability ~1e-16), rounds to an even neighbour; move those by one ulp."""
    bad = np.rint(v) != i
    while bad.any():
        v[bad] = np.nextafter(v[bad], i[bad].astype(float))
        bad = np.rint(v) != i
    return v


class PlacementCapacity(NamedTuple):
    """How many isolation boxes a footprint holds (:func:`placement_capacity`)."""

    #: No arrangement places more boxes (of at least the smallest given size); exact for a
    #: rectangular footprint and boxes of one size.
    upper_bound: int
    #: How many :func:`draw_positions` places for these sizes (cycled) before no centre is
    #: left, in one seeded fill: what a task can expect to place (an estimate: random
    #: placement typically stops well below ``upper_bound``).
    random_fill: int


def placement_capacity(footprint: np.ndarray, half_height, half_width, *,
                       seed: int = 0) -> PlacementCapacity:
    """How many non-overlapping isolation boxes fit in a footprint, for a pre-flight check.

    Parameters
    ----------
    footprint : ndarray of bool, shape (ny, nx)
        Where centres may lie, as for :func:`draw_positions`.
    half_height, half_width : int or array_like of int, shape (n,)
        Half sizes [pixels] of the boxes, e.g. those of one task's sources (the
        largest sources of a run are those at its lowest redshift).
    seed : int
        Seed of the random fill.

    Returns
    -------
    PlacementCapacity
        ``upper_bound``: the footprint's bounding box is cut into cells of
        (2 h_min + 1) x (2 w_min + 1) pixels from its first row and column; two
        centres in one cell are closer than 2 h_min + 1 rows and 2 w_min + 1
        columns, so their boxes meet, and no arrangement holds more boxes than
        there are cells containing footprint pixels.  For a rectangular footprint
        of L_y x L_x pixels and one box size this is ceil(L_y / (2h + 1)) *
        ceil(L_x / (2w + 1)), which the square lattice attains: exact.
        ``random_fill``: the number placed by :func:`draw_positions` (with
        ``numpy.random.default_rng(seed)``) when asked for ``upper_bound + 1``
        sources whose sizes cycle through the given ones -- an estimate of what a
        task places when ``n_galaxies`` is more than fits; a task asked for at
        most this many usually places them all.
    """
    footprint, hh, hw = _half_sizes(footprint, half_height, half_width)
    if hh.size == 0:
        raise ValueError("no box sizes given")
    rows = np.flatnonzero(footprint.any(axis=1))
    if rows.size == 0:
        return PlacementCapacity(0, 0)
    cols = np.flatnonzero(footprint.any(axis=0))
    sy, sx = 2 * int(hh.min()) + 1, 2 * int(hw.min()) + 1
    box = footprint[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    ly, lx = box.shape
    cy, cx = -(-ly // sy), -(-lx // sx)
    padded = np.zeros((cy * sy, cx * sx), dtype=bool)
    padded[:ly, :lx] = box
    upper = int(np.count_nonzero(padded.reshape(cy, sy, cx, sx).any(axis=(1, 3))))
    k = np.arange(upper + 1) % hh.size
    x, _ = draw_positions(np.random.default_rng(seed), footprint, hh[k], hw[k])
    return PlacementCapacity(upper, int(x.size))
