"""Hostile cases of issue 21, bullets 6 and 7, through the command line: nothing written
outside the run directory (linked sub-directories, field names holding paths), full disks
and corrupt task files.

Every case runs ``glaciar.cli.main`` in this process (so that ``os.posix_fallocate`` can be
made to fail with ENOSPC, and the field's measurement is shared between cases) on a copy of
one 2-task run of the small survey (3 sources per task), or on a synthetic store, and
asserts: the exit status (2 for a refusal, 0 where the documented behaviour is to go on),
one line on stderr for a refusal (naming the path), nothing outside the run directory
touched, and nothing already written lost or changed (a corrupt file set aside is kept,
byte for byte, in ``results/corrupt/``).  ~15 s in all.
"""
import errno
import json
import os
import re
import shutil

import numpy as np
import pandas as pd
import pytest
import yaml

from glaciar import constants as C
from glaciar.cli import main
from glaciar.config import load_config
from glaciar.execute import simulate
from glaciar.store import read_results, task_filename, task_key, write_task_table

#: Files a command may rewrite in place without changing what a run holds.
_VOLATILE = {C.LOCK_NAME, C.FINGERPRINT_CACHE_NAME}
_KEYS = [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_ITERATION, C.COL_SOURCE]


# --------------------------------------------------------------------------
# Fixtures and helpers
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def two_task_run(small_survey, tmp_path_factory):
    """The small survey's field, z = 8, m = 24 and 27.5, 1 iteration of 3 sources:
    (config path, finished run directory)."""
    d = yaml.safe_load(small_survey.read_text())
    base = small_survey.parent
    d["survey"]["image_dir"] = str(base / d["survey"]["image_dir"])
    for b in d["survey"]["bands"].values():
        b["psf"] = str(base / b["psf"])
    d["grid"] = {"z": {"values": [8.0]}, "mag": {"values": [24.0, 27.5]},
                 "magnitude_type": "apparent"}
    d["simulation"] = {"n_galaxies": 3, "n_iterations": 1, "seed": 11}
    root = tmp_path_factory.mktemp("hostile_store")
    cfg_path = root / "c.yaml"
    cfg_path.write_text(yaml.safe_dump(d, sort_keys=False))
    simulate(load_config(cfg_path), root / "run", workers=1, progress=False)
    return cfg_path, root / "run"


@pytest.fixture
def run(two_task_run, tmp_path):
    """A copy of the 2-task run in ``tmp_path/run``, beside ``tmp_path/outside`` (one file)."""
    _, src = two_task_run
    dst = tmp_path / "run"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(C.LOCK_NAME))
    (tmp_path / "outside").mkdir()
    (tmp_path / "outside" / "keep.txt").write_text("not glaciar's\n")
    return dst


def _snapshot(root):
    """{relative path: bytes} of every file below ``root`` (links not followed)."""
    out = {}
    for dirpath, _dirs, files in os.walk(root):
        for f in files:
            p = os.path.join(dirpath, f)
            if not os.path.islink(p):
                out[os.path.relpath(p, root)] = open(p, "rb").read()
    return out


def _cli(capsys, *argv):
    """``main(argv)``: (exit status, stderr lines)."""
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    return code, [ln for ln in err.splitlines() if ln.strip()]


def _kept(before, after):
    """Every file of ``before`` is in ``after`` unchanged (volatile files aside)."""
    for rel, data in before.items():
        if os.path.basename(rel) in _VOLATILE:
            continue
        assert after.get(rel) == data, rel


def _one_error(lines, command, pattern):
    assert len(lines) == 1, lines
    assert re.match(rf"glaciar {command}: error: {pattern}", lines[0]), lines[0]


def _rows(run):
    return read_results(run).sort_values(_KEYS).reset_index(drop=True)


def _task_files(run):
    return sorted((run / C.RESULTS_DIRNAME).glob("task_*.parquet"))




# --------------------------------------------------------------------------
# 6. Linked sub-directories of a run are refused, naming the link
# --------------------------------------------------------------------------
LINKED = [  # (sub-directory of the run, command)
    ("results", "simulate"),
    (".context", "simulate"),
    ("results/compact", "simulate"),
    ("results/corrupt", "simulate"),
    ("summary", "simulate"),
    ("summary", "report"),
    ("summary/regions", "report --regions"),
    ("fit", "fit"),
]


@pytest.mark.parametrize("sub, command", LINKED, ids=[f"{s}-{c}" for s, c in LINKED])
def test_linked_subdirectory_is_refused(sub, command, run, two_task_run, capsys):
    cfg_path, _ = two_task_run
    outside = run.parent / "outside"
    link = run / sub
    if link.exists():                       # its content moves outside, behind the link
        shutil.move(str(link), str(outside / "moved"))
        target = outside / "moved"
    else:
        target = outside
    link.parent.mkdir(parents=True, exist_ok=True)
    link.symlink_to(target, target_is_directory=True)
    before_run, before_out = _snapshot(run), _snapshot(outside)
    words = command.split()
    argv = ([words[0], cfg_path, "--out", run, "--workers", 1, "--quiet"] if words[0] ==
            "simulate" else [words[0], run, *words[1:]] + (["--quiet"] if words[0] == "fit"
                                                            else []))
    code, lines = _cli(capsys, *argv)
    assert code == 2
    _one_error(lines, words[0], rf"{re.escape(str(link))}: is a symbolic link")
    assert _snapshot(outside) == before_out
    _kept(before_run, _snapshot(run))


def test_linked_lock_file_is_refused(run, two_task_run, capsys):
    cfg_path, _ = two_task_run
    keep = run.parent / "outside" / "keep.txt"
    (run / C.LOCK_NAME).symlink_to(keep)
    before_run = _snapshot(run)
    code, lines = _cli(capsys, "simulate", cfg_path, "--out", run, "--workers", 1, "--quiet")
    assert code == 2
    _one_error(lines, "simulate", rf"{re.escape(str(run / C.LOCK_NAME))}: is a symbolic link")
    assert keep.read_text() == "not glaciar's\n"          # no pid written through the link
    _kept(before_run, _snapshot(run))


# --------------------------------------------------------------------------
# 6. Field names holding paths: report writes inside summary/, one file per field
# --------------------------------------------------------------------------
HOSTILE_FIELDS = ["../../up", "sub/x", "all", ".."]


@pytest.fixture(scope="module")
def hostile_report(tmp_path_factory):
    """A synthetic store whose fields are :data:`HOSTILE_FIELDS`, reported by ``glaciar
    report``: (root, run, exit status, stderr, files below root before, after)."""
    root = tmp_path_factory.mktemp("hostile_names") / "deep" / "er"
    run = root / "run"
    rng = np.random.default_rng(1)
    for f in HOSTILE_FIELDS:
        for mag in (24.0, 26.0):
            n = 6
            status = rng.choice(C.STATUS_CODES, size=n)
            rec = np.isin(status, C.RECOVERED_STATUSES)
            t = pd.DataFrame({C.COL_FIELD: f, C.COL_Z: 8.0, C.COL_MAG: mag, C.COL_ITERATION: 0,
                              C.COL_SOURCE: np.arange(n), C.COL_MAG_INPUT: mag,
                              C.COL_STATUS: status, C.COL_RECOVERED: rec,
                              C.COL_SELECTED: rec & (rng.uniform(size=n) < 0.5)})
            write_task_table(run, task_filename(f, 8.0, mag, 0), t,
                             key=task_key(f, 8.0, mag, 0), mag_column=C.COL_MAG_INPUT)
    (run / C.MANIFEST_NAME).write_text(json.dumps({"fields": HOSTILE_FIELDS}))
    top = root.parent.parent
    before = sorted(str(p.relative_to(top)) for p in top.rglob("*"))
    code = main(["report", str(run)])
    after = sorted(str(p.relative_to(top)) for p in top.rglob("*"))
    return top, run, code, before, after


@pytest.mark.parametrize("field", HOSTILE_FIELDS)
def test_field_names_holding_paths_stay_in_the_summary_directory(field, hostile_report):
    from astropy.table import Table

    from glaciar.tables import summary_stem

    top, run, code, before, after = hostile_report
    assert code == 0
    # The run's own lock (report holds it while it reads) is the one file beside summary/.
    made = set(after) - set(before) - {str((run / C.LOCK_NAME).relative_to(top))}
    summary = str((run / C.SUMMARY_DIRNAME).relative_to(top))
    assert made and all(m == summary or os.path.dirname(m) == summary for m in made)
    stem = summary_stem(field)
    t = Table.read(run / C.SUMMARY_DIRNAME / f"summary_{stem}.ecsv")
    assert t.meta["field"] == field and int(t["n_input"].sum()) == 12
    for kind in ("completeness", "selection_total", "selection"):
        assert (run / C.SUMMARY_DIRNAME / f"{kind}_{stem}.png").is_file()
    pooled = Table.read(run / C.SUMMARY_DIRNAME / "summary_all.ecsv")
    assert pooled.meta["field"] == "all" and int(pooled["n_input"].sum()) == 12 * len(
        HOSTILE_FIELDS)


# --------------------------------------------------------------------------
# 7. Full disks: one line naming the file; the same command resumes
# --------------------------------------------------------------------------
def test_full_disk_while_writing_a_task(run, two_task_run, capsys, monkeypatch, fallocate_enospc):
    cfg_path, _ = two_task_run
    ref = _rows(run)
    gone = _task_files(run)[1]
    gone.unlink()
    before_run = _snapshot(run)
    fallocate_enospc(where=f"/{C.RESULTS_DIRNAME}/")
    code, lines = _cli(capsys, "simulate", cfg_path, "--out", run, "--workers", 1, "--quiet")
    assert code == 2
    _one_error(lines, "simulate", rf"{re.escape(str(gone))}: no space left on device; free "
                                  r"some space and run the same command again: .*resumes")
    _kept(before_run, _snapshot(run))
    assert not list((run / C.RESULTS_DIRNAME).glob(".*.tmp"))           # nothing half-written
    monkeypatch.undo()
    code, _ = _cli(capsys, "simulate", cfg_path, "--out", run, "--workers", 1, "--quiet")
    assert code == 0
    pd.testing.assert_frame_equal(_rows(run), ref)


def test_full_disk_before_anything_is_written(two_task_run, tmp_path, capsys, monkeypatch,
                                              fallocate_enospc):
    cfg_path, _ = two_task_run
    out = tmp_path / "new_run"
    fallocate_enospc()
    code, lines = _cli(capsys, "simulate", cfg_path, "--out", out, "--workers", 1, "--quiet")
    assert code == 2
    _one_error(lines, "simulate", rf"{re.escape(str(out / C.MANIFEST_NAME))}: no space left")
    assert sorted(os.listdir(tmp_path)) == ["new_run"]
    assert set(os.listdir(out)) <= {C.LOCK_NAME}


def test_full_disk_while_reporting(run, capsys, monkeypatch, fallocate_enospc):
    before_run = _snapshot(run)
    fallocate_enospc()
    code, lines = _cli(capsys, "report", run)
    assert code == 2
    _one_error(lines, "report", rf"{re.escape(str(run / C.SUMMARY_DIRNAME))}/\S+: no space left")
    _kept(before_run, _snapshot(run))


def test_field_cache_on_a_full_disk_warns_and_the_run_goes_on(run, two_task_run, capsys,
                                                              monkeypatch, fallocate_enospc):
    """Documented: the field's arrays stay in memory (one warning naming the cache)."""
    cfg_path, _ = two_task_run
    ref = _rows(run)
    _task_files(run)[0].unlink()
    fallocate_enospc(where=f"/{C.CONTEXT_DIRNAME}/")
    code, lines = _cli(capsys, "simulate", cfg_path, "--out", run, "--workers", 1, "--quiet")
    assert code == 0
    warned = [ln for ln in lines if "field cache not written" in ln]
    assert len(warned) == 1 and re.match(rf"warning: {re.escape(str(run / C.CONTEXT_DIRNAME))}/"
                                         r"\w+: field cache not written \(No space", warned[0])
    pd.testing.assert_frame_equal(_rows(run), ref)
    assert not (run / C.CONTEXT_DIRNAME).exists() or not list(
        (run / C.CONTEXT_DIRNAME).iterdir())


# --------------------------------------------------------------------------
# 7. Corrupt task files: named by readers, set aside and redone by simulate (no loop)
# --------------------------------------------------------------------------
def _in_pages(f):
    """One byte of the pages of column ``x`` (read by ``report --regions``) flipped."""
    import pyarrow.parquet as pq

    md = pq.read_metadata(f)
    col = md.row_group(0).column(md.schema.to_arrow_schema().names.index(C.COL_X))
    start = col.dictionary_page_offset if col.has_dictionary_page else col.data_page_offset
    data = bytearray(f.read_bytes())
    at = int(start) + int(col.total_compressed_size) // 2
    data[at] ^= 0xFF
    f.write_bytes(bytes(data))


def _renamed_column(f):
    import pyarrow.parquet as pq

    name = pq.read_schema(f).names[12].encode()
    f.write_bytes(f.read_bytes().replace(name, name[:-1] + (b"X" if name[-1:] != b"X" else b"Y")))


def _garbled_footer(f):
    data = bytearray(f.read_bytes())
    n = int.from_bytes(data[-8:-4], "little")
    start = len(data) - 8 - n
    data[start:start + 24] = b"\xff" * 24
    f.write_bytes(bytes(data))


CORRUPTIONS = {"data page": _in_pages, "renamed column": _renamed_column,
               "garbled footer": _garbled_footer}
READERS = [("data page", "report --regions"), ("renamed column", "report --regions"),
           ("garbled footer", "report"), ("garbled footer", "fit")]


@pytest.mark.parametrize("kind, command", READERS, ids=[f"{k}-{c}" for k, c in READERS])
def test_readers_name_the_corrupt_file(kind, command, run, capsys):
    f = _task_files(run)[1]
    CORRUPTIONS[kind](f)
    before_run = _snapshot(run)
    words = command.split()
    code, lines = _cli(capsys, words[0], run, *words[1:], *(["--quiet"] if words[0] == "fit"
                                                             else []))
    assert code == 2
    errors = [ln for ln in lines if not ln.startswith("warning:")]
    assert len(errors) == 1, lines
    _one_error(errors, words[0], rf"{re.escape(str(f))}: unreadable task file \(.*\); `glaciar "
                                 r"simulate` into this run directory sets it aside")
    _kept(before_run, _snapshot(run))


@pytest.mark.parametrize("kind", sorted(CORRUPTIONS))
def test_simulate_sets_the_corrupt_file_aside_and_redoes_it(kind, run, two_task_run, capsys):
    """The advice readers give holds: simulate detects what they detect (it used to count a
    task with a garbled footer as done while readers told the user to run simulate)."""
    cfg_path, _ = two_task_run
    ref = _rows(run)
    f = _task_files(run)[1]
    CORRUPTIONS[kind](f)
    bad = f.read_bytes()
    code, lines = _cli(capsys, "simulate", cfg_path, "--out", run, "--workers", 1, "--quiet")
    assert code == 0
    aside = run / C.RESULTS_DIRNAME / "corrupt" / f.name
    warned = [ln for ln in lines if ln.startswith(f"warning: {f}: ")]
    assert len(warned) == 1 and f"set aside as {aside}; the task will be run again" in warned[0]
    assert aside.read_bytes() == bad                  # kept, byte for byte, inside the run
    pd.testing.assert_frame_equal(_rows(run), ref)   # every page read, checksums verified


def test_garbled_counts_are_read_from_the_rows(run, capsys):
    """Documented: counts whose digest fails are replaced by the rows' (a warning names it)."""
    import pyarrow.parquet as pq

    assert main(["report", str(run)]) == 0
    capsys.readouterr()
    f = _task_files(run)[0]
    value = pq.read_metadata(f).metadata[b"glaciar.counts"]
    data = f.read_bytes()
    at = data.index(value) + len(value) // 2
    f.write_bytes(data[:at] + bytes([data[at] ^ 0x01]) + data[at + 1:])
    ref = (run / C.SUMMARY_DIRNAME / "summary_all.ecsv").read_text()
    code, lines = _cli(capsys, "report", run)
    assert code == 0
    assert len(lines) == 1 and lines[0].startswith(f"warning: {f}: unreadable glaciar.counts "
                                                   "metadata (digest mismatch)")
    assert (run / C.SUMMARY_DIRNAME / "summary_all.ecsv").read_text() == ref


def test_truncated_field_cache_is_measured_again(run, two_task_run, capsys):
    """An interrupted run's field cache with a truncated array file: the resume warns,
    naming the cache, measures the field again and gives the same rows."""
    cfg_path, _ = two_task_run
    ref = _rows(run)
    for f in _task_files(run):
        f.unlink()
    # An unfinished run keeps its field caches (1 of its 2 tasks run).
    simulate(load_config(cfg_path), run, workers=1, progress=False, max_tasks=1)
    cache = next((run / C.CONTEXT_DIRNAME).iterdir())
    npy = max(cache.glob("*.npy"), key=lambda p: p.stat().st_size)
    with open(npy, "r+b") as fh:
        fh.truncate(npy.stat().st_size // 2)
    from glaciar.contexts import clear_contexts
    clear_contexts()             # as a new process: the cache is opened from disk
    code, lines = _cli(capsys, "simulate", cfg_path, "--out", run, "--workers", 1, "--quiet")
    assert code == 0
    assert len(lines) == 1 and re.match(rf"warning: {re.escape(str(cache))}: unreadable field "
                                        r"cache \(.*\); the field is measured again", lines[0])
    pd.testing.assert_frame_equal(_rows(run), ref)
