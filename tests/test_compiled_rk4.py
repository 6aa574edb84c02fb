"""The RK4 step's Jacobians and second derivatives on the CPU kernels (a model's
compiled derivatives, torchslq.dynamics.compiled_rk4) against the torch chain and
against automatic differentiation of the step."""

from __future__ import annotations

import sys

import pytest
import torch
from torch.func import hessian, jacrev

import torchslq as ts
from torchslq.lq import compiled
from torchslq.systems import CartPole

F64 = torch.float64

pytestmark = pytest.mark.skipif(
    not compiled.compiled_available(), reason="numba kernels not available"
)

_disc = sys.modules["torchslq.dynamics.discretize"]


def _step(dtype=F64, dt=0.07, **kw) -> ts.DiscretizedDynamics:
    return ts.discretize(CartPole(mc=torch.tensor(1.3, dtype=F64), **kw), dt).to(dtype)


def _torch_chain(step: ts.DiscretizedDynamics) -> ts.DiscretizedDynamics:
    """The same model without compiled derivatives (the torch chain)."""
    other = ts.discretize(step.continuous, step.dt)
    other.continuous = type(step.continuous)(
        **{k: getattr(step.continuous, k) for k in ("mc", "mp", "l", "g")}
    )
    other.continuous.compiled_derivatives = lambda: None
    return other


def _counting(monkeypatch, name):
    calls = []
    real = getattr(_disc, name)

    def counted(*a):
        calls.append(1)
        return real(*a)

    monkeypatch.setattr(_disc, name, counted)
    return calls


@pytest.mark.parametrize(
    "shapes",
    [
        ((3, 4), (3, 4), (3, 4)),  # s per point (DDP's costate mode)
        ((3, 4), (3, 4), (5, 1, 1)),  # extra leading weight dim (all output Hessians)
        ((1, 4), (1, 4), (3, 4)),  # one trajectory, several weights per point
        ((3, 4), (3, 1), (1, 4)),  # broadcast controls and weights
        ((3, 1), (3, 6), (2, 3, 6)),  # broadcast states, a weight dim
        ((), (), ()),  # one point
    ],
)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_kernels_equal_the_torch_chain(shapes, dtype, monkeypatch):
    """Jacobians and Hessian blocks from the kernels == the torch chain through the
    stages (CartPole.jacobians / CartPole.vhp), in broadcast layouts and both dtypes;
    the kernels must have run."""
    g = torch.Generator().manual_seed(4)
    xs, us, ss = shapes
    step = _step(dtype)
    x = (1.5 * torch.randn(*xs, 4, generator=g, dtype=F64)).to(dtype)
    u = torch.randn(*us, 1, generator=g, dtype=F64).to(dtype)
    s = torch.randn(*ss, 4, generator=g, dtype=F64).to(dtype)
    jac_calls = _counting(monkeypatch, "rk4_jacobians_compiled")
    vhp_calls = _counting(monkeypatch, "rk4_vhp_compiled")
    A, B = step.jacobians(x, u)
    H = step.vhp(x, u, s)
    assert (len(jac_calls), len(vhp_calls)) == (1, 1)
    ref = _torch_chain(step)
    A2, B2 = ref.jacobians(x, u)
    H2 = ref.vhp(x, u, s)
    assert (len(jac_calls), len(vhp_calls)) == (1, 1)  # the reference did not use them
    tol = 1e-13 if dtype == F64 else 3e-6
    for a, b in zip((A, B, *H), (A2, B2, *H2), strict=True):
        assert a.dtype == dtype and a.shape == torch.broadcast_shapes(a.shape, b.shape)
        b = b.expand_as(a)
        assert float((a - b).abs().max()) <= tol * (1 + float(b.abs().max()))
    assert float(H[0].abs().max()) > 1e-3 and float(H[2].abs().max()) > 1e-3


def test_kernels_equal_automatic_differentiation_of_the_step():
    """Independent of the chain formulas: A, B = jacrev of the RK4 step and the Hessian
    blocks = torch.func.hessian of s · step(x, u), row by row (float64)."""
    g = torch.Generator().manual_seed(11)
    step = _step(dt=0.1)
    x = 2.0 * torch.randn(6, 4, generator=g, dtype=F64)
    u = 3.0 * torch.randn(6, 1, generator=g, dtype=F64)
    s = torch.randn(6, 4, generator=g, dtype=F64)
    A, B = step.jacobians(x, u)
    Hxx, Huu, Hux = step.vhp(x, u, s)

    def flat(z, i):
        return step(z[:4].unsqueeze(0), z[4:].unsqueeze(0))[0]

    for i in range(6):
        z = torch.cat([x[i], u[i]])
        J = jacrev(flat)(z, i)
        Hz = hessian(lambda z, i=i: (s[i] * flat(z, i)).sum())(z)
        torch.testing.assert_close(A[i], J[:, :4], rtol=1e-12, atol=1e-13)
        torch.testing.assert_close(B[i], J[:, 4:], rtol=1e-12, atol=1e-13)
        torch.testing.assert_close(Hxx[i], Hz[:4, :4], rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(Huu[i], Hz[4:, 4:], rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(Hux[i], Hz[4:, :4], rtol=1e-10, atol=1e-12)


def test_cartpole_compiled_derivatives_equal_its_torch_derivatives():
    """CartPole.compiled_derivatives (one row) == CartPole.jacobians and the Hessian of
    each output by torch.func.hessian; an empty H asks for the Jacobians only."""
    import numpy as np

    model = CartPole(mc=1.1, mp=0.3, l=0.7, g=9.0)
    derivs = model.compiled_derivatives()
    _, params = model.compiled_rhs()
    g = torch.Generator().manual_seed(2)
    for _ in range(5):
        x = 2.0 * torch.randn(4, generator=g, dtype=F64)
        u = torch.randn(1, generator=g, dtype=F64)
        fz, H = np.zeros((4, 5)), np.full((4, 5, 5), np.nan)
        derivs(x.numpy(), u.numpy(), params, fz, H)
        fx, fu = model.jacobians(x, u)
        torch.testing.assert_close(torch.from_numpy(fz), torch.cat([fx, fu], -1))
        for j in range(4):
            Hj = hessian(lambda z, j=j: model(z[:4], z[4:])[j])(torch.cat([x, u]))
            torch.testing.assert_close(torch.from_numpy(H[j]), Hj, rtol=1e-12, atol=1e-13)
        fz2 = np.full((4, 5), np.nan)
        derivs(x.numpy(), u.numpy(), params, fz2, np.zeros((0, 5, 5)))
        assert np.array_equal(fz, fz2)


def test_nan_states_give_nan_derivatives():
    """A NaN state is not skipped as 'not curved': its Jacobians and Hessians are NaN,
    the other rows are unaffected."""
    step = _step()
    x = torch.zeros(3, 4, dtype=F64)
    x[1, 1] = float("nan")
    u = torch.ones(3, 1, dtype=F64)
    A, _ = step.jacobians(x, u)
    Hxx, _, _ = step.vhp(x, u, torch.ones(3, 4, dtype=F64))
    assert bool(torch.isnan(A[1]).any()) and bool(torch.isnan(Hxx[1]).any())
    assert bool(torch.isfinite(A[[0, 2]]).all()) and bool(torch.isfinite(Hxx[[0, 2]]).all())


def test_the_torch_chain_is_used_where_the_kernels_cannot(monkeypatch):
    """Per-element parameters (no compiled rhs), Euler, states or parameters that need
    autograd: the torch chain (with its graph) instead of the kernels."""
    jac_calls = _counting(monkeypatch, "rk4_jacobians_compiled")
    vhp_calls = _counting(monkeypatch, "rk4_vhp_compiled")
    x, u = torch.randn(2, 4, dtype=F64), torch.randn(2, 1, dtype=F64)
    s = torch.randn(2, 4, dtype=F64)
    per_elem = ts.discretize(CartPole(mc=torch.tensor([[1.0], [1.2]], dtype=F64)), 0.05)
    euler = ts.discretize(CartPole(), 0.05, "euler")
    for step in (per_elem, euler):
        step.jacobians(x, u)
        step.vhp(x, u, s)
    assert (jac_calls, vhp_calls) == ([], [])
    mc = torch.nn.Parameter(torch.tensor(1.2, dtype=F64))
    step = ts.discretize(CartPole(mc=mc), 0.05)
    A, _ = step.jacobians(x, u)
    assert A.requires_grad and jac_calls == []  # the graph to mc is kept
    (dA,) = torch.autograd.grad(A.sum(), mc)
    with torch.no_grad():  # nothing needs autograd: the kernel
        A0, _ = step.jacobians(x, u)
    assert jac_calls == [1] and torch.allclose(A0, A.detach(), rtol=1e-13, atol=1e-14)
    xg = x.clone().requires_grad_(True)
    A, _ = ts.discretize(CartPole(), 0.05).jacobians(xg, u)
    assert A.requires_grad and jac_calls == [1]
    assert float(dA.abs()) > 0


def test_ddp_solve_with_the_kernels_equals_the_torch_chain():
    """A whole DDP (value mode, every step's output Hessians) swing-up with the kernels
    reaches the same solutions as with the torch chain (same iterations and statuses,
    costs to round-off)."""
    from torchslq.tasks import cartpole_swingup

    problem, x0 = cartpole_swingup(batch=4, horizon=30, seed=2)
    assert problem.dynamics.continuous.compiled_derivatives() is not None
    fast = ts.DDP(max_iter=80, progress=False).solve(problem, x0)
    problem.dynamics.continuous.compiled_derivatives = lambda: None
    ref = ts.DDP(max_iter=80, progress=False).solve(problem, x0)
    assert bool(fast.converged.all()) and torch.equal(fast.status, ref.status)
    assert torch.equal(fast.iterations, ref.iterations)
    torch.testing.assert_close(fast.cost, ref.cost, rtol=1e-10, atol=0)
    torch.testing.assert_close(fast.u, ref.u, rtol=1e-6, atol=1e-8)
