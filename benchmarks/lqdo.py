"""Benchmark: Herber & Sundarrajan (2020) Tables 1-4 with ``torchslq.lqdo``, ours beside
the paper's, plus batched against one-by-one solves.

Not part of the test suite. Run from the repository root::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/lqdo.py              # everything
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/lqdo.py --quick      # small rows only
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/lqdo.py --no-ipopt   # without CasADi

Writes ``benchmarks/results/lqdo.json`` and ``benchmarks/results/lqdo.md`` (``--out`` to
change the stem). What each row means is in :mod:`reproductions.lqdo`: ours are wall
times of the whole solve including building the problem and its transcription, best of
3 runs after a warm-up (1 run for the largest meshes), float64, one torch thread; the
paper's were measured on an AMD 3970X with MATLAB 2020a (fmincon / quadprog), so the
ratio compares machines as well as methods. The small rows of Tables 1-3 are also
checked in ``tests/test_lqdo_paper.py``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from reproductions import lqdo as R  # noqa: E402


def _commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short=10", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
    except OSError:
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--quick",
        action="store_true",
        help="without Van der Pol TR2000/PS40 (100 QLIN iterations each) and with a batch of 64",
    )
    ap.add_argument("--no-ipopt", action="store_true", help="skip the CasADi + IPOPT rows")
    ap.add_argument("--batch", type=int, default=256, help="batch size of the batched rows")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "lqdo"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    torch.set_default_dtype(torch.float64)
    ipopt = not args.no_ipopt
    t_start = time.perf_counter()
    load0 = os.getloadavg()
    if args.quick:
        tables = {
            "Table 1 (container crane)": R.table1(
                ("TR20", "TR200", "TR2000", "PS10", "PS40"), ipopt=ipopt
            ),
            "Table 2 (Van der Pol V2; V1 below)": R.table2(("TR20", "TR200", "PS10"), ipopt=ipopt),
            "Table 3 (co-design transfer)": R.table3(("TR200", "TR2000", "PS10"), ipopt=ipopt),
            "Table 4 (vehicle suspension, synthetic road)": R.table4(
                ("TR200", "TR2000"), ipopt=ipopt
            ),
        }
    else:
        tables = {
            "Table 1 (container crane)": R.table1(ipopt=ipopt),
            "Table 2 (Van der Pol V2; V1 below)": R.table2(ipopt=ipopt),
            "Table 3 (co-design transfer)": R.table3(ipopt=ipopt),
            "Table 4 (vehicle suspension, synthetic road)": R.table4(ipopt=ipopt),
        }
    B = 64 if args.quick else args.batch
    batch_rows = R.batched(B=B, n_single=8 if args.quick else 16)
    total = time.perf_counter() - t_start
    cmd = "OMP_NUM_THREADS=1 .venv/bin/python benchmarks/lqdo.py " + " ".join(argv or sys.argv[1:])
    meta = dict(
        command=cmd.strip(),
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        commit=_commit(),
        torch=torch.__version__,
        python=platform.python_version(),
        cpu_count=os.cpu_count(),
        load_average_start=load0,
        load_average_end=os.getloadavg(),
        total_seconds=total,
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(
        json.dumps(dict(meta=meta, tables=tables, batched=batch_rows), indent=1, default=str)
    )
    lines = [
        "# LQDO (Herber & Sundarrajan 2020): Tables 1-4, ours beside the paper's",
        "",
        f"Command: `{meta['command']}` (commit `{meta['commit']}`, {meta['date']}).",
        "",
        f"float64, CPU, torch {meta['torch']}, one torch thread, {meta['cpu_count']} cores shared with "
        f"other processes (load average {tuple(round(x, 2) for x in load0)} at start, "
        f"{tuple(round(x, 2) for x in meta['load_average_end'])} at end): absolute times are noisy. "
        f"Total wall time {total:.0f} s.",
        "",
        "Ours: wall time of the whole solve (problem, transcription, OLQ detection, all QPs), "
        "best of 3 after a warm-up (1 run for TR2000 and the suspension), the sparse solvers' "
        "kept structures cleared before each run. QLIN = Algorithm 1 (Clarabel QPs; one sparse "
        "LU for a QP without inequalities or a convex one whose few inequalities are inactive, "
        "the co-design rows; the dense torch interior point where Clarabel fails); "
        "QLIN+merit = with the l1-merit line search, QLIN+TR = with the trust region on the "
        "parameters (and a second-order correction), SQP+TR = the trust region with the "
        "Lagrangian's Hessian (the safeguarded rows are compared with the paper's "
        "interior-point rows); TLFP = two-level with exact dv/dp; IPOPT = CasADi + IPOPT, exact Hessian, on "
        "the same transcription. Paper: AMD 3970X, MATLAB 2020a. `speedup` = paper time / ours "
        "(different machines). The suspension's road is synthetic (the paper's is not "
        "published), so its objective values are not comparable.",
        "",
    ]
    for name, rows in tables.items():
        lines += [f"## {name}", "", R.format_rows(rows, R.TABLE_COLUMNS), ""]
    lines += [
        "## Batched against one-by-one",
        "",
        "Per-problem wall time of one batched call (the dense interior point) and of solving "
        "the same problems one at a time (first problems of the batch), same run. The "
        "co-design rows: best of 3 batched calls and of 3 passes over the single problems, "
        "each after a warm-up; the crane rows: the batched call and a pass over the single "
        "problems with each backend in turn, three rounds after a warm-up of each, best of "
        "each (the machine's speed drifts; measured in blocks the ratio took the drift). The "
        "crane's batch runs on the reduced Newton system (`kkt='auto'`; on the CPU in float64 "
        "its iterations are one compiled loop per element); "
        "`per_problem_batched_full_kkt_ms` is the same batch on the full KKT matrix "
        "(`qp_options={'kkt': 'full'}`, one run) and `full_kkt_equal` whether its objectives "
        "agree to 1e-6; `per_problem_batched_torch_loop_ms` / `torch_loop_equal` the same "
        "for the reduced system's iterations as batched torch ops (`set_compiled(False)`, as "
        "on a GPU; best of 2).",
        "",
        R.format_rows(batch_rows),
        "",
    ]
    out.with_suffix(".md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
