"""The session manifest's schema (pydantic models), imported when a manifest is read: the readers
are registered by every command, and importing pydantic is a tenth of ``imupipe ingest``."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .csv import WHITESPACE, ColumnRef
from .manifest import UNITS, StreamName


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


PerAxis = float | tuple[float, float, float]


class SessionInfo(_Model):
    name: str
    description: str = ""
    device: str = "imu"  # device of streams that do not name one


class StreamSpec(_Model):
    """One stream from one file: ``SI = (raw - offset) * scale * unit_factor``."""

    stream: StreamName
    file: str
    device: str | None = None
    reader: str | None = None  # a registered reader parses the file instead of this module
    source_stream: str | None = None  # with reader: which of its streams (default: the only one)
    source_device: str | None = None  # with reader: which of its devices (default: the only one)
    format: Literal["csv", "matlab"] | None = None  # default: by suffix
    delimiter: str = ","  # one character, or "whitespace"
    skip_lines: int = Field(0, ge=0, le=1_000_000)  # lines before the header (or the data, without header)
    header: bool = True
    variable: str | None = None  # matlab: dataset name (default: the file's only one)
    columns: dict[str, ColumnRef] = {}  # t, x, y, z (or t, temperature) -> name / 0-based index
    time_unit: Literal["s", "ms", "us", "ns", "samples"] = "s"
    rate_hz: float | None = Field(None, gt=0)  # fixed rate when there is no time column
    unit: str | None = None  # default: the canonical SI unit of the stream
    scale: PerAxis = 1.0
    lsb_per_unit: PerAxis | None = None  # datasheet sensitivity, e.g. 16384 LSB/g: scale = 1/it
    offset: PerAxis = 0.0
    repair: list[Literal["drop_zero_padding"]] = []

    @model_validator(mode="after")
    def _consistent(self) -> StreamSpec:
        axes = self.axes()
        if self.unit is not None and self.unit not in UNITS[self.stream]:
            raise ValueError(f"unit {self.unit!r} does not fit stream {self.stream!r}; "
                             f"known: {', '.join(UNITS[self.stream])}")
        if self.lsb_per_unit is not None and self.scale != 1.0:
            raise ValueError("give either scale or lsb_per_unit, not both")
        if self.reader is None:
            extra = sorted(set(self.columns) - {"t", *axes})
            if extra:
                raise ValueError(f"columns has unknown key(s) {', '.join(extra)}; "
                                 f"{self.stream} takes t, {', '.join(axes)}")
            if self.columns and not set(axes) <= set(self.columns):
                missing = [a for a in axes if a not in self.columns]
                raise ValueError(f"columns lacks {', '.join(missing)}")
            if self.columns and "t" not in self.columns and self.rate_hz is None:
                raise ValueError("no time column: give columns.t or rate_hz")
            if "t" in self.columns and self.rate_hz is not None and self.time_unit != "samples":
                raise ValueError("both columns.t and rate_hz: give one (or time_unit = "
                                 "\"samples\" for a sample counter)")
            if self.time_unit == "samples" and self.rate_hz is None:
                raise ValueError("time_unit = \"samples\" needs rate_hz")
            if self.delimiter != WHITESPACE and len(self.delimiter) != 1:
                raise ValueError("delimiter must be one character or \"whitespace\"")
        return self

    def axes(self) -> list[str]:
        return ["temperature"] if self.stream == "temperature" else ["x", "y", "z"]

    def column_refs(self) -> dict[str, ColumnRef]:
        """Explicit columns, or positional defaults: [t,] x, y, z (or [t,] temperature)."""
        if self.columns:
            return dict(self.columns)
        keys = self.axes() if self.rate_hz is not None and self.time_unit != "samples" \
            else ["t", *self.axes()]
        return {k: i for i, k in enumerate(keys)}

    def scale_factors(self) -> np.ndarray:
        """(k,) per-axis factor from raw values to the declared unit."""
        scale = 1.0 / np.asarray(self.lsb_per_unit, float) if self.lsb_per_unit is not None \
            else np.asarray(self.scale, float)
        return np.broadcast_to(scale, (len(self.axes()),))


class Sections(_Model):
    """Named protocol sections, from a file (imucal's section list) and/or inline."""

    file: str | None = None  # JSON {name: {start, end}} or CSV "name,start,end"
    stream: StreamName = "accel"  # whose samples the indices count
    device: str | None = None
    unit: Literal["samples", "s"] = "samples"  # samples: 0-based, end exclusive; s: from 1st sample
    items: dict[str, tuple[float, float]] = {}


class Manifest(_Model):
    session: SessionInfo
    streams: list[StreamSpec] = Field(min_length=1)
    sections: Sections | None = None
    meta: dict[str, Any] = {}  # free-form facts copied into Recording.meta["meta"]
