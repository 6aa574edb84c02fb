"""The differentiable MPC layer: gradients against central finite differences of the full
nonlinear solve, implicit vs unroll, inverse optimal control, bounds, batch == singles,
unconverged handling, warm start and validation."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from torch import nn

from torchslq import DDP, ILQR, MPC, SLQ, Cost, LearnedDynamics, QuadraticCost, Status, discretize
from torchslq.mpc import implicit_solution
from torchslq.systems import Pendulum

DT, T = 0.05, 20
TIGHT = dict(max_iter=300, tol=1e-11, progress=False)


def pendulum_mpc(mass, damping, x_ref, q_diag, backward="implicit", solver=None, **kw):
    dyn = discretize(Pendulum(mass=mass, damping=damping), DT, method="rk4")
    cost = QuadraticCost(
        Q=torch.diag(q_diag),
        R=0.1 * torch.eye(1, dtype=torch.float64),
        Qf=torch.diag(torch.tensor([10.0, 1.0], dtype=torch.float64)),
        x_ref=x_ref,
    )
    solver = solver if solver is not None else ILQR(**TIGHT)
    return MPC(dyn, cost, T, solver=solver, backward=backward, warm_start=False, **kw)


X0 = torch.tensor([[0.3, 0.0], [-0.5, 0.4], [2.0, -1.0]], dtype=torch.float64)
gen = torch.Generator().manual_seed(0)
WX = torch.randn(3, T + 1, 2, generator=gen, dtype=torch.float64)
WU = torch.randn(3, T, 1, generator=gen, dtype=torch.float64)
THETA = torch.tensor([1.2, 0.3, 1.0, 0.2, 1.0, 0.1], dtype=torch.float64)  # m, b, xref, Q


def loss_of(theta: torch.Tensor, x0: torch.Tensor, backward="implicit", **kw) -> torch.Tensor:
    mpc = pendulum_mpc(theta[0], theta[1], theta[2:4], theta[4:6], backward=backward, **kw)
    x, u = mpc(x0)
    return (WX * x).sum() + (WU * u).sum()


def fd_grad(fn, p: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    g = torch.zeros_like(p)
    with torch.no_grad():
        for i in range(p.numel()):
            e = torch.zeros_like(p).view(-1)
            e[i] = eps
            e = e.view_as(p)
            g.view(-1)[i] = (fn(p + e) - fn(p - e)) / (2 * eps)
    return g


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).norm() / b.norm())


@pytest.fixture(scope="module")
def fd_reference():
    g_theta = fd_grad(lambda th: loss_of(th, X0), THETA)
    g_x0 = fd_grad(lambda x0: loss_of(THETA, x0), X0)
    return g_theta, g_x0


def autograd_grads(backward: str):
    theta = THETA.clone().requires_grad_(True)
    x0 = X0.clone().requires_grad_(True)
    loss_of(theta, x0, backward=backward).backward()
    return theta.grad, x0.grad


def test_implicit_gradients_match_finite_differences(fd_reference, backend):
    """Dynamics parameters (mass, damping), cost parameters (reference, Q) and x0."""
    g_theta, g_x0 = autograd_grads("implicit")
    fd_theta, fd_x0 = fd_reference
    assert rel(g_theta, fd_theta) < 1e-6
    assert rel(g_x0, fd_x0) < 1e-6
    for i in range(THETA.numel()):  # every parameter, not only the big ones
        assert abs(g_theta[i] - fd_theta[i]) <= 1e-5 * (1 + abs(fd_theta[i]))


def test_implicit_gn_error_is_measured(fd_reference):
    """Dropping the dynamics curvature is an approximation on a nonlinear problem: its
    error is orders of magnitude above the exact implicit gradient's."""
    g_theta, _ = autograd_grads("implicit_gn")
    e_gn = rel(g_theta, fd_reference[0])
    g_exact, _ = autograd_grads("implicit")
    e_exact = rel(g_exact, fd_reference[0])
    print(f"relative gradient error: implicit {e_exact:.2e}, implicit_gn {e_gn:.2e}")
    assert e_gn > 1e-3
    assert e_gn > 100 * e_exact


def test_unroll_agrees_with_implicit_at_convergence():
    g_imp, gx_imp = autograd_grads("implicit")
    g_unr, gx_unr = autograd_grads("unroll")
    assert rel(g_unr, g_imp) < 1e-6
    assert rel(gx_unr, gx_imp) < 1e-6


def test_implicit_gradient_of_every_solver_is_the_same():
    """The backward pass depends on the solution, not on how it was found."""
    ref, _ = autograd_grads("implicit")
    for solver in (DDP(**TIGHT), SLQ(max_iter=300, tol=1e-11, progress=False)):
        theta = THETA.clone().requires_grad_(True)
        loss_of(theta, X0, solver=solver).backward()
        assert rel(theta.grad, ref) < 1e-6


def test_values_are_the_solvers_solution():
    mpc = pendulum_mpc(*[THETA[0], THETA[1], THETA[2:4], THETA[4:6]])
    x0 = X0.clone().requires_grad_(True)
    x, u = mpc(x0)
    res = mpc.last_result
    assert torch.equal(x.detach(), res.x) and torch.equal(u.detach(), res.u)
    assert x.requires_grad and u.requires_grad


def test_batch_equals_singles(backend):
    theta = THETA.clone().requires_grad_(True)
    x0 = X0.clone().requires_grad_(True)
    loss_of(theta, x0).backward()
    g_sum = torch.zeros_like(THETA)
    for i in range(X0.shape[0]):
        th = THETA.clone().requires_grad_(True)
        xi = X0[i].clone().requires_grad_(True)
        mpc = pendulum_mpc(th[0], th[1], th[2:4], th[4:6])
        x, u = mpc(xi)  # unbatched input -> unbatched output
        assert x.shape == (T + 1, 2) and u.shape == (T, 1)
        ((WX[i] * x).sum() + (WU[i] * u).sum()).backward()
        g_sum += th.grad
        torch.testing.assert_close(xi.grad, x0.grad[i], rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(g_sum, theta.grad, rtol=1e-8, atol=1e-10)


def test_inverse_optimal_control_gradient_vanishes_at_true_parameters():
    """Imitation loss ||x - x_expert||^2 + ||u - u_expert||^2 is minimal (zero) at the
    expert's parameters: its gradient through the layer is ~0 there and not elsewhere."""
    with torch.no_grad():
        x_e, u_e = pendulum_mpc(THETA[0], THETA[1], THETA[2:4], THETA[4:6])(X0)

    def grad_at(theta0):
        theta = theta0.clone().requires_grad_(True)
        x, u = pendulum_mpc(theta[0], theta[1], theta[2:4], theta[4:6])(X0)
        ((x - x_e).pow(2).sum() + (u - u_e).pow(2).sum()).backward()
        return theta.grad

    g_true = grad_at(THETA)
    g_off = grad_at(THETA * torch.tensor([1.1, 0.8, 1.0, 1.0, 1.2, 1.0], dtype=torch.float64))
    assert g_true.norm() < 1e-8
    assert g_off.norm() > 1e-2


class BumpCost(Cost):
    """Non-quadratic learnable cost: 1 - cos(theta - goal) + w thd^2 + r u^2."""

    def __init__(self, goal, w):
        super().__init__(state_dim=2, control_dim=1)
        self.goal = nn.Parameter(torch.tensor(goal, dtype=torch.float64))
        self.w = nn.Parameter(torch.tensor(w, dtype=torch.float64))

    def stage(self, x, u, t):
        return (
            1 - torch.cos(x[..., 0] - self.goal) + self.w * x[..., 1] ** 2 + 0.05 * u[..., 0] ** 2
        )

    def terminal(self, x):
        return 10 * (1 - torch.cos(x[..., 0] - self.goal)) + x[..., 1] ** 2


def test_general_cost_and_learned_dynamics_gradients_match_finite_differences():
    torch.manual_seed(3)
    net = nn.Sequential(nn.Linear(3, 16), nn.Tanh(), nn.Linear(16, 2)).double()
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(0.1)
    dyn = LearnedDynamics(net, 2, 1)
    cost = BumpCost(0.5, 0.1)
    mpc = MPC(dyn, cost, 10, solver=DDP(**TIGHT), warm_start=False)
    x0 = torch.tensor([[0.1, 0.0], [-0.3, 0.2]], dtype=torch.float64)
    wx = torch.randn(2, 11, 2, dtype=torch.float64)

    def loss():
        x, u = mpc(x0)
        return (wx * x).sum() + u.pow(2).sum()

    params = [net[2].bias, net[0].weight] + [p for p in cost.parameters()]
    loss().backward()
    gen = torch.Generator().manual_seed(1)
    for p in params:  # two random directions per parameter tensor
        for _ in range(2):
            v = torch.randn(p.shape, generator=gen, dtype=p.dtype)
            old = p.data.clone()
            with torch.no_grad():
                p.data.copy_(old + 1e-5 * v)
                lp = loss()
                p.data.copy_(old - 1e-5 * v)
                lm = loss()
                p.data.copy_(old)
            fd = (lp - lm) / 2e-5
            g = (p.grad * v).sum()
            assert abs(g - fd) <= 1e-6 * (1 + abs(fd)), (p.shape, float(g), float(fd))


def test_bounded_controls_gradients(backend):
    """With |u| <= 0.6 some controls saturate: they are held fixed (zero sensitivity),
    and the gradient still matches finite differences (the active set is locally
    constant)."""
    x0 = torch.tensor([[2.5, 0.0], [-0.4, 0.1]], dtype=torch.float64)

    def run(theta, x0=x0):
        mpc = pendulum_mpc(theta[0], theta[1], theta[2:4], theta[4:6], u_min=-0.6, u_max=0.6)
        x, u = mpc(x0)
        return x, u, mpc.last_result

    theta = THETA.clone().requires_grad_(True)
    x, u, res = run(theta)
    active = res.active_bounds != 0
    assert 0 < int(active.sum()) < active.numel()
    assert float(u.detach().abs().max()) <= 0.6 + 1e-12
    # du/dtheta is zero on the active set: the gradient of the active controls' sum
    (g_active,) = torch.autograd.grad(u[active].sum(), theta, retain_graph=True)
    assert float(g_active.abs().max()) == 0.0
    loss = (WX[:2] * x).sum() + (WU[:2] * u).sum()
    loss.backward()

    def f(th):
        xx, uu, r = run(th)
        assert torch.equal(r.active_bounds != 0, active)  # same active set
        return (WX[:2] * xx).sum() + (WU[:2] * uu).sum()

    fd = fd_grad(f, THETA, eps=1e-6)
    assert rel(theta.grad, fd) < 1e-5


def test_unconverged_elements_raise_warn_or_zero():
    theta = THETA.clone().requires_grad_(True)
    few = ILQR(max_iter=2, tol=1e-12, progress=False)
    with pytest.raises(RuntimeError, match="did not converge"):
        pendulum_mpc(theta[0], theta[1], theta[2:4], theta[4:6], solver=few, unconverged="raise")(
            X0
        )
    with pytest.warns(RuntimeWarning, match="did not converge"):
        out = pendulum_mpc(theta[0], theta[1], theta[2:4], theta[4:6], solver=few)(X0)
    assert (out.status == Status.MAX_ITER).all() and not out.converged.any()
    # "zero": only unconverged elements lose their gradient; with tol 1e-6 the start
    # [0.3, 0] needs 3 iterations and [-2, -6] needs 10, so max_iter=5 splits them
    solver = ILQR(max_iter=5, tol=1e-6, progress=False)
    x0 = torch.tensor([[0.3, 0.0], [-2.0, -6.0]], dtype=torch.float64).requires_grad_(True)
    mpc = pendulum_mpc(
        theta[0], theta[1], theta[2:4], theta[4:6], solver=solver, unconverged="zero"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "zero" does not warn
        out = mpc(x0)
    assert out.converged.tolist() == [True, False]
    (out.u.sum()).backward()
    bad = ~out.converged
    assert float(x0.grad[bad].abs().max()) == 0.0
    assert float(x0.grad[~bad].abs().max()) > 0.0


def test_no_gradient_needed_returns_plain_solution():
    mpc = pendulum_mpc(
        1.0,
        0.1,
        torch.tensor([1.0, 0.0], dtype=torch.float64),
        torch.tensor([1.0, 0.1], dtype=torch.float64),
        solver=ILQR(max_iter=50, tol=1e-6, progress=False),
    )
    x, u = mpc(X0)
    assert not x.requires_grad and not u.requires_grad
    with torch.no_grad():
        x2, _ = mpc(X0.clone().requires_grad_(True))
    assert not x2.requires_grad


def test_warm_start_shifts_previous_solution_and_saves_iterations():
    dyn = discretize(Pendulum(), DT, method="rk4")
    cost = QuadraticCost(
        Q=torch.diag(torch.tensor([1.0, 0.1], dtype=torch.float64)),
        R=0.1 * torch.eye(1, dtype=torch.float64),
        Qf=torch.diag(torch.tensor([10.0, 1.0], dtype=torch.float64)),
        x_ref=torch.tensor([1.0, 0.0], dtype=torch.float64),
    )
    # (at tol 1e-9 the last iterations are at the gradient's rounding level, and how
    # many a solve takes there changes with the rounding of its LQ passes)
    warm = MPC(dyn, cost, T, solver=ILQR(max_iter=200, tol=1e-7, progress=False))
    cold = MPC(dyn, cost, T, solver=ILQR(max_iter=200, tol=1e-7, progress=False), warm_start=False)
    x = X0.clone()
    a = warm.step(x)
    u_prev = warm.last_result.u
    x = dyn(x, a)
    stored = warm._warm["u"]
    torch.testing.assert_close(stored[:, :-1], u_prev[:, 1:])
    torch.testing.assert_close(stored[:, -1], u_prev[:, -1])
    out_w = warm(x)
    out_c = cold(x)
    torch.testing.assert_close(out_w.u, out_c.u, rtol=1e-6, atol=1e-7)
    assert int(out_w.result.iterations.sum()) < int(out_c.result.iterations.sum())
    assert a.shape == (3, 1)
    warm.reset()
    assert warm._warm is None


def test_float32_runs():
    dyn = discretize(Pendulum(mass=nn.Parameter(torch.tensor(1.0))), DT, method="rk4")
    cost = QuadraticCost(
        Q=torch.diag(torch.tensor([1.0, 0.1])), R=0.1 * torch.eye(1), x_ref=torch.tensor([1.0, 0.0])
    )
    mpc = MPC(dyn, cost, T, solver=ILQR(max_iter=100, tol=1e-4, progress=False))
    x0 = X0.float().requires_grad_(True)
    x, u = mpc(x0)
    u.sum().backward()
    assert x.dtype == torch.float32 and torch.isfinite(x0.grad).all()
    assert dyn.continuous.mass.grad is not None and torch.isfinite(dyn.continuous.mass.grad)


def test_validation():
    dyn = discretize(Pendulum(), DT)
    cost = QuadraticCost(Q=torch.eye(2), R=torch.eye(1))
    with pytest.raises(ValueError, match="backward"):
        MPC(dyn, cost, T, backward="adjoint")
    with pytest.raises(ValueError, match="warm_start"):
        MPC(dyn, cost, T, warm_start="yes")
    with pytest.raises(ValueError, match="unconverged"):
        MPC(dyn, cost, T, unconverged="ignore")
    with pytest.raises(ValueError, match="bounds need an ILQR"):
        MPC(dyn, cost, T, solver=SLQ(), u_max=1.0)
    with pytest.raises(TypeError, match="solver"):
        MPC(dyn, cost, T, solver="ilqr")
    with pytest.raises(ValueError, match="horizon"):
        MPC(dyn, cost, 0)
    mpc = MPC(dyn, cost, T)
    with pytest.raises(ValueError, match=r"x0 must have shape \(B, 2\)"):
        mpc(torch.zeros(3, 3))
    with pytest.raises(TypeError, match="x0"):
        mpc(torch.zeros(3, 2, dtype=torch.int64))


def test_shifted_warm_start_applies_the_previous_gains():
    """The guess is ``u_prev + K_prev (x - x_prev)`` rolled out from the new state: equal
    to the plain shift when the state is where the model predicted, corrected when not."""
    dyn = discretize(Pendulum(), DT, method="rk4")
    cost = QuadraticCost(
        Q=torch.diag(torch.tensor([1.0, 0.1], dtype=torch.float64)),
        R=0.1 * torch.eye(1, dtype=torch.float64),
        x_ref=torch.tensor([1.0, 0.0], dtype=torch.float64),
    )
    mpc = MPC(dyn, cost, T, solver=ILQR(max_iter=200, tol=1e-9, progress=False))
    out = mpc(X0)
    res = out.result
    x_pred = res.x[:, 1]
    guess, _ = mpc._initial_guess(x_pred, None)
    torch.testing.assert_close(guess[:, :-1], res.u[:, 1:], rtol=0, atol=1e-12)
    x_off = x_pred + torch.tensor([0.05, -0.1], dtype=torch.float64)
    guess, guess_x = mpc._initial_guess(x_off, None)
    # the states handed to the solver (which then skips its initial rollout) are the
    # rollout of the guess from the new state, bit for bit
    from torchslq.dynamics.rollout import rollout

    assert torch.equal(guess_x, rollout(mpc.problem.transition, x_off, guess))
    K1 = res.K[:, 1]
    expected_first = res.u[:, 1] + (K1 @ (x_off - x_pred).unsqueeze(-1))[..., 0]
    torch.testing.assert_close(guess[:, 0], expected_first, rtol=1e-12, atol=1e-12)
    assert float((guess[:, :-1] - res.u[:, 1:]).abs().max()) > 1e-3


def test_indefinite_elements_get_zero_gradient_and_do_not_poison_the_batch():
    """Elements stopped far from a minimum where the Hessian of the Lagrangian is not
    positive definite keep the solver's values, get zero gradient, and the shared
    parameters' gradient equals that of the other elements alone (no NaN)."""
    kw = dict(dtype=torch.float64)

    def build(goal):
        cost = QuadraticCost(
            0.05 * torch.eye(2, **kw),
            0.005 * torch.eye(1, **kw),
            Qf=100 * torch.eye(2, **kw),
            x_ref=goal,
        )
        solver = ILQR(max_iter=3, tol=1e-8, progress=False)
        return MPC(discretize(Pendulum(), 0.05), cost, 30, solver=solver, warm_start=False)

    gen = torch.Generator().manual_seed(0)
    x0 = (torch.rand(64, 2, generator=gen, **kw) * 2 - 1) * 3
    goal = torch.tensor([math.pi, 0.0], **kw, requires_grad=True)
    mpc = build(goal)
    with torch.no_grad():
        res = mpc(x0).result
    _, _, lq_status = implicit_solution(mpc.problem, x0, res.x, res.u)
    not_pd = lq_status == Status.NOT_POSITIVE_DEFINITE
    assert 0 < int(not_pd.sum()) < 64
    x0r = x0.clone().requires_grad_(True)
    with pytest.warns(RuntimeWarning):
        out = build(goal)(x0r)
    assert torch.equal(out.x.detach(), out.result.x) and torch.isfinite(out.x).all()
    (out.u.sum() + out.x.sum()).backward()
    assert torch.isfinite(goal.grad).all() and torch.isfinite(x0r.grad).all()
    assert float(x0r.grad[not_pd].abs().max()) == 0.0
    assert float(x0r.grad[~not_pd].abs().max()) > 0.0
    # the same gradient from the other elements alone
    goal2 = goal.detach().clone().requires_grad_(True)
    with pytest.warns(RuntimeWarning):
        out2 = build(goal2)(x0[~not_pd])
    (out2.u.sum() + out2.x.sum()).backward()
    torch.testing.assert_close(goal.grad, goal2.grad, rtol=1e-9, atol=1e-12)


def _fixed_point_lq_solution(problem, x0, x, u, hessian, active=None):
    """Independent reference for the implicit derivative: the LQ problem whose minimiser
    is the solution ``(x, u)`` itself, built from ``create_graph`` Jacobians and cost
    gradients and differentiated through ``lqr_solve``'s own implicit backward (the
    formulation of Amos et al. 2018; a different code path from implicit_solution's)."""
    from torchslq import linearize, lqr_solve
    from torchslq.mpc import cost_gradients, lagrangian_hessian

    T = problem.horizon
    A, Bm = linearize(problem.dynamics, x[:, :T], u, create_graph=True)
    Q, R, S, _, _ = lagrangian_hessian(problem, x, u, hessian)
    lx, lu = cost_gradients(problem.cost, x, u)
    uf = u
    if active is not None:
        keep = (~active).to(x.dtype)
        Bm = Bm * keep.unsqueeze(-2)
        R = R * keep.unsqueeze(-1) * keep.unsqueeze(-2) + torch.diag_embed(1.0 - keep)
        S = S * keep.unsqueeze(-1)
        uf = u * keep
    c = problem.transition(x[:, :T], u) - (A @ x[:, :T, :, None])[..., 0]
    c = c - (Bm @ uf[..., None])[..., 0]
    q = lx - (Q @ x[..., None])[..., 0]
    q = torch.cat([q[:, :T] - (S.mT @ uf[..., None])[..., 0], q[:, T:]], dim=1)
    r = lu - (S @ x[:, :T, :, None])[..., 0] - (R @ uf[..., None])[..., 0]
    if active is not None:
        r = r * keep
    sol = lqr_solve(A, Bm, Q, R, x0, q, r, S, c)
    return sol.x, sol.u


@pytest.mark.parametrize("hessian", ["exact", "gn"])
@pytest.mark.parametrize("bounded", [False, True])
def test_implicit_solution_equals_fixed_point_lq_derivative(hessian, bounded):
    """implicit_solution's backward (KKT residual + adjoint LQ sweep) gives the same
    gradients w.r.t. x0, dynamics and cost parameters as differentiating the fixed-point
    LQ problem through lqr_solve, to round-off, for both Hessians, with and without
    active bounds."""
    x0 = torch.tensor([[2.5, 0.0], [-0.4, 0.1]], dtype=torch.float64)
    kw = dict(u_min=-0.6, u_max=0.6) if bounded else {}
    theta = THETA.clone().requires_grad_(True)
    x0r = x0.clone().requires_grad_(True)
    mpc = pendulum_mpc(theta[0], theta[1], theta[2:4], theta[4:6], **kw)
    with torch.no_grad():
        res = mpc(x0).result
    active = res.active_bounds != 0 if bounded else None
    if bounded:
        assert 0 < int(active.sum()) < active.numel()
    grads = []
    for build in ("implicit", "reference"):
        if build == "implicit":
            x, u, st = implicit_solution(
                mpc.problem, x0r, res.x, res.u, hessian=hessian, active=active
            )
            assert bool((st == Status.CONVERGED).all())
            assert torch.equal(x.detach(), res.x) and torch.equal(u.detach(), res.u)
        else:
            x, u = _fixed_point_lq_solution(mpc.problem, x0r, res.x, res.u, hessian, active)
        loss = (WX[:2] * x).sum() + (WU[:2] * u).sum()
        grads.append(torch.autograd.grad(loss, (theta, x0r)))
    for g, g_ref in zip(grads[0], grads[1], strict=True):
        assert float(g_ref.abs().max()) > 0
        torch.testing.assert_close(g, g_ref, rtol=1e-8, atol=1e-10)


def test_default_solver_tolerance_follows_the_dtype():
    """The default solver asks for ||dJ/dU|| < 1e-8 in float64 but 1e-4 in float32 (1e-8
    is below float32's round-off floor: every element would stall and warn). The float32
    solve then converges without a warning, to the float64 solution within float32
    accuracy; a user's solver keeps its own tolerance."""
    dyn = discretize(Pendulum(mass=nn.Parameter(torch.tensor(1.0))), DT, method="rk4")
    cost = QuadraticCost(
        Q=torch.diag(torch.tensor([1.0, 0.1])), R=0.1 * torch.eye(1), x_ref=torch.tensor([1.0, 0.0])
    )
    mpc = MPC(dyn, cost, T, warm_start=False)
    x0 = X0.float().requires_grad_(True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        out32 = mpc(x0)
    assert bool(out32.converged.all())
    assert float(out32.result.grad_norm.max()) < 1e-4
    out64 = MPC(dyn.double(), cost.double(), T, warm_start=False)(X0)
    assert bool(out64.converged.all()) and float(out64.result.grad_norm.max()) < 1e-8
    torch.testing.assert_close(out32.u.double(), out64.u, rtol=0, atol=1e-3)
    own = MPC(dyn.float(), cost.float(), T, solver=ILQR(max_iter=30, tol=1e-8, progress=False))
    with pytest.warns(RuntimeWarning, match="did not converge"):
        own(X0.float().requires_grad_(True))
