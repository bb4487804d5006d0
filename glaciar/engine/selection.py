"""Colour and S/N selection criteria as safe expressions over per-source columns.

A selection is a list of expressions such as ``"sn_f160w >= 8"`` or
``"maglim_f125w - mag_f160w > 1.5"``; a source is selected when all of them
hold. Expressions are parsed with :mod:`ast` and evaluated by a small
interpreter over a whitelist of constructs, never by :func:`eval`, so a
configuration file cannot run code.

Missing values follow three-valued (Kleene / SQL ``NULL``) logic: a
comparison involving a NaN is *unknown*, ``not unknown`` is unknown,
``unknown and False`` is False, ``unknown or True`` is True, and an
expression that ends unknown does not pass. A source with a NaN in a column
that a cut depends on therefore never passes it, even through a negation.
"""
from __future__ import annotations

import ast
import difflib
import math
import sys
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

__all__ = ["DEFAULT_JDROPOUT", "SelectionError", "Selection", "compile_selection",
           "ALLOWED_FUNCTIONS"]

#: BoRG J125-dropout criteria of Bernard et al. (2016), as used by Carrasco et
#: al. (2018, Sect. 3.1). ``maglim`` is the magnitude of max(flux, 1 sigma), so a
#: J-band non-detection enters the colour with its 1-sigma limit instead of a
#: NaN or a 99 magnitude that would silently pass the cut.
DEFAULT_JDROPOUT = ("sn_f160w >= 8", "sn_f606w < 1.5", "sn_f098m < 1.5",
                    "maglim_f125w - mag_f160w > 1.5")

#: Longest expression [characters], most nested constructs, most expressions: real
#: selections are far below; the limits keep a hostile configuration from
#: exhausting memory or the recursion stack while it is parsed or reported.
MAX_EXPRESSION_CHARS = 1000
MAX_EXPRESSION_DEPTH = 60
MAX_EXPRESSIONS = 100

#: Functions an expression may call, with their number of arguments.
ALLOWED_FUNCTIONS = {"abs": 1, "log10": 1, "sqrt": 1, "isfinite": 1,
                     "minimum": 2, "maximum": 2, "where": 3}


class SelectionError(ValueError):
    """A selection expression is invalid, unsafe, or refers to an unknown column."""


# ---------------------------------------------------------------------------
# Values of the interpreter: numbers (numpy arrays or scalars) and truth values
# with an explicit "known" mask (False where a NaN made the answer unknown).
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class _Truth:
    value: Any   # bool array/scalar; False wherever known is False
    known: Any   # bool array/scalar


def _truth(x) -> _Truth:
    """Interpret a column or number as a truth value (non-zero is true, NaN unknown)."""
    if isinstance(x, _Truth):
        return x
    x = np.asarray(x)
    if x.dtype == bool:
        return _Truth(x, np.ones_like(x, dtype=bool))
    if x.dtype.kind == "f":
        known = ~np.isnan(x)
        return _Truth((x != 0) & known, known)
    if x.dtype.kind in "iu":
        return _Truth(x != 0, np.ones(x.shape, dtype=bool))
    raise TypeError(f"cannot use a value of type {x.dtype} as true/false")


def _number(x):
    """Interpret a truth value as a number (1/0, NaN where unknown)."""
    if isinstance(x, _Truth):
        return np.where(x.known, np.asarray(x.value, dtype=float), np.nan)
    if np.asarray(x).dtype == bool:
        # numpy adds booleans as logical or; arithmetic on flags wants 0/1.
        return np.asarray(x, dtype=np.int64)
    return x


def _and(a: _Truth, b: _Truth) -> _Truth:
    value = a.value & b.value
    # Known when both are known, or when either is a known False.
    known = (a.known & b.known) | (a.known & ~a.value) | (b.known & ~b.value)
    return _Truth(value, known)


def _or(a: _Truth, b: _Truth) -> _Truth:
    value = a.value | b.value
    known = (a.known & b.known) | a.value | b.value   # a known True decides
    return _Truth(value, known)


def _not(a: _Truth) -> _Truth:
    return _Truth(~a.value & a.known, a.known)


def _is_nan(x):
    x = np.asarray(x)
    return np.isnan(x) if x.dtype.kind in "fc" else np.zeros(x.shape, dtype=bool)


_COMPARE = {ast.Lt: np.less, ast.LtE: np.less_equal, ast.Gt: np.greater,
            ast.GtE: np.greater_equal, ast.Eq: np.equal, ast.NotEq: np.not_equal}
_ARITH = {ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply,
          ast.Div: np.true_divide, ast.Pow: np.power}
_CONSTRUCT_NAMES = {
    ast.Attribute: "attribute access", ast.Subscript: "subscript", ast.Lambda: "lambda",
    ast.Starred: "starred argument", ast.ListComp: "comprehension",
    ast.SetComp: "comprehension", ast.DictComp: "comprehension",
    ast.GeneratorExp: "generator expression", ast.IfExp: "conditional expression (use where())",
    ast.List: "list", ast.Tuple: "tuple", ast.Dict: "dict", ast.Set: "set",
    ast.JoinedStr: "f-string", ast.NamedExpr: "assignment expression",
    ast.Await: "await", ast.Yield: "yield", ast.YieldFrom: "yield",
    ast.FloorDiv: "operator //", ast.Mod: "operator %", ast.MatMult: "operator @",
    ast.LShift: "operator <<", ast.RShift: "operator >>", ast.BitXor: "operator ^",
    ast.Is: "operator 'is'", ast.IsNot: "operator 'is not'", ast.In: "operator 'in'",
    ast.NotIn: "operator 'not in'",
}


def _describe(node: ast.AST, expression: str) -> str:
    name = _CONSTRUCT_NAMES.get(type(node), type(node).__name__)
    segment = ast.get_source_segment(expression, node) if hasattr(node, "lineno") else None
    return f"{name} ({segment!r})" if segment else name


class _Validator:
    """Check an expression's syntax tree against the whitelist; collect column names."""

    def __init__(self, expression: str):
        self.expression = expression
        self.columns: list[str] = []

    def parenthesised(self, node: ast.AST) -> bool:
        # ast drops parentheses; look at the source (offsets are UTF-8 bytes, one line).
        src = self.expression.encode("utf-8")
        if getattr(node, "lineno", 1) != 1 or getattr(node, "end_lineno", 1) != 1:
            return True
        return (src[:node.col_offset].rstrip().endswith(b"(")
                and src[node.end_col_offset:].lstrip().startswith(b")"))

    def fail(self, what: str):
        raise SelectionError(f"selection expression {_quote(self.expression)}: {what} is not allowed")

    def visit(self, node: ast.AST, parent: ast.AST | None = None) -> None:
        if isinstance(node, ast.Expression):
            self.visit(node.body, node)
        elif isinstance(node, ast.BoolOp):
            for v in node.values:
                self.visit(v, node)
        elif isinstance(node, ast.BinOp):
            if type(node.op) not in _ARITH and not isinstance(node.op, (ast.BitAnd, ast.BitOr)):
                self.fail(_describe(node.op, self.expression))
            if (isinstance(node.op, (ast.BitAnd, ast.BitOr)) and isinstance(parent, ast.Compare)
                    and not self.parenthesised(node)):
                # `a > 1 & b < 2` parses as `a > (1 & b) < 2`: almost never meant.
                sym = "&" if isinstance(node.op, ast.BitAnd) else "|"
                raise SelectionError(
                    f"selection expression {_quote(self.expression)}: '{sym}' binds more tightly "
                    f"than comparisons; put each comparison in parentheses or use "
                    f"'and'/'or'")
            self.visit(node.left, node)
            self.visit(node.right, node)
        elif isinstance(node, ast.UnaryOp):
            if not isinstance(node.op, (ast.USub, ast.UAdd, ast.Not, ast.Invert)):
                self.fail(_describe(node.op, self.expression))
            self.visit(node.operand, node)
        elif isinstance(node, ast.Compare):
            for op in node.ops:
                if type(op) not in _COMPARE:
                    self.fail(_describe(op, self.expression))
            self.visit(node.left, node)
            for c in node.comparators:
                self.visit(c, node)
        elif isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name):
                self.fail(f"call of {_describe(node.func, self.expression)}")
            fname = node.func.id
            if fname not in ALLOWED_FUNCTIONS:
                self.fail(f"call of {fname!r} (allowed functions: "
                          f"{', '.join(sorted(ALLOWED_FUNCTIONS))})")
            if node.keywords:
                self.fail(f"keyword argument in {fname}()")
            if len(node.args) != ALLOWED_FUNCTIONS[fname]:
                raise SelectionError(
                    f"selection expression {_quote(self.expression)}: {fname}() takes "
                    f"{ALLOWED_FUNCTIONS[fname]} argument(s), got {len(node.args)}")
            for a in node.args:
                self.visit(a, node)
        elif isinstance(node, ast.Name):
            if node.id.startswith("__") or node.id.endswith("__"):
                self.fail(f"dunder name {node.id!r}")
            if node.id in ALLOWED_FUNCTIONS:
                self.fail(f"function {node.id!r} used as a value")
            if node.id not in self.columns:
                self.columns.append(node.id)
        elif isinstance(node, ast.Constant):
            if isinstance(node.value, bool) or (
                    isinstance(node.value, (int, float)) and not isinstance(node.value, complex)):
                return
            self.fail(f"constant {node.value!r} ({type(node.value).__name__})")
        else:
            self.fail(_describe(node, self.expression))


def _constant(value):
    if isinstance(value, bool):
        return np.bool_(value)
    if isinstance(value, int):
        # numpy integers: `10 ** 10 ** 10` overflows instead of hanging on a
        # Python big-int computation. Integers beyond 64 bits are refused at
        # compile time (they could only enter bitwise tests, where a float is wrong).
        return np.int64(value)
    return np.float64(value)


def _real(x):
    """Arithmetic is done in float64: integer overflow (``2 ** 64``) must not wrap silently."""
    x = _number(x)
    if np.asarray(x).dtype.kind in "iub":
        return np.asarray(x, dtype=np.float64)
    return x


def _quote(expr: str, limit: int = 60) -> str:
    """An expression as quoted in messages, shortened (a message stays one readable line)."""
    return repr(expr) if len(expr) <= limit else repr(expr[:limit - 3]) + "..."


def _literal(expr: str, node: ast.Constant, limit: int = 24) -> str:
    """A numeric literal as written in ``expr``, shortened, with its digit count when long."""
    text = ast.get_source_segment(expr.strip(), node) or "?"
    if len(text) <= limit:
        return text
    return f"{text[:limit - 3]}... ({len(text)} characters)"


def _depth(tree: ast.AST) -> int:
    deepest, stack = 0, [(tree, 1)]
    while stack:
        node, d = stack.pop()
        deepest = max(deepest, d)
        stack.extend((child, d + 1) for child in ast.iter_child_nodes(node))
    return deepest


class _Evaluator:
    def __init__(self, columns: Mapping[str, np.ndarray]):
        self.columns = columns

    def eval(self, node: ast.AST):
        if isinstance(node, ast.Expression):
            return self.eval(node.body)
        if isinstance(node, ast.Constant):
            return _constant(node.value)
        if isinstance(node, ast.Name):
            return self.columns[node.id]
        if isinstance(node, ast.BoolOp):
            combine = _and if isinstance(node.op, ast.And) else _or
            result = _truth(self.eval(node.values[0]))
            for v in node.values[1:]:
                result = combine(result, _truth(self.eval(v)))
            return result
        if isinstance(node, ast.UnaryOp):
            x = self.eval(node.operand)
            if isinstance(node.op, ast.Not):
                return _not(_truth(x))
            if isinstance(node.op, ast.Invert):
                if isinstance(x, _Truth) or np.asarray(x).dtype == bool:
                    return _not(_truth(x))
                return np.invert(_integer(x, "~"))
            x = _real(x)
            return np.negative(x) if isinstance(node.op, ast.USub) else np.positive(x)
        if isinstance(node, ast.BinOp):
            a, b = self.eval(node.left), self.eval(node.right)
            if isinstance(node.op, (ast.BitAnd, ast.BitOr)):
                if _is_logical(a) or _is_logical(b):
                    f = _and if isinstance(node.op, ast.BitAnd) else _or
                    return f(_truth(a), _truth(b))
                f = np.bitwise_and if isinstance(node.op, ast.BitAnd) else np.bitwise_or
                return f(_integer(a, "&/|"), _integer(b, "&/|"))
            return _ARITH[type(node.op)](_real(a), _real(b))
        if isinstance(node, ast.Compare):
            left = _number(self.eval(node.left))
            result = None
            for op, comp in zip(node.ops, node.comparators):
                right = _number(self.eval(comp))
                known = ~(_is_nan(left) | _is_nan(right))
                t = _Truth(_COMPARE[type(op)](left, right) & known, known)
                result = t if result is None else _and(result, t)
                left = right
            return result
        if isinstance(node, ast.Call):
            name = node.func.id
            args = [self.eval(a) for a in node.args]
            if name == "isfinite":
                x = args[0]
                if isinstance(x, _Truth):
                    return _Truth(x.known, np.ones_like(x.known))
                x = np.asarray(x)
                ok = np.isfinite(x) if x.dtype.kind in "fc" else np.ones(x.shape, dtype=bool)
                return _Truth(ok, np.ones(x.shape, dtype=bool))
            if name == "where":
                cond = _truth(args[0])
                a, b = args[1], args[2]
                if _is_logical(a) or _is_logical(b):
                    a, b = _truth(a), _truth(b)
                    return _Truth(np.where(cond.value, a.value, b.value) & cond.known,
                                  np.where(cond.value, a.known, b.known) & cond.known)
                out = np.where(cond.value, _number(a), _number(b)).astype(float)
                return np.where(cond.known, out, np.nan)
            args = [_number(a) for a in args]
            func = {"abs": np.abs, "log10": np.log10, "sqrt": np.sqrt,
                    "minimum": np.minimum, "maximum": np.maximum}[name]
            return func(*args)
        raise SelectionError(f"internal error: unexpected node {type(node).__name__}")


def _is_logical(x) -> bool:
    return isinstance(x, _Truth) or np.asarray(x).dtype == bool


def _integer(x, op):
    x = np.asarray(_number(x))
    if x.dtype.kind not in "iub":
        raise TypeError(f"operator {op} needs integer or true/false operands, got {x.dtype}")
    return x


def _column_array(table, name: str) -> np.ndarray:
    col = table[name]
    if hasattr(col, "to_numpy"):
        arr = col.to_numpy()
        if arr.dtype == object:
            # pandas nullable dtypes (Int64, boolean, Float64) with <NA>: NaN means unknown.
            arr = col.to_numpy(dtype=float, na_value=np.nan)
        return arr
    return np.asarray(col)


class Selection:
    """A compiled list of selection expressions; all must hold.

    Attributes
    ----------
    expressions : tuple of str
        The expressions, as given.
    columns : tuple of str
        The column names they use, in order of first appearance.

    Calling the object on a table (a mapping of column name to 1-D array, or a
    :class:`pandas.DataFrame`) returns a boolean array, True where every
    expression holds; a NaN that a cut depends on makes it False.
    """

    def __init__(self, expressions: Sequence[str], trees: Sequence[ast.Expression],
                 columns: Sequence[str]):
        self.expressions = tuple(expressions)
        self._trees = tuple(trees)
        self.columns = tuple(columns)

    def __repr__(self) -> str:
        return f"Selection({list(self.expressions)!r})"

    def _columns_of(self, table) -> tuple[dict, int]:
        available = list(table.columns) if hasattr(table, "columns") else list(table.keys())
        missing = [c for c in self.columns if c not in available]
        if missing:
            hints = []
            for m in missing:
                close = difflib.get_close_matches(m, [str(a) for a in available], n=3)
                hints.append(f"{m!r}" + (f" (did you mean {', '.join(map(repr, close))}?)"
                                         if close else ""))
            raise SelectionError(f"selection uses column(s) not in the table: {', '.join(hints)}")
        cols = {c: _column_array(table, c) for c in self.columns}
        if hasattr(table, "__len__") and hasattr(table, "columns"):
            n = len(table)
        elif cols:
            n = len(next(iter(cols.values())))
        else:
            n = len(_column_array(table, available[0])) if available else 0
        return cols, n

    def masks(self, table) -> dict[str, np.ndarray]:
        """Per-expression boolean masks (useful to see which cut removes a source).

        Parameters
        ----------
        table : mapping of str to array_like, or pandas.DataFrame
            Per-source columns, all of the same length.

        Returns
        -------
        dict
            Expression -> boolean array of the table's length.
        """
        return self._masks(table)[0]

    def _masks(self, table) -> tuple[dict[str, np.ndarray], int]:
        cols, n = self._columns_of(table)
        ev = _Evaluator(cols)
        out = {}
        with np.errstate(all="ignore"):
            for expr, tree in zip(self.expressions, self._trees):
                try:
                    t = _truth(ev.eval(tree))
                    mask = np.broadcast_to(np.asarray(t.value & t.known, dtype=bool), (n,))
                except (TypeError, ValueError) as exc:
                    raise SelectionError(f"selection expression {expr!r}: {exc}") from None
                out[expr] = mask.copy()
        return out, n

    def __call__(self, table) -> np.ndarray:
        """True where all expressions hold (see the class docstring)."""
        masks, n = self._masks(table)
        result = np.ones(n, dtype=bool)
        for m in masks.values():
            result &= m
        return result


def compile_selection(expressions: Sequence[str],
                      available_columns: Iterable[str] | None = None) -> Selection:
    """Parse and check selection expressions.

    Parameters
    ----------
    expressions : sequence of str
        Each a Python-syntax expression over column names using numbers,
        ``+ - * / **``, unary ``-``, comparisons (chained allowed),
        ``and``/``or``/``not``, ``& | ~`` (logical on true/false values,
        bitwise on integer columns such as flags), parentheses, and the
        functions ``abs, log10, sqrt, minimum, maximum, where, isfinite``.
    available_columns : iterable of str, optional
        If given, every name used must be one of these.

    Returns
    -------
    Selection

    Raises
    ------
    SelectionError
        On a syntax error, a construct outside the whitelist (attribute
        access, subscripts, other calls, lambdas, strings, dunder names, ...),
        or an unknown column (with close matches).
    """
    if isinstance(expressions, str):
        expressions = [expressions]
    available = None if available_columns is None else [str(c) for c in available_columns]
    if len(expressions) > MAX_EXPRESSIONS:
        raise SelectionError(f"{len(expressions)} selection expressions; at most "
                             f"{MAX_EXPRESSIONS} are allowed")
    trees, columns = [], []
    for expr in expressions:
        if not isinstance(expr, str):
            raise SelectionError(f"selection expression {str(expr)[:60]!r}: expected a string, "
                                 f"got {type(expr).__name__}")
        if not expr.strip():
            raise SelectionError("selection expression is empty")
        if len(expr) > MAX_EXPRESSION_CHARS:
            raise SelectionError(f"selection expression {_quote(expr)}: {len(expr)} characters "
                                 f"(at most {MAX_EXPRESSION_CHARS} characters)")
        try:
            tree = ast.parse(expr.strip(), mode="eval")
        except SyntaxError as exc:
            raise SelectionError(f"selection expression {_quote(expr)}: invalid syntax "
                                 f"({exc.msg})") from None
        except (RecursionError, MemoryError):
            raise SelectionError(f"selection expression {_quote(expr)}: nested too deeply "
                                 f"to parse") from None
        if _depth(tree) > MAX_EXPRESSION_DEPTH:
            raise SelectionError(f"selection expression {_quote(expr)}: nested more than "
                                 f"{MAX_EXPRESSION_DEPTH} levels deep")
        for node in ast.walk(tree):
            if not isinstance(node, ast.Constant) or isinstance(node.value, bool):
                continue
            # The refusal quotes the literal as written: an integer beyond float range
            # cannot be formatted as a float (OverflowError), and 1e400 has already
            # become inf.
            if isinstance(node.value, int) and not -2**63 <= node.value < 2**63:
                raise SelectionError(f"selection expression {_quote(expr)}: integer constant "
                                     f"{_literal(expr, node)} is outside the 64-bit range")
            if isinstance(node.value, float) and not math.isfinite(node.value):
                raise SelectionError(f"selection expression {_quote(expr)}: number "
                                     f"{_literal(expr, node)} is beyond the float range "
                                     f"(|x| < {sys.float_info.max:.3g})")
        v = _Validator(expr.strip())
        v.visit(tree)
        if available is not None:
            for name in v.columns:
                if name not in available:
                    close = difflib.get_close_matches(name, available, n=3)
                    hint = f"; did you mean {', '.join(map(repr, close))}?" if close else ""
                    raise SelectionError(f"selection expression {_quote(expr)}: unknown column "
                                         f"{name!r}{hint}")
        trees.append(tree)
        columns.extend(c for c in v.columns if c not in columns)
    return Selection(expressions, trees, columns)
