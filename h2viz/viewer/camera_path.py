"""Fly-through camera paths: keyframes of a camera (viser's wxyz + position, OpenCV camera axes), a duration and a
field of view; positions follow a cubic spline and rotations a rotation spline through the keyframes (both C2, so
the camera neither jerks nor stops at a keyframe), sampled at the video's frame rate. Saved as JSON. NumPy and
SciPy only."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from h2viz.errors import H2vizError
from h2viz.viewer.shapes import pose_from_wxyz, view_intrinsics, wxyz_position

MAX_TRAJECTORY_KEYFRAMES = 24  # the trajectory preset keeps at most this many of the recorded poses


class CameraPathError(H2vizError):
    """A camera path is invalid or cannot be read."""


@dataclass
class CameraKeyframe:
    wxyz: list[float]  # camera-to-world rotation (w, x, y, z)
    position: list[float]  # camera centre in world metres


@dataclass
class CameraPath:
    keyframes: list[CameraKeyframe] = field(default_factory=list)
    duration_s: float = 5.0
    fov_deg: float = 60.0  # vertical field of view
    fps: int = 30
    width: int = 640
    height: int = 480

    @property
    def n_frames(self) -> int:
        return max(1, int(round(self.duration_s * self.fps)))

    def add(self, wxyz: np.ndarray, position: np.ndarray, at: int | None = None) -> None:
        kf = CameraKeyframe([float(v) for v in wxyz], [float(v) for v in position])
        self.keyframes.insert(len(self.keyframes) if at is None else at, kf)

    def move(self, index: int, delta: int) -> None:
        """Move keyframe `index` by `delta` places (clamped)."""
        target = int(np.clip(index + delta, 0, len(self.keyframes) - 1))
        self.keyframes.insert(target, self.keyframes.pop(index))

    def K(self) -> np.ndarray:
        return view_intrinsics(np.deg2rad(self.fov_deg), self.width, self.height)

    def poses(self, n: int | None = None) -> np.ndarray:
        """T_world_camera (n,4,4) of the path's n frames (default n_frames), the first at the first keyframe and the
        last at the last one."""
        self.check()
        n = self.n_frames if n is None else int(n)
        T = np.array([pose_from_wxyz(np.array(k.wxyz), np.array(k.position)) for k in self.keyframes])  # (K,4,4)
        if len(T) == 1:
            return np.repeat(T, n, axis=0)
        knots = np.linspace(0.0, 1.0, len(T))
        t = np.linspace(0.0, 1.0, n)
        bc = "natural" if len(T) > 2 else "not-a-knot"
        positions = CubicSpline(knots, T[:, :3, 3], axis=0, bc_type=bc)(t)  # (n,3)
        rotations = RotationSpline(knots, Rotation.from_matrix(T[:, :3, :3]))(t).as_matrix()  # (n,3,3)
        out = np.tile(np.eye(4), (n, 1, 1))
        out[:, :3, :3], out[:, :3, 3] = rotations, positions
        return out

    def check(self, what: str = "camera path") -> None:
        if not self.keyframes:
            raise CameraPathError(f"{what}: no keyframes; add at least one (two for a motion)")
        if not (self.duration_s > 0 and 1 <= self.fps <= 240 and 0 < self.fov_deg < 180):
            raise CameraPathError(
                f"{what}: duration_s must be > 0, fps 1..240 and fov_deg 0..180 "
                f"(got {self.duration_s}, {self.fps}, {self.fov_deg})"
            )
        if self.width % 2 or self.height % 2 or not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise CameraPathError(
                f"{what}: the video size {self.width}x{self.height} must be even (H.264) and 16..4096 pixels a side"
            )
        for i, k in enumerate(self.keyframes):
            if len(k.wxyz) != 4 or len(k.position) != 3 or not np.isfinite(k.wxyz + k.position).all():
                raise CameraPathError(f"{what}: keyframe {i} needs a finite wxyz (4 numbers) and position (3)")
            if np.linalg.norm(k.wxyz) < 1e-6:
                raise CameraPathError(f"{what}: keyframe {i} has a zero rotation quaternion")

    def save(self, path: Path) -> Path:
        path = Path(path)
        path.write_text(json.dumps(asdict(self), indent=1))
        return path


def load_path(path: Path) -> CameraPath:
    """Read and check a camera path JSON file; CameraPathError naming the file and the problem."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
        keyframes = [CameraKeyframe(list(k["wxyz"]), list(k["position"])) for k in doc.pop("keyframes")]
        cam = CameraPath(keyframes, **doc)
    except (OSError, json.JSONDecodeError) as e:
        raise CameraPathError(f"{path}: cannot read the camera path ({e})") from e
    except (KeyError, TypeError, AttributeError) as e:
        raise CameraPathError(
            f"{path}: not a camera path ({type(e).__name__}: {e}); expected keyframes (each with wxyz and "
            "position), duration_s, fov_deg, fps, width, height, as the dashboard's Save path writes"
        ) from e
    cam.check(str(path))
    return cam


def trajectory_path(trajectory: np.ndarray, K: np.ndarray, height: int, seconds_per_pose: float = 0.1) -> CameraPath:
    """The preset that flies along recorded poses (N,4,4) with the sensor's vertical field of view."""
    if len(trajectory) == 0:
        raise CameraPathError("trajectory preset: no frames mapped yet")
    keep = np.unique(np.linspace(0, len(trajectory) - 1, min(len(trajectory), MAX_TRAJECTORY_KEYFRAMES)).round())
    path = CameraPath(duration_s=max(1.0, len(trajectory) * seconds_per_pose))
    path.fov_deg = float(np.rad2deg(2.0 * np.arctan2(0.5 * height, K[1, 1])))
    for i in keep.astype(int):
        wxyz, position = wxyz_position(trajectory[i])
        path.add(wxyz, position)
    return path
