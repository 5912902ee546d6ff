"""SE(3), back-projection, pixel rays and ray/box intersection in NumPy (torch twins live in mapping/)."""

from __future__ import annotations

import numpy as np


def invert_se3(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (..., 4, 4)."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4,4) transform to points (N,3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates u (H,W), v (H,W) as float64 (u along width)."""
    v, u = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    return u, v


def backproject(depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray | None = None) -> np.ndarray:
    """Valid depth pixels (depth > 0) lifted to 3-D points (N,3), in world frame when a pose is given."""
    v, u = np.nonzero(depth_m > 0)
    z = depth_m[v, u].astype(np.float64)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    pts = np.stack([x, y, z], axis=1)
    return transform_points(T_world_camera, pts) if T_world_camera is not None else pts


def camera_rays(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """Camera-frame ray directions (H,W,3) with z = 1 (so depth along the ray = t)."""
    u, v = pixel_grid(height, width)
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)


def world_rays(
    K: np.ndarray, T_world_camera: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """Origins (H*W,3) and z-normalised world directions (H*W,3) of every pixel."""
    d_cam = camera_rays(K, height, width).reshape(-1, 3)
    d_world = d_cam @ T_world_camera[:3, :3].T
    origins = np.broadcast_to(T_world_camera[:3, 3], d_world.shape).copy()
    return origins, d_world


def project(
    points_world: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N,2) and camera depth z (N,) of world points."""
    p = transform_points(invert_se3(T_world_camera), points_world)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]], axis=1)
    return uv, z


def ray_aabb(
    origins: np.ndarray, dirs: np.ndarray, box_min: np.ndarray, box_max: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Slab test: entry/exit t (N,) of rays against boxes (N,3)/(3,); exit < entry means a miss."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        t0 = (box_min - origins) * inv
        t1 = (box_max - origins) * inv
    t_near = np.nanmax(np.minimum(t0, t1), axis=-1)
    t_far = np.nanmin(np.maximum(t0, t1), axis=-1)
    return np.maximum(t_near, 0.0), t_far


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """T_world_camera (4,4) of an OpenCV camera at `eye` looking at `target` (+y down, world up = `up`, default +z)."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else up
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-8:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def quat_to_rotation(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrix (3,3) from a unit quaternion in (x, y, z, w) order."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_from_tq(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 transform from a translation (3,) and a quaternion (x, y, z, w)."""
    T = np.eye(4)
    T[:3, :3] = quat_to_rotation(q_xyzw)
    T[:3, 3] = t
    return T


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions (N,4) at fractions alpha (N,), shortest arc."""
    q0 = q0 / np.linalg.norm(q0, axis=1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=1, keepdims=True)
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    theta = np.arccos(np.clip(np.abs(dot), 0.0, 1.0))  # (N,)
    sin = np.sin(theta)
    small = sin < 1e-9
    safe = np.where(small, 1.0, sin)
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * theta) / safe)
    w1 = np.where(small, alpha, np.sin(alpha * theta) / safe)
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def drop_unused_vertices(n_vertices: int, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which of n_vertices vertices the faces (M,3) use, (n_vertices,) bool, and the faces re-indexed into the
    used vertices kept in order (vertices[used] goes with them)."""
    used = np.zeros(n_vertices, dtype=bool)
    used[faces] = True
    new_index = (np.cumsum(used) - 1).astype(faces.dtype)  # old vertex -> its row among the used ones
    return used, new_index[faces]
