"""FFT convolution of 2-d real arrays without importing :mod:`scipy.signal`.

``scipy.signal`` imports ``scipy.stats`` (~0.4 s of CPU and ~18 MB in every process
that renders a template or measures a depth map; measured with everything else
``glaciar simulate`` imports already loaded).  :func:`fftconvolve` takes
``scipy.signal.fftconvolve``'s own steps for real 2-d inputs -- the same
``scipy.fft`` transforms of the same padded shapes, the same product and inverse,
the same slice -- so its results are the same bits (tests/test_fftconv.py); any
other input goes to ``scipy.signal.fftconvolve`` itself.
"""
from __future__ import annotations

import numpy as np
from scipy import fft as sp_fft

__all__ = ["fftconvolve"]


def fftconvolve(in1, in2, mode: str = "full") -> np.ndarray:
    """``scipy.signal.fftconvolve(in1, in2, mode)``, bit for bit.

    Parameters
    ----------
    in1, in2 : array_like
        2-d real floating-point arrays (any other input, or a side of length 1 in
        either, which scipy multiplies by broadcasting, is handed to scipy).
    mode : {"full", "same"}
        "full": the whole convolution, shape ``in1.shape + in2.shape - 1``; "same": its
        centre, of ``in1``'s shape ("valid" is handed to scipy).

    Returns
    -------
    numpy.ndarray
        A new array.
    """
    a, b = np.asarray(in1), np.asarray(in2)
    if (mode not in ("full", "same") or a.ndim != 2 or b.ndim != 2
            or a.dtype.kind != "f" or b.dtype.kind != "f" or min(a.shape + b.shape) <= 1):
        from scipy.signal import fftconvolve as scipy_fftconvolve

        return scipy_fftconvolve(a, b, mode=mode)
    full = [a.shape[k] + b.shape[k] - 1 for k in range(2)]
    fshape = [sp_fft.next_fast_len(n, True) for n in full]
    ret = sp_fft.irfftn(sp_fft.rfftn(a, fshape, axes=[0, 1]) * sp_fft.rfftn(b, fshape, axes=[0, 1]),
                        fshape, axes=[0, 1])[:full[0], :full[1]]
    if mode == "same":          # the centre of the full convolution, as scipy's _centered
        y0, x0 = (full[0] - a.shape[0]) // 2, (full[1] - a.shape[1]) // 2
        ret = ret[y0:y0 + a.shape[0], x0:x0 + a.shape[1]]
    return ret.copy()
