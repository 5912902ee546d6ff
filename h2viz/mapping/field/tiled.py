"""Decoders run tile by tile with recomputation, so that their activations stay in the CPU's caches.

A ReLU decoder on N points writes and reads an (N, width) activation per layer several times between its
forward and backward passes; at N = 64k and width 64 that is 16 MB a tensor, and the pass is bound by memory
traffic. `tiled(net, x)` computes the output without keeping activations, and the backward pass recomputes
each tile's forward pass and back-propagates it at once while it is still in cache (activation
checkpointing per tile). Results equal net(x) and its gradients up to float round-off.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

TILE = 8192
"""Points per tile: (TILE, 64) float32 activations are 2 MB, the size of a core's L2 cache here."""


MIN_TILES = 4
"""Below this many tiles the plain pass is as fast (measured: colour decoder on 20k points, bench/encoding.py)."""


class _Tiled(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, x: Tensor, net: nn.Module, tile: int, *params: Tensor) -> Tensor:
        """x (N, D_in) -> net(x) (N, D_out), computed tile by tile without a graph."""
        with torch.no_grad():
            out = torch.cat([net(x[i : i + tile]) for i in range(0, x.shape[0], tile)]) if x.shape[0] else net(x)
        ctx.save_for_backward(x)
        ctx.net, ctx.tile, ctx.params = net, tile, params
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_out: Tensor) -> tuple[Tensor | None, ...]:
        """Recompute and back-propagate one tile at a time; parameter gradients summed over tiles."""
        (x,) = ctx.saved_tensors
        want_x = ctx.needs_input_grad[0]
        params = [p for p, need in zip(ctx.params, ctx.needs_input_grad[3:], strict=True) if need]
        grads = [torch.zeros_like(p) for p in params]
        grad_x = torch.empty_like(x) if want_x else None
        for i in range(0, x.shape[0], ctx.tile):
            with torch.enable_grad():
                xt = x[i : i + ctx.tile].detach().requires_grad_(want_x)
                y = ctx.net(xt)
                inputs = [xt, *params] if want_x else params
                got = torch.autograd.grad(y, inputs, grad_out[i : i + ctx.tile], allow_unused=True)
            if want_x:
                grad_x[i : i + ctx.tile] = got[0]
                got = got[1:]
            for g, add in zip(grads, got, strict=True):
                if add is not None:
                    g += add
        it = iter(grads)
        param_grads = [next(it) if need else None for need in ctx.needs_input_grad[3:]]
        return (grad_x, None, None, *param_grads)


def tiled(net: nn.Module, x: Tensor, tile: int = TILE) -> Tensor:
    """net(x) for x (N, D_in), differentiable w.r.t. x and net's parameters, with per-tile recomputation."""
    if x.shape[0] < MIN_TILES * tile:
        return net(x)
    if not torch.is_grad_enabled():  # inference: tile by tile as well, nothing to keep
        return torch.cat([net(x[i : i + tile]) for i in range(0, x.shape[0], tile)])
    return _Tiled.apply(x, net, tile, *net.parameters())
