"""Pendulum-on-cart train (GoPRONTO 2022, Section V), the batched DARE and the paper's
problem builder, each against an independent computation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch

import torchslq
from reproductions.gopronto import (
    PAPER_TABLE1_PARAMS,
    pendulum_train_dynamics,
    pendulum_train_problem,
    theta_reference,
    upright_linearization,
)
from torchslq.lq import dare, dare_gain, dare_residual
from torchslq.systems import PendulumCartTrain, PendulumCartTrainRK4

DT = torch.float64


# ---------------------------------------------------------------------- hand transcription
def hand_xdot(x: list[float], u: list[float], coupling: str = "paper", **over) -> list[float]:
    """Section V.1 equations, written out per cart with plain floats (erratum: cos before
    w_ddot), solved with a 2x2 numpy linear solve of the mass matrix."""
    p = {**PAPER_TABLE1_PARAMS, **over}
    Mp, l, fp, Mc, ks, fc, g = (p[k] for k in ("Mp", "l", "fp", "Mc", "ks", "fc", "g"))
    N = len(u)
    w = [x[4 * i + 2] for i in range(N)]
    out = []
    for i in range(N):
        th, thd, wi, wd = x[4 * i : 4 * i + 4]
        w_next = w[i + 1] if i + 1 < N else 0.0
        w_prev = w[i - 1] if i > 0 else 0.0
        if coupling == "paper":  # "- ks w_{i+1} + ks w_{i-1}" on the left-hand side
            spring_lhs = -ks * w_next + ks * w_prev
        else:
            spring_lhs = (ks * (wi - w_next) if i + 1 < N else 0.0) + (
                ks * (wi - w_prev) if i > 0 else 0.0
            )
        # Mp l^2 thdd - Mp l cos(th) wdd = -fp thd + Mp l g sin(th)
        # -1/2 Mp l cos(th) thdd + (Mc + Mp) wdd = u - fc wd - 1/2 Mp l sin(th) thd^2 - spring
        M = np.array([[Mp * l**2, -Mp * l * math.cos(th)], [-0.5 * Mp * l * math.cos(th), Mc + Mp]])
        rhs = np.array(
            [
                -fp * thd + Mp * l * g * math.sin(th),
                u[i] - fc * wd - 0.5 * Mp * l * math.sin(th) * thd**2 - spring_lhs,
            ]
        )
        thdd, wdd = np.linalg.solve(M, rhs)
        out += [thd, float(thdd), wd, float(wdd)]
    return out


@pytest.mark.parametrize("coupling", ["paper", "spring"])
@pytest.mark.parametrize("N", [1, 2, 3])
def test_dynamics_match_hand_transcription(N, coupling):
    g = torch.Generator().manual_seed(N)
    x = torch.randn(6, 4 * N, dtype=DT, generator=g) * 1.5
    u = torch.randn(6, N, dtype=DT, generator=g) * 3.0
    f = PendulumCartTrain(N, coupling=coupling, **PAPER_TABLE1_PARAMS)
    got = f(x, u)
    ref = torch.tensor(
        [hand_xdot(x[b].tolist(), u[b].tolist(), coupling) for b in range(x.shape[0])], dtype=DT
    )
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)


def test_default_parameters_are_table_one():
    f = PendulumCartTrain(2)
    x = torch.tensor([0.3, -0.2, 0.1, 0.4, -0.5, 0.7, -0.2, 0.1], dtype=DT)
    u = torch.tensor([1.0, -2.0], dtype=DT)
    torch.testing.assert_close(f(x, u), torch.tensor(hand_xdot(x.tolist(), u.tolist()), dtype=DT))


@pytest.mark.parametrize("coupling", ["paper", "spring"])
def test_continuous_jacobians_match_autodiff(coupling):
    N = 4
    f = PendulumCartTrain(N, coupling=coupling)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(3, 5, 4 * N, dtype=DT, generator=g)
    u = torch.randn(3, 5, N, dtype=DT, generator=g)
    A, B = f.jacobians(x, u)
    Aa, Ba = torch.func.vmap(torch.func.jacrev(lambda a, b: f(a, b), argnums=(0, 1)))(
        x.reshape(-1, 4 * N), u.reshape(-1, N)
    )
    torch.testing.assert_close(A.reshape(-1, 4 * N, 4 * N), Aa, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(B.reshape(-1, 4 * N, N), Ba, rtol=1e-12, atol=1e-12)


def test_discrete_jacobians_match_autodiff_and_finite_differences():
    N = 3
    dyn = pendulum_train_dynamics(N)
    assert dyn.has_analytic_jacobians and dyn.dt == 0.05 and dyn.method == "rk4"
    g = torch.Generator().manual_seed(4)
    x = torch.randn(4, 4 * N, dtype=DT, generator=g)
    u = torch.randn(4, N, dtype=DT, generator=g)
    A, B = torchslq.linearize(dyn, x, u)
    Aa, Ba = torchslq.linearize(lambda a, b: dyn(a, b), x, u)  # plain callable: autodiff
    torch.testing.assert_close(A, Aa, rtol=1e-11, atol=1e-12)
    torch.testing.assert_close(B, Ba, rtol=1e-11, atol=1e-12)
    # central differences on one column each
    h = 1e-6
    e = torch.zeros(4 * N, dtype=DT)
    e[5] = h
    fd = (dyn(x + e, u) - dyn(x - e, u)) / (2 * h)
    torch.testing.assert_close(A[..., 5], fd, rtol=1e-7, atol=1e-8)


@pytest.mark.parametrize("coupling", ["paper", "spring"])
@pytest.mark.parametrize("N", [1, 2, 5, 11])
def test_banded_rk4_jacobians_match_dense_chain_and_autodiff(N, coupling):
    """PendulumCartTrainRK4 (banded chain) == discretize(...) (dense chain) == autodiff;
    N = 11 exceeds the band (carts i-2..i+2): the band must hold every nonzero."""
    train = PendulumCartTrain(N, coupling=coupling)
    fast = PendulumCartTrainRK4(train, 0.05)
    dense = torchslq.discretize(train, 0.05, "rk4")
    g = torch.Generator().manual_seed(10 + N)
    x = torch.randn(2, 3, 4 * N, dtype=DT, generator=g)
    u = torch.randn(2, 3, N, dtype=DT, generator=g) * 3
    torch.testing.assert_close(fast(x, u), dense(x, u), rtol=0, atol=0)
    A, B = fast.jacobians(x, u)
    Ad, Bd = dense.jacobians(x, u)
    Aa, Ba = torchslq.linearize(lambda a, b: dense(a, b), x, u)
    torch.testing.assert_close(A, Ad, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(B, Bd, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(A, Aa, rtol=1e-11, atol=1e-12)
    torch.testing.assert_close(B, Ba, rtol=1e-11, atol=1e-12)
    if N == 11:
        Ar = A.reshape(2, 3, N, 4, N, 4)
        assert Ar[:, :, 5, :, 3].abs().min() == 0 and Ar[:, :, 5, 1, 3, 2].abs().min() > 0
        assert Ar[:, :, 5, :, :3].abs().max() == 0 and Ar[:, :, 5, :, 8:].abs().max() == 0


def test_per_element_parameters_broadcast():
    N = 2
    Mp = torch.tensor([[0.2], [0.5], [1.0]], dtype=DT)
    f = PendulumCartTrain(N, Mp=Mp)
    g = torch.Generator().manual_seed(5)
    x = torch.randn(3, 7, 4 * N, dtype=DT, generator=g)
    u = torch.randn(3, 7, N, dtype=DT, generator=g)
    out = f(x, u)
    A, B = f.jacobians(x, u)
    Ad, Bd = PendulumCartTrainRK4(f, 0.05).jacobians(x, u)
    for b in range(3):
        fb = PendulumCartTrain(N, Mp=float(Mp[b, 0]))
        torch.testing.assert_close(out[b], fb(x[b], u[b]))
        Ab, Bb = fb.jacobians(x[b], u[b])
        torch.testing.assert_close(A[b], Ab)
        torch.testing.assert_close(B[b], Bb)
        Adb, Bdb = torchslq.discretize(fb, 0.05).jacobians(x[b], u[b])
        torch.testing.assert_close(Ad[b], Adb)
        torch.testing.assert_close(Bd[b], Bdb)


@pytest.mark.parametrize("coupling", ["paper", "spring"])
def test_upright_is_an_unstable_equilibrium(coupling):
    N = 3
    f = PendulumCartTrain(N, coupling=coupling)
    x0, u0 = torch.zeros(4 * N, dtype=DT), torch.zeros(N, dtype=DT)
    assert f(x0, u0).abs().max() == 0
    dyn = pendulum_train_dynamics(N, coupling=coupling)
    assert dyn(x0, u0).abs().max() == 0
    # the open-loop linearisation is unstable (inverted pendulums): a DT eigenvalue > 1
    A, B = upright_linearization(dyn)
    assert torch.linalg.eigvals(A).abs().max() > 1.05
    # ... and controllable through the cart forces thanks to the cos(theta) coupling
    ctrb = torch.cat([torch.linalg.matrix_power(A, k) @ B for k in range(4 * N)], -1)
    assert torch.linalg.matrix_rank(ctrb) == 4 * N
    # single pendulum check by hand: thdd = (Mc+Mp) Mp l g th / D0 with D0 = Mp l^2 (Mc + Mp/2)
    p = PAPER_TABLE1_PARAMS
    Ac, _ = f.jacobians(x0, u0)
    D0 = p["Mp"] * p["l"] ** 2 * (p["Mc"] + 0.5 * p["Mp"])
    assert Ac[1, 0].item() == pytest.approx((p["Mc"] + p["Mp"]) * p["Mp"] * p["l"] * p["g"] / D0)


# ---------------------------------------------------------------------- DARE
def test_dare_matches_scipy_and_solves_the_equation():
    g = torch.Generator().manual_seed(6)
    Bsz, n, m = 5, 6, 2
    A = torch.randn(Bsz, n, n, dtype=DT, generator=g) * 0.6  # several are open-loop unstable
    Bm = torch.randn(Bsz, n, m, dtype=DT, generator=g)
    L = torch.randn(Bsz, n, n, dtype=DT, generator=g)
    Q = L @ L.mT / n + 0.1 * torch.eye(n, dtype=DT)
    R = torch.diag_embed(torch.rand(Bsz, m, dtype=DT, generator=g) + 0.1)
    assert (torch.linalg.eigvals(A).abs().amax(-1) > 1).any()
    X = dare(A, Bm, Q, R)
    for b in range(Bsz):
        Xs = scipy.linalg.solve_discrete_are(
            A[b].numpy(), Bm[b].numpy(), Q[b].numpy(), R[b].numpy()
        )
        err = np.abs(X[b].numpy() - Xs).max() / np.abs(Xs).max()
        assert err < 1e-9
    res = dare_residual(A, Bm, Q, R, X)
    assert (res.abs().amax((-2, -1)) / X.abs().amax((-2, -1))).max() < 1e-10
    # stabilising: the closed loop A - B K is Schur
    K = dare_gain(A, Bm, X, R)
    assert torch.linalg.eigvals(A - Bm @ K).abs().max() < 1


def test_dare_broadcasts_shared_weights():
    g = torch.Generator().manual_seed(7)
    A = torch.randn(3, 4, 4, dtype=DT, generator=g) * 0.5
    Bm = torch.randn(3, 4, 1, dtype=DT, generator=g)
    Q, R = torch.eye(4, dtype=DT), torch.eye(1, dtype=DT)
    X = dare(A, Bm, Q, R)
    for b in range(3):
        torch.testing.assert_close(X[b], dare(A[b], Bm[b], Q, R), rtol=1e-12, atol=1e-12)


def test_dare_refuses_unstabilisable():
    A = torch.diag(torch.tensor([2.0, 0.5], dtype=DT))
    Bm = torch.tensor([[0.0], [1.0]], dtype=DT)  # the unstable mode is not reachable
    with pytest.raises(RuntimeError):
        dare(A, Bm, torch.eye(2, dtype=DT), torch.eye(1, dtype=DT), max_iter=60)


def test_pendulum_train_terminal_weight_matches_scipy():
    N = 3
    setup = pendulum_train_problem(N, 30.0)
    A, B = upright_linearization(setup.problem.dynamics)
    Xs = scipy.linalg.solve_discrete_are(A.numpy(), B.numpy(), setup.Q.numpy(), setup.R.numpy())
    assert np.abs(setup.Qf.numpy() - Xs).max() / np.abs(Xs).max() < 1e-9


# ---------------------------------------------------------------------- problem builder
def test_reference_curve():
    T = 10.0
    t = torch.linspace(0, T, 200001, dtype=DT)
    amp = math.radians(60.0)
    th, thd = theta_reference(t, amp, T)
    # amplitude: max |theta_ref| over [0, T] is theta_amp, reached at T/2 +- atanh(1/sqrt3)
    assert th.max().item() == pytest.approx(amp, rel=1e-9)
    assert th.min().item() == pytest.approx(-amp, rel=1e-9)
    t_max = t[th.argmax()].item()
    assert t_max == pytest.approx(T / 2 + math.atanh(1 / math.sqrt(3)), abs=1e-4)
    # the printed formula, normalised numerically on the grid
    s = t - T / 2
    raw = torch.tanh(s) * (1 - torch.tanh(s) ** 2)
    torch.testing.assert_close(th, amp * raw / raw.abs().max(), rtol=1e-9, atol=1e-12)
    # derivative by autograd
    tt = t[::1000].clone().requires_grad_(True)
    (gth,) = torch.autograd.grad(theta_reference(tt, amp, T)[0].sum(), tt)
    torch.testing.assert_close(thd[::1000], gth, rtol=1e-12, atol=1e-12)


def test_problem_builder_encodes_the_paper_setup():
    N = 2
    amps = [30.0, -60.0, 80.0]
    setup = pendulum_train_problem(N, amps)
    P = setup.problem
    assert (P.state_dim, P.control_dim, P.horizon) == (8, 2, 200)
    assert P.dynamics.dt == 0.05 and P.dynamics.method == "rk4"
    torch.testing.assert_close(
        setup.Q.diagonal(), torch.tensor([100.0, 1.0, 0.1, 0.1] * N, dtype=DT)
    )
    assert (setup.Q - torch.diag(setup.Q.diagonal())).abs().max() == 0
    torch.testing.assert_close(setup.R, 0.1 * torch.eye(N, dtype=DT))
    torch.testing.assert_close(setup.R_reg, torch.eye(N, dtype=DT))
    assert setup.x0.shape == (3, 8) and setup.x0.abs().max() == 0
    # references: theta and theta_dot of every cart; cart positions/velocities zero
    xr = setup.x_ref.reshape(3, 201, N, 4)
    assert xr[..., 2:].abs().max() == 0
    t = torch.arange(201, dtype=DT) * 0.05
    for b, a in enumerate(amps):
        th, thd = theta_reference(t, math.radians(a), 10.0)
        for i in range(N):
            torch.testing.assert_close(xr[b, :, i, 0], th)
            torch.testing.assert_close(xr[b, :, i, 1], thd)
    # the cost is the paper's J = sum_t |x - xref|_Q^2 + |u|_R^2 + |x_T - xref_T|_Qf^2
    g = torch.Generator().manual_seed(8)
    u = torch.randn(3, 200, N, dtype=DT, generator=g)
    x = P.rollout(setup.x0, u)
    J = P.cost(x, u)
    Qn, Rn, Qfn = setup.Q.numpy(), setup.R.numpy(), setup.Qf.numpy()
    for b in range(3):
        dx = (x[b] - setup.x_ref[b]).numpy()
        ub = u[b].numpy()
        Jb = sum(dx[k] @ Qn @ dx[k] + ub[k] @ Rn @ ub[k] for k in range(200))
        Jb += dx[200] @ Qfn @ dx[200]
        assert J[b].item() == pytest.approx(Jb, rel=1e-12)


def test_diagonal_tracking_cost_equals_quadratic_cost():
    """The fast cost of the builder has QuadraticCost's value and expansion, also on a
    batch of line-search trials (extra leading dim)."""
    N = 3
    setup = pendulum_train_problem(N, [30.0, 70.0])
    fast = setup.problem.cost
    assert isinstance(fast, torchslq.QuadraticCost)
    ref = torchslq.QuadraticCost(fast.Q, fast.R, fast.Qf, x_ref=fast.x_ref)
    g = torch.Generator().manual_seed(9)
    x = torch.randn(5, 2, 201, 4 * N, dtype=DT, generator=g)
    u = torch.randn(5, 2, 200, N, dtype=DT, generator=g)
    torch.testing.assert_close(fast(x, u), ref(x, u), rtol=1e-13, atol=0)
    e1, e2 = fast.quadratize(x[0], u[0]), ref.quadratize(x[0], u[0])
    for a, b in ((e1.lxx, e2.lxx), (e1.luu, e2.luu), (e1.lx, e2.lx), (e1.lu, e2.lu)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # bits of one element do not depend on the batch it is evaluated in
    assert torch.equal(fast(x[:1, :1], u[:1, :1])[0, 0], fast(x, u)[0, 0])
