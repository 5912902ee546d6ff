"""bfloat16 colour decoding against the float32 decoder: values and parameter gradients at batch sizes around
the padding multiple, large batches, and the configuration switch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from h2viz.config import MappingConfig
from h2viz.errors import ConfigError
from h2viz.mapping.field import bf16
from h2viz.mapping.field.bf16 import ROWS, TILE, decode_bf16, native_bf16, use_bf16
from h2viz.mapping.field.hybrid_field import HybridField, mlp
from h2viz.mapping.field.octree import VoxelOctree


def _decoder(seed: int = 0) -> torch.nn.Sequential:
    torch.manual_seed(seed)
    return mlp(8, 64, 2, 3)


def _grads(net: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.grad.reshape(-1) for p in net.parameters()])  # type: ignore[union-attr]


@pytest.mark.parametrize("n", [1, ROWS - 1, ROWS, 3 * ROWS + 17])
def test_values_and_gradients_match_float32(n: int) -> None:
    net = _decoder()
    x = torch.randn(n, 8) * 0.5
    target = torch.rand(n, 3)
    # float32 reference
    ref = torch.sigmoid(net(x))
    (ref - target).abs().mean().backward()
    g_ref = _grads(net)
    net.zero_grad()
    x_half = x.clone().requires_grad_()
    out = torch.sigmoid(decode_bf16(net, x_half))
    (out - target).abs().mean().backward()
    g_half = _grads(net)
    assert out.dtype == torch.float32 and out.shape == (n, 3)
    # bfloat16 keeps 8 significant bits: colours agree to a few thousandths, far from a wrong product
    assert (out - ref).abs().max() < 0.01
    assert float((out - ref).detach().abs().mean()) < 2e-3
    # the L1 gradient flips sign only where a colour is within rounding of its target: cosine, not equality
    cosine = torch.nn.functional.cosine_similarity(g_ref, g_half, dim=0)
    assert cosine > 0.98
    assert torch.isclose(g_half.norm(), g_ref.norm(), rtol=0.05)
    assert x_half.grad is not None and x_half.grad.shape == (n, 8)


def test_large_batches_without_gradient_decode_tile_by_tile() -> None:
    net = _decoder(2)
    x = torch.randn(2 * TILE + 5, 8)
    with torch.no_grad():
        tiles = decode_bf16(net, x)
        whole = bf16._padded_call(net, x)
        ref = net(x)
    assert tiles.shape == (2 * TILE + 5, 3)
    torch.testing.assert_close(tiles, whole, rtol=0, atol=1e-5)
    assert (tiles - ref).abs().max() < 0.05  # logits, before the sigmoid


def test_precision_setting() -> None:
    assert use_bf16("float32") is False
    assert use_bf16("bfloat16") is True
    assert use_bf16("auto") is native_bf16()
    with pytest.raises(ConfigError, match="mapping.color.color_precision.*float32"):
        use_bf16("half")


def test_the_field_decodes_colour_in_the_configured_precision() -> None:
    tree = VoxelOctree(0.1, min_points=0, expansion=False)
    tree.allocate(np.array([[0.05, 0.05, 0.05]]))
    cfg = dict(hash_log2_size=10, color_prior=False)  # the decoder alone (with priors it starts near zero)
    fields = {p: HybridField(MappingConfig().updated(**cfg, color_precision=p)) for p in ("float32", "bfloat16")}  # type: ignore[arg-type]
    fields["bfloat16"].load_state_dict(fields["float32"].state_dict())
    with torch.no_grad():
        for f in fields.values():
            f.color_grid.tables.uniform_(-1.0, 1.0)  # features large enough to make the decoder's output vary
        fields["bfloat16"].color_grid.tables.copy_(fields["float32"].color_grid.tables)
    points = torch.rand(700, 3) * 0.1
    with torch.no_grad():
        full, half = (fields[p].color(points) for p in ("float32", "bfloat16"))
    assert fields["bfloat16"].color_bf16 and not fields["float32"].color_bf16
    assert float(full.std()) > 0.01  # colours differ between points
    assert 0 < float((full - half).abs().max()) < 0.01  # rounded, yet the same colours
