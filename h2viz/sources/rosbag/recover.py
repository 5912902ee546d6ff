"""Reading what survives of a truncated or unindexed bag: sequential scans of ROS 1 bags and MCAP files,
and a tolerant read of SQLite storage. Each scanner indexes messages as (log time, connection, block)
where a block is a chunk (ROS 1, MCAP) or a row (SQLite), so reading stays lazy afterwards."""

from __future__ import annotations

import bz2
import logging
import sqlite3
import struct
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import BinaryIO

import lz4.frame
from rosbags.typesys import get_types_from_idl, get_types_from_msg
from rosbags.typesys.msg import normalize_msgtype

if sys.version_info >= (3, 14):
    from compression import zstd
else:  # the backport that rosbags itself depends on
    from backports import zstd

log = logging.getLogger("h2viz.sources.rosbag")

ROS1_MAGIC = b"#ROSBAG V2.0\n"
MCAP_MAGIC = b"\x89MCAP0\r\n"


class Damaged(Exception):
    """The file ends or breaks inside a record; carries the byte offset where reading stopped."""

    def __init__(self, offset: int, what: str) -> None:
        super().__init__(f"{what} at byte {offset}")
        self.offset = offset


@dataclass(frozen=True)
class ScanConnection:
    id: int
    topic: str
    msgtype: str


@dataclass
class ScanIndex:
    """What a scan found: connections, (log_ns, conn_id, block) per readable message, the damage."""

    connections: dict[int, ScanConnection] = field(default_factory=dict)
    entries: list[tuple[int, int, int]] = field(default_factory=list)
    typedefs: dict[str, object] = field(default_factory=dict)
    damage: str = ""


def _exact(bio: BinaryIO, n: int, what: str) -> bytes:
    pos = bio.tell()
    data = bio.read(n)
    if len(data) != n:
        raise Damaged(pos, f"file ends inside {what}")
    return data


# ------------------------------------------------------------------------------------------ ROS 1


def _ros1_fields(raw: bytes) -> dict[str, bytes]:
    fields: dict[str, bytes] = {}
    pos = 0
    while pos + 4 <= len(raw):
        (n,) = struct.unpack_from("<I", raw, pos)
        key, _, value = raw[pos + 4 : pos + 4 + n].partition(b"=")
        fields[key.decode(errors="replace")] = value
        pos += 4 + n
    return fields


def _ros1_records(buf: bytes) -> Iterator[tuple[dict[str, bytes], bytes]]:
    """Complete (header fields, data) records of a chunk's payload; stops at a partial record."""
    pos = 0
    while pos + 4 <= len(buf):
        (hlen,) = struct.unpack_from("<I", buf, pos)
        if pos + 8 + hlen > len(buf):
            return
        header = _ros1_fields(buf[pos + 4 : pos + 4 + hlen])
        (dlen,) = struct.unpack_from("<I", buf, pos + 4 + hlen)
        start = pos + 8 + hlen
        if start + dlen > len(buf):
            return
        yield header, buf[start : start + dlen]
        pos = start + dlen


def _ros1_time(raw: bytes) -> int:
    sec, nsec = struct.unpack("<II", raw[:8])
    return sec * 1_000_000_000 + nsec


class Ros1Scanner:
    """Sequential reader of ROS 1 (v2.0) bag records, tolerant of a missing index or a cut file."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def _record(self, bio: BinaryIO) -> tuple[dict[str, bytes], bytes, bool]:
        header = _ros1_fields(
            _exact(bio, struct.unpack("<I", _exact(bio, 4, "a record"))[0], "a record header")
        )
        (dlen,) = struct.unpack("<I", _exact(bio, 4, "a record"))
        data = bio.read(dlen)
        return header, data, len(data) == dlen

    def _payload(self, header: dict[str, bytes], data: bytes, complete: bool, pos: int) -> bytes:
        if header.get("op") != b"\x05":
            return data
        compression = header.get("compression", b"none").decode()
        if compression == "none":
            return data  # a partial chunk still holds its complete leading records
        if not complete:
            raise Damaged(pos, f"file ends inside a {compression} chunk")
        if compression == "bz2":
            return bz2.decompress(data)
        if compression == "lz4":
            return lz4.frame.decompress(data)
        raise Damaged(pos, f"unknown chunk compression '{compression}'")

    def _add(self, index: ScanIndex, header: dict[str, bytes], data: bytes, block: int) -> None:
        op = header.get("op")
        if op == b"\x07":
            conn = struct.unpack("<I", header["conn"])[0]
            fields = _ros1_fields(data)
            msgtype = normalize_msgtype(fields["type"].decode())
            index.connections[conn] = ScanConnection(conn, header["topic"].decode(), msgtype)
            index.typedefs.update(get_types_from_msg(fields.get("message_definition", b"").decode(), msgtype))
        elif op == b"\x02":
            index.entries.append((_ros1_time(header["time"]), struct.unpack("<I", header["conn"])[0], block))

    def scan(self) -> ScanIndex:
        index = ScanIndex()
        size = self.path.stat().st_size
        with self.path.open("rb") as bio:
            if bio.read(len(ROS1_MAGIC)) != ROS1_MAGIC:
                raise Damaged(0, "not a ROS 1 (v2.0) bag: wrong magic")
            while bio.tell() < size:
                pos = bio.tell()
                try:
                    header, data, complete = self._record(bio)
                    records = _ros1_records(self._payload(header, data, complete, pos))
                    for inner_header, inner_data in (
                        records if header.get("op") == b"\x05" else [(header, data)]
                    ):
                        self._add(index, inner_header, inner_data, pos)
                    if not complete:
                        raise Damaged(pos, "file ends inside a record")
                except (Damaged, struct.error, KeyError, OSError, ValueError) as e:
                    index.damage = (
                        f"{e} of {size}" if isinstance(e, Damaged) else f"unreadable record at byte {pos}"
                    )
                    break
        return index

    def read_block(self, block: int) -> Iterator[tuple[int, int, bytes]]:
        """(conn_id, log_ns, data) of every complete message in the chunk or record at `block`."""
        with self.path.open("rb") as bio:
            bio.seek(block)
            header, data, complete = self._record(bio)
            records = _ros1_records(self._payload(header, data, complete, block))
            for h, d in records if header.get("op") == b"\x05" else [(header, data)]:
                if h.get("op") == b"\x02":
                    yield struct.unpack("<I", h["conn"])[0], _ros1_time(h["time"]), d


# ------------------------------------------------------------------------------------------- MCAP


def _string(buf: BytesIO) -> str:
    (n,) = struct.unpack("<I", buf.read(4))
    return buf.read(n).decode()


class McapScanner:
    """Sequential reader of MCAP records (ros2 profile, cdr), tolerant of a missing summary or a cut file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.schema_names: dict[int, str] = {}

    def _records(self, bio: BinaryIO, end: int) -> Iterator[tuple[int, int, bytes, bool]]:
        """(offset, opcode, content, complete) of each record until `end`; the last may be partial."""
        while bio.tell() < end:
            pos = bio.tell()
            head = bio.read(9)
            if len(head) < 9:
                raise Damaged(pos, "file ends inside a record header")
            op, n = struct.unpack("<BQ", head)
            content = bio.read(n)
            yield pos, op, content, len(content) == n

    def _chunk_records(self, content: bytes, complete: bool, pos: int) -> Iterator[tuple[int, bytes]]:
        buf = BytesIO(content)
        _start, _end, _usize, _crc = struct.unpack("<QQQI", _exact(buf, 28, "a chunk"))
        compression = _string(buf)
        (n,) = struct.unpack("<Q", _exact(buf, 8, "a chunk"))
        payload = buf.read(n)
        if compression == "":
            pass  # a partial uncompressed chunk still holds its complete leading records
        elif not complete or len(payload) != n:
            raise Damaged(pos, f"file ends inside a {compression} chunk")
        elif compression == "zstd":
            payload = zstd.decompress(payload)
        elif compression == "lz4":
            payload = lz4.frame.decompress(payload)
        else:
            raise Damaged(pos, f"unknown chunk compression '{compression}'")
        inner = BytesIO(payload)
        for _, op, data, whole in self._records(inner, len(payload)):
            if whole:
                yield op, data

    def _add(self, index: ScanIndex, op: int, data: bytes, block: int) -> None:
        buf = BytesIO(data)
        if op == 0x03:  # schema
            sid = struct.unpack("<H", buf.read(2))[0]
            name, encoding = _string(buf), _string(buf)
            (n,) = struct.unpack("<I", buf.read(4))
            text = buf.read(n).decode()
            self.schema_names[sid] = name
            if text:
                index.typedefs.update(
                    get_types_from_idl(text) if encoding == "ros2idl" else get_types_from_msg(text, name)
                )
        elif op == 0x04:  # channel
            cid, sid = struct.unpack("<HH", buf.read(4))
            index.connections[cid] = ScanConnection(cid, _string(buf), self.schema_names.get(sid, ""))
        elif op == 0x05:  # message
            cid, _seq, log_ns = struct.unpack("<HIQ", buf.read(14))
            index.entries.append((log_ns, cid, block))

    def scan(self) -> ScanIndex:
        index = ScanIndex()
        size = self.path.stat().st_size
        with self.path.open("rb") as bio:
            if bio.read(8) != MCAP_MAGIC:
                raise Damaged(0, "not an MCAP file: wrong magic")
            try:
                for pos, op, content, complete in self._records(bio, size):
                    if op in (0x02, 0x0F):  # footer, data end: the summary that follows is not needed
                        break
                    pairs = self._chunk_records(content, complete, pos) if op == 0x06 else [(op, content)]
                    for inner_op, data in pairs if op == 0x06 or complete else []:
                        self._add(index, inner_op, data, pos)
                    if not complete:
                        raise Damaged(pos, "file ends inside a record")
            except (Damaged, struct.error, OSError, ValueError, zstd.ZstdError) as e:
                index.damage = f"{e} of {size}" if isinstance(e, Damaged) else f"unreadable record ({e})"
        return index

    def read_block(self, block: int) -> Iterator[tuple[int, int, bytes]]:
        with self.path.open("rb") as bio:
            bio.seek(block)
            for pos, op, content, complete in self._records(bio, block + 1):
                pairs = self._chunk_records(content, complete, pos) if op == 0x06 else [(op, content)]
                for inner_op, data in pairs:
                    if inner_op == 0x05:
                        cid, _seq, log_ns, _pub = struct.unpack_from("<HIQQ", data)
                        yield cid, log_ns, data[22:]


# ----------------------------------------------------------------------------------------- SQLite


class SqliteScanner:
    """Rows of a rosbag2 SQLite file read in storage order; a cut file yields the rows before the damage."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.db = sqlite3.connect(f"file:{path}?immutable=1", uri=True, check_same_thread=False)
        self.db.execute("PRAGMA writable_schema=ON")  # accept a page count larger than the file

    def scan(self) -> ScanIndex:
        index = ScanIndex()
        try:
            for tid, name, msgtype in self.db.execute("SELECT id, name, type FROM topics"):
                index.connections[int(tid)] = ScanConnection(int(tid), str(name), str(msgtype))
            tables = {r[0] for r in self.db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
            if "message_definitions" in tables:
                for msgtype, encoding, text in self.db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions"
                ):
                    if text and encoding == "ros2msg":
                        index.typedefs.update(get_types_from_msg(text, msgtype))
                    elif text and encoding == "ros2idl":
                        index.typedefs.update(get_types_from_idl(text))
        except sqlite3.DatabaseError as e:
            raise Damaged(0, f"topics table unreadable ({e})") from e
        try:
            for rowid, tid, log_ns in self.db.execute("SELECT id, topic_id, timestamp FROM messages"):
                index.entries.append((int(log_ns), int(tid), int(rowid)))
        except sqlite3.DatabaseError as e:
            index.damage = f"database damaged after {len(index.entries)} messages ({e})"
        return index

    def read_block(self, block: int) -> Iterator[tuple[int, int, bytes]]:
        for tid, log_ns, data in self.db.execute(
            "SELECT topic_id, timestamp, data FROM messages WHERE id=?", (block,)
        ):
            yield int(tid), int(log_ns), bytes(data)
