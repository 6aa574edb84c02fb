"""Batched products of tiny matrices on the CPU: the layouts the Riccati kernel could use.

Not part of the test suite. Run from the repo root::

    .venv/bin/python benchmarks/tiny_matmul.py      # writes benchmarks/results/tiny_matmul.{md,json}

The Riccati step multiplies ``B`` independent ``(n+1) x (m+n+1)``-sized matrices. torch's
CPU ``bmm`` dispatches one BLAS call per matrix, which dominates for tiny matrices. Times
(us per product, best of ``--repeat`` loops of ``--calls`` calls, float64, one thread) of:

* ``bmm``: ``A @ X`` with ``A (B, r, k)``, ``X (B, k, c)`` (what the kernel does now);
* ``broadcast``: ``(A[..., :, :, None] * X[..., None, :, :]).sum(-2)`` in the same
  batch-first layout;
* ``batch-last``: the same product on ``(r, k, B)`` / ``(k, c, B)`` tensors,
  ``(A[:, :, None] * X[None]).sum(1)``: the batch is the contiguous inner dimension, so
  the multiply-add vectorises over it;
* ``einsum batch-last``: ``torch.einsum('ikb,kjb->ijb')``.

All four must agree to 1e-12 (checked). Ratios compare timings of the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import torch

CASES = [(1, 5, 6), (64, 5, 6), (512, 5, 6), (4096, 5, 6), (64, 9, 13), (512, 13, 17)]


def per_call_us(fn, calls: int, repeat: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        for _ in range(calls):
            fn()
        best = min(best, (time.perf_counter() - t) / calls)
    return best * 1e6


def time_case(A, X, Al, Xl, calls: int, repeat: int) -> dict[str, float]:
    return {
        "bmm": per_call_us(lambda: A @ X, calls, repeat),
        "broadcast": per_call_us(
            lambda: (A.unsqueeze(-1) * X.unsqueeze(-3)).sum(-2), calls, repeat
        ),
        "batch-last": per_call_us(
            lambda: (Al.unsqueeze(2) * Xl.unsqueeze(0)).sum(1), calls, repeat
        ),
        "einsum batch-last": per_call_us(
            lambda: torch.einsum("ikb,kjb->ijb", Al, Xl), calls, repeat
        ),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    rows = []
    for B, r, c in CASES:
        k = r  # (r x r) @ (r x c), as in V @ F
        A = torch.randn(B, r, k, generator=g, dtype=torch.float64)
        X = torch.randn(B, k, c, generator=g, dtype=torch.float64)
        Al, Xl = A.permute(1, 2, 0).contiguous(), X.permute(1, 2, 0).contiguous()
        ref = A @ X
        for out in (
            (A.unsqueeze(-1) * X.unsqueeze(-3)).sum(-2),
            (Al.unsqueeze(2) * Xl.unsqueeze(0)).sum(1).permute(2, 0, 1),
            torch.einsum("ikb,kjb->ijb", Al, Xl).permute(2, 0, 1),
        ):
            assert torch.allclose(out, ref, rtol=1e-12, atol=1e-12)
        t = time_case(A, X, Al, Xl, args.calls, args.repeat)
        rows.append({"B": B, "shape": f"({r}x{k}) @ ({k}x{c})", **t})
        print(rows[-1], flush=True)
    cmd = "python benchmarks/tiny_matmul.py"
    meta = {
        "command": cmd,
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "torch": torch.__version__,
        "load": list(os.getloadavg()),
    }
    lines = [
        "# Batched products of tiny matrices (CPU, float64, 1 thread)",
        "",
        f"```\n{cmd}\n```",
        "",
        f"{meta['date']}, {meta['machine']}, torch {meta['torch']}, load {meta['load']}.",
        "See the script's docstring for what each column computes; us per product.",
        "",
        "| B | product | bmm | broadcast | batch-last | einsum batch-last | bmm / batch-last |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['B']} | {r['shape']} | {r['bmm']:.1f} | {r['broadcast']:.1f} | "
            f"{r['batch-last']:.1f} | {r['einsum batch-last']:.1f} | "
            f"{r['bmm'] / r['batch-last']:.2f}x |"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "tiny_matmul.md").write_text("\n".join(lines) + "\n")
    (out / "tiny_matmul.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
