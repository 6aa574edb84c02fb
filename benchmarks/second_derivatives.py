"""Analytic second derivatives (a model's ``vhp``) against reverse-over-reverse autodiff.

Not part of the test suite. Run from the repo root::

    .venv/bin/python benchmarks/second_derivatives.py            # full
    .venv/bin/python benchmarks/second_derivatives.py --quick    # smaller, -> /tmp

float64, ``torch.set_num_threads(1)``; both ways alternate in one process and the
reported time is the minimum over the repeats (median beside it). The autodiff side is the
same step wrapped in a ``Dynamics`` that keeps its analytic Jacobians but has no ``vhp``,
so :func:`torchslq.dynamics.dynamics_vhp` / ``dynamics_hessians`` differentiate it
(reverse-over-reverse, ``vmap`` over the basis, in chunks of
``HESSIAN_CHUNK_ROWS`` rows).

* ``vhp`` / ``hessians``: one call on random states, controls and weights of shape
  ``(B, T, .)``: the cart-pole RK4 step (``CartPole.vhp`` chained through RK4 by stage
  adjoints) and the unicycle (``torchslq.systems.Unicycle``, discrete);
* ``solve``: DDP (value mode: all output Hessians; costate mode: one VHP per iteration)
  on the cart-pole swing-up of ``benchmarks/peers.py`` (B = 64) and the unicycle
  (B = 512), ``tol = 1e-6``, ``compact=True``; iterations and the largest relative cost
  difference between the two ways are printed beside the times.

Results go to ``--out`` (``second_derivatives.{json,md}``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import torchslq as ts  # noqa: E402
from torchslq.dynamics import dynamics_hessians, dynamics_vhp  # noqa: E402
from torchslq.systems import CartPole, MassChain, Unicycle  # noqa: E402

F64 = torch.float64


class Autodiff(ts.Dynamics):
    """``step`` with its analytic Jacobians but without ``vhp``: autodiff second derivatives."""

    def __init__(self, step):
        super().__init__()
        self.step, self.state_dim, self.control_dim = step, step.state_dim, step.control_dim

    def forward(self, x, u):
        return self.step(x, u)

    def jacobians(self, x, u):
        return self.step.jacobians(x, u)


def _alternate(fns: dict, repeats: int) -> tuple[dict[str, list[float]], dict]:
    times = {k: [] for k in fns}
    out = {}
    for k, fn in fns.items():  # warm-up
        out[k] = fn()
    for _ in range(repeats):
        for k, fn in fns.items():
            t = time.perf_counter()
            out[k] = fn()
            times[k].append(time.perf_counter() - t)
    return times, out


def _row(kind: str, case: str, times: dict, extra: dict | None = None) -> dict:
    a, d = times["analytic"], times["autodiff"]
    row = {
        "kind": kind,
        "case": case,
        "analytic_min_s": min(a),
        "analytic_median_s": statistics.median(a),
        "autodiff_min_s": min(d),
        "autodiff_median_s": statistics.median(d),
        "ratio_min": min(d) / min(a),
        **(extra or {}),
    }
    print(
        f"{kind:8s} {case:34s} analytic {min(a) * 1e3:9.2f} ms  autodiff {min(d) * 1e3:9.2f} ms"
        f"  x{row['ratio_min']:.2f}"
        + ("" if not extra else "  " + " ".join(f"{k}={v}" for k, v in extra.items())),
        flush=True,
    )
    return row


def bench_calls(cases, repeats, rows):
    for name, step, B, T in cases:
        g = torch.Generator().manual_seed(0)
        n, m = step.state_dim, step.control_dim
        x = 0.8 * torch.randn(B, T, n, generator=g, dtype=F64)
        u = torch.randn(B, T, m, generator=g, dtype=F64)
        s = torch.randn(B, T, n, generator=g, dtype=F64)
        auto = Autodiff(step)
        for kind, fn in (("vhp", dynamics_vhp), ("hessians", dynamics_hessians)):
            args = (x, u, s) if kind == "vhp" else (x, u)
            fns = {
                "analytic": lambda f=fn, d=step, a=args: f(d, *a),
                "autodiff": lambda f=fn, d=auto, a=args: f(d, *a),
            }
            times, out = _alternate(fns, repeats)
            err = max(
                float((p - q).abs().max())
                for p, q in zip(out["analytic"], out["autodiff"], strict=True)
            )
            rows.append(_row(kind, f"{name} B={B} T={T}", times, {"max_abs_diff": f"{err:.1e}"}))


def bench_solves(cases, repeats, rows):
    from torchslq.tasks import cartpole_swingup

    for name, B, mode in cases:
        if name == "cartpole":
            problem, x0 = cartpole_swingup(B)
        else:  # the peers table's unicycle (crocoddyl's weights; the bench extra)
            from peers import unicycle_problem

            problem, x0 = unicycle_problem(B)
        auto = ts.Problem(Autodiff(problem.dynamics), problem.cost, problem.horizon)
        solver = ts.DDP(second_order=mode, max_iter=500, tol=1e-6, progress=False, compact=True)
        fns = {
            "analytic": lambda s=solver, p=problem, x=x0: s.solve(p, x),
            "autodiff": lambda s=solver, p=auto, x=x0: s.solve(p, x),
        }
        times, out = _alternate(fns, repeats)
        a, d = out["analytic"], out["autodiff"]
        extra = {
            "iters": f"{a.iterations.float().mean():.2f}/{d.iterations.float().mean():.2f}",
            "cost_rel_diff": f"{float(((a.cost - d.cost).abs() / d.cost.abs()).max()):.1e}",
        }
        rows.append(_row("solve", f"{name} B={B} DDP({mode})", times, extra))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--solve-repeats", type=int, default=3)
    ap.add_argument("--out", default=None)
    ap.add_argument("--name", default="second_derivatives")
    args = ap.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out or ("/tmp/torchslq_bench" if args.quick else "benchmarks/results"))
    cartpole = ts.discretize(CartPole(mc=1.0, mp=0.1, l=0.5), 0.05)
    if args.quick:
        calls = [("cart-pole RK4", cartpole, 64, 20)]
        solves = [("cartpole", 8, "value")]
        args.repeats, args.solve_repeats = 3, 1
    else:
        chain = ts.discretize(MassChain(), 0.1)  # the MPC layer benchmark's model
        calls = [
            ("cart-pole RK4", cartpole, 512, 50),
            ("unicycle", Unicycle(0.1), 512, 20),
            ("mass chain RK4", chain, 64, 40),
        ]
        solves = [
            ("cartpole", 64, "value"),
            ("cartpole", 64, "costate"),
            ("unicycle", 512, "value"),
        ]
    load0 = os.getloadavg()
    rows: list[dict] = []
    bench_calls(calls, args.repeats, rows)
    bench_solves(solves, args.solve_repeats, rows)
    cmd = "python benchmarks/second_derivatives.py" + (" --quick" if args.quick else "")
    meta = {
        "command": cmd,
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "torch": torch.__version__,
        "load_start": load0,
        "load_end": os.getloadavg(),
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = [
        "# Analytic second derivatives (`vhp`) vs reverse-over-reverse autodiff",
        "",
        f"`{cmd}`, {meta['date']}, {meta['machine']}, torch {meta['torch']}, float64, "
        f"1 thread; load average {load0[0]:.2f} at start, {meta['load_end'][0]:.2f} at end "
        "(a shared box: times are noisy; the two ways alternate in one process).",
        "",
        "| kind | case | analytic min [ms] | analytic median | autodiff min [ms] | autodiff median | autodiff / analytic | notes |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        notes = " ".join(
            f"{k}={r[k]}" for k in ("max_abs_diff", "iters", "cost_rel_diff") if k in r
        )
        lines.append(
            f"| {r['kind']} | {r['case']} | {r['analytic_min_s'] * 1e3:.2f} | "
            f"{r['analytic_median_s'] * 1e3:.2f} | {r['autodiff_min_s'] * 1e3:.2f} | "
            f"{r['autodiff_median_s'] * 1e3:.2f} | {r['ratio_min']:.2f} | {notes} |"
        )
    (out / f"{args.name}.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / args.name}.json and .md")


if __name__ == "__main__":
    main()
