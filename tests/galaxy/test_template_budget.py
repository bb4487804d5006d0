"""Memory of glaciar.galaxy.templates.TemplateCache across groups of tasks (begin_group).

A run's tasks come in chunks of one redshift; a redshift's stamps are rarely read once
the next starts.  Without groups the cache grew to its byte bound with every redshift's
stamps (issue 24: peak RSS at 1200^2).  These fail before begin_group existed.
"""
from __future__ import annotations

import numpy as np
import pytest

from glaciar.galaxy.psf import gaussian_psf
from glaciar.galaxy.templates import TEMPLATE_CACHE_BYTES, TemplateCache

#: Sub-pixel offsets of the positions used (x = 20 + k/8): 8 stamps per shape and band.
OFFSETS = [20.0 + k / 8 for k in range(8)]


@pytest.fixture(scope="module")
def psfs():
    return {"a": gaussian_psf(0.15, 0.08), "b": gaussian_psf(0.2, 0.08)}


def one_task(cache, sizes):
    """Every band, shape and offset of ``sizes`` (r_e [px]): a task's stamp calls."""
    for r in sizes:
        for band in ("a", "b"):
            for x in OFFSETS:
                cache.stamp(band, 1.0, 0.7, 30.0, r, x, 15.0)


def alone(psfs, sizes) -> int:
    """Bytes a fresh cache holds after one task of ``sizes`` (independent of groups)."""
    cache = TemplateCache(psfs)
    one_task(cache, sizes)
    return cache.stats.bytes


Z1_SIZES = (1.0, 1.5)      # r_e at the first redshift
Z2_SIZES = (0.9, 1.35)     # smaller at the next: other stamps


def test_default_bound_is_the_constant(psfs):
    assert TemplateCache(psfs).max_bytes == TEMPLATE_CACHE_BYTES


def test_new_group_replaces_the_previous_groups_stamps(psfs):
    w1, w2 = alone(psfs, Z1_SIZES), alone(psfs, Z2_SIZES)
    cache = TemplateCache(psfs)
    cache.begin_group(9.6)
    one_task(cache, Z1_SIZES)
    assert cache.stats.bytes == w1
    cache.begin_group(9.8)
    one_task(cache, Z2_SIZES)
    # Not both redshifts' stamps (w1 + w2, as an ungrouped cache of this bound holds).
    assert cache.stats.bytes <= max(w1, w2) < w1 + w2
    assert cache.stats.evictions > 0
    # Every stamp of the current group is still there: a second task renders nothing.
    conv = cache.stats.convolutions
    one_task(cache, Z2_SIZES)
    assert cache.stats.convolutions == conv


def test_same_group_again_keeps_every_hit(psfs):
    cache = TemplateCache(psfs)
    cache.begin_group(9.6)
    one_task(cache, Z1_SIZES)
    conv, hits = cache.stats.convolutions, cache.stats.hits
    cache.begin_group(9.6)               # a second chunk of the same redshift
    one_task(cache, Z1_SIZES)
    n_calls = len(Z1_SIZES) * 2 * len(OFFSETS)
    assert cache.stats.convolutions == conv
    assert cache.stats.hits == hits + n_calls
    assert cache.stats.evictions == 0


def test_stamps_read_again_by_the_new_group_are_kept(psfs):
    # Sizes that do not change with z: the next redshift reads the same stamps.
    cache = TemplateCache(psfs)
    cache.begin_group(9.6)
    one_task(cache, Z1_SIZES)
    cache.begin_group(9.8)
    one_task(cache, Z1_SIZES[:1] + Z2_SIZES)      # one shared size, two new ones
    conv = cache.stats.convolutions
    one_task(cache, Z1_SIZES[:1] + Z2_SIZES)
    assert cache.stats.convolutions == conv       # the shared size's stamps were not evicted


def test_bytes_never_exceed_the_bound(psfs):
    w1 = alone(psfs, Z1_SIZES[:1])
    cache = TemplateCache(psfs, max_bytes=w1)
    for g, sizes in enumerate((Z1_SIZES, Z2_SIZES, Z1_SIZES)):
        cache.begin_group(g)
        for r in sizes:
            for x in OFFSETS:
                cache.stamp("a", 1.0, 0.7, 30.0, r, x, 15.0)
                assert 0 < cache.stats.bytes <= w1
    # The bytes are those of the arrays held (a stamp's bytes: the array it returns).
    one = cache.stamp("a", 1.0, 0.7, 30.0, Z1_SIZES[1], OFFSETS[-1], 15.0).data.nbytes
    assert one <= cache.stats.bytes


def test_stamps_identical_with_and_without_groups(psfs):
    a, b = TemplateCache(psfs), TemplateCache(psfs, max_bytes=0)
    for g, sizes in enumerate((Z1_SIZES, Z2_SIZES, Z1_SIZES)):
        a.begin_group(g)
        for r in sizes:
            for x in OFFSETS:
                pa, pb = a.stamp("b", 4.0, 0.5, 60.0, r, x, 3.0), b.stamp("b", 4.0, 0.5, 60.0, r, x, 3.0)
                assert np.array_equal(pa.data, pb.data) and (pa.x0, pa.y0) == (pb.x0, pb.y0)
                assert pa.in_stamp_fraction == pb.in_stamp_fraction
