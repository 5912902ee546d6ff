"""Fast paths of the field against their references: the fused prior kernel vs the torch trilinear blend, and
the tiled decoder vs a plain pass (values and gradients)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.config import MappingConfig
from h2viz.mapping.backend import resolve_backend
from h2viz.mapping.field.hybrid_field import HybridField, mlp
from h2viz.mapping.field.octree import VoxelOctree
from h2viz.mapping.field.tiled import tiled

pytest.importorskip("numba")


def _field(kernels: str) -> tuple[HybridField, VoxelOctree]:
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    rng = np.random.default_rng(0)
    tree.allocate((rng.integers(-5, 5, size=(200, 3)) + 0.5) * 0.1)
    field = HybridField(MappingConfig().updated(hash_log2_size=12), resolve_backend(kernels))
    field.sync(tree)
    field.priors = torch.from_numpy(rng.normal(size=tree.n_corners).astype(np.float32)).requires_grad_()
    return field, tree


def test_fused_prior_matches_the_torch_blend_and_its_gradient() -> None:
    fast, tree = _field("auto")
    ref, _ = _field("torch")
    rng = np.random.default_rng(1)
    voxel = torch.from_numpy(rng.integers(0, tree.n_voxels, 5000))
    local = torch.from_numpy(rng.uniform(-0.02, 1.02, size=(5000, 3)).astype(np.float32))  # faces and beyond
    points = fast.voxel_origin[voxel] + local * 0.1
    grad = torch.randn(5000)
    out_fast = fast.prior_sdf(points, voxel)
    out_ref = ref.prior_sdf(points, voxel)
    torch.testing.assert_close(out_fast, out_ref, rtol=1e-5, atol=1e-5)
    (out_fast * grad).sum().backward()
    (out_ref * grad).sum().backward()
    torch.testing.assert_close(fast.priors.grad, ref.priors.grad, rtol=1e-4, atol=1e-4)
    # the blend reproduces corner values exactly at the corners
    corner = torch.from_numpy(tree.voxel_corners[voxel[:1].numpy()][0])
    at_corner = fast.prior_sdf(fast.voxel_origin[voxel[:1]] + 0.1, voxel[:1])
    torch.testing.assert_close(at_corner, fast.priors.detach()[corner[7:8]])


@pytest.mark.parametrize("layers", [1, 2])
def test_tiled_decoder_matches_a_plain_pass(layers: int) -> None:
    torch.manual_seed(0)
    net = mlp(8, 64, layers, 3)
    x = torch.randn(10_000, 8)
    grad = torch.randn(10_000, 3)
    x_plain = x.clone().requires_grad_()
    net(x_plain).backward(grad)
    plain = [p.grad.clone() for p in net.parameters()]
    net.zero_grad()
    x_tiled = x.clone().requires_grad_()
    out = tiled(net, x_tiled, tile=1000)
    torch.testing.assert_close(out, net(x), rtol=1e-6, atol=1e-6)
    out.backward(grad)
    torch.testing.assert_close(x_tiled.grad, x_plain.grad, rtol=1e-5, atol=1e-6)
    for p, g in zip(net.parameters(), plain, strict=True):
        torch.testing.assert_close(p.grad, g, rtol=0, atol=1e-5 * float(g.abs().max()))  # float32 sums of 10k terms
