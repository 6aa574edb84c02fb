"""torchslq on a user's own models beside trajax (JAX): the cart-pole swing-up.

Not part of the test suite. What a user gets without writing derivatives or compiled
hooks: the problem is trajax's and mpc.pytorch's common benchmark (state ``[s, theta,
s_dot, theta_dot]``, theta = 0 hanging, cart 1.0, tip 0.1, pole 0.5, g = 9.81; one RK4
step per dt = 0.05, T = 50; cost ``sum_t 0.01 u_t^2 + 100 |x_T - [0, pi, 0, 0]|^2``;
``u = 0`` initially; ``x0 = [0, 0.05 N(0,1), 0, 0]`` from
``numpy.random.default_rng(seed).standard_normal(B)``), float64, with three models:

* ``user``: :class:`UserCartPole`, a plain :class:`torchslq.ContinuousDynamics` (torch
  ops only: Jacobians by ``torch.func``), ``torchslq.discretize(model, 0.05, "rk4")``;
* ``learned``: :class:`LearnedCartPole`, a discrete :class:`torchslq.Dynamics`
  ``x_next = rk4_step(x, u) + mlp([x, u])`` (a 5-64-64-4 tanh MLP, see
  :func:`residual_mlp`), the same weights given to trajax;
* ``zoo``: the library's :class:`torchslq.systems.CartPole` (analytic derivatives and
  compiled hooks): a reference row.

Solvers: torchslq ``ILQR`` and ``DDP`` (``max_iter = 500``, ``tol = 1e-6`` on
``||dJ/dU||``, ``compact=True``, ``progress=False``), each with the default single
shooting and with ``shooting="multiple"`` (rows ``ILQR-MS``, ``DDP-MS``: every model call
one batched call over all nodes, :mod:`torchslq.solvers.shooting`), one batched call; the first call
of each configuration is timed apart ("first call": one-time compilation and caches),
then ``--repeats`` timed solves. trajax ``optimizers.ilqr`` (``maxiter = 500``,
``grad_norm_threshold = 1e-6``) under ``jax.jit(jax.vmap(...))`` with x64, compiled
ahead of time (``lower(...).compile()``, timed and excluded; reused for ``zoo``, whose
JAX model is ``user``'s), then ``--repeats`` timed solves. Note that trajax tests the
gradient of the iterate *before* its last step (it steps once more after the test
passes) and, under ``vmap``, runs every instance until the slowest stops.

Every solver's controls are rolled out through the configuration's torch model and
costed by the formula above (float64); each instance's cost is compared with trajax's
(within 1e-6 relative; max relative gap), and ``||dJ/dU||`` at the returned controls is
recomputed by autograd for every solver. Per-iteration time = time / max iterations.
Ratios ``t_trajax / t_torchslq`` are from the same run (> 1: torchslq faster). Results
are saved after every configuration, so a stopped run keeps what it measured.

    .venv/bin/python benchmarks/user_models.py                         # B in {1, 64, 512}
    .venv/bin/python benchmarks/user_models.py --batches 2 --out /tmp/um  # a quick check
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _env import load, package_versions  # noqa: E402
from torch import nn  # noqa: E402

import torchslq as ts  # noqa: E402
from torchslq.dynamics import codegen  # noqa: E402
from torchslq.systems import CartPole  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "examples"))
# the cart-pole's equations as a user writes them (torch ops only), shared with the
# constrained example
from constrained_cartpole import UserCartPole  # noqa: E402

DT, T, MC, MP, L, G = 0.05, 50, 1.0, 0.1, 0.5, 9.81
R_U, W_F = 0.01, 100.0  # sum_t R_U u_t^2 + W_F |x_T - GOAL|^2
GOAL = (0.0, math.pi, 0.0, 0.0)
MAX_ITER, TOL, RTOL = 500, 1e-6, 1e-6
F64 = torch.float64


# ---------------------------------------------------------------------------- models
class UserCartPoleTorchPath(UserCartPole):
    """:class:`UserCartPole` kept on torch ops (no generated compiled code): what a user's
    model cost before :mod:`torchslq.dynamics.codegen`."""

    generate_compiled_code = False


def residual_mlp() -> nn.Sequential:
    """``Linear(5, 64) - Tanh - Linear(64, 64) - Tanh - Linear(64, 4)`` in float64,
    initialised after ``torch.manual_seed(1)``; the last layer's weight and bias are
    then multiplied by 1e-3, so the residual is small (about 1e-4 per step)."""
    torch.manual_seed(1)
    net = nn.Sequential(
        nn.Linear(5, 64, dtype=F64), nn.Tanh(),
        nn.Linear(64, 64, dtype=F64), nn.Tanh(),
        nn.Linear(64, 4, dtype=F64),
    )  # fmt: skip
    with torch.no_grad():
        net[-1].weight.mul_(1e-3)
        net[-1].bias.mul_(1e-3)
    return net


class LearnedCartPole(ts.Dynamics):
    """A learned residual on the RK4 step: ``x_next = rk4_step(x, u) + mlp([x, u])``,
    ``rk4_step`` the discretised :class:`UserCartPole`, ``mlp`` :func:`residual_mlp`
    (seed 1, last layer scaled by 1e-3)."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.rk4_step = ts.discretize(UserCartPole(), DT, "rk4").double()
        self.mlp = residual_mlp()

    def forward(self, x, u):
        return self.rk4_step(x, u) + self.mlp(torch.cat([x, u], -1))


def make_problem(model: str) -> ts.Problem:
    if model == "learned":
        dyn = LearnedCartPole()
    else:
        models = {"user": UserCartPole, "user-torch": UserCartPoleTorchPath}
        f = models[model]() if model in models else CartPole(mc=MC, mp=MP, l=L)
        dyn = ts.discretize(f, DT, "rk4").double()
    cost = ts.QuadraticCost(
        Q=torch.zeros(4, 4, dtype=F64),
        R=2 * R_U * torch.eye(1, dtype=F64),  # the 1/2 convention
        Qf=2 * W_F * torch.eye(4, dtype=F64),
        x_ref=torch.tensor(GOAL, dtype=F64),
    )
    return ts.Problem(dyn, cost, T)


def initial_states(B: int, seed: int) -> torch.Tensor:
    x0 = torch.zeros(B, 4, dtype=F64)
    x0[:, 1] = torch.from_numpy(0.05 * np.random.default_rng(seed).standard_normal(B))
    return x0


def evaluate(problem: ts.Problem, x0: torch.Tensor, u) -> tuple[np.ndarray, np.ndarray]:
    """Cost and ``||dJ/dU||`` per instance of controls ``u (B, T, 1)`` on the torch model."""
    u = torch.tensor(np.asarray(u, dtype=np.float64), requires_grad=True)
    with torch.enable_grad():
        x = problem.rollout(x0, u)
        goal = torch.tensor(GOAL, dtype=F64)
        J = R_U * u.pow(2).sum((1, 2)) + W_F * (x[:, -1] - goal).pow(2).sum(-1)
        (g,) = torch.autograd.grad(J.sum(), u)
    return J.detach().numpy(), g.flatten(1).norm(dim=1).numpy()


# ---------------------------------------------------------------------------- solvers
def run_torchslq(name: str, problem: ts.Problem, x0: torch.Tensor, repeats: int) -> dict:
    cls = {"ilqr": ts.ILQR, "ddp": ts.DDP}[name.removesuffix("-ms")]
    shooting = "multiple" if name.endswith("-ms") else "single"
    solver = cls(max_iter=MAX_ITER, tol=TOL, compact=True, progress=False, shooting=shooting)
    t0 = time.perf_counter()
    solver.solve(problem, x0)
    first, times = time.perf_counter() - t0, []
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = solver.solve(problem, x0)
        times.append(time.perf_counter() - t0)
    names = ts.status_names(r.status)
    return {
        "u": r.u.numpy(),
        "first": first,
        "times": times,
        "iters": r.iterations.numpy(),
        "converged": int(r.converged.sum()),
        "status": {k: names.count(k) for k in dict.fromkeys(names)},
    }


_TRAJAX: dict = {}  # kind -> jit(vmap(ilqr)); (kind, B) -> (compiled, compile seconds)


def trajax_fn(kind: str, path: str, net: nn.Sequential | None):
    if kind in _TRAJAX:
        return _TRAJAX[kind]
    if path not in sys.path:
        sys.path.insert(0, path)
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from trajax.optimizers import ilqr

    goal = jnp.asarray(GOAL)

    def f(x, u):
        th, thd, F = x[1], x[3], u[0]
        s, c = jnp.sin(th), jnp.cos(th)
        D = MC + MP * s * s
        sdd = (F + MP * s * (L * thd * thd + G * c)) / D
        thdd = (-F * c - MP * L * thd * thd * c * s - (MC + MP) * G * s) / (L * D)
        return jnp.stack([x[2], thd, sdd, thdd])

    def rk4(x, u):
        k1 = f(x, u)
        k2 = f(x + 0.5 * DT * k1, u)
        k3 = f(x + 0.5 * DT * k2, u)
        k4 = f(x + DT * k3, u)
        return x + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    if kind == "learned":
        layers = [m for m in net if isinstance(m, nn.Linear)]
        Wb = [
            (jnp.asarray(m.weight.detach().numpy()), jnp.asarray(m.bias.detach().numpy()))
            for m in layers
        ]

        def dynamics(x, u, t):
            z = jnp.concatenate([x, u])
            for W, b in Wb[:-1]:
                z = jnp.tanh(W @ z + b)
            return rk4(x, u) + Wb[-1][0] @ z + Wb[-1][1]

    else:

        def dynamics(x, u, t):
            return rk4(x, u)

    def cost(x, u, t):  # trajax calls it for t = 0..T (u padded with zeros at T)
        return jnp.where(t == T, W_F * jnp.sum((x - goal) ** 2), R_U * jnp.dot(u, u))

    def one(x0, U):
        X, U, obj, grad, _, _, it = ilqr(
            cost, dynamics, x0, U, maxiter=MAX_ITER, grad_norm_threshold=TOL
        )
        return U, it

    _TRAJAX[kind] = jax.jit(jax.vmap(one))
    return _TRAJAX[kind]


def run_trajax(model: str, path: str, net, x0: torch.Tensor, repeats: int) -> dict:
    import jax

    kind = "learned" if model == "learned" else "cartpole"
    fn = trajax_fn(kind, path, net)
    B = x0.shape[0]
    xj = jax.numpy.asarray(x0.numpy())
    Uj = jax.numpy.zeros((B, T, 1), dtype=jax.numpy.float64)
    reused = (kind, B) in _TRAJAX
    if not reused:  # compiled ahead of time, so the compilation is timed apart
        t0 = time.perf_counter()
        _TRAJAX[kind, B] = (fn.lower(xj, Uj).compile(), time.perf_counter() - t0)
    compiled, t_compile = _TRAJAX[kind, B]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        U, it = jax.block_until_ready(compiled(xj, Uj))
        times.append(time.perf_counter() - t0)
    return {"u": np.asarray(U), "first": t_compile, "reused": reused, "times": times,
            "iters": np.asarray(it)}  # fmt: skip


# ---------------------------------------------------------------------------- report
def _f(v, fmt=".3g") -> str:
    return "-" if v is None else format(v, fmt)


def markdown(meta: dict, rows: list) -> str:
    out = ["# torchslq on user models vs trajax: cart-pole swing-up", "", "```"]
    out += [
        meta["command"],
        "```",
        "",
        f"{meta['date']}, {meta['machine']}, {meta['cores']} cores; threads {meta['threads']}, "
        f"float64; load average at start {meta['load_start']}, at end {meta['load_end']} "
        "(absolute times are noisy on a shared machine; ratios are from the same run). "
        + ", ".join(f"{k} {v}" for k, v in meta["versions"].items())
        + f". max_iter {MAX_ITER}, tol {TOL:g}, seed {meta['seed']}, repeats {meta['repeats']}.",
        "",
        "Problem, models and solvers: the docstring of `benchmarks/user_models.py`. Costs "
        "and `||dJ/dU||` recomputed on each solver's controls through the torch model; "
        f"`cost match`: instances within {RTOL:g} relative of trajax's cost. First call: "
        "torchslq's first solve of the configuration; trajax's compilation (excluded).",
        "",
        "| model | B | solver | model code | first call [s] | time [s] (best; all) | per iteration [ms] | "
        "iterations mean/max | status | max dJ/dU | mean cost | cost match | max rel gap | "
        "t_trajax / t |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "time_s" not in r:
            out.append(
                f"| {r['model']} | {r['B']} | {r['solver']} |" + " - |" * 10 + f" {r['note']} |"
            )
            continue
        runs = ", ".join(f"{t:.3g}" for t in r["times_s"])
        match = "-" if r.get("cost_match") is None else f"{r['cost_match']}/{r['B']}"
        out.append(
            f"| {r['model']} | {r['B']} | {r['solver']} | {r.get('model_code', '-')} | "
            f"{r['first_s']:.3g}"
            f"{' (reused)' if r.get('compile_reused') else ''} | {r['time_s']:.3g} ({runs}) | "
            f"{1e3 * r['per_iter_s']:.3g} | {r['iters_mean']:.1f}/{r['iters_max']} | "
            f"{r['status']} | {r['max_grad']:.1e} | {r['mean_cost']:.10g} | {match} | "
            f"{_f(r.get('max_rel_gap'), '.1e')} | {_f(r.get('ratio'), '.2f')} |"
        )
    out += [
        "",
        "## Ratios t_trajax / t_torchslq (> 1: torchslq faster)",
        "",
        "| model | B | solver | time | per iteration |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        if r.get("ratio") is not None:
            out.append(
                f"| {r['model']} | {r['B']} | {r['solver']} | {r['ratio']:.2f} | "
                f"{r['ratio_per_iter']:.2f} |"
            )
    return "\n".join(out) + "\n"


def versions() -> dict[str, str]:
    return package_versions("torch", "jax", "jaxlib", "numpy")


def discrete_path(dyn, x0: torch.Tensor) -> str:
    """What a discrete model (the learned one) runs on: its traced graph written as a
    compiled step and, where they are written too, its Jacobians
    (:mod:`torchslq.dynamics.network_codegen`), or torch ops."""
    from torchslq.dynamics import network_codegen

    if network_codegen.network_step(dyn) is None:
        return "torch ops"
    u = torch.zeros(x0.shape[0], dyn.control_dim, dtype=x0.dtype)
    with torch.no_grad():
        jacobians = network_codegen.network_jacobians(dyn, x0, u) is not None
    return "compiled step and Jacobians" if jacobians else "compiled step"


def row_of(model, B, solver, res, problem, x0) -> dict:
    J, gn = evaluate(problem, x0, res["u"])
    it = res["iters"]
    f = getattr(problem.dynamics, "continuous", None)
    # "compiled": code generated from the model's forward (the zoo's too)
    path = discrete_path(problem.dynamics, x0) if f is None else codegen.explain(f)
    best = min(res["times"])
    return {
        "model": model, "B": B, "solver": solver, "first_s": res["first"],
        "times_s": res["times"], "time_s": best, "per_iter_s": best / max(int(it.max()), 1),
        "iters_mean": float(it.mean()), "iters_max": int(it.max()), "status": res["status"],
        "max_grad": float(gn.max()), "mean_cost": float(J.mean()), "J": J.tolist(),
        "model_code": path if solver.startswith("torchslq") else "jax.jit",
    }  # fmt: skip


def bench(args, model: str, B: int, rows: list, save) -> None:
    problem, x0 = make_problem(model), initial_states(B, args.seed)
    mine = []
    for name in args.solvers:
        try:
            res = run_torchslq(name, problem, x0, args.repeats)
            res["status"] = ", ".join(f"{k} {v}" for k, v in res["status"].items())
            row = row_of(model, B, f"torchslq {name.upper()}", res, problem, x0)
        except Exception as e:  # noqa: BLE001
            traceback.print_exc()
            row = {"model": model, "B": B, "solver": f"torchslq {name}", "note": repr(e)}
        rows.append(row)
        mine.append(row)
        save()
        print_row(row)
    try:
        net = problem.dynamics.mlp if model == "learned" else None
        res = run_trajax(model, args.trajax, net, x0, args.repeats)
        res["status"] = f"stopped before maxiter {int((res['iters'] < MAX_ITER).sum())}"
        trow = row_of(model, B, "trajax ilqr (jit(vmap))", res, problem, x0)
        trow["compile_reused"] = res["reused"]
    except ImportError as e:
        msg = f"not run: jax/trajax not importable ({e}); give its checkout with --trajax"
        trow = {"model": model, "B": B, "solver": "trajax ilqr", "note": msg}
    except Exception as e:  # noqa: BLE001
        traceback.print_exc()
        trow = {"model": model, "B": B, "solver": "trajax ilqr", "note": repr(e)}
    rows.append(trow)
    if "time_s" in trow:
        Jt = np.asarray(trow["J"])
        for r in (r for r in mine if "time_s" in r):
            rel = np.abs(np.asarray(r["J"]) - Jt) / np.maximum(np.abs(Jt), 1e-300)
            r["cost_match"], r["max_rel_gap"] = int((rel <= RTOL).sum()), float(rel.max())
            r["ratio"] = trow["time_s"] / r["time_s"]
            r["ratio_per_iter"] = trow["per_iter_s"] / r["per_iter_s"]
    save()
    print_row(trow)
    for r in mine:
        if r.get("ratio") is not None:
            print(f"    {r['solver']}: cost match {r['cost_match']}/{B}, max rel gap "
                  f"{r['max_rel_gap']:.1e}, t_trajax/t {r['ratio']:.2f}, per iteration "
                  f"{r['ratio_per_iter']:.2f}", flush=True)  # fmt: skip


def print_row(r: dict) -> None:
    head = f"{r['model']:8s} B={r['B']:<4d} {r['solver']:24s}"
    if "time_s" not in r:
        print(f"{head} {r['note']}", flush=True)
        return
    print(
        f"{head} first {r['first_s']:7.3f} s  best {r['time_s']:7.3f} s  "
        f"{1e3 * r['per_iter_s']:7.2f} ms/it  iters {r['iters_mean']:.1f}/{r['iters_max']}  "
        f"max dJ/dU {r['max_grad']:.1e}  mean cost {r['mean_cost']:.10g}  [{r['status']}]",
        flush=True,
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", default="user,user-torch,learned,zoo")
    ap.add_argument(
        "--solvers",
        default="ilqr,ddp,ilqr-ms,ddp-ms",
        help="ilqr, ddp; -ms: with shooting='multiple'",
    )
    ap.add_argument("--batches", default="1,64,512")
    ap.add_argument("--repeats", type=int, default=1, help="timed solves; the best is kept")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--trajax", default="/tmp/trajax", help="path of a trajax checkout")
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--name", default="user_models")
    args = ap.parse_args(argv)
    args.solvers, args.repeats = args.solvers.split(","), max(1, args.repeats)
    # XLA reads its flags when jax starts, so before jax is imported (in trajax_fn)
    xla = ("--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
           if args.threads == 1 else f"intra_op_parallelism_threads={args.threads}")  # fmt: skip
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + xla).strip()
    torch.set_num_threads(args.threads)
    argv = sys.argv[1:] if argv is None else list(argv)
    meta = {
        "command": "python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *argv]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": platform.machine(),
        "cores": os.cpu_count(),
        "versions": versions(),
        "threads": args.threads,
        "seed": args.seed,
        "repeats": args.repeats,
        "trajax": args.trajax,
        "load_start": load(),
    }
    print(meta["command"], "| load", meta["load_start"], flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []

    def save():  # after every configuration, so a stopped run keeps what it measured
        meta["load_end"] = load()
        (out / f"{args.name}.json").write_text(
            json.dumps({"meta": meta, "rows": rows}, indent=1, default=float)
        )
        (out / f"{args.name}.md").write_text(markdown(meta, rows))

    for model in args.models.split(","):
        for B in (int(b) for b in args.batches.split(",")):
            bench(args, model, B, rows, save)
    save()
    print(f"wrote {out / (args.name + '.json')} and {out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
