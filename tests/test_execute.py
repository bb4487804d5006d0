"""End-to-end behaviour of the run loop: determinism, resume, refusal, invariants."""
import concurrent.futures as cf
import math
import multiprocessing
import shutil
import warnings

import numpy as np
import pandas as pd
import pytest
import yaml

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.engine.task import TaskSpec
from glaciar.execute import _chunks, simulate
from glaciar.inputs import InputError
from glaciar.plan import plan_tasks
from glaciar.store import read_results
from glaciar.rundir import StoreMismatchError, read_manifest


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


# ------------------------------------------------------------------------------
# Parallel start and scheduling of :func:`glaciar.execute.simulate` (issue 11, points 5 and 6).
#
# * Guided chunks: every pending task once, in plan order, a chunk within one
#   (field, z), chunk sizes shrinking to single tasks at the end of the run.
# * A start with 2 workers is a start with 1 (the forked set-up helper of issue 11
#   is gone since issue 22): the same manifest, a bad input refused with the same
#   one-line error and nothing written, the preflight's warnings passed on, no
#   process left behind.
# * With an executor, the workers' CPU during their chunks is counted in
#   ``process_cpu_seconds`` (``remote_cpu_seconds``).
#
# Tiny runs on ``small_survey`` (320^2, <= 2 tasks each); ~10 s on 2 cores.
# ------------------------------------------------------------------------------
fork_only = pytest.mark.skipif(multiprocessing.get_start_method(allow_none=True) not in (None, "fork")
                               or multiprocessing.get_all_start_methods()[0] != "fork",
                               reason="the set-up helper is forked")


def _specs(counts):
    """Task specs in plan order: ``counts[(field_index, z_index)]`` iterations each."""
    out = []
    for (f, z), n in counts.items():
        for it in range(n):
            out.append(TaskSpec(field=f"f{f}", field_index=f, z_index=z, mag_index=0,
                                iteration=it, z=8.0 + z, mag=26.0))
    return out


@pytest.mark.parametrize("n_workers", [1, 2, 5])
def test_chunks_cover_the_plan_in_order_and_shrink(n_workers):
    counts = {(0, 0): 37, (0, 1): 5, (0, 2): 1, (1, 0): 60, (1, 1): 17}
    specs = _specs(counts)
    chunks = _chunks(specs, n_workers)
    assert [s for ch in chunks for s in ch] == specs              # each task once, plan order
    for ch in chunks:
        assert len({(s.field_index, s.z_index) for s in ch}) == 1  # one (field, z) per chunk
    sizes = [len(ch) for ch in chunks]
    # The first chunk holds at most 1 / (4 n) of the run, the last one is a single task, and
    # sizes never grow within a (field, z) group: the workers share the tail task by task.
    assert sizes[0] <= math.ceil(len(specs) / (4 * n_workers))
    assert sizes[-1] == 1
    start = 0
    for n in counts.values():
        group, total = [], 0
        while total < n:
            group.append(sizes[start + len(group)])
            total += group[-1]
        assert total == n and group == sorted(group, reverse=True)
        start += len(group)
    assert len(chunks) >= 4 * n_workers
    assert _chunks([], n_workers) == []


@pytest.fixture(scope="module")
def survey_copy(small_survey, tmp_path_factory):
    """A private copy of ``small_survey`` (its images may be damaged here)."""
    dst = tmp_path_factory.mktemp("survey_copy") / "survey"
    shutil.copytree(small_survey.parent, dst)
    return dst / small_survey.name


def _with(config_path, tmp_path, **simulation):
    data = yaml.safe_load(config_path.read_text())
    data["simulation"].update(simulation)
    p = config_path.parent / f"{tmp_path.name}.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return load_config(p)


def test_parallel_start_writes_the_serial_manifest(survey_copy, tmp_path):
    cfg = load_config(survey_copy)
    simulate(cfg, tmp_path / "serial", workers=1, progress=False, max_tasks=0)
    stats = simulate(cfg, tmp_path / "two", workers=2, progress=False, max_tasks=0)
    assert read_manifest(tmp_path / "two") == read_manifest(tmp_path / "serial")
    # The same fingerprint cache and stored config, whatever the worker count.
    for name in (C.FINGERPRINT_CACHE_NAME, C.RUN_CONFIG_NAME):
        assert (tmp_path / "two" / name).read_bytes() == (tmp_path / "serial" / name).read_bytes()
    assert stats["n_run"] == 0 and stats["setup_seconds"] <= stats["wall_seconds"]
    assert multiprocessing.active_children() == []                # the helper was reaped


def test_parallel_start_refuses_a_bad_image_before_writing(survey_copy, tmp_path):
    cfg = load_config(survey_copy)
    image = survey_copy.parent / cfg.survey.image_dir / cfg.survey.science.format(
        field=cfg.survey.fields[0], band=cfg.survey.bands[1].name)
    good = image.read_bytes()
    try:
        image.write_bytes(b"SIMPLE  =                    T" + b" " * 50 + b"garbage" * 600)
        errors = []
        for workers in (1, 2):
            with pytest.raises(InputError) as exc:
                simulate(cfg, tmp_path / f"run{workers}", workers=workers, progress=False)
            assert not (tmp_path / f"run{workers}").exists()   # nothing created
            errors.append(str(exc.value))
    finally:
        image.write_bytes(good)
    assert errors[0] == errors[1]
    assert errors[0].startswith(f"survey.science (field {cfg.survey.fields[0]!r}, band "
                                f"{cfg.survey.bands[1].name!r}): {image}")
    assert "\n" not in errors[0]
    assert multiprocessing.active_children() == []


def test_parallel_start_passes_on_the_preflight_warning(survey_copy, tmp_path):
    cfg = _with(survey_copy, tmp_path, n_galaxies=5000)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        simulate(cfg, tmp_path / "run", workers=2, progress=False, max_tasks=0)
    fit = [w for w in caught if "sources fit per task" in str(w.message)]
    assert len(fit) == 1 and fit[0].category is UserWarning
    assert "of simulation.n_galaxies = 5000" in str(fit[0].message)


def test_executor_workers_cpu_is_counted(survey_copy, tmp_path):
    cfg = load_config(survey_copy)
    # An executor the caller owns: its workers are not reaped during the call, so their CPU
    # must come back with the chunks (field set-up and tasks).
    with cf.ProcessPoolExecutor(max_workers=1) as ex:
        stats = simulate(cfg, tmp_path / "run", executor=ex, progress=False, max_tasks=2)
    assert stats["n_run"] == 2
    # The chunk's worker CPU holds the tasks' timers and the field set-up around them.
    assert stats["remote_cpu_seconds"] >= 0.95 * stats["cpu_seconds"] > 0
    assert stats["process_cpu_seconds"] >= stats["remote_cpu_seconds"]
    # The pool's own workers are reaped by simulate: nothing is counted twice.
    own = simulate(cfg, tmp_path / "own", workers=2, progress=False, max_tasks=2)
    assert own["remote_cpu_seconds"] == 0.0
    assert own["process_cpu_seconds"] >= 0.95 * own["cpu_seconds"] > 0


@fork_only
def test_a_callers_process_pool_measures_the_field_once(survey_copy, tmp_path, monkeypatch):
    """A caller's process pool measures the field in one of its workers (issue 24), once: the
    other worker maps its cache."""
    import os

    from glaciar import contexts

    cfg = load_config(survey_copy)
    contexts.clear_contexts()
    log = tmp_path / "builds.txt"
    real = contexts.build_field_context

    def counting(*args, **kwargs):
        with open(log, "a") as fh:
            fh.write(f"{os.getpid()}\n")
        return real(*args, **kwargs)

    monkeypatch.setattr(contexts, "build_field_context", counting)
    with cf.ProcessPoolExecutor(max_workers=2) as ex:
        stats = simulate(cfg, tmp_path / "run", executor=ex, progress=False, max_tasks=2)
    assert stats["n_run"] == 2
    builds = log.read_text().split()
    assert len(builds) == 1 and builds[0] != str(os.getpid())


def test_prewarm_fills_the_colour_tables_a_task_reads(survey_copy):
    """A spawned worker's warm-up job (glaciar.manifest._prewarm) computes the SED tables of every
    redshift of the plan: the tasks' own draws then add no table (no cache miss)."""
    import types

    import numpy as np

    from glaciar import fieldprep, manifest
    from glaciar.config import config_to_dict
    from glaciar.engine.context import FieldContext
    from glaciar.engine.task import draw_task_sources
    from glaciar.galaxy import sed
    from glaciar.survey import Survey

    cfg = load_config(survey_copy)
    sed._band_table.cache_clear()
    manifest._prewarm(config_to_dict(cfg), str(cfg.base_dir))
    warmed = sed._band_table.cache_info()
    assert warmed.currsize >= len(cfg.grid.z_values) * len(cfg.survey.bands)
    settings, _ = fieldprep.field_settings(cfg, Survey.from_config(cfg), cfg.survey.fields[0])
    # the settings the draws read, no pixel
    ctx = types.SimpleNamespace(**settings, quantise_r_eff=FieldContext.quantise_r_eff)
    for spec in plan_tasks(cfg):
        draw_task_sources(np.random.default_rng(0), 5, spec.z, spec.mag, ctx)
    assert sed._band_table.cache_info().misses == warmed.misses
