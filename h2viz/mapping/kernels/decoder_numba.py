"""Fused CPU kernels (numba) for a one-hidden-layer ReLU decoder, y = W2 relu(W1 x + b1) + b2: the geometry MLP.

The decoder is narrow (8 -> 64 -> 1 by default) and runs on every training sample, so through torch it is a
chain of small matrix products that each stream an (N, 64) activation through memory several times. Here one
pass per sample keeps the 64 hidden values in registers: the forward pass writes y only; the backward pass
recomputes the hidden layer and accumulates every parameter gradient per thread block (the W1 gradient GROUP
samples at a time), then the blocks are summed. `FusedDecoder` gives the same values and gradients as the
torch module up to float round-off (tests/mapping/kernels/test_decoder_numba.py checks it against torch).
"""

from __future__ import annotations

import time
from typing import Any

import numba
import numpy as np
import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from h2viz.errors import H2vizError
from h2viz.mapping.kernels.jit import njit, parallel_region

BLOCKS_PER_THREAD = 4
"""Sample blocks per thread: enough to balance the load, few enough that the per-block gradients stay small."""


ZERO = np.float32(0.0)
"""Every constant in the kernels is float32: a bare 0.0 is float64 in numba and turns the products it meets
into float64 ones, which LLVM cannot pack eight to a vector (the backward pass ran 1.7x slower that way)."""


@njit(inline=True)
def _pre_activation(x: np.ndarray, p: int, w1t: np.ndarray, b1: np.ndarray, h: np.ndarray) -> None:
    """h (H,) <- W1 x[p] + b1, the hidden layer before its ReLU."""
    for j in range(h.shape[0]):
        h[j] = b1[j]
    for k in range(x.shape[1]):
        xk = x[p, k]
        for j in range(h.shape[0]):
            h[j] += w1t[k, j] * xk


@njit(fastmath=True)
def decode_range(
    x: np.ndarray, w1t: np.ndarray, b1: np.ndarray, w2: np.ndarray, b2: np.ndarray, start: int, stop: int, y: np.ndarray
) -> None:
    """y[start:stop] (.,O) <- decoder(x[start:stop] (.,D)), serially; w1t (D,H) is W1 transposed, w2 (O,H)."""
    hidden, d_out = w1t.shape[1], w2.shape[0]
    h = np.empty(hidden, dtype=x.dtype)
    for p in range(start, stop):
        _pre_activation(x, p, w1t, b1, h)
        for o in range(d_out):
            acc = ZERO
            for j in range(hidden):
                acc += w2[o, j] * max(h[j], ZERO)
            y[p, o] = acc + b2[o]


@njit(parallel=True, fastmath=True)
def _forward_kernel(
    x: np.ndarray, w1t: np.ndarray, b1: np.ndarray, w2: np.ndarray, b2: np.ndarray, n_blocks: int, y: np.ndarray
) -> None:
    """y (N,O) <- decoder(x (N,D)), blocks of points in parallel."""
    n = x.shape[0]
    for block in numba.prange(n_blocks):
        decode_range(x, w1t, b1, w2, b2, block * n // n_blocks, (block + 1) * n // n_blocks, y)


GROUP = 4
"""Samples whose hidden-layer gradients are added into the W1 gradient together: its (D,H) accumulators are
loaded and stored once per group instead of once per sample (backward pass 2.9 -> 2.4-2.6 ms on 46.5k samples)."""


@njit(inline=True)
def _sample_backward(
    x: np.ndarray,
    grad_y: np.ndarray,
    p: int,
    w1t: np.ndarray,
    b1: np.ndarray,
    w2: np.ndarray,
    h: np.ndarray,
    dh: np.ndarray,
    gb1: np.ndarray,
    gw2: np.ndarray,
    gb2: np.ndarray,
    want_x: bool,
    grad_x: np.ndarray,
) -> None:
    """Sample p's hidden-layer gradient dh (H,), its shares of the b1, W2 and b2 gradients, and grad_x[p]."""
    _pre_activation(x, p, w1t, b1, h)  # recomputed: cheaper than storing (N,H)
    dh[:] = ZERO
    for o in range(w2.shape[0]):
        g = grad_y[p, o]
        gb2[o] += g
        w2o, gw2o = w2[o], gw2[o]
        for j in range(h.shape[0]):
            alive = h[j] > ZERO
            gw2o[j] += g * h[j] if alive else ZERO
            dh[j] += g * w2o[j] if alive else ZERO
    for j in range(h.shape[0]):
        gb1[j] += dh[j]
    if want_x:
        for k in range(x.shape[1]):
            acc = ZERO
            wk = w1t[k]
            for j in range(h.shape[0]):
                acc += wk[j] * dh[j]
            grad_x[p, k] = acc


@njit(parallel=True, fastmath=True)
def _backward_kernel(
    x: np.ndarray,
    grad_y: np.ndarray,
    w1t: np.ndarray,
    b1: np.ndarray,
    w2: np.ndarray,
    want_x: bool,
    grad_x: np.ndarray,
    g_w1t: np.ndarray,
    g_b1: np.ndarray,
    g_w2: np.ndarray,
    g_b2: np.ndarray,
) -> None:
    """Gradients of sum(grad_y * decoder(x)): grad_x (N,D) when want_x, and per block (B,...) parameter gradients
    g_w1t (B,D,H), g_b1 (B,H), g_w2 (B,O,H), g_b2 (B,O), overwritten here."""
    n, d_in, hidden, d_out = x.shape[0], x.shape[1], w1t.shape[1], w2.shape[0]
    n_blocks = g_b1.shape[0]
    for block in numba.prange(n_blocks):
        gw1t = np.zeros((d_in, hidden), np.float32)  # this block's sums, written out once at the end
        gb1 = np.zeros(hidden, np.float32)
        gw2 = np.zeros((d_out, hidden), np.float32)
        gb2 = np.zeros(d_out, np.float32)
        h = np.empty(hidden, np.float32)
        dh = np.empty((GROUP, hidden), np.float32)  # the hidden-layer gradients of a group of samples
        start, stop = block * n // n_blocks, (block + 1) * n // n_blocks
        for first in range(start, stop, GROUP):
            size = min(GROUP, stop - first)
            for q in range(size):
                _sample_backward(x, grad_y, first + q, w1t, b1, w2, h, dh[q], gb1, gw2, gb2, want_x, grad_x)
            if size == GROUP:
                for k in range(d_in):
                    x0, x1, x2, x3 = x[first, k], x[first + 1, k], x[first + 2, k], x[first + 3, k]
                    gk = gw1t[k]
                    for j in range(hidden):
                        gk[j] += x0 * dh[0, j] + x1 * dh[1, j] + x2 * dh[2, j] + x3 * dh[3, j]
            else:  # the block's last few samples
                for q in range(size):
                    for k in range(d_in):
                        xk = x[first + q, k]
                        gk = gw1t[k]
                        for j in range(hidden):
                            gk[j] += xk * dh[q, j]
        g_w1t[block], g_b1[block], g_w2[block], g_b2[block] = gw1t, gb1, gw2, gb2


def is_supported(net: nn.Module) -> bool:
    """True for nn.Sequential(Linear, ReLU, Linear), the shape of decoder these kernels run."""
    if not isinstance(net, nn.Sequential) or len(net) != 3:
        return False
    first, act, last = net[0], net[1], net[2]
    return isinstance(first, nn.Linear) and isinstance(act, nn.ReLU) and isinstance(last, nn.Linear)


DecoderWeights = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""W1 transposed (D,H), b1 (H,), W2 (O,H), b2 (O,): the kernels' view of a decoder."""


def decoder_weights(net: nn.Sequential) -> DecoderWeights:
    """The kernels' float32 CPU arrays of a supported decoder (views of its parameters where possible)."""
    first, last = net[0], net[2]
    as_np = lambda t: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32)  # noqa: E731
    return as_np(first.weight.T), as_np(first.bias), as_np(last.weight), as_np(last.bias)


def decode(net: nn.Sequential, x: Tensor) -> Tensor:
    """net(x) (N,O) of contiguous CPU float32 x (N,D) through the forward kernel; no autograd."""
    w1t, b1, w2, b2 = decoder_weights(net)
    y = torch.empty(x.shape[0], w2.shape[0], dtype=x.dtype)
    if x.shape[0]:
        with parallel_region() as threads:
            _forward_kernel(x.numpy(), w1t, b1, w2, b2, threads * BLOCKS_PER_THREAD, y.numpy())
    return y


class _FusedDecoder(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, x: Tensor, net: nn.Sequential, *params: Tensor) -> Tensor:
        """x (N,D) float32 -> net(x) (N,O); params are net's, listed so that autograd tracks them."""
        x = x.detach().contiguous()
        ctx.save_for_backward(x)
        ctx.net = net
        return decode(net, x)

    @staticmethod
    @once_differentiable
    def backward(ctx: Any, grad_y: Tensor) -> tuple[Tensor | None, ...]:
        """grad_y (N,O) -> grad of x (N,D) and of W1, b1, W2, b2."""
        (x,) = ctx.saved_tensors
        w1t, b1, w2, b2 = decoder_weights(ctx.net)
        want_x = bool(ctx.needs_input_grad[0])
        with parallel_region() as threads:
            blocks = max(1, min(threads * BLOCKS_PER_THREAD, x.shape[0]))
            g_w1t = np.empty((blocks, *w1t.shape), np.float32)
            g_b1 = np.empty((blocks, *b1.shape), np.float32)
            g_w2 = np.empty((blocks, *w2.shape), np.float32)
            g_b2 = np.empty((blocks, *b2.shape), np.float32)
            grad_x = torch.empty_like(x) if want_x else torch.empty(0, x.shape[1])
            gy = grad_y.contiguous().to(x.dtype).numpy()
            _backward_kernel(x.numpy(), gy, w1t, b1, w2, want_x, grad_x.numpy(), g_w1t, g_b1, g_w2, g_b2)
        g_w1 = torch.from_numpy(g_w1t.sum(0)).T.contiguous()
        param_grads = (
            g_w1,
            torch.from_numpy(g_b1.sum(0)),
            torch.from_numpy(g_w2.sum(0)),
            torch.from_numpy(g_b2.sum(0)),
        )
        return (grad_x if want_x else None, None, *param_grads)


def fused_decoder(net: nn.Sequential, x: Tensor) -> Tensor:
    """net(x) for CPU float32 x (N,D) through the fused kernels; differentiable w.r.t. x and net's parameters."""
    if not is_supported(net):
        raise H2vizError("the fused decoder kernels run nn.Sequential(Linear, ReLU, Linear) only; call the module")
    if x.device.type != "cpu" or x.dtype != torch.float32 or x.ndim != 2 or x.shape[1] != net[0].in_features:
        raise H2vizError(f"the fused decoder needs CPU float32 input (N,{net[0].in_features}), got {tuple(x.shape)}")
    if not torch.is_grad_enabled():
        return decode(net, x.contiguous())
    return _FusedDecoder.apply(x, net, net[0].weight, net[0].bias, net[2].weight, net[2].bias)


def warmup() -> float:
    """Compile (or load from the cache) both kernels on tiny inputs; returns seconds."""
    start = time.perf_counter()
    net = nn.Sequential(nn.Linear(8, 16), nn.ReLU(), nn.Linear(16, 1))
    x = torch.rand(5, 8, requires_grad=True)
    fused_decoder(net, x).sum().backward()
    return time.perf_counter() - start
