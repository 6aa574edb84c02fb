"""A learned model's wide layer chains in blocks of rows
(torchslq.dynamics.network_chains): which chains are taken; the generated Jacobians and
Hessians with them against torch.func's per-row derivatives and against the row sweep
alone; the step on many rows at once against forward."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_graph_jacobian import data, mlp, reference, reference_hessians
from torch import nn

import torchslq as ts
from torchslq._backend import model_fns
from torchslq.dynamics import network_chains, network_codegen
from torchslq.dynamics.graph_jacobian import _program, _root

pytestmark = [pytest.mark.codegen, pytest.mark.network_derivatives]

F64 = torch.float64


class Activated(ts.Dynamics):
    """A chain that starts with an activation and has a layer without a bias, on the
    state alone; its output is the model's output."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        torch.manual_seed(4)
        self.net = nn.Sequential(
            nn.Linear(4, 20), nn.SiLU(), nn.Linear(20, 18, bias=False), nn.ReLU(),
            nn.Linear(18, 4),
        ).to(F64)  # fmt: skip
        self.b = nn.Linear(1, 4).to(F64)

    def forward(self, x, u):
        return x + self.net(torch.sigmoid(x)) + self.b(u)


class Stacked(ts.Dynamics):
    """Two chains, the second on the first's output (scaled): only the first is taken."""

    state_dim, control_dim = 4, 2

    def __init__(self):
        super().__init__()
        self.first = mlp(nn.Tanh(), nn.Tanh(), k=6, out=4, seed=5)
        self.second = mlp(nn.Tanh(), nn.Tanh(), k=4, out=4, seed=6)

    def forward(self, x, u):
        h = self.first(torch.cat([x, u], -1))
        return x + 0.1 * self.second(0.5 * h)


def _chains(model) -> list:
    """The chains the generated Jacobians take for ``model``."""
    program = _program(model)
    _, w = network_codegen._write(program, _root(model), model.state_dim, model.control_dim, F64)
    return network_chains.find_chains(
        program, w, model.state_dim,
        lambda t: w.param(_root(model), ("weight", t)),
        lambda t: w.param(_root(model), ("weight_rows", t)),
    )  # fmt: skip


def _jacobians(model, x, u):
    with torch.no_grad():
        return network_codegen.network_jacobians(model, x, u)


MODELS = {
    "residual-tanh": (lambda: ts.LearnedDynamics(mlp(nn.Tanh(), nn.Tanh()), 4, 2), 2),
    "activated": (Activated, 1),
}


def test_which_chains_are_taken():
    """A chain runs from an activation or layer to the last node used by the next alone;
    a chain on another chain's output, layers narrower than WIDE and more outputs than
    states are not taken (the row sweep keeps them)."""
    (chain,) = _chains(MODELS["residual-tanh"][0]())
    assert len(chain.nodes) == 5 and [op[0] for op in chain.ops][::2] == ["linear"] * 3
    (chain,) = _chains(Activated())  # the sigmoid and the five layers
    assert [op[0] for op in chain.ops] == ["activation", "linear"] * 3
    assert chain.ops[3][-1] is None  # (the layer without a bias)
    (chain,) = _chains(Stacked())  # the first only
    assert chain.input.target is torch.cat
    narrow = ts.LearnedDynamics(
        nn.Sequential(nn.Linear(6, 12), nn.Tanh(), nn.Linear(12, 12), nn.Tanh(), nn.Linear(12, 4))
        .to(F64), 4, 2,
    )  # fmt: skip

    class WideOut(ts.Dynamics):
        state_dim, control_dim = 4, 2

        def __init__(self):
            super().__init__()
            self.net = mlp(nn.Tanh(), nn.Tanh(), k=6, out=8, seed=2)

        def forward(self, x, u):
            return x + self.net(torch.cat([x, u], -1))[..., 2:6]

    assert _chains(narrow) == [] and _chains(WideOut()) == []


@pytest.mark.parametrize("name", list(MODELS))
def test_blocked_chains_equal_autodiff(name, monkeypatch):
    """At row counts below, at and across the block size the Jacobians with the chains
    in blocks are torch.func's; for the residual MLP also the row sweep's (chains off)
    to rounding. (Each model compiles its functions: a few, for the suite's time.)"""
    make, m = MODELS[name]
    model = make()
    assert len(_chains(model)) == 1
    rows = network_chains.BLOCK_ROWS
    for lead in ((1,), (rows,), (rows + 1,), (3, rows - 7)):
        x, u = data(lead=lead, m=m, scale=1.0, seed=len(lead) + lead[-1])
        got = _jacobians(model, x, u)
        assert got is not None
        A_ref, B_ref = reference(model, x, u)
        assert float(A_ref.abs().max()) > 1e-2 and float(B_ref.abs().max()) > 1e-3
        torch.testing.assert_close(got[0], A_ref, rtol=1e-12, atol=1e-13)
        torch.testing.assert_close(got[1], B_ref, rtol=1e-12, atol=1e-13)
    if name != "residual-tanh":
        return
    monkeypatch.setattr(network_chains, "enabled", False)
    rows_only = make()  # (a new model: its text and function are written without chains)
    rows_only.load_state_dict(model.state_dict())
    assert _chains(rows_only) == []
    A_rows, B_rows = _jacobians(rows_only, x, u)
    torch.testing.assert_close(got[0], A_rows, rtol=1e-13, atol=1e-14)
    torch.testing.assert_close(got[1], B_rows, rtol=1e-13, atol=1e-14)


def test_blocked_chains_hessians_equal_nested_autodiff():
    """Every output's Hessian with a chain in blocks (its tangents pushed forward and
    each activation's curvature on the block: a sigmoid first, SiLU, ReLU without
    curvature) is torch.func's (jacfwd over jacrev), across the block size. (The
    learned models of tests/test_network_codegen.py check other activations' chains.)"""
    model = Activated()
    x, u = data(lead=(network_chains.BLOCK_ROWS + 5,), m=1, scale=1.0, seed=3)
    with torch.no_grad():
        got = network_codegen.network_hessians(model, x, u)
    assert got is not None
    H_ref = reference_hessians(model, x, u)
    assert max(float(h.abs().max()) for h in H_ref) > 1e-3  # curvature to get right
    torch.testing.assert_close(got[0], reference(model, x, u)[0], rtol=1e-12, atol=1e-13)
    for h, h_ref in zip(got[2], H_ref, strict=True):
        torch.testing.assert_close(h, h_ref, rtol=1e-10, atol=1e-12)


def test_step_on_many_rows_equals_forward():
    """The step on many rows at once (the chain's layers as matrix products over blocks
    of rows, registered for the model's step: model_fns.register_rows) is forward's to
    rounding at row counts below, at and across the block size, and writes only the
    rows it is given; a model without a chain has none (its one-row step serves)."""
    size = network_chains.BLOCK_ROWS
    # a chain on the state that starts with an activation; a chain on [x, u] whose output
    # feeds a second MLP left in the rows
    for model, m in ((Activated(), 1), (Stacked(), 2)):
        with torch.no_grad():
            step, params = model.compiled_step()
        rows_fn = model_fns.rows_step(step)
        assert rows_fn is not None
        for R in (1, size, size + 1, 2 * size + 3):
            x, u = data(lead=(R,), m=m, scale=1.0, seed=R)
            r0 = 0 if R == 1 else 2
            out = np.full((R, 4), np.nan)
            rows_fn(r0, R, x.numpy(), u.numpy(), params, out)
            with torch.no_grad():
                ref = model(x, u)
            got = torch.from_numpy(out[r0:])
            torch.testing.assert_close(got, ref[r0:], rtol=1e-13, atol=1e-14)
            assert np.isnan(out[:r0]).all()
    narrow = ts.LearnedDynamics(
        nn.Sequential(nn.Linear(5, 12), nn.Tanh(), nn.Linear(12, 4)).to(F64), 4, 1
    )
    with torch.no_grad():
        step, _ = narrow.compiled_step()
    assert model_fns.rows_step(step) is None
