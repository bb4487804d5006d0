"""The reference (original-image) sep extraction of a large image, by full-width row strips.

:func:`strip_extract` returns what one ``sep.extract`` call (CLEAN off) on the whole
detection image returns -- the same catalogue rows in the same order and the same
segmentation map, bit for bit -- while holding only a strip of rows at a time.

Why a strip's objects are the whole frame's
-------------------------------------------
Read from sep's source (``src/extract.c``, ``deblend.c``, ``analyse.c``):

1. *Detection is local.*  A pixel is above threshold when its filtered value
   (the convolution of rows ``y - hf .. y + hf``, ``hf`` the filter half-height,
   masked pixels zeroed first) exceeds ``DETECT_THRESH`` times its RMS.  In a
   strip extracted from rows ``ya .. yb - 1`` the rows ``ya + hf .. yb - hf - 1``
   therefore have the whole frame's detection mask.  A connected (8-neighbour)
   region whose rows and whose neighbours' rows all lie there is a whole-frame
   region: same pixels, same minimum-area test, same multi-threshold deblending
   tree, same pixel-chain order (lutz builds a region's chain from its own
   segments only).  Each strip *owns* the regions whose last row lies in its own
   rows; a strip with an owned region that reaches its cut top is extracted again
   with twice as many rows above, until none does (at the image's edges nothing is
   cut).
2. *Coordinates are absolute.*  sep adds an object's ``xmin`` / ``ymin`` back to
   its centroid in double precision (``analyse``: ``my = ym + ymin``), and
   ``gatherup`` takes ``x - mx`` in single precision: a strip cut out at row 0
   would round differently.  Each strip is therefore passed to sep inside a
   canvas of the image's width whose rows ``0 .. ya - 1`` are zeros that are never
   written (``np.zeros``: the kernel's shared zero page, no resident memory), so
   every coordinate is the whole frame's; sep's first-rows quirks (the mask
   is not applied to the rows its line buffer preloads, ``SEP_OBJ_TRUNC`` on the
   first and last rows) then apply to the same image rows too.
3. *Deblending draws random numbers from one stream per call.*  ``gatherup``
   hands each faint pixel of a split region to a child with ``rand_r`` on a seed
   that ``sep_extract`` resets to 1, so a split region's footprints depend on
   how many draws every split region before it, anywhere in the frame, made;
   regions that are not split draw nothing.  All split regions are therefore
   extracted once more together, in one call, on an otherwise empty frame-sized
   canvas (their pixels and the filter half-width around them written, the RMS
   set to 1e30 on every other pixel within twice the half-width plus one of them,
   so nothing else is detected and no region grows): the stream then meets them
   in the whole frame's order with the whole frame's draws in between, and their
   children (same count and order as in the strips, the tree being deterministic)
   take their footprints and catalogue rows from this call.  The regions keep
   their rows but are packed to the left (:func:`pack_columns`): sep adds ``xmin``
   back to a centroid in double precision, which rounds the same after an integer
   shift that keeps the value in its power-of-two range ``[2**k, 2**(k+1))``;
   ``gatherup`` then takes ``x - mx`` exactly as in the frame.  Regions ending on
   one row are completed from left to right, so their left-to-right order is kept;
   regions near the image's edges or across a power of two stay.  The canvas is
   private anonymous memory with small pages, so only the packed columns' pages
   become resident (at 16000^2: ~1.2 GB for data, RMS and segmentation, against
   ~3 GB for the regions at their true columns).  The replay is checked against the
   strips (object counts, footprints); should it differ, it is made again at the
   true columns.
4. *Order and ids.*  sep appends an object when the scan leaves its region
   (children of a split region consecutively); regions owned by earlier strips
   end on earlier rows, and within a strip sep's own order is the frame's.  The
   catalogue is the strips' kept rows in strip order, the segmentation ids their
   positions + 1.

Only the convolution filter with the per-pixel RMS threshold is handled
(:func:`strips_apply`); CLEAN is applied afterwards by the caller (glaciar's exact
emulation works on a CLEAN-off extraction).  ``tests/engine/test_reference.py``
checks the result against one ``sep.extract`` call on images with large, blended and
masked objects cut by strips of a few rows.
"""
from __future__ import annotations

import mmap
import warnings

import numpy as np
from scipy import ndimage

from glaciar.engine import sepscan
from glaciar.engine.detect import DetectionError, DetectionParams, release_mapped, sanitize, sep_extract

__all__ = ["STRIP_PIXELS", "strips_apply", "strip_reference_applies", "strip_extract", "strip_reference",
           "SanitizedRows", "pack_columns"]

#: Pixels a strip owns [pixels] (~1050 rows at 16000 columns): its sep call holds
#: ~13 bytes per pixel of it, plus the rows above and below it.
STRIP_PIXELS = 1 << 24
_EIGHT = np.ones((3, 3), dtype=bool)          # sep's regions are 8-connected
_BIG_RMS = np.float32(1e30)                   # an RMS no filtered value exceeds


def strips_apply(params: DetectionParams) -> bool:
    """Whether :func:`strip_extract` reproduces ``params``' extraction (the
    convolution filter or none, and the per-pixel RMS threshold)."""
    return params.filter_kernel is None or (params.filter_type == "conv" and params.threshold_rms == "pixel")


def strip_reference_applies(params: DetectionParams) -> bool:
    """Whether :func:`strip_reference` reproduces ``params``' reference extraction: the sep
    backend with ``clean_style="region"`` (CLEAN on or off) and :func:`strips_apply`."""
    return params.backend == "sep" and params.clean_style == "region" and strips_apply(params)


def _sanitized_rows(image, rms, mask, ya, yb):
    out = sanitize(image[ya:yb], rms[ya:yb], None if mask is None else mask[ya:yb])
    release_mapped(image, rms, mask)        # a spilled input's pages, read once
    return out


def _canvas_extract(image, rms, mask, ya, yb, params):
    """sep (CLEAN off) on rows ``ya .. yb - 1`` placed at their true rows of a zero canvas,
    and those rows' above-threshold mask (every region, whatever its area)."""
    nx = image.shape[1]
    d, e, nd = _sanitized_rows(image, rms, mask, ya, yb)
    above = sepscan.detection_mask(d, e, nd, params, y0=ya)[0]
    data = np.zeros((yb, nx), dtype=np.float32)
    err = np.zeros((yb, nx), dtype=np.float32)
    nodata = np.zeros((yb, nx), dtype=bool)
    data[ya:], err[ya:], nodata[ya:] = d, e, nd
    del d, e, nd
    cat, seg = sep_extract(data, err, nodata, params, False)
    return cat, seg, above


def _strip(image, rms, mask, y0, y1, halo, params):
    """The objects of the regions ending in rows ``y0 .. y1 - 1``, from one exact extraction.

    Returns ``(cat, seg_rows, ya, keep_ids, obj_region, regions)``: the strip's catalogue,
    its segmentation's rows ``ya ..``, the ids kept (in sep's order), each kept object's
    region index into ``regions`` (a list of (y0, y1, x0, x1, pixel mask, n_objects)).
    """
    ny = image.shape[0]
    hf = 0 if params.filter_kernel is None else params.filter_halfwidth
    yb = min(ny, y1 + halo)
    up = halo
    while True:
        ya = max(0, y0 - up)
        cat, seg, above = _canvas_extract(image, rms, mask, ya, yb, params)
        s = seg[ya:]
        # regions from the above-threshold mask, not the segmentation: a region the cut leaves
        # below DETECT_MINAREA has no segment in the strip, yet must send the strip up
        above |= s > 0
        lab, _ = ndimage.label(above, structure=_EIGHT)
        del above
        boxes = ndimage.find_objects(lab)
        n = len(cat)
        region_of = np.zeros(n + 1, dtype=np.int64)          # object id -> region label
        on = s > 0
        region_of[s[on]] = lab[on]
        del on
        last = np.array([b[0].stop - 1 + ya for b in boxes], dtype=np.int64)
        first = np.array([b[0].start + ya for b in boxes], dtype=np.int64)
        owned = (last >= y0) & (last < y1)
        cut = owned & (first < ya + hf + 1) if ya > 0 else np.zeros_like(owned)
        if not cut.any():
            break
        if ya == 0:                       # pragma: no cover - nothing is cut at the image's top
            raise DetectionError("strip extraction: a region at the image's top was cut")
        up *= 2
    ids = np.arange(1, n + 1)
    # objects with no pixel in rows ya.. (the canvas's zero rows just above ya) are not owned
    inreg = region_of[1:] > 0
    keep = ids[inreg & owned[np.maximum(region_of[1:], 1) - 1]] if len(boxes) else ids[:0]
    labels, first_pos, counts = np.unique(region_of[keep], return_index=True, return_counts=True)
    # in sep's order (that of their first child), which is the order their draws are made in
    split_labels = labels[counts > 1][np.argsort(first_pos[counts > 1], kind="stable")]
    regions, index = [], {}
    for lb in split_labels.tolist():
        sl = boxes[lb - 1]
        index[lb] = len(regions)
        regions.append((sl[0].start + ya, sl[0].stop + ya, sl[1].start, sl[1].stop, lab[sl] == lb))
    obj_split = np.array([index.get(int(r), -1) for r in region_of[keep]], dtype=np.int64)
    return cat[keep - 1], s, ya, keep, obj_split, regions


def _binade(v):
    """floor(log2(v)) of positive integers (the power-of-two range of a double holding v)."""
    return np.floor(np.log2(np.maximum(v, 1))).astype(np.int64)


def pack_columns(boxes, nx, hf):
    """Column shifts that pack the split regions to the left of their power-of-two ranges.

    Parameters
    ----------
    boxes : ndarray of int (n, 4)
        The regions' ``(y0, y1, x0, x1)`` boxes [pixels] in sep's emission order.
    nx : int
        Image width [pixels].
    hf : int
        Filter half-width [pixels].

    Returns
    -------
    shift : ndarray of int or None
        Columns to add to each region (rows never move), or None when the regions do not
        fit or their order would change.  A moved region's columns stay in one range
        ``[2**k, 2**(k+1))``, so every centroid sep computes (``xm + xmin`` in double
        precision) rounds to the whole frame's plus the shift; it stays ``2*hf + 1``
        columns away from the image's edges (same convolution, same ``SEP_OBJ_TRUNC``);
        boxes grown by ``hf + 1`` stay disjoint, so no region reads another's pixels
        through the filter; regions ending on the same row keep the left-to-right order
        sep completes them in (a region nested in another's box may end on the same row
        and be completed first: such rows are placed in emission order, else kept).
        Regions outside these rules keep their columns.
    """
    n = len(boxes)
    x0 = boxes[:, 2].astype(np.int64)
    last = boxes[:, 1].astype(np.int64) - 1
    key = x0.copy()                         # regions are placed by increasing key
    fixed = np.zeros(n, dtype=bool)
    grouped = set()
    for _ in range(_PACK_PASSES):
        new, stuck, wrong = _pack_pass(boxes, nx, hf, np.lexsort((np.arange(n), key)), fixed)
        if stuck is not None:               # no room left in its range: it stays
            fixed[stuck] = True
            continue
        if not wrong.size:
            return new - x0
        for y in wrong.tolist():
            on = last == y
            if y in grouped:                # placed together and still out of order: they stay
                fixed |= on
            else:                           # a nested pair: the row's regions placed together
                key[on] = x0[on].min()
                grouped.add(y)
    return None


#: Packing passes :func:`pack_columns` makes at most (each pass after the first keeps the
#: regions that found no room or no order in the previous one).
_PACK_PASSES = 64


def _pack_pass(boxes, nx, hf, order, fixed):
    """One packing of :func:`pack_columns`: regions placed in ``order``, ``fixed`` ones
    kept; returns the new first columns (None if a region finds no room), that region's
    index, and the last rows where the left-to-right order differs from the emission order."""
    m = hf + 1
    edge = 2 * hf + 1
    y0, y1, x0, x1 = (boxes[:, i].astype(np.int64) for i in range(4))
    n = len(y0)
    ny = int(y1.max()) + m if n else 0
    band = _binade(x0)
    keep = (x0 < edge) | (x1 > nx - edge) | (band != _binade(x1 - 1)) | fixed
    front, limit = {}, {}

    def rows_of(k):
        if k not in front:
            front[k] = np.full(ny, 1 << k, dtype=np.int64)
            limit[k] = np.full(ny, min(1 << (k + 1), nx), dtype=np.int64)
        return front[k], limit[k]

    # regions that stay: in each range they reach, the left ones set where packing starts in
    # their rows, the others a limit it must stay below
    for i in np.flatnonzero(keep):
        a, b = max(0, y0[i] - m), y1[i] + m
        for k in range(int(_binade(max(1, x0[i] - m))), int(_binade(max(1, x1[i] + m - 1))) + 1):
            lo, hi = 1 << k, min(1 << (k + 1), nx)
            if lo >= nx or x1[i] + m <= lo or x0[i] - m >= hi:
                continue
            f, lim = rows_of(k)
            if x0[i] - m <= lo:
                f[a:b] = np.maximum(f[a:b], x1[i] + m)
            else:
                lim[a:b] = np.minimum(lim[a:b], x0[i] - m)
    new = x0.copy()
    # left to right, each region as far left as the regions already placed in its rows allow
    for i in order[~keep[order]].tolist():
        f, lim = rows_of(int(band[i]))
        a, b = max(0, y0[i] - m), y1[i] + m
        x = max(int(f[a:b].max()) + m, 1 << int(band[i]))
        w = int(x1[i] - x0[i])
        if x + w + m > int(lim[a:b].min()):
            return None, i, None
        new[i] = x
        f[a:b] = x + w + m
    # sep completes regions ending on one row from left to right: that order must be the frame's
    last = y1 - 1
    o = np.lexsort((np.arange(n), last))
    same = last[o][1:] == last[o][:-1]
    moved = ~(keep[o][1:] & keep[o][:-1])
    wrong = same & moved & (new[o][1:] < new[o][:-1] + (x1 - x0)[o][:-1])
    return new, None, np.unique(last[o][1:][wrong])


def _hugepages(on: bool) -> bool:
    """Turn numpy's huge-page advice for large arrays on or off; returns the previous setting.

    With transparent huge pages on request (Linux ``madvise`` mode), numpy asks for them on
    every large array, and one written pixel then makes 2 MB resident: sep's segmentation
    of the mostly empty replay canvas would be resident whole."""
    core = getattr(np, "_core", None) or getattr(np, "core", None)       # numpy 2 / numpy 1
    setter = getattr(getattr(core, "multiarray", None), "_set_madvise_hugepage", None)
    return bool(setter(on)) if setter is not None else on


def _zero_canvas(shape, dtype):
    """A zero-filled array on private anonymous memory with small pages: only the pages
    written become resident (reading the others maps the kernel's zero page; a shared
    mapping, ``mmap``'s default, would allocate them as sep reads them)."""
    size = int(np.prod(shape))
    nbytes = max(size * np.dtype(dtype).itemsize, 1)
    flags = getattr(mmap, "MAP_PRIVATE", 0) | getattr(mmap, "MAP_ANONYMOUS", 0)
    buf = mmap.mmap(-1, nbytes, flags=flags) if flags else mmap.mmap(-1, nbytes)
    if hasattr(buf, "madvise") and hasattr(mmap, "MADV_NOHUGEPAGE"):
        buf.madvise(mmap.MADV_NOHUGEPAGE)
    return np.frombuffer(buf, dtype=dtype, count=size).reshape(shape)


#: Catalogue fields holding an absolute column.
_X_FIELDS = ("xmin", "xmax", "x", "xpeak", "xcpeak")


def _replay(image, rms, mask, regions, params, pack: bool = True):
    """sep (CLEAN off) on the split regions alone, in one call, on a frame-sized canvas.

    Rows stay the whole frame's; with ``pack``, columns are moved by :func:`pack_columns`
    (left within their power-of-two ranges) so the regions share few memory pages.  Only
    the pages written are resident (anonymous memory, small pages).

    Returns ``(cat, seg, shift)``: sep's catalogue with its column fields moved back, the
    canvas's segmentation, each region's column shift.
    """
    ny, nx = image.shape
    hf = 0 if params.filter_kernel is None else params.filter_halfwidth
    boxes = np.array([r[:4] for r in regions], dtype=np.int64).reshape(-1, 4)
    shift = pack_columns(boxes, nx, hf) if pack else None
    if shift is None:
        shift = np.zeros(len(regions), dtype=np.int64)
    data = _zero_canvas((ny, nx), np.float32)
    err = _zero_canvas((ny, nx), np.float32)

    def grown(r, g):
        return max(0, r[0] - g), min(ny, r[1] + g), max(0, r[2] - g), min(nx, r[3] + g)

    for r, dx in zip(regions, shift.tolist()):
        # every pixel whose filtered value reads the written data gets an RMS nothing exceeds
        a, b, c, d = grown(r, 2 * hf + 1)
        err[a:b, c + dx:d + dx] = _BIG_RMS
    for k, (r, dx) in enumerate(zip(regions, shift.tolist())):
        a, b, c, d = grown(r, hf)
        dd, ee, _ = sanitize(image[a:b, c:d], rms[a:b, c:d], None if mask is None else mask[a:b, c:d])
        if k % 256 == 255:
            release_mapped(image, rms, mask)
        data[a:b, c + dx:d + dx] = dd
        inside = np.zeros(dd.shape, dtype=bool)
        inside[r[0] - a:r[1] - a, r[2] - c:r[3] - c] = r[4]
        err[a:b, c + dx:d + dx][inside] = ee[inside]
    was = _hugepages(False)
    try:
        cat, seg = sep_extract(data, err, None, params, False)
    finally:
        _hugepages(was)
    del data, err
    if shift.any() and len(cat):
        # each object's column shift, from the canvas region holding it
        ids = np.zeros(len(cat), dtype=np.int64)
        for r, dx in zip(regions, shift.tolist()):
            piece = seg[r[0]:r[1], r[2] + dx:r[3] + dx]
            ids[piece[piece > 0] - 1] = dx
        for f in _X_FIELDS:
            cat[f] = cat[f] - ids.astype(cat[f].dtype)
    return cat, seg, shift


def strip_extract(image, rms, mask, params: DetectionParams, strip_rows: int | None = None,
                  halo: int | None = None, out: np.ndarray | None = None):
    """``sep.extract`` (CLEAN off) of the whole image, computed by row strips.

    Parameters
    ----------
    image, rms : ndarray (ny, nx)
        Background-subtracted detection image and its RMS [image units], any dtype
        (a memory map is read a strip at a time); sanitized as
        :func:`glaciar.engine.detect.sanitize` does.
    mask : ndarray of bool or None
        True where there are no data.
    params : DetectionParams
        Must satisfy :func:`strips_apply`.
    strip_rows : int, optional
        Rows each strip owns (default :data:`STRIP_PIXELS` / nx).
    halo : int, optional
        Rows read below a strip and, at first, above it (default 64; at least the
        filter half-width + 1).
    out : ndarray of int32, optional
        Zero-filled (ny, nx) array the segmentation is written into (e.g. a map on
        disk); default a new array.

    Returns
    -------
    cat : structured ndarray
        sep's catalogue of the whole image (row i: segment id i + 1).
    seg : ndarray of int32
        The segmentation map (``out``).

    Raises
    ------
    ValueError
        When ``params`` are not handled (:func:`strips_apply`).
    DetectionError
        When sep fails.
    """
    if not strips_apply(params):
        raise ValueError("strip_extract handles the 'conv' filter with threshold_rms='pixel' only; "
                         f"got filter_type={params.filter_type!r}, threshold_rms={params.threshold_rms!r}")
    ny, nx = image.shape
    hf = 0 if params.filter_kernel is None else params.filter_halfwidth
    rows = max(1, int(strip_rows) if strip_rows else (STRIP_PIXELS // max(nx, 1)))
    halo = max(hf + 1, 64 if halo is None else int(halo))
    seg = np.zeros((ny, nx), dtype=np.int32) if out is None else out
    cats, split_pos, regions = [], [], []
    total = 0
    for y0 in range(0, ny, rows):
        y1 = min(ny, y0 + rows)
        cat, s, ya, keep, obj_split, regs = _strip(image, rms, mask, y0, y1, halo, params)
        lut = np.zeros(len(keep) and int(keep[-1]) + 1 or 1, dtype=np.int32)
        single = obj_split < 0
        lut[keep[single]] = total + 1 + np.flatnonzero(single).astype(np.int32)
        rel = ndimage.find_objects(s)          # boxes of the strip's ids, to write by object
        for k in keep[single].tolist():
            sl = rel[k - 1]
            piece = s[sl]
            hit = piece == k
            seg[sl[0].start + ya:sl[0].stop + ya, sl[1]][hit] = lut[k]
        # split regions: their children's global positions, in order, per region
        for i, r in enumerate(regs):
            pos = total + np.flatnonzero(obj_split == i)
            split_pos.append(pos)
            regions.append(r)
        cats.append(cat)
        total += len(cat)
        del s, rel
        release_mapped(seg)             # a segmentation on disk: its written pages go
    if not cats:
        return np.zeros(0, dtype=sep_extract_dtype()), seg
    full = np.concatenate(cats)
    if regions:
        del cats
        _place_split(full, seg, image, rms, mask, regions, split_pos, params)
    return full, seg


def _place_split(full, seg, image, rms, mask, regions, split_pos, params):
    """The split regions' objects and footprints from their replay, into ``full`` and ``seg``.

    The packed replay is checked against the strips (same object count per region, same
    footprints); should it ever differ, the regions are replayed at their true columns."""
    counts = [p.size for p in split_pos]
    for pack in (True, False):
        rcat, rseg, shift = _replay(image, rms, mask, regions, params, pack=pack)
        if len(rcat) != sum(counts):
            if pack and shift.any():
                warnings.warn("strip extraction: the packed replay of the split regions differs from "
                              "the strips; replayed at their true columns (more memory)",
                              RuntimeWarning, stacklevel=2)
                continue
            raise DetectionError(f"strip extraction: {len(rcat)} objects in the split regions' "
                                 f"replay, {sum(counts)} in the strips")
        start, owns = 0, []
        for r, k, dx in zip(regions, counts, shift.tolist()):
            piece = rseg[r[0]:r[1], r[2] + dx:r[3] + dx]
            own = (piece > start) & (piece <= start + k)
            if not np.array_equal(own, r[4]):
                break
            owns.append((piece, own, start))
            start += k
        else:
            break
        if not (pack and shift.any()):
            raise DetectionError("strip extraction: a split region's replay differs from its strip")
        del rcat, rseg, owns
        warnings.warn("strip extraction: the packed replay of the split regions differs from the "
                      "strips; replayed at their true columns (more memory)", RuntimeWarning, stacklevel=2)
    for k, (r, pos, (piece, own, start)) in enumerate(zip(regions, split_pos, owns)):
        full[pos] = rcat[start:start + pos.size]
        lut = np.zeros(pos.size + 1, dtype=np.int32)
        lut[1:] = pos + 1
        seg[r[0]:r[1], r[2]:r[3]][own] = lut[piece[own] - start]
        if k % 1024 == 1023:
            release_mapped(seg)             # a segmentation on disk: its written pages go
    release_mapped(seg)


def sep_extract_dtype():
    """The dtype of sep's catalogue (from an empty extraction)."""
    cat, _ = sep_extract(np.zeros((4, 4), dtype=np.float32), np.ones((4, 4), dtype=np.float32),
                         np.zeros((4, 4), dtype=bool), DetectionParams(filter_kernel=None), False)
    return cat.dtype


# --------------------------------------------------------------------------
# The whole reference (segmentation + photometry) of a large field, memory bounded
# --------------------------------------------------------------------------

class SanitizedRows:
    """Row slices of :func:`~glaciar.engine.detect.sanitize` ``(image, rms, mask)``, made on
    request: ``.data[a:b]``, ``.err[a:b]``, ``.nodata[a:b]`` (nothing full-frame is held; the
    pages of memory-mapped inputs are dropped after each read).  Sanitizing is per pixel, so
    a slice is the whole-frame result's slice."""

    def __init__(self, image, rms, mask):
        self._src = (image, rms, mask)
        self._key = None
        self._val = None
        self.shape = tuple(np.shape(image))
        self.data = _RowView(self, 0, np.float32)
        self.err = _RowView(self, 1, np.float32)
        self.nodata = _RowView(self, 2, np.bool_)

    def rows(self, a: int, b: int):
        """``(data, err, nodata)`` of rows ``a .. b - 1``."""
        if self._key != (a, b):
            image, rms, mask = self._src
            self._val = _sanitized_rows(image, rms, mask, a, b)
            self._key = (a, b)
        return self._val


class _RowView:
    """One of :class:`SanitizedRows`' arrays, sliced by rows."""

    ndim = 2

    def __init__(self, owner: SanitizedRows, k: int, dtype):
        self._owner, self._k, self.dtype = owner, k, np.dtype(dtype)
        self.shape = owner.shape

    def __getitem__(self, key):
        rows, rest = (key[0], key[1:]) if isinstance(key, tuple) else (key, ())
        if not isinstance(rows, slice):
            raise TypeError("row views are read by slices of rows")
        a, b, step = rows.indices(self.shape[0])
        if step != 1:
            raise TypeError("row views are read by contiguous rows")
        out = self._owner.rows(a, b)[self._k]
        return out[(slice(None),) + tuple(rest)] if rest else out


class _MapRows:
    """Row slices of a memory map, copied, its pages dropped after each read."""

    ndim = 2

    def __init__(self, arr):
        self._arr, self.shape, self.dtype = arr, arr.shape, arr.dtype

    def __getitem__(self, key):
        out = np.array(self._arr[key])
        release_mapped(self._arr)
        return out

    def __setitem__(self, key, value):
        self._arr[key] = value
        release_mapped(self._arr)


def _row_canvas(rows: SanitizedRows, seg, lo: int, hi: int):
    """Rows ``lo .. hi - 1`` of the sanitized image, RMS, no-data mask and segmentation at
    their true rows of zero canvases ``hi`` rows high (absolute coordinates for sep)."""
    nx = rows.shape[1]
    d, e, nd = rows.rows(lo, hi)
    out = [np.zeros((hi, nx), dtype=dt) for dt in (np.float32, np.float32, bool, np.int32)]
    out[0][lo:], out[1][lo:], out[2][lo:] = d, e, nd
    out[3][lo:] = seg[lo:hi]
    release_mapped(seg)
    return out


def _span(y, ext, ny):
    """Rows ``lo, hi`` holding every pixel sep reads for ellipses of half-height ``ext``
    about ``y`` (3 rows of margin over sep's box rounding)."""
    ext = np.nan_to_num(ext, nan=0.0, posinf=float(ny))
    lo = int(max(0, np.floor(np.min(y - ext)) - 3))
    hi = int(min(ny, np.ceil(np.max(y + ext)) + 4))
    return lo, hi


def strip_reference(det_image_sub, det_rms, params: DetectionParams, zeropoint: float, mask=None,
                    photometry=None, seg_out=None):
    """:func:`glaciar.engine.measure.reference_extraction` of a large image (sep backend,
    ``clean_style="region"``, CLEAN on or off), with no full-frame array in memory.

    The segmentation is :func:`strip_extract`'s, written into ``seg_out`` (default a
    scratch map on disk, :func:`glaciar.engine.fieldcache.scratch_array`); the AUTO
    photometry runs by row bands of objects on zero canvases holding the rows their
    Kron and AUTO ellipses read, at their true rows (sep measures each object on its own
    pixels, so each result is the whole frame's); the region boxes read the image by row
    tiles.  With CLEAN on, glaciar's exact emulation of sep's CLEAN
    (:func:`glaciar.engine.segmentation.clean_extraction`) runs on the strips' result,
    reading the image by row tiles and cut-outs.  Same
    :class:`~glaciar.engine.measure.FieldReference`, bit for bit.

    Parameters
    ----------
    As :func:`~glaciar.engine.measure.reference_extraction` (``det_image_sub``, ``det_rms``,
    ``mask`` may be memory maps); ``seg_out``: zero-filled (ny, nx) int32 array to write
    the segmentation into.
    """
    from glaciar.engine import photometry as phot
    from glaciar.engine.canvas import ObjectBoxes, ellipse_half_extent, safe_shape
    from glaciar.engine.fieldcache import scratch_array
    from glaciar.engine.measure import FieldReference, reference_boxes

    from glaciar.engine.segmentation import clean_extraction

    if not strip_reference_applies(params):
        raise ValueError("strip_reference handles the sep backend with clean_style 'region', the "
                         "'conv' filter (or none) and threshold_rms='pixel' only; got backend="
                         f"{params.backend!r}, clean_style={params.clean_style!r}, filter_type="
                         f"{params.filter_type!r}, threshold_rms={params.threshold_rms!r}")
    ny, nx = np.shape(det_image_sub)
    seg = scratch_array((ny, nx), np.int32) if seg_out is None else seg_out
    cat, seg = strip_extract(det_image_sub, det_rms, mask, params, out=seg)
    det = SanitizedRows(det_image_sub, det_rms, mask)
    if params.clean:
        # glaciar's exact CLEAN on the CLEAN-off extraction (what the whole-frame reference
        # does above EMULATED_CLEAN_MIN_OBJECTS objects, and equal to sep's own below)
        cat, _ = clean_extraction(cat, _MapRows(seg), det.data, det.err, det.nodata, params)
    n = len(cat)
    if n == 0:
        return FieldReference(seg, np.zeros(0), np.zeros(0), cat)
    geo = {f: np.asarray(cat[f], dtype=np.float64) for f in ("x", "y", "a", "b", "theta")}
    a, b, th = safe_shape(geo["a"], geo["b"], geo["theta"])
    x, y = geo["x"], geo["y"]
    band = det if photometry is None else SanitizedRows(photometry[0], photometry[1], mask)
    kr = np.empty(n)
    flux = np.empty(n)
    order = np.argsort(y, kind="stable")
    band_rows = max(1, STRIP_PIXELS // max(nx, 1))
    edges = np.searchsorted(y[order], np.arange(0, ny + band_rows, band_rows), side="left")
    for i0, i1 in zip(edges[:-1], edges[1:]):
        if i1 <= i0:
            continue
        g = order[i0:i1]
        ids = (g + 1).astype(np.int32)
        lo, hi = _span(y[g], ellipse_half_extent(a[g], b[g], th[g], 6.0)[0], ny)
        d, e, nd, s = _row_canvas(det, seg, lo, hi)
        kr[g] = phot.kron_radius(d, x[g], y[g], a[g], b[g], th[g], segmap=s, seg_id=ids, mask=nd)
        scale = phot.auto_scale(kr[g], params.phot_autoparams)
        lo2, hi2 = _span(y[g], ellipse_half_extent(a[g], b[g], th[g], scale)[0], ny)
        if band is not det or lo2 < lo or hi2 > hi:
            del d, e, nd, s
            d, e, nd, s = _row_canvas(band, seg, min(lo, lo2), max(hi, hi2))
        flux[g] = phot.auto_photometry(d, e, phot.Ellipses(x[g], y[g], a[g], b[g], th[g], scale),
                                       segmap=s, seg_id=ids, mask=nd)[0]
        del d, e, nd, s
    scale = phot.auto_scale(kr, params.phot_autoparams)
    mag, _, _ = phot.magnitudes(flux, np.ones_like(flux), zeropoint)
    region_box, need_box = reference_boxes(det.data, det.err, det.nodata, _MapRows(seg), geo,
                                           a, b, th, scale, params)
    return FieldReference(seg, flux, mag, cat, ObjectBoxes.build(region_box, need_box, seg.shape))
