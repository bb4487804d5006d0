"""glaciar.taskfile.columns_table: a task's column arrays as pandas' own conversion makes them.

A run's tasks write their rows without building a DataFrame (no pandas import): the Arrow
table, its schema metadata, the Parquet bytes and the DataFrame read back must be those of
``pyarrow.Table.from_pandas(pandas.DataFrame(columns), preserve_index=False)``.
"""
from __future__ import annotations

import io
import subprocess
import sys
import textwrap

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from glaciar.taskfile import columns_table, ipc_bytes, ipc_table, parquet_bytes


def _columns(n: int = 7) -> dict:
    """Every column kind a task's rows have (and a few more), NaN and infinities included."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=n)
    x[[1, 4]] = np.nan
    x[2], x[3] = np.inf, -0.0
    return {
        "field": np.full(n, "GOODS-S déjà", dtype=object),     # text, object array
        "band": np.array(["f160w", "f125w"] * (n // 2) + ["f098m"] * (n % 2)),  # text, numpy str
        "z": np.full(n, 9.6),
        "x": x,
        "mag_f32": x.astype(np.float32),
        "source": np.arange(n, dtype=np.int64),
        "status": np.array([0, 1, 2, -1, 0, 1, 2][:n], dtype=np.int8),
        "mobs_bin": np.arange(n, dtype=np.int32) - 3,
        "flags_u": np.arange(n, dtype=np.uint16),
        "recovered": np.arange(n) % 2 == 0,
        "all_nan": np.full(n, np.nan),
    }


def _read_back(data: bytes) -> pd.DataFrame:
    return pq.read_table(io.BytesIO(data)).to_pandas()


def test_columns_table_is_pandas_conversion_with_its_metadata():
    cols = _columns()
    want = pa.Table.from_pandas(pd.DataFrame(cols), preserve_index=False)
    got = columns_table(cols)
    assert got.schema.equals(want.schema, check_metadata=True)
    assert got.schema.metadata[b"pandas"] == want.schema.metadata[b"pandas"]
    assert got.equals(want)
    assert got.column("x").null_count == 2          # NaN as null, as pandas' conversion
    # The same Parquet file, and the same DataFrame read back (dtypes, values, index, order).
    for small in (True, False):
        assert parquet_bytes(got, small=small) == parquet_bytes(want, small=small)
    back, ref = _read_back(parquet_bytes(got, True)), _read_back(parquet_bytes(want, True))
    assert list(back.columns) == list(cols)
    assert list(back.dtypes) == list(ref.dtypes)
    assert back.index.equals(ref.index)
    pd.testing.assert_frame_equal(back, ref, check_exact=True)


def test_columns_table_of_no_rows_or_mixed_text_is_pandas_conversion():
    # pandas types an empty text column and a text column with a NaN on its own: as before.
    for cols in ({k: v[:0] for k, v in _columns().items()},
                 {"field": np.array(["a", np.nan], dtype=object), "z": np.array([1.0, 2.0])}):
        want = pa.Table.from_pandas(pd.DataFrame(cols), preserve_index=False)
        got = columns_table(cols)
        assert got.schema.equals(want.schema, check_metadata=True)
        assert got.equals(want)


def test_footer_tables_of_columns_are_the_dataframe_conversion():
    cols = _columns()
    from_arrays = ipc_table(ipc_bytes(cols))
    from_frame = ipc_table(ipc_bytes(pd.DataFrame(cols)))
    assert from_arrays.equals(from_frame) and from_arrays.schema.equals(from_frame.schema)


def test_footer_tables_of_a_part_are_written_as_one_batch_of_their_dataframe():
    # A compaction concatenates the tasks' footer tables (one chunk each) and writes them
    # without a DataFrame: the same table, in one record batch.
    parts = [ipc_table(ipc_bytes({k: v[i:i + 2] for k, v in _columns(7).items()}))
             for i in (0, 2, 4)]
    joined = pa.concat_tables(parts)
    direct = pa.ipc.open_stream(ipc_bytes(joined))
    batches = list(direct)
    assert len(batches) == 1
    got = pa.Table.from_batches(batches)
    want = ipc_table(ipc_bytes(joined.to_pandas()))
    assert got.equals(want) and got.schema.equals(want.schema)


def test_columns_table_imports_no_pandas():
    code = textwrap.dedent("""
        import sys
        import numpy as np
        from glaciar.taskfile import columns_table, ipc_bytes, parquet_bytes
        cols = {"field": np.full(3, "F01", dtype=object), "x": np.array([1.0, np.nan, 2.0]),
                "ok": np.array([True, False, True]), "n": np.arange(3)}
        parquet_bytes(columns_table(cols), small=True)
        ipc_bytes(cols)
        print("pandas" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "False"
