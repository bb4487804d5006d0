"""Lensing of injected sources, against analytic lenses and brute-force integrals."""
import math

import numpy as np
import pytest
from scipy.special import gamma as gamma_fn, gammaincinv

from glaciar.galaxy.lensing import (SISLens, convergence_shear_from_deflection, distance_ratio,
                                    jacobian, lensed_shape, magnification, source_plane_area)
from glaciar.galaxy.sersic import sersic_stamp


def test_sis_magnification_is_the_analytic_one():
    """SIS: mu = r / (r - theta_E), at any angle (negative inside the Einstein ring)."""
    lens = SISLens(theta_e=8.0, x0=1.5, y0=-2.0)
    rng = np.random.default_rng(1)
    r = rng.uniform(1.0, 60.0, 500)
    phi = rng.uniform(0, 2 * np.pi, 500)
    x, y = lens.x0 + r * np.cos(phi), lens.y0 + r * np.sin(phi)
    mu = magnification(*lens.convergence_shear(x, y))
    np.testing.assert_allclose(mu, r / (r - 8.0), rtol=1e-12)


def test_kappa_gamma_from_deflection_maps_match_the_analytic_lens():
    """Finite differences of an SIS + external shear deflection map: kappa and gamma to 1 %
    of kappa beyond 10 pixels from the centre (the documented (h/r)^2 error)."""
    lens = SISLens(theta_e=2.0, x0=0.013, y0=-0.021, gamma1_ext=0.05, gamma2_ext=-0.03)
    h = 0.06                                           # arcsec per pixel
    yy, xx = np.mgrid[-150:151, -150:151] * h
    k, g1, g2 = convergence_shear_from_deflection(*lens.deflection(xx, yy), pixel_scale=h)
    ka, g1a, g2a = lens.convergence_shear(xx, yy)
    r = np.hypot(xx - lens.x0, yy - lens.y0)
    inside = (r > 10 * h) & (np.abs(xx) < 148 * h) & (np.abs(yy) < 148 * h)
    for got, want in ((k, ka), (g1, g1a), (g2, g2a)):
        assert np.max(np.abs(got - want)[inside] / ka[inside]) < 0.01


def test_distance_ratio_against_comoving_distances():
    """Flat cosmology: D_ls / D_s = 1 - chi_l / chi_s; 0 in front of the lens."""
    from astropy.cosmology import Planck18

    zs = np.array([0.2, 0.308, 1.0, 6.0, 9.5])
    got = distance_ratio(0.308, zs, "Planck18")
    chi_l = Planck18.comoving_distance(0.308).value
    want = np.where(zs > 0.308, 1 - chi_l / Planck18.comoving_distance(zs).value, 0.0)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-12)


def _sersic_unit_flux(n, r_eff, q, pa_deg):
    """Unit-total-flux elliptical Sersic intensity I(x, y), written from its definition."""
    b = gammaincinv(2 * n, 0.5)
    norm = 2 * math.pi * q * r_eff ** 2 * n * math.exp(b) * b ** (-2 * n) * gamma_fn(2 * n)
    c, s = math.cos(math.radians(pa_deg)), math.sin(math.radians(pa_deg))

    def intensity(x, y):
        u, v = x * c + y * s, -x * s + y * c
        rr = np.sqrt(u ** 2 + (v / q) ** 2)
        return np.exp(-b * ((rr / r_eff) ** (1 / n) - 1)) / norm
    return intensity


LENS = dict(kappa=0.3, gamma1=0.15, gamma2=-0.1)


def test_lensed_stamp_is_the_source_seen_through_the_jacobian():
    """The stamp rendered from lensed_shape equals, pixel by pixel, the source's intensity
    at beta = A theta (surface brightness conserved), integrated by brute force; its total
    flux is |mu| times the intrinsic one to 1e-4."""
    n, r_e, q, pa = 1.0, 2.5, 0.7, 30.0
    shp = lensed_shape(r_e, q, pa, **LENS)
    mu = float(shp.magnification)
    assert mu == pytest.approx(1 / ((1 - 0.3) ** 2 - 0.15 ** 2 - 0.1 ** 2), rel=1e-12)
    stamp = sersic_stamp(n, float(shp.r_eff), float(shp.axis_ratio), float(shp.position_angle_deg),
                         shape=(121, 121), flux=abs(mu))
    src = _sersic_unit_flux(n, r_e, q, pa)
    a = jacobian(**LENS)
    sub = 12                                            # sub-pixels per pixel side
    off = (np.arange(sub) + 0.5) / sub - 0.5
    ty, tx = np.mgrid[0:121, 0:121] - 60.0
    ty = ty[:, :, None, None] + off[None, None, :, None]
    tx = tx[:, :, None, None] + off[None, None, None, :]
    bx, by = a[0, 0] * tx + a[0, 1] * ty, a[1, 0] * tx + a[1, 1] * ty
    brute = src(bx, by).mean(axis=(2, 3))
    assert np.max(np.abs(stamp - brute)) < 1e-4 * abs(mu)
    # Total flux: integrate the image-plane intensity over a wide, fine grid.
    g = np.arange(-400, 400) * 0.25 + 0.125
    gx, gy = np.meshgrid(g, g)
    total = src(a[0, 0] * gx + a[0, 1] * gy, a[1, 0] * gx + a[1, 1] * gy).sum() * 0.25 ** 2
    assert total == pytest.approx(abs(mu), rel=1e-4)


@pytest.mark.parametrize("lens", [LENS, dict(kappa=0.0, gamma1=0.0, gamma2=0.4),
                                  dict(kappa=0.6, gamma1=-0.5, gamma2=0.2)])
def test_second_moments_stretch_as_the_jacobian(lens):
    """Second moments of the rendered stamp: Q_image = A^-1 Q_source A^-T (axis ratio and
    stretch direction to 1 %), also for a negative-parity image (third case)."""
    n, r_e, q, pa = 0.5, 3.0, 0.8, 70.0
    shp = lensed_shape(r_e, q, pa, **lens)
    stamp = sersic_stamp(n, float(shp.r_eff), float(shp.axis_ratio), float(shp.position_angle_deg),
                         shape=(201, 201))
    yy, xx = np.mgrid[0:201, 0:201] - 100.0
    w = stamp / stamp.sum()
    qm = np.array([[np.sum(w * xx * xx), np.sum(w * xx * yy)],
                   [np.sum(w * xx * yy), np.sum(w * yy * yy)]])
    qm -= np.eye(2) / 12.0             # Sheppard: pixel integration adds 1/12 px^2 per axis
    c, s = math.cos(math.radians(pa)), math.sin(math.radians(pa))
    rot = np.array([[c, -s], [s, c]])
    q_src = rot @ np.diag([1.0, q ** 2]) @ rot.T
    ainv = np.linalg.inv(jacobian(**lens))
    q_img = ainv @ q_src @ ainv.T
    ev_m, vec_m = np.linalg.eigh(qm)
    ev_a, vec_a = np.linalg.eigh(q_img)
    assert math.sqrt(ev_m[0] / ev_m[1]) == pytest.approx(math.sqrt(ev_a[0] / ev_a[1]), rel=0.01)
    assert abs(vec_m[:, 1] @ vec_a[:, 1]) > math.cos(math.radians(0.5))
    # The stamp's major-axis direction is the one lensed_shape reports.
    d = math.radians(float(shp.position_angle_deg))
    assert abs(vec_a[0, 1] * math.cos(d) + vec_a[1, 1] * math.sin(d)) > 1 - 1e-9


def test_unlensed_shape_is_unchanged():
    shp = lensed_shape([1.0, 3.0], [0.4, 1.0], [10.0, 0.0], 0.0, 0.0, 0.0)
    np.testing.assert_allclose(shp.r_eff, [1.0, 3.0], rtol=1e-12)
    np.testing.assert_allclose(shp.axis_ratio, [0.4, 1.0], rtol=1e-12)
    assert shp.position_angle_deg[0] == pytest.approx(10.0, abs=1e-9)
    np.testing.assert_allclose(shp.magnification, 1.0)


def test_source_plane_area_behind_an_sis_is_the_analytic_one():
    """A square field of side 2L centred on an SIS: sum(pixel area / |mu|) = the integral of
    |1 - theta_E / r| over the square, 4 L^2 - 8 L theta_E asinh(1) + 2 pi theta_E^2."""
    lens = SISLens(theta_e=5.0)
    half, h = 30.0, 0.05
    g = np.arange(-half, half, h) + h / 2
    xx, yy = np.meshgrid(g, g)
    area = source_plane_area(magnification(*lens.convergence_shear(xx, yy)), h * h)
    want = 4 * half ** 2 - 8 * half * 5.0 * math.asinh(1.0) + 2 * math.pi * 5.0 ** 2
    assert area == pytest.approx(want, rel=0.01)
    # Unlensed: the image-plane area.
    assert source_plane_area(np.ones((10, 10)), 0.25) == pytest.approx(25.0, rel=1e-12)


def test_area_nodes_keep_the_source_plane_area_at_every_source_redshift():
    """Nodes of an SIS + shear field with two depth halves: the depth-binned areas add up to
    the footprint, and sum(area |mean 1/mu|) at D_ls/D_s = 0.6 and 0.9 equals the pixel sum
    of 1/|mu| (to 1e-3: only nodes that straddle the critical curve approximate it)."""
    from glaciar.galaxy.lensing import lens_area_nodes, node_inverse_magnification

    lens = SISLens(theta_e=5.0, gamma1_ext=0.05, gamma2_ext=0.02)
    g = np.arange(-30.0, 30.0, 0.1) + 0.05
    xx, yy = np.meshgrid(g, g)
    depth = np.where(xx < 0, 27.31, 28.07)
    depth[:5] = np.nan                                 # outside the footprint
    k, g1, g2 = lens.convergence_shear(xx, yy)
    nodes = lens_area_nodes(depth, k, g1, g2, 0.01 / 3600, depth_bin_mag=0.25, ratio_range=(0.6, 0.9))
    area = np.array(nodes["area_arcmin2"])
    assert area.sum() == pytest.approx(np.isfinite(depth).sum() * 0.01 / 3600, rel=1e-9)
    assert sorted(set(np.round(nodes["depth"], 6))) == [27.31, 28.07]
    ok = np.isfinite(depth)
    for r in (0.6, 0.9):
        want = np.abs(1 - 2 * r * k + r * r * (k * k - g1 * g1 - g2 * g2))[ok].sum() * 0.01 / 3600
        got = np.sum(area * np.abs(node_inverse_magnification(nodes, r)))
        assert got == pytest.approx(want, rel=1e-3)
    assert len(area) < 4000
