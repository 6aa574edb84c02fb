"""The Sideris & Bobrow problem builders encode eqs. (63)-(66) exactly, and the
steepest-descent baseline (GradientMethod) is the costate gradient and descends.

SLQ's iteration counts on Table 1 are tested elsewhere; nothing here runs SLQ to
convergence.
"""

from __future__ import annotations

import pytest
import torch

from reproductions import (
    drag_vehicle_problem,
    format_table,
    hopper_problem,
)
from reproductions.sideris import DRAG, HOPPER, table1_rows
from torchslq import Problem, QuadraticCost, Status
from torchslq.solvers import GradientMethod, SolverResult
from torchslq.systems import DragVehicle

DT = torch.float64


def _eq65(x, u, *, q, r, qfin, N, target):
    """Eq. (65) as printed, by an explicit loop (x: (N+1, 2), u: (N, 1))."""
    Ts = 1.0 / N
    J = qfin * (x[N, 0] - target) ** 2
    for n in range(N):
        J = J + Ts * (q * (x[n, 0] ** 2 + x[n, 1] ** 2) + r * u[n, 0] ** 2)
    return J


def _eq66(x, u, *, y_target, qfin, q, r, N, tf):
    """Eq. (66), literal reading of the garbled equation, by an explicit loop."""
    J = 0.5 * qfin * (x[N, 0] - y_target) ** 2 + x[N, 1] ** 2
    for n in range(N):
        J = J + tf / (2 * N) * (q * x[n, 2] ** 2 + r * u[n, 0] ** 2)
    return J


def test_drag_vehicle_cost_is_eq65():
    torch.manual_seed(0)
    betas = [0.01, 0.1, 1.0]
    problem, x0 = drag_vehicle_problem(betas)
    N = DRAG["N"]
    assert problem.horizon == N and x0.shape == (3, 2) and bool((x0 == 0).all())
    x = 5.0 * torch.randn(3, N + 1, 2, dtype=DT)
    u = torch.randn(3, N, 1, dtype=DT)
    J = problem.cost(x, u)
    for b in range(3):
        ref = _eq65(
            x[b], u[b], q=DRAG["q"], r=DRAG["r"], qfin=DRAG["qfin"], N=N, target=DRAG["target"]
        )
        torch.testing.assert_close(J[b], ref, rtol=1e-12, atol=1e-9)


def test_drag_vehicle_dynamics_are_eqs63_64_per_beta():
    torch.manual_seed(1)
    betas = [0.05, 0.5]
    N = 40
    problem, x0 = drag_vehicle_problem(betas, N=N)
    u = torch.randn(2, N, 1, dtype=DT)
    x = problem.rollout(x0, u)
    m, Ts = DRAG["m"], 1.0 / N
    for b, beta in enumerate(betas):
        p, v = torch.zeros((), dtype=DT), torch.zeros((), dtype=DT)
        for n in range(N):
            p, v = (
                v * Ts + p,
                -(1.0 / m) * (beta * Ts * v**2 * torch.sign(v) - Ts * u[b, n, 0]) + v,
            )
            torch.testing.assert_close(x[b, n + 1], torch.stack([p, v]), rtol=1e-12, atol=1e-12)


def test_hopper_cost_is_eq66_per_target():
    torch.manual_seed(2)
    targets = [1.0, 20.0, 50.0]
    problem, x0 = hopper_problem(targets)
    N = HOPPER["N"]
    assert problem.horizon == N and x0.shape == (3, 3) and bool((x0 == 0).all())
    x = 10.0 * torch.randn(3, N + 1, 3, dtype=DT)
    u = 10.0 * torch.randn(3, N, 1, dtype=DT)
    J = problem.cost(x, u)
    for b, yt in enumerate(targets):
        ref = _eq66(
            x[b],
            u[b],
            y_target=yt,
            qfin=HOPPER["qfin"],
            q=HOPPER["q"],
            r=HOPPER["r"],
            N=N,
            tf=HOPPER["tf"],
        )
        torch.testing.assert_close(J[b], ref, rtol=1e-12, atol=1e-9)
    # zero controls from rest: the mass falls onto the spring (contact at y = yp = 0)
    xz = problem.rollout(x0, torch.zeros(3, N, 1, dtype=DT))
    assert float(xz[0, 1, 1]) == pytest.approx(-HOPPER["g"] * HOPPER["tf"] / N)


def _small_drag(betas=(0.01, 0.1), N=50):
    return drag_vehicle_problem(list(betas), N=N)


def test_gradient_direction_is_minus_autograd_gradient(backend):
    torch.manual_seed(3)
    problem, x0 = _small_drag()
    u = torch.randn(2, problem.horizon, 1, dtype=DT)
    d = GradientMethod().direction(problem, problem.rollout(x0, u), u)
    uu = u.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(problem.total_cost(x0, uu).sum(), uu)
    torch.testing.assert_close(d["du"], -g, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(d["grad"], g, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(d["slope"], -(g * g).sum(dim=(1, 2)), rtol=1e-10, atol=0.0)
    assert bool((d["curvature"] > 0).all()) and not bool(d["failed"].any())


@pytest.mark.parametrize("line_search", ["exact", "armijo"])
def test_gradient_method_decreases_cost(line_search):
    problem, x0 = _small_drag()
    res = GradientMethod(max_iter=15, line_search=line_search, progress=False).solve(problem, x0)
    assert isinstance(res, SolverResult)
    hist = res.history["cost"]
    assert bool((hist[:, 1:] <= hist[:, :-1]).all())
    assert bool((res.cost < 1e-2 * hist[:, 0]).all())
    assert bool((res.iterations > 0).all())
    assert res.options["solver"] == "gradient"
    # the adaptive search range lets steps exceed 1 (the gradient has no natural scale)
    assert float(res.history["step"].max()) != 1.0
    assert all(s in (Status.MAX_ITER, Status.CONVERGED) for s in res.status.tolist())


def test_gradient_method_batch_matches_one_by_one(backend):
    problem, x0 = _small_drag()
    gm = GradientMethod(max_iter=6, line_search="exact", progress=False)
    res = gm.solve(problem, x0)
    for b, beta in enumerate((0.01, 0.1)):
        p1, x01 = _small_drag((beta,))
        r1 = gm.solve(p1, x01)
        torch.testing.assert_close(r1.cost[0], res.cost[b], rtol=1e-10, atol=0.0)
        assert int(r1.iterations[0]) == int(res.iterations[b])


def test_gradient_method_options_and_unit_range():
    with pytest.raises(ValueError):
        GradientMethod(search_range="bogus")
    with pytest.raises(ValueError):
        GradientMethod(growth=0.5)
    # (0, 1] search on a problem whose good gradient steps are far below 1 still descends
    dyn = DragVehicle(beta=0.1, Ts=0.05)
    cost = QuadraticCost(Q=torch.eye(2, dtype=DT), R=torch.eye(1, dtype=DT))
    problem = Problem(dyn, cost, horizon=20)
    x0 = torch.tensor([[1.0, 0.0]], dtype=DT)
    res = GradientMethod(max_iter=5, search_range="unit", progress=False).solve(problem, x0)
    assert float(res.cost[0]) < float(res.history["cost"][0, 0])
    assert float(res.history["step"].max()) <= 1.0


def test_format_table_and_rows():
    problem, x0 = _small_drag()
    res = GradientMethod(max_iter=2, progress=False).solve(problem, x0)
    rows = table1_rows([0.01, 0.1], res)
    assert rows[0]["paper"] == 9 and rows[1]["paper"] == 21
    text = format_table(rows, ["beta", "paper", "iterations", "status"])
    lines = text.splitlines()
    assert len(lines) == 4 and lines[0].startswith("| beta |") and "| 0.1 | 21 |" in lines[3]
