"""Reading, writing and identifying configurations (the file edge of :mod:`glaciar.config`).

``load_config`` reads YAML with a bounded loader (duplicate keys refused,
aliases limited so an alias bomb cannot expand, size and nesting bounded,
UTF-8 required), recognises GLACiAR's flat ``parameters.yaml`` and validates
with the typed models of :mod:`glaciar.config.models`. Errors name the file
and the key path, e.g.::

    config.yaml: survey.bands.f160w.zeropoint: expected a finite number, got 'abc'
"""
from __future__ import annotations

import copy
import hashlib
import json
import os
from pathlib import Path
from typing import Mapping

from pydantic import ValidationError

from .common import (At, ConfigError, format_validation_error, read_yaml, show,
                     unknown_key_error)
from .glaciar_compat import GLACIAR_TO_SCHEMA, TOP_KEYS, glaciar_to_schema, is_glaciar_parameters
from .models import Config
from .user_selection import selection_data

__all__ = ["config_from_dict", "load_config", "config_to_dict", "config_hash", "store_hash",
           "missing_files", "check_files"]

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
    context = {"base_dir": base_dir, "warnings": [], "origins": {}}
    if data is None:
        raise ConfigError(f"{source_name}: <top level>: the configuration is empty")
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source_name}: <top level>: expected a mapping of sections, "
                          f"got {show(data)}")
    try:
        if is_glaciar_parameters(data):
            data, origins, warnings = glaciar_to_schema(data, base_dir)
            context["origins"].update({k: f"from GLACiAR key '{v}'" for k, v in origins.items()
                                       if k != v})
            context["warnings"].extend(warnings)
        else:
            hints = {k: f"a GLACiAR parameters.yaml key; in this schema use {v}"
                     for k, v in GLACIAR_TO_SCHEMA.items()}
            for key in data:
                if key not in TOP_KEYS:
                    raise unknown_key_error(key, TOP_KEYS, hints)
    except At as exc:
        where = ".".join(map(str, exc.loc)) or "<top level>"
        raise ConfigError(f"{source_name}: {where}: {exc.message}") from None
    try:
        cfg = Config.model_validate(data, context=context)
    except ValidationError as exc:
        raise format_validation_error(exc, source_name, context["origins"]) from None
    return cfg.model_copy(update={"path": None if path is None else Path(path).resolve(),
                                  "base_dir": base_dir,
                                  "warnings": tuple(context["warnings"])})


def load_config(path: str | os.PathLike) -> Config:
    """Read and validate a YAML configuration file.

    Parameters
    ----------
    path : path-like
        A glaciar config (see :func:`glaciar.config.template_yaml`) or a GLACiAR
        ``parameters.yaml``. Relative paths inside are relative to its directory.

    Returns
    -------
    Config

    Raises
    ------
    FileNotFoundError
        The file does not exist.
    ConfigError
        Not UTF-8, too large, YAML syntax error (with line and column), an
        alias bomb, or invalid content.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"config file not found: {path}")
    data = read_yaml(path)
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
    # survey.lens only when given: unlensed configurations keep their files and hashes.
    survey = s.model_dump(mode="json", exclude={"bands", "fields_file"} |
                          ({"lens"} if s.lens is None else set()))
    survey["bands"] = {b.name: b.model_dump(mode="json", exclude={"name"}) for b in s.bands}
    out = {
        "survey": survey,
        "grid": {"z": {"values": list(cfg.grid.z_values)},
                 "mag": {"values": list(cfg.grid.mag_values)},
                 "magnitude_type": cfg.grid.magnitude_type,
                 # Only when given: configurations without cells keep their hashes.
                 **({"cells": [c.model_dump(mode="json", exclude_none=True)
                               for c in cfg.grid.cells]} if cfg.grid.cells else {}),
                 **({"box": cfg.grid.box.model_dump(mode="json", exclude_none=True)}
                    if cfg.grid.box is not None else {})},
        "simulation": cfg.simulation.model_dump(mode="json"),
        "source": cfg.source.model_dump(mode="json"),
        "detection": cfg.detection.model_dump(mode="json", by_alias=True),
        "classification": cfg.classification.model_dump(mode="json"),
        "noise": cfg.noise.model_dump(mode="json"),
        "selection": selection_data(cfg.selection),
        "output": cfg.output.model_dump(mode="json"),
        # Only when given: configurations without interlopers keep their hashes.
        **({"interlopers": cfg.interlopers.model_dump(mode="json")}
           if cfg.interlopers is not None else {}),
    }
    out = copy.deepcopy(_plain(out))
    if rel is not None:
        # Only values that are paths: image_dir, filter/PSF files, sex_file, FILTER_NAME.
        out["survey"]["image_dir"] = _plain(str(s.image_dir), rel)
        for b in s.bands:
            entry = out["survey"]["bands"][b.name]
            if os.path.isabs(b.filter):
                entry["filter"] = _plain(b.filter, rel)
            if isinstance(b.psf, str):
                entry["psf"] = _plain(b.psf, rel)
        for key in ("sex_file", "FILTER_NAME"):
            v = out["detection"].get(key)
            if isinstance(v, str) and os.path.isabs(v):
                out["detection"][key] = _plain(v, rel)
    return out


def _sha256_json(d: dict) -> str:
    text = json.dumps(d, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


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
    magnitude values, its cells and box, and ``simulation.n_iterations``: those only add or remove
    tasks (each task's random stream is keyed by its field name, z, magnitude
    and iteration, not by its position in the grid), so a results store can be
    extended with more cells or iterations and stay consistent.
    """
    d = config_to_dict(cfg, relative_to=cfg.base_dir)
    d.pop("output", None)
    d.pop("interlopers", None)      # in the interloper tasks' own keys (glaciar.plan)
    d["survey"].pop("fields", None)
    d["grid"].pop("z", None)
    d["grid"].pop("mag", None)
    d["grid"].pop("cells", None)
    d["grid"].pop("box", None)
    d["simulation"].pop("n_iterations", None)
    return _sha256_json(d)


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
            for key, tmpl in (("survey.science", s.science), ("survey.noise", s.noise)):
                if tmpl is None:
                    continue
                p = s.image_dir / tmpl.format(field=f, band=b.name)
                if not p.is_file():
                    out.append(f"{key} (field {f!r}, band {b.name!r}): {p}")
    if s.mask is not None:
        for f in s.fields:
            p = s.image_dir / s.mask.format(field=f)
            if not p.is_file():
                out.append(f"survey.mask (field {f!r}): {p}")
    for b in s.bands:
        if isinstance(b.psf, str) and not Path(b.psf).is_file():
            out.append(f"survey.bands.{b.name}.psf: {b.psf}")
        if os.path.isabs(b.filter) and not Path(b.filter).is_file():
            out.append(f"survey.bands.{b.name}.filter: {b.filter}")
    fname = cfg.detection.filter_name
    if cfg.detection.filter and os.path.isabs(fname) and not Path(fname).is_file():
        out.append(f"detection.FILTER_NAME: {fname}")
    return out


def check_files(cfg: Config) -> None:
    """Raise FileNotFoundError listing every missing input file (see :func:`missing_files`)."""
    missing = missing_files(cfg)
    if missing:
        name = cfg.path if cfg.path is not None else "config"
        raise FileNotFoundError(f"{name}: {len(missing)} input file(s) not found:\n  "
                                + "\n  ".join(missing))
