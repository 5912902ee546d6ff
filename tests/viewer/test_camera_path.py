"""Camera paths (spline through keyframes, JSON round trip, clear errors) and fly-through MP4s rendered from the real
Mapper (tiny configuration, trained on the analytic room): frame count and size as requested, and the first frame
is a direct render of the first keyframe's camera."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from h2viz.viewer.camera_path import CameraPath, CameraPathError, load_path, trajectory_path
from h2viz.viewer.shapes import to_rgb8, wxyz_position
from h2viz.viewer.video import BACKDROP, read_video, render_path_video
from tests.viewer.fakes import BoxRoomSource, intrinsics, room_pose, tiny_mapping_config


def _path(n_keyframes: int, **kw: object) -> CameraPath:
    path = CameraPath(**kw)  # type: ignore[arg-type]
    for i in range(n_keyframes):
        wxyz, position = wxyz_position(room_pose(2 * i, 12))
        path.add(wxyz, position)
    return path


def test_path_passes_through_its_keyframes_and_moves_smoothly() -> None:
    path = _path(4, duration_s=3.0, fps=10)
    poses = path.poses(31)  # keyframes at frames 0, 10, 20, 30
    for i, frame in enumerate((0, 10, 20, 30)):
        np.testing.assert_allclose(poses[frame], room_pose(2 * i, 12), atol=1e-9)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 3.0 * np.median(steps)  # no jumps between keyframes
    speed_change = np.abs(np.diff(steps)).max()
    assert speed_change < 0.25 * steps.mean()  # the velocity is continuous across keyframes
    angles = Rotation.from_matrix(poses[:-1, :3, :3]).inv() * Rotation.from_matrix(poses[1:, :3, :3])
    assert angles.magnitude().max() < 3.0 * np.median(angles.magnitude())


def test_two_keyframes_meet_halfway_at_the_mean_position_and_rotation() -> None:
    a, b = np.eye(4), np.eye(4)
    b[:3, :3] = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    b[:3, 3] = [2.0, 0.0, 0.0]
    path = CameraPath()
    for T in (a, b):
        path.add(*wxyz_position(T))
    mid = path.poses(3)[1]
    np.testing.assert_allclose(mid[:3, 3], [1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(Rotation.from_matrix(mid[:3, :3]).as_euler("xyz", degrees=True), [0, 45, 0], atol=1e-6)


def test_reorder_save_and_load(tmp_path: Path) -> None:
    path = _path(3, duration_s=2.0, width=320, height=240)
    first = path.keyframes[0]
    path.move(0, +5)  # clamped to the end
    assert path.keyframes[-1] is first
    loaded = load_path(path.save(tmp_path / "p.json"))
    assert loaded == path


def test_bad_paths_name_the_file_and_the_problem(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(CameraPathError, match="bad.json: cannot read"):
        load_path(bad)
    bad.write_text(json.dumps({"frames": []}))
    with pytest.raises(CameraPathError, match="bad.json: not a camera path"):
        load_path(bad)
    odd = _path(2, width=321)
    with pytest.raises(CameraPathError, match="must be even"):
        load_path(odd.save(tmp_path / "odd.json"))
    with pytest.raises(CameraPathError, match="no keyframes"):
        CameraPath().poses()


def test_trajectory_preset_flies_along_the_recorded_poses() -> None:
    traj = np.array([room_pose(i, 100) for i in range(100)])
    path = trajectory_path(traj, intrinsics(64, 48), 48)
    poses = path.poses()
    np.testing.assert_allclose(poses[0], traj[0], atol=1e-9)
    np.testing.assert_allclose(poses[-1], traj[-1], atol=1e-9)
    assert len(path.keyframes) <= 24 and path.duration_s == pytest.approx(10.0)


@pytest.fixture(scope="module")
def mapper():  # noqa: ANN201 (torch-backed)
    from h2viz.mapping.mapper import Mapper

    m = Mapper(tiny_mapping_config())
    for frame in BoxRoomSource(n=6, width=64, height=48):
        m.integrate(frame)
    return m


def test_video_has_the_requested_frames_and_size_and_starts_at_the_first_camera(mapper, tmp_path: Path) -> None:  # noqa: ANN001
    path = _path(3, duration_s=0.5, fps=24, width=96, height=64, fov_deg=60.0)
    done: list[int] = []
    out = render_path_video(
        lambda K, T, h, w: mapper.render(K, T, h, w, "rgb"), path, tmp_path / "fly.mp4", lambda d, _n: done.append(d)
    )
    frames = read_video(out)
    assert len(frames) == path.n_frames == 12 and done == list(range(1, 13))
    assert frames[0].shape == (64, 96, 3)
    direct = to_rgb8(mapper.render(path.K(), room_pose(0, 12), 64, 96, "rgb"), "rgb", BACKDROP).astype(np.float64)
    mse = np.mean((frames[0].astype(np.float64) - direct) ** 2)
    assert 10 * np.log10(255.0**2 / max(mse, 1e-9)) > 30.0  # H.264 at crf 18 keeps the render
    other = to_rgb8(mapper.render(path.K(), room_pose(4, 12), 64, 96, "rgb"), "rgb", BACKDROP).astype(np.float64)
    assert np.mean((frames[0] - other) ** 2) > 4 * mse  # ... and it is not just any view of the room
