"""A small, faithful ArduPilot DataFlash log, written byte by byte from the documented format.

DataFlash (ArduPilot ``libraries/AP_Logger``; pymavlink ``DFReader.py``): every
message is ``0xA3 0x95 <type>`` then a little-endian payload. Type 128 is ``FMT``
(``BBnNZ``: type, length incl. the 3 header bytes, name char[4], format char[16],
columns char[64]) and defines every other type, itself first. Format characters
used: ``Q`` uint64, ``B`` uint8, ``f`` float32, ``I`` uint32, ``h`` int16,
``H`` uint16, ``N`` char[16]. ``IMU`` and ``MAG`` use ArduPilot 4.x's layouts
(instance field ``I``); ``MagX`` is in milligauss.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

HEAD = b"\xa3\x95"
STRUCT = {"Q": "Q", "B": "B", "f": "f", "I": "I", "h": "h", "H": "H", "N": "16s", "n": "4s",
          "Z": "64s"}
FORMATS = {  # name: (type id, format, columns)
    "FMT": (128, "BBnNZ", "Type,Length,Name,Format,Columns"),
    "PARM": (64, "QNf", "TimeUS,Name,Value"),
    "IMU": (65, "QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
    "MAG": (66, "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
}


def _pack(name: str, *values) -> bytes:
    type_id, fmt, _ = FORMATS[name]
    body = struct.pack("<" + "".join(STRUCT[c] for c in fmt), *values)
    return HEAD + bytes([type_id]) + body


def _fmt_message(name: str) -> bytes:
    type_id, fmt, columns = FORMATS[name]
    length = 3 + struct.calcsize("<" + "".join(STRUCT[c] for c in fmt))
    return _pack("FMT", type_id, length, name.encode(), fmt.encode(), columns.encode())


def write_dataflash(path: Path, n: int = 200, imus: int = 2, params: dict | None = None,
                    seed: int = 0) -> dict:
    """Write ``n`` samples per IMU instance (400 Hz) and a 50 Hz magnetometer; return the truth:
    ``{"imu<i>": (t_us, acc (n, 3) float32, gyro (n, 3) float32, T (n,) float32),
    "mag0": (t_us, mag_mG (m, 3) int16)}``."""
    rng = np.random.default_rng(seed)
    out = bytearray(b"".join(_fmt_message(k) for k in FORMATS))
    for name, value in (params or {}).items():
        out += _pack("PARM", 1000, name.encode(), value)
    t_us = 2_000_000 + np.arange(n, dtype=np.uint64) * 2500
    truth = {}
    for i in range(imus):
        acc = rng.normal([0, 0, -9.8], 0.05, (n, 3)).astype(np.float32)
        gyro = rng.normal(0, 0.01, (n, 3)).astype(np.float32)
        temp = (40 + 0.01 * np.arange(n) + i).astype(np.float32)
        truth[f"imu{i}"] = (t_us + i, acc, gyro, temp)
    mag = rng.normal([200, 20, 400], 3, ((n + 7) // 8, 3)).astype(np.int16)
    truth["mag0"] = (t_us[::8] + 7, mag)
    for k in range(n):  # interleaved as a logger writes them
        for i in range(imus):
            t, acc, gyro, temp = truth[f"imu{i}"]
            out += _pack("IMU", int(t[k]), i, *gyro[k], *acc[k], 0, 0, float(temp[k]), 1, 1,
                         400, 400)
        if k % 8 == 0:
            out += _pack("MAG", int(truth["mag0"][0][k // 8]), 0, *mag[k // 8], 0, 0, 0, 0, 0,
                         0, 1, 0)
    Path(path).write_bytes(bytes(out))
    return truth
