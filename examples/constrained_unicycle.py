"""A unicycle reaching a goal around circular obstacles, from B start poses at once.

The kinematic unicycle (:class:`torchslq.systems.Unicycle`: state ``[px, py, theta]``,
control ``[v, w]``, one Euler step per dt = 0.1 s), T = 40 steps, cost
``sum_t 1/2 (v_t^2 + w_t^2)`` (effort only), with

* three circular obstacles, ``r_j^2 - |p_t - o_j|^2 <= 0`` for ``t = 0 .. T-1``
  (a stage inequality :class:`torchslq.Constraints`);
* the goal pose ``x_T = [4, 0, 0]`` as a terminal equality constraint;
* a speed limit ``|v| <= V_MAX``, ``|w| <= W_MAX`` (ILQR's box QP).

Starts: ``px = 0``, ``py ~ U[-1, 1]``, ``theta ~ U[-0.5, 0.5]`` (numpy
``default_rng(seed)``), the initial guess ``v = 1 m/s, w = 0`` (a straight drive, which
goes through the obstacles). All B elements are solved in one batched
``ILQR(constraints=...)`` call; the script prints status counts, the largest violation,
the cost, the iterations, the wall time and the closest approach to each obstacle.

    python examples/constrained_unicycle.py                  # B = 64, about 15 s (1 core)
    python examples/constrained_unicycle.py --batch 512 --plot runs/unicycle.png
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

import torchslq as ts
from torchslq.systems import Unicycle

DT, T = 0.1, 40
GOAL = (4.0, 0.0, 0.0)
# (ox, oy, r): every obstacle is touched by some of the optimal paths
OBSTACLES = ((1.2, 0.25, 0.45), (2.6, -0.35, 0.5), (2.2, 0.9, 0.4))
V_MAX, W_MAX = 2.0, 3.0
V_INIT = 1.0  # m/s, the initial guess: GOAL's distance over T * DT


def obstacle_rows(x: torch.Tensor, u: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``r^2 - |p - o|^2 (..., T, 3)``: positive inside an obstacle."""
    obs = torch.tensor(OBSTACLES, dtype=x.dtype, device=x.device)
    d = x[..., None, :2] - obs[:, :2]
    return obs[:, 2] ** 2 - (d * d).sum(-1)


def obstacle_jacobians(x: torch.Tensor, u: torch.Tensor, t: torch.Tensor):
    """``(c_x (..., T, 3, 3), c_u (..., T, 3, 2))`` of :func:`obstacle_rows`."""
    obs = torch.tensor(OBSTACLES, dtype=x.dtype, device=x.device)
    cx = x.new_zeros(*x.shape[:-1], len(OBSTACLES), 3)
    cx[..., :2] = -2.0 * (x[..., None, :2] - obs[:, :2])
    return cx, u.new_zeros(*u.shape[:-1], len(OBSTACLES), 2)


def initial_states(batch: int, seed: int = 0) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    x0 = np.zeros((batch, 3))
    x0[:, 1] = rng.uniform(-1.0, 1.0, batch)
    x0[:, 2] = rng.uniform(-0.5, 0.5, batch)
    return torch.from_numpy(x0)


def initial_controls(batch: int) -> torch.Tensor:
    u = torch.zeros(batch, T, 2, dtype=torch.float64)
    u[..., 0] = V_INIT
    return u


class UserUnicycle(ts.Dynamics):
    """The same Euler step written as a user would (no compiled hooks): the library's
    speed on a user's own model (``--model user`` in ``benchmarks/constrained.py``)."""

    state_dim, control_dim = 3, 2

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        th = x[..., 2]
        v, w = u[..., 0] * DT, u[..., 1] * DT
        return torch.stack(
            [x[..., 0] + torch.cos(th) * v, x[..., 1] + torch.sin(th) * v, th + w], -1
        )


def make_problem(model: str = "zoo") -> ts.Problem:
    """``model="zoo"``: :class:`torchslq.systems.Unicycle` (compiled rollouts);
    ``"user"``: :class:`UserUnicycle`."""
    cost = ts.QuadraticCost(
        torch.zeros(3, 3, dtype=torch.float64),
        torch.eye(2, dtype=torch.float64),
        Qf=torch.zeros(3, 3, dtype=torch.float64),
    )
    dyn = UserUnicycle() if model == "user" else Unicycle(DT).double()
    return ts.Problem(dyn, cost, T)


def make_constraints() -> list[ts.Constraints]:
    goal = torch.tensor(GOAL, dtype=torch.float64)
    # analytic Jacobians (optional: torch.func's default costs a vjp + vmap pass per
    # iteration, a third of the solve at small B)
    return [
        ts.Constraints(stage=obstacle_rows, stage_jacobian=obstacle_jacobians),
        ts.Constraints(
            terminal=lambda x: x - goal.to(x),
            kind="equality",
            terminal_jacobian=lambda x: torch.eye(3, dtype=x.dtype).expand(*x.shape[:-1], 3, 3),
        ),
    ]


def make_solver(
    tol: float = 1e-6,
    constraint_tol: float = 1e-6,
    max_iter: int = 300,
    penalty_factor: float = 100.0,
    solver: str = "ilqr",
    **options,
) -> ts.ILQR | ts.DDP:
    """``solver="ilqr"`` (Gauss-Newton constraint Hessian) or ``"ddp"`` (the dynamics'
    and the constraint rows' curvature: fewer inner iterations, each dearer)."""
    return {"ilqr": ts.ILQR, "ddp": ts.DDP}[solver](
        max_iter=max_iter,
        tol=tol,
        u_min=torch.tensor([-V_MAX, -W_MAX]),
        u_max=torch.tensor([V_MAX, W_MAX]),
        constraints=make_constraints(),
        constraint_tol=constraint_tol,
        # the penalty grows 100x when the violation does not shrink fourfold (the
        # default; 10x took 1.5-2.5x the inner iterations to the same solution here)
        penalty_factor=penalty_factor,
        progress=False,
        **options,
    )


def summary(r: ts.SolverResult, wall: float) -> str:
    names = ts.status_names(r.status)
    counts = {k: names.count(k) for k in dict.fromkeys(names)}
    conv = r.status == ts.Status.CONVERGED
    obs = torch.tensor(OBSTACLES, dtype=r.x.dtype)
    clear = ((r.x[:, :-1, None, :2] - obs[:, :2]).norm(dim=-1) - obs[:, 2]).amin((0, 1))
    goal = torch.tensor(GOAL, dtype=r.x.dtype)
    return "\n".join(
        [
            f"B = {r.x.shape[0]}, wall {wall:.1f} s",
            "status: " + ", ".join(f"{k} {v}" for k, v in counts.items()),
            f"max violation: {r.max_violation.max().item():.2e} (converged elements: "
            f"{r.max_violation[conv].max().item() if conv.any() else float('nan'):.2e})",
            f"cost: mean {r.cost.mean().item():.6f}, min {r.cost.min().item():.6f}, "
            f"max {r.cost.max().item():.6f}",
            f"iterations: outer mean {r.outer_iterations.double().mean().item():.1f} "
            f"max {int(r.outer_iterations.max())}; inner (total) mean "
            f"{r.iterations.double().mean().item():.1f} max {int(r.iterations.max())}",
            "closest approach to each obstacle's rim [m]: "
            + ", ".join(f"{c:.2e}" for c in clear.tolist())
            + f"; max |x_T - goal| = {(r.x[:, -1] - goal).abs().max().item():.2e}",
        ]
    )


def plot(r: ts.SolverResult, path: str, count: int = 32) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for ox, oy, rad in OBSTACLES:
        ax.add_patch(plt.Circle((ox, oy), rad, color="0.75"))
    for b in range(min(count, r.x.shape[0])):
        ax.plot(r.x[b, :, 0], r.x[b, :, 1], lw=0.8)
    ax.plot(*GOAL[:2], "k*", ms=12)
    ax.set_aspect("equal")
    ax.set_xlabel("px [m]")
    ax.set_ylabel("py [m]")
    ax.set_title(f"unicycle around obstacles ({min(count, r.x.shape[0])} of {r.x.shape[0]})")
    fig.savefig(path, dpi=120, bbox_inches="tight")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--constraint-tol", type=float, default=1e-6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--plot", default=None, help="save a figure of the paths here")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    problem = make_problem()
    x0 = initial_states(args.batch, args.seed)
    solver = make_solver(args.tol, args.constraint_tol)
    t0 = time.perf_counter()
    r = solver.solve(problem, x0, initial_controls(args.batch))
    wall = time.perf_counter() - t0
    print(
        f"unicycle to {GOAL} around {len(OBSTACLES)} obstacles: |v| <= {V_MAX:g}, "
        f"|w| <= {W_MAX:g}, x_T = goal; cost sum 1/2 |u|^2; T = {T}, dt = {DT}"
    )
    print(summary(r, wall))
    if args.plot:
        plot(r, args.plot)
        print(f"figure: {args.plot}")


if __name__ == "__main__":
    main()
