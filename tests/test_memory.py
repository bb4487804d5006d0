"""glaciar.memory.release_memory: what a finished run lets go before its summaries."""
from __future__ import annotations

import gc

import numpy as np

from glaciar.engine.shotnoise import noisy_pixels, wings_cache_info
from glaciar.fieldprep import shared_template_cache
from glaciar.galaxy.psf import gaussian_psf
from glaciar.memory import release_memory


def test_release_drops_the_shared_templates_and_their_splits():
    psfs = {"a": gaussian_psf(0.15, 0.08)}
    # Other tests in this process may have filled the shared cache: start without it.
    release_memory()
    gc.collect()
    n0, b0 = wings_cache_info()
    cache = shared_template_cache(psfs, 0.995)
    assert shared_template_cache(psfs, 0.995) is cache          # kept between fields
    rng = np.random.default_rng(3)
    for k in range(4):
        noisy_pixels(cache.stamp("a", 1.0, 0.7, 30.0, 1.2, 10.0 + k / 8, 5.0).data, 300.0, 2.0, rng)
    assert wings_cache_info()[0] == n0 + 4
    del cache
    release_memory()
    assert wings_cache_info() == (n0, b0)                         # the splits left with them
    fresh = shared_template_cache(psfs, 0.995)
    assert fresh.stats.entries == 0 and fresh.stats.convolutions == 0
