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
counts are small.

Randomness: each band's noise comes from its own stream, a child of the task's
``SeedSequence`` (:func:`shot_noise_rng`), never from the task's stream: the
task's draws (positions, shapes, ...) are the same with or without shot noise,
and a run without gains draws nothing.  Sources are drawn in their order, so a
task's noise does not depend on the worker, the order of tasks, resume, or on
which detection window (or mode) later reads the pixels.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

__all__ = ["GAUSSIAN_ABOVE_COUNTS", "SHOT_NOISE_STREAM_KEY", "shot_noise_gains", "shot_noise_rng",
           "noisy_pixels", "add_shot_noise"]

#: Pixels expecting at least this many electrons get the Gaussian limit of Poisson noise.
GAUSSIAN_ABOVE_COUNTS = 1.0e4

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


def noisy_pixels(data: np.ndarray, flux: float, gain: float, rng: np.random.Generator) -> np.ndarray:
    """``data * flux`` with the photon noise of its electrons (one realisation).

    Parameters
    ----------
    data : ndarray
        Unit-flux template (pixels sum to the in-stamp fraction of the light).
    flux : float
        Total flux [image units].
    gain : float
        Electrons per image unit (> 0).
    rng : numpy.random.Generator
        Consumed in pixel order: Poisson draws for the pixels below
        :data:`GAUSSIAN_ABOVE_COUNTS`, then normal draws for those above.

    Returns
    -------
    ndarray, float64
        New array [image units], shape of ``data``.
    """
    pix = np.asarray(data, dtype=np.float64) * float(flux)
    counts = np.maximum(pix * gain, 0.0)
    high = counts >= GAUSSIAN_ABOVE_COUNTS
    if not high.any():
        return rng.poisson(counts) / gain
    out = np.empty_like(pix)
    low = ~high
    out[low] = rng.poisson(counts[low]) / gain
    ph = pix[high]
    out[high] = ph + np.sqrt(ph / gain) * rng.standard_normal(ph.size)
    return out


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
    out = []
    for k, (y0, x0, data, flux) in enumerate(stamps):
        if noisy is not None and not noisy[k]:
            out.append((y0, x0, data, flux))
        else:
            out.append((y0, x0, noisy_pixels(data, flux, gain, rng)))
    return out
