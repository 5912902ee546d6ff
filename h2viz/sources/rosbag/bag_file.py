"""One opened bag (ROS 1 .bag, ROS 2 folder, .mcap or .db3 file) behind a small lazy interface: topics,
raw messages in log-time order, deserialisation and header stamps read without decoding the payload.
Bags that rosbags cannot open (cut, unindexed) are read through the tolerant scanners instead."""

from __future__ import annotations

import logging
import struct
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from h2viz.errors import SourceError
from h2viz.sources.rosbag.recover import McapScanner, Ros1Scanner, ScanIndex, SqliteScanner

log = logging.getLogger("h2viz.sources.rosbag")

BAG_SUFFIXES = (".bag", ".mcap", ".db3")


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class RawMessage:
    topic: str
    msgtype: str
    log_ns: int  # time the recorder logged the message
    data: bytes | memoryview


class _Scanner(Protocol):
    def read_block(self, block: int) -> Iterator[tuple[int, int, bytes]]: ...


def recovery_typestore(typedefs: dict[str, object], ros2: bool) -> Typestore:
    """Default types of the ROS generation, overridden by the definitions found in the file."""
    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    try:
        store.register(typedefs)  # type: ignore[arg-type]
    except Exception:  # a definition differs from the default one: use the file's alone
        store = get_typestore(Stores.EMPTY)
        store.register(typedefs)  # type: ignore[arg-type]
    return store


def select_blocks(entries: np.ndarray, conn_ids: Collection[int], start: int, stop: int) -> list[int]:
    """Blocks holding a wanted message, in file order; `entries` is (M,3) int64 (log_ns, conn_id, block)."""
    t, c, b = entries[:, 0], entries[:, 1], entries[:, 2]
    mask = np.isin(c, np.fromiter(conn_ids, dtype=np.int64)) & (t >= start) & (t < stop)
    return [int(x) for x in np.unique(b[mask])]


def looks_like_bag(path: Path) -> bool:
    """A ROS 1 .bag file, a .mcap / .db3 storage file or a ROS 2 bag folder with metadata.yaml."""
    if path.is_file():
        return path.suffix in BAG_SUFFIXES
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _storage_files(path: Path) -> list[Path]:
    """The storage files of a ROS 2 bag folder (from metadata.yaml, else every .db3 / .mcap in it)."""
    if path.is_file():
        return [path]
    try:
        meta = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        files = [path / Path(p).name for p in meta["relative_file_paths"]]
    except (OSError, KeyError, TypeError, yaml.YAMLError):
        files = []
    files = [f for f in files if f.is_file()]
    return files or sorted([*path.glob("*.db3"), *path.glob("*.mcap")])


def header_stamp(data: bytes | memoryview, ros2: bool) -> tuple[int, str]:
    """(header.stamp in ns, header.frame_id) read from the first bytes of a serialised stamped message."""
    raw = bytes(data[:512])
    try:
        if ros2:  # CDR: 4-byte encapsulation, int32 sec, uint32 nanosec, string (uint32 length incl. NUL)
            endian = "<" if raw[1] == 1 else ">"
            sec, nsec, n = struct.unpack_from(endian + "iII", raw, 4)
            frame = raw[16 : 16 + max(0, n - 1)]
        else:  # ROS 1: uint32 seq, uint32 sec, uint32 nsec, string (uint32 length)
            _seq, sec, nsec, n = struct.unpack_from("<IIII", raw, 0)
            frame = raw[16 : 16 + n]
    except (struct.error, IndexError):
        return 0, ""
    return sec * 1_000_000_000 + nsec, frame.decode(errors="replace").lstrip("/")


class BagFile:
    """An opened bag. `damage` is empty for a healthy file, else says where reading stopped."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.ros2 = not (path.is_file() and path.suffix == ".bag")
        self.damage = ""
        self._reader: AnyReader | None = None
        self._scanners: list[tuple[_Scanner, ScanIndex, np.ndarray]] = []  # entries (M,3) int64
        default = get_typestore(Stores.ROS2_HUMBLE if self.ros2 else Stores.ROS1_NOETIC)
        try:
            reader = AnyReader([path], default_typestore=default)
            reader.open()
            self._reader = reader
            self.typestore: Typestore = reader.typestore
        except Exception as e:  # rosbags refuses the file: read what a sequential scan can
            self._recover(str(e) or type(e).__name__)
        self.topics = self._list_topics()

    # -- opening ------------------------------------------------------------------------------------
    def _recover(self, reason: str) -> None:
        files = _storage_files(self.path)
        typedefs: dict[str, object] = {}
        for f in files:
            try:
                scanner = {".bag": Ros1Scanner, ".mcap": McapScanner, ".db3": SqliteScanner}[f.suffix](f)
                index = scanner.scan()
            except Exception as e:  # Damaged, OSError, sqlite3 and type-parsing errors alike
                raise SourceError(
                    f"{f}: cannot be read as a ROS bag ({reason}; {e}). Check that the file is a complete "
                    "ROS 1 .bag, ROS 2 .db3 / .mcap or a ROS 2 bag folder, and pass it to --data"
                ) from e
            entries = np.array(index.entries, dtype=np.int64).reshape(-1, 3)  # (M,3) log_ns, conn, block
            self._scanners.append((scanner, index, entries))
            typedefs.update(index.typedefs)
            if index.damage:
                self.damage = f"{f.name}: {index.damage}"
        if not files:
            raise SourceError(
                f"{self.path}: no bag storage files found ({reason}); pass a .bag, .db3, .mcap or bag folder"
            )
        self.typestore = recovery_typestore(typedefs, self.ros2)
        log.warning(
            "%s could not be opened normally (%s); reading it sequentially%s",
            self.path,
            reason,
            f": {self.damage}, messages after that are lost" if self.damage else "",
        )

    def _list_topics(self) -> dict[str, TopicInfo]:
        counts: dict[str, TopicInfo] = {}
        if self._reader is not None:
            for name, info in self._reader.topics.items():
                counts[name] = TopicInfo(name, info.msgtype or "", info.msgcount)
            return counts
        for _, index, entries in self._scanners:
            for cid, conn in index.connections.items():
                old = counts.get(conn.topic)
                n = int(np.count_nonzero(entries[:, 1] == cid)) + (old.count if old else 0)
                counts[conn.topic] = TopicInfo(conn.topic, conn.msgtype, n)
        return counts

    # -- reading ------------------------------------------------------------------------------------
    @property
    def time_range_ns(self) -> tuple[int, int]:
        """(first, last) log time of the readable messages."""
        if self._reader is not None:
            return self._reader.start_time, max(self._reader.start_time, self._reader.end_time - 1)
        times = np.concatenate([e[:, 0] for _, _, e in self._scanners] + [np.zeros(0, np.int64)])
        return (int(times.min()), int(times.max())) if times.size else (0, 0)

    def messages(
        self, topics: Collection[str], start_ns: int | None = None, stop_ns: int | None = None
    ) -> Iterator[RawMessage]:
        """Raw messages of `topics` with start_ns <= log time < stop_ns; stops (and records why) at damage."""
        try:
            if self._reader is not None:
                conns = [c for c in self._reader.connections if c.topic in topics]
                if conns:
                    for conn, log_ns, data in self._reader.messages(conns, start=start_ns, stop=stop_ns):
                        yield RawMessage(conn.topic, conn.msgtype, log_ns, data)
                return
            yield from self._scanned(topics, start_ns or 0, stop_ns if stop_ns is not None else 2**63 - 1)
        except Exception as e:  # a damaged chunk or row in a file that opened: keep what was read
            self.damage = self.damage or f"reading stopped ({type(e).__name__}: {e})"
            log.warning("%s: %s; the messages after it are skipped", self.path, self.damage)

    def _scanned(self, topics: Collection[str], start: int, stop: int) -> Iterator[RawMessage]:
        for scanner, index, entries in self._scanners:
            conns = {c.id: c for c in index.connections.values() if c.topic in topics}
            for block in select_blocks(entries, conns, start, stop):
                for cid, log_ns, data in scanner.read_block(block):
                    if cid in conns and start <= log_ns < stop:
                        yield RawMessage(conns[cid].topic, conns[cid].msgtype, log_ns, data)

    def first(self, topic: str) -> Any | None:
        """The first message of `topic` deserialised, or None when it has none."""
        for raw in self.messages([topic]):
            return self.decode(raw)
        return None

    def decode(self, raw: RawMessage) -> Any:
        """Deserialise one raw message (ValueError-like rosbags errors propagate to the caller)."""
        if self.ros2:
            return self.typestore.deserialize_cdr(raw.data, raw.msgtype)
        return self.typestore.deserialize_ros1(raw.data, raw.msgtype)

    def stamp(self, raw: RawMessage) -> tuple[int, str]:
        """(header stamp ns, frame_id) without deserialising; the log time when the stamp is zero."""
        stamp_ns, frame = header_stamp(raw.data, self.ros2)
        return (stamp_ns or raw.log_ns), frame

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None
