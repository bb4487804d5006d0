"""Field set-up in the workers (issue 24, point 2).

* With 2 workers, each of a run's two fields is measured once, in a pool worker, never
  in the run's own process; an interrupted run's resume maps the workers' caches
  (nothing measured again); manifest and rows equal a serial run's; the measuring
  warnings reach the caller once each.
* A field whose measurement fails in a worker: the caller gets the error, the caches
  the other workers wrote are removed, no process is left behind.

Two 192^2 demo fields, 4 tasks of 6 sources; ~15 s on 2 cores.
"""
import multiprocessing
import os
import warnings

import pandas as pd
import pytest
import yaml

import glaciar.contexts as contexts
from glaciar import constants as C
from glaciar.config import load_config
from glaciar.execute import simulate
from glaciar.rundir import read_manifest
from glaciar.store import read_results

pytestmark = pytest.mark.skipif(multiprocessing.get_start_method(allow_none=True) not in
                                (None, "fork") or multiprocessing.get_all_start_methods()[0] != "fork",
                                reason="the counting hook reaches the workers by fork")

FIELDS = ("fa", "fb")


@pytest.fixture(scope="module")
def two_fields(tmp_path_factory):
    """Two demo fields in one directory; detection band without a noise map (so each field's
    set-up warns, naming the field). Returns the config path."""
    from glaciar.demo import build_demo_survey

    out = tmp_path_factory.mktemp("two_fields")
    build_demo_survey(out, shape=(192, 192), seed=41, field=FIELDS[0])
    demo = build_demo_survey(out, shape=(192, 192), seed=42, field=FIELDS[1])
    d = yaml.safe_load(demo.read_text())
    d["survey"]["fields"] = list(FIELDS)
    d["survey"]["noise"] = None
    d["grid"]["z"] = {"values": [8.0]}
    d["grid"]["mag"] = {"values": [26.0]}
    d["simulation"].update(n_galaxies=6, n_iterations=2)
    path = out / "two.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


@pytest.fixture
def builds(tmp_path, monkeypatch):
    """A file that gets the pid of each field measurement
    (``glaciar.contexts.build_field_context``), in whichever (forked) process it runs."""
    log = tmp_path / "builds.txt"
    log.write_text("")
    build = contexts.build_field_context

    def counted(cfg, survey, field):
        with open(log, "a") as fh:
            fh.write(f"{os.getpid()} {field}\n")
        return build(cfg, survey, field)

    monkeypatch.setattr(contexts, "build_field_context", counted)
    return log


def _measured(log):
    return [tuple(line.split()) for line in log.read_text().splitlines()]


def _rows(run):
    df = read_results(run)
    return df.sort_values(list(df.columns)).reset_index(drop=True)


def _no_depth_map_warnings(caught):
    return sorted(str(w.message) for w in caught if "no noise map for the detection band" in
                  str(w.message))


def test_fields_are_measured_in_the_workers_and_match_the_serial_run(two_fields, builds,
                                                                      tmp_path):
    cfg = load_config(two_fields)
    contexts.clear_contexts()
    simulate(cfg, tmp_path / "serial", workers=1, progress=False)
    serial_builds = _measured(builds)
    assert sorted(f for _, f in serial_builds) == list(FIELDS)
    assert {pid for pid, _ in serial_builds} == {str(os.getpid())}
    builds.write_text("")
    contexts.clear_contexts()
    run = tmp_path / "two"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stats = simulate(cfg, run, workers=2, progress=False, max_tasks=1)
    assert stats["n_run"] == 1
    first = _measured(builds)
    # Each field once, in a worker; the run's own process measured none.
    assert sorted(f for _, f in first) == list(FIELDS)
    assert str(os.getpid()) not in {pid for pid, _ in first}
    # The workers' warnings reach the caller, once per field.
    said = _no_depth_map_warnings(caught)
    assert len(said) == 2 and all(f"field {f!r}" in m for f, m in zip(FIELDS, said)), said
    # The interrupted run kept the workers' caches: its resume maps them, measuring nothing.
    assert len(list((run / C.CONTEXT_DIRNAME).iterdir())) == 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        stats = simulate(cfg, run, workers=2, progress=False)
    assert (stats["n_done_before"], stats["n_run"]) == (1, 3)
    assert _measured(builds) == first
    assert len(_no_depth_map_warnings(caught)) == 2
    assert read_manifest(run) == read_manifest(tmp_path / "serial")
    assert (run / C.MANIFEST_NAME).read_bytes() == (tmp_path / "serial" / C.MANIFEST_NAME).read_bytes()
    pd.testing.assert_frame_equal(_rows(run), _rows(tmp_path / "serial"))
    assert multiprocessing.active_children() == []


def test_a_field_failing_in_a_worker_leaves_no_cache(two_fields, tmp_path, monkeypatch):
    cfg = load_config(two_fields)
    build = contexts.build_field_context

    def failing(cfg, survey, field):
        if field == FIELDS[1]:
            raise RuntimeError(f"field {field}: cannot be measured")
        return build(cfg, survey, field)

    monkeypatch.setattr(contexts, "build_field_context", failing)
    contexts.clear_contexts()
    run = tmp_path / "run"
    with pytest.raises(RuntimeError, match=f"^field {FIELDS[1]}: cannot be measured$"):
        simulate(cfg, run, workers=2, progress=False)
    # The first field's cache, written by the other worker, is gone again; so is the pool.
    assert not (run / C.CONTEXT_DIRNAME).exists() or not list((run / C.CONTEXT_DIRNAME).iterdir())
    assert not (run / C.MANIFEST_NAME).exists()
    assert multiprocessing.active_children() == []
