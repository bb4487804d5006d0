"""The ``selection:`` key as a user function: ``{function: "pkg.mod:name", kwargs: {...}}``,
and what the rest of glaciar needs to know of any selection (its plain data, its
description, the bands it reads, the object the engine applies).

The function itself is imported and checked by :mod:`glaciar.engine.user_selection`
when the configuration is validated (:meth:`glaciar.config.models.Config._cross_checks`).
"""
from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from pydantic import Field, PrivateAttr

from ..engine.user_selection import SelectionFunction, function_columns, import_selection_function
from .common import At, show
from .section import Section

__all__ = ["SelectionFunctionConfig", "selection_data", "selection_description",
           "engine_selection"]

#: Deepest nesting and most items of ``selection.kwargs`` (plain YAML data, not a data set).
MAX_KWARGS_DEPTH = 8
MAX_KWARGS_ITEMS = 10_000


def _plain_data(value, loc: tuple, depth: int = 0, count: list | None = None):
    """``value`` checked to be plain YAML data (str, number, bool, null, lists, mappings
    with string keys): kwargs enter the run's identity as JSON."""
    count = [0] if count is None else count
    count[0] += 1
    if count[0] > MAX_KWARGS_ITEMS or depth > MAX_KWARGS_DEPTH:
        raise At(f"more than {MAX_KWARGS_ITEMS} items or {MAX_KWARGS_DEPTH} levels; pass a "
                 "file name instead", *loc)
    if value is None or isinstance(value, (str, bool, int)):
        return value
    if isinstance(value, float):
        if value != value or value in (float("inf"), float("-inf")):
            raise At(f"expected a finite number, got {show(value)}", *loc)
        return value
    if isinstance(value, (list, tuple)):
        return [_plain_data(v, loc + (i,), depth + 1, count) for i, v in enumerate(value)]
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise At(f"keys must be strings, got {show(k)}", *loc)
            out[k] = _plain_data(v, loc + (k,), depth + 1, count)
        return out
    raise At(f"expected plain data (string, number, true/false, list, mapping), got "
             f"{show(value)}", *loc)


class SelectionFunctionConfig(Section):
    """``selection: {function: "package.module:callable", kwargs: {...}}``.

    The callable (importable from the Python environment glaciar runs in) is called
    as ``f(table, **kwargs)`` on every task's sources and on the catalogue, and
    returns booleans or probabilities (see :mod:`glaciar.engine.user_selection`).
    ``version`` and ``kind`` are read from the function when the whole configuration
    is validated.
    """

    function: str = Field(description="'package.module:callable' returning booleans "
                                      "(selected) or probabilities per source")
    kwargs: dict[str, Any] = Field(default_factory=dict, description="keyword arguments of "
                                   "every call (plain data)")
    _version: str = PrivateAttr("")
    _kind: str = PrivateAttr("")

    @classmethod
    def _prepare(cls, data: dict, info) -> dict:
        if "function" in data and not isinstance(data["function"], str):
            raise At(f"expected 'package.module:callable', got {show(data['function'])}",
                     "function")
        if "kwargs" in data:
            if not isinstance(data["kwargs"], Mapping):
                raise At(f"expected a mapping of keyword arguments, got {show(data['kwargs'])}",
                         "kwargs")
            data["kwargs"] = _plain_data(data["kwargs"], ("kwargs",))
        return data

    @property
    def version(self) -> str:
        """The version the function declares ('' before the configuration is validated)."""
        return self._version

    @property
    def kind(self) -> str:
        """``"boolean"`` or ``"probability"`` (what it returned on the check table)."""
        return self._kind

    def resolved(self, loaded: SelectionFunction) -> None:
        """Record what :func:`~glaciar.engine.user_selection.load_selection_function` found."""
        self._version, self._kind = loaded.version, loaded.kind


def selection_data(selection) -> list | dict:
    """The ``selection`` value as plain data (a config file's form): a list of
    expressions, or ``{"function": ..., "kwargs": {...}}``."""
    if isinstance(selection, SelectionFunctionConfig):
        return {"function": selection.function, "kwargs": json.loads(json.dumps(selection.kwargs))}
    return list(selection)


def selection_description(selection) -> list[str]:
    """Human-readable selection criteria (the manifest's and catalogue's ``selection``):
    the expressions, or one line naming the function, its version and kwargs."""
    if isinstance(selection, SelectionFunctionConfig):
        kw = (", kwargs " + json.dumps(selection.kwargs, sort_keys=True)) if selection.kwargs else ""
        return [f"function {selection.function} (version {selection.version}, "
                f"{selection.kind}{kw})"]
    return list(selection)


def engine_selection(cfg):
    """The object the engine applies: a compiled expression list, a
    :class:`~glaciar.engine.user_selection.SelectionFunction`, or None (no selection).

    A function's version and kind are those found when ``cfg`` was validated (no
    second dry call).
    """
    from ..engine.selection import compile_selection

    sel = cfg.selection
    if isinstance(sel, SelectionFunctionConfig):
        n_ap = len(cfg.detection.phot_apertures)
        return SelectionFunction(spec=sel.function.strip(), version=sel.version, kind=sel.kind,
                                 columns=function_columns(cfg.survey.band_names, n_ap),
                                 kwargs=dict(sel.kwargs),
                                 func=import_selection_function(sel.function))
    return compile_selection(sel) if sel else None
