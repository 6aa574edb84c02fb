"""GoPRONTO (Algorithms 2-4), first-order PRONTO (Algorithm 1) and the gradient baseline."""

from __future__ import annotations

import math

import pytest
import torch

import torchslq
from torchslq import Dynamics, GoPRONTO, GradientMethod, Problem, QuadraticCost
from torchslq.costs.barrier import box_log_barrier
from torchslq.dynamics.rollout import rollout
from torchslq.solvers.gopronto import closed_loop_growth, curve_gradient, project
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


def random_curve(seed: int, T: int, B: int, scale: float):
    """TwoLink problem, initial states, a random curve (alpha, mu) and random gains K."""
    g = torch.Generator().manual_seed(seed)
    prob = Problem(TwoLink(), nonquadratic_cost(), T)
    x0 = 0.5 * torch.randn(B, 3, dtype=DT, generator=g)
    alpha = scale * torch.randn(B, T, 3, dtype=DT, generator=g)
    mu = scale * torch.randn(B, T, 2, dtype=DT, generator=g)
    K = 0.5 * torch.randn(B, T, 2, 3, dtype=DT, generator=g)
    return prob, x0, alpha, mu, K


def autograd_curve_gradient(prob, x0, alpha, mu, K):
    """Reference: reverse-mode autodiff of ``J(P(alpha, mu))`` through the projection."""
    a = alpha.clone().requires_grad_(True)
    m = mu.clone().requires_grad_(True)
    x, u = project(prob.transition, x0, a, m, K)
    return torch.autograd.grad(prob.cost(x, u).sum(), (a, m))


# ---------------------------------------------------------------------------- the gradient
def test_costate_gradient_equals_autograd(backend):
    T = 12
    prob, x0, alpha, mu, K = random_curve(0, T, 3, 0.3)
    f = prob.transition
    ga_ref, gm_ref = autograd_curve_gradient(prob, x0, alpha, mu, K)
    with torch.no_grad():
        x, u = project(f, x0, alpha, mu, K)
        A, Bm = torchslq.linearize(f, x[:, :T], u)
        e = prob.cost.quadratize(x, u)
        ga, gm, _ = curve_gradient(A, Bm, e.lx, e.lu, K)
    assert torch.allclose(gm, gm_ref, atol=1e-8, rtol=1e-8)
    assert torch.allclose(ga, ga_ref, atol=1e-8, rtol=1e-8)
    assert ga_ref.abs().max() > 1e-3  # the alpha part is not trivially zero


def test_reported_gradient_norm_is_that_of_the_returned_curve():
    prob, x0, *_ = random_curve(2, 12, 2, 0.3)
    r = GoPRONTO(variant="conjugate", max_iter=4, progress=False).solve(prob, x0)
    ga, gm = autograd_curve_gradient(prob, x0, r.alpha, r.mu, r.K)
    ref = (ga.pow(2).sum((1, 2)) + gm.pow(2).sum((1, 2))).sqrt()
    assert torch.allclose(r.grad_norm, ref, rtol=1e-8)
    assert bool((ref > 1e-4).all())  # not converged: a non-trivial comparison


def test_projection_is_a_projection():
    T = 15
    prob, x0, alpha, mu, K = random_curve(1, T, 2, 1.0)
    f = prob.transition
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


@pytest.fixture(scope="module")
def twolink():
    """A smooth nonlinear problem and its solution by an independent solver (iLQR)."""
    torch.manual_seed(0)
    prob = Problem(TwoLink(), nonquadratic_cost(), 15)
    x0 = 0.5 * torch.randn(2, 3, dtype=DT)
    ref = torchslq.ILQR(max_iter=100, progress=False).solve(prob, x0)
    assert ref.converged.all()
    return prob, x0, ref


@pytest.mark.parametrize("variant", ["gradient", "conjugate", "heavy_ball", "nesterov"])
def test_variants_decrease_cost_and_reach_small_gradient(variant, twolink):
    prob, x0, ref = twolink
    # tol 2e-6: these first-order methods reach a round-off floor (cost changes of
    # 1e-15 relative in the last iterations) between ~5e-7 and ~1.5e-6 on this problem,
    # depending on the rounding of the kernel: conjugate gradients stalled at 1.51e-6
    # with the compiled Riccati kernel and at 8.2e-7 with the torch one; 1e-7 never
    # converged, and heavy-ball missed 1e-6 on torch 2.11 (GPU machine's CPU run)
    r = GoPRONTO(variant=variant, max_iter=200, tol=2e-6, progress=False).solve(prob, x0)
    assert r.converged.all(), (variant, r.status_names())
    assert bool((r.grad_norm < 2e-6).all())
    hist = r.history["cost"]
    assert bool((hist[:, 1:] <= hist[:, :-1] + 1e-12).all())  # Armijo: never increases
    assert bool((hist[:, -1] < hist[:, 0]).all())
    assert torch.allclose(r.cost, ref.cost, rtol=1e-9)
    assert torch.allclose(r.u, ref.u, atol=1e-5)


@pytest.mark.parametrize("variant", ["gradient", "nesterov"])
def test_variants_on_pendulum_swingup(variant):
    prob, x0 = pendulum_swingup(batch=2, horizon=30)
    r = GoPRONTO(variant=variant, max_iter=30, progress=False).solve(prob, x0)
    hist, g = r.history["cost"], r.history["grad_norm"]
    assert bool((hist[:, 1:] <= hist[:, :-1] + 1e-9).all())
    assert bool((hist[:, -1] < 0.1 * hist[:, 0]).all())
    assert bool((g[:, -1] < 0.1 * g[:, 0]).all())
    # the returned trajectory is the projection of the returned curve
    x, u = project(prob.transition, x0, r.alpha, r.mu, r.K)
    assert torch.allclose(x, r.x, atol=1e-10) and torch.allclose(u, r.u, atol=1e-10)


class SoftenedGrowth(Dynamics):
    """Scalar ``x+ = a(x) x + 0.1 u``, ``a = 0.9 + 0.4 x^2/(1+x^2)``: stable near 0,
    unstable near the target 2 (linearisation ~1.35)."""

    state_dim, control_dim = 1, 1

    def forward(self, x, u):
        return (0.9 + 0.4 * x**2 / (1 + x**2)) * x + 0.1 * u


def test_gain_recomputation_rule_and_counting():
    T = 40
    cost = QuadraticCost(
        torch.eye(1, dtype=DT), 0.01 * torch.eye(1, dtype=DT), x_ref=torch.tensor([2.0], dtype=DT)
    )
    prob = Problem(SoftenedGrowth(), cost, T)
    x0 = torch.tensor([[0.0], [0.1]], dtype=DT)
    kw = dict(R_reg=1e4, max_iter=30, progress=False)  # weak gains: no margin to spare
    never = GoPRONTO(recompute="never", **kw).solve(prob, x0)
    auto = GoPRONTO(recompute="auto", stability_tol=20.0, **kw).solve(prob, x0)
    always = GoPRONTO(recompute="always", **kw).solve(prob, x0)
    # the gains computed about the start (x ~ 0) amplify more than stability_tol about
    # the trajectory the solver moves to (an independent linearisation) ...
    A, B = torchslq.linearize(prob.transition, never.x[:, :T], never.u)
    assert bool((closed_loop_growth(A, B, never.K) > 20.0).all())
    assert never.recomputations.tolist() == [0, 0]
    # ... so "auto" recomputes them, a few times, not at every iteration
    assert bool((auto.recomputations >= 1).all()) and bool((auto.recomputations <= 5).all())
    for r in (never, auto, always):
        assert torch.equal(r.recomputations, r.history["recompute"].sum(1))
    assert torch.equal(always.recomputations, always.iterations)  # every step accepted
    assert not bool(auto.history["recompute"][:, 0].any())  # the first gains are not counted
    for r in (never, auto, always):
        hist = r.history["cost"]
        assert bool((hist[:, -1] < 0.6 * hist[:, 0]).all())


def test_batch_equals_singles(backend):
    prob, x0 = pendulum_swingup(batch=3, horizon=30)
    solver = GoPRONTO(variant="conjugate", max_iter=15, progress=False)
    rb = solver.solve(prob, x0)
    for i in range(3):
        ri = solver.solve(prob, x0[i])  # unbatched in, unbatched out
        assert ri.x.shape == (31, 2) and ri.K.shape == (30, 1, 2) and ri.alpha.shape == (30, 2)
        assert ri.recomputations.ndim == 0 and ri.extra["cg_restarts"].ndim == 0
        assert torch.allclose(ri.x, rb.x[i], atol=1e-9, rtol=1e-9)
        assert torch.allclose(ri.u, rb.u[i], atol=1e-9, rtol=1e-9)
        assert int(ri.iterations) == int(rb.iterations[i])
        assert torch.allclose(ri.history["grad_norm"], rb.history["grad_norm"][i], rtol=1e-8)


def test_chunked_armijo_equals_all_at_once():
    prob, x0 = pendulum_swingup(batch=2, horizon=30)
    r1 = GoPRONTO(max_iter=12, armijo_chunk=1, progress=False).solve(prob, x0)
    r2 = GoPRONTO(max_iter=12, progress=False).solve(prob, x0)  # one rollout of 30 trials
    assert torch.equal(r1.history["step"], r2.history["step"])
    assert torch.allclose(r1.x, r2.x, atol=1e-12)


def test_barrier_keeps_inputs_inside_bounds():
    prob, x0 = pendulum_swingup(batch=2, horizon=30)
    free = GoPRONTO(max_iter=10, progress=False).solve(prob, x0)
    u_max = 2.0
    assert float(free.u.abs().max()) > 2 * u_max  # the bound is active
    # an infeasible initial guess is clipped into the bounds (feasible start)
    u_init = torch.full((30, 1), 5.0, dtype=DT)
    r = GoPRONTO(max_iter=40, u_max=u_max, progress=False).solve(prob, x0, u_init=u_init)
    assert float(r.u.abs().max()) < u_max
    assert torch.allclose(
        box_log_barrier(r.u, torch.tensor([u_max], dtype=DT)).isfinite().double(),
        torch.ones(2, dtype=DT),
    )
    obj = r.history["objective"]
    assert bool(torch.isfinite(obj).all())
    assert bool((r.history["cost"][:, -1] < r.history["cost"][:, 0]).all())
    w = r.history["barrier_weight"]
    assert bool((w[:, 1:] <= w[:, :-1]).all()) and bool((w[:, -1] < w[:, 0]).all())
    # bounds given per input as a tensor behave the same
    r2 = GoPRONTO(max_iter=5, u_max=torch.tensor([u_max], dtype=DT), progress=False).solve(prob, x0)
    assert float(r2.u.abs().max()) < u_max


def test_constant_step_momentum(twolink):
    prob, x0, _ = twolink
    kw = dict(step=0.02, gamma_hb=0.5, max_iter=25, tol=1e-9, progress=False)
    grad = GoPRONTO(**kw).solve(prob, x0)
    for variant in ("heavy_ball", "nesterov"):
        mom = GoPRONTO(variant=variant, **kw).solve(prob, x0)
        assert bool((mom.history["step"][:, 1:] == 0.02).all())  # constant, every iteration
        # momentum accelerates the constant-step gradient method (the paper's Figure 7)
        assert bool((mom.grad_norm < 0.5 * grad.grad_norm).all()), variant
        assert bool((mom.cost <= grad.cost).all())


def test_pronto_matches_ilqr_and_identity_weights_descend(backend):
    prob, x0 = pendulum_swingup(batch=2, horizon=40)
    ref = torchslq.ILQR(max_iter=100, progress=False).solve(prob, x0)
    assert ref.converged.all()
    r = torchslq.PRONTO(max_iter=60, tol=1e-6, progress=False).solve(prob, x0)
    assert r.converged.all(), r.status_names()
    assert torch.allclose(r.cost, ref.cost, rtol=1e-8)
    assert torch.equal(r.recomputations, r.iterations)  # gains at every iteration
    ri = torchslq.PRONTO(weights="identity", max_iter=10, progress=False).solve(prob, x0)
    hist = ri.history["cost"]
    assert bool((hist[:, 1:] <= hist[:, :-1]).all()) and bool(
        (hist[:, -1] < 0.5 * hist[:, 0]).all()
    )


def test_float32():
    prob, x0 = pendulum_swingup(batch=2, horizon=30, dtype=torch.float32)
    for solver in (
        GoPRONTO(variant="nesterov", max_iter=20, progress=False),
        torchslq.PRONTO(max_iter=5, progress=False),
    ):
        r = solver.solve(prob, x0)
        assert r.x.dtype == torch.float32 and r.K.dtype == torch.float32
        assert bool(torch.isfinite(r.x).all())
        hist = r.history["cost"]
        assert bool((hist[:, -1] < 0.2 * hist[:, 0]).all())


def test_logger_receives_every_iteration():
    class Recorder:
        def __init__(self):
            self.its, self.options, self.result = [], None, None

        def log_options(self, name, options):
            self.options = (name, options)

        def log_iteration(self, it, **kw):
            self.its.append((it, kw["cost"].clone(), kw["grad_norm"].clone()))

        def log_result(self, result, problem=None):
            self.result = result

    prob, x0 = pendulum_swingup(batch=2, horizon=20)
    log = Recorder()
    r = GoPRONTO(max_iter=5, progress=False).solve(prob, x0, logger=log)
    assert log.options[0] == "gopronto" and log.options[1]["variant"] == "gradient"
    assert [i for i, *_ in log.its] == list(range(6))
    assert torch.equal(torch.stack([c for _, c, _ in log.its], 1), r.history["cost"])
    assert log.result is r


def test_validation_errors():
    with pytest.raises(ValueError, match="variant"):
        GoPRONTO(variant="adam")
    with pytest.raises(ValueError, match="step"):
        GoPRONTO(step="wolfe")
    with pytest.raises(ValueError, match="step"):
        GoPRONTO(step=-1e-3)
    with pytest.raises(TypeError, match="step"):
        GoPRONTO(step=[0.1])
    with pytest.raises(ValueError, match="tol"):
        GoPRONTO(tol=0.0)
    with pytest.raises(ValueError, match="gamma_hb"):
        GoPRONTO(variant="heavy_ball", gamma_hb=1.0)
    with pytest.raises(ValueError, match="max_iter"):
        GoPRONTO(max_iter=-1)
    with pytest.raises(ValueError, match="recompute"):
        GoPRONTO(recompute="sometimes")
    with pytest.raises(ValueError, match="u_max"):
        GoPRONTO(u_max=-1.0)
    with pytest.raises(ValueError, match="barrier_min"):
        GoPRONTO(barrier_weight=1e-3, barrier_min=1e-2)
    with pytest.raises(TypeError, match="R_reg"):
        GoPRONTO(R_reg="identity")
    with pytest.raises(TypeError, match="unknown option"):
        GoPRONTO(gamma=0.1)
    with pytest.raises(ValueError, match="order"):
        torchslq.PRONTO(order="second")
    with pytest.raises(ValueError, match="weights"):
        torchslq.PRONTO(weights="newton")
    with pytest.raises(TypeError, match="variant"):
        torchslq.PRONTO(variant="nesterov")
    prob, x0 = pendulum_swingup(batch=2, horizon=10)
    with pytest.raises(ValueError, match="Q_reg"):
        GoPRONTO(Q_reg=torch.eye(3, dtype=DT)).solve(prob, x0)
    with pytest.raises(ValueError, match="u_max"):
        GoPRONTO(u_max=torch.ones(2, dtype=DT)).solve(prob, x0)
    with pytest.raises(ValueError, match="alpha_init"):
        GoPRONTO().solve(prob, x0, alpha_init=torch.zeros(9, 2, dtype=DT))
    with pytest.raises(ValueError, match="x0"):
        GoPRONTO().solve(prob, torch.zeros(2, 3, dtype=DT))


def test_non_finite_element_does_not_poison_the_batch():
    prob, x0 = unstable_problem(30)
    bad = torch.tensor([[1e200, 0.0]], dtype=DT)  # its cost overflows to inf
    solver = GoPRONTO(max_iter=15, progress=False)
    rb = solver.solve(prob, torch.cat([bad, x0[:1]]))
    r1 = solver.solve(prob, x0[:1])
    assert rb.status_names()[0] == "non_finite"
    assert int(rb.iterations[0]) == 0
    assert torch.allclose(rb.x[1], r1.x[0], atol=1e-10)
    assert int(rb.iterations[1]) == int(r1.iterations[0]) > 0


def test_float32_stops_as_stalled_at_its_precision_limit(twolink):
    """In float32 a gradient tolerance of 1e-7 is below what the iteration can resolve:
    with the shared stall rule GoPRONTO stops (status ``stalled``) long before
    ``max_iter``, at the float64 optimum to float32 precision; without it, it runs on."""
    prob, x0, ref = twolink
    x32 = x0.float()
    r = GoPRONTO(max_iter=150, tol=1e-7, progress=False).solve(prob, x32)
    r0 = GoPRONTO(max_iter=150, tol=1e-7, progress=False, stall_iters=0).solve(prob, x32)
    assert r.status_names() == ["stalled", "stalled"]
    assert int(r.iterations.max()) < 100
    assert r0.status_names() == ["max_iter", "max_iter"]
    torch.testing.assert_close(r.cost.double(), ref.cost, rtol=1e-6, atol=0)
    with pytest.raises(ValueError, match="stall_iters"):
        GoPRONTO(stall_iters=-1)
