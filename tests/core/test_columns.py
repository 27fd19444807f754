"""imupipe.columns: fixed-size-list columns as numpy and masked rows of a table, as Arrow's own
flatten and filter give them, without importing pyarrow.compute where it is not needed."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pyarrow as pa
import pytest

from imupipe.columns import MAX_RUNS, arrow_column, kept_rows, vectors


@pytest.mark.parametrize("values", [np.arange(5, dtype=np.int64), np.linspace(-1.0, 2.0, 7),
                                    np.arange(12.0).reshape(3, 4)[1], np.arange(12.0).reshape(3, 4)[:, 2]])
def test_arrow_column_is_pa_array_of_the_same_values(values):
    """The same array as ``pa.array`` gives, over the numpy memory where it is contiguous (a
    row of a 2-D array, as the MCAP reader passes), copied where it is strided."""
    col = arrow_column(values)
    assert col.equals(pa.array(values)) and col.type == pa.array(values).type
    if values.flags.c_contiguous:
        assert col.buffers()[1].address == values.ctypes.data


def _table(n: int = 40) -> pa.Table:
    v = np.arange(3.0 * n).reshape(n, 3)
    return pa.table({"t": np.arange(n, dtype=np.int64),
                     "v": pa.FixedSizeListArray.from_arrays(pa.array(v.ravel()), 3),
                     "s": pa.array([f"r{i}" for i in range(n)])},
                    metadata={b"imupipe.schema": b"x"})


def _masks(n: int):
    rng = np.random.default_rng(0)
    yield np.zeros(n, bool)
    yield np.ones(n, bool)
    yield np.arange(n) >= n // 2
    yield rng.random(n) < 0.7
    yield np.arange(n) % 2 == 0  # n / 2 runs


@pytest.mark.parametrize("n", [5, 40, 4 * MAX_RUNS])  # the last: more runs than MAX_RUNS
def test_kept_rows_are_arrows_filter(n):
    whole = _table(n)
    for table in (whole, whole.slice(1, n - 2), pa.concat_tables([whole.slice(0, 3), whole.slice(3)])):
        for keep in _masks(table.num_rows):
            got, want = kept_rows(table, keep), table.filter(pa.array(keep))
            assert got.equals(want, check_metadata=True)


def test_vectors_of_sliced_and_chunked_columns_and_null_rows():
    table = _table(10)
    want = np.arange(30.0).reshape(10, 3)
    np.testing.assert_array_equal(vectors(table, "v"), want)
    np.testing.assert_array_equal(vectors(table.slice(3, 4), "v"), want[3:7])
    chunked = pa.concat_tables([table.slice(0, 4), table.slice(4)])
    np.testing.assert_array_equal(vectors(chunked, "v"), want)
    with_null = pa.table({"v": pa.array([[1.0, 2.0], None, [5.0, 6.0]], type=pa.list_(pa.float64(), 2))})
    np.testing.assert_array_equal(vectors(with_null, "v"), [[1.0, 2.0], [np.nan, np.nan], [5.0, 6.0]])


def test_neither_imports_pyarrow_compute():
    code = ("import sys, numpy as np, pyarrow as pa\n"
            "from imupipe.columns import kept_rows, vectors\n"
            "t = pa.table({'v': pa.FixedSizeListArray.from_arrays(pa.array(np.arange(12.0)), 3)})\n"
            "kept_rows(t, np.array([1, 0, 1, 1], bool)); vectors(t.slice(1), 'v')\n"
            "assert 'pyarrow.compute' not in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True)
