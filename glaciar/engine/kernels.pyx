# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled kernels of the engine's hot loops (optional: each has a numpy twin that gives the
same numbers, used when this extension is not built).

The stamp-pasting kernel adds each stamp's part to each window it overlaps in one loop
(:meth:`glaciar.engine.scene.Scene.paste_windows` otherwise makes a few numpy calls per stamp and
window); it rounds as numpy does, one product and one sum per pixel (built without fused
multiply-adds, see setup.py).

The filter kernel is :func:`glaciar.engine.sepscan.sep_filter`'s float32 correlation in one
pass per row instead of a whole-array pass per tap: the same products summed in the same order.

The shot-noise kernel draws from numpy's own C distributions (``numpy.random.c_distributions``,
the functions ``Generator.poisson`` and ``Generator.random`` call for each value), on the
generator's own bit stream and under its lock: the same draws, in the same order, as the numpy
code of :func:`glaciar.engine.shotnoise.noisy_pixels`, at a fraction of its per-call overhead.
``glaciar.engine.shotnoise`` checks that at import
(:func:`glaciar.engine.shotnoise.kernel_agrees`) and falls back to numpy if a numpy with other
algorithms is ever installed beside this build.
"""
from cpython.pycapsule cimport PyCapsule_GetPointer, PyCapsule_IsValid
from libc.stdint cimport int64_t
from numpy.random cimport bitgen_t
from numpy.random.c_distributions cimport random_poisson, random_standard_uniform

__all__ = ["stamp_shot_noise", "add_stamp_parts", "filter_padded"]

cdef bitgen_t *_bitgen(object bit_generator) except NULL:
    capsule = bit_generator.capsule
    if not PyCapsule_IsValid(capsule, "BitGenerator"):
        raise ValueError("stamp_shot_noise: not a numpy BitGenerator")
    return <bitgen_t *> PyCapsule_GetPointer(capsule, "BitGenerator")


def stamp_shot_noise(object bit_generator, const int64_t[::1] core, const double[::1] core_values,
                     const double[::1] cum, double scale, double gain, double[::1] out):
    """One stamp's photon noise where its core is below the Gaussian switch and its wings are
    sparse: the core drawn pixel by pixel, then the wings by Poisson splitting.

    Parameters
    ----------
    bit_generator : numpy.random.BitGenerator
        The band's stream (``Generator.bit_generator``), consumed as ``noisy_pixels`` does.
    core : int64 array
        Flat indices of the core pixels; ``core_values`` the template there (> 0).
    cum : float64 array
        Cumulative sum of the wings (core pixels as 0), one element per stamp pixel.
    scale : float
        Electrons per unit of the template (flux x gain).
    gain : float
        Electrons per image unit.
    out : float64 array
        Zeroed flat stamp [image units], written in place.
    """
    cdef bitgen_t *rng = _bitgen(bit_generator)
    cdef Py_ssize_t i, m = core.shape[0], size = out.shape[0], ncum = cum.shape[0]
    cdef double one = 1.0 / gain
    if core_values.shape[0] != m or ncum != size:
        raise ValueError("stamp_shot_noise: core/core_values or cum/out sizes differ")
    with bit_generator.lock, nogil:
        for i in range(m):
            out[core[i]] = <double> random_poisson(rng, core_values[i] * scale) / gain
        if ncum > 0 and cum[ncum - 1] * scale > 0.0:
            _place_electrons(rng, cum, scale, one, out)


cdef void _place_electrons(bitgen_t *rng, const double[::1] cum, double scale, double one,
                           double[::1] out) noexcept nogil:
    """Poisson splitting: N ~ Poisson(cum[-1] scale) electrons, each in pixel i with
    probability (cum[i] - cum[i-1]) / cum[-1]."""
    cdef Py_ssize_t lo, hi, mid, ncum = cum.shape[0]
    cdef double top = cum[ncum - 1], u
    cdef int64_t k, n = random_poisson(rng, top * scale)
    for k in range(n):
        # searchsorted(cum, u, side="right"): the first pixel whose cumulative sum exceeds u;
        # an electron adds the same 1 / gain wherever it falls, so placing them unsorted
        # changes no pixel.
        u = random_standard_uniform(rng) * top
        lo, hi = 0, ncum
        while lo < hi:
            mid = (lo + hi) >> 1
            if cum[mid] <= u:
                lo = mid + 1
            else:
                hi = mid
        if lo > ncum - 1:
            lo = ncum - 1
        out[lo] += one


def add_stamp_parts(double[:, ::1] canvas, list stamps, list fluxes, const int64_t[:, ::1] boxes,
                    const int64_t[:, ::1] rects, const int64_t[:, ::1] offsets,
                    const int64_t[:] ks, const int64_t[:] ws):
    """Add stamp ``ks[p]``'s part inside window ``ws[p]`` to that window's place on the canvas,
    for each pair ``p`` in order: ``canvas[cy + y - y0, cx + x - x0] += stamp[y - sy0, x - sx0]``
    (times the stamp's flux when it is not None) over the overlap.

    Parameters
    ----------
    canvas : float64 array, C-contiguous
        The tiled windows, written in place.
    stamps : list of 2-d float64 arrays
        Each stamp's pixels (a unit-flux template when its flux is not None).
    fluxes : list of float or None
    boxes : int64 array (n, 4)
        Each stamp's image rows and columns ``sy0, sy1, sx0, sx1`` (exclusive ends).
    rects : int64 array (W, 4)
        Each window's image ``y0, y1, x0, x1``; ``offsets`` (W, 2) its canvas row and column.
    ks, ws : int64 arrays
        The overlapping (stamp, window) pairs; a pixel gets its stamps in the pairs' order.
    """
    cdef Py_ssize_t p, i, j, k, w, last = -1, n = ks.shape[0]
    cdef int64_t sy0, sy1, sx0, sx1, y0, y1, x0, x1, ay0, ay1, ax0, ax1, cy, cx
    cdef const double[:, :] part
    cdef double f = 1.0
    cdef bint scaled = False
    if ws.shape[0] != n:
        raise ValueError("add_stamp_parts: ks and ws differ in length")
    for p in range(n):
        k, w = ks[p], ws[p]
        if k != last:
            part = stamps[k]
            flux = fluxes[k]
            scaled = flux is not None
            f = <double> flux if scaled else 1.0
            last = k
        sy0, sy1, sx0, sx1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        y0, y1, x0, x1 = rects[w, 0], rects[w, 1], rects[w, 2], rects[w, 3]
        cy, cx = offsets[w, 0], offsets[w, 1]
        # Unchecked indexing below: every box must match its stamp and every window the canvas.
        if (sy1 - sy0 != part.shape[0] or sx1 - sx0 != part.shape[1] or cy < 0 or cx < 0
                or cy + y1 - y0 > canvas.shape[0] or cx + x1 - x0 > canvas.shape[1]):
            raise ValueError(f"add_stamp_parts: stamp {k} or window {w} does not fit its array")
        ay0, ay1 = max(sy0, y0), min(sy1, y1)
        ax0, ax1 = max(sx0, x0), min(sx1, x1)
        with nogil:
            if scaled:
                for i in range(ay0, ay1):
                    for j in range(ax0, ax1):
                        canvas[cy + i - y0, cx + j - x0] += part[i - sy0, j - sx0] * f
            else:
                for i in range(ay0, ay1):
                    for j in range(ax0, ax1):
                        canvas[cy + i - y0, cx + j - x0] += part[i - sy0, j - sx0]


def filter_padded(const float[:, ::1] padded, const float[:, ::1] kernel, float[:, ::1] out):
    """``out[y, x] = sum over taps (row-major) of kernel[i, j] * padded[y + i, x + j]``, each
    product rounded to float32 and added to a float32 sum that starts at 0, in tap order.

    Parameters
    ----------
    padded : float32 array (>= H + kh - 1, >= W + kw - 1)
        The image in a frame of zeros (``kh // 2`` rows and ``kw // 2`` columns before it).
    kernel : float32 array (kh, kw)
        The normalised filter.
    out : float32 array (H, W)
        Written in place.
    """
    cdef Py_ssize_t y, x, i, j, H = out.shape[0], W = out.shape[1]
    if H == 0 or W == 0:
        return
    cdef Py_ssize_t kh = kernel.shape[0], kw = kernel.shape[1]
    cdef float kv
    cdef float *row
    cdef const float *src
    if padded.shape[0] < H + kh - 1 or padded.shape[1] < W + kw - 1:
        raise ValueError("filter_padded: the padded image is smaller than the output plus the kernel")
    with nogil:
        for y in range(H):
            row = &out[y, 0]
            for x in range(W):
                row[x] = 0.0
            for i in range(kh):
                for j in range(kw):
                    kv = kernel[i, j]
                    src = &padded[y + i, j]
                    for x in range(W):
                        row[x] = row[x] + kv * src[x]
