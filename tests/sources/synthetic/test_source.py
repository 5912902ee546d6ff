"""The built-in synthetic source: determinism, exact z-depth, agreement with its ground-truth mesh,
coverage of the room by the trajectory and the common FrameSource options."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from h2viz.config import SourceConfig, SyntheticConfig
from h2viz.geometry import backproject, look_at, project
from h2viz.sources.base import make_source
from h2viz.sources.synthetic.scene import build_scene
from h2viz.sources.synthetic.source import FPS, SyntheticSource, intrinsics

W, H = 160, 120


def make(seed: int = 0, **kw: object) -> SyntheticSource:
    common = {k: kw.pop(k) for k in list(kw) if k in ("stride", "max_frames")}
    synth = SyntheticConfig(seed=seed, width=W, height=H, prefetch=0)
    return SyntheticSource(SourceConfig(format="synthetic", synthetic=replace(synth, **kw), **common))


@pytest.fixture(scope="module")
def src() -> SyntheticSource:
    return make()


def distance_to_mesh(mesh: trimesh.Trimesh, points: np.ndarray, k: int = 64) -> np.ndarray:
    """Exact point-to-triangle distance (N,) over the k triangles with the nearest centroids."""
    _, cand = cKDTree(mesh.triangles_center).query(points, k=k)  # (N,k)
    tris = mesh.triangles[cand.ravel()]
    closest = trimesh.triangles.closest_point(tris, np.repeat(points, k, axis=0))
    return np.linalg.norm(closest - np.repeat(points, k, axis=0), axis=1).reshape(-1, k).min(axis=1)


def clear_floor_spot(mesh: trimesh.Trimesh, half_m: float) -> np.ndarray:
    """An (x, y) where a square of half size `half_m` is open floor all the way up (found with trimesh's
    own ray queries, independently of the source's renderer)."""
    for x in np.arange(-1.8, 1.81, 0.2):
        for y in np.arange(-1.4, 1.41, 0.2):
            gx, gy = np.meshgrid(np.linspace(-half_m, half_m, 31), np.linspace(-half_m, half_m, 31))
            origins = np.stack([x + gx.ravel(), y + gy.ravel(), np.full(gx.size, 2.5)], 1)
            tri = mesh.ray.intersects_first(origins, np.tile([0.0, 0.0, -1.0], (len(origins), 1)))
            if np.all(tri >= 0) and np.all(np.abs(mesh.triangles[tri][..., 2]) < 1e-9):
                return np.array([x, y])
    raise AssertionError("no open floor found")


def test_frames_have_the_documented_layout(src: SyntheticSource) -> None:
    three = make(n_frames=3)
    frames = list(three)
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.timestamp for f in frames] == pytest.approx([0.0, 1 / FPS, 2 / FPS])
    assert [three.timestamp(p, k) for p, k in three.selected()] == pytest.approx([0.0, 1 / FPS, 2 / FPS])
    f = frames[1]
    assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.uint8
    assert f.depth_m.shape == (H, W) and f.depth_m.dtype == np.float32
    assert f.K[0, 0] == f.K[1, 1] and f.K[0, 2] == (W - 1) / 2 and f.K[1, 2] == (H - 1) / 2
    assert f.K[0, 0] == pytest.approx((W / 2) / np.tan(np.radians(70.0) / 2))
    assert np.mean(f.depth_m > 0) > 0.9 and f.depth_m.max() < 7.0  # inside a 5 x 4 m room
    assert f.rgb.reshape(-1, 3).std(axis=0).min() > 15  # textured, not flat
    np.testing.assert_array_equal(f.T_world_camera, three.poses[1])


def test_same_seed_gives_identical_frames_with_or_without_prefetch() -> None:
    a = list(make(n_frames=12, prefetch=0, depth_noise_m=0.01))
    b = list(make(n_frames=12, prefetch=3, depth_noise_m=0.01))
    assert len(a) == len(b) == 12
    for fa, fb in zip(a, b, strict=True):
        np.testing.assert_array_equal(fa.rgb, fb.rgb)
        np.testing.assert_array_equal(fa.depth_m, fb.depth_m)
        np.testing.assert_array_equal(fa.T_world_camera, fb.T_world_camera)


def test_prefetch_renders_ahead_only_while_frames_are_read_in_order() -> None:
    source = make(n_frames=30, prefetch=2)
    rendered: list[int] = []
    render = source.render_frame
    source.render_frame = lambda index: rendered.append(index) or render(index)  # type: ignore[method-assign]
    try:
        source.load(0, 0)
        source.load(1, 1)
        assert set(source._pending) == {2, 3}  # read in order: the next two are rendered ahead
        source.load(20, 20)  # 2..19 passed over (real-time playback): nothing is rendered ahead
        assert not source._pending
        source.load(21, 21)  # in order again
        assert set(source._pending) == {22, 23}
        source.close()
        assert not set(rendered) & set(range(4, 20))
    finally:
        source.close()


def test_different_seed_gives_a_different_scene(src: SyntheticSource) -> None:
    other = make(seed=1)
    assert build_scene(0) is build_scene(0) and build_scene(1) is not build_scene(0)  # cached per seed
    m0, m1 = src.ground_truth_mesh(), other.ground_truth_mesh()
    assert len(m0.vertices) != len(m1.vertices) or not np.allclose(m0.vertices, m1.vertices)
    assert not np.allclose(src.poses, other.poses)
    T = look_at(np.array([1.2, 0.8, 1.5]), np.array([-0.5, -0.5, 0.4]))
    rgb0, depth0 = src.render_view(src.K, T, H, W)
    rgb1, depth1 = other.render_view(src.K, T, H, W)
    assert np.mean(np.any(rgb0 != rgb1, axis=2)) > 0.2 and np.abs(depth0 - depth1).max() > 0.05


def test_depth_is_z_depth_of_the_floor_seen_from_above(src: SyntheticSource) -> None:
    mesh = src.ground_truth_mesh()
    x, y = clear_floor_spot(mesh, 0.45)
    K = intrinsics(W, H, 60.0)
    for height_m, tilt_rad in ((0.35, 0.0), (0.3, 0.35)):  # straight down, then tilted
        eye = np.array([x, y, height_m])
        target = eye + [np.sin(tilt_rad), 0.0, -np.cos(tilt_rad)]
        T = look_at(eye, target, up=np.array([1.0, 0.0, 0.0]) if tilt_rad == 0 else np.array([0.0, 0.0, 1.0]))
        _, depth = src.render_view(K, T, H, W)
        rays = np.stack(
            np.meshgrid((np.arange(W) - K[0, 2]) / K[0, 0], (np.arange(H) - K[1, 2]) / K[1, 1]), -1
        )
        d_world = np.concatenate([rays, np.ones((H, W, 1))], -1) @ T[:3, :3].T  # (H,W,3), camera z = 1
        expected = -height_m / d_world[..., 2]  # the floor z = 0 meets eye + t d at this t = camera z
        assert expected.max() < 0.8  # every pixel sees the open floor patch
        np.testing.assert_allclose(depth, expected, atol=1e-4)


def test_backprojected_depth_lies_on_the_ground_truth_mesh(src: SyntheticSource) -> None:
    mesh = src.ground_truth_mesh()
    rng = np.random.default_rng(0)
    for index in (0, 137):
        f = src.get(index, index)
        assert f is not None
        pts = backproject(f.depth_m, f.K, f.T_world_camera)
        pts = pts[rng.choice(len(pts), 2000, replace=False)]
        assert distance_to_mesh(mesh, pts).max() < 1e-3


def test_two_frames_agree_where_they_overlap(src: SyntheticSource) -> None:
    a, b = src.get(40, 40), src.get(43, 43)
    assert a is not None and b is not None
    pts = backproject(a.depth_m, a.K, a.T_world_camera)  # (N,3) world points of frame a
    uv, z = project(pts, b.K, b.T_world_camera)
    u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = (z > 0) & (u0 >= 0) & (v0 >= 0) & (u0 < W - 1) & (v0 < H - 1)
    uv, z, u0, v0 = uv[ok], z[ok], u0[ok], v0[ok]
    quad = np.stack(
        [b.depth_m[v0, u0], b.depth_m[v0, u0 + 1], b.depth_m[v0 + 1, u0], b.depth_m[v0 + 1, u0 + 1]], 1
    )
    inv = 1.0 / np.where(quad > 0, quad, np.inf)  # inverse depth is affine in pixels on a plane
    planar = np.all(quad > 0, axis=1) & (np.abs(inv[:, 0] + inv[:, 3] - inv[:, 1] - inv[:, 2]) < 1e-5)
    planar &= np.ptp(quad, axis=1) < 0.1 * quad.min(axis=1)  # one plane, no depth edge inside
    fu, fv = (uv[:, 0] - u0)[:, None], (uv[:, 1] - v0)[:, None]
    w = np.concatenate([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], 1)
    z_b = 1.0 / np.sum(w * inv, axis=1)  # depth frame b sees where frame a's point lands
    err, hidden = (z - z_b)[planar], (z - z_b)[planar] > 0.01  # hidden: b sees something in front
    assert np.sum(np.abs(err) < 1e-3) > 5000
    assert np.mean((np.abs(err) < 1e-3) | hidden) > 0.98 and np.median(np.abs(err)) < 1e-4


def test_trajectory_sees_nearly_all_of_the_scene(src: SyntheticSource) -> None:
    mesh = src.ground_truth_mesh()
    pts, _ = trimesh.sample.sample_surface(mesh, 20000, seed=0)
    seen = np.zeros(len(pts), dtype=bool)
    lo, hi = src.cfg.depth_min_m, src.cfg.depth_max_m
    for T in src.poses[::5]:
        uv, z = project(pts, src.K, T)
        inside = (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)
        idx = np.flatnonzero(inside & (z > lo) & (z < hi) & ~seen)
        to_point = pts[idx] - T[:3, 3]  # ray from the camera that reaches the point at t = 1
        tri = mesh.ray.intersects_first(np.broadcast_to(T[:3, 3], to_point.shape), to_point)
        hit = tri >= 0
        n, corner = mesh.face_normals[tri[hit]], mesh.triangles[tri[hit], 0]
        t = np.einsum("ij,ij->i", corner - T[:3, 3], n) / np.einsum("ij,ij->i", to_point[hit], n)
        seen[idx[hit][t > 1 - 2e-3 / np.linalg.norm(to_point[hit], axis=1)]] = True  # first hit is the point
    assert seen.mean() > 0.95


def test_camera_stays_clear_of_every_surface(src: SyntheticSource) -> None:
    mesh = src.ground_truth_mesh()
    eyes = src.poses[:, :3, 3]
    assert distance_to_mesh(mesh, eyes).min() > 0.4
    up = np.tile([0.0, 0.0, 1.0], (len(eyes), 1))
    assert np.all(mesh.ray.intersects_first(eyes, up) < 0)  # nothing above: not inside or under anything
    lo, hi = src.scene_bounds()
    assert np.all(eyes > lo) and np.all(eyes < hi)


def test_render_view_reproduces_the_frames(src: SyntheticSource) -> None:
    f = src.get(90, 90)
    assert f is not None
    rgb, depth = src.render_view(f.K, f.T_world_camera, H, W)
    np.testing.assert_array_equal(rgb, f.rgb)
    np.testing.assert_array_equal(depth, f.depth_m)


def test_depth_noise_is_gaussian_and_seeded_per_frame(src: SyntheticSource) -> None:
    noisy = make(n_frames=20, depth_noise_m=0.01)
    f3, f4 = noisy.get(3, 3), noisy.get(4, 4)
    assert f3 is not None and f4 is not None
    clean3 = src.render_view(f3.K, f3.T_world_camera, H, W)[1]
    valid = clean3 > 0
    diff = (f3.depth_m - clean3)[valid]
    assert np.std(diff) == pytest.approx(0.01, rel=0.1) and abs(np.mean(diff)) < 1e-3
    assert np.all(f3.depth_m[~valid] == 0)
    clean4 = src.render_view(f4.K, f4.T_world_camera, H, W)[1]
    diff4 = (f4.depth_m - clean4)[clean4 > 0]
    assert np.std(diff4) == pytest.approx(0.01, rel=0.1) and not np.allclose(diff4[:100], diff[:100])


def test_stride_and_max_frames_come_from_the_base_class() -> None:
    s = make(n_frames=40, stride=7, max_frames=5, prefetch=2)
    frames = list(s)
    assert len(s) == 5 and [f.index for f in frames] == [0, 7, 14, 21, 28]
    assert [f.timestamp for f in frames] == pytest.approx([i / FPS for i in (0, 7, 14, 21, 28)])
    for f in frames:
        np.testing.assert_array_equal(f.T_world_camera, s.poses[f.index])
    s.close()


def test_ground_truth_mesh_is_one_coloured_room(src: SyntheticSource) -> None:
    mesh = src.ground_truth_mesh()
    assert isinstance(mesh, trimesh.Trimesh) and mesh.visual.kind == "vertex"
    colors = np.asarray(mesh.visual.vertex_colors)
    assert colors.shape == (len(mesh.vertices), 4) and colors.dtype == np.uint8
    assert colors[:, :3].std(axis=0).min() > 20
    assert mesh.edges_unique_length.max() < 0.08  # fine enough for vertex colours
    lo, hi = src.scene_bounds()
    np.testing.assert_allclose(lo, [-2.5, -2.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(hi, [2.5, 2.0, 2.6], atol=1e-6)
    mesh.vertices += 1.0  # a copy: the source's own scene is untouched
    assert np.allclose(src.ground_truth_mesh().bounds[0], lo)


def test_default_source_is_the_synthetic_room() -> None:
    s = make_source(SourceConfig())
    assert isinstance(s, SyntheticSource) and s.format_name == "synthetic"
    assert not SyntheticSource.looks_like(Path("."))
    assert len(s) == SyntheticConfig().n_frames
