"""The example systems in torchslq.systems: analytic Jacobians, physics, per-element params."""

from __future__ import annotations

import math

import pytest
import torch

import torchslq
from torchslq.systems import CartPole, DragVehicle, Hopper, Pendulum

DT = torch.float64
GEN_SEED = 0


def _gen(seed: int = GEN_SEED) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _rand(*shape, scale=1.0, seed=GEN_SEED):
    return scale * torch.randn(*shape, dtype=DT, generator=_gen(seed))


def random_inputs(name: str, lead=(4, 6), seed: int = 1):
    """Random states/controls covering each system's interesting regions."""
    g = _gen(seed)
    if name == "pendulum":
        x = torch.stack(
            [
                torch.empty(*lead, dtype=DT).uniform_(-math.pi, math.pi, generator=g),
                3.0 * torch.randn(*lead, dtype=DT, generator=g),
            ],
            -1,
        )
        u = 2.0 * torch.randn(*lead, 1, dtype=DT, generator=g)
    elif name == "cartpole":
        x = torch.randn(*lead, 4, dtype=DT, generator=g)
        x[..., 1] = torch.empty(*lead, dtype=DT).uniform_(-4.0, 4.0, generator=g)
        x[..., 3] *= 4.0
        u = 5.0 * torch.randn(*lead, 1, dtype=DT, generator=g)
    elif name == "drag":
        x = torch.randn(*lead, 2, dtype=DT, generator=g)
        x[..., 1] *= 10.0
        u = torch.randn(*lead, 1, dtype=DT, generator=g)
    elif name == "hopper":
        y = 5.0 * torch.randn(*lead, dtype=DT, generator=g)
        # compression e = yp - y across flight (e<0), the quadratic blend and the linear part
        e = torch.empty(*lead, dtype=DT).uniform_(-0.3, 0.4, generator=g)
        yd = 20.0 * torch.randn(*lead, dtype=DT, generator=g)
        x = torch.stack([y, yd, y + e], -1)
        u = 10.0 * torch.randn(*lead, 1, dtype=DT, generator=g)
    else:  # pragma: no cover
        raise KeyError(name)
    return x, u


CONTINUOUS = {
    "pendulum": lambda: Pendulum(mass=1.3, length=0.7, g=9.81, damping=0.2),
    "cartpole": lambda: CartPole(mc=1.0, mp=0.1, l=0.5),
    "cartpole_l02": lambda: CartPole(l=0.2),
}
DISCRETE = {
    "drag": lambda: DragVehicle(beta=0.5),
    "hopper": lambda: Hopper(),
}


def _kind(name: str) -> str:
    return name.split("_")[0]


def autodiff_jacobians(f, x, u):
    """Reference Jacobians by torch.func.jacrev of a plain callable (no analytic override)."""
    return torchslq.linearize(lambda xx, uu: f(xx, uu), x, u, method="jacrev")


# ---------------------------------------------------------------- analytic Jacobians


@pytest.mark.parametrize("name", sorted(CONTINUOUS))
def test_continuous_jacobians_match_autodiff(name):
    model = CONTINUOUS[name]()
    assert model.has_analytic_jacobians
    x, u = random_inputs(_kind(name))
    A, B = model.jacobians(x, u)
    A_ref, B_ref = autodiff_jacobians(model, x, u)
    assert A.shape == (4, 6, model.state_dim, model.state_dim)
    assert B.shape == (4, 6, model.state_dim, model.control_dim)
    torch.testing.assert_close(A, A_ref, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(B, B_ref, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("method,dt", [("rk4", 0.05), ("euler", 0.02)])
@pytest.mark.parametrize("name", sorted(CONTINUOUS))
def test_discretized_jacobians_match_autodiff(name, method, dt):
    disc = torchslq.discretize(CONTINUOUS[name](), dt, method)
    assert disc.has_analytic_jacobians
    x, u = random_inputs(_kind(name))
    A, B = torchslq.linearize(disc, x, u)  # chained analytic Jacobians
    A_ref, B_ref = autodiff_jacobians(disc, x, u)
    torch.testing.assert_close(A, A_ref, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(B, B_ref, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("name", sorted(DISCRETE))
def test_discrete_jacobians_match_autodiff(name):
    model = DISCRETE[name]()
    assert model.has_analytic_jacobians
    x, u = random_inputs(name)
    A, B = torchslq.linearize(model, x, u)
    A_ref, B_ref = autodiff_jacobians(model, x, u)
    torch.testing.assert_close(A, A_ref, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(B, B_ref, atol=1e-10, rtol=1e-10)


def test_jacobians_unbatched_and_float32():
    for model, n in ((Pendulum(), 2), (CartPole(), 4), (DragVehicle(), 2), (Hopper(), 3)):
        x, u = torch.ones(n, dtype=torch.float32), torch.ones(1, dtype=torch.float32)
        out = model(x, u)
        A, B = model.jacobians(x, u)
        assert out.shape == (n,) and A.shape == (n, n) and B.shape == (n, 1)
        assert out.dtype == A.dtype == B.dtype == torch.float32


def test_hopper_spring_is_c1_and_gradients_finite():
    alpha = 0.1
    h = Hopper(alpha=alpha)
    for knot in (0.0, alpha):
        e = torch.tensor([knot - 1e-12, knot + 1e-12], dtype=DT)
        phi, dphi = Hopper._phi(e, alpha)
        assert abs(phi[0] - phi[1]) < 1e-11
        assert abs(dphi[0] - dphi[1]) < 1e-10
    # a 100-step rollout through flight, touchdown and stance: finite gradients everywhere
    u = torch.zeros(100, 1, dtype=DT, requires_grad=True)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    xs = []
    for t in range(100):
        x = h(x, u[t] + 5.0 * math.sin(0.3 * t))
        xs.append(x)
    xs = torch.stack(xs)
    assert (xs[:, 2] - xs[:, 0] > alpha).any() and (xs[:, 2] - xs[:, 0] < 0).any()
    xs[-1, 0].backward()
    assert torch.isfinite(u.grad).all() and u.grad.abs().sum() > 0


# ---------------------------------------------------------------- physics sanity checks


def _simulate(step, x, u, steps):
    for _ in range(steps):
        x = step(x, u)
    return x


def test_pendulum_energy_conserved_without_damping():
    model = Pendulum(mass=0.8, length=1.3, damping=0.0)
    step = torchslq.discretize(model, 1e-3, "rk4")
    x0 = torch.tensor([[2.5, 0.0], [0.3, 1.0], [-1.0, -4.0]], dtype=DT)
    u = torch.zeros(3, 1, dtype=DT)
    E0 = model.energy(x0)
    x1 = _simulate(step, x0, u, 500)
    assert (x1 - x0).abs().max() > 0.1  # it actually moved
    torch.testing.assert_close(model.energy(x1), E0, atol=1e-6, rtol=0)


def test_pendulum_power_balance_and_small_oscillation():
    # dE/dt = tau thd - b thd^2 along the vector field, with per-element parameters
    B = 5
    g = _gen(3)
    m = torch.rand(B, 1, dtype=DT, generator=g) + 0.5
    l = torch.rand(B, 1, dtype=DT, generator=g) + 0.5
    b = torch.rand(B, 1, dtype=DT, generator=g)
    model = Pendulum(mass=m, length=l, damping=b)
    x, u = random_inputs("pendulum", lead=(B, 7))
    xr = x.clone().requires_grad_(True)
    (dE,) = torch.autograd.grad(model.energy(xr).sum(), xr)
    dEdt = (dE * model(x, u)).sum(-1)
    thd = x[..., 1]
    torch.testing.assert_close(dEdt, u[..., 0] * thd - b * thd**2, atol=1e-10, rtol=1e-10)
    # linearisation at rest without damping: eigenvalues +-i sqrt(g/l)
    A, _ = Pendulum(length=2.0, damping=0.0).jacobians(
        torch.zeros(2, dtype=DT), torch.zeros(1, dtype=DT)
    )
    ev = torch.linalg.eigvals(A)
    torch.testing.assert_close(ev.imag.abs(), torch.full((2,), math.sqrt(9.81 / 2.0), dtype=DT))


def test_cartpole_equilibria_and_upright_instability():
    mc, mp, l, g = 1.0, 0.1, 0.5, 9.81
    model = CartPole(mc=mc, mp=mp, l=l, g=g)
    u0 = torch.zeros(1, dtype=DT)
    for th in (0.0, math.pi):
        x = torch.tensor([0.7, th, 0.0, 0.0], dtype=DT)
        assert model(x, u0).abs().max() < 1e-14
    # upright: one unstable eigenvalue sqrt((mc + mp) g / (mc l)); hanging: oscillatory
    A, _ = model.jacobians(torch.tensor([0.0, math.pi, 0.0, 0.0], dtype=DT), u0)
    lam = torch.linalg.eigvals(A).real.max()
    assert abs(lam - math.sqrt((mc + mp) * g / (mc * l))) < 1e-10
    A, _ = model.jacobians(torch.zeros(4, dtype=DT), u0)
    assert torch.linalg.eigvals(A).real.abs().max() < 1e-10


def test_cartpole_momentum_and_energy():
    model = CartPole(l=0.2)
    step = torchslq.discretize(model, 1e-3, "rk4")
    x0 = torch.tensor([[0.0, 2.0, 0.5, -1.0], [1.0, 3.0, -0.2, 2.0]], dtype=DT)
    # no force: energy and momentum conserved (to integration accuracy)
    u = torch.zeros(2, 1, dtype=DT)
    x1 = _simulate(step, x0, u, 400)
    assert (x1 - x0).abs().max() > 0.1
    torch.testing.assert_close(model.energy(x1), model.energy(x0), atol=1e-6, rtol=0)
    torch.testing.assert_close(model.momentum(x1), model.momentum(x0), atol=1e-9, rtol=0)
    # constant force: dp/dt = F
    F = torch.tensor([[1.5], [-0.7]], dtype=DT)
    x1 = _simulate(step, x0, F, 400)
    torch.testing.assert_close(
        model.momentum(x1), model.momentum(x0) + F[:, 0] * 0.4, atol=1e-9, rtol=0
    )


def test_drag_vehicle_one_step_and_euler_convergence():
    m, beta, Ts = 0.0259, 0.1, 1 / 500
    model = DragVehicle(beta=beta, m=m, Ts=Ts)
    x0 = torch.tensor([[0.0, 3.0], [1.0, -3.0], [2.0, 0.0]], dtype=DT)
    # one step with u = 0: drag opposes the motion, odd in v
    x1 = model(x0, torch.zeros(3, 1, dtype=DT))
    torch.testing.assert_close(x1[:, 0], x0[:, 0] + Ts * x0[:, 1])
    decay = Ts * beta * 9.0 / m
    torch.testing.assert_close(x1[:, 1], torch.tensor([3.0 - decay, -3.0 + decay, 0.0], dtype=DT))
    # a force equal to the drag holds the velocity
    hold = beta * x0[:, 1:] * x0[:, 1:].abs()
    torch.testing.assert_close(model(x0, hold)[:, 1], x0[:, 1])
    # coasting converges to v(t) = v0 / (1 + beta |v0| t / m) at first order
    v0, t_end = 5.0, 0.2
    exact = v0 / (1 + beta * v0 * t_end / m)
    errs = []
    for N in (100, 200, 400):
        step = DragVehicle(beta=beta, m=m, Ts=t_end / N)
        x = _simulate(step, torch.tensor([0.0, v0], dtype=DT), torch.zeros(1, dtype=DT), N)
        errs.append(abs(x[1].item() - exact))
    assert 1.8 < errs[0] / errs[1] < 2.2 and 1.8 < errs[1] / errs[2] < 2.2


def test_drag_vehicle_euler_stability_threshold():
    # |dv(n+1)/dv(n)| > 1 exactly beyond |v| = m / (beta Ts) (the paper's beta = 1 trouble)
    m, beta, Ts = 0.0259, 1.0, 1 / 500
    vcrit = m / (beta * Ts)
    assert abs(vcrit - 12.95) < 1e-12
    v = torch.tensor([0.99 * vcrit, 1.01 * vcrit, -1.01 * vcrit], dtype=DT)
    x = torch.stack([torch.zeros_like(v), v], -1)
    A, _ = DragVehicle(beta=beta, m=m, Ts=Ts).jacobians(x, torch.zeros(3, 1, dtype=DT))
    assert A[0, 1, 1].abs() < 1 < A[1, 1, 1].abs() and A[2, 1, 1].abs() > 1


def test_hopper_free_flight_is_exact_euler_parabola():
    h = Hopper()
    g, dt, N = 386.4, h.dt, 30
    x0 = torch.tensor([[10.0, 50.0, 0.0], [40.0, -20.0, -1.0]], dtype=DT)
    u = torch.zeros(2, 1, dtype=DT)
    x = x0
    for k in range(1, N + 1):
        x = h(x, u)
        t = k * dt
        y0, v0 = x0[:, 0], x0[:, 1]
        # Euler: y_k = y0 + v0 t - g t^2 / 2 + g dt t / 2, v_k = v0 - g t
        torch.testing.assert_close(x[:, 0], y0 + v0 * t - g * t * t / 2 + g * dt * t / 2)
        torch.testing.assert_close(x[:, 1], v0 - g * t)
        torch.testing.assert_close(x[:, 2], x0[:, 2])
        assert (x[:, 2] < x[:, 0]).all()  # still in flight


def test_hopper_static_stance_equilibrium_and_piston():
    k, g, alpha = 500.0, 386.4, 0.1
    h = Hopper(k_over_m=k, g=g, alpha=alpha)
    e_star = g / k + alpha / 2  # linear part: k (e - alpha/2) = g
    x = torch.tensor([3.0, 0.0, 3.0 + e_star], dtype=DT)
    torch.testing.assert_close(h(x, torch.zeros(1, dtype=DT)), x, atol=1e-12, rtol=0)
    # the piston integrates the control
    x1 = h(x, torch.tensor([2.0], dtype=DT))
    assert abs(x1[2].item() - (3.0 + e_star + 2.0 * h.dt)) < 1e-14
    # in the quadratic blend the spring force is k e^2 / (2 alpha)
    x = torch.tensor([0.0, 0.0, 0.05], dtype=DT)
    assert abs(h.spring_acceleration(x).item() - k * 0.05**2 / (2 * alpha)) < 1e-12


# ---------------------------------------------------------------- per-element parameters


PER_ELEMENT = [
    (
        Pendulum,
        "pendulum",
        {"mass": [1.0, 2.0, 0.5], "length": [1.0, 0.3, 2.0], "damping": [0.0, 0.1, 0.7]},
    ),
    (CartPole, "cartpole", {"mc": [1.0, 2.0, 0.5], "mp": [0.1, 0.3, 0.05], "l": [0.5, 0.2, 1.0]}),
    (DragVehicle, "drag", {"beta": [0.01, 0.1, 0.5], "m": [0.0259, 0.05, 0.0259]}),
    (Hopper, "hopper", {"k_over_m": [500.0, 300.0, 800.0], "alpha": [0.1, 0.05, 0.2]}),
]


@pytest.mark.parametrize("cls,kind,params", PER_ELEMENT, ids=[p[1] for p in PER_ELEMENT])
def test_per_element_parameters_match_separate_models(cls, kind, params):
    Bn, T = 3, 5
    x, u = random_inputs(kind, lead=(Bn, T), seed=7)
    batched = cls(**{k: torch.tensor(v, dtype=DT).reshape(Bn, 1) for k, v in params.items()})
    singles = [cls(**{k: v[b] for k, v in params.items()}) for b in range(Bn)]
    models = [(batched, singles)]
    if kind in ("pendulum", "cartpole"):
        models.append(
            (torchslq.discretize(batched, 0.05), [torchslq.discretize(s, 0.05) for s in singles])
        )
    for bm, sms in models:
        out = bm(x, u)
        A, B = torchslq.linearize(bm, x, u)
        assert out.shape == x.shape and A.shape == (Bn, T, x.shape[-1], x.shape[-1])
        for b, sm in enumerate(sms):
            torch.testing.assert_close(out[b], sm(x[b], u[b]), atol=1e-13, rtol=1e-13)
            Ab, Bb = torchslq.linearize(sm, x[b], u[b])
            torch.testing.assert_close(A[b], Ab, atol=1e-13, rtol=1e-13)
            torch.testing.assert_close(B[b], Bb, atol=1e-13, rtol=1e-13)


def test_learnable_parameter_and_dtype_follow_input():
    mass = torch.nn.Parameter(torch.tensor(1.5, dtype=DT))
    model = torchslq.discretize(Pendulum(mass=mass), 0.1)
    assert any(p is mass for p in model.parameters())
    x = torch.tensor([[0.5, 0.0]], dtype=DT)
    u = torch.tensor([[1.0]], dtype=DT)
    model(x, u)[0, 1].backward()
    assert mass.grad is not None and mass.grad.abs() > 0
    # a float64 buffer parameter does not promote float32 inputs
    m32 = Pendulum(mass=torch.full((2,), 2.0, dtype=DT))
    out = m32(torch.zeros(2, 2), torch.ones(2, 1))
    assert out.dtype == torch.float32
    assert m32.state_dict()["mass"].shape == (2,)


@pytest.mark.parametrize(
    "make,arg",
    [
        (lambda: Pendulum(mass=-1.0), "mass"),
        (lambda: Pendulum(length=torch.tensor([1.0, 0.0])), "length"),
        (lambda: CartPole(l=0.0), "l"),
        (lambda: DragVehicle(Ts=0.0), "Ts"),
        (lambda: Hopper(alpha=0.0), "alpha"),
        (lambda: Hopper(N=0), "N"),
        (lambda: Pendulum(damping="x"), "damping"),
    ],
)
def test_invalid_parameters(make, arg):
    with pytest.raises((ValueError, TypeError), match=arg):
        make()


@pytest.mark.parametrize("cls,kind,params", PER_ELEMENT, ids=[p[1] for p in PER_ELEMENT])
def test_per_element_parameters_autodiff_vjp(cls, kind, params):
    # linearize's "vjp" path calls the model once on the full (B, T, n) batch, so
    # per-element parameters need no analytic Jacobians either
    Bn, T = 3, 5
    x, u = random_inputs(kind, lead=(Bn, T), seed=11)
    model = cls(**{k: torch.tensor(v, dtype=DT).reshape(Bn, 1) for k, v in params.items()})
    A, B = torchslq.linearize(lambda xx, uu: model(xx, uu), x, u, method="vjp")
    A_ref, B_ref = model.jacobians(x, u)
    torch.testing.assert_close(A, A_ref, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(B, B_ref, atol=1e-10, rtol=1e-10)
