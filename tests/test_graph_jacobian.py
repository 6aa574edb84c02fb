"""Jacobians of learned models by their traced graph (torchslq.dynamics.graph_jacobian)
against torch.func's per-row jacrev, the cases that keep autograd, and a solve's iterates
with and without the graph path."""

from __future__ import annotations

import importlib

import pytest
import torch
import torch.nn.functional as F
from torch import nn
from torch.func import jacfwd, jacrev, vmap

import torchslq as ts
from torchslq.dynamics import _mlp, linearize, linearize_with_hessians, row_blocks
from torchslq.dynamics import graph_jacobian as gj
from torchslq.systems import CartPole

F64 = torch.float64
linearize_module = importlib.import_module("torchslq.dynamics.linearize")


def reference(model, x, u):
    """Per-row Jacobians by torch.func (no graph path: it declines inside transforms)."""
    lead = x.shape[:-1]
    xf, uf = x.reshape(-1, x.shape[-1]), u.reshape(-1, u.shape[-1])

    def one(xi, ui):
        return model(xi.unsqueeze(0), ui.unsqueeze(0)).squeeze(0)

    A, B = vmap(jacrev(one, argnums=(0, 1)))(xf, uf)
    return A.reshape(*lead, *A.shape[-2:]), B.reshape(*lead, *B.shape[-2:])


def data(lead=(6, 7), n=4, m=2, dtype=F64, scale=1.5, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = scale * torch.randn(*lead, n, generator=g, dtype=dtype)
    u = scale * torch.randn(*lead, m, generator=g, dtype=dtype)
    return x, u


def mlp(*acts, k=6, out=4, seed=0, dtype=F64) -> nn.Sequential:
    torch.manual_seed(seed)
    layers, width = [], k
    for act in acts:
        layers += [nn.Linear(width, 16), act]
        width = 16
    return nn.Sequential(*layers, nn.Linear(width, out)).to(dtype)


ACTIVATIONS = {
    "tanh": (nn.Tanh(), nn.Tanh()),
    "sigmoid-silu": (nn.Sigmoid(), nn.SiLU()),
    "softplus-elu": (nn.Softplus(beta=2.0, threshold=3.0), nn.ELU(alpha=0.7)),
    "relu-leaky": (nn.ReLU(), nn.LeakyReLU(0.1)),
    "identity": (nn.Identity(), nn.Tanh()),
    "gelu": (nn.GELU(), nn.Tanh()),
}


def assert_graph_equals_jacrev(model, x, u) -> None:
    """The graph path is taken, by itself and by ``linearize``, and both give
    torch.func's per-row Jacobians."""
    got = gj.graph_jacobians(model, x, u)
    assert got is not None  # the graph path is taken
    A_ref, B_ref = reference(model, x, u)
    assert B_ref.abs().max() > 1e-3
    torch.testing.assert_close(got[0], A_ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(got[1], B_ref, rtol=1e-12, atol=1e-14)
    # linearize takes it by default
    A, B = linearize(model, x, u)
    torch.testing.assert_close(A, A_ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(B, B_ref, rtol=1e-12, atol=1e-14)


def assert_graph_derivatives_equal_autodiff(model, x, u, curved: bool = True) -> None:
    """:func:`graph_jacobians` and :func:`graph_hessians` are taken and give torch.func's
    per-row Jacobians and nested-autodiff Hessians (``curved``: Hessians not all near
    zero, so that there is curvature to get right)."""
    got = gj.graph_jacobians(model, x, u)
    assert got is not None
    A_ref, B_ref = reference(model, x, u)
    torch.testing.assert_close(got[0], A_ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(got[1], B_ref, rtol=1e-12, atol=1e-14)
    H_ref = reference_hessians(model, x, u)
    hess = gj.graph_hessians(model, x, u)
    assert hess is not None and (max(h.abs().max() for h in H_ref) > 1e-4 or not curved)
    torch.testing.assert_close(hess[0], A_ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(hess[1], B_ref, rtol=1e-12, atol=1e-14)
    for h, r in zip(hess[2], H_ref, strict=True):
        torch.testing.assert_close(h, r, rtol=1e-11, atol=1e-13)


@pytest.mark.parametrize("name", list(ACTIVATIONS))
@pytest.mark.parametrize("residual", [True, False])
def test_learned_dynamics_equal_jacrev(name, residual):
    model = ts.LearnedDynamics(mlp(*ACTIVATIONS[name]), 4, 2, residual=residual)
    assert_graph_equals_jacrev(model, *data())


class PhysicsResidual(ts.Dynamics):
    """A learned residual on a discretised physics step, with the arithmetic nodes the
    graph path differentiates: sums, differences, products with numbers, a vector and
    another node, division by a number, negation, functional and method activations."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.step = ts.discretize(CartPole(), 0.05, "rk4").to(F64)
        torch.manual_seed(3)
        self.net = nn.Sequential(nn.Linear(5, 12), nn.Tanh(), nn.Linear(12, 4)).to(F64)
        self.gate = nn.Linear(4, 4).to(F64)
        self.register_buffer("scale", torch.tensor([1.0, 0.5, -2.0, 0.25], dtype=F64))

    def forward(self, x, u):
        z = torch.cat([x, u], dim=-1)
        r = self.net(z)
        g = torch.sigmoid(self.gate(x)) * F.silu(r)  # a product of two nodes
        h = self.gate(r).tanh() * self.scale - 0.5 * torch.relu(x) / 3.0
        return self.step(x, u) + 0.1 * r - (-g) + h * 0.01


def test_physics_residual_with_arithmetic_equals_jacrev():
    model = PhysicsResidual()
    x, u = data(m=1, scale=1.0)
    got = gj.graph_jacobians(model, x, u)
    assert got is not None
    A_ref, B_ref = reference(model, x, u)
    torch.testing.assert_close(got[0], A_ref, rtol=1e-11, atol=1e-13)
    torch.testing.assert_close(got[1], B_ref, rtol=1e-11, atol=1e-13)


class Features(ts.Dynamics):
    """Features made from the state before a network, as learned models often do: slices
    of the last dim, ``sin`` and ``cos`` of an angle, squares, an exponential and
    powers (functional, method and operator forms), and a slice of the network's
    output."""

    state_dim, control_dim = 4, 2

    def __init__(self):
        super().__init__()
        self.net = mlp(nn.GELU(), nn.Tanh(), k=13, out=6)

    def forward(self, x, u):
        angle = x[..., 1:2]
        feats = torch.cat(
            [
                x[..., :1],
                torch.sin(angle),
                angle.cos(),
                torch.square(x[..., 2:]),
                0.1 * u.exp(),
                x[..., 2:3] ** 3,
                x[..., 3:].pow(2),
                u[..., 1:].sin().square(),
                (1.0 + u.square()) ** 0.5,
                x[..., :1] ** 1,
            ],
            -1,
        )
        return x + 0.1 * self.net(feats)[..., 1:5]


def test_features_of_the_state_equal_jacrev():
    assert_graph_equals_jacrev(Features(), *data(scale=1.0))  # every op of the features


class Entries(ts.Dynamics):
    """Entries of the state taken one by one (``x[..., i]`` drops the last dim) and put
    back with ``torch.stack(..., -1)`` and ``unsqueeze(-1)``, as physics code writes it,
    around a network."""

    state_dim, control_dim = 4, 2

    def __init__(self):
        super().__init__()
        self.net = mlp(nn.Tanh(), k=8, out=4)

    def forward(self, x, u):
        s, th, v, w = x[..., 0], x[..., 1], x[..., 2], x[..., 3]
        f = u[..., -1]
        feats = torch.stack(
            [
                s,
                torch.sin(th),
                th.cos(),
                v * w,
                -w / 2.0,
                f**2,
                torch.tanh(f) * 0.5 + 1.0,
                u[..., 0],
            ],
            -1,
        )
        physics = torch.stack([v, w, torch.sin(th) * f, 2.0 - s], -1)
        out = x + 0.1 * self.net(feats) + 0.01 * physics
        return torch.cat([out[..., :3], out[..., 3:] + (th * v).unsqueeze(-1)], -1)


def test_entries_of_the_state_equal_autodiff():
    # integer indexing, stack and unsqueeze are taken
    assert_graph_derivatives_equal_autodiff(Entries(), *data(scale=1.0))


class GrayBox(ts.Dynamics):
    """Physics written inline in torch ops (the cart-pole's accelerations: entries of the
    state, sin and cos, products, quotients by a state-dependent denominator, a
    reciprocal) plus a network, one Euler step."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.net = mlp(nn.Tanh(), k=5, out=4)

    def forward(self, x, u):
        sd, th, thd = x[..., 2], x[..., 1], x[..., 3]
        f = u[..., 0]
        s, c = torch.sin(th), torch.cos(th)
        D = 1.0 + 0.1 * s * s
        sdd = (f + 0.1 * s * (0.5 * thd**2 + 9.81 * c)) / D
        thdd = (-f * c - 0.05 * thd**2 * c * s - 1.1 * 9.81 * s) / (0.5 * D)
        damp = 1.0 / (2.0 + c)
        xdot = torch.stack([sd, thd, sdd - damp * sd, thdd], -1)
        return x + 0.05 * xdot + 0.01 * self.net(torch.cat([x, u], -1))


def test_gray_box_physics_equals_jacrev(monkeypatch):
    model = GrayBox()
    x, u = data(m=1, scale=1.0)
    A_ref, B_ref = reference(model, x, u)
    # its 39 elementwise nodes are more than the sweep is taken for: autograd's pass
    assert gj._program(model).elementwise > gj.MAX_ELEMENTWISE
    assert gj.graph_jacobians(model, x, u) is None
    A, B = linearize(model, x, u)
    torch.testing.assert_close(A, A_ref, rtol=1e-12, atol=1e-14)
    monkeypatch.setattr(gj, "MAX_ELEMENTWISE", 1000)  # quotients by nodes are taken
    assert_graph_derivatives_equal_autodiff(model, x, u)


class EntriesElsewhere(ts.Dynamics):
    """Entries of the state whose meaning depends on the batch dims: stacked along
    another dim, unsqueezed elsewhere, or combined with a tensor (broadcast along what
    the graph holds as rows)."""

    state_dim, control_dim = 4, 2

    def __init__(self, how: str):
        super().__init__()
        self.how = how
        self.net = mlp(nn.Tanh())
        self.register_buffer("w", torch.tensor([0.5], dtype=F64))

    def forward(self, x, u):
        out = x + self.net(torch.cat([x, u], -1))
        th = x[..., 1]
        if self.how == "stack":
            return out + torch.stack([th, th, th, th], 0).movedim(0, -1)
        if self.how == "unsqueeze":
            return out + th.unsqueeze(0).movedim(0, -1)
        return out + (th * self.w).unsqueeze(-1)


@pytest.mark.parametrize("how", ["stack", "unsqueeze", "tensor"])
def test_entries_used_elsewhere_keep_autograd(how):
    model = EntriesElsewhere(how)
    x, u = data()
    assert gj.graph_jacobians(model, x, u) is None
    A, B = linearize(model, x, u)
    A_ref, B_ref = reference(model, x, u)
    torch.testing.assert_close(A, A_ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(B, B_ref, rtol=1e-12, atol=1e-14)


def test_blocks_of_rows_give_the_same_jacobians(monkeypatch):
    model = ts.LearnedDynamics(mlp(nn.Tanh(), nn.Tanh()), 4, 2)
    x, u = data(lead=(13, 11))
    whole = gj.graph_jacobians(model, x, u)
    # 16-wide layers, 4 outputs, float64: 512 bytes a row, so blocks of 5 rows (the
    # last one short); on the CPU only
    monkeypatch.setattr(row_blocks, "BLOCK_BYTES", 5 * 16 * 4 * 8)
    blocked = gj.graph_jacobians(model, x, u)
    torch.testing.assert_close(blocked[0], whole[0], rtol=1e-14, atol=1e-15)
    torch.testing.assert_close(blocked[1], whole[1], rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize(
    "make, scale",
    [
        (lambda: ts.LearnedDynamics(mlp(nn.Tanh(), nn.ReLU()), 4, 2), 1.5),
        (Features, 1.0),
    ],
    ids=["learned", "features"],
)
def test_float32_works(make, scale):
    model = make().to(torch.float32)
    x, u = data(scale=scale, dtype=torch.float32)
    got = gj.graph_jacobians(model, x, u)
    assert got is not None and got[0].dtype == torch.float32
    A_ref, B_ref = reference(model, x, u)
    torch.testing.assert_close(got[0], A_ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got[1], B_ref, rtol=1e-5, atol=1e-6)


def test_a_plain_network_on_the_concatenation():
    net = mlp(nn.Tanh(), nn.SiLU())
    x, u = data()
    A_ref, B_ref = reference(lambda x, u: net(torch.cat([x, u], -1)), x, u)
    got = gj.graph_jacobians(net, x, u)
    assert got is not None
    torch.testing.assert_close(got[0], A_ref, rtol=1e-12, atol=1e-14)
    A, B = linearize(net, x, u)
    torch.testing.assert_close(B, B_ref, rtol=1e-12, atol=1e-14)


class Indexing(ts.Dynamics):
    """A model the graph path does not take (indexing by a tensor, or ``x[:, :]``, whose
    meaning depends on the batch dims), with a network."""

    state_dim, control_dim = 4, 2

    def __init__(self, rows: bool = False):
        super().__init__()
        self.rows = rows
        self.net = mlp(nn.Tanh())

    def forward(self, x, u):
        out = self.net(torch.cat([x, u], -1))
        if self.rows:
            return out + x[:, :]
        return out + torch.sin(x[..., torch.tensor([0, 0, 1, 1])])


class PerElement(ts.Dynamics):
    """A network with a per-element gain ``(B, 1, 1)``: its rows are not independent."""

    state_dim, control_dim = 4, 2

    def __init__(self, batch):
        super().__init__()
        self.net = mlp(nn.Tanh())
        self.gain = nn.Parameter(torch.linspace(0.5, 2.0, batch, dtype=F64).reshape(batch, 1, 1))

    def forward(self, x, u):
        return x + self.net(torch.cat([x, u], -1)) * self.gain


class Broadcasting(ts.Dynamics):
    """A node combined with one of another width (broadcast): kept on autograd."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.net = mlp(nn.Tanh(), k=5)

    def forward(self, x, u):
        return self.net(torch.cat([x, u], -1)) + x * u


class BroadcastAtTheOutput(ts.Dynamics):
    """A one-wide node broadcast over the state by the output's sum (a feature, or a
    single control added to every state): kept on autograd (the sum's identity
    sensitivity is not the narrow node's, which feeds every output)."""

    def __init__(self, m: int):
        super().__init__()
        self.state_dim, self.control_dim = 4, m
        self.net = mlp(nn.Tanh(), k=4 + m)

    def forward(self, x, u):
        narrow = u if self.control_dim == 1 else torch.sin(x[..., 1:2])
        return x + self.net(torch.cat([x, u], -1)) + narrow


# (model maker, control dim) of the graphs the graph path does not take
NOT_TAKEN = [
    pytest.param(Indexing, 2, id="indexing"),
    pytest.param(lambda: Indexing(rows=True), 2, id="indexing-rows"),
    pytest.param(lambda: PerElement(6), 2, id="per-element"),
    pytest.param(Broadcasting, 1, id="broadcasting"),
    pytest.param(lambda: BroadcastAtTheOutput(2), 2, id="broadcast-feature"),
    pytest.param(lambda: BroadcastAtTheOutput(1), 1, id="broadcast-control"),
]


@pytest.mark.parametrize("make, m", NOT_TAKEN)
def test_what_keeps_autograd_is_still_right(make, m):
    model = make()
    x, u = data(m=m)
    assert gj.graph_jacobians(model, x, u) is None
    A, B = linearize(model, x, u)
    if isinstance(model, PerElement):  # per-row references would lose the gain's rows
        with torch.no_grad():
            g = model.gain
        Jn, Ju = reference(lambda x, u: model.net(torch.cat([x, u], -1)), x, u)
        A_ref = torch.eye(4, dtype=F64) + Jn * g.unsqueeze(-1)
        B_ref = Ju * g.unsqueeze(-1)
    else:
        A_ref, B_ref = reference(model, x, u)
    torch.testing.assert_close(A, A_ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(B, B_ref, rtol=1e-12, atol=1e-14)


def test_a_model_without_a_linear_layer_is_not_traced(monkeypatch):
    traced = []
    monkeypatch.setattr(gj, "_program", lambda model: traced.append(model))
    step = ts.discretize(CartPole(), 0.05, "rk4").to(F64)
    x, u = data(m=1, scale=0.5)
    linearize(step, x, u)
    assert traced == []


def test_an_output_that_is_not_a_state_is_reported():
    model = ts.LearnedDynamics(mlp(nn.Tanh(), out=3), 4, 2, residual=False)
    x, u = data()
    with pytest.raises(ValueError, match="its last dim must be state_dim = 4"):
        linearize(model, x, u)


def _learned_cart_move():
    """A learned residual cart-pole moving the cart, three initial angles."""
    torch.manual_seed(0)

    class Learned(ts.Dynamics):
        state_dim, control_dim = 4, 1

        def __init__(self):
            super().__init__()
            self.step = ts.discretize(CartPole(), 0.05, "rk4").to(F64)
            self.net = nn.Sequential(
                nn.Linear(5, 16), nn.Tanh(), nn.Linear(16, 16), nn.Tanh(), nn.Linear(16, 4)
            ).to(F64)
            with torch.no_grad():
                self.net[-1].weight.mul_(1e-2)

        def forward(self, x, u):
            return self.step(x, u) + self.net(torch.cat([x, u], -1))

    cost = ts.QuadraticCost(
        Q=torch.eye(4, dtype=F64),
        R=0.1 * torch.eye(1, dtype=F64),
        Qf=10.0 * torch.eye(4, dtype=F64),
        x_ref=torch.tensor([0.5, 0.0, 0.0, 0.0], dtype=F64),
    )
    x0 = torch.zeros(3, 4, dtype=F64)
    x0[:, 1] = torch.tensor([0.0, 0.1, -0.2], dtype=F64)
    return ts.Problem(Learned(), cost, 30), x0


def _with_and_without(monkeypatch, name: str, solver, problem, x0):
    """The solve with the graph path ``name`` (every call taking it) and without it."""
    calls = []
    real = getattr(gj, name)

    def counted(*args):
        out = real(*args)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(linearize_module, name, counted)
    with_graph = solver.solve(problem, x0)
    assert calls and all(calls)
    monkeypatch.setattr(linearize_module, name, lambda *a: None)
    return with_graph, solver.solve(problem, x0)


def test_learned_solve_iterates_equal_autograd(monkeypatch):
    """ILQR with multiple shooting on a learned residual cart-pole (a cart move): the
    same iterations and costs with the graph path as with autograd's Jacobians."""
    problem, x0 = _learned_cart_move()
    solver = ts.ILQR(max_iter=150, tol=1e-6, shooting="multiple", progress=False)
    with_graph, without = _with_and_without(monkeypatch, "graph_jacobians", solver, problem, x0)
    assert torch.equal(with_graph.iterations, without.iterations)
    assert torch.equal(with_graph.status, without.status)
    assert bool((with_graph.status == ts.Status.CONVERGED).all())
    assert int(with_graph.iterations.min()) >= 3
    # the same iterates up to the Jacobians' rounding
    torch.testing.assert_close(
        with_graph.history["cost"], without.history["cost"], rtol=1e-11, atol=0.0
    )


class Counting(ts.Dynamics):
    """A learned residual that counts its calls and their rows."""

    state_dim, control_dim = 4, 2

    def __init__(self, batch: int | None = None):
        super().__init__()
        self.net = mlp(nn.Tanh(), nn.Tanh())
        self.calls: list[int] = []
        if batch is not None:  # a per-element gain (B, 1, 1)
            self.gain = nn.Parameter(torch.linspace(0.5, 2.0, batch, dtype=F64).reshape(-1, 1, 1))

    def forward(self, x, u):
        self.calls.append(x.shape[:-1].numel())
        out = x + self.net(torch.cat([x, u], -1))
        return out * self.gain if hasattr(self, "gain") else out


def test_call_in_blocks(monkeypatch):
    # 16-wide layers, float64: 128 bytes a row; blocks of 10 rows
    monkeypatch.setattr(row_blocks, "BLOCK_BYTES", 10 * 16 * 8)
    x, u = data(lead=(6, 7))
    model = Counting()
    with torch.no_grad():
        whole = model(x, u)
        model.calls.clear()
        blocked = row_blocks.call_in_blocks(model, x, u)
    assert model.calls == [10, 10, 10, 10, 2]  # 42 rows
    torch.testing.assert_close(blocked, whole, rtol=1e-14, atol=1e-15)
    # one call: per-element data, a graph to record, few rows
    per_element = Counting(batch=6)
    with torch.no_grad():
        row_blocks.call_in_blocks(per_element, x, u)
    model.calls.clear()
    out = row_blocks.call_in_blocks(model, x, u)  # the network's weights need grad
    assert out.requires_grad
    with torch.no_grad():
        row_blocks.call_in_blocks(model, x[:1, :1], u[:1, :1])
    assert (per_element.calls, model.calls) == ([42], [42, 1])


class Scaled(ts.Dynamics):
    """A residual scaled by a Python number and a branch on a flag, both read by the
    trace as they are when it is made."""

    state_dim, control_dim = 4, 2

    def __init__(self):
        super().__init__()
        self.net = mlp(nn.Tanh())
        self.scale = 0.1
        self.residual = True

    def forward(self, x, u):
        out = self.scale * self.net(torch.cat([x, u], -1))
        return x + out if self.residual else out


def test_a_model_changed_after_its_trace_is_traced_again():
    model = Scaled()
    x, u = data()
    first = gj.graph_jacobians(model, x, u)
    torch.testing.assert_close(first[1], reference(model, x, u)[1], rtol=1e-12, atol=1e-14)
    model.scale = 0.5
    model.residual = False
    got = gj.graph_jacobians(model, x, u)
    assert got is not None  # traced again
    A_ref, B_ref = reference(model, x, u)
    torch.testing.assert_close(got[0], A_ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(got[1], B_ref, rtol=1e-12, atol=1e-14)


def reference_hessians(model, x, u):
    """Every output's Hessian blocks per row by torch.func (jacfwd over jacrev), in
    dynamics_hessians' layout."""
    n, m = x.shape[-1], u.shape[-1]
    z = torch.cat([x, u], -1).reshape(-1, n + m)

    def one(zi):
        return model(zi[:n].unsqueeze(0), zi[n:].unsqueeze(0)).squeeze(0)

    H = vmap(jacfwd(jacrev(one)))(z).movedim(1, 0)  # (n, rows, k, k)
    lead = x.shape[:-1]
    return (
        H[..., :n, :n].reshape(n, *lead, n, n),
        H[..., n:, n:].reshape(n, *lead, m, m),
        H[..., n:, :n].reshape(n, *lead, m, n),
    )


@pytest.mark.parametrize("name", list(ACTIVATIONS))
def test_graph_hessians_of_learned_dynamics_equal_nested_autodiff(name):
    model = ts.LearnedDynamics(mlp(*ACTIVATIONS[name]), 4, 2)
    assert_graph_derivatives_equal_autodiff(model, *data(), curved=name != "relu-leaky")


def test_graph_hessians_of_products_and_a_physics_step(monkeypatch):
    """Products of two nodes, functional and method activations, and a discretised
    physics submodule (its own Hessians), in blocks of rows and in one."""
    model = PhysicsResidual()
    x, u = data(m=1, scale=1.0)
    H_ref = reference_hessians(model, x, u)
    whole = gj.graph_hessians(model, x, u)
    monkeypatch.setattr(row_blocks, "BLOCK_BYTES", 7 * 16 * 5 * 8)  # blocks of 7 rows
    blocked = gj.graph_hessians(model, x, u)
    for got in (whole, blocked):
        for h, r in zip(got[2], H_ref, strict=True):
            torch.testing.assert_close(h, r, rtol=1e-11, atol=1e-13)
    # linearize_with_hessians takes it
    A, B, hessians = linearize_with_hessians(model, x, u)
    for h, r in zip(hessians(), H_ref, strict=True):
        torch.testing.assert_close(h, r, rtol=1e-11, atol=1e-13)


def test_graph_hessians_of_features_equal_nested_autodiff(monkeypatch):
    """The features' curvature (sin, cos, exp, squares, powers; slices add none), in
    blocks of rows and in one."""
    model = Features()
    x, u = data(scale=1.0)
    H_ref = reference_hessians(model, x, u)
    assert max(h.abs().max() for h in H_ref) > 1e-3
    whole = gj.graph_hessians(model, x, u)
    assert whole is not None
    monkeypatch.setattr(row_blocks, "BLOCK_BYTES", 9 * 16 * 6 * 8)  # blocks of 9 rows
    blocked = gj.graph_hessians(model, x, u)
    for got in (whole, blocked):
        for h, r in zip(got[2], H_ref, strict=True):
            torch.testing.assert_close(h, r, rtol=1e-11, atol=1e-13)


def test_only_last_dim_slices_and_entries_are_taken():
    """``z[..., i:j]`` and ``z[..., i]`` (held as the column ``i:i+1``) are taken;
    ``z[:, i:j]`` slices the state on (rows, n) but a time dim on (B, T, n), and a step,
    a bool or a tensor index: all keep autograd."""
    assert gj._last_dim_part((Ellipsis, slice(1, 3))) == (slice(1, 3), False)
    assert gj._last_dim_part((Ellipsis, slice(None, -1))) == (slice(None, -1), False)
    assert gj._last_dim_part((Ellipsis, 1)) == (slice(1, 2), True)
    assert gj._last_dim_part((Ellipsis, -1)) == (slice(-1, None), True)
    for index in (
        (slice(None), slice(1, 3)),
        slice(1, 3),
        (Ellipsis, slice(0, 4, 2)),
        (Ellipsis, True),
        (Ellipsis, torch.tensor([0, 1])),
    ):
        assert gj._last_dim_part(index) is None


def test_graph_hessians_decline_wide_inputs():
    k = _mlp.MAX_INPUT + 1
    model = ts.LearnedDynamics(mlp(nn.Tanh(), k=k, out=k - 1), k - 1, 1)
    x, u = data(n=k - 1, m=1)
    assert gj.graph_hessians(model, x, u) is None
    assert gj.graph_jacobians(model, x, u) is not None


def test_learned_ddp_iterates_equal_autograd(monkeypatch):
    """DDP (value mode: every output's Hessians) on a learned residual cart-pole: the
    same iterations and costs with the graph's Hessians as with autograd's."""
    problem, x0 = _learned_cart_move()
    solver = ts.DDP(max_iter=60, tol=1e-8, progress=False)
    with_graph, without = _with_and_without(monkeypatch, "graph_hessians", solver, problem, x0)
    assert bool((with_graph.status == ts.Status.CONVERGED).all())
    assert torch.equal(with_graph.iterations, without.iterations)
    torch.testing.assert_close(
        with_graph.history["cost"], without.history["cost"], rtol=1e-11, atol=0.0
    )
