"""MCAP files of ROS 2 IMU messages -> canonical tables.

Topics are found by schema name (``sensor_msgs/msg/Imu``, ``MagneticField``,
``Temperature``); each topic namespace is one device (``/imu0/imu`` ->
``imu0``; ``/imu`` -> ``imu``). Sample time is ``header.stamp`` (``log_time``
when the stamp is zero). REP-145: an Imu message whose
``linear_acceleration_covariance[0]`` is -1 carries no accelerometer sample,
likewise for the gyroscope.

Fast path: with the summary's chunk indexes and the message indexes, each
chunk is decompressed once and all its IMU messages are decoded together with
numpy (``cdr.decode``). Files the fast path does not cover (unindexed files,
big-endian or non-standard CDR) go through the generic ``mcap_ros2`` decoder
(extra ``ros``), with identical results. Messages are taken in file order.
"""

from __future__ import annotations

import logging
import struct
import warnings
from collections import defaultdict, deque
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import lz4.frame
import numpy as np
import pyarrow as pa
import zstandard
from isal.isal_zlib import crc32  # CRC-32 as zlib's, ~9x faster (SIMD)
from mcap.exceptions import McapError
from mcap.reader import SeekingReader, make_reader

from .. import schemas
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

LOOKAHEAD = 2  # chunks read and decompressed ahead, in a thread, while one is decoded
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
        self.v[:, self.n:end] = values.T
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
    f.seek(0)
    summary = SeekingReader(f).get_summary()
    if summary is None or not summary.chunk_indexes:
        raise NotCovered("the file has no chunk index")
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
    decompressor = zstandard.ZstdDecompressor()
    # one thread reads and decompresses ahead (zstd and crc32 release the GIL)
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="imupipe-mcap")
    try:
        pending: deque = deque()
        for index in indexes:
            pending.append(pool.submit(_load_chunk, f, path, index, decompressor))
            if len(pending) > LOOKAHEAD:
                _decode_chunk(path, *pending.popleft().result(), wanted, pieces)
        while pending:
            _decode_chunk(path, *pending.popleft().result(), wanted, pieces)
    finally:
        pool.shutdown(cancel_futures=True)


def _load_chunk(f, path: Path, index, decompressor) -> tuple[object, bytes, np.ndarray]:
    """Read one chunk with its message indexes; decompress and check its CRC."""
    start = index.chunk_start_offset
    where = f"{path}: MCAP chunk at byte {start}"
    f.seek(start)
    raw = f.read(index.chunk_length + index.message_index_length)
    if len(raw) < index.chunk_length + index.message_index_length:
        raise ReaderError(f"{where} runs past the end of the file (truncated); {RECOVER}")
    if raw[0] != OP_CHUNK:
        raise ReaderError(f"{where}: the chunk index points at no chunk (corrupt index); {RECOVER}")
    usize, crc, clen = struct.unpack_from("<QII", raw, 25)
    compression = raw[41:41 + clen].decode("ascii", "replace")
    (rlen,) = struct.unpack_from("<Q", raw, 41 + clen)
    data = raw[49 + clen:49 + clen + rlen]
    try:
        if compression == "zstd":
            out = decompressor.decompress(data, max_output_size=usize)
        elif compression == "lz4":
            out = lz4.frame.decompress(data)
        elif compression == "":
            out = data
        else:
            raise ReaderError(f"{where} uses compression {compression!r}, which imupipe cannot "
                              "read; convert the file with `mcap convert` (zstd or lz4)")
    except (zstandard.ZstdError, RuntimeError) as exc:
        raise ReaderError(f"{where} is corrupt (cannot decompress: {exc}); {RECOVER}") from None
    if len(out) != usize or (crc and crc32(out) != crc):
        raise ReaderError(f"{where} is corrupt (CRC mismatch); {RECOVER}")
    return index, raw, np.frombuffer(out, np.uint8)


def _decode_chunk(path: Path, index, raw: bytes, buf: np.ndarray, wanted: dict,
                  pieces: Pieces) -> None:
    """Decode every wanted message of one decompressed chunk, one numpy pass per topic."""
    start = index.chunk_start_offset
    where = f"{path}: MCAP chunk at byte {start}"
    by_key: dict[tuple[str, str], list[int]] = defaultdict(list)
    for cid in index.message_index_offsets:
        if cid in wanted:
            by_key[wanted[cid]].append(cid)
    for (topic, kind), cids in by_key.items():
        offsets = np.concatenate(
            [_message_offsets(raw, index.message_index_offsets[c] - start, c, where) for c in cids]
        ).astype(np.int64)
        if len(cids) > 1 or not (offsets[1:] > offsets[:-1]).all():
            offsets.sort()  # file order
        try:
            ops = buf[offsets]
            record = cdr.rows(buf, offsets + 1, 16)  # length u64, channel u16, sequence u32, ...
        except IndexError:
            raise ReaderError(f"{where}: its message index points past the chunk; {RECOVER}"
                              ) from None
        channel = record.view("<u2")[:, 4]
        ok = channel == cids[0] if len(cids) == 1 else np.isin(channel, cids)
        if not ((ops == OP_MESSAGE) & ok).all():
            raise ReaderError(f"{where}: its message index does not match its messages; {RECOVER}")
        starts = offsets + MESSAGE_HEAD
        lengths = record.view("<u8")[:, 0].astype(np.int64) - (MESSAGE_HEAD - 9)
        try:
            sec, nanosec, block = cdr.decode(kind, buf, starts, lengths)
        except IndexError:
            raise ReaderError(f"{where}: a message runs past the chunk; {RECOVER}") from None
        t = sec * 1_000_000_000 + nanosec
        unstamped = t == 0
        if unstamped.any():  # fall back to log_time
            t[unstamped] = cdr.rows(buf, offsets[unstamped] + 15, 8).view("<u8")[:, 0]
        pieces.add(topic, kind, t, block)


def _message_offsets(raw: bytes, at: int, channel: int, where: str) -> np.ndarray:
    """Offsets into the uncompressed chunk of one channel's messages (its message index)."""
    if at < 0 or at + 15 > len(raw) or raw[at] != OP_MESSAGE_INDEX:
        raise ReaderError(f"{where}: message index of channel {channel} is missing; {RECOVER}")
    cid, nbytes = struct.unpack_from("<HI", raw, at + 9)
    if cid != channel or at + 15 + nbytes > len(raw) or nbytes % 16:
        raise ReaderError(f"{where}: message index of channel {channel} is corrupt; {RECOVER}")
    return np.frombuffer(raw, "<u8", count=nbytes // 8, offset=at + 15)[1::2]


# --------------------------------------------------------------------------- generic path


def _read_generic(f, pieces: Pieces, other: set[str]) -> None:
    """Decode message by message with ``mcap_ros2`` (extra ``ros``), in file order."""
    decoder_module = require("mcap_ros2.decoder", "ros")
    factory = decoder_module.DecoderFactory()
    f.seek(0)
    reader = make_reader(f, validate_crcs=True)
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
                raise ValueError(f"topic {channel.topic} is not ROS 2 CDR; imupipe reads ROS 2")
        msg = decode(message.data)
        stamps, logs, blocks = rows[channel.topic, kind]
        stamps.append((msg.header.stamp.sec, msg.header.stamp.nanosec))
        logs.append(message.log_time)
        blocks.append(_block_of(kind, msg))
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
            columns = {"t_ns": sink.t[:sink.n]}
            for j, name in enumerate(COLUMNS[stream]):
                columns[name] = sink.v[j, :sink.n]
            devices[names[key]][stream] = schemas.stamp(pa.table(columns), stream,
                                                        extra={"imupipe.topic": key[0]})
    return Recording(source=str(path), devices=dict(devices))
