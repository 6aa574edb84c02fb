"""Constrained cart-pole swing-up: a track limit, bounded force and an exact goal, B at once.

The cart-pole of the iLQR benchmark (state ``[s, theta, s_dot, theta_dot]``, theta = 0
hanging, cart 1.0 kg, tip 0.1 kg, pole 0.5 m, g = 9.81; one RK4 step per dt = 0.05 s,
T = 50), now with

* a track limit ``|s_t| <= S_MAX`` for ``t = 0 .. T`` (state bounds,
  ``Constraints(x_min=, x_max=)``): the unconstrained swing-up runs the cart out to
  ``|s| ~ 0.65 - 0.69`` m, so 0.5 m binds;
* a force limit ``|u| <= U_MAX`` by ILQR's box QP (the unconstrained forces peak at
  about 7.6 N; with 6 N IPOPT finds a feasible swing-up from every start tried, with
  5 N from about six in seven: the others end ``infeasible``);
* the goal ``x_T = [0, pi, 0, 0]`` as a terminal equality constraint, so the cost is
  only the effort ``sum_t 0.01 u_t^2`` (no terminal weight: the goal is exact).

``x0 = [0, 0.05 N(0, 1), 0, 0]`` from ``numpy.random.default_rng(seed)``, ``u = 0``
initially. ``ILQR(constraints=...)`` solves all elements in one batched
augmented-Lagrangian solve (per-element multipliers and penalties), and the script
prints the status counts, the largest constraint violation, the cost, the iterations
and the wall time, and checks the solution against the limits.

The model is the zoo's :class:`torchslq.systems.CartPole` (the one
``benchmarks/peers.py`` uses); ``--model user`` swaps in the same equations written as
a plain :class:`torchslq.ContinuousDynamics` (:class:`UserCartPole`: no analytic
derivatives, no compiled hooks), which gives the same solution more slowly.

    python examples/constrained_cartpole.py                   # B = 64, about 25 s (1 core)
    python examples/constrained_cartpole.py --batch 512       # the issue's B
    python examples/constrained_cartpole.py --model user --batch 16
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

import torchslq as ts
from torchslq.systems import CartPole

DT, T, MC, MP, L, G = 0.05, 50, 1.0, 0.1, 0.5, 9.81
S_MAX = 0.5  # m; binds: the unconstrained swing-up reaches |s| = 0.65-0.69 m
U_MAX = 6.0  # N; binds: the unconstrained forces reach 7.6 N
R_U = 0.01  # running cost 0.01 u^2
GOAL = (0.0, math.pi, 0.0, 0.0)


class UserCartPole(ts.ContinuousDynamics):
    """The cart-pole's equations as a user would write them (torch ops only)."""

    state_dim, control_dim = 4, 1

    def forward(self, x, u, t=None):
        th, sd, thd, F = x[..., 1], x[..., 2], x[..., 3], u[..., 0]
        s, c = torch.sin(th), torch.cos(th)
        D = MC + MP * s * s
        sdd = (F + MP * s * (L * thd * thd + G * c)) / D
        thdd = (-F * c - MP * L * thd * thd * c * s - (MC + MP) * G * s) / (L * D)
        return torch.stack([sd, thd, sdd, thdd], -1)


def initial_states(batch: int, seed: int = 0) -> torch.Tensor:
    x0 = torch.zeros(batch, 4, dtype=torch.float64)
    x0[:, 1] = torch.from_numpy(0.05 * np.random.default_rng(seed).standard_normal(batch))
    return x0


def make_problem(model: str = "zoo", terminal_weight: float = 0.0) -> ts.Problem:
    """The effort-only problem (``sum_t R_U u_t^2 + terminal_weight |x_T - goal|^2``)."""
    f = UserCartPole() if model == "user" else CartPole(mc=MC, mp=MP, l=L)
    dyn = ts.discretize(f, DT, "rk4").double()
    cost = ts.QuadraticCost(
        torch.zeros(4, 4, dtype=torch.float64),
        2 * R_U * torch.eye(1, dtype=torch.float64),  # QuadraticCost is 1/2 u'Ru
        Qf=2 * terminal_weight * torch.eye(4, dtype=torch.float64),
        x_ref=torch.tensor(GOAL, dtype=torch.float64),
    )
    return ts.Problem(dyn, cost, T)


def make_constraints(s_max: float = S_MAX) -> list[ts.Constraints]:
    inf = math.inf
    goal = torch.tensor(GOAL, dtype=torch.float64)
    track = ts.Constraints(
        x_min=torch.tensor([-s_max, -inf, -inf, -inf]), x_max=torch.tensor([s_max, inf, inf, inf])
    )
    # the goal's Jacobian is the identity: given, it saves a torch.func pass per iteration
    arrive = ts.Constraints(
        terminal=lambda x: x - goal.to(x),
        kind="equality",
        terminal_jacobian=lambda x: torch.eye(4, dtype=x.dtype).expand(*x.shape[:-1], 4, 4),
    )
    return [track, arrive]


def make_solver(
    s_max: float = S_MAX,
    u_max: float = U_MAX,
    tol: float = 1e-6,
    constraint_tol: float = 1e-6,
    max_iter: int = 500,
    al_max_iter: int = 30,
    penalty_factor: float = 100.0,
    solver: str = "ilqr",
    **options,
) -> ts.ILQR | ts.DDP:
    """``solver="ilqr"`` (Gauss-Newton constraint Hessian) or ``"ddp"`` (the dynamics'
    and the constraint rows' curvature: fewer inner iterations, each dearer)."""
    return {"ilqr": ts.ILQR, "ddp": ts.DDP}[solver](
        max_iter=max_iter,
        tol=tol,
        u_min=-u_max,
        u_max=u_max,
        constraints=make_constraints(s_max),
        constraint_tol=constraint_tol,
        al_max_iter=al_max_iter,
        # the penalty grows 100x when the violation does not shrink fourfold (the
        # default; 10x took 1.5-2.5x the inner iterations to the same solution here)
        penalty_factor=penalty_factor,
        progress=False,
        **options,
    )


def summary(r: ts.SolverResult, wall: float, s_max: float, u_max: float) -> str:
    names = ts.status_names(r.status)
    counts = {k: names.count(k) for k in dict.fromkeys(names)}
    conv = r.status == ts.Status.CONVERGED
    goal = torch.tensor(GOAL, dtype=r.x.dtype)
    lines = [
        f"B = {r.x.shape[0]}, wall {wall:.1f} s",
        "status: " + ", ".join(f"{k} {v}" for k, v in counts.items()),
        f"max violation: {r.max_violation.max().item():.2e} (converged elements: "
        f"{r.max_violation[conv].max().item() if conv.any() else float('nan'):.2e})",
        f"cost: mean {r.cost.mean().item():.6f}, min {r.cost.min().item():.6f}, "
        f"max {r.cost.max().item():.6f}",
        f"iterations: outer mean {r.outer_iterations.double().mean().item():.1f} "
        f"max {int(r.outer_iterations.max())}; inner (total) mean "
        f"{r.iterations.double().mean().item():.1f} max {int(r.iterations.max())}",
        f"max |s_t| = {r.x[..., 0].abs().max().item():.7f} (limit {s_max:g}), max |u_t| = "
        f"{r.u.abs().max().item():.7f} (limit {u_max:g}), max |x_T - goal| = "
        f"{(r.x[:, -1] - goal).abs().max().item():.2e}",
    ]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model", choices=("zoo", "user"), default="zoo")
    ap.add_argument("--s-max", type=float, default=S_MAX)
    ap.add_argument("--u-max", type=float, default=U_MAX)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--constraint-tol", type=float, default=1e-6)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    problem = make_problem(args.model)
    x0 = initial_states(args.batch, args.seed)
    solver = make_solver(args.s_max, args.u_max, args.tol, args.constraint_tol)
    t0 = time.perf_counter()
    r = solver.solve(problem, x0)
    wall = time.perf_counter() - t0
    print(
        f"constrained cart-pole swing-up ({args.model} model): |s| <= {args.s_max:g}, "
        f"|u| <= {args.u_max:g}, x_T = goal; cost sum {R_U:g} u^2; T = {T}, dt = {DT}"
    )
    print(summary(r, wall, args.s_max, args.u_max))


if __name__ == "__main__":
    main()
