"""Gravitational lensing of an injected source by a foreground cluster: local lens maps,
their scaling with source redshift, and the image of an elliptical Sersic source.

Conventions
-----------
Angles are in the image's pixel frame: ``x`` along array axis 1, ``y`` along axis 0,
position angles counter-clockwise from +x toward +y (as :func:`glaciar.galaxy.sersic.sersic_stamp`).
The shear components are relative to those axes: gamma1 > 0 stretches images along x
(``beta = A theta`` compresses x offsets), gamma2 > 0 along the diagonal x = y; an
isothermal sphere's images are stretched tangentially (gamma1 < 0 on the x axis).  The lens equation ``beta = theta - alpha(theta)`` has the Jacobian

    A = d beta / d theta = [[1 - kappa - gamma1,     -gamma2       ],
                            [    -gamma2,         1 - kappa + gamma1]]

(rows and columns in (x, y) order), magnification ``mu = 1 / det A =
1 / ((1 - kappa)^2 - gamma^2)``, negative for images of odd parity (between the critical
curves).  Public lens models (e.g. the Hubble Frontier Fields') give kappa and gamma for
``D_ls / D_s = 1``; at a source redshift ``z_s`` they are multiplied by
``D_ls(z_l, z_s) / D_s(z_s)`` (:func:`distance_ratio`).

The image of a source is exact for a lens that is linear across it (the Jacobian constant
over the source's extent): an elliptical isophote ``beta^T M_s beta = r^2`` maps to the
ellipse ``theta^T (A^T M_s A) theta = r^2``, so an elliptical Sersic profile stays an
elliptical Sersic profile of the same index with the same surface brightness, its
half-light ellipse the image of the source's (:func:`lensed_shape`), and its total flux
``|mu|`` times the intrinsic one.  Where kappa and gamma vary across a stamp the image is
the one of the Jacobian at the source's centre; the error grows with the stamp's size
over the scale on which the maps change (for a singular isothermal sphere, ~r_e / (2 r)
in the magnification at distance r from its centre).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["jacobian", "magnification", "distance_ratio", "convergence_shear_from_deflection",
           "lensed_shape", "LensedShape", "SISLens", "source_plane_area",
           "lens_area_nodes", "node_inverse_magnification",
           "LENS_SHIFT_BIN_MAG", "NODE_KEYS"]

#: Bin width of the magnification shift 2.5 log10|mu| when pixels are grouped into area nodes [mag].
LENS_SHIFT_BIN_MAG = 0.05
#: |2.5 log10 mu| beyond this (|mu| > 10^4, on a critical curve) falls in the last bin [mag].
MAX_SHIFT_MAG = 10.0
#: The columns of a field's lens area nodes (:func:`lens_area_nodes`).
NODE_KEYS = ("depth", "kappa", "gamma", "kappa2_minus_gamma2", "area_arcmin2")


def jacobian(kappa, gamma1, gamma2) -> np.ndarray:
    """The lensing Jacobian ``A = d beta / d theta``, shape ``(..., 2, 2)`` in (x, y) order.

    Parameters
    ----------
    kappa, gamma1, gamma2 : array_like
        Convergence and shear (dimensionless), broadcast together.
    """
    k, g1, g2 = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (kappa, gamma1, gamma2)))
    a = np.empty(k.shape + (2, 2))
    a[..., 0, 0] = 1.0 - k - g1
    a[..., 1, 1] = 1.0 - k + g1
    a[..., 0, 1] = a[..., 1, 0] = -g2
    return a


def magnification(kappa, gamma1, gamma2) -> np.ndarray:
    """Signed magnification ``1 / ((1 - kappa)^2 - gamma1^2 - gamma2^2)``.

    ``inf`` on a critical curve; negative for images of odd parity.
    """
    k, g1, g2 = (np.asarray(v, dtype=float) for v in (kappa, gamma1, gamma2))
    det = (1.0 - k) ** 2 - g1 ** 2 - g2 ** 2
    with np.errstate(divide="ignore"):
        return 1.0 / det


def distance_ratio(z_lens: float, z_source, cosmology="Planck18") -> np.ndarray:
    """``D_ls / D_s``: the factor that scales kappa and gamma normalised to ``D_ls/D_s = 1``.

    Parameters
    ----------
    z_lens : float
        Lens redshift.
    z_source : array_like
        Source redshift(s); 0 where ``z_source <= z_lens`` (no lensing).
    cosmology : str or astropy.cosmology.Cosmology
        A realisation name or instance (:func:`glaciar.galaxy.population.get_cosmology`).

    Returns
    -------
    ndarray
        The ratio of angular-diameter distances, in [0, 1).
    """
    from .population import get_cosmology

    cosmo = get_cosmology(cosmology)
    zs = np.atleast_1d(np.asarray(z_source, dtype=float))
    out = np.zeros(zs.shape)
    behind = zs > z_lens
    if behind.any():
        d_ls = cosmo.angular_diameter_distance(z_lens, zs[behind]).value
        d_s = cosmo.angular_diameter_distance(zs[behind]).value
        out[behind] = d_ls / d_s
    return out.reshape(np.shape(z_source))


def convergence_shear_from_deflection(alpha_x, alpha_y, pixel_scale: float = 1.0):
    """kappa, gamma1, gamma2 from deflection maps by second-order central differences.

    Parameters
    ----------
    alpha_x, alpha_y : ndarray, shape (ny, nx)
        Deflection along x (axis 1) and y (axis 0), in the angular unit of ``pixel_scale``
        (e.g. arcsec, with ``pixel_scale`` in arcsec per pixel).
    pixel_scale : float
        The maps' pixel size in the deflections' unit.

    Returns
    -------
    kappa, gamma1, gamma2 : ndarray, shape (ny, nx)
        ``kappa = (dax/dx + day/dy) / 2``, ``gamma1 = (dax/dx - day/dy) / 2``,
        ``gamma2 = (dax/dy + day/dx) / 2``.  Central differences inside, one-sided at the
        edges (first order there): the error is ~ h^2/6 times the deflection's third
        derivative (for a singular isothermal sphere of Einstein radius theta_E,
        ~ (h / r)^2 kappa at distance r: 0.3 % of kappa at r = 10 h).
    """
    ax, ay = (np.asarray(a, dtype=float) for a in (alpha_x, alpha_y))
    if ax.shape != ay.shape or ax.ndim != 2:
        raise ValueError(f"deflection maps must be 2-d and of one shape, got {ax.shape} and {ay.shape}")
    if min(ax.shape) < 3:
        raise ValueError(f"deflection maps must be at least 3x3 pixels, got {ax.shape}")
    h = float(pixel_scale)
    dax_dy, dax_dx = np.gradient(ax, h)
    day_dy, day_dx = np.gradient(ay, h)
    return (0.5 * (dax_dx + day_dy), 0.5 * (dax_dx - day_dy), 0.5 * (dax_dy + day_dx))


@dataclass(frozen=True)
class LensedShape:
    """An elliptical Sersic source's image under a locally linear lens.

    Attributes
    ----------
    r_eff : ndarray
        Semi-major-axis half-light radius of the image [the source's unit].
    axis_ratio : ndarray
        Its b/a, in (0, 1].
    position_angle_deg : ndarray
        Its major axis, degrees in [0, 180) counter-clockwise from +x toward +y.
    magnification : ndarray
        Signed ``mu``; the image's total flux is ``|mu|`` times the source's.
    """

    r_eff: np.ndarray
    axis_ratio: np.ndarray
    position_angle_deg: np.ndarray
    magnification: np.ndarray


def lensed_shape(r_eff, axis_ratio, position_angle_deg, kappa, gamma1, gamma2) -> LensedShape:
    """The half-light ellipse of a source's image: ``M_image = A^T M_source A``.

    Parameters
    ----------
    r_eff : array_like
        Source-plane semi-major-axis half-light radius (any angular unit, > 0).
    axis_ratio : array_like
        Source-plane b/a in (0, 1].
    position_angle_deg : array_like
        Source-plane position angle [deg], counter-clockwise from +x toward +y.
    kappa, gamma1, gamma2 : array_like
        The lens at the image's centre, scaled to the source's redshift.

    Returns
    -------
    LensedShape
        Exact for a lens linear across the source (see the module's docstring); the
        image's axis ratio may fall below what :func:`~glaciar.galaxy.sersic.sersic_stamp`
        renders (0.05) near a critical curve, and ``|mu|`` is infinite on one: callers
        flag those sources.
    """
    r, q, pa, k, g1, g2 = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (r_eff, axis_ratio, position_angle_deg,
                                                 kappa, gamma1, gamma2)))
    if np.any(~(r > 0)) or np.any(~((q > 0) & (q <= 1))):
        raise ValueError("lensed_shape: r_eff must be > 0 and axis_ratio in (0, 1]")
    phi = np.deg2rad(pa)
    c, s = np.cos(phi), np.sin(phi)
    # Source quadratic form M_s = R diag(1/a^2, 1/b^2) R^T with a = r_eff, b = q r_eff.
    ia, ib = 1.0 / r ** 2, 1.0 / (q * r) ** 2
    ms = np.empty(r.shape + (2, 2))
    ms[..., 0, 0] = ia * c * c + ib * s * s
    ms[..., 1, 1] = ia * s * s + ib * c * c
    ms[..., 0, 1] = ms[..., 1, 0] = (ia - ib) * c * s
    a = jacobian(k, g1, g2)
    mi = np.swapaxes(a, -1, -2) @ ms @ a
    # Eigenvalues of the symmetric 2x2 form in closed form (no per-source eigh call).
    p, t, u = mi[..., 0, 0], mi[..., 1, 1], mi[..., 0, 1]
    half_tr, root = 0.5 * (p + t), np.hypot(0.5 * (p - t), u)
    lam_min, lam_max = half_tr - root, half_tr + root
    with np.errstate(divide="ignore", invalid="ignore"):
        r_img = 1.0 / np.sqrt(lam_min)
        q_img = np.sqrt(lam_min / lam_max)
    # Major axis: the eigenvector of the smaller eigenvalue.
    pa_img = np.rad2deg(0.5 * np.arctan2(-2.0 * u, t - p)) % 180.0
    return LensedShape(r_img, q_img, pa_img, magnification(k, g1, g2))


def source_plane_area(magnification, pixel_area: float) -> float:
    """Source-plane area behind image-plane pixels: ``sum(pixel_area / |mu|)``.

    Parameters
    ----------
    magnification : array_like
        Signed magnification per image-plane pixel (non-finite values, i.e. on a critical
        curve, contribute 0).
    pixel_area : float
        One pixel's image-plane area (any unit; the result is in the same unit).

    Notes
    -----
    Exact for maps that are constant across each pixel; a region imaged several times
    counts once per image (this is the area surveyed per image, the term of V_eff).
    """
    mu = np.asarray(magnification, dtype=float)
    with np.errstate(divide="ignore"):
        inv = np.where(np.isfinite(mu) & (mu != 0), 1.0 / np.abs(mu), 0.0)
    return float(pixel_area * inv.sum())


def lens_area_nodes(depth, kappa, gamma1, gamma2, area_per_sample, *, depth_bin_mag: float,
                    ratio_range=(1.0, 1.0), shift_bin_mag: float = LENS_SHIFT_BIN_MAG) -> dict:
    """Group a field's pixels into (local depth, magnification) nodes for V_eff.

    V_eff behind a lens is a sum over image-plane area of ``A / |mu(z)|`` times the
    selection probability at the depth and the magnified magnitude ``m - 2.5 log10 |mu|``
    there; ``mu`` at a source redshift follows from kappa and |gamma| of the normalised
    model alone: ``det A = 1 / mu = 1 - 2 r kappa + r^2 (kappa^2 - |gamma|^2)`` with
    ``r = D_ls / D_s``.  Pixels are grouped by depth bin (the edges of
    :func:`glaciar.engine.depth.depth_area_histogram`), by image parity at both ends of
    ``ratio_range`` and by bins of ``2.5 log10 |mu|`` of width ``shift_bin_mag`` at both
    ends; each node carries its area and the area-weighted means of depth, kappa, |gamma|
    and ``kappa^2 - |gamma|^2``.

    Accuracy: ``det A`` is linear in kappa and ``kappa^2 - |gamma|^2``, so a node's mean
    ``1/mu`` at any r is exact (:func:`node_inverse_magnification`), and a node whose
    pixels keep one parity over the range gives the exact source-plane area there; only
    pixels that cross a critical curve inside the range are approximated (0.06 % of the
    area for an SIS with external shear, r = 0.6-0.9: tests/galaxy/test_lensing.py).  A
    node's magnification shift is within ~``shift_bin_mag`` / 2 of each of its pixels' at
    the range's ends.

    Parameters
    ----------
    depth : array_like
        Local depth per sample [AB mag], NaN outside the footprint (skipped).
    kappa, gamma1, gamma2 : array_like
        The normalised lens model (D_ls/D_s = 1) at the same samples.
    area_per_sample : float or array_like
        Image-plane area of each sample [arcmin^2].
    depth_bin_mag : float
        Depth bin width [mag] (edges at its integer multiples).
    ratio_range : (float, float)
        D_ls/D_s at the lowest and highest source redshift V_eff will integrate over.
    shift_bin_mag : float
        Bin width of ``2.5 log10 |mu|`` [mag].

    Returns
    -------
    dict
        Keys :data:`NODE_KEYS`: lists of floats (JSON-ready), one entry per non-empty node.
    """
    d, k, g1, g2 = (np.ravel(np.asarray(v, dtype=float)) for v in (depth, kappa, gamma1, gamma2))
    w = np.broadcast_to(np.asarray(area_per_sample, dtype=float), np.shape(depth)).ravel()
    if not (d.size == k.size == g1.size == g2.size):
        raise ValueError("lens_area_nodes: depth and the lens maps must have one size, got "
                         f"{d.size}, {k.size}, {g1.size}, {g2.size}")
    ok = np.isfinite(d)
    if np.any(~np.isfinite(k[ok] + g1[ok] + g2[ok])):
        raise ValueError("lens_area_nodes: the lens model is not finite everywhere in the footprint")
    d, k, g, w = d[ok], k[ok], np.hypot(g1[ok], g2[ok]), w[ok]
    if d.size == 0:
        return {key: [] for key in NODE_KEYS}
    s2 = k * k - g * g
    key = np.floor(d / depth_bin_mag).astype(np.int64)
    key -= key.min()
    for r in (float(v) for v in ratio_range):
        det = 1.0 - 2.0 * r * k + r * r * s2
        with np.errstate(divide="ignore"):
            shift = np.clip(-2.5 * np.log10(np.abs(det)), -MAX_SHIFT_MAG, MAX_SHIFT_MAG)
        cell = np.floor(shift / shift_bin_mag).astype(np.int64)
        n_cells = int(2 * MAX_SHIFT_MAG / shift_bin_mag) + 2
        key = (key * 2 + (det > 0)) * n_cells + (cell - cell.min())
    uniq, inv = np.unique(key, return_inverse=True)
    area = np.bincount(inv, weights=w)

    def mean(v):
        return np.bincount(inv, weights=w * v) / area
    return {"depth": mean(d).tolist(), "kappa": mean(k).tolist(), "gamma": mean(g).tolist(),
            "kappa2_minus_gamma2": mean(s2).tolist(), "area_arcmin2": area.tolist()}


def node_inverse_magnification(nodes: dict, ratio) -> np.ndarray:
    """Area-weighted mean ``1 / mu`` of each node (:func:`lens_area_nodes`) for sources at
    ``D_ls / D_s = ratio`` (array_like, broadcast as ``ratio[..., None]`` over the nodes).

    Signed; ``abs`` of it is the source-plane area per unit image-plane area.
    """
    r = np.asarray(ratio, dtype=float)[..., None]
    k = np.asarray(nodes["kappa"], dtype=float)
    s2 = np.asarray(nodes["kappa2_minus_gamma2"], dtype=float)
    return 1.0 - 2.0 * r * k + r * r * s2


@dataclass(frozen=True)
class SISLens:
    """A singular isothermal sphere plus an external shear: the analytic cluster lens.

    Parameters
    ----------
    theta_e : float
        Einstein radius for ``D_ls / D_s = 1`` [the unit of positions, e.g. arcsec].
    x0, y0 : float
        Centre [same unit].
    gamma1_ext, gamma2_ext : float
        Constant external shear (same axes as :mod:`glaciar.galaxy.lensing`).
    """

    theta_e: float
    x0: float = 0.0
    y0: float = 0.0
    gamma1_ext: float = 0.0
    gamma2_ext: float = 0.0

    def _offsets(self, x, y):
        dx = np.asarray(x, dtype=float) - self.x0
        dy = np.asarray(y, dtype=float) - self.y0
        return dx, dy, np.hypot(dx, dy)

    def deflection(self, x, y, scale: float = 1.0):
        """``(alpha_x, alpha_y)`` at (x, y), ``scale`` = D_ls/D_s (1: the normalised model).

        The SIS deflects by theta_E toward its centre; the external shear adds
        ``Gamma theta`` (its lensing potential ``(g1 (x^2 - y^2) + 2 g2 x y) / 2``).
        """
        dx, dy, r = self._offsets(x, y)
        with np.errstate(invalid="ignore", divide="ignore"):
            ux, uy = np.where(r > 0, dx / r, 0.0), np.where(r > 0, dy / r, 0.0)
        ax = self.theta_e * ux + self.gamma1_ext * dx + self.gamma2_ext * dy
        ay = self.theta_e * uy + self.gamma2_ext * dx - self.gamma1_ext * dy
        return scale * ax, scale * ay

    def convergence_shear(self, x, y, scale: float = 1.0):
        """Analytic ``(kappa, gamma1, gamma2)`` at (x, y): kappa = gamma_SIS = theta_E / (2 r),
        the SIS shear tangential (gamma1 = -gamma cos 2 phi, gamma2 = -gamma sin 2 phi)."""
        dx, dy, r = self._offsets(x, y)
        with np.errstate(divide="ignore", invalid="ignore"):
            kappa = self.theta_e / (2.0 * r)
            phi2 = 2.0 * np.arctan2(dy, dx)
        g1 = -kappa * np.cos(phi2) + self.gamma1_ext
        g2 = -kappa * np.sin(phi2) + self.gamma2_ext
        return scale * kappa, scale * g1, scale * g2

    def source_position(self, x, y, scale: float = 1.0):
        """The source-plane position ``beta = theta - alpha(theta)`` of an image at (x, y)."""
        ax, ay = self.deflection(x, y, scale)
        return np.asarray(x, dtype=float) - ax, np.asarray(y, dtype=float) - ay
