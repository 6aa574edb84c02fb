"""The fused Armijo search (one CPU kernel per search: trials rolled out and costed in
turn) against the batched search on torch ops (``armijo_search`` with the closed-loop
rollout and the cost as evaluator): the same steps, costs, flags and trajectories, bit
for bit, and the same whole solves."""

from __future__ import annotations

import pytest
import torch

import torchslq as ts
from torchslq._backend import dispatch
from torchslq.costs.quadratic import compiled_cost_evaluation
from torchslq.dynamics.rollout import compiled_step_of, rollout, rollout_closed_loop
from torchslq.solvers.descent import LineSearch
from torchslq.solvers.line_search import TrialRecorder, armijo_search
from torchslq.solvers.stopping import ROUNDOFF_NOISE

F64 = torch.float64
T = 12

pytestmark = pytest.mark.skipif(
    not dispatch.compiled_available(), reason="numba kernels not available"
)


def _cartpole():
    return ts.discretize(ts.systems.CartPole(), 0.05, "rk4").double()


def _cost(B: int, g: torch.Generator, per_element: bool) -> ts.QuadraticCost:
    lead = (B,) if per_element else ()
    Qf = torch.diag_embed(1 + torch.rand(*lead, 4, generator=g, dtype=F64))
    x_ref = torch.tensor([0.0, 3.14159, 0.0, 0.0], dtype=F64)
    Q = 0.1 * torch.eye(4, dtype=F64) if per_element else torch.zeros(4, 4, dtype=F64)
    return ts.QuadraticCost(Q=Q, R=0.05 * torch.eye(1, dtype=F64), Qf=50 * Qf, x_ref=x_ref)


def _search_inputs(B: int, g: torch.Generator, cost: ts.QuadraticCost):
    dyn = _cartpole()
    x0 = 0.1 * torch.randn(B, 4, generator=g, dtype=F64)
    u = (0.5 * torch.randn(B, T, 1, generator=g, dtype=F64)).clamp(-0.5, 0.7)  # inside the bounds
    x = rollout(dyn, x0, u)
    K = 0.05 * torch.randn(B, T, 1, 4, generator=g, dtype=F64)
    k = torch.randn(B, T, 1, generator=g, dtype=F64)
    # k a descent direction of the closed-loop cost, its slope by a difference quotient
    h = 1e-7
    with torch.no_grad():
        xh, uh = rollout_closed_loop(dyn, x[:, 0], x, u, K, k, torch.full((B,), h, dtype=F64))
        xm, um = rollout_closed_loop(dyn, x[:, 0], x, u, K, k, torch.full((B,), -h, dtype=F64))
        slope = (cost(xh, uh) - cost(xm, um)) / (2 * h)
    k = k * torch.where(slope > 0, -1.0, 1.0).view(B, 1, 1)
    slope = -slope.abs()
    k[1] = -k[1]  # an ascent direction claimed to descend: no step of the grid passes
    k[2] = 0.0  # the trials equal the nominal: accepted by the round-off rule
    K[2] = 0.0
    slope[2] = -1e-300
    curvature = slope.abs() * torch.rand(B, generator=g, dtype=F64)
    active = torch.ones(B, dtype=torch.bool)
    active[3] = False  # not searched
    return dyn, x, u, K, k, slope, curvature, active


@pytest.mark.parametrize("per_element", [False, True])
@pytest.mark.parametrize("bounded", [False, True])
@pytest.mark.parametrize("quadratic", [False, True])
def test_fused_search_equals_the_batched_search(per_element, bounded, quadratic):
    B = 7
    g = torch.Generator().manual_seed(3)
    cost = _cost(B, g, per_element)
    dyn, x, u, K, k, slope, curvature, active = _search_inputs(B, g, cost)
    lo = hi = None
    if bounded:
        lo = torch.full((B, T, 1), -0.6, dtype=F64)
        hi = torch.full((B, T, 1), 0.8, dtype=F64)
    curv = curvature if quadratic else None
    with torch.no_grad(), compiled_cost_evaluation():
        J0 = cost(x, u)
        if quadratic:
            # element 5: the full step passes by the curvature term alone (with half of
            # it, it would not): J(1) = J0 + 0.4 (slope + curvature / 3)
            x1, u1 = rollout_closed_loop(dyn, x[:, 0], x, u, K, k, torch.ones(B, dtype=F64), lo, hi)
            gap = (cost(x1, u1)[5] - J0[5]) / 0.4
            slope[5] = torch.minimum(slope[5], gap - 1.0)
            curvature[5] = 3.0 * (gap - slope[5])
        trials = TrialRecorder()

        def evaluate(alphas):
            x0c = x[:, 0].expand(alphas.shape[0], B, 4)
            xc, uc = rollout_closed_loop(dyn, x0c, x, u, K, k, alphas, lo, hi)
            trials.record(alphas, xc, uc)
            return cost(xc, uc)

        # a large c1: the model decrease decides which step passes
        ref = armijo_search(
            evaluate, J0, slope, curvature=curv, c1=0.4, active=active, skip_settled=True,
            first_trials=2, pass_size=3,
        )  # fmt: skip
        x_ref, u_ref = trials.select(ref[0])
        grid = 0.5 ** torch.arange(20, dtype=F64)
        terms = cost.compiled_terms(x, u)
        assert terms is not None and compiled_step_of(dyn) is not None
        out = dispatch.armijo_rollout_compiled(
            *compiled_step_of(dyn), x, u, K, k, lo, hi, grid, J0, slope, curv, 0.4,
            ROUNDOFF_NOISE * torch.finfo(F64).eps, active, terms,
        )  # fmt: skip
    alpha, J, ok, x_new, u_new = out
    for a, b in zip((alpha, J, ok), ref, strict=True):
        assert torch.equal(a, b)
    assert torch.equal(x_new[ok], x_ref[ok]) and torch.equal(u_new[ok], u_ref[ok])
    # the cases the inputs were built for happened
    if not bounded:  # (clamped, a long step along an ascent direction may pass)
        assert not bool(ok[1]) and float(alpha[1]) == 0.0
    assert bool(ok[2]) and float(alpha[2]) == 1.0 and float(J[2]) == float(J0[2])
    assert not bool(ok[3]) and float(J[3]) == float(J0[3])
    assert bool(ok[[0, 4, 5, 6]].all())
    if quadratic:
        assert float(alpha[5]) == 1.0
    if bounded:  # the bounds were active in the accepted trials
        assert float(u_new[ok].min()) == -0.6 and float(u_new[ok].max()) == 0.8


def _count_fused(monkeypatch) -> list[bool]:
    """Record, for every line search from now on, whether it ran fused."""
    calls: list[bool] = []
    fused = LineSearch._fused_armijo

    def counted(self, *args):
        out = fused(self, *args)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(LineSearch, "_fused_armijo", counted)
    return calls


def _solve_both(solver, problem, x0, monkeypatch):
    calls = _count_fused(monkeypatch)
    r_fused = solver.solve(problem, x0)
    monkeypatch.setattr(LineSearch, "_fused_armijo", lambda self, *args: None)
    r_torch = solver.solve(problem, x0)
    return r_fused, r_torch, calls


@pytest.mark.parametrize(
    "solver",
    [
        ts.ILQR(max_iter=200, tol=1e-7, progress=False),
        ts.ILQR(max_iter=200, tol=1e-7, progress=False, u_min=-2.0, u_max=2.0),
        ts.DDP(max_iter=100, tol=1e-7, progress=False),
        ts.ILQR(max_iter=200, tol=1e-7, progress=False, compact=True),
    ],
    ids=["ilqr", "ilqr-bounds", "ddp", "ilqr-compact"],
)
def test_solves_with_the_fused_search_equal_the_torch_search(solver, monkeypatch):
    B = 6
    g = torch.Generator().manual_seed(1)
    problem = ts.Problem(_cartpole(), _cost(B, g, per_element=True), 30)
    x0 = torch.zeros(B, 4, dtype=F64)
    x0[:, 1] = 0.3 * torch.randn(B, generator=g, dtype=F64)
    r_fused, r_torch, calls = _solve_both(solver, problem, x0, monkeypatch)
    assert calls and all(calls)  # every search ran fused
    assert torch.equal(r_fused.status, r_torch.status)
    assert torch.equal(r_fused.iterations, r_torch.iterations)
    assert torch.equal(r_fused.u, r_torch.u) and torch.equal(r_fused.x, r_torch.x)
    assert bool(r_fused.converged.all())


def test_fused_search_not_taken_where_it_does_not_apply(monkeypatch):
    """float32 (no cost kernel) and a cost without kernel arrays take the torch search."""
    g = torch.Generator().manual_seed(2)
    dyn = _cartpole()
    cost = _cost(2, g, per_element=False)
    x0 = torch.zeros(2, 4, dtype=F64)
    x0[:, 1] = 0.2
    solver = ts.ILQR(max_iter=100, tol=1e-3, progress=False)
    calls = _count_fused(monkeypatch)
    r32 = solver.solve(ts.Problem(dyn.float(), cost.float(), 20), x0.float())
    assert calls and not any(calls)
    assert bool(r32.converged.all())
    # a cost without kernel arrays (any cost but QuadraticCost)
    calls.clear()
    target = torch.tensor([0.0, 3.14159, 0.0, 0.0], dtype=F64)
    general = ts.Cost(
        lambda x, u, t: 0.05 * u.pow(2).sum(-1),
        lambda x: 10.0 * (x - target).pow(2).sum(-1),
        state_dim=4,
        control_dim=1,
    )
    r = solver.solve(ts.Problem(dyn, general, 20), x0)
    assert calls and not any(calls)
    assert bool(r.converged.all())
