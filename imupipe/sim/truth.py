"""The hidden truth of a simulated session: every parameter, the true segments, a ``Calibration``.

Written beside every recording as ``<out>.truth.json``. Times are seconds from
the first sample. ``calibration`` follows ``imupipe.models`` (``M = inv(S)``;
``b0`` includes the turn-on bias of the first power cycle), so a solver's result
compares directly with ``load_truth(path).calibration``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ReaderError
from ..models import Calibration, TriadCalibration

FORMAT_VERSION = 1


@dataclass(frozen=True)
class Truth:
    """The truth dictionary (as in the JSON file) and the true ``Calibration``."""

    data: dict[str, Any]
    calibration: Calibration

    def segments(self, kind: str | None = None, label: str | None = None) -> list[dict[str, Any]]:
        """True segments ``{kind, label, t_start_s, t_end_s}``, filtered by kind and/or label."""
        return [s for s in self.data["segments"]
                if (kind is None or s["kind"] == kind) and (label is None or s["label"] == label)]

    @property
    def rests(self) -> np.ndarray:
        """(n, 2) start and end (s) of every true rest with samples, in time order."""
        return np.array([[s["t_start_s"], s["t_end_s"]] for s in self.segments("rest")]).reshape(-1, 2)

    @property
    def turns(self) -> np.ndarray:
        """(n, 2) start and end (s) of every true rotation."""
        return np.array([[s["t_start_s"], s["t_end_s"]] for s in self.segments("turn")]).reshape(-1, 2)

    @property
    def reference_rests(self) -> dict[str, int]:
        """Label (``reference_y_up``, ``reference_x_up``, ...) -> index into ``rests``."""
        return dict(self.data["reference_rests"])

    @property
    def effects(self) -> dict[str, dict[str, Any]]:
        return dict(self.data["effects"])

    def to_json(self) -> str:
        return json.dumps(self.data, indent=1) + "\n"


def make_truth(data: dict[str, Any]) -> Truth:
    """Build the ``Truth`` (and its ``Calibration``) from a truth dictionary."""
    triads = {}
    for sensor, d in data["imu"].items():
        if sensor not in ("accel", "gyro", "mag"):
            continue
        S = np.array(d["S"])
        b0 = np.array(d["b0"]) + np.array(data["turn_on_bias"][sensor][0])
        triads[sensor] = TriadCalibration(sensor, np.linalg.inv(S), b0, np.array(d["k"]), solver="truth")
    return Truth(data, Calibration(triads, {"source": "simulator truth", "seed": data.get("seed")}))


def load_truth(path: Path | str) -> Truth:
    """Read ``<recording>.truth.json`` (or the recording's path: ``.truth.json`` is appended)."""
    path = Path(path)
    if not path.name.endswith(".truth.json"):
        path = path.with_name(path.name + ".truth.json")
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ReaderError(f"{path}: no truth file; simulate with `imupipe simulate` to get one") from None
    except json.JSONDecodeError as exc:
        raise ReaderError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if data.get("format_version", FORMAT_VERSION) > FORMAT_VERSION:
        raise ReaderError(f"{path}: truth format {data['format_version']} is newer than this imupipe")
    return make_truth(data)
