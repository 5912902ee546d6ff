"""The hybrid field's residual bound: the hash grid corrects the prior SDF by at most residual_bound (tr units)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.config import MappingConfig
from h2viz.mapping.field.hybrid_field import HybridField
from h2viz.mapping.field.octree import VoxelOctree


def _field(**kw: object) -> tuple[HybridField, torch.Tensor, torch.Tensor]:
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    tree.allocate(np.array([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05]]))
    field = HybridField(MappingConfig().updated(hash_log2_size=10, **kw))  # type: ignore[arg-type]
    field.sync(tree)
    field.priors = torch.linspace(-2.0, 2.0, tree.n_corners)
    points = torch.rand(500, 3) * torch.tensor([0.2, 0.1, 0.1])
    voxel = (points[:, 0] >= 0.1).long()
    return field, points, voxel


@pytest.mark.parametrize("raw", [-6.0, -0.3, 0.2, 4.0])
def test_the_residual_is_squashed_to_the_bound_and_unbounded_without_priors(raw: float) -> None:
    field, points, voxel = _field(residual_bound=1.5)
    with torch.no_grad():
        field.geo_mlp[-1].weight.zero_()
        field.geo_mlp[-1].bias.fill_(raw)
        residual = field.sdf(points, voxel) - field.prior_sdf(points, voxel)
    torch.testing.assert_close(residual, torch.full_like(residual, 1.5 * np.tanh(raw / 1.5)))
    assert residual.abs().max() < 1.5
    unbounded, _, _ = _field(residual_bound=0.0)
    no_priors, _, _ = _field(priors=False)
    for f in (unbounded, no_priors):
        with torch.no_grad():
            f.geo_mlp[-1].weight.zero_()
            f.geo_mlp[-1].bias.fill_(raw)
            torch.testing.assert_close(f.residual(f.geo_grid(points)), torch.full((500, 1), raw))


def test_gradients_flow_through_the_bound() -> None:
    field, points, voxel = _field()
    field.sdf(points, voxel).sum().backward()
    assert field.geo_mlp[-1].bias.grad is not None and float(field.geo_mlp[-1].bias.grad) > 0
