"""Tests of :class:`torchslq.ILQR` against independent computations (float64):

* LQ problem (linear dynamics, a general :class:`torchslq.Cost` that is quadratic with a
  ``u'Sx`` cross term and linear terms): one iteration lands on ``lqr_solve``'s optimum;
* quadratic cost: iLQR and closed-loop Armijo SLQ are both Gauss-Newton, same solution;
  a general ``Cost`` written as the same quadratic gives the same solve;
* non-convex cost: the cart-pole swing-up of Lieskovsky et al. (2025), Section V-B
  (running cost ``1 + cos(theta) + 10 s^2 + 3e-2 u^2``, no final cost), with and
  without the eigenvalue floor;
* per-element behaviour: batch == single solves, a NaN element is isolated, the
  Levenberg-Marquardt ``mu`` of an element whose ``Quu`` is indefinite at ``mu = 0``
  adapts without touching the others; the ``rtol`` stopping rule; validation.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import pytest
import torch

from torchslq import (
    ILQR,
    SLQ,
    Cost,
    Problem,
    QuadraticCost,
    Status,
    discretize,
    linearize,
    lqr_solve,
)
from torchslq.dynamics import Dynamics
from torchslq.systems import CartPole, Pendulum

# forward-mode AD (jvp) makes torch load jit-scripted decompositions once
pytestmark = pytest.mark.filterwarnings(
    "ignore:`torch.jit.script` is deprecated:DeprecationWarning"
)

torch.set_num_threads(1)

F64 = torch.float64
SQRT_EPS = math.sqrt(torch.finfo(F64).eps)


# ----------------------------------------------------------------------------- helpers


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / max(float(b.norm()), 1e-300))


class Linear(Dynamics):
    """``x+ = A x + B u + c`` (time-invariant; Jacobians by autodiff)."""

    def __init__(self, A, B, c):
        super().__init__()
        self.state_dim, self.control_dim = A.shape[-1], B.shape[-1]
        self.register_buffer("A", A)
        self.register_buffer("B", B)
        self.register_buffer("c", c)

    def forward(self, x, u):
        return x @ self.A.mT + u @ self.B.mT + self.c


class Masked(Dynamics):
    """``inner(x, u) * mask`` with a per-element ``mask (B, 1, 1)`` (1 or nan)."""

    def __init__(self, inner: Dynamics, mask: torch.Tensor):
        super().__init__()
        self.inner = inner
        self.state_dim, self.control_dim = inner.state_dim, inner.control_dim
        self.register_buffer("mask", mask)

    def forward(self, x, u):
        return self.inner(x, u) * self.mask


def pendulum_rk4(x, u, dt, b=0.1, g=9.81):
    """One RK4 step of the unit pendulum ``thdd = tau - b thd - g sin th``, written here
    independently of torchslq (``x (..., 2)``, ``u (..., 1)``)."""

    def f(z):
        return torch.stack([z[..., 1], u[..., 0] - b * z[..., 1] - g * torch.sin(z[..., 0])], -1)

    k1 = f(x)
    k2 = f(x + 0.5 * dt * k1)
    k3 = f(x + 0.5 * dt * k2)
    k4 = f(x + dt * k3)
    return x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


def my_rollout(step, x0, U):
    xs = [x0]
    for t in range(U.shape[0]):
        xs.append(step(xs[-1], U[t]))
    return torch.stack(xs)


# ----------------------------------------------------------------------------- 1. LQ


def lq_problem(seed=3, n=3, m=2, T=12, Bsz=3):
    """A linear-quadratic problem (time-varying weights with cross terms, affine
    dynamics), ``x0``, ``u_init`` and its :func:`lqr_solve` solution."""
    problem, x0, u_init, d = lq_case(seed, n, m, T, Bsz)
    lq = lqr_solve(
        d["A"].expand(Bsz, T, n, n),
        d["B"].expand(Bsz, T, n, m),
        d["Q"].expand(Bsz, T + 1, n, n),
        d["R"].expand(Bsz, T, m, m),
        x0,
        q=d["q"].expand(Bsz, T + 1, n),
        r=d["r"].expand(Bsz, T, m),
        S=d["S"].expand(Bsz, T, m, n),
        c=d["c"].expand(Bsz, T, n),
    )
    return problem, x0, u_init, lq


def lq_case(seed=3, n=3, m=2, T=12, Bsz=3):
    """``(problem, x0, u_init, data)``: the problem of :func:`lq_problem` and its data
    ``A (T,n,n), B, Q (T+1,n,n), R, q, r, S, c`` (shared by the batch)."""
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(n, dtype=F64) + 0.3 * torch.randn(n, n, generator=g, dtype=F64)
    Bm = torch.randn(n, m, generator=g, dtype=F64)
    c = 0.1 * torch.randn(n, generator=g, dtype=F64)
    L = torch.randn(T, n + m, n + m, generator=g, dtype=F64) / (n + m) ** 0.5
    H = L @ L.mT + 0.1 * torch.eye(n + m, dtype=F64)  # joint Hessian: S is a real cross term
    Q, R, S = H[:, :n, :n], H[:, n:, n:], H[:, n:, :n]
    Lf = torch.randn(n, n, generator=g, dtype=F64)
    Qf = Lf @ Lf.T + torch.eye(n, dtype=F64)
    q = torch.randn(T + 1, n, generator=g, dtype=F64)
    r = torch.randn(T, m, generator=g, dtype=F64)

    def stage(x, u, t):  # 1/2 x'Q_t x + 1/2 u'R_t u + u'S_t x + q_t'x + r_t'u
        return (
            0.5 * torch.einsum("...ti,tij,...tj->...t", x, Q[t], x)
            + 0.5 * torch.einsum("...ti,tij,...tj->...t", u, R[t], u)
            + torch.einsum("...ti,tij,...tj->...t", u, S[t], x)
            + (q[t] * x).sum(-1)
            + (r[t] * u).sum(-1)
        )

    def terminal(x):
        return 0.5 * torch.einsum("...i,ij,...j->...", x, Qf, x) + (q[T] * x).sum(-1)

    problem = Problem(Linear(A, Bm, c), Cost(stage, terminal, state_dim=n, control_dim=m), T)
    x0 = torch.randn(Bsz, n, generator=g, dtype=F64)
    u_init = 3.0 * torch.randn(Bsz, T, m, generator=g, dtype=F64)
    data = dict(
        A=A.expand(T, n, n), B=Bm.expand(T, n, m), Q=torch.cat([Q, Qf[None]]), R=R, q=q,
        r=r, S=S, c=c.expand(T, n),
    )  # fmt: skip
    return problem, x0, u_init, data


@pytest.mark.parametrize("floor", [None, SQRT_EPS])
def test_lq_problem_one_iteration(floor):
    """The second-order expansion of a quadratic cost is exact and the dynamics are
    linear: the first full step is the optimum (the eigenvalue floor, below every
    eigenvalue of the joint Hessian here, changes nothing)."""
    problem, x0, u_init, lq = lq_problem()
    assert bool((lq.status == Status.CONVERGED).all())
    res = ILQR(hessian_floor=floor, progress=False).solve(problem, x0, u_init)
    assert res.status_names() == ["converged"] * 3
    assert torch.equal(res.iterations, torch.ones(3, dtype=torch.int64))
    assert bool((res.history["step"][:, 1] == 1.0).all())
    assert rel_err(res.u, lq.u) < 1e-8
    assert rel_err(res.x, lq.x) < 1e-8
    torch.testing.assert_close(res.cost, lq.cost, rtol=1e-10, atol=1e-10)
    assert bool((res.grad_norm < 1e-8 * res.history["grad_norm"][:, 0]).all())
    # the feedback gains are the LQ optimum's
    assert rel_err(res.K, lq.K) < 1e-8
    # and it is a real step: the initial guess was far from the optimum
    assert bool((res.history["cost"][:, 0] > res.cost + 1.0).all())


def test_lq_problem_unbatched():
    problem, x0, u_init, lq = lq_problem()
    r1 = ILQR(progress=False).solve(problem, x0[1], u_init[1])
    assert r1.u.shape == (12, 2) and r1.x.shape == (13, 3) and r1.K.shape == (12, 2, 3)
    assert r1.status.shape == () and int(r1.status) == Status.CONVERGED
    assert rel_err(r1.u, lq.u[1]) < 1e-8


# ----------------------------------------------------------------------------- 2. vs SLQ


def swing_up_quadratic(T=30, dt=0.05, general=False) -> Problem:
    dyn = discretize(Pendulum(damping=0.1), dt, "rk4")
    Q = torch.diag(torch.tensor([0.1, 0.01], dtype=F64)) * dt
    R = torch.tensor([[0.1 * dt]], dtype=F64)
    Qf = torch.diag(torch.tensor([10.0, 1.0], dtype=F64))
    xr = torch.tensor([math.pi, 0.0], dtype=F64)
    if not general:
        return Problem(dyn, QuadraticCost(Q, R, Qf=Qf, x_ref=xr.expand(T + 1, 2)), T)

    def stage(x, u, t):
        e = x - xr
        return 0.5 * ((e @ Q) * e).sum(-1) + 0.5 * ((u @ R) * u).sum(-1)

    def terminal(x):
        e = x - xr
        return 0.5 * ((e @ Qf) * e).sum(-1)

    return Problem(dyn, Cost(stage, terminal, state_dim=2, control_dim=1), T)


SWING_X0 = torch.tensor([[0.0, 0.0], [-0.5, 1.0], [1.0, -1.0]], dtype=F64)


def test_quadratic_cost_matches_closed_loop_armijo_slq(backend):
    """With a quadratic cost (and no dynamics Hessian) iLQR's subproblem is SLQ's
    Gauss-Newton subproblem: both find the same local optimum."""
    problem = swing_up_quadratic()
    ri = ILQR(tol=1e-8, progress=False).solve(problem, SWING_X0)
    rs = SLQ(rollout="closed_loop", line_search="armijo", tol=1e-8, progress=False).solve(
        problem, SWING_X0
    )
    assert bool(ri.converged.all()) and bool(rs.converged.all())
    assert bool((ri.grad_norm < 1e-8).all())
    for i in range(SWING_X0.shape[0]):
        assert rel_err(ri.u[i], rs.u[i]) < 1e-6, i
        assert rel_err(ri.x[i], rs.x[i]) < 1e-6, i
    torch.testing.assert_close(ri.cost, rs.cost, rtol=1e-10, atol=0)
    # the swing-up happened (cost far below the initial one, near upright at the end)
    assert bool((ri.cost < 0.2 * ri.history["cost"][:, 0]).all())
    assert bool((torch.cos(ri.x[:, -1, 0]) < -0.9).all())

    # the same quadratic as a general Cost (autodiff derivatives): the same solve
    rg = ILQR(tol=1e-8, progress=False).solve(swing_up_quadratic(general=True), SWING_X0)
    assert torch.equal(rg.iterations, ri.iterations)
    assert rel_err(rg.u, ri.u) < 1e-9
    torch.testing.assert_close(rg.cost, ri.cost, rtol=1e-12, atol=0)


# ----------------------------------------------------------------------------- 3. cart-pole


def cartpole_nonconvex(T=25) -> Problem:
    """Lieskovsky et al. (2025), Section V-B: cart 1 kg, tip 0.1 kg, pole 0.2 m, horizon
    2 s (RK4 with dt = 2/T), ``l = 1 + cos(theta) + 10 s^2 + 3e-2 u^2`` (times dt), no
    final cost. ``cos(theta)`` is concave around the hanging position."""
    dt = 2.0 / T
    dyn = discretize(CartPole(mc=1.0, mp=0.1, l=0.2), dt, "rk4")

    def stage(x, u, t):
        return dt * (1.0 + torch.cos(x[..., 1]) + 10.0 * x[..., 0] ** 2 + 3e-2 * u[..., 0] ** 2)

    return Problem(dyn, Cost(stage, state_dim=4, control_dim=1), T)


CARTPOLE_X0 = torch.tensor([0.0, 1e-3 * math.pi, 0.0, 0.0], dtype=F64)


def _assert_monotone(H: torch.Tensor) -> None:
    noise = 64 * torch.finfo(F64).eps * H[:-1].abs()
    assert bool((H[1:] <= H[:-1] + noise).all()), (H[1:] - H[:-1]).max()


def test_cartpole_nonconvex_with_hessian_floor():
    """With the cost Hessian's eigenvalues clipped at sqrt(eps) (the paper's
    regularisation) iLQR converges to a swing-up from rest."""
    problem = cartpole_nonconvex()
    res = ILQR(max_iter=250, tol=1e-5, hessian_floor=SQRT_EPS, progress=False).solve(
        problem, CARTPOLE_X0
    )
    assert res.status_names() == ["converged"]
    assert float(res.grad_norm) < 1e-5
    H = res.history["cost"]
    assert H.shape == (int(res.iterations) + 1,)
    _assert_monotone(H)
    # staying down costs 2 per second for 2 s; the swing-up is much cheaper
    assert abs(float(H[0]) - 4.0) < 1e-4
    assert float(res.cost) < 3.0
    # the pole ends (near) upright: theta = pi modulo 2 pi
    assert math.cos(float(res.x[-1, 1])) < -0.99
    assert abs(float(res.x[-1, 0])) < 0.1  # and the cart is back near the origin
    # the reported cost is the cost of the reported trajectory
    dt = 2.0 / problem.horizon
    th, s, u = res.x[:-1, 1], res.x[:-1, 0], res.u[:, 0]
    J = dt * (1 + torch.cos(th) + 10 * s**2 + 3e-2 * u**2).sum()
    torch.testing.assert_close(res.cost, J, rtol=1e-12, atol=0)
    # x is the rollout of u
    torch.testing.assert_close(problem.rollout(CARTPOLE_X0[None], res.u[None])[0], res.x)


def test_cartpole_nonconvex_plain_descends():
    """Without the floor ``Quu`` is indefinite along the way (the negative curvature of
    ``cos(theta)`` at the bottom), so only the Levenberg-Marquardt ``mu`` keeps the steps
    descending: every iteration is accepted and lowers the cost, nothing fails.

    (It converges far more slowly than with the floor: still ``grad_norm ~ 5e-3`` after
    600 iterations with T = 25, so only the first iterations are checked here.)"""
    problem = cartpole_nonconvex()
    x = problem.rollout(CARTPOLE_X0[None], torch.zeros(1, problem.horizon, 1, dtype=F64))
    lxx = problem.cost.quadratize(x, torch.zeros(1, problem.horizon, 1, dtype=F64)).lxx
    assert float(torch.linalg.eigvalsh(lxx[0, :-1]).min()) < 0  # non-convex indeed
    res = ILQR(max_iter=30, progress=False).solve(problem, CARTPOLE_X0)
    assert int(res.status) == Status.MAX_ITER
    assert int(res.iterations) == 30
    assert bool((res.history["step"][1:] > 0).all())
    H = res.history["cost"]
    _assert_monotone(H)
    assert float(H[-1]) < float(H[0]) - 0.3


# ----------------------------------------------------------------------------- 4. per element


PEND_T, PEND_DT = 20, 0.05
PEND_X0 = torch.tensor([[0.1, 0.0], [0.3, 0.0], [-0.5, 1.0], [1.0, -1.0]], dtype=F64)


def pendulum_nonconvex(dyn=None) -> Problem:
    """Pendulum swing-up with the energy-like, non-convex cost ``2 (1 + cos theta)``."""
    dt = PEND_DT
    if dyn is None:
        dyn = discretize(Pendulum(damping=0.1), dt, "rk4")

    def stage(x, u, t):
        return dt * (2 * (1 + torch.cos(x[..., 0])) + 0.01 * x[..., 1] ** 2 + 0.1 * u[..., 0] ** 2)

    def terminal(x):
        return 10 * (1 + torch.cos(x[..., 0])) + 0.5 * x[..., 1] ** 2

    return Problem(dyn, Cost(stage, terminal, state_dim=2, control_dim=1), PEND_T)


PEND_SOLVER = dict(tol=1e-6, max_iter=100, progress=False)


@functools.cache
def pendulum_batch():
    return ILQR(**PEND_SOLVER).solve(pendulum_nonconvex(), PEND_X0)


def _assert_same(rb, i, r1, what):
    assert int(rb.iterations[i]) == int(r1.iterations), what
    assert int(rb.status[i]) == int(r1.status), what
    assert rel_err(rb.u[i], r1.u) < 1e-12, what
    assert rel_err(rb.x[i], r1.x) < 1e-12, what
    assert rel_err(rb.K[i], r1.K) < 1e-12, what
    torch.testing.assert_close(rb.cost[i], r1.cost, rtol=1e-13, atol=0)
    torch.testing.assert_close(rb.history["cost"][i, : int(r1.iterations) + 1], r1.history["cost"])


def test_batch_equals_single_solves():
    rb = pendulum_batch()
    assert bool(rb.converged.all()), rb.status_names()
    assert bool((rb.grad_norm < 1e-6).all())
    assert len(set(rb.iterations.tolist())) > 1  # elements really finish at different times
    for i in range(PEND_X0.shape[0]):
        _assert_same(rb, i, ILQR(**PEND_SOLVER).solve(pendulum_nonconvex(), PEND_X0[i]), f"x0 {i}")
    # frozen after convergence: the history repeats the final cost
    for i in range(PEND_X0.shape[0]):
        k = int(rb.iterations[i])
        assert bool((rb.history["cost"][i, k:] == rb.cost[i]).all())
        assert bool((rb.history["step"][i, k + 1 :] == 0).all())


def test_nan_element_is_isolated(backend):
    """Element 1's dynamics return NaN: it is NON_FINITE from the start, and the others
    are exactly their rows of the clean batch (a batch solves every row as if alone)."""
    base = discretize(Pendulum(damping=0.1), PEND_DT, "rk4")
    mask = torch.ones(3, 1, 1, dtype=F64)
    mask[1] = float("nan")
    x0 = torch.stack([PEND_X0[0], PEND_X0[1], PEND_X0[3]])
    rb = ILQR(**PEND_SOLVER).solve(pendulum_nonconvex(Masked(base, mask)), x0)
    ref = pendulum_batch()
    assert rb.status_names()[1] == "non_finite"
    assert int(rb.iterations[1]) == 0
    for i, j in ((0, 0), (2, 3)):
        _assert_same(rb, i, _row(ref, j), f"element {i}")
        assert bool(torch.isfinite(rb.history["cost"][i]).all())
        assert bool(torch.isfinite(rb.K[i]).all())


def _row(res, j):
    """Row ``j`` of a batched result as an unbatched one (for :func:`_assert_same`)."""

    class R:
        pass

    r = R()
    for name in ("u", "x", "K", "cost", "iterations", "status"):
        setattr(r, name, getattr(res, name)[j])
    r.history = {"cost": res.history["cost"][j, : int(res.iterations[j]) + 1]}
    return r


def _count_riccati_passes(monkeypatch) -> dict[str, int]:
    """Count iLQR/DDP's Riccati passes: ``calls["n"]``."""
    import torchslq.solvers.newton as ilqr_mod  # iLQR/DDP's direction

    calls = {"n": 0}
    orig = ilqr_mod.riccati_backward

    def counting(*args, **kwargs):
        calls["n"] += 1
        return orig(*args, **kwargs)

    monkeypatch.setattr(ilqr_mod, "riccati_backward", counting)
    return calls


def test_nan_element_does_not_slow_the_others(monkeypatch):
    """A failed element never stops, slows or poisons the others."""
    calls = _count_riccati_passes(monkeypatch)
    base = discretize(Pendulum(damping=0.1), PEND_DT, "rk4")
    x0 = PEND_X0[1:3]
    solver = ILQR(tol=1e-6, max_iter=3, progress=False)
    solver.solve(pendulum_nonconvex(base), x0)
    clean = calls["n"]
    calls["n"] = 0
    mask = torch.tensor([1.0, float("nan"), 1.0], dtype=F64).reshape(3, 1, 1)
    x0n = torch.stack([x0[0], x0[0], x0[1]])
    solver.solve(pendulum_nonconvex(Masked(base, mask)), x0n)
    assert calls["n"] == clean, (calls["n"], clean)


# ----------------------------------------------------------------------------- 5. mu


MU_T, MU_DT = 20, 0.05
MU_A = torch.tensor([[0.0], [1.0], [0.0], [3.0]], dtype=F64)
MU_X0 = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.5, 1.0], [0.5, 1.0]], dtype=F64)


def mu_problem(a: torch.Tensor) -> Problem:
    """Pendulum to ``theta = 1`` with a per-element control term ``a (-u^2/2 + u^4)``:
    for ``a >= 1`` the control Hessian at ``u = 0`` is negative."""
    dt = MU_DT
    dyn = discretize(Pendulum(damping=0.1), dt, "rk4")

    def stage(x, u, t):
        v = u[..., 0]
        return dt * (
            0.5 * (x[..., 0] - 1.0) ** 2
            + 0.05 * x[..., 1] ** 2
            + 0.1 * v**2
            + a * (-0.5 * v**2 + v**4)
        )

    def terminal(x):
        return 5.0 * (x[..., 0] - 1.0) ** 2 + 0.5 * x[..., 1] ** 2

    return Problem(dyn, Cost(stage, terminal, state_dim=2, control_dim=1), MU_T)


def _J_of_U(a: float, x0: torch.Tensor):
    """``J(U)`` through the independent rollout of this file."""
    dt = MU_DT

    def J(U):
        x = my_rollout(lambda z, v: pendulum_rk4(z, v, dt), x0, U)
        v = U[:, 0]
        run = (
            dt
            * (
                0.5 * (x[:-1, 0] - 1) ** 2
                + 0.05 * x[:-1, 1] ** 2
                + 0.1 * v**2
                + a * (-0.5 * v**2 + v**4)
            ).sum()
        )
        return run + 5.0 * (x[-1, 0] - 1) ** 2 + 0.5 * x[-1, 1] ** 2

    return J


def test_mu_adapts_for_indefinite_control_hessian(backend):
    problem = mu_problem(MU_A)
    T = MU_T
    u0 = torch.zeros(4, T, 1, dtype=F64)
    # at the initial guess, Quu of the last step (luu + B' Phi_xx B, independent of the
    # value recursion) is negative for a >= 1: no factorisation exists at mu = 0
    x = problem.rollout(MU_X0, u0)
    e = problem.cost.quadratize(x, u0)
    A, Bm = linearize(problem.transition, x[:, :T], u0)
    QuuT = e.luu[:, -1] + Bm[:, -1].mT @ e.lxx[:, T] @ Bm[:, -1]
    assert QuuT[:, 0, 0].tolist()[1] < 0 and QuuT[:, 0, 0].tolist()[3] < 0
    assert QuuT[:, 0, 0].tolist()[0] > 0 and QuuT[:, 0, 0].tolist()[2] > 0

    solver = ILQR(tol=1e-8, max_iter=60, progress=False)
    rb = solver.solve(problem, MU_X0)
    assert rb.status_names() == ["converged"] * 4
    assert bool((rb.grad_norm < 1e-8).all())
    for i in range(4):
        H = rb.history["cost"][i, : int(rb.iterations[i]) + 1]
        _assert_monotone(H)
        # a local minimum of J(U): zero gradient, positive definite Hessian (autograd
        # through the independent rollout)
        J = _J_of_U(float(MU_A[i]), MU_X0[i])
        U = rb.u[i].clone().requires_grad_(True)
        (g,) = torch.autograd.grad(J(U), U)
        assert float(g.norm()) < 1e-7
        Hess = torch.autograd.functional.hessian(J, rb.u[i], vectorize=True).reshape(T, T)
        assert float(torch.linalg.eigvalsh(Hess).min()) > 0
        torch.testing.assert_close(J(rb.u[i]), rb.cost[i], rtol=1e-12, atol=0)
    # mu and its schedule are per element: the convex elements solved without the
    # indefinite ones (and vice versa) give exactly their rows of the mixed batch
    for idx in ([0, 2], [1, 3]):
        rs = solver.solve(mu_problem(MU_A[idx]), MU_X0[idx])
        for j, i in enumerate(idx):
            _assert_same(rb, i, _row(rs, j), f"element {i}")
    # the non-convex term was active: the control sits in its wells |u| ~ 1/2, not at 0
    assert float(rb.u[1].abs().min()) > 0.3 and float(rb.u[3].abs().min()) > 0.3


def test_mu_max_stops_an_element_that_needs_more():
    """Element 1 needs ``mu > 0.03`` at its first backward pass (its last-step Quu is
    about -0.037 at u = 0); with ``mu_max = 1e-3`` it should stop, the others not."""
    res = ILQR(mu_max=1e-3, tol=1e-8, max_iter=60, progress=False).solve(
        mu_problem(MU_A[:2]), MU_X0[:2]
    )
    names = res.status_names()
    assert names[0] == "converged" and names[1] != "converged", names


# ----------------------------------------------------------------------------- 6. rtol


def test_rtol_stops_earlier_on_the_same_path():
    """``rtol`` only stops: the iterates are those of the ``rtol = 0`` solve up to the
    first accepted step whose relative cost change is at most ``rtol``.

    (Caveat seen here: the first steps from near the hanging position are damped by a
    large ``mu``, so with ``rtol = 1e-3`` elements 0 and 1 are declared converged after
    one iteration at about twice the optimal cost.)"""
    ref = pendulum_batch()  # rtol = 0
    rtol = 1e-3
    res = ILQR(rtol=rtol, **PEND_SOLVER).solve(pendulum_nonconvex(), PEND_X0)
    assert res.status_names() == ["converged"] * 4
    assert bool((res.iterations < ref.iterations).all())
    for i in range(4):
        k = int(res.iterations[i])
        # the same iterates as the rtol = 0 solve, stopped at iteration k
        torch.testing.assert_close(res.history["cost"][i, : k + 1], ref.history["cost"][i, : k + 1])
        H = res.history["cost"][i, : k + 1]
        change = (H[:-1] - H[1:]).abs() <= rtol * H[:-1].abs()
        # the rule fires at the last accepted step and not before
        assert bool(change[-1]) and not bool(change[:-1].any()), change
        # stopped on the cost change, not on the gradient
        assert float(res.grad_norm[i]) > PEND_SOLVER["tol"]


# ----------------------------------------------------------------------------- 7. validation


def test_option_validation():
    for kw in (
        {"rollout": "open_loop"},
        {"line_search": "exact"},
        {"mu_factor": 1.0},
        {"mu_init": -1.0},
        {"mu_min": 2.0, "mu_max": 1.0},
        {"rtol": -1e-3},
    ):
        with pytest.raises(ValueError):
            ILQR(**kw)
    s = ILQR()
    assert s.options.rollout == "closed_loop" and s.options.line_search == "armijo"
    assert s.mu_init == 0.0 and s.hessian_floor is None


def test_float32_solve_at_its_precision_limit_stops_as_stalled():
    import torchslq as ts

    """In float32 a gradient tolerance of 1e-4 is below what some elements' float32
    gradients can resolve: their line searches keep accepting noise-level steps. With the
    stall rule they stop early with status ``stalled`` (not converged) at the float64
    optimum to float32 precision; without it they run to ``max_iter``."""
    from torchslq.systems import MassChain

    dyn = ts.discretize(MassChain(4, mass=1.0, k3=1.0, damping=0.1), 0.1)
    q = torch.tensor([1.0] * 4 + [0.1] * 4)
    goal = torch.tensor([0.25, 0.5, 0.75, 1.0] + [0.0] * 4)
    x0 = 0.5 * torch.randn(64, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    results = {}
    for dtype in (torch.float32, torch.float64):
        Q = torch.diag(q).to(dtype)
        cost = ts.QuadraticCost(Q, 0.1 * torch.eye(4, dtype=dtype), 10 * Q, x_ref=goal.to(dtype))
        prob = ts.Problem(dyn, cost, 40)
        tol = 1e-4 if dtype == torch.float32 else 1e-9
        for stall in (10, 0) if dtype == torch.float32 else (10,):
            solver = ts.ILQR(max_iter=60, tol=tol, progress=False, stall_iters=stall)
            results[dtype, stall] = solver.solve(prob, x0.to(dtype))
    r, r0, ref = results[torch.float32, 10], results[torch.float32, 0], results[torch.float64, 10]
    assert bool(ref.converged.all())
    stalled = r.status == ts.Status.STALLED
    assert bool(stalled.any()), r.status_names()
    assert set(r.status_names()) <= {"converged", "stalled"}
    assert int(r.iterations[stalled].max()) < 40  # vs 60 (max_iter) without the rule:
    assert set(r0.status_names()) <= {"converged", "max_iter"}
    # without it they keep iterating on noise: most to max_iter, the others (a float32
    # gradient that happens to dip below tol) longer than with the rule
    assert bool((r0.iterations[stalled] > r.iterations[stalled]).all())
    assert 2 * int((r0.status[stalled] == ts.Status.MAX_ITER).sum()) > int(stalled.sum())
    # stopping lost nothing the extra iterations would have gained
    torch.testing.assert_close(r.cost[stalled].double(), ref.cost[stalled], rtol=1e-6, atol=0)
    torch.testing.assert_close(r.cost.double(), r0.cost.double(), rtol=1e-6, atol=0)


def test_stall_iters_validation():
    import torchslq as ts

    with pytest.raises(ValueError, match="stall_iters"):
        ts.ILQR(stall_iters=-1)


@pytest.mark.parametrize("solver_cls", ["ILQR", "DDP-costate", "DDP"])
def test_final_pass_is_skipped_without_changing_the_solve(monkeypatch, solver_cls):
    """At the iteration where the gradient test stops every running element, iLQR/DDP
    skip the second-order terms and the Riccati pass (their step would be discarded).
    Same iterates, costs, statuses, iterations and gains as computing that pass, and
    one pass fewer per solve (counted)."""
    from torchslq import DDP

    make = {
        "ILQR": lambda: ILQR(**PEND_SOLVER),
        "DDP-costate": lambda: DDP(second_order="costate", **PEND_SOLVER),
        "DDP": lambda: DDP(**PEND_SOLVER),
    }[solver_cls]
    calls = _count_riccati_passes(monkeypatch)
    x0 = PEND_X0[:1]
    skipped = make().solve(pendulum_nonconvex(), x0)
    n_skipped = calls["n"]
    calls["n"] = 0
    # the reference: no element ever counts as stopped before its pass
    newton = ILQR._newton  # the direction, told of no gradient tolerance to skip at
    monkeypatch.setattr(
        ILQR, "_newton", lambda self, **kw: dataclasses.replace(newton(self, **kw), skip_tol=None)
    )
    full = make().solve(pendulum_nonconvex(), x0)
    n_full = calls["n"]
    assert bool(full.converged.all()) and bool(skipped.converged.all())
    assert n_skipped == n_full - 1  # the last pass (no restarts on this problem)
    assert torch.equal(skipped.iterations, full.iterations)
    assert torch.equal(skipped.status, full.status)
    assert torch.equal(skipped.u, full.u) and torch.equal(skipped.cost, full.cost)
    torch.testing.assert_close(skipped.grad_norm, full.grad_norm, rtol=0, atol=0)
    # gains: those of the last step taken (one iterate before the final point, whose
    # gradient was still above tol), close to the final point's
    assert bool(torch.isfinite(skipped.K).all()) and bool((skipped.K != 0).any())
    assert rel_err(skipped.K, full.K) < 5e-3


def test_converged_initial_guess_still_gets_gains():
    """An element already converged at the initial guess stops at iteration 0, where
    the pass is never skipped: its gains are the pass's at that point, not zeros."""
    ref = pendulum_batch()
    r = ILQR(**PEND_SOLVER).solve(pendulum_nonconvex(), PEND_X0, ref.u)
    assert bool((r.iterations == 0).all()) and bool(r.converged.all())
    assert bool((r.K != 0).any(dim=(1, 2, 3)).all())
    torch.testing.assert_close(r.K, ref.K, rtol=1e-3, atol=1e-4)


@pytest.mark.parametrize("bounded", [False, True])
def test_x_init_skips_the_initial_rollout_and_gives_the_same_solve(bounded, monkeypatch):
    """solve(..., x_init=rollout of u_init): the same result bit for bit without the
    initial rollout (one model rollout fewer); with bounds that clamp u_init the given
    states are not those of the clamped controls and are ignored (still the same result);
    a wrong shape or first state is an error."""
    import torchslq.solvers.base as slq_mod  # the descent solvers' initial rollout
    from torchslq import discretize
    from torchslq.dynamics.rollout import rollout

    dyn = discretize(CartPole(), 0.05)
    cost = QuadraticCost(torch.eye(4, dtype=F64), 0.1 * torch.eye(1, dtype=F64))
    problem = Problem(dyn, cost, 15)
    g = torch.Generator().manual_seed(2)
    x0 = 0.3 * torch.randn(3, 4, generator=g, dtype=F64)
    u0 = 2.0 * torch.randn(3, 15, 1, generator=g, dtype=F64)
    xs = rollout(problem.transition, x0, u0)
    kw = dict(max_iter=30, tol=1e-9, progress=False)
    solver = ILQR(u_min=-1.0, u_max=1.0, **kw) if bounded else ILQR(**kw)
    calls = {"n": 0}
    real = slq_mod.rollout

    def counting(*a):
        calls["n"] += 1
        return real(*a)

    monkeypatch.setattr(slq_mod, "rollout", counting)
    ref = solver.solve(problem, x0, u0)
    n_ref = calls["n"]
    got = solver.solve(problem, x0, u0, x_init=xs)
    assert calls["n"] - n_ref == (1 if bounded else 0)  # clamped u_init: rolled out again
    for name in ("x", "u", "cost", "iterations", "status"):
        assert torch.equal(getattr(got, name), getattr(ref, name)), name
    with pytest.raises(ValueError, match="x_init"):
        solver.solve(problem, x0, u0, x_init=xs[:, :-1])
    bad = xs.clone()
    bad[1, 0, 0] += 1e-3
    with pytest.raises(ValueError, match="x0"):
        solver.solve(problem, x0, u0, x_init=bad)
