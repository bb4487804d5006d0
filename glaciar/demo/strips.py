"""The demo field by strips of rows, for mosaics too large to build in memory.

:func:`iter_demo_strips` yields the science and weight pixels of every band
strip by strip (top to bottom), so :func:`~glaciar.demo.survey.build_demo_survey`
can stream them into the FITS files with memory bounded by the strip size
(peak RSS 1.2-1.4 GB from 4000^2 to 16000^2, measured) instead of the ~200 bytes
per pixel of :func:`~glaciar.demo.images.make_demo_images`.

It is the same field as :func:`make_demo_images` with the same seed:

* exposure, coverage and weights are elementwise, computed on the strip's rows:
  bit-identical;
* the population is drawn from the same streams through the footprint's row
  counts (:class:`~glaciar.demo.sky.RowFootprint`): the same catalogue;
* every galaxy stamp is rendered once (kept while strips still touch it) and added
  in catalogue order, like the whole-image scene;
* the PSF convolution of a strip reads the scene ``RENDER_PSF_SIZE // 2`` rows
  beyond it (zero beyond the image edge, as the whole-image ``fftconvolve``):
  the model equals the whole-image one up to FFT rounding (~1e-16 of the
  brightest pixel), which is the only difference;
* the sky noise draws the same white normals in the same (row-major) order and
  convolves them with the drizzle kernel over the strip plus the kernel's
  half-width on each side, wrapping at the top and bottom edges as the
  whole-image noise does (the image's last rows are drawn once ahead, from a copy
  of the stream): bit-identical; the shot-noise normals likewise.

The FFT rounding means a float32 pixel may differ in its last bit from
:func:`make_demo_images`' output, so :func:`build_demo_survey` uses this path only
above ``STRIP_MIN_PIXELS`` and the default demo and the tests' fields stay
byte-identical.
"""
from __future__ import annotations

from typing import Iterator

import numpy as np

from ..constants import COL_AXIS_RATIO, COL_PA, COL_R_EFF_PIX, COL_SERSIC_N, COL_X, COL_Y
from .bands import (DEMO_BANDS, DEMO_BANDS_SPEC, DEMO_FIELD, DEMO_PIXEL_SCALE_ARCSEC,
                    RENDER_PSF_SIZE, TRUNCATION_R_EFF)
from .images import (band_science_weight, band_setup, check_arguments, check_noise_scale,
                     psf_file_image)
from .sky import (RowFootprint, dither_coverage, draw_population, relative_exposure,
                  sersic_stamp_fast)

#: Above this many pixels :func:`build_demo_survey` writes the images strip by strip
#: (the whole-image generator's peak is ~200 bytes per pixel: ~0.8 GB at 2048^2).
STRIP_MIN_PIXELS = 2048 * 2048
#: Pixels per strip (rows = this / nx, at least 64): ~250 bytes per strip pixel at the peak
#: (four bands' scenes with the PSF's halo rows, FFT buffers, noise and output strips).
STRIP_PIXELS = 4_000_000


def strip_rows_for(shape: tuple[int, int]) -> int:
    """Rows per strip for an image of ``shape`` (ny, nx)."""
    return int(min(shape[0], max(64, STRIP_PIXELS // max(int(shape[1]), 1))))


class _WrappedWhiteRows:
    """Rows of a white-noise image drawn row-major from ``rng``, read with top/bottom wrap.

    ``rows(a, b)`` returns image rows ``a <= y < b`` where ``a`` may be down to
    ``-halo`` and ``b`` up to ``ny + halo`` (row ``y`` then means ``y mod ny``);
    successive calls must not go back.  The last ``halo`` rows are drawn ahead
    from a copy of the stream (discarding the rows before them), the first
    ``halo`` rows are kept when they are drawn.
    """

    def __init__(self, seed_sequence, shape: tuple[int, int], halo: int, chunk_rows: int):
        self._ny, self._nx = shape
        self._halo = int(halo)
        self._rng = np.random.default_rng(seed_sequence)
        self._buf = np.zeros((0, self._nx))
        self._buf_start = 0                 # image row of self._buf[0]
        self._tail = self._head = np.zeros((0, self._nx))
        if self._halo:
            ahead = np.random.default_rng(seed_sequence)
            left = self._ny - self._halo
            while left > 0:
                n = min(left, chunk_rows)
                ahead.standard_normal((n, self._nx))
                left -= n
            self._tail = ahead.standard_normal((self._halo, self._nx))

    def rows(self, a: int, b: int) -> np.ndarray:
        drawn = self._buf_start + self._buf.shape[0]
        stop = min(b, self._ny)
        if stop > drawn:
            new = self._rng.standard_normal((stop - drawn, self._nx))
            self._buf = np.concatenate([self._buf, new]) if self._buf.size else new
        if self._head.shape[0] < self._halo and self._buf_start == 0:
            self._head = self._buf[:self._halo].copy()
        # Rows before max(a, 0) are never read again.
        lo = max(a, 0)
        if lo > self._buf_start:
            self._buf = self._buf[lo - self._buf_start:]
            self._buf_start = lo
        parts = []
        if a < 0:
            parts.append(self._tail[self._halo + a:])
        parts.append(self._buf[:stop - self._buf_start])
        if b > self._ny:
            parts.append(self._head[:b - self._ny])
        return np.concatenate(parts) if len(parts) > 1 else parts[0]


def _unit_noise_strip(white: _WrappedWhiteRows, y0: int, y1: int, kernel_1d: np.ndarray) -> np.ndarray:
    """Rows ``y0:y1`` of :func:`~glaciar.demo.noise.correlated_unit_noise` (bit-identical)."""
    from scipy.ndimage import convolve1d

    h = kernel_1d.size // 2
    w = white.rows(y0 - h, y1 + h)
    # Along y the strip carries its halo, so the inner rows see exactly the whole-image
    # neighbours (mode irrelevant there); along x every row is whole, wrapped as before.
    along_y = convolve1d(w, kernel_1d, axis=0, mode="wrap")[h:h + (y1 - y0)]
    return convolve1d(along_y, kernel_1d, axis=1, mode="wrap")


def iter_demo_strips(shape: tuple[int, int] = (1000, 1000), *, seed: int = 2018,
                     pixel_scale_arcsec: float = DEMO_PIXEL_SCALE_ARCSEC,
                     source_density_arcmin2: float = 250.0, n_galaxies: int | None = None,
                     n_stars: int = 6, field: str = DEMO_FIELD, noise_scale=1.0,
                     strip_rows: int | None = None) -> tuple[dict, Iterator]:
    """The demo field of :func:`~glaciar.demo.images.make_demo_images`, strip by strip.

    Parameters are those of :func:`make_demo_images`, plus

    strip_rows : int, optional
        Rows per strip (default :func:`strip_rows_for`).  ``noise_scale`` may be a
        number or an array of the image shape (e.g. a memory map); it is read by strips.

    Returns
    -------
    info : dict
        ``"truth"``, ``"psf"``, ``"psf_pixel_scale_arcsec"``, ``"rms_nominal"`` and
        ``"field"`` as :func:`make_demo_images` returns them (no ``"model"``).
    strips : iterator of (y0, y1, science, weight)
        Image rows ``y0 <= y < y1`` and ``{band: float32 (y1 - y0, nx)}`` science
        [e-/s] and weight [(e-/s)^-2] pixels, top to bottom, covering the image once.
        Consume it once, in order.
    """
    shape = check_arguments(shape, pixel_scale_arcsec, source_density_arcmin2, n_galaxies, n_stars)
    ny, nx = shape
    noise_scale = check_noise_scale(noise_scale, shape)
    rows_per = strip_rows_for(shape) if strip_rows is None else int(strip_rows)
    if rows_per < 1:
        raise ValueError(f"strip_rows must be >= 1, got {strip_rows!r}")
    streams = np.random.SeedSequence(int(seed)).spawn(1 + 2 * len(DEMO_BANDS))
    rng_pop = np.random.default_rng(streams[0])

    def footprint_rows(y0, y1):
        return relative_exposure(dither_coverage(shape, (y0, y1)), DEMO_BANDS[0], shape, y0) > 0

    footprint = RowFootprint(footprint_rows, ny, rows_per)
    if n_galaxies is None:
        area_arcmin2 = footprint.size * (pixel_scale_arcsec / 60.0) ** 2
        n_galaxies = int(round(source_density_arcmin2 * area_arcmin2))
    truth = draw_population(rng_pop, footprint, int(n_galaxies), int(n_stars), pixel_scale_arcsec)

    setup = {b: band_setup(b, pixel_scale_arcsec) for b in DEMO_BANDS}
    info = {"truth": truth, "field": str(field),
            "psf": {b: psf_file_image(b) for b in DEMO_BANDS},
            "psf_pixel_scale_arcsec": {b: DEMO_BANDS_SPEC[b].psf_pixel_scale_arcsec for b in DEMO_BANDS},
            "rms_nominal": {b: float(setup[b][2]) for b in DEMO_BANDS}}
    return info, _strips(shape, truth, streams, setup, noise_scale, rows_per)


def _strips(shape, truth, streams, setup, noise_scale, rows_per):
    from scipy.signal import fftconvolve

    ny, nx = shape
    halo = RENDER_PSF_SIZE // 2          # rows of scene the PSF carries into a strip
    flux = {b: 10.0 ** (-0.4 * (np.asarray(truth[f"mag_{b}"]) - DEMO_BANDS_SPEC[b].zeropoint))
            for b in DEMO_BANDS}
    cols = [np.asarray(truth[c], dtype=np.float64)
            for c in (COL_X, COL_Y, COL_R_EFF_PIX, COL_SERSIC_N, COL_AXIS_RATIO, COL_PA)]
    is_star = np.asarray(truth["is_star"])
    galaxies = np.flatnonzero(~is_star)
    stars = np.flatnonzero(is_star)
    # Conservative row reach of every galaxy stamp (the stamp itself is clipped exactly).
    reach = np.ceil(TRUNCATION_R_EFF * cols[2][galaxies] + 2.0) + 1.0
    g_lo, g_hi = cols[1][galaxies] - reach, cols[1][galaxies] + reach
    star_y = np.asarray(truth[COL_Y], dtype=np.int64)[stars]
    star_x = np.asarray(truth[COL_X], dtype=np.int64)[stars]
    white = {b: _WrappedWhiteRows(streams[1 + 2 * k], shape, setup[b][1].size // 2, rows_per)
             for k, b in enumerate(DEMO_BANDS)}
    poisson = {b: np.random.default_rng(streams[2 + 2 * k]) for k, b in enumerate(DEMO_BANDS)}
    stamps: dict[int, tuple | None] = {}

    for y0 in range(0, ny, rows_per):
        y1 = min(y0 + rows_per, ny)
        lo, hi = y0 - halo, y1 + halo          # scene rows the strip's model reads
        scene = {b: np.zeros((hi - lo, nx)) for b in DEMO_BANDS}
        for j in np.flatnonzero((g_hi >= lo) & (g_lo < hi)):
            i = int(galaxies[j])
            if i not in stamps:
                stamps[i] = sersic_stamp_fast(*(float(c[i]) for c in cols), shape)
            if stamps[i] is None:
                continue
            sy, sx, img = stamps[i]
            a, b_ = max(sy, lo), min(sy + img.shape[0], hi)
            if a >= b_:
                continue
            part = img[a - sy:b_ - sy]
            for b in DEMO_BANDS:
                scene[b][a - lo:b_ - lo, sx:sx + img.shape[1]] += flux[b][i] * part
        for i, y, x in zip(stars, star_y, star_x):
            if lo <= y < hi:
                for b in DEMO_BANDS:
                    scene[b][y - lo, x] += flux[b][i]
        # Stamps no later strip reads are dropped.
        for j in np.flatnonzero(g_hi < y1 - halo):
            stamps.pop(int(galaxies[j]), None)

        coverage = dither_coverage(shape, (y0, y1))
        science, weight = {}, {}
        for b in DEMO_BANDS:
            psf_image, kernel_1d, rms_nominal = setup[b]
            model = fftconvolve(scene.pop(b), psf_image, mode="same")[halo:halo + (y1 - y0)]
            exposure = relative_exposure(coverage, b, shape, y0)
            science[b], weight[b] = band_science_weight(
                model, exposure, rms_nominal, noise_scale[y0:y1],
                _unit_noise_strip(white[b], y0, y1, kernel_1d), poisson[b],
                DEMO_BANDS_SPEC[b].exptime_s)
        yield y0, y1, science, weight


__all__ = ["STRIP_MIN_PIXELS", "STRIP_PIXELS", "iter_demo_strips", "strip_rows_for"]
