"""Selections made by a user's Python function (issue 23, point 1).

``selection: {function: "module:callable"}``: the same rows as the equivalent expression
list, probabilities drawn reproducibly, the example photo-z recovering the redshift of
noiseless sources, one-line refusals of bad callables, the declared version in the
store's identity.  The functions live in a module written into a temporary directory
put on ``sys.path`` (and ``PYTHONPATH``, for subprocesses).
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from glaciar import constants as C
from glaciar.cli import main
from glaciar.config import ConfigError, config_to_dict, load_config
from glaciar.engine.task import field_key
from glaciar.engine.user_selection import draw_selected
from glaciar.execute import simulate
from glaciar.pipeline.catalog import run_catalog
from glaciar.rundir import StoreMismatchError
from glaciar.store import read_results

REPO = Path(__file__).resolve().parents[2]
MODULE = "glaciar_test_usersel"
KEY = [C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]
#: The cell of small_survey the runs here simulate (2 tasks of its 8).
CELL = {"z": {"values": [10.4]}, "mag": {"values": [24.0]}}

SOURCE = '''
import numpy as np

glaciar_selection_version = "1"


def jdropout(t):
    """The default BoRG J125-dropout expressions, as numpy (NaN compares False)."""
    with np.errstate(invalid="ignore"):
        return ((t["sn_f160w"] >= 8) & (t["sn_f606w"] < 1.5) & (t["sn_f098m"] < 1.5)
                & (t["maglim_f125w"] - t["mag_f160w"] > 1.5))


def logistic(t, sn0=10.0, width=4.0):
    """P(selected) rising with the F160W S/N (probabilities strictly inside (0, 1))."""
    sn = np.nan_to_num(t["sn_f160w"], nan=-100.0)
    return 0.02 + 0.96 / (1.0 + np.exp(-(sn - sn0) / width))


def raises(t):
    return 1 / 0


def too_short(t):
    return np.ones(len(t["sn_f160w"]) - 1, bool)


def non_finite(t):
    return np.full(len(t["sn_f160w"]), np.nan)


def outside(t):
    return np.full(len(t["sn_f160w"]), 1.5)


def integers(t):
    return np.ones(len(t["sn_f160w"]), dtype=np.int64)


def nan_on_real_data(t):
    """Passes the configuration check; NaN where a measured magnitude is NaN (real data)."""
    return t["mag_f606w"] * 0.0 + 0.5


not_callable = 3


def unversioned(t):
    return t["sn_f160w"] > 0


unversioned_module_version = None
'''


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """The module of selection functions, importable here and in subprocesses."""
    d = tmp_path / "usermods"
    d.mkdir()
    (d / f"{MODULE}.py").write_text(textwrap.dedent(SOURCE))
    monkeypatch.syspath_prepend(str(d))
    monkeypatch.setenv("PYTHONPATH", f"{d}:{REPO}")
    sys.modules.pop(MODULE, None)
    yield d
    sys.modules.pop(MODULE, None)


def _config(small_survey, tmp_path, name, selection) -> Path:
    """small_survey's configuration (absolute paths) on CELL, with ``selection``, in tmp_path."""
    d = config_to_dict(load_config(small_survey))
    d["selection"] = selection
    d["grid"].update(CELL)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def _rows(run) -> pd.DataFrame:
    return read_results(run).sort_values(KEY).reset_index(drop=True)


def test_function_reproducing_the_expressions_gives_identical_rows(small_run, small_survey,
                                                                    user_module, tmp_path):
    cfg_e, run_e = small_run
    assert cfg_e.selection == tuple(yaml.safe_load(Path(small_survey).read_text())["selection"])
    path = _config(small_survey, tmp_path, "fn", {"function": f"{MODULE}:jdropout"})
    cfg = load_config(path)
    assert (cfg.selection.version, cfg.selection.kind) == ("1", "boolean")
    simulate(cfg, tmp_path / "run", workers=1, progress=False)
    got = _rows(tmp_path / "run")
    want = _rows(run_e)
    want = want[(want[C.COL_Z] == 10.4) & (want[C.COL_MAG] == 24.0)].reset_index(drop=True)
    assert len(got) == len(want) > 0 and want[C.COL_SELECTED].any()
    assert C.COL_P_SELECTED not in got.columns
    pd.testing.assert_frame_equal(got, want, check_exact=True)

    # The declared version is part of the store's identity: a new one refuses the resume.
    module = sys.modules[MODULE]
    module.glaciar_selection_version = "2"
    with pytest.raises(StoreMismatchError, match=r"selection\.version: 1 -> 2"):
        simulate(load_config(path), tmp_path / "run", workers=1, progress=False)
    module.glaciar_selection_version = "1"


def test_probabilities_are_drawn_reproducibly(small_survey, user_module, tmp_path):
    path = _config(small_survey, tmp_path, "prob",
                   {"function": f"{MODULE}:logistic", "kwargs": {"sn0": 10.0, "width": 4.0}})
    cfg = load_config(path)
    assert cfg.selection.kind == "probability"
    simulate(cfg, tmp_path / "w1", workers=1, progress=False)
    simulate(load_config(path), tmp_path / "w2", workers=2, progress=False)
    one, two = _rows(tmp_path / "w1"), _rows(tmp_path / "w2")
    pd.testing.assert_frame_equal(one, two, check_exact=True)
    p = one[C.COL_P_SELECTED].to_numpy()
    sel, rec = one[C.COL_SELECTED].to_numpy(), one[C.COL_RECOVERED].to_numpy()
    assert ((p > 0) & (p < 1)).all()
    assert not (sel & ~rec).any()                       # selected needs recovered
    # Expected count among the recovered, within 4 binomial standard deviations.
    pr = p[rec]
    assert abs(sel.sum() - pr.sum()) <= 4 * np.sqrt((pr * (1 - pr)).sum()) + 1
    # The same callable selects the catalogue; its draw comes from the run's seed and field.
    cat = run_catalog(tmp_path / "w1")
    fn = sys.modules[MODULE].logistic
    p_cat = fn({c: cat[c].to_numpy(float) for c in cat.columns if c.endswith(
        ("_f160w", "_f098m", "_f125w", "_f606w"))}, sn0=10.0, width=4.0)
    np.testing.assert_array_equal(cat[C.COL_P_SELECTED].to_numpy(), p_cat)
    usable = cat[C.COL_RECOVERED].to_numpy() & cat["in_footprint"].to_numpy()
    want = usable & draw_selected(p_cat, (cfg.simulation.seed, field_key(cfg.survey.fields[0])))
    np.testing.assert_array_equal(cat[C.COL_SELECTED].to_numpy(), want)
    assert want.any() and (~want & usable).any()
    # The draw itself, on many rows: mean matches, reproducible, depends on the entropy.
    q = np.random.default_rng(1).uniform(0, 1, 40_000)
    a = draw_selected(q, (7, 9))
    assert abs(a.mean() - q.mean()) < 4 * np.sqrt((q * (1 - q)).sum()) / q.size
    assert (a == draw_selected(q, (7, 9))).all() and (a != draw_selected(q, (7, 10))).any()
    assert draw_selected(np.ones(50), (1,)).all() and not draw_selected(np.zeros(50), (1,)).any()


def test_example_photoz_recovers_redshift_of_noiseless_sources(monkeypatch):
    from glaciar.galaxy import sed

    monkeypatch.syspath_prepend(str(REPO / "examples"))
    import photoz_selection as ps

    bands = ("f090w", "f115w", "f150w", "f200w", "f277w", "f356w", "f444w")
    filters = {b: f"nircam_{b}" for b in bands}
    zp = {b: 28.0866 for b in bands}
    z_true = np.array([6.23, 7.5, 8.3, 9.71, 11.2, 12.66, 14.1])
    mags = np.array([sed.band_magnitudes(z, [-2.2], list(filters.values()), mag=[27.0],
                                         detection_index=4)[0] for z in z_true])
    sigma = 10 ** (-0.4 * (31.0 - 28.0866))            # a 31 mag 1-sigma error
    table = {}
    for j, b in enumerate(bands):
        table[f"flux_iso_{b}"] = np.where(np.isfinite(mags[:, j]),
                                          10 ** (-0.4 * (mags[:, j] - 28.0866)), 0.0)
        table[f"fluxerr_iso_{b}"] = np.full(z_true.size, sigma)
    step = 0.1
    z_grid, pz = ps.photoz(table, filters=filters, zeropoints=zp, z_step=step)
    z_best = z_grid[pz.argmax(axis=1)]
    assert np.all(np.abs(z_best - z_true) <= step + 1e-9), np.c_[z_true, z_best]
    chosen = ps.select(table, filters=filters, zeropoints=zp, z_cut=7.0, p_min=0.7)
    assert chosen.tolist() == (z_true > 7.0 + step).tolist()


@pytest.mark.parametrize("function, words", [
    ("no_such_module_xyz:f", ["no_such_module_xyz", "cannot be imported", "ModuleNotFoundError"]),
    (f"{MODULE}:missing", ["has no attribute 'missing'"]),
    (f"{MODULE}:not_callable", ["is not callable"]),
    (f"{MODULE}:raises", ["raised ZeroDivisionError: division by zero"]),
    (f"{MODULE}:too_short", ["returned 2 values for a table of 3 sources"]),
    (f"{MODULE}:non_finite", ["non-finite values"]),
    (f"{MODULE}:outside", ["outside [0, 1]", "max 1.5"]),
    (f"{MODULE}:integers", ["dtype int64"]),
    ("not a name", ["expected 'package.module:callable'"]),
])
def test_bad_callables_are_refused_in_one_line(small_survey, user_module, tmp_path, capsys,
                                               function, words):
    path = _config(small_survey, tmp_path, "bad", {"function": function})
    out = tmp_path / "never"
    assert main(["simulate", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "selection.function" in err, err
    for w in words + [function.partition(":")[0] if ":" in function else function]:
        assert w in err, (w, err)
    assert not out.exists()


def test_function_without_a_version_is_refused(small_survey, user_module, tmp_path):
    (user_module / "glaciar_test_unversioned.py").write_text("def f(t):\n    return t['sn_f160w'] > 0\n")
    path = _config(small_survey, tmp_path, "nover", {"function": "glaciar_test_unversioned:f"})
    with pytest.raises(ConfigError, match=r"declares no version; set f\.glaciar_selection_version"):
        load_config(path)
    # Through the command line, in its own process: exit 2, one line.
    r = subprocess.run([sys.executable, "-m", "glaciar", "simulate", str(path), "--out",
                        str(tmp_path / "x")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "glaciar_test_unversioned:f" in r.stderr and not (tmp_path / "x").exists()


def test_failure_on_real_data_stops_the_run_in_one_line(small_survey, user_module, tmp_path,
                                                        capsys):
    path = _config(small_survey, tmp_path, "late", {"function": f"{MODULE}:nan_on_real_data"})
    load_config(path)                                   # passes the configuration check
    assert main(["simulate", str(path), "--out", str(tmp_path / "run"), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert any(f"selection function '{MODULE}:nan_on_real_data': returned non-finite" in e
               for e in err), err
