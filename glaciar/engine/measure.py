"""Detect, classify and measure injected sources: the one entry point a task calls.

Windowed detection
------------------
Each injected source is detected in a cut-out *window* of the injected
detection image.  Windows of many sources are tiled into one *canvas*,
separated by masked blank gaps wider than the filter kernel, and extracted with
one ``sep.extract`` call.  A window is grown (and the source re-done in the
next round) until every connected above-threshold region that matters lies at
least ``filter half-width + 1`` pixels inside the window edge (sides on the
image edge excepted, where the full frame has the same edge):

* regions with a pixel in the search box;
* regions touching the bounding boxes of the Kron-radius ellipse (6 a, 6 b),
  the AUTO ellipse and the largest circular aperture (they decide which pixels
  are masked as neighbours).

Then every pixel of those regions has the same filtered value and threshold as
in the full frame, so the regions are identical.

Two sep behaviours would still make a cut-out differ from the full frame, and
both are made window-independent here, identically in ``mode="full"``:

1. *Deblending is random.*  sep (like SExtractor) hands the faint pixels of a
   split region to its children by drawing random numbers from one stream per
   ``sep.extract`` call, so a deblended footprint depends on every region
   processed before it anywhere in the image.  A region with more than one
   segment that contains (part of) a source's search box is therefore
   re-extracted *alone* (same pixels; the RMS set to infinity outside the
   region so nothing else is detected), which makes its deblending
   deterministic.
2. *CLEAN compares objects across the whole image* (within 10 (a1 + a2)), so a
   cut-out changes which spurious objects are removed.  The tiled extraction
   runs with CLEAN off, and CLEAN is applied inside each re-extracted region:
   i.e. CLEAN acts between the deblended children of one region, not between
   separate regions.  Regions with a single segment are unaffected by CLEAN
   in sep (it only removes objects).

With ``filter_type="matched"`` the noise enters the filter and point 1 is only
approximately window-independent.

The reference (original-image) extraction is a plain full-frame sep run with
CLEAN as configured; it is done once per field and shared by both modes.

Speed without changing answers
------------------------------
Each shortcut below only decides *how much* is computed, never a result
(``tests/test_windowed.py``, ``tests/test_windowed_batching.py``):

* the first window is ``DetectionParams.initial_window`` (41 px: most sources
  are exact after one extraction); a side whose required box reaches the
  window edge grows by half the window, other sides just enough;
* canvases are built by :meth:`Scene.paste_windows` (one overlap search per
  canvas, stamps added where windows read them);
* a region's box is the union of its segments' boxes from sep's catalogue;
* a re-extracted (deblended) region is cached by its image position and
  pixels for the whole call, so a later round or an overlapping window reuses
  it (the extraction depends on nothing else);
* band canvases hold only the pixels photometry reads: each detection's
  segment and AUTO/aperture box; the detection band reuses the detection
  canvas; windows that must grow get no band photometry.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
from scipy import ndimage

from glaciar.constants import (COL_FLAGS, FLAG_SATURATED, FLAG_SEP_ERROR, FLAG_WINDOW_AT_LIMIT,
                               STATUS_NOT_DETECTED, band_column)
from glaciar.engine import photometry as phot
from glaciar.engine.classify import ClassificationParams, classify, footprint_overlap, input_pixel, \
    select_detection
from glaciar.engine.detect import DetectionError, DetectionParams, _sep_extract, sanitize
from glaciar.engine.scene import Scene

__all__ = ["FieldReference", "reference_extraction", "measure_injected", "output_columns"]

_BIG_RMS = np.float32(1e30)
_EIGHT = np.ones((3, 3), dtype=bool)   # sep/SExtractor regions are 8-connected
_MAX_CANVAS_PIXELS = 600_000           # keep one sep call's buffers small
_REMOVED = np.int32(2 ** 31 - 1)       # label of pixels whose object CLEAN removed


@dataclass(frozen=True, eq=False)
class FieldReference:
    """Extraction of the original detection image, once per field.

    Attributes
    ----------
    segmap : ndarray of int32
        Full-frame segmentation of the original detection image.
    flux : ndarray
        Detection-band AUTO flux per original id (index id - 1) [image units].
    mag : ndarray
        AUTO magnitude per original id (detection zeropoint); NaN for flux <= 0.
    catalog : structured ndarray or None
        sep's catalogue (row id - 1).
    """

    segmap: np.ndarray
    flux: np.ndarray
    mag: np.ndarray
    catalog: np.ndarray | None = None


def reference_extraction(det_image_sub, det_rms, params: DetectionParams, zeropoint: float,
                         mask=None, photometry=None) -> FieldReference:
    """Extract the original (un-injected) detection image once per field.

    Parameters
    ----------
    det_image_sub : ndarray
        Background-subtracted original detection image [image units].
    det_rms : ndarray
        Per-pixel RMS [image units].
    params : DetectionParams
    zeropoint : float
        AB zeropoint of the detection image.
    mask : ndarray of bool, optional
        True where there are no data.
    photometry : (image, rms), optional
        The band whose AUTO magnitudes the original sources get when it is not
        the detection image (a coadded detection image: fluxes in the
        detection *band*, the band ``zeropoint`` belongs to).

    Returns
    -------
    FieldReference
        Segmentation map and AUTO flux/magnitude per original source
        (MAG_AUTO as SExtractor: Kron factor and minimum radius from
        ``params.phot_autoparams``; neighbours masked).
    """
    data, err, nodata = sanitize(det_image_sub, det_rms, mask)
    cat, seg = _sep_extract(data, err, nodata, params, params.clean)
    n = len(cat)
    if n == 0:
        return FieldReference(seg, np.zeros(0), np.zeros(0), cat)
    ids = np.arange(1, n + 1, dtype=np.int32)
    a, b, th = _shape(cat["a"], cat["b"], cat["theta"])
    kr = phot.kron_radius(data, cat["x"], cat["y"], a, b, th, segmap=seg, seg_id=ids, mask=nodata)
    scale = phot.auto_scale(kr, params.phot_autoparams)
    if photometry is not None:
        data, err, nodata = sanitize(photometry[0], photometry[1], mask)
    flux, _ = phot.auto_photometry(data, err, cat["x"], cat["y"], a, b, th, scale,
                                   segmap=seg, seg_id=ids, mask=nodata)
    mag, _, _ = phot.magnitudes(flux, np.ones_like(flux), zeropoint)
    return FieldReference(seg, flux, mag, cat)


def _shape(a, b, theta):
    # sep requires a >= b >= 0 and |theta| <= pi/2; guard degenerate 1-pixel-wide objects
    a = np.maximum(np.asarray(a, dtype=np.float64), 1e-3)
    b = np.clip(np.asarray(b, dtype=np.float64), 1e-3, a)
    th = np.clip(np.asarray(theta, dtype=np.float64), -np.pi / 2, np.pi / 2)
    return a, b, th


def output_columns(bands, n_apertures: int) -> list[str]:
    """Names of the per-source columns :func:`measure_injected` returns."""
    cols = ["status", "detection_id", COL_FLAGS, "overlap_fraction", "blend_original_id",
            "blend_original_mag", "x_det", "y_det", "flux_auto_template"]
    for b in bands:
        q = ["flux_iso", "fluxerr_iso", "flux_auto", "fluxerr_auto"]
        for k in range(n_apertures):
            q += [f"flux_aper{k}", f"fluxerr_aper{k}"]
        q += ["mag", "magerr", "sn", "maglim"]
        cols += [band_column(x, b) for x in q]
    return cols


# --------------------------------------------------------------------------
# Canvas: tiled windows
# --------------------------------------------------------------------------
def _pack(heights, widths, gap):
    """Shelf-pack rectangles; returns (y offsets, x offsets, canvas shape)."""
    k = len(heights)
    order = np.argsort(-np.asarray(heights), kind="stable")
    area = float(np.sum((np.asarray(heights) + gap) * (np.asarray(widths) + gap)))
    width = int(max(np.max(widths) + 2 * gap, np.sqrt(area) * 1.1))
    oy = np.zeros(k, dtype=np.int64)
    ox = np.zeros(k, dtype=np.int64)
    y = x = gap
    shelf = 0
    for i in order:
        h, w = int(heights[i]), int(widths[i])
        if x + w + gap > width and x > gap:
            y += shelf + gap
            x = gap
            shelf = 0
        oy[i], ox[i] = y, x
        x += w + gap
        shelf = max(shelf, h)
    return oy, ox, (int(y + shelf + gap), int(width))


class _Canvas:
    """Windows of the detection image (and later the bands) tiled into one array."""

    def __init__(self, ctx, rects, full=False):
        self.ctx = ctx
        self.rects = rects                      # (K, 4) y0, y1, x0, x1 image coords
        hh = rects[:, 1] - rects[:, 0]
        ww = rects[:, 3] - rects[:, 2]
        if full:
            self.oy = np.zeros(1, dtype=np.int64)
            self.ox = np.zeros(1, dtype=np.int64)
            self.shape = ctx.shape
        else:
            self.oy, self.ox, self.shape = _pack(hh, ww, ctx.gap)
        self.full = full
        det = np.zeros(self.shape)
        err = np.ones(self.shape, dtype=np.float32)
        nodata = np.ones(self.shape, dtype=bool)
        ref = np.zeros(self.shape, dtype=np.int32)
        ctx.det_scene.paste_windows(det, rects, self.oy, self.ox)
        for k, (y0, y1, x0, x1) in enumerate(rects.tolist()):
            sl = self.slice(k)
            err[sl] = ctx.det_rms[y0:y1, x0:x1]
            nodata[sl] = False if ctx.mask is None else ctx.mask[y0:y1, x0:x1]
            ref[sl] = ctx.ref_segmap[y0:y1, x0:x1]
        with np.errstate(invalid="ignore"):
            nodata |= ~np.isfinite(det) | ~(np.isfinite(err) & (err > 0))
        det[nodata] = 0.0
        err[nodata] = 1.0
        self.det = det
        self.det32 = det.astype(np.float32)
        self.err = err
        self.nodata = nodata
        self.ref = ref

    def slice(self, k):
        y0, y1, x0, x1 = self.rects[k]
        return (slice(self.oy[k], self.oy[k] + y1 - y0), slice(self.ox[k], self.ox[k] + x1 - x0))

    def band(self, name, windows, boxes=None):
        """Band data, RMS and no-data mask on the canvas.

        Only the listed windows are filled, or with ``boxes`` ((K, 4) canvas
        y0, y1, x0, x1 inside those windows) only those parts.  Pixels not
        filled are flagged as no data; no aperture of the sources measured
        reaches them (see ``room`` in :func:`_analyse` and :func:`_band_boxes`).
        """
        ctx = self.ctx
        scene, brms = ctx.band_scenes[name], ctx.band_rms[name]
        if scene is ctx.det_scene and brms is ctx.det_rms and ctx.det_rms.dtype == np.float32:
            # The detection band read through the detection canvas: same pixels, same
            # no-data definition (its RMS is float32, so err's cast changed nothing).
            rms = self.err.astype(np.float64)
            rms[self.nodata] = 0.0
            return self.det, rms, self.nodata
        windows = np.asarray(windows, dtype=np.int64)
        if boxes is None:
            cy, cx = self.oy[windows], self.ox[windows]
            img = self.rects[windows]
        else:
            boxes = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
            keep = (boxes[:, 1] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 2])
            boxes, windows = boxes[keep], windows[keep]
            cy, cx = boxes[:, 0], boxes[:, 2]
            dy = self.rects[windows, 0] - self.oy[windows]      # canvas -> image
            dx = self.rects[windows, 2] - self.ox[windows]
            img = np.stack([boxes[:, 0] + dy, boxes[:, 1] + dy, boxes[:, 2] + dx, boxes[:, 3] + dx], axis=1)
        data = np.zeros(self.shape)
        rms = np.zeros(self.shape)
        scene.paste_windows(data, img, cy, cx)
        for (y0, y1, x0, x1), py, px in zip(img.tolist(), cy.tolist(), cx.tolist()):
            rms[py:py + y1 - y0, px:px + x1 - x0] = brms[y0:y1, x0:x1]
        with np.errstate(invalid="ignore"):
            bad = self.nodata | ~np.isfinite(data) | ~(np.isfinite(rms) & (rms > 0))
        data[bad] = 0.0
        rms[bad] = 0.0
        return data, rms, bad


class _Context:
    def __init__(self, **kw):
        self.__dict__.update(kw)


def _ellipse_half_extent(a, b, theta, r):
    c, s = np.cos(theta), np.sin(theta)
    dx = r * np.sqrt((a * c) ** 2 + (b * s) ** 2)
    dy = r * np.sqrt((a * s) ** 2 + (b * c) ** 2)
    return dy, dx


# --------------------------------------------------------------------------
# Main entry point
# --------------------------------------------------------------------------
def measure_injected(det_scene: Scene, det_rms: np.ndarray, band_scenes: Mapping[str, Scene],
                     band_rms: Mapping[str, np.ndarray], x: np.ndarray, y: np.ndarray,
                     input_flux_det: np.ndarray, input_mag_det: np.ndarray,
                     reference: FieldReference, params: DetectionParams,
                     classification: ClassificationParams, zeropoints: Mapping[str, float],
                     gains: Mapping[str, float | None], detection_band: str,
                     mask: np.ndarray | None = None, mode: str = "windowed",
                     diagnostics: dict | None = None, input_templates=None,
                     noise_models: Mapping | None = None,
                     det_background: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Detect, classify and measure N injected sources.

    Parameters
    ----------
    det_scene : Scene
        Background-subtracted original detection image + injected stamps.
    det_rms : ndarray
        RMS of the original detection image [image units] (detection threshold
        and ISO errors).
    band_scenes, band_rms : mapping band -> Scene / ndarray
        Every measured band, the detection band included.
    x, y : array of float, shape (N,)
        Input positions, 0-based pixels (x along numpy axis 1).
    input_flux_det, input_mag_det : array, shape (N,)
        Total input flux [image units] and AB magnitude in the detection band.
    reference : FieldReference
        Original-image extraction of this field.
    params : DetectionParams
    classification : ClassificationParams
    zeropoints, gains : mapping band -> float / float or None
    detection_band : str
    mask : ndarray of bool, optional
        True where there are no data (all bands).
    mode : {"windowed", "full"}
        ``full`` extracts the whole injected image once (validation).
    diagnostics : dict, optional
        If given, filled with ``"window"``: (N, 4) int array, the last
        window of each source (y0, y1, x0, x1, image pixels; the whole image
        in ``full`` mode), and ``"rounds"``: number of extraction rounds
        (benchmarks; no effect on the results).
    input_templates : sequence of length N, optional
        Per source, its injected detection-band stamp ``(y0, x0, data, flux)``
        (pixels ``data * flux`` [image units] at image row/column y0, x0) or
        None if nothing was injected in that band.  Default: the stamps of
        ``det_scene``, one per source in order.  The status-2 flux test
        compares the detection's AUTO flux with this template's flux through
        the same Kron ellipse and masks (column ``flux_auto_template``; see
        :mod:`glaciar.engine.classify`).
    noise_models : mapping band -> glaciar.engine.noise.CorrelatedNoise, optional
        Correlated-noise models: the background variance of every ISO,
        aperture and AUTO error in that band is scaled by ``r(N)^2``.
    det_background : ndarray, optional
        Background map of the detection band [image units] (what was
        subtracted from its image): a detection is flagged
        ``FLAG_SATURATED`` when its peak plus the background at its centre
        reaches ``params.satur_level`` (SExtractor's rule); None = 0.

    Returns
    -------
    dict of str -> ndarray, each of length N
        See :func:`output_columns`.  Measured quantities are NaN for
        undetected sources; ``detection_id`` is the label of the detection in
        this call's extraction (0 = none; not comparable between modes).
    """
    if mode not in ("windowed", "full"):
        raise ValueError(f"mode must be 'windowed' or 'full', got {mode!r}")
    bands = list(band_scenes)
    if detection_band not in band_scenes:
        raise ValueError(f"detection band {detection_band!r} missing from band_scenes ({', '.join(bands)})")
    for b in bands:
        if b not in band_rms:
            raise ValueError(f"band_rms has no entry for band {b!r}")
        if b not in zeropoints:
            raise ValueError(f"zeropoints has no entry for band {b!r}")
        if band_scenes[b].shape != det_scene.shape:
            raise ValueError(f"band {b!r} image shape {band_scenes[b].shape} differs from the detection image {det_scene.shape}")
    if det_rms.shape != det_scene.shape or reference.segmap.shape != det_scene.shape:
        raise ValueError("det_rms and reference.segmap must have the detection image's shape")
    if classification.sn_definition == "aper" and classification.sn_aperture_index >= len(params.phot_apertures):
        raise ValueError(f"sn_aperture_index {classification.sn_aperture_index} but only "
                         f"{len(params.phot_apertures)} PHOT_APERTURES")
    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    y = np.atleast_1d(np.asarray(y, dtype=np.float64))
    n = x.size
    if y.size != n or np.size(input_flux_det) != n or np.size(input_mag_det) != n:
        raise ValueError("x, y, input_flux_det and input_mag_det must have the same length")

    hw = params.filter_halfwidth
    ctx = _Context(noise_models=dict(noise_models or {}),
                   det_scene=det_scene, det_rms=det_rms, band_scenes=band_scenes, band_rms=band_rms,
                   mask=mask, ref_segmap=reference.segmap, ref_mag=reference.mag, params=params,
                   cls=classification, zeropoints=zeropoints, gains=gains, det_band=detection_band,
                   bands=bands, shape=det_scene.shape, margin=hw + 1,
                   gap=max(hw + 1, 2),
                   input_flux=np.asarray(input_flux_det, dtype=np.float64).ravel(),
                   input_mag=np.asarray(input_mag_det, dtype=np.float64).ravel(), x=x, y=y,
                   templates=_input_templates(det_scene, input_templates, n),
                   det_background=det_background)

    out = {c: np.full(n, np.nan) for c in output_columns(bands, len(params.phot_apertures))}
    out["status"] = np.full(n, STATUS_NOT_DETECTED, dtype=np.int8)
    out["detection_id"] = np.zeros(n, dtype=np.int64)
    out[COL_FLAGS] = np.zeros(n, dtype=np.int32)
    out["blend_original_id"] = np.zeros(n, dtype=np.int64)
    if n == 0:
        if diagnostics is not None:
            diagnostics.update(window=np.zeros((0, 4), dtype=np.int64), rounds=0)
        return out
    ctx.out = out
    ctx.at_max = np.zeros(n, dtype=bool)
    ctx.isolated = {}

    ny, nx = ctx.shape
    if mode == "full":
        rects = np.array([[0, ny, 0, nx]], dtype=np.int64)
        _run_canvas(ctx, np.arange(n), rects, np.zeros(n, dtype=np.int64), full=True)
        if diagnostics is not None:
            diagnostics.update(window=np.repeat(rects, n, axis=0), rounds=1)
        return out

    ix, iy = input_pixel(x, y)
    r = params.initial_window // 2
    if params.backphoto_type == "local":
        # the local-background annulus must fit too: start from a window that holds it
        r = max(r, params.backphoto_thick + 16)
    rects = np.stack([np.clip(iy - r, 0, ny), np.clip(iy + r + 1, 0, ny),
                      np.clip(ix - r, 0, nx), np.clip(ix + r + 1, 0, nx)], axis=1)
    pending = np.arange(n)
    rounds = 0
    while pending.size:
        rounds += 1
        # chunk so one sep call stays small
        areas = (rects[pending, 1] - rects[pending, 0] + ctx.gap) * (rects[pending, 3] - rects[pending, 2] + ctx.gap)
        chunks = np.split(pending, np.flatnonzero(np.diff(np.cumsum(areas) // _MAX_CANVAS_PIXELS)) + 1)
        grow_all = []
        for chunk in chunks:
            grow_all.append(_run_canvas(ctx, chunk, rects[chunk], np.arange(chunk.size), full=False,
                                        all_rects=rects))
        pending = np.concatenate(grow_all) if grow_all else np.zeros(0, dtype=np.int64)
    if diagnostics is not None:
        diagnostics.update(window=rects.copy(), rounds=rounds)
    return out


def _run_canvas(ctx, src, rects, src_win, full, all_rects=None):
    """Extract one canvas; finish what is exact, return sources whose window must grow."""
    try:
        canvas = _Canvas(ctx, rects, full=full)
        cat, seg = _sep_extract(canvas.det32, canvas.err, canvas.nodata, ctx.params, clean=False)
    except DetectionError:
        if len(rects) > 1:   # isolate the failing window(s)
            grow = [_run_canvas(ctx, src[i:i + 1], rects[src_win[i]][None], np.zeros(1, dtype=np.int64),
                                full, all_rects) for i in range(src.size)]
            return np.concatenate(grow)
        ctx.out[COL_FLAGS][src] |= FLAG_SEP_ERROR
        return np.zeros(0, dtype=np.int64)
    return _analyse(ctx, canvas, cat, seg, src, src_win, all_rects)


def _analyse(ctx, cv, cat, seg, src, src_win, all_rects):
    params, cls = ctx.params, ctx.cls
    m = ctx.margin
    ny, nx = ctx.shape
    full = cv.full
    # ---- regions (8-connected components of detected pixels) and their boxes
    comp, ncomp = ndimage.label(seg > 0, structure=_EIGHT)
    nseg = len(cat)
    seg2comp = np.zeros(nseg + 1, dtype=np.int64)
    nzpix = np.flatnonzero(seg)
    seg2comp[seg.ravel()[nzpix]] = comp.ravel()[nzpix]
    segs_per_comp = np.bincount(seg2comp[1:], minlength=ncomp + 1)
    # A region's box is the union of its segments' boxes, which sep's catalogue
    # gives (x/ymin, x/ymax: the extremes of each object's pixels, the same pixels
    # it writes to the segmentation map; no CLEAN here): no scan of the canvas.
    cb = np.zeros((ncomp + 1, 4), dtype=np.int64)
    if ncomp:
        cb[1:, 0] = cb[1:, 2] = np.iinfo(np.int64).max // 4
        cb[1:, 1] = cb[1:, 3] = -(np.iinfo(np.int64).max // 4)
        c = seg2comp[1:]
        np.minimum.at(cb[:, 0], c, np.asarray(cat["ymin"], dtype=np.int64))
        np.maximum.at(cb[:, 1], c, np.asarray(cat["ymax"], dtype=np.int64) + 1)
        np.minimum.at(cb[:, 2], c, np.asarray(cat["xmin"], dtype=np.int64))
        np.maximum.at(cb[:, 3], c, np.asarray(cat["xmax"], dtype=np.int64) + 1)
        cb[0] = 0

    # ---- per-source window geometry on the canvas
    k = src_win
    rect = cv.rects[k]
    wy0 = cv.oy[k]
    wx0 = cv.ox[k]
    wy1 = wy0 + rect[:, 1] - rect[:, 0]
    wx1 = wx0 + rect[:, 3] - rect[:, 2]
    # constrained sides: not on the image edge
    lo_y = np.where(rect[:, 0] > 0, wy0 + m, -10 ** 9)
    hi_y = np.where(rect[:, 1] < ny, wy1 - m, 10 ** 9)
    lo_x = np.where(rect[:, 2] > 0, wx0 + m, -10 ** 9)
    hi_x = np.where(rect[:, 3] < nx, wx1 - m, 10 ** 9)
    cx = ctx.x[src] - rect[:, 2] + wx0
    cy = ctx.y[src] - rect[:, 0] + wy0
    bounds = np.stack([wy0, wy1, wx0, wx1], axis=1)

    grow = np.zeros(src.size, dtype=bool)
    edge = np.zeros(src.size, dtype=bool)
    need = np.stack([cy, cy + 1, cx, cx + 1], axis=1).astype(np.int64)   # canvas bbox required exact

    # region boxes with a neutral entry for background (label 0), so the union of the
    # boxes of the regions touching a bbox needs no filtering
    big = 2 ** 40
    cbn = cb.copy()
    cbn[0] = (big, -big, big, -big)
    lo_y_l, hi_y_l, lo_x_l, hi_x_l = lo_y.tolist(), hi_y.tolist(), lo_x.tolist(), hi_x.tolist()
    need_l = need.tolist()
    H_cv, W_cv = cv.shape

    def check(i, by0, by1, bx0, bx1):
        """Is bbox (canvas) and every region touching it exact for source i?  Updates need[i]."""
        by0, by1 = max(by0, 0), min(by1, H_cv)
        bx0, bx1 = max(bx0, 0), min(bx1, W_cv)
        ry0, ry1, rx0, rx1 = by0, by1, bx0, bx1
        if by1 > by0 and bx1 > bx0:
            sub = comp[by0:by1, bx0:bx1]
            labs = sub[sub > 0]
            if labs.size:
                # the union of the boxes of the regions met (no np.unique: a repeated
                # label only repeats its box)
                b = cbn[labs]
                lo_b, hi_b = b.min(axis=0).tolist(), b.max(axis=0).tolist()
                ry0 = min(ry0, lo_b[0])
                ry1 = max(ry1, hi_b[1])
                rx0 = min(rx0, lo_b[2])
                rx1 = max(rx1, hi_b[3])
        nd = need_l[i]
        nd[0], nd[1], nd[2], nd[3] = min(nd[0], ry0), max(nd[1], ry1), min(nd[2], rx0), max(nd[3], rx1)
        return ry0 >= lo_y_l[i] and ry1 <= hi_y_l[i] and rx0 >= lo_x_l[i] and rx1 <= hi_x_l[i]

    def room(i, by0, by1, bx0, bx1):
        """Apertures running off the image edge are measured on the window alone.

        sep scales aperture sums up for masked pixels but not for pixels
        outside the array, so the blank gap around a window must not enter an
        aperture: such sources are measured on their window cut from the
        canvas, where the image edge is the array edge, as in the full frame.
        """
        if not full and max(wy0[i] - by0, by1 - wy1[i], wx0[i] - bx0, bx1 - wx1[i]) > 0:
            edge[i] = True

    at_max = np.zeros(src.size, dtype=bool) if full else ctx.at_max[src]
    # canvas box holding every band pixel a source's AUTO and circular apertures can touch
    phot_box = np.zeros((src.size, 4), dtype=np.int64)

    def fail(i):
        if at_max[i]:
            ctx.out[COL_FLAGS][src[i]] |= FLAG_WINDOW_AT_LIMIT
        else:
            grow[i] = True

    # ---- stage A: regions in the search box must be exact
    # (vectorised over sources: the regions of each search box, clipped to its window)
    icx, icy = input_pixel(cx, cy)
    h = cls.search_box // 2
    by0, by1 = np.maximum(icy - h, wy0), np.minimum(icy + h + 1, wy1)
    bx0, bx1 = np.maximum(icx - h, wx0), np.minimum(icx + h + 1, wx1)
    box_off = np.arange(-h, h + 1)
    py, px = icy[:, None] + box_off, icx[:, None] + box_off
    inbox = (((py >= by0[:, None]) & (py < by1[:, None]))[:, :, None]
             & ((px >= bx0[:, None]) & (px < bx1[:, None]))[:, None, :])
    box_lab = comp[np.clip(py, 0, H_cv - 1)[:, :, None], np.clip(px, 0, W_cv - 1)[:, None, :]]
    box_lab = np.where(inbox, box_lab, 0).reshape(src.size, -1)
    if not full:
        rb = cbn[box_lab]
        ry0, ry1 = np.minimum(by0, rb[:, :, 0].min(axis=1)), np.maximum(by1, rb[:, :, 1].max(axis=1))
        rx0, rx1 = np.minimum(bx0, rb[:, :, 2].min(axis=1)), np.maximum(bx1, rb[:, :, 3].max(axis=1))
        need = np.stack([np.minimum(need[:, 0], ry0), np.maximum(need[:, 1], ry1),
                         np.minimum(need[:, 2], rx0), np.maximum(need[:, 3], rx1)], axis=1)
        need_l = need.tolist()
        exact = (ry0 >= lo_y) & (ry1 <= hi_y) & (rx0 >= lo_x) & (rx1 <= hi_x)
        for i in np.flatnonzero(~exact):
            fail(i)
    split_in_box = segs_per_comp[box_lab] >= 2

    # ---- canonical (isolated) re-extraction of deblended regions in search boxes
    pseg = seg.astype(np.int64)
    tab = _segment_table(cat)
    next_label = nseg + 1
    done_comps = {}
    sep_failed = np.zeros(src.size, dtype=bool)
    for i in np.flatnonzero(split_in_box.any(axis=1) & ~grow):
        for c in np.unique(box_lab[i][split_in_box[i]]).tolist():
            if c in done_comps:
                if done_comps[c] is None:
                    sep_failed[i] = True
                continue
            try:
                off = (int(rect[i, 0] - wy0[i]), int(rect[i, 2] - wx0[i]))   # canvas -> image
                next_label = _isolate(cv, comp, c, cb[c], bounds[i], pseg, tab, next_label, ctx, off)
                done_comps[c] = True
            except DetectionError:
                done_comps[c] = None
                sep_failed[i] = True
    tab = {f: np.concatenate(v) for f, v in tab.items()}

    # ---- choose the detection
    pix = np.flatnonzero(pseg)
    lab_pix = pseg.ravel()[pix]
    nl = int(next_label)
    seg_flux = np.bincount(lab_pix, weights=cv.det.ravel()[pix], minlength=nl)
    label = select_detection(pseg, cx, cy, seg_flux, cls.search_box, bounds=bounds)
    label[grow | sep_failed] = 0
    det = label > 0

    # ---- stage B: measurement apertures must see exact segmentation
    xs = tab["x"][label]
    ys = tab["y"][label]
    a, b, th = _shape(tab["a"][label], tab["b"][label], tab["theta"][label])
    if not full:
        dy6, dx6 = _ellipse_half_extent(a, b, th, 6.0)
        for i in np.flatnonzero(det):
            bb = (int(np.floor(ys[i] - dy6[i])) - 1, int(np.ceil(ys[i] + dy6[i])) + 2,
                  int(np.floor(xs[i] - dx6[i])) - 1, int(np.ceil(xs[i] + dx6[i])) + 2)
            if not check(i, *bb):
                fail(i)
            room(i, *bb)
        det &= ~grow
    # Segmentation for neighbour masking in Kron/AUTO: pixels of objects that CLEAN removed
    # (in re-extracted regions) stay masked for everyone, so the masks do not depend on
    # which regions a given window re-extracted.
    pseg32 = pseg.astype(np.int32)
    pseg32[(pseg32 == 0) & (seg > 0)] = _REMOVED
    kr = np.full(src.size, np.nan)
    for ii, sl in _groups(cv, np.flatnonzero(det), edge, src_win):
        oy, ox = sl[0].start, sl[1].start
        kr[ii] = phot.kron_radius(cv.det[sl], xs[ii] - ox, ys[ii] - oy, a[ii], b[ii], th[ii],
                                  segmap=pseg32[sl], seg_id=label[ii], mask=cv.nodata[sl])
    scale = phot.auto_scale(kr, params.phot_autoparams)
    if not full:
        dya, dxa = _ellipse_half_extent(a, b, th, scale)
        rap = 0.5 * max(params.phot_apertures)
        dya, dxa = np.maximum(dya, rap), np.maximum(dxa, rap)
        # MASK_TYPE CORRECT reads pixels mirrored about the centre: up to 2 more pixels out
        grow_px = 2 if params.mask_type is not None else 0
        if params.backphoto_type == "local":
            sbox = phot.segment_boxes(pix, lab_pix, W_cv, nl)
            _, annulus = phot.local_background_boxes(sbox[label], params.backphoto_thick, ctx.shape)
        for i in np.flatnonzero(det):
            bb = (int(np.floor(ys[i] - dya[i])) - 1 - grow_px, int(np.ceil(ys[i] + dya[i])) + 2 + grow_px,
                  int(np.floor(xs[i] - dxa[i])) - 1 - grow_px, int(np.ceil(xs[i] + dxa[i])) + 2 + grow_px)
            if not check(i, *bb):
                fail(i)
            room(i, *bb)
            if params.backphoto_type == "local":
                # BACKPHOTO_TYPE LOCAL: the annulus pixels and which of them belong to objects
                # must be those of the full frame (upper sides: one pixel more, SExtractor's test)
                ab = annulus[i].tolist()
                ab = (ab[0], ab[1] + 1, ab[2], ab[3] + 1)
                if not check(i, *ab):
                    fail(i)
                bb = (min(bb[0], ab[0]), max(bb[1], ab[1]), min(bb[2], ab[2]), max(bb[3], ab[3]))
            phot_box[i] = bb

    # ---- windows that must grow: new rects (or, at max_window, one last round unchecked)
    need = np.array(need_l, dtype=np.int64).reshape(-1, 4)
    regrow = []
    if not full:
        for i in np.flatnonzero(grow):
            s = src[i]
            oy, ox = wy0[i] - rect[i, 0], wx0[i] - rect[i, 2]   # canvas -> image offset
            pad = m + 4
            ny0 = min(rect[i, 0], need[i, 0] - oy - pad)
            ny1 = max(rect[i, 1], need[i, 1] - oy + pad)
            nx0 = min(rect[i, 2], need[i, 2] - ox - pad)
            nx1 = max(rect[i, 3], need[i, 3] - ox + pad)
            # A side whose required box reaches the window edge may hide a region that
            # continues outside: grow it by at least half the window size, so the rounds
            # stay few.  A side whose box ends inside (within the margin) grows to it + pad.
            gy = max(16, (rect[i, 1] - rect[i, 0]) // 2)
            gx = max(16, (rect[i, 3] - rect[i, 2]) // 2)
            ny0 = min(ny0, rect[i, 0] - gy) if need[i, 0] - oy <= rect[i, 0] else ny0
            ny1 = max(ny1, rect[i, 1] + gy) if need[i, 1] - oy >= rect[i, 1] else ny1
            nx0 = min(nx0, rect[i, 2] - gx) if need[i, 2] - ox <= rect[i, 2] else nx0
            nx1 = max(nx1, rect[i, 3] + gx) if need[i, 3] - ox >= rect[i, 3] else nx1
            new = np.array([max(ny0, 0), min(ny1, ny), max(nx0, 0), min(nx1, nx)])
            mw = ctx.params.max_window
            iy_, ix_ = int(np.floor(ctx.y[s] + 0.5)), int(np.floor(ctx.x[s] + 0.5))
            if new[1] - new[0] > mw:
                new[0], new[1] = max(iy_ - mw // 2, new[0]), min(iy_ - mw // 2 + mw, new[1])
            if new[3] - new[2] > mw:
                new[2], new[3] = max(ix_ - mw // 2, new[2]), min(ix_ - mw // 2 + mw, new[3])
            if np.array_equal(new, all_rects[s]):
                ctx.at_max[s] = True          # redo once more without the checks, flagged
            all_rects[s] = new
            regrow.append(s)

    fin = ~grow
    ctx.out[COL_FLAGS][src[sep_failed]] |= FLAG_SEP_ERROR
    # (pseg is unchanged since pix, lab_pix were taken from it)
    _finish(ctx, cv, pseg, pseg32, label * fin, xs, ys, a, b, th, scale, src, src_win, fin, rect, wy0, wx0,
            edge, phot_box, bounds, pix, lab_pix)
    return np.array(regrow, dtype=np.int64)


def _segment_table(cat):
    """Label-indexed geometry (index 0 = no detection), as lists of arrays to concatenate."""
    tab = {}
    for f in ("x", "y", "a", "b", "theta"):
        tab[f] = [np.array([np.nan]), np.asarray(cat[f], dtype=np.float64)]
    return tab


def _isolate(cv, comp, c, box, win, pseg, tab, next_label, ctx, offset):
    """Re-extract region ``c`` alone (fresh deblending RNG, CLEAN within the region).

    The cut-out is the region's box plus the filter half-width + 1, clipped to
    the window ``win`` (y0, y1, x0, x1), so it is the same array in a window
    and in the full frame.  ``offset`` (dy, dx) turns canvas into image
    coordinates: the same region (same image position, same pixels) met again
    in another window or a later round reuses the first result, which is
    exact because the extraction depends only on the cut-out.
    """
    params = ctx.params
    pad = params.filter_halfwidth + 1
    y0, y1 = max(box[0] - pad, win[0]), min(box[1] + pad, win[1])
    x0, x1 = max(box[2] - pad, win[2]), min(box[3] + pad, win[3])
    inside = comp[y0:y1, x0:x1] == c
    key = (y0 + offset[0], y1 + offset[0], x0 + offset[1], x1 + offset[1], inside.tobytes())
    hit = ctx.isolated.get(key, False)
    if hit is None:
        raise DetectionError("sep failed on this region before")
    if hit is False:
        data = np.ascontiguousarray(cv.det32[y0:y1, x0:x1])
        err = np.array(cv.err[y0:y1, x0:x1], dtype=np.float32, order="C")
        err[~inside] = _BIG_RMS   # nothing outside the region can pass the threshold
        nod = np.ascontiguousarray(cv.nodata[y0:y1, x0:x1])
        try:
            cat, seg = _sep_extract(data, err, nod, params, params.clean)
        except DetectionError:
            ctx.isolated[key] = None
            raise
        hit = (seg, {f: np.asarray(cat[f], dtype=np.float64) for f in ("x", "y", "a", "b", "theta")}, len(cat))
        ctx.isolated[key] = hit
    seg, geo, k = hit
    region = pseg[y0:y1, x0:x1]
    region[inside] = 0
    new = seg > 0
    region[new] = seg[new] + (next_label - 1)
    tab["x"].append(geo["x"] + x0)
    tab["y"].append(geo["y"] + y0)
    for f in ("a", "b", "theta"):
        tab[f].append(geo[f])
    return next_label + k


def _groups(cv, ii, edge, src_win):
    """Yield (source indices, canvas slice): all non-edge sources on the whole canvas,
    then each edge source on its own window (see ``room`` in :func:`_analyse`)."""
    ii = np.asarray(ii, dtype=np.int64)
    whole = (slice(0, cv.shape[0]), slice(0, cv.shape[1]))
    inner = ii[~edge[ii]]
    if inner.size:
        yield inner, whole
    for i in ii[edge[ii]]:
        yield np.array([i]), cv.slice(src_win[i])


def _band_boxes(width, pix, lab_pix, labels, phot_box, bounds):
    """Per detected source, the part of its window the band photometry reads (canvas
    coordinates): its segment (ISO) and its AUTO / aperture box, inside the window.
    Band pixels elsewhere are never read, so they need not be pasted.

    ``pix``, ``lab_pix``: flat canvas indices and labels of the segment pixels
    (at least those of ``labels``)."""
    boxes = np.array(phot_box, dtype=np.int64).reshape(-1, 4)
    if labels.size and pix.size:
        nl = int(max(labels.max(), lab_pix.max())) + 1
        order = np.argsort(lab_pix, kind="stable")
        ls = lab_pix[order]
        rows, cols = np.divmod(pix[order], width)
        start = np.flatnonzero(np.r_[True, ls[1:] != ls[:-1]])
        present = ls[start]
        seg = np.zeros((nl, 4), dtype=np.int64)
        seg[:, 0] = seg[:, 2] = np.iinfo(np.int64).max // 4
        seg[:, 1] = seg[:, 3] = -(np.iinfo(np.int64).max // 4)
        seg[present, 0] = np.minimum.reduceat(rows, start)
        seg[present, 1] = np.maximum.reduceat(rows, start) + 1
        seg[present, 2] = np.minimum.reduceat(cols, start)
        seg[present, 3] = np.maximum.reduceat(cols, start) + 1
        sb = seg[labels]
        boxes[:, 0] = np.minimum(boxes[:, 0], sb[:, 0])
        boxes[:, 1] = np.maximum(boxes[:, 1], sb[:, 1])
        boxes[:, 2] = np.minimum(boxes[:, 2], sb[:, 2])
        boxes[:, 3] = np.maximum(boxes[:, 3], sb[:, 3])
    boxes[:, 0] = np.maximum(boxes[:, 0], bounds[:, 0])
    boxes[:, 1] = np.minimum(boxes[:, 1], bounds[:, 1])
    boxes[:, 2] = np.maximum(boxes[:, 2], bounds[:, 2])
    boxes[:, 3] = np.minimum(boxes[:, 3], bounds[:, 3])
    return boxes


def _finish(ctx, cv, pseg, pseg32, label, xs, ys, a, b, th, scale, src, src_win, fin, rect, wy0, wx0, edge,
            phot_box, bounds, pix, lab_all):
    """Classification and photometry of the finished sources of a canvas.

    ``pix``, ``lab_all``: ``np.flatnonzero(pseg)`` and the labels there."""
    out, params, cls = ctx.out, ctx.params, ctx.cls
    idx = np.flatnonzero(fin)
    if idx.size == 0:
        return
    lab = label[idx]
    det = lab > 0
    s = src[idx]
    out["detection_id"][s] = lab
    # classification geometry
    n_fp, n_ov, blend = footprint_overlap(pseg, lab, cv.ref, ctx.ref_mag)
    # photometry in every band
    di = np.flatnonzero(det)
    # Pixels of the measured segments only: ISO sums per label are the same
    # (bincount adds each label's pixels in the same row-major order).
    wanted = np.zeros(int(max(lab_all.max(initial=0), lab.max(initial=0))) + 1, dtype=bool)
    wanted[lab[det]] = True
    keep = wanted[lab_all]
    pix, lab_all = pix[keep], lab_all[keep]
    if cv.full:
        windows, boxes = np.zeros(1, dtype=np.int64), None
    else:
        j = idx[di]
        windows = src_win[j]
        boxes = _band_boxes(cv.shape[1], pix, lab_all, lab[di], phot_box[j], bounds[j])
    flux_sn = err_sn = None
    auto_det = tpl_det = None
    for band in ctx.bands:
        data, rms, bad = cv.band(band, windows, boxes)
        gain = ctx.gains.get(band)
        noise = ctx.noise_models.get(band)
        fi, fei = phot.iso_photometry(data, rms, pseg, lab, gain=gain, pixels=pix, noise=noise)
        fa = np.full((len(params.phot_apertures), lab.size), np.nan)
        fea = fa.copy()
        fau = np.full(lab.size, np.nan)
        feau = fau.copy()
        pos = np.full(label.size, -1, dtype=np.int64)
        pos[idx] = np.arange(idx.size)          # canvas source index -> row of this finish
        jd = idx[di]
        dbkg = None
        if params.backphoto_type == "local" and jd.size:
            # BACKPHOTO_TYPE LOCAL: per band, from the annulus around each segment's box
            sbox = phot.segment_boxes(pix, lab_all, cv.shape[1], int(lab.max()) + 1)[lab[di]]
            dbkg = phot.local_background(data, pseg32, bad, sbox, params.backphoto_thick,
                                         shape=ctx.shape, bounds=bounds[jd])
            npix = np.bincount(lab_all, minlength=int(lab.max()) + 1)[lab[di]]
            fi[di] = fi[di] - npix * dbkg
        if params.mask_type is not None and jd.size:
            r = pos[jd]
            fa[:, r], fea[:, r], fau[r], feau[r] = phot.sextractor_photometry(
                data, rms, pseg32, lab[r], bad, xs[jd], ys[jd], a[jd], b[jd], th[jd], scale[jd],
                params.phot_apertures, params.mask_type, gain=gain, dbkg=dbkg, bounds=bounds[jd],
                noise=noise)
        else:
            for j, sl in _groups(cv, jd, edge, src_win):
                oy, ox = sl[0].start, sl[1].start
                r = pos[j]
                fa[:, r], fea[:, r] = phot.aperture_photometry(data[sl], rms[sl], xs[j] - ox, ys[j] - oy,
                                                               params.phot_apertures, gain=gain, mask=bad[sl],
                                                               noise=noise)
                fau[r], feau[r] = phot.auto_photometry(data[sl], rms[sl], xs[j] - ox, ys[j] - oy, a[j], b[j],
                                                       th[j], scale[j], gain=gain, segmap=pseg32[sl],
                                                       seg_id=lab[r], mask=bad[sl], noise=noise)
            if dbkg is not None:
                # sep's sums stand for the whole aperture inside the image (masked pixels are
                # scaled up), so the area to subtract is the aperture's area inside the image
                r = pos[jd]
                ca, ea = phot.aperture_area(cv.shape, xs[jd], ys[jd], params.phot_apertures, a[jd], b[jd],
                                            th[jd], scale[jd], bounds=bounds[jd])
                fa[:, r] -= ca * dbkg
                fau[r] -= ea * dbkg
        if cls.sn_definition == "iso":
            f, fe = fi, fei
        elif cls.sn_definition == "auto":
            f, fe = fau, feau
        else:
            f, fe = fa[cls.sn_aperture_index], fea[cls.sn_aperture_index]
        f = np.where(det, f, np.nan)
        fe = np.where(det, fe, np.nan)
        zp = ctx.zeropoints[band]
        mag, magerr, sn = phot.magnitudes(f, fe, zp)
        col = lambda q: band_column(q, band)  # noqa: E731
        out[col("flux_iso")][s] = fi
        out[col("fluxerr_iso")][s] = fei
        out[col("flux_auto")][s] = fau
        out[col("fluxerr_auto")][s] = feau
        for kk in range(len(params.phot_apertures)):
            out[col(f"flux_aper{kk}")][s] = fa[kk]
            out[col(f"fluxerr_aper{kk}")][s] = fea[kk]
        out[col("mag")][s] = mag
        out[col("magerr")][s] = magerr
        out[col("sn")][s] = sn
        out[col("maglim")][s] = phot.limiting_magnitude(f, fe, zp)
        if band == ctx.det_band:
            flux_sn, err_sn = f, fe
            if jd.size:
                _flag_saturated(ctx, data, pix, lab_all, lab, di, s, xs[jd] - wx0[jd] + rect[jd, 2],
                                ys[jd] - wy0[jd] + rect[jd, 0])
            # The status-2 flux test: AUTO flux vs the injected template through the same ellipse.
            auto_det = fau
            tpl_det = _template_auto_flux(ctx, cv, pseg32, lab, idx, di, s, xs, ys, a, b, th, scale,
                                          rect, wy0, wx0, edge, src_win, rms, bad)
    with np.errstate(divide="ignore", invalid="ignore"):
        sn_det = flux_sn / err_sn
    bmag = np.full(lab.size, np.nan)
    has = blend > 0
    bmag[has] = ctx.ref_mag[blend[has] - 1]
    status = classify(lab, sn_det, n_fp, n_ov, bmag, ctx.input_mag[s], auto_det, tpl_det, cls)
    out["status"][s] = status
    with np.errstate(divide="ignore", invalid="ignore"):
        out["overlap_fraction"][s] = np.where(det, n_ov / np.maximum(n_fp, 1), np.nan)
    out["blend_original_id"][s] = blend
    out["flux_auto_template"][s] = tpl_det
    out["blend_original_mag"][s] = bmag
    # detection centroid in image coordinates
    j = idx
    out["x_det"][s] = np.where(det, xs[j] - wx0[j] + rect[j, 2], np.nan)
    out["y_det"][s] = np.where(det, ys[j] - wy0[j] + rect[j, 0], np.nan)


def _flag_saturated(ctx, data, pix, lab_all, lab, di, s, x_img, y_img):
    """FLAG_SATURATED where a detection's peak in the detection band plus the background at
    its centre reaches SATUR_LEVEL (SExtractor's FLAGS bit 4)."""
    thr = np.full(di.size, float(ctx.params.satur_level))
    if ctx.det_background is not None:
        ny, nx = ctx.shape
        iy = np.clip((y_img + 0.5).astype(np.int64), 0, ny - 1)
        ix = np.clip((x_img + 0.5).astype(np.int64), 0, nx - 1)
        thr -= np.asarray(ctx.det_background, dtype=np.float64)[iy, ix]
    n = int(max(lab_all.max(initial=0), lab.max(initial=0))) + 1
    t = np.full(n, np.inf)
    t[lab[di]] = thr
    sat = phot.saturated(data, pix, lab_all, t, n)[lab[di]]
    ctx.out[COL_FLAGS][s[di][sat]] |= FLAG_SATURATED


def _input_templates(det_scene, templates, n):
    """Per-source (y0, x0, data, flux) of the injected detection-band stamps (see measure_injected)."""
    if templates is None:
        # A Scene keeps each stamp's flux factor (None: pre-multiplied); one stamp per source.
        templates = [(y0, x0, d, 1.0 if f is None else f)
                     for (y0, x0, d), f in zip(det_scene.stamps, det_scene._flux)]
    templates = list(templates)
    if len(templates) != n:
        raise ValueError(f"input_templates (default: the detection scene's stamps) has "
                         f"{len(templates)} entries for {n} sources")
    return templates


def _template_auto_flux(ctx, cv, pseg32, lab, idx, di, s, xs, ys, a, b, th, scale, rect, wy0, wx0, edge,
                        src_win, rms, bad):
    """AUTO flux of each finished source's own noiseless template (NaN if undetected).

    Each template is pasted alone into a zero canvas (clipped to its window,
    which holds its whole Kron ellipse) and measured with the source's ellipse,
    neighbour segments and no-data mask, exactly as its data were: so a
    windowed and a full-frame extraction give the same value, and other
    injected sources never enter it.
    """
    out = np.full(lab.size, np.nan)
    tcv = np.zeros(cv.shape)
    pos = np.full(src_win.size, -1, dtype=np.int64)      # canvas source index -> row of lab
    pos[idx] = np.arange(idx.size)
    for jj, sl in _groups(cv, idx[di], edge, src_win):
        oy, ox = sl[0].start, sl[1].start
        for j in jj.tolist():
            r = pos[j]
            t = ctx.templates[s[r]]
            if t is None:
                out[r] = 0.0
                continue
            ty0, tx0, data, flux = t
            ry0, ry1, rx0, rx1 = rect[j].tolist()
            y0, y1 = max(ty0, ry0), min(ty0 + data.shape[0], ry1)
            x0, x1 = max(tx0, rx0), min(tx0 + data.shape[1], rx1)
            if y1 <= y0 or x1 <= x0:
                out[r] = 0.0
                continue
            cy, cx = y0 - ry0 + wy0[j], x0 - rx0 + wx0[j]
            box = (slice(cy, cy + y1 - y0), slice(cx, cx + x1 - x0))
            tcv[box] = data[y0 - ty0:y1 - ty0, x0 - tx0:x1 - tx0] * flux
            if ctx.params.mask_type is not None:
                f = phot.sextractor_photometry(tcv, rms, pseg32, lab[r:r + 1], bad, xs[j:j + 1], ys[j:j + 1],
                                               a[j:j + 1], b[j:j + 1], th[j:j + 1], scale[j:j + 1],
                                               ctx.params.phot_apertures, ctx.params.mask_type,
                                               bounds=np.array([[wy0[j], wy0[j] + ry1 - ry0, wx0[j],
                                                                 wx0[j] + rx1 - rx0]]))[2]
                out[r] = f[0]
                tcv[box] = 0.0
                continue
            f, _ = phot.auto_photometry(tcv[sl], rms[sl], xs[j:j + 1] - ox, ys[j:j + 1] - oy, a[j:j + 1],
                                        b[j:j + 1], th[j:j + 1], scale[j:j + 1], segmap=pseg32[sl],
                                        seg_id=lab[r:r + 1], mask=bad[sl])
            out[r] = f[0]
            tcv[box] = 0.0
    return out
