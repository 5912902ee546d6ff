"""RosbagSource on real bag files written by the rosbags writers (ROS 1, ROS 2 sqlite3, ROS 2 mcap):
frames compared one by one with what was written (pixels exact for lossless encodings, depth in
metres, poses to 1e-6), every message encoding, pose sources, intrinsics sources and the errors."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from h2viz.config import IntrinsicsConfig, SourceConfig, apply_overrides, load_config
from h2viz.errors import SourceError
from h2viz.sources.base import detect_format, make_source
from h2viz.sources.rosbag import RosbagSource, bag_info
from h2viz.types import RgbdFrame
from tests.sources.rosbag.bagwriter import (
    KINDS,
    BagBuilder,
    BagOptions,
    Frame,
    body_offset,
    look_along_z,
    storage_file,
    synthetic_frames,
    write_bag,
)

FRAMES, K = synthetic_frames()
DELAY_NS = BagOptions().depth_delay_ns


def make(tmp_path: Path, kind: str, opt: BagOptions | None = None, frames: list[Frame] = FRAMES) -> Path:
    return write_bag(tmp_path / ("b.bag" if kind == "ros1" else "b"), kind, frames, K, opt)


def open_source(path: Path, **rosbag: object) -> RosbagSource:
    cfg = SourceConfig(format="rosbag", path=str(path))
    for key, value in rosbag.items():
        if key == "intrinsics":
            cfg.intrinsics = value  # type: ignore[assignment]
        else:
            setattr(cfg.rosbag, key, value)
    return RosbagSource(cfg)


def check_frames(
    got: list[RgbdFrame], want: list[Frame], rgb_exact: bool = True, depth_atol: float = 1e-6
) -> None:
    assert len(got) == len(want)
    for i, (g, w) in enumerate(zip(got, want, strict=True)):
        assert g.index == i
        assert g.timestamp == pytest.approx((w.stamp_ns + DELAY_NS) * 1e-9, abs=1e-9)
        if rgb_exact:
            np.testing.assert_array_equal(g.rgb, w.rgb)
        valid = w.depth_m > 0
        np.testing.assert_allclose(g.depth_m[valid], w.depth_m[valid], atol=depth_atol, rtol=0)
        assert np.all(g.depth_m[~valid] == 0)
        np.testing.assert_allclose(g.T_world_camera, w.T_world_camera, atol=1e-6)
        np.testing.assert_allclose(g.K, K, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_each_bag_kind_reads_every_frame_exactly(tmp_path: Path, kind: str) -> None:
    path = make(tmp_path, kind)
    assert detect_format(path) == "rosbag"
    src = make_source(SourceConfig(path=str(path)))
    assert isinstance(src, RosbagSource) and len(src) == len(FRAMES)
    frames = list(src)
    check_frames(frames, FRAMES)
    assert src.skipped == [] and src.dropped == 0
    known = [src.timestamp(position, key) for position, key in src.selected()]  # without loading
    assert known == pytest.approx([f.timestamp for f in frames], abs=1e-9)
    # random access through load() gives the same frames as the streaming pass
    position, key = src.selected()[7]
    frame = src.get(position, key)
    assert frame is not None
    np.testing.assert_array_equal(frame.rgb, FRAMES[7].rgb)
    np.testing.assert_allclose(frame.T_world_camera, FRAMES[7].T_world_camera, atol=1e-6)


@pytest.mark.parametrize("kind", ["sqlite3", "mcap"])
def test_ros2_storage_file_is_readable_on_its_own(tmp_path: Path, kind: str) -> None:
    db = storage_file(make(tmp_path, kind))
    assert RosbagSource.looks_like(db) and detect_format(db) == "rosbag"
    check_frames(list(open_source(db)), FRAMES)


def test_looks_like(tmp_path: Path) -> None:
    (tmp_path / "folder").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    assert not RosbagSource.looks_like(tmp_path / "folder")
    assert not RosbagSource.looks_like(tmp_path / "notes.txt")
    (tmp_path / "folder" / "metadata.yaml").write_text("x")
    assert RosbagSource.looks_like(tmp_path / "folder")


@pytest.mark.parametrize(
    ("kind", "rgb", "padding", "bigendian"),
    [
        ("ros1", "bgr8", 0, False),
        ("sqlite3", "rgba8", 6, False),
        ("mcap", "bgra8", 0, True),
        ("ros1", "png", 0, False),
        ("mcap", "rgb8", 5, True),
    ],
)
def test_colour_encodings_and_row_padding(
    tmp_path: Path, kind: str, rgb: str, padding: int, bigendian: bool
) -> None:
    opt = BagOptions(rgb=rgb, row_padding=padding, bigendian=bigendian)
    src = open_source(make(tmp_path, kind, opt))
    assert src.topics.rgb.endswith("/compressed") == (rgb == "png")
    check_frames(list(src), FRAMES)


def test_mono8_colour_is_grey(tmp_path: Path) -> None:
    frames = list(open_source(make(tmp_path, "ros1", BagOptions(rgb="mono8", extra_topics=False))))
    for g, w in zip(frames, FRAMES, strict=True):
        np.testing.assert_array_equal(g.rgb, np.repeat(w.rgb[..., :1], 3, axis=2))


def test_jpeg_colour_within_tolerance(tmp_path: Path) -> None:
    frames = list(open_source(make(tmp_path, "sqlite3", BagOptions(rgb="jpeg"))))
    check_frames(frames, FRAMES, rgb_exact=False)
    for g, w in zip(frames, FRAMES, strict=True):
        err = np.abs(g.rgb.astype(np.int16) - w.rgb.astype(np.int16))
        assert (
            err.mean() < 4.0 and np.median(err) <= 3
        )  # jpeg loss; a channel swap gives ~17, a 1-px shift ~10


@pytest.mark.parametrize(
    ("kind", "depth", "bigendian", "atol"),
    [
        ("ros1", "32FC1", False, 1e-6),
        ("sqlite3", "32FC1", True, 1e-6),
        ("mcap", "16UC1", True, 1e-6),
        ("ros1", "cd16", False, 1e-6),
        ("mcap", "cd32", False, 2e-3),  # compressedDepth 32FC1 quantises inverse depth
    ],
)
def test_depth_encodings(tmp_path: Path, kind: str, depth: str, bigendian: bool, atol: float) -> None:
    src = open_source(make(tmp_path, kind, BagOptions(depth=depth, bigendian=bigendian)))
    assert ("compressedDepth" in src.topics.depth) == depth.startswith("cd")
    check_frames(list(src), FRAMES, depth_atol=atol)


def test_16uc1_depth_scale(tmp_path: Path) -> None:
    frames = list(open_source(make(tmp_path, "ros1"), depth_scale=0.0005))
    for g, w in zip(frames, FRAMES, strict=True):
        valid = w.depth_m > 0
        np.testing.assert_allclose(g.depth_m[valid], w.depth_m[valid] / 2, atol=1e-6)


def test_tf_poses_through_a_static_body_camera_link(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    R_body_camera = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical axes in a body
    T_body_camera = body_offset(R_body_camera @ look_along_z(0, 0, 0.4)[:3, :3], 0.15)
    opt = BagOptions(poses="tf", body_offset=T_body_camera)
    with caplog.at_level(logging.INFO, logger="h2viz.sources.rosbag"):
        src = open_source(make(tmp_path, "mcap", opt))
    assert src.topics.tf and not src.topics.pose
    assert any("/tf" in r.getMessage() for r in caplog.records)
    check_frames(list(src), FRAMES)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="h2viz.sources.rosbag"):
        check_frames(list(open_source(src.bag.path, world_frame="map")), FRAMES)
    assert "world frame 'map'" in caplog.text and "root 'world'" in caplog.text
    with pytest.raises(
        SourceError, match=r"frame 'nope' is not in /tf.*base_link.*source\.rosbag\.camera_frame"
    ):
        open_source(src.bag.path, camera_frame="nope")


@pytest.mark.parametrize(("kind", "poses"), [("ros1", "odom"), ("sqlite3", "odom"), ("mcap", "transform")])
def test_body_poses_with_configured_or_static_camera_offset(tmp_path: Path, kind: str, poses: str) -> None:
    T_body_camera = body_offset(look_along_z(0, 0, -0.3)[:3, :3], -0.2)
    path = make(tmp_path, kind, BagOptions(poses=poses, body_offset=T_body_camera))
    assert open_source(path).topics.pose == ("/odom" if poses == "odom" else "/vicon/rig")
    # camera offset from /tf_static, found from the odometry's child frame
    check_frames(list(open_source(path)), FRAMES)
    # camera offset from the configuration (T_body_camera wins over /tf_static)
    check_frames(
        list(open_source(path, body_frame="base_link", T_body_camera=list(T_body_camera.reshape(-1)))), FRAMES
    )
    wrong = list(open_source(path, T_body_camera=list(np.eye(4).reshape(-1))))
    assert np.abs(wrong[0].T_world_camera - FRAMES[0].T_world_camera).max() > 0.1


def test_missing_camera_info_uses_configured_intrinsics_or_says_how(tmp_path: Path) -> None:
    path = make(tmp_path, "ros1", BagOptions(camera_info=False))
    with pytest.raises(SourceError, match=r"source\.intrinsics\.fx="):
        open_source(path)
    ic = IntrinsicsConfig(fx=150.0, fy=151.0, cx=80.0, cy=60.0)
    frames = list(open_source(path, intrinsics=ic))
    np.testing.assert_allclose(frames[0].K, [[150, 0, 80], [0, 151, 60], [0, 0, 1]])
    assert len(frames) == len(FRAMES)
    assert "no CameraInfo" in bag_info(path, SourceConfig().rosbag)


def test_camera_info_size_is_checked_against_the_images(tmp_path: Path) -> None:
    half = np.array([[0, 0, 0.5], [0, 0, 0.5]])
    K_full = K.copy()
    K_full[:2] = (K[:2] + half) * 2 - half  # the same camera calibrated at 320x240
    scaled = write_bag(tmp_path / "a", "mcap", FRAMES[:2], K_full, BagOptions(info_size=(320, 240)))
    np.testing.assert_allclose(open_source(scaled).K, K, atol=1e-9)
    odd = write_bag(tmp_path / "b", "mcap", FRAMES[:2], K, BagOptions(info_size=(200, 120)))
    with pytest.raises(SourceError, match="/camera/depth/camera_info.*200x120.*160x120"):
        open_source(odd)


def test_topic_overrides_from_config_file_and_command_line(tmp_path: Path) -> None:
    path = make(tmp_path, "sqlite3")
    cfg = apply_overrides(
        load_config(), [f"source.path={path}", "source.rosbag.rgb_topic=/camera/infra1/image_rect_raw"]
    )
    frames = list(make_source(cfg.source))
    np.testing.assert_array_equal(frames[3].rgb, np.repeat(FRAMES[3].rgb[..., 1:2], 3, axis=2))
    yaml_file = tmp_path / "bag.yaml"
    yaml_file.write_text("source:\n  rosbag:\n    depth_topic: /nope\n")
    cfg = load_config([yaml_file], [f"source.path={path}"])
    with pytest.raises(SourceError, match=r"'/nope' is not in the bag.*source\.rosbag\.depth_topic"):
        make_source(cfg.source)


def test_frames_without_pose_or_colour_are_skipped_and_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    stamps = [f.stamp_ns for f in FRAMES]
    # poses only around frames 0-5 (every 10 ms), then one far sample: frames 6-9 lie in a 200 ms gap
    times = list(range(stamps[0] - 5_000_000, stamps[5] + 15_000_000, 10_000_000)) + [stamps[9] + 200_000_000]
    path = make(tmp_path, "ros1", BagOptions(pose_times_ns=times))
    with caplog.at_level(logging.WARNING):
        src = open_source(path, max_pose_gap_s=0.1)
    check_frames(list(src), FRAMES[:6])
    assert [s.reason for s in src.skipped] == ["no pose at this time"] * 4
    assert "max_pose_gap_s" in caplog.text
    assert len(list(open_source(path, max_pose_gap_s=1.0))) == 10  # interpolated across the gap
    # colour 40 ms away from depth is beyond max_time_gap_s = 0.03
    slow, _ = synthetic_frames(rate_hz=10.0)  # 100 ms apart: depth 40 ms after colour has no closer one
    far = make(tmp_path / "far", "mcap", BagOptions(depth_delay_ns=40_000_000), frames=slow)
    src = open_source(far)
    assert len(src) == 0 and len(src.skipped) == 10 and "no colour image within" in src.skipped[0].reason
    assert len(open_source(far, max_time_gap_s=0.05)) == 10


def test_missing_streams_are_errors_naming_the_option(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match=r"no poses.*source\.rosbag\.pose_topic"):
        open_source(make(tmp_path / "a", "ros1", BagOptions(poses="none")))
    path = make(tmp_path / "b", "ros1", BagOptions(extra_topics=False))
    with pytest.raises(
        SourceError, match=r"pose topic '/camera/color/image_raw' is of type sensor_msgs/msg/Image"
    ):
        open_source(path, pose_topic="/camera/color/image_raw")
    with pytest.raises(SourceError, match=r"not a depth encoding.*source\.rosbag\.depth_topic"):
        open_source(path, depth_topic="/camera/color/image_raw", rgb_topic="/camera/color/image_raw")


def test_bag_info_lists_topics_and_the_choice(tmp_path: Path) -> None:
    path = make(tmp_path, "mcap", BagOptions(rgb="png"))
    report = bag_info(path, SourceConfig().rosbag)
    lines = report.splitlines()
    assert "ROS 2 bag" in lines[0] and "60 messages" in lines[0]
    duration_s = (
        FRAMES[-1].stamp_ns + DELAY_NS - (FRAMES[0].stamp_ns - 5_000_000)
    ) * 1e-9  # first pose to last depth
    row = next(x for x in lines if x.strip().startswith("/camera/depth/image_rect_raw "))
    assert row.split()[1:] == ["10", f"{9 / duration_s:.2f}", "sensor_msgs/msg/Image"]
    assert any("/camera_pose" in x and "20" in x and "PoseStamped" in x for x in lines)
    used = report.split("h2viz would use:")[1]
    assert "depth: /camera/depth/image_rect_raw (16uc1)" in used
    assert "colour: /camera/color/image_raw/compressed" in used
    assert "intrinsics: /camera/depth/camera_info" in used and "poses: /camera_pose" in used


def test_opening_reads_stamps_without_decoding_images(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from h2viz.sources.rosbag import bag_file

    decoded: list[str] = []
    original = bag_file.BagFile.decode

    def counting(self: bag_file.BagFile, raw: bag_file.RawMessage) -> object:
        decoded.append(raw.topic)
        return original(self, raw)

    monkeypatch.setattr(bag_file.BagFile, "decode", counting)
    src = open_source(make(tmp_path, "ros1"))
    images = [t for t in decoded if "image" in t]
    assert len(src) == 10 and len(images) <= 6  # the first message of each image topic, a few times at most
    decoded.clear()
    assert len(list(src)) == 10
    assert sorted(decoded) == sorted([src.topics.depth] * 10 + [src.topics.rgb] * 10)  # each image once


def test_a_corrupt_message_skips_its_frame_only(tmp_path: Path) -> None:
    src = open_source(make(tmp_path, "sqlite3", BagOptions(corrupt_depth_at=4)))
    frames = list(src)
    check_frames(frames[:4], FRAMES[:4])
    assert [f.index for f in frames] == [0, 1, 2, 3, 5, 6, 7, 8, 9]
    (skip,) = src.skipped
    assert "/camera/depth/image_rect_raw" in skip.reason and "too few" in skip.reason
    assert skip.key == f"depth@{(FRAMES[4].stamp_ns + DELAY_NS) * 1e-9:.6f}s"


def test_stride_max_frames_and_downscale_apply(tmp_path: Path) -> None:
    path = make(tmp_path, "mcap")
    cfg = SourceConfig(format="rosbag", path=str(path), stride=3, max_frames=3, downscale=2)
    src = RosbagSource(cfg)
    frames = list(src)
    assert [f.index for f in frames] == [0, 3, 6]
    assert frames[1].depth_m.shape == (60, 80) and frames[1].rgb.shape == (60, 80, 3)
    np.testing.assert_allclose(frames[1].T_world_camera, FRAMES[3].T_world_camera, atol=1e-6)
    full = list(open_source(path))[3]  # the streamed frame is the base post-processing of the full one
    shrunk = src.postprocess(full)
    np.testing.assert_array_equal(frames[1].depth_m, shrunk.depth_m)
    np.testing.assert_array_equal(frames[1].rgb, shrunk.rgb)
    np.testing.assert_allclose(frames[1].K, shrunk.K)
    assert frames[1].K[0, 0] == pytest.approx(K[0, 0] / 2)


def test_discovery_prefers_registered_depth_raw_colour_and_the_matching_camera_info(tmp_path: Path) -> None:
    opt, f = BagOptions(), FRAMES[0]
    depth_mm = np.round(f.depth_m * 1000).astype(np.uint16)
    with BagBuilder(tmp_path / "rs.bag", "ros1", opt) as bag:
        for topic, px, enc in [
            ("/camera/color/image_raw", f.rgb, "rgb8"),
            ("/camera/infra1/image_rect_raw", f.rgb[..., 0].copy(), "mono8"),
            ("/camera/depth/image_rect_raw", depth_mm, "16UC1"),
            ("/camera/aligned_depth_to_color/image_raw", depth_mm, "16UC1"),
            ("/camera/depth/color/points_depth_vis", f.rgb, "rgb8"),  # a colourised depth view
        ]:
            bag.write(topic, bag.image(f.stamp_ns, "cam", px, enc, opt), f.stamp_ns)
        for ns in ("/camera/color", "/camera/depth", "/camera/aligned_depth_to_color"):
            bag.write(f"{ns}/camera_info", bag.camera_info(f.stamp_ns, "cam", K, (160, 120)), f.stamp_ns)
        pose = bag.msg(
            "geometry_msgs/msg/PoseStamped", header=bag.header(f.stamp_ns, "map"), pose=bag.pose(np.eye(4))
        )
        bag.write("/orb_slam/camera_pose", pose, f.stamp_ns)
    report = bag_info(tmp_path / "rs.bag", SourceConfig().rosbag)
    assert "depth: /camera/aligned_depth_to_color/image_raw (16uc1)" in report
    assert "colour: /camera/color/image_raw (rgb8)" in report
    assert "intrinsics: /camera/aligned_depth_to_color/camera_info" in report
    assert "poses: /orb_slam/camera_pose (PoseStamped)" in report
