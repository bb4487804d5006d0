"""The demo survey on disk: FITS images, PSF files and a configuration.

:func:`build_demo_survey` writes what :func:`~glaciar.demo.images.make_demo_images` builds;
above ``strips.STRIP_MIN_PIXELS`` it streams the same field strip by strip
(:func:`~glaciar.demo.strips.iter_demo_strips`) into the FITS files, so a 16000^2
survey is written with bounded memory.
"""
from __future__ import annotations

import io
import math
import os
import tempfile
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from .bands import (DEMO_BANDS, DEMO_BANDS_SPEC, DEMO_CONFIG_NAME, DEMO_FIELD, DEMO_MOFFAT_BETA,
                    DEMO_PIXEL_SCALE_ARCSEC, CRVAL_DEG)
from .images import make_demo_images
from . import strips as _strips


def _image_header(shape: tuple[int, int], band: str, pixel_scale_arcsec: float, kind: str,
                  field: str = DEMO_FIELD):
    from astropy.io import fits

    spec = DEMO_BANDS_SPEC[band]
    ny, nx = shape
    h = fits.Header()
    h["TELESCOP"] = "HST"
    h["INSTRUME"] = "WFC3"
    h["DETECTOR"] = "UVIS" if "uvis" in spec.filter else "IR"
    h["FILTER"] = band.upper()
    h["OBJECT"] = field
    h["ORIGIN"] = ("glaciar demo", "synthetic BoRG-like field")
    h["WCSAXES"] = 2
    h["CTYPE1"] = "RA---TAN"
    h["CTYPE2"] = "DEC--TAN"
    h["CUNIT1"] = "deg"
    h["CUNIT2"] = "deg"
    h["CRPIX1"] = 0.5 * (nx + 1)
    h["CRPIX2"] = 0.5 * (ny + 1)
    h["CRVAL1"] = CRVAL_DEG[0]
    h["CRVAL2"] = CRVAL_DEG[1]
    h["CD1_1"] = -pixel_scale_arcsec / 3600.0
    h["CD1_2"] = 0.0
    h["CD2_1"] = 0.0
    h["CD2_2"] = pixel_scale_arcsec / 3600.0
    h["RADESYS"] = "ICRS"
    h["EXPTIME"] = (spec.exptime_s, "[s] nominal exposure time")
    if kind == "science":
        h["BUNIT"] = "ELECTRONS/S"
        h["MAGZPT"] = (spec.zeropoint, "AB zeropoint of ELECTRONS/S")
        h["DEPTH5S"] = (spec.depth_5sigma, "5 sigma point source AB, r=0.2 arcsec aperture")
    else:
        h["BUNIT"] = "(ELECTRONS/S)**-2"
        h["WHTTYPE"] = ("IVM", "inverse variance of the sky noise per pixel")
    return h


def _fits_bytes(data: np.ndarray, header) -> bytes:
    from astropy.io import fits

    buf = io.BytesIO()
    fits.PrimaryHDU(data=data, header=header).writeto(buf)
    return buf.getvalue()


def _stream_header(shape: tuple[int, int], header):
    """The primary header :func:`_fits_bytes` writes for float32 data of ``shape``, without the data."""
    from astropy.io import fits

    ny, nx = shape
    h = fits.PrimaryHDU(data=np.zeros((1, 1), np.float32), header=header).header
    h["NAXIS1"], h["NAXIS2"] = int(nx), int(ny)
    return h


class _FitsRowWriter:
    """A float32 primary-HDU FITS file written by strips of rows, then renamed into place.

    ``write(rows)`` appends rows (top to bottom, as the image is stored); ``commit()``
    after the last row makes the file appear at ``path`` (atomic rename; the same bytes
    as :func:`_fits_bytes` of the whole image); ``discard()`` removes the temporary file.
    """

    def __init__(self, path: Path, shape: tuple[int, int], header):
        from astropy.io import fits

        from ..rundir import process_umask

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self._tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp",
                                         dir=self.path.parent)
        os.close(fd)                 # an empty file: StreamingHDU writes it as a new one
        os.chmod(self._tmp, 0o666 & ~process_umask())
        self._hdu = fits.StreamingHDU(self._tmp, _stream_header(shape, header))
        self._done = False

    def write(self, rows: np.ndarray) -> None:
        self._hdu.write(np.ascontiguousarray(rows, dtype=np.float32))

    def commit(self) -> None:
        self._hdu.close()
        with open(self._tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(self._tmp, self.path)
        self._done = True

    def discard(self) -> None:
        if self._done:
            return
        try:
            self._hdu.close()
        except Exception:            # incomplete data: astropy complains; the file goes anyway
            pass
        try:
            os.unlink(self._tmp)
        except FileNotFoundError:
            pass


def _write_images_by_strips(out_dir: Path, field: str, shape, seed, source_density_arcmin2,
                            n_stars, noise_scale) -> dict:
    """Stream the demo images into their FITS files; returns :func:`iter_demo_strips`' info."""
    info, strips = _strips.iter_demo_strips(shape, seed=seed,
                                            source_density_arcmin2=source_density_arcmin2,
                                            n_stars=n_stars, field=field, noise_scale=noise_scale)
    shape = tuple(int(v) for v in shape)
    writers = {}
    with ExitStack() as stack:
        for b in DEMO_BANDS:
            for kind, name in (("science", "drz"), ("weight", "wht")):
                w = _FitsRowWriter(out_dir / "images" / f"{field}_{b}_{name}.fits", shape,
                                   _image_header(shape, b, DEMO_PIXEL_SCALE_ARCSEC, kind, field))
                writers[kind, b] = w
                stack.callback(w.discard)
        for _, _, science, weight in strips:
            for b in DEMO_BANDS:
                writers["science", b].write(science[b])
                writers["weight", b].write(weight[b])
        for w in writers.values():
            w.commit()
    return info


def config_dumper():
    """A SafeDumper (no Python tags) writing mappings as blocks and scalar lists inline."""
    import yaml

    class _Dumper(yaml.SafeDumper):
        pass

    def _list(dumper, value):
        flow = all(not isinstance(v, (list, dict)) for v in value)
        return dumper.represent_sequence("tag:yaml.org,2002:seq", value, flow_style=flow)

    _Dumper.add_representer(list, _list)
    return _Dumper


def _grid_values(values) -> list[float]:
    vals = [float(round(float(v), 6)) for v in np.atleast_1d(np.asarray(values, dtype=float))]
    if not vals or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"grid values must be a non-empty list of finite numbers, got {values!r}")
    return vals


def build_demo_survey(out_dir, *, shape: tuple[int, int] = (1000, 1000), seed: int = 2018,
                      n_galaxies: int = 50, n_iterations: int = 2,
                      z_values=tuple(np.round(np.arange(7.8, 12.6 + 1e-9, 0.4), 6)) + (12.9,),
                      mag_values=tuple(np.round(np.arange(24.5, 28.5 + 1e-9, 0.5), 6)),
                      source_density_arcmin2: float = 250.0, n_stars: int = 6,
                      field: str = DEMO_FIELD, noise_scale=1.0) -> Path:
    """Write the demo survey (FITS images, weight maps, PSFs and a config) to ``out_dir``.

    Layout: ``out_dir/demo.yaml``, ``out_dir/images/<field>_<band>_drz.fits``
    (float32, e-/s, TAN WCS at 0.08"/px), ``out_dir/images/<field>_<band>_wht.fits``
    (inverse variance), ``out_dir/psf/psf_<band>.fits`` (with ``PIXSCALE``).
    Every file is written atomically.  Fields of other names (and the same
    pixel scale and PSFs) can be written into one directory; the config
    ``demo.yaml`` then describes the last one written.

    Parameters
    ----------
    out_dir : str or path-like
        Directory to write into (created if needed; existing demo files are replaced).
    shape : (int, int)
        Image shape (ny, nx) [pixels].
    seed : int
        Seed of the images; also written as the simulation seed of the config.
    n_galaxies : int
        Artificial sources injected per iteration (config ``simulation.n_galaxies``).
    n_iterations : int
        Iterations per (field, z, mag) (config ``simulation.n_iterations``).
    z_values, mag_values : sequence of float
        Redshift grid and apparent F160W magnitude grid [AB] of the config.
        Defaults 7.8-12.6 step 0.4 and 12.9 (the J125-dropout's lower edge inside; F160W,
        the detection band, receives no flux from z = 12.99, where Lyman-alpha leaves it,
        so the selection ends there) and 24.5-28.5 step 0.5: 252 tasks, about a minute
        on 2 cores.
    source_density_arcmin2, n_stars, noise_scale : see :func:`make_demo_images`.
    field : str
        Field name, used in the file names and the config (default ``demo01``).

    Returns
    -------
    pathlib.Path
        Path of the config file.
    """
    import yaml
    from astropy.io import fits

    from ..rundir import atomic_write_bytes, atomic_write_text

    if int(n_galaxies) < 1 or int(n_iterations) < 1:
        raise ValueError(f"n_galaxies and n_iterations must be >= 1, got {n_galaxies}, {n_iterations}")
    out_dir = Path(out_dir)
    image_shape = tuple(int(v) for v in shape)
    if image_shape[0] * image_shape[1] > _strips.STRIP_MIN_PIXELS:
        # Large mosaics: the same field streamed by strips (bounded memory; equal to the
        # whole-image one up to FFT rounding, see glaciar.demo.strips).
        demo = _write_images_by_strips(out_dir, field, image_shape, seed, source_density_arcmin2,
                                       n_stars, noise_scale)
    else:
        demo = make_demo_images(shape, seed=seed, source_density_arcmin2=source_density_arcmin2,
                                n_stars=n_stars, field=field, noise_scale=noise_scale)
        image_shape = demo["science"][DEMO_BANDS[0]].shape
        for b in DEMO_BANDS:
            for kind, name in (("science", "drz"), ("weight", "wht")):
                atomic_write_bytes(out_dir / "images" / f"{field}_{b}_{name}.fits",
                                   _fits_bytes(demo[kind][b],
                                               _image_header(image_shape, b, DEMO_PIXEL_SCALE_ARCSEC,
                                                             kind, field)))
    for b in DEMO_BANDS:
        ph = fits.Header()
        ph["PIXSCALE"] = (demo["psf_pixel_scale_arcsec"][b], "[arcsec/pixel]")
        ph["FILTER"] = b.upper()
        ph["PSFMODEL"] = ("MOFFAT", "analytic, pixel-integrated")
        ph["FWHM"] = (DEMO_BANDS_SPEC[b].psf_fwhm_arcsec, "[arcsec]")
        ph["BETA"] = DEMO_MOFFAT_BETA
        atomic_write_bytes(out_dir / "psf" / f"psf_{b}.fits", _fits_bytes(demo["psf"][b], ph))

    config = {
        "survey": {
            "fields": [field],
            "image_dir": "images",
            "science": "{field}_{band}_drz.fits",
            "noise": "{field}_{band}_wht.fits",
            "noise_type": "weight",
            "pixel_scale_arcsec": None,
            "detection_band": DEMO_BANDS[0],
            "bands": {b: {"filter": DEMO_BANDS_SPEC[b].filter,
                          "zeropoint": DEMO_BANDS_SPEC[b].zeropoint,
                          "gain": DEMO_BANDS_SPEC[b].exptime_s,
                          "psf": f"psf/psf_{b}.fits",
                          "psf_pixel_scale_arcsec": DEMO_BANDS_SPEC[b].psf_pixel_scale_arcsec}
                      for b in DEMO_BANDS},
        },
        "grid": {"z": {"values": _grid_values(z_values)},
                 "mag": {"values": _grid_values(mag_values)},
                 "magnitude_type": "apparent"},
        "simulation": {"n_galaxies": int(n_galaxies), "n_iterations": int(n_iterations),
                       "seed": int(seed)},
        "source": {"r_eff_kpc_z6": 1.075, "size_evolution": -1.0, "r_eff_scatter_dex": 0.0,
                   "size_luminosity_slope": 0.0, "sersic_indices": [1.0, 4.0],
                   "sersic_fractions": [0.5, 0.5], "ellipticity_bins": 1,
                   "position_angle_bins": 1, "round_de_vaucouleurs": False, "beta_mean": -2.2,
                   "beta_sd": 0.4, "beta_per": "source", "igm": "inoue14",
                   "cosmology": "Planck18", "stamp_flux_fraction": 0.995},
        "detection": {"sex_file": None, "DETECT_THRESH": 0.7, "DETECT_MINAREA": 9,
                      "FILTER": True, "FILTER_NAME": "gauss_2.0_5x5", "DEBLEND_NTHRESH": 32,
                      "DEBLEND_MINCONT": 0.005, "CLEAN": True, "CLEAN_PARAM": 1.0,
                      "BACK_SIZE": 64, "BACK_FILTERSIZE": 3, "PHOT_APERTURES": [4.0, 8.0],
                      "PHOT_AUTOPARAMS": [2.5, 3.5]},
        "classification": {"min_sn": 8.0, "sn_definition": "iso", "sn_aperture_index": 0,
                           "search_box": 3, "max_overlap_fraction": 0.25, "flux_tolerance": 0.25},
        "selection": ["sn_f160w >= 8", "sn_f606w < 1.5", "sn_f098m < 1.5",
                      "maglim_f125w - mag_f160w > 1.5"],
        "output": {"regions": False},
    }
    depths = ", ".join(f"{b.upper()} {DEMO_BANDS_SPEC[b].depth_5sigma}" for b in DEMO_BANDS)
    header = (
        "# glaciar demo survey: a synthetic BoRG-like field (written by glaciar.demo).\n"
        f"# Field {field}, {image_shape[1]} x {image_shape[0]} px at "
        f"{DEMO_PIXEL_SCALE_ARCSEC}\"/px, image seed {seed}; drizzle-like correlated noise,\n"
        "# inverse-variance weight maps, Moffat PSFs written at 0.13\"/px (IR) and 0.04\"/px (F606W).\n"
        f"# 5-sigma point-source depths (r = 0.2\" aperture, full exposure): {depths}.\n"
        "# gain = exposure time [s] (electrons per e-/s). Selection: BoRG J125-dropouts.\n"
        "# Paths are relative to this file. Schema: docs/config-schema.yaml.\n"
    )
    scale = np.asarray(noise_scale, dtype=np.float64)
    if np.any(scale != 1.0):
        header += (f"# Sky noise RMS scaled by noise_scale = {float(scale.min()):g}"
                   + (f" to {float(scale.max()):g} across the field" if np.ptp(scale) > 0 else "")
                   + " (the depths above are for 1).\n")
    path = out_dir / DEMO_CONFIG_NAME
    atomic_write_text(path, header + yaml.dump(config, Dumper=config_dumper(), sort_keys=False,
                                               default_flow_style=False, width=100))
    return path
