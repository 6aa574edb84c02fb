"""ILQR with multiple shooting (``shooting="multiple"``, :mod:`torchslq.solvers.shooting`).

Checked against independent computations: a dense KKT solve of an LQ problem started
from nodes that violate the dynamics, single-shooting ILQR's optimum and autograd's
gradient of ``J(U)`` through a rollout written here, per-problem solves against the
batch; and that the model is called a fixed number of times per iteration, not once per
time step.
"""

from __future__ import annotations

import math

import pytest
import torch
from test_ilqr import PEND_X0, lq_case, pendulum_nonconvex, pendulum_rk4
from test_lq_kernel import dense_kkt
from torch import nn

from torchslq import DDP, ILQR, Problem, QuadraticCost, Status, discretize
from torchslq.dynamics import Dynamics
from torchslq.systems import CartPole

pytestmark = pytest.mark.filterwarnings(
    "ignore:`torch.jit.script` is deprecated:DeprecationWarning"
)

torch.set_num_threads(1)
F64 = torch.float64
MS = dict(shooting="multiple", progress=False)


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / max(float(b.norm()), 1e-300))


# ----------------------------------------------------------------------------- LQ


def test_lq_problem_from_nodes_off_the_dynamics_is_solved_in_one_step():
    """Linear dynamics, quadratic cost: the LQ step with the defects as affine terms is
    the optimum, whatever the nodes. Started from random nodes (large defects) and
    random controls, one step reaches the dense KKT solution and closes the defects."""
    problem, x0, u_init, d = lq_case(seed=5, T=10)
    Bsz, T, n = x0.shape[0], problem.horizon, problem.state_dim
    g = torch.Generator().manual_seed(6)
    x_init = 2.0 * torch.randn(Bsz, T + 1, n, generator=g, dtype=F64)
    x_init[:, 0] = x0
    gaps0 = problem.dynamics(x_init[:, :T], u_init) - x_init[:, 1:]
    assert float(gaps0.abs().max()) > 1.0  # really off the dynamics
    res = ILQR(**MS).solve(problem, x0, u_init, x_init=x_init)
    assert res.status_names() == ["converged"] * Bsz
    assert torch.equal(res.iterations, torch.ones(Bsz, dtype=torch.int64))
    for b in range(Bsz):
        x, u, _, cost = dense_kkt(d["A"], d["B"], d["Q"], d["R"], x0[b], d["q"], d["r"],
                                  d["S"], d["c"])  # fmt: skip
        assert rel_err(res.u[b], u) < 1e-9
        assert rel_err(res.x[b], x) < 1e-9
        torch.testing.assert_close(res.cost[b], cost, rtol=1e-10, atol=1e-10)


def test_option_validation():
    with pytest.raises(ValueError, match="shooting"):
        ILQR(shooting="double")
    with pytest.raises(ValueError, match="u_max"):
        ILQR(shooting="multiple", u_max=1.0)
    with pytest.raises(ValueError, match="constraints"):
        from torchslq import Constraints

        ILQR(shooting="multiple", constraints=Constraints(x_max=1.0))
    with pytest.raises(ValueError, match="defect_tol"):
        ILQR(shooting="multiple", defect_tol=-1.0)
    with pytest.raises(ValueError, match="DDP supports shooting='single'"):
        DDP(shooting="multiple")


# ----------------------------------------------------------------------------- nonlinear


def swing_up(B: int):
    """trajax's cart-pole swing-up (the user-models benchmark's problem), T = 50."""
    dyn = discretize(CartPole(mc=1.0, mp=0.1, l=0.5), 0.05, "rk4").double()
    goal = torch.tensor([0.0, math.pi, 0.0, 0.0], dtype=F64)
    cost = QuadraticCost(
        Q=torch.zeros(4, 4, dtype=F64),
        R=0.02 * torch.eye(1, dtype=F64),
        Qf=200.0 * torch.eye(4, dtype=F64),
        x_ref=goal,
    )
    x0 = torch.zeros(B, 4, dtype=F64)
    x0[:, 1] = 0.05 * torch.randn(B, generator=torch.Generator().manual_seed(0), dtype=F64)
    return Problem(dyn, cost, 50), x0, goal


def test_swing_up_reaches_the_single_shooting_optimum():
    problem, x0, goal = swing_up(3)
    ms = ILQR(max_iter=500, tol=1e-6, **MS).solve(problem, x0)
    ss = ILQR(max_iter=500, tol=1e-6, progress=False).solve(problem, x0)
    assert bool(ms.converged.all()) and bool(ss.converged.all())
    torch.testing.assert_close(ms.cost, ss.cost, rtol=1e-9, atol=0)
    assert rel_err(ms.u, ss.u) < 1e-4  # both stop at ||dJ/dU|| < 1e-6 (ill-conditioned)
    # the result's states are its controls' rollout (a step written here, not the model)
    cp = problem.dynamics.continuous

    def step(x, u):
        def f(z):
            s, th, sd, thd = z.unbind(-1)
            D = cp.mc + cp.mp * torch.sin(th) ** 2
            sdd = (u[..., 0] + cp.mp * torch.sin(th) * (cp.l * thd**2 + 9.81 * torch.cos(th))) / D
            thdd = (
                -u[..., 0] * torch.cos(th)
                - cp.mp * cp.l * thd**2 * torch.cos(th) * torch.sin(th)
                - (cp.mc + cp.mp) * 9.81 * torch.sin(th)
            ) / (cp.l * D)
            return torch.stack([sd, thd, sdd, thdd], -1)

        dt = 0.05
        k1 = f(x)
        k2 = f(x + 0.5 * dt * k1)
        k3 = f(x + 0.5 * dt * k2)
        k4 = f(x + dt * k3)
        return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    U = ms.u.clone().requires_grad_(True)
    xs = [x0]
    for t in range(50):
        xs.append(step(xs[-1], U[:, t]))
    x = torch.stack(xs, 1)
    assert rel_err(ms.x, x.detach()) < 1e-12
    J = 0.01 * (U**2).sum((1, 2)) + 100.0 * ((x[:, -1] - goal) ** 2).sum(-1)
    torch.testing.assert_close(J.detach(), ms.cost, rtol=1e-12, atol=0)
    (grad,) = torch.autograd.grad(J.sum(), U)
    assert float(grad.flatten(1).norm(dim=1).max()) < 1e-6


def test_batch_equals_single_solves():
    problem = pendulum_nonconvex()
    rb = ILQR(tol=1e-6, max_iter=100, **MS).solve(problem, PEND_X0)
    assert bool(rb.converged.all()), rb.status_names()
    assert len(set(rb.iterations.tolist())) > 1
    for i in range(PEND_X0.shape[0]):
        r1 = ILQR(tol=1e-6, max_iter=100, **MS).solve(problem, PEND_X0[i])
        assert int(rb.iterations[i]) == int(r1.iterations)
        assert rel_err(rb.u[i], r1.u) < 1e-12
        torch.testing.assert_close(rb.cost[i], r1.cost, rtol=1e-13, atol=0)
    # compaction solves the running elements only, with the same result
    rc = ILQR(tol=1e-6, max_iter=100, compact=True, **MS).solve(problem, PEND_X0)
    assert torch.equal(rc.iterations, rb.iterations)
    assert rel_err(rc.u, rb.u) < 1e-12


def test_pendulum_in_float32():
    problem = pendulum_nonconvex()
    r64 = ILQR(tol=1e-6, max_iter=100, **MS).solve(problem, PEND_X0)
    p32 = pendulum_nonconvex(discretize(problem.dynamics.continuous.float(), 0.05, "rk4"))
    r32 = ILQR(tol=1e-3, max_iter=100, **MS).solve(p32, PEND_X0.float())
    assert r32.u.dtype == torch.float32
    assert bool(torch.isfinite(r32.cost).all())
    torch.testing.assert_close(r32.cost.double(), r64.cost, rtol=1e-4, atol=1e-4)


class CountingResidual(Dynamics):
    """``pendulum_rk4(x, u) + mlp([x, u])`` (a learned residual on the torch path),
    counting its calls."""

    state_dim, control_dim = 2, 1

    def __init__(self):
        super().__init__()
        torch.manual_seed(3)
        self.mlp = nn.Sequential(nn.Linear(3, 16), nn.Tanh(), nn.Linear(16, 2)).double()
        with torch.no_grad():
            self.mlp[-1].weight.mul_(1e-2)
        self.calls = 0

    def forward(self, x, u):
        self.calls += 1
        return pendulum_rk4(x, u, 0.05) + self.mlp(torch.cat([x, u], -1))


def test_learned_model_is_called_a_fixed_number_of_times_per_iteration():
    """A model on the torch path: the optimum of single shooting, with a number of
    model calls per iteration that does not grow with the horizon (single shooting
    calls it at least T times per iteration)."""
    dyn = CountingResidual()
    problem = pendulum_nonconvex(dyn)
    T = problem.horizon
    ss = ILQR(tol=1e-8, max_iter=200, progress=False).solve(problem, PEND_X0)
    dyn.calls = 0
    ms = ILQR(tol=1e-8, max_iter=200, **MS).solve(problem, PEND_X0)
    ms_calls = dyn.calls
    assert bool(ms.converged.all()) and bool(ss.converged.all())
    torch.testing.assert_close(ms.cost, ss.cost, rtol=1e-10, atol=0)
    its = int(ms.iterations.max())
    # per iteration: the Jacobians, the line search's passes; plus the final rollout
    assert ms_calls <= 6 * (its + 1) + T, (ms_calls, its)
    dyn.calls = 0
    ILQR(tol=1e-8, max_iter=200, progress=False).solve(problem, PEND_X0)
    assert dyn.calls >= T * int(ss.iterations.max())


def test_status_of_a_non_finite_element():
    """An element whose model returns NaN ends ``non_finite``; the others are solved as
    without it."""

    class Masked(Dynamics):
        state_dim, control_dim = 2, 1

        def __init__(self, mask):
            super().__init__()
            self.register_buffer("mask", mask)

        def forward(self, x, u):
            return pendulum_rk4(x, u, 0.05) * self.mask

    mask = torch.ones(3, 1, 1, dtype=F64)
    mask[1] = float("nan")
    x0 = PEND_X0[:3]
    rb = ILQR(tol=1e-6, max_iter=100, **MS).solve(pendulum_nonconvex(Masked(mask)), x0)
    ref = ILQR(tol=1e-6, max_iter=100, **MS).solve(pendulum_nonconvex(), x0)
    assert rb.status_names()[1] == "non_finite"
    assert int(rb.status[0]) == int(rb.status[2]) == Status.CONVERGED
    for i in (0, 2):
        assert rel_err(rb.u[i], ref.u[i]) < 1e-10


def test_learned_residual_example():
    """``examples/learned_residual_swingup.py --quick``: the grey-box model fits the real
    system, and both shootings reach the same optimum, whose plan swings the real
    cart-pole up with its feedback gains."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "examples" / "learned_residual_swingup.py"
    spec = importlib.util.spec_from_file_location("_example_learned_residual", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = mod.main(["--quick"])
    assert out["fit_mse"] < 1e-4
    for shooting in ("single", "multiple"):
        assert out[shooting]["converged"] == out["B"], shooting
        assert out[shooting]["real_final_error_max"] < 0.3, shooting
    assert out["max_rel_cost_gap"] < 1e-8


def test_mpc_layer_with_multiple_shooting_has_the_single_shooting_gradients():
    """The MPC layer's solve by multiple shooting: the same controls and implicit
    gradients (w.r.t. a model parameter and x0) as with single shooting, whose gradients
    tests/test_mpc.py checks against finite differences; warm-started steps run too."""
    from torchslq import MPC
    from torchslq.systems import Pendulum

    goal = torch.tensor([math.pi, 0.0], dtype=F64)
    cost = QuadraticCost(
        Q=torch.diag(torch.tensor([1.0, 0.1], dtype=F64)), R=0.1 * torch.eye(1, dtype=F64),
        x_ref=goal,
    )  # fmt: skip
    x0 = torch.tensor([[0.3, 0.0], [-0.5, 0.2], [0.9, -0.4]], dtype=F64)
    out = {}
    for shooting in ("single", "multiple"):
        mass = torch.nn.Parameter(torch.tensor(0.7, dtype=F64))
        xg = x0.clone().requires_grad_(True)
        solver = ILQR(tol=1e-9, max_iter=200, progress=False, shooting=shooting)
        policy = MPC(discretize(Pendulum(mass=mass), 0.1), cost, horizon=10, solver=solver)
        x, u = policy(xg)
        gm, gx = torch.autograd.grad((u**2).sum() + x[:, -1].sum(), (mass, xg))
        out[shooting] = (u.detach(), gm, gx)
        policy.step(x0)
        assert policy.step(x0).shape[0] == 3  # a warm-started second step
    (u1, gm1, gx1), (u2, gm2, gx2) = out["single"], out["multiple"]
    assert rel_err(u2, u1) < 1e-8
    torch.testing.assert_close(gm2, gm1, rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(gx2, gx1, rtol=1e-7, atol=1e-9)


def test_a_quadratic_costs_hessians_are_projected_once_per_solve(monkeypatch):
    """Multiple shooting floors the cost Hessians' eigenvalues at every iteration; a
    QuadraticCost's Hessians are the same tensors at every iteration, so they are
    projected once per solve, with the same solve as projecting them every time (a cost
    whose expansion returns new tensors)."""
    from torchslq.solvers import newton

    problem, x0, _ = swing_up(3)
    calls = []
    project = newton.project_psd

    def counted(H, floor):
        calls.append(H.shape)
        return project(H, floor)

    monkeypatch.setattr(newton, "project_psd", counted)
    once = ILQR(max_iter=60, tol=1e-6, **MS).solve(problem, x0)
    assert len(calls) == 2  # the stage and the terminal Hessians, for the whole solve
    assert int(once.iterations.max()) > 5

    class Fresh(QuadraticCost):  # the same cost, its Hessians new tensors at each call
        def quadratize(self, x, u):
            e = super().quadratize(x, u)
            e.lxx, e.luu = e.lxx.clone(), e.luu.clone()
            return e

    c = problem.cost
    fresh = Problem(problem.dynamics, Fresh(Q=c.Q, R=c.R, Qf=c.Qf, x_ref=c.x_ref), problem.horizon)
    calls.clear()
    every = ILQR(max_iter=60, tol=1e-6, **MS).solve(fresh, x0)
    assert len(calls) == 2 * (int(every.iterations.max()) + 1)
    for name in ("u", "x", "cost", "iterations", "status"):
        assert torch.equal(getattr(once, name), getattr(every, name)), name
