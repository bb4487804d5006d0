"""Interlopers end to end on the small demo survey: injected beside the target population,
their rows, the passing fraction ``glaciar fit`` writes, the target's rows untouched."""
import numpy as np
import pandas as pd
import pytest

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.execute import simulate
from glaciar.pipeline.contamination import add_contamination, interloper_rows, run_contamination
from glaciar.plan import finished_specs, plan_tasks
from glaciar.shards import shard_tasks
from glaciar.store import read_results
from tiny_runs import load_dict, tiny_config

#: Balmer-break galaxies at z = 2.4-3 put their break between F125W and F160W: some pass
#: the BoRG J-dropout selection (the demo's default).
SECTION = {"z_range": [2.4, 3.0], "z_step": 0.6, "mag_range": [24.0, 27.0], "mag_step": 1.0,
           "n_per_task": 12, "dusty": {"weight": 0.3},
           "balmer": {"weight": 0.7, "d4000": [2.0, 2.6], "beta_blue": 3.0}}


@pytest.fixture(scope="module")
def run(small_survey_dict, tmp_path_factory):
    """one_task_run's configuration plus interlopers, run once: (config, run dir)."""
    d = tiny_config(small_survey_dict)
    d["interlopers"] = SECTION
    tmp = tmp_path_factory.mktemp("interlopers")
    cfg = load_dict(d, tmp / "c.yaml")
    simulate(cfg, tmp / "run", workers=1, progress=False)
    return cfg, tmp / "run"


def test_target_rows_are_bit_identical_with_interlopers(run, one_task_run):
    _, run_dir = run
    _, plain = one_task_run
    got, want = read_results(run_dir), read_results(plain)
    assert list(got.columns) == list(want.columns)       # no population column added
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    assert not (plain / "interlopers").exists()


def test_interloper_rows_are_the_configured_population(run):
    cfg, run_dir = run
    rows = interloper_rows(run_dir, cfg)
    assert len(rows) == 2 * 3 * 12
    assert set(rows["population"]) == {"interloper"}
    assert set(rows[C.COL_Z]) == {2.4, 3.0}
    cell = rows[C.COL_MAG].to_numpy()
    assert np.all(np.abs(rows[C.COL_MAG_INPUT] - cell) <= 0.5)
    assert set(rows["interloper_family"]) == {"dusty", "balmer"}
    # the same engine: recovered, classified and selected like the target population
    assert rows[C.COL_RECOVERED].any() and rows[C.COL_SELECTED].any()
    assert not (rows[C.COL_SELECTED] & ~rows[C.COL_RECOVERED]).any()


def test_fitted_contamination_matches_the_binned_fraction(run):
    cfg, run_dir = run
    c = run_contamination(run_dir, cfg, "f160w")
    rows = interloper_rows(run_dir, cfg)
    # Binned here from the rows: weights = default counts (log10 dN/dm = 1.75 + 0.2 (m - 26))
    # x cell width / sources injected in the cell.
    m_in = rows[C.COL_MAG_INPUT].to_numpy()
    cell = rows[C.COL_MAG].to_numpy()
    n_cell = pd.Series(cell).map(pd.Series(cell).value_counts()).to_numpy()
    w = 10 ** (1.75 + 0.2 * (m_in - 26.0)) * 1.0 / n_cell
    m_obs = rows["mag_auto_f160w"].to_numpy()
    sel = rows[C.COL_SELECTED].to_numpy() & np.isfinite(m_obs)
    edges = [24.0, 25.0, 26.0, 27.0]
    np.testing.assert_array_equal(c.m_edges, edges)
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        binned = (w[sel & (m_obs >= lo) & (m_obs < hi)].sum()
                  / w[(m_in >= lo) & (m_in < hi)].sum())
        assert c.lower[k] <= binned <= c.upper[k], (k, binned, c.lower[k], c.upper[k])
        assert c.estimate[k] == pytest.approx(binned, rel=1e-12)
    assert c.estimate.max() > 0
    assert set(c.family_estimate) == {"dusty", "balmer"}
    np.testing.assert_allclose(sum(c.family_estimate.values()), c.estimate, rtol=1e-12)


def test_fit_attaches_the_contamination_and_resume_runs_nothing(run):
    cfg, run_dir = run
    from analytic_sf import lf_sf
    sf = lf_sf(n_draws=1)
    add_contamination(run_dir, {"detection_band": "f160w"}, [sf])
    np.testing.assert_array_equal(sf.interlopers.estimate,
                                  run_contamination(run_dir, cfg, "f160w").estimate)
    # a resumed run finds every task of both populations done, each in its own store
    plan = plan_tasks(load_config(run_dir / C.RUN_CONFIG_NAME))
    assert finished_specs(run_dir, plan) == set(plan)


def test_shards_partition_both_populations(run):
    cfg, _ = run
    plan = plan_tasks(cfg)
    assert sum(bool(s.population) for s in plan) == 6
    for n in (2, 3, 5):
        parts = [shard_tasks(plan, k, n) for k in range(1, n + 1)]
        assert sorted(map(repr, sum(parts, []))) == sorted(map(repr, plan))
