"""A learned model's closed-loop rollouts on its compiled step against torch ops.

Not part of the test suite. Run from the repo root::

    .venv/bin/python benchmarks/learned_rollouts.py            # -> benchmarks/results
    .venv/bin/python benchmarks/learned_rollouts.py --quick    # fewer rows and rounds

The models of ``benchmarks/learned_derivatives.py``: ``learned`` (the user's cart-pole RK4
step, generated code, plus a 5-64-64-4 tanh residual MLP), ``features`` (a 6-64-64-4 tanh
MLP on slices and ``sin``/``cos`` of the state) and ``graybox`` (the cart-pole's
equations inline in torch ops in one RK4 step, plus the MLP). Each has a compiled step
written from its traced graph (``torchslq/dynamics/network_codegen.py``); the same
model with ``generate_compiled_code = False`` is rolled out step by step on torch ops,
as before that step existed. A rollout is
:func:`torchslq.dynamics.rollout_closed_loop` over ``T = 50`` steps with random gains
and a nominal trajectory, ``rows`` trials at once (a line search's candidate steps times
the batch), inside one solve's scope (what a solve pins once, pinned once). float64, one
thread. The compiled step runs two ways: as the library takes it (``compiled``: from
``MIN_BLOCK_ROWS`` rows a model with wide layer chains runs its step on many rows at
once, one call per time step with the layers as matrix products,
:mod:`torchslq.dynamics.network_chains`) and one row at a time (``one-row``: that
threshold set out of reach). The three ways alternate ``--rounds`` times and the
minimum of 3 calls each is kept. The largest difference between the compiled and the
torch ops' states is printed beside the times.
Results go to ``--out`` (``learned_rollouts.{json,md}``).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _env import load, run_meta, write_report  # noqa: E402
from learned_derivatives import MODELS  # noqa: E402

from torchslq._backend import dispatch  # noqa: E402
from torchslq._backend.model_fns import rows_step  # noqa: E402
from torchslq._pinned import solve_scope  # noqa: E402
from torchslq.dynamics.rollout import rollout_closed_loop  # noqa: E402

COMMAND = "python benchmarks/learned_rollouts.py"
T = 50


def _time(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def measure(name: str, rows: int, rounds: int) -> dict:
    """Minimum times (ms) of one rollout of ``rows`` rows, compiled step and torch ops."""
    fast = MODELS[name]()
    slow = copy.deepcopy(fast)
    slow.generate_compiled_code = False
    g = torch.Generator().manual_seed(rows)
    n, m = fast.state_dim, fast.control_dim
    data = {
        "x0": 0.3 * torch.randn(rows, n, generator=g, dtype=torch.float64),
        "x_nom": 0.3 * torch.randn(rows, T + 1, n, generator=g, dtype=torch.float64),
        "u_nom": torch.randn(rows, T, m, generator=g, dtype=torch.float64),
        "K": 0.1 * torch.randn(rows, T, m, n, generator=g, dtype=torch.float64),
        "k": torch.randn(rows, T, m, generator=g, dtype=torch.float64),
        "alpha": torch.full((1, rows), 0.5, dtype=torch.float64),
    }
    times = {"compiled": float("inf"), "one-row": float("inf"), "torch": float("inf")}
    outs = {}
    threshold = dispatch.MIN_BLOCK_ROWS
    with solve_scope(), torch.no_grad():
        step = fast.compiled_step()
        on_rows = step is not None and rows_step(step[0]) is not None and rows >= threshold
        for _ in range(rounds):
            for way, model in (("compiled", fast), ("one-row", fast), ("torch", slow)):
                dispatch.MIN_BLOCK_ROWS = 10**9 if way == "one-row" else threshold
                outs[way] = rollout_closed_loop(model, **data)[0]  # (a warm-up at first)
                times[way] = min(
                    times[way], _time(lambda m=model: rollout_closed_loop(m, **data)) * 1e3
                )
        dispatch.MIN_BLOCK_ROWS = threshold
    return {
        "model": name,
        "rows": rows,
        "compiled_step": step is not None,
        "on_rows": on_rows,
        "compiled_ms": round(times["compiled"], 3),
        "one_row_ms": round(times["one-row"], 3),
        "torch_ms": round(times["torch"], 3),
        "speedup": round(times["torch"] / times["compiled"], 2),
        "rows_speedup": round(times["one-row"] / times["compiled"], 2),
        "max_abs_diff": float((outs["compiled"] - outs["torch"]).abs().max()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="rows 1, 64 and 2 rounds, to /tmp")
    ap.add_argument("--models", default=",".join(MODELS), help="of " + ",".join(MODELS))
    ap.add_argument("--rows", default="1,8,64,512,1536,4096")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    if args.quick:
        args.rows, args.rounds, args.out = "1,64", 2, "/tmp"
    torch.set_num_threads(1)
    load0 = load()
    rows = []
    for name in args.models.split(","):
        for r in (int(b) for b in args.rows.split(",")):
            row = measure(name, r, args.rounds)
            print(json.dumps(row), flush=True)
            rows.append(row)
    write_report(
        args.out,
        "learned_rollouts",
        "A learned model's rollouts: compiled step vs torch ops (`benchmarks/learned_rollouts.py`)",
        run_meta(COMMAND, argv, load0),
        rows,
        f"One closed-loop rollout of T = {T} steps over `rows` rows; the three ways alternate "
        f"in one process, {args.rounds} rounds, minimum of 3 calls each. `compiled step`: "
        "as the library takes it; `on rows`: that is the step on many rows at once (a model "
        f"with wide layer chains, from {dispatch.MIN_BLOCK_ROWS} rows); `one-row step`: the "
        "compiled step one row at a time. `max abs diff`: the largest difference between the "
        "compiled step's and the torch ops' states. `step taken`: the model has its compiled "
        "step (else every way is torch ops). Models as in `learned_derivatives.md`.",
        ["model", "rows", "step taken", "on rows", "compiled step [ms]", "one-row step [ms]",
         "torch ops [ms]", "one-row / compiled", "torch / compiled", "max abs diff"],
        lambda r: [
            r["model"], str(r["rows"]), "yes" if r["compiled_step"] else "no",
            "yes" if r["on_rows"] else "no", str(r["compiled_ms"]), str(r["one_row_ms"]),
            str(r["torch_ms"]), f"{r['rows_speedup']}x", f"{r['speedup']}x",
            f"{r['max_abs_diff']:.1e}",
        ],
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
