"""Tiny runs of the session's small survey, for the run-directory tests.

Configurations as dicts (absolute paths, so that copies can live anywhere), written and
loaded; snapshots of a directory's files; the rows of a run in a stable order.
"""
import json
import os
import re
import shutil

import yaml

from glaciar import constants as C
from glaciar.cli import main
from glaciar.config import load_config
from glaciar.store import read_results


def absolute_config(small_survey):
    """The small survey's config with absolute paths, so that copies can live anywhere."""
    d = yaml.safe_load(small_survey.read_text())
    root = small_survey.parent
    d["survey"]["image_dir"] = str(root / d["survey"]["image_dir"])
    for b in d["survey"]["bands"].values():
        b["psf"] = str(root / b["psf"])
    return d


def tiny_config(d, *, fields=None, z=(8.0,), mag=(24.0,), n_iter=1, n_gal=3, seed=11):
    d = json.loads(json.dumps(d))
    if fields is not None:
        d["survey"]["fields"] = list(fields)
    d["grid"] = {"z": {"values": list(z)}, "mag": {"values": list(mag)},
                 "magnitude_type": "apparent"}
    d["simulation"] = {"n_galaxies": n_gal, "n_iterations": n_iter, "seed": seed}
    return d


def write_yaml(d, path):
    path.write_text(yaml.safe_dump(d, sort_keys=False, allow_unicode=True), encoding="utf-8")
    return path


def load_dict(d, path):
    return load_config(write_yaml(d, path))


def file_snapshot(root):
    """{relative path: (bytes, mode)} of every file below ``root`` (hidden ones included)."""
    out = {}
    for dirpath, _dirs, files in os.walk(root):
        for f in files:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, root)] = (open(p, "rb").read(), os.stat(p).st_mode)
    return out


def sorted_rows(df):
    keys = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]
    return df.sort_values(keys).reset_index(drop=True)


def link_field(image_dir, src_field, new_field, dst_dir, copy=False):
    """Images of ``new_field`` in ``dst_dir``: links (or copies) of ``src_field``'s files."""
    for p in image_dir.glob(f"{src_field}_*.fits"):
        q = dst_dir / p.name.replace(src_field, new_field, 1)
        if copy:
            shutil.copyfile(p, q)
        else:
            q.symlink_to(p)


#: Files a command may rewrite in place without changing what a run holds.
VOLATILE_FILES = {C.LOCK_NAME, C.FINGERPRINT_CACHE_NAME}
TASK_KEYS = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]


# --------------------------------------------------------------------------
# Fixtures and helpers
# --------------------------------------------------------------------------


def tree_bytes(root):
    """{relative path: bytes} of every file below ``root`` (links not followed)."""
    out = {}
    for dirpath, _dirs, files in os.walk(root):
        for f in files:
            p = os.path.join(dirpath, f)
            if not os.path.islink(p):
                out[os.path.relpath(p, root)] = open(p, "rb").read()
    return out


def cli(capsys, *argv):
    """``main(argv)``: (exit status, stderr lines)."""
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    return code, [ln for ln in err.splitlines() if ln.strip()]


def kept(before, after):
    """Every file of ``before`` is in ``after`` unchanged (volatile files aside)."""
    for rel, data in before.items():
        if os.path.basename(rel) in VOLATILE_FILES:
            continue
        assert after.get(rel) == data, rel


def one_error(lines, command, pattern):
    assert len(lines) == 1, lines
    assert re.match(rf"glaciar {command}: error: {pattern}", lines[0]), lines[0]


def run_rows(run):
    return read_results(run).sort_values(TASK_KEYS).reset_index(drop=True)


def task_files(run):
    return sorted((run / C.RESULTS_DIRNAME).glob("task_*.parquet"))
