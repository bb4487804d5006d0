"""Toy images shared by tests (not collected: no ``test_`` prefix)."""
from __future__ import annotations

import numpy as np


def exponential_galaxy(xx, yy, x0, y0, flux, r, q=1.0, pa=0.0):
    """An exponential profile of total ``flux`` (before pixelisation), scale length ``r``
    [pixels], axis ratio ``q`` and position angle ``pa`` [rad], on the grids ``xx``, ``yy``."""
    dx, dy = xx - x0, yy - y0
    u = dx * np.cos(pa) + dy * np.sin(pa)
    v = (-dx * np.sin(pa) + dy * np.cos(pa)) / q
    return flux * np.exp(-np.hypot(u, v) / r) / (2 * np.pi * r * r * q)
