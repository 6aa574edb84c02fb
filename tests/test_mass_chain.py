"""MassChain: analytic Jacobians vs autodiff, physics, per-element and learnable parameters."""

from __future__ import annotations

import pytest
import torch

import torchslq
from torchslq.systems import MassChain

DT = torch.float64


def _inputs(N=4, lead=(3, 5), seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(*lead, 2 * N, dtype=DT, generator=g)
    u = torch.randn(*lead, N, dtype=DT, generator=g)
    return x, u


def _autodiff(f, x, u):
    return torchslq.linearize(lambda a, b: f(a, b), x, u, method="jacrev")


@pytest.mark.parametrize("N", [1, 2, 4])
def test_jacobians_match_autodiff(N):
    model = MassChain(N, mass=1.3, k=0.7, k3=2.0, damping=0.2)
    assert model.has_analytic_jacobians
    assert (model.state_dim, model.control_dim) == (2 * N, N)
    x, u = _inputs(N)
    A, B = model.jacobians(x, u)
    A_ref, B_ref = _autodiff(model, x, u)
    assert A.shape == (3, 5, 2 * N, 2 * N) and B.shape == (3, 5, 2 * N, N)
    torch.testing.assert_close(A, A_ref, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(B, B_ref, atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize("method", ["rk4", "euler"])
def test_discretized_jacobians_match_autodiff(method):
    disc = torchslq.discretize(MassChain(k3=3.0), 0.1, method)
    x, u = _inputs()
    A, B = torchslq.linearize(disc, x, u)
    A_ref, B_ref = _autodiff(disc, x, u)
    torch.testing.assert_close(A, A_ref, atol=1e-11, rtol=1e-11)
    torch.testing.assert_close(B, B_ref, atol=1e-11, rtol=1e-11)


def test_per_element_parameters_and_unbatched():
    B = 3
    g = torch.Generator().manual_seed(1)
    mass = torch.rand(B, 1, dtype=DT, generator=g) + 0.5
    k3 = torch.rand(B, 1, dtype=DT, generator=g)
    model = MassChain(mass=mass, k3=k3)
    x, u = _inputs(lead=(B, 5))
    out = model(x, u)
    A, Bm = model.jacobians(x, u)
    for i in range(B):
        single = MassChain(mass=float(mass[i]), k3=float(k3[i]))
        torch.testing.assert_close(out[i], single(x[i], u[i]))
        Ai, Bi = single.jacobians(x[i, 0], u[i, 0])  # unbatched
        torch.testing.assert_close(A[i, 0], Ai)
        torch.testing.assert_close(Bm[i, 0], Bi)


def test_physics_rest_forces_and_energy():
    model = MassChain(k=1.5, k3=0.5, damping=0.0)
    x, u = torch.zeros(8, dtype=DT), torch.zeros(4, dtype=DT)
    assert model(x, u).abs().max() == 0
    # a uniform stretch loads every spring equally: only the free last mass accelerates
    p = torch.tensor([0.5, 1.0, 1.5, 2.0], dtype=DT)
    a = model(torch.cat([p, torch.zeros(4, dtype=DT)]), u)[4:]
    s = 1.5 * 0.5 + 0.5 * 0.5**3
    torch.testing.assert_close(a, torch.tensor([0.0, 0.0, 0.0, -s], dtype=DT))
    # energy E = sum 1/2 m v^2 + k e^2/2 + k3 e^4/4 is conserved without damping/force
    step = torchslq.discretize(model, 1e-3, "rk4")

    def energy(z):
        e = z[:4] - torch.cat([torch.zeros(1, dtype=DT), z[:3]])
        return 0.5 * (z[4:] ** 2).sum() + (0.75 * e**2 + 0.125 * e**4).sum()

    z = torch.tensor([0.3, -0.2, 0.5, 0.1, 0.0, 0.4, -0.3, 0.2], dtype=DT)
    E0 = energy(z)
    for _ in range(500):
        z = step(z, u)
    torch.testing.assert_close(energy(z), E0, atol=1e-9, rtol=0)


def test_parameters_learnable_through_jacobians():
    k3 = torch.nn.Parameter(torch.tensor(2.0, dtype=DT))
    mass = torch.nn.Parameter(torch.tensor(1.2, dtype=DT))
    model = torchslq.discretize(MassChain(mass=mass, k3=k3), 0.1)
    x, u = _inputs(lead=(2, 3))
    A, B = torchslq.linearize(model, x, u, create_graph=True)
    (A.sum() + B.sum()).backward()
    assert k3.grad is not None and mass.grad is not None
    assert k3.grad.abs() > 0 and mass.grad.abs() > 0


def test_second_derivatives_first_then_again_and_after_dtype_change():
    """Calling the model first inside torch.func transforms (dynamics_vhp), then again
    in another transform, then in float32 after ``.float()``: a tensor created inside the
    first transform and reused later made functorch fail ("escaped?"); the matrices are
    buffers now. The second-order terms match autograd's Hessian."""
    from torchslq import discretize
    from torchslq.dynamics import dynamics_vhp

    dyn = discretize(MassChain(3, k3=2.0), 0.1)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 6, generator=g, dtype=torch.float64)
    u = torch.randn(2, 3, generator=g, dtype=torch.float64)
    s = torch.randn(2, 6, generator=g, dtype=torch.float64)
    first = dynamics_vhp(dyn, x, u, s)
    second = dynamics_vhp(dyn, x, u, s)
    for a, b in zip(first, second, strict=True):
        assert torch.equal(a, b)

    def sf(z):
        return (s[1] * dyn(z[:6].unsqueeze(0), z[6:].unsqueeze(0))[0]).sum()

    H = torch.autograd.functional.hessian(sf, torch.cat([x[1], u[1]]))
    torch.testing.assert_close(first[0][1], H[:6, :6], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(first[2][1], H[6:, :6], rtol=1e-10, atol=1e-12)
    dyn32 = dyn.float()
    out = dynamics_vhp(dyn32, x.float(), u.float(), s.float())
    torch.testing.assert_close(out[0].double(), first[0], rtol=1e-4, atol=1e-5)
