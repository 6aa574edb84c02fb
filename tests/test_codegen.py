"""Compiled code generated from a user's own torch model (torchslq.dynamics.codegen):
the generated right-hand side and derivatives against the model's forward and
torch.func, the cases that must stay on the torch path, and solves that equal the
torch path's."""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pytest
import torch
from numba.core import types as nb_types
from torch import nn

import torchslq as ts
from torchslq.dynamics import CompiledDerivatives, codegen, dynamics_hessians, dynamics_vhp

pytestmark = pytest.mark.codegen  # generated compiled code on (tests/conftest.py)


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    # the generated modules go to a fresh directory (shared by this file's tests)
    monkeypatch.setenv("TORCHSLQ_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "codegen"))
    monkeypatch.setenv("TORCHSLQ_CODEGEN", "1")


class UserCartPole(ts.ContinuousDynamics):
    state_dim, control_dim = 4, 1

    def forward(self, x, u, t=None):
        th, sd, thd, F = x[..., 1], x[..., 2], x[..., 3], u[..., 0]
        s, c = torch.sin(th), torch.cos(th)
        D = 1.0 + 0.1 * s * s
        sdd = (F + 0.1 * s * (0.5 * thd * thd + 9.81 * c)) / D
        thdd = (-F * c - 0.1 * 0.5 * thd * thd * c * s - 1.1 * 9.81 * s) / (0.5 * D)
        return torch.stack([sd, thd, sdd, thdd], -1)


class DampedPendulum(ts.ContinuousDynamics):
    """Parameters and a buffer; writes its output in place; tanh, exp, sqrt, pow."""

    state_dim, control_dim = 2, 2

    def __init__(self):
        super().__init__()
        self.damping = nn.Parameter(torch.tensor(0.3, dtype=torch.float64))
        self.register_buffer("gains", torch.tensor([1.5, -0.7], dtype=torch.float64))

    def forward(self, x, u, t=None):
        out = torch.zeros_like(x)
        out[..., 0] = x[..., 1]
        drive = (self.gains * torch.tanh(u)).sum(-1)
        out[..., 1] = (
            -9.81 * torch.sin(x[..., 0])
            - self.damping * x[..., 1] * torch.exp(-0.1 * x[..., 0] ** 2)
            + drive / torch.sqrt(1.0 + x[..., 1] ** 2)
        )
        return out


class LinearModel(ts.ContinuousDynamics):
    """No curvature: matrix products with constant matrices."""

    state_dim, control_dim = 3, 1

    def __init__(self):
        super().__init__()
        self.register_buffer("A", torch.tensor([[0.0, 1, 0], [0, 0, 1], [-1, -2, -3]]).double())
        self.register_buffer("B", torch.tensor([[0.0], [0], [1]]).double())

    def forward(self, x, u, t=None):
        return x @ self.A.mT + u @ self.B.mT


class Branches(ts.ContinuousDynamics):
    """torch.where, clamp, relu, comparisons: compiled as branches, with torch's
    derivatives on each side."""

    state_dim, control_dim = 2, 1

    def forward(self, x, u, t=None):
        a = torch.where(x[..., 0] > 0.2, x[..., 0] ** 2, 0.5 * x[..., 0])
        b = torch.clamp(x[..., 1] * u[..., 0], -1.0, 1.5) + torch.relu(x[..., 0] - x[..., 1])
        return torch.stack([a + torch.maximum(x[..., 1], u[..., 0]), b], -1)


class Constants(ts.ContinuousDynamics):
    """Tensors that are neither inputs nor parameters: a plain tensor attribute and a
    tensor literal in forward (constants of the traced graph)."""

    state_dim, control_dim = 2, 1

    def __init__(self):
        super().__init__()
        self.K = torch.tensor([[0.0, 1.0], [-2.0, -0.5]], dtype=torch.float64)

    def forward(self, x, u, t=None):
        w = torch.tensor([0.0, 1.5], dtype=torch.float64)
        return x @ self.K.mT + w * u + 0.1 * torch.sin(x) * x[..., :1]


class InverseSquare(ts.ContinuousDynamics):
    """Negative integer powers in the model and in its derivatives (an inverse-square
    pull): printed as products of reciprocals, not calls of pow."""

    state_dim, control_dim = 2, 1

    def forward(self, x, u, t=None):
        r2 = 1.0 + x[..., 0] ** 2
        pull = -x[..., 0] / r2**1.5 + u[..., 0] / (r2 * r2)
        return torch.stack([x[..., 1], pull - 0.1 * x[..., 1] / r2], -1)


def _reference(model, x, u):
    """forward, [f_x | f_u] and per-output Hessians in z = (x, u) by torch.func, row by row."""
    n = x.shape[-1]

    def f(z):
        return model(z[:n][None], z[n:][None])[0]

    z = torch.cat([x, u], -1)
    with torch.no_grad():
        F = torch.stack([f(zr) for zr in z])
    J = torch.stack([torch.func.jacrev(f)(zr) for zr in z]).detach()
    H = torch.stack([torch.func.hessian(f)(zr) for zr in z]).detach()
    return F, J, H


@pytest.mark.parametrize(
    "model_cls", [UserCartPole, DampedPendulum, LinearModel, Branches, Constants, InverseSquare]
)
def test_generated_functions_equal_forward_and_torch_func_derivatives(model_cls):
    model = model_cls()
    assert codegen.explain(model) == "compiled"
    hooks = codegen.generated_hooks(model)
    n, m = model.state_dim, model.control_dim
    gen = torch.Generator().manual_seed(5)
    x = 2 * torch.randn(16, n, generator=gen, dtype=torch.float64)
    u = 2 * torch.randn(16, m, generator=gen, dtype=torch.float64)
    F, J, H = _reference(model, x, u)
    rhs, p = model.compiled_rhs()
    derivs = model.compiled_derivatives()
    if isinstance(derivs, CompiledDerivatives):
        fn, outs, ents = derivs
    else:  # no curvature: a plain function that writes all of H
        fn, outs, ents = derivs, range(n), range(n + m)
        assert model_cls is LinearModel
    for r in range(16):
        out = np.zeros(n)
        fz = np.zeros((n, n + m))
        Hc = np.full((n, n + m, n + m), np.nan)
        rhs(x[r].numpy(), u[r].numpy(), p, out)
        fn(x[r].numpy(), u[r].numpy(), p, fz, Hc)
        np.testing.assert_allclose(out, F[r].numpy(), rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(fz, J[r].numpy(), rtol=1e-12, atol=1e-12)
        idx = np.ix_(list(outs), list(ents), list(ents))
        np.testing.assert_allclose(Hc[idx], H[r].numpy()[idx], rtol=1e-11, atol=1e-11)
        # outside the declared pattern the Hessians are zero
        mask = np.ones(H[r].shape, dtype=bool)
        mask[idx] = False
        assert np.all(H[r].numpy()[mask] == 0)
    assert hooks.tensor_names == tuple(
        k for k, _ in (*model.named_parameters(), *model.named_buffers())
    )
    source = open(hooks.source_path).read()
    assert "**(-" not in source and "**-" not in source  # no pow for integer powers


def test_generated_code_reads_the_current_parameter_values():
    model = DampedPendulum()
    rhs, _ = model.compiled_rhs()
    with torch.no_grad():
        model.damping.fill_(2.5)
        model.gains.mul_(-3.0)
    rhs2, p = model.compiled_rhs()
    assert rhs2 is rhs  # the same compiled function, new numbers
    x = torch.tensor([[0.4, -1.2]], dtype=torch.float64)
    u = torch.tensor([[0.3, 0.8]], dtype=torch.float64)
    out = np.zeros(2)
    rhs(x[0].numpy(), u[0].numpy(), p, out)
    with torch.no_grad():
        np.testing.assert_allclose(out, model(x, u)[0].numpy(), rtol=1e-13)


def test_an_equal_model_reuses_the_generated_module():
    a, b = UserCartPole(), UserCartPole()
    ha, hb = codegen.generated_hooks(a), codegen.generated_hooks(b)
    assert ha.source_path is not None and ha.source_path == hb.source_path
    assert ha.rhs is hb.rhs


class ValueBranch(ts.ContinuousDynamics):
    state_dim, control_dim = 1, 1

    def forward(self, x, u, t=None):
        if bool((x > 0).all()):  # a branch on the values: cannot be compiled as traced
            return -x + u
        return x + u


class MixesRows(ts.ContinuousDynamics):
    state_dim, control_dim = 2, 1

    def forward(self, x, u, t=None):
        return x - x.mean(0, keepdim=True) + u


class PerElementMass(ts.ContinuousDynamics):
    state_dim, control_dim = 2, 1

    def __init__(self, mass):
        super().__init__()
        self.register_buffer("mass", mass)  # (B, 1): one per element, against (B, T)

    def forward(self, x, u, t=None):
        return torch.stack([x[..., 1], u[..., 0] / self.mass], -1)


class BigNetwork(ts.ContinuousDynamics):
    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(5, 64), nn.Tanh(), nn.Linear(64, 4)).double()

    def forward(self, x, u, t=None):
        return self.net(torch.cat([x, u], -1))


class OptedOut(UserCartPole):
    generate_compiled_code = False


@pytest.mark.parametrize(
    "model, reason",
    [
        (ValueBranch(), "could not be traced"),
        (MixesRows(), "not independent"),
        (PerElementMass(torch.full((3, 1), 2.0, dtype=torch.float64)), "could not be traced"),
        (BigNetwork(), "parameter entries"),
        (OptedOut(), "generate_compiled_code is False"),
    ],
    ids=["value-branch", "mixes-rows", "per-element", "network", "opted-out"],
)
def test_models_the_generator_cannot_take_keep_the_torch_path(model, reason):
    why = codegen.explain(model)
    assert why != "compiled" and reason in why
    assert model.compiled_rhs() is None and model.compiled_derivatives() is None
    # and they still solve (the torch path), e.g. one ILQR iteration
    n, m = model.state_dim, model.control_dim
    B = 3
    cost = ts.QuadraticCost(torch.eye(n, dtype=torch.float64), torch.eye(m, dtype=torch.float64))
    problem = ts.Problem(ts.discretize(model, 0.1), cost, 5)
    x0 = torch.ones(B, n, dtype=torch.float64)
    res = ts.ILQR(max_iter=1).solve(problem, x0)
    assert torch.isfinite(res.cost).all()


def test_code_generation_can_be_turned_off(monkeypatch):
    monkeypatch.setenv("TORCHSLQ_CODEGEN", "0")
    model = UserCartPole()
    assert model.compiled_rhs() is None
    assert "off" in codegen.explain(model)


def _swingup(model, B=3, dtype=torch.float64):
    kw = {"dtype": dtype}
    cost = ts.QuadraticCost(
        torch.zeros(4, 4, **kw),
        0.02 * torch.eye(1, **kw),
        Qf=200.0 * torch.eye(4, **kw),
        x_ref=torch.tensor([0.0, math.pi, 0.0, 0.0], **kw),
    )
    problem = ts.Problem(ts.discretize(model, 0.05).to(dtype), cost, 50)
    x0 = torch.zeros(B, 4, **kw)
    x0[:, 1] = torch.tensor([0.05, -0.03, 0.01][:B], **kw)
    return problem, x0


@pytest.mark.parametrize("solver", [ts.ILQR, ts.DDP])
def test_solve_on_generated_code_equals_the_torch_path(solver, monkeypatch):
    problem, x0 = _swingup(UserCartPole())
    assert codegen.explain(problem.dynamics.continuous) == "compiled"
    # DDP to convergence; ILQR (~180 iterations here) for its first 40 on the torch path
    max_iter = 500 if solver is ts.DDP else 40
    fast = solver(max_iter=max_iter, tol=1e-6).solve(problem, x0)
    monkeypatch.setenv("TORCHSLQ_CODEGEN", "0")
    problem_t, _ = _swingup(UserCartPole())
    slow = solver(max_iter=max_iter, tol=1e-6).solve(problem_t, x0)
    if solver is ts.DDP:
        assert fast.converged.all() and slow.converged.all()
    torch.testing.assert_close(fast.cost, slow.cost, rtol=1e-9, atol=0)
    torch.testing.assert_close(fast.u, slow.u, rtol=0, atol=1e-6)
    torch.testing.assert_close(fast.iterations, slow.iterations)


def test_float32_model_solves_on_generated_code():
    problem, x0 = _swingup(UserCartPole(), dtype=torch.float32)
    res = ts.DDP(max_iter=200, tol=1e-3).solve(problem, x0)
    ref = ts.DDP(max_iter=200, tol=1e-8).solve(*_swingup(UserCartPole()))
    assert res.x.dtype == torch.float32
    torch.testing.assert_close(res.cost.double(), ref.cost, rtol=1e-3, atol=0)


def test_parameters_that_need_grad_take_the_autograd_path():
    """A learnable parameter under autograd: the kernels (which take numbers) are
    skipped and the Jacobians keep their graph to the parameter."""
    model = DampedPendulum()
    step = ts.discretize(model, 0.1)
    x = torch.tensor([[0.3, -0.2], [1.0, 0.5]], dtype=torch.float64)
    u = torch.tensor([[0.1, 0.2], [-0.4, 0.3]], dtype=torch.float64)
    A, B = ts.linearize(step, x, u, create_graph=True)
    assert A.requires_grad
    (dA,) = torch.autograd.grad(A.sum(), model.damping)
    eps = 1e-6
    with torch.no_grad():
        model.damping += eps
    Ap, _ = ts.linearize(step, x, u)  # the compiled path (no grad needed)
    with torch.no_grad():
        model.damping -= 2 * eps
    Am, _ = ts.linearize(step, x, u)
    torch.testing.assert_close(dA, (Ap.sum() - Am.sum()) / (2 * eps), rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(Ap, A.detach(), rtol=1e-5, atol=1e-5)


@pytest.fixture
def fresh_bound(monkeypatch, tmp_path):
    """torchslq._backend.bound as in a new process on a machine where no large pass has
    taken a bound kernel (its notes in ``tmp_path``)."""
    from torchslq._backend import bound

    monkeypatch.setattr(bound, "_TAKEN", set())
    monkeypatch.setattr(bound, "_NOTED", {})
    monkeypatch.setattr(bound, "_taken_file", lambda module: tmp_path / "module.taken")
    return bound


def test_kernels_given_function_values_equal_the_bound_kernels(monkeypatch, fresh_bound):
    """The RK4, rollout and fused line-search kernels called with the model's functions
    as first-class function values (compiled once per machine, cached) compute bit for bit what the
    generated module's copies with the functions bound in compute (large passes); their
    compiled signatures take function values. (Not called with the dispatchers
    themselves: a cached kernel would add a signature per process to its on-disk index,
    which numba cannot load back once those dispatchers are gone.)"""
    from torchslq._backend import _numba_kernels, _numba_search, bound, dispatch
    from torchslq.costs.quadratic import compiled_cost_evaluation
    from torchslq.dynamics import _numba_rk4
    from torchslq.dynamics.rollout import compiled_step_of, rollout, rollout_closed_loop

    step = ts.discretize(UserCartPole(), 0.05)
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(7, 3, 4, generator=gen, dtype=torch.float64)
    u = torch.randn(7, 3, 1, generator=gen, dtype=torch.float64)
    s = torch.randn(7, 3, 4, generator=gen, dtype=torch.float64)
    K = 0.1 * torch.randn(7, 3, 1, 4, generator=gen, dtype=torch.float64)
    alpha = torch.tensor([1.0, 0.5]).double()[:, None].expand(2, 7)

    # the fused line search: trials of the rollout above, a quadratic cost
    eye = torch.eye(4, dtype=torch.float64)
    cost = ts.QuadraticCost(Q=0.1 * eye, R=0.05 * torch.eye(1).double(), Qf=50 * eye)
    with torch.no_grad():
        x_nom = rollout(step, x[:, 0], u[:, :2])
        J0 = cost(x_nom, u[:, :2])
    grid = 0.5 ** torch.arange(12, dtype=torch.float64)
    slope = -torch.rand(7, generator=gen, dtype=torch.float64)
    active = torch.ones(7, dtype=torch.bool)

    def outputs():
        A, B = step.compiled_jacobians(x, u)
        H = step.compiled_vhp(x, u, s)
        xs, us = rollout_closed_loop(step, x[:, 0], x, u, K, u, alpha)
        with compiled_cost_evaluation():
            terms = cost.compiled_terms(x_nom, u[:, :2])
        search = dispatch.armijo_rollout_compiled(
            *compiled_step_of(step), x_nom, u[:, :2], K[:, :2], u[:, :2], None, None, grid,
            J0, slope, None, 1e-4, 0.0, active, terms,
        )  # fmt: skip
        return A, B, *H, xs, us, *search

    assert codegen.explain(step.continuous) == "compiled"
    as_values = outputs()
    assert bool(as_values[-3].any()) and not bool(as_values[-3].all())  # some trials pass
    for kernel in (
        _numba_rk4.rk4_lanes_kernel,
        _numba_kernels.closed_loop_rollout_kernel,
        _numba_search.armijo_rollout_kernel,
    ):
        fn_args = [
            a for sig in kernel.signatures for a in sig if isinstance(a, nb_types.FunctionType)
        ]
        assert fn_args, f"{kernel.__name__} ran without function values"
    monkeypatch.setattr(bound, "MIN_ROWS", 0)  # the generated module's own kernels
    module = bound.bound_kernels(step.continuous.compiled_rhs()[0], 1, "jacobians_kernel", "f8")
    assert module is not None
    with_bound = outputs()
    assert module.closed_loop_rollout_kernel.signatures and module.jacobians_kernel.signatures
    assert module.armijo_rollout_kernel.signatures
    for a, b in zip(as_values, with_bound, strict=True):
        assert torch.equal(a, b)


def test_inlined_model_kernels_serve_small_passes(fresh_bound):
    """``inline_model_kernels()``: a small solve (B = 1) runs the generated module's
    kernels with the model's functions inlined, which otherwise only a pass of
    ``MIN_ROWS`` rows takes, and reaches the generic kernels' solution in the same
    iterations; the previous setting comes back."""
    from torchslq.dynamics import inline_model_kernels

    bound = fresh_bound
    step = ts.discretize(UserCartPole(), 0.05)
    eye = torch.eye(4, dtype=torch.float64)
    goal = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)  # move the cart
    cost = ts.QuadraticCost(Q=0.1 * eye, R=0.05 * torch.eye(1).double(), Qf=50 * eye, x_ref=goal)
    problem = ts.Problem(step, cost, 30)
    x0 = torch.tensor([[0.0, 0.3, 0.0, 0.0]], dtype=torch.float64)
    solver = ts.ILQR(max_iter=200, tol=1e-6, progress=False)
    generic = solver.solve(problem, x0)
    assert not bound._TAKEN  # small passes: the kernels taking function values
    old = inline_model_kernels(True)
    try:
        inlined = solver.solve(problem, x0)
    finally:
        assert inline_model_kernels(old) is True
    taken = {key[1] for key in bound._TAKEN}
    assert {"jacobians_only_kernel", "armijo_rollout_kernel"} <= taken, taken
    assert bool(generic.converged.all()) and bool(inlined.converged.all())
    assert torch.equal(inlined.iterations, generic.iterations)
    torch.testing.assert_close(inlined.u, generic.u, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(inlined.cost, generic.cost, rtol=1e-12, atol=0)


def test_straight_line_jacobians_equal_the_lanes_kernel(monkeypatch, fresh_bound):
    """A generated continuous model's Jacobian-only kernel (every stage in local
    variables, the model's constant zeros left out of the chain rule) gives the lanes
    kernel's bits on finite rows, and a row with a NaN state is not finite in both."""
    from torchslq._backend import bound

    step = ts.discretize(UserCartPole(), 0.05)
    gen = torch.Generator().manual_seed(4)
    x = 3 * torch.randn(1100, 4, generator=gen, dtype=torch.float64)
    u = 5 * torch.randn(1100, 1, generator=gen, dtype=torch.float64)
    x[7, 1] = float("nan")
    x[9, 3] = float("inf")
    monkeypatch.setattr(bound, "MIN_ROWS", 10**9)  # the lanes kernel, function values
    A0, B0 = step.compiled_jacobians(x, u)
    monkeypatch.setattr(bound, "MIN_ROWS", 0)
    A1, B1 = step.compiled_jacobians(x, u)
    module = bound.bound_kernels(step.continuous.compiled_rhs()[0], 1, "jacobians_kernel", "f8")
    assert module.jacobians_only_kernel.signatures  # it ran
    fin = torch.isfinite(x).all(1)
    assert torch.equal(A1[fin], A0[fin]) and torch.equal(B1[fin], B0[fin])
    for A, B in ((A0, B0), (A1, B1)):
        bad = ~(torch.isfinite(A).flatten(1).all(1) & torch.isfinite(B).flatten(1).all(1))
        assert bad.tolist() == (~fin).tolist()
    A_ad, B_ad = torch.func.vmap(torch.func.jacrev(step, argnums=(0, 1)))(x[:3], u[:3])
    torch.testing.assert_close(A1[:3], A_ad, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(B1[:3], B_ad, rtol=1e-12, atol=1e-12)


def test_small_passes_take_the_bound_kernels_once_a_large_pass_has(monkeypatch, fresh_bound):
    """A pass under MIN_ROWS rows runs the generic kernels until a large pass has taken
    the generated module's kernel for that dtype (then compiled), in this process or,
    by the note it leaves beside the module, in an earlier one; per kernel and dtype.
    A B = 1 solve after a B = 64 one takes them and gives the same controls."""
    from torchslq._backend import model_fns

    bound = fresh_bound
    step = ts.discretize(UserCartPole(), 0.05)
    rhs = step.continuous.compiled_rhs()[0]
    small, large = bound.MIN_ROWS - 1, bound.MIN_ROWS
    assert bound.bound_kernels(rhs, small, "jacobians_kernel", np.float64) is None
    module = bound.bound_kernels(rhs, large, "jacobians_kernel", np.float64)
    assert module is not None
    assert bound.bound_kernels(rhs, small, "jacobians_kernel", np.float64) is module
    assert bound.bound_kernels(rhs, small, "jacobians_kernel", np.float32) is None
    assert bound.bound_kernels(rhs, small, "armijo_rollout_kernel", np.float64) is None
    assert bound.bound_kernels(rhs.py_func, large, "jacobians_kernel", np.float64) is None
    # a later process: the note beside the module says the kernel is compiled and cached
    monkeypatch.setattr(bound, "_TAKEN", set())
    monkeypatch.setattr(bound, "_NOTED", {})
    assert bound.bound_kernels(rhs, small, "jacobians_kernel", np.float64) is module
    assert bound.bound_kernels(rhs, small, "jacobians_kernel", np.float32) is None
    assert bound.bound_kernels(rhs, small, "armijo_rollout_kernel", np.float64) is None

    monkeypatch.setattr(bound, "_TAKEN", set())
    monkeypatch.setattr(bound, "_NOTED", {})
    bound._taken_file(module).unlink()
    eye = torch.eye(4, dtype=torch.float64)
    problem = ts.Problem(
        step.double(), ts.QuadraticCost(Q=0.1 * eye, R=0.1 * eye[:1, :1], Qf=10 * eye), 30
    )
    x0 = torch.zeros(64, 4, dtype=torch.float64)
    x0[:, 1] = torch.linspace(-0.5, 0.5, 64, dtype=torch.float64)
    solver = ts.ILQR(max_iter=30, tol=1e-9, progress=False)
    generic = solver.solve(problem, x0[:1])  # 30 rows: the generic kernels
    kernel, fns = model_fns.rollout_kernel(
        "closed_loop_rollout_kernel", step.compiled_step()[0], np.float64, np.float64, 30
    )
    assert fns and kernel is not module.closed_loop_rollout_kernel
    solver.solve(problem, x0)  # 64 x 30 rows: the module's kernels
    kernel, fns = model_fns.rollout_kernel(
        "closed_loop_rollout_kernel", step.compiled_step()[0], np.float64, np.float64, 30
    )
    assert kernel is module.closed_loop_rollout_kernel and len(fns) == 1
    again = solver.solve(problem, x0[:1])
    assert torch.equal(generic.u, again.u) and torch.equal(generic.x, again.x)


class UserUnicycle(ts.Dynamics):
    """A discrete model written by a user: its step is compiled, with its derivatives."""

    state_dim, control_dim = 3, 2

    def __init__(self, dt=0.1):
        super().__init__()
        self.dt = dt

    def forward(self, x, u):
        th = x[..., 2]
        v, w = u[..., 0] * self.dt, u[..., 1] * self.dt
        return torch.stack(
            [x[..., 0] + torch.cos(th) * v, x[..., 1] + torch.sin(th) * v, th + w], -1
        )


def test_discrete_model_step_and_derivatives_equal_torch_func():
    from torchslq.dynamics.linearize import dynamics_vhp
    from torchslq.dynamics.rollout import rollout

    model = UserUnicycle()
    assert codegen.explain(model) == "compiled"
    gen = torch.Generator().manual_seed(4)
    x = torch.randn(6, 3, generator=gen, dtype=torch.float64)
    u = torch.randn(6, 2, generator=gen, dtype=torch.float64)
    s = torch.randn(6, 3, generator=gen, dtype=torch.float64)

    def f(a, b):  # the torch form, out of codegen's reach
        return model.forward(a, b)

    A, B = model.compiled_jacobians(x, u)
    Ar, Br = torch.func.vmap(torch.func.jacrev(f, argnums=(0, 1)))(x, u)
    torch.testing.assert_close(A, Ar, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(B, Br, rtol=1e-13, atol=1e-13)
    for got, want in zip(model.compiled_vhp(x, u, s), dynamics_vhp(f, x, u, s), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    us = torch.randn(6, 9, 2, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(rollout(model, x, us), rollout(f, x, us), rtol=1e-13, atol=1e-13)
    # a model with a changed attribute is generated again (its step reads dt as a number)
    model.dt = 0.2
    torch.testing.assert_close(rollout(model, x, us), rollout(f, x, us), rtol=1e-13, atol=1e-13)


def test_discrete_model_ddp_solve_equals_the_torch_path(monkeypatch):
    cost = ts.QuadraticCost(0.1 * torch.eye(3, dtype=torch.float64), torch.eye(2, dtype=torch.float64),
                            Qf=50 * torch.eye(3, dtype=torch.float64),
                            x_ref=torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64))  # fmt: skip
    x0 = torch.tensor([[0.0, 0.0, 0.3], [0.2, -0.5, -1.0]], dtype=torch.float64)
    fast = ts.DDP(max_iter=100, tol=1e-8).solve(ts.Problem(UserUnicycle(), cost, 20), x0)
    monkeypatch.setenv("TORCHSLQ_CODEGEN", "0")
    slow = ts.DDP(max_iter=100, tol=1e-8).solve(ts.Problem(UserUnicycle(), cost, 20), x0)
    assert fast.converged.all() and slow.converged.all()
    torch.testing.assert_close(fast.cost, slow.cost, rtol=1e-10, atol=0)
    torch.testing.assert_close(fast.u, slow.u, rtol=0, atol=1e-7)


class FloatBranch(ts.ContinuousDynamics):
    """A float attribute in Python control flow: traced as a constant (not an input)."""

    state_dim, control_dim = 1, 1

    def __init__(self, k):
        super().__init__()
        self.k = k

    def forward(self, x, u, t=None):
        if self.k > 0:
            return -self.k * x + u
        return torch.sin(x) + u


def test_float_attributes_are_inputs_unless_they_steer_control_flow():
    from torchslq.systems import CartPole

    a, b = CartPole(mc=1.0), CartPole(mc=2.5, l=0.3)
    ha, hb = codegen.generated_hooks(a), codegen.generated_hooks(b)
    assert ha.source_path == hb.source_path and "@mc" in ha.tensor_names  # one module
    x = torch.tensor([[0.1, 0.7, -0.2, 0.4]], dtype=torch.float64)
    u = torch.tensor([[0.3]], dtype=torch.float64)
    for model in (a, b):
        rhs, p = model.compiled_rhs()
        out = np.zeros(4)
        rhs(x[0].numpy(), u[0].numpy(), p, out)
        np.testing.assert_allclose(out, model(x, u)[0].detach().numpy(), rtol=1e-13)

    model = FloatBranch(2.0)
    x1, u1 = torch.tensor([[0.5]], dtype=torch.float64), torch.tensor([[0.1]], dtype=torch.float64)
    for k in (2.0, 3.0, -1.0):  # each value its own constants (and branch)
        model.k = k
        assert codegen.explain(model) == "compiled"
        rhs, p = model.compiled_rhs()
        out = np.zeros(1)
        rhs(x1[0].numpy(), u1[0].numpy(), p, out)
        np.testing.assert_allclose(out, model(x1, u1)[0].numpy(), rtol=1e-13)


def test_discretized_forward_called_from_python_runs_the_compiled_step(monkeypatch):
    """A discretised model called directly (e.g. inside a user's own model, a learned
    residual on the step) runs the generated step in one kernel call without autograd;
    with autograd, the torch ops (and the graph)."""
    step = ts.discretize(UserCartPole(), 0.05)
    gen = torch.Generator().manual_seed(6)
    x = torch.randn(3, 5, 4, generator=gen, dtype=torch.float64)
    u = torch.randn(5, 1, generator=gen, dtype=torch.float64)  # broadcast against x
    with torch.no_grad():
        fast = step(x, u)
    xg = x.clone().requires_grad_(True)
    slow = step(xg, u)  # autograd: the torch path
    assert slow.grad_fn is not None and fast.grad_fn is None
    torch.testing.assert_close(fast, slow.detach(), rtol=1e-13, atol=1e-13)
    from torchslq._backend import dispatch

    calls = []
    original = dispatch._launch

    def counting(kernel, *args):
        calls.append(kernel.__name__)
        return original(kernel, *args)

    monkeypatch.setattr(dispatch, "_launch", counting)
    with torch.no_grad():
        step(x, u)
    assert calls == ["step_rows_kernel"]


class ResidualOnStep(ts.Dynamics):
    """A learned residual on a discretised model: too many parameters to be generated
    itself, so it is linearised by autograd, where its inner step stands in by its
    compiled Jacobians."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.step = ts.discretize(UserCartPole(), 0.05)
        torch.manual_seed(4)
        self.net = nn.Sequential(nn.Linear(5, 32), nn.Tanh(), nn.Linear(32, 4)).double()

    def forward(self, x, u):
        return self.step(x, u) + 0.1 * self.net(torch.cat([x, u], -1))


def _count_standins(monkeypatch, name: str) -> list[bool]:
    """Whether each call of the stand-in ``name`` of DiscretizedDynamics applied."""
    calls: list[bool] = []
    original = getattr(ts.DiscretizedDynamics, name)

    def counting(self, *args):
        out = original(self, *args)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(ts.DiscretizedDynamics, name, counting)
    return calls


def _without_graph_path(monkeypatch) -> None:
    """Learned models' Jacobians by autograd (not by their traced graph)."""
    import importlib

    linearize_module = importlib.import_module("torchslq.dynamics.linearize")
    monkeypatch.setattr(linearize_module, "graph_jacobians", lambda *args: None)


def _without_generated_jacobians(monkeypatch) -> None:
    """Learned models' Jacobians not by their generated reverse sweep
    (:mod:`torchslq.dynamics.network_reverse`)."""
    from torchslq.dynamics import network_codegen

    monkeypatch.setattr(network_codegen, "network_jacobians", lambda *args: None)


@pytest.mark.network_derivatives
@pytest.mark.parametrize("path", ["generated", "graph", "autograd"])
def test_a_generated_step_inside_a_model_enters_its_jacobians_by_its_kernels(monkeypatch, path):
    """By the model's generated Jacobians or its traced graph (the step's Jacobians from
    its kernels in both) or, where neither applies, by autograd with the step standing
    in by its kernels."""
    model = ResidualOnStep()
    gen = torch.Generator().manual_seed(12)
    x = torch.randn(3, 7, 4, generator=gen, dtype=torch.float64)
    u = torch.randn(3, 7, 1, generator=gen, dtype=torch.float64)
    if path != "generated":
        _without_generated_jacobians(monkeypatch)
    if path == "autograd":
        _without_graph_path(monkeypatch)
    model.compiled_step()  # written first: its writing evaluates the step's Jacobians once
    calls = _count_standins(monkeypatch, "linear_standin")
    kernels = _count_standins(monkeypatch, "compiled_jacobians")
    A, B = ts.linearize(model, x, u)
    # the step entered once, by its kernels
    assert (kernels, calls) == (([True], [True]) if path == "autograd" else ([True], []))
    graph = path != "autograd"
    # torch.func's pullback of the whole model (the step on its torch ops)
    Ar, Br = ts.linearize(model, x, u, method="vjp")
    assert calls == ([] if graph else [True])
    torch.testing.assert_close(A, Ar, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(B, Br, rtol=1e-12, atol=1e-12)
    # and central differences
    h = 1e-6
    with torch.no_grad():
        for j in range(4):
            e = torch.zeros(4, dtype=torch.float64)
            e[j] = h
            fd = (model(x + e, u) - model(x - e, u)) / (2 * h)
            torch.testing.assert_close(A[..., j], fd, rtol=1e-7, atol=1e-8)
        fd = (model(x, u + h) - model(x, u - h)) / (2 * h)
        torch.testing.assert_close(B[..., 0], fd, rtol=1e-7, atol=1e-8)
    # graphs through the Jacobians keep the torch ops
    A2, _ = ts.linearize(model, x, u, create_graph=True)
    assert A2.requires_grad and calls == ([] if graph else [True])


@pytest.mark.parametrize("graph", [True, False], ids=["graph", "autograd"])
def test_a_generated_step_inside_a_model_in_a_large_batch(monkeypatch, graph):
    """The graph path in blocks of rows, and the autograd pass in a batch large enough
    to pull back one output at a time, against torch.func's per-row Jacobians of the
    whole model."""
    from torchslq.dynamics.linearize import POOL_ELEMENTS, _one_at_a_time

    if not graph:
        _without_graph_path(monkeypatch)
    model = ResidualOnStep()
    half = POOL_ELEMENTS // 64 + 5  # rows x width 32 (the network's layers) past it
    assert _one_at_a_time(2 * half, 32)
    gen = torch.Generator().manual_seed(14)
    x = torch.randn(2, half, 4, generator=gen, dtype=torch.float64)
    u = torch.randn(2, half, 1, generator=gen, dtype=torch.float64)
    A, B = ts.linearize(model, x, u)
    Ar, Br = ts.linearize(model, x, u, method="jacrev")
    torch.testing.assert_close(A, Ar, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(B, Br, rtol=1e-12, atol=1e-12)


def _without_quadratic_standin(monkeypatch):
    """The step's torch ops instead of its Taylor expansion (the independent path)."""
    monkeypatch.setattr(ts.DiscretizedDynamics, "quadratic_standin", lambda self, x, u: None)


def test_a_generated_step_inside_a_model_enters_its_hessians_by_its_kernels(monkeypatch):
    model = ResidualOnStep()
    gen = torch.Generator().manual_seed(13)
    x = torch.randn(3, 7, 4, generator=gen, dtype=torch.float64)
    u = torch.randn(3, 7, 1, generator=gen, dtype=torch.float64)
    s = torch.randn(3, 7, 4, generator=gen, dtype=torch.float64)
    calls = _count_standins(monkeypatch, "quadratic_standin")
    H = dynamics_hessians(model, x, u)
    V = dynamics_vhp(model, x, u, s)
    assert calls == [True, True]  # one model call per pass, the step by its kernels
    _without_quadratic_standin(monkeypatch)
    Hr = dynamics_hessians(model, x, u)  # the RK4 stages' torch ops, twice differentiated
    Vr = dynamics_vhp(model, x, u, s)
    for got, ref in zip((*H, *V), (*Hr, *Vr), strict=True):
        assert got.shape == ref.shape
        torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-12)
    # and central differences of the Jacobians
    h = 1e-5
    z = torch.cat([x, u], -1)
    for j in range(5):
        e = torch.zeros(5, dtype=torch.float64)
        e[j] = h
        Ap, Bp = ts.linearize(model, *(z + e).split([4, 1], -1))
        Am, Bm = ts.linearize(model, *(z - e).split([4, 1], -1))
        fd = (torch.cat([Ap, Bp], -1) - torch.cat([Am, Bm], -1)) / (2 * h)  # (3, 7, 4, 5)
        col = (
            torch.cat([H[0][..., j], H[2][..., j]], -1)
            if j < 4
            else torch.cat([H[2][..., 0, :], H[1][..., 0, :]], -1)
        )  # d/dz_j of row i of [A | B], the output index first
        torch.testing.assert_close(col, fd.movedim(-2, 0), rtol=1e-6, atol=1e-7)


def test_ddp_on_a_model_with_a_generated_step_matches_its_torch_ops(monkeypatch):
    """DDP's value mode takes every output's Hessian at every node: with the inner step
    entering by its Taylor expansion, the iterates are those of the torch-ops path."""
    problem = ts.Problem(
        ResidualOnStep(),
        ts.QuadraticCost(
            Q=torch.zeros(4, 4, dtype=torch.float64),
            R=0.02 * torch.eye(1, dtype=torch.float64),
            Qf=200 * torch.eye(4, dtype=torch.float64),
            x_ref=torch.tensor([0.0, math.pi, 0.0, 0.0], dtype=torch.float64),
        ),
        horizon=20,
    )
    x0 = torch.zeros(2, 4, dtype=torch.float64)
    x0[:, 1] = torch.tensor([0.1, -0.2], dtype=torch.float64)
    solver = ts.DDP(max_iter=6, tol=1e-14, progress=False)
    r = solver.solve(problem, x0)
    _without_quadratic_standin(monkeypatch)
    rr = solver.solve(problem, x0)
    assert int(r.iterations.min()) == 6
    torch.testing.assert_close(r.u, rr.u, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(r.cost, rr.cost, rtol=1e-11, atol=0.0)


class UserPendulum(ts.ContinuousDynamics):
    state_dim, control_dim = 2, 1

    def forward(self, x, u, t=None):
        return torch.stack([x[..., 1], -9.81 * torch.sin(x[..., 0]) + u[..., 0]], -1)


class WrappedStep(ts.Dynamics):
    """A user's discrete model around a discretised one (small enough to be generated
    itself): building its code calls the inner model's, which is built in turn. (A
    pendulum: the cart-pole's RK4 step took 15-35 s of symbolic second derivatives.)"""

    state_dim, control_dim = 2, 1

    def __init__(self):
        super().__init__()
        self.inner = ts.discretize(UserPendulum(), 0.05)

    def forward(self, x, u):
        return self.inner(x, u) + 0.01 * torch.tanh(x)


def test_a_model_wrapping_a_generated_model_is_generated_too(monkeypatch):
    import threading

    # a busy machine must not turn this into a symbolic time-out (kept for its budget)
    monkeypatch.setenv("TORCHSLQ_CODEGEN_BUDGET", "600")
    model = WrappedStep()
    result = {}
    worker = threading.Thread(target=lambda: result.update(why=codegen.explain(model)))
    worker.start()
    worker.join(timeout=240)  # a non-reentrant lock used to deadlock here
    assert not worker.is_alive() and result["why"] == "compiled"
    x = torch.randn(5, 2, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    u = torch.randn(5, 1, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    A, B = model.compiled_jacobians(x, u)
    Ar, Br = torch.func.vmap(torch.func.jacrev(lambda a, b: model.forward(a, b), argnums=(0, 1)))(
        x, u
    )
    torch.testing.assert_close(A, Ar, rtol=1e-11, atol=1e-12)
    torch.testing.assert_close(B, Br, rtol=1e-11, atol=1e-12)


class OwnJacobians(UserCartPole):
    """A user's analytic Jacobians (here deliberately scaled): they are what the model is
    linearised with, not the generated ones; its rollouts still run generated code."""

    calls = 0

    def jacobians(self, x, u, t=None):
        OwnJacobians.calls += 1
        n = x.shape[-1]
        z = torch.cat([x, u], -1)
        J = torch.func.vmap(torch.func.jacrev(lambda r: UserCartPole.forward(self, r[:n], r[n:])))(
            z.reshape(-1, z.shape[-1])
        )
        J = 2.0 * J.reshape(*z.shape[:-1], n, z.shape[-1])
        return J[..., :n], J[..., n:]


def test_a_models_own_analytic_jacobians_override_the_generated_ones():
    model = OwnJacobians()
    assert model.compiled_rhs() is not None and model.compiled_derivatives() is None
    step = ts.discretize(model, 0.05)
    x = torch.tensor([[0.1, 0.5, -0.2, 0.3]], dtype=torch.float64)
    u = torch.tensor([[0.4]], dtype=torch.float64)
    before = OwnJacobians.calls
    A, B = ts.linearize(step, x, u)
    assert OwnJacobians.calls == before + 4  # chained through the four RK4 stages
    A0, B0 = ts.linearize(ts.discretize(UserCartPole(), 0.05), x, u)
    assert not torch.allclose(B, B0, rtol=1e-3)  # the scaled analytic Jacobians were used


class CachedElsewhere(ts.ContinuousDynamics):
    """A model of its own (a module no other test loads)."""

    state_dim, control_dim = 2, 1

    def forward(self, x, u, t=None):
        return torch.stack([x[..., 1], -2.5 * torch.sin(x[..., 0]) + 0.7 * u[..., 0]], -1)


def test_a_cached_file_from_another_library_version_is_generated_again(tmp_path, monkeypatch):
    """A cache directory shared by several versions of the library: a file named like
    this version's module but lacking a kernel (another version's generator) is
    regenerated, not served; and another generator names its files differently."""
    import sys

    monkeypatch.setenv("TORCHSLQ_CACHE_DIR", str(tmp_path))
    first = codegen.generated_hooks(CachedElsewhere())
    path = first.source_path
    text = open(path).read()
    assert "def derivatives(" in text
    with open(path, "w") as f:  # as another generator wrote it: no `derivatives`
        f.write(text.replace("def derivatives(", "def derivatives_of_another_kind("))
    name = next(k for k, v in sys.modules.items() if getattr(v, "__file__", None) == path)
    monkeypatch.delitem(sys.modules, name)  # as in a new process

    step = ts.discretize(CachedElsewhere(), 0.05)
    x = torch.randn(6, 2, dtype=torch.float64)
    u = torch.randn(6, 1, dtype=torch.float64)
    with torch.no_grad():
        got = step(x, u)
    assert "def derivatives(" in open(path).read()
    want = step(x.requires_grad_(True), u).detach()  # the torch RK4 step
    torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-13)

    monkeypatch.setattr(codegen, "_SOURCES_DIGEST", [b"another generator"])
    other = codegen.generated_hooks(CachedElsewhere())
    assert other.source_path != path


def test_a_time_out_is_kept_for_its_budget_only(tmp_path, monkeypatch):
    """A model whose symbolic derivatives ran out of the budget is declined, and the
    verdict kept on disk answers later processes with that budget without trying again;
    a larger budget (a quieter machine, a patient user) tries again and generates it."""
    monkeypatch.setenv("TORCHSLQ_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("TORCHSLQ_CODEGEN_BUDGET", "0")
    assert codegen.explain(CachedElsewhere()).startswith("its symbolic second derivatives took")
    assert list(tmp_path.rglob("*.unsupported"))
    tries = []
    generate = codegen._generate
    monkeypatch.setattr(codegen, "_generate", lambda *a: tries.append(1) or generate(*a))
    assert "took over 0 s" in codegen.explain(CachedElsewhere())  # a new instance: from disk
    assert tries == []
    monkeypatch.setenv("TORCHSLQ_CODEGEN_BUDGET", "600")
    assert codegen.explain(CachedElsewhere()) == "compiled"
    assert tries == [1]


def _helper_module(tmp_path, name: str, body: str):
    """A module file ``name.py`` in ``tmp_path`` (on sys.path), imported afresh."""
    import importlib
    import sys

    (tmp_path / f"{name}.py").write_text(body)
    if str(tmp_path) not in sys.path:
        sys.path.insert(0, str(tmp_path))
    sys.modules.pop(name, None)
    importlib.invalidate_caches()
    return importlib.import_module(name)


def test_a_warm_cache_serves_an_equal_model_without_tracing(tmp_path, monkeypatch):
    """The second model of a class (another process, in effect: the per-instance memo is
    bypassed) finds its code through the source index, without the trace that imports
    torch's compiler stack; its functions equal the forward."""
    monkeypatch.setenv("TORCHSLQ_CACHE_DIR", str(tmp_path / "cache"))
    mod = _helper_module(
        tmp_path,
        "src_index_model",
        "import torch\nimport torchslq as ts\n\n"
        "class Damped(ts.ContinuousDynamics):\n"
        "    state_dim, control_dim = 2, 1\n"
        "    def __init__(self, c=0.3):\n"
        "        super().__init__()\n"
        "        self.c = c\n"
        "    def forward(self, x, u, t=None):\n"
        "        return torch.stack([x[..., 1], u[..., 0] - self.c * x[..., 1]"
        " - torch.sin(x[..., 0])], -1)\n",
    )
    first = codegen.generated_hooks(mod.Damped())
    assert first is not None
    traced = []
    original = codegen._trace
    monkeypatch.setattr(codegen, "_trace", lambda *a: traced.append(1) or original(*a))
    second = mod.Damped(c=0.7)  # another value of a float attribute: the same code
    hooks = codegen.generated_hooks(second)
    assert traced == [] and hooks.source_path == first.source_path
    x, u = np.array([0.4, -0.2]), np.array([0.5])
    out = np.zeros(2)
    hooks.rhs(x, u, hooks.params(second), out)
    want = second(torch.tensor(x), torch.tensor(u)).numpy()
    np.testing.assert_allclose(out, want, rtol=1e-14)


def test_a_changed_helper_in_another_file_is_traced_again(tmp_path, monkeypatch):
    """The source index keys on the model's own class files: a function it calls from
    elsewhere that changed is caught by the numeric check, and the model is traced."""
    monkeypatch.setenv("TORCHSLQ_CACHE_DIR", str(tmp_path / "cache"))
    helper = _helper_module(tmp_path, "src_index_helper", "def k():\n    return 2.0\n")
    mod = _helper_module(
        tmp_path,
        "src_index_user",
        "import torch\nimport torchslq as ts\nimport src_index_helper\n\n"
        "class UsesHelper(ts.ContinuousDynamics):\n"
        "    state_dim, control_dim = 1, 1\n"
        "    def forward(self, x, u, t=None):\n"
        "        return -src_index_helper.k() * x + u\n",
    )
    first = codegen.generated_hooks(mod.UsesHelper())
    helper.k = lambda: 5.0  # the helper changes, the model's file does not
    traced = []
    original = codegen._trace
    monkeypatch.setattr(codegen, "_trace", lambda *a: traced.append(1) or original(*a))
    model = mod.UsesHelper()
    hooks = codegen.generated_hooks(model)
    assert traced == [1] and hooks.source_path != first.source_path
    out = np.zeros(1)
    hooks.rhs(np.array([1.0]), np.array([0.0]), hooks.params(model), out)
    assert out[0] == pytest.approx(-5.0)


class CaughtBranch(ts.ContinuousDynamics):
    """A branch on the values whose failure to trace the forward itself catches."""

    state_dim, control_dim = 1, 1

    def forward(self, x, u, t=None):
        try:
            positive = bool((x > 0).all())
        except Exception:
            positive = False
        return -x + u if positive else x + u


class ItemScale(ts.ContinuousDynamics):
    state_dim, control_dim = 1, 1

    def forward(self, x, u, t=None):
        return x / (1.0 + x.abs().max().item()) + u  # a number read from the state


class EqualBranch(ts.ContinuousDynamics):
    state_dim, control_dim = 1, 1

    def forward(self, x, u, t=None):
        return -x + u if torch.equal(x, torch.zeros_like(x)) else x + u


@pytest.mark.parametrize("model_cls", [ValueBranch, CaughtBranch, ItemScale, EqualBranch])
def test_data_dependent_control_flow_is_rejected_not_traced_as_one_branch(model_cls, monkeypatch):
    """The trace runs forward on zeros: a branch or number read from the values would
    hold the zeros' branch. Each model keeps the torch path: its solve equals the one
    with code generation off."""
    model = model_cls()
    why = codegen.explain(model)
    assert "could not be traced" in why and "DataDependent" in why
    assert model.compiled_rhs() is None
    cost = ts.QuadraticCost(torch.eye(1, dtype=torch.float64), torch.eye(1, dtype=torch.float64))
    x0 = torch.tensor([[1.0], [-0.5]], dtype=torch.float64)
    res = ts.ILQR(max_iter=3).solve(ts.Problem(ts.discretize(model, 0.1), cost, 5), x0)
    monkeypatch.setenv("TORCHSLQ_CODEGEN", "0")
    ref = ts.ILQR(max_iter=3).solve(ts.Problem(ts.discretize(model_cls(), 0.1), cost, 5), x0)
    assert torch.equal(res.u, ref.u) and torch.equal(res.x, ref.x)
    assert not torch.equal(res.x[:, 1:], res.x[:, :-1])  # the states move


def test_the_traced_graph_is_functional_aten_ops_with_constants_as_get_attr():
    from torchslq.dynamics._trace import Untraceable, trace

    K = torch.tensor([2.0, -1.0], dtype=torch.float64)

    def fn(x, u):
        out = torch.zeros_like(x)
        out[..., 0] = x[..., 1] * K[0]  # an in-place write through a view
        out[:, 1:] += u
        return out.t().contiguous()

    x, u = torch.randn(2, 2, dtype=torch.float64), torch.randn(2, 1, dtype=torch.float64)
    gm = trace(fn, x, u)
    calls = [node for node in gm.graph.nodes if node.op == "call_function"]
    assert calls and all(isinstance(node.target, torch._ops.OpOverload) for node in calls)
    assert any(node.target.__name__.startswith("select_copy") for node in calls)
    for node in calls:  # no mutation; a view only of a constant (of the rest: *_copy ops)
        assert not node.target._schema.is_mutable, node.target
        if any(r.alias_info is not None for r in node.target._schema.returns):
            assert node.args[0].op == "get_attr", node.target
    consts = [getattr(gm, n.target) for n in gm.graph.nodes if n.op == "get_attr"]
    assert len(consts) == 1 and torch.equal(consts[0], K)
    assert [n.op for n in gm.graph.nodes].count("placeholder") == 2
    torch.testing.assert_close(gm(x, u), fn(x, u), rtol=0, atol=0)

    def writes_a_captured_tensor(x, u):
        K.mul_(2.0)  # a tensor functionalization does not own: refused before it runs
        return x

    with pytest.raises(Untraceable, match="in-place"):
        trace(writes_a_captured_tensor, x, u)
    assert torch.equal(K, torch.tensor([2.0, -1.0], dtype=torch.float64))


def test_a_cold_build_and_solve_import_no_compiler_stack(tmp_path):
    """Tracing, generating and checking a model's code in a fresh process with an empty
    cache, and solving on it, import neither torch._dynamo nor torch._inductor (over a
    second of imports, which torch's make_fx and fake tensors pay)."""
    import json
    import os
    import subprocess
    import sys

    script = tmp_path / "cold.py"
    script.write_text(
        "import json, sys\n"
        "import torch\n"
        "import torchslq as ts\n"
        "from torchslq.dynamics import codegen\n"
        "\n"
        "class Pendulum(ts.ContinuousDynamics):\n"
        "    state_dim, control_dim = 2, 1\n"
        "    def forward(self, x, u, t=None):\n"
        "        out = torch.zeros_like(x)\n"
        "        out[..., 0] = x[..., 1]\n"
        "        out[..., 1] = -9.81 * torch.sin(x[..., 0]) + u[..., 0]\n"
        "        return out\n"
        "\n"
        "def loaded():\n"
        "    return [k for k in ('torch._dynamo', 'torch._inductor') if k in sys.modules]\n"
        "\n"
        "model = Pendulum()\n"
        "before = loaded()\n"
        "why = codegen.explain(model)\n"
        "after_build = loaded()\n"
        "f64 = torch.float64\n"
        "cost = ts.QuadraticCost(torch.eye(2, dtype=f64), torch.eye(1, dtype=f64))\n"
        "problem = ts.Problem(ts.discretize(model, 0.05), cost, 10)\n"
        "res = ts.ILQR(max_iter=3).solve(problem, torch.ones(2, 2, dtype=f64))\n"
        "print(json.dumps(dict(why=why, before=before, after_build=after_build,\n"
        "                      after_solve=loaded(), finite=bool(torch.isfinite(res.cost).all()))))\n"
    )
    cache = tmp_path / "cache"
    env = dict(os.environ, TORCHSLQ_CACHE_DIR=str(cache), TORCHSLQ_CODEGEN="1")
    out = subprocess.run(
        [sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["why"] == "compiled" and got["finite"]
    assert list(cache.glob("generated_v*/m_*.checked"))  # traced, generated and checked here
    assert got["before"] == [] and got["after_build"] == [], got
    assert got["after_solve"] == [], got


def test_a_model_first_built_in_inference_mode_is_compiled(tmp_path, monkeypatch):
    """The build's check differentiates the forward by autograd, which records nothing
    in inference mode: it runs outside it."""
    monkeypatch.setenv("TORCHSLQ_CACHE_DIR", str(tmp_path / "cache"))  # traced and checked here
    model = DampedPendulum()
    with torch.inference_mode():
        assert codegen.explain(model) == "compiled"
    assert list((tmp_path / "cache").glob("generated_v*/m_*.checked"))


def test_a_solve_looks_up_a_models_generated_code_once(monkeypatch):
    """Inside hooks_pinned (a solver's loop) a model's structure is checked once, not at
    every lookup (three per iLQR iteration); outside it a change is seen again."""
    from torchslq.systems import CartPole

    calls = []
    real = codegen._structure_key
    monkeypatch.setattr(codegen, "_structure_key", lambda m: calls.append(1) or real(m))
    dyn = ts.discretize(CartPole(), 0.05, "rk4").double()
    cost = ts.QuadraticCost(
        Q=torch.zeros(4, 4, dtype=torch.float64),
        R=0.1 * torch.eye(1, dtype=torch.float64),
        Qf=10 * torch.eye(4, dtype=torch.float64),
    )
    x0 = torch.tensor([[0.0, 0.3, 0.0, 0.0]], dtype=torch.float64)
    problem = ts.Problem(dyn, cost, 20)
    r = ts.ILQR(max_iter=30, progress=False).solve(problem, x0)
    pinned = len(calls)  # (one lookup before the loop's block)
    calls.clear()
    monkeypatch.setattr(codegen, "hooks_pinned", contextlib.nullcontext)
    r_unpinned = ts.ILQR(max_iter=30, progress=False).solve(problem, x0)
    assert torch.equal(r.u, r_unpinned.u)
    assert int(r.iterations.max()) >= 3 and pinned <= 2
    assert len(calls) >= 3 * int(r.iterations.max())
    monkeypatch.undo()

    model = FloatBranch(2.0)  # a float attribute traced as a constant
    with codegen.hooks_pinned():
        h2 = codegen.generated_hooks(model)
        model.k = 3.0
        assert codegen.generated_hooks(model) is h2  # pinned: not looked at again
    h3 = codegen.generated_hooks(model)  # outside: the change is seen
    assert h3 is not h2
    x1, u1 = torch.tensor([[0.5]], dtype=torch.float64), torch.tensor([[0.1]], dtype=torch.float64)
    rhs, p = model.compiled_rhs()
    out = np.zeros(1)
    rhs(x1[0].numpy(), u1[0].numpy(), p, out)
    np.testing.assert_allclose(out, model(x1, u1)[0].numpy(), rtol=1e-13)


def test_the_line_limit_counts_what_a_first_solve_compiles(tmp_path, monkeypatch):
    """MAX_GENERATED_LINES bounds the model's own two functions (a first solve compiles
    them); the fused ``rhs_derivatives`` that large passes compile is not counted, so it
    does not halve the size of the models the generator takes."""
    monkeypatch.setenv("TORCHSLQ_CACHE_DIR", str(tmp_path / "full"))
    text = open(codegen.generated_hooks(CachedElsewhere()).source_path).read().splitlines()
    fused = text.index("def rhs_derivatives(x, u, p, out, fz, H):")
    own = fused - 3  # the lines before the blank lines and decorator of the fused one
    assert "def derivatives(x, u, p, fz, H):" in text[:own]
    for limit, verdict in ((own, "compiled"), (own - 1, "lines of generated code")):
        monkeypatch.setattr(codegen, "MAX_GENERATED_LINES", limit)
        monkeypatch.setenv("TORCHSLQ_CACHE_DIR", str(tmp_path / str(limit)))
        assert verdict in codegen.explain(CachedElsewhere())
