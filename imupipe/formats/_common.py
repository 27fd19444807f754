"""What the format exporters share: the run's facts, frames, units, and what a target drops.

imupipe's convention (``imupipe.models``)::

    x = M (y - b0 - k (T - 25))        y raw (sensor axes, raw units), x corrected (SI)

Every exporter re-expresses ``M``, ``b0``, ``k`` in its target's convention and
records, through ``Notes``, each conversion it made and each part the target
cannot hold: both go into a comment block of the written file and the second
also into the log (one warning per item), never dropped silently.

Frames: PX4 and ArduPilot correct sensor data in the board's FRD axes (x
forward, y right, z down); ROS (REP-103) uses FLU (x forward, y left, z up).
The two differ by a half turn about x, ``R = diag(1, -1, -1)`` (mavros'
``ftf::transform_frame_aircraft_baselink``). When the reader knows the
recording's convention (table metadata ``imupipe.frame_convention``) and the
target's differs, the calibration is carried over exactly: ``M' = R M R``,
``b' = R b``, ``k' = R k``. When it does not, axes are kept as recorded and the
file says so.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from .. import schemas
from ..errors import ImupipeError
from ..io import write_text
from ..models import SENSORS, UNITS, Calibration, TriadCalibration
from ..paths import under

log = logging.getLogger("imupipe.formats")

EXPORT_DIR = "export"
FLU_FRD = np.diag([1.0, -1.0, -1.0])  # FLU <-> FRD, its own inverse
NOISE_SCHEMA = "noise"


class ExportError(ImupipeError):
    """The calibration cannot be written in the requested format (says why and what to do)."""


@dataclass
class Notes:
    """Conversions made and parts dropped for one written file (``said`` / ``dropped``)."""

    fmt: str
    session: str
    said: list[str] = field(default_factory=list)
    dropped: list[str] = field(default_factory=list)

    def say(self, text: str) -> None:
        self.said.append(text)

    def drop(self, text: str) -> None:
        """A part of the calibration the target cannot hold: in the file and in the log."""
        self.dropped.append(text)
        log.warning("%s: %s export: %s", self.session, self.fmt, text)

    def comment(self, prefix: str = "# ") -> list[str]:
        lines = [f"{prefix}Conversions:"] + [f"{prefix}  - {s}" for s in self.said]
        if self.dropped:
            lines += [f"{prefix}NOT HELD or NOT KNOWN here (also in the log):"]
            lines += [f"{prefix}  - {s}" for s in self.dropped]
        return lines


@dataclass(frozen=True)
class Source:
    """What an exporter works from: the merged calibration and the run's facts.

    ``facts``: stream -> ``ingest.stream_facts`` entry (``rate_hz``, ``topic``,
    ``device_id``, ``frame_convention``, temperature ``min_C``/``max_C``);
    ``noise``: a table of schema ``noise`` when the pipeline has one.
    """

    session: str
    calibration: Calibration
    raw_units: Mapping[str, str]
    facts: Mapping[str, Mapping[str, Any]]
    device: str | None
    version: str
    noise: pa.Table | None = None

    @classmethod
    def of(cls, results: Mapping[str, pa.Table], context: Mapping[str, Any]) -> Source:
        calibration_tables = [t for t in results.values() if schemas.schema_of(t) == "calibration"]
        noise = [t for t in results.values() if schemas.schema_of(t) == NOISE_SCHEMA]
        session = str(context.get("session", "?"))
        if not calibration_tables:
            raise ExportError(f"{session}: no calibration to export")
        return cls(session, Calibration.from_tables(*calibration_tables),
                   dict(context.get("raw_units") or {}), dict(context.get("stream_facts") or {}),
                   context.get("device"), str(context.get("imupipe_version", "?")),
                   noise[-1] if noise else None)

    @property
    def triads(self) -> dict[str, TriadCalibration]:
        return {s: self.calibration.triads[s] for s in SENSORS if s in self.calibration.triads}

    def raw_unit(self, sensor: str) -> str:
        return self.raw_units.get(sensor, UNITS[sensor])

    def require_si(self, fmt: str, why: str) -> None:
        """Raise ``ExportError`` when a triad's raw values are not in SI (e.g. counts)."""
        bad = [f"{s} in {self.raw_unit(s)}" for s in self.triads if self.raw_unit(s) != UNITS[s]]
        if bad:
            raise ExportError(
                f"{self.session}: cannot export to {fmt}: raw values are {', '.join(bad)}, and "
                f"{why}; calibrate a recording in SI units (a session manifest can apply the "
                "datasheet scale: `lsb_per_unit`, docs/session-manifest.md)")

    def instance(self) -> int:
        """The sensor instance a device name ends with (``imu1`` -> 1), else 0."""
        m = re.search(r"(\d+)$", self.device or "")
        return int(m.group(1)) if m else 0

    def temperature_range(self) -> tuple[float, float] | None:
        t = self.facts.get("temperature", {})
        return (t["min_C"], t["max_C"]) if "min_C" in t else None

    def rate_hz(self, sensor: str) -> float | None:
        return self.facts.get(sensor, {}).get("rate_hz")

    def in_frame(self, sensor: str, target: str | None, notes: Notes) -> TriadCalibration:
        """``sensor``'s calibration in the ``target`` convention ("FRD", "FLU" or None: as recorded)."""
        triad = self.calibration[sensor]
        source = self.facts.get(sensor, {}).get("frame_convention")
        if target is None:
            notes.say(f"{sensor}: axes as recorded (this format has no frame convention)")
            return triad
        if source is None:
            notes.say(f"{sensor}: axes as recorded; the recording does not say its frame "
                      f"convention, so they are taken to be {target} already")
            return triad
        if source == target:
            notes.say(f"{sensor}: recorded in {source}, the target's convention: axes unchanged")
            return triad
        if {source, target} != {"FLU", "FRD"}:
            raise ExportError(f"{self.session}: {sensor} is recorded in frame convention "
                              f"{source!r}; imupipe converts only between FLU and FRD")
        R = FLU_FRD
        notes.say(f"{sensor}: recorded in {source}, written in {target}: M' = R M R, b' = R b, "
                  "k' = R k with R = diag(1, -1, -1) (half turn about x)")
        return TriadCalibration(sensor, R @ triad.M @ R, R @ triad.b0, R @ triad.k,
                                triad.T_ref_C, triad.solver, triad.details)


def cross_axis(M: np.ndarray) -> float:
    """Largest off-diagonal term of ``M`` relative to its diagonal, ``|M_ij| / sqrt(|M_ii M_jj|)``."""
    d = np.sqrt(np.abs(np.outer(np.diag(M), np.diag(M))))
    off = np.abs(M) / d
    np.fill_diagonal(off, 0.0)
    return float(off.max())


def polar(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``M = U P``: ``U`` orthogonal, ``P`` symmetric positive definite (SVD)."""
    W, s, Vt = np.linalg.svd(M)
    return W @ Vt, Vt.T @ np.diag(s) @ Vt


def symmetric_part_held(M: np.ndarray, holder: str, notes: Notes) -> np.ndarray:
    """``M`` when symmetric (to rounding), else the ``P`` of ``M = U P``, saying ``U`` is dropped."""
    if np.allclose(M, M.T, rtol=0, atol=1e-12 * np.abs(M).max()):
        return M
    U, P = polar(M)
    notes.drop(f"mag: the rotation part U of M = U P ({rotation_deg(U):.3g} deg): {holder} soft-iron "
               "matrix is symmetric; written P, so corrected fields come out rotated by U^-1")
    return P


def rotation_deg(U: np.ndarray) -> float:
    """Angle of the rotation (or improper rotation's rotation part) ``U``, degrees."""
    R = U * np.sign(np.linalg.det(U))
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def num(x: float) -> str:
    """A float written so that parsing it gives the same double back, and that YAML 1.1
    (PyYAML, which Kalibr uses) reads as a float: ``3e-06`` would be a string there."""
    text = repr(float(x))
    mantissa, e, exponent = text.partition("e")
    return f"{mantissa}.0e{exponent}" if e and "." not in mantissa else text


def header(fmt: str, target: str, source: Source, prefix: str = "# ") -> list[str]:
    lines = [
        f"{fmt} written by imupipe {source.version} for {target}",
        f"session: {source.session}" + (f" (device {source.device})" if source.device else ""),
        "from imupipe's calibration: x = M (y - b0 - k (T - 25 degC)), y raw, x corrected",
    ]
    return [f"{prefix}{line}" for line in lines]


def write_files(out_dir: Path, texts: Mapping[str, str]) -> list[Path]:
    """Write every file atomically (all texts are rendered before the first write)."""
    paths = []
    for name, text in texts.items():
        path = under(Path(out_dir), name)  # a name never leads out of the export folder
        write_text(path, text)
        paths.append(path)
    return paths


class FormatExporter:
    """Base of the format exporters: ``render`` the files, then write them.

    Subclasses set ``name`` (the ``--export`` name), ``target`` (what loads the
    files), ``files`` (the names written under ``export/``) and implement
    ``render(source) -> {file name: text}``.
    """

    name: str
    target: str
    files: tuple[str, ...]

    def export(self, results: Mapping[str, pa.Table], context: Mapping[str, Any],
               out_dir: Path) -> list[Path]:
        return write_files(out_dir, self.render(Source.of(results, context)))

    def render(self, source: Source) -> dict[str, str]:
        raise NotImplementedError
