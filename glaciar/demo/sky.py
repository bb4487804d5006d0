"""Exposure, footprint and the background sources of the demo field."""
from __future__ import annotations

import math

import numpy as np

from ..constants import (COL_AXIS_RATIO, COL_PA, COL_R_EFF_ARCSEC, COL_R_EFF_PIX, COL_SERSIC_N,
                         COL_X, COL_Y)
from .bands import (DEMO_BANDS, COLOUR_SCATTER_MAG, COUNT_BREAK_MAG, COUNT_SLOPE_BRIGHT,
                    COUNT_SLOPE_FAINT, MAG_RANGE_F160W, SED_TYPES, SUPERSAMPLE,
                    TRUNCATION_R_EFF)


# --------------------------------------------------------------------------
# Exposure and footprint
# --------------------------------------------------------------------------
_TILT_DEG = 4.0          # detector footprint tilted against the north-up drizzle grid


def dither_coverage(shape: tuple[int, int], rows: tuple[int, int] | None = None) -> np.ndarray:
    """Fraction of the three dithered exposures covering each pixel (0, 1/3, 2/3, 1).

    ``rows = (y0, y1)`` computes only image rows ``y0 <= y < y1`` of the field of
    ``shape`` (every pixel's value is elementwise, so a strip equals the same rows of
    the whole map bit for bit).
    """
    ny, nx = shape
    y0, y1 = (0, ny) if rows is None else rows
    yy = np.arange(y0, y1, dtype=np.float64)[:, None] - 0.5 * (ny - 1)
    xx = np.arange(nx, dtype=np.float64)[None, :] - 0.5 * (nx - 1)
    c, s = math.cos(math.radians(_TILT_DEG)), math.sin(math.radians(_TILT_DEG))
    dither = 0.015 * np.array([[0.0, 0.0], [1.0, 0.5], [-0.5, 1.0]]) * min(ny, nx)
    margin = 0.01 * min(ny, nx)
    # Half sides such that every tilted exposure fits inside the image with the margin.
    half_x = (0.5 * nx - margin - np.abs(dither[:, 0]).max()) / (c + s)
    half_y = (0.5 * ny - margin - np.abs(dither[:, 1]).max()) / (c + s)
    coverage = np.zeros((y1 - y0, nx))
    for dx, dy in dither:
        u = (xx - dx) * c + (yy - dy) * s
        v = -(xx - dx) * s + (yy - dy) * c
        coverage += (np.abs(u) <= half_x) & (np.abs(v) <= half_y)
    return coverage / len(dither)


def relative_exposure(coverage: np.ndarray, band: str, shape: tuple[int, int] | None = None,
                       row0: int = 0) -> np.ndarray:
    """Relative exposure map of ``band`` (1 = the nominal depth; 0 = no data), deterministic.

    ``coverage`` may be the strip of rows ``row0 ...`` of a field of ``shape``
    (:func:`dither_coverage` with ``rows``); the result is then the same strip of the whole map.
    """
    ny, nx = coverage.shape if shape is None else shape
    yy = np.arange(row0, row0 + coverage.shape[0], dtype=np.float64)[:, None] - 0.5 * (ny - 1)
    xx = np.arange(nx, dtype=np.float64)[None, :] - 0.5 * (nx - 1)
    # Smooth exposure gradient (flat-field / pixel-area / pointing differences), +-~12 %.
    xh, yh = xx / (0.5 * nx), yy / (0.5 * ny)
    tilt = {"f160w": (0.12, -0.08), "f098m": (-0.10, 0.06), "f125w": (0.08, 0.10),
            "f606w": (-0.06, -0.12)}[band]
    exposure = coverage * (1.0 + tilt[0] * xh + tilt[1] * yh + 0.04 * (xh ** 2 + yh ** 2 - 2.0 / 3.0))
    if band == "f606w":
        # UVIS chip gap, partly filled by the dithers: a half-depth stripe across the field.
        c, s = math.cos(math.radians(_TILT_DEG)), math.sin(math.radians(_TILT_DEG))
        v = -xx * s + yy * c
        exposure *= np.where(np.abs(v - 0.12 * ny) <= 0.02 * ny, 0.5, 1.0)
    else:
        # IR "blobs": small patches of lowered sensitivity.
        for fy, fx in ((-0.20, 0.20), (0.22, -0.15)):
            blob = (yy - fy * ny) ** 2 + (xx - fx * nx) ** 2 <= (0.03 * min(ny, nx)) ** 2
            exposure = np.where(blob, 0.8 * exposure, exposure)
    return exposure


# --------------------------------------------------------------------------
# Sources
# --------------------------------------------------------------------------
def _sample_counts_magnitudes(rng: np.random.Generator, n: int) -> np.ndarray:
    """F160W magnitudes from the broken power-law counts on [19, 29] (exact inverse CDF).

    dN/dm ~ 10^(0.3 m) up to H = 25 and ~ 10^(0.15 m) beyond, continuous at the
    break: the flattening of deep near-IR counts.  A single 0.3 slope normalised
    to a non-confused total would leave 3-4x too few galaxies at the magnitudes
    that are detected (H < 27), hence too little blending with real sources.
    """
    lo, hi = MAG_RANGE_F160W
    a1, a2 = COUNT_SLOPE_BRIGHT * math.log(10.0), COUNT_SLOPE_FAINT * math.log(10.0)
    # Counts per magnitude are exp(a1 (m - mb)) below the break, exp(a2 (m - mb)) above.
    n1 = (1.0 - math.exp(-a1 * (COUNT_BREAK_MAG - lo))) / a1
    n2 = (math.exp(a2 * (hi - COUNT_BREAK_MAG)) - 1.0) / a2
    u = rng.uniform(size=n) * (n1 + n2)
    bright = u < n1
    mag = np.empty(n)
    mag[bright] = COUNT_BREAK_MAG + np.log(np.exp(-a1 * (COUNT_BREAK_MAG - lo)) + a1 * u[bright]) / a1
    mag[~bright] = COUNT_BREAK_MAG + np.log1p(a2 * (u[~bright] - n1)) / a2
    return mag


class _ArrayFootprint:
    """The footprint's pixels in row-major order (``np.nonzero``'s), from the whole boolean map."""

    def __init__(self, footprint: np.ndarray):
        self._fy, self._fx = np.nonzero(footprint)
        self.size = int(self._fy.size)
        # Stars keep 3 pixels off the low edges (their PSF files are centred on a pixel).
        self._inner = np.flatnonzero((self._fy > 2) & (self._fx > 2))
        self.n_inner = int(self._inner.size)

    def pixels(self, k):
        """(y, x) of the footprint pixels of row-major ranks ``k``."""
        return self._fy[k], self._fx[k]

    def inner_pixels(self, j):
        """(y, x) of the inner (y > 2 and x > 2) footprint pixels of ranks ``j`` among those."""
        return self.pixels(self._inner[j])


class RowFootprint:
    """As :class:`_ArrayFootprint` without ever holding the whole map.

    ``rows(y0, y1)`` returns the footprint's rows ``y0 <= y < y1`` (bool); the
    per-row pixel counts are taken once, strip by strip, and a rank is located
    by its row (cumulative counts) and recomputing that row: the same pixels as
    ``np.nonzero`` of the whole map, so the population drawn from it is the same.
    """

    def __init__(self, rows, ny: int, strip_rows: int):
        self._rows, self._ny, self._strip = rows, int(ny), int(strip_rows)
        counts, inner = np.zeros(ny, np.int64), np.zeros(ny, np.int64)
        for y0 in range(0, ny, self._strip):
            m = rows(y0, min(y0 + self._strip, ny))
            counts[y0:y0 + m.shape[0]] = m.sum(axis=1)
            inner[y0:y0 + m.shape[0]] = m[:, 3:].sum(axis=1)
        inner[:3] = 0
        self._cum, self._cum_inner = np.cumsum(counts), np.cumsum(inner)
        self.size = int(self._cum[-1]) if ny else 0
        self.n_inner = int(self._cum_inner[-1]) if ny else 0

    def _locate(self, k, cum, first_col: int):
        k = np.asarray(k, dtype=np.int64)
        y = np.searchsorted(cum, k, side="right")
        offset = k - np.concatenate([[0], cum])[y]
        x = np.zeros(k.shape, dtype=np.int64)
        for y0 in np.unique(y // self._strip) * self._strip:
            in_strip = (y >= y0) & (y < y0 + self._strip)
            m = self._rows(int(y0), min(int(y0) + self._strip, self._ny))
            for yy in np.unique(y[in_strip]):
                sel = y == yy
                cols = np.flatnonzero(m[yy - y0])
                x[sel] = cols[cols >= first_col][offset[sel]]
        return y, x

    def pixels(self, k):
        return self._locate(k, self._cum, 0)

    def inner_pixels(self, j):
        return self._locate(j, self._cum_inner, 3)


def draw_population(rng: np.random.Generator, footprint, n_galaxies: int,
                     n_stars: int, pixel_scale_arcsec: float):
    """Catalogue of the injected real population (galaxies first, then stars).

    ``footprint``: the boolean map, or a :class:`RowFootprint` (same draws, same catalogue).
    """
    from astropy.table import Table

    fp = footprint if hasattr(footprint, "pixels") else _ArrayFootprint(footprint)
    if fp.size == 0:
        raise ValueError("demo field has an empty footprint; use a larger shape")
    # Galaxies: uniform inside the footprint, continuous sub-pixel positions.
    pick = rng.integers(0, fp.size, size=n_galaxies)
    py, px = fp.pixels(pick)
    gx = px + rng.uniform(-0.5, 0.5, size=n_galaxies)
    gy = py + rng.uniform(-0.5, 0.5, size=n_galaxies)
    mag_h = _sample_counts_magnitudes(rng, n_galaxies)
    fractions = np.array([t[1] for t in SED_TYPES])
    sed = rng.choice(len(SED_TYPES), size=n_galaxies, p=fractions / fractions.sum())
    sersic_n = np.empty(n_galaxies)
    q = np.empty(n_galaxies)
    size_offset = np.empty(n_galaxies)
    mags = {"f160w": mag_h}
    for b in DEMO_BANDS[1:]:
        mags[b] = np.empty(n_galaxies)
    for k, (_, _, colours, n_range, q_range, dlogr) in enumerate(SED_TYPES):
        sel = sed == k
        m = int(sel.sum())
        sersic_n[sel] = rng.uniform(*n_range, size=m)
        q[sel] = rng.uniform(*q_range, size=m)
        size_offset[sel] = dlogr
        for b in DEMO_BANDS[1:]:
            mags[b][sel] = mag_h[sel] + colours[b] + rng.normal(0.0, COLOUR_SCATTER_MAG, size=m)
    # Magnitude-size relation: r_e = 0.28" at H = 24, shrinking by 0.08 dex per magnitude,
    # 0.2 dex log-normal scatter (roughly the CANDELS H-band relation of faint galaxies).
    log_re = -0.55 - 0.08 * (mag_h - 24.0) + size_offset + rng.normal(0.0, 0.2, size=n_galaxies)
    r_eff_arcsec = np.clip(10.0 ** log_re, 0.04, 1.5)
    pa = rng.uniform(0.0, 180.0, size=n_galaxies)

    # Stars: on pixel centres (so a star is exactly the PSF sampled on the grid), the first
    # two bright, the rest faint; colours of G-M dwarfs.
    # (rng.choice of the n_inner ranks draws what rng.choice of the array of them draws.)
    pick = rng.choice(fp.n_inner, size=n_stars, replace=False) if n_stars else np.zeros(0, int)
    sy, sx = fp.inner_pixels(pick)
    sx, sy = sx.astype(float), sy.astype(float)
    n_bright = min(2, n_stars)
    star_h = np.concatenate([rng.uniform(18.0, 19.5, n_bright), rng.uniform(20.0, 24.5, n_stars - n_bright)])
    v_minus_h = rng.uniform(0.6, 2.5, n_stars)
    star_mags = {"f160w": star_h, "f098m": star_h + 0.1 + 0.2 * v_minus_h,
                 "f125w": star_h + 0.05 + 0.1 * v_minus_h, "f606w": star_h + v_minus_h}

    ntot = n_galaxies + n_stars
    table = Table()
    table["id"] = np.arange(1, ntot + 1)
    table[COL_X] = np.concatenate([gx, sx])
    table[COL_Y] = np.concatenate([gy, sy])
    for b in DEMO_BANDS:
        table[f"mag_{b}"] = np.concatenate([mags[b], star_mags[b]])
    table[COL_R_EFF_ARCSEC] = np.concatenate([r_eff_arcsec, np.zeros(n_stars)])
    table[COL_R_EFF_PIX] = table[COL_R_EFF_ARCSEC] / pixel_scale_arcsec
    table[COL_SERSIC_N] = np.concatenate([sersic_n, np.full(n_stars, np.nan)])
    table[COL_AXIS_RATIO] = np.concatenate([q, np.ones(n_stars)])
    table[COL_PA] = np.concatenate([pa, np.zeros(n_stars)])
    table["is_star"] = np.concatenate([np.zeros(n_galaxies, bool), np.ones(n_stars, bool)])
    table["sed_type"] = [SED_TYPES[k][0] for k in sed] + ["star"] * n_stars
    return table


def sersic_stamp_fast(x: float, y: float, r_eff_pix: float, n: float, q: float, pa_deg: float,
                       shape: tuple[int, int]):
    """Unit-flux Sersic stamp for the *background scene*, clipped to the image.

    Scene realism, not injection accuracy, is the goal here: a 4x4 supersampled
    analytic profile on the pixel grid, truncated at 5 r_e and normalised to
    unit sum over the truncated profile (so the catalogue flux is all inside
    5 r_e; for n = 4 the untruncated profile would have ~15 % outside).  Errors
    are ~10 % on the central pixel of sub-pixel galaxies.  Injected sources use
    :mod:`glaciar.galaxy.sersic`, which integrates the profile accurately.

    Returns
    -------
    (y0, x0, stamp) or None if the stamp misses the image.
    """
    from scipy.special import gammaincinv

    b_n = gammaincinv(2.0 * n, 0.5)
    r_max = TRUNCATION_R_EFF * r_eff_pix
    half = max(2, int(math.ceil(r_max + 1.0)))
    ix, iy = int(round(x)), int(round(y))
    ss = SUPERSAMPLE
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    gx = (np.arange(ix - half, ix + half + 1)[:, None] + sub[None, :]).ravel() - x
    gy = (np.arange(iy - half, iy + half + 1)[:, None] + sub[None, :]).ravel() - y
    c, s = math.cos(math.radians(pa_deg)), math.sin(math.radians(pa_deg))
    u = gx[None, :] * c + gy[:, None] * s
    v = -gx[None, :] * s + gy[:, None] * c
    r = np.sqrt(u ** 2 + (v / q) ** 2)
    img = np.where(r <= r_max, np.exp(-b_n * (r / r_eff_pix) ** (1.0 / n)), 0.0)
    size = 2 * half + 1
    img = img.reshape(size, ss, size, ss).sum(axis=(1, 3))
    img /= img.sum()
    ny, nx = shape
    y0, x0 = iy - half, ix - half
    ya, xa = max(y0, 0), max(x0, 0)
    yb, xb = min(y0 + size, ny), min(x0 + size, nx)
    if ya >= yb or xa >= xb:
        return None
    return ya, xa, img[ya - y0:yb - y0, xa - x0:xb - x0]


