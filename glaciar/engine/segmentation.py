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

The windowed engine never builds the full product of an injected image: it
reproduces it exactly around each injected source
(:mod:`glaciar.engine.measure`), using the product of the *original* image
(:func:`sep_segmentation`, once per field) for the objects injection does not
touch.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from glaciar.engine import clean as cl
from glaciar.engine.detect import DetectionParams, _sep_extract, detection_rms, sanitize

__all__ = ["Segmentation", "sep_segmentation", "isolate_region", "region_objects", "apply_clean"]

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
        Pre-CLEAN labels 1..m, in sep's object order (sep backend only).
    cat : structured ndarray or None, shape (m,)
        sep catalogue rows of the pre-CLEAN objects (image coordinates).
    objects : CleanObjects or None
        What CLEAN reads of each pre-CLEAN object.
    key : ndarray of int64, shape (m, 3)
        sep's order of the objects: (row, column) where the scan closed the
        object's region, then the child's rank in its region's deblending.
    obj_box : ndarray of int64, shape (m, 4)
        Box (y0, y1, x0, x1) of each object's region (all its deblended
        children share it).
    comp_box : ndarray of int64, shape (K, 4)
        Boxes of every connected above-threshold region, those below
        DETECT_MINAREA included.
    owner : ndarray of int64, shape (m,)
        Pre-CLEAN index of the surviving object each object's pixels went
        to (itself for survivors; -1: removed and left unlabelled).
    post : ndarray of int64, shape (m,)
        Post-CLEAN label of each pre-CLEAN object's pixels (0: unlabelled).
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
    objects: cl.CleanObjects | None = None
    key: np.ndarray | None = None
    obj_box: np.ndarray | None = None
    comp_box: np.ndarray | None = None
    owner: np.ndarray | None = None
    post: np.ndarray | None = None
    _tree: object = field(default=None, repr=False)

    def __len__(self):
        return int(np.size(self.x))

    def first_pixel(self):
        """Flat index of one pixel (the first in raster order) of each pre-CLEAN object."""
        if getattr(self, "_first", None) is None:
            flat = self.pre_seg.ravel()
            nz = np.flatnonzero(flat)
            lab, idx = np.unique(flat[nz], return_index=True)
            first = np.full(len(self.objects), -1, dtype=np.int64)
            first[lab - 1] = nz[idx]
            self._first = first
        return self._first

    def kdtree(self):
        """k-d tree of the pre-CLEAN barycentres (built once)."""
        if self._tree is None:
            from scipy.spatial import cKDTree
            o = self.objects
            self._tree = cKDTree(np.c_[o.x, o.y] if len(o) else np.zeros((0, 2)))
        return self._tree


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
    return _sep_extract(np.ascontiguousarray(data32, dtype=np.float32), err,
                        np.ascontiguousarray(nodata), params, bool(clean))


def region_objects(inside, cat, seg, data32, filt, thr, params: DetectionParams, lutz=None):
    """CLEAN inputs and sep order of the objects of one region of a cut-out.

    Parameters
    ----------
    inside : ndarray of bool
        The region's pixels in the cut-out (8-connected).
    cat : structured ndarray
        sep rows of the region's objects (cut-out coordinates): one row, or
        the children of its isolated extraction.
    seg : ndarray of int
        Cut-out labels: pixel -> row index + 1 of ``cat`` (0 elsewhere).
    data32, filt, thr : ndarray of float32
        Cut-out image, filtered image and threshold [image units].
    params : DetectionParams
    lutz : (pixels, row, column), optional
        The region's :func:`~glaciar.engine.clean.lutz_regions` entry in the
        cut-out's flat indices, if already known.

    Returns
    -------
    objects : CleanObjects
        Barycentres as in ``cat``.
    done : (int, int)
        (row, column) of the cut-out at which sep's scan closes the region.
    """
    h, w = inside.shape
    if lutz is None:
        lutz = cl.lutz_one(inside)
    pix, yd, xd = lutz
    n = len(cat)
    sf = np.asarray(seg).ravel()
    if n == 1:
        orders = [pix]
    else:
        oo = cl.child_pixel_orders(pix, w, sf, filt.ravel(), list(range(1, n + 1)),
                                   np.float32(cat["thresh"][0]), params.deblend_nthresh)
        orders = [oo[k] for k in range(1, n + 1)]
    objs = cl.clean_objects(cat, orders, data32.ravel(), filt.ravel(), thr.ravel(), params.detect_minarea)
    return objs, (int(yd), int(xd))


# --------------------------------------------------------------------------
# Full image
# --------------------------------------------------------------------------
def apply_clean(objects: cl.CleanObjects, params: DetectionParams, key=None):
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
        docstring; ``pre_seg``, ``cat``, ``objects``, ``key``, ``obj_box``,
        ``comp_box``, ``owner`` and ``post`` filled.

    Raises
    ------
    DetectionError
        When sep fails on the image or on a split region.
    """
    data, e, nodata = sanitize(image_sub, err, mask)
    e = detection_rms(e, nodata, params)
    H, W = data.shape
    cat0, seg0 = _sep_extract(data, e, nodata, params, False)
    dmask, filt, thr = cl.detection_mask(data, e, nodata, params)
    comps = cl.lutz_regions(dmask, 1)
    sf = seg0.ravel()
    pad = params.filter_halfwidth + 1
    cats, pre_seg = [], np.zeros((H, W), dtype=np.int32)
    objs, keys, oboxes = [], [], []
    comp_box = np.zeros((len(comps), 4), dtype=np.int64)
    nxt = 1
    for ci, (pix, yd, xd) in enumerate(comps):
        ys, xs = np.divmod(pix, W)
        box = (int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1)
        comp_box[ci] = box
        if pix.size < params.detect_minarea:
            continue
        labs = sf[pix]
        labs = np.unique(labs[labs > 0])
        if labs.size == 0:
            continue
        y0, y1 = max(box[0] - pad, 0), min(box[1] + pad, H)
        x0, x1 = max(box[2] - pad, 0), min(box[3] + pad, W)
        inside = np.zeros((y1 - y0, x1 - x0), dtype=bool)
        inside[ys - y0, xs - x0] = True
        local = ((ys - y0) * (x1 - x0) + (xs - x0), yd - y0, xd - x0)
        if labs.size == 1:
            c = cat0[labs - 1]
            lseg = inside.astype(np.int32)
        else:
            c, lseg = isolate_region(data[y0:y1, x0:x1], e[y0:y1, x0:x1], nodata[y0:y1, x0:x1], inside, params)
            lseg = np.where(inside, lseg, 0)
            c = _shift(c, y0, x0)
        o, _ = region_objects(inside, c, lseg, data[y0:y1, x0:x1], filt[y0:y1, x0:x1],
                              thr[y0:y1, x0:x1], params, lutz=local)
        k = len(c)
        objs.append(o)
        cats.append(c)
        keys.append(np.c_[np.full(k, yd), np.full(k, xd), np.arange(k)])
        oboxes.append(np.tile(box, (k, 1)))
        sub = pre_seg[y0:y1, x0:x1]
        sub[lseg > 0] = lseg[lseg > 0] + (nxt - 1)
        nxt += k
    if objs:
        objects = cl.CleanObjects.concat(objs)
        cat = np.concatenate(cats)
        key = np.concatenate(keys).astype(np.int64)
        obj_box = np.concatenate(oboxes).astype(np.int64)
    else:
        objects, cat = cl.CleanObjects.empty(), cat0[:0]
        key, obj_box = np.zeros((0, 3), dtype=np.int64), np.zeros((0, 4), dtype=np.int64)
    owner, surv = apply_clean(objects, params)
    return _post_clean(pre_seg, cat, objects, key, obj_box, comp_box, owner, surv)


def _post_clean(pre_seg, cat, objects, key, obj_box, comp_box, owner, surv):
    m = len(objects)
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
                        objects=objects, key=key, obj_box=obj_box, comp_box=comp_box,
                        owner=np.asarray(owner, dtype=np.int64), post=post)


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
