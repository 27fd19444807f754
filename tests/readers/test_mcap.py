"""MCAP reader: the vectorised fast path, the generic fallback and the mcap_ros2
reference decoder give identical arrays; REP-145, stamps and device naming."""

from __future__ import annotations

import logging
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import IndexType, Writer
from mcap_ros2.decoder import DecoderFactory

from imupipe.cli import main
from imupipe.ingest import choose_reader, read_recording
from imupipe.io import read_arrow
from imupipe.plugins import make_registry
from imupipe.readers.mcap import McapReader, device_names, read_mcap
from imupipe.writers.mcap import SCHEMA_TEXT, write_mcap

LOGGER = "imupipe.readers.mcap"
COLUMNS = {"accel": "xyz", "gyro": "xyz", "mag": "xyz", "temperature": ("temperature",)}


def reference(path: Path) -> dict[tuple[str, str], dict[str, np.ndarray]]:
    """Decode message by message with mcap_ros2 in file order, applying REP-145 and the
    stamp rule."""
    rows = defaultdict(list)
    with open(path, "rb") as f:
        reader = NonSeekingReader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
            device = channel.topic.rsplit("/", 1)[0].strip("/") or "imu"
            t = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec or message.log_time
            if schema.name == "sensor_msgs/msg/Imu":
                if msg.linear_acceleration_covariance[0] != -1:
                    a = msg.linear_acceleration
                    rows[device, "accel"].append((t, a.x, a.y, a.z))
                if msg.angular_velocity_covariance[0] != -1:
                    g = msg.angular_velocity
                    rows[device, "gyro"].append((t, g.x, g.y, g.z))
            elif schema.name == "sensor_msgs/msg/MagneticField":
                m = msg.magnetic_field
                rows[device, "mag"].append((t, m.x, m.y, m.z))
            elif schema.name == "sensor_msgs/msg/Temperature":
                rows[device, "temperature"].append((t, msg.temperature))
    out = {}
    for key, values in rows.items():
        columns = list(zip(*values))
        out[key] = {"t_ns": np.array(columns[0], np.int64),
                    **{c: np.array(v, np.float64) for c, v in zip(COLUMNS[key[1]], columns[1:])}}
    return out


def arrays(recording) -> dict[tuple[str, str], dict[str, np.ndarray]]:
    return {(device, stream): {c: table.column(c).to_numpy() for c in table.column_names}
            for device, streams in recording.devices.items() for stream, table in streams.items()}


def assert_same(actual: dict, expected: dict) -> None:
    assert sorted(actual) == sorted(expected)
    for key, columns in expected.items():
        assert sorted(actual[key]) == sorted(columns), key
        for column, e in columns.items():
            a = actual[key][column]
            assert a.dtype == e.dtype, (key, column)
            np.testing.assert_array_equal(a, e, err_msg=f"{key} {column}")


def fallback_messages(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == LOGGER and "generic ROS 2 decoder" in r.getMessage()]


def test_fast_path_equals_generic_and_reference_decoder(tmp_path, mcap_kit, caplog):
    recording = mcap_kit.synthetic_recording()
    path = tmp_path / "two_imus.mcap"
    write_mcap(path, recording, chunk_size=16_384)
    with open(path, "rb") as f:
        assert len(make_reader(f).get_summary().chunk_indexes) > 5  # several chunks

    with caplog.at_level(logging.INFO, logger=LOGGER):
        fast = read_mcap(path)
        assert fallback_messages(caplog) == []  # the fast path did the work
        generic = read_mcap(path, fast=False)
        assert fallback_messages(caplog)  # ... and this one went the other way

    assert_same(arrays(fast), arrays(generic))
    assert_same(arrays(fast), reference(path))
    assert_same(arrays(fast), arrays(recording))  # and the writer lost nothing
    table = fast.devices["imu0"]["accel"]
    assert table.schema.metadata[b"imupipe.schema"] == b"accel"
    assert table.schema.metadata[b"imupipe.topic"] == b"/imu0/imu"


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_other_chunk_compressions_take_the_fast_path(tmp_path, mcap_kit, caplog, compression):
    path = tmp_path / f"{compression}.mcap"
    write_mcap(path, mcap_kit.synthetic_recording(seed=1, n=600), compression=compression,
               chunk_size=8192)
    with caplog.at_level(logging.INFO, logger=LOGGER):
        fast = read_mcap(path)
    assert fallback_messages(caplog) == []
    assert_same(arrays(fast), reference(path))


def _fallback_file(tmp_path, mcap_kit, case: str):
    rng = np.random.default_rng(7)
    n = 300
    t = mcap_kit.T0_NS + np.arange(n, dtype=np.int64) * 2_000_000
    gyro, accel = rng.standard_normal((n, 3)), rng.standard_normal((n, 3))
    options, encoding = {}, {}
    if case == "unindexed":
        options = {"use_chunking": False, "index_types": IndexType.NONE, "use_summary": False}
    elif case == "no message index":
        options = {"index_types": IndexType.CHUNK}
    elif case == "summary without channels":
        options = {"repeat_channels": False}
    elif case == "big-endian CDR":
        encoding = {"big_endian": True}
    elif case == "trailing bytes":
        encoding = {"trailing": b"\0" * 8}
    messages = mcap_kit.imu_messages("/imu/imu", t, gyro, accel, **encoding)
    path = mcap_kit.write_raw(tmp_path / "f.mcap", messages, **options)
    expected = {("imu", "accel"): {"t_ns": t, **dict(zip("xyz", accel.T))},
                ("imu", "gyro"): {"t_ns": t, **dict(zip("xyz", gyro.T))}}
    return path, expected


@pytest.mark.parametrize("case", ["unindexed", "no message index", "summary without channels",
                                  "big-endian CDR", "trailing bytes"])
def test_layouts_the_fast_path_does_not_cover_fall_back(tmp_path, mcap_kit, caplog, case):
    path, expected = _fallback_file(tmp_path, mcap_kit, case)
    with caplog.at_level(logging.INFO, logger=LOGGER):
        recording = read_mcap(path)
    assert len(fallback_messages(caplog)) == 1
    assert_same(arrays(recording), expected)
    assert_same(arrays(recording), reference(path))


def test_many_batches_through_the_reused_buffers(tmp_path, mcap_kit, monkeypatch, caplog):
    """Small batches: buffers are reused many times over; results stay identical."""
    from imupipe.readers import mcap as reader

    path = tmp_path / "batches.mcap"
    write_mcap(path, mcap_kit.synthetic_recording(seed=9, n=3000), chunk_size=4096)
    monkeypatch.setattr(reader, "BATCH_BYTES", 10_000)
    with caplog.at_level(logging.INFO, logger=LOGGER):
        fast = read_mcap(path)
    assert fallback_messages(caplog) == []
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(list(reader._batches(chunks))) > 3 * (reader.LOOKAHEAD + 1)
    assert_same(arrays(fast), reference(path))


def test_two_channels_on_one_topic_merge_in_file_order(tmp_path, mcap_kit, caplog):
    """Two publishers on one topic (two channel ids), without statistics: one stream."""
    kit = mcap_kit
    path = tmp_path / "two_channels.mcap"
    t = kit.T0_NS + np.arange(400, dtype=np.int64) * 1_000_000
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=2048, use_statistics=False)
        w.start("ros2", "test")
        schema = w.register_schema("sensor_msgs/msg/MagneticField", "ros2msg", SCHEMA_TEXT["mag"])
        channels = [w.register_channel("/m/mag", "cdr", schema) for _ in range(2)]
        for i, ti in enumerate(t.tolist()):
            data = kit.cdr_message(*divmod(ti, 1_000_000_000), "m", [i, 2 * i, 3 * i] + [0] * 9)
            w.add_message(channels[i % 2 if i < 200 else (i // 7) % 2], ti, data, ti)
        w.finish()
    with caplog.at_level(logging.INFO, logger=LOGGER):
        fast = read_mcap(path)
    assert fallback_messages(caplog) == []
    mag = fast.devices["m"]["mag"]
    np.testing.assert_array_equal(mag.column("t_ns").to_numpy(), t)
    np.testing.assert_array_equal(mag.column("z").to_numpy(), 3.0 * np.arange(400))
    assert_same(arrays(fast), arrays(read_mcap(path, fast=False)))


def test_frame_ids_of_different_lengths_in_one_chunk(tmp_path, mcap_kit, caplog):
    """The float block's offset depends on the frame_id length: computed per message."""
    rng = np.random.default_rng(3)
    n = 500
    t = mcap_kit.T0_NS + np.arange(n, dtype=np.int64) * 1_000_000
    gyro, accel = rng.standard_normal((n, 3)), rng.standard_normal((n, 3))
    frames = ["", "a", "imu_link", "a_rather_longer_frame_id"]
    messages = []
    for i in range(n):
        sec, nanosec = divmod(int(t[i]), 1_000_000_000)
        data = mcap_kit.cdr_message(sec, nanosec, frames[i % 4],
                                    mcap_kit.imu_block(gyro[i].tolist(), accel[i].tolist()))
        messages.append(("/imu/imu", "imu", int(t[i]), data))
    path = mcap_kit.write_raw(tmp_path / "frames.mcap", messages, chunk_size=1 << 20)
    with caplog.at_level(logging.INFO, logger=LOGGER):
        recording = read_mcap(path)
    assert fallback_messages(caplog) == []
    np.testing.assert_array_equal(recording.devices["imu"]["accel"].column("x").to_numpy(),
                                  accel[:, 0])
    np.testing.assert_array_equal(recording.devices["imu"]["gyro"].column("z").to_numpy(),
                                  gyro[:, 2])


def test_rep145_flags_and_zero_stamps(tmp_path, mcap_kit):
    """covariance[0] = -1 drops that part; a zero header stamp falls back to log_time."""
    kit = mcap_kit
    msgs = [
        ("/imu", "imu", 10, kit.cdr_message(0, 0, "f", kit.imu_block((1, 2, 3), (4, 5, 6)))),
        ("/imu", "imu", 20, kit.cdr_message(5, 7, "f", kit.imu_block((7, 8, 9), accel_cov0=-1))),
        ("/imu", "imu", 30, kit.cdr_message(6, 0, "f", kit.imu_block(accel=(1, 1, 1),
                                                                     gyro_cov0=-1))),
        ("/gyro_only/imu", "imu", 40,
         kit.cdr_message(7, 0, "g", kit.imu_block((3, 3, 3), accel_cov0=-1))),
    ]
    path = kit.write_raw(tmp_path / "rep145.mcap", msgs)
    for fast in (True, False):
        rec = arrays(read_mcap(path, fast=fast))
        assert sorted(rec) == [("gyro_only", "gyro"), ("imu", "accel"), ("imu", "gyro")]
        np.testing.assert_array_equal(rec["imu", "accel"]["t_ns"], [10, 6_000_000_000])
        np.testing.assert_array_equal(rec["imu", "accel"]["z"], [6, 1])
        np.testing.assert_array_equal(rec["imu", "gyro"]["t_ns"], [10, 5_000_000_007])
        np.testing.assert_array_equal(rec["imu", "gyro"]["x"], [1, 7])


def test_other_topics_are_ignored(tmp_path, mcap_kit):
    kit = mcap_kit
    chatter = b"\x00\x01\x00\x00\x06\x00\x00\x00hello\x00"
    msgs = [("/chatter", "std_msgs/msg/String", 5, chatter),
            ("/imu/imu", "imu", 10,
             kit.cdr_message(1, 0, "f", kit.imu_block((1, 2, 3), (4, 5, 6))))]
    path = kit.write_raw(tmp_path / "mixed.mcap", msgs,
                         extra_schemas=[("std_msgs/msg/String", "string data")])
    rec = read_mcap(path)
    assert list(rec.devices) == ["imu"]
    assert rec.devices["imu"]["accel"].column("y").to_pylist() == [5.0]


def test_device_names_from_topic_namespaces():
    names = device_names([("/imu0/imu", "imu"), ("/imu0/mag", "mag"), ("/imu", "imu"),
                          ("/robot/imu1/imu", "imu")])
    assert names == {("/imu0/imu", "imu"): "imu0", ("/imu0/mag", "mag"): "imu0",
                     ("/imu", "imu"): "imu", ("/robot/imu1/imu", "imu"): "robot/imu1"}
    with pytest.warns(UserWarning, match="shares namespace"):
        names = device_names([("/imu/data", "imu"), ("/imu/data_raw", "imu")])
    assert names == {("/imu/data", "imu"): "imu/data", ("/imu/data_raw", "imu"): "imu/data_raw"}


def test_registered_reader_claims_mcap_files(tmp_path, mcap_kit):
    path = tmp_path / "no_suffix.bin"
    write_mcap(path, mcap_kit.synthetic_recording(n=100))
    registry = make_registry()
    assert isinstance(choose_reader(path, registry), McapReader)
    reader = registry.get("readers", "mcap")
    assert reader.sniff(path, path.read_bytes()[:64])
    assert reader.sniff(Path("x.MCAP"), b"")  # by suffix, so a broken .mcap gets MCAP errors
    assert not reader.sniff(Path("x.csv"), b"t_ns,accel_x\n")
    rec = read_recording(path, registry)
    assert set(rec.devices) == {"imu0", "imu1"}


def test_cli_ingest_gives_the_reference_decoders_values(tmp_path, mcap_kit):
    path = tmp_path / "session.mcap"
    write_mcap(path, mcap_kit.synthetic_recording(seed=5, n=1500), chunk_size=32_768)
    out = tmp_path / "tables"
    assert main(["ingest", str(path), "--out", str(out), "--quiet"]) == 0
    written = {(p.parent.name, p.stem): read_arrow(p) for p in out.glob("*/*.arrow")}
    actual = {key: {c: t.column(c).to_numpy() for c in t.column_names}
              for key, t in written.items()}
    assert_same(actual, reference(path))
