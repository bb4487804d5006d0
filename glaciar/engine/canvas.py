"""Canvases of windows: the per-call context, windows tiled into one array, and box helpers.

The lower layer of :mod:`glaciar.engine.windows` (which decides the windows and checks
their exactness) that :mod:`glaciar.engine.measure` (photometry on a canvas) shares, so
that it need not import the windowing itself for these:

* :class:`MeasureContext` -- everything one :func:`~glaciar.engine.measure.measure_injected`
  call works with;
* :class:`Canvas` -- windows of the detection image (and of the bands) tiled into one
  array, separated by masked gaps (:func:`pack_windows`), with sep's above-threshold mask
  (:meth:`Canvas.detection`);
* :class:`ObjectBoxes` -- boxes of the original image's objects on a grid, for box queries;
* box helpers: :func:`label_boxes`, :func:`ellipse_boxes`, :func:`ellipse_half_extent`,
  :func:`safe_shape`, :func:`window_groups`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from glaciar.engine import sepscan
from glaciar.engine.classify import ClassificationParams
from glaciar.engine.detect import DetectionParams, detection_rms
from glaciar.engine.scene import Scene

__all__ = ["MeasureContext", "Canvas", "ObjectBoxes", "pack_windows", "label_boxes", "ellipse_boxes",
           "ellipse_half_extent", "safe_shape", "window_groups"]


@dataclass(frozen=True, eq=False)
class MeasureContext:
    """Everything one :func:`~glaciar.engine.measure.measure_injected` call works with.

    Images and settings (read only)
    ---------------------------------
    det_scene, det_rms : Scene, ndarray
        Injected detection image and its RMS [image units].
    band_scenes, band_rms : mapping band -> Scene / ndarray
    mask : ndarray of bool or None
        True where there are no data.
    ref_segmap, ref_mag : ndarray
        Original image's segmentation and AUTO magnitude per original id.
    params, cls : DetectionParams, ClassificationParams
    zeropoints, gains : mapping band -> float / float or None
    det_band : str
    bands : list of str
    noise_models : dict band -> CorrelatedNoise
    shape : (int, int)
    margin, gap : int
        Exact-zone margin (filter half-width + 1) and blank gap between windows [pixels].

    Sources
    -------
    x, y, input_flux, input_mag : ndarray, shape (N,)
    templates : list
        Per source its detection-band stamp (y0, x0, data, flux) or None.

    Per-call state (the containers are filled, never replaced)
    -----------------------------------------------------------
    out : dict of column -> ndarray (N,)
    at_max : ndarray of bool (N,)
        Window at ``max_window``: done once more unchecked, flagged.
    isolated : dict
        Cache of isolated region extractions (image box, pixels) -> result.
    det_background : ndarray or None
        Background map subtracted from the detection band [image units]
        (SATUR_LEVEL flag: pixel + background); None = 0.
    ref_objects : ObjectBoxes or None
        Original objects' boxes that size first windows (:func:`glaciar.engine.windows.initial_windows`).
    """

    det_scene: Scene
    det_rms: np.ndarray
    band_scenes: Mapping[str, Scene]
    band_rms: Mapping[str, np.ndarray]
    mask: np.ndarray | None
    ref_segmap: np.ndarray
    ref_mag: np.ndarray
    params: DetectionParams
    cls: ClassificationParams
    zeropoints: Mapping[str, float]
    gains: Mapping[str, float | None]
    det_band: str
    bands: list
    noise_models: dict
    shape: tuple
    margin: int
    gap: int
    x: np.ndarray
    y: np.ndarray
    input_flux: np.ndarray
    input_mag: np.ndarray
    templates: list
    out: dict
    at_max: np.ndarray
    isolated: dict
    det_background: np.ndarray | None = None
    ref_objects: "ObjectBoxes | None" = None


@dataclass(frozen=True, eq=False)
class ObjectBoxes:
    """Boxes of an image's objects, indexed on a grid of square cells for box queries.

    Attributes
    ----------
    region, need : ndarray of int64, shape (M, 4)
        Per object, image boxes (y0, y1, x0, x1): its above-threshold region,
        and that region widened by its Kron and AUTO ellipses.
    cell : int
        Cell side [pixels].
    ncx : int
        Cells per image row.
    start, ids : ndarray of int64
        Objects whose region box meets cell ``k``: ``ids[start[k]:start[k + 1]]``.
    """

    region: np.ndarray
    need: np.ndarray
    cell: int
    ncx: int
    start: np.ndarray
    ids: np.ndarray

    @classmethod
    def build(cls, region, need, shape, cell: int = 64) -> "ObjectBoxes":
        region = np.asarray(region, dtype=np.int64).reshape(-1, 4)
        need = np.asarray(need, dtype=np.int64).reshape(-1, 4)
        ny, nx = shape
        ncy, ncx = -(-ny // cell), -(-nx // cell)
        cy0 = np.clip(region[:, 0] // cell, 0, ncy - 1)
        cy1 = np.clip((region[:, 1] - 1) // cell, 0, ncy - 1)
        cx0 = np.clip(region[:, 2] // cell, 0, ncx - 1)
        cx1 = np.clip((region[:, 3] - 1) // cell, 0, ncx - 1)
        ob, cells = _expand_cells(cy0, cy1, cx0, cx1, ncx)
        order = np.argsort(cells, kind="stable")
        start = np.searchsorted(cells[order], np.arange(ncy * ncx + 1))
        return cls(region, need, int(cell), int(ncx), start.astype(np.int64), ob[order])

    def __len__(self):
        return len(self.region)

    def candidates(self, boxes):
        """(box index, object index) pairs of every object sharing a cell with each box.

        A superset of the objects whose region box meets the box; pairs may repeat."""
        boxes = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
        ncy = (len(self.start) - 1) // self.ncx
        c = self.cell
        cy0 = np.clip(boxes[:, 0] // c, 0, ncy - 1)
        cy1 = np.clip((boxes[:, 1] - 1) // c, 0, ncy - 1)
        cx0 = np.clip(boxes[:, 2] // c, 0, self.ncx - 1)
        cx1 = np.clip((boxes[:, 3] - 1) // c, 0, self.ncx - 1)
        bi, cells = _expand_cells(cy0, cy1, cx0, cx1, self.ncx)
        n = self.start[cells + 1] - self.start[cells]
        pair_box = np.repeat(bi, n)
        first = np.repeat(self.start[cells] - np.cumsum(n) + n, n)
        return pair_box, self.ids[first + np.arange(pair_box.size)]


def _expand_cells(cy0, cy1, cx0, cx1, ncx):
    """(item index, cell index) for every grid cell of each item's inclusive cell range."""
    hy, hx = cy1 - cy0 + 1, cx1 - cx0 + 1
    n = hy * hx
    item = np.repeat(np.arange(n.size), n)
    k = np.arange(item.size) - np.repeat(np.cumsum(n) - n, n)
    return item, (cy0[item] + k // hx[item]) * ncx + cx0[item] + k % hx[item]


def pack_windows(heights, widths, gap):
    """Shelf-pack rectangles; returns (y offsets, x offsets, canvas shape).

    Rectangles go, tallest first, left to right on shelves of a given width,
    each with ``gap`` blank pixels around it.  A few shelf widths about the
    square root of the total area are tried and the smallest canvas kept
    (its width trimmed to the rectangles it holds): every whole-canvas pass
    (sep, the filter, labelling, band canvases) costs in proportion to the
    canvas area, and one fixed width left ~20 % of it blank.
    """
    h = np.asarray(heights, dtype=np.int64).ravel()
    w = np.asarray(widths, dtype=np.int64).ravel()
    k = h.size
    order = np.argsort(-h, kind="stable")
    area = float(np.sum((h + gap) * (w + gap)))
    wmin = int(np.max(w)) + 2 * gap if k else 2 * gap
    hl, wl = h[order].tolist(), w[order].tolist()
    best = None
    for f in (0.85, 0.95, 1.0, 1.05, 1.1, 1.2, 1.35):
        width = int(max(wmin, np.sqrt(area) * f))
        oy, ox = [0] * k, [0] * k
        y = x = gap
        shelf = used = 0
        for j in range(k):
            hj, wj = hl[j], wl[j]
            if x + wj + gap > width and x > gap:
                y += shelf + gap
                x = gap
                shelf = 0
            oy[j], ox[j] = y, x
            x += wj + gap
            used = max(used, x)
            shelf = max(shelf, hj)
        shape = (int(y + shelf + gap), int(max(used, 2 * gap)))
        if best is None or shape[0] * shape[1] < best[2][0] * best[2][1]:
            best = (oy, ox, shape)
    oy = np.zeros(k, dtype=np.int64)
    ox = np.zeros(k, dtype=np.int64)
    if k:
        oy[order], ox[order] = best[0], best[1]
        return oy, ox, best[2]
    return oy, ox, (int(2 * gap), int(2 * gap))


class Canvas:
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
            self.oy, self.ox, self.shape = pack_windows(hh, ww, ctx.gap)
        self.full = full
        det = np.zeros(self.shape)
        err = np.ones(self.shape, dtype=np.float32)
        nodata = np.ones(self.shape, dtype=bool)
        gap = np.ones(self.shape, dtype=bool)
        ref = np.zeros(self.shape, dtype=np.int32)
        ctx.det_scene.paste_windows(det, rects, self.oy, self.ox)
        det_rms, mask, ref_segmap = ctx.det_rms, ctx.mask, ctx.ref_segmap
        # canvas rows and columns of every window as Python ints, so the loop only slices
        cbox = np.stack([self.oy, self.oy + hh, self.ox, self.ox + ww], axis=1).tolist()
        for (y0, y1, x0, x1), (a, b, c, d) in zip(rects.tolist(), cbox):
            err[a:b, c:d] = det_rms[y0:y1, x0:x1]
            nodata[a:b, c:d] = False if mask is None else mask[y0:y1, x0:x1]
            gap[a:b, c:d] = False
            ref[a:b, c:d] = ref_segmap[y0:y1, x0:x1]
        with np.errstate(invalid="ignore"):
            nodata |= ~np.isfinite(det) | ~(np.isfinite(err) & (err > 0))
        det[nodata] = 0.0
        err[nodata] = 1.0
        self.det = det
        self.det32 = det.astype(np.float32)
        self.err = err
        self.nodata = nodata
        # the RMS the threshold multiplies; gaps between windows count as outside the image
        self.derr = detection_rms(err, nodata & ~gap, ctx.params, outside=gap)
        self.ref = ref

    def detection(self):
        """sep's above-threshold mask of the canvas, its filtered image and threshold (cached).

        Every connected region of the mask, whatever its size, is a region
        sep sees (:func:`glaciar.engine.sepscan.detection_mask`); the exactness
        checks use these, not the segmentation, so a region a window cuts
        below DETECT_MINAREA is not missed."""
        if getattr(self, "_detection", None) is None:
            self._detection = sepscan.detection_mask(self.det32, self.derr, self.nodata, self.ctx.params)
        return self._detection

    def slice(self, k):
        y0, y1, x0, x1 = self.rects[k]
        return (slice(self.oy[k], self.oy[k] + y1 - y0), slice(self.ox[k], self.ox[k] + x1 - x0))

    def band(self, name, windows, boxes=None):
        """Band data, RMS and no-data mask on the canvas.

        Only the listed windows are filled, or with ``boxes`` ((K, 4) canvas
        y0, y1, x0, x1 inside those windows) only those parts.  Pixels not
        filled are flagged as no data; no aperture of the sources measured
        reaches them (see ``room`` in :func:`glaciar.engine.windows._analyse` and
        :func:`glaciar.engine.measure._band_boxes`).
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


def label_boxes(labels, n):
    """Bounding boxes of the labels 1..n of a label image, shape (n + 1, 4).

    Row ``c`` is (y0, y1, x0, x1) of label ``c`` (exclusive upper bounds, as
    ``scipy.ndimage.find_objects`` gives them); row 0 and labels without a
    pixel are zeros.  Same boxes as ``find_objects``, but ~5-15x faster on
    canvases holding ~1000 small noise regions (its per-label cost dominated
    the exactness checks), and no Python loop over the labels.
    """
    lab2 = np.asarray(labels)
    flat = lab2.ravel()
    pix = np.flatnonzero(flat)
    cb = np.zeros((int(n) + 1, 4), dtype=np.int64)
    if pix.size == 0:
        return cb
    lab = flat[pix]
    rows, cols = np.divmod(pix, lab2.shape[1])
    big = np.int64(2 ** 40)
    cb[:, 0::2], cb[:, 1::2] = big, -big
    np.minimum.at(cb[:, 0], lab, rows)
    np.maximum.at(cb[:, 1], lab, rows + 1)
    np.minimum.at(cb[:, 2], lab, cols)
    np.maximum.at(cb[:, 3], lab, cols + 1)
    cb[cb[:, 1] < 0] = 0
    return cb


def ellipse_boxes(x, y, dy, dx, grow=0):
    """Integer boxes (y0, y1, x0, x1) [pixels], shape (N, 4), holding every pixel an ellipse
    of half extents (dy, dx) about (x, y) can touch, ``grow`` pixels more on each side.

    The margin the exactness checks of :func:`glaciar.engine.windows._analyse` use: one pixel below
    the floor, and an exclusive upper bound two pixels above the ceiling."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    return np.stack([np.floor(y - dy).astype(np.int64) - 1 - grow, np.ceil(y + dy).astype(np.int64) + 2 + grow,
                     np.floor(x - dx).astype(np.int64) - 1 - grow, np.ceil(x + dx).astype(np.int64) + 2 + grow],
                    axis=1).reshape(-1, 4)


def ellipse_half_extent(a, b, theta, r):
    """Half extents (dy, dx) [pixels] of the ellipse of semi-axes r a, r b at angle theta."""
    c, s = np.cos(theta), np.sin(theta)
    dx = r * np.sqrt((a * c) ** 2 + (b * s) ** 2)
    dy = r * np.sqrt((a * s) ** 2 + (b * c) ** 2)
    return dy, dx


def safe_shape(a, b, theta):
    """Ellipse shape sep accepts (a >= b > 0, |theta| <= pi/2), semi-axes [pixels], angle [radians].

    sep requires a >= b >= 0 and finite values; degenerate 1-pixel-wide objects get
    the 1e-3 px floor.  sep's catalogue reports ``b = NaN`` (and, in principle, ``a``)
    when an object's second-moment matrix is not positive (negative pixels weigh in,
    as the matched filter allows): its smaller variance is negative, so the axis is
    taken as degenerate (the floor) and a NaN angle as 0.  Finite inputs are unchanged.
    """
    a = np.asarray(a, dtype=np.float64)
    a = np.where(np.isfinite(a), np.maximum(a, 1e-3), 1e-3)
    b = np.asarray(b, dtype=np.float64)
    b = np.where(np.isfinite(b), np.clip(b, 1e-3, a), 1e-3)
    th = np.asarray(theta, dtype=np.float64)
    th = np.where(np.isfinite(th), np.clip(th, -np.pi / 2, np.pi / 2), 0.0)
    return a, b, th


def window_groups(cv, ii, edge, src_win):
    """Yield (source indices, canvas slice): all non-edge sources on the whole canvas,
    then each edge source on its own window (see ``room`` in
    :func:`glaciar.engine.windows._analyse`)."""
    ii = np.asarray(ii, dtype=np.int64)
    whole = (slice(0, cv.shape[0]), slice(0, cv.shape[1]))
    inner = ii[~edge[ii]]
    if inner.size:
        yield inner, whole
    for i in ii[edge[ii]]:
        yield np.array([i]), cv.slice(src_win[i])
