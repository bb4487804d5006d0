"""sep's detection mask and CLEAN, reproduced in numpy so they can be applied anywhere.

Why
---
sep (like SExtractor) removes "spurious" detections with CLEAN: after the
whole image is extracted, every object is compared with every object within
``10 (a1 + a2)`` of it, and the fainter of a pair is removed when the
brighter one's extrapolated (Moffat-like) profile exceeds it.  sep returns
only the survivors, so two things cannot be had from it:

* CLEAN of a cut-out is not CLEAN of the full frame (the neighbours differ),
  and glaciar extracts cut-outs (:mod:`glaciar.engine.measure`);
* *who* removed an object.  SExtractor hands the removed object's pixels (and
  its isophotal flux) to the object that absorbed it (``mergeobject`` in its
  ``clean.c``); sep leaves them unlabelled, so sep's FLUX_ISO and S/N of the
  absorbing object come out low.  SExtractor also cleans as it extracts, with
  the absorbers' merged fluxes (:func:`sextractor_clean`); glaciar does either
  (``DetectionParams.clean_style``).

So glaciar extracts with CLEAN off and applies CLEAN itself, with exactly
sep's arithmetic (float32 where sep uses ``float``), on any list of objects.

What is reproduced, bit for bit (``tests/engine/test_measure.py`` checks the
survivors against ``sep.extract(..., clean=True)`` on full frames):

* the detection mask: sep's line convolution compared with ``DETECT_THRESH x
  rms`` per pixel (:func:`glaciar.engine.sepscan.detection_mask`);
* the order of objects: regions complete in the order of the pixel at which
  sep's Lutz scan closes them (:func:`glaciar.engine.sepscan.lutz_regions`), a deblended region's
  children in sep's deblending order;
* the order of each object's pixel list (Lutz order; for a deblended child,
  its core at the deblending level where it was split, in Lutz order, then
  the faint pixels handed to it, in the parent's order), which CLEAN depends
  on through ``mthresh``: the value of the ``DETECT_MINAREA``-th brightest
  pixel above threshold, found by a heap that skips the
  ``(minarea + 1)``-th pixel of the list and sifts with an off-by-one index
  (:func:`glaciar.engine.sepscan.heap_mthresh`; sep's ``analysemthresh``);
* the absorption test and the sequential loop of sep's ``clean()``
  (:func:`eats`, :func:`sep_clean`), including its order dependence (an object
  removed early cannot remove later ones).

All functions are pure (arrays in, arrays out).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from glaciar.engine.sepscan import heap_mthresh

__all__ = ["CleanObjects", "clean_objects", "eats", "abcor", "sep_clean", "sep_clean_bounded", "sextractor_clean",
           "zone_pairs", "in_zone", "profile_value", "final_owner", "CLEAN_ZONE"]

#: sep's CLEAN_ZONE: pairs further apart than CLEAN_ZONE (a1 + a2) are not compared
CLEAN_ZONE = 10.0


# --------------------------------------------------------------------------
# Objects and the CLEAN test
# --------------------------------------------------------------------------
@dataclass
class CleanObjects:
    """What CLEAN reads of each object (sep's ``objstruct`` fields), in sep's order.

    Attributes
    ----------
    x, y : ndarray of float64
        Barycentre (sep ``mx``, ``my``) [pixels].
    a, b, cxx, cyy, cxy : ndarray of float32
        Second-moment ellipse [pixels, pixels^-2].
    fdflux : ndarray of float32
        Sum of the filtered pixels (sep ``cflux``) [image units].
    thresh : ndarray of float32
        Detection threshold of the object (mean over its region) [image units].
    npix : ndarray of int64
        Pixels in the object.
    abcor : ndarray of float32
        sep's isophotal-area correction.
    mthresh : ndarray of float32
        See :func:`heap_mthresh` [image units].
    tmin : ndarray of float32
        Lowest pixel threshold of the object (SExtractor's ``dthresh`` with a
        weight map) [image units].
    """

    x: np.ndarray
    y: np.ndarray
    a: np.ndarray
    b: np.ndarray
    cxx: np.ndarray
    cyy: np.ndarray
    cxy: np.ndarray
    fdflux: np.ndarray
    thresh: np.ndarray
    npix: np.ndarray
    abcor: np.ndarray
    mthresh: np.ndarray
    tmin: np.ndarray

    def __len__(self):
        return int(np.size(self.x))

    @staticmethod
    def concat(parts) -> "CleanObjects":
        return CleanObjects(**{f: np.concatenate([np.asarray(getattr(p, f)) for p in parts]) for f in _FIELDS})

    @staticmethod
    def empty() -> "CleanObjects":
        return CleanObjects(**{f: np.zeros(0, dtype=t) for f, t in _DTYPES.items()})


_DTYPES = {"x": np.float64, "y": np.float64, "a": np.float32, "b": np.float32, "cxx": np.float32,
           "cyy": np.float32, "cxy": np.float32, "fdflux": np.float32, "thresh": np.float32,
           "npix": np.int64, "abcor": np.float32, "mthresh": np.float32, "tmin": np.float32}
_FIELDS = tuple(_DTYPES)


def clean_objects(cat, orders, data_flat, filt_flat, thr_flat, minarea: int) -> CleanObjects:
    """CLEAN inputs of sep-catalogue objects from their pixels.

    Parameters
    ----------
    cat : structured ndarray
        sep catalogue rows (fields x, y, a, b, cxx, cyy, cxy, cflux, thresh,
        npix, tnpix, peak), one per object.
    orders : sequence of int arrays
        Each object's pixels (flat indices) in sep's pixel-list order.
    data_flat, filt_flat, thr_flat : ndarray
        Unfiltered image, filtered image and threshold (flat, float32) [image units].
    minarea : int
        DETECT_MINAREA.

    Returns
    -------
    CleanObjects
        ``abcor`` as sep's ``analyse`` (from the pixels above the threshold and
        above half-way to the peak), ``mthresh`` as :func:`heap_mthresh`.
    """
    n = len(cat)
    if n == 0:
        return CleanObjects.empty()
    th = np.asarray(cat["thresh"], dtype=np.float32)
    peak = np.asarray(cat["peak"], dtype=np.float32)
    a = np.asarray(cat["a"], dtype=np.float32)
    b = np.asarray(cat["b"], dtype=np.float32)
    thresh2 = (th.astype(np.float64) + peak.astype(np.float64)) / 2.0
    orders = [np.asarray(o, dtype=np.int64) for o in orders]
    lens = np.array([o.size for o in orders], dtype=np.int64)
    allpix = np.concatenate(orders) if n else np.zeros(0, dtype=np.int64)
    owner = np.repeat(np.arange(n), lens)
    area2 = np.bincount(owner, weights=(np.asarray(data_flat)[allpix].astype(np.float64) > thresh2[owner]),
                        minlength=n)
    thr_all = np.asarray(thr_flat, dtype=np.float32)[allpix]
    tmin = np.full(n, np.inf, dtype=np.float32)
    np.minimum.at(tmin, owner, thr_all)
    tpix = (np.asarray(filt_flat, dtype=np.float32)[allpix] - thr_all).astype(np.float32)
    bounds = np.r_[0, np.cumsum(lens)]
    mth = np.array([heap_mthresh(tpix[bounds[i]:bounds[i + 1]], minarea) for i in range(n)], dtype=np.float32)
    ab = abcor(th, thresh2, area2, cat["tnpix"], a, b)
    return CleanObjects(x=np.asarray(cat["x"], dtype=np.float64), y=np.asarray(cat["y"], dtype=np.float64),
                        a=a, b=b, cxx=np.asarray(cat["cxx"], dtype=np.float32),
                        cyy=np.asarray(cat["cyy"], dtype=np.float32), cxy=np.asarray(cat["cxy"], dtype=np.float32),
                        fdflux=np.asarray(cat["cflux"], dtype=np.float32), thresh=th,
                        npix=np.asarray(cat["npix"], dtype=np.int64), abcor=ab, mthresh=mth, tmin=tmin)


def abcor(th, thresh2, area2, tnpix, a, b) -> np.ndarray:
    """sep's/SExtractor's CLEAN profile correction ``abcor`` (float32), from the area
    above half-way between threshold and peak: the one copy both input builders use."""
    darea = area2 - np.asarray(tnpix, dtype=np.float64)
    t1t2 = th.astype(np.float64) / thresh2
    with np.errstate(divide="ignore", invalid="ignore"):
        ab = (np.where(darea < 0.0, darea, -1.0)
              / (2 * math.pi * np.log(np.where(t1t2 < 1.0, t1t2, 0.99)) * a.astype(np.float64)
                 * b.astype(np.float64)))
    ab = ab.astype(np.float32)
    return np.where(t1t2 > 0.0, np.where(ab > 1.0, np.float32(1.0), ab),
                    np.float32(1.0)).astype(np.float32)


def _profile(o: CleanObjects, i, beta):
    """(amp, alpha) of object i's CLEAN profile, in sep's double arithmetic."""
    unit = math.pi * float(o.a[i]) * float(o.b[i])
    amp = float(o.fdflux[i]) / (2 * unit * float(o.abcor[i]))
    alpha = (math.pow(amp / float(o.thresh[i]), 1.0 / beta) - 1) * unit / int(o.npix[i])
    return amp, alpha


def _zone(x1, y1, a1, x2, y2, a2):
    """sep's CLEAN_ZONE test, vectorised: (inside, dx, dy) with dx, dy float32."""
    f32 = np.float32
    dx = (np.asarray(x1, dtype=np.float64) - np.asarray(x2, dtype=np.float64)).astype(f32)
    dy = (np.asarray(y1, dtype=np.float64) - np.asarray(y2, dtype=np.float64)).astype(f32)
    rlim = (np.asarray(a1, dtype=f32) + np.asarray(a2, dtype=f32)).astype(f32)
    rlim = (rlim * rlim).astype(f32)
    d2 = (dx * dx + dy * dy).astype(f32)
    return d2.astype(np.float64) <= rlim.astype(np.float64) * CLEAN_ZONE * CLEAN_ZONE, dx, dy


def in_zone(x1, y1, a1, x2, y2, a2) -> bool:
    """sep's CLEAN_ZONE test for one pair (scalars): are the two objects compared at all?"""
    f32 = np.float32
    dx = f32(x1 - x2)
    dy = f32(y1 - y2)
    rlim = f32(f32(a1) + f32(a2))
    rlim = f32(rlim * rlim)
    return float(f32(dx * dx + dy * dy)) <= float(rlim) * CLEAN_ZONE * CLEAN_ZONE


def eats(o1: CleanObjects, i, o2: CleanObjects, j, beta: float) -> bool:
    """Would object ``i`` of ``o1`` remove object ``j`` of ``o2`` (sep's test, one direction)?

    Parameters
    ----------
    o1, o2 : CleanObjects
    i, j : int
    beta : float
        CLEAN_PARAM.

    Returns
    -------
    bool
        ``j`` within CLEAN_ZONE (a_i + a_j) of ``i`` and ``i``'s profile
        ``amp (1 + alpha (cxx dx^2 + cyy dy^2 + cxy dx dy))^-beta`` above
        ``j``'s mthresh there.  (Which direction sep tests depends on the
        fluxes and the order; see :func:`sep_clean`.)
    """
    f32 = np.float32
    x1, y1, x2, y2 = float(o1.x[i]), float(o1.y[i]), float(o2.x[j]), float(o2.y[j])
    if not in_zone(x1, y1, o1.a[i], x2, y2, o2.a[j]):
        return False
    return _profile_test(o1, i, o2, j, f32(x1 - x2), f32(y1 - y2), beta)


def profile_value(o1: CleanObjects, i, dx, dy, beta):
    """Object i's CLEAN profile at offset (dx, dy) [float32 image units], or None where sep's
    test cannot succeed (``val <= 1``)."""
    f32 = np.float32
    amp, alpha = _profile(o1, i, beta)
    dx, dy = f32(dx), f32(dy)
    q = f32(f32(o1.cxx[i] * dx) * dx + f32(o1.cyy[i] * dy) * dy) + f32(o1.cxy[i] * dx) * dy
    val = 1 + alpha * float(q)
    if not val > 1.0:
        return None
    return float(f32(amp * math.pow(val, -beta) if val < 1e10 else 0.0))


def _profile_test(o1, i, o2, j, dx, dy, beta):
    prof = profile_value(o1, i, dx, dy, beta)
    return prof is not None and prof > float(o2.mthresh[j])


def sep_clean(objs: CleanObjects, beta: float, pairs=None):
    """sep's ``clean()`` on objects listed in sep's order.

    Parameters
    ----------
    objs : CleanObjects
        In the order sep would have them (its final object list).
    beta : float
        CLEAN_PARAM.
    pairs : (i, j) int arrays, optional
        The pairs (i < j) within CLEAN_ZONE of each other; by default
        :func:`zone_pairs`.

    Returns
    -------
    survives : ndarray of bool
    eater : ndarray of int
        Index of the object whose test removed each object (-1 for survivors).
        As in sep, an object removed by a later one may itself have removed
        others before; :func:`final_owner` follows the chain.
    """
    m = np.asarray(objs.mthresh, dtype=np.float32)
    return sep_clean_bounded(objs, beta, m, m, None, pairs)


#: Relative margin within which a vectorised profile value is re-checked with the scalar,
#: bit-exact arithmetic (numpy's pow may differ from C's by an ulp: ~1e-16)
_PROFILE_MARGIN = 1e-6


def sep_clean_bounded(objs: CleanObjects, beta: float, lo, hi, mthresh_of=None, pairs=None):
    """sep's ``clean()`` knowing only bounds of ``mthresh``; exact values fetched on demand.

    sep's test "i removes j" reads only the two objects' own values: the
    profile of the brighter (filtered flux) at the other's barycentre against
    the other's ``mthresh``.  Each pair's test is therefore decided up front:
    from the bounds where they settle it, else with the exact ``mthresh``
    (the expensive part: it needs the object's pixel order), asked only for
    those objects.  sep's sequential loop is then replayed over the pairs whose
    test succeeds (the only ones that change anything), with its order
    dependence: an object's own comparisons are skipped if it was removed
    before its turn, not if it is removed during it.

    Parameters
    ----------
    objs : CleanObjects
        In sep's order; ``mthresh`` is not read.
    beta : float
        CLEAN_PARAM.
    lo, hi : array of float32, shape (n,)
        Bounds of each object's ``mthresh``: ``lo <= mthresh <= hi`` [image units].
    mthresh_of : callable, optional
        ``mthresh_of(indices) -> array of float32``: the exact ``mthresh`` of
        the given objects; only called for objects whose bounds leave a test
        undecided (never when ``lo == hi``).
    pairs : (i, j) int arrays, optional
        As in :func:`sep_clean`.

    Returns
    -------
    survives, eater : as :func:`sep_clean`
    """
    n = len(objs)
    survives = np.ones(n, dtype=bool)
    eater = np.full(n, -1, dtype=np.int64)
    if n < 2:
        return survives, eater
    pi, pj = zone_pairs(objs) if pairs is None else pairs
    if pi.size == 0:
        return survives, eater
    lo = np.asarray(lo, dtype=np.float32)
    hi = np.asarray(hi, dtype=np.float32)
    _, dx, dy = _zone(objs.x[pi], objs.y[pi], objs.a[pi], objs.x[pj], objs.y[pj], objs.a[pj])
    fd = np.asarray(objs.fdflux, dtype=np.float32)
    i_eats = fd[pj] < fd[pi]                     # sep tests the brighter one's profile
    e = np.where(i_eats, pi, pj)
    v = np.where(i_eats, pj, pi)
    sdx = np.where(i_eats, dx, -dx).astype(np.float32)
    sdy = np.where(i_eats, dy, -dy).astype(np.float32)
    prof, val = _approx_profiles(objs, e, sdx, sdy, beta)
    lo_v, hi_v = lo[v].astype(np.float64), hi[v].astype(np.float64)
    tol = _PROFILE_MARGIN
    with np.errstate(invalid="ignore"):
        inner = (val > 1 + tol) & (val < 1e10 * (1 - tol))      # profile amp val^-beta
        yes = inner & (prof - tol * np.abs(prof) > hi_v)
        no = ((val < 1 - tol) | ((val > 1e10 * (1 + tol)) & (lo_v >= 0))
              | (inner & (prof + tol * np.abs(prof) < lo_v)))
    # the rest, scalar and exact: the profile, then the bounds, then the exact mthresh
    need_k, need_p = [], []
    for k in np.flatnonzero(~(yes | no)).tolist():
        p = profile_value(objs, int(e[k]), sdx[k], sdy[k], beta)
        if p is None:
            continue
        if p > hi_v[k]:
            yes[k] = True
        elif p > lo_v[k]:
            need_k.append(k)
            need_p.append(p)
    if need_k:
        need_k = np.asarray(need_k, dtype=np.int64)
        uv, inv = np.unique(v[need_k], return_inverse=True)
        if mthresh_of is None:
            raise ValueError("sep_clean_bounded: bounds leave tests undecided and no mthresh_of was given")
        mth = np.asarray(mthresh_of(uv), dtype=np.float32).astype(np.float64)
        yes[need_k] = np.asarray(need_p) > mth[inv]
    # sep's loop over the successful tests, in its order (pairs sorted by i, then j)
    ks = np.flatnonzero(yes)
    cur, alive = -1, False
    for k, i, j, ie in zip(ks.tolist(), pi[ks].tolist(), pj[ks].tolist(), i_eats[ks].tolist()):
        if i != cur:
            cur, alive = i, bool(survives[i])       # sep checks i once, before its comparisons
        if not alive or not survives[j]:
            continue
        if ie:
            survives[j] = False
            eater[j] = i
        else:
            survives[i] = False
            eater[i] = j
    return survives, eater


def _approx_profiles(o: CleanObjects, e, dx, dy, beta):
    """Objects ``e``'s CLEAN profiles at offsets (dx, dy), vectorised: (value, val) in float64.

    The arithmetic of :func:`profile_value` (float32 quadratic form, double
    profile) except numpy's ``pow``: equal to it within ~1e-15 relative, so only
    comparisons closer than :data:`_PROFILE_MARGIN` need the scalar version.
    """
    f64 = np.float64
    unit = math.pi * o.a[e].astype(f64) * o.b[e].astype(f64)
    with np.errstate(all="ignore"):
        amp = o.fdflux[e].astype(f64) / (2 * unit * o.abcor[e].astype(f64))
        alpha = (np.power(amp / o.thresh[e].astype(f64), 1.0 / beta) - 1) * unit / o.npix[e].astype(f64)
        q = (o.cxx[e] * dx) * dx + (o.cyy[e] * dy) * dy + (o.cxy[e] * dx) * dy      # float32, sep's order
        val = 1 + alpha * q.astype(f64)
        prof = amp * np.power(val, -float(beta))
    return prof, val


def zone_pairs(objs: CleanObjects, chunk: int = 65536):
    """All pairs (i < j) within sep's CLEAN_ZONE, sorted by i then j.

    Parameters
    ----------
    objs : CleanObjects
    chunk : int
        Objects queried at a time (bounds the memory of the candidate lists).

    Returns
    -------
    i, j : ndarray of int64

    Notes
    -----
    A pair is in the zone when its distance is at most ``CLEAN_ZONE (a_i + a_j)
    <= 2 CLEAN_ZONE max(a_i, a_j)``, so each object's neighbours within ``2
    CLEAN_ZONE a`` of it hold every pair in which it has the larger ``a``: the
    pair is kept from that member's query (ties: the lower index's), then sep's
    exact test decides.  The work is the sum of each object's own zone, linear
    in the number of objects (a query radius ``CLEAN_ZONE (a_i + max a)`` made
    one large object cost a large search per object).
    """
    from scipy.spatial import cKDTree

    n = len(objs)
    none = np.zeros(0, dtype=np.int64)
    if n < 2:
        return none, none.copy()
    pts = np.c_[objs.x, objs.y]
    a = np.asarray(objs.a, dtype=np.float64)
    # margin over float32 rounding of sep's test (relative ~1e-7)
    r = 2.0 * CLEAN_ZONE * a * (1 + 1e-6) + 1e-3
    tree = cKDTree(pts)
    out_i, out_j = [], []
    for c0 in range(0, n, chunk):
        c1 = min(c0 + chunk, n)
        near = tree.query_ball_point(pts[c0:c1], r[c0:c1], return_sorted=False)
        cnt = np.fromiter((len(v) for v in near), dtype=np.int64, count=c1 - c0)
        ii = np.repeat(np.arange(c0, c1, dtype=np.int64), cnt)
        jj = np.fromiter((j for v in near for j in v), dtype=np.int64, count=int(cnt.sum()))
        del near
        ai, aj = a[ii], a[jj]
        keep = (aj < ai) | ((aj == ai) & (jj > ii))
        ii, jj = ii[keep], jj[keep]
        lo, hi = np.minimum(ii, jj), np.maximum(ii, jj)
        inside, _, _ = _zone(objs.x[lo], objs.y[lo], objs.a[lo], objs.x[hi], objs.y[hi], objs.a[hi])
        out_i.append(lo[inside])
        out_j.append(hi[inside])
    ii, jj = np.concatenate(out_i), np.concatenate(out_j)
    order = np.lexsort((jj, ii))
    return ii[order], jj[order]


def sextractor_clean(objs: CleanObjects, beta: float, dthresh, pairs=None):
    """SExtractor's CLEAN (2.x ``clean()`` with ``mergeobject``) on objects in scan order.

    Each object, as it arrives, is compared with the objects kept so far (in
    the order of SExtractor's clean list: appended, and removed by moving the
    last one into the gap), within CLEAN_ZONE (a1 + a2):

    * a kept object at least as bright (filtered flux) that eats the newcomer
      absorbs it: the first such object in list order takes the newcomer's
      pixels, filtered flux and pixel count, and the newcomer is not kept;
    * otherwise the newcomer absorbs every fainter kept object it eats (its
      "menu", taken in reverse list order) and is kept.

    Tests use the absorber's flux and area *as merged so far*, the object's
    minimum pixel threshold (``dthresh``) and ``abcor`` = 1 (SExtractor with a
    detection weight map, as glaciar always has: an RMS map).

    Parameters
    ----------
    objs : CleanObjects
        In scan order.
    beta : float
        CLEAN_PARAM.
    dthresh : array of float32
        Each object's lowest pixel threshold [image units].
    pairs : (i, j) arrays, optional
        Pairs within CLEAN_ZONE (:func:`zone_pairs`).

    Returns
    -------
    survives : ndarray of bool
    master : ndarray of int
        The object each removed object was merged into (-1 for survivors);
        :func:`final_owner` follows the chain.
    """
    n = len(objs)
    survives = np.ones(n, dtype=bool)
    master = np.full(n, -1, dtype=np.int64)
    if n < 2:
        return survives, master
    f32 = np.float32
    fd = [float(v) for v in np.asarray(objs.fdflux, dtype=np.float32)]
    npx = [int(v) for v in objs.npix]
    dth = [float(v) for v in np.asarray(dthresh, dtype=np.float32)]
    mth = [float(v) for v in np.asarray(objs.mthresh, dtype=np.float32)]
    pi, pj = zone_pairs(objs) if pairs is None else pairs
    earlier = [[] for _ in range(n)]          # for each newcomer j, the earlier objects i in zone
    for i, j in zip(pi.tolist(), pj.tolist()):
        earlier[j].append(i)
    lst, pos = [], {}

    def profile(i, dx, dy):
        unit = math.pi * float(objs.a[i]) * float(objs.b[i])
        amp = fd[i] / (2 * unit * 1.0)
        alpha = (math.pow(amp / dth[i], 1.0 / beta) - 1) * unit / npx[i]
        q = f32(f32(objs.cxx[i] * dx) * dx + f32(objs.cyy[i] * dy) * dy) + f32(objs.cxy[i] * dx) * dy
        val = 1 + alpha * float(q)
        if not val > 1.0:
            return None
        return float(f32(amp * math.pow(val, -beta) if val < 1e10 else 0.0))

    for k in range(n):
        cands = sorted((pos[i], i) for i in earlier[k] if i in pos)
        menu = []
        eaten_by = -1
        for p_, i in cands:
            dx = f32(objs.x[k] - objs.x[i])
            dy = f32(objs.y[k] - objs.y[i])
            rlim = f32(f32(objs.a[k]) + f32(objs.a[i]))
            rlim = f32(rlim * rlim)
            if not float(f32(dx * dx + dy * dy)) < float(rlim) * CLEAN_ZONE * CLEAN_ZONE:
                continue
            if fd[i] < fd[k]:
                v = profile(k, dx, dy)
                if v is not None and v > mth[i]:
                    menu.append(p_)
            else:
                v = profile(i, dx, dy)
                if v is not None and v > mth[k]:
                    eaten_by = i
                    break
        if eaten_by >= 0:
            fd[eaten_by] = float(f32(f32(fd[eaten_by]) + f32(fd[k])))
            npx[eaten_by] += npx[k]
            survives[k] = False
            master[k] = eaten_by
            continue
        for p_ in sorted(menu, reverse=True):
            i = lst[p_]
            fd[k] = float(f32(f32(fd[k]) + f32(fd[i])))
            npx[k] += npx[i]
            survives[i] = False
            master[i] = k
            last = lst.pop()
            del pos[i]
            if p_ < len(lst):
                lst[p_] = last
                pos[last] = p_
        pos[k] = len(lst)
        lst.append(k)
    return survives, master


def final_owner(survives, eater) -> np.ndarray:
    """Surviving object each object's pixels end in (itself if it survives).

    Follows ``eater`` until a survivor; an object whose chain never reaches one
    (impossible in sep's loop, kept for safety) gets -1.
    """
    survives = np.asarray(survives, dtype=bool)
    eater = np.asarray(eater, dtype=np.int64)
    n = survives.size
    own = np.where(survives, np.arange(n), -1)
    for i in np.flatnonzero(~survives).tolist():
        j, seen = i, 0
        while j >= 0 and not survives[j] and seen <= n:
            j = int(eater[j])
            seen += 1
        own[i] = j if j >= 0 and survives[j] else -1
    return own
