"""ROS 1 ``.bag`` and ROS 2 bags (``metadata.yaml`` + ``.db3`` / ``.mcap``) via ``rosbags``.

``rosbags`` (pure Python, no ROS install; extra ``ros``) opens the bag and
deserialises ``sensor_msgs/Imu``, ``MagneticField`` and ``Temperature`` message
by message. Everything after that is the MCAP reader's own code
(``mcap.split``, ``mcap._recording``): the same devices (one per topic
namespace), sample times (``header.stamp``, the bag's receive time when the stamp
is zero), REP-145 "no sample" flags and frame convention (FLU), so the same
messages give identical tables from a ``.bag``, a ``.db3`` and an ``.mcap``.

A ROS 2 bag is a folder: give its ``metadata.yaml`` (or the ``.db3`` inside it;
``rosbags`` needs the ``metadata.yaml`` beside it).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from ..components import Recording
from ..errors import ReaderError, require
from . import cdr
from .mcap import Pieces, _block_of, _recording

ROS1_MAGIC = b"#ROSBAG V2.0\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
ROS2_METADATA = "rosbag2_bagfile_information"
# rosbags names ROS 1 and ROS 2 types alike: sensor_msgs/msg/Imu
KINDS = cdr.SCHEMAS


def _bag_paths(path: Path) -> Path:
    """What ``rosbags`` opens: the ``.bag`` file, or the ROS 2 bag folder."""
    if path.suffix.lower() == ".bag":
        return path
    folder = path.parent
    if not (folder / "metadata.yaml").is_file():
        raise ReaderError(f"{path}: a ROS 2 storage file without the bag's metadata.yaml beside "
                          "it; keep the bag folder whole, or rebuild it with `ros2 bag reindex`")
    return folder


class RosbagReader:
    """ROS 1 ``.bag`` files and ROS 2 bag folders, through ``rosbags``."""

    name = "rosbag"
    suffixes = (".bag", ".db3", ".yaml")

    def sniff(self, path: Path, head: bytes) -> bool:
        path = Path(path)
        if head.startswith(ROS1_MAGIC) or (path.suffix.lower() == ".db3"
                                           and head.startswith(SQLITE_MAGIC)):
            return True
        return path.name == "metadata.yaml" and ROS2_METADATA.encode() in head

    def inputs(self, path: Path) -> list[Path]:
        """A ROS 2 bag's storage files (their bytes enter the cache key)."""
        path = Path(path)
        if path.suffix.lower() == ".bag":
            return []
        return sorted(p for p in path.parent.iterdir() if p.suffix in (".db3", ".mcap")
                      and p != path)

    def read(self, path: Path) -> Recording:
        return read_bag(path)


def read_bag(path: Path | str) -> Recording:
    highlevel = require("rosbags.highlevel", "ros")
    typesys = require("rosbags.typesys", "ros")
    path = Path(path)
    rows: dict[tuple[str, str], tuple[list, list]] = defaultdict(lambda: ([], []))
    other: set[str] = set()
    try:
        store = typesys.get_typestore(typesys.Stores.LATEST)
        with highlevel.AnyReader([_bag_paths(path)], default_typestore=store) as reader:
            wanted = []
            for c in reader.connections:
                if c.msgtype in KINDS:
                    wanted.append(c)
                else:
                    other.add(f"{c.topic} ({c.msgtype})")
            for conn, log_time, data in reader.messages(connections=wanted) if wanted else ():
                msg = reader.deserialize(data, conn.msgtype)
                kind = KINDS[conn.msgtype]
                stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                times, blocks = rows[conn.topic, kind]
                times.append(stamp or log_time)  # unstamped: the bag's receive time
                blocks.append(_block_of(kind, msg))
    except ReaderError:
        raise
    except Exception as exc:  # noqa: BLE001 -- rosbags raises many types on a damaged bag
        raise ReaderError(f"{path}: not a readable ROS bag ({type(exc).__name__}: {exc}); "
                          "re-record it, or for ROS 1 try `rosbag reindex`") from None
    pieces = Pieces()
    for (topic, kind), (times, blocks) in rows.items():
        first, last = cdr.SPAN[kind]
        block = np.array(blocks, np.float64).reshape(-1, cdr.WORDS[kind])[:, first:last]
        pieces.add(topic, kind, np.array(times, np.int64), block)
    return _recording(path, pieces, other)


COMPONENTS = [RosbagReader()]
