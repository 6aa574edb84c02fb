"""Analytic second derivatives (``vhp``) of the models and their chain through
:func:`torchslq.discretize`, against automatic differentiation of the same step."""

from __future__ import annotations

import pytest
import torch
from vhp_cases import VHP_LAYOUTS

import torchslq as ts
from torchslq.dynamics import ContinuousDynamics, dynamics_hessians, dynamics_vhp
from torchslq.systems import CartPole, MassChain

F64 = torch.float64


def _models():
    g = torch.Generator().manual_seed(0)
    per_elem = torch.rand(3, 1, generator=g, dtype=F64) + 0.5  # (B, 1) parameters
    return {
        "cartpole": CartPole(),
        "cartpole-per-element-mc": CartPole(mc=per_elem),
        "mass-chain": MassChain(k3=1.7, damping=0.2),
        "mass-chain-per-element-mass": MassChain(n_masses=3, mass=per_elem, k3=0.6),
    }


def _data(n, m, seed=1, B=3, T=4):
    g = torch.Generator().manual_seed(seed)
    x = 0.8 * torch.randn(B, T, n, generator=g, dtype=F64)
    u = torch.randn(B, T, m, generator=g, dtype=F64)
    s = torch.randn(B, T, n, generator=g, dtype=F64)
    return x, u, s


@pytest.mark.parametrize("name", list(_models()))
def test_continuous_vhp_matches_the_hessian_of_each_row(name):
    """The model's vhp == torch.func.hessian of s · f on single rows."""
    model = _models()[name]
    n, m = model.state_dim, model.control_dim
    x, u, s = _data(n, m)
    Hxx, Huu, Hux = model.vhp(x, u, s)
    for b, t in ((0, 0), (2, 3), (1, 2)):

        def sf(z, b=b, t=t):
            xb = x.clone()
            ub = u.clone()
            xb[b, t], ub[b, t] = z[:n], z[n:]
            return (s[b, t] * model(xb, ub)[b, t]).sum()

        H = torch.func.hessian(sf)(torch.cat([x[b, t], u[b, t]]))
        torch.testing.assert_close(Hxx[b, t], H[:n, :n], rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(Huu.expand(3, 4, m, m)[b, t], H[n:, n:], rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(Hux.expand(3, 4, m, n)[b, t], H[n:, :n], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("method", ["rk4", "euler"])
@pytest.mark.parametrize("name", list(_models()))
def test_discretized_vhp_and_hessians_match_automatic_differentiation(name, method):
    """The chained analytic second derivatives of the integration step (RK4's stage
    adjoints) == reverse-over-reverse through the same step."""
    dyn = ts.discretize(_models()[name], 0.07, method)
    assert dyn.has_analytic_vhp
    n, m = dyn.state_dim, dyn.control_dim
    x, u, s = _data(n, m, seed=2)

    def autodiff(a, b):  # a plain callable: no analytic vhp to find
        return dyn(a, b)

    for got, ref in zip(dynamics_vhp(dyn, x, u, s), dynamics_vhp(autodiff, x, u, s), strict=True):
        assert got.shape == ref.shape
        torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-12)
    hess = dynamics_hessians(dyn, x, u)
    for got, ref in zip(hess, dynamics_hessians(autodiff, x, u), strict=True):
        assert got.shape == ref.shape
        torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-12)
    assert float(hess[0].abs().max()) > 1e-3  # a curved model: the check is not 0 == 0


def test_vhp_takes_several_weight_vectors_at_once():
    dyn = ts.discretize(CartPole(), 0.05)
    x, u, _ = _data(4, 1, seed=3)
    S = torch.randn(5, 3, 4, 4, generator=torch.Generator().manual_seed(4), dtype=F64)
    Hxx, Huu, Hux = dyn.vhp(x, u, S)
    assert Hxx.shape == (5, 3, 4, 4, 4)
    for k in (0, 4):
        torch.testing.assert_close(Hxx[k], dyn.vhp(x, u, S[k])[0], rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(Hux[k], dyn.vhp(x, u, S[k])[2], rtol=1e-12, atol=1e-14)


class _VhpOnly(ContinuousDynamics):
    """A curved model with an analytic vhp but no analytic Jacobians."""

    state_dim, control_dim = 2, 1

    def forward(self, x, u, t=None):
        return torch.stack([x[..., 1], torch.sin(x[..., 0]) * u[..., 0]], -1)

    def vhp(self, x, u, s, t=None):
        sn, c, w = torch.sin(x[..., 0]), torch.cos(x[..., 0]), s[..., 1]
        z = torch.zeros_like(sn * w)
        Hxx = torch.stack([torch.stack([-sn * u[..., 0] * w, z], -1), torch.stack([z, z], -1)], -2)
        return Hxx, z[..., None, None], torch.stack([c * w, z], -1).unsqueeze(-2)


def test_rk4_needs_analytic_jacobians_too():
    """RK4's chain needs the stages' Jacobians: without them the step falls back to
    automatic differentiation (and says so when asked directly); Euler does not."""
    x, u, s = _data(2, 1, seed=5)
    rk4, euler = ts.discretize(_VhpOnly(), 0.1), ts.discretize(_VhpOnly(), 0.1, "euler")
    assert not rk4.has_analytic_vhp and euler.has_analytic_vhp
    with pytest.raises(NotImplementedError, match="analytic vhp"):
        rk4.vhp(x, u, s)
    for dyn in (rk4, euler):
        got = dynamics_vhp(dyn, x, u, s)
        ref = dynamics_vhp(lambda a, b, dyn=dyn: dyn(a, b), x, u, s)
        for a, b in zip(got, ref, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


class Autodiff(ts.Dynamics):
    """The same step and Jacobians as ``step``; second derivatives by autodiff."""

    def __init__(self, step):
        super().__init__()
        self.step, self.state_dim, self.control_dim = step, step.state_dim, step.control_dim

    def forward(self, x, u):
        return self.step(x, u)

    def jacobians(self, x, u):
        return self.step.jacobians(x, u)

    def compiled_step(self):  # the same rollouts (kernel or torch path) as ``step``
        return self.step.compiled_step()


def test_ddp_with_analytic_second_derivatives_equals_automatic_differentiation():
    """The same DDP solve (value and costate modes) whichever way f_zz is computed."""
    from torchslq.tasks import cartpole_swingup

    problem, x0 = cartpole_swingup(3, horizon=30)
    auto = ts.Problem(Autodiff(problem.dynamics), problem.cost, problem.horizon)
    assert problem.dynamics.has_analytic_vhp and not auto.dynamics.has_analytic_vhp
    for mode in ("value", "costate"):
        # the first iterations: the same iterates up to round-off
        solver = ts.DDP(second_order=mode, max_iter=8, progress=False)
        a, b = solver.solve(problem, x0), solver.solve(auto, x0)
        assert torch.equal(a.iterations, b.iterations)
        torch.testing.assert_close(a.u, b.u, rtol=1e-7, atol=1e-8)
        # (8 iterations amplify round-off: a clean-clone run saw 1.5e-9 relative)
        torch.testing.assert_close(a.history["cost"], b.history["cost"], rtol=1e-8, atol=0)
    # a whole solve: the same minimiser (round-off can move the last gradient test
    # across tol by an iteration, or make the Armijo test at the cost's rounding floor
    # halve a last step: seen once, 30 vs 28 iterations, gradients 3e-8 vs 5e-14 there)
    solver = ts.DDP(max_iter=200, tol=1e-8, progress=False)
    a, b = solver.solve(problem, x0), solver.solve(auto, x0)
    assert bool(a.converged.all()) and bool(b.converged.all())
    assert int((a.iterations - b.iterations).abs().max()) <= 2
    torch.testing.assert_close(a.u, b.u, rtol=1e-7, atol=1e-8)
    torch.testing.assert_close(a.cost, b.cost, rtol=1e-12, atol=0)


def test_unicycle_derivatives_match_automatic_differentiation():
    from torchslq.systems import Unicycle

    dyn = Unicycle(0.1)
    x, u, s = _data(3, 2, seed=6)
    A, B = dyn.jacobians(x, u)
    Ar, Br = ts.linearize(lambda a, b: dyn(a, b), x, u)
    torch.testing.assert_close(A, Ar, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(B, Br, rtol=1e-12, atol=1e-14)
    got, ref = dynamics_hessians(dyn, x, u), dynamics_hessians(lambda a, b: dyn(a, b), x, u)
    for a, b in zip(got, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    assert float(got[0].abs().max()) > 1e-3 and float(got[2].abs().max()) > 1e-3
    with pytest.raises(ValueError, match="dt"):
        Unicycle(0.0)


def _count_analytic_vhp(monkeypatch, cls) -> dict:
    """Counts the calls of ``cls.vhp`` and of the same derivatives on the CPU kernel
    (``cls.compiled_derivatives``) in ``calls["n"]``."""
    import sys

    calls = {"n": 0}
    real = cls.vhp
    disc = sys.modules["torchslq.dynamics.discretize"]
    real_kernel = disc.rk4_vhp_compiled

    def counting(self, *a, **k):
        calls["n"] += 1
        return real(self, *a, **k)

    def counting_kernel(*a):
        calls["n"] += 1
        return real_kernel(*a)

    monkeypatch.setattr(cls, "vhp", counting)
    monkeypatch.setattr(disc, "rk4_vhp_compiled", counting_kernel)
    return calls


def test_mpc_exact_implicit_gradients_with_analytic_second_derivatives(monkeypatch):
    """The MPC layer's exact backward (Hessian of the Lagrangian) through CartPole.vhp
    (or its compiled form): the same gradients w.r.t. a learnable model parameter and x0 as with autodiff f_zz,
    and the analytic path is really taken."""
    from torch import nn

    calls = _count_analytic_vhp(monkeypatch, CartPole)
    Q = torch.diag(torch.tensor([1.0, 10.0, 0.1, 0.1], dtype=F64))
    x_ref = torch.tensor([0.0, 3.0, 0.0, 0.0], dtype=F64)
    g = torch.Generator().manual_seed(7)
    wx, wu = (
        torch.randn(2, 21, 4, generator=g, dtype=F64),
        torch.randn(2, 20, 1, generator=g, dtype=F64),
    )
    grads = []
    for analytic in (True, False):
        mc = nn.Parameter(torch.tensor(1.2, dtype=F64))
        step = ts.discretize(CartPole(mc=mc), 0.05)
        dyn = step if analytic else Autodiff(step)
        cost = ts.QuadraticCost(Q, 0.1 * torch.eye(1, dtype=F64), 10 * Q, x_ref=x_ref)
        # (iLQR never uses f_zz: both runs reach the same point, only the backward differs)
        solver = ts.ILQR(max_iter=500, tol=1e-9, progress=False)
        mpc = ts.MPC(dyn, cost, 20, solver=solver, backward="implicit", warm_start=False)
        x0 = torch.tensor([[0.1, 2.5, 0.0, 0.3], [-0.2, 2.8, 0.1, 0.0]], dtype=F64)
        x0.requires_grad_(True)
        n0 = calls["n"]
        x, u = mpc(x0)
        assert bool(mpc.last_result.converged.all())
        assert (calls["n"] > n0) == analytic
        ((wx * x).sum() + (wu * u).sum()).backward()
        grads.append((mc.grad.clone(), x0.grad.clone()))
    for a, b in zip(*grads, strict=True):
        assert float(b.abs().max()) > 1e-3
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)


def test_mass_chain_mpc_exact_gradients_and_ddp_with_analytic_second_derivatives(monkeypatch):
    """The MPC benchmark's model: the exact implicit gradients w.r.t. learnable mass, k3
    and x0 through MassChain.vhp equal those with autodiff f_zz, and DDP (costate mode,
    which uses f_zz in every step) takes the same iterates."""
    from torch import nn

    calls = _count_analytic_vhp(monkeypatch, MassChain)
    N, T = 3, 12
    Q = torch.eye(2 * N, dtype=F64)
    goal = torch.tensor([0.3, 0.6, 0.9, 0, 0, 0], dtype=F64)
    g = torch.Generator().manual_seed(8)
    x0 = 0.5 * torch.randn(2, 2 * N, generator=g, dtype=F64)
    wx = torch.randn(2, T + 1, 2 * N, generator=g, dtype=F64)
    grads, sols = [], []
    for analytic in (True, False):
        mass = nn.Parameter(torch.tensor(1.1, dtype=F64))
        k3 = nn.Parameter(torch.tensor(1.5, dtype=F64))
        step = ts.discretize(MassChain(N, mass=mass, k3=k3), 0.1)
        dyn = step if analytic else Autodiff(step)
        cost = ts.QuadraticCost(Q, 0.1 * torch.eye(N, dtype=F64), 10 * Q, x_ref=goal)
        solver = ts.DDP(second_order="costate", max_iter=100, tol=1e-10, progress=False)
        mpc = ts.MPC(dyn, cost, T, solver=solver, backward="implicit", warm_start=False)
        x0v = x0.clone().requires_grad_(True)
        n0 = calls["n"]
        x, u = mpc(x0v)
        assert bool(mpc.last_result.converged.all())
        assert (calls["n"] > n0) == analytic
        sols.append((mpc.last_result.iterations.clone(), u.detach().clone()))
        (wx * x).sum().backward()
        grads.append((mass.grad.clone(), k3.grad.clone(), x0v.grad.clone()))
    assert torch.equal(sols[0][0], sols[1][0])
    torch.testing.assert_close(sols[0][1], sols[1][1], rtol=1e-9, atol=1e-11)
    for a, b in zip(*grads, strict=True):
        assert float(b.abs().max()) > 1e-3
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize(
    "shapes",
    VHP_LAYOUTS,
)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_rk4_congruence_matches_the_torch_chain(shapes, dtype, monkeypatch):
    """The chained second derivatives with each stage's congruence on the CPU kernel ==
    the same chain written with torch products (the kernel must have run)."""
    import sys

    from torchslq._backend import dispatch as compiled

    if not compiled.compiled_available():
        pytest.skip("numba kernels not available")
    disc = sys.modules["torchslq.dynamics.discretize"]
    g = torch.Generator().manual_seed(4)
    xs, us, ss = shapes
    model = CartPole(mc=torch.tensor(1.3, dtype=F64))
    model.compiled_derivatives = lambda: None  # the torch chain (the whole chain on a
    # kernel is tested in tests/test_compiled_rk4.py)
    dyn = ts.discretize(model, 0.07).to(dtype)
    x = (0.8 * torch.randn(*xs, 4, generator=g, dtype=F64)).to(dtype)
    u = torch.randn(*us, 1, generator=g, dtype=F64).to(dtype)
    s = torch.randn(*ss, 4, generator=g, dtype=F64).to(dtype)
    calls = []
    real = disc.stage_congruence_compiled
    monkeypatch.setattr(disc, "stage_congruence_compiled", lambda *a: calls.append(1) or real(*a))
    fast = dyn.vhp(x, u, s)
    assert len(calls) == 3  # the three stages whose argument depends on an earlier one
    monkeypatch.setattr(disc, "can_use_compiled", lambda *t: False)
    slow = dyn.vhp(x, u, s)
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    for a, b in zip(fast, slow, strict=True):
        b = b.expand_as(a)
        assert a.dtype == dtype
        assert (a - b).abs().max() <= tol * (1 + b.abs().max())


@pytest.mark.parametrize(
    "name",
    ["cartpole", "cartpole-per-element-mc", "mass-chain-per-element-mass", "autodiff", "euler"],
)
def test_linearize_with_vhp_equals_the_separate_calls_and_shares_the_stages(name, monkeypatch):
    """linearize_with_vhp == linearize and dynamics_vhp at the same point (bit for bit);
    for an RK4 model with analytic derivatives the stage Jacobians are computed once for
    both (4 continuous Jacobian calls instead of 8), or not at all in torch (the
    cart-pole with scalar parameters: compiled derivatives on the CPU kernels)."""
    from torchslq.dynamics import linearize_with_vhp

    model = _models()["cartpole" if name in ("autodiff", "euler") else name]
    step = ts.discretize(model, 0.07, "euler" if name == "euler" else "rk4")
    dyn = Autodiff(step) if name == "autodiff" else step
    n, m = model.state_dim, model.control_dim
    x, u, s = _data(n, m, seed=9)
    calls = {"n": 0}
    real = type(model).jacobians

    def counting(self, *a, **k):
        calls["n"] += 1
        return real(self, *a, **k)

    monkeypatch.setattr(type(model), "jacobians", counting)
    A, B, vhp = linearize_with_vhp(dyn, x, u)
    got = vhp(s)
    shared_calls = calls["n"]
    calls["n"] = 0
    A2, B2 = ts.linearize(dyn, x, u)
    ref = dynamics_vhp(dyn, x, u, s)
    assert torch.equal(A, A2) and torch.equal(B, B2)
    for a, b in zip(got, ref, strict=True):
        assert torch.equal(a, b)
    if name in ("cartpole-per-element-mc", "mass-chain-per-element-mass"):
        assert (shared_calls, calls["n"]) == (4, 8)
    if name == "cartpole":
        assert (shared_calls, calls["n"]) == (0, 0)
    assert float(got[0].abs().max()) > 1e-4
