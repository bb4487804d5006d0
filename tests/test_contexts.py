"""Field set-up done once and memory not doubled (issue 11, points 4-5).

* A run measures each field once per process: the manifest's depth and noise
  records and the serial run's tasks share one field context (one reference
  extraction, one empty-sky distance transform for bands with the same usable
  pixels); workers forked after the manifest inherit it instead of measuring
  the field again.
* The field context releases the survey's cached science and noise images (it
  holds background-subtracted copies); a later read gives the file's values.

The timing and memory figures themselves are in ``benchmarks/scaling.py``.
"""
from __future__ import annotations

import multiprocessing
import os
import re

import numpy as np
import pandas as pd
import pytest

import glaciar.survey as survey_module
from glaciar.config import load_config
from glaciar import constants as C, contexts, fieldprep
from glaciar.contexts import clear_contexts
from glaciar.execute import simulate
from glaciar.fieldprep import build_field_context
from glaciar.survey import Survey

from tiny_runs import cli, run_rows, task_files


def _count(monkeypatch, module, name, log=None):
    calls = []
    real = getattr(module, name)

    def counting(*args, **kwargs):
        calls.append(os.getpid())
        if log is not None:
            with open(log, "a") as fh:
                fh.write(f"{os.getpid()}\n")
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, counting)
    return calls


def test_serial_run_measures_the_field_once(small_survey, tmp_path, monkeypatch):
    cfg = load_config(small_survey)
    clear_contexts()
    builds = _count(monkeypatch, contexts, "build_field_context")
    refs = _count(monkeypatch, fieldprep, "reference_extraction")
    dists = _count(monkeypatch, fieldprep, "empty_sky")
    stats = simulate(cfg, tmp_path / "run", workers=1, progress=False)
    assert stats["n_run"] == 8
    assert len(builds) == 1 and len(refs) == 1
    # The demo's bands share one footprint, so one usable-sky mask and one transform.
    assert len(dists) == 1


@pytest.mark.skipif(multiprocessing.get_start_method() != "fork",
                    reason="the patched counter reaches the workers only when they fork")
def test_pool_workers_measure_the_field_once(small_survey, tmp_path, monkeypatch):
    """With a pool the field is measured by one worker (issue 24: set-up in the workers),
    never by this process, and the other worker maps that worker's cache."""
    cfg = load_config(small_survey)
    clear_contexts()
    log = tmp_path / "builds.txt"
    _count(monkeypatch, contexts, "build_field_context", log)
    stats = simulate(cfg, tmp_path / "run", workers=2, progress=False)
    assert stats["n_run"] == 8
    builds = log.read_text().split()
    assert len(builds) == 1 and builds[0] != str(os.getpid())


def test_context_releases_the_survey_images(small_survey):
    from astropy.io import fits

    cfg = load_config(small_survey)
    survey_module.clear_cache()
    sv = Survey.from_config(cfg)
    field = cfg.survey.fields[0]
    ctx = build_field_context(cfg, sv, field)
    kinds = [k[0] for k in survey_module._CACHE]
    assert "science" not in kinds and "rms" not in kinds
    assert "footprint" in kinds                       # masks stay: the context shares them
    assert ctx.footprint is sv.footprint(field)
    # A later read goes back to the file (compared with astropy's own read).
    band = cfg.survey.detection_band
    want = fits.getdata(sv.science_path(field, band)).astype(np.float64)
    assert np.array_equal(sv.science(field, band).astype(np.float64), want)
    weight = fits.getdata(sv.noise_path(field, band)).astype(np.float64)
    got = sv.rms(field, band).astype(np.float64)
    good = weight > 0
    assert np.allclose(got[good], 1.0 / np.sqrt(weight[good]), rtol=1e-6)
    assert np.all(np.isinf(got[~good]))


# ------------------------------------------------------------------------------
# The run's field cache under hostile conditions (issue 21, bullets 6 and 7), through the
# command line: a full disk and a truncated array file.
# ------------------------------------------------------------------------------
def test_field_cache_on_a_full_disk_warns_and_the_run_goes_on(store_run, two_task_run, capsys,
                                                              monkeypatch, fallocate_enospc):
    """Documented: the field's arrays stay in memory (one warning naming the cache)."""
    cfg_path, _ = two_task_run
    ref = run_rows(store_run)
    task_files(store_run)[0].unlink()
    fallocate_enospc(where=f"/{C.CONTEXT_DIRNAME}/")
    code, lines = cli(capsys, "simulate", cfg_path, "--out", store_run, "--workers", 1, "--quiet")
    assert code == 0
    warned = [ln for ln in lines if "field cache not written" in ln]
    cache = re.escape(str(store_run / C.CONTEXT_DIRNAME))
    assert len(warned) == 1
    assert re.match(rf"warning: {cache}/\w+: field cache not written \(No space", warned[0])
    pd.testing.assert_frame_equal(run_rows(store_run), ref)
    assert not (store_run / C.CONTEXT_DIRNAME).exists() or not list(
        (store_run / C.CONTEXT_DIRNAME).iterdir())


def test_truncated_field_cache_is_measured_again(store_run, two_task_run, capsys):
    """An interrupted run's field cache with a truncated array file: the resume warns,
    naming the cache, measures the field again and gives the same rows."""
    cfg_path, _ = two_task_run
    ref = run_rows(store_run)
    for f in task_files(store_run):
        f.unlink()
    # An unfinished run keeps its field caches (1 of its 2 tasks run).
    simulate(load_config(cfg_path), store_run, workers=1, progress=False, max_tasks=1)
    cache = next((store_run / C.CONTEXT_DIRNAME).iterdir())
    npy = max(cache.glob("*.npy"), key=lambda p: p.stat().st_size)
    with open(npy, "r+b") as fh:
        fh.truncate(npy.stat().st_size // 2)
    from glaciar.contexts import clear_contexts
    clear_contexts()             # as a new process: the cache is opened from disk
    code, lines = cli(capsys, "simulate", cfg_path, "--out", store_run, "--workers", 1, "--quiet")
    assert code == 0
    assert len(lines) == 1 and re.match(rf"warning: {re.escape(str(cache))}: unreadable field "
                                        r"cache \(.*\); the field is measured again", lines[0])
    pd.testing.assert_frame_equal(run_rows(store_run), ref)
