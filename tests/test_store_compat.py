"""A store made before a detection key existed stays extendable while the key is at its default."""
import json
import shutil

import pytest
import yaml

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.execute import simulate
from glaciar.rundir import StoreMismatchError


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
