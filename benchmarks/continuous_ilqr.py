"""ContinuousILQR benchmarks (1 thread).

* ``convergence``: the discrete ILQR on RK4 grids (N = 100, 500, 2000) vs ContinuousILQR
  at rtol = 1e-4, 1e-6, 1e-8 on a swing-up problem: cost, error against a reference
  cost, iterations and wall time;
* ``batch``: B initial states in one solve vs one-by-one solves (time per problem, and
  the largest difference of the costs).

Problems: ``cartpole-convex`` / ``cartpole-nonconvex`` (Section V of the paper, see
``reproductions/continuous_ilqr.py``) and ``pendulum`` (a pendulum swing-up, tau = u,
horizon 3 s, ``l = 0.1 u^2``, ``Phi = 10 (theta - pi)^2 + thetadot^2``: the same
comparisons at a fraction of the cost).

    OMP_NUM_THREADS=1 python benchmarks/continuous_ilqr.py convergence --problem pendulum
    OMP_NUM_THREADS=1 python benchmarks/continuous_ilqr.py batch --problem pendulum --batch 256

Writes ``benchmarks/results/continuous_ilqr_<bench>_<problem>.{json,md}`` with the
command that produced them.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torchslq as ts  # noqa: E402
from reproductions import continuous_ilqr as rep  # noqa: E402

D = torch.float64


class Pendulum(ts.ContinuousDynamics):
    """theta'' = -(g/l) sin(theta) - b theta' + u (theta = 0 hangs down)."""

    state_dim, control_dim = 2, 1

    def forward(self, x, u, t=None):
        th, om = x[..., 0], x[..., 1]
        return torch.stack([om, -9.81 * torch.sin(th) - 0.1 * om + u[..., 0]], -1)


def _pend_stage(x, u, t):
    return 0.1 * u[..., 0] ** 2


def _pend_terminal(x):
    return 10.0 * (x[..., 0] - math.pi) ** 2 + x[..., 1] ** 2


PEND_TF = 3.0


def continuous_problem(name: str, batch: int = 1, seed: int = 0):
    if name.startswith("cartpole-"):
        problem, x0 = rep.cartpole_problem(name.split("-", 1)[1], batch)
        if batch > 1:  # perturbed initial angles and positions
            g = torch.Generator().manual_seed(seed)
            x0 = x0 + 0.05 * torch.randn(batch, 4, generator=g, dtype=D) * torch.tensor(
                [1.0, 1.0, 0.0, 0.0], dtype=D
            )
        return problem, x0
    cost = ts.Cost(stage=_pend_stage, terminal=_pend_terminal, state_dim=2, control_dim=1)
    problem = ts.ContinuousProblem(Pendulum(), cost, 0.0, PEND_TF)
    x0 = torch.zeros(batch, 2, dtype=D)
    if batch > 1:
        g = torch.Generator().manual_seed(seed)
        x0 = x0 + 0.3 * torch.randn(batch, 2, generator=g, dtype=D)
    return problem, x0


def discrete_problem(name: str, N: int):
    if name.startswith("cartpole-"):
        return rep.discrete_problem(name.split("-", 1)[1], N), torch.tensor([rep.X0], dtype=D)
    dt = PEND_TF / N
    cost = ts.Cost(
        stage=lambda x, u, t: dt * _pend_stage(x, u, t),
        terminal=_pend_terminal,
        state_dim=2,
        control_dim=1,
    )
    return ts.Problem(ts.discretize(Pendulum(), dt), cost, N), torch.zeros(1, 2, dtype=D)


def _warm_up(solver, problem, x0) -> None:
    """Two iterations of the same solver first, untimed: a first call compiles (numba,
    the model's generated code)."""
    solver.with_options(max_iter=2).solve(problem, x0)


def _timed_row(label: str, solver, problem, x0) -> tuple[dict, object]:
    """One solve after a warm-up: its row (cost, iterations, status, seconds) and result."""
    _warm_up(solver, problem, x0)
    t0 = time.perf_counter()
    res = solver.solve(problem, x0)
    row = {
        "method": label,
        "cost": float(res.cost[0]),
        "iterations": int(res.iterations[0]),
        "status": res.status_names()[0],
        "seconds": time.perf_counter() - t0,
    }
    return row, res


def convergence(
    name: str, rtols, grids, max_iter: int, discrete_max_iter: int, reused: list[dict]
) -> list[dict]:
    """The discrete solvers on each grid, then ContinuousILQR at each rtol (or its rows
    ``reused`` from an earlier run's JSON)."""
    rows = []
    floor = torch.finfo(D).eps ** 0.5  # the continuous solver's regularisation (11)
    discrete = {
        "ILQR": lambda: ts.ILQR(
            max_iter=discrete_max_iter, tol=1e-8, hessian_floor=floor, progress=False
        ),
        # second-order: on the coarse cart-pole grids ILQR stalls far from the optimum
        "DDP": lambda: ts.DDP(max_iter=discrete_max_iter, tol=1e-8, progress=False),
    }
    for N in grids:
        problem, x0 = discrete_problem(name, N)
        for label, make in discrete.items():
            rows.append(_timed_row(f"{label} RK4 N={N}", make(), problem, x0)[0])
    rows += reused
    for rtol in rtols if not reused else ():
        problem, x0 = continuous_problem(name)
        solver = ts.ContinuousILQR(max_iter=max_iter, rtol=rtol, atol=rtol * 1e-2, progress=False)
        row, res = _timed_row(f"ContinuousILQR rtol={rtol:g}", solver, problem, x0)
        h = res.history
        row.update(n_fwd_last=int(h["n_fwd"][0, -1]), n_bwd_last=int(h["n_bwd"][0, -1]))
        rows.append(row)
    ref = rows[-1]["cost"]  # the tightest continuous solve
    for r in rows:
        r.pop("error_vs_tightest", None)
        r["error_vs_tightest"] = abs(r["cost"] - ref)
    return rows


def batch(name: str, B: int, singles: int, rtol: float, max_iter: int) -> list[dict]:
    problem, x0 = continuous_problem(name, B)
    solver = ts.ContinuousILQR(max_iter=max_iter, rtol=rtol, atol=rtol * 1e-2, progress=False)
    _warm_up(solver, problem, x0[:1])
    t0 = time.perf_counter()
    res = solver.solve(problem, x0)
    t_batch = time.perf_counter() - t0
    diffs, t_one = [], 0.0
    for b in range(singles):
        t0 = time.perf_counter()
        one = solver.solve(problem, x0[b : b + 1])
        t_one += time.perf_counter() - t0
        diffs.append(abs(float(one.cost[0]) - float(res.cost[b])) / max(abs(float(one.cost[0])), 1))
    names = res.status_names()
    return [
        {
            "B": B,
            "rtol": rtol,
            "batched_seconds": t_batch,
            "batched_seconds_per_problem": t_batch / B,
            "one_by_one_seconds_per_problem": t_one / singles,
            "one_by_one_solved": singles,
            "speedup_per_problem": (t_one / singles) / (t_batch / B),
            "max_rel_cost_diff_batch_vs_single": max(diffs),
            "converged": names.count("converged"),
            "status_counts": {s: names.count(s) for s in set(names)},
            "iterations_max": int(res.iterations.max()),
            "fwd_steps_range": [int(res.mask.sum(1).min()) - 1, int(res.mask.sum(1).max()) - 1],
        }
    ]


def _md(rows: list[dict]) -> str:
    keys = list(rows[0].keys())
    out = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        cells = [f"{v:.6g}" if isinstance(v, float) else str(v) for v in (r[k] for k in keys)]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("bench", choices=("convergence", "batch"))
    p.add_argument(
        "--problem",
        default="pendulum",
        choices=("pendulum", "cartpole-convex", "cartpole-nonconvex"),
    )
    p.add_argument("--rtols", type=float, nargs="+", default=[1e-4, 1e-6, 1e-8])
    p.add_argument("--grids", type=int, nargs="+", default=[100, 500, 2000])
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--singles", type=int, default=8, help="one-by-one solves timed")
    p.add_argument("--rtol", type=float, default=1e-6)
    p.add_argument("--max-iter", type=int, default=200)
    p.add_argument(
        "--discrete-max-iter",
        type=int,
        default=1000,
        help="ILQR's limit (it takes more, cheaper iterations: 245 on the convex cart-pole)",
    )
    p.add_argument(
        "--reuse-continuous",
        action="store_true",
        help="convergence: take the ContinuousILQR rows (an hour on the cart-pole) from the "
        "existing result file and rerun the discrete rows only",
    )
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    out = Path(a.out)
    stem = f"continuous_ilqr_{a.bench}_{a.problem}"
    reused, note = [], ""
    if a.reuse_continuous:
        old = json.loads((out / f"{stem}.json").read_text())
        reused = [r for r in old["rows"] if r["method"].startswith("ContinuousILQR")]
        note = f" (ContinuousILQR rows from the earlier run `{old['command']}`)"
    if a.bench == "convergence":
        rows = convergence(a.problem, a.rtols, a.grids, a.max_iter, a.discrete_max_iter, reused)
    else:
        rows = batch(a.problem, a.batch, a.singles, a.rtol, a.max_iter)
    cmd = "OMP_NUM_THREADS=1 python benchmarks/continuous_ilqr.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    md = f"Command: `{cmd}`{note} (torch.set_num_threads(1))\n\n{_md(rows)}\n"
    print(md)
    out.mkdir(parents=True, exist_ok=True)
    record = {"command": cmd, "rows": rows}
    if reused:
        record["continuous_rows_from"] = old["command"]
    (out / f"{stem}.json").write_text(json.dumps(record, indent=1))
    (out / f"{stem}.md").write_text(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
