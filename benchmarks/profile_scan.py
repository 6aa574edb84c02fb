"""Where the time of one ``lqr_solve(method="scan")`` call goes, kernel by kernel.

Not part of the test suite. Run from the repo root on a machine with a CUDA GPU::

    python benchmarks/profile_scan.py --T 4096 --B 1024 --dtype float64
    python benchmarks/profile_scan.py --T 4096 --B 1024 --torch-ops   # fused kernels off

One forward call (``validate=False``, no grad; ``--backward`` adds the implicit backward
pass) on ``benchmarks/parallel_lq.py``'s problem, after a warm-up call that compiles the
fused kernels, under ``torch.profiler`` (CPU and CUDA activities). Prints and saves
(``--out/--name.{json,md}``, default ``benchmarks/results/profile_scan``) the kernels and
ops with the largest device time, with the command line, device and torch version.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from datetime import datetime
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from parallel_lq import problem, run_method  # noqa: E402

from torchslq.lq import scan_kernels  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cuda")
    p.add_argument("--T", type=int, default=4096)
    p.add_argument("--B", type=int, default=1024)
    p.add_argument("--n", type=int, default=4)
    p.add_argument("--m", type=int, default=2)
    p.add_argument("--dtype", default="float64")
    p.add_argument("--backward", action="store_true")
    p.add_argument("--torch-ops", action="store_true", help="the fused kernels off")
    p.add_argument("--rows", type=int, default=25)
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    p.add_argument("--name", default="profile_scan")
    a = p.parse_args(argv)
    cuda = a.device.startswith("cuda")
    if cuda and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device is available")
    args = problem(a.B, a.T, a.n, a.m, getattr(torch, a.dtype), a.device)
    call = run_method(args, "scan_torch" if a.torch_ops else "scan", a.backward)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    call()  # warm-up: compiles the fused kernels
    if cuda:
        torch.cuda.synchronize()
    with profile(activities=activities) as prof:
        call()
        if cuda:
            torch.cuda.synchronize()

    def device_us(e) -> float:
        return float(getattr(e, "device_time_total", 0.0) or 0.0) if cuda else 0.0

    key = "device_time_total" if cuda else "cpu_time_total"
    events = sorted(
        prof.key_averages(), key=lambda e: -(device_us(e) if cuda else e.cpu_time_total)
    )
    rows = [
        {
            "name": e.key,
            "calls": e.count,
            "device_ms": device_us(e) / 1e3,
            "cpu_ms": e.cpu_time_total / 1e3,
        }
        for e in events[: a.rows]
    ]
    table = prof.key_averages().table(sort_by=key, row_limit=a.rows, max_name_column_width=70)
    print(table)
    cmd = " ".join(
        shlex.quote(x) for x in ["python", "benchmarks/profile_scan.py", *(argv or sys.argv[1:])]
    )
    meta = {
        "command": cmd,
        "date": datetime.now().isoformat(timespec="seconds"),
        "device": torch.cuda.get_device_name() if cuda else "cpu",
        "torch": torch.__version__,
        "fused_kernels": not a.torch_ops and scan_kernels.enabled(args["A"], a.n, a.m),
    }
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{a.name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = [
        '# One `lqr_solve(method="scan")` call, kernel by kernel',
        "",
        f"`{cmd}`, {meta['date']}, device {meta['device']}, torch {meta['torch']}, fused "
        f"kernels: {meta['fused_kernels']}; T = {a.T}, B = {a.B}, n = {a.n}, m = {a.m}, "
        f"{a.dtype}, {'forward + backward' if a.backward else 'forward'}; torch.profiler "
        "after a warm-up call.",
        "",
        "| op or kernel | calls | device [ms] | CPU [ms] |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| `{r['name'][:70]}` | {r['calls']} | {r['device_ms']:.2f} | {r['cpu_ms']:.2f} |"
        for r in rows
    ]
    (out / f"{a.name}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
