"""GoPRONTO (Algorithms 2-4), first-order PRONTO (Algorithm 1) and the gradient baseline."""

from __future__ import annotations

import math

import pytest
import torch

import torchslq
from torchslq import Dynamics, GoPRONTO, GradientMethod, Problem, QuadraticCost
from torchslq.solvers.gopronto import closed_loop_growth, curve_gradient, project
from torchslq.solvers.rollout import rollout
from torchslq.tasks import pendulum_swingup

DT = torch.float64


class Linear(Dynamics):
    """x+ = A x + B u (batch-shared)."""

    def __init__(self, A: torch.Tensor, B: torch.Tensor):
        super().__init__()
        self.state_dim, self.control_dim = A.shape[0], B.shape[1]
        self.register_buffer("A", A)
        self.register_buffer("B", B)

    def forward(self, x, u):
        return x @ self.A.mT + u @ self.B.mT


class TwoLink(Dynamics):
    """A small smooth nonlinear system (n = 3, m = 2) with a cross-coupled cost below."""

    state_dim, control_dim = 3, 2

    def forward(self, x, u):
        a, b, c = x.unbind(-1)
        u1, u2 = u.unbind(-1)
        return torch.stack(
            [
                a + 0.1 * b,
                b + 0.1 * (torch.sin(a) - 0.2 * b + u1 * torch.cos(c)),
                c + 0.1 * (u2 + 0.3 * a * b),
            ],
            dim=-1,
        )


def nonquadratic_cost() -> torchslq.Cost:
    def stage(x, u, t):
        return (x**2).sum(-1) + 0.1 * (u**2).sum(-1) + 0.05 * torch.cos(x[..., 0]) * u[..., 0]

    def terminal(x):
        return 10.0 * (x**2).sum(-1) + x[..., 1] ** 4

    return torchslq.Cost(stage, terminal, state_dim=3, control_dim=2)


def unstable_problem(T: int = 60) -> tuple[Problem, torch.Tensor]:
    """A discretised double-pole unstable system (eigenvalues 1.25 and 1.1)."""
    A = torch.tensor([[1.2, 0.1], [0.05, 1.15]], dtype=DT)
    B = torch.tensor([[0.0], [0.1]], dtype=DT)
    cost = QuadraticCost(
        torch.eye(2, dtype=DT), 0.1 * torch.eye(1, dtype=DT), Qf=10 * torch.eye(2, dtype=DT)
    )
    x0 = torch.tensor([[1.0, -0.5], [0.3, 0.8]], dtype=DT)
    return Problem(Linear(A, B), cost, T), x0


# ---------------------------------------------------------------------------- the gradient
def test_costate_gradient_equals_autograd():
    torch.manual_seed(0)
    T, B = 12, 3
    prob = Problem(TwoLink(), nonquadratic_cost(), T)
    f = prob.transition
    x0 = 0.5 * torch.randn(B, 3, dtype=DT)
    alpha = 0.3 * torch.randn(B, T, 3, dtype=DT)
    alpha[:, 0] = x0
    mu = 0.3 * torch.randn(B, T, 2, dtype=DT)
    K = 0.5 * torch.randn(B, T, 2, 3, dtype=DT)

    a = alpha.clone().requires_grad_(True)
    m = mu.clone().requires_grad_(True)
    x, u = project(f, x0, a, m, K)
    J = prob.cost(x, u).sum()
    ga_ref, gm_ref = torch.autograd.grad(J, (a, m))

    with torch.no_grad():
        x, u = project(f, x0, alpha, mu, K)
        A, Bm = torchslq.linearize(f, x[:, :T], u)
        e = prob.cost.quadratize(x, u)
        ga, gm, _ = curve_gradient(A, Bm, e.lx, e.lu, K)
    assert torch.allclose(gm, gm_ref, atol=1e-8, rtol=1e-8)
    assert torch.allclose(ga, ga_ref, atol=1e-8, rtol=1e-8)
    assert ga_ref.abs().max() > 1e-3  # the alpha part is not trivially zero


def test_projection_is_a_projection():
    torch.manual_seed(1)
    T, B = 15, 2
    prob = Problem(TwoLink(), nonquadratic_cost(), T)
    f = prob.transition
    x0 = 0.5 * torch.randn(B, 3, dtype=DT)
    alpha = torch.randn(B, T, 3, dtype=DT)
    mu = torch.randn(B, T, 2, dtype=DT)
    K = 0.3 * torch.randn(B, T, 2, 3, dtype=DT)
    x, u = project(f, x0, alpha, mu, K)
    # P(alpha, mu) is a trajectory of f ...
    assert torch.allclose(rollout(f, x0, u), x, atol=1e-12)
    # ... and P(P(c)) = P(c)
    x2, u2 = project(f, x0, x[:, :T], u, K)
    assert torch.allclose(x2, x, atol=1e-12) and torch.allclose(u2, u, atol=1e-12)
    # while the curve itself is not a trajectory (the test is not vacuous)
    assert (x[:, :T] - alpha).abs().max() > 1e-2


def test_closed_loop_growth_matches_matrix_powers():
    A = torch.tensor([[1.1, 0.2], [0.0, 0.9]], dtype=DT)
    T = 30
    Ab = A.expand(1, T, 2, 2)
    Bb = torch.zeros(1, T, 2, 1, dtype=DT)
    K = torch.zeros(1, T, 1, 2, dtype=DT)
    got = closed_loop_growth(Ab, Bb, K, probes=2)
    g = torch.Generator().manual_seed(1234)
    V = torch.randn(2, 2, generator=g, dtype=torch.float64)
    V = V / V.norm(dim=0, keepdim=True)
    ref = max(
        1.0,
        max(float((torch.linalg.matrix_power(A, t) @ V).norm(dim=0).max()) for t in range(T + 1)),
    )
    assert math.isclose(float(got), ref, rel_tol=1e-12)
    assert ref > 10  # the open loop grows (1.1^30 ~ 17)


# ---------------------------------------------------------------------------- solves
def test_unstable_system_open_loop_blows_up_gopronto_bounded():
    T = 60
    prob, x0 = unstable_problem(T)
    A = prob.dynamics.A.expand(2, T, 2, 2)
    Bm = prob.dynamics.B.expand(2, T, 2, 1)
    Q, R = prob.cost.weights(T)
    sol = torchslq.lqr_solve(A, Bm, Q, R, x0=x0)
    J_opt = prob.cost(sol.x, sol.u)  # independent: the exact LQ optimum

    gm = GradientMethod(max_iter=30, line_search="armijo", progress=False).solve(prob, x0)
    # the open-loop rollout (7) of the unstable system explodes from the start (cost
    # ~1e11 at u = 0); the method stalls with a huge gradient (its scale grows like
    # 1.25^t backwards in time) far from the optimum
    assert bool((gm.history["cost"][:, 0] > 1e10).all())
    assert not gm.converged.any()
    assert bool((gm.grad_norm > 1e4).all())
    assert bool((gm.cost > 1.3 * J_opt).all())

    r = GoPRONTO(max_iter=150, tol=1e-6, progress=False).solve(prob, x0)
    assert r.converged.all(), r.status_names()
    assert r.x.abs().max() < 5.0
    # every iterate's cost stays bounded (monotone Armijo descent from a bounded start)
    hist = r.history["cost"]
    # from the same zero input curve the projected (closed-loop) start is bounded
    assert bool(torch.isfinite(hist).all()) and float(hist.max()) < 1e4
    assert torch.allclose(r.cost, J_opt, rtol=1e-9)


@pytest.mark.parametrize("variant", ["gradient", "conjugate", "heavy_ball", "nesterov"])
def test_variants_decrease_cost_and_reach_small_gradient(variant):
    torch.manual_seed(0)
    prob = Problem(TwoLink(), nonquadratic_cost(), 15)
    x0 = 0.5 * torch.randn(2, 3, dtype=DT)
    ref = torchslq.ILQR(max_iter=100, progress=False).solve(prob, x0)  # independent solver
    assert ref.converged.all()
    r = GoPRONTO(variant=variant, max_iter=200, tol=1e-7, progress=False).solve(prob, x0)
    assert r.converged.all(), (variant, r.status_names())
    assert bool((r.grad_norm < 1e-7).all())
    hist = r.history["cost"]
    assert bool((hist[:, 1:] <= hist[:, :-1] + 1e-12).all())  # Armijo: never increases
    assert bool((hist[:, -1] < hist[:, 0]).all())
    assert torch.allclose(r.cost, ref.cost, rtol=1e-9)
    assert torch.allclose(r.u, ref.u, atol=1e-5)


@pytest.mark.parametrize("variant", ["gradient", "nesterov"])
def test_variants_on_pendulum_swingup(variant):
    prob, x0 = pendulum_swingup(batch=2, horizon=40)
    r = GoPRONTO(variant=variant, max_iter=40, progress=False).solve(prob, x0)
    hist, g = r.history["cost"], r.history["grad_norm"]
    assert bool((hist[:, 1:] <= hist[:, :-1] + 1e-9).all())
    assert bool((hist[:, -1] < 0.1 * hist[:, 0]).all())
    assert bool((g[:, -1] < 0.1 * g[:, 0]).all())
    # the returned trajectory is the projection of the returned curve
    x, u = project(prob.transition, x0, r.alpha, r.mu, r.K)
    assert torch.allclose(x, r.x, atol=1e-10) and torch.allclose(u, r.u, atol=1e-10)
