"""Pixel scales from FITS headers: the one reader for science images and PSF files."""
from __future__ import annotations

import math

import numpy as np

__all__ = ["pixel_scale_matrix_arcsec", "pixel_scale_arcsec", "pixel_axis_scales_arcsec"]

#: CUNITn values understood, in arcsec per unit (FITS WCS default: degrees).
_UNITS = {"deg": 3600.0, "degree": 3600.0, "degrees": 3600.0, "arcmin": 60.0,
          "arcminutes": 60.0, "arcsec": 1.0, "arcseconds": 1.0}


def pixel_scale_matrix_arcsec(header) -> np.ndarray | None:
    """The 2x2 linear pixel → sky matrix [arcsec / pixel], or None when the header has none.

    ``PIXSCALE`` [arcsec] (Tiny Tim PSFs), else the CD matrix, else ``CDELT``
    x ``PC`` (FITS WCS paper I): CDELTi scales the rows of PC, and drizzled
    headers often carry CDELT = 1 with the scale in PC, so both are needed.
    Units are degrees unless ``CUNIT1`` says arcmin or arcsec.
    """
    if header.get("PIXSCALE") is not None:
        p = float(header["PIXSCALE"])
        return np.array([[p, 0.0], [0.0, p]])
    cunit = str(header.get("CUNIT1", "deg") or "deg").strip().lower()
    unit = _UNITS.get(cunit, 3600.0)
    if any(k in header for k in ("CD1_1", "CD1_2", "CD2_1", "CD2_2")):
        cd = np.array([[header.get("CD1_1", 0.0), header.get("CD1_2", 0.0)],
                       [header.get("CD2_1", 0.0), header.get("CD2_2", 0.0)]], dtype=float)
    elif "CDELT1" in header:
        pc = np.array([[header.get("PC1_1", 1.0), header.get("PC1_2", 0.0)],
                       [header.get("PC2_1", 0.0), header.get("PC2_2", 1.0)]], dtype=float)
        cdelt = np.array([header["CDELT1"], header.get("CDELT2", header["CDELT1"])], dtype=float)
        cd = cdelt[:, None] * pc
    else:
        return None
    return cd * unit


def pixel_axis_scales_arcsec(header) -> tuple[float, float] | None:
    """Sky lengths of the pixel's x and y sides [arcsec] (column norms), or None."""
    m = pixel_scale_matrix_arcsec(header)
    if m is None:
        return None
    sx, sy = np.sqrt((m ** 2).sum(axis=0))
    return float(sx), float(sy)


def pixel_scale_arcsec(header) -> float | None:
    """Pixel scale [arcsec / pixel] as the side of the square pixel of equal area, or None.

    sqrt(|det M|) of :func:`pixel_scale_matrix_arcsec`; equal to the side for
    square pixels whatever their rotation.  Not checked for plausibility.
    """
    if header.get("PIXSCALE") is not None:
        return float(header["PIXSCALE"])          # exactly as written
    m = pixel_scale_matrix_arcsec(header)
    return None if m is None else math.sqrt(abs(float(np.linalg.det(m))))
