# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled kernels of the engine's hot loops (optional: each has a numpy twin that gives the
same numbers, used when this extension is not built).

The shot-noise kernel draws from numpy's own C distributions (``numpy.random.c_distributions``,
the functions ``Generator.poisson`` and ``Generator.random`` call for each value), on the
generator's own bit stream and under its lock: the same draws, in the same order, as the numpy
code of :func:`glaciar.engine.shotnoise.noisy_pixels`, at a fraction of its per-call overhead.
``glaciar.engine.shotnoise`` checks that at import (:func:`kernel_agrees`) and falls back to
numpy if a numpy with other algorithms is ever installed beside this build.
"""
from cpython.pycapsule cimport PyCapsule_GetPointer, PyCapsule_IsValid
from libc.stdint cimport int64_t
from numpy.random cimport bitgen_t
from numpy.random.c_distributions cimport random_poisson, random_standard_uniform

__all__ = ["stamp_shot_noise"]

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
