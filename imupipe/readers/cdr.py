"""Vectorised CDR (little-endian, ROS 2) for the three IMU message types.

A ROS 2 ``sensor_msgs`` IMU message is a ``std_msgs/Header`` followed by a
fixed block of float64 words. The header holds one variable-length string
(``frame_id``), so the offset of the float block depends on that string's
length; it is computed per message, vectorised, and the words are then copied
out with one row-gather per message (no Python loop per message).

Byte layout of one message (offsets from the start of the message data)::

    0   encapsulation  00 01 00 00  (CDR, little endian)
    4   stamp.sec      int32
    8   stamp.nanosec  uint32
    12  frame_id len   uint32  (L, counting the trailing NUL)
    16  frame_id       L bytes
    4 + align8(12 + L)  float64 words (CDR aligns relative to byte 4)

Word order of the float block (``WORDS`` gives the count per kind):

* ``imu``: orientation xyzw (0-3), orientation_covariance (4-12),
  angular_velocity xyz (13-15), angular_velocity_covariance (16-24),
  linear_acceleration xyz (25-27), linear_acceleration_covariance (28-36).
* ``mag``: magnetic_field xyz (0-2), magnetic_field_covariance (3-11).
* ``temperature``: temperature (0), variance (1).
"""

from __future__ import annotations

import numpy as np

CDR_LE = bytes((0, 1, 0, 0))

# ROS 2 schema name -> message kind
SCHEMAS = {
    "sensor_msgs/msg/Imu": "imu",
    "sensor_msgs/msg/MagneticField": "mag",
    "sensor_msgs/msg/Temperature": "temperature",
}
KIND_SCHEMA = {kind: name for name, kind in SCHEMAS.items()}
WORDS = {"imu": 37, "mag": 12, "temperature": 2}

# word indices inside the float block
IMU_ORIENTATION, IMU_ORIENTATION_COV = 0, 4
IMU_GYRO, IMU_GYRO_COV = 13, 16
IMU_ACCEL, IMU_ACCEL_COV = 25, 28
MAG_FIELD = 0
TEMPERATURE = 0

# the needed words of each kind's float block: [first, last)
SPAN = {"imu": (IMU_GYRO, IMU_ACCEL_COV + 1), "mag": (MAG_FIELD, MAG_FIELD + 3),
        "temperature": (TEMPERATURE, TEMPERATURE + 1)}

HEADER_SIZE = 16


class NotCovered(Exception):
    """The vectorised decoder does not handle this data; a generic decoder must."""


def block_offset(strlen: np.ndarray | int) -> np.ndarray | int:
    """Offset of the float block from the start of the message data, given the frame_id length."""
    return 4 + ((12 + strlen + 7) // 8) * 8


def encode(kind: str, sec: np.ndarray, nanosec: np.ndarray, frame_id: str,
           block: np.ndarray) -> np.ndarray:
    """CDR-LE messages of one kind and frame_id: a ``(n, size)`` uint8 matrix, one row each.

    ``sec`` (n,) int32-range seconds, ``nanosec`` (n,) in [0, 1e9), ``block``
    (n, WORDS[kind]) float64 in the word order of the module docstring.
    """
    n, words = len(sec), WORDS[kind]
    if block.shape != (n, words):
        raise ValueError(f"{kind}: block must have shape ({n}, {words}), got {block.shape}")
    name = frame_id.encode() + b"\0"
    start = block_offset(len(name))
    out = np.zeros((n, start + 8 * words), np.uint8)
    out[:, 0:4] = np.frombuffer(CDR_LE, np.uint8)
    out[:, 4:8] = np.ascontiguousarray(sec, "<i4").view(np.uint8).reshape(n, 4)
    out[:, 8:12] = np.ascontiguousarray(nanosec, "<u4").view(np.uint8).reshape(n, 4)
    out[:, 12:16] = np.frombuffer(np.uint32(len(name)).astype("<u4").tobytes(), np.uint8)
    out[:, 16:16 + len(name)] = np.frombuffer(name, np.uint8)
    out[:, start:] = np.ascontiguousarray(block, "<f8").view(np.uint8).reshape(n, 8 * words)
    return out


def rows(buf: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """``(n, width)`` uint8 copy of ``buf[s:s + width]`` for every start ``s``.

    One fancy index over an overlapping-rows view: numpy copies whole rows,
    far faster than gathering byte by byte. ``IndexError`` if a row runs past
    the buffer.
    """
    if len(starts) and (starts.min() < 0 or starts.max() + width > len(buf)):
        raise IndexError(f"a {width}-byte field runs past the end of its chunk")
    if len(buf) < width:
        return np.empty((0, width), np.uint8)
    view = np.ndarray((len(buf) - width + 1, width), np.uint8, buffer=buf, strides=(1, 1))
    return view[starts]


def decode(kind: str, buf: np.ndarray, starts: np.ndarray, lengths: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode messages of one kind whose data sit at ``buf[starts[i]:starts[i] + lengths[i]]``.

    Returns ``sec`` (n,) int64, ``nanosec`` (n,) int64 and the ``SPAN[kind]``
    words of the float block (n, span) float64. Raises ``NotCovered`` for
    anything but CDR-LE data of exactly the expected size.
    """
    first, last = SPAN[kind]
    if len(starts) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, last - first))
    if lengths.min() < HEADER_SIZE:
        raise NotCovered(f"a {KIND_SCHEMA[kind]} message is shorter than its header")
    # encapsulation, sec, nanosec, frame_id length: four aligned uint32 per message
    head = rows(buf, starts, HEADER_SIZE).view("<u4")
    if not ((head[:, 0] & 0xFFFF) == 0x0100).all():  # bytes 00 01: CDR little endian
        raise NotCovered("a message is not little-endian CDR")
    at = starts + block_offset(head[:, 3].astype(np.int64))
    if not np.array_equal(at + 8 * WORDS[kind], starts + lengths):
        raise NotCovered(f"a {KIND_SCHEMA[kind]} message does not have the standard layout")
    block = rows(buf, at + 8 * first, 8 * (last - first)).view("<f8")
    return head[:, 1].view("<i4").astype(np.int64), head[:, 2].astype(np.int64), block


def decode_rows(kind: str, rows: np.ndarray, start: int, strlen: int, lengths: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Like ``decode`` for messages already gathered as rows, all with one frame_id length.

    ``rows`` (n, width) uint8 holds each message's data from column ``start``,
    through the ``SPAN[kind]`` words of its float block; ``strlen`` is the
    frame_id length (with NUL) of every message, ``lengths`` (n,) their data
    lengths. Returns None when a message's frame_id length differs (use
    ``decode``); raises ``NotCovered`` as ``decode`` does.
    """
    first, last = SPAN[kind]
    block_at = start + block_offset(strlen)
    if rows.shape[1] < block_at + 8 * last:
        raise ValueError(f"rows of {rows.shape[1]} bytes do not reach word {last} of the block")
    if not (rows[:, start + 12:start + 16].view("<u4")[:, 0] == strlen).all():
        return None
    if not ((rows[:, start] == 0) & (rows[:, start + 1] == 1)).all():
        raise NotCovered("a message is not little-endian CDR")
    if not (lengths == block_offset(strlen) + 8 * WORDS[kind]).all():
        raise NotCovered(f"a {KIND_SCHEMA[kind]} message does not have the standard layout")
    sec = rows[:, start + 4:start + 8].view("<i4")[:, 0].astype(np.int64)
    nanosec = rows[:, start + 8:start + 12].view("<u4")[:, 0].astype(np.int64)
    return sec, nanosec, rows[:, block_at + 8 * first:block_at + 8 * last].view("<f8")
