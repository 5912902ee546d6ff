"""The training path of the field (gathered leaves) equals the plain modules, values and gradients."""

from __future__ import annotations

import torch

from h2viz.mapping.encoding import HashGrid
from h2viz.mapping.field import sparse_encode


def test_sparse_encode_matches_the_grid_and_its_gradient() -> None:
    torch.manual_seed(0)
    grid = HashGrid(log2_size=12)
    torch.nn.init.uniform_(grid.tables, -1, 1)
    x = torch.rand(700, 3) * 3 - 1.5
    w = torch.randn(grid.output_dim)
    dense = grid(x)
    (dense * w).sum().backward()
    feats, leaf = sparse_encode("t", grid, x)
    torch.testing.assert_close(feats, dense, atol=1e-5, rtol=1e-5)
    (feats * w).sum().backward()
    table_grad = grid.tables.grad.view(-1, grid.n_features)
    torch.testing.assert_close(leaf.values.grad, table_grad[leaf.rows], atol=1e-4, rtol=1e-4)
    untouched = torch.ones(table_grad.shape[0], dtype=torch.bool)
    untouched[leaf.rows] = False
    assert float(table_grad[untouched].abs().max()) == 0.0
