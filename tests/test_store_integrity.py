"""Issue 21, bullets 6 and 7, below the CLI: safe file names, run sub-directories that are
links, full disks and corrupt pages.

Synthetic stores only (a few task files written with :func:`glaciar.store.write_task_table`,
no simulation); the full disk is simulated by making ``os.posix_fallocate`` fail with
``ENOSPC`` (benchmarks/full_disk.py does it on real tiny file systems).  ~2 s in all.
"""
import errno
import os
import re
import warnings

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from glaciar import constants as C
from glaciar.engine import fieldcache
from glaciar.paths import DiskFullError, UnsafePathError, file_stem, run_subdir
from glaciar.store import (StoreWarning, _read_task_file, compact, read_results, task_filename,
                           task_key, verified_task_names, write_task_table)
from glaciar.taskfile import unit_problem
from glaciar.rundir import atomic_write_bytes
from glaciar.tables import summary_stem, write_summaries


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
# 6. One function from user strings to file names
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
# 7. Full disks: one line naming the file; mapped files allocated before they are mapped
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
# 7. Corrupt pages and footers: detected, set aside, named by readers
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
