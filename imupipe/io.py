"""Atomic file output and Arrow IPC helpers: nothing half-written is ever left looking complete."""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import tempfile
import weakref
from collections.abc import Iterator
from pathlib import Path

import pyarrow as pa
from pyarrow import ipc


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it into place only if the block succeeds.

    The temporary name ``.<name>.<pid>.<random>.part`` says which process writes it, so a
    later run can remove what a killed one left (``pipeline.api.remove_stale_parts``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".part", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs are ordinary files
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def copy_file(src: Path, dst: Path) -> None:
    """``dst`` becomes a copy of ``src`` atomically (a temporary name, then a rename)."""
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


class _Hashing:
    """A write-only stream that hashes and counts the bytes passing through it (on to ``out``):
    Arrow IPC is digested and written without ever holding the whole file in memory."""

    def __init__(self, out=None):
        self.sha256, self.size, self.out, self.closed = hashlib.sha256(), 0, out, False

    def write(self, data) -> int:
        self.sha256.update(data)
        self.size += len(data)
        if self.out is not None:
            self.out.write(data)
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True


def write_arrow_hashed(path: Path, table: pa.Table) -> tuple[int, str]:
    """Write ``table`` as an Arrow IPC file, atomically; return its size and sha256."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        sink = _Hashing(fh)
        with ipc.new_file(pa.PythonFile(sink, mode="w"), table.schema) as writer:
            writer.write_table(table)
    return sink.size, sink.sha256.hexdigest()


def write_arrow(path: Path, table: pa.Table) -> None:
    """Write ``table`` as an Arrow IPC file, atomically."""
    with (
        atomic_path(path) as tmp,
        pa.OSFile(str(tmp), "wb") as sink,
        ipc.new_file(sink, table.schema) as writer,
    ):
        writer.write_table(table)


def read_arrow(path: Path) -> pa.Table:
    with pa.memory_map(str(path), "r") as source:
        return ipc.open_file(source).read_all()


def file_digest(path: Path, chunk: int = 1 << 20) -> str:
    """sha256 hex digest of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


_DIGESTS: dict[int, tuple[weakref.ref, str]] = {}  # id -> (the table, its digest): tables are immutable


def table_digest(table: pa.Table) -> str:
    """sha256 of a table's content (schema incl. metadata, and data), independent of chunking;
    remembered while the table lives (a stage's output is digested when stored, and again by
    the exports and figures keyed by it)."""
    known = _DIGESTS.get(id(table))
    if known is not None and known[0]() is table:
        return known[1]
    sink = _Hashing()
    with ipc.new_stream(pa.PythonFile(sink, mode="w"), table.schema) as writer:
        writer.write_table(table.combine_chunks())
    digest = sink.sha256.hexdigest()
    key = id(table)
    _DIGESTS[key] = (weakref.ref(table, lambda _, key=key: _DIGESTS.pop(key, None)), digest)
    return digest


def remove(path: Path) -> None:
    """Remove a file, link or folder tree if it is there."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
