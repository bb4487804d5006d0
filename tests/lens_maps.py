"""FITS lens maps of an analytic lens, written on a grid rotated or flipped relative to an
image (tests of glaciar.lensmaps and the lensed engine).

The lens is an SIS + external shear defined in the image's pixel frame (its shear along the
image's axes, lengths in image pixels).  A map pixel's value is the lens at the image
position its world coordinates fall on, with the shear tensor and the deflection vector
expressed along the map's own pixel axes (written here independently of glaciar.lensmaps).

Also a uniform mass sheet's lens nodes for a selection function (:func:`put_mass_sheet`),
the case with closed-form volumes and counts (tests of glaciar.inference.lensed).
"""
import math

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS


def lens_grid(image_header, shape, *, scale_arcsec=0.06, rotation_deg=0.0, flip=False,
              margin=8, crop=None):
    """A lens-grid WCS header covering an image (``shape`` = (ny, nx)) with ``margin`` pixels,
    its pixel axes rotated by ``rotation_deg`` and optionally flipped relative to the sky's;
    ``crop``: keep only this fraction of the grid's width (a map that does not cover)."""
    iw = WCS(image_header).celestial
    ny, nx = shape
    ra0, dec0 = iw.all_pix2world(0.5 * (nx - 1), 0.5 * (ny - 1), 0)
    t = math.radians(rotation_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    cd = scale_arcsec / 3600.0 * rot @ np.diag([-1.0, 1.0]) @ (np.diag([1.0, -1.0]) if flip else np.eye(2))
    half = int(math.ceil(math.hypot(nx, ny) / 2 * iw.proj_plane_pixel_scales()[0].value * 3600
                         / scale_arcsec)) + margin
    n = 2 * half + 1
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN", "DEC--TAN"
    h["CRVAL1"], h["CRVAL2"] = float(ra0), float(dec0)
    h["CRPIX1"], h["CRPIX2"] = half + 1.0, half + 1.0
    h["CD1_1"], h["CD1_2"], h["CD2_1"], h["CD2_2"] = cd[0, 0], cd[0, 1], cd[1, 0], cd[1, 1]
    nxl = n if crop is None else int(n * crop)
    return h, (n, nxl)


def map_values(lens, image_header, grid_header, grid_shape, image_scale_arcsec):
    """kappa, gamma1, gamma2 (map axes) and alpha_x, alpha_y (map axes, arcsec) on the grid."""
    iw, lw = WCS(image_header).celestial, WCS(grid_header).celestial
    ny, nx = grid_shape
    v, u = np.mgrid[0:ny, 0:nx].astype(float)
    ra, dec = lw.all_pix2world(u, v, 0)
    x, y = iw.all_world2pix(ra, dec, 0)
    k, g1, g2 = lens.convergence_shear(x, y)
    ax, ay = lens.deflection(x, y)
    # Orthogonal part of the map-pixel -> image-pixel matrix (CD_image^-1 CD_map).
    cdi = iw.pixel_scale_matrix
    cdl = lw.pixel_scale_matrix
    m = np.linalg.solve(cdi, cdl)
    q = m / math.sqrt(abs(np.linalg.det(m)))
    # Tensor: Gamma_map = Q^T Gamma_image Q; vector: alpha_map = Q^T alpha_image.
    gm = np.einsum("ji,...jk,kl->...il", q, np.stack([np.stack([g1, g2], -1),
                                                       np.stack([g2, -g1], -1)], -2), q)
    am = np.einsum("ji,...j->...i", q, np.stack([ax, ay], -1)) * image_scale_arcsec
    return k, gm[..., 0, 0], gm[..., 0, 1], am[..., 0], am[..., 1]


def write_maps(directory, field, lens, image_header, image_shape, image_scale_arcsec, *,
               kind="kappa", wcs=True, nan_at=None, **grid):
    """Write ``{field}_<key>.fits`` maps; return the model's config mapping (templates)."""
    gh, gshape = lens_grid(image_header, image_shape, **grid)
    full = (gshape[0], gshape[0])
    k, g1, g2, ax, ay = map_values(lens, image_header, gh, full, image_scale_arcsec)
    values = {"kappa": k, "gamma1": g1, "gamma2": g2} if kind == "kappa" else \
        {"alpha_x": ax, "alpha_y": ay}
    out = {"name": f"{kind}_maps"}
    for key, arr in values.items():
        arr = np.array(arr[:, :gshape[1]], dtype=np.float64)
        if nan_at is not None:
            iw, lw = WCS(image_header).celestial, WCS(gh).celestial
            u, v = lw.all_world2pix(*iw.all_pix2world(nan_at[0], nan_at[1], 0), 0)
            arr[int(round(float(v))) - 2:int(round(float(v))) + 3,
                int(round(float(u))) - 2:int(round(float(u))) + 3] = np.nan
        fits.PrimaryHDU(arr, header=gh if wcs else None).writeto(
            directory / f"{field}_{key}.fits", overwrite=True)
        out[key] = f"{directory}/{{field}}_{key}.fits"
    return out


def put_mass_sheet(sf, z_lens, kappa, area=800.0):
    """Give ``sf`` one lens model, "sheet": a uniform sheet of convergence ``kappa`` (no
    shear) over ``area`` [arcmin^2] at depth 27.5, lens at ``z_lens``; returns ``sf``."""
    from glaciar.galaxy.lensing import lens_area_nodes
    from glaciar.inference.lensed import LensNodes

    d = np.full((20, 20), 27.5)
    zero = np.zeros_like(d)
    nodes = lens_area_nodes(d, zero + kappa, zero, zero, area / 400, depth_bin_mag=0.05,
                            ratio_range=(0.8, 0.9))
    sf.lens_nodes = {"cl": {"sheet": LensNodes.from_dict("cl", "sheet", z_lens, nodes)}}
    return sf
