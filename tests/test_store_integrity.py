"""Issue 21, bullets 6 and 7, below the CLI: safe file names, run sub-directories that are
links, full disks and corrupt pages.

Synthetic stores only (a few task files written with :func:`glaciar.store.write_task_table`,
no simulation); the full disk is simulated by making ``os.posix_fallocate`` fail with
``ENOSPC`` (benchmarks/full_disk.py does it on real tiny file systems).  ~2 s in all.
"""
import errno
import json
import os
import re
import shutil
import warnings

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from glaciar import constants as C
from glaciar.cli import main
from glaciar.config import load_config
from glaciar.engine import fieldcache
from glaciar.execute import simulate
from glaciar.paths import DiskFullError, UnsafePathError, file_stem, run_subdir
from glaciar.store import (StoreWarning, _read_task_file, compact, read_current_results,
                           read_results, task_filename, task_key, verified_task_names,
                           write_task_table)
from glaciar.taskfile import unit_problem
from glaciar.rundir import atomic_write_bytes
from glaciar.tables import summary_stem, write_summaries

from tiny_runs import (cli, kept, link_field, load_dict, one_error, run_rows, sorted_rows,
                       task_files, tiny_config, tree_bytes, write_yaml)


# --------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------
def _rows(field="f", z=8.0, mag=24.0, it=0, n=40, seed=0):
    rng = np.random.default_rng(seed)
    status = rng.choice(C.STATUS_CODES, size=n)
    rec = np.isin(status, C.RECOVERED_STATUSES)
    return pd.DataFrame({
        C.COL_FIELD: field, C.COL_Z: z, C.COL_MAG: mag, C.COL_ITERATION: it,
        C.COL_SOURCE: np.arange(n), C.COL_X: rng.uniform(0, 100, n),
        C.COL_Y: rng.uniform(0, 100, n), C.COL_MAG_INPUT: mag + rng.normal(0, 0.1, n),
        "flux_iso_f098m": rng.normal(1.0, 0.3, n), C.COL_STATUS: status,
        C.COL_RECOVERED: rec, C.COL_SELECTED: rec & (rng.uniform(size=n) < 0.5)})


def _store(run, n_tasks=3):
    """``n_tasks`` task files of field ``f`` (iterations 0..n-1); returns {name: key}, rows."""
    wanted, frames = {}, []
    for it in range(n_tasks):
        t = _rows(it=it, seed=it)
        name, key = task_filename("f", 8.0, 24.0, it), task_key("f", 8.0, 24.0, it)
        write_task_table(run, name, t, key=key, mag_column=C.COL_MAG_INPUT)
        wanted[name] = key
        frames.append(t)
    return wanted, pd.concat(frames, ignore_index=True)


def _chunks(path):
    """(start, length) of each column chunk's pages in a Parquet file."""
    md = pq.read_metadata(path)
    out = []
    for g in range(md.num_row_groups):
        for c in range(md.row_group(g).num_columns):
            col = md.row_group(g).column(c)
            start = col.dictionary_page_offset if col.has_dictionary_page else col.data_page_offset
            out.append((int(start), int(col.total_compressed_size)))
    return out


def _at(path) -> str:
    """``path`` as a regular expression matching itself."""
    return re.escape(str(path))


def _poke(path, at, junk=b"\xa5"):
    data = bytearray(path.read_bytes())
    data[at:at + len(junk)] = bytes(b ^ j for b, j in zip(data[at:at + len(junk)], junk))
    path.write_bytes(bytes(data))


# --------------------------------------------------------------------------
# One function from user strings to file names
# --------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["demo01", "shallow", "deep", "f160w", "borg_0240+1857",
                                  "all_logistic", "a-b.c"])
def test_ordinary_names_are_kept(name):
    assert file_stem(name) == name


HOSTILE_NAMES = ["../up", "../../etc", "sub/x", "a\\b", ".", "..", "", ".hidden", "a b", "a_b",
                 "a b~", "x" * 64, "x" * 65, "x" * 200, "é", "a\x00b", "all"]


def test_hostile_names_stay_in_their_directory_and_never_collide(tmp_path):
    stems = [summary_stem(n) for n in HOSTILE_NAMES] + ["all"]     # the pooled summary's stem
    assert len(set(stems)) == len(stems)
    for s in stems:
        assert "/" not in s and "\\" not in s and "\x00" not in s
        assert s not in ("", ".", "..") and not s.startswith(".")
        assert (tmp_path / f"summary_{s}.ecsv").resolve().parent == tmp_path.resolve()


def test_summaries_of_hostile_fields_are_written_inside_the_directory(tmp_path):
    rows = pd.concat([_rows(field=f, seed=i) for i, f in enumerate(["../up", "sub/x", "all"])])
    out = tmp_path / "run" / "summary"
    paths = write_summaries(rows, out)
    assert {p.parent for p in paths} == {out}
    assert sorted(os.listdir(tmp_path)) == ["run"] and sorted(os.listdir(tmp_path / "run")) == \
        ["summary"]
    assert len(paths) == 4 and len(set(paths)) == 4                  # 3 fields + pooled
    pooled = (out / "summary_all.ecsv").read_text()
    assert "field: all" in pooled and f"n_input: {len(rows)}" not in pooled  # metadata sanity
    from astropy.table import Table
    assert int(Table.read(out / "summary_all.ecsv")["n_input"].sum()) == len(rows)


def test_a_run_subdirectory_that_is_a_link_is_refused(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    run = tmp_path / "run"
    run.mkdir()
    (run / "results").symlink_to(outside)
    with pytest.raises(UnsafePathError, match=rf"^{_at(run / 'results')}: is a symbolic link"):
        write_task_table(run, task_filename("f", 8.0, 24.0, 0), _rows(), key=task_key(
            "f", 8.0, 24.0, 0))
    with pytest.raises(UnsafePathError, match="symbolic link"):
        write_summaries(_rows(), run / "results")
    assert list(outside.iterdir()) == []
    assert run_subdir(run, "fit") == run / "fit" and (run / "fit").is_dir()


def test_a_linked_partition_of_compacted_parts_is_refused(tmp_path):
    from glaciar.paths import check_run_tree

    _store(tmp_path)
    compact(tmp_path)
    field_dir = next((tmp_path / C.RESULTS_DIRNAME / "compact").iterdir())
    z_dir = next(field_dir.iterdir())
    outside = tmp_path.parent / (tmp_path.name + "_outside")
    z_dir.rename(outside)
    z_dir.symlink_to(outside, target_is_directory=True)
    with pytest.raises(UnsafePathError, match=rf"^{_at(z_dir)}: is a symbolic link"):
        check_run_tree(tmp_path)


# --------------------------------------------------------------------------
# Full disks: one line naming the file; mapped files allocated before they are mapped
# --------------------------------------------------------------------------
def test_atomic_write_on_a_full_disk_names_the_file_and_changes_nothing(tmp_path, monkeypatch,
                                                                        fallocate_enospc):
    p = tmp_path / "x.json"
    p.write_text("old")
    fallocate_enospc()
    with pytest.raises(DiskFullError) as err:
        atomic_write_bytes(p, b"new")
    msg = str(err.value)
    assert msg.startswith(f"{p}: no space left on device;") and "resumes" in msg
    assert "\n" not in msg and err.value.errno == errno.ENOSPC
    assert p.read_text() == "old" and sorted(os.listdir(tmp_path)) == ["x.json"]


def test_field_cache_is_allocated_before_it_is_mapped(tmp_path, monkeypatch, fallocate_enospc):
    """np.lib.format.open_memmap maps a sparse file: a full disk then kills with SIGBUS.
    The cache reserves its blocks first, so the full disk is an error naming the cache."""
    fallocate_enospc()
    target = tmp_path / ".context" / "abc"
    with pytest.raises(DiskFullError, match=rf"^{_at(target)}: no space left on device"):
        fieldcache.save({"image": np.ones((64, 64), np.float32)}, target)
    assert os.listdir(tmp_path / ".context") == []        # no half-written cache left
    # Scratch copies of a field being measured, too.
    with pytest.raises(DiskFullError, match="no space left on device"):
        fieldcache.spill(np.ones((8, 8), np.float32), directory=tmp_path)


# --------------------------------------------------------------------------
# Corrupt pages and footers: detected, set aside, named by readers
# --------------------------------------------------------------------------
def test_deterministic_in_page_corruptions_are_all_detected(tmp_path):
    """Garbage in the pages of one task file: simulate's check catches every case, and a
    reader either raises naming the file or returns the original values, never others."""
    wanted, rows = _store(tmp_path, n_tasks=1)
    f = tmp_path / C.RESULTS_DIRNAME / next(iter(wanted))
    clean = f.read_bytes()
    ref = _read_task_file(f, None)
    chunks = _chunks(f)
    cases = [s + k * L // 4 for s, L in chunks[::3] for k in (1, 2, 3)]    # 3 spots per chunk
    assert len(cases) >= 10
    for at in cases:
        f.write_bytes(clean)
        _poke(f, at, b"\x5a\xa5")
        assert unit_problem(f) is not None, at
        try:
            got = _read_task_file(f, None)
        except ValueError as exc:
            assert str(exc).startswith(f"{f}: unreadable task file"), at
        else:
            pd.testing.assert_frame_equal(got, ref)


def test_corrupt_task_file_is_set_aside_and_redone(tmp_path):
    wanted, _ = _store(tmp_path)
    names = sorted(wanted)
    f = tmp_path / C.RESULTS_DIRNAME / names[1]
    start, length = _chunks(f)[8]                    # flux_iso_f098m's pages
    _poke(f, start + length // 2)
    with pytest.raises(ValueError, match=rf"^{_at(f)}: unreadable task file .*glaciar simulate"):
        read_results(tmp_path)
    with pytest.warns(StoreWarning, match=rf"{_at(f)}: corrupt .*set aside as .*will be run"):
        good = verified_task_names(tmp_path, wanted, quarantine=True)
    assert good == set(names) - {names[1]}
    assert not f.exists()
    assert (tmp_path / C.RESULTS_DIRNAME / "corrupt" / names[1]).is_file()
    assert len(read_results(tmp_path)) == 2 * 40             # the reader no longer meets it


def test_garbled_footer_that_still_parses_is_caught(tmp_path):
    """A column renamed in the footer: pyarrow reads it happily (wrong column name, so the
    rows silently lose ``flux_iso_f098m``); the schema digest catches it."""
    wanted, _ = _store(tmp_path, n_tasks=1)
    f = tmp_path / C.RESULTS_DIRNAME / next(iter(wanted))
    data = f.read_bytes()
    f.write_bytes(data.replace(b"flux_iso_f098m", b"flux_iso_f099m"))
    assert "flux_iso_f099m" in pq.read_schema(f).names          # it parses
    assert "corrupt footer" in unit_problem(f)
    with pytest.raises(ValueError, match=rf"^{_at(f)}: unreadable task file \(corrupt footer"):
        read_results(tmp_path)
    with pytest.warns(StoreWarning, match="corrupt footer"):
        assert verified_task_names(tmp_path, wanted) == set()


def test_compaction_sets_corrupt_task_files_aside_and_parts_are_checked(tmp_path):
    wanted, rows = _store(tmp_path, n_tasks=4)
    names = sorted(wanted)
    bad = tmp_path / C.RESULTS_DIRNAME / names[0]
    start, length = _chunks(bad)[8]
    _poke(bad, start + length // 2)
    with pytest.warns(StoreWarning, match=rf"{_at(bad)}: corrupt .*set aside"):
        assert compact(tmp_path) == 3
    assert (tmp_path / C.RESULTS_DIRNAME / "corrupt" / names[0]).is_file()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert verified_task_names(tmp_path, wanted) == set(names[1:])
    got = read_results(tmp_path).sort_values([C.COL_ITERATION, C.COL_SOURCE])
    want = rows[rows[C.COL_ITERATION] > 0].sort_values([C.COL_ITERATION, C.COL_SOURCE])
    pd.testing.assert_frame_equal(got.reset_index(drop=True), want.reset_index(drop=True),
                                  check_dtype=False)
    part = next((tmp_path / C.RESULTS_DIRNAME / "compact").rglob("part-*.parquet"))
    assert pq.ParquetFile(part).metadata.row_group(0).num_columns > 0
    start, length = _chunks(part)[10]
    _poke(part, start + length // 3)
    with pytest.warns(StoreWarning, match=rf"{_at(part)}: corrupt .*set aside .*its tasks"):
        assert verified_task_names(tmp_path, wanted, quarantine=True) == set()
    assert not part.exists()


# ------------------------------------------------------------------------------
# Run-directory integrity under hostile use (issue 10): task identity, corrupt and foreign
# task files, the renamed flags column.  Every simulation is tiny (the ``small_survey``
# images, 1-6 tasks of 3-6 sources).
#
# Collision-free task identity
# ------------------------------------------------------------------------------
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


def test_fields_and_grid_values_that_used_to_collide_keep_their_rows(small_survey_dict, tmp_path):
    """'a b' / 'a_b' / 'par α' and z = 8.0 / 8.00004: every task its own file and rows."""
    image_dir = tmp_path / "images"
    image_dir.mkdir()
    fields = ("a b", "a_b", "par α")
    for f in fields:
        link_field(load_config(write_yaml(small_survey_dict, tmp_path / "b.yaml")).survey.image_dir,
                    "demo01", f, image_dir)
    d = tiny_config(small_survey_dict, fields=fields, z=(8.0, 8.00004), n_gal=3)
    d["survey"]["image_dir"] = str(image_dir)
    cfg = load_dict(d, tmp_path / "c.yaml")
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


def test_rows_no_longer_listed_are_excluded_by_report_and_fit_alike(small_survey_dict, tmp_path):
    from glaciar.pipeline.inputs import read_columns
    from glaciar.report import write_summary_files

    d = tiny_config(small_survey_dict, z=(8.0, 10.4), n_iter=2)
    run = tmp_path / "run"
    simulate(load_dict(d, tmp_path / "c.yaml"), run, workers=1, progress=False)
    assert len(read_results(run)) == 2 * 2 * 3
    # Drop z = 10.4 and the second iteration: the manifest describes the run as now configured.
    small = tiny_config(small_survey_dict, z=(8.0,), n_iter=1)
    assert simulate(load_dict(small, tmp_path / "s.yaml"), run, workers=1, progress=False)["n_run"] == 0
    with pytest.warns(StoreWarning, match=r"ignoring 9 rows of 3 task\(s\)"):
        rows = read_current_results(run)
    assert set(rows[C.COL_Z]) == {8.0} and set(rows[C.COL_ITERATION]) == {0} and len(rows) == 3
    with pytest.warns(StoreWarning):
        fit_rows = read_columns(run, [C.COL_FIELD, C.COL_Z, C.COL_MAG, C.COL_RECOVERED])
    pd.testing.assert_frame_equal(fit_rows, rows[fit_rows.columns.tolist()])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StoreWarning)
        write_summary_files(run)
    from astropy.table import Table
    t = Table.read(run / C.SUMMARY_DIRNAME / "summary_all.ecsv")
    assert list(t["z"]) == [8.0] and list(t["n_input"]) == [3]


# --------------------------------------------------------------------------
# Truncated or foreign task files are redone
# --------------------------------------------------------------------------
def test_truncated_and_foreign_task_files_are_redone(small_survey_dict, tmp_path):
    d = tiny_config(small_survey_dict, mag=(24.0, 27.5), n_iter=2)
    cfg = load_dict(d, tmp_path / "c.yaml")
    run = tmp_path / "run"
    simulate(cfg, run, workers=1, progress=False)
    ref = sorted_rows(read_results(run))
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
    pd.testing.assert_frame_equal(sorted_rows(read_results(run)), ref)


def test_unreadable_task_file_is_named_when_reading(run_copy):
    _, run = run_copy
    f = next((run / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    f.write_bytes(f.read_bytes()[:100])
    with pytest.raises(ValueError, match=re.escape(f"{f}: unreadable task file")):
        read_current_results(run)


# --------------------------------------------------------------------------
# The flags column no longer shadows DataFrame.flags
# --------------------------------------------------------------------------
def test_flags_column_is_renamed(one_task_run):
    from glaciar.config import selection_columns

    _, run = one_task_run
    rows = read_results(run)
    assert C.COL_FLAGS in rows.columns and "flags" not in rows.columns
    assert isinstance(rows.flags, pd.Flags)                 # attribute access is pandas' own
    assert rows[C.COL_FLAGS].dtype.kind == "i"
    assert C.COL_FLAGS in selection_columns(["f160w"], 1) and "flags" not in selection_columns(["f160w"], 1)


# ------------------------------------------------------------------------------
# Hostile cases of issue 21, bullets 6 and 7, through the command line: nothing written
# outside the run directory (linked sub-directories, field names holding paths), full disks
# and corrupt task files.
#
# Every case runs ``glaciar.cli.main`` in this process (so that ``os.posix_fallocate`` can be
# made to fail with ENOSPC, and the field's measurement is shared between cases) on a copy of
# one 2-task run of the small survey (3 sources per task), or on a synthetic store, and
# asserts: the exit status (2 for a refusal, 0 where the documented behaviour is to go on),
# one line on stderr for a refusal (naming the path), nothing outside the run directory
# touched, and nothing already written lost or changed (a corrupt file set aside is kept,
# byte for byte, in ``results/corrupt/``).  ~15 s in all.
#
# 6. Linked sub-directories of a run are refused, naming the link
# ------------------------------------------------------------------------------
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
def test_linked_subdirectory_is_refused(sub, command, store_run, two_task_run, capsys):
    cfg_path, _ = two_task_run
    outside = store_run.parent / "outside"
    link = store_run / sub
    if link.exists():                       # its content moves outside, behind the link
        shutil.move(str(link), str(outside / "moved"))
        target = outside / "moved"
    else:
        target = outside
    link.parent.mkdir(parents=True, exist_ok=True)
    link.symlink_to(target, target_is_directory=True)
    before_run, before_out = tree_bytes(store_run), tree_bytes(outside)
    words = command.split()
    argv = ([words[0], cfg_path, "--out", store_run, "--workers", 1, "--quiet"] if words[0] ==
            "simulate" else [words[0], store_run, *words[1:]] + (["--quiet"] if words[0] == "fit"
                                                            else []))
    code, lines = cli(capsys, *argv)
    assert code == 2
    one_error(lines, words[0], rf"{re.escape(str(link))}: is a symbolic link")
    assert tree_bytes(outside) == before_out
    kept(before_run, tree_bytes(store_run))


def test_linked_lock_file_is_refused(store_run, two_task_run, capsys):
    cfg_path, _ = two_task_run
    keep = store_run.parent / "outside" / "keep.txt"
    (store_run / C.LOCK_NAME).symlink_to(keep)
    before_run = tree_bytes(store_run)
    code, lines = cli(capsys, "simulate", cfg_path, "--out", store_run, "--workers", 1, "--quiet")
    assert code == 2
    one_error(lines, "simulate", rf"{re.escape(str(store_run / C.LOCK_NAME))}: is a symbolic link")
    assert keep.read_text() == "not glaciar's\n"          # no pid written through the link
    kept(before_run, tree_bytes(store_run))


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

    top, store_run, code, before, after = hostile_report
    assert code == 0
    # The run's own lock (report holds it while it reads) is the one file beside summary/.
    made = set(after) - set(before) - {str((store_run / C.LOCK_NAME).relative_to(top))}
    summary = str((store_run / C.SUMMARY_DIRNAME).relative_to(top))
    assert made and all(m == summary or os.path.dirname(m) == summary for m in made)
    stem = summary_stem(field)
    t = Table.read(store_run / C.SUMMARY_DIRNAME / f"summary_{stem}.ecsv")
    assert t.meta["field"] == field and int(t["n_input"].sum()) == 12
    for kind in ("completeness", "selection_total", "selection"):
        assert (store_run / C.SUMMARY_DIRNAME / f"{kind}_{stem}.png").is_file()
    pooled = Table.read(store_run / C.SUMMARY_DIRNAME / "summary_all.ecsv")
    assert pooled.meta["field"] == "all" and int(pooled["n_input"].sum()) == 12 * len(
        HOSTILE_FIELDS)


# --------------------------------------------------------------------------
# 7. Full disks: one line naming the file; the same command resumes
# --------------------------------------------------------------------------
def test_full_disk_while_writing_a_task(store_run, two_task_run, capsys, monkeypatch,
                                        fallocate_enospc):
    cfg_path, _ = two_task_run
    ref = run_rows(store_run)
    gone = task_files(store_run)[1]
    gone.unlink()
    before_run = tree_bytes(store_run)
    fallocate_enospc(where=f"/{C.RESULTS_DIRNAME}/")
    code, lines = cli(capsys, "simulate", cfg_path, "--out", store_run, "--workers", 1, "--quiet")
    assert code == 2
    one_error(lines, "simulate", rf"{re.escape(str(gone))}: no space left on device; free "
                                  r"some space and run the same command again: .*resumes")
    kept(before_run, tree_bytes(store_run))
    assert not list((store_run / C.RESULTS_DIRNAME).glob(".*.tmp"))           # nothing half-written
    monkeypatch.undo()
    code, _ = cli(capsys, "simulate", cfg_path, "--out", store_run, "--workers", 1, "--quiet")
    assert code == 0
    pd.testing.assert_frame_equal(run_rows(store_run), ref)


def test_full_disk_before_anything_is_written(two_task_run, tmp_path, capsys, monkeypatch,
                                              fallocate_enospc):
    cfg_path, _ = two_task_run
    out = tmp_path / "new_run"
    fallocate_enospc()
    code, lines = cli(capsys, "simulate", cfg_path, "--out", out, "--workers", 1, "--quiet")
    assert code == 2
    one_error(lines, "simulate", rf"{re.escape(str(out / C.MANIFEST_NAME))}: no space left")
    assert sorted(os.listdir(tmp_path)) == ["new_run"]
    assert set(os.listdir(out)) <= {C.LOCK_NAME}


def test_full_disk_while_reporting(store_run, capsys, monkeypatch, fallocate_enospc):
    before_run = tree_bytes(store_run)
    fallocate_enospc()
    code, lines = cli(capsys, "report", store_run)
    assert code == 2
    summary = re.escape(str(store_run / C.SUMMARY_DIRNAME))
    one_error(lines, "report", rf"{summary}/\S+: no space left")
    kept(before_run, tree_bytes(store_run))


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
def test_readers_name_the_corrupt_file(kind, command, store_run, capsys):
    f = task_files(store_run)[1]
    CORRUPTIONS[kind](f)
    before_run = tree_bytes(store_run)
    words = command.split()
    code, lines = cli(capsys, words[0], store_run, *words[1:], *(["--quiet"] if words[0] == "fit"
                                                             else []))
    assert code == 2
    errors = [ln for ln in lines if not ln.startswith("warning:")]
    assert len(errors) == 1, lines
    one_error(errors, words[0], rf"{re.escape(str(f))}: unreadable task file \(.*\); `glaciar "
                                 r"simulate` into this run directory sets it aside")
    kept(before_run, tree_bytes(store_run))


@pytest.mark.parametrize("kind", sorted(CORRUPTIONS))
def test_simulate_sets_the_corrupt_file_aside_and_redoes_it(kind, store_run, two_task_run, capsys):
    """The advice readers give holds: simulate detects what they detect (it used to count a
    task with a garbled footer as done while readers told the user to run simulate)."""
    cfg_path, _ = two_task_run
    ref = run_rows(store_run)
    f = task_files(store_run)[1]
    CORRUPTIONS[kind](f)
    bad = f.read_bytes()
    code, lines = cli(capsys, "simulate", cfg_path, "--out", store_run, "--workers", 1, "--quiet")
    assert code == 0
    aside = store_run / C.RESULTS_DIRNAME / "corrupt" / f.name
    warned = [ln for ln in lines if ln.startswith(f"warning: {f}: ")]
    assert len(warned) == 1 and f"set aside as {aside}; the task will be run again" in warned[0]
    assert aside.read_bytes() == bad                  # kept, byte for byte, inside the run
    pd.testing.assert_frame_equal(run_rows(store_run), ref)   # every page read, checksums verified


def test_garbled_counts_are_read_from_the_rows(store_run, capsys):
    """Documented: counts whose digest fails are replaced by the rows' (a warning names it)."""
    import pyarrow.parquet as pq

    assert main(["report", str(store_run)]) == 0
    capsys.readouterr()
    f = task_files(store_run)[0]
    value = pq.read_metadata(f).metadata[b"glaciar.counts"]
    data = f.read_bytes()
    at = data.index(value) + len(value) // 2
    f.write_bytes(data[:at] + bytes([data[at] ^ 0x01]) + data[at + 1:])
    ref = (store_run / C.SUMMARY_DIRNAME / "summary_all.ecsv").read_text()
    code, lines = cli(capsys, "report", store_run)
    assert code == 0
    assert len(lines) == 1 and lines[0].startswith(f"warning: {f}: unreadable glaciar.counts "
                                                   "metadata (digest mismatch)")
    assert (store_run / C.SUMMARY_DIRNAME / "summary_all.ecsv").read_text() == ref
