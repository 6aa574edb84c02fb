"""Before/after timings of three solver internals changed for speed, in one run.

Not part of the test suite. Run from the repo root::

    .venv/bin/python benchmarks/solver_internals.py            # writes benchmarks/results/solver_internals.{md,json}

What is measured (float64, ``torch.set_num_threads(--threads)``, best of ``--repeat``):

* **staged Armijo**: the first ``--iters`` ILQR iterations on the cart-pole swing-up
  (:func:`torchslq.tasks.cartpole_swingup`, B = ``--batch``), with
  :func:`torchslq.solvers.line_search.armijo_search` trying all 20 steps at once
  (``first_trials=None``, the former behaviour) vs the 4 largest first (the default).
  The controls must come out bit-identical; the script checks it.
* **QuadraticCost**: one evaluation of a diagonal-weight tracking cost on the trials of
  a batched line search (``--trials`` x 1 x (T+1) x n, n = 200, T = 200) by the current
  elementwise path vs the former formula (``weights()`` then a broadcast ``Q @ dx``,
  which copies ``Q`` into every trial); values must agree to 1e-12 relative.
* **broadcast_shapes**: ``torchslq._shapes.broadcast_shapes`` vs ``torch.broadcast_shapes``
  on the shapes of a typical call, 2000 calls.

Ratios compare timings from the same invocation.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from pathlib import Path

import torch

import torchslq.solvers.descent as ilqr_module  # the line search of every descent solver
from torchslq import ILQR, QuadraticCost
from torchslq._shapes import broadcast_shapes
from torchslq.solvers.line_search import armijo_search
from torchslq.tasks import cartpole_swingup


def best_of(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def staged_armijo(batch: int, iters: int, repeat: int) -> dict:
    problem, x0 = cartpole_swingup(batch=batch)
    times, us = {}, {}
    for label, first in (("all 20 at once (before)", None), ("4 largest first (now)", 4)):
        ilqr_module.armijo_search = functools.partial(armijo_search, first_trials=first)
        try:
            t, res = best_of(
                lambda: ILQR(max_iter=iters, tol=1e-6, progress=False).solve(problem, x0), repeat
            )
        finally:
            ilqr_module.armijo_search = armijo_search
        times[label], us[label] = t, res.u
    a, b = us.values()
    if not torch.equal(a, b):
        raise AssertionError("staged and all-at-once Armijo gave different controls")
    return {"batch": batch, "iterations": iters, "seconds": times}


def quadratic_cost(trials: int, repeat: int) -> dict:
    n, m, T = 200, 50, 200
    g = torch.Generator().manual_seed(0)
    Q = torch.diag(torch.rand(n, generator=g, dtype=torch.float64))
    R = torch.diag(torch.rand(m, generator=g, dtype=torch.float64))
    A = torch.randn(n, n, generator=g, dtype=torch.float64)
    cost = QuadraticCost(
        Q, R, A @ A.T, x_ref=torch.randn(T + 1, n, generator=g, dtype=torch.float64)
    )
    x = torch.randn(trials, 1, T + 1, n, generator=g, dtype=torch.float64)
    u = torch.randn(trials, 1, T, m, generator=g, dtype=torch.float64)

    def before():
        Qw, Rw = cost.weights(T)
        xr, ur = cost.references(T, x)
        dx, du = x - xr, u - ur
        Jx = (dx * (Qw @ dx.unsqueeze(-1)).squeeze(-1)).sum(-1)
        Ju = (du * (Rw @ du.unsqueeze(-1)).squeeze(-1)).sum(-1)
        return 0.5 * (Jx.sum(-1) + Ju.sum(-1))

    t_before, J_before = best_of(before, repeat)
    t_now, J_now = best_of(lambda: cost(x, u), repeat)
    err = float(((J_now - J_before).abs() / J_before.abs()).max())
    if err > 1e-12:
        raise AssertionError(f"QuadraticCost paths disagree: {err}")
    return {
        "shape": [trials, 1, T + 1, n],
        "seconds": {"broadcast matmul (before)": t_before, "elementwise (now)": t_now},
        "max_rel_diff": err,
    }


def shapes(calls: int, repeat: int) -> dict:
    args = (torch.Size([1]), torch.Size([64]), torch.Size([64]), torch.Size([1]))
    t_torch, _ = best_of(lambda: [torch.broadcast_shapes(*args) for _ in range(calls)], repeat)
    t_ours, _ = best_of(lambda: [broadcast_shapes(*args) for _ in range(calls)], repeat)
    return {
        "calls": calls,
        "seconds": {"torch.broadcast_shapes": t_torch, "torchslq._shapes.broadcast_shapes": t_ours},
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--iters", type=int, default=15)
    p.add_argument("--trials", type=int, default=30)
    p.add_argument("--repeat", type=int, default=2)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default="benchmarks/results/solver_internals")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    results = {
        "staged_armijo": staged_armijo(args.batch, args.iters, args.repeat),
        "quadratic_cost": quadratic_cost(args.trials, args.repeat),
        "broadcast_shapes": shapes(2000, args.repeat),
    }
    meta = {
        "command": "python benchmarks/solver_internals.py "
        + " ".join(f"--{k} {v}" for k, v in vars(args).items() if k != "out"),
        "torch": torch.__version__,
        "machine": platform.machine(),
        "threads": args.threads,
        "load_average": list(os.getloadavg()),
        "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
    }
    lines = [
        "# Solver internals: before/after timings in one run",
        "",
        f"Command: `{meta['command']}`; torch {meta['torch']}, {meta['threads']} thread(s), "
        f"load average at the end {meta['load_average']} (shared 2-core machine).",
        "",
        "| what | before [s] | now [s] | before / now |",
        "|---|---|---|---|",
    ]
    for name, r in results.items():
        (lb, tb), (ln, tn) = r["seconds"].items()
        lines.append(f"| {name}: {lb} -> {ln} | {tb:.4f} | {tn:.4f} | {tb / tn:.1f}x |")
    sa = results["staged_armijo"]
    lines += [
        "",
        f"staged Armijo: cart-pole swing-up, B = {sa['batch']}, first {sa['iterations']} ILQR "
        "iterations; controls bit-identical (checked). QuadraticCost: diagonal Q, R, dense "
        f"Qf, x of shape {results['quadratic_cost']['shape']}; max relative difference "
        f"{results['quadratic_cost']['max_rel_diff']:.1e}. broadcast_shapes: 2000 calls on "
        "four 1-D shapes.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(text)
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))


if __name__ == "__main__":
    main()
