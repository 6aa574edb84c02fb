"""The general :class:`torchslq.Cost` and :func:`torchslq.costs.general.project_psd`,
against independent computations (float64):

* ``quadratize`` (``l_x, l_u, l_xx, l_uu, l_ux`` and the terminal terms) equals central
  finite differences of the cost *and* ``torch.autograd.functional.hessian`` of one row
  at a time, for a non-quadratic stage cost with cross terms that uses the step index
  ``t`` and a per-element parameter of shape ``(B, 1)``;
* the value equals an explicit loop over elements and steps written with ``math``;
* a subclass overriding ``stage``/``terminal`` is the same cost; an ``nn.Module`` stage
  registers its parameters (and they get gradients); bad input is a clear error;
* rows are independent: a batch (and extra leading dims) gives the values of its rows;
* ``project_psd``: symmetric, eigenvalues clipped to the floor, identity above it.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from torchslq import Cost, CostExpansion, Problem, discretize
from torchslq.costs.general import project_psd
from torchslq.systems import CartPole, Pendulum

# forward-mode AD (jvp) makes torch load jit-scripted decompositions once
pytestmark = pytest.mark.filterwarnings(
    "ignore:`torch.jit.script` is deprecated:DeprecationWarning"
)

torch.set_num_threads(1)

F64 = torch.float64
B, T, N, M = 3, 4, 3, 2
P = torch.tensor([[0.7], [-1.3], [2.0]], dtype=F64)  # per-element parameter (B, 1)


# ----------------------------------------------------------------------------- the cost


def stage_fn(x, u, t, p=P):
    """A non-quadratic, non-convex stage cost with x-x, u-u and u-x cross terms; ``t``
    weights the steps and ``p (B, 1)`` is a per-element parameter."""
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    u0, u1 = u[..., 0], u[..., 1]
    w = 1.0 + 0.5 * t.to(x.dtype)  # (T,)
    core = (
        1.0
        + torch.cos(x0)
        + 10.0 * x1**2 * x0
        + 3e-2 * u0**2 * torch.exp(x1)
        + u0 * x0
        + 0.5 * u1**2
        + 0.3 * u0 * u1 * x2
    )
    return w * core + p * torch.sin(x2) * u1**3 + 0.1 * (p * x2) ** 2


def terminal_fn(x, p=P):
    """Terminal cost: non-quadratic, with a per-element parameter (``x (..., B, n)``)."""
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    return p[:, 0] * torch.sin(x0) * x1**2 + torch.exp(0.3 * x2) + 2.0 * x0 * x2


def stage_scalar(x, u, t, p):
    """Row ``(b, t)`` of :func:`stage_fn` with python floats and ``math`` only."""
    x0, x1, x2 = x
    u0, u1 = u
    w = 1.0 + 0.5 * t
    core = (
        1.0
        + math.cos(x0)
        + 10.0 * x1**2 * x0
        + 3e-2 * u0**2 * math.exp(x1)
        + u0 * x0
        + 0.5 * u1**2
        + 0.3 * u0 * u1 * x2
    )
    return w * core + p * math.sin(x2) * u1**3 + 0.1 * (p * x2) ** 2


def terminal_scalar(x, p):
    x0, x1, x2 = x
    return p * math.sin(x0) * x1**2 + math.exp(0.3 * x2) + 2.0 * x0 * x2


def make_cost() -> Cost:
    return Cost(stage_fn, terminal_fn, state_dim=N, control_dim=M)


class SubclassCost(Cost):
    """The same cost by overriding the hooks."""

    def __init__(self):
        super().__init__(state_dim=N, control_dim=M)

    def stage(self, x, u, t):
        return stage_fn(x, u, t)

    def terminal(self, x):
        return terminal_fn(x)


def traj(seed=0, scale=0.7):
    g = torch.Generator().manual_seed(seed)
    x = scale * torch.randn(B, T + 1, N, generator=g, dtype=F64)
    u = scale * torch.randn(B, T, M, generator=g, dtype=F64)
    return x, u


@pytest.fixture(scope="module")
def expansion():
    x, u = traj()
    return x, u, make_cost().quadratize(x, u)


# ----------------------------------------------------------------------------- row helpers


def row_stage(x, u, b, t):
    """``z (n+m,) -> l(x[b,t], u[b,t], t)`` through the library's batched call (the
    row is replaced in a copy of the full grid, so the (B,1) parameter broadcasts)."""

    def f(z):
        xs = x[:, :T].clone()
        us = u.clone()
        xs[b, t] = z[:N]
        us[b, t] = z[N:]
        return stage_fn(xs, us, torch.arange(T))[b, t]

    return f, torch.cat([x[b, t], u[b, t]])


def row_terminal(x, b):
    def f(z):
        xT = x[:, T].clone()
        xT[b] = z
        return terminal_fn(xT)[b]

    return f, x[b, T].clone()


def fd_grad(f, z, h=1e-6):
    g = torch.empty_like(z)
    for i in range(z.numel()):
        e = torch.zeros_like(z)
        e[i] = h
        g[i] = (f(z + e) - f(z - e)) / (2 * h)
    return g


def fd_hess(f, z, h=1e-4):
    """Central second differences of function values."""
    k = z.numel()
    H = torch.empty(k, k, dtype=z.dtype)
    for i in range(k):
        for j in range(k):
            ei = torch.zeros_like(z)
            ej = torch.zeros_like(z)
            ei[i] = h
            ej[j] = h
            H[i, j] = (f(z + ei + ej) - f(z + ei - ej) - f(z - ei + ej) + f(z - ei - ej)) / (
                4 * h * h
            )
    return H


# ----------------------------------------------------------------------------- value


def test_value_equals_explicit_loop():
    x, u = traj(1)
    J = make_cost()(x, u)
    assert J.shape == (B,)
    for b in range(B):
        p = float(P[b, 0])
        ref = sum(stage_scalar(x[b, t].tolist(), u[b, t].tolist(), t, p) for t in range(T))
        ref += terminal_scalar(x[b, T].tolist(), p)
        assert abs(float(J[b]) - ref) <= 1e-12 * max(1.0, abs(ref)), (b, float(J[b]), ref)


def test_value_uses_step_index_and_parameter():
    """Guards against a cost test that cannot fail: t and p really matter."""
    x, u = traj(1)
    J = make_cost()(x, u)
    J_no_t = Cost(
        lambda a, b_, t: stage_fn(a, b_, torch.zeros_like(t)),
        terminal_fn,
        state_dim=N,
        control_dim=M,
    )(x, u)
    assert bool(((J - J_no_t).abs() > 1e-3).all())
    J_p = Cost(
        lambda a, b_, t: stage_fn(a, b_, t, p=P.flip(0)), terminal_fn, state_dim=N, control_dim=M
    )(x, u)
    assert bool(((J - J_p)[[0, 2]].abs() > 1e-6).all())


def test_value_extra_leading_dims_and_batch_invariance():
    """The line search evaluates ``(Na, B, T+1, n)``; each slice and each row must give
    exactly what it gives alone (elements are independent)."""
    cost = make_cost()
    xs, us = zip(*(traj(s) for s in range(5)), strict=True)
    x, u = torch.stack(xs), torch.stack(us)  # (5, B, ...)
    J = cost(x, u)
    assert J.shape == (5, B)
    for a in range(5):
        assert torch.equal(J[a], cost(x[a], u[a]))
    # one row alone (its own parameter) equals its row in the batch, bit for bit
    for b in range(B):
        pb = P[b : b + 1]
        single = Cost(
            lambda a_, u_, t, pb=pb: stage_fn(a_, u_, t, p=pb),
            lambda a_, pb=pb: terminal_fn(a_, p=pb),
            state_dim=N,
            control_dim=M,
        )
        assert torch.equal(single(x[0, b : b + 1], u[0, b : b + 1])[0], J[0, b])


def test_value_batch_invariant_long_horizon():
    """Long horizons and odd batch sizes (where a reduction's blocking could depend on
    the batch): row ``b`` of a batch is still bit-identical to the row alone."""

    def stage(x, u, t):
        return 1 + torch.cos(x[..., 1]) + 10 * x[..., 0] ** 2 + 3e-2 * u[..., 0] ** 2

    cost = Cost(stage, lambda x: (x * x).sum(-1), state_dim=4, control_dim=1)
    g = torch.Generator().manual_seed(2)
    for T_, Bsz in ((500, 7), (1000, 16)):
        x = torch.randn(3, Bsz, T_ + 1, 4, generator=g, dtype=F64)
        u = torch.randn(3, Bsz, T_, 1, generator=g, dtype=F64)
        J = cost(x, u)
        for b in range(Bsz):
            assert torch.equal(J[1, b], cost(x[1, b : b + 1], u[1, b : b + 1])[0]), (T_, b)


# ----------------------------------------------------------------------------- derivatives


def test_quadratize_shapes_and_type(expansion):
    _, _, e = expansion
    assert isinstance(e, CostExpansion)
    assert e.lxx.shape == (B, T + 1, N, N)
    assert e.luu.shape == (B, T, M, M)
    assert e.lux.shape == (B, T, M, N)
    assert e.lx.shape == (B, T + 1, N)
    assert e.lu.shape == (B, T, M)
    for t_ in (e.lxx, e.luu, e.lux, e.lx, e.lu):
        assert t_.dtype == F64 and not t_.requires_grad
        assert bool(torch.isfinite(t_).all())


@pytest.mark.parametrize("b", range(B))
def test_quadratize_stage_matches_fd_and_autograd_hessian(expansion, b):
    x, u, e = expansion
    for t in range(T):
        f, z = row_stage(x, u, b, t)
        g_ref = fd_grad(f, z)
        H_ad = torch.autograd.functional.hessian(f, z)
        H_fd = fd_hess(f, z)
        g = torch.cat([e.lx[b, t], e.lu[b, t]])
        # the library's blocks assembled into the joint (n+m) Hessian
        H = torch.cat(
            [
                torch.cat([e.lxx[b, t], e.lux[b, t].mT], -1),
                torch.cat([e.lux[b, t], e.luu[b, t]], -1),
            ],
            -2,
        )
        scale = float(H_ad.abs().max())
        torch.testing.assert_close(g, g_ref, rtol=1e-7, atol=1e-7 * float(g_ref.abs().max()))
        torch.testing.assert_close(H, H_ad, rtol=1e-12, atol=1e-12 * scale)
        torch.testing.assert_close(H, H_fd, rtol=0, atol=1e-7 * scale)
        # and the blocks individually (lux is d2l / du dx: rows u, columns x)
        torch.testing.assert_close(e.luu[b, t], H_ad[N:, N:], rtol=1e-12, atol=1e-12 * scale)
        torch.testing.assert_close(e.lux[b, t], H_ad[N:, :N], rtol=1e-12, atol=1e-12 * scale)
        torch.testing.assert_close(e.lxx[b, t], H_ad[:N, :N], rtol=1e-12, atol=1e-12 * scale)


@pytest.mark.parametrize("b", range(B))
def test_quadratize_terminal_matches_fd_and_autograd_hessian(expansion, b):
    x, _, e = expansion
    f, z = row_terminal(x, b)
    H_ad = torch.autograd.functional.hessian(f, z)
    scale = float(H_ad.abs().max())
    torch.testing.assert_close(e.lx[b, T], fd_grad(f, z), rtol=1e-7, atol=1e-8)
    torch.testing.assert_close(e.lxx[b, T], H_ad, rtol=1e-12, atol=1e-12 * scale)
    torch.testing.assert_close(e.lxx[b, T], fd_hess(f, z), rtol=0, atol=1e-7 * scale)


def test_quadratize_gradient_is_gradient_of_total_cost(expansion):
    """``l_x, l_u`` are the gradient of ``J(x, u)`` with respect to the whole grid."""
    x, u, e = expansion
    xr, ur = x.clone().requires_grad_(True), u.clone().requires_grad_(True)
    gx, gu = torch.autograd.grad(make_cost()(xr, ur).sum(), (xr, ur))
    torch.testing.assert_close(e.lx, gx, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(e.lu, gu, rtol=1e-13, atol=1e-13)


def test_quadratize_step_index_matters():
    """The Hessian rows see their own t: the t-weighted block scales with (1 + t/2)."""
    x, u = traj(3)
    x = x.clone()
    u = u.clone()
    x[:, :T] = x[:1, :1]  # every row the same point (element 0, step 0) ...
    u[:] = u[:1, :1]
    cost = Cost(
        lambda a, b_, t: stage_fn(a, b_, t, p=torch.zeros(B, 1, dtype=F64)),
        state_dim=N,
        control_dim=M,
    )
    e = cost.quadratize(x, u)
    for t in range(T):  # ... so with p = 0 row t is (1 + t/2) times row 0
        torch.testing.assert_close(e.luu[:, t], (1 + 0.5 * t) * e.luu[:, 0], rtol=1e-13, atol=0)
        torch.testing.assert_close(e.lxx[:, t], (1 + 0.5 * t) * e.lxx[:, 0], rtol=1e-13, atol=0)
        torch.testing.assert_close(e.lu[:, t], (1 + 0.5 * t) * e.lu[:, 0], rtol=1e-13, atol=0)
    # no terminal: zero terminal expansion
    assert bool((e.lxx[:, T] == 0).all()) and bool((e.lx[:, T] == 0).all())


def test_quadratize_batch_invariant():
    """Each row's expansion is what the row gives alone, bit for bit."""
    x, u = traj(4)
    e = make_cost().quadratize(x, u)
    for b in range(B):
        pb = P[b : b + 1]
        single = Cost(
            lambda a_, u_, t, pb=pb: stage_fn(a_, u_, t, p=pb),
            lambda a_, pb=pb: terminal_fn(a_, p=pb),
            state_dim=N,
            control_dim=M,
        )
        e1 = single.quadratize(x[b : b + 1], u[b : b + 1])
        for name in ("lxx", "luu", "lux", "lx", "lu"):
            assert torch.equal(getattr(e, name)[b], getattr(e1, name)[0]), name


def test_subclass_equals_callables(expansion):
    x, u, e = expansion
    sub = SubclassCost()
    assert torch.equal(sub(x, u), make_cost()(x, u))
    e2 = sub.quadratize(x, u)
    for name in ("lxx", "luu", "lux", "lx", "lu"):
        assert torch.equal(getattr(e2, name), getattr(e, name)), name


def test_quadratic_cost_expansion_is_exact():
    """A quadratic stage cost ``1/2 z'Wz + w'z`` (W non-symmetric, time-varying) has the
    constant Hessian ``sym(W_t)`` and gradient ``sym(W_t) z + w_t`` everywhere."""
    g = torch.Generator().manual_seed(5)
    W = torch.randn(T, N + M, N + M, generator=g, dtype=F64)
    w = torch.randn(T, N + M, generator=g, dtype=F64)
    Wf = torch.randn(N, N, generator=g, dtype=F64)

    def stage(x, u, t):
        z = torch.cat([x, u], -1)
        return 0.5 * torch.einsum("...ti,tij,...tj->...t", z, W[t], z) + (w[t] * z).sum(-1)

    def terminal(x):
        return 0.5 * torch.einsum("...i,ij,...j->...", x, Wf, x)

    x, u = traj(6, scale=3.0)
    e = Cost(stage, terminal, state_dim=N, control_dim=M).quadratize(x, u)
    Ws = 0.5 * (W + W.mT)
    z = torch.cat([x[:, :T], u], -1)
    gz = (Ws @ z.unsqueeze(-1))[..., 0] + w
    torch.testing.assert_close(
        e.lxx[:, :T], Ws[:, :N, :N].expand(B, T, N, N), rtol=1e-13, atol=1e-13
    )
    torch.testing.assert_close(e.luu, Ws[:, N:, N:].expand(B, T, M, M), rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(e.lux, Ws[:, N:, :N].expand(B, T, M, N), rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(e.lx[:, :T], gz[..., :N], rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(e.lu, gz[..., N:], rtol=1e-13, atol=1e-12)
    Wfs = 0.5 * (Wf + Wf.T)
    torch.testing.assert_close(e.lxx[:, T], Wfs.expand(B, N, N), rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(e.lx[:, T], x[:, T] @ Wfs, rtol=1e-13, atol=1e-12)


# ----------------------------------------------------------------------------- nn.Module stage


class QuadNet(nn.Module):
    """``l = 1/2 z'(G'G)z + a'tanh(z)`` with learnable ``G``, ``a``."""

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(7)
        self.G = nn.Parameter(torch.randn(N + M, N + M, generator=g, dtype=F64))
        self.a = nn.Parameter(torch.randn(N + M, generator=g, dtype=F64))

    def forward(self, x, u, t):
        z = torch.cat([x, u], -1)
        Gz = z @ self.G.T
        return 0.5 * (Gz * Gz).sum(-1) + (torch.tanh(z) * self.a).sum(-1)


def test_module_stage_registers_parameters_and_gets_gradients():
    net = QuadNet()
    cost = Cost(net, state_dim=N, control_dim=M)
    params = dict(cost.named_parameters())
    assert len(params) == 2
    assert {id(p) for p in params.values()} == {id(net.G), id(net.a)}
    assert cost.to(torch.float32)._stage_fn is net and net.G.dtype == torch.float32
    cost.to(F64)

    x, u = traj(8)
    J = cost(x, u).sum()
    J.backward()
    # dJ/da = sum of tanh(z) over rows; dJ/dG = sum of G z z'
    z = torch.cat([x[:, :T], u], -1).reshape(-1, N + M)
    torch.testing.assert_close(net.a.grad, torch.tanh(z).sum(0), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(net.G.grad, net.G.detach() @ (z.T @ z), rtol=1e-12, atol=1e-10)

    # quadratize: Hessian G'G + diag(a * tanh''(z)), detached from the parameters
    e = cost.quadratize(x, u)
    zz = torch.cat([x[:, :T], u], -1)
    th = torch.tanh(zz)
    d2 = -2.0 * th * (1 - th * th)
    H = (net.G.T @ net.G).detach() + torch.diag_embed(d2 * net.a.detach())
    torch.testing.assert_close(e.lxx[:, :T], H[..., :N, :N], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(e.luu, H[..., N:, N:], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(e.lux, H[..., N:, :N], rtol=1e-12, atol=1e-12)
    assert not e.luu.requires_grad


# ----------------------------------------------------------------------------- validation


def test_validation_errors():
    with pytest.raises(TypeError, match="stage"):
        Cost(3.0, state_dim=N, control_dim=M)
    with pytest.raises(TypeError, match="terminal"):
        Cost(stage_fn, "phi", state_dim=N, control_dim=M)
    for n, m in ((0, M), (N, 0), (-1, M), (2.0, M), (N, None)):
        with pytest.raises(ValueError, match="state_dim and control_dim"):
            Cost(stage_fn, state_dim=n, control_dim=m)
    with pytest.raises(TypeError):
        Cost(stage_fn)  # dims are required
    cost = make_cost()
    x, u = traj()
    bad = [
        (x[..., :2], u, "state/control dims"),  # wrong n
        (x, u[..., :1], "state/control dims"),  # wrong m
        (x[:, :T], u, "x must be"),  # T+1 vs T mismatch
        (x[0], u[0], "x must be"),  # no batch dim
    ]
    for xb, ub, msg in bad:
        with pytest.raises(ValueError, match=msg):
            cost(xb, ub)
        with pytest.raises(ValueError, match=msg):
            cost.quadratize(xb, ub)


def test_problem_checks_cost_dims():
    dyn = discretize(Pendulum(), 0.05)
    with pytest.raises(ValueError, match="dims"):
        Problem(dyn, Cost(stage_fn, state_dim=N, control_dim=M), 10)
    ok = Problem(discretize(CartPole(), 0.05), Cost(state_dim=4, control_dim=1), 10)
    assert ok.cost.state_dim == 4


# ----------------------------------------------------------------------------- project_psd


def _sym(g, *lead, k=5, scale=1.0):
    A = scale * torch.randn(*lead, k, k, generator=g, dtype=F64)
    return 0.5 * (A + A.mT)


@pytest.mark.parametrize("floor", [0.0, 1e-8, 0.3])
def test_project_psd_clips_eigenvalues(floor):
    g = torch.Generator().manual_seed(9)
    H = _sym(g, 4, 3, k=5, scale=2.0)
    w, V = torch.linalg.eigh(H)
    assert bool((w < floor).any()) and bool((w > floor).any())  # both cases present
    P_ = project_psd(H, floor)
    assert P_.shape == H.shape
    torch.testing.assert_close(P_, P_.mT, rtol=0, atol=1e-12)
    wp = torch.linalg.eigvalsh(P_)
    assert bool((wp >= floor - 1e-12).all())
    # independent reconstruction: same eigenvectors, eigenvalues max(w, floor)
    ref = V @ torch.diag_embed(torch.clamp(w, min=floor)) @ V.mT
    torch.testing.assert_close(P_, ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(
        wp, torch.sort(torch.clamp(w, min=floor), -1).values, rtol=0, atol=1e-12
    )


def test_project_psd_identity_above_floor_and_symmetric_part():
    g = torch.Generator().manual_seed(10)
    L = torch.randn(6, 4, 4, generator=g, dtype=F64)
    H = L @ L.mT + 0.5 * torch.eye(4, dtype=F64)  # eigenvalues >= 0.5
    torch.testing.assert_close(project_psd(H, 0.1), H, rtol=0, atol=1e-12)
    # a non-symmetric input is treated through its symmetric part
    Ks = torch.randn(6, 4, 4, generator=g, dtype=F64)
    K = Ks - Ks.mT  # skew
    torch.testing.assert_close(project_psd(H + K, 0.1), H, rtol=0, atol=1e-12)
    # an indefinite 2x2 with known answer: diag(-1, 2) rotated
    c, s = math.cos(0.3), math.sin(0.3)
    Rm = torch.tensor([[c, -s], [s, c]], dtype=F64)
    D = Rm @ torch.diag(torch.tensor([-1.0, 2.0], dtype=F64)) @ Rm.T
    expect = Rm @ torch.diag(torch.tensor([1e-3, 2.0], dtype=F64)) @ Rm.T
    torch.testing.assert_close(project_psd(D, 1e-3), expect, rtol=0, atol=1e-14)
