"""A store made before a detection key existed stays extendable while the key is at its default."""
import json
import shutil

import pytest
import yaml

from glaciar import constants as C
from glaciar.config import load_config
from glaciar.run import simulate
from glaciar.store import StoreMismatchError


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
