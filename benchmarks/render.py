"""Speed and accuracy of pixel-integrated Sersic stamps versus per-pixel dblquad.

Run:  python benchmarks/render.py      (about a minute on one core)

For Sersic n = 1 and 4 and r_eff = 0.3, 1, 3, 10 px (axis ratio 0.7,
PA 30 deg, centre offset (+0.23, -0.31) px from the stamp centre, stamp shape
from ``stamp_shape(..., enclosed_fraction=0.995)``) it prints, for the default
tolerance and cheaper ones:

* the time per stamp (best of a few repeats);
* max |pixel error| / flux against a reference render that integrates every
  pixel edge with a brute-force fixed rule (panels 0.1 wide in w, 20
  Gauss-Legendre nodes each), itself checked below against tight adaptive
  dblquad (epsabs 1e-13) on the sampled pixels;
* the time a per-pixel ``dblquad`` (epsabs = epsrel = 1.49e-8, GLACiAR's
  settings) takes for the stamp, measured on the pixel holding the centre plus
  7 random pixels and extrapolated to the stamp, and the speed ratio; first
  with a lean pure-``math`` integrand (the stricter comparison), then with the
  integrand written as GLACiAR writes it (numpy functions on scalars);
* the error of that dblquad on the sampled pixels, for comparison.
"""
from __future__ import annotations

import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from scipy import integrate

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from glaciar.galaxy.sersic import (  # noqa: E402
    DEFAULT_TOLERANCE,
    _render,
    sersic_bn,
    sersic_stamp,
    stamp_shape,
)

Q, PA = 0.7, 30.0
OFFSET = (0.23, -0.31)
SETTINGS = [DEFAULT_TOLERANCE, 1e-7, 1e-5, 1e-3]
GLACIAR_EPS = 1.49e-8


def profile(n, r_eff, q, pa, x0, y0):
    b = sersic_bn(n)
    c, s = math.cos(math.radians(pa)), math.sin(math.radians(pa))
    i_e = b ** (2 * n) / (2 * math.pi * q * r_eff ** 2 * n * math.exp(b) * math.gamma(2 * n))

    def intensity(y, x):
        dx, dy = x - x0, y - y0
        r = math.hypot(dx * c + dy * s, (-dx * s + dy * c) / q)
        return i_e * math.exp(-b * ((r / r_eff) ** (1 / n) - 1))
    return intensity


def profile_numpy_scalar(n, r_eff, q, pa, x0, y0):
    """The same integrand written the way GLACiAR's code does (numpy on scalars)."""
    b = sersic_bn(n)
    c, s = np.cos(np.radians(pa)), np.sin(np.radians(pa))
    i0 = b ** (2 * n) / (2 * np.pi * q * r_eff ** 2 * n * math.gamma(2 * n))

    def intensity(y, x):
        dx, dy = x - x0, y - y0
        r = np.sqrt((dx * c + dy * s) ** 2 + ((-dx * s + dy * c) / q) ** 2)
        return i0 * np.exp(-b * (r / r_eff) ** (1 / n))
    return intensity


def dblquad_pixel(f, ix, iy, eps, split_at=None):
    xs, ys = [ix - 0.5, ix + 0.5], [iy - 0.5, iy + 0.5]
    if split_at is not None:       # put the cusp on sub-rectangle corners
        x0, y0 = split_at
        if xs[0] < x0 < xs[1]:
            xs.insert(1, x0)
        if ys[0] < y0 < ys[1]:
            ys.insert(1, y0)
    return sum(integrate.dblquad(f, xa, xb, ya, yb, epsabs=eps, epsrel=eps if eps > 1e-12 else 1e-11)[0]
               for xa, xb in zip(xs[:-1], xs[1:]) for ya, yb in zip(ys[:-1], ys[1:]))


def timed_pixel(f, ix, iy):
    """GLACiAR-settings dblquad of one pixel: (value, best of 2 wall times)."""
    times = []
    for _ in range(2):
        t = time.perf_counter()
        value = dblquad_pixel(f, ix, iy, GLACIAR_EPS)
        times.append(time.perf_counter() - t)
    return value, min(times)


def best_time(fn, budget=0.5):
    fn()
    times = []
    start = time.perf_counter()
    while len(times) < 3 or (time.perf_counter() - start < budget and len(times) < 50):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main():
    rng = np.random.default_rng(42)
    header = (f"{'n':>3} {'r_e':>5} {'shape':>9} {'tolerance':>9} {'t/stamp':>9} "
              f"{'max|err|':>8} {'dblquad/stamp':>13} {'speed-up':>8} {'dblquad err':>11} "
              f"{'GLACiAR-style':>13} {'speed-up':>8}")
    print(header)
    print("-" * len(header))
    ref_check = 0.0
    for n in (1.0, 4.0):
        for r_eff in (0.3, 1.0, 3.0, 10.0):
            shape = stamp_shape(n, r_eff, Q, PA)
            ny, nx = shape
            center = ((nx - 1) / 2 + OFFSET[0], (ny - 1) / 2 + OFFSET[1])
            reference = _render(n, r_eff, Q, PA, shape, center, DEFAULT_TOLERANCE,
                                 panel_width=0.1, order=20)

            # GLACiAR-style per-pixel dblquad, timed on a few pixels
            f = profile(n, r_eff, Q, PA, *center)
            cx, cy = int(round(center[0])), int(round(center[1]))
            others = [(int(rng.integers(nx)), int(rng.integers(ny))) for _ in range(7)]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", integrate.IntegrationWarning)
                central, t_central = timed_pixel(f, cx, cy)
                rest, t_rest = zip(*(timed_pixel(f, ix, iy) for ix, iy in others))
                t_other = float(np.mean(t_rest))
                f_np = profile_numpy_scalar(n, r_eff, Q, PA, *center)
                t_central_np = timed_pixel(f_np, cx, cy)[1]
                t_other_np = float(np.mean([timed_pixel(f_np, ix, iy)[1] for ix, iy in others]))
                tight = [dblquad_pixel(f, ix, iy, 1e-13, split_at=center)
                         for ix, iy in [(cx, cy)] + others]
            sampled = [(cx, cy)] + others
            ref_vals = np.array([reference[iy, ix] for ix, iy in sampled])
            dbl_err = np.max(np.abs(np.array([central, *rest]) - ref_vals))
            ref_check = max(ref_check, np.max(np.abs(np.array(tight) - ref_vals)))
            t_dblquad = t_central + t_other * (nx * ny - 1)
            t_dblquad_np = t_central_np + t_other_np * (nx * ny - 1)

            for tol in SETTINGS:
                stamp = sersic_stamp(n, r_eff, Q, PA, shape=shape, center=center, tolerance=tol)
                err = np.max(np.abs(stamp - reference))
                t_stamp = best_time(lambda: sersic_stamp(n, r_eff, Q, PA, shape=shape,
                                                         center=center, tolerance=tol))
                label = f"{tol:.0e}" + ("*" if tol == DEFAULT_TOLERANCE else "")
                print(f"{n:>3.0f} {r_eff:>5.1f} {f'{ny}x{nx}':>9} {label:>9} "
                      f"{t_stamp * 1e3:>7.2f}ms {err:>8.1e} {t_dblquad:>12.2f}s "
                      f"{t_dblquad / t_stamp:>8.0f} {dbl_err:>11.1e} "
                      f"{t_dblquad_np:>12.2f}s {t_dblquad_np / t_stamp:>8.0f}", flush=True)
    print("-" * len(header))
    print("* default.  errors are fractions of the total flux; speed-ups are dblquad time / stamp time.")
    print(f"reference render vs tight adaptive dblquad on the sampled pixels: max |diff| = {ref_check:.1e}")


if __name__ == "__main__":
    main()
