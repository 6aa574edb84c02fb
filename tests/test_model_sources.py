"""Each zoo model's equations are written once, in torch form: its compiled hooks
(generated from its forward, as for any user's model) against that form and automatic
differentiation of it, in float64 at random points; the curvature pattern they declare
(found symbolically) against the nonzeros of the autodiff Hessians."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.func import hessian, jacrev

import torchslq as ts
from torchslq.systems import CartPole, MassChain, Unicycle

pytestmark = pytest.mark.codegen  # generated compiled code on (tests/conftest.py)

F64 = torch.float64

numba = pytest.importorskip("numba")

MODELS = {
    "cartpole": lambda: CartPole(mc=1.1, mp=0.3, l=0.7, g=9.0),
    "cartpole-default": lambda: CartPole(),
    "mass-chain-1": lambda: MassChain(1, mass=0.9, k=1.2, k3=0.5, damping=0.3),
    "mass-chain-3": lambda: MassChain(3, mass=1.3, k=0.8, k3=0.7, damping=0.2),
    "mass-chain-linear": lambda: MassChain(2, k3=0.0),  # no curvature at these parameters
}


def _points(model, count, seed):
    g = torch.Generator().manual_seed(seed)
    n, m = model.state_dim, model.control_dim
    x = 2.0 * torch.randn(count, n, generator=g, dtype=F64)
    u = 3.0 * torch.randn(count, m, generator=g, dtype=F64)
    return x, u


def _autodiff(model, x, u):
    """Jacobian ``(n, n + m)`` and per-output Hessians ``(n, n + m, n + m)`` of the torch
    form at one point, by torch.func."""
    n = x.shape[-1]

    def f(z):
        return model(z[:n], z[n:])

    z = torch.cat([x, u])
    return jacrev(f)(z), hessian(f)(z)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_compiled_rhs_equals_the_torch_form(name):
    model = MODELS[name]()
    rhs, params = model.compiled_rhs()
    x, u = _points(model, 20, 1)
    want = model(x, u)
    out = np.empty(model.state_dim)
    for i in range(len(x)):
        rhs(x[i].numpy(), u[i].numpy(), params, out)
        np.testing.assert_allclose(out, want[i].numpy(), rtol=1e-14, atol=1e-14)
    # a float32 state beside float64 parameters (the kernels' float32 path)
    out32 = np.empty(model.state_dim, dtype=np.float32)
    rhs(x[0].float().numpy(), u[0].float().numpy(), params, out32)
    np.testing.assert_allclose(out32, want[0].numpy(), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_compiled_derivatives_equal_automatic_differentiation(name):
    """``fz`` = jacrev of the torch form; ``H`` = torch.func.hessian of it at the
    declared pattern's entries, which hold every nonzero of the autodiff Hessians; the
    entries outside the pattern are left untouched; an empty ``H`` asks for ``fz`` only."""
    from torchslq.dynamics import CompiledDerivatives

    model = MODELS[name]()
    n, m = model.state_dim, model.control_dim
    cd = model.compiled_derivatives()
    _, params = model.compiled_rhs()
    pattern = np.zeros((n, n + m, n + m), dtype=bool)
    if not isinstance(cd, CompiledDerivatives):  # no curvature: H written whole, zeros
        assert name == "mass-chain-linear"
        x, u = _points(model, 3, 2)
        for i in range(len(x)):
            J, Ht = _autodiff(model, x[i], u[i])
            fz, H = np.full((n, n + m), np.nan), np.full((n, n + m, n + m), np.nan)
            cd(x[i].numpy(), u[i].numpy(), params, fz, H)
            np.testing.assert_allclose(fz, J.numpy(), rtol=1e-12, atol=1e-13)
            assert not Ht.numpy().any() and not H.any()
        return
    outs, ents = list(cd.curved_outputs), list(cd.curved_entries)
    pattern[np.ix_(outs, ents, ents)] = True
    x, u = _points(model, 8, 2)
    for i in range(len(x)):
        J, Ht = _autodiff(model, x[i], u[i])
        fz, H = np.full((n, n + m), np.nan), np.full((n, n + m, n + m), np.nan)
        cd.derivatives(x[i].numpy(), u[i].numpy(), params, fz, H)
        np.testing.assert_allclose(fz, J.numpy(), rtol=1e-12, atol=1e-13)
        assert not Ht.numpy()[~pattern].any()  # the pattern covers every nonzero
        np.testing.assert_allclose(H[pattern], Ht.numpy()[pattern], rtol=1e-11, atol=1e-12)
        assert np.isnan(H[~pattern]).all()
        fz2 = np.full((n, n + m), np.nan)
        cd.derivatives(x[i].numpy(), u[i].numpy(), params, fz2, np.zeros((0, n + m, n + m)))
        assert np.array_equal(fz, fz2)


@pytest.mark.parametrize(
    "make",
    [
        lambda p: CartPole(*p),
        lambda p: MassChain(1, *p),
        lambda p: MassChain(4, *p),
    ],
)
def test_the_derived_pattern_is_the_union_of_the_autodiff_nonzeros(make):
    """No curved output or entry is missed or extra: over many random points and
    parameters, the nonzeros of the autodiff Hessians fill exactly the declared rows
    and columns (a pattern kept by hand could drift from the model)."""
    ref = make((1.0, 1.0, 1.0, 1.0))
    outs, ents = ref.compiled_derivatives()[1:]
    n, m = ref.state_dim, ref.control_dim
    g = torch.Generator().manual_seed(5)
    seen = torch.zeros(n, n + m, n + m, dtype=torch.bool)
    for _ in range(6):
        model = make(tuple(float(v) for v in 0.2 + 2.0 * torch.rand(4, generator=g)))
        x, u = _points(model, 1, int(torch.randint(0, 1000, (1,), generator=g)))
        seen |= _autodiff(model, x[0], u[0])[1] != 0
    assert tuple(torch.nonzero(seen.flatten(1).any(1)).flatten().tolist()) == outs
    assert tuple(torch.nonzero(seen.any(0).any(0)).flatten().tolist()) == ents


@pytest.mark.parametrize("name", ["cartpole", "mass-chain-3"])
def test_torch_jacobians_and_vhp_equal_automatic_differentiation(name):
    """The torch form's analytic derivatives (the same sources, batched) against
    torch.func, with broadcast weight vectors."""
    model = MODELS[name]()
    n = model.state_dim
    x, u = _points(model, 5, 3)
    s = torch.randn(2, 5, n, generator=torch.Generator().manual_seed(3), dtype=F64)
    A, B = model.jacobians(x, u)
    Hxx, Huu, Hux = model.vhp(x, u, s)
    assert Hxx.shape == (2, 5, n, n)
    for i in range(5):
        J, Ht = _autodiff(model, x[i], u[i])
        torch.testing.assert_close(torch.cat([A[i], B[i]], -1), J, rtol=1e-12, atol=1e-13)
        for w in range(2):
            Hs = torch.einsum("j,jab->ab", s[w, i], Ht)
            torch.testing.assert_close(Hxx[w, i], Hs[:n, :n], rtol=1e-11, atol=1e-12)
            torch.testing.assert_close(Huu[w, i], Hs[n:, n:], rtol=1e-11, atol=1e-12)
            torch.testing.assert_close(Hux[w, i], Hs[n:, :n], rtol=1e-11, atol=1e-12)


def test_compiled_steps_equal_the_torch_steps():
    """The unicycle's compiled step and the RK4 step around a compiled right-hand side
    (dynamics._numba_rk4.rk4_step) against their torch forms."""
    cases = [
        (Unicycle(dt=0.07), 3, 2),
        (ts.discretize(CartPole(mc=1.3), 0.05), 4, 1),
        (ts.discretize(MassChain(3, k3=0.6), 0.1), 6, 3),
    ]
    g = torch.Generator().manual_seed(7)
    for model, n, m in cases:
        step, params = model.compiled_step()
        x = torch.randn(10, n, generator=g, dtype=F64)
        u = torch.randn(10, m, generator=g, dtype=F64)
        want = model(x, u)
        out, work = np.empty(n), np.empty((8, n))
        for i in range(10):
            step(x[i].numpy(), u[i].numpy(), params, out, work)
            np.testing.assert_allclose(out, want[i].numpy(), rtol=1e-14, atol=1e-14)


def test_per_element_parameters_have_no_compiled_hooks():
    per_elem = torch.tensor([[1.0], [1.2]], dtype=F64)
    for model in (CartPole(mc=per_elem), MassChain(2, mass=per_elem)):
        assert model.compiled_rhs() is None and model.compiled_derivatives() is None
