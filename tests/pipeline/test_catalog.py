"""``glaciar catalog`` (glaciar.pipeline.catalog) on a run.

A run's catalogue carries the run's identity; bad input is one line, exit 2, nothing written.
"""
from __future__ import annotations

import numpy as np
import pytest

from glaciar import constants as C


@pytest.mark.parametrize("suffix", [".parquet", ".ecsv", ".fits"])
def test_run_catalog_identity_round_trip(small_run, tmp_path, suffix):
    """A run's catalogue carries the run's identity (settings hash, input fingerprints,
    fields) through every format; check_identity accepts it for that run and refuses it for
    a run of other settings, in one line naming both."""
    import json
    import shutil

    from glaciar.pipeline.catalog import check_identity, read_catalog, run_catalog
    from glaciar.rundir import read_manifest

    cfg, run = small_run
    out = tmp_path / f"cat{suffix}"
    table = run_catalog(run, out)
    back, meta = read_catalog(out)
    assert len(back) == len(table) and meta["fields"] == list(cfg.survey.fields)
    np.testing.assert_array_equal(back[C.COL_SELECTED].to_numpy(bool), table[C.COL_SELECTED].to_numpy(bool))
    np.testing.assert_allclose(back[C.COL_X].to_numpy(), table[C.COL_X].to_numpy())
    manifest = read_manifest(run)
    check_identity(meta, manifest, out, run)                      # same run: accepted
    other = dict(manifest, store_hash="0" * 64)
    with pytest.raises(ValueError, match="measurement settings") as err:
        check_identity(meta, other, out, run)
    assert "\n" not in str(err.value)
    moved = dict(manifest, inputs={k: dict(v, blake2b="x") for k, v in manifest["inputs"].items()})
    with pytest.raises(ValueError, match="input files"):
        check_identity(meta, moved, out, run)
    with pytest.raises(ValueError, match="no glaciar identity"):
        check_identity({}, manifest, out, run)
    # the run's manifest is untouched by cataloguing it
    assert read_manifest(run) == manifest


def test_catalog_cli_errors(small_run, tmp_path, capsys):
    """Bad input: one line, exit 2, nothing written."""
    from glaciar.cli import main

    cfg, run = small_run
    assert main(["catalog", str(run), "--out", str(tmp_path / "c.txt")]) == 2
    assert "unknown extension" in capsys.readouterr().err
    assert main(["catalog", str(tmp_path / "nope")]) == 2
    assert "no such configuration file or run directory" in capsys.readouterr().err
    assert main(["catalog", str(run), "--out", str(tmp_path / "missing" / "c.parquet")]) == 2
    assert list(tmp_path.iterdir()) == []
    assert main(["catalog", str(run), "--out", str(tmp_path / "c.parquet"), "--regions", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "detections" in out and (tmp_path / "c.parquet").is_file() and (tmp_path / "c.reg").is_file()


def test_catalog_refuses_run_whose_inputs_changed(small_run, tmp_path):
    """A run whose images were overwritten since it ran: its selection function describes the
    old images, so cataloguing the new ones as that run is refused, naming the file."""
    import shutil

    import yaml
    from astropy.io import fits

    from glaciar.pipeline.catalog import run_catalog

    cfg, run = small_run
    src_dir = cfg.survey.image_dir
    img = tmp_path / "images"
    shutil.copytree(src_dir, img)
    copy = tmp_path / "run"
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns(C.LOCK_NAME, C.CONTEXT_DIRNAME))
    d = yaml.safe_load((copy / C.RUN_CONFIG_NAME).read_text())
    d["survey"]["image_dir"] = str(img)
    (copy / C.RUN_CONFIG_NAME).write_text(yaml.safe_dump(d, sort_keys=False))
    f = img / cfg.survey.science.format(field=cfg.survey.fields[0], band=cfg.survey.detection_band)
    with fits.open(f, mode="update") as h:
        h[0].data[5, 5] += 1.0
    with pytest.raises(ValueError, match="changed since the run"):
        run_catalog(copy, tmp_path / "c.parquet")
    assert not (tmp_path / "c.parquet").exists()
