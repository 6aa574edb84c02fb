"""The RK4 step's Jacobians and second derivatives on the CPU kernels (a model's
compiled derivatives, torchslq.dynamics.compiled_rk4) against the torch chain and
against automatic differentiation of the step."""

from __future__ import annotations

import sys

import pytest
import torch
from torch.func import hessian, jacrev
from vhp_cases import VHP_LAYOUTS

import torchslq as ts
from torchslq._backend import dispatch as compiled
from torchslq.systems import CartPole, MassChain

F64 = torch.float64

pytestmark = [
    pytest.mark.codegen,
    pytest.mark.skipif(not compiled.compiled_available(), reason="numba kernels not available"),
]

_disc = sys.modules["torchslq.dynamics.discretize"]


def _step(dtype=F64, dt=0.07, model: str = "cartpole") -> ts.DiscretizedDynamics:
    """An RK4 model with compiled derivatives: the cart-pole (declared curvature
    pattern), the same with a function that fills all of H (each point's Hessians
    scanned for their curved entries), or a chain of 3 masses (n + m = 9)."""
    if model == "mass-chain":
        return ts.discretize(MassChain(3, mass=1.3, k3=0.7, damping=0.2), dt).to(dtype)
    cont = CartPole(mc=torch.tensor(1.3, dtype=F64))
    if model == "cartpole-scan":
        cont.compiled_derivatives = lambda: _full_cartpole_derivatives()
    return ts.discretize(cont, dt).to(dtype)


def _full_cartpole_derivatives():
    import numba

    cartpole_derivatives = CartPole().compiled_derivatives().derivatives

    @numba.njit
    def full(x, u, p, fz, H):
        for j in range(H.shape[0]):
            for a in range(H.shape[1]):
                for b in range(H.shape[2]):
                    H[j, a, b] = 0.0
        cartpole_derivatives(x, u, p, fz, H)

    return full


def _torch_results(step: ts.DiscretizedDynamics, *args):
    """The step's Jacobians or Hessian blocks by the torch chain (its model's compiled
    derivatives hidden)."""
    c = step.continuous
    old = c.__dict__.get("compiled_derivatives")
    c.compiled_derivatives = lambda: None
    try:
        return step.jacobians(*args) if len(args) == 2 else step.vhp(*args)
    finally:
        del c.compiled_derivatives
        if old is not None:
            c.compiled_derivatives = old


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
        *VHP_LAYOUTS,
        ((3, 1), (3, 6), (2, 3, 6)),  # broadcast states, a weight dim
        ((), (), ()),  # one point
    ],
)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("model", ["cartpole", "cartpole-scan", "mass-chain"])
def test_kernels_equal_the_torch_chain(model, shapes, dtype, monkeypatch):
    """Jacobians and Hessian blocks from the kernels == the torch chain through the
    stages (the model's jacobians / vhp), in broadcast layouts and both dtypes; the
    kernels must have run."""
    g = torch.Generator().manual_seed(4)
    xs, us, ss = shapes
    step = _step(dtype, model=model)
    n, m = step.state_dim, step.control_dim
    x = (1.5 * torch.randn(*xs, n, generator=g, dtype=F64)).to(dtype)
    u = torch.randn(*us, m, generator=g, dtype=F64).to(dtype)
    s = torch.randn(*ss, n, generator=g, dtype=F64).to(dtype)
    jac_calls = _counting(monkeypatch, "rk4_jacobians_compiled")
    vhp_calls = _counting(monkeypatch, "rk4_vhp_compiled")
    A, B = step.jacobians(x, u)
    H = step.vhp(x, u, s)
    assert (len(jac_calls), len(vhp_calls)) == (1, 1)
    A2, B2 = _torch_results(step, x, u)
    H2 = _torch_results(step, x, u, s)
    assert (len(jac_calls), len(vhp_calls)) == (1, 1)  # the reference did not use them
    tol = 1e-13 if dtype == F64 else 3e-6
    for a, b in zip((A, B, *H), (A2, B2, *H2), strict=True):
        assert a.dtype == dtype and a.shape == torch.broadcast_shapes(a.shape, b.shape)
        b = b.expand_as(a)
        assert float((a - b).abs().max()) <= tol * (1 + float(b.abs().max()))
    assert float(H[0].abs().max()) > 1e-3
    if model != "mass-chain":  # (only its positions are curved)
        assert float(H[2].abs().max()) > 1e-3


@pytest.mark.parametrize("model", ["cartpole", "cartpole-scan", "mass-chain"])
def test_kernels_equal_automatic_differentiation_of_the_step(model):
    """Independent of the chain formulas: A, B = jacrev of the RK4 step and the Hessian
    blocks = torch.func.hessian of s · step(x, u), row by row (float64)."""
    g = torch.Generator().manual_seed(11)
    step = _step(dt=0.1, model=model)
    n, m = step.state_dim, step.control_dim
    x = 2.0 * torch.randn(6, n, generator=g, dtype=F64)
    u = 3.0 * torch.randn(6, m, generator=g, dtype=F64)
    s = torch.randn(6, n, generator=g, dtype=F64)
    A, B = step.jacobians(x, u)
    Hxx, Huu, Hux = step.vhp(x, u, s)

    def flat(z):
        return step(z[:n].unsqueeze(0), z[n:].unsqueeze(0))[0]

    for i in range(6):
        z = torch.cat([x[i], u[i]])
        J = jacrev(flat)(z)
        Hz = hessian(lambda z, i=i: (s[i] * flat(z)).sum())(z)
        torch.testing.assert_close(A[i], J[:, :n], rtol=1e-12, atol=1e-13)
        torch.testing.assert_close(B[i], J[:, n:], rtol=1e-12, atol=1e-13)
        torch.testing.assert_close(Hxx[i], Hz[:n, :n], rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(Huu[i], Hz[n:, n:], rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(Hux[i], Hz[n:, :n], rtol=1e-10, atol=1e-12)
        assert float(Hz.abs().max()) > 1e-3


@pytest.mark.parametrize("name", ["cartpole", "mass-chain"])
def test_compiled_derivatives_equal_the_models_torch_derivatives(name):
    """A model's compiled derivatives (one row) == its torch jacobians and the Hessian
    of each output by torch.func.hessian, which is zero outside the declared pattern
    (entries there are left untouched); an empty H asks for the Jacobians only."""
    import numpy as np

    from torchslq.dynamics import CompiledDerivatives

    if name == "cartpole":
        model = CartPole(mc=1.1, mp=0.3, l=0.7, g=9.0)
    else:
        model = MassChain(3, mass=1.3, k=0.8, k3=0.7, damping=0.2)
    n, m = model.state_dim, model.control_dim
    cd = model.compiled_derivatives()
    assert isinstance(cd, CompiledDerivatives)
    _, params = model.compiled_rhs()
    outs, ents = list(cd.curved_outputs), list(cd.curved_entries)
    pattern = torch.zeros(n, n + m, n + m, dtype=torch.bool)
    pattern[torch.tensor(outs)[:, None, None], torch.tensor(ents)[:, None], torch.tensor(ents)] = (
        True
    )
    g = torch.Generator().manual_seed(2)
    for _ in range(5):
        x = 2.0 * torch.randn(n, generator=g, dtype=F64)
        u = torch.randn(m, generator=g, dtype=F64)
        fz, H = np.zeros((n, n + m)), np.full((n, n + m, n + m), np.nan)
        cd.derivatives(x.numpy(), u.numpy(), params, fz, H)
        fx, fu = model.jacobians(x, u)
        torch.testing.assert_close(torch.from_numpy(fz), torch.cat([fx, fu], -1))
        Ht = torch.stack(
            [hessian(lambda z, j=j: model(z[:n], z[n:])[j])(torch.cat([x, u])) for j in range(n)]
        )
        assert float(Ht[~pattern].abs().max()) == 0.0 and float(Ht.abs().max()) > 1e-3
        torch.testing.assert_close(
            torch.from_numpy(H)[pattern], Ht[pattern], rtol=1e-12, atol=1e-13
        )
        assert bool(np.isnan(H[~pattern.numpy()]).all())  # untouched
        fz2 = np.full((n, n + m), np.nan)
        cd.derivatives(x.numpy(), u.numpy(), params, fz2, np.zeros((0, n + m, n + m)))
        assert np.array_equal(fz, fz2)


@pytest.mark.parametrize("model", ["cartpole", "cartpole-scan"])
def test_nan_states_give_nan_derivatives(model):
    """A NaN state is not skipped as 'not curved': its Jacobians and Hessians are NaN,
    the other rows are unaffected."""
    step = _step(model=model)
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


@pytest.mark.parametrize("model", ["cartpole", "mass-chain", "per-element", "autodiff"])
def test_linearize_with_hessians_equals_the_separate_calls(model, monkeypatch):
    """linearize_with_hessians == linearize and dynamics_hessians at the same point (bit
    for bit); with compiled derivatives one kernel pass gives both (the Jacobian kernel
    is not called), otherwise the Hessians come lazily from dynamics_hessians."""
    from torchslq.dynamics import dynamics_hessians, linearize_with_hessians

    if model == "per-element":
        step = ts.discretize(CartPole(mc=torch.tensor([[1.0], [1.3]], dtype=F64)), 0.05)
    elif model == "autodiff":
        inner = _step()
        step = lambda x, u: inner(x, u)  # noqa: E731 - a plain callable: autodiff
    else:
        step = _step(model=model)
    n, m = (4, 1) if model != "mass-chain" else (6, 3)
    g = torch.Generator().manual_seed(8)
    x = torch.randn(2, 5, n, generator=g, dtype=F64)
    u = torch.randn(2, 5, m, generator=g, dtype=F64)
    jac_calls = _counting(monkeypatch, "rk4_jacobians_compiled")
    A, B, hessians = linearize_with_hessians(step, x, u)
    H = hessians()
    shared_jac_calls = len(jac_calls)
    A2, B2 = ts.linearize(step, x, u)
    H2 = dynamics_hessians(step, x, u)
    assert torch.equal(A, A2) and torch.equal(B, B2)
    for a, b in zip(H, H2, strict=True):
        assert a.shape == b.shape and torch.equal(a, b)
    assert float(H[0].abs().max()) > 1e-4
    if model in ("cartpole", "mass-chain"):
        assert shared_jac_calls == 0 and len(jac_calls) == 1


@pytest.mark.parametrize("model", ["cartpole", "mass-chain"])
@pytest.mark.parametrize("R", [1, 63, 64, 65, 150])
def test_lanes_kernel_equals_the_row_by_row_kernel(model, R):
    """The lanes kernel (sums across blocks of rows) gives each row bitwise what the
    row-by-row kernel gives with the same declared pattern and per-output congruences,
    for a partial last block, a chunk of rows (others untouched) and W = 0, 1 and n
    weight vectors (W = 0: Jacobians only)."""
    import numpy as np

    from torchslq._backend.model_fns import function_value
    from torchslq.dynamics import _numba_rk4 as k
    from torchslq.dynamics.compiled_rk4 import rk4_hooks

    cont = _step(model=model).continuous
    h = rk4_hooks(cont.compiled_rhs(), cont.compiled_derivatives())
    # the model's functions as the launchers pass them (first-class function values): a
    # cached kernel called with the dispatchers themselves would add a signature per
    # process to its on-disk index, which numba cannot load once they are gone
    fns = (
        function_value(h.rhs, "rhs", np.float64, h.params.dtype),
        function_value(h.derivatives, "derivs", np.float64, h.params.dtype),
    )
    n, m = cont.state_dim, cont.control_dim
    rng = np.random.default_rng(R)
    x, u = rng.normal(size=(R, n)), rng.normal(size=(R, m))
    x[R // 2, 1] = np.nan  # a NaN row stays in its row
    r0, r1 = (0, R) if R < 4 else (2, R - 1)
    for W in (0, 1, n):
        # the row kernel picks per-output congruences (the lanes kernel's form) for many
        # weight vectors: the lanes kernel's W are compared to the first of its 2n
        S = rng.normal(size=(2 * n, R, n))
        got, want = [], []
        for kernel, out in ((k.rk4_lanes_kernel, got), (k.rk4_second_derivatives_kernel, want)):
            Wk = W if kernel is k.rk4_lanes_kernel else 2 * n
            arrays = [np.full((Wk, R, n + m, n + m), 7.0)]  # [u; x] blocks
            arrays += [np.full((R, n, n), 7.0), np.full((R, n, m), 7.0)]
            args = (*fns, h.params, 0.07, h.curved_outputs, h.curved_entries)
            kernel(r0, r1, *args, x, u, np.ascontiguousarray(S[:Wk]), *arrays)
            out.extend(arrays)
        np.testing.assert_array_equal(got[0], want[0][:W])
        for g, w in zip(got[1:], want[1:], strict=True):
            np.testing.assert_array_equal(g, w)
        assert (got[1][:r0] == 7.0).all() and (got[1][r1:] == 7.0).all()
        assert np.isnan(got[1][R // 2]).any()
        if R > 2:
            assert np.isfinite(got[1][R // 2 + 1]).all()


def test_hessian_blocks_are_views_of_one_joint_block_read_whole_by_riccati(monkeypatch):
    """The kernels' output Hessians are views of one [u; x] tensor (lower-left block
    filled too); _backend.joint_hessians finds it (not for separate tensors), the
    Riccati kernel then reads each step's block whole: a DDP solve is the same to the
    last bit as with the three blocks read separately."""
    from torchslq.dynamics import linearize_with_hessians

    step = _step(model="mass-chain")
    n, m = step.state_dim, step.control_dim
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 7, n, dtype=F64, generator=g)
    u = torch.randn(3, 7, m, dtype=F64, generator=g)
    Hxx, Huu, Hux = linearize_with_hessians(step, x, u)[2]()
    joint = compiled.joint_hessians(Hxx, Huu, Hux)
    assert joint is not None and joint.shape == (n, 3, 7, n + m, n + m)
    assert torch.equal(joint[..., :m, :m], Huu) and torch.equal(joint[..., m:, m:], Hxx)
    assert torch.equal(joint[..., :m, m:], Hux)
    assert torch.equal(joint[..., m:, :m], Hux.transpose(-1, -2))
    assert compiled.joint_hessians(Hxx.clone(), Huu.clone(), Hux.clone()) is None
    assert compiled.joint_hessians(Hxx, Huu, Hux[..., :1, :].expand_as(Hux)) is None

    from torchslq.tasks import cartpole_swingup

    problem, x0 = cartpole_swingup(batch=5, horizon=30, seed=1)
    seen = []
    real = compiled.joint_hessians

    def spy(*blocks):
        out = real(*blocks)
        seen.append(out is not None)
        return out

    monkeypatch.setattr(compiled, "joint_hessians", spy)
    whole = ts.DDP(max_iter=30, progress=False).solve(problem, x0)
    assert seen and all(seen)
    monkeypatch.setattr(compiled, "joint_hessians", lambda *blocks: None)
    blocks = ts.DDP(max_iter=30, progress=False).solve(problem, x0)
    for name in ("u", "cost", "K", "k", "iterations"):
        assert torch.equal(getattr(whole, name), getattr(blocks, name)), name
