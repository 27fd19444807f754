"""Canonical CSV reader and the column parser manifests use."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import imupipe.readers
from imupipe import schemas
from imupipe.cli import main
from imupipe.errors import ReaderError
from imupipe.ingest import read_recording
from imupipe.plugins import make_registry
from imupipe.readers import csv as csv_reader
from imupipe.readers.csv import CanonicalCsvReader, read_columns

HEADER = "t_ns,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z,mag_x,mag_y,mag_z,temperature"


@pytest.fixture
def registry():
    return make_registry([imupipe.readers], entry_points_too=False)


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def canonical_rows(n: int, seed: int = 3) -> tuple[str, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    values = rng.normal(size=(n, 10))
    t = np.arange(n, dtype=np.int64) * 10_000_000 + 1_700_000_000_000_000_000
    lines = [HEADER] + [f"{t[i]}," + ",".join(repr(float(v)) for v in values[i]) for i in range(n)]
    return "\n".join(lines) + "\n", t, values


def test_canonical_csv_round_trips_every_value(tmp_path, registry):
    text, t_expected, expected = canonical_rows(50)
    path = write(tmp_path / "session.csv", text)
    rec = read_recording(path, registry)
    streams = rec.device()
    assert sorted(streams) == ["accel", "gyro", "mag", "temperature"]
    t = streams["accel"].column("t_ns").to_numpy()
    assert t.dtype == np.int64
    np.testing.assert_array_equal(t, t_expected)  # exact: no float round trip of 1.7e18 ns
    for k, stream in enumerate(["accel", "gyro", "mag"]):
        got = np.column_stack([streams[stream].column(c).to_numpy() for c in "xyz"])
        np.testing.assert_array_equal(got, expected[:, 3 * k: 3 + 3 * k])
        schemas.check(streams[stream], stream)
    np.testing.assert_array_equal(streams["temperature"].column("temperature").to_numpy(),
                                  expected[:, 9])


def test_any_subset_of_triads(tmp_path, registry):
    path = write(tmp_path / "g.csv", "t_ns,gyro_x,gyro_y,gyro_z\n0,0.1,0.2,0.3\n5,0.1,0.2,0.4\n")
    rec = read_recording(path, registry)
    assert list(rec.device()) == ["gyro"]
    assert rec.device()["gyro"].column("z").to_pylist() == [0.3, 0.4]


def test_sniff_claims_only_the_canonical_header(tmp_path):
    reader = CanonicalCsvReader()
    good = write(tmp_path / "a.csv", HEADER + "\n0" + ",0" * 10 + "\n")
    other = write(tmp_path / "b.csv", "n_samples,acc_x\n0,1\n")
    wrong_suffix = write(tmp_path / "c.txt", HEADER + "\n")
    assert reader.sniff(good, good.read_bytes()[:64])
    assert not reader.sniff(other, other.read_bytes()[:64])
    assert not reader.sniff(wrong_suffix, wrong_suffix.read_bytes()[:64])


BAD = {
    "missing": ("t_ns,accel_x,accel_y,temperature\n0,1,2,20\n", "missing column(s) accel_z"),
    "unparseable": ("t_ns,accel_x,accel_y,accel_z\n0,1,2,3\n1,1,2,3\n2,1,x7,3\n",
                    "line 4: 'x7', not a number in column 'accel_y'"),
    "empty_value": ("t_ns,accel_x,accel_y,accel_z\n0,1,2,3\n1,1,,3\n", "line 3: an empty value"),
    "nan": ("t_ns,accel_x,accel_y,accel_z\n0,1,2,3\n1,1,2,nan\n",
            "line 3: non-finite value 'nan' in column 'accel_z'"),
    "empty": ("", "the file is empty"),
    "header_only": ("t_ns,accel_x,accel_y,accel_z\n", "has no data rows"),
    "float_time": ("t_ns,accel_x,accel_y,accel_z\n0.5,1,2,3\n", "line 2: '0.5', not a number"),
    "unknown_column": ("t_ns,accel_x,accel_y,accel_z,pressure\n0,1,2,3,4\n",
                       "unknown column(s) pressure"),
    "backwards": ("t_ns,accel_x,accel_y,accel_z\n10,1,2,3\n5,1,2,3\n", "time goes backwards"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_csv_is_one_line_exit_2_and_writes_nothing(case, tmp_path, capsys):
    text, expected = BAD[case]
    path = write(tmp_path / f"{case}.csv", text)
    out = tmp_path / "out"
    assert main(["ingest", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert str(path) in err and expected in err, err
    assert not out.exists()


def test_ingest_writes_canonical_tables(tmp_path, capsys):
    text, _, _ = canonical_rows(5)
    path = write(tmp_path / "s.csv", text)
    assert main(["ingest", str(path), "--out", str(tmp_path / "out")]) == 0
    written = sorted(p.name for p in (tmp_path / "out" / "imu").iterdir())
    assert written == ["accel.arrow", "gyro.arrow", "mag.arrow", "temperature.arrow"]


def test_read_columns_whitespace_no_header_and_index_refs(tmp_path):
    path = write(tmp_path / "x.mat", "  1.0e-02   3.3e+04  7\n\t2.0e-02  3.4e+04   8  \n")
    data = read_columns(path, {"t": "col0", "x": 1, "y": "col2"}, delimiter="whitespace",
                        header=False)
    np.testing.assert_array_equal(data["t"], [0.01, 0.02])
    np.testing.assert_array_equal(data["x"], [33000.0, 34000.0])
    np.testing.assert_array_equal(data["y"], [7.0, 8.0])


def test_read_columns_skips_lines_and_uses_other_delimiters(tmp_path):
    path = write(tmp_path / "x.csv", "Fs;100\nnote;x\na;b\n1;2\n3;4\n")
    data = read_columns(path, {"x": "b"}, delimiter=";", skip_lines=2)
    np.testing.assert_array_equal(data["x"], [2.0, 4.0])


def test_pyarrow_and_polars_parses_agree_bit_for_bit(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    values = rng.normal(scale=10.0 ** rng.integers(-9, 9, size=(200, 3)))
    t = 1_700_000_000_000_000_000 + np.arange(200, dtype=np.int64) * 9_999_991
    path = write(tmp_path / "x.csv", "t,a,b,c\n" + "".join(
        f"{t[i]},{float(values[i, 0])!r},{values[i, 1]:.17e},{values[i, 2]:.6g}\n" for i in range(200)))
    refs = {"t": "t", "a": "a", "b": "b", "c": "c"}
    fast = read_columns(path, refs, int_keys=("t",))
    assert csv_reader._number_columns(path, ",", 1, 4, {"a": 1}, ()) is not None  # pyarrow's parse took it
    monkeypatch.setattr(csv_reader, "_number_columns", lambda *args: None)  # polars' parse
    slow = read_columns(path, refs, int_keys=("t",))
    np.testing.assert_array_equal(fast["t"], t)
    np.testing.assert_array_equal(fast["a"], values[:, 0])
    for key in refs:
        assert fast[key].dtype == slow[key].dtype
        assert fast[key].tobytes() == slow[key].tobytes()


def test_skip_lines_counts_blank_lines(tmp_path):
    path = write(tmp_path / "x.csv", "\n\na,b\n1,2\n3,4\n5,6\n")  # two blank lines, then the header
    np.testing.assert_array_equal(read_columns(path, {"x": "b"}, skip_lines=2)["x"], [2.0, 4.0, 6.0])


def test_read_columns_names_the_known_columns(tmp_path):
    path = write(tmp_path / "x.csv", "a,b\n1,2\n")
    with pytest.raises(ReaderError, match=r"missing column 'c'; the header has: a, b"):
        read_columns(path, {"x": "c"})


def test_ragged_line_is_named(tmp_path):
    path = write(tmp_path / "x.csv", "a,b\n1,2\n3,4,5\n")
    with pytest.raises(ReaderError, match="line 3"):
        read_columns(path, {"x": "a"})


def test_infinite_value_is_rejected(tmp_path):
    path = write(tmp_path / "x.csv", "a\n1\ninf\n")
    with pytest.raises(ReaderError, match="line 3: non-finite"):
        read_columns(path, {"x": "a"})
