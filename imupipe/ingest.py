"""Read any recording a registered reader accepts and check its canonical tables.

Checks that apply to every format live here, once: each stream is non-empty,
claims its schema, has strictly increasing time and finite values.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyarrow as pa

from . import schemas
from .components import Recording
from .errors import ReaderError, SchemaError
from .io import write_arrow
from .paths import check_out_dir, safe_name, under, unique_names
from .plugins import Registry

STREAMS = ("accel", "gyro", "mag", "temperature")
TRIADS = ("accel", "gyro", "mag")
# Plausibility bounds of every reader's output (beyond them the file's units or clock are wrong):
MAX_ABS_VALUE = 1e12  # no sensor, in SI or raw counts, reads more; 1e300 would overflow the fits
RATE_CHECKED = ("accel", "gyro")  # a magnetometer or thermometer may well be slow
MIN_RATE_HZ, MAX_RATE_HZ = 5.0, 1e5  # 1 Hz data, or stamps off by 1000, cannot be calibrated


def check_session_path(path: Path) -> Path:
    """``path`` if it is a regular file (or a folder, which callers judge); else one clear error.

    Refused: a missing file, a symbolic-link loop, a FIFO, socket or device file
    (which would be read forever or not at all).
    """
    import errno
    import stat

    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ReaderError(f"{path}: a loop of symbolic links; point it at a recording") from None
        if exc.errno in (errno.ENOENT, errno.ENOTDIR):
            raise ReaderError(f"{path}: no such file") from None
        raise ReaderError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
                else "a device file")
        raise ReaderError(f"{path}: is {kind}, not a recording file; copy the data to a file first")
    return path


def choose_reader(path: Path, registry: Registry, name: str | None = None):
    """The reader for ``path``: ``name`` if given, else the one that claims the file."""
    if name is not None:
        return registry.get("readers", name)
    check_session_path(path)
    if path.is_dir():
        raise ReaderError(f"{path}: is a directory; give a recording file or a session.toml")
    with open(path, "rb") as f:
        head = f.read(64)
    readers = {n: registry.get("readers", n) for n in registry.names("readers")}
    chosen = registry.pm.hook.imupipe_choose_reader(path=path, head=head, readers=readers)
    if chosen is None:
        if not head:
            raise ReaderError(f"{path}: the file is empty")
        raise ReaderError(
            f"{path}: no reader accepts this file (known readers: {', '.join(sorted(readers))}); "
            "for a recording split over several files, write a session.toml manifest"
        )
    return registry.get("readers", chosen)


def read_recording(path: Path | str, registry: Registry, reader: str | None = None) -> Recording:
    """Read and check a recording."""
    path = Path(path)
    recording = choose_reader(path, registry, reader).read(path)
    if not any(stream in TRIADS for streams in recording.devices.values() for stream in streams):
        found = sorted({s for streams in recording.devices.values() for s in streams})
        raise ReaderError(
            f"{path}: holds no IMU data (no accelerometer, gyroscope or magnetometer stream; "
            f"found: {', '.join(found) or 'nothing'})"
        )
    for device, streams in recording.devices.items():
        for stream, table in streams.items():
            check_stream(table, stream, f"{path} [{device}/{stream}]")
    return recording


def check_stream(table: pa.Table, stream: str, where: str) -> None:
    """Raise ``ReaderError`` if a sample table is empty, unordered, has non-finite or absurd values."""
    try:
        schemas.check(table, stream, where)
    except SchemaError as exc:
        raise ReaderError(str(exc)) from None
    if table.num_rows == 0:
        raise ReaderError(f"{where}: stream has no samples")
    t = table.column("t_ns").to_numpy()
    dt = np.diff(t)
    if len(dt) and dt.min() <= 0:  # one pass over a good stream; where it fails, found after
        if (dt < 0).any():
            i = int(np.argmax(dt < 0))
            raise ReaderError(
                f"{where}: time goes backwards at sample {i + 1} ({t[i]} ns -> {t[i + 1]} ns); "
                "sort the recording or fix the logger's clock"
            )
        i = int(np.argmax(dt == 0))
        raise ReaderError(f"{where}: duplicate time stamp {t[i]} ns at samples {i} and {i + 1}")
    for name in table.column_names:
        if name == "t_ns" or not pa.types.is_floating(table.schema.field(name).type):
            continue
        values = table.column(name).to_numpy(zero_copy_only=False)
        if -MAX_ABS_VALUE <= values.min() and values.max() <= MAX_ABS_VALUE:  # NaN fails both
            continue
        bad = ~np.isfinite(values)
        if bad.any():
            i = int(np.argmax(bad))
            raise ReaderError(f"{where}: non-finite value {values[i]} in column {name!r} at sample {i}")
        i = int(np.argmax(np.abs(values) > MAX_ABS_VALUE))
        raise ReaderError(f"{where}: value {values[i]:.3g} in column {name!r} at sample {i} is "
                          f"beyond any sensor's range (|x| > {MAX_ABS_VALUE:g}); check the "
                          "file's unit and scale")


def check_rate(table: pa.Table, stream: str, where: str) -> None:
    """Raise ``ReaderError`` if an accel or gyro stream's rate is one no calibration can use
    (1 Hz data; time stamps in another unit than the file claims). Checked by ``imupipe run``;
    ``ingest`` converts whatever it is given."""
    if stream not in RATE_CHECKED:
        return
    t = table.column("t_ns").to_numpy()
    if len(t) < 2:
        return
    interval = float(np.median(np.diff(t)))
    rate = 1e9 / interval if interval > 0 else float("inf")
    if not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:
        raise ReaderError(
            f"{where}: sample rate {rate:.3g} Hz (median interval {interval * 1e-9:.3g} s) is "
            f"outside {MIN_RATE_HZ:g} Hz .. {MAX_RATE_HZ:g} Hz that an IMU calibration needs; "
            "are the time stamps in the unit the file claims (s, ms, us, ns)?")


def write_recording(recording: Recording, out_dir: Path) -> list[Path]:
    """Write every canonical table as Arrow IPC: ``out_dir/<device>/<stream>.arrow``.

    A device name is made a safe folder name, unique among the recording's
    devices (``paths.unique_names``), and every path is checked to lie in ``out_dir``.
    """
    out_dir = check_out_dir(Path(out_dir))
    folders = unique_names(recording.devices)
    written = []
    for device, streams in recording.devices.items():
        for stream, table in streams.items():
            path = under(out_dir, folders[device], f"{safe_name(stream, 'stream')}.arrow")
            write_arrow(path, table)
            written.append(path)
    return written


FACT_KEYS = ("imupipe.topic", "imupipe.device_id", "imupipe.frame_convention")


def sections_table(sections) -> pa.Table:
    """The ``sections`` table (schemas/sections.json) of ``Recording.meta["sections"]``: what a
    pipeline reads as ``session.sections``."""
    names = list(sections)
    col = lambda key, typ: pa.array([sections[n][key] for n in names], type=typ)  # noqa: E731
    table = pa.table({"name": pa.array(names, pa.string()), "t_start_ns": col("t_start_ns", pa.int64()),
                      "t_end_ns": col("t_end_ns", pa.int64()), "start": col("start", pa.int64()),
                      "end": col("end", pa.int64()), "stream": col("stream", pa.string())})
    return schemas.stamp(table, "sections")


def stream_facts(streams: dict[str, pa.Table]) -> dict[str, dict]:
    """Per stream, what exporters need beyond the calibration (JSON-ready).

    ``samples``, ``rate_hz`` (1 / median sample interval), the reader's metadata
    named in ``FACT_KEYS`` without the ``imupipe.`` prefix (``topic``,
    ``device_id``, ``frame_convention``), and for ``temperature`` its
    ``min_C``/``max_C``.
    """
    out: dict[str, dict] = {}
    for name, table in sorted(streams.items()):
        if "t_ns" not in table.column_names:  # not a sample stream (session.sections)
            continue
        t = table.column("t_ns").to_numpy()
        facts: dict = {"samples": len(t)}
        if len(t) > 1:
            facts["rate_hz"] = float(1e9 / np.median(np.diff(t)))
        meta = table.schema.metadata or {}
        for key in FACT_KEYS:
            if key.encode() in meta:
                facts[key.split(".", 1)[1]] = meta[key.encode()].decode()
        if name == "temperature" and len(t):
            values = table.column("temperature").to_numpy()
            facts["min_C"], facts["max_C"] = float(values.min()), float(values.max())
        out[name] = facts
    return out
