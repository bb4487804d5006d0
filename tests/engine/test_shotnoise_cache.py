"""Bookkeeping of the shot-noise core/wings splits (glaciar.engine.shotnoise).

The splits leave with their templates, so when the template cache lets a redshift's
stamps go (TemplateCache.begin_group) the splits go too: a run holds one redshift's
of each, not every redshift's up to WINGS_CACHE_BYTES.  Fails before begin_group and
wings_cache_info existed.
"""
from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest

from glaciar.engine import shotnoise
from glaciar.engine.shotnoise import CORE_FRACTION, noisy_pixels, wings_cache_info
from glaciar.galaxy.psf import gaussian_psf
from glaciar.galaxy.templates import TemplateCache

OFFSETS = [20.0 + k / 8 for k in range(8)]


def split_bytes(data: np.ndarray) -> int:
    """Bytes of a template's split, counted here: int64 core indices and float64 core values,
    + float64 cumulative sum."""
    return 16 * int(np.count_nonzero(data.ravel() >= CORE_FRACTION)) + 8 * data.size


def noisy_task(cache, sizes, rng):
    held = {}
    for r in sizes:
        for x in OFFSETS:
            data = cache.stamp("a", 1.0, 0.7, 30.0, r, x, 15.0).data
            noisy_pixels(data, 500.0, 2.0, rng)
            held[id(data)] = data
    return held


@pytest.fixture()
def empty_wings():
    gc.collect()
    before = wings_cache_info()
    yield before


def test_splits_leave_with_the_previous_redshifts_stamps(empty_wings):
    n0, b0 = empty_wings
    cache = TemplateCache({"a": gaussian_psf(0.15, 0.08)})
    rng = np.random.default_rng(1)
    cache.begin_group(9.6)
    first = noisy_task(cache, (1.0, 1.5), rng)
    n1, b1 = wings_cache_info()
    assert (n1 - n0, b1 - b0) == (len(first), sum(split_bytes(d) for d in first.values()))
    refs = [weakref.ref(d) for d in first.values()]
    del first
    cache.begin_group(9.8)
    second = noisy_task(cache, (0.9, 1.35), rng)
    gc.collect()
    alive = [r() for r in refs if r() is not None]
    # The first redshift's stamps the cache let go took their splits with them.
    assert 0 < len(alive) < len(refs)
    n2, b2 = wings_cache_info()
    assert n2 - n0 == len(alive) + len(second)
    assert b2 - b0 == sum(split_bytes(d) for d in alive + list(second.values()))


def test_splits_within_their_bound(monkeypatch, empty_wings):
    cache = TemplateCache({"a": gaussian_psf(0.15, 0.08)})
    one = split_bytes(cache.stamp("a", 1.0, 0.7, 30.0, 1.0, 20.0, 15.0).data)
    # The bound alone, whatever other tests in this process left cached: the oldest splits
    # (theirs first) make way, so at most three of this test's 8 templates keep theirs.
    monkeypatch.setattr(shotnoise, "WINGS_CACHE_BYTES", 3 * one)
    held = noisy_task(cache, (1.0,), np.random.default_rng(2))   # 8 templates, all alive
    n, b = wings_cache_info()
    assert len(held) == 8 and b <= 3 * one and 1 <= n <= 3
