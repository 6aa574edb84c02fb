"""Second derivatives of a flat MLP by its layers (torchslq.dynamics._mlp) and its
stand-in in the Hessian pass, against torch.func's nested autodiff and DDP's iterates
without the stand-in."""

from __future__ import annotations

import importlib

import pytest
import torch
from torch import nn
from torch.func import jacfwd, jacrev, vmap

import torchslq as ts
from torchslq.dynamics import _mlp, dynamics_hessians, dynamics_vhp, linearize_with_hessians
from torchslq.dynamics._mlp import MAX_INPUT, mlp_taylor

F64 = torch.float64

ACTIVATIONS = {
    "tanh": (nn.Tanh(), nn.Tanh()),
    "sigmoid-silu": (nn.Sigmoid(), nn.SiLU()),
    "softplus-elu": (nn.Softplus(beta=2.0, threshold=3.0), nn.ELU(alpha=0.7)),
    "relu-leaky": (nn.ReLU(), nn.LeakyReLU(0.1)),
    "gelu-tanh": (nn.GELU(), nn.Tanh()),
}


def net_with(acts, k=5, out=4, last=None, seed=0) -> nn.Sequential:
    torch.manual_seed(seed)
    layers = [nn.Linear(k, 16), acts[0], nn.Linear(16, 12), acts[1], nn.Linear(12, out)]
    return nn.Sequential(*layers, *([last] if last is not None else [])).to(F64)


@pytest.mark.parametrize("name", list(ACTIVATIONS))
@pytest.mark.parametrize("last", [None, nn.Sigmoid()])
def test_layered_hessians_equal_nested_autodiff(name, last):
    net = net_with(ACTIVATIONS[name], last=last)
    # spread inputs: softplus's linear region and both sides of the ReLUs are visited
    z = 2.0 * torch.randn(200, 5, generator=torch.Generator().manual_seed(1), dtype=F64)
    value, J, H = mlp_taylor(net, z)
    with torch.no_grad():
        torch.testing.assert_close(value, net(z), rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(J, vmap(jacrev(net))(z), rtol=1e-12, atol=1e-14)
    H_ref = vmap(jacfwd(jacrev(net)))(z)
    assert H_ref.abs().max() > 1e-5 or name == "relu-leaky"  # curvature to get right
    torch.testing.assert_close(H, H_ref, rtol=1e-11, atol=1e-14)


def test_only_flat_mlps_of_known_layers_are_taken():
    assert mlp_taylor(net_with(ACTIVATIONS["tanh"]), torch.zeros(3, 5, dtype=F64)) is not None
    # GELU's tanh approximation and Mish are not in the table of activations
    for unknown in (nn.GELU(approximate="tanh"), nn.Mish()):
        net = nn.Sequential(nn.Linear(5, 8), unknown, nn.Linear(8, 4)).to(F64)
        assert mlp_taylor(net, torch.zeros(3, 5, dtype=F64)) is None
    wide = nn.Sequential(nn.Linear(MAX_INPUT + 1, 8), nn.Tanh(), nn.Linear(8, 4)).to(F64)
    assert mlp_taylor(wide, torch.zeros(3, MAX_INPUT + 1, dtype=F64)) is None
    starts_nonlinear = nn.Sequential(nn.Tanh(), nn.Linear(5, 4)).to(F64)
    assert mlp_taylor(starts_nonlinear, torch.zeros(3, 5, dtype=F64)) is None


class ResidualModel(ts.Dynamics):
    """A model that calls a network among other ops: x + 0.1 tanh(x) u + net([x, u])."""

    state_dim, control_dim = 4, 1

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x, u):
        return x + 0.1 * torch.tanh(x) * u + self.net(torch.cat([x, u], -1))


def _reference_hessians(model, x, u):
    """Every output's Hessian blocks by torch.func on one row at a time (no stand-in:
    plain functions, not the Hessian pass)."""

    def row(xi, ui):
        return model(xi.unsqueeze(0), ui.unsqueeze(0)).squeeze(0)

    Hz = vmap(jacfwd(jacrev(lambda z: row(z[:4], z[4:]))))(torch.cat([x, u], -1).reshape(-1, 5))
    Hz = Hz.reshape(*x.shape[:-1], 4, 5, 5).movedim(-3, 0)
    return Hz[..., :4, :4], Hz[..., 4:, 4:], Hz[..., 4:, :4]


@pytest.mark.parametrize("name", ["tanh", "softplus-elu"])
def test_a_network_inside_a_model_enters_the_hessian_pass_by_its_layers(name, monkeypatch):
    model = ResidualModel(net_with(ACTIVATIONS[name], seed=3))
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(3, 6, 4, generator=gen, dtype=F64)
    u = torch.randn(3, 6, 1, generator=gen, dtype=F64)
    s = torch.randn(3, 6, 4, generator=gen, dtype=F64)
    calls = []
    original = _mlp.mlp_taylor

    def counting(net, z):
        out = original(net, z)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(_mlp, "mlp_taylor", counting)
    H = dynamics_hessians(model, x, u)
    V = dynamics_vhp(model, x, u, s)
    assert calls == [True, True]  # one structured pass per Hessian pass
    ref = _reference_hessians(model, x, u)
    for got, want in zip(H, ref, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-11, atol=1e-13)
    # DDP's entry: the Jacobians from the same pass as the Hessians
    A, B, hessians = linearize_with_hessians(model, x, u)
    A_ref, B_ref = ts.linearize(model, x, u, method="jacrev")
    torch.testing.assert_close(A, A_ref, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(B, B_ref, rtol=1e-12, atol=1e-14)
    for got, want in zip(hessians(), ref, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-11, atol=1e-13)
    assert calls == [True, True, True]
    weights = s.movedim(-1, 0)[..., None, None]  # (n, ..., 1, 1)
    for got, want in zip(V, ref, strict=True):  # s . f: the outputs' weighted sum
        torch.testing.assert_close(got, (weights * want).sum(0), rtol=1e-11, atol=1e-13)


def test_ddp_on_a_learned_model_matches_the_autodiff_hessians(monkeypatch):
    """DDP's value mode on a LearnedDynamics: the same iterates with the network's
    layered Hessians as with torch.func's nested autodiff."""
    torch.manual_seed(2)
    net = nn.Sequential(nn.Linear(3, 16), nn.Tanh(), nn.Linear(16, 2)).to(F64)
    with torch.no_grad():
        net[-1].weight.mul_(0.1)
    problem = ts.Problem(
        ts.LearnedDynamics(net, 2, 1),
        ts.QuadraticCost(
            Q=torch.eye(2, dtype=F64),
            R=0.1 * torch.eye(1, dtype=F64),
            Qf=10 * torch.eye(2, dtype=F64),
        ),
        horizon=15,
    )
    x0 = torch.tensor([[1.0, -0.5], [0.3, 0.8]], dtype=F64)
    solver = ts.DDP(max_iter=5, tol=1e-14, progress=False)
    r = solver.solve(problem, x0)
    linearize_module = importlib.import_module("torchslq.dynamics.linearize")
    monkeypatch.setattr(linearize_module, "takes_mlp_standin", lambda module: False)
    rr = solver.solve(problem, x0)
    assert int(r.iterations.min()) >= 3
    torch.testing.assert_close(r.u, rr.u, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(r.cost, rr.cost, rtol=1e-12, atol=0.0)


def test_the_stand_in_is_confined_to_the_hessian_pass_context():
    """The forward hook is process-wide: a network run by another thread during the pass
    (a data loader, a second solve) keeps its own output and its parameters' gradients."""
    import threading

    other_net = net_with(ACTIVATIONS["tanh"], seed=7)
    z = torch.randn(3, 5, generator=torch.Generator().manual_seed(2), dtype=F64)
    (expected,) = torch.autograd.grad(other_net(z.requires_grad_()).sum(), other_net[0].weight)
    seen = {}

    class SpawnsAThread(ResidualModel):
        def forward(self, x, u):
            def other():
                try:
                    y = other_net(z.detach().requires_grad_()).sum()
                    seen["grad"] = torch.autograd.grad(y, other_net[0].weight)[0]
                except RuntimeError as err:  # the output replaced: no graph to the weight
                    seen["error"] = err

            worker = threading.Thread(target=other)
            worker.start()
            worker.join()
            return super().forward(x, u)

    model = SpawnsAThread(net_with(ACTIVATIONS["tanh"], seed=3))
    x = torch.randn(2, 3, 4, dtype=F64)
    u = torch.randn(2, 3, 1, dtype=F64)
    H = dynamics_hessians(model, x, u)
    assert "error" not in seen
    torch.testing.assert_close(seen["grad"], expected, rtol=1e-14, atol=0.0)
    for got, want in zip(H, _reference_hessians(ResidualModel(model.net), x, u), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-11, atol=1e-13)


def test_a_model_with_its_own_jacobians_keeps_them(monkeypatch):
    """linearize_with_hessians takes a model's analytic Jacobians as they are; only the
    Hessians (lazily) come from the pass with the network's stand-in."""

    class WithJacobians(ResidualModel):
        has_analytic_jacobians = True

        def jacobians(self, x, u):
            rows = lambda xi, ui: ResidualModel.forward(self, xi, ui)  # noqa: E731
            A, B = vmap(jacrev(rows, argnums=(0, 1)))(x.reshape(-1, 4), u.reshape(-1, 1))
            return A.reshape(*x.shape, 4), B.reshape(*x.shape[:-1], 4, 1)

    model = WithJacobians(net_with(ACTIVATIONS["tanh"], seed=4))
    x = torch.randn(2, 3, 4, generator=torch.Generator().manual_seed(6), dtype=F64)
    u = torch.randn(2, 3, 1, generator=torch.Generator().manual_seed(7), dtype=F64)
    calls = []
    original = _mlp.mlp_taylor
    monkeypatch.setattr(_mlp, "mlp_taylor", lambda net, z: calls.append(1) or original(net, z))
    A, B, hessians = linearize_with_hessians(model, x, u)
    A_own, B_own = model.jacobians(x, u)
    assert calls == [] and torch.equal(A, A_own) and torch.equal(B, B_own)
    H = hessians()
    assert calls == [1]
    for got, want in zip(H, _reference_hessians(ResidualModel(model.net), x, u), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-11, atol=1e-13)
