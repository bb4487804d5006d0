"""SExtractor configuration files (``.sex``): the one reader, and its mapping onto glaciar.

A ``.sex`` file is lines of ``KEY value[,value...]  # comment``. glaciar reads
the detection and photometry keys it honours (:data:`HONOURED_KEYS`) into the
``detection:`` section (:class:`glaciar.config.models.DetectionConfig`), where
keys given explicitly in the YAML win. No key is ignored silently: a key
either is honoured, has no effect on what glaciar measures
(:data:`NO_EFFECT_KEYS`: catalogue output, memory, ...), is accepted at the
one value glaciar reproduces (:data:`DEFAULT_ONLY_KEYS`, e.g. ``THRESH_TYPE
RELATIVE``), or is refused with a one-line error
naming it.
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

from ..galaxy.filters import looks_like_path
from .common import At, add_warning, resolve_filter_name

__all__ = ["read_sex_file", "detection_keys_from_sex", "HONOURED_KEYS", "NO_EFFECT_KEYS",
           "DEFAULT_ONLY_KEYS", "GLACIAR_ONLY_KEYS"]

#: SExtractor keys glaciar reads into ``detection:`` (upper case).
HONOURED_KEYS = ("DETECT_THRESH", "DETECT_MINAREA", "FILTER", "FILTER_NAME", "FILTER_TYPE",
                 "DEBLEND_NTHRESH", "DEBLEND_MINCONT", "CLEAN", "CLEAN_PARAM", "BACK_SIZE",
                 "BACK_FILTERSIZE", "PHOT_APERTURES", "PHOT_AUTOPARAMS", "WEIGHT_TYPE",
                 "WEIGHT_GAIN", "BACKPHOTO_TYPE", "BACKPHOTO_THICK", "MASK_TYPE", "SATUR_LEVEL")
#: detection keys glaciar has and SExtractor does not (which CLEAN, which RMS the
#: RELATIVE threshold multiplies, which program segments): YAML only, never in a .sex file
GLACIAR_ONLY_KEYS = ("CLEAN_STYLE", "THRESHOLD_RMS", "BACKEND")
_LIST_KEYS = ("PHOT_APERTURES", "PHOT_AUTOPARAMS", "BACK_SIZE", "BACK_FILTERSIZE")

#: Keys that do not change which injected sources are found or the fluxes glaciar
#: measures (catalogue output, memory, verbosity, other measurements' parameters),
#: and keys whose job glaciar does elsewhere (named in the value).
NO_EFFECT_KEYS = {
    "CATALOG_NAME": "catalogue output", "CATALOG_TYPE": "catalogue output",
    "PARAMETERS_NAME": "catalogue columns", "VERBOSE_TYPE": "verbosity",
    "HEADER_SUFFIX": "headers", "WRITE_XML": "XML output", "XML_NAME": "XML output",
    "XSL_URL": "XML output", "NTHREADS": "threads", "FITS_UNSIGNED": "integer images",
    "MEMORY_OBJSTACK": "memory", "MEMORY_PIXSTACK": "memory", "MEMORY_BUFSIZE": "memory",
    "CHECKIMAGE_TYPE": "check images", "CHECKIMAGE_NAME": "check images",
    "SEEING_FWHM": "star/galaxy classifier", "STARNNW_NAME": "star/galaxy classifier",
    "PHOT_FLUXFRAC": "FLUX_RADIUS", "PHOT_PETROPARAMS": "Petrosian fluxes",
    "ANALYSIS_THRESH": "isophotal shape parameters", "MAG_GAMMA": "photographic plates",
    "MAG_ZEROPOINT": "survey.bands.<band>.zeropoint is used",
    "PIXEL_SCALE": "survey.pixel_scale_arcsec or the WCS is used",
    "INTERP_MAXXLAG": "interpolation (INTERP_TYPE)", "INTERP_MAXYLAG": "interpolation",
    "WEIGHT_IMAGE": "survey.noise is used", "PSF_NAME": "PSF fitting",
    "FLAG_IMAGE": "IMAFLAGS_* catalogue columns", "FLAG_TYPE": "IMAFLAGS_* catalogue columns",
    "ASSOC_NAME": "catalogue association", "ASSOC_DATA": "catalogue association",
    "ASSOC_PARAMS": "catalogue association", "ASSOC_RADIUS": "catalogue association",
    "ASSOC_TYPE": "catalogue association", "ASSOCSELEC_TYPE": "catalogue association",
    "ASSOCCOORD_TYPE": "catalogue association",
    "SATUR_KEY": "SATUR_LEVEL is used (glaciar reads no saturation keyword from headers)",
    "GAIN_KEY": "survey.bands.<band>.gain is used",
    "BACK_VALUE": "BACK_TYPE MANUAL only",
}
#: Keys accepted at the value that reproduces what glaciar does (SExtractor's
#: default, compared case-insensitively); any other value is refused.
DEFAULT_ONLY_KEYS = {
    "THRESH_TYPE": ("RELATIVE",), "BACK_TYPE": ("AUTO",), "DETECT_TYPE": ("CCD",),
    "BACK_FILTTHRESH": ("0", "0.0"),
    "PHOT_AUTOAPERS": ("0.0,0.0", "0,0", "0.0", "0"), "GAIN": ("0", "0.0"),
    "INTERP_TYPE": ("NONE",), "WEIGHT_THRESH": ("",),
}


def read_sex_file(path) -> dict[str, str | list[str]]:
    """Read a SExtractor configuration file.

    Parameters
    ----------
    path : path-like
        ``.sex`` file (UTF-8 or Latin-1 text).

    Returns
    -------
    dict
        Upper-case key -> value string, or list of strings for values that
        hold several comma- or blank-separated tokens. Conversion and checks
        are done by the configuration models.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"SExtractor file {path!r} not found")
    raw = Path(path).read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")     # SExtractor's own defaults files are ASCII/Latin-1
    out: dict[str, Any] = {}
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split(None, 1)
        key = parts[0].upper()
        tokens = [t for t in re.split(r"[\s,]+", parts[1].strip()) if t] if len(parts) > 1 else []
        out[key] = tokens[0] if len(tokens) == 1 else tokens
    return out


def detection_keys_from_sex(path, base_dir, info=None) -> dict[str, Any]:
    """The ``detection:`` keys a ``.sex`` file sets (raw values, validated by the model).

    ``FILTER_NAME`` is resolved next to the ``.sex`` file, then next to the
    config; when found in neither, the built-in kernel of the same name is
    used and a warning says so (SExtractor resolves it from its working
    directory, which we do not know).
    """
    keys = read_sex_file(path)
    ttype = keys.get("THRESH_TYPE", "RELATIVE")
    ttype = ttype[0] if isinstance(ttype, list) and ttype else ttype
    if str(ttype).upper() != "RELATIVE":
        raise At(f"{path}: THRESH_TYPE: only RELATIVE thresholds (in units of the background "
                 f"RMS) are supported, got {ttype}", "sex_file")
    for key, value in keys.items():
        if key in HONOURED_KEYS or key in NO_EFFECT_KEYS:
            continue
        text = ",".join(value) if isinstance(value, list) else value
        if key == "GAIN" and value == []:
            # GLACiAR's template (SExtractor_files/parameters.sex) leaves GAIN empty and
            # fills it per band from gain_values before each SExtractor call: the same
            # per-band gain glaciar takes from survey.bands.<band>.gain.
            if info is not None:
                add_warning(info, f"{path}: GAIN without a value: each band's gain is "
                            "survey.bands.<band>.gain, as GLACiAR fills it per band "
                            "(a band without one gets no source Poisson noise)")
            continue
        if key in DEFAULT_ONLY_KEYS:
            if text.upper() not in DEFAULT_ONLY_KEYS[key]:
                allowed = " or ".join(v or "(empty)" for v in DEFAULT_ONLY_KEYS[key])
                raise At(f"{path}: {key} {text}: not supported (glaciar reproduces {key} "
                         f"{allowed} only); remove the line or set it to that", "sex_file")
            continue
        if key in GLACIAR_ONLY_KEYS:
            raise At(f"{path}: {key}: glaciar's own key, not SExtractor's; set detection.{key} "
                     "in the YAML configuration instead", "sex_file")
        raise At(f"{path}: {key}: SExtractor key not supported by glaciar (it would change "
                 "the answer, and glaciar never ignores one silently); remove the line",
                 "sex_file")
    out: dict[str, Any] = {}
    for key in HONOURED_KEYS:
        if key not in keys or keys[key] == []:
            continue
        value = keys[key]
        if key == "WEIGHT_TYPE":
            # Dual-image mode gives "detection,measurement"; glaciar uses one noise map per band.
            kinds = {v.upper() for v in (value if isinstance(value, list) else [value])}
            if len(kinds) > 1:
                raise At(f"{path}: WEIGHT_TYPE: different types for detection and measurement "
                         f"({', '.join(sorted(kinds))}) are not supported", "sex_file")
            value = kinds.pop()
            if value == "NONE":
                if info is not None:
                    add_warning(info, f"{path}: WEIGHT_TYPE NONE: the survey's noise maps "
                                "(survey.noise) are used as configured; set WEIGHT_TYPE "
                                "BACKGROUND to ignore them")
                continue
        if key == "WEIGHT_GAIN" and isinstance(value, list):
            # Dual-image mode again ("detection,measurement", e.g. GLACiAR's "N,N").
            kinds = {v.upper() for v in value}
            if len(kinds) > 1:
                raise At(f"{path}: WEIGHT_GAIN: different values for detection and measurement "
                         f"({', '.join(sorted(kinds))}) are not supported", "sex_file")
            value = kinds.pop()
        if key == "FILTER_NAME":
            value = value[0] if isinstance(value, list) else value
            resolved = resolve_filter_name(value, [Path(path).parent, Path(base_dir)])
            if looks_like_path(value, (".conv",)) and not Path(resolved).is_file():
                stem = Path(value).name
                stem = stem[:-5] if stem.lower().endswith(".conv") else stem
                if info is not None:
                    add_warning(info, f"{path}: FILTER_NAME {value!r} not found next to the .sex file "
                                f"or the config; using the built-in kernel {stem!r}")
                resolved = stem
            value = resolved
        elif key in _LIST_KEYS and not isinstance(value, list):
            value = [value]
        out[key] = value
    return out
