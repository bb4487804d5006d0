"""The leaf of :mod:`glaciar.config`: what its modules share, importing none of them.

Validation vocabulary, path resolution, the context helpers of validators and the
bounded YAML reader, used by ``models``, ``io``, ``sextractor`` and ``glaciar_compat``
(which therefore never import one another to reach a helper).

Pydantic does the type checking; this module turns its errors into the one
line glaciar prints (``file: key.path: what was expected, got what``) and
adds the few types YAML users need: numbers that may arrive as strings
(PyYAML reads ``1e-3`` as a string), integers that refuse booleans, choices
matched case-insensitively with a "did you mean" hint, and lists that accept
a single value (lists: ``section.float_list``).
"""
from __future__ import annotations

import difflib
import math
import os
import reprlib
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BeforeValidator, ValidationError, ValidationInfo

from ..galaxy.filters import looks_like_path

__all__ = ["ConfigError", "At", "Int", "Float", "Choice", "show", "yaml_bool_hint",
           "format_validation_error", "unknown_key_error", "resolve_path", "add_warning",
           "resolve_filter_name", "TRUE_WORDS", "FALSE_WORDS", "parse_bool", "read_yaml",
           "MAX_CONFIG_BYTES", "MAX_YAML_ALIASES", "MAX_YAML_DEPTH", "MAX_YAML_VALUES"]


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


# ----------------------------------------------------------------------
# paths, booleans and the validation context
# ----------------------------------------------------------------------

def resolve_path(base_dir, value: str) -> str:
    """``value`` (``~`` expanded) made absolute against ``base_dir``."""
    p = Path(os.path.expanduser(value))
    return str(p if p.is_absolute() else (Path(base_dir) / p).resolve())


def add_warning(info: ValidationInfo, message: str) -> None:
    """Record ``message`` in the validation context (``Config.warnings``)."""
    (info.context or {}).setdefault("warnings", []).append(message)


def resolve_filter_name(value, base_dirs) -> str:
    """A FILTER_NAME: a built-in kernel name as is, a ``.conv`` path made absolute."""
    if not isinstance(value, str) or not value.strip():
        raise At(f"expected a built-in kernel name or a .conv file, got {show(value)}"
                 f"{yaml_bool_hint(value)}",
                 "FILTER_NAME")
    value = value.strip()
    if not looks_like_path(value, (".conv",)):
        return value
    for d in base_dirs:
        p = resolve_path(d, value)
        if Path(p).is_file():
            return p
    return resolve_path(base_dirs[0], value)    # missing: check_files reports it


#: Words read as true / false: YAML 1.1 and SExtractor spell them yes, No, Y, N.
TRUE_WORDS = frozenset(("yes", "y", "true", "t", "on", "1"))
FALSE_WORDS = frozenset(("no", "n", "false", "f", "off", "0"))


def parse_bool(value) -> bool | None:
    """``value`` as a bool (bool, 0/1 or one of the words above), or None if it is none."""
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in TRUE_WORDS | FALSE_WORDS:
        return value.strip().lower() in TRUE_WORDS
    return None


# ----------------------------------------------------------------------
# bounded YAML
# ----------------------------------------------------------------------

#: Largest configuration file read [bytes].
MAX_CONFIG_BYTES = 1_000_000
#: Most YAML aliases (``*name``) a configuration may use: enough for any real
#: file, too few for an alias bomb (each level of which doubles the data).
MAX_YAML_ALIASES = 100
#: Deepest nesting of YAML collections.
MAX_YAML_DEPTH = 50
#: Most values a configuration may hold once its aliases are expanded.
MAX_YAML_VALUES = 100_000


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys, alias bombs and absurd nesting."""

    def __init__(self, stream):
        super().__init__(stream)
        self._aliases = 0
        self._depth = 0

    def compose_document(self):
        # Aliases share nodes: count the values as if expanded (memoised per node,
        # so this is linear in the file) and refuse a document that would explode.
        node = super().compose_document()
        sizes: dict[int, int] = {}

        def size(n) -> int:
            key = id(n)
            if key not in sizes:
                sizes[key] = 1      # a recursive alias counts once
                if isinstance(n, yaml.SequenceNode):
                    total = 1 + sum(size(c) for c in n.value)
                elif isinstance(n, yaml.MappingNode):
                    total = 1 + sum(size(k) + size(v) for k, v in n.value)
                else:
                    total = 1
                sizes[key] = min(total, 10 * MAX_YAML_VALUES)
            return sizes[key]
        if node is not None and size(node) > MAX_YAML_VALUES:
            raise yaml.constructor.ConstructorError(
                None, None, f"its aliases (*name) expand to more than {MAX_YAML_VALUES} values; "
                            "refusing to expand them (YAML alias limit)", node.start_mark)
        return node

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_YAML_ALIASES:
                mark = self.peek_event().start_mark
                raise yaml.constructor.ConstructorError(
                    None, None, f"more than {MAX_YAML_ALIASES} aliases (*name); refusing to "
                                "expand them (YAML alias limit)", mark)
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise yaml.constructor.ConstructorError(
                    None, None, f"collections nested deeper than {MAX_YAML_DEPTH} levels",
                    self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _unique_mapping(loader, node, deep=False):
    seen = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {show(key)}", key_node.start_mark)
            seen.add(key)
        except TypeError:
            pass
    return loader.construct_mapping(node, deep)


_BoundedLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)


def read_yaml(path: str | os.PathLike):
    """Parse a YAML file with the bounded loader; errors name the file, line and column."""
    path = Path(path)
    size = path.stat().st_size
    if size > MAX_CONFIG_BYTES:
        raise ConfigError(f"{path}: {size} bytes; a configuration is at most "
                          f"{MAX_CONFIG_BYTES} bytes (is this the right file?)")
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); save "
                          "the file as UTF-8") from None
    try:
        return yaml.load(text, Loader=_BoundedLoader)  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{path}: {where}invalid YAML ({problem})") from None
    except RecursionError:
        raise ConfigError(f"{path}: invalid YAML (nested too deeply)") from None
