"""Speed of source placement: the free-space-map sampler against the former O(n)-retry one.

Run:  python benchmarks/placement.py            (about two minutes on one core)
      python benchmarks/placement.py --quick    (skips the old sampler's slowest rows)

For each case it prints n requested, n placed, the wall time and the time per placed
source, for the current :func:`glaciar.engine.positions.draw_positions` ("new") and
for the sampler it replaced ("old", its code copied below from commit 842ac6d so the
comparison does not depend on git), and the ratio of times.  Box half sizes are
integers drawn uniformly (seeded), the same for both samplers; each case also prints
:func:`placement_capacity` (upper bound, random fill).

Cases:

* ``open``: a 1000 x 1000 footprint, half sizes 10-25 px (isolation boxes of
  typical high-z sources plus two PSF FWHMs on HST/JWST pixels), n = 10 ... 10^6;
* ``crowded``: a 600 x 600 footprint with a chip gap and masked stars, half sizes
  20-45 px (large low-z sources), n = 50 (fits), 100 and 5000 (more than fits).

The old sampler gives up after 200 batches of 4n candidates, each checked against
every source already placed, so on a full field it spends up to 800 n x placed
candidate checks before giving up (and places fewer when it gives up before the field
is full); for n = 10^6 it would draw 4 x 10^6 candidates per batch and is
not run ("-").

Measured (2 shared cores, busy; numpy 2.4): open field, all placed: 0.008-0.02 ms per
source, 2-10x less than old.  n = 1000 and 5000 (about 430 fit): 0.07-0.08 s per call
against 15-19 s and 40-69 s for old, 150-730x less time per placed source; n = 10^6: 449
placed in 0.06 s (old: hangs).  Crowded field: n = 100 places 53 in 0.006 s (old: 55 in
0.5-1.1 s), n = 5000 places 54 in 0.007 s (old: 54 in 31-58 s), ~4000x.  Both samplers
fill a field to about the same count (random sequential jamming); old times vary ~2x
with machine load.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from glaciar.engine.positions import draw_positions, placement_capacity  # noqa: E402


def draw_positions_old(rng: np.random.Generator, footprint: np.ndarray, half_height: np.ndarray,
                       half_width: np.ndarray, *, max_batches: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """The former sampler (glaciar/engine/positions.py at 842ac6d), code unchanged, comments dropped."""
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
            xs[placed] = np.clip(xs[placed], ix - 0.5 + 1e-9, ix + 0.5 - 1e-9)
            ys[placed] = np.clip(ys[placed], iy - 0.5 + 1e-9, iy + 0.5 - 1e-9)
            placed += 1
    return xs[:placed], ys[:placed]


def _crowded_footprint() -> np.ndarray:
    fp = np.ones((600, 600), bool)
    fp[280:300, :] = False                      # chip gap
    yy, xx = np.mgrid[:600, :600]
    for cy, cx, r in ((120, 150, 40), (450, 420, 60), (500, 100, 30)):
        fp[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = False   # masked stars
    return fp


def _time(fn, *args, repeat: int = 1) -> tuple[float, int]:
    best, m = np.inf, 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        x, _ = fn(*args)
        best = min(best, time.perf_counter() - t0)
        m = x.size
    return best, m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip old-sampler runs expected to take > 10 s")
    args = ap.parse_args()
    cases = [
        ("open", np.ones((1000, 1000), bool), (10, 26), [10, 100, 300, 1000, 5000, 10**6]),
        ("crowded", _crowded_footprint(), (20, 46), [50, 100, 5000]),
    ]
    print(f"{'case':8s} {'n_req':>8s} | {'new placed':>10s} {'new s':>8s} {'ms/src':>7s} | "
          f"{'old placed':>10s} {'old s':>8s} {'ms/src':>7s} | {'old/new':>8s}")
    for name, fp, (lo, hi), ns in cases:
        sizes = np.random.default_rng(123)
        for n in ns:
            hh, hw = sizes.integers(lo, hi, n), sizes.integers(lo, hi, n)
            t_new, m_new = _time(draw_positions, np.random.default_rng(1), fp, hh, hw,
                                 repeat=3 if n <= 1000 else 1)
            slow = n >= 10**5 or (args.quick and (n >= 1000 or (name == "crowded" and n > 50)))
            if slow:
                old = f"{'-':>10s} {'-':>8s} {'-':>7s} | {'-':>8s}"
            else:
                t_old, m_old = _time(draw_positions_old, np.random.default_rng(1), fp, hh, hw)
                old = (f"{m_old:10d} {t_old:8.3f} {1e3 * t_old / max(m_old, 1):7.3f} | "
                       f"{(t_old / max(m_old, 1)) / (t_new / max(m_new, 1)):7.0f}x")
            print(f"{name:8s} {n:8d} | {m_new:10d} {t_new:8.3f} {1e3 * t_new / max(m_new, 1):7.3f} | {old}",
                  flush=True)
        t0 = time.perf_counter()
        cap = placement_capacity(fp, hh[:1000], hw[:1000])
        print(f"{name:8s} placement_capacity: upper_bound {cap.upper_bound}, random_fill "
              f"{cap.random_fill} ({time.perf_counter() - t0:.2f} s)")
    print("old/new: ratio of the times per placed source.")


if __name__ == "__main__":
    main()
