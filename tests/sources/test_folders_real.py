"""Dataset-folder sources on the real sequences in ../shared/data (skipped when absent): values equal to
the files, stride / max_frames / downscale, skipped frames, and depth agreeing in world space."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from h2viz.config import SourceConfig
from h2viz.geometry import backproject, project
from h2viz.sources.sevenscenes import SevenScenesSource
from h2viz.sources.tum import TumSource
from h2viz.types import RgbdFrame
from tests.conftest import shared_data


def dataset(name: str) -> Path:
    path = shared_data(name)
    if not path.is_dir():
        pytest.skip(f"real data {name} not found in ../shared/data")
    return path


@pytest.fixture(scope="module")
def redkitchen() -> list[RgbdFrame]:
    return list(SevenScenesSource(SourceConfig(path=str(dataset("redkitchen_50")))))


@pytest.fixture(scope="module")
def tum() -> list[RgbdFrame]:
    return list(TumSource(SourceConfig(path=str(dataset("tum_fr1_xyz_10")))))


def raw_depth_m(path: Path, scale_m: float, invalid: int | None = None) -> np.ndarray:
    """Depth PNG in metres with the default 0.05-10 m range applied, computed independently."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)
    depth = raw * scale_m
    bad = (depth < 0.05) | (depth > 10.0) | ((raw == invalid) if invalid is not None else False)
    return np.where(bad, 0.0, depth)


def agreement(a: RgbdFrame, b: RgbdFrame) -> tuple[float, float]:
    """Median |z - depth_b| of frame a's points projected into b (pixels valid in both, < 10 cm apart)
    and the share of a's points that land there."""
    pts = backproject(a.depth_m, a.K, a.T_world_camera)  # (N,3)
    uv, z = project(pts, b.K, b.T_world_camera)
    px = np.round(uv).astype(np.int64)  # (N,2)
    inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < b.width) & (px[:, 1] >= 0) & (px[:, 1] < b.height)
    d_b = np.zeros_like(z)
    d_b[inside] = b.depth_m[px[inside, 1], px[inside, 0]]
    diff = np.abs(z - d_b)
    close = inside & (d_b > 0) & (diff < 0.1)
    return float(np.median(diff[close])), float(close.mean())


def test_redkitchen_equals_files(redkitchen: list[RgbdFrame]) -> None:
    root = dataset("redkitchen_50")
    assert [f.index for f in redkitchen] == list(range(50))
    K_file = np.loadtxt(root / "camera-intrinsics.txt")
    for f, frame_id in zip(redkitchen, range(8, 58), strict=True):
        stem = root / f"frame-{frame_id:06d}"
        np.testing.assert_array_equal(f.T_world_camera, np.loadtxt(f"{stem}.pose.txt"))
        np.testing.assert_allclose(f.depth_m, raw_depth_m(Path(f"{stem}.depth.png"), 1e-3, 65535), atol=1e-6)
        np.testing.assert_array_equal(f.rgb, cv2.imread(f"{stem}.color.png")[..., ::-1])
        np.testing.assert_array_equal(f.K, K_file)
        assert f.timestamp == pytest.approx(frame_id / 30.0)
    assert 0.5 < np.median(redkitchen[0].depth_m[redkitchen[0].depth_m > 0]) < 4.0


def test_fountain_jpg_colour_and_intrinsics() -> None:
    root = dataset("fountain_33")
    src = SevenScenesSource(SourceConfig(path=str(root), stride=8))
    frames = list(src)
    assert len(SevenScenesSource(SourceConfig(path=str(root)))) == 33
    assert [f.index for f in frames] == [0, 8, 16, 24, 32] and not src.skipped
    for f in frames:
        stem = root / f"frame-{f.index:06d}"
        np.testing.assert_array_equal(f.rgb, cv2.imread(f"{stem}.color.jpg")[..., ::-1])
        np.testing.assert_array_equal(f.T_world_camera, np.loadtxt(f"{stem}.pose.txt"))
        np.testing.assert_allclose(f.depth_m, raw_depth_m(Path(f"{stem}.depth.png"), 1e-3), atol=1e-6)
        np.testing.assert_allclose(f.K, [[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]])


def read_tum_list(path: Path) -> list[tuple[float, str]]:
    rows = [line.split() for line in path.read_text().splitlines() if line and not line.startswith("#")]
    return [(float(r[0]), r[1]) for r in rows]


def expected_tum_pose(gt: np.ndarray, t: float, gap: float = 0.02) -> np.ndarray:
    """Pose at t from ground-truth rows (M,8) using scipy's Slerp (or the nearest sample)."""
    before, after = gt[gt[:, 0] <= t], gt[gt[:, 0] > t]
    T = np.eye(4)
    if len(before) and len(after) and t - before[-1, 0] <= gap and after[0, 0] - t <= gap:
        a, b = before[-1], after[0]
        w = (t - a[0]) / (b[0] - a[0])
        T[:3, :3] = Slerp([0.0, 1.0], Rotation.from_quat([a[4:], b[4:]]))([w]).as_matrix()[0]
        T[:3, 3] = (1 - w) * a[1:4] + w * b[1:4]
    else:
        row = gt[np.argmin(np.abs(gt[:, 0] - t))]
        T[:3, :3], T[:3, 3] = Rotation.from_quat(row[4:]).as_matrix(), row[1:4]
    return T


def test_tum_equals_files(tum: list[RgbdFrame]) -> None:
    root = dataset("tum_fr1_xyz_10")
    depth_rows, rgb_rows = read_tum_list(root / "depth.txt"), read_tum_list(root / "rgb.txt")
    gt = np.loadtxt(root / "groundtruth.txt")
    assert [f.index for f in tum] == list(range(10))
    for f, (t, depth_name), (_, rgb_name) in zip(tum, depth_rows, rgb_rows, strict=True):
        assert f.timestamp == t
        np.testing.assert_allclose(f.depth_m, raw_depth_m(root / depth_name, 1 / 5000), atol=1e-6)
        np.testing.assert_array_equal(f.rgb, cv2.imread(str(root / rgb_name))[..., ::-1])  # 12 ms before
        np.testing.assert_allclose(f.T_world_camera, expected_tum_pose(gt, t), atol=1e-9)
        np.testing.assert_allclose(f.K, [[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1]])


def test_redkitchen_stride_max_frames_downscale() -> None:
    root = dataset("redkitchen_50")
    src = SevenScenesSource(SourceConfig(path=str(root), stride=5, max_frames=3, downscale=2))
    frames = list(src)
    assert len(src) == 3 and [f.index for f in frames] == [0, 5, 10]
    assert frames[2].timestamp == pytest.approx(18 / 30.0)
    assert frames[0].depth_m.shape == (240, 320) and frames[0].rgb.shape == (240, 320, 3)
    np.testing.assert_allclose(frames[0].K, [[292.5, 0, 159.75], [0, 292.5, 119.75], [0, 0, 1]])
    full = raw_depth_m(root / "frame-000013.depth.png", 1e-3, 65535)
    blocks = np.stack([full[0::2, 0::2], full[0::2, 1::2], full[1::2, 0::2], full[1::2, 1::2]])  # (4,240,320)
    agree = (blocks.min(0) > 0) & (blocks.max(0) - blocks.min(0) <= 0.05 * blocks.min(0))
    got = frames[1].depth_m
    np.testing.assert_allclose(got[agree], blocks.mean(0)[agree], rtol=1e-5)
    assert (got[~agree] == 0).all() and agree.mean() > 0.8  # only edges and holes are dropped


def test_real_sequence_with_broken_frames(tmp_path: Path) -> None:
    """Linked real frames, one depth replaced by garbage and one pose by NaN: both skipped, named."""
    root = dataset("redkitchen_50")
    for p in [*root.glob("frame-00001[0-3].*"), root / "camera-intrinsics.txt"]:
        (tmp_path / p.name).symlink_to(p)
    (tmp_path / "frame-000011.depth.png").unlink()
    (tmp_path / "frame-000011.depth.png").write_bytes(b"garbage")
    (tmp_path / "frame-000012.pose.txt").unlink()
    (tmp_path / "frame-000012.pose.txt").write_text("nan " * 16)
    src = SevenScenesSource(SourceConfig(path=str(tmp_path)))
    assert [f.index for f in src] == [0, 3]
    assert len(src.skipped) == 2
    assert "frame-000011.depth.png" in src.skipped[0].reason and "decoded" in src.skipped[0].reason
    assert "frame-000012.pose.txt" in src.skipped[1].reason and "NaN" in src.skipped[1].reason


@pytest.mark.parametrize(("name", "a", "b"), [("redkitchen", 0, 5), ("redkitchen", 0, 20), ("tum", 0, 5)])
def test_nearby_frames_agree_in_world(name: str, a: int, b: int, request: pytest.FixtureRequest) -> None:
    """Measured: 4-7 mm median and 82-95 % of the points; inverted poses give > 2 cm."""
    frames: list[RgbdFrame] = request.getfixturevalue(name)
    median_m, share = agreement(frames[a], frames[b])
    assert median_m < 0.015 and share > 0.7, (median_m, share)
