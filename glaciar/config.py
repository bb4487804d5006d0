"""Configuration: YAML file -> validated, frozen dataclasses.

The schema is documented in ``docs/config-schema.yaml`` and, with comments,
in the template that ``glaciar init`` writes (:func:`template_yaml`). Every
value the paper gives a default for has that default here. Errors name the
file and the key path, e.g.::

    config.yaml: survey.bands.f160w.zeropoint: expected a number, got 'abc'

GLACiAR's flat ``parameters.yaml`` (Carrasco et al. 2018, appendix) is
recognised (no ``survey:`` section, GLACiAR keys present) and mapped onto the
schema, so a GLACiAR user's file runs as it is; the choices made in that
mapping are listed in ``Config.warnings``.

Relative paths are relative to the directory of the config file.
"""
from __future__ import annotations

import copy
import difflib
import hashlib
import json
import math
import os
import re
import string
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import yaml

from . import constants
from .engine.selection import DEFAULT_JDROPOUT, SelectionError, compile_selection

__all__ = ["ConfigError", "BandConfig", "SurveyConfig", "GridConfig", "SimulationConfig",
           "Config", "load_config", "config_from_dict", "config_to_dict", "config_hash",
           "template_yaml", "check_files", "missing_files", "selection_columns",
           "read_fields_file", "read_sex_file", "is_glaciar_parameters",
           "SOURCE_DEFAULTS", "DETECTION_DEFAULTS", "CLASSIFICATION_DEFAULTS",
           "OUTPUT_DEFAULTS", "SIMULATION_DEFAULTS", "GRID_DEFAULTS"]


class ConfigError(ValueError):
    """Invalid configuration; the message names the file and the key path."""


# ---------------------------------------------------------------------------
# Dataclasses
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class BandConfig:
    """One photometric band of the survey.

    Attributes
    ----------
    name : str
        Band name as used in file-name templates (``{band}``); per-band
        columns use ``name.lower()``.
    filter : str
        Built-in filter name (e.g. ``wfc3_ir_f160w``) or an absolute path to a
        throughput curve.
    zeropoint : float
        AB magnitude of one image unit (e.g. one e-/s) [mag].
    gain : float or None
        Electrons per image unit, for the source Poisson noise; None = none.
    psf : str or dict
        Absolute path of a FITS PSF, or an analytic PSF: ``{profile: gaussian,
        fwhm_arcsec}``, ``{profile: moffat, fwhm_arcsec, beta=2.5}`` or
        ``{profile: airy, wavelength_angstrom, diameter_m=2.4, obscuration=0.33}``
        (each with an optional odd ``size`` in pixels). Required by the config
        (the type admits None only for hand-built objects).
    psf_pixel_scale_arcsec : float or None
        Pixel scale of a FITS PSF [arcsec/pixel]; None = from its header.
    """

    name: str
    filter: str
    zeropoint: float
    gain: float | None = None
    psf: str | dict | None = None
    psf_pixel_scale_arcsec: float | None = None


@dataclass(frozen=True)
class SurveyConfig:
    """Fields, bands and image locations.

    ``science`` and ``noise`` are file-name templates inside ``image_dir``
    with the placeholders ``{field}`` and ``{band}``.
    """

    fields: tuple[str, ...]
    image_dir: Path
    science: str
    noise: str | None
    noise_type: str
    pixel_scale_arcsec: float | None
    detection_band: str
    bands: tuple[BandConfig, ...]

    @property
    def band_names(self) -> tuple[str, ...]:
        """Band names in configuration order."""
        return tuple(b.name for b in self.bands)

    def band(self, name: str) -> BandConfig:
        """The :class:`BandConfig` called ``name`` (KeyError if absent)."""
        for b in self.bands:
            if b.name == name:
                return b
        raise KeyError(f"no band {name!r}; bands are {list(self.band_names)}")


@dataclass(frozen=True)
class GridConfig:
    """Simulation grid: redshifts and magnitudes (apparent, detection band, or M_UV)."""

    z_values: tuple[float, ...]
    mag_values: tuple[float, ...]
    magnitude_type: str = "apparent"


@dataclass(frozen=True)
class SimulationConfig:
    """Sources per iteration, iterations per (field, z, mag), master seed."""

    n_galaxies: int = 100
    n_iterations: int = 100
    seed: int = 12345
    #: Injected sources never overlap within the box holding this fraction of their
    #: Sersic light plus two PSF FWHMs (outer wings may touch and then add, never overwrite).
    isolation_fraction: float = 0.95


@dataclass(frozen=True)
class Config:
    """A complete, validated configuration.

    ``source`` holds the keyword arguments of the source model, ``detection``
    SExtractor-vocabulary keys (upper case; ``sex_file`` an absolute path or
    None), ``classification`` the recovery thresholds, ``selection`` the
    selection expressions, ``output`` output options. ``path``, ``base_dir``
    and ``warnings`` do not take part in equality.
    """

    path: Path | None = field(compare=False)
    base_dir: Path = field(compare=False)
    survey: SurveyConfig
    grid: GridConfig
    simulation: SimulationConfig
    source: dict
    detection: dict
    classification: dict
    selection: tuple[str, ...]
    output: dict
    warnings: tuple[str, ...] = field(default=(), compare=False)


# ---------------------------------------------------------------------------
# Defaults (paper: Carrasco et al. 2018, Sect. 2 and appendix)
# ---------------------------------------------------------------------------
SIMULATION_DEFAULTS = {"n_galaxies": 100, "n_iterations": 100, "seed": 12345, "isolation_fraction": 0.95}
# The paper's default z range is 9.0-11.9 in 15 bins (not an even step); we
# keep 15 bins at the even 0.2 step the code actually simulates.
GRID_DEFAULTS = {"z": {"min": 9.0, "max": 11.8, "step": 0.2},
                 "mag": {"min": 24.1, "max": 27.9, "step": 0.2},
                 "magnitude_type": "apparent"}
SOURCE_DEFAULTS = {
    "r_eff_kpc_z6": 1.075,
    "size_evolution": -1.0,
    "r_eff_scatter_dex": 0.0,
    "size_luminosity_slope": 0.0,
    "sersic_indices": (1.0, 4.0),
    "sersic_fractions": (0.5, 0.5),
    "ellipticity_bins": 1,
    "position_angle_bins": 1,
    "round_de_vaucouleurs": False,
    "beta_mean": -2.2,
    "beta_sd": 0.4,
    "beta_per": "source",
    "igm": "inoue14",
    "cosmology": "Planck18",
    "stamp_flux_fraction": 0.995,
}
DETECTION_DEFAULTS = {
    "sex_file": None,
    "DETECT_THRESH": 0.7,
    "DETECT_MINAREA": 9,
    "FILTER": True,
    "FILTER_NAME": "gauss_2.0_5x5",
    "DEBLEND_NTHRESH": 32,
    "DEBLEND_MINCONT": 0.005,
    "CLEAN": True,
    "CLEAN_PARAM": 1.0,
    "BACK_SIZE": 64,
    "BACK_FILTERSIZE": 3,
    "PHOT_APERTURES": (4.0, 8.0),
    "PHOT_AUTOPARAMS": (2.5, 3.5),
}
CLASSIFICATION_DEFAULTS = {
    "min_sn": 8.0,
    "sn_definition": "iso",
    "sn_aperture_index": 0,
    "search_box": 3,
    "max_overlap_fraction": 0.25,
    "flux_tolerance": 0.25,
}
OUTPUT_DEFAULTS = {"regions": False}

_TOP_KEYS = ("survey", "grid", "simulation", "source", "detection", "classification",
             "selection", "output")
_SURVEY_KEYS = ("fields", "fields_file", "image_dir", "science", "noise", "noise_type",
                "pixel_scale_arcsec", "detection_band", "bands")
_BAND_KEYS = ("filter", "zeropoint", "gain", "psf", "psf_pixel_scale_arcsec")
# profile -> (required keys, optional keys with the defaults of glaciar.galaxy.psf)
_PSF_PROFILES = {"gaussian": (("fwhm_arcsec",), {}),
                 "moffat": (("fwhm_arcsec",), {"beta": 2.5}),
                 "airy": (("wavelength_angstrom",), {"diameter_m": 2.4, "obscuration": 0.33})}
_FILTER_FILE_SUFFIXES = (".tab", ".dat", ".par", ".fits", ".fit", ".txt", ".csv", ".ecsv")


# ---------------------------------------------------------------------------
# Error context and typed getters
# ---------------------------------------------------------------------------
class _Ctx:
    def __init__(self, source_name: str, base_dir: Path):
        self.source = source_name
        self.base_dir = base_dir
        self.origins: dict[str, str] = {}    # schema key path -> GLACiAR key
        self.warnings: list[str] = []

    def error(self, path: str, message: str) -> ConfigError:
        origin = self.origins.get(path)
        suffix = f" (from GLACiAR key '{origin}')" if origin and origin != path else ""
        return ConfigError(f"{self.source}: {path}: {message}{suffix}")


def _show(value) -> str:
    if isinstance(value, str):
        return repr(value)
    return f"{value!r} ({type(value).__name__})"


def _check_keys(ctx: _Ctx, path: str, data, allowed, hints: Mapping[str, str] | None = None):
    if not isinstance(data, Mapping):
        raise ctx.error(path or "<top level>", f"expected a mapping of keys, got {_show(data)}")
    for key in data:
        if key in allowed:
            continue
        where = f"{path}.{key}" if path else str(key)
        msg = f"unknown key {key!r}"
        if hints and key in hints:
            msg += f" ({hints[key]})"
        else:
            close = difflib.get_close_matches(str(key), [str(a) for a in allowed], n=1, cutoff=0.6)
            if close:
                msg += f"; did you mean {close[0]!r}?"
            else:
                msg += f"; allowed keys: {', '.join(map(str, allowed))}"
        raise ctx.error(where, msg)


def _float(ctx, path, value, *, gt=None, ge=None, le=None, lt=None) -> float:
    # PyYAML (YAML 1.1) reads `1e-3` (no dot) as a string: accept numeric strings.
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ctx.error(path, f"expected a number, got {_show(value)}")
    try:
        x = float(value)
    except ValueError:
        raise ctx.error(path, f"expected a number, got {value!r}") from None
    if not math.isfinite(x):
        raise ctx.error(path, f"expected a finite number, got {value!r}")
    if gt is not None and not x > gt:
        raise ctx.error(path, f"must be > {gt}, got {x:g}")
    if ge is not None and not x >= ge:
        raise ctx.error(path, f"must be >= {ge}, got {x:g}")
    if lt is not None and not x < lt:
        raise ctx.error(path, f"must be < {lt}, got {x:g}")
    if le is not None and not x <= le:
        raise ctx.error(path, f"must be <= {le}, got {x:g}")
    return x


def _opt_float(ctx, path, value, **kw) -> float | None:
    return None if value is None else _float(ctx, path, value, **kw)


def _int(ctx, path, value, *, ge=None) -> int:
    if isinstance(value, bool):
        raise ctx.error(path, f"expected an integer, got {_show(value)}")
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not isinstance(value, int):
        raise ctx.error(path, f"expected an integer, got {_show(value)}")
    if ge is not None and value < ge:
        raise ctx.error(path, f"must be >= {ge}, got {value}")
    return value


_TRUE = {"yes", "y", "true", "on", "1"}
_FALSE = {"no", "n", "false", "off", "0"}


def _bool(ctx, path, value) -> bool:
    # GLACiAR files use YAML 1.1 words (yes/No), sometimes quoted.
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in _TRUE | _FALSE:
        return value.strip().lower() in _TRUE
    raise ctx.error(path, f"expected true/false, got {_show(value)}")


def _str(ctx, path, value, *, choices=None) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ctx.error(path, f"expected a non-empty string, got {_show(value)}")
    if choices is not None:
        v = value.strip().lower()
        if v not in choices:
            close = difflib.get_close_matches(v, choices, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ctx.error(path, f"expected one of {', '.join(choices)}, got {value!r}{hint}")
        return v
    return value.strip()


def _float_list(ctx, path, value, *, min_len=1, gt=None, ge=None, le=None) -> tuple[float, ...]:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value]
    if not isinstance(value, (list, tuple)):
        raise ctx.error(path, f"expected a list of numbers, got {_show(value)}")
    if len(value) < min_len:
        raise ctx.error(path, f"expected at least {min_len} value(s), got {len(value)}")
    return tuple(_float(ctx, f"{path}[{i}]", v, gt=gt, ge=ge, le=le) for i, v in enumerate(value))


def _resolve(base_dir: Path, value: str) -> Path:
    p = Path(os.path.expanduser(value))
    return p if p.is_absolute() else (base_dir / p).resolve()


def _looks_like_path(value: str, suffixes) -> bool:
    return "/" in value or "\\" in value or value.lower().endswith(tuple(suffixes))


# ---------------------------------------------------------------------------
# Sections
# ---------------------------------------------------------------------------
def read_fields_file(path: str | os.PathLike) -> tuple[str, ...]:
    """Field names from a list file: the first token of each non-blank, non-comment line.

    Parameters
    ----------
    path : path-like
        Text file (GLACiAR's ``list_of_fields`` format).

    Returns
    -------
    tuple of str
    """
    fields = []
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            fields.append(line.split()[0])
    return tuple(fields)


def _check_template(ctx, path, template: str) -> str:
    template = _str(ctx, path, template)
    try:
        parts = list(string.Formatter().parse(template))
    except ValueError as exc:
        raise ctx.error(path, f"invalid file-name template {template!r}: {exc}") from None
    for _, name, spec, conv in parts:
        if name is None:
            continue
        if name not in ("field", "band") or spec or conv:
            raise ctx.error(path, f"template {template!r}: only the placeholders {{field}} and "
                                  f"{{band}} are allowed, found {{{name}}}")
    return template


def _template_names(template: str) -> set[str]:
    return {name for _, name, _, _ in string.Formatter().parse(template) if name}


def _parse_psf(ctx, path, value, base_dir):
    if value is None:
        return None
    if isinstance(value, str):
        return str(_resolve(base_dir, _str(ctx, path, value)))
    if not isinstance(value, Mapping):
        raise ctx.error(path, f"expected a FITS path or a mapping {{profile, fwhm_arcsec, ...}}, "
                              f"got {_show(value)}")
    if "profile" not in value:
        raise ctx.error(f"{path}.profile", "missing required key (moffat, gaussian or airy)")
    profile = _str(ctx, f"{path}.profile", value["profile"], choices=tuple(_PSF_PROFILES))
    required, optional = _PSF_PROFILES[profile]
    _check_keys(ctx, path, value, ("profile",) + required + tuple(optional) + ("size",))
    for req in required:
        if value.get(req) is None:
            raise ctx.error(f"{path}.{req}", f"missing required key for a {profile} PSF")
    psf = {"profile": profile}
    for key in required + tuple(optional):
        v = value.get(key, optional.get(key))
        if key == "obscuration":
            psf[key] = _float(ctx, f"{path}.{key}", v, ge=0.0, lt=1.0)
        elif key == "beta":
            psf[key] = _float(ctx, f"{path}.{key}", v, gt=1.0)
        else:
            psf[key] = _float(ctx, f"{path}.{key}", v, gt=0)
    if value.get("size") is not None:
        size = _int(ctx, f"{path}.size", value["size"], ge=1)
        if size % 2 == 0:
            raise ctx.error(f"{path}.size", f"must be odd (PSF centred on a pixel), got {size}")
        psf["size"] = size
    return psf


def _check_filter_name(ctx, path, name: str) -> None:
    """Fail early, naming the key, on a filter name the registry does not know."""
    try:
        from .galaxy.filters import get_filter
    except ImportError:   # registry unavailable: the run reports it
        return
    try:
        get_filter(name)
    except (ValueError, KeyError, FileNotFoundError) as exc:
        raise ctx.error(path, str(exc)) from None


def _parse_band(ctx, name, data, base_dir) -> BandConfig:
    path = f"survey.bands.{name}"
    if data is None:
        data = {}
    _check_keys(ctx, path, data, _BAND_KEYS)
    what = {"filter": "built-in filter name or throughput file",
            "zeropoint": "AB zeropoint of the image units",
            "psf": "a FITS file, or e.g. {profile: moffat, fwhm_arcsec: 0.18}"}
    for req in ("filter", "zeropoint", "psf"):
        if data.get(req) is None:
            raise ctx.error(f"{path}.{req}", f"missing required key ({what[req]})")
    filt = _str(ctx, f"{path}.filter", data["filter"])
    if _looks_like_path(filt, _FILTER_FILE_SUFFIXES):
        filt = str(_resolve(base_dir, filt))
    else:
        filt = filt.lower()
        _check_filter_name(ctx, f"{path}.filter", filt)
    return BandConfig(
        name=name,
        filter=filt,
        zeropoint=_float(ctx, f"{path}.zeropoint", data["zeropoint"]),
        gain=_opt_float(ctx, f"{path}.gain", data.get("gain"), gt=0),
        psf=_parse_psf(ctx, f"{path}.psf", data.get("psf"), base_dir),
        psf_pixel_scale_arcsec=_opt_float(ctx, f"{path}.psf_pixel_scale_arcsec",
                                          data.get("psf_pixel_scale_arcsec"), gt=0),
    )


def _parse_survey(ctx, data, base_dir) -> SurveyConfig:
    if data is None:
        raise ctx.error("survey", "missing required section")
    _check_keys(ctx, "survey", data, _SURVEY_KEYS)
    # Fields: a list in the config, or a list file.
    if data.get("fields") is not None and data.get("fields_file") is not None:
        raise ctx.error("survey.fields", "give either fields or fields_file, not both")
    if data.get("fields_file") is not None:
        fpath = _resolve(base_dir, _str(ctx, "survey.fields_file", data["fields_file"]))
        if not fpath.is_file():
            raise ctx.error("survey.fields_file", f"file not found: {fpath}")
        fields = read_fields_file(fpath)
        if not fields:
            raise ctx.error("survey.fields_file", f"no field names in {fpath}")
    elif data.get("fields") is not None:
        raw = data["fields"]
        if isinstance(raw, str):
            raw = [raw]
        if not isinstance(raw, (list, tuple)) or not raw:
            raise ctx.error("survey.fields", f"expected a non-empty list of field names, "
                                             f"got {_show(raw)}")
        fields = []
        for i, f in enumerate(raw):
            if not isinstance(f, str) or not f.strip():
                # YAML reads 0123 as an octal integer: ask for quotes rather than guess.
                raise ctx.error(f"survey.fields[{i}]", f"expected a field name string, got "
                                                       f"{_show(f)} (quote names in YAML)")
            fields.append(f.strip())
        fields = tuple(fields)
    else:
        raise ctx.error("survey.fields", "missing required key (a list of field names, or "
                                         "fields_file: a list file)")
    dup = sorted({f for f in fields if fields.count(f) > 1})
    if dup:
        raise ctx.error("survey.fields", f"duplicate field name(s): {', '.join(dup)}")

    image_dir = _resolve(base_dir, _str(ctx, "survey.image_dir", data.get("image_dir", ".")))
    if data.get("science") is None:
        raise ctx.error("survey.science", "missing required key (file-name template, e.g. "
                                          "'{field}_{band}_drz.fits')")
    science = _check_template(ctx, "survey.science", data["science"])
    noise = data.get("noise")
    noise = None if noise is None else _check_template(ctx, "survey.noise", noise)
    noise_type = _str(ctx, "survey.noise_type", data.get("noise_type", "weight"),
                      choices=("weight", "rms"))
    pixel_scale = _opt_float(ctx, "survey.pixel_scale_arcsec", data.get("pixel_scale_arcsec"),
                             gt=0)

    bands_raw = data.get("bands")
    if bands_raw is None:
        raise ctx.error("survey.bands", "missing required key (mapping band -> settings)")
    if not isinstance(bands_raw, Mapping) or not bands_raw:
        raise ctx.error("survey.bands", f"expected a non-empty mapping band -> settings, "
                                        f"got {_show(bands_raw)}")
    bands, lower = [], set()
    for name, bdata in bands_raw.items():
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_]+", name):
            raise ctx.error(f"survey.bands.{name}", "band names must be strings of letters, "
                                                   "digits and '_' (they become column names)")
        if name.lower() in lower:
            raise ctx.error(f"survey.bands.{name}", "duplicate band name (case-insensitive)")
        lower.add(name.lower())
        bands.append(_parse_band(ctx, name, bdata, base_dir))

    det = data.get("detection_band")
    if det is None:
        if len(bands) != 1:
            raise ctx.error("survey.detection_band", "missing required key (one of "
                                                     f"{', '.join(b.name for b in bands)})")
        det = bands[0].name
    det = _str(ctx, "survey.detection_band", det)
    match = [b.name for b in bands if b.name.lower() == det.lower()]
    if not match:
        close = difflib.get_close_matches(det, [b.name for b in bands], n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ctx.error("survey.detection_band", f"{det!r} is not one of the bands "
                                                 f"({', '.join(b.name for b in bands)}){hint}")
    det = match[0]

    for key, tmpl in (("survey.science", science), ("survey.noise", noise)):
        if tmpl is None:
            continue
        names = _template_names(tmpl)
        if len(bands) > 1 and "band" not in names:
            raise ctx.error(key, f"template {tmpl!r} has no {{band}} but there are "
                                 f"{len(bands)} bands")
        if len(fields) > 1 and "field" not in names:
            raise ctx.error(key, f"template {tmpl!r} has no {{field}} but there are "
                                 f"{len(fields)} fields")
    return SurveyConfig(fields=fields, image_dir=image_dir, science=science, noise=noise,
                        noise_type=noise_type, pixel_scale_arcsec=pixel_scale,
                        detection_band=det, bands=tuple(bands))


def _axis_values(ctx, path, spec, *, ge=None) -> tuple[float, ...]:
    if not isinstance(spec, Mapping):
        raise ctx.error(path, f"expected {{min, max, step}}, {{min, max, n_bins}} or "
                              f"{{values: [...]}}, got {_show(spec)}")
    _check_keys(ctx, path, spec, ("min", "max", "step", "n_bins", "values"))
    if "values" in spec:
        extra = [k for k in spec if k != "values"]
        if extra:
            raise ctx.error(f"{path}.{extra[0]}", "cannot be combined with values")
        values = _float_list(ctx, f"{path}.values", spec["values"], ge=ge)
        if any(b <= a for a, b in zip(values, values[1:])):
            raise ctx.error(f"{path}.values", "must be strictly increasing")
        return values
    for req in ("min", "max"):
        if req not in spec:
            raise ctx.error(f"{path}.{req}", "missing required key")
    lo = _float(ctx, f"{path}.min", spec["min"], ge=ge)
    hi = _float(ctx, f"{path}.max", spec["max"], ge=ge)
    if lo > hi:
        raise ctx.error(path, f"min ({lo:g}) > max ({hi:g})")
    if ("step" in spec) == ("n_bins" in spec):
        raise ctx.error(path, "give exactly one of step and n_bins")
    if "step" in spec:
        step = _float(ctx, f"{path}.step", spec["step"], gt=0)
        # max is included when it lies within step/1000 of the grid.
        n = int(math.floor((hi - lo + step / 1000.0) / step)) + 1
        values = [lo + k * step for k in range(n)]
    else:
        n = _int(ctx, f"{path}.n_bins", spec["n_bins"], ge=1)
        if n == 1 and hi != lo:
            raise ctx.error(f"{path}.n_bins", "n_bins = 1 needs min == max")
        values = [lo + k * (hi - lo) / (n - 1) for k in range(n)] if n > 1 else [lo]
    if len(values) > 10000:
        raise ctx.error(path, f"{len(values)} grid values: is the step too small?")
    # Round away binary noise (9.0 + 3*0.2 = 9.600000000000001).
    return tuple(round(v, 10) for v in values)


def _parse_grid(ctx, data) -> GridConfig:
    data = {} if data is None else data
    _check_keys(ctx, "grid", data, ("z", "mag", "magnitude_type"))
    z = _axis_values(ctx, "grid.z", data.get("z", GRID_DEFAULTS["z"]), ge=0.0)
    mag = _axis_values(ctx, "grid.mag", data.get("mag", GRID_DEFAULTS["mag"]))
    mtype = _str(ctx, "grid.magnitude_type", data.get("magnitude_type", "apparent"),
                 choices=("apparent", "absolute"))
    return GridConfig(z_values=z, mag_values=mag, magnitude_type=mtype)


def _parse_simulation(ctx, data) -> SimulationConfig:
    data = {} if data is None else data
    _check_keys(ctx, "simulation", data, tuple(SIMULATION_DEFAULTS))
    d = {**SIMULATION_DEFAULTS, **{k: v for k, v in data.items() if v is not None}}
    return SimulationConfig(
        n_galaxies=_int(ctx, "simulation.n_galaxies", d["n_galaxies"], ge=1),
        n_iterations=_int(ctx, "simulation.n_iterations", d["n_iterations"], ge=1),
        seed=_int(ctx, "simulation.seed", d["seed"], ge=0),
        isolation_fraction=_float(ctx, "simulation.isolation_fraction", d["isolation_fraction"],
                                  gt=0, le=1))


# astropy's realisations; importing astropy.cosmology to list them takes seconds.
_KNOWN_COSMOLOGIES = ("WMAP1", "WMAP3", "WMAP5", "WMAP7", "WMAP9", "Planck13", "Planck15",
                      "Planck18")


def _cosmology_names(name: str) -> tuple[str, ...]:
    if name in _KNOWN_COSMOLOGIES:
        return _KNOWN_COSMOLOGIES
    from astropy.cosmology import realizations
    return tuple(realizations.available)


def _parse_source(ctx, data) -> dict:
    data = {} if data is None else data
    _check_keys(ctx, "source", data, tuple(SOURCE_DEFAULTS))
    d = {**SOURCE_DEFAULTS, **{k: v for k, v in data.items() if v is not None}}
    p = "source."
    out = {
        "r_eff_kpc_z6": _float(ctx, p + "r_eff_kpc_z6", d["r_eff_kpc_z6"], gt=0),
        "size_evolution": _float(ctx, p + "size_evolution", d["size_evolution"]),
        "r_eff_scatter_dex": _float(ctx, p + "r_eff_scatter_dex", d["r_eff_scatter_dex"], ge=0),
        "size_luminosity_slope": _float(ctx, p + "size_luminosity_slope",
                                        d["size_luminosity_slope"]),
        "sersic_indices": _float_list(ctx, p + "sersic_indices", d["sersic_indices"],
                                      ge=0.2, le=10.0),
        "sersic_fractions": _float_list(ctx, p + "sersic_fractions", d["sersic_fractions"],
                                        ge=0.0, le=1.0),
        "ellipticity_bins": _int(ctx, p + "ellipticity_bins", d["ellipticity_bins"], ge=1),
        "position_angle_bins": _int(ctx, p + "position_angle_bins", d["position_angle_bins"],
                                    ge=1),
        "round_de_vaucouleurs": _bool(ctx, p + "round_de_vaucouleurs",
                                      d["round_de_vaucouleurs"]),
        "beta_mean": _float(ctx, p + "beta_mean", d["beta_mean"]),
        "beta_sd": _float(ctx, p + "beta_sd", d["beta_sd"], ge=0),
        "beta_per": _str(ctx, p + "beta_per", d["beta_per"], choices=("source", "iteration")),
        "igm": _str(ctx, p + "igm", d["igm"], choices=("inoue14", "madau95", "sharp")),
        "cosmology": _str(ctx, p + "cosmology", d["cosmology"]),
        "stamp_flux_fraction": _float(ctx, p + "stamp_flux_fraction", d["stamp_flux_fraction"],
                                      gt=0, lt=1),
    }
    n_idx, n_frac = len(out["sersic_indices"]), len(out["sersic_fractions"])
    if n_idx != n_frac:
        raise ctx.error(p + "sersic_fractions", f"has {n_frac} value(s) but sersic_indices "
                                                f"has {n_idx}")
    total = sum(out["sersic_fractions"])
    if abs(total - 1.0) > 1e-6:
        raise ctx.error(p + "sersic_fractions", f"must sum to 1, got {total:g}")
    names = _cosmology_names(out["cosmology"])
    if out["cosmology"] not in names:
        close = difflib.get_close_matches(out["cosmology"], names, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise ctx.error(p + "cosmology", f"unknown astropy cosmology {out['cosmology']!r} "
                                         f"(available: {', '.join(names)}){hint}")
    return out


# --- detection (SExtractor vocabulary) -------------------------------------
def _det_filter_name(ctx, path, value, base_dirs) -> str:
    value = _str(ctx, path, value)
    if not _looks_like_path(value, (".conv",)):
        return value                          # built-in kernel name
    for d in base_dirs:
        p = _resolve(d, value)
        if p.is_file():
            return str(p)
    return str(_resolve(base_dirs[0], value))  # missing: check_files reports it


def _square_int(ctx, path, value) -> int:
    # SExtractor allows "64,64"; non-square meshes are not supported by sep.
    if isinstance(value, (list, tuple)):
        vals = {_int(ctx, path, v, ge=1) for v in value}
        if len(vals) != 1:
            raise ctx.error(path, f"different values per axis ({value}) are not supported")
        return vals.pop()
    return _int(ctx, path, value, ge=1)


_DETECTION_PARSERS = {
    "DETECT_THRESH": lambda c, p, v: _float(c, p, v, gt=0),
    "DETECT_MINAREA": lambda c, p, v: _int(c, p, v, ge=1),
    "FILTER": _bool,
    "DEBLEND_NTHRESH": lambda c, p, v: _int(c, p, v, ge=1),
    "DEBLEND_MINCONT": lambda c, p, v: _float(c, p, v, ge=0, le=1),
    "CLEAN": _bool,
    "CLEAN_PARAM": lambda c, p, v: _float(c, p, v, gt=0),
    "BACK_SIZE": _square_int,
    "BACK_FILTERSIZE": _square_int,
    "PHOT_APERTURES": lambda c, p, v: _float_list(c, p, v, gt=0),
    "PHOT_AUTOPARAMS": lambda c, p, v: _float_list(c, p, v, min_len=2, gt=0),
    "FILTER_TYPE": lambda c, p, v: _filter_type(c, p, v),
}
# Optional keys: absent from the resolved dict unless given (config or .sex).
_DETECTION_OPTIONAL = ("FILTER_TYPE",)


def _filter_type(ctx, path, value) -> str:
    v = _str(ctx, path, value).lower()
    v = {"convolve": "conv"}.get(v, v)   # SExtractor's spelling
    if v not in ("conv", "matched"):
        raise ctx.error(path, f"expected CONVOLVE (conv) or MATCHED, got {value!r}")
    return v
_SEX_BOOL_KEYS = ("FILTER", "CLEAN")
_SEX_LIST_KEYS = ("PHOT_APERTURES", "PHOT_AUTOPARAMS", "BACK_SIZE", "BACK_FILTERSIZE")


def read_sex_file(path: str | os.PathLike) -> dict[str, Any]:
    """Read the detection keys glaciar uses from a SExtractor ``.sex`` file.

    Parameters
    ----------
    path : path-like
        SExtractor configuration file (``KEY value  # comment`` lines).

    Returns
    -------
    dict
        Upper-case keys among ``DETECTION_DEFAULTS`` (and ``FILTER_TYPE``, ``THRESH_TYPE``)
        with raw values: numbers, lists of numbers, booleans for Y/N keys,
        strings for ``FILTER_NAME``. Keys glaciar does not use are skipped.
    """
    from .engine.detect import read_sex_file as _read_sex_tokens

    out: dict[str, Any] = {}
    wanted = set(_DETECTION_PARSERS) | {"FILTER_NAME", "THRESH_TYPE"}
    for key, value in _read_sex_tokens(path).items():
        if key not in wanted:
            continue
        # SExtractor separates list values with commas; accept blanks too.
        tokens = [t for v in (value if isinstance(value, list) else [value])
                  for t in re.split(r"[\s,]+", v.strip()) if t]
        if not tokens:
            continue
        if key in _SEX_BOOL_KEYS:
            out[key] = tokens[0]
        elif key in ("FILTER_NAME", "THRESH_TYPE", "FILTER_TYPE"):
            out[key] = tokens[0]
        elif key in _SEX_LIST_KEYS:
            out[key] = tokens if len(tokens) > 1 else tokens[0]
        else:
            out[key] = tokens[0]   # e.g. DETECT_THRESH "1.5,25": sigma is the first value
    for key in _SEX_LIST_KEYS:
        if key in out and isinstance(out[key], list):
            out[key] = [_num(t) for t in out[key]]
        elif key in out:
            out[key] = [_num(out[key])] if key.startswith("PHOT") else _num(out[key])
    for key in ("DETECT_MINAREA", "DEBLEND_NTHRESH"):
        if key in out:
            out[key] = _num(out[key])
    return out


def _num(token: str):
    try:
        return int(token)
    except ValueError:
        try:
            return float(token)
        except ValueError:
            return token


def _parse_detection(ctx, data, base_dir) -> dict:
    data = {} if data is None else data
    if not isinstance(data, Mapping):
        raise ctx.error("detection", f"expected a mapping of keys, got {_show(data)}")
    explicit = {}
    allowed = ("sex_file",) + tuple(k for k in DETECTION_DEFAULTS if k != "sex_file") + \
        _DETECTION_OPTIONAL
    for key, value in data.items():
        k = str(key) if str(key) == "sex_file" else str(key).upper()
        if k not in allowed:
            close = difflib.get_close_matches(k, allowed, n=1, cutoff=0.6)
            hint = f"did you mean {close[0]!r}?" if close else \
                f"allowed keys: {', '.join(allowed)}"
            raise ctx.error(f"detection.{key}", f"unknown key {key!r}; {hint}")
        explicit[k] = value
    merged = dict(DETECTION_DEFAULTS)
    sex_path = None
    if explicit.get("sex_file") is not None:
        sex_path = _resolve(base_dir, _str(ctx, "detection.sex_file", explicit["sex_file"]))
        if not sex_path.is_file():
            raise ctx.error("detection.sex_file", f"file not found: {sex_path}")
        sctx = _Ctx(str(sex_path), sex_path.parent)
        from_sex = read_sex_file(sex_path)
        ttype = str(from_sex.pop("THRESH_TYPE", "RELATIVE")).upper()
        if ttype != "RELATIVE":
            raise sctx.error("THRESH_TYPE", f"only RELATIVE thresholds (in units of the "
                                            f"background RMS) are supported, got {ttype}")
        for k, v in from_sex.items():
            if k == "FILTER_NAME":
                merged[k] = _sex_filter_name(ctx, sctx, v, sex_path.parent, base_dir)
            else:
                merged[k] = _DETECTION_PARSERS[k](sctx, k, v)
    merged["sex_file"] = None if sex_path is None else str(sex_path)
    for k, v in explicit.items():
        if k == "sex_file" or v is None:
            continue
        path = f"detection.{k}"
        if k == "FILTER_NAME":
            merged[k] = _det_filter_name(ctx, path, v, [base_dir])
        else:
            merged[k] = _DETECTION_PARSERS[k](ctx, path, v)
    return merged


def _sex_filter_name(ctx, sctx, value, sex_dir: Path, base_dir: Path) -> str:
    value = _str(sctx, "FILTER_NAME", value)
    for d in (sex_dir, base_dir):
        p = _resolve(d, value)
        if p.is_file():
            return str(p)
    # SExtractor resolves FILTER_NAME from its working directory, which we do
    # not know; fall back to the built-in kernel of the same name.
    stem = Path(value).name
    if stem.lower().endswith(".conv"):
        stem = stem[:-5]
    ctx.warnings.append(f"{sctx.source}: FILTER_NAME {value!r} not found next to the .sex "
                        f"file or the config; using the built-in kernel {stem!r}")
    return stem


def _parse_classification(ctx, data, n_apertures: int) -> dict:
    data = {} if data is None else data
    _check_keys(ctx, "classification", data, tuple(CLASSIFICATION_DEFAULTS))
    d = {**CLASSIFICATION_DEFAULTS, **{k: v for k, v in data.items() if v is not None}}
    p = "classification."
    out = {
        "min_sn": _float(ctx, p + "min_sn", d["min_sn"], ge=0),
        "sn_definition": _str(ctx, p + "sn_definition", d["sn_definition"],
                              choices=("iso", "aper", "auto")),
        "sn_aperture_index": _int(ctx, p + "sn_aperture_index", d["sn_aperture_index"], ge=0),
        "search_box": _int(ctx, p + "search_box", d["search_box"], ge=1),
        "max_overlap_fraction": _float(ctx, p + "max_overlap_fraction",
                                       d["max_overlap_fraction"], ge=0, le=1),
        "flux_tolerance": _float(ctx, p + "flux_tolerance", d["flux_tolerance"], gt=0),
    }
    if out["search_box"] % 2 == 0:
        raise ctx.error(p + "search_box", f"must be odd so the box is centred on the input "
                                          f"position, got {out['search_box']}")
    if out["sn_aperture_index"] >= n_apertures:
        raise ctx.error(p + "sn_aperture_index", f"is {out['sn_aperture_index']} but "
                                                 f"detection.PHOT_APERTURES has {n_apertures} "
                                                 f"aperture(s)")
    return out


def _parse_output(ctx, data) -> dict:
    data = {} if data is None else data
    _check_keys(ctx, "output", data, tuple(OUTPUT_DEFAULTS))
    regions = data.get("regions")
    return {"regions": False if regions is None else _bool(ctx, "output.regions", regions)}


def selection_columns(band_names, n_apertures: int) -> tuple[str, ...]:
    """Names of the per-source columns a selection expression may use.

    Parameters
    ----------
    band_names : iterable of str
        Survey bands.
    n_apertures : int
        Number of photometric apertures (``flux_aper{k}_<band>``, k = 0..n-1).

    Returns
    -------
    tuple of str
        Every ``COL_*`` column of :mod:`glaciar.constants` and every per-band
        quantity (``BAND_QUANTITIES`` plus aperture fluxes) for every band.
    """
    cols = [getattr(constants, n) for n in dir(constants) if n.startswith("COL_")]
    for b in band_names:
        cols += [constants.band_column(q, b) for q in constants.BAND_QUANTITIES]
        for k in range(n_apertures):
            cols += [constants.band_column(f"flux_aper{k}", b),
                     constants.band_column(f"fluxerr_aper{k}", b)]
    return tuple(dict.fromkeys(cols))


def _parse_selection(ctx, data, present: bool, columns) -> tuple[str, ...]:
    if not present:
        try:
            compile_selection(DEFAULT_JDROPOUT, columns)
        except SelectionError:
            ctx.warnings.append("selection: no selection given and the default BoRG "
                                "J-dropout criteria need bands f160w, f125w, f098m and "
                                "f606w; no selection is applied (selected = recovered)")
            return ()
        return DEFAULT_JDROPOUT
    if data is None:
        return ()
    if isinstance(data, str):
        data = [data]
    if not isinstance(data, (list, tuple)):
        raise ctx.error("selection", f"expected a list of expression strings, got {_show(data)}")
    exprs = []
    for i, e in enumerate(data):
        if not isinstance(e, str):
            raise ctx.error(f"selection[{i}]", f"expected an expression string, got {_show(e)} "
                                               f"(quote expressions in YAML)")
        try:
            compile_selection([e], columns)
        except SelectionError as exc:
            raise ctx.error(f"selection[{i}]", str(exc)) from None
        exprs.append(e.strip())
    return tuple(exprs)


# ---------------------------------------------------------------------------
# GLACiAR parameters.yaml
# ---------------------------------------------------------------------------
_GLACIAR_KEYS = (
    "n_galaxies", "n_iterations", "mag_bins", "min_mag", "max_mag", "z_bins", "min_z", "max_z",
    "n_bands", "detection_band", "lambda_detection", "bands", "list_of_fields", "R_eff",
    "beta_mean", "beta_sd", "size_pix", "path_to_images", "image_name", "types_galaxies",
    "sersic_indices", "sersic_indexes", "fraction_type_galaxies", "fractions", "ibins", "ebins",
    "zeropoints", "gain_values", "min_sn", "dropouts", "de_Vacouleur")
_GLACIAR_TO_SCHEMA = {
    "n_galaxies": "simulation.n_galaxies", "n_iterations": "simulation.n_iterations",
    "mag_bins": "grid.mag", "min_mag": "grid.mag", "max_mag": "grid.mag", "z_bins": "grid.z",
    "min_z": "grid.z", "max_z": "grid.z", "bands": "survey.bands",
    "detection_band": "survey.detection_band", "list_of_fields": "survey.fields_file",
    "R_eff": "source.r_eff_kpc_z6", "beta_mean": "source.beta_mean", "beta_sd": "source.beta_sd",
    "size_pix": "survey.pixel_scale_arcsec", "path_to_images": "survey.image_dir",
    "image_name": "survey.science", "sersic_indices": "source.sersic_indices",
    "fraction_type_galaxies": "source.sersic_fractions", "ibins": "source.position_angle_bins",
    "ebins": "source.ellipticity_bins", "min_sn": "classification.min_sn",
    "dropouts": "selection", "de_Vacouleur": "source.round_de_vaucouleurs"}

# HST-like PSF FWHM of drizzled images [arcsec], for GLACiAR files (which have no PSF key).
_HST_FWHM_ARCSEC = {"f098m": 0.16, "f105w": 0.16, "f110w": 0.17, "f125w": 0.17, "f140w": 0.18,
                    "f160w": 0.18}
_HST_OPTICAL_FWHM_ARCSEC = 0.10
_ACS_ONLY = ("f435w", "f502n", "f550m", "f625w", "f658n", "f660n", "f775w", "f850lp", "f892n")


def is_glaciar_parameters(data) -> bool:
    """True if ``data`` (a parsed YAML mapping) is a GLACiAR ``parameters.yaml``."""
    return isinstance(data, Mapping) and "survey" not in data and \
        bool(set(map(str, data)) & set(_GLACIAR_KEYS))


def _glaciar_hst_name(ctx, b: str) -> str | None:
    m = re.fullmatch(r"f(\d{3})([a-z]+)", b)
    if not m:
        return None
    if 90 <= int(m.group(1)) < 200:
        return f"wfc3_ir_{b}"
    if b == "f606w":
        # BoRG is a WFC3 pure-parallel survey; GLACiAR's own Files/f606w.tab is the
        # WFC3/UVIS curve (it matches sedpy's wfc3_uvis_f606w to 3e-4 of the peak,
        # acs_wfc_f606w only to 0.39) and its zeropoint (26.07) the UVIS one. Only its
        # (never applied) PSF file is ACS.
        ctx.warnings.append("bands: f606w is ambiguous (WFC3/UVIS or ACS/WFC); mapped to "
                            "wfc3_uvis_f606w like GLACiAR's Files/f606w.tab (BoRG is a WFC3 "
                            "survey). Set survey.bands.f606w.filter: acs_wfc_f606w in a "
                            "schema config if your images are ACS.")
        return "wfc3_uvis_f606w"
    if b in _ACS_ONLY:
        return f"acs_wfc_{b}"
    if b in ("f475w", "f555w", "f814w"):
        ctx.warnings.append(f"bands: {b} is ambiguous (WFC3/UVIS or ACS/WFC); mapped to "
                            f"wfc3_uvis_{b}")
    return f"wfc3_uvis_{b}"


def _glaciar_filter(ctx, band: str, base_dir: Path) -> str:
    """Built-in HST filter for a GLACiAR band name, else GLACiAR's Files/<band>.tab."""
    name = _glaciar_hst_name(ctx, band.lower())
    try:
        from .galaxy.filters import BUILTIN_FILTERS
        shipped = name is not None and BUILTIN_FILTERS.get(name) is not None
    except ImportError:
        shipped = name is not None
    if shipped:
        return name
    tab = base_dir / "Files" / f"{band}.tab"
    if tab.is_file():
        ctx.warnings.append(f"bands: {band}: no built-in curve; using GLACiAR's {tab}")
        return str(tab)
    what = f"the built-in {name!r} curve is not shipped" if name else \
        f"{band!r} is not an HST filter name"
    raise ctx.error("bands", f"band {band!r}: {what} and there is no {tab}; use a schema "
                             f"config with survey.bands.{band}.filter: <curve file>")


def _glaciar_to_schema(ctx: _Ctx, data: Mapping, base_dir: Path) -> dict:
    hints = {k: f"not a GLACiAR key; GLACiAR files cannot be mixed with the `{k}:` section"
             for k in _TOP_KEYS}
    _check_keys(ctx, "", data, _GLACIAR_KEYS, hints)
    ctx.origins.update({v: k for k, v in _GLACIAR_TO_SCHEMA.items()})
    warn = ctx.warnings.append
    missing = object()

    def get(key, default=missing):
        # GLACiAR: a key present with an empty value takes the default.
        value = data.get(key)
        if value is None:
            if default is missing:
                raise ctx.error(key, "missing required GLACiAR key")
            return default
        return value

    bands = get("bands")
    if isinstance(bands, str):
        bands = [bands]
    if not isinstance(bands, list) or not all(isinstance(b, str) for b in bands):
        raise ctx.error("bands", f"expected a list of band names, got {_show(bands)}")
    nb = len(bands)
    n_bands = _int(ctx, "n_bands", get("n_bands", nb), ge=1)
    if n_bands != nb:
        raise ctx.error("n_bands", f"is {n_bands} but bands lists {nb} band(s)")
    det = _str(ctx, "detection_band", get("detection_band"))
    if det not in bands:
        raise ctx.error("detection_band", f"{det!r} is not in bands ({', '.join(bands)})")

    zps = data.get("zeropoints")
    if zps is None or not isinstance(zps, list) or len(zps) < nb:
        warn("zeropoints: missing or shorter than bands; GLACiAR's default 25.0 is used for "
             "every band")
        zps = [25.0] * nb
    gains = data.get("gain_values")
    if gains is not None and (not isinstance(gains, list) or len(gains) < nb):
        raise ctx.error("gain_values", f"expected a list of {nb} gains (one per band), "
                                       f"got {_show(gains)}")

    # Science: <path_to_images><image_name><field>_<band>.fits (string concatenation).
    prefix = _str(ctx, "path_to_images", get("path_to_images")) + \
        _str(ctx, "image_name", get("image_name"))
    image_dir, stem = os.path.split(prefix)
    stem = stem.replace("{", "{{").replace("}", "}}")

    band_cfg = {}
    for i, b in enumerate(bands):
        psf_file = base_dir / "Files" / f"psf_{b}.fits"
        if psf_file.is_file():
            psf = str(psf_file)
            warn(f"bands: {b}: using the PSF file {psf_file} (GLACiAR computed but never "
                 f"applied its PSF convolution; glaciar applies it, resampled by its header "
                 f"pixel scale)")
        else:
            fwhm = _HST_FWHM_ARCSEC.get(b.lower(), _HST_OPTICAL_FWHM_ARCSEC)
            psf = {"profile": "moffat", "fwhm_arcsec": fwhm, "beta": 2.5}
            warn(f"bands: {b}: parameters.yaml has no PSF; using an analytic Moffat PSF with "
                 f"HST-like FWHM {fwhm}\" (set survey.bands.{b}.psf in a schema config)")
        band_cfg[b] = {"filter": _glaciar_filter(ctx, b, base_dir), "zeropoint": zps[i],
                       "gain": None if gains is None else gains[i], "psf": psf}
        ctx.origins[f"survey.bands.{b}.zeropoint"] = f"zeropoints[{i}]"
        ctx.origins[f"survey.bands.{b}.gain"] = f"gain_values[{i}]"
    if gains is None:
        warn("gain_values: missing; no source Poisson noise is added")

    survey = {"fields_file": _str(ctx, "list_of_fields", get("list_of_fields")),
              "image_dir": image_dir or ".",
              "science": stem + "{field}_{band}.fits",
              "noise": stem + "{field}_{band}_rms.fits",
              "noise_type": "rms",
              "pixel_scale_arcsec": data.get("size_pix"),
              "detection_band": det,
              "bands": band_cfg}

    def centres(kmin, kmax, kbins, dmin, dmax, dbins):
        lo = _float(ctx, kmin, get(kmin, dmin))
        hi = _float(ctx, kmax, get(kmax, dmax))
        n = _int(ctx, kbins, get(kbins, dbins), ge=1)
        if lo > hi:
            raise ctx.error(kmin, f"{kmin} ({lo:g}) > {kmax} ({hi:g})")
        if n == 1:
            return {"values": [lo]}
        step = (hi - lo) / (n - 1)
        if abs(step - 0.2) > 1e-9:
            warn(f"{kbins}: GLACiAR simulates {kmin} + 0.2k but labels its tables "
                 f"{kmin} + k({kmax}-{kmin})/({kbins}-1) (step {step:.4g}); glaciar simulates "
                 f"the labelled values")
        return {"values": [round(lo + k * step, 10) for k in range(n)]}

    grid = {"z": centres("min_z", "max_z", "z_bins", 9.0, 11.9, 15),
            "mag": centres("min_mag", "max_mag", "mag_bins", 24.1, 27.9, 20),
            "magnitude_type": "apparent"}
    simulation = {"n_galaxies": get("n_galaxies", 100), "n_iterations": get("n_iterations", 100)}

    indices = data.get("sersic_indices", data.get("sersic_indexes"))
    fractions = data.get("fraction_type_galaxies", data.get("fractions"))
    indices = [1.0, 4.0] if indices is None else indices
    fractions = [0.5, 0.5] if fractions is None else fractions
    types = data.get("types_galaxies")
    if types is not None and isinstance(indices, list) and _int(ctx, "types_galaxies", types,
                                                                 ge=1) != len(indices):
        raise ctx.error("types_galaxies", f"is {types} but sersic_indices lists "
                                          f"{len(indices)} value(s)")
    ctx.origins["source.sersic_fractions"] = "fraction_type_galaxies" \
        if "fraction_type_galaxies" in data else "fractions"
    r_eff = _float(ctx, "R_eff", get("R_eff", 1.075), gt=0)
    warn(f"R_eff: {r_eff:g} is read as proper kpc at z = 6 (the paper's meaning); GLACiAR's "
         f"code used it as pixels at z = 6 with no cosmology")
    ibins = _int(ctx, "ibins", get("ibins", 1), ge=1)
    ebins = _int(ctx, "ebins", get("ebins", 1), ge=1)
    if ibins > 1:
        warn(f"ibins: {ibins} position angles spread over 0-180 deg (GLACiAR: k*90/ibins deg, "
             f"0-90 deg)")
    if ebins > 1:
        warn(f"ebins: ellipticities e = k/{ebins}, k = 0..{ebins - 1}, including round "
             f"(GLACiAR's code never drew k = 0)")
    source = {"r_eff_kpc_z6": r_eff, "beta_mean": get("beta_mean", -2.2),
              "beta_sd": get("beta_sd", 0.4), "sersic_indices": indices,
              "sersic_fractions": fractions, "position_angle_bins": ibins,
              "ellipticity_bins": ebins,
              "round_de_vaucouleurs": _bool(ctx, "de_Vacouleur", get("de_Vacouleur", False)),
              "beta_per": "iteration", "igm": "sharp"}
    warn("source: beta_per = iteration and igm = sharp reproduce the paper's spectrum model "
         "(one beta per iteration, zero flux below rest 1216 A)")

    sex = base_dir / "SExtractor_files" / "parameters.sex"
    if sex.is_file():
        detection = {"sex_file": str(sex)}
    else:
        # GLACiAR's SExtractor template (SExtractor_files/parameters.sex).
        detection = {"DETECT_THRESH": 0.7, "DETECT_MINAREA": 9, "FILTER": True,
                     "FILTER_NAME": "gauss_2.0_5x5", "DEBLEND_NTHRESH": 32,
                     "DEBLEND_MINCONT": 0.005, "CLEAN": True, "CLEAN_PARAM": 1.0,
                     "BACK_SIZE": 64, "BACK_FILTERSIZE": 3,
                     "PHOT_APERTURES": [2.0, 4.0, 6.0, 8.0, 10.0],
                     "PHOT_AUTOPARAMS": [1.5, 3.5]}
    min_sn = _float(ctx, "min_sn", get("min_sn", 8.0), ge=0)

    selection: list[str] = []
    if _bool(ctx, "dropouts", get("dropouts", False)):
        if nb < 4:
            raise ctx.error("dropouts", f"the J-dropout selection needs 4 bands ordered "
                                        f"[H, Y, J, V] as in GLACiAR, got {nb}")
        h, y, j, v = (b.lower() for b in bands[:4])
        selection = [f"sn_{h} >= {min_sn:g}", f"sn_{v} < 1.5", f"sn_{y} < 1.5",
                     f"maglim_{j} - mag_{h} > 1.5"]
        if (h, y, j, v) != ("f160w", "f098m", "f125w", "f606w"):
            warn(f"dropouts: GLACiAR's band order is [H, Y, J, V]; the J-dropout cuts use "
                 f"H={h}, Y={y}, J={j}, V={v}")
    return {"survey": survey, "grid": grid, "simulation": simulation, "source": source,
            "detection": detection, "classification": {"min_sn": min_sn},
            "selection": selection}


# ---------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------
def config_from_dict(data: Mapping, base_dir: str | os.PathLike = ".",
                     source_name: str = "<dict>", *, path: str | os.PathLike | None = None
                     ) -> Config:
    """Validate a parsed configuration mapping.

    Parameters
    ----------
    data : mapping
        The parsed YAML (schema sections, or GLACiAR's flat keys).
    base_dir : path-like
        Directory that relative paths are relative to.
    source_name : str
        Name used in error messages (normally the file name).
    path : path-like, optional
        The file the mapping came from, recorded as ``Config.path``.

    Returns
    -------
    Config

    Raises
    ------
    ConfigError
        Unknown key (with a suggestion), wrong type, out-of-range value,
        missing required key; the message names the file and the key path.
    """
    base_dir = Path(base_dir).expanduser().resolve()
    ctx = _Ctx(source_name, base_dir)
    if data is None:
        raise ctx.error("<top level>", "the configuration is empty")
    if not isinstance(data, Mapping):
        raise ctx.error("<top level>", f"expected a mapping of sections, got {_show(data)}")
    if is_glaciar_parameters(data):
        data = _glaciar_to_schema(ctx, data, base_dir)
    else:
        hints = {k: f"a GLACiAR parameters.yaml key; in this schema use {v}"
                 for k, v in _GLACIAR_TO_SCHEMA.items()}
        _check_keys(ctx, "", data, _TOP_KEYS, hints)
    survey = _parse_survey(ctx, data.get("survey"), base_dir)
    grid = _parse_grid(ctx, data.get("grid"))
    simulation = _parse_simulation(ctx, data.get("simulation"))
    source = _parse_source(ctx, data.get("source"))
    detection = _parse_detection(ctx, data.get("detection"), base_dir)
    n_ap = len(detection["PHOT_APERTURES"])
    classification = _parse_classification(ctx, data.get("classification"), n_ap)
    columns = selection_columns(survey.band_names, n_ap)
    selection = _parse_selection(ctx, data.get("selection"), "selection" in data, columns)
    output = _parse_output(ctx, data.get("output"))
    return Config(path=None if path is None else Path(path).resolve(), base_dir=base_dir,
                  survey=survey, grid=grid, simulation=simulation, source=source,
                  detection=detection, classification=classification, selection=selection,
                  output=output, warnings=tuple(ctx.warnings))


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys (PyYAML silently keeps the last)."""


def _unique_mapping(loader, node, deep=False):
    seen = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r}", key_node.start_mark)
            seen.add(key)
        except TypeError:
            pass
    return loader.construct_mapping(node, deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)


def load_config(path: str | os.PathLike) -> Config:
    """Read and validate a YAML configuration file.

    Parameters
    ----------
    path : path-like
        A glaciar config (see :func:`template_yaml`) or a GLACiAR
        ``parameters.yaml``. Relative paths inside are relative to its directory.

    Returns
    -------
    Config

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ConfigError
        YAML syntax error (with line and column) or invalid content.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"config file not found: {path}")
    try:
        data = yaml.load(path.read_text(), Loader=_UniqueKeyLoader)  # noqa: S506 (safe loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{path}: {where}invalid YAML ({problem})") from None
    return config_from_dict(data, path.resolve().parent, str(path), path=path)


def _plain(value, relative_to: Path | None = None):
    if isinstance(value, Mapping):
        return {str(k): _plain(v, relative_to) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v, relative_to) for v in value]
    if isinstance(value, Path):
        value = str(value)
    if isinstance(value, str) and relative_to is not None and os.path.isabs(value):
        return Path(os.path.relpath(value, relative_to)).as_posix()
    return value


def config_to_dict(cfg: Config, relative_to: str | os.PathLike | None = None) -> dict:
    """The resolved configuration as plain data (YAML/JSON-serialisable).

    Parameters
    ----------
    cfg : Config
    relative_to : path-like, optional
        Write paths relative to this directory instead of absolute.

    Returns
    -------
    dict
        Schema-shaped mapping with every default filled in;
        ``config_from_dict(config_to_dict(cfg), base_dir)`` equals ``cfg``
        (with ``base_dir = relative_to`` when that is given).
    """
    rel = None if relative_to is None else Path(relative_to).resolve()
    s = cfg.survey
    bands = {}
    for b in s.bands:
        bands[b.name] = {"filter": b.filter, "zeropoint": b.zeropoint, "gain": b.gain,
                         "psf": copy.deepcopy(b.psf),
                         "psf_pixel_scale_arcsec": b.psf_pixel_scale_arcsec}
    psf_paths = {b.name: b.psf for b in s.bands if isinstance(b.psf, str)}
    out = {
        "survey": {"fields": list(s.fields), "image_dir": str(s.image_dir),
                   "science": s.science, "noise": s.noise, "noise_type": s.noise_type,
                   "pixel_scale_arcsec": s.pixel_scale_arcsec,
                   "detection_band": s.detection_band, "bands": bands},
        "grid": {"z": {"values": list(cfg.grid.z_values)},
                 "mag": {"values": list(cfg.grid.mag_values)},
                 "magnitude_type": cfg.grid.magnitude_type},
        "simulation": {"n_galaxies": cfg.simulation.n_galaxies,
                       "n_iterations": cfg.simulation.n_iterations,
                       "seed": cfg.simulation.seed,
                       "isolation_fraction": cfg.simulation.isolation_fraction},
        "source": dict(cfg.source),
        "detection": dict(cfg.detection),
        "classification": dict(cfg.classification),
        "selection": list(cfg.selection),
        "output": dict(cfg.output),
    }
    out = _plain(out)
    if rel is not None:
        # Only values that are paths: image_dir, filter/PSF files, sex_file, FILTER_NAME.
        out["survey"]["image_dir"] = _plain(str(s.image_dir), rel)
        for b in s.bands:
            if os.path.isabs(b.filter):
                out["survey"]["bands"][b.name]["filter"] = _plain(b.filter, rel)
            if b.name in psf_paths:
                out["survey"]["bands"][b.name]["psf"] = _plain(psf_paths[b.name], rel)
        for key in ("sex_file", "FILTER_NAME"):
            v = cfg.detection.get(key)
            if isinstance(v, str) and os.path.isabs(v):
                out["detection"][key] = _plain(v, rel)
    return out


def config_hash(cfg: Config) -> str:
    """SHA-256 (hex) of the science-relevant configuration.

    Everything except ``output`` enters, with paths relative to the config's
    directory (so a project moved as a whole keeps its hash), as canonical
    JSON (sorted keys, no whitespace).
    """
    d = config_to_dict(cfg, relative_to=cfg.base_dir)
    d.pop("output", None)
    return _sha256_json(d)


def store_hash(cfg: Config) -> str:
    """SHA-256 (hex) of the settings that fix every task's rows.

    As :func:`config_hash`, but without the field list, the grid's z and
    magnitude values and ``simulation.n_iterations``: those only add or remove
    tasks (each task's random stream is keyed by its field name, z, magnitude
    and iteration, not by its position in the grid), so a results store can be
    extended with more cells or iterations and stay consistent.
    """
    d = config_to_dict(cfg, relative_to=cfg.base_dir)
    d.pop("output", None)
    d["survey"].pop("fields", None)
    d["grid"].pop("z", None)
    d["grid"].pop("mag", None)
    d["simulation"].pop("n_iterations", None)
    return _sha256_json(d)


def _sha256_json(d: dict) -> str:
    text = json.dumps(d, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def template_yaml() -> str:
    """The commented configuration template that ``glaciar init`` writes."""
    return resources.files("glaciar").joinpath("data", "template.yaml").read_text("utf-8")


def missing_files(cfg: Config) -> list[str]:
    """Input files of ``cfg`` that do not exist, one message per file.

    Checks the science and noise image of every field and band, every FITS
    PSF and filter-curve file, and a ``.conv`` detection filter. Each message
    names the key it came from, e.g.
    ``"survey.science (field 'f1', band 'f160w'): /data/f1_f160w.fits"``.
    """
    s = cfg.survey
    out = []
    for f in s.fields:
        for b in s.bands:
            names = (("survey.science", s.science), ("survey.noise", s.noise))
            for key, tmpl in names:
                if tmpl is None:
                    continue
                p = s.image_dir / tmpl.format(field=f, band=b.name)
                if not p.is_file():
                    out.append(f"{key} (field {f!r}, band {b.name!r}): {p}")
    for b in s.bands:
        if isinstance(b.psf, str) and not Path(b.psf).is_file():
            out.append(f"survey.bands.{b.name}.psf: {b.psf}")
        if os.path.isabs(b.filter) and not Path(b.filter).is_file():
            out.append(f"survey.bands.{b.name}.filter: {b.filter}")
    fname = cfg.detection.get("FILTER_NAME")
    if isinstance(fname, str) and os.path.isabs(fname) and not Path(fname).is_file():
        out.append(f"detection.FILTER_NAME: {fname}")
    return out


def check_files(cfg: Config) -> None:
    """Raise FileNotFoundError listing every missing input file (see :func:`missing_files`)."""
    missing = missing_files(cfg)
    if missing:
        name = cfg.path if cfg.path is not None else "config"
        raise FileNotFoundError(f"{name}: {len(missing)} input file(s) not found:\n  "
                                + "\n  ".join(missing))
