"""The segmentation product of a full image: what every detection backend returns.

A :class:`Segmentation` is a post-CLEAN segmentation map with one geometry row
per label (barycentre, second-moment ellipse), plus, for sep, the pre-CLEAN
objects that produced it.  :mod:`glaciar.engine.measure` classifies and
measures injected sources on it, whichever backend made it:

* ``sep`` (:func:`sep_segmentation`): sep's detection and deblending, with

  - *canonical deblending*: sep hands the faint pixels of a split region to
    its children with random numbers from one stream per call, so a
    deblended footprint depends on every region extracted before it.  Each
    split region is re-extracted alone (its box plus the filter half-width
    + 1; RMS infinite outside the region), which makes the split a function
    of the region's own pixels -- the same in a cut-out and in the full frame.
  - *CLEAN applied by glaciar* (:mod:`glaciar.engine.clean`) on the
    canonically deblended objects in sep's order, as
    ``DetectionParams.clean_style`` says: ``"sextractor"`` (default),
    SExtractor's incremental CLEAN, where an absorbed object's pixels go to
    the object that absorbed it (following the chain to a survivor; its
    ``mergeobject``); ``"sep"``, sep's CLEAN bit for bit, removed pixels left
    unlabelled; ``"sep-merge"``, sep's decisions with SExtractor's hand-over.
    The absorbing object keeps its own barycentre and ellipse (SExtractor
    does not update them); its isophotal flux, measured on the map, includes
    the absorbed pixels.

* ``source-extractor`` (:mod:`glaciar.engine.sextractor_backend`): the
  SExtractor binary's check-image segmentation and catalogue.

With the default ``clean_style="region"`` the windowed engine never builds the
full product of an injected image: it reproduces its segmentation exactly around
each injected source (:mod:`glaciar.engine.windows`).  The task-wide CLEAN styles
(the other three) are made here, on the whole injected image
(:func:`glaciar.engine.measure.runs_full_frame`), and on the original image once
per field for its reference.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from glaciar.engine import clean as cl
from glaciar.engine import sepscan
from glaciar.engine.blocks import row_tiles
from glaciar.engine.detect import SEP_OBJ_MERGED, DetectionParams, sep_extract, detection_rms, sanitize

__all__ = ["Segmentation", "SegmentedBatch", "sep_segmentation", "isolate_region", "apply_clean",
           "clean_extraction",
           "sep_extract_clean", "EMULATED_CLEAN_MIN_OBJECTS"]

_BIG_RMS = np.float32(1e30)


@dataclass(eq=False)
class Segmentation:
    """Post-CLEAN segmentation of one image and, for sep, its pre-CLEAN objects.

    Attributes
    ----------
    seg : ndarray of int32, shape (H, W)
        Post-CLEAN labels 1..n (0: no object).
    x, y, a, b, theta : ndarray of float64, shape (n,)
        Geometry of label ``k`` at index ``k - 1``: barycentre [pixels, 0-based,
        x along axis 1], semi-axes [pixels], position angle [radians,
        counter-clockwise from +x].
    flux_iso : ndarray of float64 or None, shape (n,)
        The backend's own isophotal flux, when it reports one [image units].
    pre_seg : ndarray of int32 or None
        Pre-CLEAN labels 1..m, in sep's object order (sep backend only): with
        ``seg``, which pixels belong to objects CLEAN removed.
    cat : structured ndarray or None, shape (m,)
        sep catalogue rows of the pre-CLEAN objects (image coordinates).
    owner : ndarray of int64, shape (m,)
        Pre-CLEAN index of the surviving object each object's pixels went
        to (itself for survivors; -1: removed and left unlabelled).
    """

    seg: np.ndarray
    x: np.ndarray
    y: np.ndarray
    a: np.ndarray
    b: np.ndarray
    theta: np.ndarray
    flux_iso: np.ndarray | None = None
    pre_seg: np.ndarray | None = None
    cat: np.ndarray | None = None
    owner: np.ndarray | None = None

    def __len__(self):
        return int(np.size(self.x))


@dataclass(frozen=True, eq=False)
class SegmentedBatch:
    """The exact segmentation of a batch of sources on one canvas (what photometry needs).

    Arrays of length B are per source of the batch (canvas coordinates).

    Attributes
    ----------
    canvas : glaciar.engine.canvas.Canvas
    seg : ndarray of int64
        Canvas segmentation (canonically deblended, CLEAN applied).
    seg32 : ndarray of int32
        ``seg`` with pixels of objects CLEAN removed set to :data:`glaciar.engine.windows.REMOVED`
        (masked as neighbours for everyone).
    label : ndarray of int (B,)
        Label of each source's detection in ``seg`` (0: none, or not done).
    x, y, a, b, theta : ndarray (B,)
        The detection's centroid [canvas pixels] and shape.
    kron_scale : ndarray (B,)
        AUTO ellipse scale (Kron factor x radius, at least the minimum radius).
    src : ndarray of int (B,)
        Index of each source in the call.
    src_win : ndarray of int (B,)
        Its window on the canvas.
    done : ndarray of bool (B,)
        Exact: to be measured now (the others grow and are redone).
    rect : ndarray (B, 4)
        Its window (y0, y1, x0, x1) [image pixels].
    wy0, wx0 : ndarray (B,)
        The window's corner on the canvas.
    edge : ndarray of bool (B,)
        Apertures reach the window edge: measured on the window alone.
    phot_box : ndarray (B, 4)
        Canvas box photometry reads (AUTO ellipse, apertures).
    bounds : ndarray (B, 4)
        The window on the canvas (y0, y1, x0, x1).
    pix, lab_pix : ndarray
        ``np.flatnonzero(seg)`` and the labels there.
    """

    canvas: "Canvas"
    seg: np.ndarray
    seg32: np.ndarray
    label: np.ndarray
    x: np.ndarray
    y: np.ndarray
    a: np.ndarray
    b: np.ndarray
    theta: np.ndarray
    kron_scale: np.ndarray
    src: np.ndarray
    src_win: np.ndarray
    done: np.ndarray
    rect: np.ndarray
    wy0: np.ndarray
    wx0: np.ndarray
    edge: np.ndarray
    phot_box: np.ndarray
    bounds: np.ndarray
    pix: np.ndarray
    lab_pix: np.ndarray


# --------------------------------------------------------------------------
# One region
# --------------------------------------------------------------------------
def isolate_region(data32, err32, nodata, inside, params: DetectionParams, clean: bool = False):
    """sep on one region alone: canonical deblending (CLEAN off unless ``clean``).

    Parameters
    ----------
    data32, err32 : ndarray of float32
        Cut-out holding the region plus at least the filter half-width around
        it [image units].
    nodata : ndarray of bool
    inside : ndarray of bool
        The region's pixels; the RMS is set to 1e30 elsewhere, so nothing else
        is detected while the filtered values of the region stay exact.
    params : DetectionParams
    clean : bool
        Run sep's CLEAN inside the region (``clean_style="region"``: CLEAN
        acts between the deblended children of one region only).

    Returns
    -------
    cat, seg : sep catalogue and segmentation of the cut-out

    Raises
    ------
    DetectionError
    """
    err = np.array(err32, dtype=np.float32, order="C")
    err[~inside] = _BIG_RMS
    return sep_extract(np.ascontiguousarray(data32, dtype=np.float32), err,
                        np.ascontiguousarray(nodata), params, bool(clean))


def _region_objects(pix, cat, seg, data32, filt, thr, params: DetectionParams):
    """CLEAN inputs of the objects of one region of a cut-out.

    Parameters
    ----------
    pix : ndarray of int
        The region's pixels (flat indices of the cut-out) in sep's scan order
        (:func:`~glaciar.engine.sepscan.lutz_regions`).
    cat : structured ndarray
        sep rows of the region's objects (cut-out coordinates): one row, or
        the children of its isolated extraction.
    seg : ndarray of int
        Cut-out labels: pixel -> row index + 1 of ``cat`` (0 elsewhere).
    data32, filt, thr : ndarray of float32
        Cut-out image, filtered image and threshold [image units].
    params : DetectionParams

    Returns
    -------
    CleanObjects
        Barycentres as in ``cat``.
    """
    w = seg.shape[1]
    n = len(cat)
    sf = np.asarray(seg).ravel()
    if n == 1:
        orders = [pix]
    else:
        oo = sepscan.child_pixel_orders(pix, w, sf, filt.ravel(), list(range(1, n + 1)),
                                   np.float32(cat["thresh"][0]), params.deblend_nthresh)
        orders = [oo[k] for k in range(1, n + 1)]
    return cl.clean_objects(cat, orders, data32.ravel(), filt.ravel(), thr.ravel(), params.detect_minarea)


# --------------------------------------------------------------------------
# Full image
# --------------------------------------------------------------------------
def apply_clean(objects: cl.CleanObjects, params: DetectionParams):
    """CLEAN as configured (``params.clean``, ``params.clean_style``) on objects in sep's order.

    Returns
    -------
    owner : ndarray of int64
        Index of the object whose label each object's pixels take: itself if
        it survives, the surviving absorber when removed pixels are handed
        over (styles ``"sextractor"`` and ``"sep-merge"``), -1 when they are
        left unlabelled (``"sep"``).
    survives : ndarray of bool
    """
    n = len(objects)
    if not params.clean or n < 2:
        return np.arange(n, dtype=np.int64), np.ones(n, dtype=bool)
    beta = float(params.clean_param)
    if params.clean_style == "sextractor":
        surv, eater = cl.sextractor_clean(objects, beta, objects.tmin)
    else:
        surv, eater = cl.sep_clean(objects, beta)
    own = cl.final_owner(surv, eater)
    if params.clean_style == "sep":
        own = np.where(surv, np.arange(n), -1)
    return own, surv


def sep_segmentation(image_sub, err, params: DetectionParams, mask=None) -> Segmentation:
    """The sep backend's product for a full image.

    Parameters
    ----------
    image_sub : ndarray
        Background-subtracted detection image [image units].
    err : ndarray
        Per-pixel RMS [image units] (the threshold multiplies it, or its
        filtered version: ``params.threshold_rms``).
    params : DetectionParams
    mask : ndarray of bool, optional
        True where there are no data.

    Returns
    -------
    Segmentation
        With canonical deblending and CLEAN as described in the module
        docstring; ``pre_seg``, ``cat`` and ``owner`` filled.

    Raises
    ------
    DetectionError
        When sep fails on the image or on a split region.
    """
    data, e, nodata = sanitize(image_sub, err, mask)
    e = detection_rms(e, nodata, params)
    H, W = data.shape
    cat0, seg0 = sep_extract(data, e, nodata, params, False)
    dmask, filt, thr = sepscan.detection_mask(data, e, nodata, params)
    comps = sepscan.lutz_regions(dmask, 1)
    sf = seg0.ravel()
    pad = params.filter_halfwidth + 1
    cats, pre_seg = [], np.zeros((H, W), dtype=np.int32)
    objs = []
    nxt = 1
    for pix, _, _ in comps:                 # in sep's order (where its scan closes each region)
        if pix.size < params.detect_minarea:
            continue
        ys, xs = np.divmod(pix, W)
        box = (int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1)
        labs = sf[pix]
        labs = np.unique(labs[labs > 0])
        if labs.size == 0:
            continue
        y0, y1 = max(box[0] - pad, 0), min(box[1] + pad, H)
        x0, x1 = max(box[2] - pad, 0), min(box[3] + pad, W)
        inside = np.zeros((y1 - y0, x1 - x0), dtype=bool)
        inside[ys - y0, xs - x0] = True
        local = (ys - y0) * (x1 - x0) + (xs - x0)
        if labs.size == 1:
            c = cat0[labs - 1]
            lseg = inside.astype(np.int32)
        else:
            c, lseg = isolate_region(data[y0:y1, x0:x1], e[y0:y1, x0:x1], nodata[y0:y1, x0:x1], inside, params)
            lseg = np.where(inside, lseg, 0)
            c = _shift(c, y0, x0)
        objs.append(_region_objects(local, c, lseg, data[y0:y1, x0:x1], filt[y0:y1, x0:x1],
                                    thr[y0:y1, x0:x1], params))
        cats.append(c)
        sub = pre_seg[y0:y1, x0:x1]
        sub[lseg > 0] = lseg[lseg > 0] + (nxt - 1)
        nxt += len(c)
    if objs:
        objects, cat = cl.CleanObjects.concat(objs), np.concatenate(cats)
    else:
        objects, cat = cl.CleanObjects.empty(), cat0[:0]
    owner, surv = apply_clean(objects, params)
    return _post_clean(pre_seg, cat, owner, surv)


def _post_clean(pre_seg, cat, owner, surv):
    """The post-CLEAN product: survivors relabelled 1..n in order, pixels to their owners."""
    m = len(cat)
    post_label = np.zeros(m + 1, dtype=np.int64)
    keep = np.flatnonzero(surv)
    post_label[keep + 1] = np.arange(1, keep.size + 1)
    post = np.where(owner >= 0, post_label[np.maximum(owner, 0) + 1], 0)
    lut = np.zeros(m + 1, dtype=np.int32)
    lut[1:] = post
    seg = lut[pre_seg]
    a = np.maximum(np.asarray(cat["a"], dtype=np.float64)[keep], 0.0) if m else np.zeros(0)
    return Segmentation(seg=seg, x=np.asarray(cat["x"], dtype=np.float64)[keep],
                        y=np.asarray(cat["y"], dtype=np.float64)[keep], a=a,
                        b=np.asarray(cat["b"], dtype=np.float64)[keep],
                        theta=np.asarray(cat["theta"], dtype=np.float64)[keep], pre_seg=pre_seg, cat=cat,
                        owner=np.asarray(owner, dtype=np.int64))


def _shift(cat, dy, dx):
    """Copy of sep rows with pixel coordinates shifted by (dy, dx)."""
    c = np.array(cat, copy=True)
    for f in ("x", "xpeak", "xcpeak", "xmin", "xmax"):
        if f in c.dtype.names:
            c[f] = c[f] + dx
    for f in ("y", "ypeak", "ycpeak", "ymin", "ymax"):
        if f in c.dtype.names:
            c[f] = c[f] + dy
    return c


# --------------------------------------------------------------------------
# Full-frame sep extraction with CLEAN, in linear time
# --------------------------------------------------------------------------
#: Pre-CLEAN objects from which :func:`sep_extract_clean` replaces sep's own CLEAN
#: (quadratic in the number of objects) by glaciar's (linear); below it sep's is
#: faster.  From ``benchmarks/fullframe_clean.py`` on the demo survey (loaded 2-core
#: machine): emulation / sep time 1.9 at 28k objects (4000^2), 0.83 at 69k (6000^2),
#: 0.46 at 116k (8000^2); the two meet near 57k.
EMULATED_CLEAN_MIN_OBJECTS = 60000
#: Fewest image pixels per pre-CLEAN object expected (the demo survey has ~550): images
#: too small to hold EMULATED_CLEAN_MIN_OBJECTS objects at that density go straight to
#: sep's CLEAN, without an extraction to count them (a guess: it only decides speed)
_MIN_PIXELS_PER_OBJECT = 100


def sep_extract_clean(data, err, nodata, params: DetectionParams, min_objects=None):
    """What ``sep.extract(..., clean=True)`` returns, in time linear in the number of objects.

    sep's CLEAN compares every object with every earlier one.  Here sep runs
    with CLEAN off and glaciar's bit-exact CLEAN (:mod:`glaciar.engine.clean`)
    removes the same objects: the catalogue rows of the survivors and the
    segmentation relabelled 1..n in their order, removed objects' pixels 0,
    exactly as sep's.

    Parameters
    ----------
    data, err, nodata : ndarray
        As passed to sep (:func:`glaciar.engine.detect.sep_extract`): sanitized
        float32 image and the detection RMS [image units], no-data mask.
    params : DetectionParams
        Detection settings; CLEAN_PARAM from ``params.clean_param`` (CLEAN is
        applied whatever ``params.clean`` says).
    min_objects : int, optional
        Below this many pre-CLEAN objects sep's own CLEAN is run instead
        (default :data:`EMULATED_CLEAN_MIN_OBJECTS`; 0: always glaciar's).

    Returns
    -------
    cat : structured ndarray
        sep's catalogue of the surviving objects.
    seg : ndarray of int32
        Segmentation map (0: no object).

    Raises
    ------
    DetectionError
        When sep fails.

    Notes
    -----
    Memory beyond sep's own output stays bounded: per-object pixel statistics
    are gathered by row tiles with the filter's halo, and the segmentation is
    relabelled in place.  ``mthresh`` (which needs an object's pixel order) is
    computed only for objects whose CLEAN test is not settled by the bounds
    ``min <= mthresh <= max`` of ``filtered - threshold`` over the object's
    pixels (:func:`glaciar.engine.clean.sep_clean_bounded`), region by region.
    sep's quirks are kept: no-data pixels of the first ``filter_halfwidth``
    rows are not masked (:func:`~glaciar.engine.sepscan.threshold_map`).  The matched filter's
    detection mask is reproduced only up to rounding, so with
    ``filter_type="matched"`` sep's own CLEAN is always used.  Images too
    small to hold ``min_objects`` objects at ``_MIN_PIXELS_PER_OBJECT`` go
    straight to sep's CLEAN; on larger ones below the crossover the extraction
    without CLEAN is spent for the count.
    """
    min_objects = EMULATED_CLEAN_MIN_OBJECTS if min_objects is None else int(min_objects)
    if (params.filter_kernel is not None and params.filter_type == "matched") or \
            np.size(data) < min_objects * _MIN_PIXELS_PER_OBJECT:
        return sep_extract(data, err, nodata, params, True)
    cat, seg = sep_extract(data, err, nodata, params, False)
    n = len(cat)
    if n < min_objects:
        del seg
        return sep_extract(data, err, nodata, params, True)
    return clean_extraction(cat, seg, data, err, nodata, params)


def clean_extraction(cat, seg, data, err, nodata, params: DetectionParams):
    """sep's CLEAN applied to a CLEAN-off extraction ``(cat, seg)`` of ``data`` (glaciar's
    bit-exact emulation, :func:`sep_extract_clean`'s second half): the survivors' rows and
    ``seg`` relabelled in place.  The arrays are read by row tiles and cut-outs only."""
    n = len(cat)
    if n < 2:
        return cat, seg
    objs, lo, hi = _tiled_light_objects(data, err, nodata, seg, cat, params)
    merged = (np.asarray(cat["flag"]) & SEP_OBJ_MERGED) != 0

    def mthresh_of(idx):
        # a deblended child's pixel order needs its region (its siblings' pixels too);
        # any other object is its whole region: its own pixels, gathered for all at once
        idx = np.asarray(idx, dtype=np.int64)
        out = _object_mthresh(idx[~merged[idx]], n, data, err, nodata, seg, params)
        wanted = np.zeros(n, dtype=bool)
        wanted[idx] = True
        for k in idx[merged[idx]].tolist():
            if k not in out:
                out.update(_region_mthresh(k, data, err, nodata, seg, cat, params, wanted))
        return np.array([out[k] for k in idx.tolist()], dtype=np.float32)

    surv, _ = cl.sep_clean_bounded(objs, float(params.clean_param), lo, hi, mthresh_of)
    keep = np.flatnonzero(surv)
    lut = np.zeros(n + 1, dtype=np.int32)
    lut[keep + 1] = np.arange(1, keep.size + 1, dtype=np.int32)
    for y0, y1, _, _ in row_tiles(seg.shape, 0):
        seg[y0:y1] = lut[seg[y0:y1]]
    return cat[keep], seg


def _tile_as_sep(data, err, nodata, ya, yb, params: DetectionParams):
    """Rows ``[ya, yb)`` of the image (float32), filtered and thresholded as sep does them
    (rows within the filter's half-height of ``ya`` or ``yb`` are right only if those are
    the image's edges: the caller reads a halo)."""
    d = np.asarray(data[ya:yb], dtype=np.float32)
    filt = d if params.filter_kernel is None else sepscan.sep_filter(d, params.filter_kernel)
    return d, filt, sepscan.threshold_map(err[ya:yb], nodata[ya:yb], params, y0=ya)


def _tiled_light_objects(data, err, nodata, seg, cat, params: DetectionParams):
    """CLEAN inputs that need no pixel order of a full image's objects, by row tiles.

    Returns
    -------
    objects : CleanObjects
        ``mthresh`` NaN.
    lo, hi : ndarray of float32
        Bounds of each object's ``mthresh``: min and max of ``filtered -
        threshold`` over its pixels, both 0 for objects with fewer than
        DETECT_MINAREA pixels (their ``mthresh`` is 0) [image units].
    """
    n = len(cat)
    lo = np.full(n, np.inf, dtype=np.float32)
    hi = np.full(n, -np.inf, dtype=np.float32)
    tmin = np.full(n, np.inf, dtype=np.float32)
    npx = np.zeros(n, dtype=np.int64)
    area2 = np.zeros(n, dtype=np.float64)
    th = np.asarray(cat["thresh"], dtype=np.float32)
    thresh2 = (th.astype(np.float64) + np.asarray(cat["peak"], dtype=np.float32).astype(np.float64)) / 2.0
    for y0, y1, ya, yb in row_tiles(seg.shape, params.filter_halfwidth):
        lab = seg[y0:y1]
        on = lab > 0
        if not on.any():
            continue
        li = lab[on] - 1
        d, filt, thr = _tile_as_sep(data, err, nodata, ya, yb, params)
        r = slice(y0 - ya, y1 - ya)
        t_on = thr[r][on]
        tp = (filt[r][on] - t_on).astype(np.float32)
        np.minimum.at(lo, li, tp)
        np.maximum.at(hi, li, tp)
        np.minimum.at(tmin, li, t_on)
        npx += np.bincount(li, minlength=n)
        area2 += np.bincount(li, weights=d[r][on].astype(np.float64) > thresh2[li], minlength=n)
    small = npx < int(params.detect_minarea)                # heap_mthresh: 0 below DETECT_MINAREA
    lo[small] = 0.0
    hi[small] = 0.0
    a = np.asarray(cat["a"], dtype=np.float32)
    b = np.asarray(cat["b"], dtype=np.float32)
    ab = cl.abcor(th, thresh2, area2, cat["tnpix"], a, b)
    objs = cl.CleanObjects(x=np.asarray(cat["x"], dtype=np.float64), y=np.asarray(cat["y"], dtype=np.float64),
                           a=a, b=b, cxx=np.asarray(cat["cxx"], dtype=np.float32),
                           cyy=np.asarray(cat["cyy"], dtype=np.float32),
                           cxy=np.asarray(cat["cxy"], dtype=np.float32),
                           fdflux=np.asarray(cat["cflux"], dtype=np.float32), thresh=th,
                           npix=np.asarray(cat["npix"], dtype=np.int64), abcor=ab,
                           mthresh=np.full(n, np.nan, dtype=np.float32), tmin=tmin)
    return objs, lo, hi


def _region_mthresh(k, data, err, nodata, seg, cat, params: DetectionParams, wanted=None):
    """Exact ``mthresh`` of the objects of the deblended region holding object ``k``.

    sep labels every pixel of a region (its deblending hands each pixel of a
    split region to one child), so the region is the 8-connected component of
    labelled pixels holding ``k``'s pixels: found in a cut-out grown until it
    holds the component with a blank border, then put in sep's order
    (:func:`~glaciar.engine.sepscan.lutz_one`,
    :func:`~glaciar.engine.sepscan.child_pixel_orders`).

    ``wanted`` (bool per object, optional) limits the work to the children it
    marks (and ``k``): a child's order does not depend on its siblings'.

    Returns
    -------
    dict index -> float32
    """
    H, W = seg.shape
    h = params.filter_halfwidth
    y0, y1 = int(cat["ymin"][k]), int(cat["ymax"][k]) + 1
    x0, x1 = int(cat["xmin"][k]), int(cat["xmax"][k]) + 1
    eight = np.ones((3, 3), dtype=bool)
    while True:
        cy0, cy1, cx0, cx1 = max(y0 - 1, 0), min(y1 + 1, H), max(x0 - 1, 0), min(x1 + 1, W)
        lab = seg[cy0:cy1, cx0:cx1]
        comp = ndimage.label(lab > 0, structure=eight)[0]
        inside = comp == comp[lab == k + 1][0]          # the children of a region are connected
        sib = np.unique(lab[inside]) - 1
        # the component's objects' boxes: the whole region once they fit (no pixel in the border)
        by0, by1 = int(cat["ymin"][sib].min()), int(cat["ymax"][sib].max()) + 1
        bx0, bx1 = int(cat["xmin"][sib].min()), int(cat["xmax"][sib].max()) + 1
        if by0 >= y0 and by1 <= y1 and bx0 >= x0 and bx1 <= x1:
            break
        y0, y1, x0, x1 = min(y0, by0), max(y1, by1), min(x0, bx0), max(x1, bx1)
    fy0, fy1, fx0, fx1 = max(cy0 - h, 0), min(cy1 + h, H), max(cx0 - h, 0), min(cx1 + h, W)
    d = np.asarray(data[fy0:fy1, fx0:fx1], dtype=np.float32)
    filt = d if params.filter_kernel is None else sepscan.sep_filter(d, params.filter_kernel)
    c = (slice(cy0 - fy0, cy1 - fy0), slice(cx0 - fx0, cx1 - fx0))
    filt = np.ascontiguousarray(filt[c])
    thr = sepscan.threshold_map(err[cy0:cy1, cx0:cx1], nodata[cy0:cy1, cx0:cx1], params, y0=cy0)
    pix = sepscan.lutz_one(inside)[0]
    labs = sib + 1
    if labs.size == 1:
        orders = {int(labs[0]): pix}
    else:
        todo = labs if wanted is None else labs[wanted[sib] | (sib == k)]
        orders = sepscan.child_pixel_orders(pix, inside.shape[1], lab.ravel(), filt.ravel(), todo.tolist(),
                                       np.float32(cat["thresh"][labs[0] - 1]), params.deblend_nthresh)
    tp = (filt - thr).astype(np.float32).ravel()
    return {lab_ - 1: sepscan.heap_mthresh(tp[o], params.detect_minarea) for lab_, o in orders.items()}


def _object_mthresh(idx, n_objects, data, err, nodata, seg, params: DetectionParams):
    """Exact ``mthresh`` of objects that are a whole region each (not deblended).

    Their pixels are gathered by row tiles (raster order), put in sep's order
    by :func:`~glaciar.engine.sepscan.lutz_one` on each object's own mask, and
    run through :func:`~glaciar.engine.sepscan.heap_mthresh`.

    Returns
    -------
    dict index -> float32
    """
    idx = np.asarray(idx, dtype=np.int64)
    if idx.size == 0:
        return {}
    H, W = seg.shape
    need = np.zeros(int(n_objects) + 1, dtype=bool)
    need[idx + 1] = True
    flats, labs, tps = [], [], []
    for y0, y1, ya, yb in row_tiles(seg.shape, params.filter_halfwidth):
        lab = seg[y0:y1].ravel()
        sel = np.flatnonzero(need[lab])
        if sel.size == 0:
            continue
        _, filt, thr = _tile_as_sep(data, err, nodata, ya, yb, params)
        r = slice(y0 - ya, y1 - ya)
        tps.append((filt[r].ravel()[sel] - thr[r].ravel()[sel]).astype(np.float32))
        flats.append(sel + y0 * W)
        labs.append(lab[sel])
    flat, lab, tp = np.concatenate(flats), np.concatenate(labs), np.concatenate(tps)
    order = np.argsort(lab, kind="stable")            # each object's pixels in raster order
    flat, lab, tp = flat[order], lab[order], tp[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    ends = np.r_[starts[1:], lab.size]
    out = {}
    m = int(params.detect_minarea)
    for s0, s1 in zip(starts.tolist(), ends.tolist()):
        ys, xs = np.divmod(flat[s0:s1], W)
        y0, x0 = int(ys.min()) - 1, int(xs.min()) - 1
        w = int(xs.max()) - x0 + 2
        mask = np.zeros((int(ys.max()) - y0 + 2, w), dtype=bool)
        local = (ys - y0) * w + (xs - x0)               # increasing: raster order
        mask.ravel()[local] = True
        pix = sepscan.lutz_one(mask)[0]
        out[int(lab[s0]) - 1] = sepscan.heap_mthresh(tp[s0:s1][np.searchsorted(local, pix)], m)
    return out
