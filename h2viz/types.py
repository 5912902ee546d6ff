"""Plain data passed between threads: frames in, snapshots out, commands back. NumPy only, no torch."""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from h2viz.errors import FrameError


def check_pose(T: np.ndarray, what: str) -> np.ndarray:
    """Return `T` as a float64 (4,4) rigid transform or raise FrameError naming `what`."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise FrameError(f"{what}: pose must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise FrameError(f"{what}: pose contains inf/NaN; the frame is skipped")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-2) or abs(np.linalg.det(R) - 1.0) > 1e-2:
        raise FrameError(f"{what}: pose rotation is not orthonormal (det={np.linalg.det(R):.3f})")
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        raise FrameError(f"{what}: last pose row must be [0 0 0 1], got {T[3]}")
    return T


@dataclass(frozen=True)
class RgbdFrame:
    """One registered RGB-D frame with its camera-to-world pose (OpenCV camera axes)."""

    index: int  # position in the source's own sequence (before stride)
    timestamp: float  # seconds
    rgb: np.ndarray  # (H,W,3) uint8
    depth_m: np.ndarray  # (H,W) float32, 0 = invalid
    K: np.ndarray  # (3,3) float64 pinhole intrinsics
    T_world_camera: np.ndarray  # (4,4) float64, camera -> world
    name: str = ""  # file or topic the frame came from, for messages

    def __post_init__(self) -> None:
        what = self.name or f"frame {self.index}"
        rgb, depth = self.rgb, self.depth_m
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise FrameError(f"{what}: colour must be (H,W,3) uint8, got {rgb.shape} {rgb.dtype}")
        if depth.ndim != 2 or depth.dtype != np.float32:
            raise FrameError(f"{what}: depth must be (H,W) float32, got {depth.shape} {depth.dtype}")
        if rgb.shape[:2] != depth.shape:
            raise FrameError(
                f"{what}: colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                f"{depth.shape[1]}x{depth.shape[0]}; resize one of them or set source.downscale"
            )
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise FrameError(f"{what}: intrinsics must be a finite 3x3 matrix with fx, fy > 0")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_world_camera", check_pose(self.T_world_camera, what))

    @property
    def height(self) -> int:
        return int(self.depth_m.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth_m.shape[1])


@dataclass(frozen=True)
class MeshChunk:
    """The welded, coloured surface of one chunk of leaf voxels."""

    key: tuple[int, int, int]  # chunk grid coordinate
    vertices: np.ndarray  # (N,3) float32, world metres
    faces: np.ndarray  # (M,3) int32
    colors: np.ndarray  # (N,3) uint8
    version: int  # map version at which this chunk was last re-meshed


class KeyframeState(str, Enum):
    """Coverage state of a keyframe in the current selection round."""

    SELECTED = "selected"  # optimised in the current round
    COVERED = "covered"  # selected earlier in this round
    UNCOVERED = "uncovered"  # not yet selected in this round


@dataclass(frozen=True)
class KeyframeInfo:
    index: int  # frame index
    T_world_camera: np.ndarray  # (4,4)
    K: np.ndarray  # (3,3)
    width: int
    height: int
    thumbnail: np.ndarray  # (h,w,3) uint8
    state: KeyframeState


@dataclass(frozen=True)
class FrameStats:
    """What mapping one frame cost and reached."""

    index: int
    map_time_s: float
    iterations: int
    n_voxels: int
    n_keyframes: int
    losses: dict[str, float] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per stage: allocation, keyframes, sampling, forward, backward, optimiser."""
    keyframe_mb: float = 0.0
    """Memory of the keyframes after this frame (rays, voxel lists, thumbnails), MB."""
    view_mb: float = 0.0
    """Memory of the stored colour views after this frame (h2viz.mapping.field.color_views), MB."""


@dataclass(frozen=True)
class MapSnapshot:
    """Frozen NumPy view of the map handed from the worker to the viewer (arrays are never mutated)."""

    version: int
    frames_done: int
    frames_total: int | None
    chunks: dict[tuple[int, int, int], MeshChunk]  # every current chunk; compare .version to diff
    voxel_size_m: float
    voxel_coords: np.ndarray  # (V,3) int32 leaf voxel grid coordinates
    keyframes: tuple[KeyframeInfo, ...]
    trajectory: np.ndarray  # (N,4,4) T_world_camera of every mapped frame
    current_frame: RgbdFrame | None
    stats: tuple[FrameStats, ...]
    paused: bool = False
    finished: bool = False
    skipped: int = 0
    dropped: int = 0
    metrics: dict[str, float] = field(default_factory=dict)
    memory_mb: float = 0.0
    refine_left: int = 0  # refinement steps still to run (they run while mapping is paused or finished)
    refined: int = 0  # refinement steps run so far
    phase: str = ""  # real-time mode: streaming | sharpening | settled (h2viz.mapping.anytime.Phase); "" otherwise
    opt_steps: int = 0  # real-time mode: optimisation steps so far (between frames and after the stream)
    preparing: tuple[int, int] | None = None  # (done, total) frames the source prepares before real-time playback
    waiting: int = 0  # real-time mode: frames that arrived and wait to be integrated (up to anytime.backlog_frames)
    lag_s: float = 0.0  # real-time mode: how long the newest integrated frame waited after it arrived


class RenderMode(str, Enum):
    RGB = "rgb"
    DEPTH = "depth"
    NORMAL = "normal"
    PRIOR = "prior"  # depth of the prior-only geometry


@dataclass
class Command:
    """A request from the viewer to the worker; the worker resolves `reply` when done."""

    kind: str  # pause | resume | step | set | render | export | save
    args: dict[str, Any] = field(default_factory=dict)
    reply: Future[Any] = field(default_factory=Future)
