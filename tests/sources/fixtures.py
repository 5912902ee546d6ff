"""Small datasets written into a test's tmp_path in each folder layout, with the values the sources
must read back: 64x48 depth planes with known metres, smooth colours and known camera-to-world poses.

With `broken=True` each layout also holds frames that must be skipped (corrupt image, NaN pose,
missing file...); `bad` maps their positions to the file name the skip reason has to mention.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from h2viz.geometry import pose_from_tq

H, W = 48, 64
K_FIXTURE = np.array([[50.0, 0.0, 31.5], [0.0, 52.0, 23.5], [0.0, 0.0, 1.0]])
TUM_T0 = 1305031100.0  # seconds; TUM-like absolute timestamps


@dataclass
class Fixture:
    root: Path
    K: np.ndarray  # (3,3) intrinsics of the depth image
    poses: list[np.ndarray] = field(default_factory=list)  # (4,4) expected T_world_camera per position
    depth_m: list[np.ndarray] = field(default_factory=list)  # (H,W) float32 expected metres per position
    rgb: list[np.ndarray] = field(default_factory=list)  # (H,W,3) uint8 expected colour per position
    timestamps: list[float] = field(default_factory=list)
    bad: dict[int, str] = field(default_factory=dict)  # position -> file named by the skip reason

    def good(self) -> list[int]:
        return [i for i in range(len(self.poses)) if i not in self.bad]


def fixture_pose(i: int) -> np.ndarray:
    """A rigid camera-to-world pose that differs per frame (rotation about a tilted axis + translation)."""
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    angle = 0.07 * i + 0.1
    q = np.append(np.sin(angle / 2) * axis, np.cos(angle / 2))
    return pose_from_tq(np.array([0.05 * i, -0.02 * i + 0.3, 0.03 * i - 1.0]), q)


def fixture_depth_raw(i: int, units_per_m: float, h: int = H, w: int = W) -> np.ndarray:
    """(h,w) uint16 depth: a slanted plane 1.0 + 0.1 i metres deep, with an invalid (0) corner block."""
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    depth_m = 1.0 + 0.1 * i + 0.004 * u + 0.002 * v
    raw = np.round(depth_m * units_per_m).astype(np.uint16)
    raw[:4, :4] = 0
    return raw


def fixture_rgb(i: int, h: int = H, w: int = W) -> np.ndarray:
    """(h,w,3) uint8 smooth colours; the blue channel encodes the frame (30 * i)."""
    u = np.arange(w)[None, :] * 255 // max(w - 1, 1)
    v = np.arange(h)[:, None] * 255 // max(h - 1, 1)
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = u
    rgb[..., 1] = v
    rgb[..., 2] = 30 * i
    return rgb


def write_color(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def write_depth(path: Path, raw: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), raw)


def write_garbage(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG this is not an image at all")


def matrix_text(M: np.ndarray) -> str:
    return "\n".join(" ".join(f"{x:.17g}" for x in row) for row in M) + "\n"


def _expected_depth(raw: np.ndarray, scale_m: float) -> np.ndarray:
    return raw.astype(np.float32) * np.float32(scale_m)


def write_replica(root: Path, n: int = 6, broken: bool = True) -> Fixture:
    """NICE-SLAM Replica layout; broken: frame 1 colour corrupt, frame 3 pose NaN, frame 4 depth missing."""
    fx = Fixture(root, K_FIXTURE.copy())
    rows = []
    for i in range(n):
        raw = fixture_depth_raw(i, 6553.5)
        write_color(root / "results" / f"frame{i:06d}.jpg", fixture_rgb(i))
        write_depth(root / "results" / f"depth{i:06d}.png", raw)
        T = fixture_pose(i)
        rows.append(" ".join(f"{x:.17g}" for x in T.ravel()))
        fx.poses.append(T)
        fx.depth_m.append(_expected_depth(raw, 1.0 / 6553.5))
        fx.rgb.append(fixture_rgb(i))
        fx.timestamps.append(i / 30.0)
    if broken:
        write_garbage(root / "results" / "frame000001.jpg")
        rows[3] = " ".join(["nan"] * 16)
        (root / "results" / "depth000004.png").unlink()
        fx.bad = {1: "frame000001.jpg", 3: "traj.txt", 4: "depth000004.png"}
    (root / "traj.txt").write_text("\n".join(rows) + "\n")
    return fx


def write_scannet(root: Path, ids: tuple[int, ...] = (100, 0, 15, 5, 20, 10), broken: bool = True) -> Fixture:
    """ScanNet layout with 128x96 colour over 64x48 depth; positions follow the ids sorted numerically.
    broken: id 5 pose inf, id 10 depth corrupt, id 20 colour missing."""
    fx = Fixture(root, K_FIXTURE.copy())
    K4 = np.eye(4)
    K4[:3, :3] = K_FIXTURE
    (root / "intrinsic").mkdir(parents=True)
    (root / "intrinsic" / "intrinsic_depth.txt").write_text(matrix_text(K4))
    (root / "pose").mkdir()
    for i, key in enumerate(sorted(ids)):
        small = fixture_rgb(i)
        write_color(root / "color" / f"{key}.jpg", np.repeat(np.repeat(small, 2, axis=0), 2, axis=1))
        raw = fixture_depth_raw(i, 1000.0)
        write_depth(root / "depth" / f"{key}.png", raw)
        T = fixture_pose(i)
        (root / "pose" / f"{key}.txt").write_text(matrix_text(T))
        fx.poses.append(T)
        fx.depth_m.append(_expected_depth(raw, 1.0 / 1000.0))
        fx.rgb.append(small)
        fx.timestamps.append(key / 30.0)
    if broken:
        T_bad = fixture_pose(0)
        T_bad[0, 3] = np.inf
        (root / "pose" / "5.txt").write_text(matrix_text(T_bad))
        write_garbage(root / "depth" / "10.png")
        (root / "color" / "20.jpg").unlink()
        pos = {key: i for i, key in enumerate(sorted(ids))}
        fx.bad = {pos[5]: "pose/5.txt", pos[10]: "depth/10.png", pos[20]: "color/20.jpg"}
    return fx


def write_sevenscenes(
    root: Path, n: int = 6, broken: bool = True, intrinsics: bool = True, first_id: int = 0
) -> Fixture:
    """7-Scenes / 3DMatch layout (PNG colour, 65535 = invalid depth block);
    broken: frame 1 colour corrupt, frame 3 pose NaN, frame 4 depth missing."""
    fx = Fixture(root, K_FIXTURE.copy())
    root.mkdir(parents=True, exist_ok=True)
    if intrinsics:
        (root / "camera-intrinsics.txt").write_text(matrix_text(K_FIXTURE))
    for i in range(n):
        stem = f"frame-{first_id + i:06d}"
        raw = fixture_depth_raw(i, 1000.0)
        raw[-3:, -5:] = 65535
        write_color(root / f"{stem}.color.png", fixture_rgb(i))
        write_depth(root / f"{stem}.depth.png", raw)
        T = fixture_pose(i)
        (root / f"{stem}.pose.txt").write_text(matrix_text(T))
        depth = _expected_depth(raw, 1.0 / 1000.0)
        depth[raw == 65535] = 0.0
        fx.poses.append(T)
        fx.depth_m.append(depth)
        fx.rgb.append(fixture_rgb(i))
        fx.timestamps.append((first_id + i) / 30.0)
    if broken:
        write_garbage(root / f"frame-{first_id + 1:06d}.color.png")
        (root / f"frame-{first_id + 3:06d}.pose.txt").write_text(matrix_text(np.full((4, 4), np.nan)))
        (root / f"frame-{first_id + 4:06d}.depth.png").unlink()
        fx.bad = {1: f"frame-{first_id + 1:06d}.color.png", 3: f"frame-{first_id + 3:06d}.pose.txt"}
        fx.bad[4] = f"frame-{first_id + 4:06d}.depth.png"
    return fx


def tum_tq(s: float) -> tuple[np.ndarray, np.ndarray]:
    """Analytic translation (3,) and quaternion xyzw (4,) at s seconds after TUM_T0: constant velocity
    and a constant-rate rotation about a fixed axis, so lerp + slerp between samples reproduce it exactly."""
    axis = np.array([1.0, 2.0, 3.0]) / np.linalg.norm([1.0, 2.0, 3.0])
    angle = 0.3 + 1.5 * s
    q = np.append(np.sin(angle / 2) * axis, np.cos(angle / 2))
    return np.array([0.2 + 0.5 * s, -0.1 + 0.3 * s, 1.0 - 0.2 * s]), q


def tum_trajectory(s: float) -> np.ndarray:
    """(4,4) camera-to-world pose of `tum_tq` at s seconds after TUM_T0."""
    return pose_from_tq(*tum_tq(s))


def _tum_list(path: Path, kind: str, stamps: list[float], names: list[str]) -> None:
    lines = [f"# {kind}", "# file: fixture", "# timestamp filename"]
    lines += [f"{t:.6f} {name}" for t, name in zip(stamps, names, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def write_tum(root: Path, n: int = 8, broken: bool = True) -> Fixture:
    """TUM RGB-D layout: colour at 30 Hz from TUM_T0 + 0.1 s, depth 12 ms later, ground truth every 10 ms.
    broken: frame 1 has no ground truth within 20 ms (samples 0.13-0.16 s removed), frame 3 only a
    sample 2 ms before it (0.22, 0.23 s removed: nearest, not interpolated), frame 5 no colour line,
    frame 6 depth corrupt, frame 7 depth missing."""
    fx = Fixture(root, np.eye(3))
    root.mkdir(parents=True, exist_ok=True)
    rgb_t, depth_t, rgb_names, depth_names = [], [], [], []
    for i in range(n):
        t_c = round(TUM_T0 + 0.1 + i / 30.0, 6)
        t_d = round(t_c + 0.012, 6)
        rgb_t.append(t_c)
        depth_t.append(t_d)
        rgb_names.append(f"rgb/{t_c:.6f}.png")
        depth_names.append(f"depth/{t_d:.6f}.png")
        write_color(root / rgb_names[-1], fixture_rgb(i))
        raw = fixture_depth_raw(i, 5000.0)
        write_depth(root / depth_names[-1], raw)
        fx.poses.append(tum_trajectory(t_d - TUM_T0))
        fx.depth_m.append(_expected_depth(raw, 1.0 / 5000.0))
        fx.rgb.append(fixture_rgb(i))
        fx.timestamps.append(t_d)
    samples = [k for k in range(41) if not (broken and (13 <= k <= 16 or k in (22, 23)))]
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for k in samples:
        t, q = tum_tq(k * 0.01)
        q = -q if k % 2 else q  # same rotation; interpolation must take the shorter arc
        gt.append(f"{TUM_T0 + k * 0.01:.6f} " + " ".join(f"{x:.12f}" for x in (*t, *q)))
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if broken:
        fx.poses[3] = tum_trajectory(0.21)
        del rgb_t[5], rgb_names[5]
        write_garbage(root / depth_names[6])
        (root / depth_names[7]).unlink()
        fx.bad = {1: "groundtruth.txt", 5: "rgb.txt", 6: depth_names[6], 7: depth_names[7]}
    _tum_list(root / "rgb.txt", "color images", rgb_t, rgb_names)
    _tum_list(root / "depth.txt", "depth maps", depth_t, depth_names)
    return fx
