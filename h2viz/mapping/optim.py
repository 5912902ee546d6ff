"""Adam over named tensors that may grow (corner priors) and may be updated row-sparsely (hash tables).

Row-sparse tensors only update rows whose gradient is non-zero this step (lazy Adam, as for embedding
tables): untouched hash entries and priors keep their moments, which saves a dense pass over millions of
entries per iteration.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from h2viz.mapping.backend import Backend


@dataclass
class _Slot:
    get: Callable[[], torch.Tensor]
    sparse: bool
    m: torch.Tensor
    v: torch.Tensor
    steps: torch.Tensor  # (rows,) per-row step counts for sparse tensors, (1,) otherwise
    extra: dict[str, torch.Tensor] = field(default_factory=dict)


class GrowingAdam:
    """Adam (betas 0.9/0.99, eps 1e-15) over tensors looked up by name each step."""

    def __init__(
        self,
        lr: float,
        betas: tuple[float, float] = (0.9, 0.99),
        eps: float = 1e-15,
        backend: Backend | None = None,
    ) -> None:
        self.lr, self.betas, self.eps = lr, betas, eps
        self.backend = backend  # its tensor kernels run the row-sparse steps (None: the torch code)
        self.slots: dict[str, _Slot] = {}

    def add(self, name: str, get: Callable[[], torch.Tensor], sparse: bool = False) -> None:
        p = get()
        rows = p.numel() // (p.shape[-1] if p.dim() > 1 else 1) if sparse else 1
        self.slots[name] = _Slot(get, sparse, torch.zeros_like(p), torch.zeros_like(p), p.new_zeros(rows))

    def zero_grad(self) -> None:
        for slot in self.slots.values():
            slot.get().grad = None

    def _fit(self, slot: _Slot, p: torch.Tensor) -> None:
        """Pad moments when the tensor grew (new rows start with zero moments)."""
        n = p.shape[0] - slot.m.shape[0]
        if n > 0:
            pad = p.new_zeros((n, *p.shape[1:]))
            slot.m = torch.cat([slot.m, pad])
            slot.v = torch.cat([slot.v, pad.clone()])
            if slot.sparse:
                slot.steps = torch.cat([slot.steps, p.new_zeros(n)])

    @torch.no_grad()
    def step(self) -> None:
        b1, b2 = self.betas
        for slot in self.slots.values():
            p = slot.get()
            if p.grad is None:
                continue
            self._fit(slot, p)
            g = p.grad
            if slot.sparse:
                width = p.shape[-1] if p.dim() > 1 else 1
                P, G, M, V = (x.view(-1, width) for x in (p, g, slot.m, slot.v))  # (rows, width)
                if not self._fused_update(P, G, M, V, slot.steps):
                    rows = torch.nonzero(G.abs().sum(1) > 0)[:, 0]
                    self._update(P, M, V, G, rows, slot.steps, b1, b2)
            else:
                slot.steps += 1
                slot.m.mul_(b1).add_(g, alpha=1 - b1)
                slot.v.mul_(b2).addcmul_(g, g, value=1 - b2)
                t = float(slot.steps.item())
                denom = (slot.v / (1 - b2**t)).sqrt_().add_(self.eps)
                p.addcdiv_(slot.m, denom, value=-self.lr / (1 - b1**t))

    def _fused_update(
        self, p: torch.Tensor, g: torch.Tensor, m: torch.Tensor, v: torch.Tensor, steps: torch.Tensor
    ) -> bool:
        """The row-sparse step through the compiled kernel (kernels.optim_numba) when it applies: contiguous
        float32 CPU tensors and a backend with tensor kernels. False when it does not (the torch code runs instead)."""
        tensors = (p, g, m, v, steps)
        kernels = None if self.backend is None else self.backend.cpu_kernels(*tensors)
        if kernels is None or any(t.dtype != torch.float32 for t in tensors):
            return False
        if not all(t.is_contiguous() for t in tensors):
            return False
        kernels.optim.sparse_adam(*(t.detach().numpy() for t in tensors), self.lr, *self.betas, self.eps)
        return True

    def _update(
        self,
        p: torch.Tensor,
        m: torch.Tensor,
        v: torch.Tensor,
        g: torch.Tensor,
        rows: torch.Tensor,
        steps: torch.Tensor,
        b1: float,
        b2: float,
    ) -> None:
        """Adam on the given rows of (rows, width) views only, with per-row bias correction."""
        steps[rows] += 1
        t = steps[rows][:, None]
        gr = g[rows]
        mr = m[rows].mul_(b1).add_(gr, alpha=1 - b1)
        vr = v[rows].mul_(b2).addcmul_(gr, gr, value=1 - b2)
        m[rows], v[rows] = mr, vr
        denom = (vr / (1 - b2**t)).sqrt_().add_(self.eps)
        p[rows] -= self.lr * (mr / (1 - b1**t)) / denom

    def state_dict(self) -> dict[str, dict[str, torch.Tensor]]:
        return {k: {"m": s.m, "v": s.v, "steps": s.steps} for k, s in self.slots.items()}

    def load_state_dict(self, state: dict[str, dict[str, torch.Tensor]]) -> None:
        for k, st in state.items():
            if k in self.slots:
                s = self.slots[k]
                s.m, s.v, s.steps = st["m"].clone(), st["v"].clone(), st["steps"].clone()
