"""Values a solve computes once (``torchslq._pinned``): once per scope, per owner, and
forgotten with the scope or the owner; a model's or cost's new values are seen by the
next solve."""

from __future__ import annotations

import gc
import math
import weakref

import pytest
import torch
from torch import nn

import torchslq as ts
from torchslq._pinned import _PINNED, pinned, solve_scope

pytestmark = pytest.mark.codegen  # the generated code's parameter arrays are pinned

F64 = torch.float64


def test_once_per_scope_and_owner():
    a, b = nn.Linear(2, 2), nn.Linear(2, 2)
    calls: list[str] = []

    def compute(tag):
        calls.append(tag)
        return tag

    with solve_scope():
        assert [pinned(a, "v", lambda: compute("a")) for _ in range(3)] == ["a"] * 3
        assert pinned(b, "v", lambda: compute("b")) == "b"
        assert pinned(a, ("v", 2), lambda: compute("a2")) == "a2"  # another key
        with solve_scope():  # nested: the outer scope's values
            assert pinned(a, "v", lambda: compute("x")) == "a"
    assert calls == ["a", "b", "a2"]
    assert pinned(a, "v", lambda: compute("after")) == "after"  # outside: every call
    assert pinned(a, "v", lambda: compute("after")) == "after"
    assert calls[-2:] == ["after", "after"]


def test_an_owner_that_goes_takes_its_values():
    """A compacting solve makes a subset of a per-element cost for each iteration: its
    pinned values must not outlive it (they would pile up for the whole solve)."""
    with solve_scope():
        sub = nn.Linear(2, 2)
        pinned(sub, "w", lambda: torch.zeros(1000))
        ref = weakref.ref(sub)
        del sub
        gc.collect()
        assert ref() is None
        assert len(_PINNED.get()["values"]) == 0


class _Pendulum(ts.ContinuousDynamics):
    state_dim, control_dim = 2, 1

    def __init__(self, length: float):
        super().__init__()
        self.length = length  # a float attribute: a parameter of the generated code
        self.damping = nn.Parameter(torch.tensor(0.1, dtype=F64), requires_grad=False)

    def forward(self, x, u, t=None):
        th, om = x[..., 0], x[..., 1]
        acc = -9.81 / self.length * torch.sin(th) - self.damping * om + u[..., 0]
        return torch.stack([om, acc], -1)


def _problem(model: _Pendulum) -> ts.Problem:
    cost = ts.QuadraticCost(
        Q=0.1 * torch.eye(2, dtype=F64),
        R=0.1 * torch.eye(1, dtype=F64),
        Qf=10.0 * torch.eye(2, dtype=F64),
        x_ref=torch.tensor([math.pi, 0.0], dtype=F64),
    )
    return ts.Problem(ts.discretize(model, 0.05, "rk4").double(), cost, 40)


X0 = torch.tensor([[0.1, 0.0], [-0.2, 0.3]], dtype=F64)


def test_a_solve_sees_values_changed_since_the_last():
    """One problem solved, its model changed (a float attribute and a parameter) and its
    cost's goal moved, and solved again: the second solve equals a fresh problem's with
    the new values, not the first's (what a solve pins belongs to that solve)."""
    solver = ts.ILQR(max_iter=100, tol=1e-8, progress=False)
    model = _Pendulum(1.0)
    problem = _problem(model)
    first = solver.solve(problem, X0)
    model.length = 0.7
    with torch.no_grad():
        model.damping.fill_(0.3)
    problem.cost.x_ref = torch.full_like(problem.cost.x_ref, 3.0)  # a new tensor
    second = solver.solve(problem, X0)
    fresh = _Pendulum(0.7)
    with torch.no_grad():
        fresh.damping.fill_(0.3)
    expected_problem = _problem(fresh)
    expected_problem.cost.x_ref = torch.full_like(expected_problem.cost.x_ref, 3.0)
    expected = solver.solve(expected_problem, X0)
    assert bool(first.converged.all()) and bool(second.converged.all())
    assert torch.equal(second.u, expected.u)
    assert not torch.allclose(second.u, first.u, atol=1e-3)
