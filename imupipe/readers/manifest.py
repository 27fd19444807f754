"""Session manifest (``session.toml``): a recording split over several files.

Names each file, its stream, columns, units and time base, and optional
protocol sections; see docs/session-manifest.md for the format. Paths are
relative to the manifest. Files are parsed here directly (CSV and MATLAB
buffers) or, with ``reader = "NAME"``, by any registered reader, so a plugin's
format can be part of a session without this module knowing it.
"""

from __future__ import annotations

import json
import math
import os
import re
import tomllib
import warnings
from contextvars import ContextVar
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import pyarrow as pa

from ..components import Recording
from ..errors import ConfigError, ReaderError, describe_validation
from .csv import ColumnRef, canonical_table, read_columns

if TYPE_CHECKING:
    from ._manifest_model import Manifest, Sections, StreamSpec

StreamName = Literal["accel", "gyro", "mag", "temperature"]
G0 = 9.80665  # standard gravity, m/s^2 per g

# unit -> (factor, addend): SI = value * factor + addend. "counts" keeps the raw unit.
UNITS: dict[str, dict[str, tuple[float, float]]] = {
    "accel": {"m/s^2": (1.0, 0.0), "m/s2": (1.0, 0.0), "g": (G0, 0.0), "mg": (G0 * 1e-3, 0.0),
              "counts": (1.0, 0.0)},
    "gyro": {"rad/s": (1.0, 0.0), "deg/s": (math.pi / 180, 0.0), "dps": (math.pi / 180, 0.0),
             "mrad/s": (1e-3, 0.0), "rpm": (2 * math.pi / 60, 0.0), "counts": (1.0, 0.0)},
    "mag": {"T": (1.0, 0.0), "mT": (1e-3, 0.0), "uT": (1e-6, 0.0), "nT": (1e-9, 0.0),
            "gauss": (1e-4, 0.0), "G": (1e-4, 0.0), "mG": (1e-7, 0.0), "mgauss": (1e-7, 0.0),
            "counts": (1.0, 0.0)},
    "temperature": {"degC": (1.0, 0.0), "K": (1.0, -273.15), "counts": (1.0, 0.0)},
}
CANONICAL_UNIT = {"accel": "m/s^2", "gyro": "rad/s", "mag": "T", "temperature": "degC"}
TIME_UNITS = {"s": 1e9, "ms": 1e6, "us": 1e3, "ns": 1.0}
RAW_UNIT_KEY = "imupipe.raw_unit"  # table metadata: values in this unit, not the SI one
INT64_NS = 2.0**63  # |t_ns| must stay below this
FORMATS_BY_SUFFIX = {".csv": "csv", ".txt": "csv", ".tsv": "csv", ".dat": "csv",
                     ".mat": "matlab", ".h5": "matlab", ".hdf5": "matlab"}


def load_manifest(path: Path) -> Manifest:
    """Parse and validate a manifest; errors name the file and the key path."""
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the manifest ({exc})") from None
    except RecursionError:
        raise ConfigError(f"{path}: not valid TOML (arrays or tables nested too deeply)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    from pydantic import ValidationError

    from ._manifest_model import Manifest

    try:
        return Manifest.model_validate(doc)
    except ValidationError as exc:
        raise ConfigError(f"{path}: {describe_validation(exc, Manifest)}") from None


_READING: ContextVar[tuple[str, ...]] = ContextVar("imupipe_manifests_reading", default=())
MAX_NESTING = 4  # a manifest's stream read through a reader that reads a manifest ...


def read_manifest(path: Path) -> Recording:
    """Read every stream a manifest names into one ``Recording``.

    A manifest that names itself (or a manifest naming it back) through
    ``reader = "session"`` is an error, not an endless recursion.
    """
    key = os.path.realpath(path)
    reading = _READING.get()
    if key in reading or len(reading) >= MAX_NESTING:
        chain = " -> ".join([*reading, key])
        raise ConfigError(f"{path}: the manifest refers to itself ({chain}); "
                          "name the data files, not a manifest, in streams[].file")
    token = _READING.set((*reading, key))
    try:
        return _read_manifest(path)
    finally:
        _READING.reset(token)


def _read_manifest(path: Path) -> Recording:
    manifest = load_manifest(path)
    devices: dict[str, dict[str, pa.Table]] = {}
    for i, spec in enumerate(manifest.streams):
        device = spec.device or manifest.session.device
        if spec.stream in devices.get(device, {}):
            raise ConfigError(f"{path}: streams[{i}]: a second {spec.stream!r} stream for device "
                              f"{device!r}; give it another `device`")
        devices.setdefault(device, {})[spec.stream] = read_stream(spec, path, i)
    meta: dict[str, Any] = {"session": manifest.session.name, "manifest": str(path),
                            "description": manifest.session.description, "meta": manifest.meta}
    if manifest.sections is not None:
        meta["sections"] = resolve_sections(manifest.sections, devices, manifest.session.device,
                                            path)
    return Recording(source=str(path), devices=devices, meta=meta)


def _file(manifest_path: Path, name: str) -> Path:
    return Path(os.path.normpath(manifest_path.parent / name))


def read_stream(spec: StreamSpec, manifest_path: Path, index: int) -> pa.Table:
    """One canonical table from the file a stream spec names."""
    path = _file(manifest_path, spec.file)
    if not path.is_file():
        raise ReaderError(f"{manifest_path}: streams[{index}].file: no such file {path}")
    if spec.reader is not None:
        t_ns, values = _via_reader(spec, path)
    else:
        t_ns, values = _parse(spec, path)
    unit = spec.unit or CANONICAL_UNIT[spec.stream]
    factor, addend = UNITS[spec.stream][unit]
    offset = np.broadcast_to(np.asarray(spec.offset, float), (len(values),))
    scale = spec.scale_factors()
    si = [(v - offset[k]) * scale[k] * factor + addend for k, v in enumerate(values)]
    extra = {"imupipe.source": str(path), "imupipe.source_unit": unit}
    if unit == "counts":  # left unconverted: calibration.json says so (raw_units)
        extra[RAW_UNIT_KEY] = unit
    return canonical_table(spec.stream, t_ns, si, extra)


def _parse(spec: StreamSpec, path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    fmt = spec.format or FORMATS_BY_SUFFIX.get(path.suffix.lower())
    if fmt is None:
        raise ReaderError(f"{path}: cannot tell the format from the suffix; "
                          "give format = \"csv\" or \"matlab\" in the manifest")
    refs = spec.column_refs()
    if fmt == "csv":
        if spec.stream == "temperature" and not spec.columns:
            _check_positional_temperature(spec, path, len(refs))
        int_keys = ("t",) if spec.time_unit == "ns" else ()
        data = read_columns(path, refs, delimiter=spec.delimiter, skip_lines=spec.skip_lines,
                            header=spec.header, int_keys=int_keys)
    else:
        from .matlab import read_buffer

        data = _pick_columns(path, read_buffer(path, spec.variable), refs)
    if "drop_zero_padding" in spec.repair:
        data = _drop_zero_padding(data, path)
    n = len(next(iter(data.values())))
    if "t" in data:
        t = data["t"]
        if spec.time_unit == "ns" and t.dtype.kind in "iu":
            t_ns = t.astype(np.int64)
        else:
            per = 1e9 / spec.rate_hz if spec.time_unit == "samples" \
                else TIME_UNITS[spec.time_unit]
            t_ns = _to_ns(t, per, spec, refs["t"], path)
    else:
        t_ns = np.round(np.arange(n) * (1e9 / spec.rate_hz)).astype(np.int64)
    return t_ns, [data[a] for a in spec.axes()]


def _check_positional_temperature(spec: StreamSpec, path: Path, used: int) -> None:
    """A file of more columns than [t,] temperature is not a temperature stream by position.

    (A triad's file offered as temperature would otherwise give its x axis as degrees.)
    """
    from .csv import first_line, split_fields

    width = len(split_fields(first_line(path, spec.skip_lines), spec.delimiter))
    if width > used:
        raise ReaderError(
            f"{path}: offered as a temperature stream but it has {width} columns (a temperature "
            f"file has {used}); name them with columns = {{ t = ..., temperature = ... }}")


def _to_ns(t: np.ndarray, per: float, spec: StreamSpec, ref: ColumnRef, path: Path
           ) -> np.ndarray:
    """(n,) int64 ns from a float time column ``t`` in units of ``per`` ns, checked."""
    t = np.asarray(t, dtype=np.float64)
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        raise ReaderError(f"{path}: time column {ref!r} has non-finite value {t[i]} at row {i}; "
                          "fix the file or give rate_hz instead of a time column")
    with np.errstate(over="ignore", invalid="ignore"):
        ns = np.round(t * per)
    big = ~(np.abs(ns) < INT64_NS)
    if big.any():
        i = int(np.argmax(big))
        hint = " is the column in ns?" if spec.time_unit != "ns" else ""
        raise ReaderError(f"{path}: time column {ref!r} with time_unit {spec.time_unit!r} "
                          f"overflows int64 nanoseconds ({t[i]:g} at row {i});{hint} "
                          "set time_unit to the column's unit")
    return ns.astype(np.int64)


def _pick_columns(path: Path, buffer: np.ndarray, refs: dict[str, ColumnRef]
                  ) -> dict[str, np.ndarray]:
    """Columns of an (n, k) buffer by 0-based index (or ``colN``)."""
    out = {}
    for key, ref in refs.items():
        m = re.fullmatch(r"col(\d+)", ref) if isinstance(ref, str) else None
        i = int(m.group(1)) if m else ref
        if not isinstance(i, int) or not 0 <= i < buffer.shape[1]:
            raise ReaderError(f"{path}: no column {ref!r} in a buffer of {buffer.shape[1]} "
                              "columns; refer to columns by 0-based index")
        out[key] = np.asarray(buffer[:, i], dtype=np.float64)
    return out


def _drop_zero_padding(data: dict[str, np.ndarray], path: Path) -> dict[str, np.ndarray]:
    """Drop trailing all-zero rows: a logger's preallocated buffer that was never filled."""
    stacked = np.column_stack(list(data.values()))
    nonzero = np.flatnonzero((stacked != 0).any(axis=1))
    keep = int(nonzero[-1]) + 1 if nonzero.size else 0
    if keep < len(stacked):
        warnings.warn(f"{path}: dropped {len(stacked) - keep} trailing all-zero rows "
                      "(repair = drop_zero_padding)", stacklevel=2)
    return {k: v[:keep] for k, v in data.items()}


def _via_reader(spec: StreamSpec, path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    # A fresh registry: read() has none, and the manifest may name any plugin's reader.
    from ..ingest import read_recording
    from ..plugins import make_registry

    recording = read_recording(path, make_registry(), reader=spec.reader)
    device = recording.device(spec.source_device)
    name = spec.source_stream
    if name is None:
        if len(device) != 1:
            raise ReaderError(f"{path}: reader {spec.reader!r} gives streams "
                              f"{', '.join(sorted(device))}; choose one with source_stream")
        name = next(iter(device))
    if name not in device:
        raise ReaderError(f"{path}: reader {spec.reader!r} gives no stream {name!r}; "
                          f"it gives {', '.join(sorted(device))}")
    table = device[name]
    cols = ["temperature"] if name == "temperature" else ["x", "y", "z"]
    if len(cols) != len(spec.axes()):
        raise ReaderError(f"{path}: stream {name!r} cannot be taken as {spec.stream!r}")
    return (table.column("t_ns").to_numpy(),
            [table.column(c).to_numpy(zero_copy_only=False) for c in cols])


def resolve_sections(sections: Sections, devices: dict[str, dict[str, pa.Table]],
                     default_device: str, path: Path) -> dict[str, dict[str, Any]]:
    """Sections as ``{name: {start, end, t_start_ns, t_end_ns, stream}}``.

    ``start``/``end``: 0-based sample indices into ``stream`` (end exclusive);
    ``t_start_ns``/``t_end_ns``: time of the first and last sample inside.
    """
    device = sections.device or default_device
    table = devices.get(device, {}).get(sections.stream)
    if table is None:
        raise ConfigError(f"{path}: sections.stream: no {sections.stream!r} stream on device "
                          f"{device!r}")
    t = table.column("t_ns").to_numpy()
    raw: dict[str, tuple[float, float]] = {}
    if sections.file is not None:
        raw.update(_section_file(_file(path, sections.file)))
    raw.update(sections.items)
    out = {}
    for name, (a, b) in raw.items():
        if not (np.isfinite(a) and np.isfinite(b)):
            raise ConfigError(f"{path}: sections: {name!r} = [{a}, {b}] is not a pair of finite "
                              f"numbers; give its start and end in {sections.unit}")
        if sections.unit == "s":
            a, b = (int(np.searchsorted(t, t[0] + x * 1e9)) for x in (a, b))
        start, end = int(a), int(b)
        if not 0 <= start < end <= len(t):
            raise ConfigError(f"{path}: sections: {name!r} = [{start}, {end}) is outside the "
                              f"{len(t)} samples of {sections.stream!r}")
        out[name] = {"start": start, "end": end, "t_start_ns": int(t[start]),
                     "t_end_ns": int(t[end - 1]), "stream": sections.stream}
    return out


def _section_file(path: Path) -> dict[str, tuple[float, float]]:
    """imucal's section list: JSON ``{name: {"start": i, "end": j}}`` or CSV ``name,start,end``."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the section list ({exc.strerror})") from None
    try:
        if path.suffix.lower() == ".json":
            return {k: (v["start"], v["end"]) for k, v in json.loads(text).items()}
        rows = [line.split(",") for line in text.splitlines()[1:] if line.strip()]
        return {r[0].strip(): (float(r[1]), float(r[2])) for r in rows}
    except (ValueError, KeyError, TypeError, IndexError, AttributeError):
        raise ConfigError(f"{path}: not a section list; expected JSON "
                          "{\"name\": {\"start\": i, \"end\": j}} or CSV rows name,start,end") from None


_SESSION_TABLE = re.compile(rb"^\s*\[session\]", re.MULTILINE)


class ManifestReader:
    """``*.toml`` files with a ``[session]`` table."""

    name = "session"
    suffixes = (".toml",)

    def sniff(self, path: Path, head: bytes) -> bool:
        if path.suffix.lower() not in self.suffixes:
            return False
        with open(path, "rb") as f:
            return bool(_SESSION_TABLE.search(f.read(1 << 16)))

    def read(self, path: Path) -> Recording:
        return read_manifest(Path(path))

    def inputs(self, path: Path) -> list[Path]:
        """The data files the manifest names (streams and the sections file)."""
        manifest = load_manifest(Path(path))
        names = [s.file for s in manifest.streams]
        if manifest.sections is not None and manifest.sections.file is not None:
            names.append(manifest.sections.file)
        return [_file(Path(path), name) for name in names]

    def delegates(self, path: Path) -> list[str]:
        """The registered readers the manifest hands files to (they shape its tables too)."""
        return sorted({s.reader for s in load_manifest(Path(path)).streams if s.reader})


COMPONENTS = [ManifestReader()]
