"""Pose tracks from pose messages and the tf tree: interpolation in time (lerp + slerp), tf chaining
between two frames, and conversion of PoseStamped / Odometry / TransformStamped messages."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from h2viz.geometry import invert_se3, slerp

POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/TransformStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)
TF_TYPE = "tf2_msgs/msg/TFMessage"


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices (N,3,3) from quaternions (N,4) in (x, y, z, w) order (normalised here)."""
    q = q_xyzw / np.linalg.norm(q_xyzw, axis=-1, keepdims=True)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    R = np.empty((q.shape[0], 3, 3))
    R[:, 0] = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1)
    R[:, 1] = np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1)
    R[:, 2] = np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1)
    return R


def compose(t_xyz: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 transforms (N,4,4) from translations (N,3) and quaternions (N,4)."""
    T = np.tile(np.eye(4), (t_xyz.shape[0], 1, 1))
    T[:, :3, :3] = quat_to_matrix(q_xyzw)
    T[:, :3, 3] = t_xyz
    return T


@dataclass
class PoseTrack:
    """Time-stamped rigid transforms of one frame relative to another, sorted by time."""

    times_s: np.ndarray  # (M,)
    t_xyz: np.ndarray  # (M,3)
    q_xyzw: np.ndarray  # (M,4) unit quaternions
    static: bool = False

    @staticmethod
    def build(samples: list[tuple[float, np.ndarray, np.ndarray]], static: bool = False) -> PoseTrack:
        """From (time_s, t (3,), q (4,)) samples in any order; duplicate stamps keep the last."""
        samples = sorted(samples, key=lambda s: s[0])
        times = np.array([s[0] for s in samples], dtype=np.float64)
        keep = np.append(np.diff(times) > 0, True) if len(times) else np.zeros(0, bool)
        t = np.array([s[1] for s in samples], dtype=np.float64).reshape(-1, 3)[keep]
        q = np.array([s[2] for s in samples], dtype=np.float64).reshape(-1, 4)[keep]
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        return PoseTrack(times[keep], t, q, static)

    def sample(
        self, query_s: np.ndarray, max_extrapolate_s: float, max_span_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Transforms (N,4,4) at query times (N,) and validity (N,): interpolated between neighbours at
        most `max_span_s` apart, held constant up to `max_extrapolate_s` beyond either end."""
        n, m = query_s.shape[0], self.times_s.shape[0]
        if m == 0:
            return np.tile(np.eye(4), (n, 1, 1)), np.zeros(n, bool)
        if self.static or m == 1:
            T = np.repeat(compose(self.t_xyz[:1], self.q_xyzw[:1]), n, axis=0)
            ok = np.ones(n, bool) if self.static else np.abs(query_s - self.times_s[0]) <= max_extrapolate_s
            return T, ok
        hi = np.clip(np.searchsorted(self.times_s, query_s), 1, m - 1)  # (N,) right neighbour
        lo = hi - 1
        t0, t1 = self.times_s[lo], self.times_s[hi]
        a = np.clip((query_s - t0) / (t1 - t0), -1.0, 2.0)  # beyond [0, 1]: constant-velocity extrapolation
        t = self.t_xyz[lo] + a[:, None] * (self.t_xyz[hi] - self.t_xyz[lo])
        q = slerp(self.q_xyzw[lo], self.q_xyzw[hi], a)
        inside = (query_s >= self.times_s[0]) & (query_s <= self.times_s[-1])
        nearest = np.minimum(np.abs(query_s - t0), np.abs(query_s - t1))
        ok = np.where(
            inside, (t1 - t0 <= max_span_s) | (nearest <= max_extrapolate_s), nearest <= max_extrapolate_s
        )
        return compose(t, q), ok


def _xyz(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


def _xyzw(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z, v.w], dtype=np.float64)


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def frame_name(name: str) -> str:
    """tf frame names without the ROS 1 leading slash."""
    return str(name).lstrip("/")


@dataclass(frozen=True)
class PoseSample:
    stamp_ns: int
    t_xyz: np.ndarray  # (3,)
    q_xyzw: np.ndarray  # (4,)
    parent: str  # frame the pose is expressed in
    child: str  # frame the pose describes ("" when the message does not say)


def pose_sample(msg: Any, msgtype: str) -> PoseSample:
    """The pose carried by a PoseStamped / PoseWithCovarianceStamped / Odometry / TransformStamped."""
    parent = frame_name(msg.header.frame_id)
    if msgtype.endswith("TransformStamped"):
        tr = msg.transform
        return PoseSample(
            stamp_ns(msg.header),
            _xyz(tr.translation),
            _xyzw(tr.rotation),
            parent,
            frame_name(msg.child_frame_id),
        )
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    child = frame_name(getattr(msg, "child_frame_id", ""))
    return PoseSample(stamp_ns(msg.header), _xyz(pose.position), _xyzw(pose.orientation), parent, child)


@dataclass
class TfTree:
    """Edges child -> (parent, track) collected from /tf and /tf_static."""

    samples: dict[tuple[str, str], list[tuple[float, np.ndarray, np.ndarray]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    static_edges: set[tuple[str, str]] = field(default_factory=set)
    _tracks: dict[str, tuple[str, PoseTrack]] = field(default_factory=dict)

    def add(self, msg: Any, static: bool, origin_ns: int) -> None:
        """Record every TransformStamped of a TFMessage (times in seconds after `origin_ns`)."""
        for tf in msg.transforms:
            s = pose_sample(tf, "geometry_msgs/msg/TransformStamped")
            self.samples[(s.parent, s.child)].append(((s.stamp_ns - origin_ns) * 1e-9, s.t_xyz, s.q_xyzw))
            if static:
                self.static_edges.add((s.parent, s.child))
        self._tracks.clear()

    def tracks(self) -> dict[str, tuple[str, PoseTrack]]:
        """child -> (parent, track of T_parent_child); a child with several parents keeps the busiest."""
        if not self._tracks:
            for (parent, child), samples in sorted(self.samples.items(), key=lambda kv: len(kv[1])):
                static = (parent, child) in self.static_edges
                self._tracks[child] = (parent, PoseTrack.build(samples[-1:] if static else samples, static))
        return self._tracks

    @property
    def frames(self) -> set[str]:
        return {f for edge in self.samples for f in edge}

    def ancestors(self, frame: str) -> list[str]:
        """frame, its parent, ... up to the root of its tree."""
        chain, tracks = [frame], self.tracks()
        while chain[-1] in tracks and tracks[chain[-1]][0] not in chain:
            chain.append(tracks[chain[-1]][0])
        return chain

    def root(self, frame: str) -> str:
        return self.ancestors(frame)[-1]

    def connected(self, target: str, source: str) -> bool:
        return bool(set(self.ancestors(target)) & set(self.ancestors(source)))

    def _down(
        self, lca: str, frame: str, query_s: np.ndarray, gap_s: float, span_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """T_lca_frame (N,4,4) and validity (N,) along the chain from `lca` down to `frame`."""
        n = query_s.shape[0]
        T, ok = np.tile(np.eye(4), (n, 1, 1)), np.ones(n, bool)
        tracks = self.tracks()
        for child in self.ancestors(frame)[: self.ancestors(frame).index(lca)]:
            T_edge, ok_edge = tracks[child][1].sample(query_s, gap_s, span_s)
            T, ok = T_edge @ T, ok & ok_edge
        return T, ok

    def lookup(
        self, target: str, source: str, query_s: np.ndarray, gap_s: float, span_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """T_target_source (N,4,4) at the query times and validity (N,); raises KeyError when unconnected."""
        up_target = self.ancestors(target)
        lca = next((f for f in self.ancestors(source) if f in up_target), None)
        if lca is None:
            raise KeyError(f"no tf path between '{target}' and '{source}'")
        T_lca_source, ok_s = self._down(lca, source, query_s, gap_s, span_s)
        T_lca_target, ok_t = self._down(lca, target, query_s, gap_s, span_s)
        return invert_se3(T_lca_target) @ T_lca_source, ok_s & ok_t

    def static_lookup(self, target: str, source: str) -> np.ndarray | None:
        """T_target_source when every edge between the two frames is static, else None."""
        try:
            T, ok = self.lookup(target, source, np.zeros(1), 0.0, 0.0)
        except KeyError:
            return None
        return T[0] if ok[0] else None
