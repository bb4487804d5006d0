"""Tests for glaciar.galaxy.sersic.

Accuracy is held against integrations written here, independently of the
module: the profile, its normalisation and b_n (Brent root of the defining
equation) are re-implemented below, and pixels are integrated with adaptive
QUADPACK (scipy.integrate) at tolerances far below the asserted ones:

* a pixel holding the profile centre is integrated in polar coordinates about
  the centre in the *pixel* frame, split at the four corner angles, with the
  radius substituted as r = R(theta) u^(4n) so that r^(1/n) = R^(1/n) u^4 and
  the cusp becomes a smooth polynomial in u;
* any other pixel is integrated with dblquad in Cartesian coordinates, split
  at the centre's x and y lines when they cross it;
* the light inside a stamp rectangle is 1 - (light outside), the outside
  being, in polar coordinates about the centre, an angular quad of a radial
  quad from the rectangle's edge to infinity in t = b_n (r e(theta)/r_eff)^(1/n),
  where the integrand t^(2n-1) e^-t decays exponentially.

The module instead integrates the analytic enclosed fraction along pixel
edges in the circularised frame, so the two share no code and no formulation.
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, strategies as st
from scipy import integrate, optimize, special

from glaciar.galaxy.sed import mag_to_flux
from glaciar.galaxy.sersic import (MAX_STAMP_PIXELS, N_MAX, enclosed_fraction, radius_enclosing,
                                   sersic_bn, sersic_intensity, sersic_stamp, stamp_shape)

from renderer_box import (CHEAP_SETTINGS, RENDER_SIDE, R_EFF_MAX, STAMP_SUM_TOL, ZEROPOINT,
                          axis_ratio, light_in_rectangle, magnitude, odd_cap, offset,
                          position_angle, r_eff, sersic_n)

DEFAULT_TOL = 1e-9          # the module's stated default accuracy (fraction of flux)


# ---------------------------------------------------------------------------
# independent reference
# ---------------------------------------------------------------------------
def ref_bn(n):
    return optimize.brentq(lambda b: special.gammainc(2 * n, b) - 0.5,
                           1e-6, 4 * n + 2, xtol=1e-15, rtol=1e-15)


class RefProfile:
    """Unit-flux elliptical Sersic profile, pixel-frame coordinates."""

    def __init__(self, n, r_eff, q, pa_deg, x0, y0):
        self.n, self.re, self.q, self.x0, self.y0 = n, r_eff, q, x0, y0
        self.b = ref_bn(n)
        self.c = math.cos(math.radians(pa_deg))
        self.s = math.sin(math.radians(pa_deg))
        total_over_ie = (2 * math.pi * q * r_eff ** 2 * n * math.exp(self.b)
                         * math.gamma(2 * n) / self.b ** (2 * n))
        self.ie = 1.0 / total_over_ie

    def ell_radius(self, dx, dy):
        xp = dx * self.c + dy * self.s
        yp = (-dx * self.s + dy * self.c) / self.q
        return math.hypot(xp, yp)

    def __call__(self, x, y):
        r = self.ell_radius(x - self.x0, y - self.y0)
        return self.ie * math.exp(-self.b * ((r / self.re) ** (1 / self.n) - 1))

    def _polar_setup(self, xlo, xhi, ylo, yhi):
        corners = [(xhi, yhi), (xlo, yhi), (xlo, ylo), (xhi, ylo)]
        angles = sorted(math.atan2(cy - self.y0, cx - self.x0) for cx, cy in corners)

        def boundary(t):            # distance from the centre to the rectangle edge
            ct, st = math.cos(t), math.sin(t)
            lim = []
            if ct > 0:
                lim.append((xhi - self.x0) / ct)
            if ct < 0:
                lim.append((xlo - self.x0) / ct)
            if st > 0:
                lim.append((yhi - self.y0) / st)
            if st < 0:
                lim.append((ylo - self.y0) / st)
            return min(lim)

        edges = angles + [angles[0] + 2 * math.pi]
        return boundary, list(zip(edges[:-1], edges[1:]))

    def pixel_with_centre(self, ix, iy):
        m = 4 * self.n
        boundary, pieces = self._polar_setup(ix - 0.5, ix + 0.5, iy - 0.5, iy + 0.5)

        def radial(t):
            rt = boundary(t)
            e = self.ell_radius(math.cos(t), math.sin(t))
            k = self.b * (rt * e / self.re) ** (1 / self.n)

            def g(u):
                if u == 0:
                    return 0.0
                return (self.ie * math.exp(self.b - k * u ** (m / self.n))
                        * rt * rt * m * u ** (2 * m - 1))
            return integrate.quad(g, 0, 1, epsabs=1e-14, epsrel=1e-12, limit=200)[0]

        return sum(integrate.quad(radial, a, b, epsabs=1e-13, epsrel=1e-11, limit=200)[0]
                   for a, b in pieces)

    def pixel(self, ix, iy):
        if abs(ix - self.x0) <= 0.5 and abs(iy - self.y0) <= 0.5:
            return self.pixel_with_centre(ix, iy)
        xs = [ix - 0.5, ix + 0.5]
        ys = [iy - 0.5, iy + 0.5]
        if xs[0] < self.x0 < xs[1]:
            xs.insert(1, self.x0)
        if ys[0] < self.y0 < ys[1]:
            ys.insert(1, self.y0)
        total = 0.0
        for xa, xb in zip(xs[:-1], xs[1:]):
            for ya, yb in zip(ys[:-1], ys[1:]):
                total += integrate.dblquad(lambda y, x: self(x, y), xa, xb, ya, yb,
                                           epsabs=1e-13, epsrel=1e-11)[0]
        return total

    def outside_light(self, xlo, xhi, ylo, yhi):
        boundary, pieces = self._polar_setup(xlo, xhi, ylo, yhi)
        n, b = self.n, self.b

        # I r dr with t = b (r e / r_eff)^(1/n):
        #   I r dr = I_e e^b (r_eff/e)^2 n b^(-2n) t^(2n-1) e^(-t) dt
        def radial(t):
            e = self.ell_radius(math.cos(t), math.sin(t))
            t_edge = b * (boundary(t) * e / self.re) ** (1 / n)
            pref = self.ie * math.exp(b) * (self.re / e) ** 2 * n * b ** (-2 * n)
            tail = integrate.quad(lambda v: math.exp(-v + (2 * n - 1) * math.log(v)),
                                  t_edge, np.inf, epsabs=1e-14, epsrel=1e-12, limit=200)[0]
            return pref * tail

        return sum(integrate.quad(radial, a, b_, epsabs=1e-13, epsrel=1e-11, limit=200)[0]
                   for a, b_ in pieces)


# ---------------------------------------------------------------------------
# b_n and enclosed light
# ---------------------------------------------------------------------------
def test_bn_known_values():
    # Ciotti & Bertin (1999) quote b_1 = 1.678347, b_4 = 7.669249
    assert sersic_bn(1.0) == pytest.approx(1.678347, abs=1e-6)
    assert sersic_bn(4.0) == pytest.approx(7.669249, abs=1e-6)


@pytest.mark.parametrize("n", [0.2, 0.5, 0.7, 1.0, 2.5, 4.0, 8.0, 10.0])
def test_bn_solves_defining_equation(n):
    b = sersic_bn(n)
    assert special.gammainc(2 * n, b) == pytest.approx(0.5, abs=1e-14)
    assert b == pytest.approx(ref_bn(n), rel=1e-13)
    if n >= 1:
        # asymptotic series (Ciotti & Bertin 1999), error O(n^-3) < 1e-5 here
        series = 2 * n - 1 / 3 + 4 / (405 * n) + 46 / (25515 * n ** 2)
        assert b == pytest.approx(series, abs=1e-5)


def test_bn_accepts_arrays():
    ns = np.array([0.5, 1.0, 4.0])
    out = sersic_bn(ns)
    assert out.shape == (3,)
    assert np.allclose(out, [ref_bn(v) for v in ns], rtol=1e-13)
    # n = 0.5 is a Gaussian: P(1, b) = 1 - e^-b = 1/2
    assert out[0] == pytest.approx(math.log(2), rel=1e-14)


@pytest.mark.parametrize("n", [0.5, 1.0, 4.0, 8.0])
@pytest.mark.parametrize("radius", [0.1, 1.0, 3.0, 20.0])
def test_enclosed_fraction_matches_radial_quadrature(n, radius):
    # round profile with r_eff = 1: fraction = 2 pi int_0^R I(r) r dr
    p = RefProfile(n, 1.0, 1.0, 0.0, 0.0, 0.0)
    # substitute r = R u^(4n) to smooth the cusp (see module docstring)
    m = 4 * n
    g = lambda u: (p(radius * u ** m, 0.0) * radius * radius * m * u ** (2 * m - 1)) if u > 0 else 0.0
    direct = 2 * math.pi * integrate.quad(g, 0, 1, epsabs=1e-14, epsrel=1e-12, limit=200)[0]
    assert enclosed_fraction(n, radius) == pytest.approx(direct, abs=1e-11)
    if radius == 1.0:
        assert enclosed_fraction(n, radius) == pytest.approx(0.5, abs=1e-14)


@pytest.mark.parametrize("n", [0.2, 1.0, 4.0, 10.0])
def test_radius_enclosing_inverts_enclosed_fraction(n):
    fracs = np.array([0.01, 0.3, 0.5, 0.9, 0.995, 0.9999])
    radii = radius_enclosing(n, fracs)
    assert np.allclose(enclosed_fraction(n, radii), fracs, rtol=0, atol=1e-12)
    assert radius_enclosing(n, 0.5) == pytest.approx(1.0, rel=1e-12)


# ---------------------------------------------------------------------------
# intensity normalisation
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("n,q,pa", [(0.5, 1.0, 0.0), (1.0, 0.3, 20.0), (4.0, 0.7, -65.0)])
def test_intensity_matches_reference_and_normalisation(n, q, pa):
    r_eff = 2.3
    p = RefProfile(n, r_eff, q, pa, 1.0, -2.0)
    xs = np.array([1.0, 3.0, -4.0, 10.0])
    ys = np.array([-2.0, 0.5, 2.0, -7.0])
    got = sersic_intensity(n, r_eff, xs, ys, q, pa, center=(1.0, -2.0), flux=2.0)
    assert np.allclose(got, [2 * p(x, y) for x, y in zip(xs, ys)], rtol=1e-12, atol=0)
    # I_e on the major axis at r_eff = 1 / total
    phi = math.radians(pa)
    at_re = sersic_intensity(n, r_eff, 1.0 + r_eff * math.cos(phi),
                             -2.0 + r_eff * math.sin(phi), q, pa, center=(1.0, -2.0))
    assert at_re == pytest.approx(p.ie, rel=1e-12)


# ---------------------------------------------------------------------------
# pixel accuracy against adaptive 2-D quadrature
# ---------------------------------------------------------------------------
CENTER = (7.3, 6.85)                      # sub-pixel offset, inside pixel (7, 7)
PIXELS = [(7, 7), (8, 7), (6, 7), (7, 6), (8, 8), (10, 7), (9, 3), (0, 14)]   # (ix, iy)
CASES = [(n, re, q, pa) for n in (0.5, 1.0, 2.0, 4.0, 8.0) for re in (0.3, 1.0, 3.0, 10.0)
         for q, pa in ((1.0, 0.0), (0.2, 30.0))]
# the extremes of the supported range
CASES += [(0.2, 0.3, 0.05, 60.0), (10.0, 0.3, 0.05, 10.0), (10.0, 0.1, 1.0, 0.0), (0.2, 5.0, 0.5, 45.0)]


@pytest.mark.parametrize("n,r_eff,q,pa", CASES)
def test_pixels_match_adaptive_quadrature(n, r_eff, q, pa):
    stamp = sersic_stamp(n, r_eff, q, pa, shape=(15, 15), center=CENTER)
    cheap = sersic_stamp(n, r_eff, q, pa, shape=(15, 15), center=CENTER, tolerance=1e-5)
    ref = RefProfile(n, r_eff, q, pa, *CENTER)
    iy, ix = np.unravel_index(np.argmax(stamp), stamp.shape)
    pixels = PIXELS + ([(ix, iy)] if (ix, iy) not in PIXELS else [])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        expected = np.array([ref.pixel(x, y) for x, y in pixels])
    got = np.array([stamp[y, x] for x, y in pixels])
    got_cheap = np.array([cheap[y, x] for x, y in pixels])
    assert np.max(np.abs(got - expected)) < DEFAULT_TOL
    assert np.max(np.abs(got_cheap - expected)) < 1e-5


@pytest.mark.parametrize("n,r_eff,q,pa,center", [
    (1.0, 1.0, 0.7, 30.0, (4.3, 5.1)),       # integer 2n: closed-form Q
    (0.35, 0.3, 0.2, 60.0, (7.3, 6.85)),     # 2n = 0.7: scipy gammainc/gammaincc
    (4.0, 2.0, 1.0, 0.0, (7.5, 7.0)),        # centre on a grid line: many panels per edge
    (8.0, 0.3, 0.05, 10.0, (7.3, 6.85)),
])
def test_small_and_large_batch_layouts_agree(monkeypatch, n, r_eff, q, pa, center):
    # Small batches evaluate all quadrature nodes as one flat array, large ones
    # group panels by order; the pixel tests above see only the flat layout, so
    # hold the grouped one to it (same nodes and weights: round-off level).
    import glaciar.galaxy.sersic as sersic
    flat = sersic_stamp(n, r_eff, q, pa, shape=(15, 15), center=center)
    monkeypatch.setattr(sersic, "_FLAT_MAX_NODES", 0)
    grouped = sersic_stamp(n, r_eff, q, pa, shape=(15, 15), center=center)
    assert np.allclose(grouped, flat, rtol=0, atol=1e-15)


@pytest.mark.parametrize("n,r_eff,q,pa", CASES)
def test_stamp_sum_is_light_inside_rectangle(n, r_eff, q, pa):
    ny, nx = 21, 25
    center = (12.3, 9.6)
    stamp = sersic_stamp(n, r_eff, q, pa, shape=(ny, nx), center=center, flux=1.0)
    ref = RefProfile(n, r_eff, q, pa, *center)
    inside = 1.0 - ref.outside_light(-0.5, nx - 0.5, -0.5, ny - 0.5)
    assert stamp.sum() == pytest.approx(inside, abs=1e-9)
    assert np.all(stamp >= 0)


# ---------------------------------------------------------------------------
# invariants
# ---------------------------------------------------------------------------
def test_flux_scales_linearly():
    a = sersic_stamp(4.0, 1.3, 0.6, 25.0, shape=(21, 21))
    b = sersic_stamp(4.0, 1.3, 0.6, 25.0, shape=(21, 21), flux=37.5)
    assert np.allclose(b, 37.5 * a, rtol=1e-14, atol=0)


@pytest.mark.parametrize("n,r_eff,q,pa", [(1.0, 2.0, 0.4, 20.0), (4.0, 0.3, 0.7, 65.0)])
def test_rotation_symmetries(n, r_eff, q, pa):
    shape = (17, 17)
    s = sersic_stamp(n, r_eff, q, pa, shape=shape)
    # +90 deg: the profile at (x, y) is the old one at (y, -x) about the centre,
    # i.e. new[c + j, c + i] = old[c - i, c + j]
    r90 = sersic_stamp(n, r_eff, q, pa + 90.0, shape=shape)
    c = 8
    jj, ii = np.mgrid[-c:c + 1, -c:c + 1]
    assert np.allclose(r90[c + jj, c + ii], s[c - ii, c + jj], rtol=0, atol=1e-14)
    # reflection about y = x: PA -> 90 - PA is the transpose
    assert np.allclose(sersic_stamp(n, r_eff, q, 90.0 - pa, shape=shape), s.T, rtol=0, atol=1e-14)
    # reflection about the x axis: PA -> -PA flips axis 0
    assert np.allclose(sersic_stamp(n, r_eff, q, -pa, shape=shape), s[::-1, :], rtol=0, atol=1e-14)
    # a half turn changes nothing
    assert np.allclose(sersic_stamp(n, r_eff, q, pa + 180.0, shape=shape), s, rtol=0, atol=1e-14)
    # the major axis lies along PA: with PA = 0 the x profile is wider
    s0 = sersic_stamp(n, r_eff, q, 0.0, shape=shape)
    assert s0[c, c + 3] > s0[c + 3, c]


def test_mirror_symmetry_at_default_centre():
    s = sersic_stamp(2.0, 1.7, 0.5, 0.0, shape=(15, 19))
    assert np.allclose(s, s[::-1, :], rtol=0, atol=1e-15)
    assert np.allclose(s, s[:, ::-1], rtol=0, atol=1e-15)


def test_integer_centre_shift_is_array_shift():
    big = sersic_stamp(4.0, 0.8, 0.6, 35.0, shape=(31, 31), center=(16.25, 13.6))
    ref = sersic_stamp(4.0, 0.8, 0.6, 35.0, shape=(31, 31), center=(15.25, 15.6))
    # moving the centre by (+1, -2) pixels moves the image by the same amount
    assert np.allclose(big[1:29, 1:], ref[3:31, :30], rtol=0, atol=1e-14)


@pytest.mark.parametrize("n", [0.5, 4.0, 8.0])
def test_centre_on_pixel_edge_and_corner(n):
    # centre on the line x = 7.5 between columns 7 and 8: mirror image about it
    s = sersic_stamp(n, 0.3, 1.0, 0.0, shape=(15, 15), center=(7.5, 7.0))
    assert np.allclose(s[:, 8:], s[:, 7::-1][:, :7], rtol=0, atol=1e-14)
    assert s[7, 7] == pytest.approx(s[7, 8], abs=1e-14)
    # centre on a pixel corner: the four pixels around it are equal
    c = sersic_stamp(n, 0.3, 1.0, 0.0, shape=(15, 15), center=(7.5, 7.5))
    four = [c[7, 7], c[7, 8], c[8, 7], c[8, 8]]
    assert np.ptp(four) < 1e-14
    # and the cusp sitting on a corner of the pixel is integrated correctly
    ref = RefProfile(n, 0.3, 1.0, 0.0, 7.5, 7.5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        assert c[7, 7] == pytest.approx(ref.pixel(7, 7), abs=DEFAULT_TOL)


def test_sub_pixel_shift_moves_light():
    s0 = sersic_stamp(1.0, 1.0, 1.0, 0.0, shape=(11, 11))
    s1 = sersic_stamp(1.0, 1.0, 1.0, 0.0, shape=(11, 11), center=(5.4, 5.0))
    assert s1[5, 6] > s0[5, 6] and s1[5, 4] < s0[5, 4]
    # First moment follows the centre.  Pixel-centre moments are biased by the
    # light's asymmetry within pixels, except for a well-sampled Gaussian
    # (n = 0.5; sigma = r_eff / sqrt(2 ln 2) = 4.2 px), where the bias is
    # ~exp(-2 pi^2 sigma^2) and the 81 px stamp truncates < 1e-20 of the light.
    big = sersic_stamp(0.5, 5.0, 1.0, 0.0, shape=(81, 81), center=(40.4, 39.8))
    ys, xs = np.mgrid[0:81, 0:81]
    assert (big * xs).sum() / big.sum() == pytest.approx(40.4, abs=1e-9)
    assert (big * ys).sum() / big.sum() == pytest.approx(39.8, abs=1e-9)


# ---------------------------------------------------------------------------
# stamp shape
# ---------------------------------------------------------------------------
def _brute_shape(n, r_eff, q, pa, frac):
    a = radius_enclosing(n, frac) * r_eff
    t = np.linspace(0, 2 * np.pi, 400001)
    phi = math.radians(pa)
    x = a * np.cos(t) * math.cos(phi) - q * a * np.sin(t) * math.sin(phi)
    y = a * np.cos(t) * math.sin(phi) + q * a * np.sin(t) * math.cos(phi)
    # the ellipse must fit for a centre up to 1/2 px off the central pixel centre
    mx = math.ceil(np.abs(x).max() - 1e-9)
    my = math.ceil(np.abs(y).max() - 1e-9)
    return 2 * my + 1, 2 * mx + 1


@pytest.mark.parametrize("n,r_eff,q,pa", [(1.0, 1.3, 1.0, 0.0), (4.0, 0.5, 0.3, 30.0),
                                          (2.0, 3.0, 0.7, 110.0), (0.5, 0.2, 0.05, 90.0)])
def test_stamp_shape_is_smallest_holding_ellipse(n, r_eff, q, pa):
    shape = stamp_shape(n, r_eff, q, pa, enclosed_fraction=0.995)
    assert shape == _brute_shape(n, r_eff, q, pa, 0.995)
    assert all(v % 2 == 1 for v in shape)


@pytest.mark.parametrize("n,r_eff,q,pa", [(1.0, 1.3, 1.0, 0.0), (4.0, 0.5, 0.3, 30.0),
                                          (0.5, 2.0, 0.5, 60.0)])
def test_default_stamp_holds_requested_light(n, r_eff, q, pa):
    shape = stamp_shape(n, r_eff, q, pa, enclosed_fraction=0.99)
    ny, nx = shape
    for dx, dy in [(0.0, 0.0), (0.5, 0.5), (-0.5, 0.3), (0.2, -0.5)]:
        center = ((nx - 1) / 2 + dx, (ny - 1) / 2 + dy)
        s = sersic_stamp(n, r_eff, q, pa, center=center, enclosed_fraction=0.99)
        assert s.shape == shape
        assert s.sum() >= 0.99


# ---------------------------------------------------------------------------
# input validation
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs,match", [
    (dict(n=0.1), "Sersic index n"),
    (dict(n=10.5), "Sersic index n"),
    (dict(r_eff=0.0), "r_eff"),
    (dict(r_eff=np.nan), "r_eff"),
    (dict(axis_ratio=0.01), "axis_ratio"),
    (dict(axis_ratio=1.2), "axis_ratio"),
    (dict(position_angle=np.inf), "position_angle"),
    (dict(shape=(10, 11)), "odd positive"),
    (dict(shape=(0, 11)), "odd positive"),
    (dict(shape=(11,)), "odd positive"),
    (dict(center=(1.0,)), "center"),
    (dict(tolerance=0.0), "tolerance"),
    (dict(enclosed_fraction=1.0), "enclosed_fraction"),
])
def test_stamp_rejects_bad_input(kwargs, match):
    args = dict(n=1.0, r_eff=1.0, axis_ratio=1.0, position_angle=0.0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        sersic_stamp(args.pop("n"), args.pop("r_eff"), args.pop("axis_ratio"),
                     args.pop("position_angle"), **args)


def test_helpers_reject_bad_input():
    with pytest.raises(ValueError, match="Sersic index n"):
        sersic_bn([1.0, 12.0])
    with pytest.raises(ValueError, match="radius_over_r_eff"):
        enclosed_fraction(1.0, -1.0)
    with pytest.raises(ValueError, match="fraction"):
        radius_enclosing(1.0, 0.0)
    with pytest.raises(ValueError, match="axis_ratio"):
        stamp_shape(1.0, 1.0, axis_ratio=0.0)


# ------------------------------------------------------------------------------
# Property-based stress of the source renderer (issue 10, point 8): hypothesis draws over
# the parameter box of tests/renderer_box.py, against its independent references.
#
# Sersic stamps
# ------------------------------------------------------------------------------
@CHEAP_SETTINGS
@given(n=sersic_n, r=r_eff, q=axis_ratio, pa=position_angle, dx=offset, dy=offset, m=magnitude)
def test_stamp_sum_is_flux_times_light_in_its_rectangle(n, r, q, pa, dx, dy, m):
    """Any profile, any sub-pixel centre: pixels finite and >= 0, and their sum is
    flux x (light inside the rectangle) to the documented tolerance."""
    flux = mag_to_flux(m, ZEROPOINT)
    ny, nx = stamp_shape(n, r, q, pa)
    shape = (odd_cap(ny, RENDER_SIDE), odd_cap(nx, RENDER_SIDE))
    center = ((shape[1] - 1) / 2 + dx, (shape[0] - 1) / 2 + dy)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        stamp = sersic_stamp(n, r, q, pa, shape=shape, center=center, flux=flux)
    assert stamp.shape == shape
    assert np.all(np.isfinite(stamp)) and np.all(stamp >= 0)
    inside = light_in_rectangle(n, r, q, pa, center, shape)
    assert abs(stamp.sum() / flux - inside) <= STAMP_SUM_TOL
    assert stamp.sum() <= flux * (1 + 1e-12)


@CHEAP_SETTINGS
@given(n=sersic_n, r=r_eff, q=axis_ratio, pa=position_angle,
       frac=st.floats(0.5, 0.9999), corner=st.sampled_from([(-0.5, -0.5), (-0.5, 0.5), (0.5, -0.5),
                                                            (0.5, 0.5)]))
def test_default_stamp_shape_holds_requested_light(n, r, q, pa, frac, corner):
    """stamp_shape's promise over the whole box, checked by the reference without
    rendering: even with the centre at a corner of the central pixel, the rectangle
    holds at least ``enclosed_fraction``.  Stamps beyond MAX_STAMP_PIXELS are
    refused with a ValueError (before anything is allocated)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ny, nx = stamp_shape(n, r, q, pa, enclosed_fraction=frac)
    assert ny % 2 == 1 and nx % 2 == 1
    center = ((nx - 1) / 2 + corner[0], (ny - 1) / 2 + corner[1])
    assert light_in_rectangle(n, r, q, pa, center, (ny, nx)) >= frac - 1e-12
    if ny * nx > MAX_STAMP_PIXELS:
        with pytest.raises(ValueError, match="exceeds MAX_STAMP_PIXELS"):
            sersic_stamp(n, r, q, pa, enclosed_fraction=frac)


def test_largest_default_stamps_are_refused_clearly():
    """The corner of the box the issue names: n = 10, r_eff = 100 px at 99.5 %."""
    assert stamp_shape(N_MAX, R_EFF_MAX) == (39699, 39699)
    with pytest.raises(ValueError, match=r"39699 x 39699 px .* exceeds MAX_STAMP_PIXELS"):
        sersic_stamp(N_MAX, R_EFF_MAX)
