"""RGB-D frames from ROS 1 .bag, ROS 2 sqlite3 / mcap bags with the `rosbags` library (no ROS install).

Opening reads only small things: the first message of each image topic (discovery), one CameraInfo,
the pose topic or /tf, and the header stamps of the colour and depth messages (without decoding
them). Frames are then decoded while streaming through the bag once, or one by one via `load`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Hashable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from h2viz.config import SourceConfig
from h2viz.errors import FrameError, SourceError
from h2viz.sources.base import FrameSource, SkippedFrame
from h2viz.sources.rosbag.bag_file import BagFile, RawMessage, looks_like_bag
from h2viz.sources.rosbag.decode import (
    camera_info_K,
    decode_color,
    decode_depth,
    fit_K,
    image_size,
    match_color_size,
)
from h2viz.sources.rosbag.frames import FrameKey, associate, paced, stream_pairs
from h2viz.sources.rosbag.topics import bag_info, discover, require
from h2viz.sources.rosbag.trajectory import camera_trajectory
from h2viz.types import RgbdFrame

__all__ = ["FrameKey", "RosbagSource", "bag_info"]

log = logging.getLogger("h2viz.sources.rosbag")


class RosbagSource(FrameSource):
    """Colour + depth + CameraInfo + poses (pose topic or tf tree) associated by timestamp."""

    format_name = "rosbag"
    clock: Callable[[], float] = staticmethod(time.monotonic)  # real-time mode's wall clock
    sleep: Callable[[float], None] = staticmethod(time.sleep)

    @staticmethod
    def looks_like(path: Path) -> bool:
        return looks_like_bag(Path(path))

    def __init__(self, cfg: SourceConfig) -> None:
        super().__init__(cfg)
        self.rcfg = cfg.rosbag
        self.dropped = 0  # frames passed over in real-time mode because a newer one was due
        self.bag = BagFile(Path(cfg.path))
        if self.bag.damage:
            self.skip(str(self.bag.path), f"{self.bag.damage}; the frames after the damage are lost")
        self.topics = discover(self.bag, self.rcfg)
        require(self.topics, self.bag)
        first_depth = self.bag.first(self.topics.depth)
        self._check_decodable(first_depth)
        self.depth_size = image_size(first_depth)  # (w, h)
        self.camera_frame = self.rcfg.camera_frame.lstrip("/") or str(first_depth.header.frame_id).lstrip("/")
        self.K = self._intrinsics()
        self._keys, self._T = self._plan()

    # -- opening -----------------------------------------------------------------------------------
    def _check_decodable(self, first_depth: Any) -> None:
        """The first depth and colour messages must decode: wrong topics / encodings fail here, once."""
        try:
            decode_depth(first_depth, self.topics.depth, self.rcfg.depth_scale)
            decode_color(self.bag.first(self.topics.rgb), self.topics.rgb)
        except FrameError as e:
            raise SourceError(f"{self.bag.path}: {e}") from e

    def _intrinsics(self) -> np.ndarray:
        """K (3,3) of the depth images: source.intrinsics when set, else the CameraInfo."""
        ic, (w, h) = self.cfg.intrinsics, self.depth_size
        if ic.is_set():
            cx, cy = (ic.cx, ic.cy) if (ic.cx or ic.cy) else ((w - 1) / 2, (h - 1) / 2)
            return np.array([[ic.fx, 0.0, cx], [0.0, ic.fy, cy], [0.0, 0.0, 1.0]])
        if not self.topics.camera_info:
            raise SourceError(
                f"{self.bag.path}: no CameraInfo topic and no intrinsics configured; set "
                "source.intrinsics.fx=... source.intrinsics.fy=... source.intrinsics.cx=... "
                "source.intrinsics.cy=... (or source.rosbag.camera_info_topic=<topic>)"
            )
        topic = self.topics.camera_info
        K, wi, hi = camera_info_K(self.bag.first(topic), topic)
        return fit_K(K, (wi, hi), (w, h), topic)

    def _stamps(self, topic: str) -> np.ndarray:
        """(N,2) int64 [log_ns, header stamp ns] of every message of `topic`, read without decoding."""
        rows = [(raw.log_ns, self.bag.stamp(raw)[0]) for raw in self.bag.messages([topic])]
        return np.array(rows, dtype=np.int64).reshape(-1, 2)

    def _plan(self) -> tuple[list[FrameKey], np.ndarray]:
        """Keys and T_world_camera (N,4,4) of the frames with a colour image within max_time_gap_s and a
        pose; the others are counted as skipped."""
        depth, rgb = self._stamps(self.topics.depth), self._stamps(self.topics.rgb)
        if depth.shape[0] == 0 or rgb.shape[0] == 0:
            raise SourceError(
                f"{self.bag.path}: no readable colour or depth messages; check them with h2viz bag-info"
            )
        keys, gap_ok = associate(depth, rgb, self.rcfg.max_time_gap_s * 1e9)
        origin_ns = int(depth[:, 1].min())
        T, pose_ok = camera_trajectory(
            self.bag, self.topics, self.rcfg, self.camera_frame, depth[:, 1], origin_ns
        )
        self._count_skips(keys, gap_ok, pose_ok)
        good = np.nonzero(gap_ok & pose_ok)[0]
        return [keys[i] for i in good], T[good]

    def _count_skips(self, keys: list[FrameKey], gap_ok: np.ndarray, pose_ok: np.ndarray) -> None:
        gap, name = self.rcfg.max_time_gap_s, self.bag.path.name
        no_pose = gap_ok & ~pose_ok
        self.skipped += [
            SkippedFrame(str(keys[i]), f"no colour image within {gap} s") for i in np.flatnonzero(~gap_ok)
        ]
        self.skipped += [SkippedFrame(str(keys[i]), "no pose at this time") for i in np.flatnonzero(no_pose)]
        if (~gap_ok).any():
            log.warning("%s: %d depth frames have no colour image within %s s and are skipped "
                        "(source.rosbag.max_time_gap_s)", name, int((~gap_ok).sum()), gap)  # fmt: skip
        if no_pose.any():
            log.warning("%s: %d frames have no pose within %s s, or lie between pose samples more than %s s "
                        "apart, and are skipped (source.rosbag.max_time_gap_s / max_pose_gap_s)",
                        name, int(no_pose.sum()), gap, self.rcfg.max_pose_gap_s)  # fmt: skip

    # -- frames ------------------------------------------------------------------------------------
    def keys(self) -> Sequence[Hashable]:
        return self._keys

    def timestamp(self, position: int, key: Hashable) -> float | None:
        return key.depth_stamp_ns * 1e-9 if isinstance(key, FrameKey) else None

    def describe(self) -> str:
        poses = "/tf" if self.topics.tf else self.topics.pose
        return f"rosbag {self.bag.path} (depth {self.topics.depth}, colour {self.topics.rgb}, poses {poses})"

    def load(self, position: int, key: Hashable) -> RgbdFrame:
        if not isinstance(key, FrameKey):
            raise FrameError(f"{self.bag.path}: {key!r} is not a frame key of this bag")
        depth = self._fetch(self.topics.depth, key.depth_log_ns, key.depth_stamp_ns)
        rgb = self._fetch(self.topics.rgb, key.rgb_log_ns, key.rgb_stamp_ns)
        return self._build(position, key, depth, rgb)

    def _fetch(self, topic: str, log_ns: int, stamp_ns: int) -> RawMessage:
        for raw in self.bag.messages([topic], log_ns, log_ns + 1):
            if self.bag.stamp(raw)[0] == stamp_ns:
                return raw
        raise FrameError(f"{self.bag.path}: the {topic} message at {stamp_ns * 1e-9:.6f} s cannot be read")

    def _decode(self, raw: RawMessage) -> Any:
        try:
            return self.bag.decode(raw)
        except Exception as e:  # rosbags raises several types on corrupt payloads
            raise FrameError(
                f"{self.bag.path}: {raw.topic} message at {raw.log_ns * 1e-9:.6f} s is corrupt ({e})"
            ) from e

    def _build(self, position: int, key: FrameKey, depth_raw: RawMessage, rgb_raw: RawMessage) -> RgbdFrame:
        depth = decode_depth(self._decode(depth_raw), depth_raw.topic, self.rcfg.depth_scale)  # (H,W) metres
        rgb = decode_color(self._decode(rgb_raw), rgb_raw.topic)  # (h,w,3)
        size = (depth.shape[1], depth.shape[0])
        K = self.K if size == self.depth_size else fit_K(self.K, self.depth_size, size, depth_raw.topic)
        return RgbdFrame(
            index=position,
            timestamp=key.depth_stamp_ns * 1e-9,
            rgb=match_color_size(rgb, depth.shape, rgb_raw.topic),
            depth_m=depth,
            K=K,
            T_world_camera=self._T[position],
            name=f"{self.bag.path.name}:{depth_raw.topic}@{key.depth_stamp_ns * 1e-9:.6f}",
        )

    # -- streaming ---------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[RgbdFrame]:
        """One pass through the bag; in real-time mode frames come at the bag's rate, newest first."""
        keys = [(p, k) for p, k in self.selected() if isinstance(k, FrameKey)]
        frames = stream_pairs(self.bag, self.topics.depth, self.topics.rgb, keys, self._missing)
        if self.cfg.realtime:
            frames = paced(frames, self.clock, self.sleep, self._drop)
        for position, key, depth_raw, rgb_raw in frames:
            try:
                yield self.postprocess(self._build(position, key, depth_raw, rgb_raw))
            except FrameError as e:
                self.skip(str(key), str(e))

    def _missing(self, key: FrameKey) -> None:
        self.skip(
            str(key), f"its colour or depth message could not be read ({self.bag.damage or 'not in the bag'})"
        )

    def _drop(self) -> None:
        self.dropped += 1

    def close(self) -> None:
        self.bag.close()
