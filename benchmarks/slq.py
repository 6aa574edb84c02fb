"""Benchmark of the batched SLQ solver (``torchslq.SLQ``): time to converge vs batch size.

Not part of the test suite (``pytest`` only collects ``tests/``). Run from the repo root::

    .venv/bin/python benchmarks/slq.py --quick --out /tmp/slq_quick   # a quick subset
    .venv/bin/python benchmarks/slq.py                                 # full run

What is measured
----------------
Two problems, float64 on the CPU, ``torch.set_num_threads(--threads)`` (default 1):

* ``pendulum``: :func:`torchslq.tasks.pendulum_swingup` (horizon 100, dt 0.05, seed 0,
  ``x0 ~ U(-1, 1)^2`` per element), ``SLQ(rollout="closed_loop", line_search="exact",
  max_iter=100, tol=1e-6)``;
* ``drag``: the viscous-drag vehicle of Sideris & Bobrow (2005), Section 4.1 (N = 500,
  m = 0.0259, q = 1, r = 10, qfin = 1e6), one element per ``beta``, the betas cycling
  over ``0.01, 0.05, 0.1, 0.5``; the paper's setting ``SLQ(line_search="armijo",
  rollout="open_loop", max_iter=300, tol=1e-6)``.

For every batch size B in ``--batches``:

* **solve**: ``SLQ.solve`` from ``u = 0`` (wall and process CPU time of the call, best of up to
  ``--repeat`` runs, stopping early once ``--solve-budget`` seconds are spent; at least
  one). A batched solve loops until its slowest element stops, so the reported
  iterations are mean / max over the elements and ``loop iters`` is the number of
  directions computed (max iterations + 1 when every element converged);
* **B = 1** is the one-by-one baseline: the first ``--baseline`` problems of the set
  (pendulum: the first initial states of the seed; drag: betas 0.01, 0.05, 0.1, 0.5)
  each solved ALONE; its time per problem is the mean over those solves. Per-problem
  time at B is ``solve time / B``; ``speedup`` is per-problem time at B = 1 over
  per-problem time at B (same run). Because the batched loop runs for the slowest
  element, the speedup also depends on the iteration counts; ``iter speedup`` compares
  the cost of one loop iteration per problem instead (``t_iter(1) B / t_iter(B)``);
* **split**: the per-iteration cost split, timed piece by piece at a representative
  iterate (the state after ``--rep-iter`` SLQ iterations from ``u = 0``) with exactly the
  calls ``SLQ.direction`` / ``SLQ.solve`` make: ``linearize`` (``torchslq.linearize``),
  ``quad+grad`` (``problem.cost.quadratize`` + ``torchslq.solvers.costate_gradient``),
  ``riccati+rollout`` (``torchslq.riccati_backward`` + ``torchslq.rollout_linear``),
  ``line search`` (``SLQ()._line_search``: all trial rollouts + costs + selection); each
  the best of ``--repeat`` calls (fewer once a piece has used ``--split-budget`` seconds),
  wall and CPU time (the table shows CPU). The solves themselves are run by a subclass of
  SLQ that adds up the time spent in ``direction`` and ``_line_search``, so the table
  also gives the split inside the real solves and the ``rest`` per loop iteration
  (masking, norms, stopping tests, history).

Configurations whose solve is estimated (wall split x expected loop iterations: the most
seen at a smaller B in this run, else 101 for the pendulum and 40 for the drag vehicle)
to take longer than ``--time-limit`` seconds are not solved ("skipped"); their split is
still measured and the estimate reported. ``--mallopt`` sets glibc's malloc to keep
large blocks in the heap (see ``tune_malloc``), for comparison runs.

The machine this was written for has 2 cores that other processes share: the load
average at start and end is recorded and every ratio is taken within one run.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import torch

from torchslq import SLQ, linearize, riccati_backward, rollout_linear
from torchslq.solvers import costate_gradient, rollout
from torchslq.tasks import drag_vehicle_problem as _drag_builder
from torchslq.tasks import pendulum_swingup

DRAG_BETAS = (0.01, 0.05, 0.1, 0.5)
SYSTEMS = ("pendulum", "drag")
SETTINGS = {
    "pendulum": {
        "solver": {"line_search": "exact", "rollout": "closed_loop", "max_iter": 100, "tol": 1e-6},
        "problem": "pendulum_swingup(B, horizon=100, dt=0.05, seed=0), float64",
        "expect_loops": 101,
    },
    "drag": {
        "solver": {"line_search": "armijo", "rollout": "open_loop", "max_iter": 300, "tol": 1e-6},
        "problem": "Sideris & Bobrow drag vehicle, N=500, betas cycling over "
        + ", ".join(map(str, DRAG_BETAS))
        + ", float64",
        "expect_loops": 40,
    },
}
PIECES = ("linearize", "quad+grad", "riccati+rollout", "line search")


# ---------------------------------------------------------------------------- problems
DRAG_SOURCE = "torchslq.tasks.drag_vehicle_problem"


def drag_betas(B: int, start: int = 0) -> list[float]:
    return [DRAG_BETAS[(start + i) % len(DRAG_BETAS)] for i in range(B)]


def make_problem(system: str, B: int, index: int | None = None):
    """``(problem, x0)`` of batch ``B``; with ``index`` the single problem number ``index``
    of the set (B = 1, same element as in every larger batch)."""
    if system == "pendulum":
        if index is None:
            return pendulum_swingup(B, horizon=100, dt=0.05, seed=0)
        problem, x0 = pendulum_swingup(index + 1, horizon=100, dt=0.05, seed=0)
        return problem, x0[index : index + 1].clone()
    if index is None:
        return _drag_builder(drag_betas(B))
    return _drag_builder(drag_betas(1, start=index))


def make_solver(system: str, **extra) -> SLQ:
    return SLQ(progress=False, **{**SETTINGS[system]["solver"], **extra})


class _Timed:
    """Wraps a callable piece of a solver's rule (its direction or its line search) and
    adds up the wall / CPU time of its calls into ``acc[key]``."""

    def __init__(self, piece, acc: list):
        self.piece, self.acc = piece, acc

    def __call__(self, *a):
        t, c = time.perf_counter(), time.process_time()
        out = self.piece(*a)
        self.acc[0] += time.perf_counter() - t
        self.acc[1] += time.process_time() - c
        self.acc[2] += 1
        return out

    def __getattr__(self, name):  # the direction's other methods (after_search)
        return getattr(self.piece, name)


class TimedSLQ(SLQ):
    """SLQ that adds up the wall / CPU time spent in its direction and its line search
    during a real solve (two clock reads per call; nothing else changes)."""

    def __init__(self, **kw):
        super().__init__(**kw)
        object.__setattr__(self, "acc", {"direction": [0.0, 0.0, 0], "line search": [0.0, 0.0, 0]})

    def rule(self):
        rule = super().rule()
        return dataclasses.replace(
            rule,
            direction=_Timed(rule.direction, self.acc["direction"]),
            search=_Timed(rule.search, self.acc["line search"]),
        )


# ---------------------------------------------------------------------------- timing
def best_of(fn, repeat: int, budget: float) -> tuple[float, float, list[list[float]]]:
    """Best wall and best CPU (process) time of up to ``repeat`` calls of ``fn`` (stop
    once ``budget`` s are used); also the ``[wall, cpu]`` samples."""
    samples: list[list[float]] = []
    spent = 0.0
    for _ in range(max(1, repeat)):
        t, c = time.perf_counter(), time.process_time()
        fn()
        samples.append([time.perf_counter() - t, time.process_time() - c])
        spent += samples[-1][0]
        if spent >= budget:
            break
    return min(w for w, _ in samples), min(c for _, c in samples), samples


def measure_split(system: str, problem, x0, args) -> dict:
    """Per-iteration cost split at a representative iterate (see the module docstring)."""
    solver = make_solver(system)
    rep = make_solver(system, max_iter=args.rep_iter) if args.rep_iter > 0 else None
    with torch.no_grad():
        if rep is not None:
            res = rep.solve(problem, x0)
            x, u = res.x, res.u
        else:
            x0, u, _ = problem.check_inputs(x0, None)
            x = rollout(problem.transition, x0, u)
        T = problem.horizon
        f, cost_fn = problem.transition, problem.cost
        method = solver.options.linearize_method
        A, Bm = linearize(f, x[:, :T], u, method=method)
        e = cost_fn.quadratize(x, u)
        d = solver.direction(problem, x, u)

        def lin():
            linearize(f, x[:, :T], u, method=method)

        def quad_grad():
            ee = cost_fn.quadratize(x, u)
            costate_gradient(A, Bm, ee.lx, ee.lu)

        def ric_roll():
            fc = riccati_backward(A, Bm, e.lxx, e.luu, e.lx, e.lu, e.lux)
            rollout_linear(A, Bm, fc.K, fc.k, torch.zeros_like(x[:, 0]))

        rule = solver.rule()
        state = solver.initial_state(problem, x[:, 0], u, x)
        running = torch.ones(x.shape[0], dtype=torch.bool)

        def line_search():
            rule.search(problem, state, d, running)

        def direction():
            solver.direction(problem, x, u)

        out, cpu, samples = {}, {}, {}
        for name, fn in zip(
            (*PIECES, "direction"), (lin, quad_grad, ric_roll, line_search, direction), strict=True
        ):
            fn()  # warm-up at this shape
            out[name], cpu[name], samples[name] = best_of(fn, args.repeat, args.split_budget)
    out["sum"] = sum(out[p] for p in PIECES)
    cpu["sum"] = sum(cpu[p] for p in PIECES)
    return {"seconds": out, "cpu_seconds": cpu, "samples": samples, "rep_iter": args.rep_iter}


def run_solve(system: str, problem, x0) -> dict:
    solver = TimedSLQ(progress=False, **SETTINGS[system]["solver"])
    t, c = time.perf_counter(), time.process_time()
    res = solver.solve(problem, x0)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    it = res.iterations.to(torch.float64)
    names = res.status_names()
    return {
        "wall": wall,
        "cpu": cpu,
        "in_solve": {k: {"wall": v[0], "cpu": v[1], "calls": v[2]} for k, v in solver.acc.items()},
        "loop_iters": int(res.history["time"].shape[0]),
        "iters": [int(i) for i in res.iterations],
        "iters_mean": float(it.mean()),
        "iters_max": int(it.max()),
        "converged": float(res.converged.to(torch.float64).mean()),
        "status": {s: names.count(s) for s in sorted(set(names))},
    }


def measure_baseline(system: str, args) -> dict:
    """The first ``args.baseline`` problems of the set solved one at a time."""
    runs = []
    spent = 0.0
    for _ in range(max(1, args.repeat)):
        solos = [run_solve(system, *make_problem(system, 1, index=i)) for i in range(args.baseline)]
        wall = sum(s["wall"] for s in solos)
        runs.append({"wall": wall, "cpu": sum(s["cpu"] for s in solos), "solos": solos})
        spent += wall
        if spent >= args.solve_budget:
            break
    best = min(runs, key=lambda r: r["wall"])
    solos = best["solos"]
    iters = [s["iters"][0] for s in solos]
    loops = sum(s["loop_iters"] for s in solos)
    status: dict[str, int] = {}
    in_solve = {k: {"wall": 0.0, "cpu": 0.0, "calls": 0} for k in solos[0]["in_solve"]}
    for s in solos:
        for k, v in s["status"].items():
            status[k] = status.get(k, 0) + v
        for k, v in s["in_solve"].items():
            for f in v:
                in_solve[k][f] += v[f]
    return {
        "wall": best["wall"],
        "cpu": best["cpu"],
        "samples": [[r["wall"], r["cpu"]] for r in runs],
        "n_problems": len(solos),
        "per_problem": best["wall"] / len(solos),
        "per_problem_cpu": best["cpu"] / len(solos),
        "per_iter": best["wall"] / loops,
        "per_iter_cpu": best["cpu"] / loops,
        "loop_iters": loops,
        "in_solve": in_solve,
        "iters": iters,
        "iters_mean": sum(iters) / len(iters),
        "iters_max": max(iters),
        "converged": sum(s["converged"] for s in solos) / len(solos),
        "status": status,
        "solo_walls": [s["wall"] for s in solos],
    }


def measure_batch(system: str, B: int, args, expect_loops: int, overhead: float) -> dict:
    problem, x0 = make_problem(system, B)
    split = measure_split(system, problem, x0, args)
    per_iter_est = split["seconds"]["sum"] * overhead
    est = per_iter_est * expect_loops
    entry: dict = {"split": split, "estimate_s": est}
    if est > args.time_limit:
        entry["skipped"] = (
            f"estimated {est:.0f} s > --time-limit {args.time_limit:.0f} s "
            f"({per_iter_est:.2f} s/iter x {expect_loops} loop iterations)"
        )
        return entry
    runs = []
    spent = 0.0
    for _ in range(max(1, args.repeat)):
        runs.append(run_solve(system, problem, x0))
        spent += runs[-1]["wall"]
        if spent + runs[-1]["wall"] > args.solve_budget:
            break
    best = min(runs, key=lambda r: r["wall"])
    entry.update(
        {
            "wall": best["wall"],
            "cpu": best["cpu"],
            "samples": [[r["wall"], r["cpu"]] for r in runs],
            "per_problem": best["wall"] / B,
            "per_problem_cpu": best["cpu"] / B,
            "per_iter": best["wall"] / best["loop_iters"],
            "per_iter_cpu": best["cpu"] / best["loop_iters"],
            "loop_iters": best["loop_iters"],
            "in_solve": best["in_solve"],
            "iters_mean": best["iters_mean"],
            "iters_max": best["iters_max"],
            "converged": best["converged"],
            "status": best["status"],
        }
    )
    return entry


# ---------------------------------------------------------------------------- report
def _ms(s: float | None) -> str:
    if s is None:
        return "-"
    return f"{s * 1e3:.1f}" if s < 10 else f"{s * 1e3:.0f}"


def _s(s: float | None) -> str:
    return "-" if s is None else f"{s:.2f}"


def tables(results: dict) -> str:
    head = (
        "| system | B | solve wall (s) | solve CPU (s) | iters mean / max | loop iters "
        "| time/iter (ms) | time/problem (ms) | speedup/problem vs B=1 (wall / CPU) "
        "| iter speedup | converged |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    rows = []
    split_rows = []
    for system, per_b in results.items():
        base = per_b.get("1")
        for b_str, r in per_b.items():
            B = int(b_str)
            if "skipped" in r:
                est = r["split"]["seconds"]["sum"]
                isp = f"{base['per_iter'] * B / est:.1f}x (split)" if base else "-"
                rows.append(
                    f"| {system} | {B} | skipped (est. {r['estimate_s']:.0f} s) | - | - | - "
                    f"| ({_ms(est)} split sum) | - | - | {isp} | - |"
                )
            else:
                label = f"1 ({r['n_problems']} solved alone)" if B == 1 else str(B)
                sp = (
                    f"{base['per_problem'] / r['per_problem']:.1f}x / "
                    f"{base['per_problem_cpu'] / r['per_problem_cpu']:.1f}x"
                    if base
                    else "-"
                )
                isp = f"{base['per_iter'] * B / r['per_iter']:.1f}x" if base else "-"
                rows.append(
                    f"| {system} | {label} | {_s(r['wall'])} | {_s(r['cpu'])} "
                    f"| {r['iters_mean']:.1f} / {r['iters_max']} | {r['loop_iters']} "
                    f"| {_ms(r['per_iter'])} | {_ms(r['per_problem'])} | {sp} | {isp} "
                    f"| {r['converged'] * 100:.1f}% |"
                )
            s = r["split"]["cpu_seconds"]
            tot = s["sum"]
            cells = " | ".join(f"{_ms(s[p])} ({100 * s[p] / tot:.0f}%)" for p in PIECES)
            ins = "- | - | -"
            if "in_solve" in r:
                d, ls = r["in_solve"]["direction"], r["in_solve"]["line search"]
                rest = (r["cpu"] - d["cpu"] - ls["cpu"]) / r["loop_iters"]
                ins = (
                    f"{_ms(d['cpu'] / max(1, d['calls']))} | "
                    f"{_ms(ls['cpu'] / max(1, ls['calls']))} | {_ms(rest)}"
                )
            split_rows.append(
                f"| {system} | {B} | {cells} | {_ms(tot)} | {_ms(s['direction'])} "
                f"| {_ms(r['split']['seconds']['sum'])} | {ins} | {_ms(tot / B)} |"
            )
    split_head = (
        "| system | B | linearize | quad+grad | riccati+rollout | line search | sum "
        "| direction() | sum (wall) | in solve: direction | in solve: line search "
        "| in solve: rest/iter | sum / B |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    return (
        "### Time to converge\n\n"
        + head
        + "\n".join(rows)
        + "\n\n### Per-iteration split (CPU ms, best of the repeats; share of the sum "
        "of the four pieces)\n\n" + split_head + "\n".join(split_rows) + "\n"
    )


def tune_malloc() -> bool:
    """glibc: serve large blocks from the heap and keep freed memory (no mmap/munmap and
    page faults for every big temporary). Process-wide; for comparison runs only."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:  # pragma: no cover - not glibc
        return False
    m_trim, m_top_pad, m_mmap = -1, -2, -3
    ok = libc.mallopt(m_mmap, 2**31 - 1) == 1
    ok &= libc.mallopt(m_trim, 2**31 - 1) == 1
    ok &= libc.mallopt(m_top_pad, 256 << 20) == 1
    return bool(ok)


def git_state() -> dict:
    """Commit of the checkout and the library files that differ from it (other work may
    be in progress in the same tree)."""
    import subprocess

    def git(*a: str) -> str:
        try:
            return subprocess.run(
                ["git", *a], capture_output=True, text=True, check=True, timeout=20
            ).stdout.rstrip("\n")
        except (OSError, subprocess.SubprocessError):
            return ""

    dirty = git("status", "--porcelain", "--", "torchslq")
    return {"commit": git("rev-parse", "HEAD").strip(), "torchslq_changes": dirty.splitlines()}


def loadavg() -> list[float] | None:
    try:
        return [float(v) for v in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:  # pragma: no cover
        return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="batches 1,16; repeat 1; baseline 2")
    p.add_argument("--batches", default=None, help="comma list (default 1,16,256,4096)")
    p.add_argument("--systems", default=",".join(SYSTEMS), help="pendulum,drag")
    p.add_argument("--repeat", type=int, default=None, help="timed repeats (default 3)")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1)")
    p.add_argument("--baseline", type=int, default=None, help="problems solved alone for B=1")
    p.add_argument("--rep-iter", type=int, default=2, help="iterations to the split iterate")
    p.add_argument("--time-limit", type=float, default=120.0, help="max est. s per solve")
    p.add_argument("--solve-budget", type=float, default=40.0, help="s of repeats per config")
    p.add_argument("--split-budget", type=float, default=8.0, help="s of repeats per piece")
    p.add_argument(
        "--mallopt",
        action="store_true",
        help="glibc mallopt: no mmap / trim for large blocks (comparison runs)",
    )
    p.add_argument("--out", default="benchmarks/results/slq", help="output prefix (.json/.md)")
    args = p.parse_args(argv)
    if args.batches is None:
        args.batches = "1,16" if args.quick else "1,16,256,4096"
    if args.repeat is None:
        args.repeat = 1 if args.quick else 3
    if args.baseline is None:
        args.baseline = 2 if args.quick else 4
    batches = sorted({int(b) for b in args.batches.split(",") if b.strip()})
    systems = [s.strip() for s in args.systems.split(",") if s.strip()]
    for s in systems:
        if s not in SYSTEMS:
            p.error(f"unknown system {s!r}; choose from {SYSTEMS}")
    mallopt = tune_malloc() if args.mallopt else None
    torch.set_num_threads(args.threads)
    torch.set_default_dtype(torch.float64)
    command = "python benchmarks/slq.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    command = command.strip()
    load0 = loadavg()
    git0 = git_state()
    t_start = time.perf_counter()
    print(f"# {command}")
    print(
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, "
        f"{os.cpu_count()} CPUs, load average {load0}"
    )

    results: dict[str, dict[str, dict]] = {}
    for system in systems:
        # warm-up: one small solve (first-call overheads, allocator)
        make_solver(system, max_iter=2).solve(*make_problem(system, 1, index=0))
        per_b: dict[str, dict] = {}
        results[system] = per_b
        # loop iterations expected before any solve of this run (a prior from earlier
        # runs: the pendulum batch of 256 already has an element at max_iter); then the
        # largest count seen so far in this run
        expect = SETTINGS[system]["expect_loops"]
        seen = 0
        overhead = 1.0
        for B in batches:
            t0 = time.perf_counter()
            if B == 1:
                base = measure_baseline(system, args)
                split = measure_split(system, *make_problem(system, 1, index=0), args)
                base["split"] = split
                per_b["1"] = base
                r = base
            else:
                r = measure_batch(system, B, args, expect, overhead)
                per_b[str(B)] = r
            if "wall" in r:
                seen = max(seen, r["iters_max"] + 1)
                expect = seen
                overhead = max(1.0, r["per_iter"] / r["split"]["seconds"]["sum"])
                print(
                    f"[{system}] B={B}: solve {r['wall']:.2f} s, iters mean "
                    f"{r['iters_mean']:.1f} max {r['iters_max']}, {r['per_iter'] * 1e3:.1f} "
                    f"ms/iter, {r['per_problem'] * 1e3:.2f} ms/problem "
                    f"({time.perf_counter() - t0:.0f} s incl. split)",
                    flush=True,
                )
            else:
                print(f"[{system}] B={B}: SKIPPED, {r['skipped']}", flush=True)
            s = r["split"]["seconds"]
            print(
                "    split (ms): "
                + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in s.items() if k != "direction"),
                flush=True,
            )

    load1 = loadavg()
    total = time.perf_counter() - t_start
    table = tables(results)
    print()
    print(table)
    skipped = [
        f"{sys_} B={b}: {r['skipped']}"
        for sys_, per_b in results.items()
        for b, r in per_b.items()
        if "skipped" in r
    ]
    meta = {
        "command": command,
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "threads": torch.get_num_threads(),
        "mallopt": mallopt,
        "git_start": git0,
        "git_end": git_state(),
        "dtype": "float64",
        "loadavg_start": load0,
        "loadavg_end": load1,
        "total_wall_s": total,
        "drag_problem_source": DRAG_SOURCE,
        "settings": SETTINGS,
        "args": vars(args),
        "skipped": skipped,
    }
    notes = (
        f"float64, CPU, torch {torch.__version__}, torch threads {torch.get_num_threads()}, "
        f"{os.cpu_count()} CPU cores shared with other processes (load average {load0} at "
        f"start, {load1} at end): absolute times are noisy; ratios (speedups) are taken "
        f"within this one run. Total benchmark wall time {total:.0f} s. Library: commit "
        f"`{git0['commit'][:10]}` at start"
        + (
            f" with uncommitted changes in {', '.join(c[3:] for c in git0['torchslq_changes'])}"
            if git0["torchslq_changes"]
            else ""
        )
        + " (see the JSON for the state at the end; other work shares this checkout).\n\n"
        "Settings: pendulum = `pendulum_swingup(B, horizon=100, dt=0.05, seed=0)`, "
        "`SLQ(rollout='closed_loop', line_search='exact', max_iter=100, tol=1e-6)`; drag = "
        "Sideris & Bobrow drag vehicle (N = 500) with betas cycling over "
        f"{', '.join(map(str, DRAG_BETAS))}, `SLQ(line_search='armijo', "
        "rollout='open_loop', max_iter=300, tol=1e-6)` (the paper's setting; problem from "
        f"{DRAG_SOURCE}). All solves start from u = 0.\n\n"
        "Columns: `solve wall` / `solve CPU` = wall and process CPU time of `SLQ.solve` "
        "(best of the repeats; with one torch thread the CPU time is the work done, "
        "without the time spent waiting for a core, so it is the steadier number here); "
        f"B = 1 is the first {args.baseline} problems of the set solved one at a time "
        "(sum of their times; drag: one per beta); `loop iters` = directions computed (a "
        "batch runs until its slowest element stops); `time/iter`, `time/problem` = wall "
        "solve / loop iters, / B (B = 1: mean over the single solves); `speedup/problem` "
        "= time/problem at B = 1 over time/problem at B (wall, and the same with CPU "
        "times); `iter speedup` = (wall time/iter at B = 1) x B / (wall time/iter at B), "
        "the batching gain per loop iteration, independent of iteration counts (skipped "
        "rows: from the split sum).\n\n"
        "Split: each piece timed alone (CPU time, best of the repeats) at the iterate "
        f"after {args.rep_iter} SLQ iterations from u = 0 (B = 1: problem 0 alone): "
        "`linearize` = `torchslq.linearize`, `quad+grad` = `cost.quadratize` + "
        "`costate_gradient`, `riccati+rollout` = `riccati_backward` + `rollout_linear`, "
        "`line search` = `SLQ._line_search` (all trial rollouts, their costs and the "
        "selection); `direction()` = the whole `SLQ.direction` call (the first three "
        "pieces plus the slope). `in solve`: the CPU time per call of `direction` and "
        "`_line_search` summed over the actual solves above (an instrumented SLQ "
        "subclass), and the rest of the solve per loop iteration (masking, norms, "
        "stopping tests, history). In-solve times are higher than the best-of split on a "
        "loaded machine (colder caches, fresh allocations).\n"
    )
    if mallopt:
        notes += (
            "\nRun with `--mallopt`: glibc serves large blocks from the heap and keeps "
            "freed memory (M_MMAP_THRESHOLD = M_TRIM_THRESHOLD = 2^31-1, M_TOP_PAD = "
            "256 MiB).\n"
        )
    if skipped:
        notes += "\nSkipped (estimated from the split x expected loop iterations):\n\n"
        notes += "".join(f"* {s}\n" for s in skipped)
    md = f"# SLQ benchmark: time to converge vs batch size\n\nCommand: `{command}`\n\n"
    md += notes + "\n" + table
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.with_suffix(".json").write_text(
            json.dumps({"meta": meta, "results": results}, indent=1) + "\n"
        )
        out.with_suffix(".md").write_text(md)
        print(f"saved {out.with_suffix('.json')} and {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
