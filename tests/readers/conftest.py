"""Fixtures for reader tests: small synthetic recordings and hand-made MCAP files.

Test files get them through the ``mcap_kit`` fixture. ``cdr_message`` encodes
with ``struct``, independently of ``imupipe.readers.cdr``, so the vectorised
decoder is checked against a second encoder.
"""

from __future__ import annotations

import struct
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pyarrow as pa
import pytest
from mcap.writer import CompressionType, IndexType, Writer

from imupipe.components import Recording
from imupipe.readers import cdr
from imupipe.writers.mcap import SCHEMA_TEXT

T0_NS = 1_700_000_000_000_000_000


def triad(t: np.ndarray, rng: np.random.Generator, mean=(0.0, 0.0, 0.0), sd=1.0) -> pa.Table:
    return pa.table({"t_ns": t, **{c: m + sd * rng.standard_normal(len(t))
                                   for c, m in zip("xyz", mean)}})


def synthetic_recording(seed: int = 0, n: int = 2000) -> Recording:
    """Two IMUs. ``imu0``: accel and gyro stamps partly differ (REP-145 split messages),
    mag at a tenth of the rate, temperature; ``imu1``: accel and gyro on the same stamps."""
    rng = np.random.default_rng(seed)
    t = T0_NS + np.arange(n, dtype=np.int64) * 1_000_000 + 123
    t_gyro = t.copy()
    t_gyro[1::3] += 250_000  # every third gyro sample has no accel partner
    temp = pa.table({"t_ns": t[::50], "temperature": 25.0 + rng.standard_normal(len(t[::50]))})
    return Recording(source="synthetic", devices={
        "imu0": {"accel": triad(t, rng, (0, 0, 9.81), 0.05), "gyro": triad(t_gyro, rng, sd=0.01),
                 "mag": triad(t[::10], rng, (2e-5, 0, -4e-5), 1e-7), "temperature": temp},
        "imu1": {"accel": triad(t[:n // 2], rng, (9.81, 0, 0), 0.05),
                 "gyro": triad(t[:n // 2], rng, sd=0.01)},
    })


def imu_block(gyro=(0.0, 0.0, 0.0), accel=(0.0, 0.0, 0.0), *, gyro_cov0=0.0, accel_cov0=0.0):
    """The 37 float64 words of an Imu message (orientation unknown per REP-145)."""
    block = [0.0, 0.0, 0.0, 1.0, -1.0] + [0.0] * 8
    block += [*gyro, gyro_cov0] + [0.0] * 8
    block += [*accel, accel_cov0] + [0.0] * 8
    return block


def cdr_message(sec: int, nanosec: int, frame_id: str, block, *, big_endian: bool = False,
                trailing: bytes = b"") -> bytes:
    """A ROS 2 message: header then float64 words, CDR encoded with ``struct``."""
    e = ">" if big_endian else "<"
    name = frame_id.encode() + b"\0"
    out = bytearray((0, 0 if big_endian else 1, 0, 0))
    out += struct.pack(e + "iII", sec, nanosec, len(name)) + name
    while (len(out) - 4) % 8:
        out += b"\0"
    out += struct.pack(f"{e}{len(block)}d", *block)
    return bytes(out) + trailing


def write_raw(path: Path, messages, *, extra_schemas=(), chunk_size: int = 4096,
              compression=CompressionType.ZSTD, index_types=IndexType.ALL,
              use_chunking: bool = True, use_summary: bool = True,
              repeat_channels: bool = True) -> Path:
    """Write ``messages`` [(topic, kind, log_time_ns, data)] in the given order.

    ``kind`` is a key of ``cdr.KIND_SCHEMA`` or, for other topics, a schema name
    listed in ``extra_schemas`` [(name, text)].
    """
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=compression, index_types=index_types,
                   use_chunking=use_chunking, use_statistics=use_summary,
                   use_summary_offsets=use_summary, repeat_channels=use_summary and repeat_channels,
                   repeat_schemas=use_summary and repeat_channels)
        w.start(profile="ros2", library="imupipe-tests")
        schema_ids = {k: w.register_schema(cdr.KIND_SCHEMA[k], "ros2msg", text)
                      for k, text in SCHEMA_TEXT.items()}
        for name, text in extra_schemas:
            schema_ids[name] = w.register_schema(name, "ros2msg", text.encode())
        channels: dict[str, int] = {}
        for topic, kind, log_time, data in messages:
            if topic not in channels:
                channels[topic] = w.register_channel(topic, "cdr", schema_ids[kind])
            w.add_message(channels[topic], log_time, data, log_time)
        w.finish()
    return path


def imu_messages(topic: str, t_ns: np.ndarray, gyro: np.ndarray, accel: np.ndarray,
                 **kwargs) -> list[tuple[str, str, int, bytes]]:
    """Imu messages with both parts, stamped ``t_ns`` (log_time = stamp)."""
    out = []
    for t, g, a in zip(t_ns.tolist(), gyro.tolist(), accel.tolist()):
        sec, nanosec = divmod(t, 1_000_000_000)
        out.append((topic, "imu", t, cdr_message(sec, nanosec, "imu", imu_block(g, a), **kwargs)))
    return out


@pytest.fixture
def mcap_kit() -> SimpleNamespace:
    """The helpers above, for tests (conftest modules are not imported by name)."""
    return SimpleNamespace(T0_NS=T0_NS, triad=triad, synthetic_recording=synthetic_recording,
                           imu_block=imu_block, cdr_message=cdr_message, write_raw=write_raw,
                           imu_messages=imu_messages)
