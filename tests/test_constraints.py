"""Constrained ILQR/DDP (augmented Lagrangian) against independent computations.

* an LQ problem with linear path, state and terminal constraints against the dense QP:
  the active set read from the solution is certified by the KKT conditions of the
  condensed QP (primal feasibility of the inactive rows, nonnegative multipliers of the
  active inequality rows), so the QP's solution is the global optimum; the solver's
  controls and multipliers must match it;
* a problem whose unconstrained optimum is feasible gives the unconstrained solution;
* an element that cannot be feasible ends ``infeasible`` while the others converge, and
  each element of a batch equals its own solve;
* Jacobians of constraint rows against finite differences.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchslq as ts
from torchslq import Status
from torchslq.constraints import ConstraintSet
from torchslq.dynamics import Dynamics

DT = 0.1
T = 15
S_MAX = 0.5
U_MAX = 2.0


class DoubleIntegrator(Dynamics):
    state_dim, control_dim = 2, 1

    def forward(self, x, u):
        return torch.stack([x[..., 0] + DT * x[..., 1], x[..., 1] + DT * u[..., 0]], -1)


def lq_problem(dtype=torch.float64):
    cost = ts.QuadraticCost(
        Q=torch.eye(2, dtype=dtype),
        R=0.1 * torch.eye(1, dtype=dtype),
        Qf=torch.eye(2, dtype=dtype),
        x_ref=torch.tensor([1.0, 0.0], dtype=dtype),
    )
    return ts.Problem(DoubleIntegrator(), cost, T)


def lq_constraints():
    inf = float("inf")
    return [
        ts.Constraints(x_max=torch.tensor([S_MAX, inf])),  # s_t <= S_MAX, t = 0..T
        ts.Constraints(terminal=lambda x: x[..., 1:2], kind="equality"),  # v_T = 0
        ts.Constraints(stage=lambda x, u, t: torch.cat([u - U_MAX, -u - U_MAX], -1)),
    ]


X0 = torch.tensor([[0.0, 0.0], [0.2, 0.1], [-1.0, 0.5], [0.4, -0.3]], dtype=torch.float64)


def dense_qp(x0: np.ndarray):
    """The condensed QP ``min 1/2 U'HU + g'U`` s.t. ``G U <= h``, ``E U = f`` of
    :func:`lq_problem` with :func:`lq_constraints` (rows in the solver's order: stage
    rows ``[s_t - S_MAX, u_t - U_MAX, -u_t - U_MAX]`` for each ``t``, then the terminal
    rows ``[s_T - S_MAX]`` and the equality ``v_T``)."""
    A = np.array([[1.0, DT], [0.0, 1.0]])
    Bm = np.array([[0.0], [DT]])
    # x_t = Phi_t x0 + Gam_t U
    Phi = [np.eye(2)]
    Gam = [np.zeros((2, T))]
    for t in range(T):
        Phi.append(A @ Phi[-1])
        G = A @ Gam[-1]
        G[:, t] += Bm[:, 0]
        Gam.append(G)
    ref = np.array([1.0, 0.0])
    H = 0.1 * np.eye(T)
    g = np.zeros(T)
    for t in range(T + 1):  # Q = Qf = I
        H += Gam[t].T @ Gam[t]
        g += Gam[t].T @ (Phi[t] @ x0 - ref)
    Gi, hi = [], []
    for t in range(T):
        Gi.append(Gam[t][0])
        hi.append(S_MAX - Phi[t][0] @ x0)
        e = np.zeros(T)
        e[t] = 1.0
        Gi += [e, -e]
        hi += [U_MAX, U_MAX]
    Gi.append(Gam[T][0])
    hi.append(S_MAX - Phi[T][0] @ x0)
    E = Gam[T][1][None]
    f = np.array([-Phi[T][1] @ x0])
    return H, g, np.array(Gi), np.array(hi), E, f


def certified_qp_solution(x0: np.ndarray, active: np.ndarray):
    """Solve the equality QP with ``active`` inequality rows held and check the KKT
    conditions of the inequality QP: returns ``(U, nu_ineq (all rows), nu_eq)``."""
    H, g, G, h, E, f = dense_qp(x0)
    Ca = np.vstack([G[active], E])
    ba = np.concatenate([h[active], f])
    k = Ca.shape[0]
    K = np.block([[H, Ca.T], [Ca, np.zeros((k, k))]])
    sol = np.linalg.solve(K, np.concatenate([-g, ba]))
    U, nu = sol[:T], sol[T:]
    nu_in = np.zeros(G.shape[0])
    nu_in[active] = nu[: active.sum()]
    assert (nu_in >= -1e-9).all(), "the active set is not optimal (negative multiplier)"
    assert (G @ U <= h + 1e-9).all(), "the QP solution violates an inactive row"
    return U, nu_in, nu[active.sum() :]


def test_lq_with_constraints_matches_dense_qp():
    problem = lq_problem()
    # the loop's solution is as exact as its violation: 1e-8 for a 1e-6 comparison
    solver = ts.ILQR(constraints=lq_constraints(), tol=1e-10, constraint_tol=1e-8, progress=False)
    r = solver.solve(problem, X0)
    assert (r.status == Status.CONVERGED).all(), r.status_names()
    assert (r.max_violation <= 1e-8).all()
    lam, lam_T = r.multipliers["stage"], r.multipliers["terminal"]
    assert lam.shape == (4, T, 3) and lam_T.shape == (4, 2)
    for b in range(X0.shape[0]):
        x0 = X0[b].numpy()
        _, _, G, h, _, _ = dense_qp(x0)
        U_ours = r.u[b, :, 0].numpy()
        active = G @ U_ours >= h - 1e-5
        U, nu_in, nu_eq = certified_qp_solution(x0, active)
        assert np.abs(U_ours - U).max() < 1e-6
        # solver rows: stage (T, 3) then terminal [bound, equality]
        ours_in = np.concatenate([lam[b].reshape(-1).numpy(), lam_T[b, :1].numpy()])
        scale = 1.0 + np.abs(nu_in).max()
        assert np.abs(ours_in - nu_in).max() < 1e-5 * scale
        assert abs(lam_T[b, 1].item() - nu_eq[0]) < 1e-5 * (1 + abs(nu_eq[0]))
    # the constraints bind: the unconstrained optimum violates them
    free = ts.ILQR(tol=1e-10, progress=False).solve(problem, X0)
    assert (free.x[..., 0].amax(1) > S_MAX + 1e-3).any()


def test_feasible_unconstrained_optimum_is_returned():
    problem = lq_problem()
    loose = [
        ts.Constraints(x_max=torch.tensor([10.0, float("inf")])),
        ts.Constraints(stage=lambda x, u, t: u.abs() - 100.0),
    ]
    r = ts.ILQR(constraints=loose, tol=1e-10, progress=False).solve(problem, X0)
    free = ts.ILQR(tol=1e-10, progress=False).solve(problem, X0)
    assert (r.status == Status.CONVERGED).all()
    assert torch.allclose(r.u, free.u, atol=1e-12, rtol=0)
    assert torch.equal(r.outer_iterations, torch.ones_like(r.outer_iterations))
    assert (r.multipliers["stage"] == 0).all()


def test_infeasible_element_is_flagged_and_others_unaffected():
    problem = lq_problem()
    # x0 of element 1 starts beyond the bound: no control can satisfy s_0 <= S_MAX
    x0 = torch.tensor([[0.0, 0.0], [0.9, 0.0], [0.2, 0.1]], dtype=torch.float64)
    solver = ts.ILQR(constraints=lq_constraints(), tol=1e-9, penalty_max=1e5, progress=False)
    r = solver.solve(problem, x0)
    assert r.status_names() == ["converged", "infeasible", "converged"]
    assert r.max_violation[1] > 0.3
    for b in (0, 2):
        single = solver.solve(problem, x0[b : b + 1])
        assert single.status.item() == Status.CONVERGED
        torch.testing.assert_close(r.u[b], single.u[0], atol=1e-12, rtol=0)
        torch.testing.assert_close(r.multipliers["stage"][b], single.multipliers["stage"][0])


def test_ddp_and_float32_with_constraints():
    problem = lq_problem()
    r64 = ts.DDP(constraints=lq_constraints(), tol=1e-10, progress=False).solve(problem, X0)
    ref = ts.ILQR(constraints=lq_constraints(), tol=1e-10, progress=False).solve(problem, X0)
    assert (r64.status == Status.CONVERGED).all()
    torch.testing.assert_close(r64.u, ref.u, atol=1e-6, rtol=0)
    # ALTRO's/trajax's schedule (the penalty rises at every infeasible iteration)
    always = ts.ILQR(
        constraints=lq_constraints(), tol=1e-10, penalty_update="always", progress=False
    ).solve(problem, X0)
    assert (always.status == Status.CONVERGED).all()
    # both stop at a violation of 1e-6: their controls agree to a few times that
    torch.testing.assert_close(always.u, ref.u, atol=1e-5, rtol=0)
    assert (always.history["penalty"][:, -1] >= ref.history["penalty"][:, -1]).all()
    p32 = lq_problem(torch.float32)
    r32 = ts.ILQR(constraints=lq_constraints(), tol=1e-4, progress=False).solve(p32, X0.float())
    assert r32.u.dtype == torch.float32
    assert (r32.max_violation <= 1e-4).all()
    torch.testing.assert_close(r32.u.double(), ref.u, atol=2e-3, rtol=0)


def test_unbatched_and_result_round_trip(tmp_path):
    problem = lq_problem()
    solver = ts.ILQR(constraints=lq_constraints(), tol=1e-9, progress=False)
    r = solver.solve(problem, X0[1])
    assert r.u.shape == (T, 1) and r.multipliers["stage"].shape == (T, 3)
    assert r.max_violation.ndim == 0
    rb = solver.solve(problem, X0[1:2])
    torch.testing.assert_close(r.u, rb.u[0], atol=1e-12, rtol=0)
    rb.save(tmp_path / "r.pt")
    back = ts.SolverResult.load(tmp_path / "r.pt")
    assert torch.equal(back.multipliers["terminal"], rb.multipliers["terminal"])
    assert torch.equal(back.max_violation, rb.max_violation)


def test_constraint_jacobians_match_finite_differences():
    torch.manual_seed(0)
    centre = torch.tensor([0.3, -0.2], dtype=torch.float64)

    def obstacle(x, u, t):
        d = x[..., :2] - centre
        return torch.stack([0.25 - (d * d).sum(-1), x[..., 2] * u[..., 0] - 1.0], -1)

    cset = ConstraintSet(
        [
            ts.Constraints(stage=obstacle, terminal=lambda x: x[..., :2].sin()),
            ts.Constraints(x_min=torch.tensor([-1.0, -float("inf"), -2.0])),
        ]
    )
    x = torch.randn(2, 5, 3, dtype=torch.float64)
    u = torch.randn(2, 4, 1, dtype=torch.float64)
    v = cset.values(x, u, jacobians=True)
    assert v.stage.shape == (2, 4, 4) and v.terminal.shape == (2, 4)
    eps = 1e-6
    for i in range(3):
        d = torch.zeros(3, dtype=torch.float64)
        d[i] = eps
        fd = (cset.values(x + d, u).stage - cset.values(x - d, u).stage) / (2 * eps)
        torch.testing.assert_close(v.cx[..., i], fd, atol=1e-8, rtol=0)
        fdT = (cset.values(x + d, u).terminal - cset.values(x - d, u).terminal) / (2 * eps)
        torch.testing.assert_close(v.cxT[..., i], fdT, atol=1e-8, rtol=0)
    du = torch.full((1,), eps, dtype=torch.float64)
    fdu = (cset.values(x, u + du).stage - cset.values(x, u - du).stage) / (2 * eps)
    torch.testing.assert_close(v.cu[..., 0], fdu, atol=1e-8, rtol=0)
    stage_eq, terminal_eq = cset.dims(3, 1, x)
    assert not stage_eq.any() and stage_eq.numel() == 4 and terminal_eq.numel() == 4


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kind": "bounds", "x_max": 1.0}, "kind must be one of"),
        ({"stage": 3}, "stage must be callable"),
        ({}, "needs stage, terminal"),
        ({"x_max": 1.0, "kind": "equality"}, "inequality"),
        ({"x_min": 1.0, "x_max": 0.0}, "x_min must be <= x_max"),
        ({"x_max": float("nan")}, "x_max contains NaN"),
        ({"stage_jacobian": lambda x, u, t: None, "terminal": lambda x: x}, "needs stage"),
    ],
)
def test_constraints_validation(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        ts.Constraints(**kwargs)


def test_solver_options_validation():
    with pytest.raises(TypeError, match="Constraints"):
        ts.ILQR(constraints=lambda x: x)
    with pytest.raises(ValueError, match="penalty_factor"):
        ts.ILQR(constraints=lq_constraints(), penalty_factor=1.0)
    with pytest.raises(ValueError, match="constraint_tol"):
        ts.DDP(constraints=lq_constraints(), constraint_tol=0.0)
    with pytest.raises(TypeError, match="unknown option"):
        ts.SLQ(constraints=lq_constraints())


class Pendulum(Dynamics):
    state_dim, control_dim = 2, 1

    def forward(self, x, u):
        dx = torch.stack([x[..., 1], u[..., 0] - torch.sin(x[..., 0])], -1)
        return x + DT * dx


class SpeedLimit(torch.nn.Module):
    """``omega_t <= w`` with a learnable ``w``."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor(0.8, dtype=torch.float64))

    def forward(self, x, u, t):
        return x[..., 1:2] - self.w


def test_mpc_constrained_gradients_match_finite_differences():
    """Implicit gradients with the active set held (speed limit, terminal equality,
    control bound) against central differences of re-solves, for x0, the cost's goal
    and the constraint's own parameter, along a random direction."""
    torch.manual_seed(0)
    goal = torch.tensor([1.5, 0.0], dtype=torch.float64, requires_grad=True)
    limit = SpeedLimit()
    cost = ts.QuadraticCost(
        Q=0.1 * torch.eye(2, dtype=torch.float64),
        R=torch.eye(1, dtype=torch.float64),
        Qf=torch.eye(2, dtype=torch.float64),
        x_ref=goal,
    )
    constraints = [
        ts.Constraints(stage=limit),
        ts.Constraints(terminal=lambda x: x[..., :1] - 1.2, kind="equality"),
    ]
    solver = ts.ILQR(tol=1e-11, max_iter=200, constraint_tol=1e-10, progress=False)
    mpc = ts.MPC(
        Pendulum(), cost, 20, solver=solver, constraints=constraints, u_max=1.1, warm_start=False
    )
    assert any(p is limit.w for p in mpc.parameters())
    x0 = torch.tensor([[0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    W = torch.randn(1, 20, 1, dtype=torch.float64)
    V = torch.randn(1, 21, 2, dtype=torch.float64)

    def loss():
        x, u = mpc(x0)
        return (W * u).sum() + (V * x).sum()

    L = loss()
    r = mpc.last_result
    assert (r.status == Status.CONVERGED).all()
    # the speed limit binds on element 0, the control bound somewhere, the goal always
    assert (r.multipliers["stage"][0] > 0).any() and r.active_bounds.abs().sum() > 0
    L.backward()
    params = [x0, goal, limit.w]
    grads = [p.grad.clone() for p in params]
    dirs = [torch.randn_like(p) for p in params]
    analytic = sum((g * d).sum() for g, d in zip(grads, dirs, strict=True)).item()
    eps = 1e-4  # solves are exact to ~1e-10: a larger step keeps their error out of the quotient
    with torch.no_grad():
        for p, d in zip(params, dirs, strict=True):
            p += eps * d
        Lp = loss().item()
        for p, d in zip(params, dirs, strict=True):
            p -= 2 * eps * d
        Lm = loss().item()
        for p, d in zip(params, dirs, strict=True):
            p += eps * d
    fd = (Lp - Lm) / (2 * eps)
    assert abs(analytic - fd) < 1e-5 * (1 + abs(fd))
    # holding the active set matters: the unconstrained layer's gradient differs
    assert abs(limit.w.grad.item()) > 1e-3


def test_mpc_constraints_need_a_capable_solver():
    c = ts.Constraints(x_max=1.0)
    problem = lq_problem()
    with pytest.raises(ValueError, match="supports_constraints"):
        ts.MPC(problem.dynamics, problem.cost, T, solver=ts.SLQ(progress=False), constraints=c)
    with pytest.raises(ValueError, match="unroll"):
        ts.MPC(problem.dynamics, problem.cost, T, constraints=c, backward="unroll")


def test_multipliers_warm_start_solver_and_mpc():
    """Starting from the solution's own multipliers, one outer iteration suffices (and
    gives the same solution); the MPC layer reuses them between calls."""
    problem = lq_problem()
    solver = ts.ILQR(constraints=lq_constraints(), tol=1e-10, progress=False)
    cold = solver.solve(problem, X0)
    warm = solver.solve(problem, X0, cold.u, multipliers=cold.multipliers)
    assert (warm.status == Status.CONVERGED).all()
    assert (warm.outer_iterations == 1).all() and (cold.outer_iterations > 3).all()
    torch.testing.assert_close(warm.u, cold.u, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="multipliers"):
        ts.ILQR(progress=False).solve(problem, X0, multipliers=cold.multipliers)
    with pytest.raises(ValueError, match=r"multipliers\['stage'\]"):
        solver.solve(problem, X0, multipliers={"stage": torch.zeros(3), "terminal": torch.zeros(2)})
    mpc = ts.MPC(
        problem.dynamics, problem.cost, T, solver=solver, constraints=lq_constraints(),
        warm_start="reuse",
    )  # fmt: skip
    first = mpc(X0).result
    second = mpc(X0).result
    assert (first.outer_iterations > 3).all() and (second.outer_iterations == 1).all()
    torch.testing.assert_close(second.u, first.u, atol=1e-6, rtol=0)


def test_polish_reaches_the_qp_solution_to_round_off():
    """Newton steps on the active set end the AL loop early and meet the KKT conditions
    to round-off: the certified QP solution to 1e-9 (the loop alone: 1e-6)."""
    problem = lq_problem()
    plain = ts.ILQR(constraints=lq_constraints(), tol=1e-10, progress=False)
    polished = plain.with_options(polish=True)
    r0 = plain.solve(problem, X0)
    r = polished.solve(problem, X0)
    assert (r.status == Status.CONVERGED).all()
    assert (r.max_violation <= 1e-12).all() and (r.grad_norm <= 1e-10).all()
    assert (r.outer_iterations < r0.outer_iterations).all()
    for b in range(X0.shape[0]):
        x0 = X0[b].numpy()
        _, _, G, h, _, _ = dense_qp(x0)
        active = G @ r.u[b, :, 0].numpy() >= h - 1e-5
        U, nu_in, nu_eq = certified_qp_solution(x0, active)
        assert np.abs(r.u[b, :, 0].numpy() - U).max() < 1e-9
        ours_in = np.concatenate(
            [
                r.multipliers["stage"][b].reshape(-1).numpy(),
                r.multipliers["terminal"][b, :1].numpy(),
            ]
        )
        assert np.abs(ours_in - nu_in).max() < 1e-8 * (1 + np.abs(nu_in).max())


def test_augmented_terms_expansion_matches_autograd():
    """The subproblem's quadratic model with ``curvature=True`` is the exact Hessian of the
    augmented Lagrangian (autograd of its value), and its gradient is exact either way."""
    from torchslq.constraints import AugmentedLagrangianCost

    torch.manual_seed(1)
    n, m, Tn = 3, 2, 4
    centre = torch.tensor([0.2, -0.1], dtype=torch.float64)

    def obstacle(x, u, t):
        return (0.5 - (x[..., :2] - centre).pow(2).sum(-1) + 0.1 * u[..., 0] ** 2).unsqueeze(-1)

    cset = ConstraintSet(
        [
            ts.Constraints(stage=obstacle),
            ts.Constraints(terminal=lambda x: x[..., :2].sin() - 0.3, kind="equality"),
        ]
    )
    base = ts.QuadraticCost(
        Q=torch.eye(n, dtype=torch.float64), R=torch.eye(m, dtype=torch.float64)
    )
    x = 0.3 * torch.randn(2, Tn + 1, n, dtype=torch.float64)
    u = 0.3 * torch.randn(2, Tn, m, dtype=torch.float64)
    stage_eq, terminal_eq = cset.dims(n, m, x)
    lam = torch.rand(2, Tn, 1, dtype=torch.float64)
    lam_T = torch.randn(2, 2, dtype=torch.float64)
    rho = torch.tensor([3.0, 0.5], dtype=torch.float64)
    for curvature in (True, False):
        al = AugmentedLagrangianCost(base, cset, lam, lam_T, rho, stage_eq, terminal_eq, curvature)
        e = al.quadratize(x, u)
        for b in range(2):

            def f(xb, ub, b=b, al=al):
                xx, uu = x.clone(), u.clone()
                xx[b], uu[b] = xb, ub
                return al(xx, uu)[b]

            gx, gu = torch.func.grad(f, argnums=(0, 1))(x[b], u[b])
            torch.testing.assert_close(e.lx[b], gx)
            torch.testing.assert_close(e.lu[b], gu)
            if not curvature:
                continue
            H = torch.autograd.functional.hessian(f, (x[b], u[b]))
            for t in range(Tn):
                torch.testing.assert_close(e.lxx[b, t], H[0][0][t, :, t, :])
                torch.testing.assert_close(e.luu[b, t], H[1][1][t, :, t, :])
                torch.testing.assert_close(e.lux[b, t], H[1][0][t, :, t, :])
            torch.testing.assert_close(e.lxx[b, Tn], H[0][0][Tn, :, Tn, :])
