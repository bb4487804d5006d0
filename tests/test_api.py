"""The public API (glaciar.load_config, simulate, catalog, fit, lf): what the CLI and the
notebooks call; arguments reach the layer below, errors are the documented ones."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

import glaciar
from glaciar import constants as C


def test_public_names():
    for name in ("load_config", "simulate", "catalog", "fit", "lf", "SelectionFunction",
                 "sersic_stamp"):
        assert name in glaciar.__all__ and getattr(glaciar, name) is not None
    assert callable(glaciar.demo.build_demo_survey)


def test_load_config_errors(tmp_path, small_survey):
    from glaciar.config import ConfigError

    with pytest.raises(FileNotFoundError):
        glaciar.load_config(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text(small_survey.read_text().replace("zeropoint: 25.946", "zeropoint: abc"))
    with pytest.raises(ConfigError, match="zeropoint"):
        glaciar.load_config(bad)
    # a config whose images are elsewhere: every missing file listed, unless not asked
    moved = tmp_path / "moved.yaml"
    moved.write_text(small_survey.read_text())
    with pytest.raises(FileNotFoundError, match="input file"):
        glaciar.load_config(moved)
    assert glaciar.load_config(moved, check_inputs=False).survey.detection_band == "f160w"


def test_simulate_seed_reaches_the_tasks(small_run, tmp_path):
    """glaciar.simulate with the config's seed reproduces the shared run's rows bit for bit;
    another seed gives other draws."""
    from glaciar.store import read_current_results

    cfg, run = small_run
    want = read_current_results(run).sort_values([C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE])
    stats = glaciar.simulate(cfg.path, tmp_path / "a")
    assert stats["n_sources"] == len(want)
    got = read_current_results(tmp_path / "a").sort_values(
        [C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE])
    np.testing.assert_array_equal(got[C.COL_X].to_numpy(), want[C.COL_X].to_numpy())
    glaciar.simulate(cfg, tmp_path / "b", seed=cfg.simulation.seed + 1)
    other = read_current_results(tmp_path / "b")
    assert not np.array_equal(np.sort(other[C.COL_X].to_numpy()), np.sort(want[C.COL_X].to_numpy()))
    with pytest.raises(TypeError):
        glaciar.simulate(42, tmp_path / "c")


def test_fit_returns_the_written_selection_function(small_run, tmp_path):
    cfg, run = small_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    sf = glaciar.fit(copy, model="logistic", max_steps=300, seed=1, plots=False)
    back = glaciar.SelectionFunction.read(copy / C.SELECTION_FUNCTION_NAME)
    np.testing.assert_array_equal(sf.draws, back.draws)
    assert sf.param_names == back.param_names
