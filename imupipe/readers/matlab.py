"""MATLAB v7.3 (HDF5) sample buffers, as sunsided/sensor-fusion logs them.

Each variable is an (n, 1 + k) buffer of rows ``[t, values...]`` (t in seconds).
Read alone, a file's known buffers are taken with sunsided's units:
``accelBuffer`` [g], ``gyroBuffer`` [deg/s], ``compassBuffer`` [gauss],
``temperatureBuffer`` [degC]. Other variable names or units go through a
session manifest (``format = "matlab"``, ``variable``, ``unit``). Needs the
``matlab`` extra (h5py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..components import Recording
from ..errors import ReaderError, require
from .csv import canonical_table

MAGIC = b"MATLAB 7.3 MAT-file"
KNOWN_BUFFERS = {  # variable -> (stream, unit)
    "accelBuffer": ("accel", "g"),
    "gyroBuffer": ("gyro", "deg/s"),
    "compassBuffer": ("mag", "gauss"),
    "temperatureBuffer": ("temperature", "degC"),
}


def variables(path: Path) -> list[str]:
    """Names of the numeric datasets at the top level of a v7.3 MAT file."""
    h5py = require("h5py", "matlab")
    with _open(path, h5py) as f:
        return sorted(k for k, v in f.items() if isinstance(v, h5py.Dataset) and not k.startswith("#"))


def read_buffer(path: Path, variable: str | None = None) -> np.ndarray:
    """The (n, k) float64 array of ``variable`` (default: the file's only variable).

    MATLAB stores column-major, so HDF5 shows an (n, k) matrix as (k, n): transposed back here.
    """
    h5py = require("h5py", "matlab")
    with _open(path, h5py) as f:
        names = sorted(k for k, v in f.items() if isinstance(v, h5py.Dataset) and not k.startswith("#"))
        if variable is None:
            if len(names) != 1:
                raise ReaderError(f"{path}: holds variables {', '.join(names) or 'none'}; "
                                  "name one with `variable = \"NAME\"` in the manifest")
            variable = names[0]
        if variable not in names:
            raise ReaderError(f"{path}: no variable {variable!r}; it holds {', '.join(names)}")
        data = f[variable]
        if data.ndim != 2 or data.dtype.kind not in "fiu":
            raise ReaderError(f"{path}: variable {variable!r} is not a numeric matrix "
                              f"(shape {data.shape}, type {data.dtype})")
        try:
            return np.asarray(data, dtype=np.float64).T
        except (OSError, ValueError, RuntimeError) as exc:  # a corrupt or truncated data block
            raise ReaderError(f"{path}: variable {variable!r} cannot be read ({exc}); the file "
                              "is damaged: save or copy it again") from None


def _open(path: Path, h5py):
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise ReaderError(f"{path}: not a MATLAB v7.3 (HDF5) file ({exc}); save it with "
                          "`save -v7.3` or export CSV") from None


class MatlabReader:
    """Sunsided-style MATLAB v7.3 buffers (``KNOWN_BUFFERS``) in one file."""

    name = "matlab"
    suffixes = (".mat",)

    def sniff(self, path: Path, head: bytes) -> bool:
        return path.suffix.lower() in self.suffixes and head.startswith(MAGIC)

    def read(self, path: Path) -> Recording:
        from .manifest import UNITS

        path = Path(path)
        present = [v for v in variables(path) if v in KNOWN_BUFFERS]
        if not present:
            raise ReaderError(f"{path}: no known buffer ({', '.join(KNOWN_BUFFERS)}); describe "
                              "the file in a session.toml with format = \"matlab\", variable, unit")
        streams = {}
        for variable in present:
            stream, unit = KNOWN_BUFFERS[variable]
            buffer = read_buffer(path, variable)
            width = 2 if stream == "temperature" else 4
            if buffer.shape[1] != width:
                raise ReaderError(f"{path}: {variable} has {buffer.shape[1]} columns, expected "
                                  f"{width} ([t, values...])")
            factor, addend = UNITS[stream][unit]
            t_ns = np.round(buffer[:, 0] * 1e9).astype(np.int64)
            values = [buffer[:, k] * factor + addend for k in range(1, width)]
            streams[stream] = canonical_table(stream, t_ns, values, {
                "imupipe.source": str(path), "imupipe.source_unit": unit})
        return Recording(source=str(path), devices={"imu": streams})


COMPONENTS = [MatlabReader()]
