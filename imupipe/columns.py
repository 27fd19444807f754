"""Arrow columns as numpy arrays, read without a Python object per row, and numpy arrays as
Arrow columns without a copy; rows of a table kept by a mask without importing pyarrow.compute
where it is not needed (its import is ~40 ms, a twentieth of a short run)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

MAX_RUNS = 64  # runs of kept rows above which ``kept_rows`` leaves the work to Arrow's filter


def arrow_column(values: np.ndarray) -> pa.Array:
    """A 1-D integer or floating numpy array (not bool: Arrow packs those into bits) as an Arrow
    array over the same memory (a copy only when it is strided), without ``pa.array``'s
    masked-array check: its first use imports numpy.ma (~17 ms, 3 % of ``imupipe ingest`` of a
    1 h recording)."""
    values = np.ascontiguousarray(values)
    return pa.Array.from_buffers(pa.from_numpy_dtype(values.dtype), len(values), [None, pa.py_buffer(values)])


def vectors(table: pa.Table, name: str) -> np.ndarray:
    """(n, k) a fixed-size-list column of a table (a null row: NaNs)."""
    col = table.column(name).combine_chunks()
    k = col.type.list_size
    if col.null_count:  # rare: a null row reads as NaNs
        return np.array([[np.nan] * k if r is None else r for r in col.to_pylist()], float).reshape(-1, k)
    # the (possibly sliced) rows' child values: flatten() without importing pyarrow.compute
    return col.values.slice(col.offset * k, len(col) * k).to_numpy(zero_copy_only=False).reshape(len(col), k)


def equals(table: pa.Table, name: str, value: str) -> np.ndarray:
    """(n,) bool: a string column equals ``value`` (compared in Arrow: no Python strings per row)."""
    import pyarrow.compute as pc

    return pc.equal(table.column(name), value).to_numpy(zero_copy_only=False)


def kept_rows(table: pa.Table, keep: np.ndarray) -> pa.Table:
    """The rows and metadata of ``table.filter(keep)``, from slices of its runs of kept rows when
    they are few (a short list of turns, a residual table's sensors)."""
    edges = np.flatnonzero(np.diff(np.r_[0, np.asarray(keep, bool).astype(np.int8), 0]))
    if len(edges) > 2 * MAX_RUNS:
        return table.filter(pa.array(keep))
    parts = [table.slice(a, b - a) for a, b in zip(edges[0::2], edges[1::2], strict=True)]
    return pa.concat_tables(parts).combine_chunks() if parts else table.slice(0, 0)
