"""The growing, row-sparse Adam matches torch's Adam on touched rows and leaves other rows alone."""

from __future__ import annotations

import pytest
import torch

from h2viz.mapping.optim import GrowingAdam
from tests.mapping.backends import FAST, REFERENCE


def test_dense_slot_matches_torch_adam() -> None:
    torch.manual_seed(0)
    a = torch.randn(5, 3, requires_grad=True)
    b = a.detach().clone().requires_grad_(True)
    ours = GrowingAdam(1e-2)
    ours.add("a", lambda: a)
    ref = torch.optim.Adam([b], lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    for _ in range(5):
        for p, opt in ((a, ours), (b, ref)):
            opt.zero_grad()
            (p**3).sum().backward()
            opt.step()
    torch.testing.assert_close(a, b)


@pytest.mark.parametrize("fused", [True, False])
def test_sparse_slot_updates_only_touched_rows_like_adam(fused: bool) -> None:
    torch.manual_seed(0)
    table = torch.randn(2, 10, 2, requires_grad=True)
    start = table.detach().clone()
    ours = GrowingAdam(1e-2, backend=FAST if fused else REFERENCE)
    ours.add("t", lambda: table, sparse=True)
    rows = torch.tensor([1, 4, 13])
    ref = start.view(-1, 2)[rows].clone().requires_grad_(True)
    ref_opt = torch.optim.Adam([ref], lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    for _ in range(3):
        ours.zero_grad()
        (table.view(-1, 2)[rows] ** 2).sum().backward()
        ours.step()
        ref_opt.zero_grad()
        (ref**2).sum().backward()
        ref_opt.step()
    flat = table.detach().view(-1, 2)
    torch.testing.assert_close(flat[rows], ref.detach())
    untouched = torch.ones(20, dtype=torch.bool)
    untouched[rows] = False
    assert torch.equal(flat[untouched], start.view(-1, 2)[untouched])


def test_growing_tensor_keeps_moments_of_old_rows() -> None:
    holder = {"p": torch.zeros(3, requires_grad=True)}
    opt = GrowingAdam(0.1)
    opt.add("p", lambda: holder["p"], sparse=True)
    holder["p"].grad = torch.tensor([1.0, 0.0, 0.0])
    opt.step()
    grown = torch.cat([holder["p"].detach(), torch.zeros(2)]).requires_grad_(True)
    holder["p"] = grown
    grown.grad = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0])
    opt.step()
    assert opt.slots["p"].m.shape == (5,)
    assert opt.slots["p"].steps.tolist() == [2, 0, 0, 0, 1]
    assert grown[0] < -0.15 and grown[4] < -0.05 and grown[1] == 0


def test_the_compiled_sparse_step_matches_the_torch_code() -> None:
    """Corner priors (1-D, growing) over 30 steps with a changing set of touched rows, NaN gradients skipped."""
    pytest.importorskip("numba")
    torch.manual_seed(1)
    start = torch.randn(300)
    runs = {}
    for fused in (True, False):
        holder = {"p": start.clone().requires_grad_(True)}
        opt = GrowingAdam(1e-2, backend=FAST if fused else REFERENCE)
        opt.add("priors", lambda h=holder: h["p"], sparse=True)
        gen = torch.Generator().manual_seed(2)
        for step in range(30):
            if step == 10:  # the octree grew
                holder["p"] = torch.cat([holder["p"].detach(), torch.ones(50)]).requires_grad_(True)
            p = holder["p"]
            touched = torch.rand(p.shape[0], generator=gen) < 0.3
            p.grad = torch.where(touched, torch.randn(p.shape[0], generator=gen), torch.zeros(()))
            p.grad[5] = float("nan") if step == 3 else p.grad[5]  # a row whose gradient is not finite is left alone
            opt.step()
        runs[fused] = (holder["p"].detach(), opt.slots["priors"])
    (p_fast, s_fast), (p_ref, s_ref) = runs[True], runs[False]
    torch.testing.assert_close(p_fast, p_ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(s_fast.m, s_ref.m, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(s_fast.v, s_ref.v, rtol=1e-5, atol=1e-9)
    assert torch.equal(s_fast.steps, s_ref.steps) and s_fast.steps.max() > 5
    assert p_fast.shape == (350,) and torch.isfinite(p_fast).all()  # the NaN gradient moved nothing
