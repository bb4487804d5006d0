"""Run-directory integrity under hostile use (issue 10): task identity, content-aware store
identity, validate-then-write, the run lock, process hygiene, corrupt task files, umask,
the renamed flags column and one-line CLI errors.

Every simulation here is tiny (the ``small_survey`` images, 1-6 tasks of 3-6 sources);
the two subprocess tests run ~18 tasks with 2 workers.
"""
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import pandas as pd
import pytest
import yaml
from astropy.io import fits

from glaciar import constants as C
from glaciar.cli import main
from glaciar.config import load_config
from glaciar.execute import simulate
from glaciar.inputs import InputError
from glaciar.manifest import prepare_run_dir
from glaciar.plan import plan_tasks
from glaciar.store import StoreWarning, read_current_results, read_results, task_filename
from glaciar.rundir import (RunLock, RunLockedError, StoreMismatchError, atomic_write_text,
                            file_fingerprint, read_manifest)


# --------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------
def _base_dict(small_survey):
    """The small survey's config with absolute paths, so that copies can live anywhere."""
    d = yaml.safe_load(small_survey.read_text())
    base = small_survey.parent
    d["survey"]["image_dir"] = str(base / d["survey"]["image_dir"])
    for b in d["survey"]["bands"].values():
        b["psf"] = str(base / b["psf"])
    return d


def _tiny(d, *, fields=None, z=(8.0,), mag=(24.0,), n_iter=1, n_gal=3, seed=11):
    d = json.loads(json.dumps(d))
    if fields is not None:
        d["survey"]["fields"] = list(fields)
    d["grid"] = {"z": {"values": list(z)}, "mag": {"values": list(mag)},
                 "magnitude_type": "apparent"}
    d["simulation"] = {"n_galaxies": n_gal, "n_iterations": n_iter, "seed": seed}
    return d


def _write(d, path):
    path.write_text(yaml.safe_dump(d, sort_keys=False, allow_unicode=True), encoding="utf-8")
    return path


def _load(d, path):
    return load_config(_write(d, path))


def _snapshot(root):
    """{relative path: (bytes, mode)} of every file below ``root`` (hidden ones included)."""
    out = {}
    for dirpath, _dirs, files in os.walk(root):
        for f in files:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, root)] = (open(p, "rb").read(), os.stat(p).st_mode)
    return out


def _sorted(df):
    keys = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]
    return df.sort_values(keys).reset_index(drop=True)


def _link_field(image_dir, src_field, new_field, dst_dir, copy=False):
    """Images of ``new_field`` in ``dst_dir``: links (or copies) of ``src_field``'s files."""
    for p in image_dir.glob(f"{src_field}_*.fits"):
        q = dst_dir / p.name.replace(src_field, new_field, 1)
        if copy:
            shutil.copyfile(p, q)
        else:
            q.symlink_to(p)


@pytest.fixture(scope="module")
def base(small_survey):
    return _base_dict(small_survey)


@pytest.fixture(scope="module")
def one_task_run(base, tmp_path_factory):
    """A finished one-task run (1 field, z = 8, m = 24, 3 sources): (config dict, run dir)."""
    d = _tiny(base)
    tmp = tmp_path_factory.mktemp("one_task")
    cfg = _load(d, tmp / "c.yaml")
    simulate(cfg, tmp / "run", workers=1, progress=False)
    return d, tmp / "run"


@pytest.fixture
def run_copy(one_task_run, tmp_path):
    d, run = one_task_run
    shutil.copytree(run, tmp_path / "run")
    return json.loads(json.dumps(d)), tmp_path / "run"


# --------------------------------------------------------------------------
# 1. Collision-free task identity
# --------------------------------------------------------------------------
def test_task_filenames_are_injective():
    keys = [("par α", 8.0, 24.0, 0), ("par β", 8.0, 24.0, 0), ("a b", 8.0, 24.0, 0),
            ("a_b", 8.0, 24.0, 0), ("a/b", 8.0, 24.0, 0), ("a_b", 9.0, 24.0, 0),
            ("a_b", 9.00004, 24.0, 0), ("a_b", 9.0, 24.00001, 0), ("a_b", 9.0, 24.0, 1),
            ("a_b", -9.0, 24.0, 0), ("a_b", 9.0 + 1e-15, 24.0, 0)]
    names = [task_filename(*k) for k in keys]
    assert len(set(names)) == len(keys)
    # Deterministic, one path component, readable start.
    assert task_filename("par α", 8.0, 24.0, 0) == names[0]
    assert all("/" not in n and n.startswith("task_") and n.endswith(".parquet") for n in names)
    assert names[2].startswith("task_a_b-") and "_z+008.0000_m+024.0000_i0000_" in names[2]


def test_fields_and_grid_values_that_used_to_collide_keep_their_rows(base, tmp_path):
    """'a b' / 'a_b' / 'par α' and z = 8.0 / 8.00004: every task its own file and rows."""
    image_dir = tmp_path / "images"
    image_dir.mkdir()
    fields = ("a b", "a_b", "par α")
    for f in fields:
        _link_field(load_config(_write(base, tmp_path / "b.yaml")).survey.image_dir,
                    "demo01", f, image_dir)
    d = _tiny(base, fields=fields, z=(8.0, 8.00004), n_gal=3)
    d["survey"]["image_dir"] = str(image_dir)
    cfg = _load(d, tmp_path / "c.yaml")
    stats = simulate(cfg, tmp_path / "run", workers=1, progress=False)
    assert stats["n_run"] == 6 and stats["n_done_before"] == 0
    assert len(list((tmp_path / "run" / C.RESULTS_DIRNAME).glob("task_*.parquet"))) == 6
    rows = read_results(tmp_path / "run")
    counts = rows.groupby([C.COL_FIELD, C.COL_Z]).size()
    assert sorted(counts.index) == sorted((f, z) for f in fields for z in (8.0, 8.00004))
    assert (counts == 3).all()
    # Resume finds every finished task of this format.
    again = simulate(cfg, tmp_path / "run", workers=1, progress=False)
    assert again["n_run"] == 0 and again["n_done_before"] == 6


def test_region_files_do_not_collide(tmp_path):
    from glaciar.tables import write_regions

    keys = [("a b", 8.0), ("a_b", 8.0), ("a_b", 8.00004), ("par α", 8.0)]
    rows = pd.DataFrame({C.COL_FIELD: [k[0] for k in keys], C.COL_Z: [k[1] for k in keys],
                         C.COL_MAG: 24.0, C.COL_ITERATION: 0, C.COL_X: 1.0, C.COL_Y: 2.0,
                         C.COL_STATUS: C.STATUS_ISOLATED})
    paths = write_regions(rows, tmp_path)
    # One file per field: "a b" and "a_b" do not share one; "a_b" holds both of its tasks.
    assert len(set(paths)) == 3 and all(p.is_file() for p in paths)
    assert sorted(p.read_text().count("circle(") for p in paths) == [1, 1, 2]


def test_store_of_the_old_format_is_refused_not_mixed(run_copy, tmp_path):
    d, run = run_copy
    m = read_manifest(run)
    del m["store_format"]
    (run / C.MANIFEST_NAME).write_text(json.dumps(m))
    before = _snapshot(run)
    with pytest.raises(StoreMismatchError, match=r"store format 1.*use another --out"):
        simulate(_load(d, tmp_path / "c.yaml"), run, workers=1, progress=False)
    assert _snapshot(run) == before


# --------------------------------------------------------------------------
# 2. Content-aware store identity
# --------------------------------------------------------------------------
def test_manifest_records_fingerprints_and_version(one_task_run):
    import glaciar

    d, run = one_task_run
    m = read_manifest(run)
    assert m["store_format"] == C.STORE_FORMAT and m["glaciar_version"] == glaciar.__version__
    psf = d["survey"]["bands"]["f160w"]["psf"]
    got = m["inputs"]["survey.bands.f160w.psf"]
    data = open(psf, "rb").read()
    assert got["size"] == len(data)
    assert got["blake2b"] == hashlib.blake2b(data, digest_size=16).hexdigest()
    # Every image and noise map of the field, by key.
    assert sum(k.startswith("survey.science (field 'demo01'") for k in m["inputs"]) == 4
    assert sum(k.startswith("survey.noise (field 'demo01'") for k in m["inputs"]) == 4


def test_changed_psf_is_refused_naming_key_and_file(run_copy, tmp_path):
    d, run = run_copy
    psf = tmp_path / "psf_f160w.fits"
    shutil.copyfile(d["survey"]["bands"]["f160w"]["psf"], psf)
    d["survey"]["bands"]["f160w"]["psf"] = str(psf)
    cfg = _load({**d, "grid": {**d["grid"], "mag": {"values": [24.0, 25.0]}}}, tmp_path / "c.yaml")
    # Same content at another path: the same store (paths are not identity); one new task runs.
    assert simulate(cfg, run, workers=1, progress=False)["n_run"] == 1
    with fits.open(psf, mode="update") as hdul:
        hdul[0].data = hdul[0].data * 1.0001
    before = _snapshot(run)
    with pytest.raises(StoreMismatchError) as exc:
        simulate(cfg, run, workers=1, progress=False)
    assert str(exc.value) == (f"survey.bands.f160w.psf: {psf} changed since the run started "
                              "(content differs); use another --out")
    assert _snapshot(run) == before


def test_changed_image_matters_only_for_fields_with_results(base, tmp_path):
    image_dir = tmp_path / "images"
    image_dir.mkdir()
    src = load_config(_write(base, tmp_path / "b.yaml")).survey.image_dir
    for f in ("f1", "f2"):
        _link_field(src, "demo01", f, image_dir, copy=True)
    d = _tiny(base, fields=("f1", "f2"))
    d["survey"]["image_dir"] = str(image_dir)
    cfg = _load(d, tmp_path / "c.yaml")
    run = tmp_path / "run"
    assert simulate(cfg, run, workers=1, progress=False, max_tasks=1)["n_run"] == 1   # f1 only

    def touch_image(field):
        with fits.open(image_dir / f"{field}_f125w_drz.fits", mode="update") as hdul:
            hdul[0].data[0, 0] += 1.0

    touch_image("f2")                     # no task of f2 finished: accepted
    assert simulate(cfg, run, workers=1, progress=False)["n_run"] == 1
    touch_image("f1")
    with pytest.raises(StoreMismatchError,
                       match=r"survey.science \(field 'f1', band 'f125w'\): .*f1_f125w_drz.fits "
                             r"changed since the run started"):
        simulate(cfg, run, workers=1, progress=False)


def test_run_directory_own_config_is_the_same_store(one_task_run, tmp_path):
    _, run = one_task_run
    shutil.copytree(run, tmp_path / "run")
    cfg = load_config(tmp_path / "run" / C.RUN_CONFIG_NAME)
    stats = simulate(cfg, tmp_path / "run", workers=1, progress=False)
    assert stats["n_run"] == 0 and stats["n_done_before"] == 1


def test_other_settings_are_refused_naming_the_key(run_copy, tmp_path):
    d, run = run_copy
    d["classification"] = {**(d.get("classification") or {}), "min_sn": 6.0}
    with pytest.raises(StoreMismatchError, match=r"classification.min_sn: 8.0 -> 6.0"):
        simulate(_load(d, tmp_path / "c.yaml"), run, workers=1, progress=False)


def test_rows_no_longer_listed_are_excluded_by_report_and_fit_alike(base, tmp_path):
    from glaciar.cli import _report
    from glaciar.pipeline.inputs import read_columns

    d = _tiny(base, z=(8.0, 10.4), n_iter=2)
    run = tmp_path / "run"
    simulate(_load(d, tmp_path / "c.yaml"), run, workers=1, progress=False)
    assert len(read_results(run)) == 2 * 2 * 3
    # Drop z = 10.4 and the second iteration: the manifest describes the run as now configured.
    small = _tiny(base, z=(8.0,), n_iter=1)
    assert simulate(_load(small, tmp_path / "s.yaml"), run, workers=1, progress=False)["n_run"] == 0
    with pytest.warns(StoreWarning, match=r"ignoring 9 rows of 3 task\(s\)"):
        rows = read_current_results(run)
    assert set(rows[C.COL_Z]) == {8.0} and set(rows[C.COL_ITERATION]) == {0} and len(rows) == 3
    with pytest.warns(StoreWarning):
        fit_rows = read_columns(run, [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_RECOVERED])
    pd.testing.assert_frame_equal(fit_rows, rows[fit_rows.columns.tolist()])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StoreWarning)
        _report(run)
    from astropy.table import Table
    t = Table.read(run / C.SUMMARY_DIRNAME / "summary_all.ecsv")
    assert list(t["z"]) == [8.0] and list(t["n_input"]) == [3]


def test_fingerprint_cache_skips_unchanged_files(tmp_path):
    p = tmp_path / "f.bin"
    p.write_bytes(b"abc")
    cache = {}
    fp = file_fingerprint(p, cache)
    assert fp == {"size": 3, "blake2b": hashlib.blake2b(b"abc", digest_size=16).hexdigest()}
    entry = cache[str(p.resolve())]
    # A cache entry with the same size and mtime is trusted (the file is not read again) ...
    cache[str(p.resolve())] = {**entry, "blake2b": "cached"}
    from glaciar import rundir
    rundir._FINGERPRINTS.clear()
    assert file_fingerprint(p, cache)["blake2b"] == "cached"
    # ... a new mtime is not.
    os.utime(p, ns=(entry["mtime_ns"] + 10**9, entry["mtime_ns"] + 10**9))
    assert file_fingerprint(p, cache)["blake2b"] == fp["blake2b"]


# --------------------------------------------------------------------------
# 3. Validate, then write
# --------------------------------------------------------------------------
def _psf_with_nan(src, dst):
    with fits.open(src) as hdul:
        data = hdul[0].data.astype(float)
        data[3, 3] = np.nan
        fits.writeto(dst, data, hdul[0].header)


def _hostile(kind, base, tmp_path):
    """A config dict with one bad input file; returns (dict, the bad file, expected key)."""
    d = _tiny(base)
    if kind.startswith("psf"):
        bad = tmp_path / "bad_psf.fits"
        src = d["survey"]["bands"]["f098m"]["psf"]
        if kind == "psf_nan":
            _psf_with_nan(src, bad)
        elif kind == "psf_text":
            bad.write_text("this is not a FITS file\n")
        elif kind == "psf_empty":
            bad.write_bytes(b"")
        d["survey"]["bands"]["f098m"]["psf"] = str(bad)
        return d, bad, "survey.bands.f098m.psf"
    image_dir = tmp_path / "images"
    shutil.copytree(d["survey"]["image_dir"], image_dir)
    d["survey"]["image_dir"] = str(image_dir)
    bad = image_dir / "demo01_f125w_drz.fits"
    if kind == "image_text":
        bad.write_text("SIMPLE = nonsense\n")
    elif kind == "image_truncated":
        data = bad.read_bytes()
        bad.write_bytes(data[: len(data) // 2])
    elif kind == "image_1d":
        fits.writeto(bad, np.ones(50, np.float32), overwrite=True)
    elif kind == "image_all_nan":
        fits.writeto(bad, np.full((320, 320), np.nan, np.float32), overwrite=True)
    return d, bad, "survey.science (field 'demo01', band 'f125w')"


HOSTILE_FILES = ["psf_nan", "psf_text", "psf_empty", "image_text", "image_truncated",
                 "image_1d", "image_all_nan"]


@pytest.mark.parametrize("kind", HOSTILE_FILES)
def test_bad_input_file_leaves_runs_untouched(kind, base, one_task_run, tmp_path):
    d, bad, key = _hostile(kind, base, tmp_path)
    cfg = _load(d, tmp_path / "c.yaml")
    shutil.copytree(one_task_run[1], tmp_path / "run")
    before = _snapshot(tmp_path / "run")
    for out in (tmp_path / "run", tmp_path / "new"):
        with pytest.raises((InputError, ValueError)) as exc:
            simulate(cfg, out, workers=1, progress=False)
        msg = str(exc.value)
        assert msg.startswith(f"{key}: {bad}: ") and "\n" not in msg, msg
    assert _snapshot(tmp_path / "run") == before
    assert not (tmp_path / "new").exists()


def test_bad_arguments_write_nothing(one_task_run, tmp_path):
    d, _ = one_task_run
    cfg = _load(d, tmp_path / "c.yaml")
    for kwargs, match in (({"seed": -1}, r"seed: expected an integer >= 0, got -1"),
                          ({"workers": 0}, r"workers: expected an integer >= 1, got 0"),
                          ({"workers": -3}, r"workers: expected an integer >= 1, got -3"),
                          ({"mode": "fast"}, r"mode: expected 'windowed' or 'full'")):
        with pytest.raises(ValueError, match=match):
            simulate(cfg, tmp_path / "new", progress=False, **kwargs)
    assert not (tmp_path / "new").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(FileExistsError, match="exists and is not a directory"):
        simulate(cfg, tmp_path / "file", progress=False)
    assert (tmp_path / "file").read_text() == "x"


# --------------------------------------------------------------------------
# 4. The run lock
# --------------------------------------------------------------------------
def test_second_writer_is_refused_and_live_temp_files_survive(run_copy, tmp_path):
    d, run = run_copy
    cfg = _load(d, tmp_path / "c.yaml")
    tmp_file = run / C.RESULTS_DIRNAME / ".task_inflight.parquet.abc.tmp"
    tmp_file.write_bytes(b"half a task")
    code = ("import sys; from glaciar.rundir import RunLock; RunLock(sys.argv[1]).acquire(); "
            "print('locked', flush=True); sys.stdin.read()")
    holder = subprocess.Popen([sys.executable, "-c", code, str(run)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = _snapshot(run)
        with pytest.raises(RunLockedError) as exc:
            simulate(cfg, run, workers=1, progress=False)
        assert str(exc.value) == f"{run}: another glaciar run is writing here (pid {holder.pid})"
        assert _snapshot(run) == before                    # the live run's temp file too
        # The CLI says the same in one line, exit 2.
        assert main(["simulate", str(tmp_path / "c.yaml"), "--out", str(run), "--quiet"]) == 2
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)
    # Once the holder is gone the lock is free, and the stale temp file is cleaned up.
    assert simulate(cfg, run, workers=1, progress=False)["n_run"] == 0
    assert not tmp_file.exists()


def test_lock_is_released_after_a_run_and_after_a_failure(run_copy, tmp_path):
    d, run = run_copy
    simulate(_load(d, tmp_path / "c.yaml"), run, workers=1, progress=False)
    with RunLock(run):                                     # free again
        pass
    bad = {**d, "simulation": {**d["simulation"], "seed": 12}}
    with pytest.raises(StoreMismatchError):
        simulate(_load(bad, tmp_path / "bad.yaml"), run, workers=1, progress=False)
    with RunLock(run):
        pass


# --------------------------------------------------------------------------
# 5. Process hygiene
# --------------------------------------------------------------------------
def _children(pid):
    psutil = pytest.importorskip("psutil")
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _gone(procs, timeout):
    psutil = pytest.importorskip("psutil")
    deadline = time.time() + timeout
    while time.time() < deadline:
        alive = []
        for p in procs:
            try:
                if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                    alive.append(p)
            except psutil.NoSuchProcess:
                pass
        if not alive:
            return True
        time.sleep(0.05)
    return False


def _start_cli_run(base, tmp_path):
    d = _tiny(base, z=(8.0, 10.4), mag=(24.0, 26.0, 27.5), n_iter=3, n_gal=6)
    cfg_path = _write(d, tmp_path / "c.yaml")
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "glaciar.cli", "simulate", str(cfg_path),
                             "--out", str(run), "--workers", "2", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    results = run / C.RESULTS_DIRNAME
    deadline = time.time() + 120
    workers = []
    while time.time() < deadline and proc.poll() is None:
        workers = _children(proc.pid)
        if len(workers) >= 2 and results.is_dir() and any(results.glob("task_*.parquet")):
            break
        time.sleep(0.05)
    assert proc.poll() is None and len(workers) >= 2, "the run ended before it could be killed"
    return proc, workers, cfg_path, run


def _kill_all(procs):
    for p in procs:
        try:
            p.kill()
        except Exception:  # noqa: BLE001 - already gone
            pass


def test_workers_die_with_a_killed_parent(base, tmp_path):
    proc, workers, _, run = _start_cli_run(base, tmp_path)
    try:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        assert _gone(workers, timeout=5), [p.pid for p in workers]
    finally:
        _kill_all(workers)


def test_sigterm_stops_cleanly_and_resumes(base, tmp_path):
    proc, workers, cfg_path, run = _start_cli_run(base, tmp_path)
    try:
        os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 128 + signal.SIGTERM
        assert err.strip().splitlines() == ["glaciar simulate: terminated (SIGTERM); finished "
                                            "tasks are kept, run the same command to resume"]
        assert _gone(workers, timeout=5)
    finally:
        _kill_all(workers)
    cfg = load_config(cfg_path)
    stats = simulate(cfg, run, workers=1, progress=False)
    assert stats["n_done_before"] >= 1 and stats["n_done_before"] + stats["n_run"] == len(plan_tasks(cfg))
    assert not list((run / C.RESULTS_DIRNAME).glob(".*.tmp"))
    rows = read_results(run)
    assert (rows.groupby([C.COL_Z, C.COL_MAG, C.COL_ITERATION]).size() == 6).all()


# --------------------------------------------------------------------------
# 6. Truncated or foreign task files are redone
# --------------------------------------------------------------------------
def test_truncated_and_foreign_task_files_are_redone(base, tmp_path):
    d = _tiny(base, mag=(24.0, 27.5), n_iter=2)
    cfg = _load(d, tmp_path / "c.yaml")
    run = tmp_path / "run"
    simulate(cfg, run, workers=1, progress=False)
    ref = _sorted(read_results(run))
    files = sorted((run / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    assert len(files) == 4
    cut, foreign = files[0], files[1]
    data = cut.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    shutil.copyfile(files[2], foreign)                   # a complete file of another task
    with pytest.warns(StoreWarning) as rec:
        stats = simulate(cfg, run, workers=1, progress=False)
    msgs = [str(w.message) for w in rec]
    assert any(str(cut) in m and "not a complete Parquet file" in m for m in msgs)
    assert any(str(foreign) in m and "holds another task" in m for m in msgs)
    assert stats["n_done_before"] == 2 and stats["n_run"] == 2
    pd.testing.assert_frame_equal(_sorted(read_results(run)), ref)


def test_unreadable_task_file_is_named_when_reading(run_copy):
    _, run = run_copy
    f = next((run / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    f.write_bytes(f.read_bytes()[:100])
    with pytest.raises(ValueError, match=re.escape(f"{f}: unreadable task file")):
        read_current_results(run)


# --------------------------------------------------------------------------
# 7. Outputs honour the umask
# --------------------------------------------------------------------------
@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_atomic_writes_honour_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == mode


def test_run_files_are_readable_by_the_group_with_umask_022(one_task_run, tmp_path):
    d, _ = one_task_run
    cfg = _load(d, tmp_path / "c.yaml")
    old = os.umask(0o022)
    try:
        simulate(cfg, tmp_path / "run", workers=1, progress=False)
    finally:
        os.umask(old)
    modes = {p.name: p.stat().st_mode & 0o777 for p in (tmp_path / "run").rglob("*") if p.is_file()}
    assert modes and set(modes.values()) == {0o644}, modes


# --------------------------------------------------------------------------
# 8. The flags column no longer shadows DataFrame.flags
# --------------------------------------------------------------------------
def test_flags_column_is_renamed(one_task_run):
    from glaciar.config import selection_columns

    _, run = one_task_run
    rows = read_results(run)
    assert C.COL_FLAGS in rows.columns and "flags" not in rows.columns
    assert isinstance(rows.flags, pd.Flags)                 # attribute access is pandas' own
    assert rows[C.COL_FLAGS].dtype.kind == "i"
    assert C.COL_FLAGS in selection_columns(["f160w"], 1) and "flags" not in selection_columns(["f160w"], 1)


# --------------------------------------------------------------------------
# 9. CLI values: one line, exit 2, nothing written
# --------------------------------------------------------------------------
CLI_CASES = [
    (["simulate", "{cfg}", "--out", "{out}", "--workers", "0"], "--workers: expected an integer >= 1, got '0'"),
    (["simulate", "{cfg}", "--out", "{out}", "--workers", "-3"], "--workers: expected an integer >= 1, got '-3'"),
    (["simulate", "{cfg}", "--out", "{out}", "--seed", "abc"], "--seed: expected an integer >= 0, got 'abc'"),
    (["simulate", "{cfg}", "--out", "{out}", "--seed", "-1"], "--seed: expected an integer >= 0, got '-1'"),
    (["simulate", "{cfg}", "--out", "{out}", "--mode", "fast"], "--mode: invalid choice: 'fast'"),
    (["fit", "{out}", "--area-arcmin2", "-1"], "--area-arcmin2: expected a finite number > 0, got '-1'"),
    (["fit", "{out}", "--area-arcmin2", "nan"], "--area-arcmin2: expected a finite number > 0, got 'nan'"),
    (["fit", "{out}", "--area-arcmin2", "inf"], "--area-arcmin2: expected a finite number > 0, got 'inf'"),
    (["fit", "{out}", "--max-steps", "0"], "--max-steps: expected an integer >= 1, got '0'"),
    (["next", "{out}", "-n", "0"], "-n: expected an integer >= 1, got '0'"),
    (["next", "{out}", "-n", "-1"], "-n: expected an integer >= 1, got '-1'"),
    (["simulate"], "the following arguments are required: config"),
]


@pytest.mark.parametrize("argv, expected", CLI_CASES, ids=[" ".join(c[0][2:]) or c[0][0] for c in CLI_CASES])
def test_bad_cli_values_one_line_exit_2(argv, expected, one_task_run, tmp_path, capsys):
    d, _ = one_task_run
    cfg = _write(d, tmp_path / "c.yaml")
    out = tmp_path / "out"
    argv = [a.format(cfg=cfg, out=out) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [f"glaciar: error: {expected}" if "invalid choice" not in expected
                                else err.splitlines()[0]]
    assert expected in err and "usage" not in err
    assert not out.exists()


def test_out_pointing_to_a_file_is_refused(one_task_run, tmp_path, capsys):
    d, _ = one_task_run
    cfg = _write(d, tmp_path / "c.yaml")
    f = tmp_path / "results.txt"
    f.write_text("keep me")
    assert main(["simulate", str(cfg), "--out", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [f"glaciar simulate: error: --out {f}: exists and is not a directory"]
    assert f.read_text() == "keep me"


def test_near_equal_grid_values_get_their_own_random_streams():
    """z = 9.0 and 9.00004 are different tasks with different files *and* different draws."""
    from glaciar.engine.task import TaskSpec, task_rng

    a = TaskSpec("f", 0, 0, 0, 0, 9.0, 25.0)
    b = TaskSpec("f", 0, 1, 0, 0, 9.00004, 25.0)
    c = TaskSpec("f", 0, 0, 1, 0, 9.0, 25.0 + 1e-12)
    ra, ia = task_rng(1, a)
    rb, ib = task_rng(1, b)
    rc, ic = task_rng(1, c)
    assert len({ia, ib, ic}) == 3
    assert len({tuple(r.random(3)) for r in (ra, rb, rc)}) == 3
    assert task_rng(1, a)[1] == ia                     # and each is reproducible
