"""Imitation through a constrained MPC layer: why the backward pass must know the constraints.

An expert swings a pendulum towards a target angle under a speed limit ``omega <= 0.8``
and a torque limit ``|u| <= 1.1`` (both bind on the expert's trajectories). A learner
with the same constraints but an unknown target angle ``g`` (the cost's ``x_ref``)
fits ``g`` to the expert's controls by gradient descent through ``torchslq.MPC``.

Two backward passes are compared from the same start:

* ``active set``: the layer's own (``MPC(constraints=...)``): the implicit function
  theorem on the KKT conditions with the active constraints held
  (:mod:`torchslq.mpc.constrained`);
* ``ignore constraints``: the same solution differentiated as if it were unconstrained
  (the unconstrained layer's KKT sensitivity, :func:`torchslq.mpc.implicit.implicit_solution`),
  which is what differentiating a constrained solver with an unconstrained layer gives.

Run: ``python examples/mpc_constrained_imitation.py [--steps 10] [--batch 8]`` (about a minute).
"""

from __future__ import annotations

import argparse
import time

import torch

import torchslq as ts
from torchslq.dynamics import Dynamics
from torchslq.mpc.implicit import implicit_solution

DT, T = 0.1, 20
SPEED_LIMIT, TORQUE_LIMIT = 0.8, 1.1


class Pendulum(Dynamics):
    """``theta'' = u - sin(theta)``, explicit Euler with step ``DT``."""

    state_dim, control_dim = 2, 1

    def forward(self, x, u):
        return x + DT * torch.stack([x[..., 1], u[..., 0] - torch.sin(x[..., 0])], -1)


def make_mpc(goal: torch.Tensor) -> ts.MPC:
    cost = ts.QuadraticCost(
        Q=torch.diag(torch.tensor([1.0, 0.1])),
        R=torch.eye(1),
        Qf=10.0 * torch.eye(2),
        x_ref=torch.stack([goal, torch.zeros_like(goal)]),
    )
    speed = ts.Constraints(stage=lambda x, u, t: x[..., 1:2] - SPEED_LIMIT)
    solver = ts.ILQR(tol=1e-9, max_iter=200, constraint_tol=1e-8, progress=False)
    return ts.MPC(
        Pendulum(), cost, T, solver=solver, constraints=speed,
        u_min=-TORQUE_LIMIT, u_max=TORQUE_LIMIT, warm_start="reuse", unconverged="zero",
    )  # fmt: skip


def loss_and_grad(g0: float, x0, u_expert, mode: str) -> tuple[float, float]:
    """The imitation loss at target ``g0`` and its gradient by the backward ``mode``
    (``"active_set"`` or ``"ignore"``)."""
    g = torch.tensor(g0, requires_grad=True)
    mpc = make_mpc(g)
    if mode == "active_set":
        _, u = mpc(x0)
    else:
        with torch.no_grad():
            mpc(x0)
        r = mpc.last_result
        _, u, _ = implicit_solution(mpc.problem, x0, r.x, r.u)
    loss = (u - u_expert).pow(2).mean()
    loss.backward()
    return loss.item(), g.grad.item()


def finite_difference(g0: float, x0, u_expert, eps: float = 1e-4) -> float:
    with torch.no_grad():
        lp = (make_mpc(torch.tensor(g0 + eps))(x0).u - u_expert).pow(2).mean()
        lm = (make_mpc(torch.tensor(g0 - eps))(x0).u - u_expert).pow(2).mean()
    return ((lp - lm) / (2 * eps)).item()


def train(x0, u_expert, mode: str, steps: int, lr: float) -> list[tuple[float, float]]:
    """``(loss, g)`` per step of plain gradient descent with the backward ``mode``."""
    g, record = 0.3, []
    for _ in range(steps):
        loss, grad = loss_and_grad(g, x0, u_expert, mode)
        record.append((loss, g))
        g -= lr * grad
    return record


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=2.0)
    args = ap.parse_args()
    torch.set_default_dtype(torch.float64)
    torch.manual_seed(0)
    x0 = torch.stack([0.3 * torch.randn(args.batch), 0.2 * torch.randn(args.batch)], -1)
    g_true = torch.tensor(1.0)
    with torch.no_grad():
        expert = make_mpc(g_true)
        out = expert(x0)
    r = expert.last_result
    print(
        f"expert: target angle {g_true.item()}, {r.status_names().count('converged')}/"
        f"{args.batch} converged, speed limit active on "
        f"{int((r.multipliers['stage'] > 0).any(-1).any(-1).sum())} trajectories, torque limit "
        f"on {int((r.active_bounds != 0).any(-1).any(-1).sum())}"
    )
    print("\ngradient of the loss with respect to g: the two backward passes vs finite differences")
    print("   g    finite diff.   active set       ignore constraints")
    for g0 in (0.3, 0.6, 0.9):
        fd = finite_difference(g0, x0, out.u)
        ga = loss_and_grad(g0, x0, out.u, "active_set")[1]
        gi = loss_and_grad(g0, x0, out.u, "ignore")[1]
        print(
            f"{g0:5.2f}  {fd:12.6f}  {ga:12.6f} ({abs(ga - fd) / abs(fd):.1e})  "
            f"{gi:12.6f} ({abs(gi - fd) / abs(fd):.1e})"
        )
    print(f"\ngradient descent on g from 0.3, step {args.lr}:")
    results = {}
    for mode in ("active_set", "ignore"):
        t = time.perf_counter()
        results[mode] = train(x0, out.u, mode, args.steps, args.lr)
        loss, g = results[mode][-1]
        print(
            f"{mode:>10}: after {args.steps} steps loss {loss:.3e}, g = {g:.5f} "
            f"(error {abs(g - g_true.item()):.2e}), {time.perf_counter() - t:.1f} s"
        )
    print("\nstep   loss (active set)   g      loss (ignore)   g")
    for i in range(0, args.steps, max(1, args.steps // 10)):
        (la, ga), (li, gi) = results["active_set"][i], results["ignore"][i]
        print(f"{i:4d}   {la:14.3e}  {ga:7.4f}   {li:12.3e}  {gi:7.4f}")


if __name__ == "__main__":
    main()
