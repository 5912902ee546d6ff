"""Colour priors: the compiled kernels match the torch reference, a constant colour comes back exactly, a sharp
colour edge is blended over one lattice cell (at the default and at finer lattices), nothing observed reads as the
neutral colour, and a checkpoint of another lattice resolution is refused with the setting to use."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.mapping.field.color_prior import EMPTY, SUB, ColorPrior, compact_sums
from h2viz.mapping.field.octree import VoxelOctree
from tests.mapping.backends import FAST, REFERENCE

VS = 0.1


def _octree(points: np.ndarray) -> VoxelOctree:
    octree = VoxelOctree(VS, 0, expansion=False)
    octree.allocate(points.astype(np.float32))
    return octree


def _prior(octree: VoxelOctree, fused: bool, sub: int = SUB) -> tuple[ColorPrior, torch.Tensor]:
    prior = ColorPrior(VS, backend=FAST if fused else REFERENCE, sub=sub)
    prior.grow(octree.n_voxels)
    origin = torch.from_numpy(octree.voxel_coords().astype(np.float32)) * VS  # (V,3) metres
    return prior, origin


def test_a_constant_colour_comes_back_and_unobserved_space_is_neutral() -> None:
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(0.0, 0.3, (5000, 2)), np.full(5000, 0.05)]  # a plane through the middle of voxels
    octree = _octree(pts)
    prior, origin = _prior(octree, fused=True)
    colour = torch.tensor([0.2, 0.5, 0.9])
    prior.add(octree, origin, torch.from_numpy(pts).float(), colour.expand(len(pts), 3))
    rgb, w = prior.colors(octree, origin, torch.tensor([[0.15, 0.15, 0.05], [0.15, 0.15, 0.09], [5.0, 5.0, 5.0]]))
    assert torch.allclose(rgb[0], colour, atol=1e-5) and w[0] > 0
    assert torch.allclose(rgb[2], torch.full((3,), EMPTY)) and w[2] == 0  # outside the map
    assert torch.allclose(rgb[1], torch.full((3,), EMPTY)) and w[1] == 0  # 4 cm off the plane: nothing splatted


@pytest.mark.parametrize("sub", [SUB, 12, 16])
def test_a_colour_edge_is_blended_over_one_lattice_cell(sub: int) -> None:
    x = np.linspace(0.001, 0.299, 600)
    xx, yy = np.meshgrid(x, x)
    pts = np.c_[xx.ravel(), yy.ravel(), np.full(xx.size, 0.05)]
    octree = _octree(pts)
    prior, origin = _prior(octree, fused=True, sub=sub)
    red = (pts[:, 0] < 0.15).astype(np.float32)  # red left of x = 15 cm, black right of it
    rgb = torch.from_numpy(np.c_[red, np.zeros_like(red), np.zeros_like(red)])
    prior.add(octree, origin, torch.from_numpy(pts).float(), rgb)
    cell = VS / sub
    probe = torch.tensor([[0.15 - 1.5 * cell, 0.12, 0.05], [0.15 + 1.5 * cell, 0.12, 0.05]])
    got, _ = prior.colors(octree, origin, probe)
    assert got[0, 0] > 0.97 and got[1, 0] < 0.03  # a cell and a half from the edge: the pure colours


@pytest.mark.parametrize(("seed", "sub"), [(0, SUB), (1, SUB), (2, 12)])
def test_kernels_match_the_torch_reference(seed: int, sub: int) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.2, 0.2, (4000, 3)).astype(np.float32)
    pts[:1000, 2] = 0.0  # on voxel faces
    octree = _octree(pts)
    rgb = torch.from_numpy(rng.uniform(0, 1, (len(pts), 3)).astype(np.float32))
    fused, origin = _prior(octree, fused=True, sub=sub)
    ref, _ = _prior(octree, fused=False, sub=sub)
    fused.add(octree, origin, torch.from_numpy(pts), rgb)
    ref.add(octree, origin, torch.from_numpy(pts), rgb)
    assert torch.allclose(fused.sums, ref.sums, atol=1e-4)
    queries = torch.from_numpy(rng.uniform(-0.25, 0.25, (3000, 3)).astype(np.float32))
    queries[:500, 0] = 0.1  # on voxel faces, read from both sides
    a, wa = fused.colors(octree, origin, queries)
    b, wb = ref.colors(octree, origin, queries)
    assert torch.allclose(a, b, atol=1e-4) and torch.allclose(wa, wb, atol=1e-4)


def test_the_splat_kernel_gives_the_same_sums_on_any_number_of_threads() -> None:
    """Threads share the voxels and each voxel's lattice takes its points in order: the sums of a serial splat,
    bit for bit (prefetching lattice lines ahead changes nothing)."""
    kernels = pytest.importorskip("h2viz.mapping.kernels.color_prior_numba")
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.3, 0.3, (20_000, 3)).astype(np.float32)
    octree = _octree(pts)
    rgb = rng.uniform(0, 1, (len(pts), 3)).astype(np.float32)
    table = FAST.array_kernels.walk.voxel_hash(octree)  # type: ignore[union-attr]
    origin = (octree.voxel_coords() * VS).astype(np.float32)
    results = []
    for parts in (1, 2, 3):
        sums = np.zeros((octree.n_voxels * (SUB + 1) ** 3, 4), np.float32)
        kernels._splat_kernel(pts, rgb, *table, origin, VS, SUB, sums, parts)
        results.append(sums)
    assert results[0].any()
    assert all(np.array_equal(results[0], other) for other in results[1:])


def test_storage_grows_without_losing_lattices() -> None:
    prior = ColorPrior(VS, sub=SUB)
    prior.grow(3)
    prior.sums[1, 5] = torch.tensor([1.0, 2.0, 3.0, 4.0])
    for n in (10, 300, 301):
        prior.grow(n)
        assert prior.sums.shape == (n, (SUB + 1) ** 3, 4)
        assert torch.equal(prior.sums[1, 5], torch.tensor([1.0, 2.0, 3.0, 4.0]))


def test_a_checkpoint_of_another_lattice_resolution_names_the_setting() -> None:
    saved = ColorPrior(VS, sub=8)
    saved.grow(2)
    with pytest.raises(ValueError, match="mapping.color.color_prior_cells=8"):
        ColorPrior(VS, sub=12).load(saved.sums)
    with pytest.raises(ValueError, match="mapping.color.color_prior_cells=8"):  # the same from its compact form
        ColorPrior(VS, sub=12).load(compact_sums(saved.sums))


def test_a_checkpoint_keeps_only_the_lattice_points_colour_was_splatted_on_and_restores_them_exactly() -> None:
    prior = ColorPrior(VS, sub=SUB)
    prior.grow(4)
    rng = torch.Generator().manual_seed(0)
    points = torch.rand(50, 3, generator=rng) * VS + torch.tensor([VS, 0.0, 0.0])  # inside voxel 1
    origins = torch.tensor([[0.0, 0, 0], [VS, 0, 0], [0, VS, 0], [0, 0, VS]])  # (4,3)
    prior.splat(points, torch.ones(50, dtype=torch.long), origins, torch.rand(50, 3, generator=rng))
    saved = compact_sums(prior.sums)
    touched = int((prior.sums[..., 3] != 0).sum())
    assert saved["rows"].shape == (touched,) and saved["sums"].shape == (touched, 4)
    assert 0 < touched <= 8 * 50 < prior.sums.shape[0] * prior.sums.shape[1]  # 8 lattice points a splat at most
    restored = ColorPrior(VS, sub=SUB)
    restored.load(saved)
    assert torch.equal(restored.sums, prior.sums)
    restored.grow(6)  # and it grows on from there
    assert torch.equal(restored.sums[:4], prior.sums) and not restored.sums[4:].any()
    bad = dict(saved, rows=saved["rows"][:-1])
    with pytest.raises(ValueError, match="inconsistent"):
        ColorPrior(VS, sub=SUB).load(bad)
