"""Tiny runs of the session's small survey, for the run-directory tests.

Configurations as dicts (absolute paths, so that copies can live anywhere), written and
loaded; snapshots of a directory's files; the rows of a run in a stable order.
"""
import json
import os
import shutil

import yaml

from glaciar import constants as C
from glaciar.config import load_config


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
