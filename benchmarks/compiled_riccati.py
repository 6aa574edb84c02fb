"""The compiled CPU Riccati kernel (numba) against the torch path, per pass and per solve.

Not part of the test suite. Run from the repo root::

    .venv/bin/python benchmarks/compiled_riccati.py            # kernel grid + solves
    .venv/bin/python benchmarks/compiled_riccati.py --quick    # smaller, a sanity check

Both paths run in the same process, alternating (``torchslq.lq.set_compiled``),
float64, ``torch.set_num_threads(1)``; the reported time is the minimum over the
repeats (and the median beside it), the ratio is torch / compiled (> 1: compiled
faster).

* ``pass``: one ``riccati_homogeneous`` call with per-element, time-varying random data
  and a per-element ``reg`` (what iLQR/DDP pass), shapes ``(B, T, n, m)``;
* ``solve``: whole solves, the settings of ``benchmarks/peers.py`` (``tol = 1e-6``,
  ``compact=True``): the unicycle (T = 20, B = 512) with DDP and ILQR, the cart-pole
  swing-up (T = 50, B = 64) with DDP, and with ``|u| <= 8`` (the control-limited pass,
  box QPs) with ILQR and DDP; the iteration counts and final costs of both paths
  are printed beside the times (they differ only by rounding).

Results go to ``--out`` (``compiled_riccati.{json,md}``).
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
from torchslq.lq import set_compiled  # noqa: E402
from torchslq.lq.riccati import riccati_homogeneous  # noqa: E402

F64 = torch.float64


def _pass_data(B: int, T: int, n: int, m: int):
    g = torch.Generator().manual_seed(0)
    mn1 = m + n + 1
    F = 0.3 * torch.randn(B, T, n + 1, mn1, generator=g, dtype=F64)
    F[..., :n, m : m + n] += torch.eye(n, dtype=F64)
    F[..., n, :] = 0.0
    F[..., n, -1] = 1.0
    G = torch.randn(B, T, mn1, mn1, generator=g, dtype=F64)
    H = G @ G.mT / mn1 + 0.1 * torch.eye(mn1, dtype=F64)
    VhT = torch.eye(n + 1, dtype=F64).expand(B, n + 1, n + 1)
    reg = torch.full((B,), 1e-3, dtype=F64)
    return F, H, VhT, reg


def _alternate(fn, repeats: int):
    times = {True: [], False: []}
    out = {}
    for flag in (True, False):  # warm-up (and the kernel's compile) outside the timing
        set_compiled(flag)
        fn()
    for _ in range(repeats):
        for flag in (True, False):
            set_compiled(flag)
            t = time.perf_counter()
            out[flag] = fn()
            times[flag].append(time.perf_counter() - t)
    set_compiled(True)
    return times, out


def bench_passes(shapes, repeats, rows):
    for B, T, n, m in shapes:
        F, H, VhT, reg = _pass_data(B, T, n, m)
        times, _ = _alternate(
            lambda F=F, H=H, VhT=VhT, reg=reg: riccati_homogeneous(F, H, VhT, reg), repeats
        )
        rows.append(_row("pass", f"B={B} T={T} n={n} m={m}", times))


def _unicycle(B: int):
    from peers import TorchUnicycle

    kw = {"dtype": F64}
    cost = ts.QuadraticCost(
        100 * torch.eye(3, **kw), torch.eye(2, **kw), Qf=100 * torch.eye(3, **kw)
    )
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(B, 3, generator=g, dtype=F64) * 2 - 1
    return ts.Problem(TorchUnicycle(0.1), cost, 20), x0


def bench_solves(cases, repeats, rows):
    from torchslq.tasks import cartpole_swingup

    for name, B, solver_cls, bounds in cases:
        problem, x0 = _unicycle(B) if name == "unicycle" else cartpole_swingup(B)
        kw = {} if bounds is None else {"u_min": -bounds, "u_max": bounds}
        solver = solver_cls(max_iter=500, tol=1e-6, progress=False, compact=True, **kw)
        times, out = _alternate(lambda s=solver, p=problem, x=x0: s.solve(p, x), repeats)
        extra = {
            f"{'compiled' if f else 'torch'}_iters": f"{out[f].iterations.float().mean():.2f}/{int(out[f].iterations.max())}"
            for f in (True, False)
        }
        extra["cost_rel_diff"] = float(
            ((out[True].cost - out[False].cost).abs() / out[False].cost.abs()).max()
        )
        label = f"{name} B={B} {solver_cls.__name__}" + (
            "" if bounds is None else f" |u|<={bounds:g}"
        )
        rows.append(_row("solve", label, times, extra))


def _row(kind, case, times, extra=None):
    c, t = times[True], times[False]
    row = {
        "kind": kind,
        "case": case,
        "compiled_min_s": min(c),
        "compiled_median_s": statistics.median(c),
        "torch_min_s": min(t),
        "torch_median_s": statistics.median(t),
        "ratio_min": min(t) / min(c),
        **(extra or {}),
    }
    print(
        f"{kind:5s} {case:32s} compiled {min(c) * 1e3:9.2f} ms (med {statistics.median(c) * 1e3:9.2f})"
        f"  torch {min(t) * 1e3:9.2f} ms (med {statistics.median(t) * 1e3:9.2f})  x{row['ratio_min']:.2f}"
        + ("" if not extra else "  " + " ".join(f"{k}={v}" for k, v in extra.items())),
        flush=True,
    )
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--solve-repeats", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--name", default="compiled_riccati")
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.quick:
        shapes = [(64, 20, 3, 2)]
        cases = [("unicycle", 64, ts.DDP, None)]
    else:
        shapes = [
            (1, 50, 4, 1),
            (64, 40, 8, 4),
            (512, 20, 3, 2),
            (512, 50, 4, 1),
            (1024, 100, 12, 4),
        ]
        cases = [
            ("unicycle", 512, ts.DDP, None),
            ("unicycle", 512, ts.ILQR, None),
            ("cartpole", 64, ts.DDP, None),
            ("cartpole", 64, ts.ILQR, 8.0),
            ("cartpole", 64, ts.DDP, 8.0),
        ]
    load0 = os.getloadavg()
    rows: list[dict] = []
    bench_passes(shapes, args.repeats, rows)
    bench_solves(cases, args.solve_repeats, rows)
    meta = {
        "command": "python benchmarks/compiled_riccati.py" + (" --quick" if args.quick else ""),
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "torch": torch.__version__,
        "numba": __import__("numba").__version__,
        "load_start": load0,
        "load_end": os.getloadavg(),
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = [
        "# Compiled CPU Riccati kernel vs the torch path",
        "",
        f"`{meta['command']}`, {meta['date']}, {meta['machine']}, torch {meta['torch']}, "
        f"numba {meta['numba']}, float64, 1 thread; load average {load0[0]:.2f} at start, "
        f"{meta['load_end'][0]:.2f} at end (a shared box: times are noisy, the two paths "
        "alternate in one process).",
        "",
        "| kind | case | compiled min [ms] | compiled median | torch min [ms] | torch median | torch / compiled | notes |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        notes = " ".join(
            f"{k}={v:.1e}" if isinstance(v, float) else f"{k}={v}"
            for k, v in r.items()
            if k.endswith("iters") or k == "cost_rel_diff"
        )
        lines.append(
            f"| {r['kind']} | {r['case']} | {r['compiled_min_s'] * 1e3:.2f} | {r['compiled_median_s'] * 1e3:.2f} "
            f"| {r['torch_min_s'] * 1e3:.2f} | {r['torch_median_s'] * 1e3:.2f} | {r['ratio_min']:.2f} | {notes} |"
        )
    (out / f"{args.name}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
