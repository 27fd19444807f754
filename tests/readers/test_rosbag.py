"""ROS 1 ``.bag`` and ROS 2 ``.db3`` bags: the same messages give the MCAP path's tables.

The same messages (two IMUs, REP-145 split messages, an unstamped message, a
magnetometer, a temperature and an unrelated topic) are written with ``rosbags``
to a ROS 1 bag, a ROS 2 SQLite bag and a ROS 2 MCAP bag; imupipe reads the first
two with the ``rosbag`` reader and the ``.mcap`` with its own MCAP reader.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import imupipe.readers
from imupipe.errors import ReaderError
from imupipe.ingest import read_recording
from imupipe.plugins import make_registry

rosbags = pytest.importorskip("rosbags", reason="needs the ros extra (rosbags)")
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.LATEST)
T = STORE.types
T0 = 1_700_000_000_000_000_000
N = 60


def _header(t_ns: int, frame: str):
    stamp = T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def _vec(v):
    return T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def messages() -> list[tuple[str, str, int, object]]:
    """(topic, msgtype, receive time ns, message), in receive-time order."""
    rng = np.random.default_rng(3)
    out = []
    for i in range(N):
        t = T0 + i * 5_000_000
        for topic in ("/imu0/imu", "/imu1/data"):
            acc_cov, gyro_cov = np.zeros(9), np.zeros(9)
            if topic == "/imu0/imu" and i % 4 == 1:
                acc_cov[0] = -1.0  # REP-145: this message carries no accelerometer sample
            stamp = 0 if (topic == "/imu1/data" and i == 7) else t - 1_000  # one unstamped
            msg = T["sensor_msgs/msg/Imu"](
                header=_header(stamp, "imu_link"),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.full(9, -1.0),
                angular_velocity=_vec(rng.normal(0, 0.01, 3)), angular_velocity_covariance=gyro_cov,
                linear_acceleration=_vec(rng.normal([0, 0, 9.81], 0.05)),
                linear_acceleration_covariance=acc_cov)
            out.append((topic, "sensor_msgs/msg/Imu", t + (topic == "/imu1/data"), msg))
        if i % 5 == 0:
            mag = T["sensor_msgs/msg/MagneticField"](
                header=_header(t + 7, "mag"), magnetic_field=_vec(rng.normal(2e-5, 1e-7, 3)),
                magnetic_field_covariance=np.zeros(9))
            temp = T["sensor_msgs/msg/Temperature"](header=_header(t + 9, "imu_link"),
                                                    temperature=30.0 + i / N, variance=0.0)
            out += [("/imu0/mag", "sensor_msgs/msg/MagneticField", t + 2, mag),
                    ("/imu0/temperature", "sensor_msgs/msg/Temperature", t + 3, temp)]
        status = T["std_msgs/msg/String"](data="ok")
        out.append(("/status", "std_msgs/msg/String", t + 4, status))
    return out


def write_ros1(path: Path) -> Path:
    with Writer1(path) as writer:
        conns = {}
        for topic, msgtype, t, msg in messages():
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=STORE)
            writer.write(conns[topic], t, STORE.serialize_ros1(msg, msgtype))
    return path


def write_ros2(folder: Path, storage: StoragePlugin) -> Path:
    with Writer2(folder, version=8, storage_plugin=storage) as writer:
        conns = {}
        for topic, msgtype, t, msg in messages():
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=STORE)
            writer.write(conns[topic], t, STORE.serialize_cdr(msg, msgtype))
    return folder


@pytest.fixture
def registry():
    return make_registry([imupipe.readers], entry_points_too=False)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("bags")
    return {"ros1": write_ros1(root / "s.bag"),
            "db3": write_ros2(root / "sqlite", StoragePlugin.SQLITE3),
            "mcap": write_ros2(root / "mcap", StoragePlugin.MCAP)}


def test_bag_db3_and_mcap_give_identical_tables(bags, registry):
    via_mcap = read_recording(next(bags["mcap"].glob("*.mcap")), registry)
    db3_file = next(bags["db3"].glob("*.db3"))
    for path in (bags["ros1"], bags["db3"] / "metadata.yaml", db3_file):
        rec = read_recording(path, registry)
        assert sorted(rec.devices) == sorted(via_mcap.devices) == ["imu0", "imu1"]
        for device, streams in via_mcap.devices.items():
            assert sorted(rec.devices[device]) == sorted(streams)
            for stream, table in streams.items():
                assert rec.devices[device][stream].equals(table, check_metadata=True), (
                    path, device, stream)
    imu0 = via_mcap.devices["imu0"]
    assert imu0["accel"].num_rows == N - N // 4 and imu0["gyro"].num_rows == N  # REP-145
    assert sorted(imu0) == ["accel", "gyro", "mag", "temperature"]
    t = via_mcap.devices["imu1"]["accel"].column("t_ns").to_numpy()
    assert t[7] == T0 + 7 * 5_000_000 + 1  # unstamped: the receive time
    meta = imu0["accel"].schema.metadata
    assert meta[b"imupipe.topic"] == b"/imu0/imu" and meta[b"imupipe.frame_convention"] == b"FLU"


def test_reader_is_chosen_by_the_file(bags, registry):
    from imupipe.ingest import choose_reader

    assert choose_reader(bags["ros1"], registry).name == "rosbag"
    assert choose_reader(bags["db3"] / "metadata.yaml", registry).name == "rosbag"
    reader = choose_reader(next(bags["db3"].glob("*.db3")), registry)
    assert reader.name == "rosbag"
    assert reader.inputs(bags["db3"] / "metadata.yaml") == sorted(bags["db3"].glob("*.db3"))


def test_truncated_ros1_bag(bags, tmp_path, registry):
    cut = tmp_path / "cut.bag"
    data = bags["ros1"].read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ReaderError, match=r"cut.bag: not a readable ROS bag .*rosbag reindex"):
        read_recording(cut, registry)


def test_bag_without_imu_topics(tmp_path, registry):
    path = tmp_path / "status.bag"
    with Writer1(path) as writer:
        conn = writer.add_connection("/status", "std_msgs/msg/String", typestore=STORE)
        writer.write(conn, T0, STORE.serialize_ros1(T["std_msgs/msg/String"](data="x"),
                                                    "std_msgs/msg/String"))
    with pytest.raises(ReaderError, match=r"no ROS 2 IMU topic .*topics found: /status "
                                          r"\(std_msgs/msg/String\)"):
        read_recording(path, registry)


def test_db3_without_its_metadata(bags, tmp_path, registry):
    lone = tmp_path / "lone.db3"
    lone.write_bytes(next(bags["db3"].glob("*.db3")).read_bytes())
    with pytest.raises(ReaderError, match="without the bag's metadata.yaml"):
        read_recording(lone, registry)


def test_cli_bad_bag_exits_2(tmp_path, capsys):
    from imupipe import cli

    bad = tmp_path / "bad.bag"
    bad.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 100)
    assert cli.main(["ingest", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.bag: not a readable ROS bag" in err


def test_a_bag_folder_is_one_session(bags, registry):
    from imupipe.pipeline.api import expand_inputs, session_ids

    root = bags["ros1"].parent
    found = expand_inputs([str(root)], registry)
    assert found == [bags["mcap"] / "metadata.yaml", bags["ros1"].resolve(),
                     bags["db3"] / "metadata.yaml"]
    assert session_ids(found) == ["mcap", "s", "sqlite"]
