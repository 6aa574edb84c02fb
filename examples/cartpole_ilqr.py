"""Cart-pole swing-up from 512 initial states in one batch: iLQR, SLQ and DDP.

The problem is the iLQR benchmark setting (:func:`torchslq.tasks.cartpole_swingup`):
point-mass cart-pole (cart 1.0 kg, tip 0.1 kg, pole 0.5 m, g = 9.81, theta = 0 hanging
down), one RK4 step per dt = 0.05 s, T = 50 steps, cost
``sum_t 0.01 u_t^2 + 100 |x_T - [0, pi, 0, 0]|^2``, ``u = 0`` initially,
``x0 = [0, 0.05 N(0, 1), 0, 0]``.

Solved by ``ILQR``, ``SLQ(rollout="closed_loop")``, ``DDP`` (classic value-gradient
second-order terms) and by ``ILQR`` with the force limited to ``|u| <= U_MAX`` (the
unconstrained optimum peaks at about 7.6 N, so the bound is active for a good part of the
horizon). TensorBoard logs go to ``runs/cartpole/<solver>`` and a trajectory figure
per solver to ``runs/cartpole/<solver>.png``; a summary table (iterations, cost, time,
success rate = final angle within 0.1 rad of upright) is printed.

    python examples/cartpole_ilqr.py                 # B = 512
    python examples/cartpole_ilqr.py --batch 64      # quicker
    tensorboard --logdir runs/cartpole
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from torchslq import DDP, ILQR, SLQ, TensorBoardLogger
from torchslq.plotting import trajectory_figure
from torchslq.tasks import cartpole_swingup, swingup_success

U_MAX = 5.0  # N; binds (the unconstrained optimal forces reach about 7.6 N); 4 N is too
# little: iLQR then stops at a local optimum that does not swing up (cost ~65)
LABELS = ["s [m]", "theta [rad]", "s_dot [m/s]", "theta_dot [rad/s]"]


def solvers(max_iter: int, tol: float) -> dict:
    out = {
        "ilqr": ILQR(max_iter=max_iter, tol=tol, compact=True),
        "slq_closed_loop": SLQ(max_iter=max_iter, tol=tol, rollout="closed_loop", compact=True),
        "ddp": DDP(max_iter=max_iter, tol=tol, compact=True),
    }
    out[f"ilqr_umax{U_MAX:g}"] = ILQR(
        max_iter=max_iter, tol=tol, u_min=-U_MAX, u_max=U_MAX, compact=True
    )
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=512)
    ap.add_argument("--max-iter", type=int, default=500)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="runs/cartpole")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    problem, x0 = cartpole_swingup(args.batch, horizon=50, dt=0.05, seed=0)
    dt = problem.dynamics.dt
    rows = []
    for name, solver in solvers(args.max_iter, args.tol).items():
        with TensorBoardLogger(out / name, plot_elements=4, dt=dt) as logger:
            t0 = time.perf_counter()
            res = solver.solve(problem, x0, logger=logger)
            wall = time.perf_counter() - t0
        fig = trajectory_figure(
            res.x,
            res.u,
            dt=dt,
            max_elements=4,
            state_labels=LABELS,
            control_labels=["F [N]"],
            title=f"cart-pole swing-up, {name} (4 of {args.batch})",
        )
        fig.savefig(out / f"{name}.png", dpi=110)
        succ = swingup_success(res.x, angle_index=1).double().mean().item()
        it = res.iterations.double()
        rows.append(
            (
                name,
                it.mean().item(),
                int(it.max()),
                res.cost.mean().item(),
                res.cost.max().item(),
                res.converged.double().mean().item(),
                succ,
                wall,
                res.u.abs().max().item(),
            )
        )
        print(f"{name}: {wall:.1f} s", flush=True)

    print(f"\ncart-pole swing-up, B = {args.batch}, T = 50, dt = 0.05, tol = {args.tol:g}")
    hdr = (
        "| solver | iters mean | iters max | cost mean | cost max | converged | success | "
        "time [s] | max abs u |"
    )
    print(hdr)
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r[0]} | {r[1]:.1f} | {r[2]} | {r[3]:.6f} | {r[4]:.6f} | {100 * r[5]:.1f}% | "
            f"{100 * r[6]:.1f}% | {r[7]:.1f} | {r[8]:.2f} |"
        )
    print(f"\nTensorBoard logs and figures in {out}/ (tensorboard --logdir {out})")


if __name__ == "__main__":
    main()
