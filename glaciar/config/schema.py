"""``glaciar init``'s template and the documented schema, generated from the models.

Both are built from :mod:`glaciar.config.models` (keys, defaults, constraints
and descriptions), so they cannot drift from what the code accepts. The
documented schema is committed as ``docs/config-schema.yaml``; regenerate it
with ``python -c "import glaciar.config as c; print(c.schema_yaml(), end='')" > docs/config-schema.yaml`` (a test
checks that the committed copy is current).
"""
from __future__ import annotations

import typing
from pathlib import Path

import annotated_types as at
import yaml
from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from ..engine.selection import DEFAULT_JDROPOUT
from .models import SECTIONS, AxisSpec
from .section import Section
from .survey_models import BandConfig, DetectionImageConfig, PsfProfile, SurveyConfig

__all__ = ["template_yaml", "schema_yaml"]

_HEADER = """\
# glaciar configuration (written by `glaciar init`; edit, then `glaciar simulate THIS_FILE`).
#
# Relative paths are relative to the directory of this file. Every key except
# survey.fields, survey.science, survey.detection_band and each band's filter,
# zeropoint and psf has a default: the value shown here (the paper's default where
# Carrasco et al. 2018 give one). Unknown keys are errors, so typos are caught.
# A GLACiAR parameters.yaml (flat keys n_galaxies, min_mag, ...) is also accepted.
# Every key, its type, default and constraints: docs/config-schema.yaml.
"""
_COMMENT_COLUMN = 38
#: Keys the template leaves out (an alternative to a key it shows, documented in its comment).
_TEMPLATE_SKIP = {"survey": ("fields_file",)}


def _flow(value) -> str:
    """A value as one line of YAML flow style."""
    if isinstance(value, Path):
        value = str(value)
    if isinstance(value, tuple):
        value = list(value)
    text = yaml.safe_dump(value, default_flow_style=True, sort_keys=False, width=10_000,
                          allow_unicode=True).strip()
    return text[:-4].rstrip() if text.endswith("\n...") or text.endswith(" ...") else text


def _field_value(info):
    extra = info.json_schema_extra or {}
    for key in ("template", "example"):
        if key in extra:
            return extra[key]
    if info.default_factory is not None:
        value = info.default_factory()
        return value.model_dump(mode="json", by_alias=True) if isinstance(value, BaseModel) \
            else value
    return None if info.default is PydanticUndefined else info.default


def _default_value(info):
    if info.default_factory is None:
        return info.default
    extra = info.json_schema_extra or {}
    if "template" in extra:
        return extra["template"]
    value = info.default_factory()
    return value.model_dump(mode="json", by_alias=True) if isinstance(value, BaseModel) else value


def _line(indent: int, key: str, value_text: str, comment: str | None) -> str:
    text = f"{' ' * indent}{key}:{' ' + value_text if value_text else ''}"
    if comment:
        text = text.ljust(_COMMENT_COLUMN - 1) + f" # {comment}"
    return text


def _model_lines(model: type[Section], indent: int, values: dict | None = None,
                 skip=()) -> list[str]:
    lines = []
    for name, info in model.model_fields.items():
        if name in model._internal or name in skip:
            continue
        key = info.alias or name
        if values is not None:
            if key not in values:
                continue
            value = values[key]
        else:
            value = _field_value(info)
        lines.append(_line(indent, key, _flow(value), info.description))
    return lines


def _bands_lines(indent: int) -> list[str]:
    info = SurveyConfig.model_fields["bands"]
    lines = [_line(indent, "bands", "", info.description)]
    for i, (name, settings) in enumerate(info.json_schema_extra["example"].items()):
        lines.append(f"{' ' * (indent + 2)}{name}:")
        if i == 0:
            # The first band shows every key with its comment.
            full = {}
            for fname, finfo in BandConfig.model_fields.items():
                if fname in BandConfig._internal:
                    continue
                full[fname] = settings.get(fname, _field_value(finfo) if fname not in settings
                                           and finfo.default is not PydanticUndefined else None)
            lines += _model_lines(BandConfig, indent + 4, full)
        else:
            lines += [_line(indent + 4, k, _flow(v), None) for k, v in settings.items()]
    return lines


def template_yaml() -> str:
    """The commented configuration template that ``glaciar init`` writes.

    Every section with every key: required keys with an example value (the
    BoRG J125-dropout set-up of the paper), the others with their default,
    each commented with its meaning and unit.
    """
    out = [_HEADER]
    for section, info in SECTIONS.items():
        model = _section_model(info.annotation)
        if model is None:      # selection: a list of expressions
            out.append(_line(0, section, "", info.description))
            out += [f"  - {_flow(e)}" for e in DEFAULT_JDROPOUT]
        elif model is SurveyConfig:
            out.append(_line(0, section, "", info.description))
            out += _model_lines(model, 2, skip=("bands",) + _TEMPLATE_SKIP.get(section, ()))
            out += _bands_lines(2)
        elif info.default is None:
            # An optional section stays off in the template (empty: absent), its keys
            # shown commented out.
            out.append(_line(0, section, "", info.description))
            lines = _model_lines(model, 2, skip=_TEMPLATE_SKIP.get(section, ()))
            out += ["# " + ln if ln.strip() else ln for ln in lines]
        else:
            out.append(_line(0, section, "", info.description))
            out += _model_lines(model, 2, skip=_TEMPLATE_SKIP.get(section, ()))
        out.append("")
    return "\n".join(out)


def _section_model(annotation):
    if isinstance(annotation, type) and issubclass(annotation, Section):
        return annotation
    # An optional section (`interlopers: ... | None`): its model.
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if len(args) == 1 and isinstance(args[0], type) and issubclass(args[0], Section):
        return args[0]
    return None


def _type_name(annotation) -> str:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Annotated:
        return _type_name(args[0])
    if origin is typing.Literal:
        return " | ".join(map(str, args))
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        return " or ".join(_type_name(a) for a in args)
    if origin is tuple:
        return f"list of {_type_name(args[0])}"
    if isinstance(annotation, type) and issubclass(annotation, Section):
        return "mapping"
    if annotation is type(None):
        return "null"
    return {float: "number", int: "integer", str: "string", bool: "true/false",
            dict: "mapping", Path: "path"}.get(annotation, getattr(annotation, "__name__",
                                                                   str(annotation)))


def _constraints(info) -> list[str]:
    out = []
    symbols = {at.Gt: (">", "gt"), at.Ge: (">=", "ge"), at.Lt: ("<", "lt"), at.Le: ("<=", "le")}

    def collect(metadata):
        for m in metadata:
            for cls, (sym, attr) in symbols.items():
                if isinstance(m, cls):
                    out.append(f"{sym} {getattr(m, attr)}")
            if isinstance(m, at.MinLen) and m.min_length > 0:
                out.append(f"at least {m.min_length} value(s)")
            if isinstance(m, at.MaxLen):
                out.append(f"at most {m.max_length} value(s)")
    collect(info.metadata)
    args = typing.get_args(info.annotation)
    for a in args:
        if isinstance(a, typing.Any.__class__) or not hasattr(a, "metadata"):
            continue
        collect(getattr(a, "metadata", []))
    return out


def _describe_model(model: type[Section]) -> dict:
    entries = {}
    for name, info in model.model_fields.items():
        if name in model._internal:
            continue
        entry = {"type": _type_name(info.annotation)}
        if info.is_required():
            entry["required"] = True
        else:
            entry["default"] = yaml.safe_load(_flow(_default_value(info)))
        cons = _constraints(info)
        if cons:
            entry["constraints"] = cons
        entry["description"] = info.description
        entries[info.alias or name] = entry
    return entries


def schema_yaml() -> str:
    """Every key of the configuration: type, default (or required), constraints, meaning."""
    doc = {}
    for section, info in SECTIONS.items():
        model = _section_model(info.annotation)
        doc[section] = {"description": info.description}
        if model is None:
            doc[section].update({"type": "list of expression strings", "default":
                                 "the BoRG J125-dropout (see template) when its bands exist"})
        else:
            doc[section]["keys"] = _describe_model(model)
    doc["survey"]["keys"]["bands"]["type"] = "mapping band name -> settings (ordered)"
    doc["survey"]["keys"]["bands"]["each band"] = _describe_model(BandConfig)
    doc["survey"]["keys"]["bands"]["each band"]["psf"]["analytic profile keys"] = \
        _describe_model(PsfProfile)
    doc["grid"]["keys"]["z"]["axis keys"] = _describe_model(AxisSpec)
    doc["survey"]["keys"]["detection_image"]["keys"] = _describe_model(DetectionImageConfig)
    text = yaml.safe_dump(doc, sort_keys=False, allow_unicode=True, width=100)
    return ("# glaciar configuration schema: every key, its type, default and constraints.\n"
            "# Generated from glaciar/config/models.py by\n"
            "#   python -c \"import glaciar.config as c; print(c.schema_yaml(), end='')\" "
            "> docs/config-schema.yaml\n"
            "# Paths are relative to the directory of the config file.\n" + text)


