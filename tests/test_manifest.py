"""A store made before a detection key existed stays extendable while the key is at its default."""
import hashlib
import json
import shutil

import numpy as np
import pytest
import yaml
from astropy.io import fits

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.execute import simulate
from glaciar.inputs import InputError
from glaciar.rundir import StoreMismatchError, read_manifest

from tiny_runs import file_snapshot, link_field, load_dict, tiny_config, write_yaml


def _older_store(small_run, tmp_path, key="CLEAN_STYLE"):
    cfg, run = small_run
    dst = tmp_path / "run"
    shutil.copytree(run, dst, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    mpath = dst / C.MANIFEST_NAME
    manifest = json.loads(mpath.read_text())
    # What a glaciar without this key recorded: no such setting at all.
    del manifest["store_settings"]["detection"][key]
    manifest["store_hash"] = "0" * 64
    mpath.write_text(json.dumps(manifest))
    return cfg, dst


def test_a_key_added_since_at_its_default_is_the_same_store(small_run, tmp_path):
    cfg, run = _older_store(small_run, tmp_path)
    n = len(list((run / C.RESULTS_DIRNAME).glob("task_*.parquet")))
    stats = simulate(cfg, run, workers=1, progress=False)
    assert stats["n_run"] == 0 and stats["n_done_before"] == n


def test_a_key_added_since_set_otherwise_is_refused_by_name(small_run, small_survey, tmp_path):
    _, run = _older_store(small_run, tmp_path)
    d = yaml.safe_load(small_survey.read_text())
    d.setdefault("detection", {})["CLEAN_STYLE"] = "sep"
    path = small_survey.parent / "other_clean.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(StoreMismatchError, match="CLEAN_STYLE: <unset> -> sep"):
        simulate(load_config(path), run, workers=1, progress=False)


def test_task_files_without_checksums_or_digests_stay_done_and_readable(small_run, tmp_path):
    """Task files written before page checksums and footer digests (issue 21): a resume
    counts them as done (nothing set aside, no warning), readers read the same rows,
    and compaction folds them into a part that has both."""
    import warnings

    import pandas as pd
    import pyarrow.parquet as pq

    from glaciar.store import compact, read_results
    from glaciar.taskfile import unit_problem

    cfg, src = small_run
    run = tmp_path / "run"
    shutil.copytree(src, run, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    keys = [C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]
    ref = read_results(run).sort_values(keys).reset_index(drop=True)
    files = sorted((run / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    for f in files:                      # as glaciar wrote them before: no checksums, no digests
        t = pq.read_table(f)
        meta = {k: v for k, v in t.schema.metadata.items()
                if k not in (b"glaciar.schema.blake2b", b"glaciar.pages.blake2b")}
        pq.write_table(t.replace_schema_metadata(meta), f)
        assert unit_problem(f) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        stats = simulate(cfg, run, workers=1, progress=False)
        assert stats["n_run"] == 0 and stats["n_done_before"] == len(files)
        pd.testing.assert_frame_equal(read_results(run).sort_values(keys).reset_index(drop=True),
                                      ref)
        assert compact(run) == len(files)
    part = next((run / C.RESULTS_DIRNAME / "compact").rglob("part-*.parquet"))
    assert b"glaciar.pages.blake2b" in pq.read_metadata(part).metadata and unit_problem(part) is None
    pd.testing.assert_frame_equal(read_results(run).sort_values(keys).reset_index(drop=True), ref)


# ------------------------------------------------------------------------------
# Run-directory integrity under hostile use (issue 10): a store of another format or of other
# settings is refused by name, and every input is checked before anything is written.
# ------------------------------------------------------------------------------
def test_store_of_the_old_format_is_refused_not_mixed(run_copy, tmp_path):
    d, run = run_copy
    m = read_manifest(run)
    del m["store_format"]
    (run / C.MANIFEST_NAME).write_text(json.dumps(m))
    before = file_snapshot(run)
    with pytest.raises(StoreMismatchError, match=r"store format 1.*use another --out"):
        simulate(load_dict(d, tmp_path / "c.yaml"), run, workers=1, progress=False)
    assert file_snapshot(run) == before


# --------------------------------------------------------------------------
# Content-aware store identity
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
    cfg = load_dict({**d, "grid": {**d["grid"], "mag": {"values": [24.0, 25.0]}}}, tmp_path / "c.yaml")
    # Same content at another path: the same store (paths are not identity); one new task runs.
    assert simulate(cfg, run, workers=1, progress=False)["n_run"] == 1
    with fits.open(psf, mode="update") as hdul:
        hdul[0].data = hdul[0].data * 1.0001
    before = file_snapshot(run)
    with pytest.raises(StoreMismatchError) as exc:
        simulate(cfg, run, workers=1, progress=False)
    assert str(exc.value) == (f"survey.bands.f160w.psf: {psf} changed since the run started "
                              "(content differs); use another --out")
    assert file_snapshot(run) == before


def test_changed_image_matters_only_for_fields_with_results(small_survey_dict, tmp_path):
    image_dir = tmp_path / "images"
    image_dir.mkdir()
    src = load_config(write_yaml(small_survey_dict, tmp_path / "b.yaml")).survey.image_dir
    for f in ("f1", "f2"):
        link_field(src, "demo01", f, image_dir, copy=True)
    d = tiny_config(small_survey_dict, fields=("f1", "f2"))
    d["survey"]["image_dir"] = str(image_dir)
    cfg = load_dict(d, tmp_path / "c.yaml")
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
        simulate(load_dict(d, tmp_path / "c.yaml"), run, workers=1, progress=False)


# --------------------------------------------------------------------------
# Validate, then write
# --------------------------------------------------------------------------
def _psf_with_nan(src, dst):
    with fits.open(src) as hdul:
        data = hdul[0].data.astype(float)
        data[3, 3] = np.nan
        fits.writeto(dst, data, hdul[0].header)


def _hostile(kind, small_survey_dict, tmp_path):
    """A config dict with one bad input file; returns (dict, the bad file, expected key)."""
    d = tiny_config(small_survey_dict)
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
def test_bad_input_file_leaves_runs_untouched(kind, small_survey_dict, one_task_run, tmp_path):
    d, bad, key = _hostile(kind, small_survey_dict, tmp_path)
    cfg = load_dict(d, tmp_path / "c.yaml")
    shutil.copytree(one_task_run[1], tmp_path / "run")
    before = file_snapshot(tmp_path / "run")
    for out in (tmp_path / "run", tmp_path / "new"):
        with pytest.raises((InputError, ValueError)) as exc:
            simulate(cfg, out, workers=1, progress=False)
        msg = str(exc.value)
        assert msg.startswith(f"{key}: {bad}: ") and "\n" not in msg, msg
    assert file_snapshot(tmp_path / "run") == before
    assert not (tmp_path / "new").exists()


def test_bad_arguments_write_nothing(one_task_run, tmp_path):
    d, _ = one_task_run
    cfg = load_dict(d, tmp_path / "c.yaml")
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
