"""Cost of band magnitudes at many redshifts: the z lattice against one exact table per z.

A ``grid.box`` run has a new z for nearly every task.  This times
``glaciar.galaxy.sed.band_magnitudes`` for K box redshifts (a shifted Halton
sequence over z = 9-11, the demo's four bands) with the lattice (the default)
against the exact table at every z, each from a cold cache, and prints the
ratio and the largest difference between the two.

    python benchmarks/box_colours.py [--points K]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from glaciar.box import box_points
from glaciar.galaxy import sed
from glaciar.galaxy.filters import get_filter

BANDS = ["wfc3_uvis_f606w", "wfc3_ir_f098m", "wfc3_ir_f125w", "wfc3_ir_f160w"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--points", type=int, default=400)
    args = p.parse_args()
    filters = [get_filter(b) for b in BANDS]
    zs = [z for z, _ in box_points((9.0, 11.0), (25.0, 28.0), args.points, seed=1)]
    beta = np.random.default_rng(0).normal(-2.0, 0.4, 100)
    mag = np.full(beta.size, 26.0)

    sed._band_table.cache_clear()
    t0 = time.process_time()
    exact = [np.stack([sed._band_table(z, f, "inoue14").colour(beta) for f in filters], 1)
             for z in zs]
    t_exact = time.process_time() - t0

    sed._band_table.cache_clear()
    t0 = time.process_time()
    lat = [sed.band_magnitudes(z, beta, filters, mag=mag, detection_index=3) for z in zs]
    t_lattice = time.process_time() - t0

    diff = max(float(np.nanmax(np.abs(np.where(np.isfinite(m), m, 0)
                                      - np.where(np.isfinite(m), 26.0 + e - e[:, 3:4], 0))))
               for m, e in zip(lat, exact))
    print(f"{args.points} box redshifts x {len(BANDS)} bands: exact table per z "
          f"{t_exact:.2f} s CPU, lattice {t_lattice:.2f} s CPU, ratio "
          f"{t_exact / t_lattice:.1f}x; largest difference {diff:.2e} mag")


if __name__ == "__main__":
    main()
