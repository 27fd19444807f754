"""ArduPilot DataFlash logs (``.bin``) via pymavlink's ``DFReader``: the ``ardupilot`` extra.

Devices, one per sensor instance (several IMUs kept apart):

- ``imu<i>``: ``IMU`` messages of instance ``I = i`` (older logs: ``IMU``, ``IMU2``,
  ``IMU3``): accel ``AccX..Z`` [m/s^2], gyro ``GyrX..Z`` [rad/s], and the IMU's
  temperature ``T`` [degC] when logged (the barometer's ``BARO.Temp`` is another
  chip's and is not used).
- ``mag<j>``: ``MAG`` messages of instance ``I = j`` (older: ``MAG2``, ``MAG3``),
  ``MagX..Z`` [milligauss -> T].

Times are ``TimeUS`` (boot time, µs -> ns). ArduPilot logs its sensors in the
board's FRD axes *after* its own calibration (``INS_ACCOFFS``/``ACCSCAL``,
``INS_GYROFFS``, ``COMPASS_OFS``/``DIA``/``ODI``); the log's ``PARM`` values of
those are kept in ``Recording.meta["parameters"]`` and, when any differs from
its default, a warning says that a calibration of this log comes on top of them
(reset them before recording a calibration session).
"""

from __future__ import annotations

import re
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

from ..components import Recording
from ..errors import ReaderError, require
from .csv import canonical_table

HEAD = b"\xa3\x95"  # every DataFlash message starts with these two bytes
T_PER_MILLIGAUSS = 1e-7
FRD = {"imupipe.frame_convention": "FRD"}
CAL_PARAM = re.compile(r"^(INS_(ACC\d?OFFS|ACC\d?SCAL|GYR\d?OFFS|GYROFFS)|COMPASS_(OFS|DIA|ODI)\d?)_[XYZ]$")


def _default(name: str) -> float:
    return 1.0 if ("SCAL" in name or "DIA" in name) else 0.0


class DataflashReader:
    """ArduPilot DataFlash ``.bin`` logs."""

    name = "dataflash"
    suffixes = (".bin",)

    def sniff(self, path: Path, head: bytes) -> bool:
        # the first message of a DataFlash log defines the FMT message itself (type 128)
        return Path(path).suffix.lower() in self.suffixes and head.startswith(HEAD + b"\x80")

    def read(self, path: Path) -> Recording:
        dfreader = require("pymavlink.DFReader", "ardupilot")
        path = Path(path)
        rows: dict[tuple[str, int], list] = defaultdict(list)
        params: dict[str, float] = {}
        log = None
        try:
            log = dfreader.DFReader_binary(str(path))
            while (m := log.recv_match(type=["IMU", "IMU2", "IMU3", "MAG", "MAG2", "MAG3",
                                             "PARM"])) is not None:
                kind = m.get_type()
                if kind == "PARM":
                    params[m.Name] = float(m.Value)
                    continue
                base = kind[:3]
                instance = int(getattr(m, "I", int(kind[3:] or 1) - 1))
                if base == "IMU":
                    rows[base, instance].append((m.TimeUS, m.AccX, m.AccY, m.AccZ, m.GyrX,
                                                 m.GyrY, m.GyrZ, getattr(m, "T", np.nan)))
                else:
                    rows[base, instance].append((m.TimeUS, m.MagX, m.MagY, m.MagZ))
            left = log.data_len - log.offset
        except Exception as exc:  # noqa: BLE001 -- DFReader raises many types on bad bytes
            raise ReaderError(f"{path}: not a readable DataFlash log ({type(exc).__name__}: "
                              f"{exc}); copy the .bin from the SD card again") from None
        finally:
            if log is not None:
                log.close()
        if left > 0:  # a log cut off mid-message (power lost): its complete messages stand
            warnings.warn(f"{path}: the last {left} bytes are no complete message (the log was "
                          "cut off?); read the messages before them", stacklevel=2)
        if not rows:
            raise ReaderError(f"{path}: no IMU or MAG messages; enable IMU logging "
                              "(LOG_BITMASK) and record again")
        devices = {}
        for (base, i), values in sorted(rows.items()):
            a = np.array(values, dtype=np.float64)
            t = np.asarray([v[0] for v in values], np.int64) * 1000
            if base == "IMU":
                streams = {"accel": canonical_table("accel", t, list(a[:, 1:4].T), FRD),
                           "gyro": canonical_table("gyro", t, list(a[:, 4:7].T), FRD)}
                if np.isfinite(a[:, 7]).all():
                    streams["temperature"] = canonical_table("temperature", t, [a[:, 7]], FRD)
                devices[f"imu{i}"] = streams
            else:
                devices[f"mag{i}"] = {"mag": canonical_table(
                    "mag", t, list(a[:, 1:4].T * T_PER_MILLIGAUSS), FRD)}
        calibration = {k: v for k, v in params.items() if CAL_PARAM.match(k)}
        changed = sorted(k for k, v in calibration.items() if v != _default(k))
        if changed:
            warnings.warn(f"{path}: ArduPilot logged its sensors already corrected by "
                          f"{', '.join(changed[:6])}{' ...' if len(changed) > 6 else ''}; a "
                          "calibration of this log comes on top of them (reset them to 0 / 1 "
                          "before recording a calibration session)", stacklevel=2)
        return Recording(source=str(path), devices=devices, meta={"parameters": calibration})


COMPONENTS = [DataflashReader()]
