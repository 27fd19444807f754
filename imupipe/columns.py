"""Arrow columns as numpy arrays, read without a Python object per row."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc


def vectors(table: pa.Table, name: str) -> np.ndarray:
    """(n, k) a fixed-size-list column of a table."""
    col = table.column(name).combine_chunks()
    return col.flatten().to_numpy(zero_copy_only=False).reshape(len(col), -1)


def equals(table: pa.Table, name: str, value: str) -> np.ndarray:
    """(n,) bool: a string column equals ``value`` (compared in Arrow: no Python strings per row)."""
    return pc.equal(table.column(name), value).to_numpy(zero_copy_only=False)
