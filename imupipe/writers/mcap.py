"""Write a canonical recording as MCAP with standard ROS 2 messages.

Per device ``D``: ``sensor_msgs/msg/Imu`` on ``/D/imu`` (accelerometer and
gyroscope), ``sensor_msgs/msg/MagneticField`` on ``/D/mag`` and
``sensor_msgs/msg/Temperature`` on ``/D/temperature``, CDR little endian,
all topics interleaved by time as a recorder writes them. ``header.stamp``,
``log_time`` and ``publish_time`` are the sample time ``t_ns``.

REP-145: orientation is never provided (``orientation_covariance[0] = -1``).
An accelerometer and a gyroscope sample with the same stamp share one Imu
message; a sample without a partner gets a message of its own whose missing
part has ``covariance[0] = -1`` and zero values. Other covariances are zero
("unknown").
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pyarrow as pa
from mcap.writer import CompressionType, Writer

from .. import __version__
from ..components import Recording
from ..io import atomic_path
from ..readers import cdr

COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
               "none": CompressionType.NONE, "": CompressionType.NONE}

_SEP = "=" * 80
_TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec"
_HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id"
_VECTOR3 = "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z"
_QUATERNION = "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1"


def _definition(body: str, *deps: str) -> bytes:
    return "\n".join([body, *(f"{_SEP}\n{d}" for d in deps)]).encode() + b"\n"


# ros2msg schema text, with dependencies, as `ros2 bag record` stores it
SCHEMA_TEXT = {
    "imu": _definition(
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance",
        _HEADER, _TIME, _QUATERNION, _VECTOR3),
    "mag": _definition(
        "std_msgs/Header header\ngeometry_msgs/Vector3 magnetic_field\n"
        "float64[9] magnetic_field_covariance",
        _HEADER, _TIME, _VECTOR3),
    "temperature": _definition(
        "std_msgs/Header header\nfloat64 temperature\nfloat64 variance", _HEADER, _TIME),
}
TOPIC_SUFFIX = {"imu": "imu", "mag": "mag", "temperature": "temperature"}


def write_mcap(path: Path | str, recording: Recording, *, compression: str = "zstd",
               chunk_size: int = 1 << 20) -> None:
    """Write ``recording`` to ``path`` (atomically) as a ROS 2 MCAP file.

    ``compression``: ``"zstd"``, ``"lz4"`` or ``"none"``; ``chunk_size``: bytes
    of uncompressed messages per chunk.
    """
    if compression not in COMPRESSION:
        raise ValueError(f"compression must be one of {sorted(COMPRESSION)}, got {compression!r}")
    topics = []  # (topic, kind, t_ns (n,), bytes per message, all its messages as one bytes)
    for device, streams in recording.devices.items():
        for kind, (t, block) in _blocks(streams).items():
            sec, nanosec = _split_ns(t, f"{recording.source} [{device}]")
            rows = cdr.encode(kind, sec, nanosec, device, block)
            topic = f"/{device}/{TOPIC_SUFFIX[kind]}"
            topics.append((topic, kind, t, rows.shape[1], rows.tobytes()))
            del rows

    # interleave by time; ties keep topic order, as a recorder's queue would
    t_all = np.concatenate([np.empty(0, np.int64)] + [t for _, _, t, _, _ in topics])
    src = np.concatenate([np.empty(0, np.int64)] +
                         [np.full(len(t), k) for k, (_, _, t, _, _) in enumerate(topics)])
    seq = np.concatenate([np.empty(0, np.int64)] + [np.arange(len(t)) for _, _, t, _, _ in topics])
    order = np.argsort(t_all, kind="stable")

    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as f:
        writer = Writer(f, chunk_size=chunk_size, compression=COMPRESSION[compression])
        writer.start(profile="ros2", library=f"imupipe {__version__}")
        schema_ids = {}
        for kind in dict.fromkeys(kind for _, kind, _, _, _ in topics):
            schema_ids[kind] = writer.register_schema(cdr.KIND_SCHEMA[kind], "ros2msg",
                                                      SCHEMA_TEXT[kind])
        channels = [writer.register_channel(topic, "cdr", schema_ids[kind])
                    for topic, kind, _, _, _ in topics]
        add = writer.add_message
        for k, i, t in zip(src[order].tolist(), seq[order].tolist(), t_all[order].tolist()):
            size, blob = topics[k][3], topics[k][4]
            add(channels[k], t, blob[i * size:(i + 1) * size], t, i)
        writer.finish()


def _column(table: pa.Table, name: str) -> np.ndarray:
    return table.column(name).to_numpy()


def _xyz(table: pa.Table) -> np.ndarray:
    return np.column_stack([_column(table, c).astype(np.float64) for c in ("x", "y", "z")])


def _blocks(streams: Mapping[str, pa.Table]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per message kind: stamps (n,) int64 ns and float blocks (n, cdr.WORDS[kind])."""
    out = {}
    accel, gyro = streams.get("accel"), streams.get("gyro")
    if accel is not None or gyro is not None:
        out["imu"] = _imu_block(accel, gyro)
    if "mag" in streams:
        t = _column(streams["mag"], "t_ns").astype(np.int64)
        block = np.zeros((len(t), cdr.WORDS["mag"]))
        block[:, cdr.MAG_FIELD:cdr.MAG_FIELD + 3] = _xyz(streams["mag"])
        out["mag"] = (t, block)
    if "temperature" in streams:
        table = streams["temperature"]
        t = _column(table, "t_ns").astype(np.int64)
        block = np.zeros((len(t), cdr.WORDS["temperature"]))
        block[:, cdr.TEMPERATURE] = _column(table, "temperature")  # degC, as the ROS message
        out["temperature"] = (t, block)
    return out


def _imu_block(accel: pa.Table | None, gyro: pa.Table | None) -> tuple[np.ndarray, np.ndarray]:
    """Imu messages for an accelerometer and a gyroscope stream (either may be absent)."""
    ta = _column(accel, "t_ns").astype(np.int64) if accel is not None else np.empty(0, np.int64)
    tg = _column(gyro, "t_ns").astype(np.int64) if gyro is not None else np.empty(0, np.int64)
    xa = _xyz(accel) if accel is not None else np.empty((0, 3))
    xg = _xyz(gyro) if gyro is not None else np.empty((0, 3))
    if np.array_equal(ta, tg):  # one message per sample pair (duplicates kept as they are)
        ia = ig = np.arange(len(ta))
        pair_t, a_only, g_only = ta, np.empty(0, np.int64), np.empty(0, np.int64)
    else:
        pair_t, ia, ig = np.intersect1d(ta, tg, return_indices=True)
        a_only = np.setdiff1d(np.arange(len(ta)), ia)
        g_only = np.setdiff1d(np.arange(len(tg)), ig)
    n_pair, n_a = len(pair_t), len(a_only)
    t = np.concatenate([pair_t, ta[a_only], tg[g_only]])
    block = np.zeros((len(t), cdr.WORDS["imu"]))
    block[:, cdr.IMU_ORIENTATION + 3] = 1.0  # identity quaternion, flagged unknown below
    block[:, cdr.IMU_ORIENTATION_COV] = -1.0  # REP-145: no orientation
    acc = slice(cdr.IMU_ACCEL, cdr.IMU_ACCEL + 3)
    gyr = slice(cdr.IMU_GYRO, cdr.IMU_GYRO + 3)
    block[:n_pair, acc], block[:n_pair, gyr] = xa[ia], xg[ig]
    block[n_pair:n_pair + n_a, acc] = xa[a_only]
    block[n_pair:n_pair + n_a, cdr.IMU_GYRO_COV] = -1.0  # REP-145: no gyroscope sample
    block[n_pair + n_a:, gyr] = xg[g_only]
    block[n_pair + n_a:, cdr.IMU_ACCEL_COV] = -1.0  # REP-145: no accelerometer sample
    order = np.argsort(t, kind="stable")
    return t[order], block[order]


def _split_ns(t: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """ROS ``builtin_interfaces/Time`` (sec int32, nanosec uint32) of stamps in ns."""
    sec, nanosec = np.divmod(t, 1_000_000_000)
    if len(sec) and (sec.min() < 0 or sec.max() >= 2**31):
        raise ValueError(f"{where}: time stamps must lie in [0, 2**31) s for an MCAP log_time "
                         "and a ROS 2 stamp; shift t_ns")
    return sec, nanosec
