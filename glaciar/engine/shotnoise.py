"""Photon (shot) noise of the injected sources.

A real galaxy's pixels carry the Poisson noise of its own electrons; a stamp of
``flux x template`` does not.  Where a band's gain ``g`` (electrons per image
unit, ``survey.bands.<band>.gain``) is known, each injected stamp's pixels ``p``
[image units] are replaced once, before any window reads them, by::

    Poisson(max(p g, 0)) / g                       where p g <  GAUSSIAN_ABOVE_COUNTS
    p + sqrt(p / g) N(0, 1)                        where p g >= GAUSSIAN_ABOVE_COUNTS

Mean and variance are exact (p and p / g) in both regimes.  The Gaussian limit
drops only the Poisson skewness 1/sqrt(p g) of a pixel (< 0.01 above the switch;
in a sum over pixels, e.g. an aperture, the skewness of the source's part is at
most 1/sqrt(its electrons) either way).  The switch guards numpy's Poisson
sampler against huge counts (it refuses lambda > ~9e18) and costs nothing where
counts are small.  A stamp's faint wings are drawn by Poisson splitting, exactly
the same distribution at a cost per electron instead of per pixel
(:func:`noisy_pixels`).

Randomness: each band's noise comes from its own stream, a child of the task's
``SeedSequence`` (:func:`shot_noise_rng`), never from the task's stream: the
task's draws (positions, shapes, ...) are the same with or without shot noise,
and a run without gains draws nothing.  Sources are drawn in their order, so a
task's noise does not depend on the worker, the order of tasks, resume, or on
which detection window (or mode) later reads the pixels.
"""
from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from typing import Mapping, NamedTuple, Sequence

import numpy as np

from glaciar.engine.compiled import KERNELS

__all__ = ["GAUSSIAN_ABOVE_COUNTS", "CORE_FRACTION", "DENSE_WINGS_COUNTS", "WINGS_CACHE_BYTES",
           "SHOT_NOISE_STREAM_KEY", "KERNEL", "kernel_agrees", "shot_noise_gains", "wings_cache_info",
           "shot_noise_rng", "noisy_pixels", "add_shot_noise"]

#: Pixels expecting at least this many electrons get the Gaussian limit of Poisson noise.
GAUSSIAN_ABOVE_COUNTS = 1.0e4

#: Template pixels holding at least this fraction of the flux (the core) are drawn one by one,
#: the others (the wings: ~1-10 % of the light in 50-99 % of the pixels) by Poisson splitting.
CORE_FRACTION = 1.0e-4

#: Wings expecting more electrons than this per pixel on average are drawn pixel by pixel
#: (Poisson splitting costs ~3 per-pixel draws per electron).
DENSE_WINGS_COUNTS = 0.25

#: Upper bound on the bytes of the per-template core/wings splits kept (8 bytes per template
#: pixel, the template's own size, and 8 more per core pixel).  Entries leave with their
#: template, so in a run the splits held follow the template cache (glaciar.galaxy.templates:
#: about one redshift's stamps, which is what the tasks re-use); this bound is for callers
#: with templates of their own.
WINGS_CACHE_BYTES = 128 * 2**20

#: First extra spawn-key word of the shot-noise streams (an arbitrary fixed 63-bit value, so
#: that it cannot meet the small indices of ``SeedSequence.spawn`` children).
SHOT_NOISE_STREAM_KEY = int.from_bytes(b"shotnois", "big") >> 1


def shot_noise_gains(setting: bool | None, gains: Mapping[str, float | None]) -> dict[str, float]:
    """The bands that get shot noise, with their gains.

    Parameters
    ----------
    setting : bool or None
        ``source.shot_noise``: False = none; True or None (the default) = in every
        band with a gain.
    gains : mapping band -> float or None
        ``survey.bands.<band>.gain`` [electrons per image unit]; None = unknown.

    Returns
    -------
    dict
        band -> gain, only the bands with a gain (empty when ``setting`` is False).
    """
    if setting is False:
        return {}
    return {b: float(g) for b, g in gains.items() if g is not None}


def shot_noise_rng(seed: int, task_key: Sequence[int], band_key: int) -> np.random.Generator:
    """The generator of one band's shot noise in one task.

    A child of the task's ``SeedSequence(seed, spawn_key=task_key)`` (the key of
    :meth:`glaciar.engine.task.TaskSpec.spawn_key`), keyed by the band
    (``band_key``, e.g. :func:`glaciar.engine.task.field_key` of its name, so a
    band's noise does not depend on the band order).
    """
    key = tuple(int(k) for k in task_key) + (SHOT_NOISE_STREAM_KEY, int(band_key))
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=key))


class _Wings(NamedTuple):
    """A template split for :func:`noisy_pixels`: its core pixels and its wings' cumulative sum."""

    ref: object              #: weak reference to the template (the entry lives as long as it)
    core: np.ndarray         #: flat indices of the pixels >= CORE_FRACTION
    cum: np.ndarray          #: cumulative sum of the other pixels (core pixels and negatives as 0)
    nbytes: int
    core_values: np.ndarray  #: the template's values at ``core`` (all >= CORE_FRACTION > 0)
    core_max: float          #: their maximum (0 without a core)
    wings_sum: float         #: ``cum[-1]`` (0 without wings)


_WINGS: "OrderedDict[int, _Wings]" = OrderedDict()
_WINGS_BYTES = [0]
#: Reentrant: a template freed while the lock is held (garbage collection) calls _forget.
_WINGS_LOCK = threading.RLock()


def _forget(key: int) -> None:
    with _WINGS_LOCK:
        entry = _WINGS.pop(key, None)
        if entry is not None:
            _WINGS_BYTES[0] -= entry.nbytes


def wings_cache_info() -> tuple[int, int]:
    """(entries, bytes) of the core/wings splits this process keeps (:func:`noisy_pixels`)."""
    with _WINGS_LOCK:
        return len(_WINGS), _WINGS_BYTES[0]


def _wings(data: np.ndarray) -> _Wings:
    """The core/wings split of a template, cached while the template lives (the template cache
    shares one array per shape, position and band) in at most :data:`WINGS_CACHE_BYTES`."""
    key = id(data)
    with _WINGS_LOCK:
        entry = _WINGS.get(key)
        if entry is not None and entry.ref() is data:
            _WINGS.move_to_end(key)
            return entry
    flat = data.ravel()
    core = np.flatnonzero(flat >= CORE_FRACTION)
    wings = np.maximum(flat, 0.0)
    core_values = flat[core]
    wings[core] = 0.0
    cum = np.cumsum(wings)
    extra = (core_values, float(core_values.max(initial=0.0)), float(cum[-1]) if cum.size else 0.0)
    try:
        ref = weakref.ref(data, lambda _, k=key: _forget(k))
    except TypeError:                       # not weak-referenceable: not cached
        return _Wings(None, core, cum, 0, *extra)
    entry = _Wings(ref, core, cum, core.nbytes + cum.nbytes + core_values.nbytes, *extra)
    with _WINGS_LOCK:
        _forget(key)
        _WINGS[key] = entry
        _WINGS_BYTES[0] += entry.nbytes
        while _WINGS_BYTES[0] > WINGS_CACHE_BYTES and len(_WINGS) > 1:
            _forget(next(iter(_WINGS)))
    return entry


def _per_pixel(counts: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Electrons drawn pixel by pixel: Poisson, its Gaussian limit from GAUSSIAN_ABOVE_COUNTS."""
    high = counts >= GAUSSIAN_ABOVE_COUNTS
    if not high.any():
        return rng.poisson(counts).astype(np.float64)
    out = np.empty(counts.size)
    out[~high] = rng.poisson(counts[~high])
    out[high] = counts[high] + np.sqrt(counts[high]) * rng.standard_normal(int(high.sum()))
    return out


def noisy_pixels(data: np.ndarray, flux: float, gain: float, rng: np.random.Generator,
                 out: np.ndarray | None = None) -> np.ndarray:
    """``data * flux`` with the photon noise of its electrons (one realisation).

    The core of the template (pixels holding >= :data:`CORE_FRACTION` of the flux)
    is drawn pixel by pixel (Poisson, or its Gaussian limit from
    :data:`GAUSSIAN_ABOVE_COUNTS` electrons).  The wings, most of a stamp's pixels
    but little of its light, are drawn by Poisson splitting: their total
    N ~ Poisson(sum of their expected counts), each of the N electrons placed in
    wing pixel i with probability counts_i / sum -- the same distribution as
    independent Poisson draws, at a cost per electron instead of per pixel.  Wings
    expecting more than :data:`DENSE_WINGS_COUNTS` electrons per pixel on average
    (very bright sources) are drawn pixel by pixel too.

    Parameters
    ----------
    data : ndarray
        Unit-flux template (pixels sum to the in-stamp fraction of the light).
    flux : float
        Total flux [image units].
    gain : float
        Electrons per image unit (> 0).
    rng : numpy.random.Generator
        Consumed in this order: the core's Poisson draws, its normal draws, then
        the wings' total and the placements (or the wings' per-pixel draws).
    out : ndarray, optional
        A zeroed, C-contiguous float64 array of ``data.size`` elements to write the
        pixels into (e.g. a slice of one block for many stamps); a new one by default.

    Returns
    -------
    ndarray, float64
        ``out`` (or a new array) [image units] in the shape of ``data``; expected counts
        below 0 (numerical noise of the convolution, ~1e-17) count as 0.
    """
    data = np.asarray(data, dtype=np.float64)
    scale = float(flux) * float(gain)           # electrons per unit of the template
    w = _wings(data)
    size = data.size
    if out is None:
        out = np.zeros(size)
    elif out.size != size or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ValueError(f"noisy_pixels: out must be a C-contiguous float64 array of {size} "
                         f"elements, got {out.dtype} {out.shape}")
    else:
        out = out.reshape(size)
    # Only the pixels drawn are written (divided by the gain there): the untouched rest of a
    # large stamp stays in zero pages the system has not allocated.  The core's values are
    # > 0 (no clip needed) and, a positive scale being monotone in floating point, their
    # largest count is core_max * scale exactly: below the Gaussian switch, plain Poisson.
    sparse = w.wings_sum * scale <= DENSE_WINGS_COUNTS * (size - w.core.size)
    if KERNEL is not None and sparse and 0.0 <= w.core_max * scale < GAUSSIAN_ABOVE_COUNTS:
        KERNEL.stamp_shot_noise(rng.bit_generator, w.core, w.core_values, w.cum, scale, float(gain), out)
    else:
        _numpy_draws(data.ravel(), w, scale, gain, rng, out, sparse)
    return out.reshape(data.shape)


def _numpy_draws(flat, w: _Wings, scale: float, gain: float, rng, out, sparse: bool) -> None:
    """:func:`noisy_pixels`' draws with numpy into the flat zeroed ``out``: what the compiled
    kernel must equal (:func:`kernel_agrees`) and what runs where it does not apply."""
    counts = w.core_values * scale
    if w.core_max * scale < GAUSSIAN_ABOVE_COUNTS:
        out[w.core] = rng.poisson(counts) / gain
    else:
        out[w.core] = _per_pixel(counts, rng) / gain
    total = w.wings_sum * scale
    if not sparse:
        wings = np.ones(flat.size, dtype=bool)
        wings[w.core] = False
        out[wings] = _per_pixel(np.maximum(flat[wings], 0.0) * scale, rng) / gain
    elif total > 0.0:
        n = rng.poisson(total)
        # Placed in sorted order: each search then starts where the last ended, so a template's
        # cumulative sum (cold in the cache) is read mostly forward (~25 % less CPU); every
        # electron adds the same 1 / gain, so the order of the additions changes no pixel.
        u = rng.random(n) * w.cum[-1]
        u.sort()
        where = np.searchsorted(w.cum, u, side="right")
        np.minimum(where, flat.size - 1, out=where)     # u * cum[-1] rounded up to cum[-1]
        np.add.at(out, where, 1.0 / gain)


def kernel_agrees(kernel) -> bool:
    """Whether a compiled ``stamp_shot_noise`` gives :func:`noisy_pixels`' numpy draws bit for
    bit on a small stamp (both of numpy's Poisson algorithms, ~50 wing electrons) and leaves
    the stream where numpy leaves it."""
    # 20 x 20: 391 wing pixels holding 2 % of the light (~50 electrons) around 9 core pixels
    # expecting 0.3 to 250 electrons; one wing pixel is the convolution's -1e-17.
    template = np.full((20, 20), 5.0e-5)
    template[9:12, 9:12] = np.geomspace(1.2e-4, 0.1, 9).reshape(3, 3)
    template[0, 3] = -1.0e-17
    w = _wings(template)
    scale = 2500.0
    mine, theirs = np.random.default_rng(20261128), np.random.default_rng(20261128)
    got, want = np.zeros(template.size), np.zeros(template.size)
    kernel.stamp_shot_noise(mine.bit_generator, w.core, w.core_values, w.cum, scale, 2.5, got)
    _numpy_draws(template.ravel(), w, scale, 2.5, theirs, want, sparse=True)
    return bool(np.array_equal(got, want) and mine.random() == theirs.random())


#: The compiled shot-noise kernel (glaciar.engine.kernels), or None: not built, or built against
#: a numpy whose Poisson or uniform draws differ from the installed one's (then the numpy code,
#: which gives the rows of the installed numpy, runs instead).
KERNEL = KERNELS if KERNELS is not None and kernel_agrees(KERNELS) else None


def add_shot_noise(stamps: Sequence[tuple], gain: float, rng: np.random.Generator,
                   noisy: Sequence[bool] | None = None) -> list:
    """One band's stamps with shot noise, each fixed once (pre-multiplied).

    Parameters
    ----------
    stamps : sequence of (y0, x0, data, flux)
        Lazily scaled stamps as :class:`glaciar.engine.scene.Scene` takes them, in
        source order.
    gain : float
        The band's electrons per image unit.
    rng : numpy.random.Generator
        The band's stream (:func:`shot_noise_rng`).
    noisy : sequence of bool, optional
        False for stamps left as they are (no draw either): the stamps of sources
        fainter than ``FAINT_MAG_LIMIT``, whose stamps are skipped by default, so the
        noise of the others is the same whether such stamps are rendered or not.

    Returns
    -------
    list
        ``(y0, x0, pixels)`` for the noisy stamps (pixels a new array [image
        units]), the others unchanged.  A shared template is never modified.
    """
    drawn = [noisy is None or bool(noisy[k]) for k in range(len(stamps))]
    # One zeroed block for the band's noisy stamps, each written into its slice: fresh
    # zero pages a stamp never writes cost nothing, where an allocation per stamp (~190 kB,
    # a recycled heap chunk) is zeroed whole and faulted in each time (~2x the CPU of it).
    block = np.zeros(sum(np.size(st[2]) for st, d in zip(stamps, drawn) if d))
    out, start = [], 0
    for (y0, x0, data, flux), d in zip(stamps, drawn):
        if not d:
            out.append((y0, x0, data, flux))
            continue
        size = np.size(data)
        out.append((y0, x0, noisy_pixels(data, flux, gain, rng, out=block[start:start + size])))
        start += size
    return out
