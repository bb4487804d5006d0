"""Issue 21, bullets 6 and 7, below the CLI: safe file names, run sub-directories that are
links, full disks and corrupt pages.

Synthetic stores only (a few task files written with :func:`glaciar.store.write_task_table`,
no simulation); the full disk is simulated by making ``os.posix_fallocate`` fail with
``ENOSPC`` (benchmarks/full_disk.py does it on real tiny file systems).  ~2 s in all.
"""
import errno
import os
import re
import shutil
import warnings

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from glaciar import constants as C
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

from tiny_runs import link_field, load_dict, sorted_rows, tiny_config, write_yaml


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
    from glaciar.cli import _report
    from glaciar.pipeline.inputs import read_columns

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
        _report(run)
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
