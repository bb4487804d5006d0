"""What a task's stored counts are keyed on, shared by the store and the tables.

The names of the per-status counts and the global lattice of the measured magnitude
m_obs on which :func:`glaciar.store.task_histogram` bins sources and from which
:func:`glaciar.tables.transfer_from_histograms` rebuilds the transfer matrices.  A leaf
(numpy and :mod:`glaciar.constants` only), so that ``store`` (which writes the counts)
and ``tables`` (which reads them and writes files through ``store``) do not import each
other.
"""
from __future__ import annotations

import numpy as np

from . import constants as C

__all__ = ["STATUS_COLUMNS", "TRANSFER_MOBS_STEP", "MOBS_BIN_FAINT", "MOBS_BIN_BRIGHT",
           "mobs_lattice_edge", "mobs_lattice_index"]

#: summary column of each status code
STATUS_COLUMNS = {code: f"n_status_{code}" if code >= 0 else f"n_status_m{-code}"
                  for code in C.STATUS_CODES}

#: Width of a bin of the m_obs lattice [mag] (anchored at 0 mag).
TRANSFER_MOBS_STEP = C.TRANSFER_MOBS_STEP
#: Overflow bins of the m_obs lattice (int32 extremes): NaN or +inf measured magnitude (flux
#: <= 0) and sources not recovered in the faint one, -inf in the bright one.
MOBS_BIN_FAINT = np.iinfo(np.int32).max
MOBS_BIN_BRIGHT = np.iinfo(np.int32).min


def mobs_lattice_edge(b) -> np.ndarray:
    """Lower edge [mag] of lattice bin ``b`` of the measured magnitude: ``b * TRANSFER_MOBS_STEP``
    rounded to 1e-6 mag, as :func:`glaciar.tables.transfer_matrix` rounds its default edges."""
    return np.round(np.asarray(b, float) * TRANSFER_MOBS_STEP, 6)


def mobs_lattice_index(m_obs) -> np.ndarray:
    """Index ``b`` of the lattice bin [edge(b), edge(b + 1)) holding each measured magnitude.

    The global lattice of ``TRANSFER_MOBS_STEP`` anchored at 0 mag (:func:`mobs_lattice_edge`);
    NaN and +inf give ``MOBS_BIN_FAINT``, -inf ``MOBS_BIN_BRIGHT`` (int32).
    """
    m = np.asarray(m_obs, float)
    fin = np.isfinite(m)
    lim = float(MOBS_BIN_FAINT - 2)
    b = np.floor(np.clip(np.where(fin, m, 0.0) / TRANSFER_MOBS_STEP, -lim, lim))
    # floor(m / step) can miss by one against the rounded edges: correct both ways.
    b = np.where(m < mobs_lattice_edge(b), b - 1, b)
    b = np.where(m >= mobs_lattice_edge(b + 1), b + 1, b)
    out = np.where(fin, b, np.where(m == -np.inf, MOBS_BIN_BRIGHT, MOBS_BIN_FAINT))
    return out.astype(np.int32)
