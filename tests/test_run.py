"""End-to-end behaviour of the run loop: determinism, resume, refusal, invariants."""
import numpy as np
import pandas as pd
import pytest

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.execute import simulate
from glaciar.plan import plan_tasks
from glaciar.store import read_results
from glaciar.rundir import StoreMismatchError


def _sorted(df):
    keys = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]
    return df.sort_values(keys).reset_index(drop=True)


@pytest.fixture(scope="module")
def serial_run(small_run):
    """``small_survey`` simulated serially (the session's shared ``small_run``)."""
    cfg, out = small_run
    return cfg, out, _sorted(read_results(out))


def test_every_task_written_once(serial_run):
    cfg, out, rows = serial_run
    n_tasks = len(plan_tasks(cfg))
    assert len(list((out / C.RESULTS_DIRNAME).glob("task_*.parquet"))) == n_tasks
    assert not list((out / C.RESULTS_DIRNAME).glob(".*tmp"))
    per_task = rows.groupby([C.COL_Z, C.COL_MAG, C.COL_ITERATION]).size()
    assert (per_task == cfg.simulation.n_galaxies).all()


def test_per_source_invariants(serial_run):
    cfg, _, rows = serial_run
    det = cfg.survey.detection_band
    assert set(rows[C.COL_STATUS]).issubset(C.STATUS_CODES)
    np.testing.assert_array_equal(rows[C.COL_RECOVERED], rows[C.COL_STATUS].isin(C.RECOVERED_STATUSES))
    assert not (rows[C.COL_SELECTED] & ~rows[C.COL_RECOVERED]).any()
    # Apparent-magnitude grid: the detection-band input magnitude is the nominal one.
    np.testing.assert_allclose(rows[C.COL_MAG_INPUT], rows[C.COL_MAG], atol=1e-4)
    np.testing.assert_allclose(rows[C.band_column("mag_in", det)], rows[C.COL_MAG_INPUT])
    # The stamp holds at most all of the light, and at least the configured fraction.
    d = rows[C.band_column("mag_in_stamp", det)] - rows[C.band_column("mag_in", det)]
    assert (d >= -1e-9).all() and (d <= -2.5 * np.log10(0.995) + 1e-6).all()
    # Bright sources at z = 8 are almost all recovered; at 27.5 far fewer.
    bright = rows[(rows.mag == 24.0)]
    faint = rows[(rows.mag == 27.5)]
    assert bright[C.COL_RECOVERED].mean() > 0.8
    assert faint[C.COL_RECOVERED].mean() < bright[C.COL_RECOVERED].mean()
    # Sources at z = 10.4 have no flux in F098M/F606W (blueward of the break).
    hi = rows[rows.z == 10.4]
    assert np.isinf(hi[C.band_column("mag_in", "f606w")]).all()
    assert (hi[C.band_column("flux_in", "f606w")] == 0).all()


def test_same_table_with_two_workers(serial_run, tmp_path):
    cfg, _, rows = serial_run
    import resource

    def own_cpu():
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    c0 = own_cpu()
    stats = simulate(cfg, tmp_path, workers=2, progress=False)
    parent = own_cpu() - c0
    pd.testing.assert_frame_equal(_sorted(read_results(tmp_path)), rows)
    # Whole-process CPU is this process's plus the workers' (their tasks and set-up): at
    # least the parent's own share plus what the tasks' timers measured in the workers.
    assert stats["cpu_seconds"] > 0
    assert stats["process_cpu_seconds"] >= parent + 0.95 * stats["cpu_seconds"]


def test_resume_skips_finished_and_matches(serial_run, tmp_path):
    cfg, _, rows = serial_run
    first = simulate(cfg, tmp_path, workers=1, progress=False, max_tasks=3)
    assert first["n_run"] == 3
    files = sorted((tmp_path / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    before = {p.name: p.read_bytes() for p in files}
    second = simulate(cfg, tmp_path, workers=1, progress=False)
    assert second["n_done_before"] == 3 and second["n_run"] == len(plan_tasks(cfg)) - 3
    for name, data in before.items():
        assert (tmp_path / C.RESULTS_DIRNAME / name).read_bytes() == data
    pd.testing.assert_frame_equal(_sorted(read_results(tmp_path)), rows)


def test_refuses_store_of_other_seed(serial_run):
    cfg, out, _ = serial_run
    with pytest.raises(StoreMismatchError, match="different configuration or seed"):
        simulate(cfg, out, workers=1, seed=cfg.simulation.seed + 1, progress=False)


def test_windowed_equals_full_frame(serial_run, tmp_path):
    cfg, _, rows = serial_run
    simulate(cfg, tmp_path, workers=1, progress=False, mode="full", max_tasks=4)
    full = _sorted(read_results(tmp_path))
    win = rows.merge(full[[C.COL_Z, C.COL_MAG, C.COL_ITERATION]].drop_duplicates())
    win = _sorted(win)
    np.testing.assert_array_equal(win[C.COL_STATUS], full[C.COL_STATUS])
    det = cfg.survey.detection_band
    np.testing.assert_allclose(win[C.band_column("flux_iso", det)], full[C.band_column("flux_iso", det)],
                               rtol=1e-9, equal_nan=True)


def test_any_executor_gives_the_same_table(serial_run, tmp_path):
    """The run loop takes any concurrent.futures.Executor (a Dask client's included).

    Spawned workers start from a fresh interpreter, as on a cluster.
    """
    import concurrent.futures as cf
    import multiprocessing

    cfg, _, rows = serial_run
    with cf.ProcessPoolExecutor(max_workers=2, mp_context=multiprocessing.get_context("spawn")) as ex:
        simulate(cfg, tmp_path, executor=ex, progress=False)
    pd.testing.assert_frame_equal(_sorted(read_results(tmp_path)), rows)


def test_kill_loses_only_tasks_in_flight(serial_run, small_survey, tmp_path):
    """SIGKILL mid-run: what is written stays readable, and a resume completes the same table."""
    import os
    import signal
    import subprocess
    import sys
    import time

    cfg, _, rows = serial_run
    code = ("from glaciar.config import load_config; from glaciar.execute import simulate; "
            f"simulate(load_config({str(small_survey)!r}), {str(tmp_path)!r}, workers=1, progress=False)")
    proc = subprocess.Popen([sys.executable, "-c", code])
    results = tmp_path / C.RESULTS_DIRNAME
    deadline = time.time() + 120
    while time.time() < deadline and len(list(results.glob("task_*.parquet"))) < 2:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    written = sorted(results.glob("task_*.parquet"))
    assert 2 <= len(written) < len(plan_tasks(cfg))
    for p in written:                        # every file on disk is complete
        assert len(pd.read_parquet(p)) == cfg.simulation.n_galaxies
    simulate(cfg, tmp_path, workers=1, progress=False)
    assert not list(results.glob(".*.tmp"))
    pd.testing.assert_frame_equal(_sorted(read_results(tmp_path)), rows)


def _variant(cfg, **changes):
    """The config with some sections changed (dotted keys), through its own dict form."""
    from glaciar.config import config_from_dict, config_to_dict

    d = config_to_dict(cfg)
    for dotted, value in changes.items():
        node = d
        *path, last = dotted.split(".")
        for k in path:
            node = node[k]
        node[last] = value
    return config_from_dict(d, cfg.base_dir)


def test_extending_grid_and_iterations_keeps_finished_rows(serial_run, tmp_path):
    """More z values, magnitudes and iterations: only the new tasks run, old rows stay."""
    import shutil

    cfg, out, rows = serial_run
    shutil.copytree(out, tmp_path / "ext")
    zs = sorted(set(cfg.grid.z_values) | {9.2})
    bigger = _variant(cfg, **{"grid.z": {"values": zs},
                              "simulation.n_iterations": cfg.simulation.n_iterations + 1})
    stats = simulate(bigger, tmp_path / "ext", workers=1, progress=False)
    assert stats["n_done_before"] == len(plan_tasks(cfg))
    assert stats["n_run"] == len(plan_tasks(bigger)) - len(plan_tasks(cfg))
    ext = _sorted(read_results(tmp_path / "ext"))
    keys = [C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]
    old = ext.merge(rows[keys], on=keys)
    pd.testing.assert_frame_equal(_sorted(old), rows)
    # ... and the extended store equals a fresh run of the extended config.
    simulate(bigger, tmp_path / "fresh", workers=1, progress=False)
    pd.testing.assert_frame_equal(_sorted(read_results(tmp_path / "fresh")), ext)


def test_refuses_store_of_other_science_settings(serial_run):
    cfg, out, _ = serial_run
    other = _variant(cfg, **{"detection.DETECT_THRESH": 1.5})
    with pytest.raises(StoreMismatchError, match="only fields, grid values and n_iterations"):
        simulate(other, out, workers=1, progress=False)


def test_preflight_says_how_many_sources_fit(small_survey, tmp_path):
    """n_galaxies beyond what the footprint holds: a warning with the number, before any task."""
    import warnings

    import yaml

    from glaciar.plan import placement_preflight
    from glaciar.survey import Survey

    data = yaml.safe_load(small_survey.read_text())
    data["simulation"]["n_galaxies"] = 5000
    p = small_survey.parent / "crowded.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    cfg = load_config(p)
    messages = placement_preflight(cfg, Survey.from_config(cfg))
    assert len(messages) == 1 and "of simulation.n_galaxies = 5000" in messages[0]
    fits = int(messages[0].split("about ")[1].split()[0])
    assert 0 < fits < 5000
    assert placement_preflight(load_config(small_survey), Survey.from_config(load_config(small_survey))) == []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        simulate(cfg, tmp_path / "run", workers=1, progress=False, max_tasks=1)
    assert any("sources fit per task" in str(w.message) for w in caught)
    rows = pd.read_parquet(next((tmp_path / "run" / "results").rglob("*.parquet")))
    # A task places about what the pre-flight estimated (its own draw of sizes and positions).
    assert 0.5 * fits <= len(rows) <= 1.5 * fits


def test_detection_band_flux_limit_and_edges(small_survey):
    """The z where F160W stops receiving flux: Lyman-alpha at the filter's red end."""
    from glaciar.galaxy.filters import get_filter
    from glaciar.pipeline.fit import _physical_edges
    from glaciar.plan import detection_z_limit

    cfg = load_config(small_survey)
    z_lim = detection_z_limit(cfg)
    f = get_filter("wfc3_ir_f160w")
    wave, thr = np.asarray(f.wave_angstrom), np.asarray(f.throughput)
    red_end = wave[thr > 1e-3 * thr.max()].max()
    # IGM absorbs blueward of Lyman-alpha: the band loses its flux as Ly-a crosses its red end
    assert abs(z_lim - (red_end / 1215.67 - 1.0)) < 0.08, (z_lim, red_end)
    high = {"end": "high", "z": 12.6, "ratio": 1.0, "mag": 26.0, "extend_dz": 1.8}
    low = {"end": "low", "z": 7.8, "ratio": 0.5, "mag": 26.0, "extend_dz": 0.5}
    assert _physical_edges([high, low], None) == [high, low]
    out = _physical_edges([high, low], 12.99)
    assert out[1] == low and out[0]["z_limit"] == 12.99 and out[0]["extend_dz"] == pytest.approx(0.34)
    assert _physical_edges([{**high, "z": 12.9}], 12.99) == []        # within 0.1: nothing lost
