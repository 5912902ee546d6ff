"""Frames of a bag as pairs of messages: association of depth and colour by header stamp, one streaming
pass that hands out each frame's two raw messages in order, and real-time pacing at the bag's rate."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from h2viz.sources.rosbag.bag_file import BagFile, RawMessage

GIVE_UP_NS = 1_000_000_000  # a frame's message counts as missing once the stream is this far past it


@dataclass(frozen=True)
class FrameKey:
    """Where one frame's depth and colour messages are in the bag (log time + header stamp)."""

    depth_log_ns: int
    depth_stamp_ns: int
    rgb_log_ns: int
    rgb_stamp_ns: int

    def __str__(self) -> str:
        return f"depth@{self.depth_stamp_ns * 1e-9:.6f}s"


RawFrame = tuple[int, FrameKey, RawMessage, RawMessage]  # position, key, depth message, colour message


def associate(depth: np.ndarray, rgb: np.ndarray, max_gap_ns: float) -> tuple[list[FrameKey], np.ndarray]:
    """One key per depth message (N,2) [log_ns, stamp_ns] with the colour message (M,2) nearest in stamp,
    and whether that colour lies within `max_gap_ns` (N,)."""
    rgb = rgb[np.argsort(rgb[:, 1], kind="stable")]
    m = rgb.shape[0]
    right = np.clip(np.searchsorted(rgb[:, 1], depth[:, 1]), 0, m - 1)  # (N,)
    left = np.clip(right - 1, 0, m - 1)
    pick = np.where(np.abs(rgb[left, 1] - depth[:, 1]) <= np.abs(rgb[right, 1] - depth[:, 1]), left, right)
    ok = np.abs(rgb[pick, 1] - depth[:, 1]) <= max_gap_ns
    keys = [
        FrameKey(int(d[0]), int(d[1]), int(c[0]), int(c[1])) for d, c in zip(depth, rgb[pick], strict=True)
    ]
    return keys, ok


def stream_pairs(
    bag: BagFile,
    depth_topic: str,
    rgb_topic: str,
    keys: list[tuple[int, FrameKey]],
    on_missing: Callable[[FrameKey], None],
) -> Iterator[RawFrame]:
    """Each frame's (depth, colour) raw messages in order from a single pass over the bag; only frames
    between the current one and the stream position are held (raw bytes, not decoded)."""
    if not keys:
        return
    want: dict[tuple[str, int, int], list[int]] = {}
    for i, (_, k) in enumerate(keys):
        want.setdefault((depth_topic, k.depth_log_ns, k.depth_stamp_ns), []).append(i)
        want.setdefault((rgb_topic, k.rgb_log_ns, k.rgb_stamp_ns), []).append(i)
    parts: list[dict[str, RawMessage]] = [{} for _ in keys]
    lo = min(min(k.depth_log_ns, k.rgb_log_ns) for _, k in keys)
    hi = max(max(k.depth_log_ns, k.rgb_log_ns) for _, k in keys) + 1
    done = 0
    for raw in bag.messages([depth_topic, rgb_topic], lo, hi):
        for i in want.get((raw.topic, raw.log_ns, bag.stamp(raw)[0]), ()):
            parts[i][raw.topic] = raw
        while done < len(keys):
            position, key = keys[done]
            if len(parts[done]) == 2:
                yield position, key, parts[done][depth_topic], parts[done][rgb_topic]
            elif raw.log_ns > max(key.depth_log_ns, key.rgb_log_ns) + GIVE_UP_NS:
                on_missing(key)
            else:
                break
            parts[done] = {}
            done += 1
    for _, key in keys[done:]:
        on_missing(key)


def paced(
    frames: Iterator[RawFrame],
    clock: Callable[[], float],
    sleep: Callable[[float], None],
    on_drop: Callable[[], None],
) -> Iterator[RawFrame]:
    """Frames released at the bag's rate (wall clock from the first one); when the consumer falls
    behind, the newest frame already due is released and the older due ones are dropped."""
    start: tuple[float, int] | None = None
    current = next(frames, None)
    while current is not None:
        upcoming = next(frames, None)
        now = clock()
        if start is None:
            start = (now, current[1].depth_stamp_ns)
        t0, s0 = start
        if upcoming is not None and t0 + (upcoming[1].depth_stamp_ns - s0) * 1e-9 <= now:
            on_drop()
            current = upcoming
            continue
        due = t0 + (current[1].depth_stamp_ns - s0) * 1e-9
        if due > now:
            sleep(due - now)
        yield current
        current = upcoming
