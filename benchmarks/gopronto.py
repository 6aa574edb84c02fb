"""GoPRONTO vs PRONTO on the pendulum-on-cart train: a Table III analogue, a profile of
one GoPRONTO iteration, and many trains in one batch.

* Table III analogue: seconds per iteration (from the solver's own ``history["time"]``)
  and total seconds of a capped run, for N in {2, 5, 10, 50, 100}, Gradient GoPRONTO
  (Armijo) vs first-order PRONTO (when ``torchslq.PRONTO`` exists), float64, start at
  rest, +-30 deg. The paper: 33.13 s per GoPRONTO iteration at N = 100 in plain Python
  (target here: under 0.5 s on 2 cores).
* Profile: where one GoPRONTO solve at the largest N spends its time (cProfile,
  cumulative seconds of the solver's stages).
* Batch: ``--batch`` pendulum trains (N = ``--batch-carts``) with different amplitudes in
  ONE solve (each element has its own step size and stopping), against solving the
  first ``--singles`` of them one by one (same options; iterations and costs must agree).

Usage::

    python benchmarks/gopronto.py                      # everything, default caps
    python benchmarks/gopronto.py --carts 2 5 10 --iters 20
    python benchmarks/gopronto.py --skip-table --batch 64 --singles 4

Results: ``benchmarks/results/gopronto_bench.{json,md}``. Timings on a shared machine
are noisy; compare ratios measured in the same run.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import json
import platform
import pstats
import sys
import time
from pathlib import Path

import torch

# the paper reproductions live in the checkout's reproductions/, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reproductions.gopronto import PAPER_TABLE3, make_solver, pendulum_train_problem  # noqa: E402

OUT = Path(__file__).resolve().parent / "results"

STAGES = {
    "projection_gains": "projection gains (Riccati, n = 4N)",
    "_expand": "linearise + quadratise",
    "curve_gradient": "costate gradient (eq. 16)",
    "closed_loop_growth": "gain stability test",
    "_line_search": "line search (batched trial rollouts + costs)",
    "linearize": "  of which: linearize",
    "rollout_closed_loop": "closed-loop rollouts (projection + trials)",
    "riccati_backward": "  of which: riccati_backward",
}


def _env() -> dict:
    return {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "machine": platform.machine(),
        "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
    }


def _timed_solve(name: str, setup, max_iter: int, tol: float, **kwargs) -> dict:
    solver = make_solver(name, setup, max_iter=max_iter, tol=tol, **kwargs)
    t0 = time.perf_counter()
    res = solver.solve(setup.problem, setup.x0)
    total = time.perf_counter() - t0
    h = res.history["time"]
    it = int(res.iterations.max())
    setup_s = float(h[0]) if h.numel() else float("nan")
    per_it = float(h[it] - h[0]) / it if it > 0 else float("nan")
    rec = getattr(res, "recomputations", None)
    return {
        "solver": name + "".join(f" ({k}={v})" for k, v in kwargs.items()),
        "n_carts": setup.n_carts,
        "batch": setup.batch_size,
        "iterations": res.iterations.tolist(),
        "status": res.status_names(),
        "cost": res.cost.tolist(),
        "grad_norm": res.grad_norm.tolist(),
        "first_iteration_s": setup_s,
        "s_per_iteration": per_it,
        "total_s": total,
        "recomputations": None if rec is None else rec.tolist(),
    }


def table3(carts: list[int], iters: int, backtracks: int) -> list[dict]:
    import torchslq

    rows = []
    runs = [("gopronto-gradient", {})]
    if backtracks > 0:
        # with fewer trials the first trial must start near the accepted steps (~1e-4
        # here; the default step0 = 1 needs ~13 halvings)
        runs.append(("gopronto-gradient", {"max_backtracks": backtracks, "step0": 1e-3}))
    if hasattr(torchslq, "PRONTO"):
        runs.append(("pronto", {}))
    for N in carts:
        setup = pendulum_train_problem(N, 30.0)
        for name, kw in runs:
            r = _timed_solve(name, setup, iters, 1e-12, **kw)
            rows.append(r)
            print(
                f"[table3] N={N:3d} {r['solver']:18s} {r['s_per_iteration']:.3f} s/it, first "
                f"{r['first_iteration_s']:.2f} s, total {r['total_s']:.2f} s "
                f"({r['iterations'][0]} it)",
                flush=True,
            )
    return rows


def profile_solve(N: int, iters: int) -> dict:
    setup = pendulum_train_problem(N, 30.0)
    solver = make_solver("gopronto-gradient", setup, max_iter=iters, tol=1e-12)
    pr = cProfile.Profile()
    t0 = time.perf_counter()
    pr.enable()
    res = solver.solve(setup.problem, setup.x0)
    pr.disable()
    total = time.perf_counter() - t0
    st = pstats.Stats(pr)
    out = {"n_carts": N, "iterations": int(res.iterations.max()), "total_s": total, "stages": {}}
    for (_file, _line, fn), (_cc, nc, _tt, ct, _callers) in st.stats.items():
        if fn in STAGES:
            prev = out["stages"].get(fn, {"calls": 0, "cum_s": 0.0})
            out["stages"][fn] = {"calls": prev["calls"] + nc, "cum_s": prev["cum_s"] + ct}
    return out


def _problem(N: int, amps, projection: str):
    setup = pendulum_train_problem(N, amps)
    if projection == "R":  # projection weight R_reg = R instead of the paper's I
        setup = dataclasses.replace(setup, R_reg=setup.R)
    return setup


def batch_vs_singles(
    B: int, N: int, singles: int, max_iter: int, tol: float, projection: str = "paper"
) -> dict:
    amps = torch.linspace(10.0, 80.0, B, dtype=torch.float64)
    setup = _problem(N, amps, projection)
    batched = _timed_solve("gopronto-gradient", setup, max_iter, tol)
    print(f"[batch] B={B} N={N}: {batched['total_s']:.1f} s", flush=True)
    single_rows = []
    t_singles = 0.0
    for b in range(singles):
        sb = _problem(N, float(amps[b]), projection)
        r = _timed_solve("gopronto-gradient", sb, max_iter, tol)
        t_singles += r["total_s"]
        single_rows.append(r)
    agree = []
    for b, r in enumerate(single_rows):
        agree.append(
            {
                "amplitude_deg": float(amps[b]),
                "iterations_batch": batched["iterations"][b],
                "iterations_single": r["iterations"][0],
                "cost_batch": batched["cost"][b],
                "cost_single": r["cost"][0],
                "rel_cost_diff": abs(batched["cost"][b] - r["cost"][0]) / abs(r["cost"][0]),
            }
        )
    per_single = t_singles / max(singles, 1)
    return {
        "projection": projection,
        "B": B,
        "n_carts": N,
        "max_iter": max_iter,
        "tol": tol,
        "batched": batched,
        "singles": single_rows,
        "agreement": agree,
        "batch_total_s": batched["total_s"],
        "single_mean_s": per_single,
        "one_by_one_estimate_s": per_single * B,
        "speedup": per_single * B / batched["total_s"],
    }


def to_markdown(res: dict) -> str:
    parts = ["# GoPRONTO / PRONTO timings on the pendulum-on-cart train (Table III analogue)"]
    parts.append(f"Command: `{res['command']}`. Environment: `{json.dumps(res['env'])}`.")
    parts.append(
        "Timings come from a shared 2-core machine on which other engineers' jobs were "
        "running: absolute numbers are noisy (often 1.5-3x slower than an idle machine); "
        "ratios are measured in the same run. s/iteration is the solver's own "
        "history['time'] over the iterations after the first; 'first' is the time to "
        "iteration 0 (initial projection gains: one Riccati pass with n = 4N, plus the "
        "first projection and gradient). Capped runs: the totals are for the capped "
        "number of iterations, not to convergence."
    )
    if res.get("table3"):
        lines = [
            "| N | solver | ours s/iteration | paper s/iteration | ours first (s) | "
            "ours total (s) / iterations | paper total (s) | K recomputations |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in res["table3"]:
            N = r["n_carts"]
            col = 1 if r["solver"].startswith("gopronto") else 0
            pp = PAPER_TABLE3["per_iteration"].get(N, (None, None))[col]
            pt = PAPER_TABLE3["total"].get(N, (None, None))[col]
            rec = "-" if r["recomputations"] is None else str(r["recomputations"][0])
            lines.append(
                f"| {N} | {r['solver']} | {r['s_per_iteration']:.3f} | {pp} | "
                f"{r['first_iteration_s']:.2f} | {r['total_s']:.2f} / {r['iterations'][0]} | "
                f"{pt} | {rec} |"
            )
        parts.append("\n".join(lines))
    if res.get("profile"):
        p = res["profile"]
        lines = [
            f"Profile of one Gradient GoPRONTO solve, N = {p['n_carts']}, "
            f"{p['iterations']} iterations, {p['total_s']:.1f} s under cProfile:",
            "",
            "| stage | calls | cumulative s |",
            "|---|---|---|",
        ]
        for fn, v in sorted(p["stages"].items(), key=lambda kv: -kv[1]["cum_s"]):
            lines.append(f"| {STAGES[fn]} (`{fn}`) | {v['calls']} | {v['cum_s']:.2f} |")
        parts.append("\n".join(lines))
    if res.get("batch"):
        b = res["batch"]
        lines = [
            f"{b['B']} pendulum trains (N = {b['n_carts']}, amplitudes 10..80 deg) in one "
            f"batch, Gradient GoPRONTO (Armijo, projection R_reg = "
            f"{'I' if b.get('projection', 'paper') == 'paper' else 'R'}), cap "
            f"{b['max_iter']} iterations, tol "
            f"{b['tol']:g}: {b['batch_total_s']:.1f} s for the batch; one by one "
            f"{b['single_mean_s']:.1f} s per problem (mean of {len(b['singles'])}), i.e. "
            f"~{b['one_by_one_estimate_s']:.0f} s for all {b['B']}: speed-up "
            f"{b['speedup']:.1f}x.",
            "",
            "| amplitude | iterations (batch) | iterations (single) | cost (batch) | "
            "cost (single) | rel. diff |",
            "|---|---|---|---|---|---|",
        ]
        for a in b["agreement"]:
            lines.append(
                f"| {a['amplitude_deg']:.2f} | {a['iterations_batch']} | "
                f"{a['iterations_single']} | {a['cost_batch']:.10g} | {a['cost_single']:.10g} "
                f"| {a['rel_cost_diff']:.1e} |"
            )
        its = b["batched"]["iterations"]
        st = b["batched"]["status"]
        lines.append("")
        lines.append(
            f"Per-element iterations in the batch: min {min(its)}, max {max(its)}; status "
            + ", ".join(f"{s}: {st.count(s)}" for s in sorted(set(st)))
            + "."
        )
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n"


def main() -> None:
    import sys

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--carts", type=int, nargs="+", default=[2, 5, 10, 50, 100])
    p.add_argument("--iters", type=int, default=10, help="iterations per timed solve")
    p.add_argument(
        "--backtracks",
        type=int,
        default=6,
        help="also time GoPRONTO with this max_backtracks and step0 = 1e-3 (Armijo "
        "trials per iteration, all rolled out as one batch; solver default: 30 trials "
        "from step0 = 1); 0 to skip",
    )
    p.add_argument("--profile-carts", type=int, default=100)
    p.add_argument("--profile-iters", type=int, default=5)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--batch-carts", type=int, default=10)
    p.add_argument("--batch-max-iter", type=int, default=50)
    p.add_argument("--batch-tol", type=float, default=1e-3)
    p.add_argument("--singles", type=int, default=4)
    p.add_argument("--batch-projection", choices=["paper", "R"], default="paper")
    p.add_argument("--skip-table", action="store_true")
    p.add_argument("--skip-profile", action="store_true")
    p.add_argument("--skip-batch", action="store_true")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--name", default="bench", help="results file gopronto_<name>.*")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    res: dict = {
        "env": _env(),
        "command": "python benchmarks/gopronto.py " + " ".join(sys.argv[1:]),
    }
    if not a.skip_table:
        res["table3"] = table3(a.carts, a.iters, a.backtracks)
    if not a.skip_profile:
        res["profile"] = profile_solve(a.profile_carts, a.profile_iters)
        print(f"[profile] {res['profile']}", flush=True)
    if not a.skip_batch:
        res["batch"] = batch_vs_singles(
            a.batch, a.batch_carts, a.singles, a.batch_max_iter, a.batch_tol, a.batch_projection
        )
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"gopronto_{a.name}.json").write_text(json.dumps(res, indent=1))
    md = to_markdown(res)
    (OUT / f"gopronto_{a.name}.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
