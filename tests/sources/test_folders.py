"""Dataset-folder sources on small datasets written in each layout: values read back exactly, bad
frames skipped and counted with messages naming the file, whole-source problems raised as SourceError."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from h2viz.config import IntrinsicsConfig, SourceConfig, TumConfig
from h2viz.errors import SourceError
from h2viz.sources.base import FrameSource
from h2viz.sources.replica import ReplicaSource
from h2viz.sources.scannet import ScanNetSource
from h2viz.sources.sevenscenes import SevenScenesSource
from h2viz.sources.tum import PRESETS, TumSource
from tests.sources.fixtures import (
    K_FIXTURE,
    Fixture,
    fixture_rgb,
    tum_trajectory,
    write_color,
    write_replica,
    write_scannet,
    write_sevenscenes,
    write_tum,
)

FIXTURE_INTRINSICS = IntrinsicsConfig(fx=50.0, fy=52.0, cx=31.5, cy=23.5)


def check_source(src: FrameSource, fx: Fixture, rgb_tol: float, pose_tol: float = 1e-9) -> None:
    """Every good frame equals the fixture's truth; every bad one is skipped naming its file."""
    frames = list(src)
    assert [f.index for f in frames] == fx.good()
    for f in frames:
        i = f.index
        np.testing.assert_allclose(f.T_world_camera, fx.poses[i], atol=pose_tol)
        np.testing.assert_allclose(f.depth_m, fx.depth_m[i], rtol=1e-6, atol=1e-7)
        assert f.depth_m.dtype == np.float32 and f.rgb.dtype == np.uint8
        assert np.abs(f.rgb.astype(float) - fx.rgb[i]).mean() <= rgb_tol
        assert f.timestamp == pytest.approx(fx.timestamps[i], abs=1e-9)
    known = {position: src.timestamp(position, key) for position, key in src.selected()}  # without loading
    assert [known[f.index] for f in frames] == pytest.approx([f.timestamp for f in frames], abs=1e-9)
    assert len(src.skipped) == len(fx.bad)
    for (pos, name), skipped in zip(sorted(fx.bad.items()), src.skipped, strict=True):
        assert name in skipped.reason, (pos, skipped)


# ------------------------------------------------------------------------------------------- Replica


def test_replica_reads_frames_and_skips_bad_ones(tmp_path: Path) -> None:
    fx = write_replica(tmp_path / "room0")
    src = ReplicaSource(SourceConfig(path=str(fx.root), intrinsics=FIXTURE_INTRINSICS))
    assert len(src) == 6
    check_source(src, fx, rgb_tol=3.0)
    assert np.allclose(next(iter(src)).K, K_FIXTURE)


def test_replica_short_trajectory_uses_matching_frames(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    fx = write_replica(tmp_path / "room0", broken=False)
    lines = (fx.root / "traj.txt").read_text().splitlines()
    (fx.root / "traj.txt").write_text("\n".join(lines[:4]) + "\n")
    with caplog.at_level(logging.WARNING, logger="h2viz.sources"):
        src = ReplicaSource(SourceConfig(path=str(fx.root), intrinsics=FIXTURE_INTRINSICS))
    assert "4 poses" in caplog.text and "traj.txt" in caplog.text
    frames = list(src)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    np.testing.assert_allclose(frames[3].T_world_camera, fx.poses[3], atol=1e-12)


def test_replica_whole_source_errors(tmp_path: Path) -> None:
    fx = write_replica(tmp_path / "room0", broken=False)
    with pytest.raises(SourceError, match="1200x680"):  # 64x48 images need explicit intrinsics
        ReplicaSource(SourceConfig(path=str(fx.root)))
    (fx.root / "traj.txt").unlink()
    with pytest.raises(SourceError, match="traj.txt"):
        ReplicaSource(SourceConfig(path=str(fx.root), intrinsics=FIXTURE_INTRINSICS))
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match="no frame"):
        ReplicaSource(SourceConfig(path=str(tmp_path / "empty")))


# ------------------------------------------------------------------------------------------- ScanNet


def test_scannet_numeric_order_resized_colour_and_skips(tmp_path: Path) -> None:
    fx = write_scannet(tmp_path / "scene0000_00")
    src = ScanNetSource(SourceConfig(path=str(fx.root)))
    assert list(src.keys()) == [0, 5, 10, 15, 20, 100]
    check_source(src, fx, rgb_tol=3.0)
    frame = next(iter(src))
    assert frame.rgb.shape == (48, 64, 3)
    np.testing.assert_allclose(frame.K, K_FIXTURE)
    assert "inf/NaN" in src.skipped[0].reason


def test_scannet_intrinsics_file_or_override(tmp_path: Path) -> None:
    fx = write_scannet(tmp_path / "scene", broken=False)
    (fx.root / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(SourceError, match="intrinsic_depth.txt"):
        ScanNetSource(SourceConfig(path=str(fx.root)))
    override = IntrinsicsConfig(fx=70.0, fy=71.0, cx=30.0, cy=20.0)
    frame = next(iter(ScanNetSource(SourceConfig(path=str(fx.root), intrinsics=override))))
    np.testing.assert_allclose(frame.K, [[70, 0, 30], [0, 71, 20], [0, 0, 1]])


# ---------------------------------------------------------------------------------------------- TUM


def test_tum_association_interpolation_and_skips(tmp_path: Path) -> None:
    fx = write_tum(tmp_path / "rgbd_dataset_freiburg2_desk")
    src = TumSource(SourceConfig(path=str(fx.root)))
    fx.K = np.array([[520.9, 0, 325.1], [0, 521.0, 249.7], [0, 0, 1]])
    check_source(src, fx, rgb_tol=0.0, pose_tol=2e-6)
    frames = {f.index: f for f in src}
    np.testing.assert_allclose(frames[0].K, fx.K)
    # frame 3 takes the nearest sample (2 ms before), which differs from the pose at its own time
    assert not np.allclose(
        frames[3].T_world_camera, tum_trajectory(fx.timestamps[3] - 1305031100.0), atol=1e-3
    )
    assert "no pose" in src.skipped[0].reason and "no colour" not in src.skipped[0].reason
    assert "colour" in src.skipped[1].reason


def test_tum_wider_gap_matches_more(tmp_path: Path) -> None:
    fx = write_tum(tmp_path / "fr1_seq")
    src = TumSource(SourceConfig(path=str(fx.root), tum=TumConfig(max_time_gap_s=0.05)))
    frames = {f.index: f for f in src}
    assert sorted(frames) == [0, 1, 2, 3, 4, 5]
    for i in (1, 3):  # both bracketing samples are now within the gap: interpolated to the frame's time
        expected = tum_trajectory(fx.timestamps[i] - 1305031100.0)
        np.testing.assert_allclose(frames[i].T_world_camera, expected, atol=2e-6)
    assert frames[5].rgb[0, 0, 2] == fixture_rgb(6)[0, 0, 2]  # colour of frame 6, 21 ms away


@pytest.mark.parametrize(
    ("name", "preset"), [("rgbd_dataset_freiburg3_office", "fr3"), ("tum_fr1_xyz", "fr1")]
)
def test_tum_preset_from_folder_name(tmp_path: Path, name: str, preset: str) -> None:
    fx = write_tum(tmp_path / name, n=2, broken=False)
    src = TumSource(SourceConfig(path=str(fx.root)))
    fx_, fy, cx, cy = PRESETS[preset]
    np.testing.assert_allclose(src.K, [[fx_, 0, cx], [0, fy, cy], [0, 0, 1]])


def test_tum_preset_fallback_explicit_and_override(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    fx = write_tum(tmp_path / "my_sequence", n=2, broken=False)
    with caplog.at_level(logging.WARNING, logger="h2viz.sources"):
        src = TumSource(SourceConfig(path=str(fx.root)))
    assert src.K[0, 0] == 517.3 and "fr1" in caplog.text
    src = TumSource(SourceConfig(path=str(fx.root), tum=TumConfig(preset="fr2")))
    assert src.K[0, 0] == 520.9
    src = TumSource(SourceConfig(path=str(fx.root), intrinsics=FIXTURE_INTRINSICS))
    np.testing.assert_allclose(next(iter(src)).K, K_FIXTURE)
    with pytest.raises(SourceError, match="preset"):
        TumSource(SourceConfig(path=str(fx.root), tum=TumConfig(preset="fr9")))


def test_tum_missing_groundtruth_or_bad_line(tmp_path: Path) -> None:
    fx = write_tum(tmp_path / "fr1_a", n=2, broken=False)
    gt = fx.root / "groundtruth.txt"
    gt.write_text(gt.read_text() + "1305031100.5 1 2 3\n")
    with pytest.raises(SourceError, match=r"groundtruth.txt line \d+"):
        TumSource(SourceConfig(path=str(fx.root)))
    gt.unlink()
    with pytest.raises(SourceError, match="groundtruth.txt"):
        TumSource(SourceConfig(path=str(fx.root)))


# ------------------------------------------------------------------------------------- 7-Scenes


def test_sevenscenes_reads_frames_and_skips_bad_ones(tmp_path: Path) -> None:
    fx = write_sevenscenes(tmp_path / "seq-01", first_id=3)
    src = SevenScenesSource(SourceConfig(path=str(fx.root)))
    assert list(src.keys()) == [3, 4, 5, 6, 7, 8]
    check_source(src, fx, rgb_tol=0.0)
    frame = next(iter(src))
    np.testing.assert_allclose(frame.K, K_FIXTURE)
    assert frame.depth_m[-1, -1] == 0.0  # 65535 = invalid


def test_sevenscenes_intrinsics_default_and_parent(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    fx = write_sevenscenes(tmp_path / "chess" / "seq-01", n=2, broken=False, intrinsics=False)
    with caplog.at_level(logging.WARNING, logger="h2viz.sources"):
        src = SevenScenesSource(SourceConfig(path=str(fx.root)))
    np.testing.assert_allclose(src.K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    assert "585" in caplog.text
    (tmp_path / "chess" / "camera-intrinsics.txt").write_text("60 0 30\n0 61 22\n0 0 1\n")  # 3DMatch layout
    src = SevenScenesSource(SourceConfig(path=str(fx.root)))
    np.testing.assert_allclose(src.K, [[60, 0, 30], [0, 61, 22], [0, 0, 1]])


def test_sevenscenes_colour_size_jpg_and_depth_scale(tmp_path: Path) -> None:
    fx = write_sevenscenes(tmp_path / "seq", n=3, broken=False)
    (fx.root / "frame-000000.color.png").unlink()
    write_color(fx.root / "frame-000000.color.jpg", np.repeat(np.repeat(fx.rgb[0], 2, 0), 2, 1))
    write_color(fx.root / "frame-000001.color.png", np.zeros((64, 64, 3), np.uint8))  # 1:1 onto 4:3 depth
    src = SevenScenesSource(SourceConfig(path=str(fx.root), depth_scale=0.0005))
    frames = list(src)
    assert [f.index for f in frames] == [0, 2]
    assert np.abs(frames[0].rgb.astype(float) - fx.rgb[0]).mean() < 3.0
    np.testing.assert_allclose(frames[1].depth_m, fx.depth_m[2] / 2, rtol=1e-6)
    assert "frame-000001.color.png" in src.skipped[0].reason and "64x64" in src.skipped[0].reason


def test_sevenscenes_downscale_stride_max_frames(tmp_path: Path) -> None:
    fx = write_sevenscenes(tmp_path / "seq", n=6, broken=False)
    src = SevenScenesSource(SourceConfig(path=str(fx.root), downscale=2, stride=2, max_frames=2))
    frames = list(src)
    assert len(src) == 2 and [f.index for f in frames] == [0, 2]
    assert frames[1].depth_m.shape == (24, 32) and frames[1].rgb.shape == (24, 32, 3)
    np.testing.assert_allclose(frames[1].K, [[25, 0, 15.5], [0, 26, 11.5], [0, 0, 1]])
    full = fx.depth_m[2]
    blocks = np.stack([full[0::2, 0::2], full[0::2, 1::2], full[1::2, 0::2], full[1::2, 1::2]])  # (4,24,32)
    whole = (blocks > 0).all(axis=0)
    expected = np.where(whole, blocks.mean(axis=0), 0.0)  # block centre = where K's principal point moved
    np.testing.assert_allclose(frames[1].depth_m, expected, rtol=1e-5)
    assert (frames[1].depth_m[~whole] == 0).all()
    expected_rgb = cv2.resize(fx.rgb[2], (32, 24), interpolation=cv2.INTER_AREA)
    assert np.abs(frames[1].rgb.astype(int) - expected_rgb).max() <= 1


def test_sevenscenes_empty_and_scene_level_folders(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(SourceError, match="no frame"):
        SevenScenesSource(SourceConfig(path=str(tmp_path / "empty")))
    write_sevenscenes(tmp_path / "heads" / "seq-02", n=1, broken=False)
    with pytest.raises(SourceError, match="seq-02"):
        SevenScenesSource(SourceConfig(path=str(tmp_path / "heads")))
    fx = write_sevenscenes(tmp_path / "nopose", n=2, broken=False)
    for p in fx.root.glob("*.pose.txt"):
        p.unlink()
    with pytest.raises(SourceError, match="pose"):
        SevenScenesSource(SourceConfig(path=str(fx.root)))
