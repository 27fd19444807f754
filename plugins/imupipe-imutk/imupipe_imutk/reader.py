"""imu_tk's ASCII sample files: rows ``t x y z`` (t [s], x y z raw counts), one sensor per file.

imu_tk (Tedaldi et al., ICRA 2014) reads these with ``importAsciiData``: one
sample per line, whitespace-separated, no header. The Xsens test data ship them
with a ``.mat`` suffix although they are text.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pyarrow as pa
from imupipe import schemas
from imupipe.components import Recording
from imupipe.errors import ReaderError

_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")
STREAM_BY_NAME = (("acc", "accel"), ("gyr", "gyro"), ("mag", "mag"))


def stream_from_name(path: Path) -> str | None:
    """``xsens_acc.mat`` -> ``accel``; None when the name does not say."""
    stem = path.stem.lower()
    for key, stream in STREAM_BY_NAME:
        if key in stem:
            return stream
    return None


def load(path: Path) -> np.ndarray:
    """The (n, 4) float64 rows ``[t_s, x, y, z]``; ``ReaderError`` names the first bad line."""
    rows = []
    with open(path, encoding="ascii", errors="replace") as f:
        for number, line in enumerate(f, start=1):
            fields = line.split()
            if not fields:
                continue
            if len(fields) != 4:
                raise ReaderError(f"{path}: line {number}: {len(fields)} columns, expected 4 "
                                  "(t x y z)")
            try:
                rows.append([float(v) for v in fields])
            except ValueError:
                raise ReaderError(f"{path}: line {number}: not a number in {line.strip()!r}") \
                    from None
    if not rows:
        raise ReaderError(f"{path}: holds no samples")
    return np.asarray(rows, dtype=np.float64)


class ImutkTextReader:
    """imu_tk ASCII files; values stay raw counts (``imupipe.source_unit = counts``)."""

    name = "imutk_text"
    suffixes = (".mat", ".txt", ".dat")

    def sniff(self, path: Path, head: bytes) -> bool:
        if path.suffix.lower() not in self.suffixes or head.startswith(b"MATLAB"):
            return False
        with open(path, "rb") as f:
            first = f.readline(4096).decode("ascii", errors="replace").split()
        return len(first) == 4 and all(_NUMBER.match(v) for v in first)

    def read(self, path: Path) -> Recording:
        path = Path(path)
        stream = stream_from_name(path)
        if stream is None:
            raise ReaderError(f"{path}: cannot tell the sensor from the file name (expected "
                              "'acc', 'gyr' or 'mag' in it); rename the file or name the stream "
                              "in a session.toml with reader = \"imutk_text\"")
        data = load(path)
        table = pa.table({"t_ns": np.round(data[:, 0] * 1e9).astype(np.int64),
                          "x": data[:, 1], "y": data[:, 2], "z": data[:, 3]})
        table = schemas.stamp(table, stream, {"imupipe.source": str(path),
                                              "imupipe.source_unit": "counts"})
        return Recording(source=str(path), devices={"imu": {stream: table}})
