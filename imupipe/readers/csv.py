"""CSV: the canonical layout (read without a manifest) and column-mapped parsing.

Canonical layout: a header ``t_ns,accel_x,accel_y,accel_z,gyro_x,gyro_y,gyro_z,
mag_x,mag_y,mag_z,temperature`` with any subset of whole triads, ``t_ns`` int64
nanoseconds, values SI (m/s^2, rad/s, T) and degC. Any other layout (units,
fixed rate, column names, header lines, delimiter) is described by a session
manifest (``manifest.py``), which parses the file with ``read_columns``.
"""

from __future__ import annotations

import io
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa

from .. import schemas
from ..components import Recording
from ..errors import ReaderError

if TYPE_CHECKING:
    import polars as pl

CANONICAL = {
    "accel": ("accel_x", "accel_y", "accel_z"),
    "gyro": ("gyro_x", "gyro_y", "gyro_z"),
    "mag": ("mag_x", "mag_y", "mag_z"),
    "temperature": ("temperature",),
}
WHITESPACE = "whitespace"  # delimiter value: runs of blanks/tabs, as in imu_tk's text files

ColumnRef = str | int  # a header name, or a 0-based column index


def first_line(path: Path, skip_lines: int = 0, limit: int = 1 << 16) -> str:
    """The first line after ``skip_lines`` lines (at most ``limit`` bytes), without its newline
    (and without a UTF-8 byte-order mark at the start of the file)."""
    with open(path, "rb") as f:
        for _ in range(skip_lines):
            if not f.readline(limit):
                break
        line = f.readline(limit)
        if skip_lines == 0:
            line = line.removeprefix(b"\xef\xbb\xbf")  # a UTF-8 byte-order mark
        return line.decode("utf-8", errors="replace").rstrip("\r\n")


def split_fields(line: str, delimiter: str) -> list[str]:
    if delimiter == WHITESPACE:
        return line.split()
    return [f.strip().strip('"') for f in line.split(delimiter)]


def read_columns(path: Path, refs: Mapping[str, ColumnRef], *, delimiter: str = ",",
                 skip_lines: int = 0, header: bool = True,
                 int_keys: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Parse columns of a delimited text file.

    ``refs`` maps an output key to a header name or 0-based column index. Returns
    key -> array with one value per data row: float64, or int64 for ``int_keys``.
    Raises ``ReaderError`` naming the file and the line for a missing column, an
    empty or unparseable value, or a non-finite value.
    """
    if not path.is_file():
        raise ReaderError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise ReaderError(f"{path}: the file is empty")
    names = split_fields(first_line(path, skip_lines), delimiter) if header else []
    indices = {key: _resolve(path, ref, names, header) for key, ref in refs.items()}
    first_data_line = skip_lines + (2 if header else 1)  # 1-based line number of data row 0

    source: Path | io.BytesIO = path
    sep = delimiter
    if delimiter == WHITESPACE:
        # Runs of blanks become one comma, so one fast parser serves both layouts.
        lines = path.read_bytes().split(b"\n")
        source, sep = io.BytesIO(b"\n".join(b",".join(line.split()) for line in lines)), ","
    width = len(names) if header else len(split_fields(first_line(path, skip_lines), delimiter))
    numbers = _number_columns(source, sep, skip_lines + header, width, indices, int_keys)
    if numbers is not None:
        return numbers
    # Something is off (or unusual): polars parses it, as text if need be, and says where.
    import polars as pl  # here, not at module level: registering the readers stays cheap

    dtypes = {i: pl.Float64 for i in indices.values()}
    dtypes.update({indices[k]: pl.Int64 for k in int_keys if k in indices})
    frame = _typed_frame(source, sep, header, skip_lines, width, dtypes)
    if frame is None:  # something is off: parse as text to say where
        frame = _text_frame(path, source, sep, header, skip_lines, delimiter, names)
    if frame.height == 0:
        raise ReaderError(f"{path}: has no data rows")
    out = {}
    for key, index in indices.items():
        if index >= frame.width:
            raise ReaderError(f"{path}: no column {index} (the file has {frame.width} columns)")
        label = names[index] if header else f"column {index}"
        column = frame.to_series(index)
        dtype = dtypes[index] if key not in int_keys else pl.Int64
        if column.dtype == pl.String:
            column = column.str.strip_chars()
            values = column.cast(dtype, strict=False)
            bad = values.is_null()
            if bad.any():
                row = int(bad.arg_max())
                text = column[row]
                what = "an empty value" if text in (None, "") else f"{text!r}, not a number"
                raise ReaderError(f"{path}: line {first_data_line + row}: {what} in column "
                                  f"{label!r}; fix or remove that row")
        else:
            values = column.cast(dtype)
        array = values.to_numpy()
        if dtype == pl.Float64:
            finite = np.isfinite(array)
            if not finite.all():
                row = int(np.argmin(finite))
                raise ReaderError(f"{path}: line {first_data_line + row}: non-finite value "
                                  f"{str(column[row])!r} in column {label!r}; fix or remove "
                                  "that row")
        out[key] = array
    return out


def _number_columns(source: Path | io.BytesIO, sep: str, skip_rows: int, width: int,
                    indices: Mapping[str, int], int_keys: tuple[str, ...]) -> dict[str, np.ndarray] | None:
    """The fast path (pyarrow's CSV parser, already loaded): key -> the wanted column as
    numbers; None on any trouble: a row without ``width`` fields, a blank line, an empty,
    missing or non-finite value."""
    import pyarrow.csv as pcsv

    types = {f"f{i}": pa.float64() for i in indices.values()}
    types.update({f"f{indices[k]}": pa.int64() for k in int_keys if k in indices})
    names = [f"f{i}" for i in range(width)]
    try:
        table = pcsv.read_csv(
            source, read_options=pcsv.ReadOptions(skip_rows=skip_rows, column_names=names),
            parse_options=pcsv.ParseOptions(delimiter=sep, ignore_empty_lines=False),
            convert_options=pcsv.ConvertOptions(column_types=types, include_columns=list(types)))
    except (pa.ArrowException, OSError, ValueError):  # ValueError: a non-ASCII delimiter
        return None
    finally:
        if isinstance(source, io.BytesIO):
            source.seek(0)
    if not table.num_rows:
        return None
    out = {}
    for key, index in indices.items():
        column = table.column(f"f{index}")
        if column.null_count:
            return None
        out[key] = column.to_numpy()
        if key not in int_keys and not np.isfinite(out[key]).all():
            return None
    return out


def _typed_frame(source: Path | io.BytesIO, sep: str, header: bool, skip_lines: int, width: int,
                 dtypes: dict[int, pl.DataType]) -> pl.DataFrame | None:
    """Polars' typed parse of the wanted columns; None on any trouble or empty value."""
    import polars as pl

    schema = {f"c{i}": dtypes.get(i, pl.String) for i in range(width)}
    try:
        frame = pl.read_csv(source, separator=sep, has_header=header, skip_rows=skip_lines,
                            schema=schema, quote_char='"')
    except (pl.exceptions.PolarsError, OSError):
        return None
    finally:
        if isinstance(source, io.BytesIO):
            source.seek(0)
    frame = _drop_trailing_blank(frame)
    if any(frame.to_series(i).null_count() for i in dtypes if i < frame.width):
        return None
    return frame


def _drop_trailing_blank(frame: pl.DataFrame) -> pl.DataFrame:
    """Without the rows of blank lines at the end of the file (all fields empty)."""
    import polars as pl

    if frame.height == 0 or frame.width == 0:
        return frame
    empty = pl.all_horizontal(
        [pl.col(c).is_null() | (pl.col(c).cast(pl.String).str.strip_chars() == "")
         for c in frame.columns])
    blank = frame.select(empty.alias("blank")).to_series().to_numpy()
    keep = len(blank)
    while keep and blank[keep - 1]:
        keep -= 1
    return frame.head(keep)


def _text_frame(path: Path, source: Path | io.BytesIO, sep: str, header: bool, skip_lines: int,
                delimiter: str, names: list[str]) -> pl.DataFrame:
    """Every column as text (the slow path that finds the bad line)."""
    import polars as pl

    try:
        # All columns, not a projection: polars checks row widths only of what it parses.
        return _drop_trailing_blank(pl.read_csv(
            source, separator=sep, has_header=header, skip_rows=skip_lines, infer_schema=False,
            quote_char='"'))
    except pl.exceptions.NoDataError:
        raise ReaderError(f"{path}: has no data rows") from None
    except (pl.exceptions.PolarsError, OSError) as exc:
        line = _first_ragged_line(path, delimiter, skip_lines, header, len(names) or None)
        where = f"line {line}" if line else "somewhere"
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ReaderError(f"{path}: cannot parse {where} ({msg}); check the delimiter and "
                          "header lines") from None


def _resolve(path: Path, ref: ColumnRef, names: list[str], header: bool) -> int:
    if isinstance(ref, int):
        if ref < 0 or (header and ref >= len(names)):
            raise ReaderError(f"{path}: no column {ref} (the file has {len(names)} columns)")
        return ref
    if not header:
        m = re.fullmatch(r"col(\d+)", ref)
        if m:
            return int(m.group(1))
        raise ReaderError(f"{path}: column {ref!r} cannot be found in a file without a header; "
                          "refer to columns as col0, col1, ... or by 0-based index")
    if ref in names:
        return names.index(ref)
    raise ReaderError(f"{path}: missing column {ref!r}; the header has: {', '.join(names)}")


def _first_ragged_line(path: Path, delimiter: str, skip_lines: int, header: bool,
                       width: int | None) -> int | None:
    """The 1-based number of the first data line whose field count differs (slow; errors only)."""
    with open(path, encoding="utf-8", errors="replace") as f:
        for number, line in enumerate(f, start=1):
            if number <= skip_lines + (1 if header else 0) or not line.strip():
                continue
            n = len(split_fields(line.rstrip("\r\n"), delimiter))
            if width is None:
                width = n
            elif n != width:
                return number
    return None


@dataclass(frozen=True)
class CanonicalCsvReader:
    """The canonical CSV layout (``CANONICAL``), recognised by its ``t_ns`` header."""

    name: str = "csv"
    suffixes: tuple[str, ...] = (".csv",)

    def sniff(self, path: Path, head: bytes) -> bool:
        if path.suffix.lower() not in self.suffixes:
            return False
        return split_fields(first_line(path), ",")[:1] == ["t_ns"]

    def read(self, path: Path) -> Recording:
        names = split_fields(first_line(path), ",")
        known = {c for cols in CANONICAL.values() for c in cols} | {"t_ns"}
        unknown = [n for n in names if n not in known]
        if unknown or names[:1] != ["t_ns"]:
            raise ReaderError(
                f"{path}: not the canonical CSV layout (unknown column(s) {', '.join(unknown)}); "
                "rename them or describe the layout in a session.toml manifest"
            )
        present = {}
        for stream, cols in CANONICAL.items():
            have = [c for c in cols if c in names]
            if have and len(have) < len(cols):
                missing = [c for c in cols if c not in names]
                raise ReaderError(f"{path}: missing column(s) {', '.join(missing)} of the "
                                  f"{stream} triad; give all three axes or none")
            if have:
                present[stream] = cols
        if not present:
            raise ReaderError(f"{path}: no sensor columns besides t_ns; expected any of "
                              f"{', '.join(c for cols in CANONICAL.values() for c in cols)}")
        refs = {n: n for n in ["t_ns", *(c for cols in present.values() for c in cols)]}
        data = read_columns(path, refs, int_keys=("t_ns",))
        streams = {stream: canonical_table(stream, data["t_ns"], [data[c] for c in cols])
                   for stream, cols in present.items()}
        return Recording(source=str(path), devices={"imu": streams})


def canonical_table(stream: str, t_ns: np.ndarray, values: list[np.ndarray],
                    extra: dict[str, str] | None = None) -> pa.Table:
    """A stamped canonical table: ``t_ns`` (n,) int64 ns and (n,) SI columns of ``stream``."""
    names = ["temperature"] if stream == "temperature" else ["x", "y", "z"]
    if len(values) != len(names):
        raise ValueError(f"{stream}: expected {len(names)} value columns, got {len(values)}")
    columns = {"t_ns": pa.array(np.asarray(t_ns, dtype=np.int64))}
    columns.update({n: pa.array(np.asarray(v, dtype=np.float64)) for n, v in zip(names, values,
                                                                                  strict=True)})
    return schemas.stamp(pa.table(columns), stream, extra)


COMPONENTS = [CanonicalCsvReader()]
