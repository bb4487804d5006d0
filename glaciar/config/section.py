"""What every configuration section shares: the plausibility bounds, the base model
:class:`Section` (frozen, unknown keys refused with a suggestion) and the small
validators the sections are built from.
"""
from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, ClassVar

from pydantic import (BaseModel, BeforeValidator, ConfigDict, Field, ValidationError,
                      ValidationInfo, model_validator)

from .common import At, Float, parse_bool, show, unknown_key_error

__all__ = ["MAX_TASKS", "MAX_GRID_VALUES", "MAX_BOX_POINTS", "MAX_REDSHIFT", "MAX_ABS_MAGNITUDE",
           "MAX_PIXEL_SCALE_ARCSEC", "PSF_FWHM_RANGE_ARCSEC", "MAX_R_EFF_KPC", "MAX_APERTURE_PIX",
           "MAX_DETECT_THRESH", "Section", "Bool", "engine_default", "arg_default",
           "context_base_dir", "float_list", "validate_nested"]

#: Largest number of tasks a configuration may plan (fields x z x mag x iterations):
#: the planner holds one small object per task (~10**7 is ~2 GB).
MAX_TASKS = 10_000_000
#: Largest number of values of one grid axis.
MAX_GRID_VALUES = 10_000
#: Largest number of points of ``grid.box`` (the manifest lists each one).
MAX_BOX_POINTS = 100_000
# Plausibility bounds: far beyond any survey, they stop absurd values (1e300) before
# they overflow the arithmetic (a traceback) or name a task file too long to write.
#: Largest redshift of the grid, its cells and box.
MAX_REDSHIFT = 50.0
#: Largest |magnitude| of the grid, its cells and box [AB mag], and |zeropoint| [mag].
MAX_ABS_MAGNITUDE = 100.0
#: Pixel scales (images, FITS PSFs) at or above this are refused [arcsec / pixel].
MAX_PIXEL_SCALE_ARCSEC = 10.0
#: Range of an analytic PSF's FWHM [arcsec].
PSF_FWHM_RANGE_ARCSEC = (1e-3, 100.0)
#: Largest half-light radius at z = 6 [proper kpc].
MAX_R_EFF_KPC = 100.0
#: Largest aperture diameter [pixels].
MAX_APERTURE_PIX = 10_000.0
#: Largest detection threshold [sigma].
MAX_DETECT_THRESH = 10_000.0


def engine_default(cls, name: str):
    """Default of a dataclass field of the engine (the one place it is defined)."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            if f.default is not dataclasses.MISSING:
                return f.default
            break
    raise KeyError(f"{cls.__name__}.{name} has no plain default")


def arg_default(func, name: str):
    return inspect.signature(func).parameters[name].default


def context_base_dir(info: ValidationInfo) -> Path:
    return Path((info.context or {}).get("base_dir", "."))


def float_list(*, min_length=1, max_length=None, **bounds):
    item = Annotated[Float, Field(**bounds)] if bounds else Float

    def as_list(value):
        if isinstance(value, (int, float, str)) and not isinstance(value, bool):
            return [value]
        return value
    return Annotated[tuple[item, ...], BeforeValidator(as_list),
                     Field(min_length=min_length, max_length=max_length)]


def _bool(value):
    parsed = parse_bool(value)
    if parsed is None:
        raise At(f"expected true/false, got {show(value)}")
    return parsed


Bool = Annotated[bool, BeforeValidator(_bool)]


class Section(BaseModel):
    """A configuration section: frozen, unknown keys refused with a suggestion.

    A key given as ``null`` takes its default. Subclasses adapt the raw
    mapping in :meth:`_prepare` (e.g. reading a file the section points to).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)
    #: Fields set by glaciar, not by the user (refused in a file).
    _internal: ClassVar[tuple[str, ...]] = ()
    #: Extra words for specific unknown keys.
    _hints: ClassVar[dict[str, str]] = {}
    #: Keys whose explicit ``null`` means something (not "the default").
    _keep_none: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def user_keys(cls) -> tuple[str, ...]:
        """The keys a configuration file may give in this section."""
        return tuple(f.alias or n for n, f in cls.model_fields.items() if n not in cls._internal)

    @model_validator(mode="before")
    @classmethod
    def _check_keys(cls, data: Any, info: ValidationInfo):
        if data is None:
            data = {}
        if isinstance(data, BaseModel):
            return data
        if not isinstance(data, Mapping):
            raise At(f"expected a mapping of keys, got {show(data)}")
        data = cls._normalise_keys(dict(data))
        allowed = cls.user_keys()
        for key in data:
            if key not in allowed and key not in cls._internal:
                raise unknown_key_error(key, allowed, cls._hints)
        data = {k: v for k, v in data.items() if v is not None or k in cls._keep_none}
        return cls._prepare(data, info)

    @classmethod
    def _normalise_keys(cls, data: dict) -> dict:
        return data

    @classmethod
    def _prepare(cls, data: dict, info: ValidationInfo) -> dict:
        return data


def validate_nested(model: type[BaseModel], data, info: ValidationInfo, *loc):
    """Validate ``data`` as ``model`` with the same context; errors keep their location."""
    try:
        return model.model_validate(data, context=info.context)
    except ValidationError as exc:
        raise At("", *loc, cause=exc) from None

