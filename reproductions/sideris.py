"""Reproductions of A. Sideris and J. E. Bobrow, "A Fast Sequential Linear Quadratic
Algorithm for Solving Unconstrained Nonlinear Optimal Control Problems", American Control
Conference, 2005, Section 4: the viscous-drag vehicle (Table 1, Figures 1-2) and the
gas-actuated hopper (eq. 66, Figure 3).

The problems are built by :func:`torchslq.tasks.drag_vehicle_problem` and
:func:`torchslq.tasks.hopper_problem`, with these readings of the paper:

* drag vehicle: ``m = 25.9 g = 0.0259 kg`` (with ``m = 25.9`` the target is never
  reached and the problem does not get harder with beta, contradicting Table 1), ``N = 500``, ``Ts = 1/N``, ``r = 10``,
  ``q = 1``, ``qfin = 1e6``; the cost is eq. (65) *as printed* (no 1/2)::

      J = qfin (x(N) - 10)^2 + Ts sum_{n<N} [q (x(n)^2 + v(n)^2) + r u(n)^2]

  which is :class:`torchslq.QuadraticCost` with ``Q = 2 Ts q I``, ``R = 2 Ts r``,
  ``Qf = diag(2 qfin, 0)`` and target ``[10, 0]`` at ``n = N`` (0 before);
* hopper: the literal reading of the garbled eq. (66)::

      J = 1/2 qfin (y(N) - y°)^2 + ydot(N)^2 + tf/(2N) sum_{n<N} [q yp(n)^2 + r u(n)^2]

  with ``qfin = q = 1000``, ``r = 1``, ``N = 100``, ``tf = 1``, i.e. ``Qf = diag(qfin,
  2, 0)``, ``Q = diag(0, 0, q tf/N)``, ``R = r tf/N``; states and controls start at 0.

All values of ``beta`` (or ``y°``) are solved as ONE batch (a per-element ``(B, 1)``
parameter / reference); ``one_by_one=True`` solves them separately, which must give
the same numbers because every element has its own step size, mask and status.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchslq.plotting import save_figure
from torchslq.problem import Problem
from torchslq.solvers import SLQ, GradientMethod, SolverResult
from torchslq.tasks import (
    DRAG,
    HOPPER,
    HOPPER_TARGETS,
    TABLE1_BETAS,
    drag_vehicle_problem,
    hopper_problem,
)

__all__ = [
    "DRAG",
    "HOPPER",
    "PAPER_HOPPER",
    "PAPER_TABLE1",
    "PAPER_TABLE1_NEWTON",
    "TABLE1_BETAS",
    "HOPPER_TARGETS",
    "drag_vehicle_problem",
    "format_table",
    "hopper_problem",
    "hopper_report",
    "hopper_rows",
    "plot_drag_solution",
    "plot_hopper",
    "plot_relative_cost",
    "relative_cost_histories",
    "reproduce_hopper",
    "reproduce_table1",
    "solve_drag_vehicle",
    "solve_hopper",
    "table1_report",
    "table1_rows",
]

#: Table 1, SLQ column (a string where the paper reports no count).
PAPER_TABLE1: dict[float, int | str] = {
    0.01: 9,
    0.05: 20,
    0.1: 21,
    0.5: 35,
    1.0: "no convergence in 300",
}
#: Table 1, modified Newton column (not reproduced here; for reference only).
PAPER_TABLE1_NEWTON: dict[float, int | str] = {
    0.01: 72,
    0.05: 123,
    0.1: 90,
    0.5: "no convergence in 300",
    1.0: "no convergence in 300",
}
#: Section 4.2 text: "ranging from 3 for y° = 1, to 166 for y° = 50".
PAPER_HOPPER: dict[float, int | str] = {1.0: 3, 20.0: "not stated", 50.0: 166}


# ---------------------------------------------------------------------------- solving
def _make_solver(method: str, line_search: str, max_iter: int, tol: float, progress: bool, **kw):
    if method == "slq":
        return SLQ(max_iter=max_iter, tol=tol, line_search=line_search, progress=progress, **kw)
    if method == "gradient":
        return GradientMethod(
            max_iter=max_iter, tol=tol, line_search=line_search, progress=progress, **kw
        )
    raise ValueError(f"method must be 'slq' or 'gradient', got {method!r}")


def _pad_history(h: Tensor, length: int, fill_last: bool) -> Tensor:
    extra = length - h.shape[-1]
    if extra <= 0:
        return h
    tail = h[..., -1:] if fill_last else torch.zeros_like(h[..., -1:])
    return torch.cat([h, tail.expand(*h.shape[:-1], extra)], dim=-1)


def _cat_results(results: Sequence[SolverResult]) -> SolverResult:
    """Concatenate separate solves along the batch dim (histories padded with each
    element's final values, as a batched solve records finished elements)."""
    L = max(r.history["cost"].shape[-1] for r in results)
    hist = {
        k: torch.cat([_pad_history(r.history[k], L, fill_last=k != "step") for r in results])
        for k in ("cost", "grad_norm", "step")
    }
    hist["time"] = torch.tensor([float(r.history["time"][-1]) for r in results])
    fields = ("x", "u", "cost", "grad_norm", "iterations", "status", "converged", "K", "k")
    return SolverResult(
        **{f: torch.cat([getattr(r, f) for r in results]) for f in fields},
        history=hist,
        options=results[0].options,
    )


def _solve(
    problem: Problem,
    x0: Tensor,
    solver,
    one_by_one: bool,
    build_one,
) -> tuple[SolverResult, float]:
    t0 = time.perf_counter()
    if not one_by_one:
        res = solver.solve(problem, x0)
    else:
        res = _cat_results([solver.solve(*build_one(i)) for i in range(x0.shape[0])])
    return res, time.perf_counter() - t0


def solve_drag_vehicle(
    betas: Sequence[float] = TABLE1_BETAS,
    *,
    method: str = "slq",
    line_search: str = "armijo",
    max_iter: int = 300,
    tol: float = 1e-6,
    one_by_one: bool = False,
    progress: bool = False,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
    **solver_kwargs: Any,
) -> tuple[Problem, SolverResult, float]:
    """Solve the drag-vehicle problems from ``u = 0`` (the gradient-norm stopping test of
    Section 4); returns ``(problem, result, wall_seconds)``.

    ``one_by_one=True`` solves each beta as its own (batch of one) problem and
    concatenates the results; ``result.history["time"]`` then holds each solve's time.
    """
    betas = [float(b) for b in torch.as_tensor(betas, dtype=torch.float64).reshape(-1)]
    problem, x0 = drag_vehicle_problem(betas, dtype=dtype, device=device)
    solver = _make_solver(method, line_search, max_iter, tol, progress, **solver_kwargs)

    def one(i: int):
        return drag_vehicle_problem([betas[i]], dtype=dtype, device=device)

    res, wall = _solve(problem, x0, solver, one_by_one, one)
    return problem, res, wall


def solve_hopper(
    y_targets: Sequence[float] = HOPPER_TARGETS,
    *,
    method: str = "slq",
    line_search: str = "armijo",
    max_iter: int = 300,
    tol: float = 1e-6,
    one_by_one: bool = False,
    progress: bool = False,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
    **solver_kwargs: Any,
) -> tuple[Problem, SolverResult, float]:
    """Solve the hopper problems from zero states and controls; returns
    ``(problem, result, wall_seconds)`` (see :func:`solve_drag_vehicle`)."""
    ys = [float(y) for y in torch.as_tensor(y_targets, dtype=torch.float64).reshape(-1)]
    problem, x0 = hopper_problem(ys, dtype=dtype, device=device)
    solver = _make_solver(method, line_search, max_iter, tol, progress, **solver_kwargs)

    def one(i: int):
        return hopper_problem([ys[i]], dtype=dtype, device=device)

    res, wall = _solve(problem, x0, solver, one_by_one, one)
    return problem, res, wall


# ---------------------------------------------------------------------------- tables
def _paper_value(table: Mapping[float, int | str], key: float) -> int | str:
    for k, v in table.items():
        if abs(k - key) <= 1e-12 * max(1.0, abs(k)):
            return v
    return "-"


def table1_rows(betas: Sequence[float], result: SolverResult) -> list[dict[str, Any]]:
    """One row per beta: the paper's SLQ count beside ours, status, optimal cost, gradient
    norm, final position, peak speed and the explicit-Euler stability limit
    ``m / (beta Ts)`` of the speed."""
    names = result.status_names()
    rows = []
    Ts = 1.0 / DRAG["N"]
    for i, b in enumerate(betas):
        v = result.x[i, :, 1]
        rows.append(
            {
                "beta": float(b),
                "paper": _paper_value(PAPER_TABLE1, float(b)),
                "iterations": int(result.iterations[i]),
                "status": names[i],
                "cost": float(result.cost[i]),
                "grad_norm": float(result.grad_norm[i]),
                "x_N": float(result.x[i, -1, 0]),
                "v_max": float(v.abs().max()),
                "v_euler_limit": DRAG["m"] / (float(b) * Ts) if b > 0 else float("inf"),
            }
        )
    return rows


def _stance_phases(x: Tensor) -> int:
    """Number of maximal runs of ground contact (``yp - y >= 0``) along a trajectory."""
    contact = (x[:, 2] - x[:, 0] >= 0).to(torch.int64)
    starts = contact[1:] > contact[:-1]
    return int(contact[0]) + int(starts.sum())


def hopper_rows(y_targets: Sequence[float], result: SolverResult) -> list[dict[str, Any]]:
    """One row per target height: the paper's count, ours, status, cost, gradient norm,
    ``y(N)``, ``ydot(N)`` and the number of stance phases."""
    names = result.status_names()
    rows = []
    for i, y in enumerate(y_targets):
        rows.append(
            {
                "y_target": float(y),
                "paper": _paper_value(PAPER_HOPPER, float(y)),
                "iterations": int(result.iterations[i]),
                "status": names[i],
                "cost": float(result.cost[i]),
                "grad_norm": float(result.grad_norm[i]),
                "y_N": float(result.x[i, -1, 0]),
                "ydot_N": float(result.x[i, -1, 1]),
                "stance_phases": _stance_phases(result.x[i]),
            }
        )
    return rows


def reproduce_table1(
    betas: Sequence[float] = TABLE1_BETAS,
    *,
    line_search: str = "armijo",
    max_iter: int = 300,
    tol: float = 1e-6,
    one_by_one: bool = False,
    progress: bool = False,
    **kwargs: Any,
) -> list[dict[str, Any]]:
    """Table 1 (SLQ column): rows of :func:`table1_rows` for all betas solved as one batch
    (or one by one)."""
    _, res, _ = solve_drag_vehicle(
        betas,
        line_search=line_search,
        max_iter=max_iter,
        tol=tol,
        one_by_one=one_by_one,
        progress=progress,
        **kwargs,
    )
    return table1_rows(betas, res)


def reproduce_hopper(
    y_targets: Sequence[float] = HOPPER_TARGETS,
    *,
    line_search: str = "armijo",
    max_iter: int = 300,
    tol: float = 1e-6,
    one_by_one: bool = False,
    progress: bool = False,
    **kwargs: Any,
) -> list[dict[str, Any]]:
    """Section 4.2 iteration counts: rows of :func:`hopper_rows`."""
    _, res, _ = solve_hopper(
        y_targets,
        line_search=line_search,
        max_iter=max_iter,
        tol=tol,
        one_by_one=one_by_one,
        progress=progress,
        **kwargs,
    )
    return hopper_rows(y_targets, res)


_HEADINGS = {
    "beta": "beta",
    "y_target": "y°",
    "paper": "paper (SLQ iters)",
    "iterations": "ours (iters)",
    "status": "status",
    "cost": "optimal cost J",
    "grad_norm": "‖∇J‖",
    "x_N": "x(N)",
    "v_max": "max speed",
    "v_euler_limit": "m/(β Ts)",
    "y_N": "y(N)",
    "ydot_N": "ẏ(N)",
    "stance_phases": "stance phases",
    "one_by_one": "ours, one by one",
}


def _fmt(key: str, v: Any) -> str:
    if isinstance(v, str):
        return v
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if key in ("beta", "y_target"):
            return f"{v:g}"
        if key == "grad_norm":
            return f"{v:.2e}"
        if key in ("x_N", "y_N", "ydot_N", "v_max", "v_euler_limit"):
            return f"{v:.4g}"
        return f"{v:.8g}"
    return str(v)


def format_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None) -> str:
    """A markdown table of ``rows`` (all keys of the first row unless ``columns``)."""
    if not rows:
        return ""
    cols = list(columns) if columns is not None else list(rows[0].keys())
    head = "| " + " | ".join(_HEADINGS.get(c, c) for c in cols) + " |"
    sep = "|" + "|".join("---" for _ in cols) + "|"
    body = ["| " + " | ".join(_fmt(c, r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join([head, sep, *body])


# ---------------------------------------------------------------------------- figures
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _np(t: Tensor):
    return t.detach().to("cpu", torch.float64).numpy()


def plot_drag_solution(
    result: SolverResult, index: int, path: str | Path, *, beta: float | None = None
) -> Path:
    """Figure 1 style: optimal position, velocity and force of batch element ``index``."""
    plt = _plt()
    x, u = _np(result.x[index]), _np(result.u[index])
    N = u.shape[0]
    t = [i / N for i in range(N + 1)]
    fig, axes = plt.subplots(3, 1, figsize=(6.5, 7), sharex=True)
    axes[0].plot(t, x[:, 0])
    axes[0].set_ylabel("position x (m)")
    axes[1].plot(t, x[:, 1])
    axes[1].set_ylabel("velocity v (m/s)")
    axes[2].plot(t[:-1], u[:, 0])
    axes[2].set_ylabel("force u (N)")
    axes[2].set_xlabel("time (s)")
    for ax in axes:
        ax.grid(alpha=0.3)
    ttl = "Viscous-drag vehicle, optimal solution (Sideris & Bobrow Fig. 1)"
    if beta is not None:
        ttl += f", beta = {beta:g}"
    fig.suptitle(ttl, fontsize=10)
    return save_figure(fig, path)


def relative_cost_histories(
    beta: float = 0.1,
    *,
    line_search: str = "armijo",
    max_iter: int = 300,
    sd_line_search: str = "exact",
    sd_max_iter: int = 300,
    tol: float = 1e-6,
    progress: bool = False,
) -> dict[str, Any]:
    """Cost per iteration of SLQ and of steepest descent (:class:`GradientMethod`, exact
    line search over an adaptive range) on the drag vehicle, for Figure 2.

    Returns ``{"histories": {label: (K+1,) tensor}, "J_star": float, "results": {...}}``
    with ``J*`` the lowest cost any method reached.
    """
    _, slq, _ = solve_drag_vehicle(
        [beta], line_search=line_search, max_iter=max_iter, tol=tol, progress=progress
    )
    _, sd, _ = solve_drag_vehicle(
        [beta],
        method="gradient",
        line_search=sd_line_search,
        max_iter=sd_max_iter,
        tol=tol,
        progress=progress,
    )
    hist = {}
    for label, r in ((f"SLQ ({line_search})", slq), (f"steepest descent ({sd_line_search})", sd)):
        hist[label] = r.history["cost"][0, : int(r.iterations[0]) + 1]
    J_star = min(float(h.min()) for h in hist.values())
    return {"histories": hist, "J_star": J_star, "results": {"slq": slq, "gradient": sd}}


def plot_relative_cost(
    histories: Mapping[str, Tensor], J_star: float, path: str | Path, *, title: str | None = None
) -> Path:
    """Figure 2 style: ``(J_k - J*) / J*`` against iteration ``k`` on a log scale (points
    at or below ``J*`` are not drawn)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for label, h in histories.items():
        rel = (_np(h) - J_star) / abs(J_star)
        rel[rel <= 0] = float("nan")
        ax.semilogy(range(len(rel)), rel, marker="." if len(rel) < 60 else None, label=label)
    ax.set_xlabel("iteration k")
    ax.set_ylabel("(J_k - J*) / J*")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    ax.set_title(title or "Relative cost (Sideris & Bobrow Fig. 2)", fontsize=10)
    return save_figure(fig, path)


def plot_hopper(
    result: SolverResult,
    y_targets: Sequence[float],
    path: str | Path,
    *,
    tf: float = HOPPER["tf"],
) -> Path:
    """Figure 3 style: height ``y`` with the piston ``yp``, and the control ``u = ẏp``
    against time, one column per target height."""
    plt = _plt()
    k = len(y_targets)
    fig, axes = plt.subplots(2, k, figsize=(4.2 * k, 5.5), sharex=True, squeeze=False)
    for i, yt in enumerate(y_targets):
        x, u = _np(result.x[i]), _np(result.u[i])
        N = u.shape[0]
        t = [tf * j / N for j in range(N + 1)]
        ax = axes[0, i]
        ax.plot(t, x[:, 0], label="height y")
        ax.plot(t, x[:, 2], label="piston yp")
        ax.axhline(yt, color="k", lw=0.6, ls="--", label="target y°")
        ax.set_title(f"y° = {yt:g}", fontsize=10)
        ax.grid(alpha=0.3)
        axes[1, i].step(t[:-1], u[:, 0], where="post", color="C2")
        axes[1, i].set_xlabel("time (s)")
        axes[1, i].grid(alpha=0.3)
    axes[0, 0].set_ylabel("position (in)")
    axes[0, 0].legend(fontsize=8)
    axes[1, 0].set_ylabel("control u = dyp/dt (in/s)")
    fig.suptitle("Gas-actuated hopper (Sideris & Bobrow Fig. 3)", fontsize=10)
    return save_figure(fig, path)


# ---------------------------------------------------------------------------- reports
def _agreement(rows: list[dict[str, Any]], solo: list[dict[str, Any]], key: str, label: str) -> str:
    """Attach the one-by-one counts to ``rows``; a sentence saying whether they agree."""
    diff = []
    dJ = 0.0
    for r, s in zip(rows, solo, strict=True):
        r["one_by_one"] = s["iterations"]
        if (r["iterations"], r["status"]) != (s["iterations"], s["status"]):
            diff.append(
                f"{label} = {r[key]:g}: {r['iterations']} ({r['status']}) batched vs "
                f"{s['iterations']} ({s['status']}) alone"
            )
        dJ = max(dJ, abs(r["cost"] - s["cost"]) / max(1.0, abs(s["cost"])))
    head = "Batched and one-by-one solves: "
    if not diff:
        head += "same iteration counts and statuses"
    else:
        head += "iteration counts differ for " + "; ".join(diff)
    return head + f"; max relative difference of the final costs {dJ:.1e}."


def _write(path: str | Path | None, text: str) -> None:
    if path is None:
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


TABLE1_COLUMNS = (
    "beta",
    "paper",
    "iterations",
    "one_by_one",
    "status",
    "cost",
    "grad_norm",
    "x_N",
    "v_max",
    "v_euler_limit",
)
HOPPER_COLUMNS = (
    "y_target",
    "paper",
    "iterations",
    "one_by_one",
    "status",
    "cost",
    "grad_norm",
    "y_N",
    "ydot_N",
    "stance_phases",
)


def _batched_and_single(
    tag,
    key,
    label,
    columns,
    values,
    solve,
    rows_of,
    *,
    line_searches,
    max_iter,
    tol,
    one_by_one,
    progress,
    log,
):
    """For each line search: solve all ``values`` as one batch (and, with ``one_by_one``,
    each alone), tabulate, and yield ``(line_search, batched result, markdown section)``."""
    for ls in line_searches:
        _, res, wall = solve(values, line_search=ls, max_iter=max_iter, tol=tol, progress=progress)
        log(f"[{tag}] {ls}: batch of {len(values)} solved in {wall:.1f} s")
        rows = rows_of(values, res)
        agree = ""
        if one_by_one:
            _, solo, wall1 = solve(
                values, line_search=ls, max_iter=max_iter, tol=tol, one_by_one=True
            )
            log(f"[{tag}] {ls}: one by one solved in {wall1:.1f} s")
            agree = _agreement(rows, rows_of(values, solo), key, label)
            agree += f" Wall time {wall:.1f} s batched, {wall1:.1f} s one by one."
        cols = [c for c in columns if one_by_one or c != "one_by_one"]
        table = format_table(rows, cols)
        log(f"\nline search: {ls}\n{table}\n{agree}")
        section = f"### SLQ, line search `{ls}` (max_iter {max_iter}, tol {tol:g})\n\n"
        section += table + "\n\n" + (agree + "\n" if agree else "")
        yield ls, res, section


def table1_report(
    *,
    line_searches: Sequence[str] = ("armijo", "exact"),
    betas: Sequence[float] = TABLE1_BETAS,
    max_iter: int = 300,
    tol: float = 1e-6,
    one_by_one: bool = True,
    sd_max_iter: int = 200,
    out_dir: str | Path | None = "runs/sideris",
    results_path: str | Path | None = "benchmarks/results/sideris_table1.md",
    command: str | None = None,
    notes: str | None = None,
    progress: bool = False,
    log=print,
) -> str:
    """Reproduce Table 1 and Figures 1-2; returns (and writes) a markdown report.

    For every line search, all betas are solved as ONE batch and (``one_by_one``) again
    separately; Figure 1 is the batched beta = 0.1 solution of the first line search,
    Figure 2 the relative cost of SLQ (each line search) and of steepest descent
    (:class:`GradientMethod`, exact search) for beta = 0.1.
    """
    betas = [float(b) for b in betas]
    out = None if out_dir is None else Path(out_dir)
    sections = []
    slq_hist: dict[str, Tensor] = {}
    first = None
    for ls, res, section in _batched_and_single(
        "table1",
        "beta",
        "beta",
        TABLE1_COLUMNS,
        betas,
        solve_drag_vehicle,
        table1_rows,
        line_searches=line_searches,
        max_iter=max_iter,
        tol=tol,
        one_by_one=one_by_one,
        progress=progress,
        log=log,
    ):
        sections.append(section)
        if first is None:
            first = res
        if 0.1 in betas:
            i = betas.index(0.1)
            slq_hist[f"SLQ ({ls})"] = res.history["cost"][i, : int(res.iterations[i]) + 1]

    figs = []
    if out is not None and first is not None and 0.1 in betas:
        figs.append(
            plot_drag_solution(first, betas.index(0.1), out / "fig1_drag_beta0.1.png", beta=0.1)
        )
    sd_line = ""
    if sd_max_iter > 0:
        _, sd, wall_sd = solve_drag_vehicle(
            [0.1],
            method="gradient",
            line_search="exact",
            max_iter=sd_max_iter,
            tol=tol,
            progress=progress,
        )
        h_sd = sd.history["cost"][0, : int(sd.iterations[0]) + 1]
        hist = {**slq_hist, "steepest descent (exact)": h_sd}
        J_star = min(float(h.min()) for h in hist.values())
        rel = (h_sd - J_star) / J_star
        marks = [k for k in (1, 10, 50, 100, 200, 500) if k < rel.shape[0]] + [rel.shape[0] - 1]
        sd_line = (
            f"Steepest descent (GradientMethod, exact search over an adaptive range), "
            f"beta = 0.1, {int(sd.iterations[0])} iterations in {wall_sd:.1f} s, status "
            f"{sd.status_names()[0]}, final gradient norm {float(sd.grad_norm[0]):.2e}; "
            "relative cost (J_k - J*)/J*: "
            + ", ".join(f"k={k}: {float(rel[k]):.2e}" for k in dict.fromkeys(marks))
            + f" (J* = {J_star:.10g}, the lowest cost reached)."
        )
        log("\n" + sd_line)
        if out is not None:
            figs.append(
                plot_relative_cost(
                    hist,
                    J_star,
                    out / "fig2_relative_cost_beta0.1.png",
                    title="Relative cost, drag vehicle beta = 0.1 (Sideris & Bobrow Fig. 2)",
                )
            )
    for f in figs:
        log(f"saved {f}")

    text = "# Sideris & Bobrow (2005), Table 1: viscous-drag vehicle\n\n"
    if command:
        text += f"Command: `{command}`\n\n"
    text += (
        "Problem: eqs. (63)-(65) with these readings (m = 0.0259 kg, N = 500, "
        "r = 10, q = 1, qfin = 1e6, eq. 65 without a 1/2), u = 0 initially, stop when "
        f"‖∇J‖ < {tol:g}. 'paper' is Table 1's SLQ column; all betas are one batch "
        "('ours'), 'one by one' solves each beta alone. `m/(β Ts)` is the speed above "
        "which the explicit Euler step of the drag is unstable.\n\n"
    )
    text += "\n".join(sections)
    if sd_line:
        text += "\n### Figure 2 baseline\n\n" + sd_line + "\n"
    if figs:
        text += "\nFigures: " + ", ".join(f"`{f}`" for f in figs) + "\n"
    if notes:
        text += "\n" + notes.strip() + "\n"
    _write(results_path, text)
    return text


def hopper_report(
    *,
    line_searches: Sequence[str] = ("armijo", "exact"),
    y_targets: Sequence[float] = HOPPER_TARGETS,
    max_iter: int = 1000,
    tol: float = 1e-6,
    one_by_one: bool = True,
    out_dir: str | Path | None = "runs/sideris",
    results_path: str | Path | None = "benchmarks/results/sideris_hopper.md",
    command: str | None = None,
    notes: str | None = None,
    progress: bool = False,
    log=print,
) -> str:
    """Reproduce the hopper experiment of Section 4.2 and Figure 3; returns (and writes) a
    markdown report (see :func:`table1_report`)."""
    ys = [float(y) for y in y_targets]
    out = None if out_dir is None else Path(out_dir)
    sections, figs = [], []
    for ls, res, section in _batched_and_single(
        "hopper",
        "y_target",
        "y°",
        HOPPER_COLUMNS,
        ys,
        solve_hopper,
        hopper_rows,
        line_searches=line_searches,
        max_iter=max_iter,
        tol=tol,
        one_by_one=one_by_one,
        progress=progress,
        log=log,
    ):
        sections.append(section)
        if out is not None:
            figs.append(plot_hopper(res, ys, out / f"fig3_hopper_{ls}.png"))
    for f in figs:
        log(f"saved {f}")
    text = "# Sideris & Bobrow (2005), Section 4.2: gas-actuated hopper\n\n"
    if command:
        text += f"Command: `{command}`\n\n"
    text += (
        "Problem: Euler hopper (k/m = 500, g = 386.4, alpha = 0.1, N = 100, tf = 1) with the "
        "literal reading of the garbled eq. (66), J = 1/2 qfin (y(N) - y°)^2 + ẏ(N)^2 "
        "+ tf/(2N) Σ [q yp^2 + r u^2], qfin = q = 1000, r = 1; states and controls start "
        f"at 0; stop when ‖∇J‖ < {tol:g}. 'paper' is the count stated in Section 4.2 "
        "(3 for y° = 1, 166 for y° = 50; none for the y° = 20 of Figure 3). 'stance "
        "phases' counts the runs of ground contact (yp ≥ y).\n\n"
    )
    text += "\n".join(sections)
    if figs:
        text += "\nFigures: " + ", ".join(f"`{f}`" for f in figs) + "\n"
    if notes:
        text += "\n" + notes.strip() + "\n"
    _write(results_path, text)
    return text
