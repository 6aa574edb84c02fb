"""The fused Armijo search (one CPU kernel per search: trials rolled out and costed in
turn) against the batched search on torch ops (``armijo_search`` with the closed-loop
rollout and the cost as evaluator): the same steps, costs, flags and trajectories, bit
for bit, and the same whole solves."""

from __future__ import annotations

import pytest
import torch

import torchslq as ts
import torchslq.systems  # noqa: F401 (ts.systems)
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


class _ResidualCartPole(ts.Dynamics):
    """The cart-pole step plus a small learned residual (a 5-32-32-4 tanh MLP): a model
    whose step has a function on many rows at once (its wide layers as matrix products
    over the rows, :func:`torchslq._backend.model_fns.register_rows`)."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        torch.manual_seed(7)
        self.physics = _cartpole()
        self.net = torch.nn.Sequential(
            torch.nn.Linear(5, 32), torch.nn.Tanh(), torch.nn.Linear(32, 32), torch.nn.Tanh(),
            torch.nn.Linear(32, 4),
        ).to(F64)  # fmt: skip
        with torch.no_grad():
            self.net[-1].weight.mul_(0.01)

    def forward(self, x, u):
        return self.physics(x, u) + self.net(torch.cat([x, u], -1))


MODELS = {"cartpole": _cartpole, "learned": _ResidualCartPole}


def _search_inputs(B: int, g: torch.Generator, cost: ts.QuadraticCost, model: str = "cartpole"):
    dyn = MODELS[model]()
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


def _batched_evaluation(dyn, cost, x, u, K, k, lo, hi):
    """``(evaluate, trials)``: the batched search's evaluator (the closed-loop rollouts
    of a pass's steps, costed) and the recorder of its trajectories."""
    trials = TrialRecorder()

    def evaluate(alphas):
        x0c = x[:, 0].expand(alphas.shape[0], *x[:, 0].shape)
        xc, uc = rollout_closed_loop(dyn, x0c, x, u, K, k, alphas, lo, hi)
        trials.record(alphas, xc, uc)
        return cost(xc, uc)

    return evaluate, trials


def _fused_equals_batched(
    ref, trials, dyn, cost, x, u, K, k, lo, hi, J0, slope, curv, active, atol
):
    """The fused search (one kernel call; ``c1 = 0.4``, steps ``2^-j``) on the inputs
    of the batched search whose result is ``ref`` (its trajectories in ``trials``): the
    same steps and flags, the costs and trajectories to rounding (``atol`` for these:
    the same operations in the same order, but in separately compiled kernels, whose
    last bits have been seen to differ between processes). Returns its outputs ``(alpha,
    J, ok, x, u)``."""
    grid = 0.5 ** torch.arange(20, dtype=F64)
    terms = cost.compiled_terms(x, u)
    assert terms is not None and compiled_step_of(dyn) is not None
    out = dispatch.armijo_rollout_compiled(
        *compiled_step_of(dyn), x, u, K, k, lo, hi, grid, J0, slope, curv, 0.4,
        ROUNDOFF_NOISE * torch.finfo(F64).eps, active, terms,
    )  # fmt: skip
    alpha, J, ok, x_new, u_new = out
    x_ref, u_ref = trials.select(ref[0])
    assert torch.equal(alpha, ref[0]) and torch.equal(ok, ref[2])
    torch.testing.assert_close(J, ref[1], rtol=1e-13, atol=0.0)
    torch.testing.assert_close(x_new[ok], x_ref[ok], rtol=1e-12, atol=atol)
    torch.testing.assert_close(u_new[ok], u_ref[ok], rtol=1e-12, atol=atol)
    return out


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
        evaluate, trials = _batched_evaluation(dyn, cost, x, u, K, k, lo, hi)
        # a large c1: the model decrease decides which step passes
        ref = armijo_search(
            evaluate, J0, slope, curvature=curv, c1=0.4, active=active, skip_settled=True,
            first_trials=2, pass_size=3,
        )  # fmt: skip
        out = _fused_equals_batched(
            ref, trials, dyn, cost, x, u, K, k, lo, hi, J0, slope, curv, active, atol=1e-14
        )
    alpha, J, ok, x_new, u_new = out
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


@pytest.mark.codegen
@pytest.mark.parametrize("bounded", [False, True])
def test_fused_search_on_many_rows_equals_the_batched_search(bounded, monkeypatch):
    """With a learned model's step on many rows at once (the elements' trials side by
    side, one call per time step) the fused search takes the steps and flags of the
    batched search on the one-row step, its costs and trajectories to rounding (the
    wide layers' products sum in BLAS's order)."""
    from torchslq._backend.model_fns import rows_step

    B = 9
    monkeypatch.setattr(dispatch, "MIN_BLOCK_ROWS", 4)  # (on rows from 4 elements)
    g = torch.Generator().manual_seed(5)
    cost = _cost(B, g, per_element=True)
    dyn, x, u, K, k, slope, curvature, active = _search_inputs(B, g, cost, "learned")
    for b, factor in ((4, 40.0), (6, 15.0), (7, 100.0)):  # long steps: backtracking
        k[b] *= factor
        slope[b] *= factor
    lo = hi = None
    if bounded:
        lo = torch.full((B, T, 1), -0.6, dtype=F64)
        hi = torch.full((B, T, 1), 0.8, dtype=F64)
    with torch.no_grad(), compiled_cost_evaluation():
        assert B >= dispatch.MIN_BLOCK_ROWS and rows_step(compiled_step_of(dyn)[0]) is not None
        J0 = cost(x, u)
        evaluate, trials = _batched_evaluation(dyn, cost, x, u, K, k, lo, hi)
        with monkeypatch.context() as one_row:  # the reference on the one-row step
            one_row.setattr(dispatch, "MIN_BLOCK_ROWS", 10**9)
            ref = armijo_search(evaluate, J0, slope, c1=0.4, active=active, skip_settled=True)
        alpha, J, ok, _, _ = _fused_equals_batched(
            ref, trials, dyn, cost, x, u, K, k, lo, hi, J0, slope, None, active, atol=1e-13
        )
    # the cases the inputs were built for happened, and steps of several sizes
    assert bool(ok[2]) and float(alpha[2]) == 1.0 and not bool(ok[3])
    assert len(set(alpha[ok].tolist())) >= 2


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
    assert bool(r_fused.converged.all())
    # the same iterates to rounding in the first iterations; rounding can move a later
    # step of this swing-up (a clean-clone run saw 73 against 79 iterations for one
    # element), so the solves are compared at their end by the minimiser they reach
    first = min(r_fused.history["cost"].shape[1], r_torch.history["cost"].shape[1], 6)
    torch.testing.assert_close(
        r_fused.history["cost"][:, :first], r_torch.history["cost"][:, :first], rtol=1e-10, atol=0.0
    )
    # (perturbing x0 by 3e-16 relative moves these solves by up to 1 iteration per
    # element, their costs by 1e-15 relative and their controls by under 3e-7)
    torch.testing.assert_close(r_fused.cost, r_torch.cost, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(r_fused.u, r_torch.u, rtol=1e-5, atol=1e-6)


@pytest.mark.codegen
def test_solve_on_many_rows_equals_the_one_row_step(monkeypatch):
    """A learned model's ILQR solve with its step on many rows at once (the fused
    searches and the rollouts) takes the iterations of the solve on its one-row step
    and, to rounding, reaches the same solution."""
    from torchslq._backend import _numba_search

    B = 6
    g = torch.Generator().manual_seed(1)
    problem = ts.Problem(_ResidualCartPole(), _cost(B, g, per_element=True), 30)
    x0 = torch.zeros(B, 4, dtype=F64)
    x0[:, 1] = 0.3 * torch.randn(B, generator=g, dtype=F64)
    solver = ts.ILQR(max_iter=200, tol=1e-6, progress=False)
    monkeypatch.setattr(dispatch, "MIN_BLOCK_ROWS", 4)  # (on rows from 4 elements)
    launches = []
    kernel = _numba_search.armijo_rows_kernel
    monkeypatch.setattr(
        _numba_search, "armijo_rows_kernel", lambda *a: launches.append(1) or kernel(*a)
    )
    on_rows = solver.solve(problem, x0)
    monkeypatch.setattr(dispatch, "MIN_BLOCK_ROWS", 10**9)
    taken = len(launches)
    one_row = solver.solve(problem, x0)
    assert taken > 10 and len(launches) == taken  # every search on rows, then none
    # one element stalls at the precision limit, where rounding decides its last
    # iterations (perturbing x0 by 1e-14 relative moves it by an iteration and its
    # controls by 5e-6, the others by 2e-14): the others are compared
    both = on_rows.converged & one_row.converged
    assert int(both.sum()) >= B - 1
    assert torch.equal(on_rows.iterations[both], one_row.iterations[both])
    torch.testing.assert_close(on_rows.u[both], one_row.u[both], rtol=1e-7, atol=1e-8)
    torch.testing.assert_close(on_rows.cost, one_row.cost, rtol=1e-10, atol=0.0)


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
