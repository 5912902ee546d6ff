"""bfloat16 matrix products for the colour decoder on CPUs that execute them natively (AVX512-BF16, AMX).

The colour decoder (two hidden layers of 64) is the largest block of dense arithmetic in an optimisation step:
its forward and backward matrix products on ~13k live samples take ~6 ms in float32 on two cores, ~2.5 ms in
bfloat16. Parameters stay float32 (autocast casts them per call, Adam updates float32 masters); activations
and gradients are rounded to bfloat16 (8 significant bits: ~0.002 on a colour in [0, 1], far below what the
colour losses resolve), products accumulate in float32.

oneDNN builds (and keeps) one kernel per matrix shape, and batch sizes change every step: unpadded, a new
kernel would be built on most calls (slower than float32). Rows are therefore padded with zeros to a multiple
of ROWS; padded rows receive no gradient, so the parameters' gradients are those of the real rows.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor, nn
from torch.nn import functional

from h2viz.errors import ConfigError

PRECISIONS = ("auto", "float32", "bfloat16")
ROWS = 1024
"""Batch rows are padded to a multiple of this: ~15 distinct shapes in a run. (256 is ~10 % faster but keeps
~60 shapes' kernels, +110 MB; 1024 costs no more memory than float32.)"""
TILE = 8192
"""Rows per call when decoding without gradient (renders, mesh colours): one fixed shape, bounded memory."""


@functools.cache
def native_bf16() -> bool:
    """True when this CPU has native bfloat16 dot products (torch's own dispatch test)."""
    checks = [getattr(torch.cpu, name, None) for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported")]
    return any(check is not None and bool(check()) for check in checks)


def use_bf16(precision: str) -> bool:
    """Resolve mapping.color.color_precision: auto = bfloat16 where native_bf16(), float32 elsewhere."""
    if precision not in PRECISIONS:
        raise ConfigError(f"mapping.color.color_precision: unknown {precision!r}; use one of {PRECISIONS}")
    return precision == "bfloat16" or (precision == "auto" and native_bf16())


def _padded_call(net: nn.Module, x: Tensor) -> Tensor:
    """net(x) (N, D_out) float32 under CPU bfloat16 autocast, x (N, D_in) zero-padded to a multiple of ROWS."""
    n = x.shape[0]
    padded = functional.pad(x, (0, 0, 0, -n % ROWS))  # (ceil(N/ROWS)*ROWS, D_in), differentiable
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = net(padded)
    return y[:n].float()


def decode_bf16(net: nn.Module, x: Tensor) -> Tensor:
    """net(x) for CPU features x (N, D_in) with bfloat16 products; differentiable w.r.t. x and net's parameters."""
    if x.device.type != "cpu":
        raise ConfigError(
            "bfloat16 colour decoding runs on the CPU; set mapping.color.color_precision: float32 for CUDA"
        )
    if torch.is_grad_enabled() or x.shape[0] <= TILE:
        return _padded_call(net, x)
    return torch.cat([_padded_call(net, x[i : i + TILE]) for i in range(0, x.shape[0], TILE)])
