"""NumPy geometry for drawing: deduplicated cube edges, trajectory segments, frame point clouds,
viser camera <-> pinhole conversions and false-colour images. No viser or torch state here."""

from __future__ import annotations

import cv2
import numpy as np
import viser.transforms as vtf

from h2viz.geometry import backproject
from h2viz.types import RgbdFrame

# The 12 edges of a unit cube as (start corner offset, axis): 4 parallel edges per axis.
_EDGE_STARTS = np.array(
    [[0, j, k] for j in (0, 1) for k in (0, 1)]
    + [[i, 0, k] for i in (0, 1) for k in (0, 1)]
    + [[i, j, 0] for i in (0, 1) for j in (0, 1)],
    dtype=np.int64,
)  # (12,3)
_EDGE_AXES = np.repeat(np.arange(3), 4)  # (12,)
_OFF = 1 << 19  # coordinates are packed as 3 x 20 bits + 2 bits of axis


def cube_edges(cells: np.ndarray, cell_size_m: float) -> np.ndarray:
    """Line segments (E,2,3) float32 outlining cubes at integer `cells` (N,3); an edge shared by
    neighbouring cubes appears once."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    starts = (cells[:, None, :] + _EDGE_STARTS[None]).reshape(-1, 3)  # (12N,3)
    axes = np.broadcast_to(_EDGE_AXES, (len(cells), 12)).reshape(-1)  # (12N,)
    s = starts + _OFF
    packed = (s[:, 0] << 42) | (s[:, 1] << 22) | (s[:, 2] << 2) | axes
    _, first = np.unique(packed, return_index=True)
    starts, axes = starts[first], axes[first]
    ends = starts + np.eye(3, dtype=np.int64)[axes]
    return (np.stack([starts, ends], axis=1) * cell_size_m).astype(np.float32)


MAX_TRAJECTORY_SEGMENTS = 4096
"""Segments the trajectory is drawn with at most: a long run's path is resent with every new pose, so beyond this
every k-th pose is drawn (and the newest), keeping each update's size bounded instead of growing with the run."""


def trajectory_segments(trajectory: np.ndarray, max_segments: int = MAX_TRAJECTORY_SEGMENTS) -> np.ndarray:
    """Consecutive camera positions of poses (N,4,4) as segments (M,2,3) float32: M = N-1, or at most `max_segments`
    through every k-th pose and the newest."""
    p = trajectory[:, :3, 3]
    k = -(-(len(p) - 1) // max_segments) if len(p) > max_segments + 1 else 1
    if k > 1:
        p = np.concatenate([p[:-1:k], p[-1:]])
    return np.stack([p[:-1], p[1:]], axis=1).astype(np.float32)


def frame_points(frame: RgbdFrame, max_points: int = 20_000) -> tuple[np.ndarray, np.ndarray]:
    """World points (N,3) float32 and colours (N,3) uint8 of a frame's valid depth, subsampled."""
    step = max(1, int(np.ceil(np.sqrt(frame.height * frame.width / max_points))))
    depth = np.zeros_like(frame.depth_m)
    depth[::step, ::step] = frame.depth_m[::step, ::step]
    v, u = np.nonzero(depth > 0)
    points = backproject(depth, frame.K, frame.T_world_camera)  # same (v,u) order as nonzero
    return points.astype(np.float32), frame.rgb[v, u]


def wxyz_position(T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Viser's (wxyz, position) of a camera-to-world pose (both use OpenCV camera axes)."""
    return vtf.SO3.from_matrix(T_world_camera[:3, :3]).wxyz, T_world_camera[:3, 3].copy()


def pose_from_wxyz(wxyz: np.ndarray, position: np.ndarray) -> np.ndarray:
    """T_world_camera (4,4) of a viser camera (wxyz rotation, position)."""
    T = np.eye(4)
    T[:3, :3] = vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()
    T[:3, 3] = position
    return T


def initial_view(T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(up, eye, target) for a first look at a scene from behind and above its first camera."""
    up = -T_world_camera[:3, 1]
    axis = int(np.argmax(np.abs(up)))
    if abs(up[axis]) > 0.85:  # snap to the world axis the camera is nearly level with
        up = np.sign(up[axis]) * np.eye(3)[axis]
    forward = T_world_camera[:3, 2] - up * float(T_world_camera[:3, 2] @ up)
    forward = forward / max(float(np.linalg.norm(forward)), 1e-6)
    position = T_world_camera[:3, 3]
    return up, position - 1.5 * forward + 1.2 * up, position + 1.0 * forward


def view_intrinsics(fov_y_rad: float, width: int, height: int) -> np.ndarray:
    """Pinhole K (3,3) with square pixels for a vertical field of view and an image size."""
    f = 0.5 * height / np.tan(0.5 * fov_y_rad)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def fov_aspect(K: np.ndarray, width: int, height: int) -> tuple[float, float]:
    """Vertical field of view (radians) and aspect (width / height) of a pinhole camera."""
    return float(2.0 * np.arctan2(0.5 * height, K[1, 1])), width / max(height, 1)


PERCENTILE_SAMPLES = 20_000  # depth values the colour range of colorize_depth is taken from


def colorize_depth(depth_m: np.ndarray, backdrop: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """Turbo false colour (H,W,3) uint8 of depth (H,W) over its 2nd-98th percentile range;
    pixels without depth get `backdrop`."""
    valid = depth_m > 0
    out = np.empty((*depth_m.shape, 3), dtype=np.uint8)
    out[:] = backdrop
    if not valid.any():
        return out
    values = depth_m[valid]
    step = max(1, len(values) // PERCENTILE_SAMPLES)  # the range from a regular subsample: a display, not a statistic
    lo, hi = np.percentile(values[::step], [2, 98])
    scaled = np.clip((depth_m - lo) / max(hi - lo, 1e-6), 0, 1)
    turbo = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    np.copyto(out, turbo, where=valid[..., None])  # a masked copy: boolean indexing of (H,W,3) is ~5x slower
    return out


def to_rgb8(image: np.ndarray, mode: str, backdrop: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """A rendered image in `mode` (rgb [0,1], normal [-1,1], depth / prior metres) as (H,W,3) uint8."""
    if mode in ("depth", "prior"):
        return colorize_depth(image, backdrop)
    img = (image + 1.0) / 2.0 if mode == "normal" else image
    out = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    empty = ~np.any(image != 0, axis=-1)
    out[empty] = backdrop
    return out
