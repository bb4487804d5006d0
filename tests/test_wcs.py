"""glaciar.wcs against astropy.wcs (an independent implementation of FITS WCS paper I)."""
import math

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from astropy.wcs.utils import proj_plane_pixel_area, proj_plane_pixel_scales

from glaciar.wcs import pixel_axis_scales_arcsec, pixel_scale_arcsec, pixel_scale_matrix_arcsec


def _celestial(**cards):
    h = fits.Header({"NAXIS": 2, "NAXIS1": 10, "NAXIS2": 10, "CTYPE1": "RA---TAN",
                     "CTYPE2": "DEC--TAN", "CRVAL1": 150.0, "CRVAL2": 2.0, "CRPIX1": 5.0,
                     "CRPIX2": 5.0})
    h.update(cards)
    return h


def _rotated_cd(scale_deg, angle_deg, skew=1.0):
    a = math.radians(angle_deg)
    return {"CD1_1": -scale_deg * math.cos(a), "CD1_2": scale_deg * math.sin(a) * skew,
            "CD2_1": scale_deg * math.sin(a), "CD2_2": scale_deg * math.cos(a)}


@pytest.mark.parametrize("cards", [
    _rotated_cd(0.06 / 3600, 0.0), _rotated_cd(0.06 / 3600, 37.0),
    _rotated_cd(0.03 / 3600, 123.0, skew=1.02),
    {"CDELT1": -1.0, "CDELT2": 1.0, "PC1_1": 0.13 / 3600, "PC2_2": 0.13 / 3600},   # drizzle
    {"CDELT1": -0.04 / 3600, "CDELT2": 0.04 / 3600, "PC1_1": 0.8, "PC1_2": -0.6,
     "PC2_1": 0.6, "PC2_2": 0.8},
])
def test_scales_match_astropy(cards):
    h = _celestial(**cards)
    w = WCS(h).celestial
    ref_sides = proj_plane_pixel_scales(w) * 3600.0
    ref_side = math.sqrt(proj_plane_pixel_area(w)) * 3600.0
    assert np.allclose(pixel_axis_scales_arcsec(h), ref_sides, rtol=1e-12)
    assert pixel_scale_arcsec(h) == pytest.approx(ref_side, rel=1e-12)


def test_units_pixscale_and_absence():
    h = _celestial(CDELT1=-0.06, CDELT2=0.06, CUNIT1="arcsec", CUNIT2="arcsec")
    assert pixel_scale_arcsec(h) == pytest.approx(0.06, rel=1e-12)
    assert pixel_scale_arcsec(fits.Header({"PIXSCALE": 0.0311})) == 0.0311
    assert pixel_scale_arcsec(fits.Header({"CDELT1": -1 / 60, "CUNIT1": "arcmin"})) \
        == pytest.approx(1.0)
    assert pixel_scale_matrix_arcsec(fits.Header({"NAXIS": 2})) is None
    assert pixel_axis_scales_arcsec(fits.Header({"NAXIS": 2})) is None
