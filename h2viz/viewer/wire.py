"""Decoding of the websocket frames viser sends to a browser (zstd-compressed msgpack metadata
followed by raw binary buffers), to inspect and measure what a real browser connection received."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgspec.msgpack
import zstandard


@dataclass(frozen=True)
class WireMessage:
    type: str  # viser message class name, e.g. GlbMessage, RemoveSceneNodeMessage
    name: str | None  # scene node name when the message has one
    fields: dict[str, Any]  # decoded fields; binary buffers stay as placeholders
    nbytes: int  # payload bytes it carried (inline bytes plus extracted buffers)


def _payload_bytes(value: Any, lengths: list[int]) -> int:
    if isinstance(value, bytes | bytearray | memoryview):
        return len(value)
    if isinstance(value, dict):
        if "__binary_index" in value and "dtype" in value:
            return int(lengths[value["__binary_index"]])
        return sum(_payload_bytes(v, lengths) for v in value.values())
    if isinstance(value, list | tuple):
        return sum(_payload_bytes(v, lengths) for v in value)
    return 0


def decode_frame(payload: bytes) -> list[WireMessage]:
    """Messages of one server -> browser websocket frame (an empty list for text frames)."""
    if not isinstance(payload, bytes | bytearray) or len(payload) < 16:
        return []
    raw_size = int.from_bytes(payload[0:8], "little")
    packed_size = int.from_bytes(payload[8:16], "little")
    meta = zstandard.ZstdDecompressor().decompress(
        bytes(payload[16 : 16 + packed_size]), max_output_size=raw_size
    )
    outer = msgspec.msgpack.decode(meta)
    lengths = list(outer.get("binaryBufferLengths", ()))
    out = []
    for m in outer.get("messages", ()):
        name = m.get("name") if isinstance(m.get("name"), str) else None
        out.append(WireMessage(str(m.get("type")), name, m, _payload_bytes(m, lengths)))
    return out
