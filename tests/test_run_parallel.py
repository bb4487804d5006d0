"""Parallel start and scheduling of :func:`glaciar.execute.simulate` (issue 11, points 5 and 6).

* Guided chunks: every pending task once, in plan order, a chunk within one
  (field, z), chunk sizes shrinking to single tasks at the end of the run.
* A start with 2 workers is a start with 1 (the forked set-up helper of issue 11
  is gone since issue 22): the same manifest, a bad input refused with the same
  one-line error and nothing written, the preflight's warnings passed on, no
  process left behind.
* With an executor, the workers' CPU during their chunks is counted in
  ``process_cpu_seconds`` (``remote_cpu_seconds``).

Tiny runs on ``small_survey`` (320^2, <= 2 tasks each); ~10 s on 2 cores.
"""
import concurrent.futures as cf
import math
import multiprocessing
import shutil
import warnings

import pytest
import yaml

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.engine.task import TaskSpec
from glaciar.execute import _chunks, simulate
from glaciar.inputs import InputError
from glaciar.plan import plan_tasks
from glaciar.rundir import read_manifest

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
