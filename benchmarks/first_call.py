"""The first solve in a fresh process: a user's cart-pole model, cold and warm caches.

Not part of the test suite. Each measurement is a new Python process that imports torch
and torchslq, builds the user-models benchmark's problem (``UserCartPole`` of
``examples/constrained_cartpole.py`` under ``torchslq.discretize(..., 0.05, "rk4")``,
T = 50, B = 1) and solves it twice with ``ILQR`` (``max_iter = 500``, ``tol = 1e-6``);
then with ``DDP``; it reports the import times, the first solve (generated code found or
made, kernels loaded or compiled), the second (the steady state), the DDP solve after
them (the kernels DDP needs beyond iLQR's) and whether the process imported torch's
compiler stack (``torch._dynamo``: a second of imports, which code generation avoids).
``install``: numba's cache of the library's own kernels empty too (``NUMBA_CACHE_DIR``
a new directory): the first use after installing, every kernel compiled. ``cold``: an
empty generated-code cache (``TORCHSLQ_CACHE_DIR``) with the library's kernels cached
(beside the installed package, where an earlier run left them); ``warm``: the next
process with that cache.

    .venv/bin/python benchmarks/first_call.py     # 3 install, 3 cold and 3 warm processes
    .venv/bin/python benchmarks/first_call.py --problem masschain   # MassChain(4), (8, 4)

``--problem masschain`` solves the zoo's ``MassChain(4)`` (8 states, 4 controls, T = 20)
instead: a size without LQ kernels compiled for it, whose passes read the sizes at run
time (written to ``first_call_masschain``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from _env import load, package_versions

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, math, sys, time
t0 = time.perf_counter()
import torch
t1 = time.perf_counter()
import torchslq as ts
t2 = time.perf_counter()
sys.path.insert(0, sys.argv[1])
torch.set_num_threads(1)
f64 = torch.float64
if sys.argv[2] == "cartpole":
    from constrained_cartpole import UserCartPole
    dyn = ts.discretize(UserCartPole(), 0.05, "rk4").double()
    cost = ts.QuadraticCost(Q=torch.zeros(4, 4, dtype=f64), R=0.02 * torch.eye(1, dtype=f64),
                            Qf=200.0 * torch.eye(4, dtype=f64),
                            x_ref=torch.tensor([0.0, math.pi, 0.0, 0.0], dtype=f64))
    problem = ts.Problem(dyn, cost, 50)
    x0 = torch.tensor([[0.0, 0.05, 0.0, 0.0]], dtype=f64)
else:  # a size without kernels of its own: (8, 4), the passes that read sizes at run time
    from torchslq.systems import MassChain
    dyn = ts.discretize(MassChain(4, mass=1.0, k3=1.0, damping=0.1), 0.1)
    q = torch.tensor([1.0] * 4 + [0.1] * 4, dtype=f64)
    cost = ts.QuadraticCost(torch.diag(q), 0.1 * torch.eye(4, dtype=f64), 10 * torch.diag(q))
    problem = ts.Problem(dyn, cost, 20)
    x0 = 0.5 * torch.randn(1, 8, generator=torch.Generator().manual_seed(0), dtype=f64)
t3 = time.perf_counter()
r1 = ts.ILQR(max_iter=500, tol=1e-6, progress=False).solve(problem, x0)
t4 = time.perf_counter()
r2 = ts.ILQR(max_iter=500, tol=1e-6, progress=False).solve(problem, x0)
t5 = time.perf_counter()
r3 = ts.DDP(max_iter=500, tol=1e-6, progress=False).solve(problem, x0)
t6 = time.perf_counter()
assert bool(r1.converged.all()) and torch.equal(r1.u, r2.u) and bool(r3.converged.all())
print(json.dumps(dict(import_torch=t1 - t0, import_torchslq=t2 - t1, first_solve=t4 - t3,
                      second_solve=t5 - t4, ddp_after=t6 - t5, iterations=int(r1.iterations[0]),
                      compiler_stack="torch._dynamo" in sys.modules)))
"""


def run(problem: str, cache: str, numba_cache: str | None = None) -> dict:
    env = dict(os.environ, TORCHSLQ_CACHE_DIR=cache, OMP_NUM_THREADS="1")
    if numba_cache is not None:
        env["NUMBA_CACHE_DIR"] = numba_cache
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(ROOT / "examples"), problem],
        env=env, capture_output=True, text=True, check=True, cwd=ROOT,
    )  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3, help="processes of each kind")
    ap.add_argument(
        "--problem",
        choices=("cartpole", "masschain"),
        default="cartpole",
        help="the user's cart-pole (4, 1) or MassChain(4) (8, 4)",
    )
    ap.add_argument("--out", default=None, help="default benchmarks/results/first_call[_masschain]")
    args = ap.parse_args(argv)
    stem = "first_call" if args.problem == "cartpole" else "first_call_masschain"
    args.out = args.out or str(ROOT / "benchmarks" / "results" / stem)
    load0 = load()
    rows = []
    for rep in range(args.repeats):
        with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as nb:
            rows.append(dict(cache="install", repeat=rep, **run(args.problem, cache, nb)))
        with tempfile.TemporaryDirectory() as cache:
            rows.append(dict(cache="cold", repeat=rep, **run(args.problem, cache)))
            rows.append(dict(cache="warm", repeat=rep, **run(args.problem, cache)))
        print(*rows[-3:], sep="\n", flush=True)
    keys = ("import_torch", "import_torchslq", "first_solve", "second_solve", "ddp_after")
    summary = {
        kind: {k: statistics.median(r[k] for r in rows if r["cache"] == kind) for k in keys}
        for kind in ("install", "cold", "warm")
    }
    cmd = "python benchmarks/first_call.py " + " ".join(argv or sys.argv[1:])
    meta = dict(
        command=cmd.strip(),
        date=datetime.datetime.now().isoformat(timespec="seconds"),
        machine=f"{platform.machine()}, {os.cpu_count()} cores",
        load_average_start=load0,
        load_average_end=load(),
        versions=package_versions("torch", "numba", "sympy"),
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(
        json.dumps(dict(meta=meta, rows=rows, summary=summary), indent=1)
    )
    lines = [
        "# The first solve in a fresh process (`benchmarks/first_call.py`)",
        "",
        f"```\n{meta['command']}\n```",
        "",
        f"{meta['date']}, {meta['machine']}; load average at start {load0}, at end "
        f"{meta['load_average_end']}. {meta['versions']}.",
        "",
        "A new process per row: imports, then "
        + (
            "the user's cart-pole swing-up (B = 1, T = 50, ILQR, tol 1e-6)"
            if args.problem == "cartpole"
            else "`MassChain(4)` ((8, 4), B = 1, T = 20, ILQR, tol 1e-6)"
        )
        + " solved twice, then by DDP. `install`: numba's cache of the "
        "library's kernels empty as well (every kernel compiled, as on the first use after "
        "installing); `cold`: an empty generated-code cache, the library's kernels cached; "
        "`warm`: the next process with that cache. Medians of "
        f"{args.repeats} processes each, seconds:",
        "",
        "| cache | import torch | import torchslq | first solve | second solve | DDP after |",
        "|---|---|---|---|---|---|",
    ]
    for kind, s in summary.items():
        lines.append(
            f"| {kind} | {s['import_torch']:.2f} | {s['import_torchslq']:.2f} | "
            f"{s['first_solve']:.2f} | {s['second_solve']:.2f} | {s['ddp_after']:.2f} |"
        )
    lines += ["", "Every process:", "",
              "| cache | repeat | " + " | ".join(keys) + " | torch._dynamo imported |",
              "|---|---|" + "---|" * (len(keys) + 1)]  # fmt: skip
    for r in rows:
        lines.append(
            f"| {r['cache']} | {r['repeat']} | "
            + " | ".join(f"{r[k]:.2f}" for k in keys)
            + f" | {'yes' if r['compiler_stack'] else 'no'} |"
        )
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
