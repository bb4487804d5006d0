"""Selections made by a user's Python function (``selection: {function: "pkg.mod:name"}``).

Survey teams select on photometric redshifts (P(z > z_cut) from template fitting), not on
two colours; such a selection is code, not an expression.  glaciar imports the named
callable with :mod:`importlib` from the user's environment (an installed package or a
module on ``PYTHONPATH``; never from a string of code) and calls it on every task's
table of injected sources and on the observed catalogue, so both are selected the same way.

The call
    ``func(table, **kwargs)`` where ``table`` is a ``dict`` of column name -> read-only
    1-D ``float64`` array, exactly the columns :func:`function_columns` lists (every band's
    ISO, AUTO and aperture fluxes and errors, ``mag``, ``magerr``, ``sn``, ``maglim``,
    ``mag_auto``, ``magerr_auto``: the measured columns injections and catalogue share;
    no input redshift or magnitude, which the catalogue does not have).  ``kwargs`` are the
    config's ``selection.kwargs``.  It returns one value per row: booleans (selected), or
    floats in [0, 1] (probabilities: ``selected`` is then drawn from them with a stream
    derived from the task's seed, or from the run's seed and the field for the catalogue,
    and the probability is stored in :data:`glaciar.constants.COL_P_SELECTED`).  A
    function returns the same kind for every table.

Identity
    The function declares a version (:data:`glaciar.constants.SELECTION_VERSION_ATTRIBUTE`
    on the function, or on its module, or the module's ``__version__``); ``module:name``,
    the version and the kwargs enter the run's store settings, so changing the function's
    declared version refuses a resume like any other changed setting.  A function without
    one is refused: a hash of its source would miss the helpers and data it uses.

Errors
    Each is a :class:`~glaciar.engine.selection.SelectionError`, one line naming the
    function: not importable, not callable, no version, raises (type and message), wrong
    length, wrong dtype, non-finite values, probabilities outside [0, 1].  The
    configuration check calls the function on a tiny synthetic table
    (:func:`check_table`), so most are found before anything is written.
"""
from __future__ import annotations

import importlib
import re
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .. import constants as C
from .measure import output_columns
from .selection import SelectionError

__all__ = ["SelectionFunction", "BOOLEAN", "PROBABILITY", "function_columns",
           "import_selection_function", "declared_version", "check_table", "evaluate",
           "load_selection_function", "draw_selected", "apply_selection"]

BOOLEAN = "boolean"            #: the function returns selected / not selected
PROBABILITY = "probability"    #: the function returns P(selected) in [0, 1]

#: ``package.module:attribute[.attribute]``: dotted identifiers on both sides of one colon.
_SPEC = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")
#: Longest exception message quoted in an error [characters]: the message stays one line.
_MAX_MESSAGE = 200
#: Appended to a stream's entropy so that the selection draw never reuses the numbers of
#: the task's own stream (source properties, positions), whatever its seed.
SELECTION_DRAW_KEY = 0x5E1EC7
#: Magnitudes of the check table's rows in every band [AB]: bright, faint; the third row
#: is a non-detection (flux 0.3 sigma); CHECK_SIGMA_MAG is the 1-sigma flux error's.
CHECK_MAGS = (24.0, 27.0)
CHECK_SIGMA_MAG = 28.0


def _one_line(text: str) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= _MAX_MESSAGE else text[:_MAX_MESSAGE - 3] + "..."


def function_columns(bands: Sequence[str], n_apertures: int) -> tuple[str, ...]:
    """Columns of the table a selection function receives, in order.

    Parameters
    ----------
    bands : sequence of str
        The survey's bands.
    n_apertures : int
        Number of photometric apertures (``flux_aper{k}_<band>``).

    Returns
    -------
    tuple of str
        Every band's measured columns of :func:`glaciar.engine.measure.output_columns`:
        fluxes and errors [image units], ``mag``/``maglim``/``mag_auto`` [AB mag],
        their errors [mag] and ``sn``.
    """
    common = set(output_columns((), n_apertures))
    return tuple(c for c in output_columns(tuple(bands), n_apertures) if c not in common)


def import_selection_function(spec: str) -> Callable:
    """The callable ``spec`` names (``"package.module:name"``), imported with importlib.

    Raises
    ------
    SelectionError
        Malformed name, module not importable (or raising on import), no such
        attribute, not callable.
    """
    if not isinstance(spec, str) or not _SPEC.match(spec.strip()):
        raise SelectionError(f"selection function {str(spec)[:80]!r}: expected "
                             "'package.module:callable' (e.g. 'mysurvey.photoz:select')")
    module_name, _, attr = spec.strip().partition(":")
    try:
        obj = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001 - any import failure is the user's module's
        raise SelectionError(f"selection function {spec!r}: module {module_name!r} cannot be "
                             f"imported ({type(exc).__name__}: {_one_line(exc)}); install it "
                             "or put its directory on PYTHONPATH") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise SelectionError(f"selection function {spec!r}: {module_name!r} has no "
                                 f"attribute {attr!r}")
        obj = getattr(obj, part)
    if not callable(obj):
        raise SelectionError(f"selection function {spec!r}: is not callable (it is a "
                             f"{type(obj).__name__})")
    return obj


def declared_version(func: Callable, spec: str) -> str:
    """The version ``func`` declares: its ``glaciar_selection_version``, else its module's,
    else the module's ``__version__``.

    Raises
    ------
    SelectionError
        None declared, or not a short one-line string or integer.
    """
    module = importlib.import_module(spec.strip().partition(":")[0])
    attr = C.SELECTION_VERSION_ATTRIBUTE
    for owner, name in ((func, attr), (module, attr), (module, "__version__")):
        value = getattr(owner, name, None)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (str, int)) \
                or not str(value).strip() or len(str(value)) > 100 or "\n" in str(value):
            raise SelectionError(f"selection function {spec!r}: {name} is {value!r}; expected "
                                 "a short string or integer (e.g. '1.0')")
        return str(value).strip()
    name = spec.partition(":")[2]
    raise SelectionError(f"selection function {spec!r}: declares no version; set "
                         f"{name}.{attr} = '1' (or the module's __version__) and change it "
                         "whenever the selection changes (it enters the run's identity)")


def check_table(bands: Sequence[str], zeropoints: Mapping[str, float],
                n_apertures: int) -> dict[str, np.ndarray]:
    """A three-row table of :func:`function_columns`: a bright and a faint source and a
    non-detection in every band (the configuration check's dry call).

    Parameters
    ----------
    bands : sequence of str
    zeropoints : mapping band -> float
        AB zeropoints [mag] (fluxes are in image units).
    n_apertures : int
    """
    out = {}
    for b in bands:
        zp = float(zeropoints[b])
        err = 10.0 ** (-0.4 * (CHECK_SIGMA_MAG - zp))
        flux = np.array([10.0 ** (-0.4 * (m - zp)) for m in CHECK_MAGS] + [0.3 * err])
        sig = np.full(flux.shape, err)
        sn = flux / sig
        mag = zp - 2.5 * np.log10(flux)
        q = {"flux_iso": flux, "fluxerr_iso": sig, "flux_auto": flux, "fluxerr_auto": sig,
             "mag": mag, "magerr": 2.5 / np.log(10.0) / sn, "sn": sn,
             "maglim": zp - 2.5 * np.log10(np.maximum(flux, sig)), "mag_auto": mag,
             "magerr_auto": 2.5 / np.log(10.0) / sn}
        for k in range(n_apertures):
            q[f"flux_aper{k}"], q[f"fluxerr_aper{k}"] = flux, sig
        for quantity, values in q.items():
            out[C.band_column(quantity, b)] = values
    return {c: out[c] for c in function_columns(bands, n_apertures)}


@dataclass(frozen=True, eq=False)
class SelectionFunction:
    """A user's selection function, imported and checked.

    Attributes
    ----------
    spec : str
        ``"package.module:name"`` as configured.
    version : str
        The version it declares (:func:`declared_version`).
    kind : {"boolean", "probability"}
        What it returned on the check table.
    columns : tuple of str
        The columns it is given (:func:`function_columns`).
    kwargs : dict
        Keyword arguments of every call (``selection.kwargs``).
    func : callable
    """

    spec: str
    version: str
    kind: str
    columns: tuple[str, ...]
    kwargs: Mapping[str, Any]
    func: Callable

    def __repr__(self) -> str:
        return f"SelectionFunction({self.spec!r}, version {self.version!r}, {self.kind})"

    def __call__(self, table) -> np.ndarray:
        """The checked result on ``table`` (a DataFrame or mapping holding ``columns``):
        bool array (boolean kind) or float64 array in [0, 1] (probability kind)."""
        out = evaluate(self.func, self.spec, table, self.columns, self.kwargs)
        if out.size == 0:
            return out.astype(bool) if self.kind == BOOLEAN else out
        kind = BOOLEAN if out.dtype == bool else PROBABILITY
        if kind != self.kind:
            raise SelectionError(f"selection function {self.spec!r}: returned "
                                 f"{'booleans' if kind == BOOLEAN else 'probabilities'} but "
                                 f"{'booleans' if self.kind == BOOLEAN else 'probabilities'} "
                                 "on the configuration check's table; return one kind always")
        return out


def _input_table(table, columns: Sequence[str], spec: str) -> tuple[dict, int]:
    available = table.columns if hasattr(table, "columns") else table.keys()
    missing = [c for c in columns if c not in available]
    if missing:
        raise SelectionError(f"selection function {spec!r}: the table lacks column(s) "
                             f"{', '.join(missing[:5])}")
    if hasattr(table, "columns"):
        # One copy of the whole block (a DataFrame column at a time costs ~10 us each).
        block = np.ascontiguousarray(table[list(columns)].to_numpy(dtype=np.float64).T)
    else:       # (k, rows) as from a DataFrame, k = 0 included
        block = np.array([np.asarray(table[c], dtype=np.float64) for c in columns],
                         dtype=np.float64).reshape(len(columns), _n_rows(table))
    block.flags.writeable = False       # the engine's table is not the function's to change
    n = block.shape[1] if block.ndim == 2 else 0
    return dict(zip(columns, block)), n


def evaluate(func: Callable, spec: str, table, columns: Sequence[str],
             kwargs: Mapping[str, Any]) -> np.ndarray:
    """Call ``func(columns of table, **kwargs)`` and check what it returns.

    Returns
    -------
    numpy.ndarray
        bool (selected) or float64 in [0, 1] (probabilities), one per row.

    Raises
    ------
    SelectionError
        The function raised, or returned the wrong length, shape or dtype,
        non-finite values or probabilities outside [0, 1].
    """
    cols, n = _input_table(table, columns, spec)
    if n == 0:
        # Nothing to select (a task that placed no source, a field without detections):
        # user code need not handle empty arrays.  The caller's kind decides the dtype.
        return np.zeros(0, dtype=np.float64)
    try:
        out = func(cols, **dict(kwargs))
    except Exception as exc:  # noqa: BLE001 - the user's code: any failure stops the run
        raise SelectionError(f"selection function {spec!r} raised {type(exc).__name__}: "
                             f"{_one_line(exc)}") from None
    try:
        arr = np.asarray(out)
    except Exception:  # noqa: BLE001 - e.g. ragged sequences
        arr = np.asarray(None, dtype=object)
    if arr.ndim != 1 or arr.shape[0] != n:
        got = f"{arr.shape[0]} values" if arr.ndim == 1 else f"shape {arr.shape}"
        raise SelectionError(f"selection function {spec!r}: returned {got} for a table of "
                             f"{n} sources; expected one value per source, shape ({n},)")
    if arr.dtype == bool:
        return arr.copy()
    if arr.dtype.kind != "f":
        raise SelectionError(f"selection function {spec!r}: returned dtype {arr.dtype}; "
                             "expected booleans (selected) or floats in [0, 1] (probabilities)")
    arr = arr.astype(np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        raise SelectionError(f"selection function {spec!r}: returned non-finite values "
                             f"({int(bad.sum())} of {n}, first {arr[bad][0]} at row "
                             f"{int(np.flatnonzero(bad)[0])})")
    if n and (arr.min() < 0.0 or arr.max() > 1.0):
        raise SelectionError(f"selection function {spec!r}: returned probabilities outside "
                             f"[0, 1] (min {arr.min():.6g}, max {arr.max():.6g})")
    return arr


def load_selection_function(spec: str, kwargs: Mapping[str, Any], bands: Sequence[str],
                            zeropoints: Mapping[str, float],
                            n_apertures: int) -> SelectionFunction:
    """Import ``spec``, read its version and call it once on :func:`check_table`.

    Parameters
    ----------
    spec : str
        ``"package.module:name"``.
    kwargs : mapping
        Keyword arguments of every call.
    bands, zeropoints, n_apertures
        The survey's bands, AB zeropoints [mag] and number of apertures.

    Returns
    -------
    SelectionFunction

    Raises
    ------
    SelectionError
        Any refusal of :func:`import_selection_function`, :func:`declared_version`
        or :func:`evaluate`.
    """
    func = import_selection_function(spec)
    spec = spec.strip()
    version = declared_version(func, spec)
    columns = function_columns(bands, n_apertures)
    out = evaluate(func, spec, check_table(bands, zeropoints, n_apertures), columns, kwargs)
    return SelectionFunction(spec=spec, version=version,
                             kind=BOOLEAN if out.dtype == bool else PROBABILITY,
                             columns=columns, kwargs=dict(kwargs), func=func)


def draw_selected(probability: np.ndarray, entropy: Sequence[int]) -> np.ndarray:
    """``selected`` drawn from per-row probabilities, reproducibly.

    Parameters
    ----------
    probability : ndarray of float
        P(selected) per row, in [0, 1].
    entropy : sequence of int
        Non-negative integers identifying the table (a task's stream id; the run's
        seed and the field's key for a catalogue): the draw depends on nothing else,
        so not on workers, their number or the order tasks run in.

    Returns
    -------
    ndarray of bool
        ``u < p`` with u uniform on [0, 1) from the table's own stream (p = 1 always
        selected, p = 0 never).
    """
    ss = np.random.SeedSequence([int(e) for e in entropy] + [SELECTION_DRAW_KEY])
    u = np.random.default_rng(ss).random(np.asarray(probability).shape[0])
    return u < np.asarray(probability, dtype=np.float64)


def _n_rows(table) -> int:
    """Rows of a DataFrame, or of a mapping of equally long columns (0 without columns)."""
    if hasattr(table, "columns"):
        return len(table)
    return len(next(iter(table.values()))) if len(table) else 0


def apply_selection(selection, table, entropy: Sequence[int]) -> tuple[np.ndarray,
                                                                         np.ndarray | None]:
    """Which rows pass ``selection`` (None: all), and their probabilities.

    Parameters
    ----------
    selection : glaciar.engine.selection.Selection, SelectionFunction or None
    table : pandas.DataFrame or mapping of str to 1-d array
    entropy : sequence of int
        The table's identity for :func:`draw_selected` (probabilistic functions only).

    Returns
    -------
    passed : ndarray of bool
    probability : ndarray of float or None
        Only for a probabilistic selection function (``passed`` is drawn from it).
    """
    if selection is None:
        return np.ones(_n_rows(table), dtype=bool), None
    out = np.asarray(selection(table))
    if isinstance(selection, SelectionFunction) and selection.kind == PROBABILITY:
        return draw_selected(out, entropy), out
    return np.asarray(out, dtype=bool), None
