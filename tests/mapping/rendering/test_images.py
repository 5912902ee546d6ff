"""Novel-view renders on analytic scenes: depth against the true surface, the fast search against the
exhaustive render (every 1 cm of every allocated voxel), misses, normals, and the priors-off search."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.geometry import look_at, world_rays
from h2viz.mapping.field.octree import VoxelOctree
from h2viz.mapping.kernels import render_search
from h2viz.mapping.kernels.voxel_walk import MarchParams, rays64, render_lattice
from h2viz.mapping.mapper import Mapper
from h2viz.mapping.rendering.images import RenderParams, render_image_reference, sdf_gradient, sdf_gradient_fd
from h2viz.mapping.sampling.samples import sample_rays
from tests.mapping.analytic import Scene, intrinsics, orbit
from tests.mapping.test_mapper import small_cfg

torch.set_num_threads(2)
H, W = 48, 64
PLANE = Scene("plane")
PLANE_VIEW = look_at(np.array([0.25, -0.35, 0.9]), np.array([0.05, 0.0, 0.0]))  # novel: not a mapped pose


def mapped(scene: Scene, poses: list[np.ndarray], **cfg: object) -> Mapper:
    mapper = Mapper(small_cfg(**cfg))
    for i, T in enumerate(poses):
        mapper.integrate(scene.frame(i, T))
    return mapper


def exhaustive(mapper: Mapper, T: np.ndarray, mode: str) -> np.ndarray:
    params = RenderParams.from_config(mapper.cfg, mapper.max_depth_m)
    support = mapper.drawable() if params.surface else None  # the observed space a surface render draws in
    color = mapper._view_color(intrinsics(W, H), T) if params.surface and mode == "rgb" else None  # same colour
    args = (mapper.field, mapper.octree, intrinsics(W, H), T, H, W, mode, params)
    return render_image_reference(*args, support=support, surface_color=color)


def true_depth(scene: Scene, T: np.ndarray) -> np.ndarray:
    o, d = world_rays(intrinsics(W, H), T, H, W)
    t = scene.hit_t(o, d)
    return np.where(np.isfinite(t), t, 0.0).reshape(H, W)


@pytest.fixture(scope="module")
def plane() -> Mapper:
    """Priors only: the field is the trilinear corner priors plus a near-zero residual."""
    return mapped(PLANE, orbit(PLANE, 4, 0.6, 1.2, np.zeros(3)), max_iters=0, fine_priors=False)


@pytest.fixture(scope="module")
def fine_plane() -> Mapper:
    """Priors only, fine ones: the field is the fused 1.25 cm lattice where frames reached it."""
    return mapped(PLANE, orbit(PLANE, 4, 0.6, 1.2, np.zeros(3)), max_iters=0)


@pytest.fixture(scope="module")
def sphere() -> tuple[Scene, Mapper]:
    """Trained a little: the residual moves the surface off the priors' and voxels at the edges of the views
    have no complete priors, so both search paths run."""
    scene = Scene("sphere", center=np.array([0.03, -0.02, 0.01]), radius=0.4)
    return scene, mapped(scene, orbit(scene, 6, 1.3, 0.4, scene.center), max_iters=4, rays_per_iter=512)


def test_lattice_positions_are_the_exhaustive_samples() -> None:
    """The render walk yields exactly (bitwise) the positions and voxels of the exhaustive samples."""
    rng = np.random.default_rng(0)
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    tree.allocate((rng.integers(-8, 8, size=(400, 3)) + 0.5) * 0.1)
    R = 300
    o = torch.tensor(rng.uniform(-0.6, 0.6, size=(R, 3))).float()
    d = torch.tensor(rng.normal(size=(R, 3))).float()
    d = d / (d[:, 2:3].abs() + 0.2)
    reference = sample_rays(tree, o, d, torch.full((R,), 2.5), 0.01, jitter=False)
    corner_ids = torch.from_numpy(tree.voxel_corners)
    O, D = rays64(o, d)
    lat = render_lattice(
        tree, torch.zeros(tree.n_corners), corner_ids, None, O, D, np.full(R, 2.5), MarchParams(0.01, "distrust", 0, 0)
    )
    np.testing.assert_array_equal(lat.ray, reference.ray.numpy())
    np.testing.assert_array_equal(lat.voxel, reference.voxel.numpy())
    np.testing.assert_array_equal(lat.t, reference.t.numpy())


def test_plane_depth_is_the_true_depth(plane: Mapper) -> None:
    depth = plane.render(intrinsics(W, H), PLANE_VIEW, H, W, "depth")
    truth = true_depth(PLANE, PLANE_VIEW)
    assert (depth > 0).mean() > 0.97
    err = np.abs(depth - truth)[depth > 0]
    # the zero crossing of projective corner priors (each corner's depth difference along its first camera's axis)
    # lies within a few millimetres of the plane: 1.6 mm median measured
    assert np.median(err) < 0.002 and np.percentile(err, 95) < 0.005


def test_plane_renders_match_the_exhaustive_render(plane: Mapper) -> None:
    for mode, tol in (("depth", 5e-5), ("rgb", 1e-5), ("prior", 1e-5)):
        fast = plane.render(intrinsics(W, H), PLANE_VIEW, H, W, mode)
        ref = exhaustive(plane, PLANE_VIEW, mode)
        assert np.percentile(np.abs(fast - ref), 99) < tol, mode
        assert np.abs(fast - ref).max() < 10 * tol, mode


def test_fine_prior_renders_match_the_exhaustive_render_and_find_the_plane(fine_plane: Mapper) -> None:
    assert fine_plane.field.fine_prior is not None
    for mode, tol in (("depth", 5e-5), ("rgb", 1e-5), ("prior", 1e-5)):
        fast = fine_plane.render(intrinsics(W, H), PLANE_VIEW, H, W, mode)
        ref = exhaustive(fine_plane, PLANE_VIEW, mode)
        assert np.percentile(np.abs(fast - ref), 99) < tol, mode
        assert np.abs(fast - ref).max() < 10 * tol, mode
    depth = fine_plane.render(intrinsics(W, H), PLANE_VIEW, H, W, "depth")
    truth = true_depth(PLANE, PLANE_VIEW)
    ok = (depth > 0) & (truth > 0)
    assert ok.mean() > 0.9 and np.median(np.abs(depth - truth)[ok]) < 0.002


def test_trained_sphere_matches_the_exhaustive_render(sphere: tuple[Scene, Mapper]) -> None:
    scene, mapper = sphere
    T = look_at(np.array([1.0, 0.8, 0.5]), scene.center)
    fast = mapper.render(intrinsics(W, H), T, H, W, "depth")
    ref = exhaustive(mapper, T, "depth")
    assert ((fast > 0) == (ref > 0)).mean() > 0.995
    both = (fast > 0) & (ref > 0)
    assert both.sum() > 0.15 * H * W
    assert np.mean(np.abs(fast - ref)[both] < 5e-4) > 0.98
    fast_rgb = mapper.render(intrinsics(W, H), T, H, W, "rgb")
    ref_rgb = exhaustive(mapper, T, "rgb")
    assert np.mean(np.abs(fast_rgb - ref_rgb).max(axis=2) < 0.01) > 0.99


def test_rays_that_miss_the_map_render_empty(plane: Mapper) -> None:
    up = look_at(np.array([0.0, 0.0, 0.5]), np.array([0.1, 0.0, 2.0]))  # looking away from the plane
    for mode in ("depth", "rgb", "normal", "prior"):
        assert not plane.render(intrinsics(W, H), up, H, W, mode).any(), mode
    horizon = look_at(np.array([0.0, -0.2, 0.3]), np.array([0.0, 3.0, 0.3]))  # upper half: sky
    depth = plane.render(intrinsics(W, H), horizon, H, W, "depth")
    assert not depth[: H // 2 - 2].any()
    assert (depth[H // 2 + 4 :] > 0).mean() > 0.3


def test_plane_normals_face_up(plane: Mapper) -> None:
    normals = plane.render(intrinsics(W, H), PLANE_VIEW, H, W, "normal")
    hit = np.linalg.norm(normals, axis=2) > 0
    assert hit.mean() > 0.97
    np.testing.assert_allclose(np.linalg.norm(normals[hit], axis=1), 1.0, atol=1e-4)
    assert np.median(normals[hit][:, 2]) > 0.995 and normals[hit][:, 2].min() > 0.9


def test_the_search_evaluates_a_few_samples_per_ray(plane: Mapper, monkeypatch: pytest.MonkeyPatch) -> None:
    """Far fewer network evaluations than the exhaustive render's samples (every 1 cm of every voxel)."""
    counted = []
    residual = render_search.residual_sdf
    monkeypatch.setattr(render_search, "residual_sdf", lambda f, p: counted.append(len(p)) or residual(f, p))
    plane.render(intrinsics(W, H), PLANE_VIEW, H, W, "depth")
    params = RenderParams.from_config(plane.cfg, plane.max_depth_m)
    o, d = world_rays(intrinsics(W, H), PLANE_VIEW, H, W)
    o, d = torch.from_numpy(o).float(), torch.from_numpy(d).float()
    every = sample_rays(plane.octree, o, d, torch.full((H * W,), params.t_far), 0.01, jitter=False)
    assert H * W < sum(counted) < 10 * H * W < every.t.numel()


def test_priors_off_search_finds_the_surface() -> None:
    """Without priors every voxel is searched coarse then fine with the full SDF: the same depths as the
    exhaustive render, on the surface the field learned."""
    mapper = mapped(PLANE, orbit(PLANE, 3, 0.6, 1.2, np.zeros(3)), priors=False, max_iters=8, early_ending=False)
    fast = mapper.render(intrinsics(W, H), PLANE_VIEW, H, W, "depth")
    ref = exhaustive(mapper, PLANE_VIEW, "depth")
    assert (fast > 0).mean() > 0.95 and ((fast > 0) == (ref > 0)).mean() > 0.995
    both = (fast > 0) & (ref > 0)
    assert np.mean(np.abs(fast - ref)[both] < 1e-4) > 0.99
    assert np.median(np.abs(fast - true_depth(PLANE, PLANE_VIEW))[fast > 0]) < 0.03  # the field is coarse yet


def test_the_searchs_sdf_is_the_field(sphere: tuple[Scene, Mapper]) -> None:
    """The search's SDF (kernel prior + bounded residual, weighted where the fine priors hold) is the field's own."""
    _, mapper = sphere
    voxel = torch.arange(mapper.octree.n_voxels).repeat_interleave(40)
    points = mapper.field.voxel_origin[voxel] + torch.rand(len(voxel), 3) * mapper.voxel_size_m
    with torch.no_grad():
        prior, weight = mapper.field.prior_parts(points, voxel)
        assert weight is not None and 0.0 < float(weight.mean()) < 1.0  # fine and corner priors both in play
        sdf = prior + render_search.residual_sdf(mapper.field, points) * weight
        torch.testing.assert_close(sdf, mapper.field.sdf(points, voxel), rtol=0, atol=1e-5)


def test_finite_difference_normals_match_autograd_normals(sphere: tuple[Scene, Mapper]) -> None:
    """Rendered normals come from tetrahedral differences of the fused SDF; autograd through the field is the
    reference (they differ only within a millimetre of hash-cell and lattice-cell faces, where the gradient
    jumps). Points within the truncation band, where the fine priors are not flat."""
    _, mapper = sphere
    rng = np.random.default_rng(3)
    voxel = torch.from_numpy(rng.integers(0, mapper.octree.n_voxels, 20000))
    local = torch.from_numpy(rng.uniform(0.05, 0.95, size=(20000, 3)).astype(np.float32))
    points = torch.from_numpy(mapper.octree.voxel_coords().astype(np.float32))[voxel] * mapper.voxel_size_m
    points = points + local * mapper.voxel_size_m
    with torch.no_grad():
        near = mapper.field.sdf(points, voxel).abs() < 0.7
        points, voxel = points[near][:3000], voxel[near][:3000]
        assert len(points) > 1000
        fd = sdf_gradient_fd(mapper.field, mapper.octree, points, voxel)
    ref = sdf_gradient(mapper.field, points, voxel)
    angle = torch.rad2deg(torch.arccos((fd * ref.detach()).sum(1).clamp(-1, 1)))
    # 2.4 deg measured (0.57 with corner priors only): a 1 mm step straddles a 1.25 cm lattice cell's face, where
    # the trilinear gradient turns, at four points in ten; a wrong axis or sign would be tens of degrees
    assert float(angle.median()) < 4.0
    assert float(torch.quantile(angle, 0.9)) < 15.0
