"""Lens models of a field read and evaluated at the field's image pixels (``survey.lens``).

A :class:`FieldLens` gives, for one field and one lens model, the convergence and shear
normalised to ``D_ls / D_s = 1`` at image pixel positions, with the shear components
along the image's pixel axes (:mod:`glaciar.galaxy.lensing`'s conventions):

* FITS maps (``kappa``/``gamma1``/``gamma2`` or ``alpha_x``/``alpha_y``): each image
  position goes to world coordinates through the detection image's WCS and to the lens
  grid through the map's WCS; the maps are interpolated bilinearly there (deflections are
  first turned into kappa and gamma on the lens grid by central differences).  The shear
  is a spin-2 tensor: ``Gamma_image = Q Gamma_map Q^T`` with ``Q`` the orthogonal part of
  the local map-pixel -> image-pixel matrix, so a rotated grid turns gamma by twice the
  angle and a flipped one changes the sign of gamma2.  ``Q`` is taken once per field, at
  the centre of the image (exact for grids related by a linear map; the TAN projections
  of a cluster field differ from that by < 1e-6).
* The analytic SIS + external shear (``analytic``): evaluated in image pixels, its centre
  from the image's WCS or given in pixels.

Only the part of a map over the field (plus a margin) is kept, as float64.  Errors name
the file: a map without a celestial WCS, one that does not cover the footprint, NaN
inside the footprint, maps of one model on different grids (:func:`check_field_lens`).
The set-up's area nodes (:func:`field_lens_nodes`) are computed on a strided sample of
the footprint by row blocks (at most :data:`NODE_SAMPLES` samples).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .galaxy.lensing import SISLens, convergence_shear_from_deflection, distance_ratio, lens_area_nodes

__all__ = ["FieldLens", "field_lens", "lens_map_paths", "check_field_lens", "field_lens_nodes",
           "lens_z_range", "NODE_SAMPLES", "LensMapError"]

#: Samples of the footprint the area nodes and the coverage check read (a stride is chosen
#: so that at most this many are taken): ~1 s of WCS transforms.
NODE_SAMPLES = 1 << 21
#: Lens-grid pixels kept beyond the field's extent on each side (bilinear needs 1).
CROP_MARGIN = 3
#: The analytic SIS is read at no less than this distance from its centre [image pixels].
SIS_CORE_PIX = 0.5
#: Rows of image positions transformed at once.
ROW_BLOCK = 256


class LensMapError(ValueError):
    """A lens map is unusable; the message names the file."""


def lens_map_paths(cfg, field: str) -> dict:
    """``{model name: {map key: Path}}`` of the FITS lens models of a field (empty for the
    analytic lens or no lens)."""
    lens = cfg.survey.lens
    if lens is None:
        return {}
    out = {}
    for m in lens.models:
        paths = {}
        for key in m.map_keys:
            p = Path(getattr(m, key).format(field=field)).expanduser()
            paths[key] = p if p.is_absolute() else Path(cfg.survey.image_dir) / p
        out[m.name] = paths
    return out


def _image_wcs(survey, field: str):
    from astropy.wcs import WCS

    header = survey.header(field, survey.config.survey.detection_band)
    w = WCS(header).celestial
    if not w.has_celestial:
        raise LensMapError(f"survey.lens: the detection image of field {field!r} has no celestial "
                           "WCS, so lens maps cannot be placed on it")
    return w


def _open_map(path: Path):
    """The header (its 2-D image's) and shape of a lens map, and its celestial WCS."""
    import warnings

    from astropy.io import fits
    from astropy.wcs import WCS

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with fits.open(path, memmap=True) as hdul:
                hdu = next((h for h in hdul if h.is_image and h.header.get("NAXIS") == 2), None)
                if hdu is None:
                    raise LensMapError(f"{path}: no 2-D image in the file")
                header = hdu.header.copy()
                w = WCS(header)
    except LensMapError:
        raise
    except (OSError, ValueError, TypeError, KeyError, IndexError) as exc:
        raise LensMapError(f"{path}: unreadable lens map ({str(exc).splitlines()[0]})") from None
    if not w.has_celestial or w.celestial.naxis != 2:
        raise LensMapError(f"{path}: the lens map has no celestial WCS (CTYPE1/2 RA---/DEC--, "
                           "CRVAL, CRPIX, CD or CDELT); it cannot be placed on the images")
    return (int(header["NAXIS2"]), int(header["NAXIS1"])), w.celestial


def _read_crop(path: Path, crop) -> np.ndarray:
    """Rows and columns ``crop`` of a lens map's 2-D image, as float64 (only those are read
    into memory: a map may be as large as a mosaic)."""
    import warnings

    from astropy.io import fits

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with fits.open(path, memmap=True) as hdul:
                hdu = next(h for h in hdul if h.is_image and h.header.get("NAXIS") == 2)
                return np.array(hdu.section[crop] if hasattr(hdu, "section") else hdu.data[crop],
                                dtype=np.float64)
    except (OSError, ValueError, TypeError, KeyError, IndexError) as exc:
        raise LensMapError(f"{path}: unreadable lens map ({str(exc).splitlines()[0]})") from None


class FieldLens:
    """One field's lens model, evaluated at image pixel positions.

    Parameters
    ----------
    name : str
        Model name.
    kappa, gamma1, gamma2 : ndarray or None
        Maps on the lens grid (None for an analytic lens), shear along the grid's axes.
    to_grid : callable or None
        ``(x, y) image pixels -> (u, v)`` lens-grid pixels.
    rotation : ndarray, shape (2, 2)
        Orthogonal map-pixel -> image-pixel matrix the shear is rotated with.
    analytic : SISLens or None
        An analytic lens in image pixels.
    label : str
        What errors name (the map files).
    """

    def __init__(self, name, kappa=None, gamma1=None, gamma2=None, to_grid=None,
                 rotation=np.eye(2), analytic=None, label="analytic lens"):
        self.name, self.label = name, label
        self.maps = None if kappa is None else (kappa, gamma1, gamma2)
        self.to_grid, self.rotation, self.analytic = to_grid, np.asarray(rotation), analytic

    def __call__(self, x, y):
        """``(kappa, gamma1, gamma2)`` at image positions (x, y) [pixels], normalised to
        ``D_ls/D_s = 1``, shear along the image's pixel axes.  LensMapError where a position
        falls outside the map or the map is not finite there."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        if self.analytic is not None:
            # The SIS is singular at its centre: positions within SIS_CORE_PIX of it are read
            # at that radius (the same direction), so a footprint pixel there stays finite.
            a = self.analytic
            dx, dy = x - a.x0, y - a.y0
            r = np.hypot(dx, dy)
            with np.errstate(invalid="ignore", divide="ignore"):
                f = np.where(r < SIS_CORE_PIX, SIS_CORE_PIX / np.where(r > 0, r, 1.0), 1.0)
            dx = np.where(r > 0, dx * f, SIS_CORE_PIX)
            return a.convergence_shear(a.x0 + dx, a.y0 + dy * f)
        from scipy.ndimage import map_coordinates

        u, v = self.to_grid(x.ravel(), y.ravel())
        ny, nx = self.maps[0].shape
        outside = ~((u >= 0) & (u <= nx - 1) & (v >= 0) & (v <= ny - 1))
        if outside.any():
            k = int(np.flatnonzero(outside)[0])
            raise LensMapError(f"{self.label}: does not cover the field (image pixel "
                               f"x={x.ravel()[k]:.1f}, y={y.ravel()[k]:.1f} is outside the map)")
        coords = np.stack([v, u])
        k, g1, g2 = (map_coordinates(m, coords, order=1, mode="nearest") for m in self.maps)
        bad = ~np.isfinite(k + g1 + g2)
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise LensMapError(f"{self.label}: NaN or inf inside the footprint (image pixel "
                               f"x={x.ravel()[j]:.1f}, y={y.ravel()[j]:.1f})")
        q = self.rotation
        # Gamma_image = Q Gamma_map Q^T with Gamma = [[g1, g2], [g2, -g1]].
        a, b, c, d = q[0, 0], q[0, 1], q[1, 0], q[1, 1]
        t00 = a * a * g1 + 2 * a * b * g2 - b * b * g1
        t01 = a * c * g1 + (a * d + b * c) * g2 - b * d * g1
        shape = x.shape
        return k.reshape(shape), t00.reshape(shape), t01.reshape(shape)


def _analytic(cfg, survey, field: str) -> FieldLens:
    a = cfg.survey.lens.analytic
    scale = survey.pixel_scale_arcsec(field)
    if a.sis.center_x_pix is not None:
        x0, y0 = a.sis.center_x_pix, a.sis.center_y_pix
    else:
        x0, y0 = _image_wcs(survey, field).all_world2pix(a.sis.center_ra_deg, a.sis.center_dec_deg, 0)
    lens = SISLens(a.sis.theta_e_arcsec / scale, float(x0), float(y0), a.shear.gamma1,
                   a.shear.gamma2)
    return FieldLens("analytic", analytic=lens)


def _orthogonal(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    return u @ vt


def _fits(cfg, survey, field: str, model) -> FieldLens:
    paths = lens_map_paths(cfg, field)[model.name]
    label = ", ".join(str(p) for p in paths.values())
    grid = None
    for key, p in paths.items():
        shape, w = _open_map(p)
        if grid is None:
            grid = (shape, w, p)
        elif shape != grid[0] or not _same_grid(w, grid[1], shape):
            raise LensMapError(f"{p}: not on the grid of {grid[2]} (model {model.name!r}: every "
                               "map of a model must share one grid and WCS)")
    shape, lw, _ = grid
    iw = _image_wcs(survey, field)
    ny, nx = survey.shape(field)

    def to_grid(x, y):
        ra, dec = iw.all_pix2world(x, y, 0)
        return lw.all_world2pix(ra, dec, 0)

    # Only the lens grid over the image (+ margin) is read: memory ~ the field's area.
    bx = np.concatenate([np.linspace(0, nx - 1, 65), np.full(65, nx - 1.0),
                         np.linspace(0, nx - 1, 65), np.zeros(65)])
    by = np.concatenate([np.zeros(65), np.linspace(0, ny - 1, 65), np.full(65, ny - 1.0),
                         np.linspace(0, ny - 1, 65)])
    u, v = to_grid(bx, by)
    u0 = int(max(0, math.floor(np.nanmin(u)) - CROP_MARGIN))
    v0 = int(max(0, math.floor(np.nanmin(v)) - CROP_MARGIN))
    u1 = int(min(shape[1], math.ceil(np.nanmax(u)) + CROP_MARGIN + 1))
    v1 = int(min(shape[0], math.ceil(np.nanmax(v)) + CROP_MARGIN + 1))
    if u1 - u0 < 3 or v1 - v0 < 3:
        raise LensMapError(f"{label}: does not cover field {field!r} (no overlap with its image)")
    crop = (slice(v0, v1), slice(u0, u1))
    maps = {key: _read_crop(p, crop) for key, p in paths.items()}
    if model.kind == "kappa":
        k, g1, g2 = (maps[key] for key in ("kappa", "gamma1", "gamma2"))
    else:
        # Central differences inside the crop; its margin keeps one-sided ones off the field.
        h = 1.0 if model.deflection_unit == "pixel" else \
            float(np.sqrt(abs(np.linalg.det(lw.pixel_scale_matrix)))) * 3600.0
        k, g1, g2 = convergence_shear_from_deflection(maps["alpha_x"], maps["alpha_y"], h)

    def cropped(x, y):
        uu, vv = to_grid(x, y)
        return uu - u0, vv - v0

    # Local map-pixel -> image-pixel matrix at the image centre, by differences.
    cx, cy = 0.5 * (nx - 1), 0.5 * (ny - 1)
    uc, vc = to_grid(np.array([cx, cx + 1.0, cx]), np.array([cy, cy, cy + 1.0]))
    img_to_map = np.array([[uc[1] - uc[0], uc[2] - uc[0]], [vc[1] - vc[0], vc[2] - vc[0]]])
    rotation = _orthogonal(np.linalg.inv(img_to_map))
    return FieldLens(model.name, k, g1, g2, cropped, rotation, label=label)


def _same_grid(w1, w2, shape) -> bool:
    ny, nx = shape
    x = np.array([0.0, nx - 1.0, 0.0, nx - 1.0])
    y = np.array([0.0, 0.0, ny - 1.0, ny - 1.0])
    a, b = np.array(w1.all_pix2world(x, y, 0)), np.array(w2.all_pix2world(x, y, 0))
    return bool(np.allclose(a, b, rtol=0, atol=1e-9))


def field_lens(cfg, survey, field: str, model: int = 0) -> FieldLens | None:
    """The field's lens model number ``model`` (0: the one driving the injections), or None
    without ``survey.lens``."""
    lens = cfg.survey.lens
    if lens is None:
        return None
    if lens.analytic is not None:
        return _analytic(cfg, survey, field)
    return _fits(cfg, survey, field, lens.models[model])


class LazyFieldLens:
    """:func:`field_lens` built on first use (a worker that opens a field reads the maps
    only when a task needs them); pickles as its recipe."""

    def __init__(self, cfg, survey, field: str):
        self._args, self._lens = (cfg, survey, field), None
        self.z_lens = float(cfg.survey.lens.z_lens)

    def __call__(self, x, y):
        if self._lens is None:
            self._lens = field_lens(*self._args)
        return self._lens(x, y)

    def __getstate__(self):
        return {**self.__dict__, "_lens": None}


def _samples(footprint, stride: int):
    """Strided footprint sample positions, by row blocks: yields (x, y, rows, cols)."""
    ny, nx = footprint.shape
    cols = np.arange(stride // 2, nx, stride)
    rows = np.arange(stride // 2, ny, stride)
    for i in range(0, rows.size, ROW_BLOCK):
        r = rows[i:i + ROW_BLOCK]
        inside = np.asarray(footprint[np.ix_(r, cols)], dtype=bool)
        yy, xx = np.nonzero(inside)
        yield cols[xx].astype(float), r[yy].astype(float), r[yy], cols[xx]


def _stride(footprint) -> int:
    return max(1, int(math.ceil(math.sqrt(footprint.size / NODE_SAMPLES))))


def check_field_lens(cfg, survey, field: str) -> None:
    """Every lens model of a field readable, with a WCS, covering the footprint and finite
    there (at a strided sample of it, :data:`NODE_SAMPLES`); LensMapError naming the file."""
    lens = cfg.survey.lens
    if lens is None:
        return
    footprint = survey.footprint(field)
    stride = _stride(footprint)
    for i in range(max(1, len(lens.models))):
        provider = field_lens(cfg, survey, field, i)
        for x, y, _, _ in _samples(footprint, stride):
            provider(x, y)


def lens_z_range(cfg) -> tuple[float, float]:
    """Lowest and highest source redshift of the grid, its cells and box."""
    zs = list(cfg.grid.z_values) + [c.z for c in cfg.grid.cells]
    if cfg.grid.box is not None:
        zs += list(cfg.grid.box.z)
    return float(min(zs)), float(max(zs))


def field_lens_nodes(cfg, survey, field: str, depth, footprint) -> dict:
    """``{model name: lens area nodes}`` of a field (:func:`glaciar.galaxy.lensing.lens_area_nodes`)
    on a strided sample of its footprint, with the local depth map ``depth`` [AB mag]."""
    from . import constants as C

    lens = cfg.survey.lens
    zlo, zhi = lens_z_range(cfg)
    ratios = tuple(float(r) for r in distance_ratio(lens.z_lens, [zlo, zhi],
                                                     cfg.source.cosmology))
    stride = _stride(footprint)
    area = (stride * survey.pixel_scale_arcsec(field)) ** 2 / 3600.0
    out = {}
    for i, name in enumerate(lens.model_names):
        provider = field_lens(cfg, survey, field, i)
        parts = [[], [], [], []]
        for x, y, rows, cols in _samples(footprint, stride):
            k, g1, g2 = provider(x, y)
            for lst, v in zip(parts, (np.asarray(depth[rows, cols], float), k, g1, g2)):
                lst.append(v)
        d, k, g1, g2 = (np.concatenate(p) if p else np.zeros(0) for p in parts)
        out[name] = lens_area_nodes(d, k, g1, g2, area, depth_bin_mag=C.DEPTH_BIN_MAG,
                                    ratio_range=ratios)
    return out
