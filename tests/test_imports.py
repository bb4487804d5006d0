"""The package's shape, read from its source (issue 22, acceptance): no import cycle among
``glaciar`` modules, no import of another module's private name, no module over
``MAX_MODULE_LINES`` lines, no function over ``MAX_PARAMETERS`` parameters.

Everything is read with :mod:`ast` -- nothing is imported -- so a cycle is found even where
a function-level import keeps it from failing at import time.  A node is a module (a
package's ``__init__`` is the package's node); an edge is an explicit import, at any
level: ``from glaciar.a.b import x`` is an edge to ``glaciar.a.b`` only (Python runs
``glaciar/a/__init__`` first, but only its module-level code), ``from glaciar.a import b``
to the submodule ``b``.  Imports under ``if TYPE_CHECKING:`` never run and are left out.

The ``ALLOWED_*`` lists name today's offenders, each with the issue-22 point whose branch
removes it; the lead empties them as those branches merge.  Any offender not listed fails
(``test_*``), and so does a listed one that is gone (``test_allow_lists_are_current``), so
the lists can only shrink.
"""
from __future__ import annotations

import ast
from dataclasses import dataclass, field
from pathlib import Path

PACKAGE = "glaciar"
ROOT = Path(__file__).resolve().parents[1] / PACKAGE
MAX_MODULE_LINES = 900
MAX_PARAMETERS = 12

# Why an offender would be allowed: the issue point that removes it (all lists are empty now).
# Import edges ("importer -> imported") that close today's cycles; every other cycle fails.
ALLOWED_CYCLE_EDGES: dict = {}

# "module: imported_module._name" -- private names read across modules.
ALLOWED_PRIVATE_IMPORTS: dict = {}

# Modules over MAX_MODULE_LINES lines.
ALLOWED_LONG_MODULES: dict = {}

# "module.qualified_function" with more than MAX_PARAMETERS parameters.
ALLOWED_LONG_SIGNATURES: dict = {}


# --------------------------------------------------------------------------------------
# reading the package
# --------------------------------------------------------------------------------------

@dataclass
class Module:
    name: str
    path: Path
    is_package: bool
    tree: ast.Module
    n_lines: int
    imports: set = field(default_factory=set)        # glaciar modules imported (any level)
    private: set = field(default_factory=set)        # "imported_module._name"


def _module_name(path: Path, root: Path) -> tuple[str, bool]:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        return ".".join(parts[:-1]), True
    return ".".join(parts), False


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _nodes(tree: ast.AST):
    """The import statements and the private-attribute reads of ``tree`` (one pass),
    skipping ``if TYPE_CHECKING:`` bodies (never run, so no import cycle)."""
    imports, attributes, stack = [], [], [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            imports.append(node)
            continue
        if isinstance(node, ast.Attribute) and _is_private(node.attr):
            attributes.append(node)
        children = list(ast.iter_child_nodes(node))
        if isinstance(node, ast.If):
            test = node.test
            name = test.id if isinstance(test, ast.Name) else getattr(test, "attr", None)
            if name == "TYPE_CHECKING":
                children = [node.test, *node.orelse]
        stack.extend(children)
    return imports, attributes


def _read_package(root: Path = ROOT) -> dict[str, Module]:
    """Every module of the package at ``root`` (a directory named ``PACKAGE``), read."""
    modules = {}
    for path in sorted(root.rglob("*.py")):
        name, is_package = _module_name(path, root)
        text = path.read_text(encoding="utf-8")
        modules[name] = Module(name, path, is_package, ast.parse(text, str(path)),
                               len(text.splitlines()))
    for mod in modules.values():
        _collect_imports(mod, modules)
    return modules


def _collect_imports(mod: Module, modules: dict[str, Module]) -> None:
    """Fill ``mod.imports`` and ``mod.private`` from every import statement (module level
    and inside functions) and every ``alias._name`` attribute read of an imported module."""
    imports, attributes = _nodes(mod.tree)
    package = mod.name if mod.is_package else mod.name.rpartition(".")[0]
    aliases: dict[str, str] = {}          # local name -> glaciar module it is bound to

    def add_module(target: str) -> None:
        if target != mod.name:
            mod.imports.add(target)
            # a private module (``config/_x.py``) is its own package's business
            parent, _, last = target.rpartition(".")
            if _is_private(last) and not (mod.name + ".").startswith(parent + "."):
                mod.private.add(target)

    for node in imports:
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] != PACKAGE:
                    continue
                target = alias.name
                while target not in modules:
                    target = target.rpartition(".")[0]
                add_module(target)
                if alias.asname:
                    aliases[alias.asname] = alias.name
                else:
                    aliases[PACKAGE] = PACKAGE
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                base_parts = base_parts[:len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if base.split(".")[0] != PACKAGE:
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if sub in modules:                      # from package import submodule
                    add_module(sub)
                    aliases[alias.asname or alias.name] = sub
                    continue
                add_module(base)
                if _is_private(alias.name) and base != mod.name:
                    mod.private.add(f"{base}.{alias.name}")
    # attribute reads of a private name through a module alias: ``measure._row_tiles``
    for node in attributes:
        chain, value = [], node.value
        while isinstance(value, ast.Attribute):
            chain.append(value.attr)
            value = value.value
        if isinstance(value, ast.Name) and value.id in aliases:
            target = ".".join([aliases[value.id], *reversed(chain)])
            if target in modules and target != mod.name:
                mod.private.add(f"{target}.{node.attr}")


def _cycles(modules: dict[str, Module], allowed_edges) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), once the
    ``allowed_edges`` ("a -> b") are taken out of the graph."""
    graph = {name: sorted(t for t in mod.imports if f"{name} -> {t}" not in allowed_edges)
             for name, mod in modules.items()}
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _cycle_edges(modules, comp) -> list[str]:
    members = set(comp)
    return sorted(f"{a} -> {b}" for a in comp for b in modules[a].imports if b in members)


def _long_signatures(modules: dict[str, Module]) -> dict[str, int]:
    out = {}
    for mod in modules.values():
        def walk(node, prefix):
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    a = child.args
                    params = [*a.posonlyargs, *a.args, *a.kwonlyargs]
                    names = [p.arg for p in params]
                    if names and names[0] in ("self", "cls"):
                        names = names[1:]
                    n = len(names) + (a.vararg is not None) + (a.kwarg is not None)
                    if n > MAX_PARAMETERS:
                        out[f"{mod.name}.{prefix}{child.name}"] = n
                    walk(child, f"{prefix}{child.name}.")
                elif isinstance(child, ast.ClassDef):
                    walk(child, f"{prefix}{child.name}.")
                else:
                    walk(child, prefix)
        walk(mod.tree, "")
    return out


MODULES = _read_package()
LONG_SIGNATURES = _long_signatures(MODULES)


# --------------------------------------------------------------------------------------
# the checks
# --------------------------------------------------------------------------------------

def test_no_import_cycle():
    found = _cycles(MODULES, ALLOWED_CYCLE_EDGES)
    assert not found, "import cycles (edges inside each):\n" + "\n".join(
        "  " + "; ".join(_cycle_edges(MODULES, comp)) for comp in found)


def test_no_private_name_imported_across_modules():
    found = sorted(p for mod in MODULES.values() for p in (f"{mod.name}: {x}" for x in mod.private)
                   if p not in ALLOWED_PRIVATE_IMPORTS)
    assert not found, ("private names read from another module (make them public where "
                       "shared):\n  " + "\n  ".join(found))


def test_no_module_over_max_lines():
    found = sorted(f"{m.name} ({m.n_lines} lines)" for m in MODULES.values()
                   if m.n_lines > MAX_MODULE_LINES and m.name not in ALLOWED_LONG_MODULES)
    assert not found, f"modules over {MAX_MODULE_LINES} lines: {found}"


def test_no_function_over_max_parameters():
    found = sorted(f"{f} ({n})" for f, n in LONG_SIGNATURES.items()
                   if f not in ALLOWED_LONG_SIGNATURES)
    assert not found, f"functions over {MAX_PARAMETERS} parameters: {found}"


def test_allow_lists_are_current():
    """An allow-listed offender that is gone must leave its list (the lists only shrink)."""
    edges = {e for comp in _cycles(MODULES, ()) for e in _cycle_edges(MODULES, comp)}
    private = {f"{m.name}: {x}" for m in MODULES.values() for x in m.private}
    long_modules = {m.name for m in MODULES.values() if m.n_lines > MAX_MODULE_LINES}
    long_signatures = set(LONG_SIGNATURES)
    stale = ([e for e in ALLOWED_CYCLE_EDGES if e not in edges]
             + [p for p in ALLOWED_PRIVATE_IMPORTS if p not in private]
             + [m for m in ALLOWED_LONG_MODULES if m not in long_modules]
             + [f for f in ALLOWED_LONG_SIGNATURES if f not in long_signatures])
    assert not stale, f"allow-listed offenders that are gone (remove them): {stale}"


def test_the_reader_sees_what_python_would_import(tmp_path):
    """The graph holds function-level and relative imports, ``from package import module``
    and ``alias._name`` reads, and leaves out ``if TYPE_CHECKING:`` blocks."""
    pkg = tmp_path / PACKAGE
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "a.py": "def f():\n    from .sub import b\n    return b._hidden\n",
        "sub/__init__.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .. import c\n",
        "sub/b.py": "from ..c import _private_name\n",
        "c.py": "import glaciar.a as A\n",
        "sub/_impl.py": "",
        "d.py": "from glaciar.sub._impl import x\n",
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    modules = _read_package(pkg)
    assert modules["glaciar.a"].imports == {"glaciar.sub.b"}
    assert modules["glaciar.sub"].imports == set()                 # TYPE_CHECKING only
    assert modules["glaciar.a"].private == {"glaciar.sub.b._hidden"}
    assert modules["glaciar.sub.b"].private == {"glaciar.c._private_name"}
    assert modules["glaciar.d"].private == {"glaciar.sub._impl"}
    assert _cycles(modules, ()) == [["glaciar.a", "glaciar.c", "glaciar.sub.b"]]
    assert _cycles(modules, {"glaciar.c -> glaciar.a"}) == []
