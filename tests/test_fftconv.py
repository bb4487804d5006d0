"""glaciar.fftconv.fftconvolve is scipy.signal.fftconvolve bit for bit, without its import."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.signal import fftconvolve as scipy_fftconvolve

from glaciar.fftconv import fftconvolve


@pytest.mark.parametrize("mode", ["full", "same"])
@pytest.mark.parametrize("shapes", [((13, 17), (5, 7)), ((40, 31), (41, 29)), ((3, 2), (9, 9)),
                                    ((64, 64), (33, 33))])
def test_same_bits_as_scipy(mode, shapes):
    rng = np.random.default_rng(sum(shapes[0] + shapes[1]))
    a, b = rng.normal(size=shapes[0]), rng.random(shapes[1])
    got, want = fftconvolve(a, b, mode=mode), scipy_fftconvolve(a, b, mode=mode)
    assert got.shape == want.shape and got.dtype == want.dtype
    assert got.tobytes() == want.tobytes()


@pytest.mark.parametrize("a_shape, b_shape, dtype", [((1, 9), (5, 5), float),   # a side of 1
                                                     ((6, 6), (3, 3), np.int64),
                                                     ((8, 7), (3, 4), np.float32)])
def test_other_inputs_same_as_scipy(a_shape, b_shape, dtype):
    rng = np.random.default_rng(5)
    a = (rng.random(a_shape) * 10).astype(dtype)
    b = (rng.random(b_shape) * 10).astype(dtype)
    for mode in ("full", "same", "valid") if a_shape[0] > 1 else ("full", "same"):
        got, want = fftconvolve(a, b, mode=mode), scipy_fftconvolve(a, b, mode=mode)
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()


def test_templates_and_depth_maps_do_not_import_scipy_signal():
    code = ("import sys, glaciar.galaxy.templates, glaciar.engine.depth, glaciar.execute; "
            "print(sorted(m for m in ('scipy.signal', 'scipy.stats') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
