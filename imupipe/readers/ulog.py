"""PX4 ULog (``.ulg``) via pyulog: the ``px4`` extra.

Devices:

- ``imu``: the ``sensor_combined`` topic (PX4's selected primary IMU): accel
  [m/s^2] at ``timestamp + accelerometer_timestamp_relative``, gyro [rad/s] at
  ``timestamp``, mag [gauss -> T] (older logs) at ``timestamp +
  magnetometer_timestamp_relative``, each distinct mag sample once (the topic
  repeats the latest one at the IMU rate). No temperature (``baro_temp_celcius``
  is the barometer's, not the IMU's).
- ``imu<i>``: instance ``i`` of ``sensor_accel`` with the ``sensor_gyro``
  instance of the same ``device_id`` (one chip), temperature [degC] from
  ``sensor_accel``; times from ``timestamp_sample``.
- ``mag<j>``: instance ``j`` of ``sensor_mag`` [gauss -> T] (a separate chip),
  with its temperature when the driver reports one.

Time stamps are PX4 boot time in microseconds. Frames: PX4's drivers publish
``sensor_accel``/``sensor_gyro``/``sensor_mag`` in the board's FRD axes (x
forward, y right, z down) before any calibration, the frame in which PX4 applies
``CAL_*`` and ``TC_*`` parameters (``src/lib/sensor_calibration``);
``sensor_combined`` is already corrected by them and rotated to the body frame.
Tables carry ``imupipe.frame_convention = FRD`` and, per instance,
``imupipe.device_id`` (what PX4 matches ``CAL_ACCn_ID`` against).
"""

from __future__ import annotations

import contextlib
import io
import struct
import warnings
from pathlib import Path

import numpy as np

from ..components import Recording
from ..errors import ReaderError, require
from .csv import canonical_table

MAGIC = b"ULog\x01\x12\x35"
GAUSS = 1e-4  # T per gauss
FRD = {"imupipe.frame_convention": "FRD"}
RELATIVE_INVALID = 0x7FFFFFFF  # PX4's RELATIVE_TIMESTAMP_INVALID
TOPICS = ["sensor_combined", "sensor_accel", "sensor_gyro", "sensor_mag"]
HEADER_BYTES = 16  # magic, version, start time
MESSAGE_TYPES = frozenset(b"BFIMPQARDLCSO")  # ULog message types (msg_size u16, msg_type u8, body)
RESYNC_CHAIN = 8  # consecutive well-formed messages that mark where readable data resumes


def _chain_ok(raw: bytes, off: int, n: int = RESYNC_CHAIN) -> bool:
    for _ in range(n):
        if off + 3 > len(raw):
            return True
        size, kind = struct.unpack_from("<HB", raw, off)
        if kind not in MESSAGE_TYPES or (kind == ord("D") and size < 2) or off + 3 + size > len(raw):
            return False
        off += 3 + size
    return True


def unreadable(raw: bytes) -> tuple[list[tuple[int, int]], int]:
    """Walk the ULog message headers of ``raw``: the byte ranges ``[(start, end)]`` that are no
    well-formed message (zeroed or damaged regions: the samples in them are missing) and the
    number of bytes of a last message cut off by the end of the file (0 when complete)."""
    bad: list[tuple[int, int]] = []
    off, n = HEADER_BYTES, len(raw)
    arr = np.frombuffer(raw, np.uint8)
    valid = np.isin(arr, np.frombuffer(bytes(sorted(MESSAGE_TYPES)), np.uint8))
    while off + 3 <= n:
        size, kind = struct.unpack_from("<HB", raw, off)
        if kind in MESSAGE_TYPES and not (kind == ord("D") and size < 2):
            if off + 3 + size > n:
                return bad, n - off
            off += 3 + size
            continue
        # damaged: resume at the first offset that starts a chain of well-formed messages
        start = off
        for cand in np.flatnonzero(valid[off + 3:]) + off + 1:  # the type byte is at offset + 2
            if _chain_ok(raw, int(cand)):
                off = int(cand)
                break
        else:
            off = n
        bad.append((start, off))
    return bad, (n - off if off < n else 0)


def _ns(us: np.ndarray) -> np.ndarray:
    return np.asarray(us, dtype=np.int64) * 1000


def _xyz(data: dict, prefix: str, factor: float = 1.0) -> list[np.ndarray]:
    return [np.asarray(data[f"{prefix}{k}"], dtype=np.float64) * factor for k in "xyz"]


def _combined(data: dict) -> dict:
    """Streams of ``sensor_combined`` (field names of PX4 v1.x)."""
    t = np.asarray(data["timestamp"], dtype=np.int64)
    streams = {}
    rel = np.asarray(data.get("accelerometer_timestamp_relative", np.zeros_like(t)), np.int64)
    ok = rel != RELATIVE_INVALID
    streams["accel"] = canonical_table(
        "accel", _ns(t[ok] + rel[ok]),
        [np.asarray(data[f"accelerometer_m_s2[{i}]"], np.float64)[ok] for i in range(3)], FRD)
    streams["gyro"] = canonical_table(
        "gyro", _ns(t), [np.asarray(data[f"gyro_rad[{i}]"], np.float64) for i in range(3)], FRD)
    if "magnetometer_ga[0]" in data:
        rel = np.asarray(data["magnetometer_timestamp_relative"], np.int64)
        tm = t + rel
        # keep each distinct mag sample once: the topic repeats it until the next one arrives
        new = np.concatenate([[True], tm[1:] != tm[:-1]]) & (rel != RELATIVE_INVALID)
        if new.any():
            streams["mag"] = canonical_table(
                "mag", _ns(tm[new]),
                [np.asarray(data[f"magnetometer_ga[{i}]"], np.float64)[new] * GAUSS
                 for i in range(3)], FRD)
    return streams


def _meta(data: dict) -> dict[str, str]:
    """Frame and, when logged, the PX4 device id of one instance."""
    if "device_id" not in data:
        return FRD
    return {**FRD, "imupipe.device_id": str(int(np.asarray(data["device_id"])[0]))}


def _instance_time(data: dict) -> np.ndarray:
    return _ns(data["timestamp_sample"] if "timestamp_sample" in data else data["timestamp"])


def _warn_missing(path: Path, log) -> None:
    """One warning when part of the file is no readable message (zeroed or damaged bytes, a
    last message cut off): pyulog skips them silently and the samples in them are missing."""
    raw = path.read_bytes()
    bad, cut = unreadable(raw)
    if not bad and not cut:
        return
    what = []
    if bad:
        lost = sum(b - a for a, b in bad)
        a, b = bad[0]
        what.append(f"{lost} bytes ({100 * lost / len(raw):.2g} % of the log) are zeroed or damaged "
                    f"({len(bad)} region{'s' if len(bad) > 1 else ''}, the first at bytes {a}-{b}): "
                    "the samples in them are missing")
    if cut:
        what.append(f"it ends mid-message at byte {len(raw) - cut} of {len(raw)} (truncated: the "
                    "samples recorded after it are missing)")
    warnings.warn(f"{path}: {'; '.join(what)}; copy the .ulg from the SD card again", stacklevel=3)


class UlogReader:
    """PX4 ULog files: ``sensor_combined`` and per-instance sensor topics."""

    name = "ulog"
    suffixes = (".ulg",)

    def sniff(self, path: Path, head: bytes) -> bool:
        return head.startswith(MAGIC)

    def read(self, path: Path) -> Recording:
        pyulog = require("pyulog", "px4")
        path = Path(path)
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # pyulog prints its warnings
                log = pyulog.ULog(str(path), TOPICS)
        except Exception as exc:  # noqa: BLE001 -- pyulog raises bare Exception on bad files
            raise ReaderError(f"{path}: not a readable ULog file ({exc})") from None
        _warn_missing(path, log)
        topics: dict[str, dict[int, dict]] = {}
        for d in log.data_list:
            topics.setdefault(d.name, {})[d.multi_id] = d.data
        devices: dict[str, dict] = {}
        if "sensor_combined" in topics:
            devices["imu"] = _combined(topics["sensor_combined"][0])
        gyros = {int(np.asarray(g["device_id"])[0]): g
                 for g in topics.get("sensor_gyro", {}).values() if "device_id" in g}
        for i, acc in sorted(topics.get("sensor_accel", {}).items()):
            streams = {"accel": canonical_table("accel", _instance_time(acc), _xyz(acc, ""),
                                                _meta(acc))}
            if "temperature" in acc and np.isfinite(acc["temperature"]).all():
                streams["temperature"] = canonical_table(
                    "temperature", _instance_time(acc), [np.asarray(acc["temperature"], float)],
                    _meta(acc))
            gyro = gyros.pop(int(np.asarray(acc["device_id"])[0]), None) if "device_id" in acc \
                else None
            if gyro is not None:
                streams["gyro"] = canonical_table("gyro", _instance_time(gyro), _xyz(gyro, ""),
                                                  _meta(gyro))
            devices[f"imu{i}"] = streams
        for k, gyro in enumerate(gyros.values()):  # gyros without an accel on the same chip
            devices[f"gyro{k}"] = {"gyro": canonical_table("gyro", _instance_time(gyro),
                                                           _xyz(gyro, ""), _meta(gyro))}
        for j, mag in sorted(topics.get("sensor_mag", {}).items()):
            streams = {"mag": canonical_table("mag", _instance_time(mag), _xyz(mag, "", GAUSS),
                                              _meta(mag))}
            if "temperature" in mag and np.isfinite(mag["temperature"]).all():
                streams["temperature"] = canonical_table(
                    "temperature", _instance_time(mag), [np.asarray(mag["temperature"], float)],
                    _meta(mag))
            devices[f"mag{j}"] = streams
        if not devices:
            raise ReaderError(f"{path}: no sensor_combined, sensor_accel, sensor_gyro or "
                              "sensor_mag topic; was the IMU logged?")
        return Recording(source=str(path), devices=devices)


COMPONENTS = [UlogReader()]
