"""The bytes of one unit of the store (a task file or a compacted part) and their checks.

A unit is a Parquet file written with page checksums (:func:`parquet_bytes`) whose
footer's key-value metadata holds the task key and row count, the counts and m_obs
histograms as Arrow IPC streams (:func:`ipc_bytes`, :func:`ipc_table`), and BLAKE2b
digests of those tables, of the columns and row count (:func:`schema_digest`) and of
every byte before the footer.  :func:`task_file_problem` checks a task file from its raw
footer bytes without parsing them (a resume's fast check); :func:`unit_problem` checks
every byte.  Where units live in a run directory and how they are read, merged and
compacted is :mod:`glaciar.store`'s.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Mapping

import numpy as np

if TYPE_CHECKING:       # imported where a DataFrame is converted: a run's tasks write without it
    import pandas as pd

__all__ = ["META_TASK", "META_ROWS", "META_COUNTS", "META_COUNTS_MAG", "META_HIST",
           "META_HIST_OBS", "DIGEST_SUFFIX", "META_SCHEMA", "META_PART_TASKS",
           "parquet_bytes", "arrow_table", "columns_table", "ipc_bytes", "ipc_table", "footer_metadata", "task_file_problem",
           "schema_digest", "blake2b_digest", "unit_problem"]

#: Key-value metadata of every task file: the exact task key and the number of rows.
META_TASK = b"glaciar.task"
META_ROWS = b"glaciar.n_rows"
#: Footer metadata of the counts: an Arrow IPC stream, and the magnitude covariate they key on.
META_COUNTS = b"glaciar.counts"
META_COUNTS_MAG = b"glaciar.counts_mag_column"
#: Footer metadata of the histograms of the measured magnitude (:func:`glaciar.counting.task_histogram`): an
#: Arrow IPC stream, and the measured-magnitude column they bin.
META_HIST = b"glaciar.mobs_hist"
META_HIST_OBS = b"glaciar.mobs_hist_column"
#: Suffix of the key of a footer table's BLAKE2b digest (checked on resume, :func:`task_file_problem`).
DIGEST_SUFFIX = b".blake2b"
#: Footer metadata: BLAKE2b of the rows' column names, types and row count
#: (:func:`schema_digest`).  Parquet checksums its data pages (written with
#: ``write_page_checksum``) but not its footer: a garbled footer that still parses
#: (a renamed column, another row count) is caught by this digest.
META_SCHEMA = b"glaciar.schema.blake2b"
#: Footer metadata: BLAKE2b of every byte before the footer (pages and page headers,
#: :func:`parquet_bytes`).
_META_PAGES = b"glaciar.pages.blake2b"
#: Footer metadata of a compacted part: JSON list of [task file name, task key, n_rows].
META_PART_TASKS = b"glaciar.part_tasks"
def parquet_bytes(table, small: bool = False) -> bytes:
    """``table`` as Parquet bytes with page checksums and, in its footer, a digest of its pages.

    ``small=True`` (a task file's ~120 columns of ~100 mostly distinct values) writes
    every column plainly encoded, without dictionary pages or min/max statistics: ~35 %
    less CPU and ~15 % fewer bytes, and a smaller footer to parse.  Without statistics a
    data page's header holds no values, so a flipped byte of a small page is more likely
    in its checksummed data, which readers verify (the header is covered by the pages'
    digest, :func:`unit_problem`).  Compacted parts (repeated values, many rows) keep
    dictionaries and statistics.

    Parquet's page checksums cover a page's data, not its header; a digest of every
    byte before the footer (:data:`_META_PAGES`) covers both, and checking it costs one
    hash of the file (:func:`unit_problem`).  The key-value metadata lives only in the
    footer, which a Parquet writer writes last: the table is encoded once, the bytes
    written so far (magic and pages) are hashed before the writer closes, and the digest
    is added to the footer's key-value metadata (where :func:`unit_problem` reads it; the
    Arrow schema stored in the footer keeps the table's own metadata).  Should a writer
    ever hold back bytes of its pages until it closes (checked after the fact), the file
    is written the older way: encoded once to learn its pages, then again with their digest.
    """
    import io

    import pyarrow.parquet as pq

    buf = io.BytesIO()
    with pq.ParquetWriter(buf, table.schema, write_page_checksum=True,
                          **_writer_options(small)) as writer:
        writer.write_table(table)
        pages = buf.getvalue()
        digest = blake2b_digest(pages)
        writer.add_key_value_metadata({_META_PAGES: digest})
    data = buf.getvalue()
    if _pages_end(data) == len(pages) and data.startswith(pages):
        return data
    return _parquet_bytes_two_encodes(table, small)


def _writer_options(small: bool) -> dict:
    """Parquet writer options of :func:`parquet_bytes` (pyarrow's defaults unless ``small``)."""
    return {"use_dictionary": False, "write_statistics": False} if small else {}


def _parquet_bytes_two_encodes(table, small: bool = False) -> bytes:
    """:func:`parquet_bytes` by two encodes: the pages learnt from a first, the digest put
    in the second's footer (if its pages ever differed, the first file, page checksums only)."""
    import io

    import pyarrow.parquet as pq

    def write(t) -> bytes:
        buf = io.BytesIO()
        pq.write_table(t, buf, write_page_checksum=True, **_writer_options(small))
        return buf.getvalue()

    first = write(table)
    pages = first[:_pages_end(first)]
    meta = dict(table.schema.metadata or {})
    meta[_META_PAGES] = blake2b_digest(pages)
    second = write(table.replace_schema_metadata(meta))
    return second if second[:len(pages)] == pages else first


def _pages_end(data: bytes) -> int:
    """Offset of the footer of complete Parquet bytes (the pages end there)."""
    return len(data) - 8 - int.from_bytes(data[-8:-4], "little")


#: Arrow schemas (pandas metadata included) of the DataFrames :func:`arrow_table` converted,
#: keyed by their columns' names and dtypes: a run's task tables all share one.
_PANDAS_SCHEMAS: dict = {}
#: Schemas kept at most (a run has one or a few task-table layouts).
_PANDAS_SCHEMAS_MAX = 16


def arrow_table(df: pd.DataFrame, pandas_metadata: bool = True):
    """``df`` as a pyarrow Table: ``pa.Table.from_pandas(df, preserve_index=False)``.

    The same table, column values (NaN as null, as pandas' conversion does), types and
    schema metadata, built faster where every column is a numpy bool, integer or float
    column or a pandas string column: each column is converted on its own and the schema,
    with the pandas metadata that depends only on the columns' names and dtypes, comes
    from the first DataFrame of that layout converted by pyarrow (pyarrow's own
    per-column metadata costs ~5 ms on a 120-column task table).  Other DataFrames go
    through ``from_pandas``.  ``pandas_metadata=False`` drops the schema metadata.
    """
    import pyarrow as pa

    if isinstance(df, dict):
        # Column arrays (a task's rows): the table of their DataFrame, built without pandas.
        t = columns_table(df)
        return t if pandas_metadata else t.replace_schema_metadata(None)
    if not _fast_convertible(df):
        t = pa.Table.from_pandas(df, preserve_index=False)
        return t if pandas_metadata else t.replace_schema_metadata(None)
    arrays = [pa.array(a, from_pandas=True) for a in _column_arrays(df)]   # NaN -> null
    if not pandas_metadata:
        return pa.Table.from_arrays(arrays, names=[str(c) for c in df.columns])
    # dtype objects, not their names, in the key: str() of 120 dtypes costs ~0.4 ms.
    layout = (tuple(df.columns), tuple(df.dtypes), df.columns.name, df.columns.dtype)
    schema = _PANDAS_SCHEMAS.get(layout)
    if schema is None:
        t = pa.Table.from_pandas(df, preserve_index=False)
        if len(_PANDAS_SCHEMAS) >= _PANDAS_SCHEMAS_MAX:
            _PANDAS_SCHEMAS.clear()
        _PANDAS_SCHEMAS[layout] = t.schema
        return t
    return pa.Table.from_arrays(arrays, schema=schema)


def columns_table(cols: Mapping[str, np.ndarray]):
    """The pyarrow Table of ``arrow_table(pandas.DataFrame(cols))``, without pandas.

    ``cols``: a task's rows as column arrays (:func:`glaciar.engine.task.task_columns`).
    Numeric and bool columns convert as they are (NaN as null), a text column (strings
    only) to the Arrow type pandas gives it (:func:`_text_arrow_type`), and the schema
    carries the pandas metadata ``pyarrow.Table.from_pandas`` writes for that DataFrame
    (:func:`_pandas_schema_metadata`): the same Parquet bytes, read back into the same
    DataFrame.  Anything else (another dtype, a text column with a non-string or no value,
    columns of different lengths) goes through pandas as before.  Arrays are built from
    their buffers (:func:`_buffers_array`): ``pyarrow.array`` imports pandas.
    """
    import pyarrow as pa

    arrays = {str(k): np.asarray(v) for k, v in cols.items()}
    lengths = {a.shape[0] if a.ndim == 1 else -1 for a in arrays.values()}
    kinds = [_column_kind(a) for a in arrays.values()]
    if len(lengths) != 1 or -1 in lengths or None in kinds or len(arrays) != len(cols):
        import pandas as pd

        return arrow_table(pd.DataFrame(dict(cols)))
    text = _text_arrow_type() if "text" in kinds else None
    fields, out = [], []
    for (name, a), kind in zip(arrays.items(), kinds):
        arr = _buffers_array(a, text)
        fields.append(pa.field(name, arr.type))
        out.append(arr)
    schema = pa.schema(fields, metadata={b"pandas": _pandas_schema_metadata(arrays, kinds, text)})
    return pa.Table.from_arrays(out, schema=schema)


def _buffers_array(a: np.ndarray, text=None):
    """``pyarrow.array(a, from_pandas=True)`` (NaN as null; ``type=text`` for a text column)
    of a :func:`_column_kind` column, built from numpy buffers: ``pyarrow.array`` imports
    pandas (its ``from_pandas`` checks), which a run's tasks otherwise never need."""
    import pyarrow as pa

    n = a.shape[0]
    if a.dtype.kind == "b":
        return pa.Array.from_buffers(pa.bool_(), n, [None, pa.py_buffer(
            np.packbits(a, bitorder="little"))])
    if a.dtype.kind in "iuf":
        data = np.ascontiguousarray(a)
        valid = None
        nulls = 0
        if a.dtype.kind == "f":
            missing = np.isnan(data)
            nulls = int(np.count_nonzero(missing))
            if nulls:
                valid = pa.py_buffer(np.packbits(~missing, bitorder="little"))
        return pa.Array.from_buffers(pa.from_numpy_dtype(a.dtype), n,
                                     [valid, pa.py_buffer(data)], null_count=nulls)
    encoded = [x.encode("utf-8") for x in a.tolist()]
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum([len(e) for e in encoded], out=offsets[1:])
    if not pa.types.is_large_string(text):
        if offsets[-1] > np.iinfo(np.int32).max:        # too long for Arrow string's offsets
            return pa.array(a, type=text, from_pandas=True)
        offsets = offsets.astype(np.int32)
    return pa.Array.from_buffers(text, n, [None, pa.py_buffer(offsets),
                                           pa.py_buffer(b"".join(encoded))])


def _column_kind(a: np.ndarray) -> str | None:
    """"number" (native-order numpy bool, int, float32/64), "text" (non-empty, strings
    only) or None (other: converted through pandas)."""
    if a.dtype.kind in "biu" or (a.dtype.kind == "f" and a.dtype.itemsize in (4, 8)):
        return "number" if a.dtype.isnative else None
    if a.dtype.kind == "U" and a.size:
        return "text"
    if a.dtype.kind == "O" and a.size and all(type(x) is str for x in a):
        return "text"
    return None


def _pandas_version() -> str:
    """The installed pandas' version, without importing it (where nothing has)."""
    pd = sys.modules.get("pandas")
    if pd is not None:
        return pd.__version__
    if not _PANDAS_VERSION:
        from importlib.metadata import version

        _PANDAS_VERSION.append(version("pandas"))
    return _PANDAS_VERSION[0]


_PANDAS_VERSION: list = []


def _text_arrow_type():
    """The Arrow type of a text column converted from a DataFrame: pandas >= 3's default
    ``str`` dtype gives ``large_string``, pandas 2's object columns ``string``."""
    import pyarrow as pa

    return pa.large_string() if int(_pandas_version().split(".")[0]) >= 3 else pa.string()


def _pandas_schema_metadata(arrays: dict, kinds: list, text) -> bytes:
    """The ``pandas`` schema metadata pyarrow's ``Table.from_pandas(df, preserve_index=False)``
    writes for a DataFrame of these columns (no index, ``attrs`` empty): each column's
    logical type (a numeric dtype's name; ``unicode`` for Arrow string, ``object`` for
    large_string) and dtype (``str`` for pandas 3's text, ``object`` for pandas 2's)."""
    import pyarrow as pa

    large = pa.types.is_large_string(text) if text is not None else False
    columns = []
    for (name, a), kind in zip(arrays.items(), kinds):
        if kind == "number":
            logical = numpy_type = str(a.dtype)
        else:
            logical, numpy_type = ("object", "str") if large else ("unicode", "object")
        columns.append({"name": name, "field_name": name, "pandas_type": logical,
                        "numpy_type": numpy_type, "metadata": None})
    return json.dumps({"index_columns": [], "column_indexes": [], "columns": columns,
                       "attributes": {}, "creator": {"library": "pyarrow", "version": pa.__version__},
                       "pandas_version": _pandas_version()}).encode("utf8")


def _column_arrays(df: pd.DataFrame) -> list:
    """Each column's values of a :func:`_fast_convertible` DataFrame, in column order.

    The columns of a numpy dtype that many columns share are taken together (one
    ``to_numpy`` of those columns, transposed to rows that are contiguous columns): a
    Series per column costs ~10 us, ~1.4 ms on a 120-column task table.  Other columns
    (and every column of a narrow table, where the block costs more) one by one.  The
    values are the columns' own.
    """
    out: list = [None] * df.shape[1]
    by_dtype: dict = {}
    for i, d in enumerate(df.dtypes):
        by_dtype.setdefault(d, []).append(i)
    for d, idx in by_dtype.items():
        if isinstance(d, np.dtype) and len(idx) >= _BLOCK_MIN_COLUMNS:
            block = np.ascontiguousarray(df.iloc[:, idx].to_numpy(dtype=d).T)
            for k, i in enumerate(idx):
                out[i] = block[k]
    rest = [i for i, a in enumerate(out) if a is None]
    # A few columns left: each taken alone; many: one pass over all of them (cheaper per column).
    pairs = ((i, df.iloc[:, i]) for i in rest) if 4 * len(rest) < len(out) else \
        ((i, s) for i, (_, s) in enumerate(df.items()) if out[i] is None)
    for i, s in pairs:
        out[i] = s.to_numpy() if isinstance(s.dtype, np.dtype) else s.array
    return out


#: Columns of one dtype from which :func:`_column_arrays` takes them as one block.
_BLOCK_MIN_COLUMNS = 16


def _fast_convertible(df: pd.DataFrame) -> bool:
    """Whether :func:`arrow_table` may convert ``df`` column by column (unique string
    column names, a plain column index, no ``attrs``, numpy bool/int/float or string dtypes)."""
    import pandas as pd

    if df.attrs or not df.columns.is_unique or isinstance(df.columns, pd.MultiIndex):
        return False
    if not all(isinstance(c, str) for c in df.columns):
        return False
    return all((isinstance(d, np.dtype) and d.kind in "biuf") or isinstance(d, pd.StringDtype)
               for d in df.dtypes)


#: Rows from which a footer table is compressed (:func:`ipc_bytes`).
_IPC_ZSTD_MIN_ROWS = 64


def ipc_bytes(df) -> bytes:
    """``df`` (a DataFrame, or a dict of column arrays as :func:`arrow_table` would convert
    the DataFrame of it, or a pyarrow Table of such a conversion: written as one batch, as
    its DataFrame would be) as an Arrow IPC stream (no schema metadata), zstd-compressed
    when it is long.

    zstd: a compacted part's counts repeat their keys and are mostly small integers
    (~10x smaller footers).  A task's few rows are not compressed: Arrow compresses
    each column's buffers on their own, which costs ~1 ms for a task's 3-row counts and
    makes them larger (3192 against 2832 bytes); readers decode either
    (:func:`ipc_table`).
    """
    import pyarrow as pa

    if isinstance(df, dict):
        # A task's footer tables: no DataFrame to build and take apart again (~0.3 ms each).
        t = pa.Table.from_arrays([_arrow_column(np.asarray(v)) for v in df.values()],
                                 names=[str(c) for c in df])
    elif isinstance(df, pa.Table):
        t = df.replace_schema_metadata(None).combine_chunks()
    else:
        t = arrow_table(df, pandas_metadata=False)
    sink = pa.BufferOutputStream()
    opts = pa.ipc.IpcWriteOptions(
        compression="zstd" if t.num_rows >= _IPC_ZSTD_MIN_ROWS else None)
    with pa.ipc.new_stream(sink, t.schema, options=opts) as w:
        w.write_table(t)
    return sink.getvalue().to_pybytes()


def _arrow_column(v: np.ndarray):
    """A column array as :func:`arrow_table` converts the DataFrame column it would make:
    numbers as they are (NaN as null), text as the Arrow type pandas gives it (string with
    pandas 2's object columns, large_string with pandas 3's str dtype)."""
    kind = _column_kind(v)
    if kind is not None and v.ndim == 1:
        return _buffers_array(v, _text_arrow_type() if kind == "text" else None)
    import pandas as pd     # e.g. an empty text column: pandas types it on its own (null)

    return arrow_table(pd.DataFrame({"c": v}), False).column(0).combine_chunks()


def ipc_table(data: bytes):
    import pyarrow as pa

    return pa.ipc.open_stream(pa.py_buffer(data)).read_all()


def footer_metadata(path: Path):
    """(key-value metadata dict, None) of a Parquet file, or (None, why not)."""
    import pyarrow.parquet as pq

    try:
        meta = pq.read_metadata(path).metadata or {}
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad files
        return None, f"not a complete Parquet file ({type(exc).__name__}: {exc})"
    return meta, None


def task_file_problem(path: Path, key: str) -> str | None:
    """Why ``path`` is not a complete task file of ``key`` (None if it is).

    A footer-level check that reads ~the footer's bytes and parses nothing
    (~0.1 ms per file, where parsing the ~45 kB footer with pyarrow costs
    ~1.5 ms): the file starts and ends with Parquet's magic bytes, the footer
    length fits the file, and the footer holds this task's key (written by
    :func:`glaciar.store.write_task_table`).  Parquet writes its footer last and task files
    are renamed into place only when complete, so a cut or partly copied file
    fails the check; a file of another task fails the key test; counts or
    histograms whose bytes no longer match their stored digest fail too
    (:func:`_footer_table_problem`).
    """
    magic = b"PAR1"
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
            size = fh.seek(0, os.SEEK_END)
            if size < 12:
                return f"not a complete Parquet file ({size} bytes)"
            fh.seek(size - 8)
            tail = fh.read(8)
            n = int.from_bytes(tail[:4], "little")
            if head != magic or tail[4:] != magic or n <= 0 or n > size - 12:
                return "not a complete Parquet file (no footer: truncated or not Parquet)"
            fh.seek(size - 8 - n)
            footer = fh.read(n)
    except OSError as exc:
        return f"unreadable ({exc.strerror or exc})"
    if META_TASK not in footer:
        return "not a glaciar task file (no task key in its metadata)"
    if key.encode("utf-8") not in footer:
        return f"holds another task than {key}"
    for meta_key in (META_COUNTS, META_HIST):
        problem = _footer_table_problem(footer, meta_key)
        if problem is not None:
            return problem
    return None


def _footer_table_problem(footer: bytes, meta_key: bytes) -> str | None:
    """Why the IPC table stored under ``meta_key`` in a raw Parquet footer is unreadable.

    None when it is absent, or has no digest (a file written before digests),
    or matches its BLAKE2b digest (``meta_key + DIGEST_SUFFIX``, written
    beside it by :func:`glaciar.store.write_task_table`): hashing the few kB costs ~µs
    where decoding the table costs ~1 ms.
    """
    digest = _raw_meta_value(footer, meta_key + DIGEST_SUFFIX)
    if digest is None:
        return None
    value = _raw_meta_value(footer, meta_key)
    if value is None or blake2b_digest(value) != digest:
        return f"unreadable {meta_key.decode()} metadata (digest mismatch)"
    return None


def schema_digest(schema, n_rows: int) -> bytes:
    """BLAKE2b of an Arrow schema's column names and types and a row count (metadata ignored)."""
    text = json.dumps([[f.name, str(f.type)] for f in schema] + [int(n_rows)],
                      ensure_ascii=False, separators=(",", ":"))
    return blake2b_digest(text.encode("utf-8"))


def blake2b_digest(data: bytes) -> bytes:
    """BLAKE2b-128 of ``data`` as ASCII hex bytes (the form stored in footers)."""
    return hashlib.blake2b(data, digest_size=16).hexdigest().encode("ascii")


def _raw_meta_value(footer: bytes, meta_key: bytes) -> bytes | None:
    """The value of key-value metadata ``meta_key`` found in a raw (unparsed) Parquet footer.

    Thrift's compact protocol writes an entry as field header 0x18, varint
    length, key bytes, 0x18, varint length, value bytes; None if the key is
    absent (or the value runs past the footer).
    """
    head = b"\x18" + _varint(len(meta_key)) + meta_key + b"\x18"
    at = footer.find(head)
    if at < 0:
        return None
    i, n, shift = at + len(head), 0, 0
    while i < len(footer):
        byte = footer[i]
        n |= (byte & 0x7F) << shift
        shift += 7
        i += 1
        if not byte & 0x80:
            break
    value = footer[i:i + n]
    return value if len(value) == n else None


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        out.append((n & 0x7F) | (0x80 if n > 0x7F else 0))
        n >>= 7
        if not n:
            return bytes(out)



def unit_problem(path: str | os.PathLike) -> str | None:
    """Why a task file or compacted part is not intact (None if it is): every byte checked.

    Parses the footer (a garbled one fails, or no longer matches the digests
    glaciar wrote into it: row count, column names and types, counts,
    histograms, a part's task list), then checks every byte before the footer
    against its recorded digest (pages and page headers: one hash of the file).
    A file written before page digests has every page of every row group
    decoded instead, with Parquet's page checksums verified where it has them
    (without: pages that no longer decode).  Detection of random in-page
    garbage: benchmarks/corruption.py.
    """
    import pyarrow.parquet as pq

    path = Path(path)
    try:
        pf = pq.ParquetFile(path, page_checksum_verification=True)
        md = pf.metadata
        meta = md.metadata or {}
        rows = meta.get(META_ROWS)
        if rows is not None and int(rows) != md.num_rows:
            return (f"corrupt footer ({md.num_rows} rows where its metadata records "
                    f"{int(rows)})")
        want = meta.get(META_SCHEMA)
        if want is not None and schema_digest(pf.schema_arrow, md.num_rows) != want:
            return "corrupt footer (columns or row count differ from its recorded digest)"
        for k in (META_COUNTS, META_HIST, META_PART_TASKS):
            digest = meta.get(k + DIGEST_SUFFIX)
            if digest is not None and (k not in meta or blake2b_digest(meta[k]) != digest):
                return f"corrupt footer (unreadable {k.decode()} metadata: digest mismatch)"
        pages = meta.get(_META_PAGES)
        if pages is not None:
            if _file_pages_digest(path) != pages:
                return "corrupt data pages (digest mismatch)"
        else:       # a file from before page digests: decode every page (checksums if any)
            for _ in pf.iter_batches(batch_size=_VERIFY_BATCH_ROWS, use_threads=False):
                pass
    except Exception as exc:  # noqa: BLE001 - pyarrow raises many types for bad bytes
        text = str(exc).strip().splitlines()
        return f"corrupt ({type(exc).__name__}: {text[0] if text else 'unreadable'})"
    return None


def _file_pages_digest(path: Path) -> bytes:
    """BLAKE2b of the bytes of a Parquet file before its footer, read in blocks."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        size = fh.seek(0, os.SEEK_END)
        fh.seek(max(size - 8, 0))
        tail = fh.read(8)
        left = size - 8 - int.from_bytes(tail[:4], "little") if size >= 12 else 0
        fh.seek(0)
        while left > 0:
            block = fh.read(min(left, 1 << 22))
            if not block:
                break
            h.update(block)
            left -= len(block)
    return h.hexdigest().encode("ascii")


#: Rows decoded at a time when a unit's pages are verified (memory: one batch of columns).
_VERIFY_BATCH_ROWS = 1 << 16
