"""Ray/voxel traversal (the compiled walk with its empty-space jumps, and the NumPy reference walk) and samples
against a brute-force dense march; rendering weights on a plane."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.mapping.backend import Backend
from h2viz.mapping.field.octree import VoxelOctree
from h2viz.mapping.rendering.volume import composite, render_weights
from h2viz.mapping.sampling.samples import BandLayout, band_samples, sample_rays, traverse
from tests.mapping.backends import FAST, REFERENCE, needs_numba

WALKS = [pytest.param(FAST, id="compiled", marks=needs_numba), pytest.param(REFERENCE, id="reference")]


def random_tree(seed: int = 0) -> VoxelOctree:
    rng = np.random.default_rng(seed)
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    coords = rng.integers(-6, 6, size=(300, 3))
    tree.allocate((coords + 0.5) * 0.1)
    return tree


def brute_force_voxels(tree: VoxelOctree, o: np.ndarray, d: np.ndarray, t_far: float) -> set[int]:
    t = np.arange(0.0, t_far, 1e-4)
    pts = torch.from_numpy(o + d * t[:, None]).float()
    ids = tree.lookup_points(pts).numpy()
    return set(ids[ids >= 0].tolist())


@pytest.mark.parametrize("backend", WALKS)
def test_traversal_finds_exactly_the_voxels_a_dense_march_finds(backend: Backend) -> None:
    tree = random_tree()
    rng = np.random.default_rng(1)
    origins = rng.uniform(-0.7, 0.7, size=(40, 3))
    dirs = rng.normal(size=(40, 3))
    dirs /= np.abs(dirs[:, 2:3]) + 0.3  # arbitrary, not unit length
    hits = traverse(
        tree,
        torch.tensor(origins).float(),
        torch.tensor(dirs).float(),
        torch.zeros(40),
        torch.full((40,), 1.5),
        backend,
    )
    for r in range(40):
        found = set(hits.voxel[hits.ray == r].tolist())
        expected = brute_force_voxels(tree, origins[r], dirs[r], 1.5)
        # grazing hits shorter than the brute-force step may differ; everything else must match
        assert expected <= found
        assert len(found - expected) <= 1
    seg = hits.t_out - hits.t_in
    assert bool((seg > 0).all()) and bool((hits.t_out <= 1.5 + 1e-6).all())


@pytest.mark.parametrize("backend", WALKS)
def test_samples_lie_in_their_voxels_and_are_ordered(backend: Backend) -> None:
    tree = random_tree(2)
    rng = np.random.default_rng(3)
    o = torch.tensor(rng.uniform(-0.5, 0.5, size=(64, 3))).float()
    d = torch.nn.functional.normalize(torch.randn(64, 3), dim=1)
    s = sample_rays(tree, o, d, torch.full((64,), 2.0), 0.01, jitter=True, backend=backend)
    assert s.t.numel() > 0
    coords = torch.from_numpy(tree.voxel_coords().astype(np.float32))[s.voxel] * 0.1
    inside = ((s.points >= coords - 1e-5) & (s.points <= coords + 0.1 + 1e-5)).all(dim=1)
    assert bool(inside.all())
    assert bool((s.ray[1:] >= s.ray[:-1]).all())
    same = s.ray[1:] == s.ray[:-1]
    assert bool((s.t[1:][same] >= s.t[:-1][same] - 1e-6).all())
    # roughly one sample per centimetre of voxel interior crossed
    hits = traverse(tree, o, d, torch.zeros(64), torch.full((64,), 2.0), backend)
    assert abs(s.t.numel() - float(((hits.t_out - hits.t_in) / 0.01).sum())) < 0.1 * s.t.numel() + hits.ray.numel()


def test_rendered_depth_of_an_exact_plane_sdf() -> None:
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    g = np.stack(np.meshgrid(np.arange(-5, 5), np.arange(-5, 5), [-1, 0], indexing="ij"), -1).reshape(-1, 3)
    tree.allocate((g + 0.5) * 0.1)
    o = torch.tensor([[0.013, -0.021, 1.0]]).repeat(50, 1)
    d = torch.cat([torch.rand(50, 2) * 0.4 - 0.2, -torch.ones(50, 1)], dim=1)  # z-normalised, looking down
    s = sample_rays(tree, o, d, torch.full((50,), 3.0), 0.01, jitter=False)
    tr = 0.05
    sdf = s.points[:, 2] / tr  # plane z = 0, in truncation units (exact along the normal)
    out = composite(s, render_weights(s, sdf, tr, 0.05), None)
    # camera at height 1 looking down: the surface is at t = 1 along z-normalised rays
    assert bool(out.hit.all())
    np.testing.assert_allclose(out.depth.numpy(), 1.0, atol=3e-3)


def sparse_tree() -> VoxelOctree:
    """A few clusters of voxels metres apart: rays cross long stretches of empty space between them."""
    rng = np.random.default_rng(5)
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    centres = rng.integers(-40, 40, size=(6, 3))
    coords = (centres[:, None, :] + rng.integers(-2, 3, size=(6, 30, 3))).reshape(-1, 3)
    tree.allocate((coords + 0.5) * 0.1)
    return tree


@pytest.mark.parametrize("skip_cells", [1 << 20, 64])
@needs_numba
def test_traversal_jumps_empty_space_without_missing_voxels(monkeypatch: pytest.MonkeyPatch, skip_cells: int) -> None:
    """Empty-space jumps (fine skip cells, and coarse ones when the map's box is large) find every voxel a
    dense march finds, from t_near on."""
    assert FAST.array_kernels is not None
    raymarch = FAST.array_kernels.walk
    monkeypatch.setattr(raymarch, "SKIP_CELLS", skip_cells)
    tree = sparse_tree()
    assert (raymarch.walk_table(tree).skip_shift > 0) == (skip_cells == 64)
    rng = np.random.default_rng(6)
    coords = tree.voxel_coords()
    targets = (coords[rng.integers(len(coords), size=30)] + rng.uniform(0, 1, size=(30, 3))) * 0.1
    origins = rng.uniform(-4, 4, size=(30, 3))
    dirs = (targets - origins) / np.linalg.norm(targets - origins, axis=1, keepdims=True)
    t_near = rng.uniform(0, 0.5, size=30)
    hits = traverse(tree, *(torch.tensor(a).float() for a in (origins, dirs, t_near)), torch.full((30,), 12.0), FAST)
    for r in range(30):
        found = set(hits.voxel[hits.ray == r].tolist())
        expected = brute_force_voxels(tree, origins[r] + dirs[r] * t_near[r], dirs[r], 12.0 - t_near[r])
        assert expected <= found and len(found - expected) <= 1
    assert bool((hits.t_in >= torch.tensor(t_near).float()[hits.ray] - 1e-6).all())


@pytest.mark.parametrize("front_step_m", [0.01, 0.03])
def test_band_samples_kernel_matches_the_torch_reference(front_step_m: float) -> None:
    """The numba band sampler keeps exactly the candidates the torch code keeps, at the same positions."""
    tree = random_tree(4)
    rng = np.random.default_rng(5)
    o = torch.tensor(rng.uniform(-0.4, 0.4, size=(300, 3))).float()
    d = torch.tensor(rng.normal(size=(300, 3))).float()
    d = d / (d[:, 2:3].abs() + 0.2)
    depth = torch.tensor(rng.uniform(0.05, 1.2, size=300)).float()
    layout = BandLayout(0.15, 0.05, 0.01, front_step_m, 12)
    args = (tree, o, d, depth, layout)
    fast = band_samples(*args, generator=torch.Generator().manual_seed(7), backend=FAST)
    ref = band_samples(*args, generator=torch.Generator().manual_seed(7), backend=REFERENCE)
    assert fast.t.numel() > 300
    assert torch.equal(fast.ray, ref.ray) and torch.equal(fast.voxel, ref.voxel)
    torch.testing.assert_close(fast.t, ref.t, rtol=0, atol=1e-6)
    torch.testing.assert_close(fast.points, ref.points, rtol=0, atol=1e-6)
    assert bool((fast.t > 0).all())
    same = fast.ray[1:] == fast.ray[:-1]
    assert bool((fast.t[1:][same] > fast.t[:-1][same]).all())
    n_band = 10 + round(0.10 / front_step_m)
    per_ray = torch.bincount(fast.ray, minlength=300)
    assert int(per_ray.max()) <= n_band + 12
    rel = depth[fast.ray] - fast.t  # in front of the measured depth > 0
    front, trunc = (rel > 0.05 + 1e-6) & (rel <= 0.15 + 1e-6), rel.abs() <= 0.05 + 1e-6
    assert int(torch.bincount(fast.ray[front], minlength=300).max()) <= round(0.10 / front_step_m)
    assert int(torch.bincount(fast.ray[trunc], minlength=300).max()) <= 10  # 1 cm steps within tr


@needs_numba
def test_the_reference_walk_gives_the_compiled_walks_hits() -> None:
    """Same voxels in the same order, entry and exit t within float rounding (the compiled walk restarts its
    boundary arithmetic after each empty-space jump), from t_near to t_far on a map with long empty stretches."""
    tree = sparse_tree()
    rng = np.random.default_rng(8)
    coords = tree.voxel_coords()
    targets = (coords[rng.integers(len(coords), size=200)] + rng.uniform(0, 1, size=(200, 3))) * 0.1
    origins = rng.uniform(-4, 4, size=(200, 3))
    dirs = (targets - origins) / np.abs(targets - origins)[:, 2:3].clip(0.05)
    o, d = torch.tensor(origins).float(), torch.tensor(dirs).float()
    near, far = torch.tensor(rng.uniform(0, 0.3, size=200)).float(), torch.full((200,), 20.0)
    fast, ref = traverse(tree, o, d, near, far, FAST), traverse(tree, o, d, near, far, REFERENCE)
    assert fast.ray.numel() > 400
    assert torch.equal(fast.ray, ref.ray) and torch.equal(fast.voxel, ref.voxel)
    torch.testing.assert_close(ref.t_in, fast.t_in, rtol=0, atol=1e-5)
    torch.testing.assert_close(ref.t_out, fast.t_out, rtol=0, atol=1e-5)
