"""sep's detection scan reproduced in numpy (glaciar.engine.sepscan) against its loops written out."""
import numpy as np
import pytest


def _filter_loop(data, k):
    """sep's convolve() written out pixel by pixel: float32 sums in kernel row-major order,
    taps outside the image skipped."""
    H, W = data.shape
    ch, cw = k.shape
    out = np.zeros((H, W), dtype=np.float32)
    for y in range(H):
        for x in range(W):
            s = np.float32(0.0)
            for cy in range(ch):
                for cx in range(cw):
                    yy, xx = y + cy - ch // 2, x + cx - cw // 2
                    if 0 <= yy < H and 0 <= xx < W:
                        s = np.float32(s + np.float32(k[cy, cx] * data[yy, xx]))
            out[y, x] = s
    return out


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled kernel", "numpy"])
def test_sep_filter_equals_the_pixel_loop_bit_for_bit(compiled, monkeypatch):
    from glaciar.engine import sepscan
    from glaciar.engine.sepscan import sep_filter, sep_kernel

    if compiled and sepscan.KERNEL is None:
        pytest.skip("glaciar.engine.kernels is not built here (no C compiler at install)")
    if not compiled:
        monkeypatch.setattr(sepscan, "KERNEL", None)
    rng = np.random.default_rng(4)
    for shape, kshape in (((13, 17), (5, 5)), ((6, 4), (3, 3)), ((9, 11), (4, 3)), ((2, 7), (5, 5))):
        data = rng.normal(size=shape).astype(np.float32)
        kern = rng.uniform(-0.2, 1.0, size=kshape)
        got = sep_filter(data, kern)
        assert got.dtype == np.float32 and got.shape == shape and got.flags.c_contiguous
        assert got.tobytes() == _filter_loop(data, sep_kernel(kern)).tobytes()
