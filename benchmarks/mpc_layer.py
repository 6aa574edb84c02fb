"""Differentiable MPC in closed loop: torchslq.MPC beside mpc.pytorch's ``mpc.MPC``.

The setting recent papers use to compare differentiable MPC solvers: batch 64, horizon
40, state + control dimension 12, 50 closed-loop steps with gradients through all of
them. Not part of the test suite. Run from the repo root (mpc.pytorch is in the
``bench`` extra)::

    .venv/bin/python benchmarks/mpc_layer.py            # full: B=64, 50 steps
    .venv/bin/python benchmarks/mpc_layer.py --quick    # B=8, 10 steps, -> /tmp

Problem (float64 unless ``--dtype``; ``torch.set_num_threads(1)``):

* system: :class:`torchslq.systems.MassChain` with 4 masses (n = 8, m = 4), cubic
  hardening springs ``s(e) = k e + k3 e^3``, one RK4 step per ``dt = 0.1``. The MPC
  *model* has learnable ``mass = 1``, ``k3 = 1``, ``damping = 0.1`` (``k = 1``); the
  *plant* that the closed loop runs on has ``mass = 1.1``, ``k3 = 1.2`` (model mismatch,
  so warm starts are not exact).
* MPC problem: horizon T = 40, ``QuadraticCost(Q, R, Qf, x_ref=goal)`` with
  ``Q = diag(1, 1, 1, 1, .1, .1, .1, .1)``, ``R = 0.1 I``, ``Qf = 10 Q`` and a learnable
  goal (initially positions ``[.25, .5, .75, 1]``, velocities 0). No control bounds.
* closed loop: ``x_{k+1} = plant(x_k, a_k)``, ``a_k`` the first action of the MPC
  solved from ``x_k``, for K = 50 steps from ``x_0 ~ N(0, 0.5^2)`` (seed 0);
  loss ``L = mean_b [sum_k |p_k - p*|^2 + 0.1 |a_k|^2 + |p_K - p*|^2]`` with the fixed
  target ``p* = [.25, .5, .75, 1]``. ``L.backward()`` gives gradients w.r.t. ``x_0``
  (all of it), the model's ``mass``, ``k3``, ``damping`` and the cost's ``goal``.
* torchslq: ``MPC(..., solver=ILQR(tol=TOL on ||dJ/dU||, compact=True),
  backward="implicit" | "implicit_gn", warm_start="shift" | False)``; the MassChain's
  analytic Jacobians are used by the solver, and its analytic ``vhp`` (chained through
  RK4) by DDP and the exact backward. Method ``"torchslq implicit DDP-costate"``: the same with
  ``DDP(second_order="costate")`` as the solver (Newton steps on ``J(U)``: about half
  the iterations of ILQR's Gauss-Newton steps when warm started, each dearer).
* mpc.pytorch: ``mpc.MPC(n, m, T + 1, eps=EPS on the full-step norm (max over the
  batch), lqr_iter=LQR_ITER, not_improved_lim=LQR_ITER, exit_unconverged=False,
  detach_unconverged=False)`` with ``GradMethods.ANALYTIC`` (``grad_input`` = the
  ``torch.func`` Jacobians ``vmap(jacrev)`` of the same RK4 step, differentiable) and
  ``GradMethods.AUTO_DIFF``; warm start = its ``u_init`` set to the previous solution
  shifted by one step. **Cost mapping** (as in benchmarks/peers.py): mpc.pytorch has no
  separate terminal cost, so it gets horizon T + 1 with ``C_t = blkdiag(Q, R)``,
  ``c_t = [-Q goal, 0]`` for t < T and ``C_T = blkdiag(Qf, R)``, ``c_T = [-Qf goal, 0]``
  (equal to torchslq's cost up to a constant; the extra control u_T only enters
  ``1/2 u_T' R u_T`` and is 0 at the optimum).

Checks before timing: the closed-loop states and losses of every method are compared
with torchslq's (max abs difference). Gradient check (float64, its own smaller batch):
central finite differences of the full closed-loop loss (every MPC solved by torchslq
ILQR at ``--fd-tol``) w.r.t. ``x_0[0, 0]``, ``mass``, ``k3``, ``damping`` and
``goal[3]``, beside the gradients of torchslq implicit, implicit_gn and mpc.pytorch
ANALYTIC; relative errors ``|g - g_fd| / max(|g_fd|, 1e-12)``.

Timing: the forward (the 50 solves and plant steps, building the graph) and the
backward (``L.backward()``) are timed separately, each the median of ``--repeats`` runs
for torchslq and of ``--peer-repeats`` for mpc.pytorch. Ratios are
``t_mpc.pytorch / t_torchslq`` from the same run (> 1: torchslq faster). The machine is
shared (2 cores, several engineers' jobs): load averages are recorded and absolute
times are noisy.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import datetime  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import pstats  # noqa: E402
import shlex  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402
from _env import load, package_versions  # noqa: E402
from torch import nn  # noqa: E402

from torchslq import DDP, ILQR, MPC, QuadraticCost, discretize  # noqa: E402
from torchslq.systems import MassChain  # noqa: E402

N_MASS, DT, T = 4, 0.1, 40
NX, NU = 2 * N_MASS, N_MASS
TARGET = [0.25, 0.5, 0.75, 1.0]
MODEL = {"mass": 1.0, "k3": 1.0, "damping": 0.1}
PLANT = {"mass": 1.1, "k3": 1.2, "damping": 0.1}
U_WEIGHT = 0.1
FD_PARAMS = ("x0[0,0]", "mass", "k3", "damping", "goal[3]")


# ---------------------------------------------------------------------------- problem
def make_theta(B: int, dtype, seed: int = 0) -> dict[str, torch.Tensor]:
    """The differentiable inputs: x0 (B, n), model parameters and the cost's goal."""
    g = torch.Generator().manual_seed(seed)
    x0 = 0.5 * torch.randn(B, NX, generator=g, dtype=torch.float64)
    goal = torch.tensor(TARGET + [0.0] * N_MASS, dtype=torch.float64)
    th = {"x0": x0, "goal": goal}
    th.update({k: torch.tensor(v, dtype=torch.float64) for k, v in MODEL.items()})
    return {k: v.to(dtype).requires_grad_(True) for k, v in th.items()}


def weights(dtype):
    q = torch.tensor([1.0] * N_MASS + [0.1] * N_MASS, dtype=dtype)
    Q, R = torch.diag(q), U_WEIGHT * torch.eye(NU, dtype=dtype)
    return Q, R, 10.0 * Q


def model_dynamics(th):
    return discretize(MassChain(N_MASS, mass=th["mass"], k3=th["k3"], damping=th["damping"]), DT)


def plant_dynamics(dtype):
    return discretize(MassChain(N_MASS, **PLANT), DT)


def stage_loss(x, a, target):
    return ((x[:, :N_MASS] - target) ** 2).sum(-1) + U_WEIGHT * (a**2).sum(-1)


def closed_loop(policy, th, steps: int):
    """Run the plant under ``policy(x) -> action``; returns (loss, states (B, K+1, n))."""
    x = th["x0"]
    plant = plant_dynamics(x.dtype)
    target = torch.tensor(TARGET, dtype=x.dtype)
    loss = x.new_zeros(x.shape[0])
    xs = [x]
    for _ in range(steps):
        a = policy(x)
        loss = loss + stage_loss(x, a, target)
        x = plant(x, a)
        xs.append(x)
    loss = loss + ((x[:, :N_MASS] - target) ** 2).sum(-1)
    return loss.mean(), torch.stack(xs, 1)


# ---------------------------------------------------------------------------- torchslq
def torchslq_policy(
    th, backward: str, warm, tol: float, max_iter: int, stats: dict, solver_name: str = "ILQR"
):
    Q, R, Qf = weights(th["x0"].dtype)
    cost = QuadraticCost(Q, R, Qf, x_ref=th["goal"])
    kw = dict(max_iter=max_iter, tol=tol, progress=False, compact=True)
    if solver_name == "ILQR":
        solver = ILQR(**kw)
    elif solver_name == "DDP-costate":
        solver = DDP(second_order="costate", **kw)
    else:
        raise ValueError(f"unknown torchslq solver {solver_name!r}")
    mpc = MPC(model_dynamics(th), cost, T, solver=solver, backward=backward, warm_start=warm)

    def policy(x):
        out = mpc(x)
        r = out.result
        stats["iters"].append(float(r.iterations.double().mean()))
        stats["iters_max"] = max(stats.get("iters_max", 0), int(r.iterations.max()))
        stats["unconverged"] += int((~out.converged).sum())
        return out.action

    return policy


# ---------------------------------------------------------------------------- mpc.pytorch
class _Dx(nn.Module):
    """The model's RK4 step for mpc.pytorch; ``grad_input``: torch.func Jacobians."""

    def __init__(self, dyn):
        super().__init__()
        self.dyn = dyn

    def forward(self, x, u):
        return self.dyn(x, u)

    def grad_input(self, x, u):  # GradMethods.ANALYTIC; differentiable (graph kept)
        J = torch.func.vmap(torch.func.jacrev(lambda a, b: self.dyn(a, b), argnums=(0, 1)))
        return J(x, u)


def mpcpytorch_cost(th, B: int):
    from mpc.mpc import QuadCost

    dtype = th["x0"].dtype
    Q, R, Qf = weights(dtype)
    z = torch.zeros(NX, NU, dtype=dtype)
    C = torch.cat([torch.cat([Q, z], 1), torch.cat([z.T, R], 1)], 0)
    CT = torch.cat([torch.cat([Qf, z], 1), torch.cat([z.T, R], 1)], 0)
    Cs = torch.stack([C] * T + [CT]).unsqueeze(1).expand(T + 1, B, NX + NU, NX + NU)
    zu = torch.zeros(NU, dtype=dtype)
    c = torch.cat([-(Q @ th["goal"]), zu])
    cT = torch.cat([-(Qf @ th["goal"]), zu])
    cs = torch.stack([c] * T + [cT]).unsqueeze(1).expand(T + 1, B, NX + NU)
    return QuadCost(Cs, cs)


def mpcpytorch_policy(th, method: str, warm: bool, eps: float, lqr_iter: int, stats: dict):
    from mpc import mpc as mpcmod
    from mpc.mpc import GradMethods

    gm = {"ANALYTIC": GradMethods.ANALYTIC, "AUTO_DIFF": GradMethods.AUTO_DIFF}[method]
    dx = _Dx(model_dynamics(th))
    B = th["x0"].shape[0]
    cost = mpcpytorch_cost(th, B)
    state = {"u": None}

    class Counting(mpcmod.MPC):
        """Counts its iterations (one non-differentiable linearisation per iteration)."""

        def linearize_dynamics(self, x, u, dynamics, diff):
            if not diff:
                self.iters += 1
            return super().linearize_dynamics(x, u, dynamics, diff)

    def policy(x):
        ctrl = Counting(
            NX, NU, T + 1, u_init=state["u"], lqr_iter=lqr_iter, grad_method=gm, eps=eps,
            exit_unconverged=False, detach_unconverged=False, verbose=-1, n_batch=B,
            not_improved_lim=lqr_iter, back_eps=eps,
        )  # fmt: skip
        ctrl.iters = 0
        _, u, _ = ctrl(x, cost, dx)
        stats["iters"].append(float(ctrl.iters))
        stats["iters_max"] = max(stats.get("iters_max", 0), ctrl.iters)
        if ctrl.iters >= lqr_iter:
            stats["unconverged"] += B  # stopped at lqr_iter (batch-wide test)
        if warm:
            ud = u.detach()
            state["u"] = torch.cat([ud[1:], ud[-1:]], 0)
        return u[0]

    return policy


# ---------------------------------------------------------------------------- runs
def make_policy(name: str, th, warm: bool, args, stats: dict):
    if name.startswith("torchslq"):
        # "torchslq <backward>" (ILQR solver) or "torchslq <backward> <solver>"
        parts = name.split()
        solver_name = parts[2] if len(parts) > 2 else "ILQR"
        warm_mode = "shift" if warm else False
        return torchslq_policy(th, parts[1], warm_mode, args.tol, 200, stats, solver_name)
    method = name.split()[1]
    return mpcpytorch_policy(th, method, warm, args.eps, args.lqr_iter, stats)


def timed_run(name: str, th_base, warm: bool, steps: int, args):
    th = {k: v.detach().clone().requires_grad_(True) for k, v in th_base.items()}
    stats = {"iters": [], "unconverged": 0}
    policy = make_policy(name, th, warm, args, stats)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        loss, xs = closed_loop(policy, th, steps)
    t1 = time.perf_counter()
    loss.backward()
    t2 = time.perf_counter()
    grads = {k: v.grad.detach().clone() for k, v in th.items()}
    return {
        "forward_s": t1 - t0,
        "backward_s": t2 - t1,
        "loss": float(loss.detach()),
        "xs": xs.detach(),
        "grads": grads,
        "iters_mean": statistics.fmean(stats["iters"]) if stats["iters"] else None,
        "iters_max": stats.get("iters_max"),
        "unconverged": stats["unconverged"],
    }


def median_runs(name, th, warm, steps, args, repeats):
    runs = [timed_run(name, th, warm, steps, args) for _ in range(repeats)]
    out = dict(runs[0])
    out["forward_s"] = statistics.median(r["forward_s"] for r in runs)
    out["backward_s"] = statistics.median(r["backward_s"] for r in runs)
    out["forward_all_s"] = [r["forward_s"] for r in runs]
    out["backward_all_s"] = [r["backward_s"] for r in runs]
    return out


# ---------------------------------------------------------------------------- gradient check
def param_get(th, p):
    if p == "x0[0,0]":
        return th["x0"][0, 0]
    if p == "goal[3]":
        return th["goal"][3]
    return th[p]


def perturbed(th, p, h):
    out = {k: v.detach().clone() for k, v in th.items()}
    if p == "x0[0,0]":
        out["x0"][0, 0] += h
    elif p == "goal[3]":
        out["goal"][3] += h
    else:
        out[p] = out[p] + h
    return out


def fd_gradients(th, steps, args):
    """Central differences of the closed-loop loss, every MPC solved by torchslq at fd_tol."""
    out = {}
    for p in FD_PARAMS:
        h = args.fd_step * max(1.0, abs(float(param_get(th, p).detach())))
        vals = []
        for s in (+1, -1):
            thp = perturbed(th, p, s * h)
            stats = {"iters": [], "unconverged": 0}
            pol = torchslq_policy(thp, "implicit", False, args.fd_tol, 500, stats)
            with torch.no_grad():
                loss, _ = closed_loop(pol, thp, steps)
            if stats["unconverged"]:
                print(f"  FD {p}: {stats['unconverged']} unconverged solves", flush=True)
            vals.append(float(loss))
        out[p] = (vals[0] - vals[1]) / (2 * h)
    return out


def grad_value(grads, p):
    if p == "x0[0,0]":
        return float(grads["x0"][0, 0])
    if p == "goal[3]":
        return float(grads["goal"][3])
    return float(grads[p])


def gradient_check(args, methods):
    th = make_theta(args.grad_batch, torch.float64, seed=args.seed)
    steps = args.grad_steps
    t0 = time.perf_counter()
    fd = fd_gradients(th, steps, args)
    print(f"  FD reference ({time.perf_counter() - t0:.1f} s): {fd}", flush=True)
    rows = []
    for name in methods:
        sub = argparse.Namespace(**vars(args))
        sub.tol, sub.eps = args.fd_tol, args.grad_eps
        try:
            r = timed_run(name, th, True, steps, sub)
        except Exception as e:  # noqa: BLE001
            rows.append({"method": name, "error": f"{type(e).__name__}: {e}"})
            print(f"  {name}: FAILED {type(e).__name__}: {e}", flush=True)
            continue
        errs = {}
        for p in FD_PARAMS:
            g = grad_value(r["grads"], p)
            errs[p] = {"grad": g, "fd": fd[p], "rel_err": abs(g - fd[p]) / max(abs(fd[p]), 1e-12)}
        rows.append({"method": name, "loss": r["loss"], "errors": errs})
        print(
            f"  {name:28s} " + "  ".join(f"{p}: {e['rel_err']:.1e}" for p, e in errs.items()),
            flush=True,
        )
    return {"batch": args.grad_batch, "steps": steps, "fd": fd, "rows": rows}


# ---------------------------------------------------------------------------- profile
def profile_torchslq(th, steps, args, warm=True, backward="implicit"):
    prof = cProfile.Profile()
    thc = {k: v.detach().clone().requires_grad_(True) for k, v in th.items()}
    stats = {"iters": [], "unconverged": 0}
    policy = torchslq_policy(thc, backward, "shift" if warm else False, args.tol, 200, stats)
    prof.enable()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        loss, _ = closed_loop(policy, thc, steps)
    prof.disable()
    fwd = _pstats_text(prof)
    prof = cProfile.Profile()
    prof.enable()
    loss.backward()
    prof.disable()
    return {"forward": fwd, "backward": _pstats_text(prof)}


def _pstats_text(prof, n=30):
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("cumulative").print_stats(n)
    pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(n)
    return s.getvalue()


# ---------------------------------------------------------------------------- report


def versions() -> dict[str, str]:
    return package_versions("mpc", "numpy")


def compare_rows(rows):
    """Ratios t_peer / t_torchslq per warm setting, forward and backward."""
    out = []
    for warm in (True, False):
        ts = [r for r in rows if r["warm"] == warm and r["method"].startswith("torchslq")]
        ps = [r for r in rows if r["warm"] == warm and r["method"].startswith("mpc.pytorch")]
        for t in ts:
            for p in ps:
                out.append({
                    "warm": warm, "torchslq": t["method"], "peer": p["method"],
                    "forward_ratio": p["forward_s"] / t["forward_s"],
                    "backward_ratio": p["backward_s"] / t["backward_s"],
                    "total_ratio": (p["forward_s"] + p["backward_s"])
                    / (t["forward_s"] + t["backward_s"]),
                })  # fmt: skip
    return out


def markdown(meta, rows, rat, gc, summary, profile_notes):
    L = ["# Differentiable MPC in closed loop: torchslq.MPC vs mpc.pytorch", ""]
    L += [summary, ""]
    L += ["```", meta["command"], "```", ""]
    L += [
        f"{meta['date']}, {meta['machine']}; torch {meta['torch']}, "
        f"{', '.join(f'{k} {v}' for k, v in meta['versions'].items())}; threads 1, "
        f"{meta['dtype']}. Load average at start {meta['load_start']}, at end "
        f"{meta['load_end']}: **a shared 2-core machine on which about five engineers' "
        "jobs run at the same time**, so absolute times are noisy; every ratio compares "
        "runs from this same invocation.",
        "",
        f"Setting: batch B = {meta['B']}, horizon T = {T}, n = {NX}, m = {NU} "
        f"(MassChain, 4 masses, cubic springs, RK4 dt = {DT}), {meta['steps']} closed-loop "
        "steps on a mismatched plant, loss on the closed-loop trajectory, gradients w.r.t. "
        "x0, mass, k3, damping and goal. torchslq: ILQR tol "
        f"{meta['tol']:g} on ||dJ/dU||; mpc.pytorch: eps {meta['eps']:g} on its full-step "
        f"norm, lqr_iter {meta['lqr_iter']}. Times: median of {meta['repeats']} runs "
        f"(torchslq) and {meta['peer_repeats']} (mpc.pytorch). See the module docstring of "
        "benchmarks/mpc_layer.py for the exact problem.",
        "",
        "## Times",
        "",
        "| method | warm start | forward [s] | backward [s] | iters/solve mean (max) | "
        "unconverged solves | loss | max abs dx vs torchslq implicit |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        it = "-" if r["iters_mean"] is None else f"{r['iters_mean']:.2f} ({r['iters_max']})"
        L.append(
            f"| {r['method']} | {'on' if r['warm'] else 'off'} | {r['forward_s']:.3f} | "
            f"{r['backward_s']:.3f} | {it} | {r['unconverged']} | {r['loss']:.10g} | "
            f"{r['max_dx']:.1e} |"
        )
    L += [
        "",
        "Iterations: torchslq, per element (``SolverResult.iterations``; with "
        "``compact=True`` the batch iterates until its slowest element is done); "
        "mpc.pytorch, per batch (it iterates all elements until the batch-wide test "
        "passes). Unconverged: torchslq solves whose status is not converged; "
        "mpc.pytorch, B per solve that stopped at ``lqr_iter``.",
    ]
    L += [
        "",
        "## Ratios t_mpc.pytorch / t_torchslq (same run; > 1: torchslq faster)",
        "",
        "| warm start | torchslq | mpc.pytorch | forward | backward | forward + backward |",
        "|---|---|---|---|---|---|",
    ]
    for q in rat:
        L.append(
            f"| {'on' if q['warm'] else 'off'} | {q['torchslq']} | {q['peer']} | "
            f"{q['forward_ratio']:.1f} | {q['backward_ratio']:.1f} | {q['total_ratio']:.1f} |"
        )
    if gc is not None:
        L += [
            "",
            f"## Gradients vs central finite differences (float64, B = {gc['batch']}, "
            f"{gc['steps']} closed-loop steps)",
            "",
            f"Finite differences of the full closed-loop loss, every MPC solved by torchslq "
            f"ILQR at tol {meta['fd_tol']:g}, step {meta['fd_step']:g} x max(1, |p|). The "
            f"gradients: torchslq at tol {meta['fd_tol']:g}, mpc.pytorch at eps "
            f"{meta['grad_eps']:g}. Relative error |g - g_fd| / |g_fd|.",
            "",
            "| method | " + " | ".join(FD_PARAMS) + " |",
            "|---|" + "---|" * len(FD_PARAMS),
            "| FD value | " + " | ".join(f"{gc['fd'][p]:.6g}" for p in FD_PARAMS) + " |",
        ]
        for r in gc["rows"]:
            if "error" in r:
                L.append(f"| {r['method']} | failed: {r['error']} |")
                continue
            L.append(
                f"| {r['method']} | "
                + " | ".join(f"{r['errors'][p]['rel_err']:.1e}" for p in FD_PARAMS)
                + " |"
            )
    if profile_notes:
        L += ["", "## Where torchslq's time goes", "", profile_notes]
    return "\n".join(L) + "\n"


# ---------------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="B=8, 10 steps, output to /tmp")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--dtype", default="float64", choices=("float64", "float32"))
    ap.add_argument("--tol", type=float, default=1e-8, help="torchslq ILQR tol")
    ap.add_argument("--eps", type=float, default=1e-8, help="mpc.pytorch eps")
    ap.add_argument("--lqr-iter", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--peer-repeats", type=int, default=1)
    ap.add_argument(
        "--methods",
        default="torchslq implicit,torchslq implicit_gn,mpc.pytorch ANALYTIC,mpc.pytorch AUTO_DIFF",
    )
    ap.add_argument("--warm", default="on,off")
    ap.add_argument("--no-grad-check", action="store_true")
    ap.add_argument("--grad-batch", type=int, default=4)
    ap.add_argument("--grad-steps", type=int, default=50)
    ap.add_argument("--grad-eps", type=float, default=1e-10, help="mpc.pytorch eps (check)")
    ap.add_argument("--fd-tol", type=float, default=1e-11)
    ap.add_argument("--fd-step", type=float, default=1e-5)
    ap.add_argument("--profile", action="store_true", help="cProfile torchslq fwd/bwd")
    ap.add_argument("--profile-notes", default="", help="markdown file appended to the md")
    ap.add_argument("--summary", default="", help="file with the md's summary paragraph")
    ap.add_argument("--render-only", action="store_true", help="rewrite the md from the saved json")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    ap.add_argument("--name", default="mpc_layer")
    if "--quick" in (sys.argv[1:] if argv is None else argv):  # explicit flags still win
        ap.set_defaults(
            batch=8, steps=10, repeats=1, grad_batch=2, grad_steps=10, out="/tmp/mpc_layer_quick"
        )
    args = ap.parse_args(argv)
    args.out = args.out or "benchmarks/results"
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    warms = [w == "on" for w in args.warm.split(",")]
    meta = {
        "command": "python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *sys.argv[1:]]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "torch": torch.__version__,
        "versions": versions(),
        "load_start": load(),
        "dtype": args.dtype,
        "B": args.batch,
        "steps": args.steps,
        "tol": args.tol,
        "eps": args.eps,
        "lqr_iter": args.lqr_iter,
        "repeats": args.repeats,
        "peer_repeats": args.peer_repeats,
        "fd_tol": args.fd_tol,
        "fd_step": args.fd_step,
        "grad_eps": args.grad_eps,
    }
    print(meta["command"], "| load", meta["load_start"], flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    gc = None
    notes = Path(args.profile_notes).read_text() if args.profile_notes else ""
    summary_text = Path(args.summary).read_text().strip() if args.summary else ""
    if args.render_only:
        js = json.loads((out / f"{args.name}.json").read_text())
        md = markdown(
            js["meta"], js["rows"], js["ratios"], js["gradient_check"], summary_text, notes
        )
        (out / f"{args.name}.md").write_text(md)
        print(f"wrote {out / (args.name + '.md')}")
        return 0

    def save(summary=summary_text):
        meta["load_end"] = load()
        rat = compare_rows(rows)
        js = {"meta": meta, "rows": rows, "ratios": rat, "gradient_check": gc}
        (out / f"{args.name}.json").write_text(json.dumps(js, indent=1, default=float))
        (out / f"{args.name}.md").write_text(markdown(meta, rows, rat, gc, summary, notes))
        return rat

    # warm-up (first-call overheads: torch.func, mpc.pytorch imports)
    thw = make_theta(2, dtype, seed=123)
    for name in methods:
        timed_run(name, thw, True, 2, args)

    th = make_theta(args.batch, dtype, seed=args.seed)
    ref_xs = {}
    for warm in warms:
        for name in methods:
            reps = args.repeats if name.startswith("torchslq") else args.peer_repeats
            r = median_runs(name, th, warm, args.steps, args, reps)
            key = warm
            if key not in ref_xs:
                ref_xs[key] = r["xs"]
            max_dx = float((r["xs"] - ref_xs[key]).abs().max())
            row = {
                "method": name,
                "warm": warm,
                "forward_s": r["forward_s"],
                "backward_s": r["backward_s"],
                "forward_all_s": r["forward_all_s"],
                "backward_all_s": r["backward_all_s"],
                "loss": r["loss"],
                "max_dx": max_dx,
                "iters_mean": r["iters_mean"],
                "iters_max": r["iters_max"],
                "unconverged": r["unconverged"],
                "grad_x0_norm": float(r["grads"]["x0"].norm()),
                "grads": {k: v.tolist() for k, v in r["grads"].items() if k != "x0"},
            }
            rows.append(row)
            save()
            print(
                f"  {name:26s} warm {'on ' if warm else 'off'} fwd {r['forward_s']:8.3f} s  "
                f"bwd {r['backward_s']:8.3f} s  loss {r['loss']:.10g}  max|dx| {max_dx:.1e}  "
                f"iters {r['iters_mean']}  unconverged {r['unconverged']}",
                flush=True,
            )
    rat = save()
    for q in rat:
        print(
            f"  warm {'on ' if q['warm'] else 'off'} {q['peer']:24s} / {q['torchslq']:22s} "
            f"forward {q['forward_ratio']:6.1f}x  backward {q['backward_ratio']:6.1f}x",
            flush=True,
        )
    if not args.no_grad_check and args.dtype == "float64":
        gmethods = [m for m in methods if m != "mpc.pytorch AUTO_DIFF"]
        gc = gradient_check(args, gmethods)
        save()
    if args.profile:
        p = profile_torchslq(th, min(args.steps, 10), args)
        (out / f"{args.name}.profile.txt").write_text(
            "## forward\n" + p["forward"] + "\n## backward\n" + p["backward"]
        )
        print(p["forward"][:4000])
        print(p["backward"][:4000])
    save()
    print(f"wrote {out / (args.name + '.json')} and {out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
