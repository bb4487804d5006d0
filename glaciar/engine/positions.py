"""Random positions for injected sources: uniform inside the footprint, stamps never overlapping.

GLACiAR started every galaxy at a hard-coded pixel, forced galaxy 0 to a fixed
position and kept only a 5 r_e centre separation, so about 13 % of its stamps
overwrote each other (reference/glaciar-algorithm.md Sect. 6-7).  Here each
source owns a rectangular box (its PSF-convolved stamp); boxes of two sources
never intersect, and centres are uniform over the valid pixels.
"""
from __future__ import annotations

import numpy as np

__all__ = ["draw_positions"]


def draw_positions(rng: np.random.Generator, footprint: np.ndarray, half_height: np.ndarray,
                   half_width: np.ndarray, *, max_batches: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Draw non-overlapping source centres uniformly inside a footprint.

    Parameters
    ----------
    rng : numpy.random.Generator
        The task's random stream.
    footprint : ndarray of bool, shape (ny, nx)
        True where the detection band has valid data; a centre pixel must be True.
    half_height, half_width : ndarray of int, shape (n,)
        Half sizes [pixels] of each source's stamp box; the box of source i
        covers rows ``round(y_i) - half_height[i] .. round(y_i) + half_height[i]``.
    max_batches : int
        Number of candidate batches tried before giving up on the remaining sources.

    Returns
    -------
    x, y : ndarray of float, shape (m,)
        Centres in 0-based pixel coordinates (pixel i spans [i - 0.5, i + 0.5]),
        m <= n.  Sources are placed in index order; m < n only when the footprint
        is too crowded to place them all (the caller records how many were placed).
    """
    footprint = np.asarray(footprint, dtype=bool)
    ny, nx = footprint.shape
    hh = np.asarray(half_height, dtype=np.int64)
    hw = np.asarray(half_width, dtype=np.int64)
    n = hh.size
    xs = np.empty(n)
    ys = np.empty(n)
    placed = 0
    batch = max(64, 4 * n)
    for _ in range(max_batches):
        if placed == n:
            break
        # Uniform over the pixel grid, then rejection on the footprint: exact uniformity
        # over valid pixels without materialising the (possibly huge) index list.
        cy = rng.integers(0, ny, size=batch)
        cx = rng.integers(0, nx, size=batch)
        ux = rng.uniform(-0.5, 0.5, size=batch)
        uy = rng.uniform(-0.5, 0.5, size=batch)
        ok = footprint[cy, cx]
        for k in np.flatnonzero(ok):
            if placed == n:
                break
            iy, ix = cy[k], cx[k]
            if placed:
                py = np.rint(ys[:placed]).astype(np.int64)
                px = np.rint(xs[:placed]).astype(np.int64)
                clash = ((np.abs(py - iy) <= hh[:placed] + hh[placed])
                         & (np.abs(px - ix) <= hw[:placed] + hw[placed]))
                if clash.any():
                    continue
            xs[placed] = ix + ux[k]
            ys[placed] = iy + uy[k]
            # Keep the rounding of the stored centre on the accepted pixel.
            xs[placed] = np.clip(xs[placed], ix - 0.5 + 1e-9, ix + 0.5 - 1e-9)
            ys[placed] = np.clip(ys[placed], iy - 0.5 + 1e-9, iy + 0.5 - 1e-9)
            placed += 1
    return xs[:placed], ys[:placed]
