"""torchslq on a CUDA GPU beside the CPU of the same machine.

Not part of the test suite. Run from the repo root on a machine with a GPU::

    python benchmarks/gpu.py --parts lq --name lq             # (a) LQ kernel throughput
    python benchmarks/gpu.py --parts cartpole --name cartpole # (b) cart-pole DDP / ILQR
    python benchmarks/gpu.py --parts mpc --name mpc_layer     # (c) the MPC layer setting
    python benchmarks/gpu.py --quick --out /tmp/gpu           # tiny sizes, CPU-only is fine

Each part writes ``benchmarks/results/gpu_<name>.{json,md}`` (the markdown starts with
the command line, device name and torch version) after every measurement, so a run
stopped early keeps what it measured.

Parts:

(a) ``lq``: :func:`torchslq.lqr_solve` forward + backward (``torch.autograd.grad`` of
    ``sum(cost) + sum(x) + sum(u)`` w.r.t. ``Q, q, A, B, x0``) on a fully batched,
    time-varying random problem (all terms present), ``T = 50``, ``(n, m)`` in
    ``{(4, 1), (12, 4)}``, ``B`` in ``{1, 64, 1024, 16384}``, float32 and float64;
    ``validate=False`` (as the solvers call it). CPU with all of the machine's threads and
    with 1 thread, and CUDA. Best of the timed calls after a warm-up call (calls repeat
    until ``--budget`` seconds or 10 calls, at least 2), ``torch.cuda.synchronize()``
    before and after each timed call.
(b) ``cartpole``: the swing-up of ``benchmarks/peers.py`` (:func:`torchslq.tasks.cartpole_swingup`,
    T = 50, seed 0) solved by the solvers that ``peers.py`` builds (``DDP`` and ``ILQR``,
    ``tol = 1e-6``, ``compact=True``) with ``--cp-max-iter`` iterations at most, at
    ``B`` in ``{512, 4096}``, float64 on CUDA and CPU (all threads), float32 on CUDA.
    One timed solve after a warm-up solve at B = 64. Reported: time, iterations (mean /
    max), converged count, and the per-element cost difference to the CPU float64 solve
    (max relative, and how many within 1e-6).
(c) ``mpc``: the setting of ``benchmarks/mpc_layer.py`` (B = 64, T = 40, 4-mass chain,
    n + m = 12, model mismatch, warm-started ILQR, ``backward="implicit"``), but only
    ``--mpc-steps`` closed-loop steps; forward (the steps) and backward timed
    separately, CUDA vs CPU (1 thread, as in mpc_layer.py, and all threads), float64 and
    float32; mpc.pytorch (``mpc`` package, ``GradMethods.ANALYTIC``) on CUDA and CPU when
    importable. The loss and final states are compared with torchslq on the CPU.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from torchslq import ILQR, MPC, QuadraticCost, lqr_solve  # noqa: E402
from torchslq.tasks import cartpole_swingup  # noqa: E402

WRT = ("Q", "q", "A", "B", "x0")


# ---------------------------------------------------------------------------- helpers
def sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def timed(fn, dev: torch.device, budget: float, warmup: int = 1, max_calls: int = 10):
    """Best wall time of ``fn()`` over calls after ``warmup`` untimed ones."""
    ts: list[float] = []
    for _ in range(warmup):
        sync(dev)
        t0 = time.perf_counter()
        fn()
        sync(dev)
        tw = time.perf_counter() - t0
        if tw > 3 * budget:  # a slow call (big CPU batch): the warm-up is the only sample
            return tw, 0
    while len(ts) < max_calls and (len(ts) < 2 or sum(ts) < budget):
        sync(dev)
        t0 = time.perf_counter()
        fn()
        sync(dev)
        ts.append(time.perf_counter() - t0)
    return min(ts), len(ts)


def cpu_threads_configs(all_threads: int) -> list[tuple[str, torch.device, int]]:
    out = [(f"cpu {all_threads} thr", torch.device("cpu"), all_threads)]
    if all_threads != 1:
        out.append(("cpu 1 thr", torch.device("cpu"), 1))
    return out


def device_name() -> str:
    if torch.cuda.is_available():
        return torch.cuda.get_device_name(0)
    return "no CUDA device"


def fmt(v, spec=".3g") -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return format(v, spec)
    return str(v)


def md_table(rows: list[dict], cols: list[tuple[str, str]]) -> str:
    head = "| " + " | ".join(h for h, _ in cols) + " |\n|" + "---|" * len(cols) + "\n"
    body = "".join("| " + " | ".join(fmt(r.get(k)) for _, k in cols) + " |\n" for r in rows)
    return head + body


# ---------------------------------------------------------------------------- (a) LQ kernel
def lq_args(B: int, T: int, n: int, m: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Fully batched, time-varying, well-conditioned LQ problem (float64, CPU)."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64

    def spd(shape, k):
        M = torch.randn(*shape, k, k, generator=g, dtype=f64)
        return M @ M.mT / k + 0.5 * torch.eye(k, dtype=f64)

    A = torch.eye(n, dtype=f64) + 0.3 * torch.randn(B, T, n, n, generator=g, dtype=f64) / n
    return dict(
        A=A,
        B=torch.randn(B, T, n, m, generator=g, dtype=f64),
        Q=spd((B, T + 1), n),
        R=spd((B, T), m),
        x0=torch.randn(B, n, generator=g, dtype=f64),
        q=torch.randn(B, T + 1, n, generator=g, dtype=f64),
        r=torch.randn(B, T, m, generator=g, dtype=f64),
        S=0.1 * torch.randn(B, T, m, n, generator=g, dtype=f64),
        c=0.5 * torch.randn(B, T, n, generator=g, dtype=f64),
    )


def lq_fwd_bwd(args: dict[str, torch.Tensor]):
    a = {k: v.detach().requires_grad_(k in WRT) for k, v in args.items()}
    sol = lqr_solve(**a, validate=False)
    loss = sol.cost.sum() + sol.x.sum() + sol.u.sum()
    grads = torch.autograd.grad(loss, [a[k] for k in WRT])
    return sol.cost.detach(), grads


def bench_lq(args, meta, save):
    rows = []
    configs = cpu_threads_configs(args.threads)
    if torch.cuda.is_available():
        configs.append(("cuda", torch.device("cuda"), None))
    T = 50
    for dtype_name in args.dtypes:
        dtype = getattr(torch, dtype_name)
        for n, m in args.sizes:
            for B in args.lq_batches:
                base = lq_args(B, T, n, m)
                row = {"dtype": dtype_name, "n": n, "m": m, "B": B, "T": T}
                ref_cost = None
                for label, dev, thr in configs:
                    if thr is not None:
                        torch.set_num_threads(thr)
                    a = {k: v.to(dev, dtype) for k, v in base.items()}
                    t, calls = timed(lambda a=a: lq_fwd_bwd(a), dev, args.budget)
                    cost = lq_fwd_bwd(a)[0].to("cpu", torch.float64)
                    if ref_cost is None:
                        ref_cost = cost
                    diff = float(((cost - ref_cost).abs() / ref_cost.abs().clamp_min(1e-12)).max())
                    row[f"{label} ms"] = 1e3 * t
                    row[f"{label} calls"] = calls
                    row[f"{label} problems/s"] = B / t
                    row[f"{label} cost rel diff"] = diff
                    print(f"  lq {dtype_name} ({n},{m}) B={B:<6d} {label:12s} {1e3 * t:10.2f} ms "
                          f"({calls} calls) cost rel diff vs first {diff:.1e}", flush=True)  # fmt: skip
                    del a
                torch.set_num_threads(args.threads)
                if "cuda ms" in row:
                    for label, _, _ in configs[:-1]:
                        row[f"speedup vs {label}"] = row[f"{label} ms"] / row["cuda ms"]
                rows.append(row)
                save(rows)
    return rows


def lq_markdown(rows, args) -> str:
    thr = f"cpu {args.threads} thr"
    cols = [("dtype", "dtype"), ("(n,m)", "nm"), ("B", "B")]
    cols += [(f"{thr} [ms]", f"{thr} ms"), ("cpu 1 thr [ms]", "cpu 1 thr ms")]
    cols += [("cuda [ms]", "cuda ms"), ("cuda problems/s", "cuda problems/s")]
    cols += [(f"cuda speedup vs {thr}", f"speedup vs {thr}")]
    cols += [("cuda speedup vs cpu 1 thr", "speedup vs cpu 1 thr")]
    cols += [("max rel cost diff cuda vs cpu", "cuda cost rel diff")]
    for r in rows:
        r["nm"] = f"({r['n']},{r['m']})"
    note = (
        "\nTimes: best of the timed calls after one warm-up call (`calls` in the JSON; 0 means"
        f" the warm-up took over {3 * args.budget:g} s and is the only sample, so it includes"
        " first-call allocation). One call = `lqr_solve(..., validate=False)` forward and"
        " `torch.autograd.grad` of `sum(cost) + sum(x) + sum(u)` w.r.t. Q, q, A, B, x0."
        " Speedup = CPU time / CUDA time (> 1: the GPU is faster). Cost diff: max over the"
        f" batch of the relative difference of the optimal cost between CUDA and CPU {args.threads}"
        " threads in the same dtype.\n"
    )
    return md_table(rows, cols) + note


# ---------------------------------------------------------------------------- (b) cart-pole
def bench_cartpole(args, meta, save):
    from peers import torchslq_solvers

    torch.set_num_threads(args.threads)
    makers = torchslq_solvers(args.cp_max_iter)
    solvers = {k.replace("torchslq ", ""): v for k, v in makers.items() if "SLQ" not in k}
    runs = [("cuda", "float64"), ("cpu", "float64"), ("cuda", "float32")]
    if not torch.cuda.is_available():
        runs = [("cpu", "float64"), ("cpu", "float32")]
    rows = []
    for dev_name, dtype_name in runs:  # warm-up: one small solve per device/dtype/solver
        dev, dtype = torch.device(dev_name), getattr(torch, dtype_name)
        for mk in solvers.values():
            prob, x0 = cartpole_swingup(64, device=dev, dtype=dtype)
            mk().solve(prob, x0)
    for B in args.cp_batches:
        for sname, mk in solvers.items():
            ref = None
            for dev_name, dtype_name in runs:
                dev, dtype = torch.device(dev_name), getattr(torch, dtype_name)
                prob, x0 = cartpole_swingup(B, device=dev, dtype=dtype)
                sync(dev)
                t0 = time.perf_counter()
                r = mk().solve(prob, x0)
                sync(dev)
                t = time.perf_counter() - t0
                cost = r.cost.to("cpu", torch.float64)
                row = {
                    "B": B, "solver": sname, "device": dev_name, "dtype": dtype_name,
                    "time_s": t, "iters_mean": float(r.iterations.double().mean()),
                    "iters_max": int(r.iterations.max()), "converged": int(r.converged.sum()),
                    "cost_mean": float(cost.mean()),
                }  # fmt: skip
                if dev_name == "cpu" and dtype_name == "float64":
                    ref = cost
                row["_cost"] = cost
                rows.append(row)
                save([{k: v for k, v in r.items() if k != "_cost"} for r in rows])
                print(f"  cartpole B={B:<5d} {sname:5s} {dev_name:4s} {dtype_name} "
                      f"{t:8.2f} s iters {row['iters_mean']:.1f}/{row['iters_max']} "
                      f"converged {row['converged']}/{B}", flush=True)  # fmt: skip
            for row in rows:
                if row["B"] == B and row["solver"] == sname and ref is not None:
                    rel = (row["_cost"] - ref).abs() / ref.abs().clamp_min(1e-12)
                    row["max_rel_cost_diff_vs_cpu64"] = float(rel.max())
                    row["within_1e-6_vs_cpu64"] = int((rel <= 1e-6).sum())
            cpu_t = next(
                (
                    r["time_s"]
                    for r in rows
                    if r["B"] == B and r["solver"] == sname and r["device"] == "cpu"
                ),
                None,
            )
            for row in rows:
                if row["B"] == B and row["solver"] == sname and cpu_t:
                    row["cpu64_time_over_this"] = cpu_t / row["time_s"]
            save([{k: v for k, v in r.items() if k != "_cost"} for r in rows])
    return [{k: v for k, v in r.items() if k != "_cost"} for r in rows]


def cartpole_markdown(rows, args) -> str:
    cols = [("B", "B"), ("solver", "solver"), ("device", "device"), ("dtype", "dtype")]
    cols += [("time [s]", "time_s"), ("speedup vs cpu float64", "cpu64_time_over_this")]
    cols += [("iters mean", "iters_mean"), ("iters max", "iters_max")]
    cols += [("converged", "converged"), ("mean cost", "cost_mean")]
    cols += [("max rel cost diff vs cpu float64", "max_rel_cost_diff_vs_cpu64")]
    cols += [("within 1e-6 of cpu float64", "within_1e-6_vs_cpu64")]
    note = (
        f"\nOne solve per row (after a warm-up solve at B = 64 per device, dtype and solver);"
        f" iterations capped at {args.cp_max_iter} (`--cp-max-iter`; the CPU-only peers.py run"
        " uses 500), `tol = 1e-6` on ||dJ/dU||, `compact=True`. CPU rows use"
        f" {args.threads} threads. Costs are compared per element with the CPU float64 solve"
        " (relative difference); with the iteration cap, elements that stop at the cap are"
        " compared at the same iteration count.\n"
    )
    return md_table(rows, cols) + note


# ---------------------------------------------------------------------------- (c) MPC layer
def add_speedups(rows: list[dict]) -> None:
    """fwd+bwd speedup of every row over torchslq on the CPU, 1 thread, same dtype."""
    for row in rows:
        base = next(
            (
                r
                for r in rows
                if r["method"] == "torchslq implicit" and r["device"] == "cpu"
                and r["threads"] == 1 and r["dtype"] == row["dtype"]
            ),
            None,
        )  # fmt: skip
        if base is not None:
            row["fwd+bwd speedup vs torchslq cpu 1 thr"] = (
                base["forward_s"] + base["backward_s"]
            ) / (row["forward_s"] + row["backward_s"])


def bench_mpc(args, meta, save):
    import mpc_layer as ml

    try:
        from mpc import mpc as mpcmod
        from mpc.mpc import GradMethods, QuadCost

        meta["mpc.pytorch"] = "available"
    except ImportError as e:
        mpcmod = None
        meta["mpc.pytorch"] = f"not importable: {e}"

    def th_on(dev, dtype):
        th = ml.make_theta(args.mpc_batch, torch.float64)
        return {k: v.detach().to(dev, dtype).requires_grad_(True) for k, v in th.items()}

    def weights(dev, dtype):
        return [w.to(dev) for w in ml.weights(dtype)]

    def torchslq_policy(th, stats):
        Q, R, Qf = weights(th["x0"].device, th["x0"].dtype)
        cost = QuadraticCost(Q, R, Qf, x_ref=th["goal"])
        tol = args.mpc_tol if th["x0"].dtype == torch.float64 else args.mpc_tol32
        solver = ILQR(max_iter=200, tol=tol, progress=False, compact=True)
        mpc = MPC(ml.model_dynamics(th), cost, ml.T, solver=solver, warm_start="shift")

        def policy(x):
            out = mpc(x)
            stats["iters"].append(float(out.result.iterations.double().mean()))
            stats["unconverged"] += int((~out.converged).sum())
            return out.action

        return policy

    def mpcpytorch_policy(th, stats):
        dev, dtype = th["x0"].device, th["x0"].dtype
        B, NX, NU, T = args.mpc_batch, ml.NX, ml.NU, ml.T
        Q, R, Qf = weights(dev, dtype)
        z = torch.zeros(NX, NU, dtype=dtype, device=dev)
        C = torch.cat([torch.cat([Q, z], 1), torch.cat([z.T, R], 1)], 0)
        CT = torch.cat([torch.cat([Qf, z], 1), torch.cat([z.T, R], 1)], 0)
        Cs = torch.stack([C] * T + [CT]).unsqueeze(1).expand(T + 1, B, NX + NU, NX + NU)
        zu = torch.zeros(NU, dtype=dtype, device=dev)
        c = torch.cat([-(Q @ th["goal"]), zu])
        cT = torch.cat([-(Qf @ th["goal"]), zu])
        cs = torch.stack([c] * T + [cT]).unsqueeze(1).expand(T + 1, B, NX + NU)
        cost = QuadCost(Cs, cs)
        dx = ml._Dx(ml.model_dynamics(th))
        state = {"u": None}

        def policy(x):
            ctrl = mpcmod.MPC(
                NX, NU, T + 1, u_init=state["u"], lqr_iter=args.lqr_iter,
                grad_method=GradMethods.ANALYTIC, eps=args.mpc_tol, exit_unconverged=False,
                detach_unconverged=False, verbose=-1, n_batch=B,
                not_improved_lim=args.lqr_iter, back_eps=args.mpc_tol,
            )  # fmt: skip
            _, u, _ = ctrl(x, cost, dx)
            ud = u.detach()
            state["u"] = torch.cat([ud[1:], ud[-1:]], 0)
            return u[0]

        return policy

    def closed_loop(policy, th):
        x = th["x0"]
        dev, dtype = x.device, x.dtype
        plant = ml.plant_dynamics(dtype).to(dev, dtype)
        target = torch.tensor(ml.TARGET, dtype=dtype, device=dev)
        loss = x.new_zeros(x.shape[0])
        xs = [x]
        for _ in range(args.mpc_steps):
            a = policy(x)
            loss = loss + ml.stage_loss(x, a, target)
            x = plant(x, a)
            xs.append(x)
        loss = loss + ((x[:, : ml.N_MASS] - target) ** 2).sum(-1)
        return loss.mean(), torch.stack(xs, 1)

    def one_run(method, dev, dtype):
        th = th_on(dev, dtype)
        stats = {"iters": [], "unconverged": 0}
        make = torchslq_policy if method == "torchslq implicit" else mpcpytorch_policy
        policy = make(th, stats)
        sync(dev)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            loss, xs = closed_loop(policy, th)
        sync(dev)
        t1 = time.perf_counter()
        loss.backward()
        sync(dev)
        t2 = time.perf_counter()
        g = torch.cat([v.grad.reshape(-1) for v in th.values()]).to("cpu", torch.float64)
        return {
            "forward_s": t1 - t0, "backward_s": t2 - t1, "loss": float(loss.detach()),
            "xs": xs.detach().to("cpu", torch.float64), "grad": g,
            "iters_mean": statistics.fmean(stats["iters"]) if stats["iters"] else None,
            "unconverged": stats["unconverged"] if stats["iters"] else None,
        }  # fmt: skip

    configs = []
    for dtype_name in args.dtypes:
        if torch.cuda.is_available():
            configs.append(("torchslq implicit", "cuda", None, dtype_name))
        configs += [("torchslq implicit", "cpu", 1, dtype_name)]
        if args.threads != 1:
            configs += [("torchslq implicit", "cpu", args.threads, dtype_name)]
    if mpcmod is not None:
        if torch.cuda.is_available():
            configs.append(("mpc.pytorch ANALYTIC", "cuda", None, "float64"))
        configs.append(("mpc.pytorch ANALYTIC", "cpu", 1, "float64"))
    rows, ref = [], None
    # reference first: torchslq, CPU, float64, 1 thread
    order = sorted(configs, key=lambda c: not (c[0].startswith("torchslq") and c[1] == "cpu"
                                               and c[2] == 1 and c[3] == "float64"))  # fmt: skip
    for method, dev_name, thr, dtype_name in order:
        dev, dtype = torch.device(dev_name), getattr(torch, dtype_name)
        torch.set_num_threads(thr or args.threads)
        if dev.type == "cuda" or method.startswith("mpc.pytorch"):
            # warm-up on a short loop (CUDA context, kernels, allocator)
            steps = args.mpc_steps
            args.mpc_steps = 2
            one_run(method, dev, dtype)
            args.mpc_steps = steps
        runs = [one_run(method, dev, dtype) for _ in range(args.mpc_repeats)]
        out = runs[0]
        out["forward_s"] = min(r["forward_s"] for r in runs)
        out["backward_s"] = min(r["backward_s"] for r in runs)
        if ref is None:
            ref = out
        row = {
            "method": method, "device": dev_name, "threads": thr, "dtype": dtype_name,
            "forward_s": out["forward_s"], "backward_s": out["backward_s"],
            "iters_mean": out["iters_mean"], "unconverged": out["unconverged"],
            "loss": out["loss"],
            "max_abs_dx_vs_ref": float((out["xs"] - ref["xs"]).abs().max()),
            "grad_rel_diff_vs_ref": float((out["grad"] - ref["grad"]).norm() / ref["grad"].norm()),
        }  # fmt: skip
        rows.append(row)
        add_speedups(rows)
        print(f"  mpc {method:22s} {dev_name:4s} thr={thr} {dtype_name} fwd {row['forward_s']:.2f} s "
              f"bwd {row['backward_s']:.2f} s dx {row['max_abs_dx_vs_ref']:.1e} "
              f"grad {row['grad_rel_diff_vs_ref']:.1e}", flush=True)  # fmt: skip
        save(rows)
    torch.set_num_threads(args.threads)
    save(rows)
    return rows


def mpc_markdown(rows, args) -> str:
    cols = [("method", "method"), ("device", "device"), ("threads", "threads")]
    cols += [("dtype", "dtype"), ("forward [s]", "forward_s"), ("backward [s]", "backward_s")]
    cols += [("fwd+bwd speedup vs torchslq cpu 1 thr (same dtype)",
              "fwd+bwd speedup vs torchslq cpu 1 thr")]  # fmt: skip
    cols += [("iters/solve", "iters_mean"), ("unconverged solves", "unconverged")]
    cols += [("loss", "loss"), ("max abs dx vs torchslq cpu f64", "max_abs_dx_vs_ref")]
    cols += [("grad rel diff vs torchslq cpu f64", "grad_rel_diff_vs_ref")]
    note = (
        f"\nB = {args.mpc_batch}, T = 40, n + m = 12, **{args.mpc_steps} closed-loop steps** (the"
        " CPU benchmark mpc_layer.py runs 50), warm-started (shift) ILQR (`tol` "
        f"{args.mpc_tol:g} in float64, {args.mpc_tol32:g} in float32, `compact=True`),"
        ' `backward="implicit"`; mpc.pytorch: `GradMethods.ANALYTIC`, eps'
        f" {args.mpc_tol:g}, lqr_iter {args.lqr_iter}. Times are the best of"
        f" {args.mpc_repeats} run(s) after a 2-step warm-up run (CUDA and mpc.pytorch rows)."
        " Grad rel diff: relative norm difference of the gradient w.r.t. (x0, goal, mass, k3,"
        " damping) to torchslq's on the CPU in float64 (mpc.pytorch differentiates a"
        " Gauss-Newton KKT system, so its gradient differs by design; see mpc_layer.md).\n"
    )
    return md_table(rows, cols) + note


# ---------------------------------------------------------------------------- main
PARTS = {
    "lq": (bench_lq, lq_markdown, "LQ kernel forward + backward, T = 50"),
    "cartpole": (bench_cartpole, cartpole_markdown, "cart-pole swing-up (peers.py problem)"),
    "mpc": (bench_mpc, mpc_markdown, "differentiable MPC layer (mpc_layer.py setting)"),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", default="lq,cartpole,mpc")
    ap.add_argument("--name", default=None, help="results name: gpu_<name> (default: part)")
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test)")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--dtypes", default="float32,float64")
    ap.add_argument("--sizes", default="4x1,12x4")
    ap.add_argument("--lq-batches", default="1,64,1024,16384")
    ap.add_argument("--budget", type=float, default=1.0, help="seconds per LQ measurement")
    ap.add_argument("--cp-batches", default="512,4096")
    ap.add_argument("--cp-max-iter", type=int, default=100)
    ap.add_argument("--mpc-batch", type=int, default=64)
    ap.add_argument("--mpc-steps", type=int, default=10)
    ap.add_argument("--mpc-repeats", type=int, default=1)
    ap.add_argument("--mpc-tol", type=float, default=1e-8)
    ap.add_argument("--mpc-tol32", type=float, default=1e-4)
    ap.add_argument("--lqr-iter", type=int, default=100)
    ap.add_argument("--note", default="", help="text added under the table")
    argv = sys.argv[1:] if argv is None else argv
    if "--quick" in argv:
        ap.set_defaults(
            lq_batches="1,64", sizes="4x1", cp_batches="16", cp_max_iter=5, mpc_batch=4,
            mpc_steps=2, budget=0.05, out="/tmp/torchslq_gpu_quick",
        )  # fmt: skip
    args = ap.parse_args(argv)
    args.dtypes = [d.strip() for d in args.dtypes.split(",")]
    args.sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    args.lq_batches = [int(b) for b in args.lq_batches.split(",")]
    args.cp_batches = [int(b) for b in args.cp_batches.split(",")]
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cmd = "python " + " ".join(shlex.quote(a) for a in ["benchmarks/gpu.py", *argv])
    for part in [p.strip() for p in args.parts.split(",") if p.strip()]:
        bench, render, title = PARTS[part]
        name = f"gpu_{args.name or part}" if len(args.parts.split(",")) == 1 else f"gpu_{part}"
        meta = {
            "command": cmd,
            "part": part,
            "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "device": device_name(),
            "torch": torch.__version__,
            "cuda": torch.version.cuda,
            "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores",
            "threads": args.threads,
        }
        print(f"{cmd}\n{part}: {meta['device']}, torch {meta['torch']}", flush=True)

        def save(rows, meta=meta, name=name, render=render, title=title):
            (out / f"{name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
            md = (
                f"# torchslq on GPU: {title}\n\n```\n{meta['command']}\n```\n\n"
                f"{meta['date']}; {meta['device']}; torch {meta['torch']} (CUDA "
                f"{meta['cuda']}); {meta['machine']}; CPU runs use "
                f"`torch.set_num_threads` as labelled. "
                + (f"mpc.pytorch: {meta['mpc.pytorch']}." if "mpc.pytorch" in meta else "")
                + "\n\n"
                + render(rows, args)
                + (f"\n{args.note}\n" if args.note else "")
            )
            (out / f"{name}.md").write_text(md)

        rows = bench(args, meta, save)
        save(rows)
        print((out / f"{name}.md").read_text(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
