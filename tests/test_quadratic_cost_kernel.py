"""QuadraticCost's value on the CPU kernel (inside compiled_cost_evaluation, as in the
SLQ/iLQR/DDP loop) against the torch path, in every weight and reference layout."""

from __future__ import annotations

import sys

import pytest
import torch

import torchslq as ts
from torchslq._backend import dispatch as compiled
from torchslq.costs.quadratic import compiled_cost_evaluation

F64 = torch.float64
B, T, n, m = 5, 6, 3, 2

pytestmark = pytest.mark.skipif(
    not compiled.compiled_available(), reason="numba kernels not available"
)
_quad = sys.modules["torchslq.costs.quadratic"]


def _spd(*shape, k, g, diagonal=False):
    if diagonal:
        return torch.diag_embed(torch.rand(*shape, k, generator=g, dtype=F64) + 0.1)
    M = torch.randn(*shape, k, k, generator=g, dtype=F64)
    return M @ M.mT + 0.1 * torch.eye(k, dtype=F64)


def _cost(layout: str, g) -> ts.QuadraticCost:
    kw = {}
    if layout == "constant-diagonal":
        Q, R = _spd(k=n, g=g, diagonal=True), _spd(k=m, g=g, diagonal=True)
    elif layout == "constant-dense":
        Q, R = _spd(k=n, g=g), _spd(k=m, g=g)
        kw["Qf"] = _spd(k=n, g=g)
    elif layout == "time-varying":
        Q, R = _spd(T, k=n, g=g), _spd(T, k=m, g=g)
        kw["x_ref"] = torch.randn(T + 1, n, generator=g, dtype=F64)
        kw["u_ref"] = torch.randn(m, generator=g, dtype=F64)
    elif layout == "per-element":
        Q, R = _spd(B, T, k=n, g=g), _spd(B, 1, k=m, g=g)
        kw["Qf"] = _spd(B, k=n, g=g)
        kw["x_ref"] = torch.randn(B, T + 1, n, generator=g, dtype=F64)
        kw["u_ref"] = torch.randn(B, T, m, generator=g, dtype=F64)
    elif layout == "terminal-only":  # Q = 0 (the cart-pole benchmark's cost)
        Q, R = torch.zeros(n, n, dtype=F64), _spd(k=m, g=g, diagonal=True)
        kw["Qf"] = _spd(k=n, g=g)
        kw["x_ref"] = torch.randn(n, generator=g, dtype=F64)
    else:  # references only
        Q, R = _spd(k=n, g=g), _spd(k=m, g=g, diagonal=True)
        kw["x_ref"] = torch.randn(n, generator=g, dtype=F64)
    return ts.QuadraticCost(Q, R, **kw)


@pytest.mark.parametrize(
    "layout",
    ["constant-diagonal", "constant-dense", "time-varying", "per-element", "terminal-only", "refs"],
)
@pytest.mark.parametrize("lead", [(B,), (4, B), (1,)])
def test_kernel_equals_the_torch_path(layout, lead, monkeypatch):
    """The kernel's value == the torch path's to round-off (its sums run in another
    order), with trial dims in front and a batch of 1 broadcast against per-element
    weights; the kernel runs only inside compiled_cost_evaluation."""
    g = torch.Generator().manual_seed(3)
    cost = _cost(layout, g)
    x = torch.randn(*lead, T + 1, n, generator=g, dtype=F64)
    u = torch.randn(*lead, T, m, generator=g, dtype=F64)
    calls = []
    real = _quad._launch
    monkeypatch.setattr(_quad, "_launch", lambda *a: calls.append(1) or real(*a))
    ref = cost(x, u)
    assert calls == []
    with compiled_cost_evaluation():
        got = cost(x, u)
    assert calls == [1]
    assert got.shape == ref.shape and got.dtype == F64
    torch.testing.assert_close(got, ref, rtol=1e-14, atol=0)
    # the value of a row does not depend on the batch it is evaluated in
    if lead == (4, B):
        with compiled_cost_evaluation():
            one = cost(x[2:3], u[2:3])
        assert torch.equal(one[0], got[2])


def test_torch_path_where_the_kernel_does_not_apply(monkeypatch):
    """float32, autograd through the cost, large dimensions: the torch path (and its
    graph) inside the context too."""
    calls = []
    real = _quad._launch
    monkeypatch.setattr(_quad, "_launch", lambda *a: calls.append(1) or real(*a))
    g = torch.Generator().manual_seed(5)
    cost = _cost("constant-dense", g)
    x = torch.randn(B, T + 1, n, generator=g, dtype=F64)
    u = torch.randn(B, T, m, generator=g, dtype=F64)
    with compiled_cost_evaluation():
        cost.float()(x.float(), u.float())
        cost.double()
        xg = x.clone().requires_grad_(True)
        J = cost(xg, u)
        assert J.requires_grad
        (gx,) = torch.autograd.grad(J.sum(), xg)
        big = ts.QuadraticCost(torch.eye(40, dtype=F64), torch.eye(2, dtype=F64))
        big(torch.randn(2, T + 1, 40, dtype=F64), torch.randn(2, T, 2, dtype=F64))
    assert calls == []
    Q = cost.Q
    torch.testing.assert_close(gx[:, :T], x[:, :T] @ Q)  # dJ/dx_t = Q x_t


def test_solvers_evaluate_costs_on_the_kernel(monkeypatch):
    """ILQR's loop runs inside compiled_cost_evaluation (the kernel evaluates its line
    search trials), and its solution is that of the torch path to round-off."""
    from torchslq.tasks import pendulum_swingup

    problem, x0 = pendulum_swingup(batch=3, horizon=30, seed=1)
    calls = []
    real = _quad._compiled_terms
    monkeypatch.setattr(_quad, "_compiled_terms", lambda *a: calls.append(1) or real(*a))
    fast = ts.ILQR(max_iter=100, progress=False).solve(problem, x0)
    # the kernel's arrays: for its values and for the fused line search's trials
    assert len(calls) > 10
    monkeypatch.setattr(_quad, "_compiled_terms", lambda *a: None)
    ref = ts.ILQR(max_iter=100, progress=False).solve(problem, x0)
    assert bool(fast.converged.all()) and bool(ref.converged.all())
    torch.testing.assert_close(fast.cost, ref.cost, rtol=1e-12, atol=0)
    torch.testing.assert_close(fast.u, ref.u, rtol=1e-6, atol=1e-8)
