"""The run layer's layout (issue 22 point 1): one module per concept, strictly layered.

Field preparation < context cache < plan < input checks < manifest < execution, and the
worker-process helpers below them all; read from the modules' own import statements (AST),
so a function-level import counts too.  And the WEIGHT_TYPE rule of a band's noise RMS,
which lives in one function (:func:`glaciar.fieldprep.noise_rms`).
"""
from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

import glaciar

PACKAGE = Path(glaciar.__file__).parent
#: Bottom to top: a module may import only those before it.
LAYERS = ("workers", "fieldprep", "contexts", "plan", "inputs", "manifest", "execute")
MAX_LINES = 900


def _imports(name: str) -> list[tuple[str, str]]:
    """``(module, imported name)`` of every relative import in ``glaciar/<name>.py``."""
    tree = ast.parse((PACKAGE / f"{name}.py").read_text(encoding="utf-8"))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            for alias in node.names:
                out.append((node.module or "", alias.name))
    return out


def test_run_py_is_gone_and_nothing_imports_it():
    assert not (PACKAGE / "run.py").exists()
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                target = ("." * node.level) + (node.module or "")
                assert target not in (".run", "..run", "glaciar.run"), path
                assert not (node.module is None and any(a.name == "run" for a in node.names)
                            and node.level >= 1), path


@pytest.mark.parametrize("name", LAYERS)
def test_each_run_module_is_small_and_imports_only_below_it(name):
    assert len((PACKAGE / f"{name}.py").read_text(encoding="utf-8").splitlines()) <= MAX_LINES
    below = set(LAYERS[:LAYERS.index(name)])
    for module, imported in _imports(name):
        top = module.split(".")[0]
        if top in LAYERS:
            assert top in below, f"glaciar.{name} imports glaciar.{module} (not below it)"
            # Shared names are public: no module reaches into another's private names.
            assert not imported.startswith("_"), f"glaciar.{name} imports {module}.{imported}"


def test_noise_rms_follows_weight_type():
    from glaciar.fieldprep import noise_rms

    noise = np.full((4, 4), 0.5, np.float32)       # the map's RMS
    nodata = np.zeros((4, 4), bool)
    nodata[0, 0] = True
    measured = np.full((4, 4), 2.0, np.float32)     # sep's background RMS
    measured[0, 0] = 100.0                          # no data there: left out of the factor
    calls = []

    def background():
        calls.append(1)
        return measured

    # An absolute map (no WEIGHT_TYPE, MAP_RMS) is used as it is; the background is not measured.
    for weight_type in (None, "map_rms"):
        rms, from_background = noise_rms(noise, weight_type, background, nodata)
        assert rms is noise and not from_background
    assert calls == []
    # MAP_WEIGHT: one factor, median(2.0 / 0.5) = 4 over the pixels with data.
    rms, from_background = noise_rms(noise, "map_weight", background, nodata)
    np.testing.assert_array_equal(rms, np.full((4, 4), 2.0, np.float32))
    assert not from_background
    # BACKGROUND, or no map: sep's background RMS.
    for args in ((noise, "background"), (None, None), (None, "map_weight")):
        rms, from_background = noise_rms(*args, background, nodata)
        assert rms is measured and from_background
