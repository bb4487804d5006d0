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

import numpy as np
import pytest

import glaciar.survey as survey_module
from glaciar.config import load_config
from glaciar import contexts, fieldprep
from glaciar.contexts import clear_contexts
from glaciar.execute import simulate
from glaciar.fieldprep import build_field_context
from glaciar.survey import Survey


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
                    reason="workers inherit the main process's context only when forked")
def test_forked_workers_inherit_the_field_context(small_survey, tmp_path, monkeypatch):
    cfg = load_config(small_survey)
    clear_contexts()
    log = tmp_path / "builds.txt"
    _count(monkeypatch, contexts, "build_field_context", log)
    stats = simulate(cfg, tmp_path / "run", workers=2, progress=False)
    assert stats["n_run"] == 8
    assert log.read_text().split() == [str(os.getpid())]


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
