"""ContinuousILQR: the Riccati ODE backward pass against the CARE (scipy), the discrete
Riccati recursion as dt -> 0 and the plain (non-square-root) Riccati ODE; the LQ optimum;
the expected decrease against finite differences of the forward pass; batch vs
one-by-one; per-element failure; float32; options."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp as scipy_ivp
from scipy.linalg import solve_continuous_are

import torchslq as ts
from torchslq.problem_continuous import ContinuousProblem
from torchslq.solvers.continuous import ContinuousILQR
from torchslq.solvers.continuous.expansion import Layout
from torchslq.solvers.continuous.passes import forward_pass

D = torch.float64
pytestmark = pytest.mark.usefixtures("single_thread")

A_NP = np.array([[0.0, 1.0], [2.0, -0.5]])  # unstable open loop
B_NP = np.array([[0.0], [1.0]])
Q_NP = np.diag([1.0, 0.3])
R_NP = np.array([[0.2]])
P_CARE = solve_continuous_are(A_NP, B_NP, Q_NP, R_NP)


class Linear(ts.ContinuousDynamics):
    state_dim, control_dim = 2, 1

    def forward(self, x, u, t=None):
        A = torch.as_tensor(A_NP, dtype=x.dtype)
        B = torch.as_tensor(B_NP, dtype=x.dtype)
        return x @ A.mT + u @ B.mT


class Pendulum(ts.ContinuousDynamics):
    """theta'' = -sin(theta) - 0.1 theta' + u; an optional per-element gain ``(B, 1)``."""

    state_dim, control_dim = 2, 1

    def __init__(self, gain=None):
        super().__init__()
        self.gain = gain

    def forward(self, x, u, t=None):
        g = 1.0 if self.gain is None else self.gain
        th, om = x[..., 0], x[..., 1]
        return torch.stack([om, -g * torch.sin(th) - 0.1 * om + u[..., 0]], -1)


def lq_problem(Qf: np.ndarray, tf: float) -> ContinuousProblem:
    Q, R, F = (torch.as_tensor(M, dtype=D) for M in (Q_NP, R_NP, Qf))
    cost = ts.Cost(
        stage=lambda x, u, t: 0.5 * ((x @ Q) * x).sum(-1) + 0.5 * ((u @ R) * u).sum(-1),
        terminal=lambda x: 0.5 * ((x @ F) * x).sum(-1),
        state_dim=2,
        control_dim=1,
    )
    return ContinuousProblem(Linear(), cost, 0.0, tf)


def pendulum_problem(gain=None) -> ContinuousProblem:
    cost = ts.Cost(
        stage=lambda x, u, t: 0.05 * x[..., 1] ** 2 + 0.5 * u[..., 0] ** 2,
        terminal=lambda x: 5.0 * (x[..., 0] - 2.0) ** 2 + 0.5 * x[..., 1] ** 2,
        state_dim=2,
        control_dim=1,
    )
    return ContinuousProblem(Pendulum(gain), cost, 0.0, 2.0)


def value_hessian(problem, x0, **kw):
    """The first backward pass (about the zero-control rollout) of a max_iter=0 solve."""
    res = ContinuousILQR(max_iter=0, progress=False, **kw).solve(problem, x0)
    return res.policy


def test_riccati_ode_stays_at_the_care_solution():
    """With Phi_xx = P_care the Riccati ODE's solution is constant (-S' = 0)."""
    pol = value_hessian(lq_problem(P_CARE, 1.0), torch.tensor([[1.0, 0.0]], dtype=D))
    t = torch.tensor([[0.0, 0.3, 0.7, 0.95]], dtype=D)
    S = pol.S(t)[0].numpy()
    np.testing.assert_allclose(S, np.broadcast_to(P_CARE, S.shape), rtol=1e-6, atol=1e-8)


def test_riccati_ode_reaches_the_care_solution_over_a_long_horizon():
    """Phi = 0 (P(tf) floored at eps^(1/4), eq. 13): S(0) -> P_care as tf grows."""
    pol = value_hessian(lq_problem(np.zeros((2, 2)), 8.0), torch.tensor([[1.0, 0.0]], dtype=D))
    S0 = pol.S(torch.zeros(1, dtype=D))[0].numpy()
    np.testing.assert_allclose(S0, P_CARE, rtol=1e-6, atol=1e-8)
    # and the gain K(0) = R^-1 B' S
    K0 = pol.K(torch.zeros(1, dtype=D))[0].numpy()
    np.testing.assert_allclose(K0, np.linalg.solve(R_NP, B_NP.T @ P_CARE), rtol=1e-6)


def discrete_riccati(N: int, tf: float, Qf: np.ndarray) -> np.ndarray:
    """P_0 of the LQ problem on the explicit Euler grid (dt = tf / N)."""
    dt = tf / N
    Ad, Bd, Qd, Rd = np.eye(2) + dt * A_NP, dt * B_NP, dt * Q_NP, dt * R_NP
    P = Qf.copy()
    for _ in range(N):
        G = np.linalg.solve(Rd + Bd.T @ P @ Bd, Bd.T @ P @ Ad)
        P = Qd + Ad.T @ P @ Ad - Ad.T @ P @ Bd @ G
    return P


def test_riccati_ode_is_the_limit_of_the_discrete_recursion():
    Qf = np.diag([3.0, 0.5])
    pol = value_hessian(lq_problem(Qf, 1.0), torch.tensor([[1.0, 0.0]], dtype=D))
    S0 = pol.S(torch.zeros(1, dtype=D))[0].numpy()
    errs = [np.abs(discrete_riccati(N, 1.0, Qf) - S0).max() for N in (100, 400, 1600)]
    # first order in dt: each 4x finer grid is about 4x closer
    assert errs[0] / errs[1] > 3.5 and errs[1] / errs[2] > 3.5
    assert errs[2] < 2e-3 * np.abs(S0).max()


def test_square_root_form_equals_plain_riccati_ode():
    """S = P P' from the square-root ODE (12) vs scipy on -S' = Q + A'S + SA - SBR^-1B'S."""
    Qf = np.diag([3.0, 0.5])
    pol = value_hessian(lq_problem(Qf, 1.0), torch.tensor([[1.0, 0.0]], dtype=D))

    def plain(tau, s):
        S = s.reshape(2, 2)
        dS = Q_NP + A_NP.T @ S + S @ A_NP - S @ B_NP @ np.linalg.solve(R_NP, B_NP.T @ S)
        return dS.ravel()

    ref = scipy_ivp(plain, (0.0, 1.0), Qf.ravel(), rtol=1e-11, atol=1e-12, dense_output=True)
    t = np.array([0.0, 0.25, 0.6, 0.95])
    S = pol.S(torch.as_tensor(t, dtype=D)[None])[0].numpy()
    want = ref.sol(1.0 - t).T.reshape(-1, 2, 2)
    np.testing.assert_allclose(S, want, rtol=1e-6, atol=1e-8)
    # the square-root form keeps S symmetric by construction
    assert np.abs(S - S.transpose(0, 2, 1)).max() < 1e-14


def test_lq_problem_is_solved_in_one_step_at_the_care_cost():
    """Phi_xx = P_care: the optimal cost is x0' P_care x0 / 2 and u = -R^-1 B' P_care x."""
    x0 = torch.tensor([[1.0, 0.0], [-0.5, 1.0]], dtype=D)
    # the gradient after the exact step is the integrator's error: at the default
    # rtol = tol = 1e-6 it is 0.4-4e-6 depending on the CPU's rounding, so one step is
    # claimed at an integrator 1000x tighter than tol (gradient ~1e-8)
    solver = ContinuousILQR(tol=1e-6, rtol=1e-9, atol=1e-11, progress=False)
    res = solver.solve(lq_problem(P_CARE, 2.0), x0)
    assert res.status_names() == ["converged", "converged"]
    assert res.iterations.tolist() == [1, 1]
    want = 0.5 * np.einsum("bi,ij,bj->b", x0.numpy(), P_CARE, x0.numpy())
    np.testing.assert_allclose(res.cost.numpy(), want, rtol=1e-6)
    Kc = np.linalg.solve(R_NP, B_NP.T @ P_CARE)
    for b in range(2):
        mk = res.mask[b]
        u_want = -(res.x[b][mk].numpy() @ Kc.T)
        np.testing.assert_allclose(res.u[b][mk].numpy(), u_want, atol=1e-5 * np.abs(u_want).max())
        # the grid: per element, increasing from t0 to tf
        tb = res.t[b][mk]
        assert float(tb[0]) == 0.0 and float(tb[-1]) == 2.0 and bool((tb.diff() > 0).all())


def test_expected_decrease_is_the_derivative_of_the_forward_pass_cost():
    """dJ(alpha)/dalpha at 0 along the policy (14) equals Delta V'(0) = -eta
    (central differences of forward passes at tight tolerances)."""
    problem = pendulum_problem()
    x0 = torch.tensor([[0.3, 0.0]], dtype=D)
    res = ContinuousILQR(max_iter=0, rtol=1e-8, atol=1e-10, progress=False).solve(
        problem, x0, u_init=lambda t: 0.3 * torch.ones_like(t)
    )
    eta = 2.0 * float(res.expected_decrease[0])
    pol = res.policy
    layout = Layout(2, 1, False)

    def J(a):
        nom = forward_pass(
            problem, x0, lambda t, x: pol(t, x, a), layout, rtol=1e-9, atol=1e-11, max_steps=10**5
        )
        return float(nom.J[0])

    h = 1e-2
    slope = (J(h) - J(-h)) / (2 * h)
    assert eta > 1.0  # a real decrease is predicted
    np.testing.assert_allclose(slope, -eta, rtol=1e-4)
    # and the curvature of the quadratic model, Delta V(a) = -(a - a^2/2) eta, at a = 1/2
    assert abs(J(0.5) - float(res.cost[0]) - (-(0.5 - 0.125) * eta)) < 0.3 * 0.375 * eta


def test_nonlinear_batch_equals_one_by_one_with_own_grids_and_paper_line_search():
    gain = torch.tensor([[1.0], [2.0]], dtype=D)
    x0 = torch.tensor([[0.3, 0.0], [0.0, 0.5]], dtype=D)
    solver = ContinuousILQR(tol=1e-6, rtol=1e-5, atol=1e-7, max_iter=40, progress=False)
    res = solver.solve(pendulum_problem(gain), x0)
    assert res.status_names() == ["converged"] * 2
    assert len(set(res.mask.sum(1).tolist())) > 1  # each element its own grid
    tq = torch.linspace(0.0, 2.0, 21, dtype=D)
    for b in range(2):
        one = solver.solve(pendulum_problem(gain[b : b + 1]), x0[b : b + 1])
        # the same solution (CPU transcendental kernels may differ in the last bit with
        # the batch size, so grids agree to the step-size control, not bitwise, and at
        # the integration-noise floor one more step may or may not pass (15))
        assert abs(int(res.iterations[b]) - int(one.iterations[0])) <= 1
        torch.testing.assert_close(res.cost[b], one.cost[0], rtol=1e-6, atol=0)
        torch.testing.assert_close(
            res.policy.xbar(tq[None].expand(2, -1))[b],
            one.policy.xbar(tq[None])[0],
            rtol=0,
            atol=1e-4,
        )
        torch.testing.assert_close(
            res.policy.K(tq[None].expand(2, -1))[b], one.policy.K(tq[None])[0], rtol=1e-3, atol=1e-4
        )
    # the accepted steps are the paper's backtracking values 2^-k
    steps = res.history["step"][res.history["step"] > 0]
    np.testing.assert_allclose(np.log2(steps.numpy()), np.round(np.log2(steps.numpy())))
    # history: step counts and step-size ranges per iteration and element
    for key in ("n_bwd", "n_fwd", "h_bwd_min", "h_bwd_max", "h_fwd_min", "h_fwd_max"):
        assert res.history[key].shape == res.history["cost"].shape
    hmin, hmax = res.history["h_bwd_min"], res.history["h_bwd_max"]
    ran = torch.isfinite(hmin)  # NaN after an element finished
    assert bool((hmin[ran] < hmax[ran]).all()) and bool(ran[:, 0].all())


def test_failure_is_per_element():
    """An element whose trajectory blows up (x' = x^2 from 2 has a pole at t = 0.5) ends
    as non_finite; the others are unaffected."""

    class Blowup(ts.ContinuousDynamics):
        state_dim, control_dim = 1, 1

        def forward(self, x, u, t=None):
            return x**2 - x + u

    cost = ts.Cost(
        stage=lambda x, u, t: 0.5 * (x[..., 0] ** 2 + u[..., 0] ** 2),
        terminal=lambda x: x[..., 0] ** 2,
        state_dim=1,
        control_dim=1,
    )
    problem = ContinuousProblem(Blowup(), cost, 0.0, 1.0)
    # and a NaN initial state is its element's status too (not an error for the batch)
    x0 = torch.tensor([[0.5], [3.0], [-0.5], [float("nan")]], dtype=D)
    solver = ContinuousILQR(tol=1e-7, rtol=1e-5, atol=1e-7, progress=False, max_steps=500)
    res = solver.solve(problem, x0)
    assert res.status_names() == ["converged", "non_finite", "converged", "non_finite"]
    good = solver.solve(problem, x0[[0, 2]])
    torch.testing.assert_close(res.cost[[0, 2]], good.cost, rtol=1e-6, atol=0)


def test_float32():
    x0 = torch.tensor([[0.3, 0.0]], dtype=D)
    ref = ContinuousILQR(tol=1e-6, rtol=1e-5, atol=1e-7, progress=False).solve(
        pendulum_problem(), x0
    )
    res = ContinuousILQR(tol=1e-3, rtol=1e-4, atol=1e-6, progress=False).solve(
        pendulum_problem(), x0.float()
    )
    assert res.x.dtype == torch.float32 and res.status_names()[0] in ("converged", "stalled")
    np.testing.assert_allclose(float(res.cost[0]), float(ref.cost[0]), rtol=1e-3)


def test_options_are_validated():
    with pytest.raises(TypeError, match="unknown option"):
        ContinuousILQR(foo=1)
    with pytest.raises(ValueError, match="rtol"):
        ContinuousILQR(rtol=0.0)
    with pytest.raises(ValueError, match="alpha_min"):
        ContinuousILQR(alpha_min=2.0)
    with pytest.raises(TypeError, match="ddp"):
        ContinuousILQR(ddp="yes")
    with pytest.raises(ValueError, match="tf"):
        lq_problem(P_CARE, -1.0)
    s = ContinuousILQR(rtol=1e-5)
    assert s.options.rtol == 1e-5 and s.with_options(rtol=1e-7).options.rtol == 1e-7


def test_tensorboard_log_has_the_step_counts_of_the_history(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    x0 = torch.tensor([[1.0, 0.0]], dtype=D)
    with ts.TensorBoardLogger(tmp_path) as logger:
        res = ContinuousILQR(progress=False).solve(lq_problem(P_CARE, 1.0), x0, logger=logger)
    acc = EventAccumulator(str(tmp_path), size_guidance={"scalars": 0})
    acc.Reload()
    for key in ("n_bwd", "n_fwd", "h_bwd_min", "h_fwd_max"):
        ev = acc.Scalars(f"continuous/{key}/max")
        h = res.history[key].double()
        want = h.nan_to_num(nan=-np.inf).amax(0)
        want = want[torch.isfinite(h).any(0)]  # columns with no value are not logged
        np.testing.assert_allclose([e.value for e in ev], want.numpy(), rtol=1e-6)
    assert [e.value for e in acc.Scalars("cost/mean")] == pytest.approx(
        res.history["cost"].mean(0).tolist(), rel=1e-6
    )


def test_ddp_terms_reach_the_same_optimum_and_vanish_for_linear_dynamics():
    x0 = torch.tensor([[0.3, 0.0]], dtype=D)
    kw = dict(tol=1e-6, rtol=1e-6, atol=1e-8, progress=False)
    ilqr = ContinuousILQR(**kw).solve(pendulum_problem(), x0)
    ddp = ContinuousILQR(ddp=True, **kw).solve(pendulum_problem(), x0)
    assert ddp.status_names() == ["converged"]
    np.testing.assert_allclose(float(ddp.cost[0]), float(ilqr.cost[0]), rtol=1e-6)
    # f_zz = 0: the DDP pass is the iLQR pass
    lq = lq_problem(P_CARE, 2.0)
    a = ContinuousILQR(max_iter=0, progress=False).solve(lq, torch.tensor([[1.0, 0.0]], dtype=D))
    b = ContinuousILQR(max_iter=0, ddp=True, progress=False).solve(
        lq, torch.tensor([[1.0, 0.0]], dtype=D)
    )
    t = torch.linspace(0.0, 2.0, 9, dtype=D)[None]
    torch.testing.assert_close(a.policy.K(t), b.policy.K(t), rtol=1e-12, atol=1e-12)


def test_u_init_as_samples_or_callable():
    """Samples on linspace(t0, tf, K+1) are interpolated linearly: the same initial
    trajectory as the callable of the same piecewise-linear control."""
    problem = pendulum_problem()
    x0 = torch.tensor([[0.3, 0.0]], dtype=D)
    grid = torch.linspace(0.0, 2.0, 5, dtype=D)
    vals = torch.tensor([0.0, 1.0, -1.0, 0.5, 0.0], dtype=D)

    def pl(t):
        return torch.as_tensor(np.interp(t.numpy(), grid.numpy(), vals.numpy()), dtype=D)

    s = ContinuousILQR(max_iter=0, progress=False)
    a = s.solve(problem, x0, u_init=vals[:, None])
    b = s.solve(problem, x0, u_init=pl)
    torch.testing.assert_close(a.cost, b.cost, rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="u_init"):
        s.solve(problem, x0, u_init=torch.zeros(5, 3, dtype=D))
