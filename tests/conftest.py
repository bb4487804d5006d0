"""Shared fixtures: small demo surveys built once per test session.

Sizes and costs (measured on a shared 2-core machine):

* ``small_survey``: one 320x320 field, 2 z x 2 mag x 2 iterations x 12 sources.
* ``two_depth_survey``: fields ``shallow`` (300x300, noise x2.5: ~1.0 mag shallower)
  and ``deep`` (600x600), footprint areas 1:4; z = 8, 10 x mag 23.0-27.5 (step 0.5)
  x 4 iterations x 30 sources = 160 tasks, ~4700 sources (the small field has room
  for ~29 of the 30 per task).  Completeness runs from ~0.95 to 0 in both fields
  (50 % near 25.1 shallow, 26.2 deep); selection is ~0 at z = 8 and up to ~0.7 at
  z = 10.  Building takes ~1.5 s; ``two_depth_run`` ~13 s wall with 2 workers on an
  idle machine (~25 s while another test job shares the cores).
* ``deep_corner_survey``: one 400x400 field whose noise is x0.3 over the quadrant
  ``DEEP_CORNER_QUADRANT`` (1.31 mag deeper there); z = 8, 10 x mag 23.5-28.5 x
  5 iterations x 40 sources = 110 tasks, ~4400 sources (~1/4 in the deep quadrant).
  ``deep_corner_run`` takes ~10 s wall with 2 workers (~14 s on a shared machine).

The ``*_run`` fixtures simulate once per session (into a temporary run directory) so
that every test reading those results shares one run; ``small_run`` is ``small_survey``
simulated serially (8 tasks, 96 sources: 0.5-2 s of CPU), read by the run, CLI and Dask
tests.  Tests never write into a shared run: they copy it first (without its lock file).
``one_task_run`` and ``two_task_run`` are 1 and 2 tasks of 3 sources of the small survey
(run-directory, manifest, store and CLI tests; ``run_copy`` and ``store_run`` are copies).

Layout: the tests of ``glaciar/<pkg>/<module>.py`` are in ``tests/<pkg>/test_<module>.py``
(``tests/test_<module>_<aspect>.py`` where one file would be too long; end-to-end tests
with the entry point they drive: ``test_execute*.py``, ``test_cli*.py``,
``pipeline/test_fit.py``).  Modules without the ``test_`` prefix hold what several test
files share: ``toy_images`` (synthetic images, the crowded field, FITS surveys),
``tiny_runs`` (configurations as dicts, directory snapshots, one-line CLI errors),
``config_dicts``, ``noise_fields``, ``analytic_sf``, ``figure_cases``, ``renderer_box``
(the property tests' parameter box).  pytest imports test files in importlib mode with
``tests/`` on ``sys.path`` (pyproject.toml), so no test file imports another.

The suite runs on two processes (pytest-xdist, ``scripts/test.sh``): the session fixtures
that build files are built once for the whole session, by whichever process asks first,
and read by the others (:func:`_built_once`).
"""
import fcntl
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest


def _built_once(tmp_path_factory, name, build):
    """``build(directory)``'s JSON result, computed once per test session.

    Under pytest-xdist every worker process has its own session: a fixture built in
    each would cost its set-up (simulations of up to ~25 s) twice.  The directory sits
    in the temporary root the workers share, and an exclusive ``flock`` lets the first
    worker build it while the others wait, then read what it recorded.  A build that
    fails leaves no record: the next worker tries again (and fails the same way).
    """
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent
    path, record = root / f"shared-{name}", root / f"shared-{name}.json"
    with open(root / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not record.exists():
            shutil.rmtree(path, ignore_errors=True)
            path.mkdir()
            record.write_text(json.dumps(build(path)))
    return json.loads(record.read_text())

def _assert_same_outputs(got, want, what):
    """Every ``measure_injected`` output column equal (floats to 1e-9 relative, NaN where
    NaN, others exactly); ``detection_id`` is a label of one extraction, not comparable."""
    for c in got:
        if c == "detection_id":
            continue
        a, b = got[c], want[c]
        if a.dtype.kind == "f":
            same = (np.isnan(a) & np.isnan(b)) | (np.abs(a - b) <= 1e-9 * np.abs(b))
        else:
            same = a == b
        assert same.all(), (what, c, np.flatnonzero(~same), a[~same], b[~same])


@pytest.fixture
def assert_same_outputs():
    """:func:`_assert_same_outputs`, for tests comparing two ways of measuring."""
    return _assert_same_outputs


#: (rows, cols) slices of the deep quadrant of ``deep_corner_survey``.
DEEP_CORNER_SHAPE = (400, 400)
DEEP_CORNER_QUADRANT = (slice(0, 200), slice(0, 200))
DEEP_CORNER_NOISE_SCALE = 0.3


@pytest.fixture(scope="session")
def small_survey(tmp_path_factory):
    """A 320x320 4-band demo field with a tiny grid; returns the config path."""
    from glaciar.demo import build_demo_survey

    def build(out):
        return str(build_demo_survey(out, shape=(320, 320), seed=11, n_galaxies=12,
                                     n_iterations=2, z_values=(8.0, 10.4), mag_values=(24.0, 27.5)))

    return Path(_built_once(tmp_path_factory, "survey", build))


def _write_config(demo_config, path, *, fields, z_values, mag_values, n_galaxies, n_iterations, seed):
    """A copy of a demo config with other fields, grid and simulation settings."""
    import yaml

    cfg = yaml.safe_load(demo_config.read_text())
    cfg["survey"]["fields"] = list(fields)
    cfg["grid"] = {"z": {"values": [float(z) for z in z_values]},
                   "mag": {"values": [round(float(m), 6) for m in mag_values]},
                   "magnitude_type": "apparent"}
    cfg["simulation"] = {"n_galaxies": int(n_galaxies), "n_iterations": int(n_iterations),
                         "seed": int(seed)}
    # These surveys test depth-aware fitting against brute-force area-weighted references,
    # with grids placed around their completeness curves. The correlated-noise model
    # (noise.correlated, default auto) moves the demo's m50 0.44 mag brighter
    # (benchmarks/correlated_noise.py) and off those grids; it has its own acceptance
    # test (tests/engine/test_noise.py), so these scenarios keep uncorrelated errors.
    cfg["noise"] = {"correlated": "off"}
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


@pytest.fixture(scope="session")
def two_depth_survey(tmp_path_factory):
    """Two fields, ``shallow`` (300^2, noise x2.5) and ``deep`` (600^2); returns the config path.

    Both fields' files sit in one directory (they share the PSF files); the config
    ``two_depth.yaml`` lists ``survey.fields: [shallow, deep]``.
    """
    from glaciar.demo import build_demo_survey

    def build(out):
        build_demo_survey(out, shape=(300, 300), seed=21, field="shallow", noise_scale=2.5)
        demo = build_demo_survey(out, shape=(600, 600), seed=22, field="deep")
        # z inside the J125-dropout window, so that V_eff's z integral can be checked
        # against the binned fractions (trapezoid over these z).
        return str(_write_config(demo, out / "two_depth.yaml", fields=("shallow", "deep"),
                                 z_values=(9.5, 10.0, 10.5, 11.0, 11.5),
                                 mag_values=np.arange(23.0, 27.5 + 1e-9, 0.5),
                                 n_galaxies=30, n_iterations=3, seed=5))

    return Path(_built_once(tmp_path_factory, "two_depth", build))


@pytest.fixture(scope="session")
def deep_corner_survey(tmp_path_factory):
    """One 400^2 field, noise x0.3 over ``DEEP_CORNER_QUADRANT``; returns the config path."""
    from glaciar.demo import build_demo_survey

    def build(out):
        scale = np.ones(DEEP_CORNER_SHAPE)
        scale[DEEP_CORNER_QUADRANT] = DEEP_CORNER_NOISE_SCALE
        demo = build_demo_survey(out, shape=DEEP_CORNER_SHAPE, seed=31, field="corner",
                                 noise_scale=scale)
        return str(_write_config(demo, out / "deep_corner.yaml", fields=("corner",),
                                 z_values=(8.0, 10.0),
                                 mag_values=np.arange(23.5, 28.5 + 1e-9, 0.5),
                                 n_galaxies=40, n_iterations=5, seed=6))

    return Path(_built_once(tmp_path_factory, "deep_corner", build))


@pytest.fixture(scope="session")
def deep_corner_quadrant():
    """(rows, cols) slices of the deep quadrant of ``deep_corner_survey``, and its noise factor."""
    return DEEP_CORNER_QUADRANT, DEEP_CORNER_NOISE_SCALE


def _simulated(config_path, tmp_path_factory, name, workers=2):
    """``config_path`` simulated once per session: (Config, run directory)."""
    from glaciar.config import load_config
    from glaciar.execute import simulate

    cfg = load_config(config_path)

    def build(out):
        simulate(cfg, out, workers=workers, progress=False)
        return str(out)

    return cfg, Path(_built_once(tmp_path_factory, name, build))


@pytest.fixture(scope="session")
def small_run(small_survey, tmp_path_factory):
    """``small_survey`` simulated once, serially (workers=1): (Config, run directory).

    Shared by the session: read it, or write into a copy
    (``shutil.copytree(run, dst, ignore=shutil.ignore_patterns(C.LOCK_NAME))``).
    """
    return _simulated(small_survey, tmp_path_factory, "small_run", workers=1)


@pytest.fixture(scope="session")
def two_depth_run(two_depth_survey, tmp_path_factory):
    """``two_depth_survey`` simulated once (2 workers): (Config, run directory)."""
    return _simulated(two_depth_survey, tmp_path_factory, "two_depth_run")


@pytest.fixture(scope="session")
def deep_corner_run(deep_corner_survey, tmp_path_factory):
    """``deep_corner_survey`` simulated once (2 workers): (Config, run directory)."""
    return _simulated(deep_corner_survey, tmp_path_factory, "deep_corner_run")


@pytest.fixture
def fallocate_enospc(monkeypatch):
    """``enospc(where=None)``: make ``os.posix_fallocate`` fail with ENOSPC (a full disk),
    for files whose path contains ``where`` (every file when None)."""
    import errno
    import os

    real = os.posix_fallocate

    def enospc(where=None):
        def fake(fd, offset, length):
            if where is None or where in os.readlink(f"/proc/self/fd/{fd}"):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real(fd, offset, length)
        monkeypatch.setattr(os, "posix_fallocate", fake)
    return enospc


# --------------------------------------------------------------------------
# Tiny runs of ``small_survey`` (helpers in tiny_runs.py), once per session: the tests that
# share one read it or copy it (``run_copy``, ``store_run``), never write into it.
# --------------------------------------------------------------------------
@pytest.fixture(scope="session")
def small_survey_dict(small_survey):
    """The small survey's configuration as a dict with absolute paths."""
    from tiny_runs import absolute_config

    return absolute_config(small_survey)


@pytest.fixture(scope="session")
def one_task_run(small_survey_dict, tmp_path_factory):
    """A finished one-task run (1 field, z = 8, m = 24, 3 sources): (config dict, run dir)."""
    from glaciar.execute import simulate
    from tiny_runs import load_dict, tiny_config

    d = tiny_config(small_survey_dict)

    def build(tmp):
        simulate(load_dict(d, tmp / "c.yaml"), tmp / "run", workers=1, progress=False)
        return str(tmp / "run")

    return d, Path(_built_once(tmp_path_factory, "one_task", build))


@pytest.fixture
def run_copy(one_task_run, tmp_path):
    """A private copy of ``one_task_run``: (config dict, run dir)."""
    import json
    import shutil

    d, run = one_task_run
    shutil.copytree(run, tmp_path / "run")
    return json.loads(json.dumps(d)), tmp_path / "run"


@pytest.fixture(scope="session")
def two_task_run(small_survey_dict, tmp_path_factory):
    """The small survey's field, z = 8, m = 24 and 27.5, 1 iteration of 3 sources:
    (config path, finished run directory)."""
    from glaciar.config import load_config
    from glaciar.execute import simulate
    from tiny_runs import tiny_config, write_yaml

    def build(root):
        cfg_path = write_yaml(tiny_config(small_survey_dict, mag=(24.0, 27.5)), root / "c.yaml")
        simulate(load_config(cfg_path), root / "run", workers=1, progress=False)
        return [str(cfg_path), str(root / "run")]

    cfg_path, run = _built_once(tmp_path_factory, "two_task", build)
    return Path(cfg_path), Path(run)


@pytest.fixture
def store_run(two_task_run, tmp_path):
    """A copy of ``two_task_run`` in ``tmp_path/run``, beside ``tmp_path/outside`` (one file)."""
    import shutil

    from glaciar import constants as C

    _, src = two_task_run
    dst = tmp_path / "run"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    (tmp_path / "outside").mkdir()
    (tmp_path / "outside" / "keep.txt").write_text("not glaciar's\n")
    return dst


#: Test files that take the longest (end-to-end notebooks and fits), scheduled first: the
#: two processes split the suite by file in collection order, and a long file collected
#: last (test_notebooks.py sorts late) would leave one process working alone at the end.
LONGEST_FIRST = ("test_notebooks.py", "pipeline/test_fit.py", "inference/test_fit_sbc.py",
                 "pipeline/test_adaptive.py", "test_cli.py", "engine/test_noise.py",
                 "test_report.py", "inference/test_fit.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}

    def key(item):
        path = item.path.as_posix()
        return min((i for name, i in rank.items() if path.endswith("tests/" + name)),
                   default=len(rank))

    items.sort(key=key)          # stable: the order within a file and among the rest is kept
