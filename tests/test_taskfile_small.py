"""Task files written small (issue 24): plain pages without statistics, same rows.

A task's ~120 columns of ~100 mostly distinct values were written with dictionary pages
and min/max statistics (the default of pyarrow's writer); now plainly, which encodes in
less CPU and leaves page headers without values, so a flipped byte of a small page lands
in its checksummed data.  The Arrow table given to the writer is the one pyarrow's own
``from_pandas`` builds, whatever the order of the columns' dtypes.
"""
from __future__ import annotations

import io

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from glaciar import constants as C
from glaciar.store import read_results, write_task_table
from glaciar.taskfile import arrow_table, parquet_bytes, unit_problem


def _interleaved(n: int, seed: int) -> pd.DataFrame:
    """Columns of five dtypes interleaved (each dtype's columns are not adjacent), NaN included."""
    rng = np.random.default_rng(seed)
    cols = {}
    for i in range(6):
        cols[f"f{i}"] = np.where(rng.random(n) < 0.25, np.nan, rng.normal(size=n))
        cols[f"i{i}"] = rng.integers(-5, 5, n)
        cols[f"b{i}"] = rng.random(n) < 0.5
        cols[f"h{i}"] = rng.integers(-3, 3, n).astype(np.int8)
        cols[f"u{i}"] = rng.random(n).astype(np.float32)
    cols["field"] = pd.array([f"F{k % 3}" for k in range(n)], dtype="str")
    return pd.DataFrame(cols)


@pytest.mark.parametrize("n", [0, 1, 7, 100])
def test_arrow_table_of_interleaved_dtypes_is_pyarrows_conversion(n):
    df = _interleaved(n, n)
    want = pa.Table.from_pandas(df, preserve_index=False)
    for _ in range(2):                  # first call: pyarrow's schema; then the cached one
        assert arrow_table(df).equals(want, check_metadata=True)
    assert arrow_table(df, pandas_metadata=False).equals(
        want.replace_schema_metadata(None), check_metadata=True)
    # Values taken column by column: each column's own, not a neighbour's of its dtype.
    got = arrow_table(df)
    for name in df.columns[:-1]:
        col = got.column(name).to_numpy(zero_copy_only=False)
        ref = df[name].to_numpy()
        assert np.array_equal(col, ref, equal_nan=ref.dtype.kind == "f")


def _column_chunks(data: bytes):
    md = pq.read_metadata(io.BytesIO(data))
    rg = md.row_group(0)
    return [rg.column(i) for i in range(rg.num_columns)]


def test_small_parquet_has_plain_pages_without_statistics():
    t = pa.Table.from_pandas(_interleaved(50, 1), preserve_index=False)
    small, default = parquet_bytes(t, small=True), parquet_bytes(t)
    for c in _column_chunks(small):
        assert not c.has_dictionary_page
        assert "RLE_DICTIONARY" not in c.encodings and "PLAIN_DICTIONARY" not in c.encodings
        assert not c.is_stats_set
    assert any(c.has_dictionary_page for c in _column_chunks(default))    # parts keep them
    for data in (small, default):
        assert pq.read_table(io.BytesIO(data)).equals(t)


def test_a_task_file_is_written_small_with_the_same_rows(one_task_run, tmp_path):
    _, run = one_task_run
    path = next((run / C.RESULTS_DIRNAME).glob("task_*.parquet"))
    rows = pd.read_parquet(path)
    meta = pq.read_metadata(path).metadata
    (tmp_path / C.RESULTS_DIRNAME).mkdir()
    out = write_task_table(tmp_path, path.name, rows, key=meta[b"glaciar.task"].decode(),
                           mag_column=meta[b"glaciar.counts_mag_column"].decode(),
                           obs_column=meta[b"glaciar.mobs_hist_column"].decode())
    chunks = _column_chunks(out.read_bytes())
    assert not any(c.has_dictionary_page or c.is_stats_set for c in chunks)
    assert unit_problem(out) is None
    pd.testing.assert_frame_equal(read_results(tmp_path), rows, check_exact=True)


@pytest.mark.parametrize("n", [2, 3, 5])
def test_a_flipped_byte_mid_column_of_a_small_task_is_not_read_silently(n):
    """With statistics, the middle of a tiny column chunk lies in its page header's min/max,
    which no page checksum covers: the rows read back unchanged and the file passed.  Now
    the byte is in the page's data (its checksum fails) or its header (which no longer
    decodes)."""
    rng = np.random.default_rng(n)
    t = pa.table({"x": rng.random(n), "y": np.arange(n, dtype=float)})
    data = bytearray(parquet_bytes(t, small=True))
    col = _column_chunks(bytes(data))[0]
    data[int(col.data_page_offset) + int(col.total_compressed_size) // 2] ^= 0xFF
    with pytest.raises(OSError):
        pq.read_table(io.BytesIO(bytes(data)), page_checksum_verification=True)
