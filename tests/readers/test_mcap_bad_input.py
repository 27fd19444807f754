"""Bad MCAP input through the command line: exit status 2, one stderr line naming
the file and the problem, and no output tables written."""

from __future__ import annotations

import struct

import numpy as np
import pyarrow as pa
import pytest
from mcap.reader import make_reader

from imupipe.cli import main
from imupipe.components import Recording
from imupipe.writers.mcap import write_mcap


def ingest_fails(path, tmp_path, capsys) -> str:
    """Run ``imupipe ingest``; assert the failure contract; return the error line."""
    out = tmp_path / "tables"
    code = main(["ingest", str(path), "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 2, captured.err
    assert len(lines) == 1, lines
    assert str(path) in lines[0]
    assert not out.exists() or not any(out.rglob("*")), list(out.rglob("*"))
    assert captured.out == ""
    return lines[0]


def good_file(tmp_path, mcap_kit, name="good.mcap", **kwargs):
    path = tmp_path / name
    write_mcap(path, mcap_kit.synthetic_recording(n=800), chunk_size=16_384, **kwargs)
    return path


def first_chunk(path):
    """(byte offset of the first chunk's records, their length, offset of its compression name)."""
    with open(path, "rb") as f:
        index = min(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = path.read_bytes()
    at = index.chunk_start_offset
    (clen,) = struct.unpack_from("<I", data, at + 37)
    (rlen,) = struct.unpack_from("<Q", data, at + 41 + clen)
    return at + 49 + clen, rlen, at + 41


def test_truncated_file(tmp_path, mcap_kit, capsys):
    path = good_file(tmp_path, mcap_kit)
    data = path.read_bytes()
    path.write_bytes(data[:len(data) * 6 // 10])  # the recorder died mid-write
    line = ingest_fails(path, tmp_path, capsys)
    assert "truncated" in line and "mcap recover" in line


def test_truncated_file_run_twice_into_one_folder(tmp_path, mcap_kit, capsys):
    # the first run's manifest records the failure (no streams); the second must say the same
    path = good_file(tmp_path, mcap_kit)
    path.write_bytes(path.read_bytes()[:4000])
    for _ in range(2):
        assert main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
        assert "truncated" in capsys.readouterr().err


def test_file_cut_inside_the_header(tmp_path, mcap_kit, capsys):
    path = good_file(tmp_path, mcap_kit)
    path.write_bytes(path.read_bytes()[:20])
    assert "truncated" in ingest_fails(path, tmp_path, capsys)


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_bit_flipped_chunk_fails_its_crc(tmp_path, mcap_kit, capsys, compression):
    path = good_file(tmp_path, mcap_kit, compression=compression)
    start, length, _ = first_chunk(path)
    data = bytearray(path.read_bytes())
    data[start + length // 2] ^= 0x10
    path.write_bytes(bytes(data))
    line = ingest_fails(path, tmp_path, capsys)
    assert "corrupt" in line and "chunk at byte" in line


def test_unknown_chunk_compression(tmp_path, mcap_kit, capsys):
    path = good_file(tmp_path, mcap_kit)
    _, _, name_at = first_chunk(path)
    data = bytearray(path.read_bytes())
    assert data[name_at:name_at + 4] == b"zstd"
    data[name_at:name_at + 4] = b"zsxd"
    path.write_bytes(bytes(data))
    assert "compression 'zsxd'" in ingest_fails(path, tmp_path, capsys)


def test_only_unknown_schemas(tmp_path, mcap_kit, capsys):
    chatter = b"\x00\x01\x00\x00\x06\x00\x00\x00hello\x00"
    path = mcap_kit.write_raw(tmp_path / "chatter.mcap",
                              [("/chatter", "std_msgs/msg/String", t, chatter) for t in (1, 2)],
                              extra_schemas=[("std_msgs/msg/String", "string data")])
    line = ingest_fails(path, tmp_path, capsys)
    assert "no ROS 2 IMU topic" in line and "/chatter (std_msgs/msg/String)" in line


def test_empty_file(tmp_path, capsys):
    path = tmp_path / "empty.mcap"
    path.write_bytes(b"")
    assert "empty" in ingest_fails(path, tmp_path, capsys)


def test_not_an_mcap_file(tmp_path, capsys):
    path = tmp_path / "notes.mcap"
    path.write_text("t_ns,accel_x\n1,2\n")
    assert "not an MCAP file" in ingest_fails(path, tmp_path, capsys)


def test_time_going_backwards(tmp_path, mcap_kit, capsys):
    """log_time increases but the sensor's stamps jump back (a clock reset)."""
    t = mcap_kit.T0_NS + np.arange(200, dtype=np.int64) * 1_000_000
    stamps = t.copy()
    stamps[120:] -= 50_000_000
    messages = mcap_kit.imu_messages("/imu/imu", stamps, np.zeros((200, 3)), np.ones((200, 3)))
    messages = [(topic, kind, int(log), data) for (topic, kind, _, data), log in zip(messages, t)]
    path = mcap_kit.write_raw(tmp_path / "backwards.mcap", messages)
    assert "time goes backwards at sample 120" in ingest_fails(path, tmp_path, capsys)


def _recording(t, accel_x):
    zeros = np.zeros(len(t))
    table = pa.table({"t_ns": t, "x": accel_x, "y": zeros, "z": zeros})
    return Recording(source="test", devices={"imu": {"accel": table, "gyro": table}})


def test_duplicate_time_stamps(tmp_path, capsys):
    t = np.arange(100, dtype=np.int64) * 1_000_000 + 10**18
    t[50] = t[49]
    path = tmp_path / "dup.mcap"
    write_mcap(path, _recording(t, np.ones(100)))
    assert "duplicate time stamp" in ingest_fails(path, tmp_path, capsys)


def test_nan_in_a_message(tmp_path, capsys):
    t = np.arange(100, dtype=np.int64) * 1_000_000 + 10**18
    x = np.ones(100)
    x[30] = np.nan
    path = tmp_path / "nan.mcap"
    write_mcap(path, _recording(t, x))
    line = ingest_fails(path, tmp_path, capsys)
    assert "non-finite value nan in column 'x' at sample 30" in line


def test_swapped_schema_names_are_one_line(tmp_path, mcap_kit, capsys, monkeypatch):
    from imupipe.readers import cdr

    swapped = dict(cdr.KIND_SCHEMA)
    swapped["imu"], swapped["mag"] = cdr.KIND_SCHEMA["mag"], cdr.KIND_SCHEMA["imu"]
    monkeypatch.setattr(cdr, "KIND_SCHEMA", swapped)  # the writer names each schema wrongly
    path = good_file(tmp_path, mcap_kit, "swapped.mcap")
    monkeypatch.undo()
    line = ingest_fails(path, tmp_path, capsys)
    assert "does not decode as its schema" in line and "swapped schema" in line
