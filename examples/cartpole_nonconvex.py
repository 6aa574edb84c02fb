"""Cart-pole swing-up with the non-convex running cost of the continuous-time iLQR paper.

J. Lieskovský, J. Bušek and T. Vyhlídal, "Continuous-time iterative linear-quadratic
regulator", arXiv:2505.15525, 2025, Section V.B, with these model readings (they match the
authors' public code): cart mass mc = 1, tip mass
mp = 0.1, pole length l = 0.2, g = 9.81, theta = 0 hanging down;
``x0 = [0, 1e-3 pi, 0, 0]``, ``u = 0`` initially, horizon 2 s, running cost

    l(x, u) = 1 + cos(theta) + 10 s^2 + 3e-2 u^2,

no final cost. Discretised here with one RK4 step per dt = 2 / N (N = 500) and the
running cost integrated as ``dt * l(x_t, u_t)``, then solved by ``ILQR`` and ``DDP``
(``second_order="value"``), tol 1e-6 on the gradient norm.

The paper reports 3.668 (its own adaptive-step continuous-time solver); an independent
NLP solve of the problem as stated gives the local optimum 2.6656; the paper's numbers
are about 1 higher than the stated problem's in both variants (cause unknown). Our discrete cost is printed beside both.

    python examples/cartpole_nonconvex.py            # ~ a few minutes on 1 thread
    python examples/cartpole_nonconvex.py --max-iter 100 --no-ddp
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

from torchslq import DDP, ILQR, Cost, Problem, discretize
from torchslq.plotting import convergence_figure, trajectory_figure
from torchslq.systems import CartPole

PAPER = 3.668
NLP = 2.6656


def build(N: int = 500, tf: float = 2.0) -> tuple[Problem, torch.Tensor]:
    dt = tf / N
    dyn = discretize(CartPole(mc=1.0, mp=0.1, l=0.2, g=9.81), dt, "rk4").to(torch.float64)

    def stage(x, u, t):
        s, th, F = x[..., 0], x[..., 1], u[..., 0]
        return dt * (1.0 + torch.cos(th) + 10.0 * s**2 + 3e-2 * F**2)

    cost = Cost(stage, state_dim=4, control_dim=1)
    x0 = torch.tensor([[0.0, 1e-3 * math.pi, 0.0, 0.0]], dtype=torch.float64)
    return Problem(dyn, cost, N), x0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--N", type=int, default=500)
    ap.add_argument("--max-iter", type=int, default=300)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--no-ddp", action="store_true")
    ap.add_argument("--out", default="runs/cartpole_nonconvex")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    problem, x0 = build(args.N)
    dt = 2.0 / args.N
    runs = {"ILQR": ILQR(max_iter=args.max_iter, tol=args.tol)}
    if not args.no_ddp:
        runs["DDP"] = DDP(max_iter=args.max_iter, tol=args.tol)
    results = {}
    for name, solver in runs.items():
        t0 = time.perf_counter()
        r = solver.solve(problem, x0)
        results[name] = (r, time.perf_counter() - t0)
        print(f"{name}: J = {r.cost.item():.6f}  ({r.status_names()[0]})", flush=True)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"\nnon-convex cart-pole (l = 0.2, RK4, N = {args.N}, dt = {dt:g}), u_init = 0")
    print("| solver | cost J | paper | NLP optimum | J - NLP | iterations | status | "
          "grad norm | time [s] |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for name, (r, wall) in results.items():
        J = r.cost.item()
        print(
            f"| {name} | {J:.4f} | {PAPER} | {NLP} | {J - NLP:+.4f} | {int(r.iterations)} | "
            f"{r.status_names()[0]} | {r.grad_norm.item():.1e} | {wall:.1f} |"
        )
        fig = trajectory_figure(
            r.x,
            r.u,
            dt=dt,
            state_labels=["s [m]", "theta [rad]", "s_dot [m/s]", "theta_dot [rad/s]"],
            control_labels=["F [N]"],
            title=f"non-convex cart-pole swing-up, {name}",
        )
        fig.savefig(out / f"{name.lower()}.png", dpi=110)
    fig = convergence_figure(
        {k: v[0].history["cost"] for k, v in results.items()},
        title="non-convex cart-pole: cost per iteration",
    )
    fig.savefig(out / "convergence.png", dpi=110)
    print(f"\nfigures in {out}/")
    print(
        "Note: the paper's 3.668 comes from its continuous-time adaptive-step solver; "
        "the stated problem's NLP optimum is 2.6656 (the paper's values are "
        "about 1 higher in both variants, cause unknown). The RK4/N=500 discretisation "
        "differs from the continuous problem by O(dt^4) in the dynamics and O(dt) in the "
        "left-rectangle cost quadrature."
    )


if __name__ == "__main__":
    main()
