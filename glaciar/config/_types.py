"""Validation vocabulary shared by the configuration models.

Pydantic does the type checking; this module turns its errors into the one
line glaciar prints (``file: key.path: what was expected, got what``) and
adds the few types YAML users need: numbers that may arrive as strings
(PyYAML reads ``1e-3`` as a string), integers that refuse booleans, choices
matched case-insensitively with a "did you mean" hint, and lists that accept
a single value (lists: ``models._float_list``).
"""
from __future__ import annotations

import difflib
import math
import reprlib
from typing import Annotated, Literal

from pydantic import BeforeValidator, ValidationError

__all__ = ["ConfigError", "At", "Int", "Float", "Choice", "show", "yaml_bool_hint",
           "format_validation_error", "unknown_key_error"]


class ConfigError(ValueError):
    """Invalid configuration; the message names the file and the key path."""


class At(ValueError):
    """A validation failure at ``loc`` below the value being validated.

    Raised inside validators: pydantic records it as a ``value_error`` whose
    context holds this exception, and :func:`format_validation_error` appends
    ``loc`` to the error's location. ``cause`` may be a nested
    :class:`pydantic.ValidationError` (a model validated by hand, e.g. one
    band of the ``bands`` mapping), whose own locations are then used.
    """

    def __init__(self, message: str, *loc, cause: ValidationError | None = None):
        super().__init__(message)
        self.message = message
        self.loc = tuple(loc)
        self.cause = cause


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict, _REPR.maxstring, _REPR.maxother = 2, 6, 6, 70, 70

#: Longest quoted value in a message [characters] (a hostile value must not flood it).
MAX_SHOWN = 60


def show(value) -> str:
    """A value as quoted in messages: strings by repr, others with their type (truncated)."""
    text = _REPR.repr(value)
    if len(text) > MAX_SHOWN:
        text = text[:MAX_SHOWN - 3] + "..."
    return text if isinstance(value, str) else f"{text} ({type(value).__name__})"


#: Words YAML 1.1 (PyYAML) reads as booleans when unquoted, lower case.
YAML11_FALSE = ("off", "no", "false")
YAML11_TRUE = ("on", "yes", "true")


def yaml_bool_hint(value) -> str:
    """For a boolean where a word was expected: how to write the word (else "")."""
    if not isinstance(value, bool):
        return ""
    words = YAML11_TRUE if value else YAML11_FALSE
    return (f" (YAML reads unquoted {'/'.join(words)} as {str(value).lower()}: quote the word "
            "you meant)")


def _no_bool(kind: str):
    def check(value):
        if isinstance(value, bool):
            raise At(f"expected {kind}, got {show(value)}")
        return value
    return check


def _finite_number(value):
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise At(f"expected a number, got {show(value)}")
    try:
        x = float(value)
    except ValueError:
        raise At(f"expected a number, got {value!r}") from None
    except OverflowError:
        raise At(f"expected a finite number, got {value!r}") from None
    if not math.isfinite(x):
        raise At(f"expected a finite number, got {value!r}")
    return x


def _integer(value):
    if isinstance(value, bool):
        raise At(f"expected an integer, got {show(value)}")
    if isinstance(value, float) and value.is_integer() and math.isfinite(value):
        return int(value)
    if isinstance(value, str):
        try:
            return int(value.strip())
        except ValueError:
            pass
    if not isinstance(value, int):
        raise At(f"expected an integer, got {show(value)}")
    return value


#: An integer; refuses booleans and fractional numbers.
Int = Annotated[int, BeforeValidator(_integer)]
#: A finite float; numeric strings are accepted (YAML 1.1 reads ``1e-3`` as a string).
Float = Annotated[float, BeforeValidator(_finite_number)]


def Choice(*values: str, aliases: dict[str, str] | None = None):
    """A string among ``values``, matched case-insensitively (with a hint when close)."""
    aliases = aliases or {}

    def check(value):
        if isinstance(value, bool):
            # YAML 1.1 reads unquoted off/no/false (on/yes/true) as a boolean: take it
            # back to the word when the enumeration has exactly one such word.
            words = [w for w in (YAML11_FALSE if value is False else YAML11_TRUE) if w in values]
            if len(words) == 1:
                return words[0]
            raise At(f"expected one of {', '.join(values)}, got {show(value)}"
                     f"{yaml_bool_hint(value)}")
        if not isinstance(value, str) or not value.strip():
            raise At(f"expected one of {', '.join(values)}, got {show(value)}")
        v = aliases.get(value.strip().lower(), value.strip().lower())
        if v not in values:
            close = difflib.get_close_matches(v, values, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise At(f"expected one of {', '.join(values)}, got {value!r}{hint}")
        return v
    return Annotated[Literal[values], BeforeValidator(check)]


def unknown_key_error(key, allowed, hints: dict | None = None) -> At:
    """The error for a key that is not in ``allowed`` (with a suggestion)."""
    msg = f"unknown key {key!r}"
    if hints and key in hints:
        return At(f"{msg} ({hints[key]})", key)
    close = difflib.get_close_matches(str(key), [str(a) for a in allowed], n=1, cutoff=0.6)
    if close:
        return At(f"{msg}; did you mean {close[0]!r}?", key)
    return At(f"{msg}; allowed keys: {', '.join(map(str, allowed))}", key)


def _bound_message(kind: str, ctx: dict, value) -> str:
    op = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<",
          "less_than_equal": "<="}[kind]
    limit = next(iter(ctx.values()))
    got = f"{value:g}" if isinstance(value, (int, float)) and not isinstance(value, bool) else value
    return f"must be {op} {limit}, got {got}"


def _message(err: dict) -> str:
    kind, value, ctx = err["type"], err.get("input"), err.get("ctx") or {}
    if kind == "missing":
        return "missing required key"
    if kind == "extra_forbidden":
        return f"unknown key {err['loc'][-1]!r}"
    if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        return _bound_message(kind, ctx, value)
    if kind in ("float_parsing", "float_type", "finite_number"):
        return f"expected a finite number, got {show(value)}"
    if kind in ("int_parsing", "int_type", "int_from_float"):
        return f"expected an integer, got {show(value)}"
    if kind in ("bool_parsing", "bool_type"):
        return f"expected true/false, got {show(value)}"
    if kind in ("string_type", "string_too_short"):
        return f"expected a non-empty string, got {show(value)}{yaml_bool_hint(value)}"
    if kind in ("tuple_type", "list_type"):
        return f"expected a list, got {show(value)}"
    if kind == "too_short":
        return f"expected at least {ctx.get('min_length')} value(s), got {ctx.get('actual_length')}"
    if kind in ("dict_type", "model_type", "model_attributes_type"):
        return f"expected a mapping of keys, got {show(value)}"
    return err["msg"]


def _flatten(exc: ValidationError, prefix=()):
    for err in exc.errors(include_url=False):
        loc = prefix + tuple(err["loc"])
        cause = (err.get("ctx") or {}).get("error")
        if isinstance(cause, At):
            if cause.cause is not None:
                yield from _flatten(cause.cause, loc + cause.loc)
                continue
            yield loc + cause.loc, cause.message
        else:
            yield loc, _message(err)


def _loc_text(loc) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out or "<top level>"


def format_validation_error(exc: ValidationError, source: str,
                            origins: dict[str, str] | None = None) -> ConfigError:
    """One :class:`ConfigError` line for a pydantic error: ``source: key.path: message``.

    Only the first problem is reported (fix it, rerun); the count of the
    others is appended. ``origins`` maps schema key paths to where their
    value came from (e.g. ``from GLACiAR key 'zeropoints[0]'``).
    """
    problems = list(_flatten(exc))
    loc, message = problems[0]
    path = _loc_text(loc)
    origin = (origins or {}).get(path)
    if origin:
        message += f" ({origin})"
    more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
    return ConfigError(f"{source}: {path}: {message}{more}")
