"""Acquisition for the adaptive loop: where to simulate next."""
from __future__ import annotations

import numpy as np

__all__ = ["propose_cells"]


def propose_cells(sf_or_draws, z_grid, m_grid, n: int, *, interval: float = 0.68,
                  relative: bool = False) -> np.ndarray:
    """The (z, m) cells where the posterior of P = C S is least certain.

    The score of a cell is the width of the central ``interval`` credible
    interval of P(selected | z, m) = C S -- the absolute uncertainty of the
    quantity an LF code multiplies by, which is automatically small where P
    is certainly 0 or 1.  With ``relative=True`` the width is divided by the
    median (floored at 0.01), favouring the faint tail.

    Parameters
    ----------
    sf_or_draws : SelectionFunction or ndarray
        A fitted selection function, or draws of P on the grid with shape
        ``(n_draws, len(z_grid), len(m_grid))``.
    z_grid, m_grid : array_like
        Candidate redshifts and magnitudes [AB mag].
    n : int
        Number of cells to return.

    Returns
    -------
    numpy structured array, length min(n, n_cells), fields ``z``, ``mag``,
    ``score``, ``median``, ``width``; sorted by decreasing score (ties by z, m).
    """
    z_grid = np.asarray(z_grid, float).ravel()
    m_grid = np.asarray(m_grid, float).ravel()
    if hasattr(sf_or_draws, "grid_quantiles"):
        lo, hi = 0.5 - 0.5 * interval, 0.5 + 0.5 * interval
        med, qlo, qhi = sf_or_draws.grid_quantiles("P", z_grid, m_grid, quantiles=(0.5, lo, hi))
    else:
        d = np.asarray(sf_or_draws, float)
        if d.ndim != 3 or d.shape[1:] != (len(z_grid), len(m_grid)):
            raise ValueError(f"draws must have shape (n_draws, {len(z_grid)}, {len(m_grid)}), "
                             f"not {d.shape}")
        med, qlo, qhi = np.quantile(d, [0.5, 0.5 - 0.5 * interval, 0.5 + 0.5 * interval], axis=0)
    width = qhi - qlo
    score = width / np.maximum(med, 0.01) if relative else width
    zz, mm = np.meshgrid(z_grid, m_grid, indexing="ij")
    order = np.lexsort((mm.ravel(), zz.ravel(), -score.ravel()))[: int(n)]
    out = np.empty(len(order), dtype=[("z", float), ("mag", float), ("score", float),
                                      ("median", float), ("width", float)])
    out["z"], out["mag"] = zz.ravel()[order], mm.ravel()[order]
    out["score"], out["median"] = score.ravel()[order], med.ravel()[order]
    out["width"] = width.ravel()[order]
    return out
