"""Noise models of real images: weight-map rescaling and correlated noise.

Drizzled and PSF-matched mosaics have correlated noise: neighbouring pixels
share input photons, so the pixel-to-pixel scatter is *smaller* than a
weight map predicts while the noise of a sum over many pixels is *larger*
than the uncorrelated sum of the pixel variances. No single noise map gets
both the detection threshold (per pixel) and the photometric errors (sums)
right. This module supplies the two corrections SExtractor users apply:

* :func:`weight_rescale_factor` -- ``WEIGHT_TYPE MAP_WEIGHT``: the weight map
  is taken as *relative*; its RMS is scaled by one factor per image so that it
  matches the pixel noise measured on the image itself (SExtractor compares
  the weight-map variance with the background variance it measures in each
  mesh and scales by their median ratio). Detection thresholds are then in
  units of the true pixel noise.
* :class:`CorrelatedNoise` -- the ratio ``r(N)`` of the measured scatter of
  sums over ``N`` empty pixels (random apertures placed off every source) to
  the scatter the noise map predicts for them, ``sqrt(sum rms^2)``, kept as a
  table in ``N`` (uncorrelated noise with a correct map: ``r = 1``;
  correlated noise: ``r`` grows with ``N``; the empirical version of
  ``sigma(N) = sigma_1 alpha N^beta`` of Labbe et al. 2003). Photometric
  errors multiply the background part of their variance by ``r(N)^2`` for the
  number of pixels ``N`` they sum.

All functions take numpy arrays and return numbers or arrays; nothing here
reads files.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from glaciar.engine.blocks import row_blocks

__all__ = ["weight_rescale_factor", "empty_aperture_scatter", "background_excess", "rise_exponent",
           "MAX_RISE_EXPONENT", "robust_sigma", "map_scale_ratio", "map_type_problem",
           "MAP_TYPE_FACTOR", "empty_sky_distance", "distance_cap",
           "empty_sky", "EmptySky", "source_margin", "CorrelatedNoise",
           "DEFAULT_EMPTY_APERTURE_RADII_PIX", "MIN_EMPTY_APERTURES"]

#: Radii of the empty apertures [pixels]: from ~3 pixels (the scale of a
#: drizzle kernel) to ~200 pixels (a faint galaxy's isophotal area).
#: Radii avoid distances at which pixel centres lie exactly on the circle
#: (1, sqrt 2, 2, ...), so each aperture holds a well-defined set of pixels.
#: The 0.5-pixel "aperture" is one pixel: r(1), the pixel noise over the map.
DEFAULT_EMPTY_APERTURE_RADII_PIX = (0.5, 1.2, 1.7, 2.2, 3.2, 4.2, 6.2, 8.2, 11.2)
#: Fewest apertures of one radius for its scatter to enter the fit: with n
#: apertures the clipped scatter has a relative error of ~1/sqrt(2n) (9 % at 60).
MIN_EMPTY_APERTURES = 60
#: Clipping of the aperture sums [sigma]: faint undetected sources in "empty"
#: sky make a positive tail. A Gaussian clipped at +-3 sigma has a standard
#: deviation of 0.98654 sigma, corrected for below.
_CLIP_SIGMA = 3.0
_CLIP_STD_FACTOR = 0.986659
#: Gaussian sigma per median absolute deviation.
_MAD_TO_SIGMA = 1.482602218505602


def weight_rescale_factor(bkg_rms: np.ndarray, map_rms: np.ndarray, usable: np.ndarray) -> float:
    """Scale that makes a relative (weight-map) RMS match the measured pixel noise.

    Parameters
    ----------
    bkg_rms : ndarray
        Pixel noise measured on the image (sep's sigma-clipped background RMS
        mesh, interpolated to pixels) [image units].
    map_rms : ndarray
        RMS from the weight map, ``1/sqrt(weight)`` [image units].
    usable : ndarray of bool
        Pixels with data in both.

    Returns
    -------
    float
        ``median(bkg_rms / map_rms)`` over the usable pixels: multiply
        ``map_rms`` by it (SExtractor's MAP_WEIGHT scaling; a median so that
        a few meshes on bright sources or edges do not move it).
    """
    ok = usable & np.isfinite(bkg_rms) & np.isfinite(map_rms) & (map_rms > 0) & (bkg_rms > 0)
    if not np.any(ok):
        raise ValueError("no pixel with both a measured background RMS and a weight-map RMS")
    return float(np.median(np.asarray(bkg_rms, np.float64)[ok] / np.asarray(map_rms, np.float64)[ok]))


def robust_sigma(x: np.ndarray) -> float:
    """Iteratively 3-sigma-clipped standard deviation, corrected to a Gaussian sigma.

    More efficient than the MAD (relative error ~1/sqrt(2n) against ~1.17/sqrt(n)).
    """
    x = np.asarray(x, dtype=np.float64)
    keep = np.ones(x.size, bool)
    center = np.median(x)
    sigma = _MAD_TO_SIGMA * np.median(np.abs(x - center))     # center: the same median
    for _ in range(10):
        new = np.abs(x - center) <= _CLIP_SIGMA * sigma
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
        center, sigma = np.mean(x[keep]), np.std(x[keep], ddof=1) / _CLIP_STD_FACTOR
    return float(sigma)


#: Pixels per row tile of :func:`empty_sky_distance` with a ``cap`` (~35 bytes of work per pixel).
DISTANCE_TILE_PIXELS = 1 << 22


def empty_sky_distance(usable: np.ndarray, cap: float | None = None,
                       tile_rows: int | None = None) -> np.ndarray:
    """Distance [pixels] of every pixel to the nearest unusable one (outside the image counts).

    The ``distance`` argument of :func:`empty_aperture_scatter`: bands of a field
    that share one ``usable`` mask can share it (one Euclidean distance transform,
    the costliest full-frame step, per field instead of per band).

    Parameters
    ----------
    usable : ndarray of bool, shape (ny, nx)
    cap : float, optional
        Return ``min(distance, cap)``, computed by row tiles that carry
        ``ceil(cap) + 1`` rows beyond them: a pixel within ``cap`` of an unusable
        pixel has it inside its tile, so its distance is the whole-image one bit
        for bit, and a farther pixel's is > ``cap`` in its tile too.  Memory is
        bounded by the tile (the whole-image transform takes ~33 bytes per pixel)
        besides the float64 result.  None: the whole image at once, uncapped.
    tile_rows : int, optional
        Rows per tile with a ``cap`` (default :data:`DISTANCE_TILE_PIXELS` / nx).

    Returns
    -------
    ndarray, float64, shape (ny, nx)
    """
    usable = np.asarray(usable, dtype=bool)
    if cap is None:
        # Outside the image counts as unusable: pad before the distance transform.
        return ndimage.distance_transform_edt(np.pad(usable, 1))[1:-1, 1:-1]
    out = np.empty(usable.shape)
    for y0, y1, d in _capped_distance_tiles(usable, cap, tile_rows):
        out[y0:y1] = d
    return out


def _capped_distance_tiles(usable: np.ndarray, cap: float, tile_rows: int | None):
    """``(y0, y1, d)``: :func:`empty_sky_distance` with ``cap``, rows [y0, y1) at a time."""
    if not float(cap) > 0:
        raise ValueError(f"distance cap must be > 0 pixels, got {cap!r}")
    ny = usable.shape[0]
    halo = int(np.ceil(float(cap))) + 1
    for y0, y1, a, b in row_blocks(usable.shape, DISTANCE_TILE_PIXELS, halo, rows=tile_rows):
        # Unusable border only where the tile meets the image's edge (and at both sides).
        top, bottom = int(a == 0), int(b == ny)
        d = ndimage.distance_transform_edt(np.pad(usable[a:b], ((top, bottom), (1, 1))))
        yield y0, y1, np.minimum(d[top + y0 - a:top + y1 - a, 1:-1], float(cap))


@dataclass(frozen=True, eq=False)
class EmptySky:
    """Where empty apertures can be centred: the pixels of a usable mask farther than each
    of a few distances from every unusable pixel (:func:`empty_sky`).

    What :func:`empty_aperture_scatter` reads of an :func:`empty_sky_distance` map, in
    ~5 bytes per candidate pixel instead of the map's 8 bytes per image pixel.

    Attributes
    ----------
    indices : ndarray of int
        Flat (row-major) indices, ascending, of the pixels farther than ``limits[0]``.
    level : ndarray of uint8
        Per index, how many of ``limits`` its distance exceeds (>= 1).
    limits : tuple of float
        Distances [pixels], ascending.
    """

    indices: np.ndarray
    level: np.ndarray
    limits: tuple

    def beyond(self, limit: float) -> np.ndarray:
        """Flat indices (ascending) of the pixels farther than ``limit``, one of ``limits``."""
        k = self.limits.index(float(limit))
        return self.indices if k == 0 else self.indices[self.level > k]

    def count_beyond(self, limit: float, chunk: int | None = None) -> int:
        """``beyond(limit).size``, counted by chunks of ``chunk`` candidates (no copy of the
        indices)."""
        k = self.limits.index(float(limit))
        if k == 0:
            return int(self.indices.size)
        c = int(chunk or _CHUNK)
        return sum(int(np.count_nonzero(self.level[i:i + c] > k)) for i in range(0, self.level.size, c))

    def take_beyond(self, limit: float, positions: np.ndarray, chunk: int | None = None) -> np.ndarray:
        """``beyond(limit)[positions]`` (same order), found chunk by chunk (``chunk``
        candidates at a time, default 2^22).

        What an aperture draw reads of the candidates: a few thousand of them.  The
        farther limits' candidates are never gathered into one array (5 bytes per
        candidate pixel, ~1 GB on a 16000^2 mosaic), only each chunk's positions.
        """
        k = self.limits.index(float(limit))
        c = int(chunk or _CHUNK)
        positions = np.asarray(positions, dtype=np.int64)
        if k == 0:
            return self.indices[positions]
        out = np.empty(positions.size, dtype=self.indices.dtype)
        order = np.argsort(positions, kind="stable")
        sorted_pos = positions[order]
        start, j = 0, 0                 # candidates before this chunk; next sorted position
        for i in range(0, self.level.size, c):
            if j == sorted_pos.size:
                break
            hit = np.flatnonzero(self.level[i:i + c] > k)
            end = start + hit.size
            stop = j + int(np.searchsorted(sorted_pos[j:], end, side="left"))
            out[order[j:stop]] = self.indices[i + hit[sorted_pos[j:stop] - start]]
            start, j = end, stop
        if j != sorted_pos.size:
            raise IndexError(f"positions up to {int(sorted_pos[-1])} beyond the "
                             f"{start} candidates farther than {limit}")
        return out


def empty_sky(usable: np.ndarray, limits, tile_rows: int | None = None) -> EmptySky:
    """The candidate aperture centres of ``usable`` beyond each distance of ``limits``.

    The same comparisons ``distance > limit`` as on :func:`empty_sky_distance`'s map
    (capped just beyond the largest limit, which leaves them exact), made tile by
    tile: no full-frame distance map is kept.

    Parameters
    ----------
    usable : ndarray of bool, shape (ny, nx)
    limits : sequence of float
        Distances [pixels] (at most 255 distinct values).
    tile_rows : int, optional
        Rows per tile (default :data:`DISTANCE_TILE_PIXELS` / nx).
    """
    usable = np.asarray(usable, dtype=bool)
    lim = tuple(sorted({float(v) for v in limits}))
    if not lim or len(lim) > 255:
        raise ValueError(f"need 1 to 255 distinct distance limits, got {len(lim)}")
    dtype = np.int32 if usable.size < 2 ** 31 else np.int64
    nx = usable.shape[1]
    table = np.asarray(lim)
    # Filled tile by tile: only usable pixels can be candidates (distance > limit > 0), so
    # buffers of that size are never outgrown and no concatenation doubles them.
    n_usable = sum(int(np.count_nonzero(usable[y0:y0 + 256])) for y0 in range(0, usable.shape[0], 256))
    idx = np.empty(n_usable, dtype=dtype)
    lev = np.empty(n_usable, dtype=np.uint8)
    n = 0
    for y0, _, d in _capped_distance_tiles(usable, lim[-1] + 1.0, tile_rows):
        flat = d.reshape(-1)
        i = np.flatnonzero(flat > lim[0])
        # Number of limits strictly below each distance: how many "distance > limit" hold.
        lev[n:n + i.size] = np.searchsorted(table, flat[i], side="left")
        idx[n:n + i.size] = i + y0 * nx
        n += i.size
    # Sized for every usable pixel: shrunk in place to the candidates (the unused tail of
    # a view would stay allocated as long as the EmptySky, across the field's bands).
    idx.resize(n, refcheck=False)
    lev.resize(n, refcheck=False)
    return EmptySky(idx, lev, lim)


def source_margin(segmap: np.ndarray, margin: int, tile_rows: int | None = None) -> np.ndarray:
    """Pixels within ``margin`` steps (4-connected) of a source: ``segmap > 0`` dilated.

    ``scipy.ndimage.binary_dilation(segmap > 0, iterations=margin)``, computed by row
    tiles that carry ``margin`` rows beyond them (a dilation by ``margin`` steps reads
    no farther): the same mask without full-frame temporaries.

    Parameters
    ----------
    segmap : ndarray of int, shape (ny, nx)
    margin : int
        Dilation steps [pixels], >= 1.
    tile_rows : int, optional
        Rows per tile (default :data:`DISTANCE_TILE_PIXELS` / nx).
    """
    from glaciar.engine.detect import release_mapped

    if int(margin) < 1:
        raise ValueError(f"margin must be >= 1 pixel, got {margin!r}")
    out = np.empty(segmap.shape, dtype=bool)
    for y0, y1, a, b in row_blocks(segmap.shape, DISTANCE_TILE_PIXELS, int(margin), rows=tile_rows):
        grown = ndimage.binary_dilation(np.asarray(segmap[a:b]) > 0, iterations=int(margin))
        out[y0:y1] = grown[y0 - a:y1 - a]
        release_mapped(segmap)          # a spilled segmentation's pages, read once
    return out


#: Elements per chunk of :func:`_indices_beyond` and :func:`_keep_beyond`.
_CHUNK = 1 << 22


def _indices_beyond(flat_dist: np.ndarray, limit: float, dtype) -> np.ndarray:
    """``np.flatnonzero(flat_dist > limit)`` as ``dtype``, by chunks (no full-frame temporaries)."""
    parts = [(np.flatnonzero(flat_dist[s:s + _CHUNK] > limit) + s).astype(dtype)
             for s in range(0, flat_dist.size, _CHUNK)]
    return np.concatenate(parts) if parts else np.empty(0, dtype)


def _keep_beyond(flat_dist: np.ndarray, among: np.ndarray, limit: float) -> np.ndarray:
    """``among[flat_dist[among] > limit]`` (order kept), by chunks."""
    parts = [c[flat_dist[c] > limit] for c in (among[s:s + _CHUNK] for s in range(0, among.size, _CHUNK))]
    return np.concatenate(parts) if parts else among[:0]


def distance_cap(radii_pix) -> float:
    """Smallest :func:`empty_sky_distance` cap that leaves :func:`empty_aperture_scatter` exact.

    An aperture of radius r needs distance > r + 1; any cap above the largest r + 1
    keeps every comparison the uncapped distance would make.
    """
    return max(float(r) for r in radii_pix) + 2.0


def empty_aperture_scatter(image: np.ndarray, rms: np.ndarray, usable: np.ndarray,
                           radii_pix=DEFAULT_EMPTY_APERTURE_RADII_PIX, n_per_radius: int = 1000,
                           rng: np.random.Generator | None = None,
                           distance: np.ndarray | None = None, sky: EmptySky | None = None,
                           local: bool = False) -> tuple[np.ndarray, ...]:
    """Measured over predicted scatter of sums in random empty circular apertures.

    Parameters
    ----------
    image : ndarray
        Background-subtracted image without injected sources [image units].
    rms : ndarray
        The noise map used for errors [image units].
    usable : ndarray of bool
        Pixels that are empty sky with data: off every detected source (give
        a dilated segmentation), unmasked, finite.
    radii_pix : sequence of float
        Aperture radii [pixels].
    n_per_radius : int
        Apertures per radius (fewer where the empty sky does not hold them).
    rng : numpy.random.Generator
        Source of the aperture positions (deterministic for a seed).
    distance : ndarray, optional
        :func:`empty_sky_distance` of this ``usable`` mask, if already computed
        (capped at no less than :func:`distance_cap` of ``radii_pix``).
    sky : EmptySky, optional
        Instead of ``distance``: :func:`empty_sky` of this ``usable`` mask with (at
        least) the limits ``r + 1`` of ``radii_pix`` (the same apertures, without a
        full-frame distance map).

    Returns
    -------
    npix : ndarray
        Pixels per aperture of the radii that could be measured (at least :data:`MIN_EMPTY_APERTURES`
        apertures).
    ratio : ndarray
        Clipped scatter (3 sigma, corrected to a Gaussian sigma) of ``sum(image) / sqrt(sum(rms^2))`` over
        the apertures: 1 for uncorrelated noise and a correct map.
    n_apertures : ndarray of int
        Apertures measured per radius.
    ratio_local : ndarray
        Only with ``local=True``: the same ratio for the same apertures, each sum taken
        about its own local background (:func:`_local_background`); NaN where fewer than
        :data:`MIN_EMPTY_APERTURES` apertures have enough empty sky around them.

    Notes
    -----
    Apertures hold whole pixels (pixel centre strictly inside the circle), so
    ``N`` is a pixel count and the ratio measures the
    correlation of the noise alone, as it applies to isophotal sums.
    An aperture is used only where every pixel it touches is usable (distance
    to the nearest unusable pixel > r + 1). Apertures of one radius may
    overlap each other: their sums are then correlated, which widens the
    uncertainty of the scatter but does not bias it.
    """
    rng = np.random.default_rng() if rng is None else rng
    usable = np.asarray(usable, dtype=bool)
    # Memory-mapped images (a large field's spilled arrays) are read by row blocks, their
    # pages dropped as they go (:func:`_gather`), in the local backgrounds' annuli too.
    mapped = isinstance(image, np.memmap) or isinstance(rms, np.memmap)
    image, rms = np.asarray(image), np.asarray(rms)
    radii = [float(r) for r in radii_pix]
    nx = usable.shape[1]
    if sky is None:
        if distance is None:
            distance = empty_sky_distance(usable, cap=distance_cap(radii)) if radii else \
                np.zeros(usable.shape)
        dist = np.asarray(distance)
        if dist.shape != usable.shape:
            raise ValueError(f"distance has shape {dist.shape}, usable {usable.shape}")
        flat_dist = dist.reshape(-1)
        # Candidate centres (flat indices, ascending) for the smallest radius; every larger
        # radius keeps a subset of them, in the same order: one full-frame pass, not one per
        # radius. Chunked, and int32 where the image allows it: no full-frame temporaries.
        index_dtype = np.int32 if flat_dist.size < 2 ** 31 else np.int64
        candidates = _indices_beyond(flat_dist, min(radii) + 1.0, index_dtype) if radii else \
            np.empty(0, index_dtype)

        def count_and_take(limit):
            centres = _keep_beyond(flat_dist, candidates, limit)
            return centres.size, centres.__getitem__
    else:
        def count_and_take(limit):
            # The candidates are counted, and only the drawn ones gathered (EmptySky.take_beyond).
            return sky.count_beyond(limit), lambda pick: sky.take_beyond(limit, pick)
    out_n, out_r, out_k, out_l = [], [], [], []
    for r in radii:
        k = int(np.ceil(r))
        dy, dx = np.mgrid[-k:k + 1, -k:k + 1]
        inside = dy ** 2 + dx ** 2 < r * r
        dy, dx = dy[inside], dx[inside]
        n_centres, take = count_and_take(r + 1.0)
        if n_centres < MIN_EMPTY_APERTURES:
            continue
        pick = rng.choice(n_centres, size=min(n_per_radius, n_centres), replace=False)
        drawn = take(pick)
        # Centred on pixels, whole pixels: every aperture of a radius holds the same pattern.
        iy = drawn[:, None] // nx + dy[None, :]
        ix = drawn[:, None] % nx + dx[None, :]
        # Only the aperture pixels are converted to float64 (no full-frame copies).
        ok = usable[iy, ix]
        flat = iy * nx + ix
        s = np.where(ok, _gather(image, flat).astype(np.float64), 0.0).sum(axis=1)
        v = np.where(ok, _gather(rms, flat).astype(np.float64) ** 2, 0.0).sum(axis=1)
        good = np.isfinite(s) & (v > 0)
        if good.sum() < MIN_EMPTY_APERTURES:
            continue
        out_n.append(float(dy.size))
        out_r.append(robust_sigma(s[good] / np.sqrt(v[good])))
        out_k.append(int(good.sum()))
        if local:
            out_l.append(_local_ratio(image, rms, usable, drawn, r, dy.size, s, v, good, mapped))
    if local:
        return (np.array(out_n), np.array(out_r), np.array(out_k, dtype=np.int64),
                np.array(out_l, dtype=np.float64))
    return np.array(out_n), np.array(out_r), np.array(out_k, dtype=np.int64)


#: Local background of an empty aperture (:func:`_local_ratio`): an annulus from the
#: aperture radius + ANNULUS_GAP_PIX [pixels] (past the few-pixel correlation length of a
#: drizzle kernel, so aperture and annulus noise are nearly independent) enclosing
#: max(ANNULUS_AREA_FACTOR x N, ANNULUS_MIN_PIXELS) pixels for an aperture of N pixels.
ANNULUS_GAP_PIX = 2.0
ANNULUS_AREA_FACTOR = 4.0
ANNULUS_MIN_PIXELS = 200


def _annulus_offsets(radius: float, npix: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets (dy, dx) of the local-background annulus of an aperture of ``npix`` pixels."""
    r_in = float(radius) + ANNULUS_GAP_PIX
    area = max(ANNULUS_AREA_FACTOR * npix, ANNULUS_MIN_PIXELS)
    r_out = np.sqrt(area / np.pi + r_in * r_in)
    k = int(np.ceil(r_out))
    dy, dx = np.mgrid[-k:k + 1, -k:k + 1]
    d2 = dy ** 2 + dx ** 2
    ring = (d2 >= r_in * r_in) & (d2 < r_out * r_out)
    return dy[ring], dx[ring]


def _local_ratio(image, rms, usable, centres, radius, npix, s, v, good, mapped=False) -> float:
    """The empty-aperture ratio of sums taken about each aperture's local background.

    The background is a plane fitted (weights 1/rms^2) to the usable pixels of the
    aperture's annulus (:func:`_annulus_offsets`; at least half of them usable, else
    the aperture is dropped) and evaluated at the aperture's centre: the aperture is
    symmetric about it, so ``N`` times that value is the plane's sum over it, and a
    background gradient cancels even where the annulus is cut by a masked source.
    Subtracting it adds ``N^2 Var(plane at the centre)`` to the variance the map
    predicts (``[(X^T W X)^-1]_00`` of the fit), which enters the prediction: for
    uncorrelated noise and a correct map the ratio is 1, as without the annulus. For
    correlated noise the ratio is a weighted mean of ``r(N)^2`` and the annulus's own
    ``r^2``, with weight ~N/m <= 1/4 on the latter (equal once r(N) has levelled off).

    Returns
    -------
    float
        Clipped scatter (as :func:`empty_aperture_scatter`), NaN with too few apertures.
    """
    ny, nx = usable.shape
    ay, ax = _annulus_offsets(radius, npix)
    flat, inside = _annulus_pixels(centres, ay, ax, ny, nx)
    ok = usable.reshape(-1)[flat]
    if inside is not None:
        ok &= inside
    # In-memory images are indexed directly; memory maps by row blocks (:func:`_gather`).
    # ``mapped``: the caller's arrays were maps (np.asarray made them plain views of the map,
    # which direct indexing would fault in page by page and keep resident: ~2 GB of file
    # pages for a 16000^2 field's image and RMS).
    take = (lambda a: _gather(a, flat)) if mapped or isinstance(image, np.memmap) or \
        isinstance(rms, np.memmap) else (lambda a: np.asarray(a).reshape(-1)[flat])
    b = np.where(ok, take(image).astype(np.float64), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(ok, 1.0 / take(rms).astype(np.float64) ** 2, 0.0)
    w = np.where(np.isfinite(w) & np.isfinite(b), w, 0.0)
    keep = good & (2 * np.count_nonzero(w > 0, axis=1) >= ay.size)
    if keep.sum() < MIN_EMPTY_APERTURES:
        return float("nan")
    # Plane a + c1 dx + c2 dy by weighted least squares, one 3x3 system per aperture.
    design = np.stack([np.ones(ay.size), ax / float(radius + 1), ay / float(radius + 1)], axis=1)
    w, b = w[keep], b[keep]
    # Sums over the annulus as matrix products (BLAS): sum_k w_nk X_ki X_kj and sum_k w_nk b_nk X_ki.
    normal = (w @ (design[:, :, None] * design[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3)
    rhs = (w * b) @ design
    det = np.linalg.det(normal)
    fine = np.isfinite(det) & (det > 0)
    if fine.sum() < MIN_EMPTY_APERTURES:
        return float("nan")
    inv = np.linalg.inv(normal[fine])
    level = np.einsum("ni,ni->n", inv[:, 0, :], rhs[fine])
    t = s[keep][fine] - npix * level
    var = v[keep][fine] + npix * npix * inv[:, 0, 0]
    return robust_sigma(t / np.sqrt(var))


def _annulus_pixels(centres: np.ndarray, ay: np.ndarray, ax: np.ndarray, ny: int, nx: int):
    """Flat indices of the annulus pixels (rows: apertures) and which lie in the frame.

    Returns ``(flat, inside)``: out-of-frame pixels point at the nearest edge pixel (and
    are False in ``inside``); ``inside`` is None when every pixel is in the frame.  An
    annulus wholly inside the frame is its centre's flat index plus fixed offsets
    (``(cy + ay) nx + cx + ax``): only the apertures near an edge need the per-pixel
    bounds and clipping (~5 % of :func:`_local_ratio`'s CPU saved; its gathers and the
    plane fits' matrix products are the rest).
    """
    cy, cx = centres // nx, centres % nx
    k = int(max(np.abs(ay).max(initial=0), np.abs(ax).max(initial=0)))
    edge = (cy < k) | (cy >= ny - k) | (cx < k) | (cx >= nx - k)
    flat = centres[:, None].astype(np.int64) + (ay * nx + ax).astype(np.int64)[None, :]
    if not edge.any():
        return flat, None
    iy = cy[edge, None] + ay[None, :]
    ix = cx[edge, None] + ax[None, :]
    inside = np.ones(flat.shape, dtype=bool)
    inside[edge] = (iy >= 0) & (iy < ny) & (ix >= 0) & (ix < nx)
    flat[edge] = np.clip(iy, 0, ny - 1) * nx + np.clip(ix, 0, nx - 1)
    return flat, inside


def _gather(a: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """``a.ravel()[flat]`` (same shape as ``flat``), by blocks of rows in index order.

    A whole memory-mapped image (a spilled array of a field's set-up) has its resident
    pages dropped after each block: thousands of scattered apertures would otherwise
    fault in most of its pages and keep them in the process.
    """
    from glaciar.engine.detect import release_mapped

    nx = a.shape[1]
    idx = flat.reshape(-1)
    order = np.argsort(idx, kind="stable")
    srt = idx[order]
    out = np.empty(idx.size, dtype=a.dtype)
    for y0, y1, _, _ in row_blocks(a.shape, DISTANCE_TILE_PIXELS):
        lo, hi = np.searchsorted(srt, (y0 * nx, y1 * nx))
        if hi > lo:
            block = a[y0:y1].reshape(-1)                          # a view: only the pixels read
            out[order[lo:hi]] = block[srt[lo:hi] - y0 * nx]
            release_mapped(a)
    return out.reshape(flat.shape)


@dataclass(frozen=True)
class CorrelatedNoise:
    """Scatter of sums over ``N`` empty pixels relative to the noise map, as a table.

    ``r(N)`` is interpolated linearly in ``log N`` between the measured
    aperture areas and held at its end values outside them (no extrapolation
    to areas never measured). Drizzled noise rises from ``r(1)`` (the pixel
    noise over the map) and levels off once apertures are much larger than the
    correlation length, a shape a single power law does not follow.

    Attributes
    ----------
    npix : tuple of float
        Pixels per aperture, increasing.
    ratio : tuple of float
        Measured ``r(N)``.
    n_apertures : tuple of int
        Apertures behind each ratio (its standard error is ~1/sqrt(2n)).
    mesh_ratio : tuple of float
        Empty unless ``ratio`` was measured about local backgrounds because the sums
        about the background mesh scattered more (:func:`background_excess`): then those
        mesh ratios, per ``npix``, for the record.
    """

    npix: tuple = (1.0,)
    ratio: tuple = (1.0,)
    n_apertures: tuple = ()
    mesh_ratio: tuple = ()

    @classmethod
    def fit(cls, npix, ratio, n_apertures=None) -> "CorrelatedNoise":
        """The table of measurements (finite, positive), sorted by area."""
        npix = np.asarray(npix, dtype=np.float64)
        ratio = np.asarray(ratio, dtype=np.float64)
        n = np.full(npix.size, 1000) if n_apertures is None else np.asarray(n_apertures)
        ok = np.isfinite(npix) & np.isfinite(ratio) & (npix > 0) & (ratio > 0)
        if ok.sum() < 2:
            raise ValueError(f"need empty-aperture scatters at >= 2 areas, got {int(ok.sum())}")
        order = np.argsort(npix[ok], kind="stable")
        return cls(npix=tuple(map(float, npix[ok][order])), ratio=tuple(map(float, ratio[ok][order])),
                   n_apertures=tuple(map(int, n[ok][order])))

    def ratio_at(self, npix) -> np.ndarray:
        """``r(N)`` for sums over ``npix`` pixels."""
        logn = np.log(np.maximum(np.asarray(npix, dtype=np.float64), 1e-300))
        return np.interp(logn, np.log(self.npix), self.ratio)

    def variance_factor(self, npix) -> np.ndarray:
        """Factor on the background variance of a sum over ``npix`` pixels: ``r(N)^2``."""
        return self.ratio_at(npix) ** 2

    def is_identity(self, tolerance: float = 0.05) -> bool:
        """True when every measured ratio is within ``tolerance`` of 1, beyond its noise.

        A ratio from ``n`` apertures has a standard error of ~1/sqrt(2n); a
        measurement counts as 1 when ``|ratio - 1| <= tolerance + 3/sqrt(2n)``.
        """
        ratio = np.asarray(self.ratio, float)
        n = np.asarray(self.n_apertures if self.n_apertures else [1000] * ratio.size, float)
        return bool(np.all(np.abs(ratio - 1.0) <= tolerance + 3.0 / np.sqrt(2.0 * n)))

    def to_dict(self) -> dict:
        """Plain values for the run's manifest (``mesh_ratio`` only where local backgrounds were used)."""
        out = {"npix": list(self.npix), "ratio": list(self.ratio),
               "n_apertures": list(self.n_apertures)}
        if self.mesh_ratio:
            out["mesh_ratio"] = list(self.mesh_ratio)
        return out


#: Largest rise of ln r(N) per ln N over the largest measured areas that counts as
#: correlated noise (:func:`rise_exponent`). Correlated noise levels off (exponent -> 0)
#: once apertures exceed its correlation length; an offset common to the aperture (a
#: background residual) makes the sum's scatter grow like N, i.e. r(N) like N^(1/2).
#: 0.4 sits between: HFF A2744 F105W about local backgrounds rises with 0.28 over
#: N = 57-401 pixels, about a 64-pixel mesh around its large galaxy with 0.45.
MAX_RISE_EXPONENT = 0.4


def background_excess(ratio_mesh, ratio_local, n_apertures, tolerance: float = 0.05) -> np.ndarray:
    """Areas where sums about the background mesh scatter more than about local backgrounds.

    Parameters
    ----------
    ratio_mesh, ratio_local : array_like
        :func:`empty_aperture_scatter`'s ``ratio`` and ``ratio_local`` of the same
        apertures (NaN local ratios never count).
    n_apertures : array_like of int
        Apertures per area (each ratio's relative standard error ~1/sqrt(2n)).
    tolerance : float
        Relative excess always allowed (``noise.identity_tolerance``).

    Returns
    -------
    ndarray of bool
        True where ``ratio_mesh / ratio_local > 1 + tolerance + 3 sqrt(1/n)`` (three
        standard errors of the ratio of two such estimates): the mesh leaves a
        background residual these apertures see. Only an excess counts: a residual
        adds variance to the sums, never removes it; where the local sums scatter
        more (a background curved within the annulus), the mesh's are the better.
    """
    rm = np.asarray(ratio_mesh, np.float64)
    rl = np.asarray(ratio_local, np.float64)
    n = np.maximum(np.asarray(n_apertures, np.float64), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = rm / rl
    return np.isfinite(q) & (rl > 0) & (q > 1.0 + tolerance + 3.0 / np.sqrt(n))


def rise_exponent(npix, ratio) -> float:
    """Least-squares slope of ln r against ln N over the areas within a decade of the largest.

    Parameters
    ----------
    npix, ratio : array_like
        A :class:`CorrelatedNoise` table (areas [pixels], increasing).

    Returns
    -------
    float
        The slope (0 for noise that has levelled off, 1/2 for a coherent offset);
        NaN with fewer than two such areas.
    """
    n = np.asarray(npix, np.float64)
    r = np.asarray(ratio, np.float64)
    sel = (n >= n.max() / 10.0) & (r > 0) if n.size else np.zeros(0, bool)
    if sel.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(n[sel]), np.log(r[sel]), 1)[0])


#: A noise map whose implied pixel sigma differs from the image's measured pixel scatter
#: by more than this factor (either way) is refused (:func:`map_type_problem`): a weight
#: map read as RMS, or the reverse, is off by orders of magnitude unless sigma ~ 1.
#: Drizzled noise (pixel scatter 0.5-0.8 x the map) and maps a few times off (what
#: detection.WEIGHT_TYPE: MAP_WEIGHT rescales) stay well inside it.
MAP_TYPE_FACTOR = 30.0
#: The other reading of a refused map is named as the fix when it fits within this factor
#: (a map that fits neither reading that well is more likely in the wrong units).
MAP_TYPE_ALTERNATIVE_FACTOR = 5.0


def _implied_sigma(noise_map: np.ndarray, noise_type: str) -> np.ndarray:
    """Per-pixel sigma a noise map states when read as ``noise_type`` (NaN without data)."""
    a = np.asarray(noise_map, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        good = np.isfinite(a) & (a > 0)
        return np.where(good, 1.0 / np.sqrt(a) if noise_type == "weight" else a, np.nan)


def map_scale_ratio(science: np.ndarray, noise_map: np.ndarray, noise_type: str) -> float:
    """Median sigma the map implies over the robust pixel scatter of the image (same pixels).

    Parameters
    ----------
    science : ndarray
        Science pixels [image units] (a sample is enough: :func:`glaciar.survey.strided_sample`).
    noise_map : ndarray, same shape
        Weight (inverse variance) or RMS map [image units^-2 or image units].
    noise_type : {"weight", "rms"}

    Returns
    -------
    float
        ``median(implied sigma) / robust_sigma(science)`` over pixels with data in
        both (exact zeros of the science image excluded: fill, not sky); NaN when fewer
        than 100 such pixels or the image has no scatter (nothing to compare).
    """
    sig = _implied_sigma(noise_map, noise_type)
    sci = np.asarray(science, np.float64)
    ok = np.isfinite(sig) & np.isfinite(sci) & (sci != 0.0)
    if ok.sum() < 100:
        return float("nan")
    scatter = robust_sigma(sci[ok])
    if not scatter > 0:
        return float("nan")
    return float(np.median(sig[ok]) / scatter)


def map_type_problem(science: np.ndarray, noise_map: np.ndarray, noise_type: str) -> str | None:
    """Why a noise map cannot be what ``noise_type`` says, in one line without the path, or None.

    Refused when the implied sigma is more than :data:`MAP_TYPE_FACTOR` times off the
    image's pixel scatter (:func:`map_scale_ratio`); the fix named is the other
    ``survey.noise_type`` when that reading fits within :data:`MAP_TYPE_ALTERNATIVE_FACTOR`,
    else the map's units.
    """
    q = map_scale_ratio(science, noise_map, noise_type)
    if not np.isfinite(q) or 1.0 / MAP_TYPE_FACTOR <= q <= MAP_TYPE_FACTOR:
        return None
    other = "rms" if noise_type == "weight" else "weight"
    q_other = map_scale_ratio(science, noise_map, other)
    said = f"implied sigma {q:.3g}x the image's pixel scatter"
    if np.isfinite(q_other) and 1.0 / MAP_TYPE_ALTERNATIVE_FACTOR <= q_other <= MAP_TYPE_ALTERNATIVE_FACTOR:
        kind = "an RMS" if other == "rms" else "a weight (inverse-variance)"
        return (f"survey.noise_type is {noise_type} but the map looks like {kind} map ({said}; "
                f"read as {other}: {q_other:.3g}x); set survey.noise_type: {other}")
    return (f"survey.noise_type is {noise_type} but the map does not fit the image's noise "
            f"({said}; read as {other}: {q_other:.3g}x); check that the map is in the science "
            "image's units (or, for a relative weight map, set detection.WEIGHT_TYPE: MAP_WEIGHT)")
