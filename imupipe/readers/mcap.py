"""MCAP files of ROS 2 IMU messages -> canonical tables.

Topics are found by schema name (``sensor_msgs/msg/Imu``, ``MagneticField``,
``Temperature``); each topic namespace is one device (``/imu0/imu`` ->
``imu0``; ``/imu`` -> ``imu``). Sample time is ``header.stamp`` (``log_time``
when the stamp is zero). REP-145: an Imu message whose
``linear_acceleration_covariance[0]`` is -1 carries no accelerometer sample,
likewise for the gyroscope.

Fast path: the summary's chunk indexes locate the chunks, their message
indexes the messages. A worker thread reads consecutive chunks, decompresses
them into a reused batch buffer and checks their CRCs; meanwhile numpy decodes
the previous batch, one pass per topic (``cdr.decode_rows`` / ``cdr.decode``):
no Python loop per message. Files the fast path does not cover (unindexed,
message indexes or channels missing from the summary, big-endian or
non-standard CDR) go through the generic ``mcap_ros2`` decoder (extra ``ros``)
with identical results. Messages are taken in file order.
"""

from __future__ import annotations

import logging
import struct
import warnings
from collections import defaultdict, deque
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import lz4.frame
import numpy as np
import pyarrow as pa
import zstandard
from isal.isal_zlib import crc32  # CRC-32 as zlib's, ~9x faster (SIMD)
from mcap.exceptions import McapError

from .. import schemas
from ..columns import arrow_column
from ..components import Recording
from ..errors import ReaderError, require
from . import cdr
from .cdr import NotCovered

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
FOOTER_SIZE = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, crc
OP_CHUNK, OP_MESSAGE_INDEX, OP_MESSAGE = 0x06, 0x07, 0x05
MESSAGE_HEAD = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel, sequence, log_time, publish_time
RECOVER = ("re-record it, or salvage what it holds with the mcap CLI: "
           "`mcap recover FILE -o FIXED.mcap`")

LOOKAHEAD = 2  # batches read and decompressed ahead, in a thread, while one is decoded
BATCH_BYTES = 4 << 20  # uncompressed records per batch: amortises numpy's per-call cost
# REP-103: ROS body frames are x forward, y left, z up; exporters to FRD targets use it
FRAME_CONVENTION = "FLU"
COLUMNS = {"accel": ("x", "y", "z"), "gyro": ("x", "y", "z"), "mag": ("x", "y", "z"),
           "temperature": ("temperature",)}


class Sink:
    """Growable columns of one stream: ``t`` (n,) int64 ns, ``v`` (k, n) float64, column-major.

    Filled chunk by chunk, so that the decoded data exist once (Arrow wraps the
    columns without copying).
    """

    def __init__(self, k: int, capacity: int = 0):
        self.t, self.v, self.n = np.empty(capacity, np.int64), np.empty((k, capacity)), 0

    def append(self, t: np.ndarray, values: np.ndarray) -> None:
        """Add samples: ``t`` (m,), ``values`` (m, k)."""
        end = self.n + len(t)
        if end > len(self.t):
            grown = Sink(len(self.v), max(end, 2 * len(self.t)))
            grown.t[:self.n], grown.v[:, :self.n] = self.t[:self.n], self.v[:, :self.n]
            self.t, self.v = grown.t, grown.v
        self.t[self.n:end] = t
        for j in range(len(self.v)):  # row by row: 2x faster than assigning values.T
            self.v[j, self.n:end] = values[:, j]
        self.n = end


class Pieces(dict):
    """(topic, kind) -> stream -> ``Sink``; ``expected`` messages per (topic, kind) if known."""

    def __init__(self):
        super().__init__()
        self.expected: dict[tuple[str, str], int] = {}

    def add(self, topic: str, kind: str, t: np.ndarray, block: np.ndarray) -> None:
        streams = self.setdefault((topic, kind), {})
        for stream, (ts, values) in split(kind, t, block).items():
            if stream not in streams:
                streams[stream] = Sink(len(COLUMNS[stream]), self.expected.get((topic, kind), 0))
            streams[stream].append(ts, values)


class McapReader:
    """Reads ROS 2 ``sensor_msgs`` IMU, magnetometer and temperature topics from MCAP."""

    name = "mcap"
    suffixes = (".mcap",)

    def sniff(self, path: Path, head: bytes) -> bool:
        return head.startswith(MAGIC) or Path(path).suffix.lower() in self.suffixes

    def read(self, path: Path) -> Recording:
        return read_mcap(path)


COMPONENTS = [McapReader()]


def read_mcap(path: Path | str, *, fast: bool = True) -> Recording:
    """Read an MCAP file; ``fast=False`` forces the generic decoder (for comparisons)."""
    path = Path(path)
    pieces = Pieces()
    other: set[str] = set()
    try:
        with open(path, "rb") as f:
            size = f.seek(0, 2)
            _check_ends(f, path, size)
            try:
                if not fast:
                    raise NotCovered("the generic decoder was asked for")
                _read_fast(f, path, size, pieces, other)
            except NotCovered as why:
                log.info("%s: %s; using the generic ROS 2 decoder", path, why)
                pieces = Pieces()
                other.clear()
                _read_generic(f, pieces, other)
    except (McapError, struct.error, ValueError, EOFError, zstandard.ZstdError) as exc:
        raise ReaderError(f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc}); "
                          f"{RECOVER}") from None
    return _recording(path, pieces, other)


# --------------------------------------------------------------------------- fast path


def _check_ends(f, path: Path, size: int) -> None:
    if size == 0:
        raise ReaderError(f"{path}: the file is empty; re-record or re-export it")
    f.seek(0)
    if f.read(len(MAGIC)) != MAGIC:
        raise ReaderError(f"{path}: not an MCAP file (no MCAP magic bytes at the start); "
                          "check the file type or its extension")
    f.seek(max(size - len(MAGIC), 0))
    if size < 2 * len(MAGIC) + FOOTER_SIZE or f.read(len(MAGIC)) != MAGIC:
        raise ReaderError(f"{path}: MCAP file is truncated (no footer: the recording was cut off); "
                          f"{RECOVER}")


def _read_fast(f, path: Path, size: int, pieces: Pieces, other: set[str]) -> None:
    """Decode every IMU message chunk by chunk with numpy; ``NotCovered`` if it cannot."""
    f.seek(size - len(MAGIC) - FOOTER_SIZE)
    footer = f.read(FOOTER_SIZE)
    summary_start, _, summary_crc = struct.unpack_from("<QQI", footer, 9)
    if summary_start == 0:
        raise NotCovered("the file has no summary section (unindexed)")
    if summary_crc:
        f.seek(summary_start)
        covered = f.read(size - len(MAGIC) - summary_start - 4)
        if crc32(covered) != summary_crc:
            raise ReaderError(f"{path}: the MCAP summary section is corrupt (CRC mismatch); "
                              f"{RECOVER}")
    from mcap.reader import SeekingReader  # here: its import (~16 ms) is not every command's

    f.seek(0)
    summary = SeekingReader(f).get_summary()
    if summary is None or not summary.chunk_indexes:
        raise NotCovered("the file has no chunk index")
    if any(c not in summary.channels for i in summary.chunk_indexes
           for c in i.message_index_offsets):
        raise NotCovered("the summary does not list every channel")
    wanted = {}  # channel id -> (topic, kind)
    for cid, channel in summary.channels.items():
        schema = summary.schemas.get(channel.schema_id)
        kind = cdr.SCHEMAS.get(schema.name) if schema else None
        if kind is None:
            other.add(f"{channel.topic} ({schema.name if schema else 'no schema'})")
        elif channel.message_encoding != "cdr":
            raise NotCovered(f"topic {channel.topic} is not CDR encoded")
        else:
            wanted[cid] = (channel.topic, kind)
    if not wanted:
        return
    if summary.statistics is not None:
        for cid, count in summary.statistics.channel_message_counts.items():
            if cid in wanted:
                pieces.expected[wanted[cid]] = pieces.expected.get(wanted[cid], 0) + count
    indexes = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    if any(not index.message_index_offsets for index in indexes):
        raise NotCovered("a chunk has no message index")
    indexes = [i for i in indexes if any(c in wanted for c in i.message_index_offsets)]
    loader = _Loader(f, path, wanted)
    # one thread reads and decompresses ahead (file reads, zstd and crc32 release the GIL);
    # each batch goes into one of LOOKAHEAD + 1 reused buffers
    buffers = [bytearray() for _ in range(LOOKAHEAD + 1)]
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="imupipe-mcap")
    try:
        pending: deque = deque()
        for i, batch in enumerate(_batches(indexes)):
            if len(pending) == LOOKAHEAD:
                _decode_batch(*pending.popleft().result(), wanted, pieces)
            slot = i % len(buffers)
            needed = sum(index.uncompressed_size for index in batch)
            if len(buffers[slot]) < needed:
                buffers[slot] = bytearray(needed)
            pending.append(pool.submit(loader.load, batch, buffers[slot]))
        while pending:
            _decode_batch(*pending.popleft().result(), wanted, pieces)
    finally:
        pool.shutdown(cancel_futures=True)


def _batches(indexes: list) -> Iterator[list]:
    """Consecutive chunk indexes, about ``BATCH_BYTES`` of uncompressed records per batch."""
    batch, size = [], 0
    for index in indexes:
        if batch and size + index.uncompressed_size > BATCH_BYTES:
            yield batch
            batch, size = [], 0
        batch.append(index)
        size += index.uncompressed_size
    if batch:
        yield batch


class _Loader:
    """Reads chunks and their message indexes, decompresses them into a batch buffer.

    Used from one worker thread at a time; ``raw`` is its reused read buffer.
    """

    def __init__(self, f, path: Path, wanted: dict):
        self.f, self.path, self.wanted = f, path, wanted
        self.dctx = zstandard.ZstdDecompressor()
        self.raw = bytearray()

    def load(self, batch: list, out: bytearray) -> tuple[str, np.ndarray, dict[int, list]]:
        """Decompress ``batch`` into ``out``; return where, the records (uint8), and per
        channel the offsets of its messages into them."""
        dest = memoryview(out)
        offsets: dict[int, list[np.ndarray]] = defaultdict(list)
        pos = 0
        for index in batch:
            start, n = index.chunk_start_offset, index.chunk_length + index.message_index_length
            where = f"{self.path}: MCAP chunk at byte {start}"
            if len(self.raw) < n:
                self.raw = bytearray(n)
            raw = memoryview(self.raw)[:n]
            self.f.seek(start)
            if self.f.readinto(raw) < n:
                raise ReaderError(f"{where} runs past the end of the file (truncated); {RECOVER}")
            size = index.uncompressed_size
            self._records_into(raw, dest[pos:pos + size], where)
            for cid, at in index.message_index_offsets.items():
                if cid in self.wanted:
                    offsets[cid].append(_message_offsets(raw, at - start, cid, where) + pos)
            pos += size
        where = f"{self.path}: MCAP chunks at bytes {batch[0].chunk_start_offset}" + (
            f" to {batch[-1].chunk_start_offset}" if len(batch) > 1 else "")
        return where, np.frombuffer(out, np.uint8, count=pos), offsets

    def _records_into(self, raw: memoryview, dest: memoryview, where: str) -> None:
        """Decompress one chunk record's records into ``dest`` and check their CRC."""
        if raw[0] != OP_CHUNK:
            raise ReaderError(f"{where}: the chunk index points at no chunk (corrupt index); "
                              f"{RECOVER}")
        size, crc, clen = struct.unpack_from("<QII", raw, 25)
        compression = bytes(raw[41:41 + clen]).decode("ascii", "replace")
        (rlen,) = struct.unpack_from("<Q", raw, 41 + clen)
        data = raw[49 + clen:49 + clen + rlen]
        if size != len(dest):
            raise ReaderError(f"{where}: its size disagrees with the chunk index; {RECOVER}")
        try:
            if compression == "zstd":
                got, reader = 0, self.dctx.stream_reader(data)
                while got < size and (k := reader.readinto(dest[got:])):
                    got += k
            elif compression in ("lz4", ""):
                out = lz4.frame.decompress(data) if compression else data
                got = len(out)
                if got == size:
                    dest[:] = out
            else:
                raise ReaderError(f"{where} uses compression {compression!r}, which imupipe "
                                  "cannot read; convert the file with `mcap convert` (zstd or lz4)")
        except (zstandard.ZstdError, RuntimeError) as exc:
            raise ReaderError(f"{where} is corrupt (cannot decompress: {exc}); {RECOVER}") from None
        if got != size or (crc and crc32(dest) != crc):
            raise ReaderError(f"{where} is corrupt (CRC mismatch); {RECOVER}")


def _decode_batch(where: str, buf: np.ndarray, offsets: dict[int, list], wanted: dict,
                  pieces: Pieces) -> None:
    """Decode every wanted message of a batch of records, one numpy pass per topic."""
    by_key: dict[tuple[str, str], list[int]] = defaultdict(list)
    for cid in offsets:
        by_key[wanted[cid]].append(cid)
    for (topic, kind), cids in by_key.items():
        at = np.concatenate([part for cid in cids for part in offsets[cid]])
        if len(cids) > 1 or not (at[1:] > at[:-1]).all():
            at.sort()  # file order
        if len(at):
            pieces.add(topic, kind, *_decode_messages(where, buf, at, kind, cids))


def _decode_messages(where: str, buf: np.ndarray, at: np.ndarray, kind: str, cids: list[int]
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (n,) int64 ns and float blocks (n, span) of the messages at offsets ``at``.

    Usually one row gather per message covers the record head, the CDR header
    and the needed words (every message of a topic has the same frame_id
    length); otherwise three narrower gathers per message.
    """
    strlen_at = int(at[0]) + MESSAGE_HEAD + 12
    strlen = int(buf[strlen_at:strlen_at + 4].view("<u4")[0]) if strlen_at + 4 <= len(buf) else 0
    width = MESSAGE_HEAD + cdr.block_offset(strlen) + 8 * cdr.SPAN[kind][1]
    decoded = None
    if strlen and int(at[-1]) + width <= len(buf):
        rows = cdr.rows(buf, at, width)
        ops, length = rows[:, 0], rows[:, 1:9].view("<u8")[:, 0]
        channel = rows[:, 9:11].view("<u2")[:, 0]
        _check_records(where, ops, channel, cids)
        lengths = length.astype(np.int64) - (MESSAGE_HEAD - 9)
        decoded = cdr.decode_rows(kind, rows, MESSAGE_HEAD, strlen, lengths)
    if decoded is None:
        try:
            ops = buf[at]
            record = cdr.rows(buf, at + 1, 16)  # length u64, channel u16, sequence u32, ...
        except IndexError:
            raise ReaderError(f"{where}: a message index points past its chunk; {RECOVER}"
                              ) from None
        _check_records(where, ops, record.view("<u2")[:, 4], cids)
        lengths = record.view("<u8")[:, 0].astype(np.int64) - (MESSAGE_HEAD - 9)
        try:
            decoded = cdr.decode(kind, buf, at + MESSAGE_HEAD, lengths)
        except IndexError:
            raise ReaderError(f"{where}: a message runs past its chunk; {RECOVER}") from None
    sec, nanosec, block = decoded
    t = sec * 1_000_000_000 + nanosec
    unstamped = t == 0
    if unstamped.any():  # fall back to log_time
        t[unstamped] = cdr.rows(buf, at[unstamped] + 15, 8).view("<u8")[:, 0]
    return t, block


def _check_records(where: str, ops: np.ndarray, channel: np.ndarray, cids: list[int]) -> None:
    """The message index must point at message records of its own channel(s)."""
    ok = channel == cids[0] if len(cids) == 1 else np.isin(channel, cids)
    if not ((ops == OP_MESSAGE) & ok).all():
        raise ReaderError(f"{where}: a message index does not match its messages; {RECOVER}")


def _message_offsets(raw: memoryview, at: int, channel: int, where: str) -> np.ndarray:
    """Offsets (int64) into the uncompressed chunk of one channel's messages (its message index)."""
    if at < 0 or at + 15 > len(raw) or raw[at] != OP_MESSAGE_INDEX:
        raise ReaderError(f"{where}: message index of channel {channel} is missing; {RECOVER}")
    cid, nbytes = struct.unpack_from("<HI", raw, at + 9)
    if cid != channel or at + 15 + nbytes > len(raw) or nbytes % 16:
        raise ReaderError(f"{where}: message index of channel {channel} is corrupt; {RECOVER}")
    return np.frombuffer(raw, "<u8", count=nbytes // 8, offset=at + 15)[1::2].astype(np.int64)


# --------------------------------------------------------------------------- generic path


def _read_generic(f, pieces: Pieces, other: set[str]) -> None:
    """Decode message by message with ``mcap_ros2`` (extra ``ros``), in file order."""
    where = getattr(f, "name", "the MCAP file")
    decoder_module = require("mcap_ros2.decoder", "ros")
    factory = decoder_module.DecoderFactory()
    from mcap.reader import NonSeekingReader

    f.seek(0)
    reader = NonSeekingReader(f, validate_crcs=True)  # one linear pass needs no index
    rows: dict[tuple[str, str], tuple[list, list, list]] = defaultdict(lambda: ([], [], []))
    decoders: dict[int, object] = {}
    for schema, channel, message in reader.iter_messages(log_time_order=False):
        kind = cdr.SCHEMAS.get(schema.name) if schema else None
        if kind is None:
            other.add(f"{channel.topic} ({schema.name if schema else 'no schema'})")
            continue
        decode = decoders.get(channel.id)
        if decode is None:
            decode = decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
            if decode is None:
                raise ReaderError(f"{where}: topic {channel.topic} is not ROS 2 CDR; imupipe "
                                  "reads ROS 2")
        try:
            msg = decode(message.data)
            stamp = (msg.header.stamp.sec, msg.header.stamp.nanosec)
            block = _block_of(kind, msg)
        except Exception as exc:  # noqa: BLE001 - any decoding failure is the file's
            raise ReaderError(
                f"{where}: topic {channel.topic}: a message does not decode as its schema "
                f"{schema.name!r} ({type(exc).__name__}: {exc}); the schema name or its "
                "definition is wrong (a swapped schema?)") from None
        stamps, logs, blocks = rows[channel.topic, kind]
        stamps.append(stamp)
        logs.append(message.log_time)
        blocks.append(block)
    for (topic, kind), (stamps, logs, blocks) in rows.items():
        sec, nanosec = np.array(stamps, np.int64).reshape(-1, 2).T
        t = sec * 1_000_000_000 + nanosec
        t = np.where(t == 0, np.array(logs, np.int64), t)  # unstamped: log_time
        first, last = cdr.SPAN[kind]
        block = np.array(blocks, np.float64).reshape(-1, cdr.WORDS[kind])[:, first:last]
        pieces.add(topic, kind, t, block)


def _block_of(kind: str, msg) -> list[float]:
    """The float block of a decoded message, in ``cdr``'s word order."""
    def xyz(v):
        return [v.x, v.y, v.z]

    if kind == "imu":
        o = msg.orientation
        return [o.x, o.y, o.z, o.w, *msg.orientation_covariance,
                *xyz(msg.angular_velocity), *msg.angular_velocity_covariance,
                *xyz(msg.linear_acceleration), *msg.linear_acceleration_covariance]
    if kind == "mag":
        return [*xyz(msg.magnetic_field), *msg.magnetic_field_covariance]
    return [msg.temperature, msg.variance]


# --------------------------------------------------------------------------- both paths


def split(kind: str, t: np.ndarray, block: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Streams carried by messages of one kind: stream -> (t_ns (n,), values (n, k)).

    ``block``: the ``cdr.SPAN[kind]`` words of each message (n, span) float64.
    """
    first = cdr.SPAN[kind][0]
    if kind == "imu":
        out = {}
        for stream, word, cov in (("accel", cdr.IMU_ACCEL, cdr.IMU_ACCEL_COV),
                                  ("gyro", cdr.IMU_GYRO, cdr.IMU_GYRO_COV)):
            present = block[:, cov - first] != -1.0  # REP-145: covariance[0] = -1 means "no sample"
            if present.all():
                out[stream] = (t, block[:, word - first:word - first + 3])
            else:
                out[stream] = (t[present], block[present, word - first:word - first + 3])
        return out
    if kind == "mag":
        return {"mag": (t, block[:, cdr.MAG_FIELD - first:cdr.MAG_FIELD - first + 3])}
    return {"temperature": (t, block[:, cdr.TEMPERATURE - first:cdr.TEMPERATURE - first + 1])}


def device_names(keys: Iterable[tuple[str, str]]) -> dict[tuple[str, str], str]:
    """(topic, kind) -> device: the topic's namespace
    (``/imu0/imu`` -> ``imu0``; ``/imu`` -> ``imu``).

    Two topics of one kind in the same namespace (``/imu/data``, ``/imu/data_raw``)
    cannot share a device; each then keeps its full topic name as device name.
    """
    keys = list(keys)
    namespace = {k: k[0].rsplit("/", 1)[0].strip("/") or "imu" for k in keys}
    count: dict[tuple[str, str], int] = defaultdict(int)
    for k in keys:
        count[namespace[k], k[1]] += 1
    names = {}
    for k in keys:
        names[k] = namespace[k]
        if count[namespace[k], k[1]] > 1:
            names[k] = k[0].strip("/")
            warnings.warn(f"topic {k[0]}: shares namespace {namespace[k]!r} with another "
                          f"{cdr.KIND_SCHEMA[k[1]]} topic; read as device {names[k]!r}",
                          stacklevel=3)
    return names


def _recording(path: Path, pieces: Pieces, other: set[str]) -> Recording:
    if not pieces:
        found = ", ".join(sorted(other)) or "none"
        raise ReaderError(
            f"{path}: no ROS 2 IMU topic (sensor_msgs/msg/Imu, MagneticField or Temperature); "
            f"topics found: {found}; record the IMU driver's topics")
    names = device_names(pieces)
    devices: dict[str, dict[str, pa.Table]] = defaultdict(dict)
    for key in sorted(pieces, key=lambda k: (names[k], k)):
        for stream, sink in pieces[key].items():
            if sink.n == 0:
                continue  # e.g. an Imu topic whose messages all flag "no accelerometer"
            columns = {"t_ns": arrow_column(sink.t[:sink.n])}
            for j, name in enumerate(COLUMNS[stream]):
                columns[name] = arrow_column(sink.v[j, :sink.n])
            devices[names[key]][stream] = schemas.stamp(pa.table(columns), stream, extra={
                "imupipe.topic": key[0], "imupipe.frame_convention": FRAME_CONVENTION})
    return Recording(source=str(path), devices=dict(devices))
