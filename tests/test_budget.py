"""``simulate --adaptive --budget N`` keeps N (issue 21, bullet 5).

A design that costs more than the budget starts from a coarse subset of it
(:func:`glaciar.pipeline.adaptive.coarse_design`); a design within the budget
runs exactly as before.  Costs: the rule tests are arithmetic on configs
(< 1 s); the loop runs the small demo field (12 sources a task) for three
short fits in this process (~10 s on a shared 2-core machine).
"""
from __future__ import annotations

import json

import pandas as pd
import pytest
import yaml

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.inference.adaptive import coarse_axis, coarse_plan
from glaciar.pipeline.adaptive import coarse_design, design_sources


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
