"""MCAP writer: standard ROS 2 messages that the mcap_ros2 reference decoder reads back."""

from __future__ import annotations

from collections import Counter, defaultdict
from itertools import pairwise

import numpy as np
import pyarrow as pa
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from imupipe.components import Recording
from imupipe.readers.mcap import read_mcap
from imupipe.writers.mcap import write_mcap

T0 = 1_700_000_000_000_000_000


def triad(t, rng):
    return pa.table({"t_ns": np.asarray(t, np.int64),
                     **{c: rng.standard_normal(len(t)) for c in "xyz"}})


def decoded(path):
    """Every message in file order: (topic, schema name, log_time, publish_time, sequence, msg)."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        summary = reader.get_summary()
        msgs = [(c.topic, s.name, s.encoding, c.message_encoding, m.log_time, m.publish_time,
                 m.sequence, d)
                for s, c, m, d in reader.iter_decoded_messages(log_time_order=False)]
    return header, summary, msgs


@pytest.fixture
def recording():
    rng = np.random.default_rng(11)
    t = T0 + np.arange(400, dtype=np.int64) * 1_000_000
    return Recording(source="test", devices={
        "imu0": {"accel": triad(t, rng), "gyro": triad(t, rng), "mag": triad(t[::4], rng),
                 "temperature": pa.table({"t_ns": t[::20], "temperature": 20 + rng.random(20)})},
    })


def test_reference_decoder_reads_standard_messages(tmp_path, recording):
    path = tmp_path / "rec.mcap"
    write_mcap(path, recording, chunk_size=8192)
    header, _, msgs = decoded(path)
    assert header.profile == "ros2"
    topics = Counter(m[0] for m in msgs)
    assert topics == {"/imu0/imu": 400, "/imu0/mag": 100, "/imu0/temperature": 20}
    assert {(m[0], m[1], m[2], m[3]) for m in msgs} == {
        ("/imu0/imu", "sensor_msgs/msg/Imu", "ros2msg", "cdr"),
        ("/imu0/mag", "sensor_msgs/msg/MagneticField", "ros2msg", "cdr"),
        ("/imu0/temperature", "sensor_msgs/msg/Temperature", "ros2msg", "cdr")}
    values = defaultdict(list)
    for topic, _, _, _, log_time, publish_time, sequence, msg in msgs:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert stamp == log_time == publish_time
        assert msg.header.frame_id == "imu0"
        values[topic].append((stamp, sequence, msg))
    imu = values["/imu0/imu"]
    accel, gyro = recording.devices["imu0"]["accel"], recording.devices["imu0"]["gyro"]
    assert [s for _, s, _ in imu] == list(range(400))
    np.testing.assert_array_equal([t for t, _, _ in imu], accel.column("t_ns").to_numpy())
    for c in "xyz":
        np.testing.assert_array_equal([getattr(m.linear_acceleration, c) for *_, m in imu],
                                      accel.column(c).to_numpy())
        np.testing.assert_array_equal([getattr(m.angular_velocity, c) for *_, m in imu],
                                      gyro.column(c).to_numpy())
    for *_, m in imu:  # REP-145: no orientation; both parts present (covariance unknown = 0)
        assert m.orientation_covariance[0] == -1
        assert m.linear_acceleration_covariance[0] == 0 and m.angular_velocity_covariance[0] == 0
    mag = recording.devices["imu0"]["mag"]
    np.testing.assert_array_equal([m.magnetic_field.y for *_, m in values["/imu0/mag"]],
                                  mag.column("y").to_numpy())
    temp = recording.devices["imu0"]["temperature"]
    np.testing.assert_array_equal([m.temperature for *_, m in values["/imu0/temperature"]],
                                  temp.column("temperature").to_numpy())
    assert all(m.variance == 0 for *_, m in values["/imu0/temperature"])


def test_topics_are_interleaved_by_time(tmp_path, recording):
    path = tmp_path / "rec.mcap"
    write_mcap(path, recording, chunk_size=8192)
    _, summary, msgs = decoded(path)
    log_times = [m[4] for m in msgs]
    assert log_times == sorted(log_times)
    switches = sum(a[0] != b[0] for a, b in pairwise(msgs))
    assert switches > 150  # mag and temperature messages sit between Imu messages
    assert len(summary.chunk_indexes) > 3
    assert all(c.compression == "zstd" for c in summary.chunk_indexes)


def test_accel_and_gyro_on_different_stamps_get_separate_messages(tmp_path):
    rng = np.random.default_rng(2)
    accel, gyro = triad([0, 10, 20], rng), triad([0, 15, 20], rng)
    path = tmp_path / "split.mcap"
    write_mcap(path, Recording("t", {"imu": {"accel": accel, "gyro": gyro}}))
    _, summary, msgs = decoded(path)
    assert [s.name for s in summary.schemas.values()] == ["sensor_msgs/msg/Imu"]  # only used
    assert [(m[0], m[4], m[6]) for m in msgs] == [("/imu/imu", t, i) for i, t in
                                                 enumerate([0, 10, 15, 20])]
    m = [d for *_, d in msgs]
    assert [x.linear_acceleration_covariance[0] for x in m] == [0, 0, -1, 0]
    assert [x.angular_velocity_covariance[0] for x in m] == [0, -1, 0, 0]
    assert m[1].linear_acceleration.x == accel.column("x")[1].as_py()
    assert m[2].angular_velocity.z == gyro.column("z")[1].as_py()
    assert (m[1].angular_velocity.x, m[2].linear_acceleration.x) == (0, 0)
    back = read_mcap(path)  # and the reader undoes the split
    assert back.devices["imu"]["accel"].column("t_ns").to_pylist() == [0, 10, 20]
    assert back.devices["imu"]["gyro"].column("x").to_pylist() == gyro.column("x").to_pylist()


def test_stamps_split_into_sec_and_nanosec(tmp_path):
    rng = np.random.default_rng(4)
    t = [0, 7, 1_500_000_000, 2**31 * 1_000_000_000 - 1]
    path = tmp_path / "stamps.mcap"
    write_mcap(path, Recording("t", {"imu": {"mag": triad(t, rng)}}))
    _, _, msgs = decoded(path)
    stamps = [(m[7].header.stamp.sec, m[7].header.stamp.nanosec) for m in msgs]
    assert stamps == [(0, 0), (0, 7), (1, 500_000_000), (2**31 - 1, 999_999_999)]
    # a zero stamp reads back as log_time, which is the same zero
    assert read_mcap(path).devices["imu"]["mag"].column("t_ns").to_pylist() == t
    with pytest.raises(ValueError, match="shift t_ns"):
        write_mcap(path, Recording("t", {"imu": {"mag": triad([-1, 0], rng)}}))


@pytest.mark.parametrize("compression, name", [("lz4", "lz4"), ("none", "")])
def test_compression_choices(tmp_path, recording, compression, name):
    path = tmp_path / f"{compression}.mcap"
    write_mcap(path, recording, compression=compression, chunk_size=8192)
    _, summary, msgs = decoded(path)
    assert {c.compression for c in summary.chunk_indexes} == {name}
    assert len(msgs) == 520
    with pytest.raises(ValueError, match="compression must be one of"):
        write_mcap(tmp_path / "x.mcap", recording, compression="bz2")


def test_failed_write_leaves_the_old_file_and_no_partial_file(tmp_path, recording):
    path = tmp_path / "rec.mcap"
    path.write_bytes(b"old")
    broken = Recording("t", {"imu": {"accel": pa.table({"t_ns": [1, 2], "x": [0.0, 1.0]})}})
    with pytest.raises(KeyError):
        write_mcap(path, broken)  # no y, z columns
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["rec.mcap"]
