"""Tasks off the Cartesian grid, `glaciar next --write`, and `glaciar simulate --adaptive`.

The kill-and-resume test runs the CLI in a subprocess, SIGKILLs it while a
round's cells are being simulated, resumes, and compares every per-source row
with an uninterrupted run (issue 8's acceptance test).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from glaciar import constants as C
from glaciar.config import ConfigError, config_from_dict, config_to_dict, load_config
from glaciar.inference.adaptive import coarse_axis, coarse_plan
from glaciar.pipeline.adaptive import coarse_design, design_sources
from glaciar.plan import plan_tasks, task_cells
from glaciar.store import current_rows_mask

ADAPTIVE_ARGS = ["--adaptive", "--budget", "192", "--round-size", "96", "--max-steps", "40",
                 "--workers", "1", "--quiet"]


def _config_with(base_config: Path, tmp_path: Path, **grid) -> Path:
    d = yaml.safe_load(base_config.read_text())
    d["grid"].update(grid)
    out = tmp_path / "cfg.yaml"
    out.write_text(yaml.safe_dump(d, sort_keys=False))
    return out


# ---------------------------------------------------------------------------
# cells: planning, identity, membership
# ---------------------------------------------------------------------------
def test_cells_unite_with_the_grid_by_the_largest_iteration_count(small_survey, tmp_path):
    cells = [{"z": 9.1, "mag": 26.05, "n_iterations": 3},
             {"z": 8.0, "mag": 24.0, "n_iterations": 5},        # on the grid (2 iterations)
             {"z": 8.0, "mag": 24.0, "n_iterations": 1},        # the same cell again: max
             {"z": 10.4, "mag": 27.5, "n_iterations": 1}]       # on the grid: adds nothing
    cfg = load_config(_config_with(small_survey, tmp_path, cells=cells))
    n_f = len(cfg.survey.fields)
    counts = {}
    for t in plan_tasks(cfg):
        counts[(t.field, t.z, t.mag)] = counts.get((t.field, t.z, t.mag), 0) + 1
    # Independent count: 2 z x 2 mag x 2 iterations on the grid, one cell raised to 5,
    # one new cell of 3 iterations, per field.
    assert sum(counts.values()) == n_f * (2 * 2 * 2 - 2 + 5 + 3)
    assert all(counts[(f, 8.0, 24.0)] == 5 and counts[(f, 9.1, 26.05)] == 3
               for f in cfg.survey.fields)
    assert counts == {k: v for k, v in task_cells(cfg).items()}
    # Keys are exact values: the tasks' (field, z, mag, iteration) are unique.
    keys = [(t.field, t.z, t.mag, t.iteration) for t in plan_tasks(cfg)]
    assert len(set(keys)) == len(keys)


def test_cells_do_not_change_the_store_identity_and_round_trip(small_survey, tmp_path):
    from glaciar.config import store_hash
    from glaciar.manifest import store_settings

    plain = load_config(small_survey)
    with_cells = load_config(_config_with(small_survey, tmp_path,
                                          cells=[{"z": 9.3, "mag": 25.0}]))
    assert store_hash(plain) == store_hash(with_cells)
    assert store_settings(plain) == store_settings(with_cells)
    again = config_from_dict(config_to_dict(with_cells), base_dir=with_cells.base_dir)
    assert again == with_cells and again.grid.cells[0].z == 9.3


def test_cells_file_is_read_relative_to_the_config(small_survey, tmp_path):
    (tmp_path / "more.yaml").write_text("cells:\n- {z: 9.5, mag: 26.0, n_iterations: 4}\n")
    cfg = load_config(_config_with(small_survey, tmp_path, cells_file="more.yaml"))
    assert [(c.z, c.mag, c.n_iterations) for c in cfg.grid.cells] == [(9.5, 26.0, 4)]


@pytest.mark.parametrize("cells, where", [
    ([{"z": -1.0, "mag": 25.0}], "grid.cells[0].z"),
    ([{"z": 9.0, "mag": 25.0, "n_iterations": 0}], "grid.cells[0].n_iterations"),
    ([{"z": 9.0, "mag": 25.0, "fields": ["nope"]}], "grid.cells[0].fields"),
    ([{"z": 9.0}], "grid.cells[0].mag"),
    ([{"z": 9.0, "mag": 25.0, "colour": 1}], "grid.cells[0]"),
])
def test_bad_cells_are_refused_by_location(small_survey, tmp_path, cells, where):
    with pytest.raises(ConfigError) as err:
        load_config(_config_with(small_survey, tmp_path, cells=cells))
    assert where in str(err.value)


def test_rows_of_listed_cells_are_current_and_others_are_not():
    manifest = {"fields": ["a", "b"], "z_values": [8.0], "mag_values": [25.0], "n_iterations": 2,
                "cells": [{"z": 9.1, "mag": 26.0, "n_iterations": 3, "fields": ["a"]}]}
    rows = pd.DataFrame({
        C.COL_FIELD: ["a", "a", "a", "b", "a", "a", "b"],
        C.COL_Z: [8.0, 8.0, 9.1, 9.1, 9.1, 9.1000001, 8.0],
        C.COL_MAG: [25.0, 25.0, 26.0, 26.0, 26.0, 26.0, 25.0],
        C.COL_ITERATION: [1, 2, 2, 0, 3, 0, 0]})
    expected = [True, False, True, False, False, False, True]
    assert current_rows_mask(rows, manifest).tolist() == expected


# ---------------------------------------------------------------------------
# next --write -> simulate --cells, by hand
# ---------------------------------------------------------------------------
def _cli(*args, cwd=None, timeout=600):
    """The command line in a fresh interpreter (`python -m glaciar`)."""
    return subprocess.run([sys.executable, "-m", "glaciar", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=timeout)


def _main(capsys, *args):
    """The command line in this process: (exit code, stderr)."""
    from glaciar.cli import main

    capsys.readouterr()
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def _rows(run_dir: Path) -> pd.DataFrame:
    files = sorted((run_dir / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    return pd.concat([pd.read_parquet(f).assign(_file=f.name) for f in files],
                     ignore_index=True)


@pytest.fixture(scope="module")
def adaptive_uninterrupted(small_survey, tmp_path_factory):
    out = tmp_path_factory.mktemp("adaptive_a") / "run"
    r = _cli("simulate", small_survey, "--out", out, *ADAPTIVE_ARGS)
    assert r.returncode == 0, r.stderr
    return out, r


def test_adaptive_loop_logs_rounds_and_stops_on_its_budget(adaptive_uninterrupted, small_survey):
    out, r = adaptive_uninterrupted
    rounds = json.loads((out / "adaptive_rounds.json").read_text())
    assert "stop" in rounds[-1] and "budget" in rounds[-1]["stop"]
    assert all("cells" in e and e["simulated"]["n_tasks_run"] > 0 for e in rounds[:-1])
    # Sources in the store = what the rounds say, and within the budget.
    rows = _rows(out)
    assert len(rows) == rounds[-1]["n_sources"] <= 192
    assert [e["n_sources"] for e in rounds] == sorted(e["n_sources"] for e in rounds)
    # The proposals are on the design's refined lattice (values and midpoints) and
    # below the detection band's z limit.
    cfg = load_config(small_survey)
    zs = np.unique(np.r_[cfg.grid.z_values, np.convolve(cfg.grid.z_values, [0.5, 0.5], "valid")])
    ms = np.unique(np.r_[cfg.grid.mag_values,
                         np.convolve(cfg.grid.mag_values, [0.5, 0.5], "valid")])
    for e in rounds[:-1]:
        for c in e["cells"]:
            assert np.isclose(zs, c["z"]).any() and np.isclose(ms, c["mag"]).any()
    # The run's stored config lists the rounds' cells: the store describes itself.
    stored = load_config(out / C.RUN_CONFIG_NAME)
    assert len(stored.grid.cells) == sum(len(e["cells"]) for e in rounds[:-1])
    assert len(plan_tasks(stored)) == rows["_file"].nunique()


def test_adaptive_run_killed_mid_round_resumes_to_the_same_table(adaptive_uninterrupted,
                                                                   small_survey, tmp_path):
    ref_dir, _ = adaptive_uninterrupted
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "glaciar", "simulate", str(small_survey), "--out", str(out),
           *ADAPTIVE_ARGS]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rounds_file, results = out / "adaptive_rounds.json", out / C.RESULTS_DIRNAME
    killed_with = None
    deadline = time.time() + 300
    try:
        while time.time() < deadline and proc.poll() is None:
            if rounds_file.exists():
                try:
                    rounds = json.loads(rounds_file.read_text())
                except ValueError:
                    rounds = []
                n_design = len(plan_tasks(load_config(small_survey)))
                n_files = len(list(results.glob("task_*.parquet")))
                # Round 0's proposal is logged and some, not all, of its tasks are written.
                if len(rounds) >= 1 and "simulated" not in rounds[-1] and n_files > n_design:
                    os.kill(proc.pid, signal.SIGKILL)
                    killed_with = (len(rounds), n_files)
                    break
            time.sleep(0.02)
    finally:
        if proc.poll() is None and killed_with is None:
            proc.kill()
        proc.wait()
    assert killed_with is not None, "the run finished before it could be killed mid-round"
    r = _cli("simulate", small_survey, "--out", out, *ADAPTIVE_ARGS)
    assert r.returncode == 0, r.stderr
    a, b = _rows(ref_dir), _rows(out)
    assert list(a["_file"].unique()) == list(b["_file"].unique())
    pd.testing.assert_frame_equal(a.reset_index(drop=True), b.reset_index(drop=True))
    ra = json.loads((ref_dir / "adaptive_rounds.json").read_text())
    rb = json.loads(rounds_file.read_text())
    assert [e.get("cells") for e in ra] == [e.get("cells") for e in rb]
    assert [e["max_sd"] for e in ra] == [e["max_sd"] for e in rb]


def test_next_writes_cells_that_simulate_reads(adaptive_uninterrupted, small_survey, tmp_path,
                                               capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(adaptive_uninterrupted[0], run, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    cells_path = tmp_path / "cells.yaml"
    code, err = _main(capsys, "next", run, "-n", "3", "--iterations", "2", "--write", cells_path)
    assert code == 0, err
    cells = yaml.safe_load(cells_path.read_text())["cells"]
    assert len(cells) == 3
    before = task_cells(load_config(run / C.RUN_CONFIG_NAME))
    for c in cells:
        have = max(before.get((f, c["z"], c["mag"]), 0) for f in load_config(small_survey)
                   .survey.fields)
        assert c["n_iterations"] == have + 2
    n_before = len(list((run / C.RESULTS_DIRNAME).glob("task_*.parquet")))
    # The run's own stored config is accepted, with the cells file on top.
    code, err = _main(capsys, "simulate", run / C.RUN_CONFIG_NAME, "--out", run, "--cells",
                      cells_path, "--workers", "1", "--quiet")
    assert code == 0, err
    n_after = len(list((run / C.RESULTS_DIRNAME).glob("task_*.parquet")))
    n_fields = len(load_config(small_survey).survey.fields)
    assert n_after - n_before == 2 * 3 * n_fields
    # `next` keeps working on the grown run (the manifest still has its grid).
    code, err = _main(capsys, "next", run, "-n", "2")
    assert code == 0, err


@pytest.mark.parametrize("args, word", [
    (["--budget", "0"], "--budget"), (["--budget", "nan"], "--budget"),
    (["--budget", "-5"], "--budget"), (["--target-sd", "inf"], "--target-sd"),
    (["--target-sd", "0"], "--target-sd"), (["--round-size", "2.5"], "--round-size"),
])
def test_bad_adaptive_arguments_are_refused_before_anything_is_written(small_survey, tmp_path,
                                                                       args, word, capsys):
    out = tmp_path / "run"
    code, err = _main(capsys, "simulate", small_survey, "--out", out, "--adaptive", *args)
    assert code == 2
    assert word in err and len(err.strip().splitlines()) <= 2
    assert not out.exists()


@pytest.mark.parametrize("n", ["0", "-1", "x", "1.5"])
def test_bad_next_counts_are_refused(tmp_path, n, capsys):
    code, err = _main(capsys, "next", tmp_path, "-n", n, "--write", tmp_path / "c.yaml")
    assert code == 2 and "-n" in err
    assert not (tmp_path / "c.yaml").exists()


# ------------------------------------------------------------------------------
# ``simulate --adaptive --budget N`` keeps N (issue 21, bullet 5).
#
# A design that costs more than the budget starts from a coarse subset of it
# (:func:`glaciar.pipeline.adaptive.coarse_design`); a design within the budget
# runs exactly as before.  Costs: the rule tests are arithmetic on configs
# (< 1 s); the loop runs the small demo field (12 sources a task) for three
# short fits in this process (~10 s on a shared 2-core machine).
# ------------------------------------------------------------------------------
def _grid_config(small_survey, tmp_path, z, mag) -> str:
    d = yaml.safe_load(small_survey.read_text())
    d["grid"]["z"], d["grid"]["mag"] = {"values": list(z)}, {"values": list(mag)}
    d["survey"]["image_dir"] = str(small_survey.parent / d["survey"]["image_dir"])
    for b in d["survey"]["bands"].values():
        b["psf"] = str(small_survey.parent / b["psf"])
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(d, sort_keys=False))
    return p


def test_coarse_rule_on_the_issue_s_12600_source_design():
    # 7 z x 18 mag x 1 iteration x 100 sources = 12 600, budget 4000 (half: 2000).
    # By hand: stride 3 keeps z 0,3,6 and mag 0,3,6,9,12,15,17 -> 21 cells, 2100 > 2000;
    # stride 4 keeps z 0,4,6 and mag 0,4,8,12,16,17 -> 18 cells, 1800 <= 2000.
    assert coarse_axis(7, 4) == [0, 4, 6] and coarse_axis(18, 4) == [0, 4, 8, 12, 16, 17]
    assert coarse_plan(7, 18, 1, 100, 4000) == (4, 1, 1800)
    # Corners too dear at 5 iterations (4 cells x 5 x 100 = 2000 > 1000): fewer iterations.
    assert coarse_plan(7, 18, 5, 100, 2000) == (17, 2, 800)


def test_coarse_design_keeps_the_extremes_and_a_budget_above_the_design_changes_nothing(
        small_survey, tmp_path):
    cfg = load_config(_grid_config(small_survey, tmp_path, (8.0, 9.0, 10.4),
                                   (24.0, 25.0, 26.0, 27.5)))
    n_fields = len(cfg.survey.fields)
    assert design_sources(cfg) == 3 * 4 * 2 * 12 * n_fields
    start, note = coarse_design(cfg, 150)
    assert start.grid.z_values == (8.0, 10.4) and start.grid.mag_values == (24.0, 27.5)
    assert start.simulation.n_iterations == 1 and design_sources(start) == 48 * n_fields
    assert "coarse start" in note
    # At or above the design's cost the loop starts from the configuration itself.
    same, note = coarse_design(cfg, design_sources(cfg))
    assert same is cfg and note is None


def test_adaptive_run_spends_its_budget_not_the_design(small_survey, tmp_path, capsys,
                                                       monkeypatch):
    import glaciar.pipeline.fit as pipeline_fit
    from glaciar.cli import main

    # The loop's last fit is written in full (~15 s here, its PPC and V_eff); what is
    # tested is what the loop simulates, so every fit is kept in memory.
    fit = pipeline_fit.run_fit
    monkeypatch.setattr(pipeline_fit, "run_fit", lambda *a, **k: fit(*a, **{**k, "write": False}))

    cfg_path = _grid_config(small_survey, tmp_path, (8.0, 9.0, 10.4), (24.0, 25.0, 26.0, 27.5))
    cfg = load_config(cfg_path)
    per_task = cfg.simulation.n_galaxies * len(cfg.survey.fields)
    budget = 100                      # the design costs 288 sources
    out = tmp_path / "run"
    code = main([str(a) for a in ("simulate", cfg_path, "--out", out, "--adaptive", "--budget",
                                  budget, "--round-size", 100, "--max-steps", 30,
                                  "--workers", 1, "--quiet")])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "coarse start" in captured.out
    files = sorted((out / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    n_simulated = sum(len(pd.read_parquet(f)) for f in files)
    # Before the change the design's 288 sources ran first, whatever the budget.
    assert n_simulated <= budget + per_task // 2, (n_simulated, budget)
    assert n_simulated < design_sources(cfg)
    rounds = json.loads((out / C.ADAPTIVE_ROUNDS_NAME).read_text())
    assert rounds[-1]["n_sources"] == n_simulated and "budget" in rounds[-1]["stop"]
    # The rounds fill in the full design's lattice, not only the coarse start's.
    stored = load_config(out / C.RUN_CONFIG_NAME)
    assert stored.grid.z_values == (8.0, 10.4)
    proposed_z = {c.z for c in stored.grid.cells}
    assert proposed_z - {8.0, 10.4}, proposed_z


def test_budget_below_one_iteration_of_the_corners_is_refused(small_survey, tmp_path, capsys):
    from glaciar.cli import main

    cfg_path = _grid_config(small_survey, tmp_path, (8.0, 9.0, 10.4), (24.0, 25.0, 26.0, 27.5))
    out = tmp_path / "run"
    code = main([str(a) for a in ("simulate", cfg_path, "--out", out, "--adaptive", "--budget",
                                  40, "--quiet")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--budget 40" in err and "48" in err, err
    assert not out.exists()


@pytest.mark.parametrize("n, k", [(1, 5), (2, 1), (5, 2), (5, 10)])
def test_coarse_axis_keeps_first_and_last(n, k):
    idx = coarse_axis(n, k)
    assert idx[0] == 0 and idx[-1] == n - 1 and idx == sorted(set(idx))
