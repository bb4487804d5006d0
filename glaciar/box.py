"""Injection points drawn continuously over a (z, m) box (``grid.box``).

The box expands into ``n_points`` (z, m) points of a randomly shifted Halton
sequence (bases 2 and 3; a Cranley-Patterson rotation by a shift derived from
the run's seed), rounded to ``BOX_Z_RESOLUTION`` and ``BOX_MAG_RESOLUTION``.
Why this construction:

* it is a pure function of (box, n, seed) computed with integer arithmetic and
  IEEE operations only, so the points are the same on every machine and with
  any numpy / scipy version (scipy's scrambled sequences depend on its random
  generator and have changed between releases);
* the first K points do not depend on ``n_points`` (a prefix of the sequence),
  so a store simulated with K points is extended, not redone, by a larger K;
* rounded values are short decimals, so task keys, manifests and YAML/JSON
  round-trips stay exact (the points flow through ``grid.cells``'s machinery).

The unshifted sequence is the one ``scipy.stats.qmc.Halton(d=2,
scramble=False)`` gives (tested against it).
"""
from __future__ import annotations

import hashlib

import numpy as np

from .constants import BOX_MAG_RESOLUTION, BOX_Z_RESOLUTION

__all__ = ["halton", "box_shift", "box_points", "box_lattice", "box_bin_edges"]

_BASES = (2, 3)
#: Values per axis of the candidate lattice over a box (``glaciar next``, ``--adaptive``):
#: about sqrt(n_points), within these bounds, before the midpoints are added.
LATTICE_MIN, LATTICE_MAX = 3, 17
#: Box points per bin (on average) of the binned summary tables (``box_summary_*.ecsv``).
POINTS_PER_BIN = 4
#: Largest number of bins per axis of the binned summary tables.
BINS_MAX = 20


def halton(n: int, start: int = 0) -> np.ndarray:
    """Points ``start .. start + n - 1`` of the 2-D Halton sequence (bases 2, 3), shape (n, 2).

    Point ``i`` is (radical inverse of i in base 2, in base 3); point 0 is (0, 0).
    The digit reversal is exact integer arithmetic, then one division.
    """
    idx = np.arange(start, start + n, dtype=np.int64)
    out = np.empty((n, 2))
    for j, b in enumerate(_BASES):
        rev = np.zeros(n, dtype=np.int64)
        denom = 1
        rest = idx.copy()
        while np.any(rest > 0):
            rev = rev * b + rest % b
            rest //= b
            denom *= b
        # rev was built with a common number of digits: rev / b^digits is the radical inverse.
        out[:, j] = rev / denom
    return out


def box_shift(seed: int) -> np.ndarray:
    """The rotation (two numbers in [0, 1)) that randomises the sequence for a run seed.

    BLAKE2b of ``"glaciar.box:<seed>"``: two 52-bit integers / 2**52 (exact floats).
    """
    h = hashlib.blake2b(f"glaciar.box:{int(seed)}".encode("ascii"), digest_size=16).digest()
    a, b = (int.from_bytes(h[i:i + 8], "little") >> 12 for i in (0, 8))
    return np.array([a, b], dtype=float) / 2.0 ** 52


def box_points(z_range, mag_range, n: int, seed: int) -> list[tuple[float, float]]:
    """The first ``n`` (z, mag) points of the box for a run seed.

    Parameters
    ----------
    z_range, mag_range : (float, float)
        Box edges, lo < hi [z; AB mag].
    n : int
        Number of points (>= 0).
    seed : int
        The run's seed (``simulation.seed``).

    Returns
    -------
    list of (float, float)
        Points rounded to ``BOX_Z_RESOLUTION`` / ``BOX_MAG_RESOLUTION`` and
        clipped inside the box (edges rounded inwards); in sequence order.
    """
    u = np.mod(halton(int(n)) + box_shift(seed), 1.0)
    out = []
    for (lo, hi), res, col in ((z_range, BOX_Z_RESOLUTION, 0), (mag_range, BOX_MAG_RESOLUTION, 1)):
        lo, hi = float(lo), float(hi)
        k = np.rint((lo + u[:, col] * (hi - lo)) / res)
        k = np.clip(k, np.ceil(lo / res - 1e-9), np.floor(hi / res + 1e-9))
        out.append(k)
    zk, mk = out
    # Decimal rounding of the integer multiple: the float nearest to k x resolution.
    nz, nm = _decimals(BOX_Z_RESOLUTION), _decimals(BOX_MAG_RESOLUTION)
    return [(round(float(a) * BOX_Z_RESOLUTION, nz), round(float(b) * BOX_MAG_RESOLUTION, nm))
            for a, b in zip(zk, mk)]


def _decimals(res: float) -> int:
    return max(0, int(round(-np.log10(res))))


def box_lattice(z_range, mag_range, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """A regular (z, mag) lattice over the box, for proposing cells where it is least certain.

    ``ceil(sqrt(n_points))`` values per axis (between ``LATTICE_MIN`` and
    ``LATTICE_MAX``), edges included, named to 1e-6 like the candidates of
    :func:`glaciar.inference.candidate_grid` (cells are keyed by exact values).
    The box's own points are not a lattice: taking their values as candidate
    axes would give n_points**2 candidates.
    """
    n = int(np.clip(np.ceil(np.sqrt(n_points)), LATTICE_MIN, LATTICE_MAX))
    return tuple(np.round(np.linspace(float(lo), float(hi), n), 6)
                 for lo, hi in (z_range, mag_range))


def box_bin_edges(z_range, mag_range, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Equal bins over the box for the binned summary tables, ~``POINTS_PER_BIN`` points each.

    ``round(sqrt(n_points / POINTS_PER_BIN))`` bins per axis (1 to ``BINS_MAX``):
    a low-discrepancy sequence fills such bins almost evenly.
    """
    n = int(np.clip(np.round(np.sqrt(n_points / POINTS_PER_BIN)), 1, BINS_MAX))
    return tuple(np.linspace(float(lo), float(hi), n + 1) for lo, hi in (z_range, mag_range))
