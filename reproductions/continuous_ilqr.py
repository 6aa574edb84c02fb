"""Reproduction of J. Lieskovský, J. Bušek and T. Vyhlídal, "Continuous-time iterative
linear-quadratic regulator", 2025, Section V: the cart-pole swing-up, convex and
non-convex variants, with :class:`torchslq.ContinuousILQR`.

The problem, as in the paper (model reading from PAPER-NOTES: ``mc = 1`` the cart,
``mp = 0.1`` the point mass at the tip, ``l = 0.2``, ``g = 9.81``; ``theta = 0`` hangs
down): horizon ``[0, 2]``, ``x0 = [0, 1e-3 pi, 0, 0]``, initial control ``u = 0``;

* convex: ``l = 1e-3 u^2``, ``Phi = 100 (s^2 + (theta - pi)^2) + sdot^2 + thetadot^2``;
* non-convex: ``l = 1 + cos(theta) + 10 s^2 + 3e-2 u^2``, no final cost.

Printed beside ours: the paper's costs and iteration counts (1.016 in 55; 3.668 in 67)
and an independent optimum of the problem as stated (PAPER-NOTES: about 0.01694 and
2.6656, both almost exactly 1 below the paper's values), and the discrete
:class:`torchslq.ILQR` on RK4 grids (zero-order hold, ``J = sum dt l + Phi``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import torchslq as ts
from torchslq.plotting import save_figure
from torchslq.systems import CartPole

__all__ = [
    "INDEPENDENT",
    "PAPER",
    "VARIANTS",
    "cartpole_problem",
    "discrete_problem",
    "figure_convergence",
    "figure_trajectory",
    "format_rows",
    "reproduce",
    "solve_continuous",
    "solve_discrete",
]

VARIANTS = ("convex", "nonconvex")
PAPER = {
    "convex": {"cost": 1.016, "iterations": 55, "h_bwd": (1e-6, 1.5e-2), "h_fwd": (1e-6, 6.9e-2)},
    "nonconvex": {
        "cost": 3.668,
        "iterations": 67,
        "h_bwd": (3.1e-9, 3.5e-2),
        "h_fwd": (1e-6, 9.7e-2),
    },
}
INDEPENDENT = {"convex": 0.01694, "nonconvex": 2.6656}
X0 = (0.0, 1e-3 * math.pi, 0.0, 0.0)
TF = 2.0


def _stage(variant: str):
    if variant == "convex":
        return lambda x, u, t: 1e-3 * u[..., 0] ** 2
    return lambda x, u, t: (
        1.0 + torch.cos(x[..., 1]) + 10.0 * x[..., 0] ** 2 + 3e-2 * u[..., 0] ** 2
    )


def _terminal(variant: str):
    if variant == "convex":
        return lambda x: (
            100.0 * (x[..., 0] ** 2 + (x[..., 1] - math.pi) ** 2) + x[..., 2] ** 2 + x[..., 3] ** 2
        )
    return None


def _check(variant: str) -> None:
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")


def cartpole_problem(
    variant: str, batch: int = 1, dtype: torch.dtype = torch.float64
) -> tuple[ts.ContinuousProblem, Tensor]:
    """The Section V problem and ``x0 (batch, 4)`` (the paper's initial state)."""
    _check(variant)
    cost = ts.Cost(stage=_stage(variant), terminal=_terminal(variant), state_dim=4, control_dim=1)
    model = CartPole(mc=1.0, mp=0.1, l=0.2, g=9.81)
    problem = ts.ContinuousProblem(model, cost, 0.0, TF)
    x0 = torch.tensor([X0], dtype=dtype).expand(batch, 4).clone()
    return problem.to(dtype), x0


def discrete_problem(variant: str, N: int, dtype: torch.dtype = torch.float64) -> ts.Problem:
    """The same problem on an RK4 grid of ``N`` steps: ``J = sum_k dt l(x_k, u_k) + Phi``."""
    _check(variant)
    dt = TF / N
    stage = _stage(variant)
    cost = ts.Cost(
        stage=lambda x, u, t: dt * stage(x, u, t),
        terminal=_terminal(variant),
        state_dim=4,
        control_dim=1,
    )
    model = ts.discretize(CartPole(mc=1.0, mp=0.1, l=0.2, g=9.81), dt, "rk4")
    return ts.Problem(model, cost, N).to(dtype)


@dataclass
class Run:
    """One solve: the result and its wall time (seconds)."""

    result: Any
    seconds: float


def solve_continuous(
    variant: str, *, rtol: float = 1e-6, max_iter: int = 200, tol: float = 1e-6, batch: int = 1
) -> Run:
    """:class:`torchslq.ContinuousILQR` (``atol = rtol / 100``) on the Section V problem."""
    problem, x0 = cartpole_problem(variant, batch)
    solver = ts.ContinuousILQR(
        max_iter=max_iter, tol=tol, rtol=rtol, atol=rtol * 1e-2, progress=False
    )
    t0 = time.perf_counter()
    res = solver.solve(problem, x0)
    return Run(res, time.perf_counter() - t0)


def solve_discrete(variant: str, N: int, *, max_iter: int = 500, tol: float = 1e-8) -> Run:
    """:class:`torchslq.ILQR` on the RK4 grid of ``N`` steps from the zero control (the
    paper's regularisation: cost Hessians floored at ``sqrt(eps)``)."""
    problem = discrete_problem(variant, N)
    x0 = torch.tensor([X0], dtype=torch.float64)
    solver = ts.ILQR(
        max_iter=max_iter, tol=tol, hessian_floor=torch.finfo(torch.float64).eps ** 0.5,
        progress=False,
    )  # fmt: skip
    t0 = time.perf_counter()
    res = solver.solve(problem, x0)
    return Run(res, time.perf_counter() - t0)


def _range(lo: Tensor, hi: Tensor) -> tuple[float, float]:
    lo, hi = lo[torch.isfinite(lo)], hi[torch.isfinite(hi)]
    return float(lo.min()), float(hi.max())


def summary(variant: str, run: Run) -> dict[str, Any]:
    """Cost, iterations, status, step-size ranges and step counts of a continuous solve
    (element 0), with the paper's and the independent values."""
    res = run.result
    h = res.history
    return {
        "variant": variant,
        "method": "ContinuousILQR",
        "rtol": res.options["rtol"],
        "cost": float(res.cost[0]),
        "iterations": int(res.iterations[0]),
        "status": res.status_names()[0],
        "h_bwd": _range(h["h_bwd_min"][0], h["h_bwd_max"][0]),
        "h_fwd": _range(h["h_fwd_min"][0], h["h_fwd_max"][0]),
        "n_bwd_last": int(h["n_bwd"][0, -1]),
        "n_fwd_last": int(h["n_fwd"][0, -1]),
        "seconds": run.seconds,
        "paper_cost": PAPER[variant]["cost"],
        "paper_iterations": PAPER[variant]["iterations"],
        "independent_cost": INDEPENDENT[variant],
    }


def discrete_summary(variant: str, N: int, run: Run) -> dict[str, Any]:
    res = run.result
    return {
        "variant": variant,
        "method": f"ILQR RK4 N={N}",
        "cost": float(res.cost[0]),
        "iterations": int(res.iterations[0]),
        "status": res.status_names()[0],
        "seconds": run.seconds,
        "paper_cost": PAPER[variant]["cost"],
        "paper_iterations": PAPER[variant]["iterations"],
        "independent_cost": INDEPENDENT[variant],
    }


def reproduce(
    variants: tuple[str, ...] = VARIANTS,
    *,
    rtol: float = 1e-6,
    grids: tuple[int, ...] = (2000,),
    max_iter: int = 200,
) -> tuple[list[dict[str, Any]], dict[str, Run]]:
    """Both variants: ContinuousILQR at ``rtol`` and the discrete ILQR on RK4 grids;
    returns the rows and the continuous runs (for the figures)."""
    rows, runs = [], {}
    for v in variants:
        run = solve_continuous(v, rtol=rtol, max_iter=max_iter)
        runs[v] = run
        rows.append(summary(v, run))
        for N in grids:
            rows.append(discrete_summary(v, N, solve_discrete(v, N)))
    return rows, runs


def format_rows(rows: list[dict[str, Any]]) -> str:
    """A markdown table: ours beside the paper's and the independent optimum."""
    head = (
        "| variant | method | cost (ours) | paper | independent | iterations (ours) | paper "
        "| status | h_bwd range | h_fwd range | s |"
    )
    lines = [head, "|" + "---|" * 11]
    for r in rows:
        hb = r.get("h_bwd")
        hf = r.get("h_fwd")
        fmt = lambda p: "" if p is None else f"{p[0]:.2g} .. {p[1]:.2g}"  # noqa: E731
        lines.append(
            f"| {r['variant']} | {r['method']}"
            + (f" rtol={r['rtol']:g}" if "rtol" in r else "")
            + f" | {r['cost']:.5f} | {r['paper_cost']} | {r['independent_cost']} "
            f"| {r['iterations']} | {r['paper_iterations']} | {r['status']} "
            f"| {fmt(hb)} | {fmt(hf)} | {r['seconds']:.1f} |"
        )
    return "\n".join(lines)


def figure_trajectory(run: Run, path: str | Path, title: str = "") -> Path:
    """Figures 2a/3a: s, theta, the control u and the accumulated cost c over time."""
    import matplotlib.pyplot as plt

    res = run.result
    mk = res.mask[0]
    t = res.t[0][mk].numpy()
    x, u, c = res.x[0][mk].numpy(), res.u[0][mk].numpy(), res.c[0][mk].numpy()
    fig, axes = plt.subplots(4, 1, figsize=(7, 8), sharex=True)
    for ax, y, lab in zip(
        axes,
        (x[:, 0], x[:, 1], u[:, 0], c),
        ("s [m]", "theta [rad]", "u [N]", "c"),
        strict=True,
    ):
        ax.plot(t, y, ".-", ms=3, lw=1)
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t [s] (markers: the forward pass's grid)")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def figure_convergence(run: Run, path: str | Path, title: str = "") -> Path:
    """Figures 2b/3b: total cost J, line-search parameter alpha, N_bwd and N_fwd per
    iteration."""
    import matplotlib.pyplot as plt

    h = run.result.history
    n = int(run.result.iterations[0]) + 1
    it = range(n)
    fig, axes = plt.subplots(4, 1, figsize=(7, 8), sharex=True)
    axes[0].semilogy(it, h["cost"][0, :n].numpy(), ".-")
    axes[0].set_ylabel("J")
    axes[1].semilogy(list(it)[1:], h["step"][0, 1:n].numpy(), ".-")
    axes[1].set_ylabel("alpha")
    axes[2].plot(it, h["n_bwd"][0, :n].numpy(), ".-")
    axes[2].set_ylabel("N_bwd")
    axes[3].plot(it, h["n_fwd"][0, :n].numpy(), ".-")
    axes[3].set_ylabel("N_fwd")
    axes[-1].set_xlabel("iteration")
    for ax in axes:
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)
