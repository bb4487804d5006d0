"""A task file is encoded once (issue 24): same rows, same footer tables, same checks.

The digest of the pages (every byte before the footer) used to need a second Parquet
encode; now the writer's own pages are hashed before it writes its footer.  Files of
the older two-encode writer must still read and pass every check.
"""
from __future__ import annotations

import hashlib
import io

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from glaciar import constants as C
from glaciar.store import read_results, write_task_table
from glaciar.taskfile import arrow_table, ipc_bytes, ipc_table, task_file_problem, unit_problem

PAGES_KEY = b"glaciar.pages.blake2b"


@pytest.fixture(scope="module")
def task_rows(one_task_run):
    """The rows of the one-task run's task file and its footer metadata."""
    _, run = one_task_run
    path = next((run / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    return pd.read_parquet(path), pq.read_metadata(path).metadata


def _footer_start(data: bytes) -> int:
    return len(data) - 8 - int.from_bytes(data[-8:-4], "little")


def _write(tmp_path, rows, meta, name="task_a.parquet"):
    (tmp_path / C.RESULTS_DIRNAME).mkdir(exist_ok=True)
    return write_task_table(tmp_path, name, rows, key=meta[b"glaciar.task"].decode(),
                            mag_column=meta[b"glaciar.counts_mag_column"].decode(),
                            obs_column=meta[b"glaciar.mobs_hist_column"].decode())


def test_a_task_file_is_encoded_once_and_passes_every_check(task_rows, tmp_path, monkeypatch):
    import pyarrow.parquet.core as pq_core

    rows, meta = task_rows
    opened = []

    class CountingWriter(pq_core.ParquetWriter):
        def __init__(self, *args, **kwargs):
            opened.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(pq_core, "ParquetWriter", CountingWriter)
    monkeypatch.setattr(pq, "ParquetWriter", CountingWriter)
    path = _write(tmp_path, rows, meta)
    assert len(opened) == 1                     # two before issue 24
    monkeypatch.undo()

    assert unit_problem(path) is None
    assert task_file_problem(path, meta[b"glaciar.task"].decode()) is None
    pd.testing.assert_frame_equal(read_results(tmp_path), rows)
    got = pq.read_metadata(path).metadata
    for k in (b"glaciar.counts", b"glaciar.mobs_hist"):   # the same footer tables
        assert ipc_table(got[k]).equals(ipc_table(meta[k]))
        assert got[k + b".blake2b"] == hashlib.blake2b(got[k], digest_size=16).hexdigest().encode()
    # The digest covers every byte before the footer: computed here from the file's bytes.
    data = path.read_bytes()
    want = hashlib.blake2b(data[:_footer_start(data)], digest_size=16).hexdigest().encode()
    assert got[PAGES_KEY] == want


def test_a_byte_changed_in_the_pages_is_found(task_rows, tmp_path):
    rows, meta = task_rows
    path = _write(tmp_path, rows, meta)
    data = bytearray(path.read_bytes())
    data[_footer_start(bytes(data)) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    assert unit_problem(path) == "corrupt data pages (digest mismatch)"


def test_a_file_of_the_two_encode_writer_still_reads(task_rows, tmp_path):
    """The older writer: encode, hash the pages, encode again with the digest in the
    table's schema metadata (so also in the Arrow schema stored in the footer)."""
    rows, meta = task_rows
    new = _write(tmp_path, rows, meta, "task_b.parquet")
    table = pq.read_table(new)
    kv = {k: v for k, v in table.schema.metadata.items() if k != PAGES_KEY}
    table = table.replace_schema_metadata(kv)

    def encode(t):
        buf = io.BytesIO()
        pq.write_table(t, buf, write_page_checksum=True)
        return buf.getvalue()

    first = encode(table)
    kv[PAGES_KEY] = hashlib.blake2b(first[:_footer_start(first)],
                                    digest_size=16).hexdigest().encode()
    old = encode(table.replace_schema_metadata(kv))
    assert old[:_footer_start(old)] == first[:_footer_start(first)]
    new.write_bytes(old)
    assert unit_problem(new) is None
    assert task_file_problem(new, meta[b"glaciar.task"].decode()) is None
    pd.testing.assert_frame_equal(read_results(tmp_path), rows)


def _frames(rows):
    rng = np.random.default_rng(3)
    more = pd.concat([rows] * 7, ignore_index=True)        # same layout, other length
    floats = more.select_dtypes("float").columns
    more[floats] = np.where(rng.random((len(more), len(floats))) < 0.3, np.nan,
                            rng.normal(size=(len(more), len(floats))))
    mixed = pd.DataFrame({"a": pd.Series(["x", "y"], dtype=object), "b": [1.5, np.nan]})
    small = pd.DataFrame({"k": np.arange(3, dtype=np.int32), "f": [0.5, np.nan, 2.0],
                          "b": [True, False, True], "s": pd.array(["a", "b", "a"], dtype="str")})
    return [rows, more, rows, mixed, small]


def test_arrow_table_is_pyarrows_conversion(task_rows):
    rows, _ = task_rows
    for df in _frames(rows):
        want = pa.Table.from_pandas(df, preserve_index=False)
        assert arrow_table(df).equals(want, check_metadata=True)
        assert arrow_table(df, pandas_metadata=False).equals(
            want.replace_schema_metadata(None), check_metadata=True)


@pytest.mark.parametrize("n", [3, 500])
def test_footer_tables_round_trip(n):
    rng = np.random.default_rng(n)
    df = pd.DataFrame({"field": pd.array(["f"] * n, dtype="str"), "key": np.arange(n) // 2,
                       "n": rng.integers(0, 9, n), "s": np.where(rng.random(n) < 0.2, np.nan,
                                                                 rng.random(n))})
    want = pa.Table.from_pandas(df, preserve_index=False).replace_schema_metadata(None)
    assert ipc_table(ipc_bytes(df)).equals(want, check_metadata=True)


def test_footer_tables_from_arrays_are_pyarrows_conversion_of_their_dataframe(task_rows):
    """A task's counts and histograms go to its footer as dicts of arrays (no DataFrame):
    the same Arrow table as pyarrow's conversion of the DataFrame, text columns included,
    for the task's rows and for none."""
    from glaciar import counting as K

    rows, meta = task_rows
    obs = meta[b"glaciar.mobs_hist_column"].decode()
    for part in (rows, rows.iloc[:0]):
        for arrays in (K.task_count_arrays(part, C.COL_MAG_INPUT), K.task_histogram_arrays(part, obs)):
            want = pa.Table.from_pandas(pd.DataFrame(arrays), preserve_index=False)
            got = ipc_table(ipc_bytes(arrays))
            assert got.equals(want.replace_schema_metadata(None), check_metadata=True)
            assert got.num_rows == want.num_rows and got.num_columns > 5
