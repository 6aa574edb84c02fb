"""Parallel-in-time LQ (``lqr_solve(method="scan")``) against the sequential kernel.

Not part of the test suite. Run from the repo root::

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/parallel_lq.py             # CPU grid
    .venv/bin/python benchmarks/parallel_lq.py --quick --out /tmp/plq        # a sanity check
    python benchmarks/parallel_lq.py --device cuda --threads 1 --name parallel_lq_cuda

What is timed: one :func:`torchslq.lqr_solve` call (``validate=False``, as the solvers
call it; forward only, under ``torch.no_grad``) on a fully batched, time-varying random
LQ problem with every term (``n = 4``, ``m = 2`` by default), for

* ``T`` in ``--T`` (default 100, 1000, 10000) and ``B`` in ``--B`` (default 1, 32,
  1024), skipping ``B * T > --max-elements`` (default 3.3e5: on a 2-core CPU shared
  with other jobs a scan over 1e6 elements takes tens of seconds per call; on a GPU
  pass e.g. ``--max-elements 1.1e7 --B 1 32 1024 4096``);
* float64 and float32;
* ``--threads`` (default 1 and 2; ``torch.set_num_threads``, which the compiled kernel
  also uses);
* the methods: ``sequential`` (the default path: on the CPU the compiled numba kernel),
  ``sequential_torch`` (the same recursion as batched torch ops per step, which is what
  a GPU runs; CPU only, where it differs from ``sequential``), ``scan`` (on a GPU with
  Triton: the fused per-step kernels of :mod:`torchslq.lq.scan_kernels`) and
  ``scan_torch`` (the scan as batched torch ops, the fused kernels switched off; GPU
  only, where it differs from ``scan``);
* ``--backward`` adds forward + backward (``autograd.grad`` of ``sum(cost) + sum(x)``
  w.r.t. ``Q, q, A, x0``), each method's own backward pass.

Each time is the minimum over calls after a warm-up call (calls repeat until
``--budget`` seconds or 5 calls; one call when it alone takes longer than the budget);
on CUDA ``torch.cuda.synchronize()`` brackets each call. Each row also reports the largest relative difference of ``x``
between the scan and the sequential kernel. Results go to ``--out/--name.{json,md}``
(default ``benchmarks/results/parallel_lq``), rewritten after every row, with the
command line that produced them.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shlex
import sys
import time
from datetime import datetime
from pathlib import Path

import torch

import torchslq as ts
from torchslq.lq import compiled_available, scan_kernels, set_compiled

ROOT = Path(__file__).resolve().parent.parent


def problem(B: int, T: int, n: int, m: int, dtype: torch.dtype, device: str, seed: int = 0):
    """A fully batched, time-varying, well-conditioned LQ problem (all terms), drawn on
    ``device`` (drawing ``B * T = 1.7e7`` steps on the CPU takes longer than solving)."""
    g = torch.Generator(device=device).manual_seed(seed)
    kw = {"dtype": torch.float64, "device": device}

    def rn(*s):
        return torch.randn(*s, generator=g, **kw)

    eye = torch.eye(n, **kw)
    A = 0.95 * eye + 0.2 * rn(B, T, n, n) / n**0.5
    Bm = rn(B, T, n, m) / n**0.5
    Lq = rn(B, T + 1, n, n) / n**0.5
    Q = Lq @ Lq.mT + 0.5 * eye
    Lr = rn(B, T, m, m) / m**0.5
    R = Lr @ Lr.mT + 0.5 * torch.eye(m, **kw)
    S = 0.1 * rn(B, T, m, n)
    args = dict(
        A=A, B=Bm, Q=Q, R=R, x0=rn(B, n), q=rn(B, T + 1, n), r=rn(B, T, m), S=S, c=0.1 * rn(B, T, n)
    )
    return {k: v.to(dtype=dtype) for k, v in args.items()}


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _free(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.empty_cache()


def timed(fn, device: str, budget: float) -> tuple[float, object]:
    out = fn()  # warm-up
    _sync(device)
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < 5 and (
        not times
        or (time.perf_counter() - start < budget and (len(times) < 2 or times[0] < budget))
    ):
        _sync(device)
        t0 = time.perf_counter()
        out = fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return min(times), out


def run_method(args: dict, method: str, backward: bool):
    torch_path = method == "sequential_torch"
    lq_method = {"sequential_torch": "sequential", "scan_torch": "scan"}.get(method, method)

    def call():
        old = set_compiled(False) if torch_path else None
        fused = scan_kernels.disabled() if method == "scan_torch" else contextlib.nullcontext()
        try:
            with fused:
                if not backward:
                    with torch.no_grad():
                        return ts.lqr_solve(**args, validate=False, method=lq_method).x
                ins = {
                    k: (v.requires_grad_(True) if k in ("Q", "q", "A", "x0") else v)
                    for k, v in args.items()
                }
                sol = ts.lqr_solve(**ins, validate=False, method=lq_method)
                loss = sol.cost.sum() + sol.x.sum()
                torch.autograd.grad(loss, [ins[k] for k in ("Q", "q", "A", "x0")])
                return sol.x.detach()
        finally:
            if old is not None:
                set_compiled(old)

    return call


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--T", type=int, nargs="+", default=[100, 1000, 10000])
    p.add_argument("--B", type=int, nargs="+", default=[1, 32, 1024])
    p.add_argument("--n", type=int, default=4)
    p.add_argument("--m", type=int, default=2)
    p.add_argument("--dtypes", nargs="+", default=["float64", "float32"])
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--methods", nargs="+", default=["sequential", "sequential_torch", "scan"])
    p.add_argument("--max-elements", type=float, default=3.3e5)
    p.add_argument(
        "--torch-max-elements",
        type=float,
        default=1.1e5,
        help="B*T cap for sequential_torch (T dispatch-bound steps, slow on the CPU)",
    )
    p.add_argument("--budget", type=float, default=2.0)
    p.add_argument(
        "--time-limit",
        type=float,
        default=float("inf"),
        help="seconds: rows not started by then are listed as skipped (results kept)",
    )
    p.add_argument("--backward", action="store_true")
    p.add_argument("--quick", action="store_true", help="T in (100, 1000), B in (1, 32)")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    p.add_argument("--name", default="parallel_lq")
    p.add_argument(
        "--rerender", action="store_true", help="only rewrite the markdown from an earlier JSON"
    )
    a = p.parse_args(argv)
    if a.quick:
        a.T, a.B = [100, 1000], [1, 32]
    device = a.device
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device is available")
    methods = [m for m in a.methods if not (m == "sequential_torch" and device != "cpu")]
    if device == "cpu" or not scan_kernels.HAVE_TRITON:
        methods = [m for m in methods if m != "scan_torch"]  # same as "scan"
    if device == "cpu" and not compiled_available():
        methods = [m for m in methods if m != "sequential_torch"]  # same as "sequential"
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    env = " ".join(f"{k}={os.environ[k]}" for k in ("OMP_NUM_THREADS",) if k in os.environ)
    cmd = " ".join(
        shlex.quote(x) for x in ["python", "benchmarks/parallel_lq.py", *(argv or sys.argv[1:])]
    )
    meta = {
        "command": (env + " " + cmd).strip(),
        "date": datetime.now().isoformat(timespec="seconds"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "device": torch.cuda.get_device_name() if device.startswith("cuda") else "cpu",
        "torch": torch.__version__,
        "compiled_available": compiled_available(),
        "n": a.n,
        "m": a.m,
        "backward": a.backward,
        "load_start": os.getloadavg()[0],
        "skipped_for_time": [],
    }
    rows: list[dict] = []

    def write(measured: bool = True) -> None:
        if measured:
            meta["load_end"] = os.getloadavg()[0]
            (out / f"{a.name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
        what = "forward + backward" if a.backward else "forward"
        lines = [
            "# Parallel-in-time LQ (associative scan) vs the sequential kernel",
            "",
            f"`{meta['command']}`, {meta['date']}, {meta['machine']}, device {meta['device']}, "
            f"torch {meta['torch']}, compiled CPU kernel available: {meta['compiled_available']}; "
            f"n = {a.n}, m = {a.m}, one `lqr_solve` call ({what}), best of the timed calls; "
            f"load average {meta['load_start']:.2f} at start, {meta['load_end']:.2f} at end "
            "(a shared box: times are noisy).",
            "",
            "`sequential`: the default path (CPU: the compiled kernel); `sequential_torch`: "
            "the same recursion as torch ops per step (what a GPU runs); `scan`: "
            '`method="scan"`. speed-up = best sequential / scan (> 1: scan faster); '
            "torch / scan = sequential_torch / scan; scan_torch / scan: the fused kernels' "
            "gain. `x rel diff`: scan vs sequential.",
            "",
            "| dtype | threads | T | B | sequential [ms] | sequential_torch [ms] | scan [ms] "
            "| scan_torch [ms] | speed-up | torch / scan | scan_torch / scan | x rel diff |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            ms = {
                k: (
                    f"{1e3 * r[k]:.2f}"
                    if r.get(k) is not None
                    else (r[k + "_error"] if r.get(k + "_error") else "-")
                )
                for k in a.methods
            }
            seqs = [r[k] for k in ("sequential", "sequential_torch") if r.get(k) is not None]
            sp = f"{min(seqs) / r['scan']:.2f}" if seqs and r.get("scan") else "-"
            diff = f"{r['x_rel_diff']:.1e}" if r.get("x_rel_diff") is not None else "-"
            st = r.get("sequential_torch")
            tsp = f"{st / r['scan']:.2f}" if st and r.get("scan") else "-"
            sc = r.get("scan_torch")
            fsp = f"{sc / r['scan']:.2f}" if sc and r.get("scan") else "-"
            lines.append(
                f"| {r['dtype']} | {r['threads']} | {r['T']} | {r['B']} | {ms.get('sequential', '-')} "
                f"| {ms.get('sequential_torch', '-')} | {ms.get('scan', '-')} "
                f"| {ms.get('scan_torch', '-')} | {sp} | {tsp} | {fsp} | {diff} |"
            )
        if meta.get("command_2"):  # rows measured by a second run on the same machine
            lines += [
                "",
                f"Rows {', '.join(meta['rows_from_command_2'])}: from a second run on the "
                f"same machine, `{meta['command_2']}`.",
            ]
        if meta.get("skipped_for_time"):
            lines += [
                "",
                "Not measured (the run's time limit came first): "
                + ", ".join(meta["skipped_for_time"])
                + ".",
            ]
        (out / f"{a.name}.md").write_text("\n".join(lines) + "\n")

    if a.rerender:  # the markdown of an earlier run, from its JSON (its command kept)
        saved = json.loads((out / f"{a.name}.json").read_text())
        meta, rows[:] = saved["meta"], saved["rows"]
        a.n, a.m, a.backward = meta["n"], meta["m"], meta["backward"]
        a.methods = sorted(
            {k for r in rows for k in r} & {"sequential", "sequential_torch", "scan", "scan_torch"}
        )
        write(measured=False)
        return
    started = time.perf_counter()
    for dt_name in a.dtypes:
        dtype = getattr(torch, dt_name)
        for threads in a.threads:
            torch.set_num_threads(threads)
            for T in a.T:
                for B in a.B:
                    if B * T > a.max_elements:
                        continue
                    if time.perf_counter() - started > a.time_limit:
                        meta["skipped_for_time"].append(f"{dt_name} T={T} B={B}")
                        continue
                    args = problem(B, T, a.n, a.m, dtype, device)
                    row: dict = {"dtype": dt_name, "threads": threads, "T": T, "B": B}
                    xs = {}
                    for method in methods:
                        if method == "sequential_torch" and B * T > a.torch_max_elements:
                            continue
                        try:
                            t, x = timed(run_method(args, method, a.backward), device, a.budget)
                        except torch.OutOfMemoryError:  # a size the device cannot hold
                            row[method + "_error"] = "out of memory"
                            del args
                            _free(device)
                            args = problem(B, T, a.n, a.m, dtype, device)
                            continue
                        except Exception as err:  # recorded, the other rows still run
                            row[method + "_error"] = type(err).__name__
                            print(f"{method} T={T} B={B}: {err!r}", flush=True)
                            continue
                        row[method] = t
                        xs[method] = x
                    if "scan" in xs and "sequential" in xs:
                        ref = xs["sequential"].double()
                        row["x_rel_diff"] = float(
                            (xs["scan"].double() - ref).norm() / ref.norm().clamp_min(1.0)
                        )
                    rows.append(row)
                    print(row, flush=True)
                    del args, xs
                    _free(device)
                    write()
    write()


if __name__ == "__main__":
    main()
