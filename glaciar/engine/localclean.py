"""CLEAN of an injected image without extracting the full frame, exactly.

CLEAN (sep's or SExtractor's, :mod:`glaciar.engine.clean`) runs through the
whole list of pre-CLEAN objects of an image in scan order, so what a window
sees is not enough.  But the injected image's object list need not be
extracted in full either: it is exactly

* the *unchanged* objects of the original image, from its product
  (:func:`~glaciar.engine.segmentation.sep_segmentation`, once per field): a
  region whose box stays more than ``filter half-width + 1`` pixels from
  every stamp box has the same pixels, filtered values and thresholds in the
  injected image, hence the same (canonically deblended) objects, CLEAN
  inputs and place in the scan order;
* plus the *affected* objects -- every other region -- from one extraction
  per task (:func:`task_clean`) of the *influence boxes* of the stamps: each
  stamp box widened by the filter half-width + 1, united with the boxes of the
  original above-threshold regions (of any size) it touches, clusters of
  stamps merged transitively.  An affected region is a connected set of
  pixels whose filtered value changed and of original regions touching them,
  so it lies inside its cluster's influence box, and an extraction of that box
  plus ``filter half-width + 1`` pixels gives it exactly.

Both sets use the same box test, so they partition the injected image's
objects.  :class:`TaskClean` runs CLEAN once on their union, in sep's scan
order, and every window of the task reads the outcome: the same, by
construction, as a full-frame extraction's.
"""
from __future__ import annotations

import numpy as np

from glaciar.engine import clean as cl
from glaciar.engine import sepscan
from glaciar.engine.detect import DetectionParams, sep_extract, detection_rms, sanitize
from glaciar.engine.canvas import label_boxes, pack_windows

__all__ = ["TaskClean", "task_clean", "influence_boxes", "stamp_boxes"]


def _intersect(a, b):
    """(len(a), len(b)) boolean: boxes (y0, y1, x0, x1) intersect (half-open)."""
    return ((a[:, None, 0] < b[None, :, 1]) & (a[:, None, 1] > b[None, :, 0])
            & (a[:, None, 2] < b[None, :, 3]) & (a[:, None, 3] > b[None, :, 2]))


def _any_intersect(a, b, chunk=2048):
    """For each box of ``a``, does it intersect any box of ``b``?"""
    out = np.zeros(a.shape[0], dtype=bool)
    if a.shape[0] == 0 or b.shape[0] == 0:
        return out
    for lo in range(0, b.shape[0], chunk):
        out |= _intersect(a, b[lo:lo + chunk]).any(axis=1)
    return out


def stamp_boxes(scene) -> np.ndarray:
    """Boxes (y0, y1, x0, x1) of every stamp a scene adds [image pixels] (a coadd: its bands')."""
    parts = [stamp_boxes(s) for s in getattr(scene, "scenes", [])]
    if getattr(scene, "stamps", None):
        parts.append(np.stack([scene._y0, scene._y1, scene._x0, scene._x1], axis=1).astype(np.int64))
    return np.concatenate(parts) if parts else np.zeros((0, 4), dtype=np.int64)


def influence_boxes(stamp_boxes, shape, halfwidth: int, comp_box=None):
    """Widened stamp boxes and the influence boxes of their clusters.

    Parameters
    ----------
    stamp_boxes : ndarray of int, shape (S, 4)
        Stamp boxes (y0, y1, x0, x1) [image pixels] (may exceed the image).
    shape : (int, int)
        Image shape.
    halfwidth : int
        Filter half-width [pixels].
    comp_box : ndarray of int, shape (K, 4), optional
        Boxes of every original above-threshold region.

    Returns
    -------
    widened : ndarray of int64, shape (S, 4)
        Stamp boxes widened by ``halfwidth + 1`` and clipped to the image: a
        region whose box misses all of them is unchanged by the injection.
    clusters : ndarray of int64, shape (C, 4)
        Influence boxes: widened stamp boxes linked when they meet or touch the
        same original region, united with the original regions they touch.
    """
    ny, nx = shape
    g = int(halfwidth) + 1
    sb = np.asarray(stamp_boxes, dtype=np.int64).reshape(-1, 4).copy()
    sb += np.array([-g, g, -g, g])
    sb[:, 0::2] = np.maximum(sb[:, 0::2], 0)
    sb[:, 1] = np.minimum(sb[:, 1], ny)
    sb[:, 3] = np.minimum(sb[:, 3], nx)
    S = sb.shape[0]
    if S == 0:
        return sb, np.zeros((0, 4), dtype=np.int64)
    cb = np.zeros((0, 4), dtype=np.int64) if comp_box is None else np.asarray(comp_box, dtype=np.int64)
    parent = list(range(S))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*np.nonzero(np.triu(_intersect(sb, sb), 1))):
        ri, rj = find(int(i)), find(int(j))
        if ri != rj:
            parent[rj] = ri
    comp_stamp = {}
    for lo in range(0, cb.shape[0], 4096):
        ci, si = np.nonzero(_intersect(cb[lo:lo + 4096], sb))
        for c, s in zip((ci + lo).tolist(), si.tolist()):
            if c in comp_stamp:
                ra, rb = find(comp_stamp[c]), find(s)
                if ra != rb:
                    parent[rb] = ra
            else:
                comp_stamp[c] = s
    box = {}
    for s in range(S):
        r = find(s)
        e = box.setdefault(r, list(sb[s]))
        e[0], e[1] = min(e[0], sb[s, 0]), max(e[1], sb[s, 1])
        e[2], e[3] = min(e[2], sb[s, 2]), max(e[3], sb[s, 3])
    for c, s in comp_stamp.items():
        e = box[find(s)]
        e[0], e[1] = min(e[0], cb[c, 0]), max(e[1], cb[c, 1])
        e[2], e[3] = min(e[2], cb[c, 2]), max(e[3], cb[c, 3])
    return sb, np.array(sorted(box.values()), dtype=np.int64).reshape(-1, 4)


class _Region:
    """An affected region of the task canvas; its objects are made when first needed.

    A region with one segment is one object at once (sep's row); a split
    region is re-extracted alone (canonical deblending) on first use.
    """

    __slots__ = ("box", "inside", "data", "err", "nod", "filt", "thr", "origin", "rows", "lseg", "first",
                 "count", "key", "objects", "ikey", "light")

    def __init__(self, box, inside, data, err, nod, filt, thr, origin, rows, ikey):
        self.box = box                  # image (y0, y1, x0, x1)
        self.inside, self.data, self.err, self.nod = inside, data, err, nod
        self.filt, self.thr = filt, thr
        self.origin = origin            # image (y, x) of cut-out pixel (0, 0)
        self.rows = rows                # sep rows (cut-out coordinates) or None until isolated
        self.lseg = None
        self.first = -1                 # first object row
        self.count = 0
        self.key = None                 # (y_done, x_done) image
        self.objects = None             # CleanObjects (image coordinates) once computed
        self.ikey = ikey                # cache key of the isolated extraction
        self.light = None               # (CleanObjects without mthresh, its bounds)


class TaskClean:
    """The pre-CLEAN objects of one injected image and their CLEAN outcome.

    Identities: an int ``r >= 0`` is row ``r`` of the original product
    (``ref``); ``-(k + 1)`` is row ``k`` of the affected objects.  Split
    affected regions are re-extracted (canonical deblending) and every
    object's CLEAN inputs computed when the outcome is first asked for.

    Parameters
    ----------
    params : DetectionParams
    ref : Segmentation or None
        Original image's product.
    ref_usable : ndarray of bool
        Original objects unchanged by the injection.
    widened : ndarray (S, 4)
        Widened stamp boxes (:func:`influence_boxes`).
    regions : list of _Region
        Affected regions.
    region_pix, region_pix_id : ndarray
        Sorted flat image indices of the affected regions' pixels and the
        region of each.
    shape : (int, int)
    isolated : dict or None
        Shared cache of isolated extractions.
    """

    def __init__(self, params, ref, ref_usable, widened, regions, region_pix, region_pix_id, shape, isolated):
        self.params, self.ref, self.ref_usable, self.widened = params, ref, ref_usable, widened
        self.regions = regions
        self.region_pix, self.region_pix_id = region_pix, region_pix_id
        self.shape = shape
        self.isolated = isolated
        self.expanded = np.zeros(len(regions), dtype=bool)
        self.x, self.y, self.oreg = [], [], []
        self._own = None
        self._absorbed = {}
        for r, g in enumerate(regions):
            if g.rows is not None:          # one segment: its object is known now
                self._add_objects(r)

    # ---- regions -> objects
    def _add_objects(self, r):
        g = self.regions[r]
        if g.rows is None:
            from glaciar.engine.segmentation import isolate_region
            hit = None if self.isolated is None else self.isolated.get(g.ikey)
            if hit is None:
                rows, lseg = isolate_region(g.data, g.err, g.nod, g.inside, self.params)
                lseg = np.where(g.inside, lseg, 0)
                if self.isolated is not None:
                    self.isolated[g.ikey] = (lseg, rows, len(rows))
            else:
                lseg, rows, _ = hit
            g.rows, g.lseg = rows, lseg
        else:
            g.lseg = g.inside.astype(np.int32)
        g.first = len(self.x)
        g.count = len(g.rows)
        oy, ox = g.origin
        # image coordinates: the cut-out's offset added once to sep's value
        self.x.extend((np.asarray(g.rows["x"], dtype=np.float64) + ox).tolist())
        self.y.extend((np.asarray(g.rows["y"], dtype=np.float64) + oy).tolist())
        self.oreg.extend([r] * g.count)
        self.expanded[r] = True

    def at_pixel(self, flat):
        """Affected object (identity) holding image pixel ``flat``, or None."""
        k = int(np.searchsorted(self.region_pix, flat))
        if not (k < self.region_pix.size and self.region_pix[k] == flat):
            return None
        r = int(self.region_pix_id[k])
        if not self.expanded[r]:
            self._add_objects(r)
        g = self.regions[r]
        y, x = divmod(int(flat), self.shape[1])
        lab = int(g.lseg[y - g.origin[0], x - g.origin[1]])
        return -(g.first + lab - 1 + 1) if lab > 0 else None

    def pixel_of(self, ident, shape=None):
        """One image pixel (y, x) of an object."""
        if ident >= 0:
            return divmod(int(self.ref.first_pixel()[ident]), self.shape[1])
        k = -ident - 1
        g = self.regions[self.oreg[k]]
        yy, xx = np.nonzero(g.lseg == k - g.first + 1)
        return int(yy[0]) + g.origin[0], int(xx[0]) + g.origin[1]

    def region_box(self, ident):
        """Box (y0, y1, x0, x1) of an object's region [image pixels]."""
        if ident >= 0:
            return tuple(int(v) for v in self.ref.obj_box[ident])
        return tuple(int(v) for v in self.regions[self.oreg[-ident - 1]].box)

    def _region_objects(self, r):
        """CLEAN inputs (image coordinates) and scan key of affected region r's objects."""
        g = self.regions[r]
        if g.objects is None:
            from glaciar.engine.segmentation import region_objects
            o, (yd, xd) = region_objects(g.inside, g.rows, g.lseg, g.data, g.filt, g.thr, self.params)
            o.x = np.asarray(self.x[g.first:g.first + g.count], dtype=np.float64)
            o.y = np.asarray(self.y[g.first:g.first + g.count], dtype=np.float64)
            g.objects, g.key = o, (yd + g.origin[0], xd + g.origin[1])
        return g.objects, g.key

    def _clean_all(self):
        """CLEAN of the injected image's whole object list (unchanged originals + affected)."""
        if self._own is not None:
            return
        for r in range(len(self.regions)):
            if not self.expanded[r]:
                self._add_objects(r)
        parts, keys, ids = [], [], []
        if self.ref is not None and len(self.ref.objects):
            rid = np.flatnonzero(self.ref_usable)
            parts.append(self.ref.objects.take(rid))
            keys.append(np.asarray(self.ref.key, dtype=np.int64)[rid])
            ids.append(rid)
        for r, g in enumerate(self.regions):
            o, (yd, xd) = self._region_objects(r)
            parts.append(o)
            keys.append(np.c_[np.full(g.count, yd), np.full(g.count, xd), np.arange(g.count)].astype(np.int64))
            ids.append(-(np.arange(g.first, g.first + g.count) + 1))
        if not parts:
            self._own = {}
            return
        objs = cl.CleanObjects.concat(parts)
        key = np.concatenate(keys)
        ident = np.concatenate(ids).astype(np.int64)
        order = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
        from glaciar.engine.segmentation import apply_clean
        own, _ = apply_clean(objs.take(order), self.params)
        ident = ident[order]
        owner = np.where(own >= 0, ident[np.maximum(own, 0)], 0)
        self._own = {int(m): (int(w) if o >= 0 else None) for m, w, o in zip(ident, owner, own)}
        self._absorbed = {}
        for m, w in self._own.items():
            if w is not None:
                self._absorbed.setdefault(w, []).append(m)

    def owner(self, ident):
        """Object whose label ``ident``'s pixels take after CLEAN (None: unlabelled)."""
        self._clean_all()
        return self._own[ident]

    def absorbed(self, ident):
        """Objects whose pixels end in ``ident`` after CLEAN (itself included if it survives)."""
        self._clean_all()
        return list(self._absorbed.get(ident, []))


def task_clean(det_scene, det_rms, params: DetectionParams, ref=None, mask=None, isolated=None) -> TaskClean:
    """Pre-CLEAN objects of an injected image that differ from the original's.

    The influence boxes (plus ``filter half-width + 1`` pixels) are tiled
    into one canvas, separated by blank no-data gaps wider than the filter,
    and extracted with one sep call (CLEAN off); split regions are
    re-extracted alone (canonical deblending).

    Parameters
    ----------
    det_scene : Scene
        Original detection image plus the task's stamps.
    det_rms : ndarray
        Detection RMS [image units].
    params : DetectionParams
    ref : Segmentation or None
        Original image's product; None: CLEAN sees only regions near stamps.
    mask : ndarray of bool, optional
        True where there are no data.
    isolated : dict, optional
        Cache of isolated extractions keyed by (image box of the cut-out,
        region pixels), shared with the windows' canonical re-extraction (:mod:`glaciar.engine.windows`).

    Returns
    -------
    TaskClean

    Raises
    ------
    DetectionError
        When sep fails on the canvas or on a split region.
    """
    from scipy import ndimage

    shape = det_scene.shape
    ny, nx = shape
    hw = params.filter_halfwidth
    m = hw + 1
    sc = det_scene
    stamps = stamp_boxes(sc)
    widened, clusters = influence_boxes(stamps, shape, hw, None if ref is None else ref.comp_box)
    usable = (np.ones(0, dtype=bool) if ref is None
              else ~_any_intersect(np.asarray(ref.obj_box, dtype=np.int64), widened))
    if clusters.shape[0] == 0:
        return TaskClean(params, ref, usable, widened, [], np.zeros(0, dtype=np.int64),
                         np.zeros(0, dtype=np.int64), shape, isolated)
    rects = np.stack([np.maximum(clusters[:, 0] - m, 0), np.minimum(clusters[:, 1] + m, ny),
                      np.maximum(clusters[:, 2] - m, 0), np.minimum(clusters[:, 3] + m, nx)], axis=1)
    hh, ww = rects[:, 1] - rects[:, 0], rects[:, 3] - rects[:, 2]
    gap = max(m, 2)
    oy, ox, cshape = pack_windows(hh, ww, gap)
    det = np.zeros(cshape)
    err = np.ones(cshape, dtype=np.float32)
    nod = np.ones(cshape, dtype=bool)
    gap = np.ones(cshape, dtype=bool)
    sc.paste_windows(det, rects, oy, ox)
    for k, (y0, y1, x0, x1) in enumerate(rects.tolist()):
        sl = (slice(oy[k], oy[k] + y1 - y0), slice(ox[k], ox[k] + x1 - x0))
        err[sl] = det_rms[y0:y1, x0:x1]
        nod[sl] = False if mask is None else mask[y0:y1, x0:x1]
        gap[sl] = False
    data, err, nod = sanitize(det, err, nod)
    err = detection_rms(err, nod & ~gap, params, outside=gap)
    cat, seg = sep_extract(data, err, nod, params, False)
    dmask, filt, thr = sepscan.detection_mask(data, err, nod, params)
    dmask |= seg > 0
    comp, ncomp = ndimage.label(dmask, structure=np.ones((3, 3), dtype=bool))
    H, W = cshape
    nc = int(ncomp)
    empty_tc = TaskClean(params, ref, usable, widened, [], np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64),
                         shape, isolated)
    if nc == 0:
        return empty_tc
    cbox = label_boxes(comp, nc)[1:]
    # which window each region lies in (windows are separated by gaps wider than 1 pixel)
    win = np.full(cshape, -1, dtype=np.int64)
    for k, (y0, y1, x0, x1) in enumerate(rects.tolist()):
        win[oy[k]:oy[k] + y1 - y0, ox[k]:ox[k] + x1 - x0] = k
    wid = win[cbox[:, 0], cbox[:, 2]]
    off = np.stack([rects[wid, 0] - oy[wid], rects[wid, 2] - ox[wid]], axis=1)       # canvas -> image
    ibox = cbox + np.repeat(off, 2, axis=1)
    cbk = clusters[wid]
    keep = ((ibox[:, 0] >= cbk[:, 0]) & (ibox[:, 1] <= cbk[:, 1]) & (ibox[:, 2] >= cbk[:, 2])
            & (ibox[:, 3] <= cbk[:, 3]))
    if ref is not None:
        keep &= _any_intersect(ibox, widened)
    npix = np.bincount(comp.ravel(), minlength=nc + 1)[1:]
    keep &= npix >= params.detect_minarea
    nseg = np.zeros(nc + 1, dtype=np.int64)
    segpix = np.flatnonzero(seg)
    sc_lab = comp.ravel()[segpix]
    labs_per_comp = {}
    if segpix.size:
        pairs = np.unique(np.c_[sc_lab, seg.ravel()[segpix]], axis=0)
        nseg = np.bincount(pairs[:, 0], minlength=nc + 1)
        for c, l in pairs.tolist():
            labs_per_comp.setdefault(c, []).append(l)
    keep &= nseg[1:] > 0
    regions, rpix, rid = [], [], []
    seen = set()
    for c0 in np.flatnonzero(keep).tolist():
        c = c0 + 1
        cy0, cy1, cx0, cx1 = cbox[c0].tolist()
        k = int(wid[c0])
        dy, dx = int(off[c0, 0]), int(off[c0, 1])
        inside_c = comp[cy0:cy1, cx0:cx1] == c
        fy, fx = np.nonzero(inside_c)
        first = int((fy[0] + cy0 + dy) * nx + fx[0] + cx0 + dx)
        if first in seen:
            continue
        seen.add(first)
        # the cut-out measure.py's _isolate would take: box + m, clipped to the window
        wy0, wy1 = int(oy[k]), int(oy[k] + rects[k, 1] - rects[k, 0])
        wx0, wx1 = int(ox[k]), int(ox[k] + rects[k, 3] - rects[k, 2])
        py0, py1, px0, px1 = max(cy0 - m, wy0), min(cy1 + m, wy1), max(cx0 - m, wx0), min(cx1 + m, wx1)
        inside = comp[py0:py1, px0:px1] == c
        labs = labs_per_comp[c]
        rows = cat[np.array(labs) - 1] if len(labs) == 1 else None
        if rows is not None:
            rows = np.array(rows, copy=True)
            rows["x"] = rows["x"] - px0          # canvas -> cut-out (exact: integer shifts)
            rows["y"] = rows["y"] - py0
        ikey = (py0 + dy, py1 + dy, px0 + dx, px1 + dx, inside.tobytes())
        regions.append(_Region((cy0 + dy, cy1 + dy, cx0 + dx, cx1 + dx), inside, data[py0:py1, px0:px1],
                               err[py0:py1, px0:px1], nod[py0:py1, px0:px1], filt[py0:py1, px0:px1],
                               thr[py0:py1, px0:px1], (py0 + dy, px0 + dx), rows, ikey))
        rpix.append((fy + cy0 + dy) * nx + (fx + cx0 + dx))
        rid.append(np.full(fy.size, len(regions) - 1, dtype=np.int64))
    if not regions:
        return empty_tc
    pix = np.concatenate(rpix).astype(np.int64)
    pid = np.concatenate(rid)
    order = np.argsort(pix, kind="stable")
    return TaskClean(params, ref, usable, widened, regions, pix[order], pid[order], shape, isolated)
