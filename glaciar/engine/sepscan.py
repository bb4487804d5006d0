"""sep's detection scan reproduced in numpy: filter, threshold, Lutz order, ``mthresh``.

What CLEAN (:mod:`glaciar.engine.clean`) and the exactness checks of the windows
(:mod:`glaciar.engine.windows`) need of sep's extraction, bit for bit
(``tests/engine/test_measure.py``, ``tests/engine/test_clean.py``):

* the detection mask: sep's line convolution (:func:`sep_filter`) compared with
  ``DETECT_THRESH x rms`` per pixel -- the one definition of the threshold
  (:func:`threshold_map`) and of "above threshold" (:func:`detection_mask`);
* the order in which sep's Lutz scan completes regions and lists their pixels
  (:func:`lutz_regions`, :func:`lutz_one`);
* ``mthresh``, the value of the ``DETECT_MINAREA``-th brightest pixel above threshold
  as sep's heap finds it (:func:`heap_mthresh`);
* the pixel order of a deblended region's children (:func:`child_pixel_orders`).

All functions are pure (arrays in, arrays out).
"""
from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from glaciar.engine.compiled import KERNELS as KERNEL

__all__ = ["KERNEL", "sep_kernel", "sep_filter", "threshold_map", "detection_mask", "lutz_regions", "lutz_one",
           "heap_mthresh", "child_pixel_orders", "SEP_BIG"]

#: sep's BIG: the noise of masked pixels, so their threshold is never reached
SEP_BIG = np.float32(1e30)
#: sep's MAXDEBAREA: the smallest branch its deblender's Lutz pass keeps [pixels]
_MAXDEBAREA = 3

_COMPLETE, _INCOMPLETE, _NONOBJECT, _OBJECT = 0, 1, 2, 3
_UNKNOWN = -1


# --------------------------------------------------------------------------
# Detection mask
# --------------------------------------------------------------------------
def sep_kernel(kernel) -> np.ndarray:
    """The filter as sep applies it: float32, divided by the float32 sum of |k|.

    Parameters
    ----------
    kernel : ndarray
        Detection filter (any normalisation).

    Returns
    -------
    ndarray of float32
    """
    k = np.ascontiguousarray(kernel, dtype=np.float32)
    s = np.float32(0.0)
    for v in k.ravel().tolist():          # float sum += fabs(double): rounded each step
        s = np.float32(float(s) + abs(v))
    return (k / s).astype(np.float32)


def sep_filter(data, kernel) -> np.ndarray:
    """Filtered image, bit-identical to sep's ``convolve()``.

    Parameters
    ----------
    data : ndarray
        Image as passed to sep [image units]; cast to float32 (no-data pixels
        must already be 0, as sep sets them).
    kernel : ndarray
        Detection filter (normalised here by the sum of its absolute values).

    Returns
    -------
    ndarray of float32
        ``sum_k kernel_k x data[y + dy_k, x + dx_k]`` accumulated in float32 in
        sep's order (kernel row-major); pixels outside the image contribute
        nothing.
    """
    data = np.asarray(data, dtype=np.float32)
    k = sep_kernel(kernel)
    ch, cw = k.shape
    H, W = data.shape
    # The image in a zero frame, as one flat array: every kernel tap is then one
    # contiguous multiply-add over all pixels (rows of width W + cw - 1, whose last
    # cw - 1 columns are discarded), ~2x faster than 2-d slices.  Taps outside the
    # image read zeros, so each sum is sep's (outside pixels skipped) plus exact
    # zeros, in the same order: the same float32 bits.
    hy, hx = ch // 2, cw // 2
    Wp = W + cw - 1
    P = np.zeros((H + ch, Wp), dtype=np.float32)       # one spare row for the last taps
    P[hy:hy + H, hx:hx + W] = data
    if KERNEL is not None:
        out = np.empty((H, W), dtype=np.float32)
        KERNEL.filter_padded(P, k, out)
        return out
    flat = P.ravel()
    n = H * Wp
    out = np.zeros(n, dtype=np.float32)
    tmp = np.empty(n, dtype=np.float32)
    for cy in range(ch):
        for cx in range(cw):
            off = cy * Wp + cx
            np.multiply(flat[off:off + n], k[cy, cx], out=tmp)
            out += tmp
    return np.ascontiguousarray(out.reshape(H, Wp)[:, :W])


def threshold_map(err, nodata, params, y0=None) -> np.ndarray:
    """Per-pixel detection threshold as sep applies it (float32 ``DETECT_THRESH x sigma``).

    The one definition of the threshold: every path that decides "above threshold"
    (:func:`detection_mask`, hence the windowed canvases, the reference's region
    boxes and the full-frame segmentation product; the emulated full-frame CLEAN's ``filtered -
    threshold`` in :mod:`glaciar.engine.segmentation`; the first-window guess of
    :func:`glaciar.engine.windows.stamp_half_sizes`) takes it from here, so they
    agree with sep, and each other, bit for bit.

    Parameters
    ----------
    err : ndarray
        Per-pixel RMS passed to sep [image units].
    nodata : ndarray of bool
        Pixels sep masks (their noise becomes 1e30, so they are never detected).
    params : DetectionParams
        ``detect_thresh`` [units of the RMS] and ``filter_halfwidth`` [rows].
    y0 : int, optional
        Image row of the arrays' first row.  sep masks each row as it reads it
        into its filter buffer, except the image's first ``filter_halfwidth``
        rows, read before its loop: there no-data pixels keep the RMS passed
        (checked against sep in ``tests/engine/test_clean.py``).  Given,
        that quirk is applied; None (arrays that are not rows of the image sep
        saw from its top, e.g. a canvas of windows) masks every no-data pixel.

    Returns
    -------
    ndarray of float32 [image units]
    """
    nd = np.asarray(nodata, dtype=bool)
    if y0 is not None:
        first = params.filter_halfwidth - int(y0)
        if first > 0 and nd[:first].any():
            nd = nd.copy()
            nd[:first] = False
    e = np.where(nd, SEP_BIG, np.asarray(err, dtype=np.float32)).astype(np.float32)
    return (np.float32(params.detect_thresh) * e).astype(np.float32)


def _matched_filter(data, err, kernel):
    """sep's matched filter (sum k f / v) / sqrt(sum k^2 / v), float32 (approximate order)."""
    k = sep_kernel(kernel).astype(np.float64)
    var = np.asarray(err, dtype=np.float64) ** 2
    inv = np.where(var > 0, 1.0 / np.where(var > 0, var, 1.0), 0.0)
    d = np.asarray(data, dtype=np.float64)
    num = ndimage.correlate(d * inv, k, mode="constant")
    den = ndimage.correlate(inv, k * k, mode="constant")
    with np.errstate(divide="ignore", invalid="ignore"):
        return (num / np.sqrt(den)).astype(np.float32)


def detection_mask(data, err, nodata, params, y0=None):
    """Pixels sep finds above threshold (every connected region, whatever its size).

    The one decision "above threshold" (threshold from :func:`threshold_map`).

    Parameters
    ----------
    data, err : ndarray
        Image and RMS as passed to sep [image units] (no-data pixels: data 0).
    nodata : ndarray of bool
    params : DetectionParams
    y0 : int, optional
        Image row of the arrays' first row (:func:`threshold_map`).

    Returns
    -------
    mask : ndarray of bool
        ``filtered > DETECT_THRESH x rms`` (exact for ``filter_type="conv"``
        and no filter; for ``"matched"``, sep's matched-filter S/N > DETECT_THRESH
        up to rounding).
    filtered : ndarray of float32
        The filtered image (sep's ``cdvalue``, used by CLEAN).
    thresh : ndarray of float32
        The per-pixel threshold.
    """
    data = np.asarray(data, dtype=np.float32)
    thr = threshold_map(err, nodata, params, y0)
    filt = data if params.filter_kernel is None else sep_filter(data, params.filter_kernel)
    if params.filter_kernel is not None and params.filter_type == "matched":
        e = np.where(nodata, np.inf, np.asarray(err, dtype=np.float64))
        sig = _matched_filter(data, e, params.filter_kernel)
        with np.errstate(invalid="ignore"):
            mask = (sig > np.float32(params.detect_thresh)) & ~nodata
    else:
        mask = filt > thr
    return mask, filt, thr


# --------------------------------------------------------------------------
# Lutz scan: pixel-list order and completion order
# --------------------------------------------------------------------------
def lutz_regions(mask, minarea: int = 1):
    """8-connected regions of a mask as sep's Lutz scan builds them.

    Parameters
    ----------
    mask : ndarray of bool, shape (H, W)
    minarea : int
        Regions with fewer pixels are not returned (sep drops them).

    Returns
    -------
    list of (pixels, y_done, x_done)
        In the order sep completes them (sorted by ``(y_done, x_done)``):
        ``pixels`` are flat indices ``y * W + x`` in the order of sep's pixel
        list; the region is closed when the scan reaches pixel ``(y_done,
        x_done)`` (row ``ymax + 1``), which depends only on the region's own
        pixels, so a region cut out with a blank border gives the same
        values (shifted).

    Notes
    -----
    A transcription of the scan in sep's ``extract.c`` / ``lutz.c``, run over
    *events* (run starts, run ends, markers left by the previous row) instead
    of every pixel: the pixels of a run between two events are appended to
    the current object as one chunk, which is what the per-pixel loop does.
    """
    mask = np.asarray(mask, dtype=bool)
    H, W = mask.shape
    if H == 0 or W == 0:
        return []
    pad = np.zeros((H, W + 2), dtype=np.int8)
    pad[:, 1:-1] = mask
    dy, dx = np.nonzero(np.diff(pad, axis=1))      # +1 at run starts, -1 at run ends (x = end)
    sgn = np.diff(pad, axis=1)[dy, dx]
    starts_y, starts_x = dy[sgn > 0], dx[sgn > 0]
    ends_x = dx[sgn < 0]
    row_start = np.searchsorted(starts_y, np.arange(H + 1))
    sx_all, ex_all = starts_x.tolist(), ends_x.tolist()
    # chunks: (flat start, length); linked lists of chunk ids
    c_start, c_len = [], []
    nxt = {}

    def update(i1, i2):
        i1[2] += i2[2]
        if i1[0] == -1:
            i1[0], i1[1] = i2[0], i2[1]
        elif i2[1] != -1:
            nxt[i1[1]] = i2[0]
            i1[1] = i2[1]

    marker = {}
    info = {}
    store = {}
    start = {}
    end = {}
    psstack = []
    co = 0
    out = []
    for yl in range(H + 1):
        ps, cs = _COMPLETE, _NONOBJECT
        if yl < H:
            runs = list(zip(sx_all[row_start[yl]:row_start[yl + 1]], ex_all[row_start[yl]:row_start[yl + 1]]))
        else:
            runs = []
        base = yl * W
        # events: (x, kind) with kind 0 = run start, 1 = inside-run marker, 2 = run end / free marker
        inside_ends = {}
        ev = []
        run_at = {}
        for xa, xb in runs:
            run_at[xa] = xb
            ev.append(xa)
            ev.append(xb)
            inside_ends[xb] = True
        ev.extend(marker)
        evs = sorted(set(ev))
        cur_run_end = -1
        pend = None          # first pixel of the run not yet appended
        for xl in evs:
            lu = xl < cur_run_end or xl in run_at
            if lu and xl in run_at:
                cur_run_end = run_at[xl]
                pend = xl
            # pixels [pend, xl) of the current run belong to the object before this event
            if pend is not None and pend < xl and (lu or xl == cur_run_end):
                cid = len(c_start)
                c_start.append(base + pend)
                c_len.append(xl - pend)
                update(info[co], [cid, cid, xl - pend])
                pend = xl if lu else None
            newmarker = marker.pop(xl, 0)
            if lu and cs != _OBJECT:
                cs = _OBJECT
                if ps == _OBJECT:
                    if start[co] == _UNKNOWN:
                        marker[xl] = "S"
                        start[co] = xl
                    else:
                        marker[xl] = "s"
                else:
                    psstack.append(ps)
                    marker[xl] = "S"
                    co += 1
                    start[co] = xl
                    ps = _COMPLETE
                    info[co] = [-1, -1, 0]
            if newmarker:
                if newmarker == "S":
                    psstack.append(ps)
                    if cs == _NONOBJECT:
                        psstack.append(_COMPLETE)
                        co += 1
                        info[co] = list(store[xl])
                        start[co] = _UNKNOWN
                    else:
                        update(info[co], store[xl])
                    ps = _OBJECT
                elif newmarker == "s":
                    if cs == _OBJECT and ps == _COMPLETE:
                        psstack.pop()
                        xl2 = start[co]
                        update(info[co - 1], info[co])
                        co -= 1
                        if start[co] == _UNKNOWN:
                            start[co] = xl2
                        else:
                            marker[xl2] = "s"
                    ps = _OBJECT
                elif newmarker == "f":
                    ps = _INCOMPLETE
                else:  # "F"
                    ps = psstack.pop()
                    if cs == _NONOBJECT and ps == _COMPLETE:
                        if start[co] == _UNKNOWN:
                            first, last, n = info[co]
                            if n >= minarea:
                                pieces = [first]
                                p = first
                                while p != last:
                                    p = nxt[p]
                                    pieces.append(p)
                                out.append((np.concatenate([np.arange(c_start[q], c_start[q] + c_len[q])
                                                            for q in pieces]).astype(np.int64), yl, xl))
                        else:
                            marker[end[co]] = "F"
                            store[start[co]] = info[co]
                        co -= 1
                        ps = psstack.pop()
            if not lu and cs == _OBJECT:
                cs = _NONOBJECT
                if ps != _COMPLETE:
                    marker[xl] = "f"
                    end[co] = xl
                else:
                    ps = psstack.pop()
                    marker[xl] = "F"
                    store[start[co]] = info[co]
                    co -= 1
    return out


def lutz_one(mask):
    """:func:`lutz_regions` of a mask holding one 8-connected region, with a fast path.

    When every row of the region is a single run, sep's pixel list is built
    by a rule that needs no scan: each new row's pixels left of the previous
    row's run start come first, then the list so far, then the rest of the
    row; the region closes at (last row + 1, end of the last row's run).
    (Checked against the full scan in ``tests/engine/test_measure.py``.)
    Other shapes go through the scan.

    Returns
    -------
    (pixels, y_done, x_done)
    """
    mask = np.asarray(mask, dtype=bool)
    H, W = mask.shape
    ys, xs = np.nonzero(mask)
    if ys.size:
        y0, y1 = int(ys[0]), int(ys[-1])
        cnt = np.bincount(ys - y0, minlength=y1 - y0 + 1)
        first = np.searchsorted(ys, np.arange(y0, y1 + 1))
        a = xs[first]
        b = xs[first + cnt - 1] + 1
        if (cnt > 0).all() and np.array_equal(b - a, cnt) and (
                cnt.size == 1 or (np.all(b[1:] >= a[:-1]) and np.all(a[1:] <= b[:-1]))):
            a_l, b_l = a.tolist(), b.tolist()
            left, mid, right = [], [np.arange(y0 * W + a_l[0], y0 * W + b_l[0])], []
            for r in range(1, len(a_l)):
                base = (y0 + r) * W
                if a_l[r] < a_l[r - 1]:
                    left.append(np.arange(base + a_l[r], base + a_l[r - 1]))
                    right.append(np.arange(base + a_l[r - 1], base + b_l[r]))
                    # the list so far becomes the middle: later prefixes go before it
                    mid = left[::-1] + mid + right
                    left, right = [], []
                else:
                    mid.append(np.arange(base + a_l[r], base + b_l[r]))
            return np.concatenate(mid).astype(np.int64), y1 + 1, b_l[-1]
    return lutz_regions(mask, 1)[0]


# --------------------------------------------------------------------------
# mthresh
# --------------------------------------------------------------------------
def heap_mthresh(values, minarea: int) -> np.float32:
    """sep's ``mthresh`` of one object: its heap of the ``minarea`` largest values.

    Parameters
    ----------
    values : array of float32
        ``filtered - threshold`` of the object's pixels, in its pixel-list order
        [image units].
    minarea : int
        DETECT_MINAREA.

    Returns
    -------
    float32
        As sep's ``analysemthresh``: 0 for fewer than ``minarea`` pixels; the
        first value for exactly ``minarea``; otherwise the root of a heap that
        never sees the ``(minarea + 1)``-th value and is sifted with sep's
        index arithmetic (not always the ``minarea``-th largest value).
    """
    m = int(minarea)
    v = np.asarray(values, dtype=np.float32).tolist()     # float32 values, exact as Python floats
    n = len(v)
    if n < m:
        return np.float32(0.0)
    heap = v[:m]
    if n == m:
        return np.float32(heap[0])
    heap.sort()                                          # sep's fqmedian on the (m+1)-th pixel
    for t in v[m + 1:]:
        if t > heap[0]:
            heap[0] = t
            j = 0
            while True:
                k = (j + 1) << 1
                if k > m:
                    break
                hk = k
                if k != m and heap[hk - 1] > heap[hk]:
                    hk += 1
                    k += 1
                hk -= 1
                if heap[j] <= heap[hk]:
                    break
                heap[hk], heap[j] = heap[j], heap[hk]
                j = k
    return np.float32(heap[0])


# --------------------------------------------------------------------------
# Pixel order of deblended children
# --------------------------------------------------------------------------
def child_pixel_orders(region, W, seg_flat, filt_flat, labels, thresh0, nthresh):
    """Pixel-list order of the children of one deblended region.

    Parameters
    ----------
    region : array of int
        Flat indices of the region's pixels in sep's (Lutz) order.
    W : int
        Image width (flat index = y * W + x).
    seg_flat : array of int
        Segmentation (flat) after deblending: which child each pixel went to.
    filt_flat : array of float32
        Filtered image (flat).
    labels : sequence of int
        The children's labels, in sep's output order.
    thresh0 : float32
        The region's (mean) detection threshold [image units].
    nthresh : int
        DEBLEND_NTHRESH.

    Returns
    -------
    dict label -> array of flat indices
        Each child's core -- the connected part above the deblending level
        ``thresh0 (peak / thresh0)^(k / nthresh)`` at the lowest level ``k`` where
        a component containing the child's filtered peak lies entirely in the
        child (if that component has fewer than MAXDEBAREA pixels, the peak was
        handed to the child from another branch: the lowest-level component of
        at least MAXDEBAREA pixels lying in the child instead) -- in Lutz order,
        then its remaining pixels in the region's order (sep's ``gatherup``
        appends them in that order).
    """
    reg = np.asarray(region, dtype=np.int64)
    ys, xs = np.divmod(reg, W)
    y0, x0 = int(ys.min()), int(xs.min())
    h, w = int(ys.max()) - y0 + 1, int(xs.max()) - x0 + 1
    loc = np.full((h, w), -1, dtype=np.int64)
    loc[ys - y0, xs - x0] = reg
    fv = np.full((h, w), -np.inf, dtype=np.float32)
    fv[ys - y0, xs - x0] = filt_flat[reg]
    sl = np.zeros((h, w), dtype=np.int64)
    sl[ys - y0, xs - x0] = seg_flat[reg]
    th0 = np.float32(thresh0)
    fdpeak = np.float32(fv.max())
    levels = []
    for k in range(1, int(nthresh)):
        t = float(th0) * math.pow(float(fdpeak) / float(th0), k / int(nthresh)) if fdpeak > 0 else float(th0)
        levels.append(np.float32(t))
    lab_cache = {}
    out = {}
    reg_lab = seg_flat[reg]
    eight = np.ones((3, 3), dtype=bool)

    def level_labels(k):
        if k not in lab_cache:
            lab_cache[k] = ndimage.label(fv > levels[k], structure=eight)[0]
        return lab_cache[k]

    for c in labels:
        pc = sl == c
        if not pc.any():
            out[c] = np.zeros(0, dtype=np.int64)
            continue
        fc = np.where(pc, fv, -np.inf)
        py, px = np.unravel_index(int(np.argmax(fc)), fc.shape)

        def settled(k):
            """Below level k the peak's component leaves the child or vanishes (monotone in k)."""
            lab = level_labels(k)
            lv = lab[py, px]
            return lv == 0 or bool(np.all(pc[lab == lv]))

        # sep walks up the levels; the first level where the peak's component lies in the
        # child (or is gone) is found by bisection, the components being nested
        lo, hi = 0, len(levels)
        while lo < hi:
            mid = (lo + hi) // 2
            if settled(mid):
                hi = mid
            else:
                lo = mid + 1
        core = None
        if lo < len(levels):
            lab = level_labels(lo)
            lv = lab[py, px]
            if lv != 0:
                comp = lab == lv
                if comp.sum() >= _MAXDEBAREA:
                    core = comp
        if core is None:
            # the child's brightest pixel was handed to it from elsewhere (sep's gatherup
            # gives pixels of branches too faint to split to any child), so its own node is
            # another component: the lowest-level one lying in the child
            core = _inner_node(pc, fv, len(levels), level_labels)
        if core is None:
            order = reg[reg_lab == c]
        else:
            cy0, cx0 = np.nonzero(core)
            by0, bx0 = int(cy0.min()), int(cx0.min())
            sub = np.pad(core[by0:cy0.max() + 1, bx0:cx0.max() + 1], 1)
            pl = lutz_one(sub)[0]
            sy, sx = np.divmod(pl, sub.shape[1])
            core_pix = loc[sy - 1 + by0, sx - 1 + bx0]
            incore = np.zeros((h, w), dtype=bool)
            incore[sy - 1 + by0, sx - 1 + bx0] = True
            rest = reg[(reg_lab == c) & ~incore[ys - y0, xs - x0]]
            order = np.concatenate([core_pix, rest])
        out[c] = order
    return out


def _inner_node(pc, fv, nlevels, level_labels):
    """Lowest-level component of at least MAXDEBAREA pixels lying entirely in ``pc``
    (the brightest, if several at that level), or None."""
    npc = pc.ravel()
    for k in range(nlevels):
        lab = level_labels(k).ravel()
        nl = int(lab.max())
        if nl == 0:
            break
        tot = np.bincount(lab, minlength=nl + 1)
        inn = np.bincount(lab, weights=npc, minlength=nl + 1)
        ok = np.flatnonzero((tot == inn) & (tot >= _MAXDEBAREA))
        ok = ok[ok > 0]
        if ok.size:
            peak = ndimage.maximum(fv, level_labels(k), ok)
            return level_labels(k) == ok[int(np.argmax(peak))]
    return None
