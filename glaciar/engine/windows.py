"""Exact local segmentation of injected sources: windows, growth, re-extraction.

The product every sep mode and the SExtractor backend return
(:class:`~glaciar.engine.segmentation.SegmentedBatch`: per source, its detection's label
on a canvas, the canvas's segmentation, the detection's geometry and Kron scale) is made here;
classification and photometry on it are :mod:`glaciar.engine.measure`'s.

Windowed detection
------------------
Each injected source is detected in a cut-out *window* of the injected
detection image.  Windows of many sources are tiled into one *canvas*,
separated by masked blank gaps wider than the filter kernel, and extracted with
one ``sep.extract`` call (CLEAN off).  A window is grown (and the source re-done
in the next round) until every connected above-threshold region that matters
lies at least ``filter half-width + 1`` pixels inside the window edge (sides on
the image edge excepted, where the full frame has the same edge):

* regions with a pixel in the search box;
* regions touching the bounding boxes of the Kron-radius ellipse (6 a, 6 b),
  the AUTO ellipse and the largest circular aperture (they decide which pixels
  are masked as neighbours).

"Regions" are the 8-connected components of sep's above-threshold mask,
recomputed exactly (:func:`glaciar.engine.sepscan.detection_mask`), *all* of
them: a region that the window cuts below DETECT_MINAREA has no segment in the
window, yet the full frame detects it, so checking only the segmentation
would miss it (the "minarea gap").  Every pixel of a region inside its
window's exact zone has the full frame's filtered value and threshold, so the
region is the full frame's.

Two sep behaviours would still make a cut-out differ from the full frame; both
are made window-independent, identically in ``mode="full"``:

1. *Deblending is random.*  sep (like SExtractor) hands the faint pixels of a
   split region to its children by drawing random numbers from one stream per
   ``sep.extract`` call, so a deblended footprint depends on every region
   processed before it anywhere in the image.  Every split region glaciar
   uses (in a search box) is therefore re-extracted *alone* (same pixels; the
   RMS set to infinity outside the region), which makes its deblending a
   function of its own pixels (:func:`glaciar.engine.segmentation.isolate_region`).
2. *CLEAN.*  ``clean_style="region"`` (default): sep's CLEAN runs inside each
   re-extracted region, i.e. between the deblended children of one region,
   never between separate regions (a single-segment region is unaffected:
   sep's CLEAN only removes objects).

The other CLEAN styles (CLEAN through the whole image's object list) and the
matched filter (noise-aware: its detection mask is recomputed only up to
rounding) never come here windowed: :func:`glaciar.engine.measure.runs_full_frame`
sends them to the full frame.  The full-frame mode (:func:`segment_full`) runs this
module's code on one canvas, the whole image, with the checks off (with a
whole-image CLEAN, the full frame is instead the image's segmentation product,
:func:`glaciar.engine.segmentation.sep_segmentation`).

Speed without changing answers
------------------------------
Each shortcut below only decides *how much* is computed, never a result
(``tests/engine/test_windows.py``):

* the first window is ``DetectionParams.initial_window`` (41 px: most faint
  sources are exact after one extraction), or larger where the source's own
  stamp predicts a larger Kron box (:func:`stamp_half_sizes`: bright sources
  skip a second round), or where original objects nearby ask for it; a side
  whose required box reaches the window edge grows by half the window, other
  sides just enough;
* canvases are built by :meth:`Scene.paste_windows` (one overlap search per
  canvas, stamps added where windows read them);
* a re-extracted (deblended) region is cached by its image position and
  pixels for the whole call, so a later round or an overlapping window reuses
  it (the extraction depends on nothing else);
* band canvases hold only the pixels photometry reads: each detection's
  segment and AUTO/aperture box; the detection band reuses the detection
  canvas; windows that must grow get no band photometry.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
from scipy import ndimage

from glaciar.constants import COL_FLAGS, FLAG_SEP_ERROR, FLAG_WINDOW_AT_LIMIT
from glaciar.engine import sepscan
from glaciar.engine import photometry as phot
from glaciar.engine.canvas import (Canvas, MeasureContext, ObjectBoxes, ellipse_boxes, ellipse_half_extent,
                                   label_boxes, safe_shape, window_groups)
from glaciar.engine.classify import input_pixel, select_detection
from glaciar.engine.detect import DetectionError, DetectionParams, sep_extract
from glaciar.engine.segmentation import SegmentedBatch, isolate_region

__all__ = ["segment_windowed", "segment_full", "initial_windows", "undetectable", "stamp_half_sizes"]

_EIGHT = np.ones((3, 3), dtype=bool)   # sep/SExtractor regions are 8-connected
_MAX_CANVAS_PIXELS = 600_000           # keep one sep call's buffers small
REMOVED = np.int32(2 ** 31 - 1)        #: label of pixels whose object CLEAN removed
# Half-size [pixels] of the box standing for an injected source's own Kron ellipse when
# first windows look for original objects it may touch: a faint detection's 6 a box
# (a ~ 1.5-3 px at the demo's limit) spans ~20-35 px.  Only sizes first windows; on the
# demo field it cut measurement CPU by 6-14 % at m = 24-28 against no neighbour look-up.
_OWN_HALF = 10
# First windows from the source's own stamp (:func:`stamp_half_sizes`) hold 6 a + this
# [pixels] (+ margin): the 75th percentile of the required half-size on the demo field at
# m = 24-26.  8-14 gave the same CPU within the noise; without it, m = 24 took ~1.2x longer.
_STAMP_SLACK = 11.0
_STAMP_CROP = 16          # half-size of the template cut-outs stamp_half_sizes reads first


def segment_full(ctx: MeasureContext, finish: Callable[[MeasureContext, SegmentedBatch], None]):
    """Segment the whole injected image once (``mode="full"``); ``finish`` measures the batch.

    Returns the (N, 4) windows (the whole image for every source)."""
    ny, nx = ctx.shape
    n = ctx.x.size
    rects = np.array([[0, ny, 0, nx]], dtype=np.int64)
    _run_canvas(ctx, np.arange(n), rects, np.zeros(n, dtype=np.int64), True, None, finish)
    return np.repeat(rects, n, axis=0)


def segment_windowed(ctx: MeasureContext, finish: Callable[[MeasureContext, SegmentedBatch], None],
                     early_exit: bool = True):
    """Windowed segmentation, rounds of growing windows until every source is exact.

    ``finish(ctx, batch)`` is called on each canvas's exact sources.  With
    ``early_exit``, sources with no above-threshold pixel in their search box
    (:func:`undetectable`) are left as they are (not detected) without an
    extraction.
    Returns the last windows ((N, 4) image y0, y1, x0, x1) and the number of rounds."""
    n = ctx.x.size
    rects = initial_windows(ctx.x, ctx.y, ctx.shape, ctx.params, ctx.cls.search_box, ctx.margin,
                            ctx.ref_objects, own_half=stamp_half_sizes(ctx))
    pending = np.arange(n)
    if early_exit and n:
        skip, boxes = undetectable(ctx)
        rects[skip] = boxes[skip]
        pending = pending[~skip]
    rounds = 0
    while pending.size:
        rounds += 1
        # chunk so one sep call stays small
        areas = (rects[pending, 1] - rects[pending, 0] + ctx.gap) * (rects[pending, 3] - rects[pending, 2] + ctx.gap)
        chunks = np.split(pending, np.flatnonzero(np.diff(np.cumsum(areas) // _MAX_CANVAS_PIXELS)) + 1)
        grow_all = []
        for chunk in chunks:
            grow_all.append(_run_canvas(ctx, chunk, rects[chunk], np.arange(chunk.size), False, rects, finish))
        pending = np.concatenate(grow_all) if grow_all else np.zeros(0, dtype=np.int64)
    return rects, rounds


def undetectable(ctx: MeasureContext):
    """Sources that no extraction can detect: no search-box pixel is above threshold.

    A detection is chosen among the segments with a pixel in the source's
    search box (:func:`~glaciar.engine.classify.select_detection`), and every
    segment pixel is above sep's threshold after filtering, so a source whose
    search box holds no such pixel is not detected, whatever the rest of the
    image.  The test needs only the search box widened by the filter's reach
    (the exact-zone margin): one canvas of those small windows, filtered and
    thresholded exactly as a detection canvas (:meth:`Canvas.detection`).
    (Exact for the filters of the windowed mode; the matched filter, recomputed
    only up to rounding, runs full frame: :func:`glaciar.engine.measure.runs_full_frame`.)

    Returns
    -------
    skip : ndarray of bool (N,)
    boxes : ndarray (N, 4)
        The small windows (y0, y1, x0, x1, image pixels).
    """
    n = ctx.x.size
    ny, nx = ctx.shape
    params = ctx.params
    ix, iy = input_pixel(ctx.x, ctx.y)
    h = ctx.cls.search_box // 2
    r = h + ctx.margin
    boxes = np.stack([np.clip(iy - r, 0, ny), np.clip(iy + r + 1, 0, ny),
                      np.clip(ix - r, 0, nx), np.clip(ix + r + 1, 0, nx)], axis=1)
    skip = np.zeros(n, dtype=bool)
    inside = (boxes[:, 1] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 2])
    ii = np.flatnonzero(inside)
    if ii.size == 0:
        return skip, boxes
    cv = Canvas(ctx, boxes[ii])
    mask = cv.detection()[0]
    # the search box on the canvas, clipped to the image (as select_detection clips it)
    off = np.arange(-h, h + 1)
    py = iy[ii, None] + off
    px = ix[ii, None] + off
    ok = (((py >= 0) & (py < ny))[:, :, None] & ((px >= 0) & (px < nx))[:, None, :])
    cy = np.clip(py - boxes[ii, 0:1] + cv.oy[:, None], 0, cv.shape[0] - 1)
    cx = np.clip(px - boxes[ii, 2:3] + cv.ox[:, None], 0, cv.shape[1] - 1)
    hit = (mask[cy[:, :, None], cx[:, None, :]] & ok).any(axis=(1, 2))
    skip[ii] = ~hit
    return skip, boxes


def stamp_half_sizes(ctx: MeasureContext):
    """Half-size [pixels] of a first window predicted from each source's own stamp, shape (N,).

    sep's Kron check box is the 6 a ellipse of the detection, and the regions
    its edge touches add a few pixels (:func:`_analyse`).  ``a`` is estimated
    from the noiseless detection-band template (``ctx.templates``): the
    intensity-weighted second moments of its pixels above DETECT_THRESH times
    the RMS at the source (no filter, no noise: a guess).  On the demo field
    the required half-size was 6 a + 8 px at the median and 6 a + 11 px at the
    75th percentile for m = 24-26 sources; the window holds 6 a + 11 px
    plus the exact-zone margin.  0 where there is no template or fewer
    than DETECT_MINAREA pixels above threshold (the default first window).
    Only sizes first windows (any window gives the same answer): bright
    sources then need no second round (at m = 24 on the demo field, 92 %
    of them did with the default 41 px).
    """
    n = ctx.x.size
    half = np.zeros(n, dtype=np.int64)
    ny, nx = ctx.shape
    ix, iy = input_pixel(ctx.x, ctx.y)
    iy, ix = np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)
    rms = np.asarray(ctx.det_rms[iy, ix], dtype=np.float64)
    minarea = int(ctx.params.detect_minarea)
    use = [i for i, t in enumerate(ctx.templates) if t is not None and rms[i] > 0 and t[3] > 0]
    if not use:
        return half
    idx = np.array(use, dtype=np.int64)
    # pixels above threshold in the unit template: data * flux > threshold at the source
    # (the detection threshold's one definition, at the source's pixel)
    thr = sepscan.threshold_map(rms[idx], np.zeros(idx.size, dtype=bool), ctx.params).astype(np.float64)
    tval = thr / np.array([ctx.templates[i][3] for i in use], dtype=np.float64)
    # All sources at once on central cut-outs of the templates (zero-padded); those with
    # above-threshold pixels on the cut-out's border are redone alone on larger ones.
    h = _STAMP_CROP
    side = 2 * h + 1
    stack = np.zeros((idx.size, side, side))
    for r, i in enumerate(use):
        data = ctx.templates[i][2]
        ny_, nx_ = data.shape
        cy, cx = (ny_ - 1) // 2, (nx_ - 1) // 2
        y0, y1, x0, x1 = max(cy - h, 0), min(cy + h + 1, ny_), max(cx - h, 0), min(cx + h + 1, nx_)
        stack[r, y0 - cy + h:y1 - cy + h, x0 - cx + h:x1 - cx + h] = data[y0:y1, x0:x1]
    m = stack > tval[:, None, None]
    border = m[:, 0].any(axis=1) | m[:, -1].any(axis=1) | m[:, :, 0].any(axis=1) | m[:, :, -1].any(axis=1)
    w = np.where(m, stack, 0.0)
    npix = m.sum(axis=(1, 2))
    c = np.arange(side, dtype=np.float64) - h
    sw = w.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        wy, wx = w.sum(axis=2), w.sum(axis=1)            # (K, side) marginals
        mx, my = (wx @ c) / sw, (wy @ c) / sw
        x2 = (wx @ (c * c)) / sw - mx * mx
        y2 = (wy @ (c * c)) / sw - my * my
        xy = np.einsum("kyx,y,x->k", w, c, c) / sw - mx * my
        a = np.sqrt(np.maximum(0.5 * (x2 + y2) + np.sqrt(0.25 * (x2 - y2) ** 2 + xy * xy), 0.0))
    for r, i in enumerate(use):
        if border[r]:
            ar = _above_threshold_a(ctx.templates[i][2], tval[r], minarea)
        elif npix[r] >= max(minarea, 1):
            ar = float(a[r])
        else:
            ar = None
        if ar is not None:
            half[i] = int(math.ceil(6.0 * ar + _STAMP_SLACK)) + ctx.margin
    return half


def _above_threshold_a(data, t, minarea):
    """Semi-major axis [pixels] from the intensity-weighted second moments of the pixels of
    ``data`` above ``t``; None if fewer than ``minarea``.

    Templates are sized for their wings (n = 4 stamps reach ~180 px), while the
    pixels above a detection threshold sit near the centre: a central cut-out is
    read, doubled while pixels on its border are above ``t``."""
    ny, nx = data.shape
    cy, cx = (ny - 1) // 2, (nx - 1) // 2
    h = 2 * _STAMP_CROP
    while True:
        y0, y1, x0, x1 = max(cy - h, 0), min(cy + h + 1, ny), max(cx - h, 0), min(cx + h + 1, nx)
        m = data[y0:y1, x0:x1] > t
        if (y0 == 0 and y1 == ny and x0 == 0 and x1 == nx) or not (
                m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()):
            break
        h *= 2
    yy, xx = np.nonzero(m)
    if yy.size < max(minarea, 1):
        return None
    w = data[y0:y1, x0:x1][yy, xx]
    sw = w.sum()
    xx, yy = xx.astype(np.float64), yy.astype(np.float64)
    mx, my = (w @ xx) / sw, (w @ yy) / sw
    dx, dy = xx - mx, yy - my
    x2, y2, xy = (w @ (dx * dx)) / sw, (w @ (dy * dy)) / sw, (w @ (dx * dy)) / sw
    return math.sqrt(max(0.5 * (x2 + y2) + math.sqrt(0.25 * (x2 - y2) ** 2 + xy * xy), 0.0))


def initial_windows(x, y, shape, params: DetectionParams, search_box: int, margin: int,
                    objects: "ObjectBoxes | None" = None, own_half=None):
    """First detection window of each source (y0, y1, x0, x1 image pixels), shape (N, 4).

    A square of ``params.initial_window`` pixels around the source, widened
    to hold what the exactness checks of :func:`_analyse` will ask for when
    the source lands near an original object, so that most sources are exact
    after one extraction:

    * the above-threshold region of every original object whose region box
      meets the box of half-size ``_OWN_HALF`` about the source (it may touch
      the source's Kron and AUTO ellipses);
    * for an object whose region box meets the search box (the source may
      merge with it, and the detection then has the object's ellipses), its
      need box (region plus Kron and AUTO ellipse boxes).

    Each side that widens gets the exact-zone ``margin`` plus 4 pixels, as a
    window grown in a later round does.  Windows are capped at
    ``params.max_window`` about the source.  A guess only: the checks decide,
    and any window holding the required boxes gives the same answer.

    Parameters
    ----------
    x, y : ndarray (N,)
        Source positions [pixels, 0-based].
    shape : (int, int)
        Image shape.
    params : DetectionParams
    search_box : int
        Side of the classification search box [pixels].
    margin : int
        Exact-zone margin (filter half-width + 1) [pixels].
    objects : ObjectBoxes or None
        Original objects' boxes (:class:`glaciar.engine.measure.FieldReference`);
        None: squares only.
    own_half : ndarray of int (N,), optional
        Per source, a larger half-size predicted from its own stamp
        (:func:`stamp_half_sizes`); the square is at least this.
    """
    ny, nx = shape
    ix, iy = input_pixel(x, y)
    r = params.initial_window // 2
    if params.backphoto_type == "local":
        # the local-background annulus must fit too: start from a window that holds it
        r = max(r, params.backphoto_thick + 16)
    if own_half is not None:
        r = np.maximum(r, np.minimum(np.asarray(own_half, dtype=np.int64), params.max_window // 2))
    rects = np.stack([iy - r, iy + r + 1, ix - r, ix + r + 1], axis=1)
    if objects is not None and len(objects) and ix.size:
        h = search_box // 2
        c = _OWN_HALF
        big = np.int64(2 ** 40)
        want = np.empty_like(rects)
        want[:, 0::2], want[:, 1::2] = big, -big
        for half, own in ((c, objects.region), (h, objects.need)):
            box = np.stack([iy - half, iy + half + 1, ix - half, ix + half + 1], axis=1)
            si, oi = objects.candidates(box)
            rb = objects.region[oi]
            meet = ((rb[:, 0] < box[si, 1]) & (rb[:, 1] > box[si, 0])
                    & (rb[:, 2] < box[si, 3]) & (rb[:, 3] > box[si, 2]))
            si, ob = si[meet], own[oi[meet]]
            for k in range(4):
                (np.minimum if k % 2 == 0 else np.maximum).at(want[:, k], si, ob[:, k])
        pad = margin + 4
        rects[:, 0] = np.minimum(rects[:, 0], want[:, 0] - pad)
        rects[:, 1] = np.maximum(rects[:, 1], want[:, 1] + pad)
        rects[:, 2] = np.minimum(rects[:, 2], want[:, 2] - pad)
        rects[:, 3] = np.maximum(rects[:, 3], want[:, 3] + pad)
        mw = params.max_window
        for lo, hi, cc in ((0, 1, iy), (2, 3, ix)):
            wide = rects[:, hi] - rects[:, lo] > mw
            rects[wide, lo] = np.maximum(cc[wide] - mw // 2, rects[wide, lo])
            rects[wide, hi] = np.minimum(cc[wide] - mw // 2 + mw, rects[wide, hi])
    rects[:, 0:2] = np.clip(rects[:, 0:2], 0, ny)
    rects[:, 2:4] = np.clip(rects[:, 2:4], 0, nx)
    return rects


def _run_canvas(ctx, src, rects, src_win, full, all_rects, finish):
    """Extract one canvas; ``finish`` what is exact, return sources whose window must grow."""
    try:
        canvas = Canvas(ctx, rects, full=full)
        cat, seg = sep_extract(canvas.det32, canvas.derr, canvas.nodata, ctx.params, clean=False)
    except DetectionError:
        if len(rects) > 1:   # isolate the failing window(s)
            grow = [_run_canvas(ctx, src[i:i + 1], rects[src_win[i]][None], np.zeros(1, dtype=np.int64),
                                full, all_rects, finish) for i in range(src.size)]
            return np.concatenate(grow)
        ctx.out[COL_FLAGS][src] |= FLAG_SEP_ERROR
        return np.zeros(0, dtype=np.int64)
    regrow, batch = _analyse(ctx, canvas, cat, seg, src, src_win, all_rects)
    finish(ctx, batch)
    return regrow


def _analyse(ctx, cv, cat, seg, src, src_win, all_rects):
    """Exactness checks and canonical re-extraction on one extracted canvas.

    Returns the sources whose window must grow and the batch of the others
    (:class:`~glaciar.engine.segmentation.SegmentedBatch`)."""
    params, cls = ctx.params, ctx.cls
    m = ctx.margin
    ny, nx = ctx.shape
    full = cv.full
    # ---- regions: 8-connected components of sep's above-threshold mask, *every* one,
    # those below DETECT_MINAREA included: a region a window truncates below
    # DETECT_MINAREA has no segment in the window, yet it is a detection in the full
    # frame, so the exactness checks must see it.
    dmask = cv.detection()[0] | (seg > 0)
    comp, ncomp = ndimage.label(dmask, structure=_EIGHT)
    nseg = len(cat)
    seg2comp = np.zeros(nseg + 1, dtype=np.int64)
    nzpix = np.flatnonzero(seg)
    seg2comp[seg.ravel()[nzpix]] = comp.ravel()[nzpix]
    segs_per_comp = np.bincount(seg2comp[1:], minlength=ncomp + 1)
    cb = label_boxes(comp, ncomp)

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
    a, b, th = safe_shape(tab["a"][label], tab["b"][label], tab["theta"][label])
    if not full:
        dy6, dx6 = ellipse_half_extent(a, b, th, 6.0)
        ii = np.flatnonzero(det)
        for i, bb in zip(ii.tolist(), ellipse_boxes(xs[ii], ys[ii], dy6[ii], dx6[ii]).tolist()):
            if not check(i, *bb):
                fail(i)
            room(i, *bb)
        det &= ~grow
    # Segmentation for neighbour masking in Kron/AUTO: pixels of objects that CLEAN removed
    # (in re-extracted regions) stay masked for everyone, so the masks do not depend on
    # which regions a given window re-extracted.
    pseg32 = pseg.astype(np.int32)
    pseg32[(pseg32 == 0) & (seg > 0)] = REMOVED
    kr = np.full(src.size, np.nan)
    for ii, sl in window_groups(cv, np.flatnonzero(det), edge, src_win):
        oy, ox = sl[0].start, sl[1].start
        kr[ii] = phot.kron_radius(cv.det[sl], xs[ii] - ox, ys[ii] - oy, a[ii], b[ii], th[ii],
                                  segmap=pseg32[sl], seg_id=label[ii], mask=cv.nodata[sl])
    scale = phot.auto_scale(kr, params.phot_autoparams)
    if not full:
        dya, dxa = ellipse_half_extent(a, b, th, scale)
        rap = 0.5 * max(params.phot_apertures)
        dya, dxa = np.maximum(dya, rap), np.maximum(dxa, rap)
        # MASK_TYPE CORRECT reads pixels mirrored about the centre: up to 2 more pixels out
        grow_px = 2 if params.mask_type is not None else 0
        if params.backphoto_type == "local":
            sbox = phot.segment_boxes(pix, lab_pix, W_cv, nl)
            _, annulus = phot.local_background_boxes(sbox[label], params.backphoto_thick, ctx.shape)
        ii = np.flatnonzero(det)
        for i, bb in zip(ii.tolist(), ellipse_boxes(xs[ii], ys[ii], dya[ii], dxa[ii], grow_px).tolist()):
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
    batch = SegmentedBatch(cv, pseg, pseg32, label * fin, xs, ys, a, b, th, scale, src, src_win, fin, rect, wy0,
                           wx0, edge, phot_box, bounds, pix, lab_pix)
    return np.array(regrow, dtype=np.int64), batch


def _segment_table(cat):
    """Label-indexed geometry (index 0 = no detection), as lists of arrays to concatenate."""
    return {f: [np.array([np.nan]), np.asarray(cat[f], dtype=np.float64)] for f in ("x", "y", "a", "b", "theta")}


def _isolate(cv, comp, c, box, win, pseg, tab, next_label, ctx, offset):
    """Re-extract region ``c`` alone (fresh deblending RNG; sep's CLEAN inside it, if on).

    The cut-out is the region's box plus the filter half-width + 1, clipped to
    the window ``win`` (y0, y1, x0, x1), so it is the same array in a window
    and in the full frame.  ``offset`` (dy, dx) turns canvas into image
    coordinates: the same region (same image position, same pixels) met again
    in another window or a later round reuses the first result, which is
    exact because the extraction depends only on the cut-out.  The region's
    children get labels ``next_label ...``; their geometry is appended to ``tab``.
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
        try:
            cat, seg = isolate_region(cv.det32[y0:y1, x0:x1], cv.derr[y0:y1, x0:x1], cv.nodata[y0:y1, x0:x1],
                                      inside, params, clean=params.clean)
        except DetectionError:
            ctx.isolated[key] = None
            raise
        hit = (np.where(inside, seg, 0), cat, len(cat))
        ctx.isolated[key] = hit
    seg, cat, k = hit
    region = pseg[y0:y1, x0:x1]
    region[inside] = 0
    new = seg > 0
    region[new] = seg[new] + (next_label - 1)
    rows = np.array(cat, copy=True)
    rows["x"] = rows["x"] + x0      # cut-out -> canvas
    rows["y"] = rows["y"] + y0
    tab["x"].append(rows["x"].astype(np.float64))
    tab["y"].append(rows["y"].astype(np.float64))
    for f in ("a", "b", "theta"):
        tab[f].append(np.asarray(cat[f], dtype=np.float64))
    return next_label + k


