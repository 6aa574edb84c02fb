"""linearize (vjp / jacrev / jacfwd), create_graph, shapes, and discretize."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

import torchslq
from torchslq import Dynamics, LearnedDynamics, discretize, linearize
from torchslq.systems import Pendulum

# forward-mode AD (jacfwd) makes torch load jit-scripted decompositions once
pytestmark = pytest.mark.filterwarnings(
    "ignore:`torch.jit.script` is deprecated:DeprecationWarning"
)

DT = torch.float64
METHODS = ("vjp", "jacrev", "jacfwd", "auto")


class Toy(Dynamics):
    """A nonlinear discrete model without analytic Jacobians (n = 3, m = 2)."""

    state_dim = 3
    control_dim = 2

    def forward(self, x, u):
        x0, x1, x2 = x.unbind(-1)
        u0, u1 = u.unbind(-1)
        return torch.stack(
            [
                x0 + 0.1 * torch.sin(x1) * u0,
                x1 * x2 + torch.tanh(u1),
                torch.exp(0.1 * x0) - u0 * u1 * x2 + x1**3,
            ],
            -1,
        )


class PendulumAutodiff(Pendulum):
    """The pendulum with its analytic Jacobians switched off."""

    has_analytic_jacobians = False


def mlp(n: int, m: int, seed: int = 0) -> nn.Sequential:
    torch.manual_seed(seed)
    return nn.Sequential(
        nn.Linear(n + m, 16), nn.Tanh(), nn.Linear(16, 16), nn.Tanh(), nn.Linear(16, n)
    ).to(DT)


def fd_jacobians(f, x, u, eps=1e-6):
    """Central finite differences; every row is perturbed at once (rows independent)."""
    cols_x, cols_u = [], []
    for z, cols, other_first in ((x, cols_x, True), (u, cols_u, False)):
        for i in range(z.shape[-1]):
            e = torch.zeros_like(z)
            e[..., i] = eps
            if other_first:
                d = (f(x + e, u) - f(x - e, u)) / (2 * eps)
            else:
                d = (f(x, u + e) - f(x, u - e)) / (2 * eps)
            cols.append(d)
    return torch.stack(cols_x, -1), torch.stack(cols_u, -1)


def inputs(n, m, lead=(3, 4), seed=0):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(*lead, n, dtype=DT, generator=g),
        torch.randn(*lead, m, dtype=DT, generator=g),
    )


def models():
    net = mlp(3, 2)
    return {
        "toy": (Toy(), lambda x, u: Toy()(x, u), 3, 2),
        "pendulum_rk4": (
            discretize(PendulumAutodiff(), 0.1, "rk4"),
            discretize(PendulumAutodiff(), 0.1, "rk4"),
            2,
            1,
        ),
        "sequential": (net, lambda x, u: net(torch.cat([x, u], -1)), 3, 3),
        "learned": (LearnedDynamics(mlp(3, 2, seed=1), 3, 2), None, 3, 2),
    }


@pytest.mark.parametrize("name", ["toy", "pendulum_rk4", "sequential", "learned"])
def test_methods_agree_with_each_other_and_finite_differences(name):
    model, f, n, m = models()[name]
    if name == "sequential":
        m = 2  # the network takes cat([x, u]) with 3 + 2 inputs
    f = f if f is not None else model
    assert not getattr(model, "has_analytic_jacobians", False)
    x, u = inputs(n, m)
    A_fd, B_fd = fd_jacobians(f, x, u)
    results = {meth: linearize(model, x, u, method=meth) for meth in METHODS}
    A0, B0 = results["vjp"]
    assert A0.shape == (3, 4, n, n) and B0.shape == (3, 4, n, m)
    for meth, (A, B) in results.items():
        assert not A.requires_grad and not B.requires_grad
        torch.testing.assert_close(A, A0, atol=1e-12, rtol=1e-12, msg=f"{meth} vs vjp")
        torch.testing.assert_close(B, B0, atol=1e-12, rtol=1e-12, msg=f"{meth} vs vjp")
        torch.testing.assert_close(A, A_fd, atol=1e-8, rtol=1e-7, msg=f"{meth} vs FD")
        torch.testing.assert_close(B, B_fd, atol=1e-8, rtol=1e-7, msg=f"{meth} vs FD")


class StateOnly(Dynamics):
    """Ignores its control: the pullback gives no gradient for ``u``."""

    state_dim, control_dim = 3, 2

    def forward(self, x, u):
        return torch.tanh(x) * x.sum(-1, keepdim=True)


@pytest.mark.parametrize("name", ["toy", "learned", "state_only"])
def test_large_batches_pull_back_one_output_at_a_time(name):
    """In a large batch the output basis is pulled back one vector at a time: the same
    Jacobians as per-row jacrev (vmap over rows) and finite differences."""
    from torchslq.dynamics.linearize import POOL_ELEMENTS, _one_at_a_time

    model = {"toy": Toy(), "learned": LearnedDynamics(mlp(3, 2, seed=2), 3, 2)}.get(
        name, StateOnly()
    )
    half = POOL_ELEMENTS // 6 + 3  # rows x width 3 (the state; the MLP's is 16) past it
    assert _one_at_a_time(2 * half, 3)
    x, u = inputs(3, 2, lead=(2, half), seed=4)
    A, B = linearize(model, x, u)
    Ar, Br = linearize(model, x, u, method="jacrev")
    torch.testing.assert_close(A, Ar, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(B, Br, atol=1e-12, rtol=1e-12)
    A_fd, B_fd = fd_jacobians(model, x, u)
    torch.testing.assert_close(A, A_fd, atol=1e-8, rtol=1e-7)
    torch.testing.assert_close(B, B_fd, atol=1e-8, rtol=1e-7)
    if name == "state_only":
        assert B.abs().max() == 0


def test_plain_callable_and_float32():
    x, u = inputs(3, 2)
    A, B = linearize(lambda xx, uu: Toy()(xx, uu), x, u)
    A_ref, B_ref = linearize(Toy(), x, u)
    torch.testing.assert_close(A, A_ref)
    torch.testing.assert_close(B, B_ref)
    A32, B32 = linearize(Toy(), x.float(), u.float(), method="jacfwd")
    assert A32.dtype == torch.float32
    torch.testing.assert_close(A32, A.float(), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("lead", [(), (5,), (2, 3), (2, 3, 2)])
@pytest.mark.parametrize("method", ["vjp", "jacrev", "jacfwd"])
def test_leading_shapes(lead, method):
    x, u = inputs(3, 2, lead=lead)
    A, B = linearize(Toy(), x, u, method=method)
    assert A.shape == (*lead, 3, 3) and B.shape == (*lead, 3, 2)
    if lead:  # each row is its own Jacobian
        A1, B1 = linearize(Toy(), x.reshape(-1, 3)[-1], u.reshape(-1, 2)[-1], method=method)
        torch.testing.assert_close(A.reshape(-1, 3, 3)[-1], A1)
        torch.testing.assert_close(B.reshape(-1, 3, 2)[-1], B1)


def test_linearize_validation():
    x, u = inputs(3, 2)
    with pytest.raises(ValueError, match="method"):
        linearize(Toy(), x, u, method="fd")
    with pytest.raises(ValueError, match="leading dims"):
        linearize(Toy(), x, u[:, :2])


@pytest.mark.parametrize("method", ["vjp", "jacrev", "jacfwd"])
@pytest.mark.parametrize("kind", ["sequential", "learned"])
def test_create_graph_parameter_gradient_matches_fd(method, kind):
    net = mlp(3, 2, seed=2)
    model = net if kind == "sequential" else LearnedDynamics(net, 3, 2)
    x, u = inputs(3, 2, lead=(2, 3), seed=5)
    W = net[0].weight

    def loss(create_graph):
        A, B = linearize(model, x, u, create_graph=create_graph, method=method)
        return A.sum() + (B**2).sum()

    L = loss(True)
    assert L.requires_grad
    (gW,) = torch.autograd.grad(L, W)
    eps = 1e-6
    for i, j in ((0, 0), (3, 4), (15, 2)):
        with torch.no_grad():
            W[i, j] += eps
            Lp = loss(False)
            W[i, j] -= 2 * eps
            Lm = loss(False)
            W[i, j] += eps
        fd = (Lp - Lm) / (2 * eps)
        assert abs(gW[i, j] - fd) <= 1e-7 * (1 + abs(fd)), (i, j, gW[i, j].item(), fd.item())


def test_create_graph_state_gradient_matches_fd():
    x, u = inputs(3, 2, lead=(4,), seed=3)
    xr = x.clone().requires_grad_(True)
    A, _ = linearize(Toy(), xr, u, create_graph=True)
    (gx,) = torch.autograd.grad(A.sum(), xr)
    eps = 1e-6
    for i in range(3):
        e = torch.zeros_like(x)
        e[..., i] = eps
        Ap, _ = linearize(Toy(), x + e, u)
        Am, _ = linearize(Toy(), x - e, u)
        fd = (Ap - Am).sum((-1, -2)) / (2 * eps)
        torch.testing.assert_close(gx[..., i], fd, atol=1e-7, rtol=1e-7)


def test_create_graph_through_analytic_jacobians():
    mass = nn.Parameter(torch.tensor(1.3, dtype=DT))
    model = discretize(Pendulum(mass=mass), 0.1, "rk4")
    assert model.has_analytic_jacobians
    x, u = inputs(2, 1, seed=4)
    A, B = linearize(model, x, u, create_graph=True)
    (g,) = torch.autograd.grad(A.sum() + B.sum(), mass)
    A0, B0 = linearize(model, x, u)
    assert not A0.requires_grad
    eps = 1e-6
    vals = []
    for s in (1, -1):
        Ap, Bp = linearize(discretize(Pendulum(mass=1.3 + s * eps), 0.1, "rk4"), x, u)
        vals.append(Ap.sum() + Bp.sum())
    fd = (vals[0] - vals[1]) / (2 * eps)
    assert abs(g - fd) < 1e-7 * (1 + abs(fd))


# ---------------------------------------------------------------- discretize


def test_discretize_validation():
    p = Pendulum()
    with pytest.raises(ValueError, match="method"):
        discretize(p, 0.1, "rk45")
    for dt in (0.0, -0.1):
        with pytest.raises(ValueError, match="dt"):
            discretize(p, dt)
    with pytest.raises(TypeError, match="ContinuousDynamics"):
        discretize(Toy(), 0.1)
    d = discretize(p, 0.1, "euler")
    assert isinstance(d, torchslq.Dynamics) and (d.state_dim, d.control_dim) == (2, 1)


def _final_state(model, x0, u, t_end, steps, method):
    step = discretize(model, t_end / steps, method)
    x = x0
    for _ in range(steps):
        x = step(x, u)
    return x


@pytest.mark.parametrize("method,order", [("rk4", 4), ("euler", 1)])
def test_convergence_order_on_pendulum(method, order):
    model = Pendulum(damping=0.3)
    x0 = torch.tensor([[2.0, 0.0], [-1.0, 3.0]], dtype=DT)
    u = torch.tensor([[0.5], [-1.0]], dtype=DT)
    t_end = 1.0
    ref = _final_state(model, x0, u, t_end, 640, "rk4")
    steps = (20, 40, 80) if method == "rk4" else (100, 200, 400)
    errs = [(_final_state(model, x0, u, t_end, s, method) - ref).norm() for s in steps]
    # halving dt divides the error by 2^order (16 for rk4, 2 for euler)
    for e1, e2 in zip(errs, errs[1:], strict=False):
        ratio = (e1 / e2).item()
        assert abs(math.log2(ratio) - order) < 0.1, (method, [e.item() for e in errs])
