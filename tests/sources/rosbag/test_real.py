"""The real TUM fr1/xyz frames (../shared/data, skipped when absent) written into ROS 1 and ROS 2 mcap bags
at full size and read back: every frame equals what TumSource reads from the folder (colour and depth
exact, the same intrinsics, poses interpolated at the depth stamps to 1e-6)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from h2viz.config import SourceConfig
from h2viz.sources.rosbag import RosbagSource
from h2viz.sources.tum import PRESETS, TumSource
from tests.conftest import shared_data
from tests.sources.rosbag.bagwriter import BagBuilder, BagOptions


def stamp_ns(text: str) -> int:
    sec, _, frac = text.partition(".")
    return int(sec) * 1_000_000_000 + int(frac.ljust(9, "0")[:9])


def rows(path: Path) -> list[list[str]]:
    return [
        line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")
    ]


def write_tum_bag(root: Path, path: Path, kind: str) -> Path:
    """Colour (rgb8), depth (16UC1, 1/5000 m), CameraInfo (fr1) and ground truth (PoseStamped) as recorded."""
    K = np.array([[517.3, 0.0, 318.6], [0.0, 516.5, 255.3], [0.0, 0.0, 1.0]])
    assert PRESETS["fr1"] == (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    opt = BagOptions()
    with BagBuilder(path, kind, opt) as bag:
        for t, name in rows(root / "rgb.txt"):
            rgb = cv2.cvtColor(cv2.imread(str(root / name), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            bag.write(
                "/camera/rgb/image_color",
                bag.image(stamp_ns(t), "rgb_optical", rgb, "rgb8", opt),
                stamp_ns(t),
            )
        for t, name in rows(root / "depth.txt"):
            depth = cv2.imread(str(root / name), cv2.IMREAD_UNCHANGED)
            assert depth.dtype == np.uint16
            bag.write(
                "/camera/depth/image", bag.image(stamp_ns(t), "rgb_optical", depth, "16UC1", opt), stamp_ns(t)
            )
            info = bag.camera_info(stamp_ns(t), "rgb_optical", K, (depth.shape[1], depth.shape[0]))
            bag.write("/camera/depth/camera_info", info, stamp_ns(t))
        for t, *values in rows(root / "groundtruth.txt"):
            T = np.eye(4)
            T[:3, 3] = [float(v) for v in values[:3]]
            T[:3, :3] = Rotation.from_quat([float(v) for v in values[3:7]]).as_matrix()
            msg = bag.msg(
                "geometry_msgs/msg/PoseStamped", header=bag.header(stamp_ns(t), "world"), pose=bag.pose(T)
            )
            bag.write("/mocap/pose", msg, stamp_ns(t))
    return path


@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_tum_frames_through_a_bag_equal_the_folder_source(tmp_path: Path, kind: str) -> None:
    root = shared_data("tum_fr1_xyz_10")
    if not root.is_dir():
        pytest.skip("real data tum_fr1_xyz_10 not found in ../shared/data")
    bag = write_tum_bag(root, tmp_path / ("tum.bag" if kind == "ros1" else "tum"), kind)
    cfg = SourceConfig(format="rosbag", path=str(bag))
    cfg.rosbag.depth_scale = 1.0 / 5000.0
    src = RosbagSource(cfg)
    assert (src.topics.rgb, src.topics.depth, src.topics.pose) == (
        "/camera/rgb/image_color", "/camera/depth/image", "/mocap/pose"
    )  # fmt: skip
    got = list(src)
    want = list(TumSource(SourceConfig(format="tum", path=str(root))))
    assert len(got) == len(want) == 10 and src.skipped == []
    for g, w in zip(got, want, strict=True):
        assert g.rgb.shape == (480, 640, 3)
        assert g.timestamp == pytest.approx(w.timestamp, abs=1e-6)
        np.testing.assert_array_equal(g.rgb, w.rgb)
        np.testing.assert_array_equal(g.depth_m, w.depth_m)
        np.testing.assert_allclose(g.K, w.K, atol=1e-9)
        np.testing.assert_allclose(g.T_world_camera, w.T_world_camera, atol=1e-6)
    travel = np.linalg.norm(got[-1].T_world_camera[:3, 3] - got[0].T_world_camera[:3, 3])
    assert travel > 0.05  # the poses are not all the same
