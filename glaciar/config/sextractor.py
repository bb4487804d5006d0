"""SExtractor configuration files (``.sex``): the one reader, and its mapping onto glaciar.

A ``.sex`` file is lines of ``KEY value[,value...]  # comment``. glaciar reads
the detection and photometry keys it honours (:data:`HONOURED_KEYS`) into the
``detection:`` section (:class:`glaciar.config.models.DetectionConfig`), where
keys given explicitly in the YAML win. ``THRESH_TYPE`` must be RELATIVE (sep
thresholds are in units of the background RMS).
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

from ._types import At

__all__ = ["read_sex_file", "detection_keys_from_sex", "HONOURED_KEYS"]

#: SExtractor keys glaciar reads into ``detection:`` (upper case).
HONOURED_KEYS = ("DETECT_THRESH", "DETECT_MINAREA", "FILTER", "FILTER_NAME", "FILTER_TYPE",
                 "DEBLEND_NTHRESH", "DEBLEND_MINCONT", "CLEAN", "CLEAN_PARAM", "BACK_SIZE",
                 "BACK_FILTERSIZE", "PHOT_APERTURES", "PHOT_AUTOPARAMS")
_LIST_KEYS = ("PHOT_APERTURES", "PHOT_AUTOPARAMS", "BACK_SIZE", "BACK_FILTERSIZE")


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
    from .models import _filter_name, _warn, looks_like_path

    keys = read_sex_file(path)
    ttype = keys.get("THRESH_TYPE", "RELATIVE")
    ttype = ttype[0] if isinstance(ttype, list) and ttype else ttype
    if str(ttype).upper() != "RELATIVE":
        raise At(f"{path}: THRESH_TYPE: only RELATIVE thresholds (in units of the background "
                 f"RMS) are supported, got {ttype}", "sex_file")
    out: dict[str, Any] = {}
    for key in HONOURED_KEYS:
        if key not in keys or keys[key] == []:
            continue
        value = keys[key]
        if key == "FILTER_NAME":
            value = value[0] if isinstance(value, list) else value
            resolved = _filter_name(value, [Path(path).parent, Path(base_dir)])
            if looks_like_path(value, (".conv",)) and not Path(resolved).is_file():
                stem = Path(value).name
                stem = stem[:-5] if stem.lower().endswith(".conv") else stem
                if info is not None:
                    _warn(info, f"{path}: FILTER_NAME {value!r} not found next to the .sex file "
                                f"or the config; using the built-in kernel {stem!r}")
                resolved = stem
            value = resolved
        elif key in _LIST_KEYS and not isinstance(value, list):
            value = [value]
        out[key] = value
    return out
