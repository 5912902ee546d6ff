"""The fused one-hidden-layer decoder kernels against the torch module: values, every gradient, edge cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from h2viz.config import MappingConfig
from h2viz.errors import H2vizError
from h2viz.mapping.field.hybrid_field import HybridField, mlp
from tests.mapping.backends import FAST, REFERENCE

numba_kernels = pytest.importorskip("h2viz.mapping.kernels.decoder_numba")


@pytest.mark.parametrize(("d_in", "hidden", "d_out", "n"), [(8, 64, 1, 20_000), (5, 17, 3, 1_001), (8, 64, 1, 3)])
def test_fused_decoder_matches_torch_values_and_gradients(d_in: int, hidden: int, d_out: int, n: int) -> None:
    torch.manual_seed(0)
    net = mlp(d_in, hidden, 1, d_out)
    x = torch.randn(n, d_in)
    grad = torch.randn(n, d_out)
    x_ref = x.clone().requires_grad_()
    y_ref = net(x_ref)
    y_ref.backward(grad)
    ref = [p.grad.clone() for p in net.parameters()]
    net.zero_grad()
    x_fast = x.clone().requires_grad_()
    y_fast = numba_kernels.fused_decoder(net, x_fast)
    y_fast.backward(grad)
    torch.testing.assert_close(y_fast, y_ref, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(x_fast.grad, x_ref.grad, rtol=1e-4, atol=1e-5)
    for got, want in zip((p.grad for p in net.parameters()), ref, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)


def test_dead_units_pass_no_gradient_and_no_grad_calls_build_no_graph() -> None:
    net = mlp(2, 4, 1, 1)
    with torch.no_grad():
        net[0].weight.copy_(torch.tensor([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]))
        net[0].bias.zero_()
        net[2].weight.copy_(torch.tensor([[1.0, 2.0, 3.0, 4.0]]))
        net[2].bias.fill_(0.5)
    x = torch.tensor([[2.0, -1.0]], requires_grad=True)  # units 0 and 3 active: y = 2*1 + 1*4 + 0.5
    y = numba_kernels.fused_decoder(net, x)
    assert y.item() == pytest.approx(6.5)
    y.sum().backward()
    torch.testing.assert_close(x.grad, torch.tensor([[1.0, -4.0]]))  # W1^T (w2 * active)
    torch.testing.assert_close(net[0].bias.grad, torch.tensor([1.0, 0.0, 0.0, 4.0]))
    torch.testing.assert_close(net[2].weight.grad, torch.tensor([[2.0, 0.0, 0.0, 1.0]]))
    with torch.no_grad():
        assert numba_kernels.fused_decoder(net, x).grad_fn is None
    empty = numba_kernels.fused_decoder(net, torch.zeros(0, 2, requires_grad=True))
    assert empty.shape == (0, 1)


def test_the_field_runs_its_default_decoder_through_the_kernels_and_matches_the_torch_path() -> None:
    cfg = MappingConfig().updated(hash_log2_size=12)
    fast = HybridField(cfg, FAST)
    ref = HybridField(cfg, REFERENCE)
    ref.load_state_dict(fast.state_dict())
    feats = torch.randn(50_000, fast.geo_grid.output_dim)
    torch.testing.assert_close(fast.residual(feats), ref.residual(feats), rtol=1e-5, atol=1e-6)
    assert numba_kernels.is_supported(fast.geo_mlp)
    assert not numba_kernels.is_supported(fast.color_mlp)  # two hidden layers: torch runs it


def test_unsupported_inputs_are_refused_with_a_message() -> None:
    with pytest.raises(H2vizError, match="Linear, ReLU, Linear"):
        numba_kernels.fused_decoder(mlp(8, 16, 2, 1), torch.zeros(3, 8))
    with pytest.raises(H2vizError, match="float32"):
        numba_kernels.fused_decoder(mlp(8, 16, 1, 1), torch.zeros(3, 8, dtype=torch.float64))
    with pytest.raises(H2vizError, match=r"\(N,8\)"):
        numba_kernels.fused_decoder(mlp(8, 16, 1, 1), torch.zeros(3, 7))
    assert not numba_kernels.is_supported(nn.Sequential(nn.Linear(8, 4), nn.Tanh(), nn.Linear(4, 1)))
    assert np.isfinite(numba_kernels.warmup())
