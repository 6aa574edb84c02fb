"""A learned model's compiled step written from its traced graph
(torchslq.dynamics.network_codegen): the step against the model's own forward, rollouts
and a solve against the torch path, what it declines, and its activations against
torch's."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from test_graph_jacobian import (
    ACTIVATIONS,
    NOT_TAKEN,
    Entries,
    Features,
    GrayBox,
    PhysicsResidual,
    Scaled,
    data,
    mlp,
    reference,
    reference_hessians,
)
from torch import nn

import torchslq as ts
from torchslq._backend import step_rows_compiled
from torchslq.dynamics import _numba_net, codegen, network_codegen
from torchslq.dynamics.rollout import rollout_closed_loop
from torchslq.systems import CartPole

# (the suite's own models otherwise keep torch ops and the traced-graph derivatives)
pytestmark = [pytest.mark.codegen, pytest.mark.network_derivatives]

F64 = torch.float64


def compiled_rows(model, x, u):
    """The network step of ``model`` on every row of ``x, u`` (None without one). (Its
    ``compiled_step`` may be codegen's instead: that takes networks of up to 256
    weights.)"""
    got = network_codegen.network_step(model)
    if got is None:
        return None
    n, m = x.shape[-1], u.shape[-1]
    out = step_rows_compiled(*got, x.reshape(-1, n).contiguous(), u.reshape(-1, m).contiguous())
    return out.reshape(x.shape)


def torch_path(model):
    """The same model without compiled code (its rollouts on torch ops)."""
    model.generate_compiled_code = False
    return model


class LearnedPhysics(ts.Dynamics):
    """A residual network on a generated physics step: the compiled step calls the
    physics module's own."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.physics = ts.discretize(CartPole(), 0.05, "rk4").to(F64)
        self.net = mlp(nn.Tanh(), nn.Tanh(), k=5, out=4)
        with torch.no_grad():
            self.net[-1].weight.mul_(0.01)

    def forward(self, x, u):
        return self.physics(x, u) + self.net(torch.cat([x, u], -1))


MODELS = {
    **{
        f"learned-{name}": (lambda a=acts: ts.LearnedDynamics(mlp(*a), 4, 2), 2)
        for name, acts in ACTIVATIONS.items()
    },
    "learned-not-residual": (
        lambda: ts.LearnedDynamics(mlp(nn.Tanh()), 4, 2, residual=False),
        2,
    ),
    # widths that are not multiples of the four columns a layer's pass takes
    "learned-odd-widths": (
        lambda: ts.LearnedDynamics(
            nn.Sequential(
                nn.Linear(6, 10), nn.Tanh(), nn.Linear(10, 13), nn.Tanh(), nn.Linear(13, 4)
            ).to(F64),
            4,
            2,
        ),
        2,
    ),
    "physics-residual": (PhysicsResidual, 1),
    "learned-physics": (LearnedPhysics, 1),
    "features": (Features, 2),
    "entries": (Entries, 2),
    "gray-box": (GrayBox, 1),
}


@pytest.mark.parametrize("name", list(MODELS))
def test_compiled_step_equals_forward(name):
    make, m = MODELS[name]
    model = make()
    x, u = data(m=m, scale=1.0)
    got = compiled_rows(model, x, u)
    assert got is not None  # the step is written
    with torch.no_grad():
        ref = model(x, u)
    torch.testing.assert_close(got, ref, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize(
    "make, m",
    [*NOT_TAKEN, pytest.param(lambda: torch_path(LearnedPhysics()), 1, id="switched-off")],
)
def test_what_the_step_declines(make, m):
    assert network_codegen.network_step(make()) is None


def test_a_physics_step_without_compiled_code_is_declined():
    model = LearnedPhysics()
    model.physics.continuous.generate_compiled_code = False
    assert model.physics.compiled_step() is None
    assert network_codegen.network_step(model) is None


def test_a_model_changed_after_its_trace_is_written_again():
    model = Scaled()
    x, u = data()
    with torch.no_grad():
        torch.testing.assert_close(compiled_rows(model, x, u), model(x, u), rtol=1e-13, atol=1e-13)
        model.scale = 0.5
        model.residual = False
        got = compiled_rows(model, x, u)
        assert got is not None
        torch.testing.assert_close(got, model(x, u), rtol=1e-13, atol=1e-13)


def _too_large_for_sympy(model) -> bool:
    """Whether codegen's symbolic path declines ``model`` by its number of weights (so
    ``linearize`` reaches the network's generated derivatives; asking codegen itself
    would run its slow symbolic pass)."""
    return sum(p.numel() for p in model.parameters()) > codegen.MAX_PARAMETERS


def generated_jacobians(model, x, u):
    """The generated Jacobians' function's ``(A, B)`` at ``x, u`` (None where it does
    not apply), with nothing recording a graph."""
    with torch.no_grad():
        return network_codegen.network_jacobians(model, x, u)


class Quotient(ts.Dynamics):
    """A network's output divided by a node of the state, and a square."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.net = mlp(nn.Tanh(), nn.Tanh(), k=5, out=4)  # (more weights than codegen takes)

    def forward(self, x, u):
        return x + 0.1 * self.net(torch.cat([x, u], -1)) / (2.0 + x * x) + 0.01 * x**2


DERIVATIVE_MODELS = {**MODELS, "quotient": (Quotient, 1)}
# each compiles a function (seconds): every activation, the arithmetic, products of nodes
# and a physics submodule, slices and features, quotients of nodes
JACOBIAN_MODELS = [
    "learned-sigmoid-silu", "learned-softplus-elu", "learned-relu-leaky", "learned-gelu",
    "physics-residual", "features", "quotient",
]  # fmt: skip


@pytest.mark.parametrize("name", JACOBIAN_MODELS)
def test_generated_jacobians_equal_autodiff(name, monkeypatch):
    """The reverse sweep written beside the step gives torch.func's per-row Jacobians
    (every activation, the arithmetic, slices, stacks and a physics submodule), and
    ``linearize`` takes it: the graph path is not called."""
    import importlib

    lin = importlib.import_module("torchslq.dynamics.linearize")
    make, m = DERIVATIVE_MODELS[name]
    model = make()
    x, u = data(m=m, scale=1.0)
    got = generated_jacobians(model, x, u)
    assert got is not None  # the Jacobians are written
    A_ref, B_ref = reference(model, x, u)
    assert A_ref.shape == got[0].shape and B_ref.shape == got[1].shape
    assert B_ref.abs().max() > 1e-3
    torch.testing.assert_close(got[0], A_ref, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(got[1], B_ref, rtol=1e-12, atol=1e-13)
    if not _too_large_for_sympy(model):
        return  # linearize takes codegen's symbolic derivatives (tests/test_codegen.py)
    monkeypatch.setattr(lin, "graph_jacobians", lambda *a: pytest.fail("graph path taken"))
    A, B = ts.linearize(model, x, u)
    torch.testing.assert_close(A, A_ref, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(B, B_ref, rtol=1e-12, atol=1e-13)


# every activation's curvature, products and quotients of nodes, powers, a physics
# submodule's Hessians (each compiles a function: a few, for the suite's time)
HESSIAN_MODELS = [
    "learned-sigmoid-silu", "learned-softplus-elu", "learned-gelu", "learned-physics",
    "quotient",
]  # fmt: skip


@pytest.mark.parametrize("name", HESSIAN_MODELS)
def test_generated_hessians_equal_nested_autodiff(name, monkeypatch):
    """The forward tangents and second-order terms written beside the step give
    torch.func's per-row Jacobians and every output's Hessian (jacfwd over jacrev), and
    ``linearize_with_hessians`` (DDP's value mode) takes them: the graph path is not
    called."""
    import importlib

    lin = importlib.import_module("torchslq.dynamics.linearize")
    make, m = DERIVATIVE_MODELS[name]
    model = make()
    x, u = data(lead=(3, 5), m=m, scale=1.0)
    with torch.no_grad():
        got = network_codegen.network_hessians(model, x, u)
    assert got is not None  # the Hessians are written
    A_ref, B_ref = reference(model, x, u)
    H_ref = reference_hessians(model, x, u)
    torch.testing.assert_close(got[0], A_ref, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(got[1], B_ref, rtol=1e-12, atol=1e-13)
    assert max(float(h.abs().max()) for h in H_ref) > 1e-4  # curvature to get right
    for h, h_ref in zip(got[2], H_ref, strict=True):
        assert h.shape == h_ref.shape
        torch.testing.assert_close(h, h_ref, rtol=1e-10, atol=1e-12)
    if not _too_large_for_sympy(model):
        return  # linearize takes codegen's symbolic derivatives (tests/test_codegen.py)
    monkeypatch.setattr(lin, "graph_hessians", lambda *a: pytest.fail("graph path taken"))
    A, B, hessians = lin.linearize_with_hessians(model, x, u)
    torch.testing.assert_close(B, B_ref, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(hessians()[1], H_ref[1], rtol=1e-10, atol=1e-12)


def test_generated_jacobians_of_wide_outputs_and_float32():
    """More outputs than are unrolled (a loop over them) and a layer narrower than four;
    a float32 model's Jacobians in float32."""
    torch.manual_seed(2)
    net = nn.Sequential(nn.Linear(13, 10), nn.Tanh(), nn.Linear(10, 3), nn.Tanh(), nn.Linear(3, 11))
    model = ts.LearnedDynamics(net.to(F64), 11, 2)
    x, u = data(n=11, m=2, scale=1.0)
    got = generated_jacobians(model, x, u)
    assert got is not None
    A_ref, B_ref = reference(model, x, u)
    torch.testing.assert_close(got[0], A_ref, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(got[1], B_ref, rtol=1e-12, atol=1e-13)
    model32 = ts.LearnedDynamics(mlp(nn.Tanh(), nn.SiLU(), dtype=torch.float32), 4, 2)
    x, u = data(m=2, dtype=torch.float32, scale=1.0)
    got = generated_jacobians(model32, x, u)
    assert got is not None and got[0].dtype == torch.float32
    A_ref, B_ref = reference(model32, x, u)
    torch.testing.assert_close(got[0], A_ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got[1], B_ref, rtol=1e-5, atol=1e-6)


def test_derivatives_of_a_large_graph_are_not_written(monkeypatch):
    """A graph with more elementwise nodes than MAX_DERIVATIVE_NODES allows gets its step
    only and keeps the traced-graph pass (its derivatives still right)."""
    monkeypatch.setattr(network_codegen, "MAX_DERIVATIVE_NODES", {"jacobians": 3, "hessians": 3})
    model = ts.LearnedDynamics(mlp(nn.Tanh(), nn.Tanh()), 4, 2)  # (4 elementwise nodes)
    x, u = data(lead=(2, 3), m=2, scale=1.0)
    with torch.no_grad():
        assert network_codegen.network_step(model) is not None
        assert network_codegen.network_hessians(model, x, u) is None
        assert generated_jacobians(model, x, u) is None
    A, _, hessians = ts.dynamics.linearize_with_hessians(model, x, u)
    torch.testing.assert_close(A, reference(model, x, u)[0], rtol=1e-12, atol=1e-13)
    H_ref = reference_hessians(model, x, u)
    torch.testing.assert_close(hessians()[0], H_ref[0], rtol=1e-10, atol=1e-12)


def test_generated_jacobians_decline():
    """Not where autograd must see the parameters, nor for a model with its own
    ``jacobians``, nor off the CPU kernels' dtypes."""
    model = LearnedPhysics()
    x, u = data(m=1, scale=1.0)
    with torch.enable_grad():
        assert network_codegen.network_jacobians(model, x, u) is None  # weights need grad
    assert generated_jacobians(model, x.to(torch.float16), u.to(torch.float16)) is None

    class Own(LearnedPhysics):
        def jacobians(self, x, u):
            return ts.linearize(self.physics, x, u)

    assert generated_jacobians(Own(), x, u) is None


def test_float32_model():
    torch.manual_seed(0)
    model = ts.LearnedDynamics(mlp(nn.Tanh(), nn.SiLU(), dtype=torch.float32), 4, 2)
    x, u = data(m=2, dtype=torch.float32, scale=1.0)
    got = compiled_rows(model, x, u)
    assert got is not None and got.dtype == torch.float32
    with torch.no_grad():
        torch.testing.assert_close(got, model(x, u), rtol=1e-5, atol=1e-5)


def test_closed_loop_rollout_equals_torch_path():
    """Candidate steps, a NaN step (not rolled out) and bounds: the compiled rollout's
    states and controls are the torch path's to rounding."""
    g = torch.Generator().manual_seed(4)
    B, T, n, m = 5, 12, 4, 1
    model = LearnedPhysics()
    d = {
        "x0": 0.3 * torch.randn(3, B, n, generator=g, dtype=F64),
        "x_nom": 0.3 * torch.randn(B, T + 1, n, generator=g, dtype=F64),
        "u_nom": torch.randn(B, T, m, generator=g, dtype=F64),
        "K": 0.2 * torch.randn(B, T, m, n, generator=g, dtype=F64),
        "k": torch.randn(B, T, m, generator=g, dtype=F64),
        "alpha": torch.tensor([[1.0] * B, [0.5] * B, [0.25, float("nan"), 0.25, 0.25, 0.25]]),
        "u_min": -1.5 * torch.ones(B, T, m, dtype=F64),
        "u_max": 1.0 * torch.ones(B, T, m, dtype=F64),
    }
    d["alpha"] = d["alpha"].to(F64)
    with torch.no_grad():
        assert "256" in codegen.explain(model)  # codegen declines it: the network step
        assert model.compiled_step() is not None
        x, u = rollout_closed_loop(model, **d)
        xr, ur = rollout_closed_loop(torch_path(LearnedPhysics()), **d)
    torch.testing.assert_close(x, xr, rtol=1e-12, atol=1e-12, equal_nan=True)
    torch.testing.assert_close(u, ur, rtol=1e-12, atol=1e-12, equal_nan=True)
    assert bool(x[2, 1, 1:].isnan().all()) and bool(x[:2].isfinite().all())


@pytest.mark.parametrize("solver", ["ddp", "ilqr"])
def test_solve_equals_torch_path(solver, monkeypatch):
    """A solve of a learned model with its compiled step (the fused line search) reaches
    the torch path's solution: the same costs (to rounding) and, for DDP, the same
    iterations."""
    from torchslq.solvers import descent

    calls = []
    real = descent.armijo_rollout_compiled

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(descent, "armijo_rollout_compiled", counting)
    cost = ts.QuadraticCost(
        Q=0.1 * torch.eye(4, dtype=F64),
        R=0.01 * torch.eye(1, dtype=F64),
        Qf=10.0 * torch.eye(4, dtype=F64),
        x_ref=torch.tensor([0.0, 0.5, 0.0, 0.0], dtype=F64),
    )
    x0 = 0.1 * torch.randn(6, 4, generator=torch.Generator().manual_seed(1), dtype=F64)
    cls = {"ddp": ts.DDP, "ilqr": ts.ILQR}[solver]
    results = []
    for make in (LearnedPhysics, lambda: torch_path(LearnedPhysics())):
        problem = ts.Problem(make(), cost, 20)
        results.append(cls(max_iter=60, tol=1e-8, progress=False).solve(problem, x0))
    fast, slow = results
    assert calls  # the compiled search ran for the first solve
    assert bool(slow.converged.any())
    if solver == "ddp":  # (iLQR's slow tail crosses tol after a rounding-dependent count)
        assert fast.status.tolist() == slow.status.tolist()
        assert fast.iterations.tolist() == slow.iterations.tolist()
    torch.testing.assert_close(fast.cost, slow.cost, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(fast.u, slow.u, rtol=0.0, atol=1e-5)  # (a flat optimum)


@pytest.mark.parametrize(
    "name, fn, ref",
    [
        ("tanh", _numba_net.tanh, torch.tanh),
        ("sigmoid", _numba_net.sigmoid, torch.sigmoid),
        ("relu", _numba_net.relu, torch.relu),
        ("silu", _numba_net.silu, torch.nn.functional.silu),
        ("gelu", _numba_net.gelu, torch.nn.functional.gelu),
        ("softplus", lambda a: _numba_net.softplus(a, 2.0, 3.0), nn.Softplus(2.0, 3.0)),
        ("elu", lambda a: _numba_net.elu(a, 0.7), nn.ELU(0.7)),
        ("leaky", lambda a: _numba_net.leaky_relu(a, 0.1), nn.LeakyReLU(0.1)),
    ],
)
def test_activations_equal_torch(name, fn, ref):
    """Within a few ulp of torch's over N(0, 3^2), tiny inputs and the edges
    (infinities, NaN, where an activation switches branch)."""
    g = torch.Generator().manual_seed(0)
    a = torch.cat(
        [
            3.0 * torch.randn(2000, generator=g, dtype=F64),
            torch.logspace(-12, -1, 50, dtype=F64),
            -torch.logspace(-12, -1, 50, dtype=F64),
            torch.tensor([0.0, 0.25, -0.25, 1.5, 20.0, -20.0, 800.0, -800.0], dtype=F64),
        ]
    )
    got = torch.tensor([fn(float(v)) for v in a], dtype=F64)
    with torch.no_grad():
        want = ref(a)
    # (relative to |a| where that is larger: GELU's 1 + erf(a / sqrt 2) cancels for
    # large negative a, in torch's formula as in this one)
    ulp = torch.finfo(F64).eps * torch.maximum(want.abs(), a.abs()).clamp_min(1e-300)
    assert float(((got - want).abs() / ulp).max()) <= 4.0
    for v in (math.inf, -math.inf):
        torch.testing.assert_close(
            torch.tensor(fn(v), dtype=F64), ref(torch.tensor(v, dtype=F64)), equal_nan=True
        )
    assert math.isnan(fn(math.nan))


def test_exp_over_its_whole_range():
    """The branch-free ``exp`` (sigmoid's, SiLU's) within 2 ulp of libm's from the
    subnormal results to overflow, its edges as libm's."""
    grid = np.concatenate([np.linspace(-745.0, 709.78, 20001), [-744.5, -708.4, -1e-300, 1e-17]])
    got = np.array([_numba_net.exp(float(v)) for v in grid])
    want = np.exp(grid)
    assert float((np.abs(got - want) / np.spacing(want)).max()) <= 2.0
    assert _numba_net.exp(709.8) == math.inf and _numba_net.exp(math.inf) == math.inf
    assert _numba_net.exp(-746.0) == 0.0 and _numba_net.exp(-math.inf) == 0.0
    assert math.isnan(_numba_net.exp(math.nan))


def test_a_node_wider_than_the_stack_takes_is_allocated(monkeypatch):
    """Nodes wider than ``STACK_MAX`` are arrays of their own: the same step."""
    monkeypatch.setattr(network_codegen, "STACK_MAX", 8)
    model = ts.LearnedDynamics(mlp(nn.Tanh(), nn.Tanh()), 4, 2)
    x, u = data(m=2, scale=1.0)
    got = compiled_rows(model, x, u)
    assert got is not None
    with torch.no_grad():
        torch.testing.assert_close(got, model(x, u), rtol=1e-13, atol=1e-13)
