"""Fast kernels of the windowed measurement against independent computations.

Each vectorised replacement of a per-object Python loop is compared here with
the straightforward computation it replaced (scipy, or a loop written out).
"""
import numpy as np
from scipy import ndimage

from glaciar.engine.canvas import label_boxes


def test_label_boxes_equal_find_objects():
    rng = np.random.default_rng(1)
    for shape, frac in (((157, 211), 0.08), ((40, 3), 0.5), ((1, 50), 0.3), ((64, 64), 0.0)):
        mask = rng.random(shape) < frac
        comp, n = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
        cb = label_boxes(comp, n)
        assert cb.shape == (n + 1, 4) and cb.dtype == np.int64
        assert np.all(cb[0] == 0)
        for c, sl in enumerate(ndimage.find_objects(comp), start=1):
            assert tuple(cb[c]) == (sl[0].start, sl[0].stop, sl[1].start, sl[1].stop)


def _stamp_ctx(templates, x, y, rms=1.0, shape=(200, 200)):
    from types import SimpleNamespace

    from glaciar.engine.detect import DetectionParams
    return SimpleNamespace(x=np.asarray(x, float), y=np.asarray(y, float), shape=shape,
                           det_rms=np.full(shape, rms), params=DetectionParams(), templates=templates,
                           margin=DetectionParams().filter_halfwidth + 1)


def test_stamp_half_sizes_follow_the_gaussian_width():
    """A bright circular Gaussian of sigma s: the above-threshold second moments give a -> s
    (the part below threshold carries a negligible share of the weight), so the
    predicted half-size is ceil(6 s + slack) + margin."""
    from glaciar.engine import windows as W

    h = 40
    yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
    out = []
    for s in (1.5, 3.0, 5.0):
        g = np.exp(-(xx ** 2 + yy ** 2) / (2 * s * s))
        g /= g.sum()
        out.append((100 - h, 100 - h, g, 1e9))
    ctx = _stamp_ctx(out + [None, (100 - h, 100 - h, g, 1e-9)], [100.0] * 5, [100.0] * 5)
    half = W.stamp_half_sizes(ctx)
    for k, s in enumerate((1.5, 3.0, 5.0)):
        lo = int(np.ceil(6 * 0.99 * s + W._STAMP_SLACK)) + ctx.margin
        hi = int(np.ceil(6 * s + W._STAMP_SLACK)) + ctx.margin
        assert lo <= half[k] <= hi
    assert half[3] == 0 and half[4] == 0          # no template; nothing above threshold


def test_initial_windows_hold_the_predicted_half_size():
    from glaciar.engine.detect import DetectionParams
    from glaciar.engine.windows import initial_windows

    params = DetectionParams()
    x = np.array([100.0, 100.0, 3.0])
    y = np.array([100.0, 150.0, 3.0])
    win = initial_windows(x, y, (400, 400), params, 3, 3, own_half=np.array([0, 35, 35]))
    r = params.initial_window // 2
    assert tuple(win[0]) == (100 - r, 101 + r, 100 - r, 101 + r)
    assert tuple(win[1]) == (150 - 35, 186, 100 - 35, 136)
    assert tuple(win[2]) == (0, 39, 0, 39)         # clipped to the image


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


def test_sep_filter_equals_the_pixel_loop_bit_for_bit():
    from glaciar.engine.sepscan import sep_filter, sep_kernel

    rng = np.random.default_rng(4)
    for shape, kshape in (((13, 17), (5, 5)), ((6, 4), (3, 3)), ((9, 11), (4, 3)), ((2, 7), (5, 5))):
        data = rng.normal(size=shape).astype(np.float32)
        kern = rng.uniform(-0.2, 1.0, size=kshape)
        got = sep_filter(data, kern)
        assert got.dtype == np.float32 and got.shape == shape and got.flags.c_contiguous
        assert np.array_equal(got, _filter_loop(data, sep_kernel(kern)))


def test_pack_windows_places_disjoint_rectangles_with_gaps():
    from glaciar.engine.canvas import pack_windows

    rng = np.random.default_rng(7)
    for k, gap in ((1, 3), (7, 2), (100, 3), (60, 4)):
        h = rng.integers(5, 80, k)
        w = rng.integers(5, 80, k)
        oy, ox, shape = pack_windows(h, w, gap)
        # every rectangle, grown by the gap, inside the canvas and disjoint from the others
        occ = np.zeros(shape, dtype=np.int64)
        for i in range(k):
            assert oy[i] >= gap and ox[i] >= gap
            assert oy[i] + h[i] + gap <= shape[0] and ox[i] + w[i] + gap <= shape[1]
            occ[oy[i]:oy[i] + h[i] + gap, ox[i]:ox[i] + w[i] + gap] += 1
        assert occ.max() == 1
        # no worse than one shelf row of the widest width per rectangle
        assert shape[0] * shape[1] <= ((h + gap).max() + gap) * (np.sum(w + gap) + gap)


def test_resample_matrix_equals_a_fresh_spline_through_the_cumulative():
    """The cached spline per input size gives the matrix a spline built on the spot gives."""
    from scipy.interpolate import CubicSpline

    from glaciar.galaxy.psf import _resample_matrix

    rng = np.random.default_rng(3)
    for n in (5, 17, 41, 17):
        new_edges = np.sort(rng.uniform(-3.0, n + 3.0, n + 1))
        edges = np.arange(-2.5, n + 2.5)
        cum = np.zeros((edges.size, n))
        cum[3:3 + n] = np.tril(np.ones((n, n)))
        cum[3 + n:] = 1.0
        ref = np.diff(CubicSpline(edges, cum, axis=0, bc_type="clamped")(np.clip(new_edges, edges[0], edges[-1])),
                      axis=0)
        assert np.array_equal(_resample_matrix(n, new_edges), ref)


def test_template_convolution_with_a_kept_raw_transform_equals_fftconvolve():
    """The template cache reuses a raw stamp's FFT across PSF offsets: bit for bit
    scipy.signal.fftconvolve(raw, psf, "full"), the first time and from the kept transform."""
    from scipy.signal import fftconvolve

    from glaciar.galaxy.templates import TemplateCache

    rng = np.random.default_rng(5)
    psf0 = rng.random((15, 15))
    cache = TemplateCache({"b": psf0 / psf0.sum()})
    for raw_shape, psf_shape in (((23, 23), (15, 15)), ((57, 41), (15, 15)), ((57, 41), (21, 19))):
        raw = rng.random(raw_shape)
        for _ in range(2):
            psf = rng.random(psf_shape)
            got = cache._convolve(raw, psf, ("raw", raw_shape))
            assert np.array_equal(got, fftconvolve(raw, psf, mode="full"))
