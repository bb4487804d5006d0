"""Tests for glaciar.galaxy.templates.TemplateCache."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, strategies as st

from scipy import signal

from glaciar.galaxy.psf import gaussian_psf, moffat_psf
from glaciar.galaxy.sed import mag_to_flux
from glaciar.galaxy.sersic import sersic_stamp, stamp_shape
from glaciar.galaxy.templates import PlacedStamp, TemplateCache

from renderer_box import (CHEAP_SETTINGS, STAMP_SUM_TOL, TEMPLATE_SIDE, ZEROPOINT, axis_ratio,
                          light_in_rectangle, magnitude, position_angle, r_eff, sersic_n)


@pytest.fixture(scope="module")
def psfs():
    return {"f125w": gaussian_psf(0.15, 0.08), "f160w": moffat_psf(0.18, 0.08, beta=3.0)}


def centroid_image(ps: PlacedStamp):
    yy, xx = np.indices(ps.data.shape)
    t = ps.data.sum()
    return (ps.data * xx).sum() / t + ps.x0, (ps.data * yy).sum() / t + ps.y0


def test_cached_equals_fresh_render_and_is_readonly(psfs):
    cache = TemplateCache(psfs)
    ps = cache.stamp("f160w", 2.0, 0.6, 35.0, 1.7, 50.25, 40.625)   # offsets +2/8, -3/8
    fresh = cache.render("f160w", 2.0, 0.6, 35.0, 1.7, 0.25, -0.375)
    assert ps.data.shape == fresh.shape
    assert np.abs(ps.data - fresh).max() <= 1e-12 * fresh.max()
    again = cache.stamp("f160w", 2.0, 0.6, 35.0, 1.7, 50.25, 40.625)
    assert again.data is ps.data
    assert cache.stats.hits == 1 and cache.stats.misses == 1
    assert not ps.data.flags.writeable
    with pytest.raises(ValueError):
        ps.data[0, 0] = 1.0


@pytest.mark.parametrize("n,r_eff", [(1.0, 0.5), (4.0, 0.5), (4.0, 1.5), (1.0, 3.0)])
def test_position_honoured(psfs, n, r_eff):
    cache = TemplateCache(psfs, subpixel=8)
    rng = np.random.default_rng(3)
    for x, y in [(100.0, 200.0), (100.5, 199.5)] + [tuple(rng.uniform(10, 90, 2)) for _ in range(3)]:
        ps = cache.stamp("f125w", n, 1.0, 0.0, r_eff, x, y)
        cx, cy = centroid_image(ps)
        assert abs(cx - x) <= 1 / 16 + 1e-6 and abs(cy - y) <= 1 / 16 + 1e-6


def test_exact_grid_positions_have_no_centroid_bias(psfs):
    # A symmetric cuspy compact source at a quantised position: only the
    # method's bias is left (rendering off-centre would give ~0.07 px here).
    cache = TemplateCache(psfs, subpixel=8)
    ps = cache.stamp("f160w", 4.0, 0.7, 20.0, 0.5, 30.375, 12.25)
    cx, cy = centroid_image(ps)
    assert abs(cx - 30.375) < 1e-3 and abs(cy - 12.25) < 1e-3


def test_flux_and_in_stamp_fraction(psfs):
    cache = TemplateCache(psfs, enclosed_fraction=0.995)
    for n, q, r in [(1.0, 0.4, 2.0), (4.0, 1.0, 1.0), (0.5, 0.8, 4.0)]:
        ps = cache.stamp("f125w", n, q, 70.0, r, 10.3, 20.9)
        assert ps.in_stamp_fraction == pytest.approx(ps.data.sum(), rel=1e-14)
        assert 0.995 - 1e-9 <= ps.in_stamp_fraction <= 1.0 + 1e-12
        # Full convolution with a unit-sum PSF keeps exactly the light of the raw
        # render (independent computation from the Sersic module).
        ny, nx = stamp_shape(n, r, q, 70.0, enclosed_fraction=0.995)
        raw = sersic_stamp(n, r, q, 70.0, shape=(ny + 2, nx + 2))
        assert ps.in_stamp_fraction == pytest.approx(raw.sum(), abs=1e-12)


def test_matches_sersic_convolved_with_psf_for_integer_position(psfs):
    """At an integer position the stamp is the centred render convolved with the PSF."""
    cache = TemplateCache(psfs)
    n, q, pa, r = 1.5, 0.5, 120.0, 2.2
    ps = cache.stamp("f125w", n, q, pa, r, 64.0, 33.0)
    ny, nx = stamp_shape(n, r, q, pa)
    raw = sersic_stamp(n, r, q, pa, shape=(ny + 2, nx + 2))
    ref = signal.convolve(raw, psfs["f125w"], mode="full", method="direct")
    np.testing.assert_allclose(ps.data, ref, rtol=0, atol=1e-13)
    # Raw centre (pixel (ny+1)/2, (nx+1)/2) plus PSF half-size lands on (33, 64).
    h = (psfs["f125w"].shape[0] - 1) // 2
    assert ps.y0 + (ny + 1) // 2 + h == 33 and ps.x0 + (nx + 1) // 2 + h == 64


def test_bands_share_one_render_and_key_canonicalisation(psfs):
    cache = TemplateCache(psfs)
    cache.stamp("f125w", 1.0, 0.5, 10.0, 2.0, 5.0, 5.0)
    cache.stamp("f160w", 1.0, 0.5, 10.0, 2.0, 5.0, 5.0)
    cache.stamp("f160w", 1.0, 0.5, 190.0, 2.0, 7.125, 5.0)   # PA + 180, other offset
    s = cache.stats
    assert s.renders == 1 and s.render_hits == 2 and s.convolutions == 3 and s.misses == 3
    # PA is irrelevant for a circle: same entry.
    a = cache.stamp("f125w", 1.0, 1.0, 0.0, 2.0, 5.0, 5.0)
    b = cache.stamp("f125w", 1.0, 1.0, 77.0, 2.0, 5.0, 5.0)
    assert a.data is b.data


def test_memory_bound_evicts(psfs):
    one = TemplateCache(psfs).stamp("f125w", 1.0, 1.0, 0.0, 2.0, 0.0, 0.0).data.nbytes
    cache = TemplateCache(psfs, max_bytes=6 * one)
    for i in range(12):
        cache.stamp("f125w", 1.0, 1.0, 0.0, 2.0 + 0.01 * i, 0.0, 0.0)
        assert cache.stats.bytes <= 6 * one
    s = cache.stats
    assert s.evictions > 0 and s.entries < 24
    # The most recent stamp is still cached; the first was evicted.
    cache.stamp("f125w", 1.0, 1.0, 0.0, 2.11, 0.0, 0.0)
    assert cache.stats.hits == 1
    renders = cache.stats.renders
    cache.stamp("f125w", 1.0, 1.0, 0.0, 2.0, 0.0, 0.0)
    assert cache.stats.renders == renders + 1


def test_quantisation_splits_half_pixels_consistently(psfs):
    cache = TemplateCache(psfs, subpixel=4)
    a = cache.stamp("f125w", 1.0, 1.0, 0.0, 1.0, 10.5, 3.0)
    b = cache.stamp("f125w", 1.0, 1.0, 0.0, 1.0, 10.49, 3.0)   # rounds to the same 1/4 px
    assert a.data is b.data and a.x0 == b.x0


def test_errors(psfs):
    with pytest.raises(ValueError, match="odd"):
        TemplateCache({"x": np.ones((4, 4))})
    with pytest.raises(ValueError, match="band 'x'.*NaN"):
        TemplateCache({"x": np.full((3, 3), np.nan)})
    cache = TemplateCache(psfs)
    with pytest.raises(KeyError, match="f200w"):
        cache.stamp("f200w", 1.0, 1.0, 0.0, 1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        cache.stamp("f125w", 1.0, 1.0, 0.0, 1.0, np.nan, 0.0)


# ------------------------------------------------------------------------------
# Fast kernels of the windowed measurement against independent computations.
# ------------------------------------------------------------------------------
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


# ------------------------------------------------------------------------------
# Property-based stress of the source renderer (issue 10, point 8): hypothesis draws over
# the parameter box of tests/renderer_box.py, against its independent references.
# ------------------------------------------------------------------------------
def _fitting_fraction(n, r, q, pa, frac):
    """``frac``, lowered (bisection, >= 0.5) until the raw template fits TEMPLATE_SIDE."""
    def fits(f):
        ny, nx = stamp_shape(n, r, q, pa, enclosed_fraction=f)
        return max(ny, nx) + 2 <= TEMPLATE_SIDE
    if fits(frac):
        return frac
    lo, hi = 0.5, frac
    assert fits(lo)
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


@CHEAP_SETTINGS
@given(n=sersic_n, r=r_eff, q=axis_ratio, pa=position_angle, frac=st.floats(0.5, 0.9999),
       x=st.floats(0.0, 500.0), y=st.floats(0.0, 500.0), fwhm=st.floats(1.0, 6.0), m=magnitude)
def test_template_reports_the_light_it_holds(n, r, q, pa, frac, x, y, fwhm, m):
    """The injection path (render, sub-pixel PSF shift, "full" convolution): the
    stamp is finite, its sum is the ``in_stamp_fraction`` it reports, that is the
    Sersic light in the raw render's rectangle (the PSF conserves flux) and at
    least the requested fraction; a source of magnitude m then carries
    flux(m) x that fraction.  Big profiles get a lower fraction so the render stays
    within TEMPLATE_SIDE (the shape rule at any size is the test above)."""
    frac = _fitting_fraction(n, r, q, pa, frac)
    flux = mag_to_flux(m, ZEROPOINT)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cache = TemplateCache({"b": gaussian_psf(fwhm * 0.06, 0.06)}, enclosed_fraction=frac)
        placed = cache.stamp("b", n, q, pa, r, x, y)
        injected = flux * placed.data
    assert np.all(np.isfinite(placed.data))
    # FFT round-off only (scipy.signal.fftconvolve: ~1e-15 of the peak)
    assert placed.data.min() >= -1e-13 * placed.data.max()
    assert placed.in_stamp_fraction == pytest.approx(placed.data.sum(), rel=1e-12)
    ny, nx = stamp_shape(n, r, q, pa, enclosed_fraction=frac)
    raw_light = light_in_rectangle(n, r, q, pa, ((nx + 1) / 2, (ny + 1) / 2), (ny + 2, nx + 2))
    assert abs(placed.in_stamp_fraction - raw_light) <= STAMP_SUM_TOL
    assert placed.in_stamp_fraction >= frac - STAMP_SUM_TOL
    assert injected.sum() == pytest.approx(flux * placed.in_stamp_fraction, rel=1e-12)
