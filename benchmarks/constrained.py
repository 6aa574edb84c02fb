"""Constrained solves beside CasADi + IPOPT (cost, violation) and trajax (time).

Not part of the test suite. The problems are the two examples' (imported from
``examples/``), float64, one CPU thread for everyone:

* **cartpole** (``examples/constrained_cartpole.py``): swing-up, RK4 step, dt = 0.05,
  T = 50, cost ``sum_t 0.01 u_t^2``; ``|s_t| <= 0.5`` (t = 0..T), ``|u_t| <= 6``,
  ``x_T = [0, pi, 0, 0]``; ``x0 = [0, 0.05 N(0,1), 0, 0]`` (``default_rng(seed)``),
  ``u = 0`` initially.
* **unicycle** (``examples/constrained_unicycle.py``): Euler step, dt = 0.1, T = 40, cost
  ``sum_t 1/2 |u_t|^2``; three circular obstacles ``r^2 - |p_t - o|^2 <= 0``
  (t = 0..T-1), ``|v| <= 2``, ``|w| <= 3``, ``x_T = [4, 0, 0]``; starts ``[0, U(-1,1),
  U(-0.5,0.5)]``, initial guess ``v = 1, w = 0``.

Solvers:

* torchslq ``ILQR(constraints=..., u_min=, u_max=)`` (augmented Lagrangian over iLQR,
  control bounds in the box QP), or ``DDP`` with ``--solver ddp`` (the same loop with the
  dynamics' and the constraint rows' curvature), as the examples build it (``make_solver``: ``tol = 1e-6``
  on each inner solve's gradient, ``penalty_factor = 100``, ``constraint_tol = 1e-6``),
  with the ``--option`` overrides named in the command (the committed run:
  ``constraint_tol = 1e-8``, so that a violation's effect on the cost, about
  ``lambda * violation``, stays below the 1e-6 cost comparison): one batched call. A
  B = 2 solve first takes the first-call costs (reported as ``first B=2 solve``).
* CasADi + IPOPT (exact Hessian, ``tol = 1e-10``, ``constr_viol_tol = 1e-10``), direct
  multiple shooting with the same step, cost and constraints (state and control limits as
  variable bounds), one instance at a time, **started from the same initial guess as the
  others** (the initial controls and their rollout), so it finds its own local optimum.
  Where IPOPT's trajectory differs from ours (``max |x - x_ipopt| > 1e-3``: a different
  local optimum), IPOPT is run again **warm started from our solution**: if it stays
  there (cost within 1e-6), ours is a local optimum IPOPT accepts.
* trajax ``constrained_ilqr`` (github.com/google/trajax, not on PyPI: ``--trajax PATH``
  to its checkout, default ``/tmp/trajax``), ``jit(vmap(...))`` over the batch,
  ``jax_enable_x64``, XLA on one thread (``--xla_cpu_multi_thread_eigen=false
  intra_op_parallelism_threads=1``), the same dynamics, cost and constraints written in
  jax (control limits as inequality rows, as trajax has no box QP), the same initial
  guess, ``grad_norm_threshold = 1e-6``, ``constraints_threshold = 1e-6``,
  ``maxiter_al = 30``, ``maxiter_ilqr = 500``, its default penalty schedule (x10 per
  outer iteration). Compiled ahead of time (``lower(...).compile()``, timed and
  excluded), then one timed solve.

Every solver's controls are rolled out through torchslq's model and costed by its cost;
the max violation is recomputed on that rollout for every solver (constraint rows and
control limits). Per instance: ``same`` when the state trajectories agree with IPOPT's
to 1e-3, and then whether the costs agree to 1e-6 relative. Ratios are
``t_trajax / t_torchslq`` from the same run. A peer that is not importable is skipped
with a message.

    .venv/bin/python benchmarks/constrained.py --option constraint_tol=1e-8   # B = 512
    .venv/bin/python benchmarks/constrained.py --batches 16 --out /tmp/c     # a quick check
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "")
    + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
).strip()

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "examples"))

import constrained_cartpole as cpx  # noqa: E402
import constrained_unicycle as unx  # noqa: E402
from _env import load, package_versions  # noqa: E402

from torchslq.constraints.spec import ConstraintSet, max_violation  # noqa: E402

RTOL = 1e-6  # cost agreement
SAME_TOL = 1e-3  # state trajectories this close: the same local optimum


# ---------------------------------------------------------------------------- problems
class Spec:
    """One problem: the torchslq pieces and the numbers the peers need."""

    def __init__(self, name: str, B: int, seed: int, model: str = "zoo"):
        self.name = name
        if name == "cartpole":
            self.problem = cpx.make_problem(model)
            self.x0 = cpx.initial_states(B, seed)
            self.u_init = torch.zeros(B, cpx.T, 1, dtype=torch.float64)
            self.constraints = cpx.make_constraints()
            self.u_max = np.array([cpx.U_MAX])
            self.T, self.n, self.m = cpx.T, 4, 1
        else:
            self.problem = unx.make_problem(model)
            self.x0 = unx.initial_states(B, seed)
            self.u_init = unx.initial_controls(B)
            self.constraints = unx.make_constraints()
            self.u_max = np.array([unx.V_MAX, unx.W_MAX])
            self.T, self.n, self.m = unx.T, 3, 2
        self.cset = ConstraintSet(self.constraints).double()
        self.eqs = self.cset.dims(self.n, self.m, self.x0)

    def solver(self, **kw):
        if self.name == "cartpole":
            return cpx.make_solver(**kw)
        return unx.make_solver(**kw)

    def evaluate(self, u: np.ndarray) -> dict[str, np.ndarray]:
        """Roll ``u (B, T, m)`` out through torchslq's model: cost, max violation, states."""
        ut = torch.as_tensor(np.array(u, dtype=np.float64))
        B = ut.shape[0]
        with torch.no_grad():
            x = self.problem.rollout(self.x0[:B], ut)
            J = self.problem.cost(x, ut)
            v = max_violation(self.cset.values(x, ut), *self.eqs)
        ub = torch.as_tensor(self.u_max)
        vu = (ut.abs() - ub).clamp_min(0).amax((1, 2))
        return {"J": J.numpy(), "viol": torch.maximum(v, vu).numpy(), "x": x.numpy()}


# ---------------------------------------------------------------------------- torchslq
def run_torchslq(spec: Spec, **options) -> dict:
    solver = spec.solver(**options)
    t0 = time.perf_counter()
    r = solver.solve(spec.problem, spec.x0, spec.u_init)
    t = time.perf_counter() - t0
    from torchslq import Status, status_names

    names = status_names(r.status)
    return {
        "u": r.u.numpy(),
        "time": t,
        "outer": r.outer_iterations.numpy(),
        "inner": r.iterations.numpy(),
        "converged": (r.status == Status.CONVERGED).numpy(),
        "status_counts": {k: names.count(k) for k in dict.fromkeys(names)},
    }


# ---------------------------------------------------------------------------- CasADi / IPOPT
def casadi_solver(spec: Spec):
    import casadi as ca

    T, n, m = spec.T, spec.n, spec.m
    xs, us = ca.SX.sym("x", n), ca.SX.sym("u", m)
    if spec.name == "cartpole":
        MC, MP, L, G, DT = cpx.MC, cpx.MP, cpx.L, cpx.G, cpx.DT
        th, thd, F = xs[1], xs[3], us[0]
        s, c = ca.sin(th), ca.cos(th)
        D = MC + MP * s * s
        sdd = (F + MP * s * (L * thd * thd + G * c)) / D
        thdd = (-F * c - MP * L * thd * thd * c * s - (MC + MP) * G * s) / (L * D)
        f = ca.Function("f", [xs, us], [ca.vertcat(xs[2], thd, sdd, thdd)])
        k1 = f(xs, us)
        k2 = f(xs + 0.5 * DT * k1, us)
        k3 = f(xs + 0.5 * DT * k2, us)
        k4 = f(xs + DT * k3, us)
        nxt = xs + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        goal = cpx.GOAL
    else:
        DT = unx.DT
        nxt = ca.vertcat(
            xs[0] + ca.cos(xs[2]) * us[0] * DT,
            xs[1] + ca.sin(xs[2]) * us[0] * DT,
            xs[2] + us[1] * DT,
        )
        goal = unx.GOAL
    step = ca.Function("step", [xs, us], [nxt])
    X, U, P = ca.SX.sym("X", n, T + 1), ca.SX.sym("U", m, T), ca.SX.sym("P", n)
    g = [ca.vec(X[:, 0] - P), ca.vec(X[:, 1:] - step.map(T)(X[:, :T], U))]
    lbg, ubg = [np.zeros(n * (T + 1))] * 2
    lbx_X, ubx_X = np.full((n, T + 1), -np.inf), np.full((n, T + 1), np.inf)
    g.append(X[:, T] - ca.DM(goal))
    lbg, ubg = [np.concatenate([lbg, np.zeros(n)])] * 2
    if spec.name == "cartpole":
        J = cpx.R_U * ca.sumsqr(U)
        lbx_X[0], ubx_X[0] = -cpx.S_MAX, cpx.S_MAX
    else:
        J = 0.5 * ca.sumsqr(U)
        rows = []
        for ox, oy, r in unx.OBSTACLES:
            rows.append(r * r - (X[0, :T] - ox) ** 2 - (X[1, :T] - oy) ** 2)
        g.append(ca.vec(ca.vertcat(*rows)))
        k = len(unx.OBSTACLES) * T
        lbg = np.concatenate([lbg, np.full(k, -np.inf)])
        ubg = np.concatenate([ubg, np.zeros(k)])
    w = ca.vertcat(ca.vec(X), ca.vec(U))
    lbw = np.concatenate([lbx_X.reshape(-1, order="F"), np.tile(-spec.u_max, T)])
    ubw = np.concatenate([ubx_X.reshape(-1, order="F"), np.tile(spec.u_max, T)])
    opts = {
        "ipopt.tol": 1e-10,
        "ipopt.constr_viol_tol": 1e-10,
        "ipopt.print_level": 0,
        "print_time": 0,
        "ipopt.sb": "yes",
        "ipopt.max_iter": 3000,
    }
    prob = {"x": w, "f": J, "g": ca.vertcat(*g), "p": P}
    nlp = ca.nlpsol("nlp", "ipopt", prob, opts)
    # started at a solution: a small barrier parameter and push, or the first iterations
    # leave the active constraints and may reach another local optimum
    warm_opts = {
        **opts,
        "ipopt.mu_init": 1e-9,
        "ipopt.warm_start_init_point": "yes",
        "ipopt.warm_start_bound_push": 1e-12,
        "ipopt.warm_start_slack_bound_push": 1e-12,
        "ipopt.warm_start_mult_bound_push": 1e-12,
    }
    nlp_warm = ca.nlpsol("nlp_warm", "ipopt", prob, warm_opts)
    nx = n * (T + 1)

    def solve(i: int, x_guess: np.ndarray, u_guess: np.ndarray, warm: bool = False):
        # an interior-point start must lie inside the variable bounds
        w0 = np.concatenate([x_guess.T.reshape(-1, order="F"), u_guess.T.reshape(-1, order="F")])
        w0 = np.clip(w0, lbw + 1e-9 * (lbw > -np.inf), ubw - 1e-9 * (ubw < np.inf))
        f = nlp_warm if warm else nlp
        sol = f(x0=w0, p=spec.x0[i].numpy(), lbx=lbw, ubx=ubw, lbg=lbg, ubg=ubg)
        st = f.stats()
        u = np.array(sol["x"]).reshape(-1)[nx:].reshape(T, m)
        return u, st["iter_count"], bool(st["success"])

    return solve


def run_ipopt(spec: Spec, guess_x: np.ndarray, guess_u: np.ndarray) -> dict:
    solve = casadi_solver(spec)
    B = guess_u.shape[0]
    us, its, ok = [], [], []
    t0 = time.perf_counter()
    for i in range(B):
        u, it, s = solve(i, guess_x[i], guess_u[i])
        us.append(u)
        its.append(it)
        ok.append(s)
    return {
        "u": np.stack(us),
        "time": time.perf_counter() - t0,
        "iters": np.array(its),
        "converged": np.array(ok),
        "solve": solve,
    }


# ---------------------------------------------------------------------------- trajax
def trajax_solver(spec: Spec, path: str):
    if path not in sys.path:
        sys.path.insert(0, path)
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from trajax.optimizers import constrained_ilqr

    T = spec.T
    umax = jnp.asarray(spec.u_max)
    if spec.name == "cartpole":
        MC, MP, L, G, DT = cpx.MC, cpx.MP, cpx.L, cpx.G, cpx.DT
        goal = jnp.asarray(cpx.GOAL)

        def f(x, u):
            th, thd, F = x[1], x[3], u[0]
            s, c = jnp.sin(th), jnp.cos(th)
            D = MC + MP * s * s
            sdd = (F + MP * s * (L * thd * thd + G * c)) / D
            thdd = (-F * c - MP * L * thd * thd * c * s - (MC + MP) * G * s) / (L * D)
            return jnp.stack([x[2], thd, sdd, thdd])

        def dynamics(x, u, t):
            k1 = f(x, u)
            k2 = f(x + 0.5 * DT * k1, u)
            k3 = f(x + 0.5 * DT * k2, u)
            k4 = f(x + DT * k3, u)
            return x + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

        def cost(x, u, t):
            return jnp.where(t == T, 0.0, cpx.R_U * jnp.dot(u, u))

        def inequality(x, u, t):
            s = jnp.stack([x[0] - cpx.S_MAX, -x[0] - cpx.S_MAX])
            return jnp.concatenate([s, u - umax, -u - umax])

    else:
        DT = unx.DT
        goal = jnp.asarray(unx.GOAL)
        obs = jnp.asarray(unx.OBSTACLES)

        def dynamics(x, u, t):
            return jnp.stack(
                [
                    x[0] + jnp.cos(x[2]) * u[0] * DT,
                    x[1] + jnp.sin(x[2]) * u[0] * DT,
                    x[2] + u[1] * DT,
                ]
            )

        def cost(x, u, t):
            return jnp.where(t == T, 0.0, 0.5 * jnp.dot(u, u))

        def inequality(x, u, t):
            d = x[None, :2] - obs[:, :2]
            rows = obs[:, 2] ** 2 - jnp.sum(d * d, -1)
            # the obstacles at t < T only (the final state is the goal), as in ours
            rows = jnp.where(t < T, rows, -1.0)
            return jnp.concatenate([rows, u - umax, -u - umax])

    def equality(x, u, t):
        return jnp.where(t == T, x - goal, jnp.zeros_like(x))

    def one(x0, U):
        out = constrained_ilqr(
            cost, dynamics, x0, U,
            equality_constraint=equality, inequality_constraint=inequality,
            maxiter_al=30, maxiter_ilqr=500, grad_norm_threshold=1e-6,
            constraints_threshold=1e-6,
        )  # fmt: skip
        X, U, *_, iteration_ilqr, iteration_al = out
        return U, out[7], iteration_ilqr, iteration_al

    return jax.jit(jax.vmap(one))


def run_trajax(spec: Spec, path: str) -> dict:
    import jax

    fn = trajax_solver(spec, path)
    x0 = jax.numpy.asarray(spec.x0.numpy())
    U0 = jax.numpy.asarray(spec.u_init.numpy())
    # compiled ahead of time, so the compilation is timed apart and the solve runs once
    t0 = time.perf_counter()
    compiled = fn.lower(x0, U0).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    U, viol, it_ilqr, it_al = jax.block_until_ready(compiled(x0, U0))
    t = time.perf_counter() - t0
    return {
        "u": np.asarray(U),
        "time": t,
        "compile": t_compile,
        "own_violation": np.asarray(viol),
        "inner": np.asarray(it_ilqr),
        "outer": np.asarray(it_al),
    }


# ---------------------------------------------------------------------------- comparison
def compare(ev: dict, ref: dict) -> dict:
    """Instances on the same local optimum as the reference (states within SAME_TOL) and
    among them the cost agreement."""
    dx = np.abs(ev["x"] - ref["x"]).max((1, 2))
    same = dx <= SAME_TOL
    rel = np.abs(ev["J"] - ref["J"]) / np.maximum(np.abs(ref["J"]), 1e-300)
    return {
        "same_optimum": int(same.sum()),
        "cost_match_same": int((same & (rel <= RTOL)).sum()),
        "max_rel_gap_same": float(rel[same].max()) if same.any() else None,
        "different_optimum": int((~same).sum()),
        "lower_than_ref": int((~same & (ev["J"] < ref["J"])).sum()),
        "higher_than_ref": int((~same & (ev["J"] > ref["J"])).sum()),
        "rel": rel,
        "same": same,
    }


def stats(a) -> dict:
    a = np.asarray(a, dtype=float)
    return {"mean": float(a.mean()), "max": float(a.max())}


def bench(args, spec: Spec, B: int, rows: list, save) -> None:
    print(f"\n== {spec.name} B={B}  load {load()}", flush=True)
    base = {"problem": spec.name, "B": B}
    # warm-up: first-call costs (numba caches, torch.func transforms) out of the timing
    w = Spec(spec.name, 2, args.seed + 1, args.model)
    t0 = time.perf_counter()
    run_torchslq(w, **args.options)
    warm = time.perf_counter() - t0
    ours = run_torchslq(spec, **args.options)
    ev = spec.evaluate(ours["u"])
    conv = ours["converged"]
    row = {
        **base,
        "solver": f"torchslq {args.solver.upper()} (AL)",
        "model": args.model,
        "time_s": ours["time"],
        "warmup_s": warm,
        "status": ours["status_counts"],
        "outer": stats(ours["outer"]),
        "inner": stats(ours["inner"]),
        "max_violation": float(ev["viol"].max()),
        "max_violation_converged": float(ev["viol"][conv].max()) if conv.any() else None,
        "converged_violation_ok": int((ev["viol"][conv] <= 1e-6).sum()),
        "converged": int(conv.sum()),
        "mean_cost": float(ev["J"].mean()),
        "options": args.options,
    }
    rows.append(row)
    save()
    print(
        f"  torchslq: {ours['time']:.2f} s (warm-up {warm:.1f} s) status {ours['status_counts']} "
        f"outer {row['outer']} inner {row['inner']} max viol {row['max_violation']:.2e}",
        flush=True,
    )
    ipopt_ev = None
    if "ipopt" in args.peers:
        try:
            guess_x = spec.evaluate(spec.u_init.numpy())["x"]
            ip = run_ipopt(spec, guess_x, spec.u_init.numpy())
            ipopt_ev = spec.evaluate(ip["u"])
            cmp = compare(ev, ipopt_ev)
            # where the optima differ: does IPOPT, started at ours, stay there?
            diff = np.nonzero(~cmp["same"])[0]
            stays = 0
            t_warm = time.perf_counter()
            for i in diff:
                u, _, ok = ip["solve"](int(i), ev["x"][i], ours["u"][i], warm=True)
                ut = torch.as_tensor(u)[None]
                with torch.no_grad():
                    xw = spec.problem.rollout(spec.x0[i : i + 1], ut)
                    Jw = float(spec.problem.cost(xw, ut))
                stays += int(ok and abs(Jw - ev["J"][i]) <= RTOL * abs(ev["J"][i]))
                if args.verbose:
                    print(
                        f"    instance {i}: IPOPT from ours {ok}, J {Jw:.10g}, ours {ev['J'][i]:.10g}"
                    )
            t_warm = time.perf_counter() - t_warm
            ipc = ip["converged"]
            rows.append(
                {
                    **base,
                    "solver": "CasADi+IPOPT (ref; cold start from the initial guess)",
                    "time_s": ip["time"],
                    "iters": stats(ip["iters"]),
                    "converged": int(ipc.sum()),
                    "max_violation": float(ipopt_ev["viol"].max()),
                    "mean_cost": float(ipopt_ev["J"].mean()),
                }
            )
            row.update(
                {
                    "vs_ipopt_same_optimum": cmp["same_optimum"],
                    "vs_ipopt_cost_match": cmp["cost_match_same"],
                    "vs_ipopt_max_rel_gap_same": cmp["max_rel_gap_same"],
                    "vs_ipopt_different_optimum": cmp["different_optimum"],
                    "vs_ipopt_ours_lower": cmp["lower_than_ref"],
                    "vs_ipopt_ours_higher": cmp["higher_than_ref"],
                    "ipopt_warm_from_ours_stays": stays,
                    "ipopt_warm_time_s": t_warm,
                    "both_converged_same_optimum": int((cmp["same"] & conv & ipc).sum()),
                    "both_converged_same_cost_match": int(
                        (cmp["same"] & conv & ipc & (cmp["rel"] <= RTOL)).sum()
                    ),
                }
            )
            save()
            print(
                f"  IPOPT: {ip['time']:.1f} s, converged {int(ipc.sum())}/{B}; ours on the same "
                f"optimum {cmp['same_optimum']} (cost within {RTOL:g}: {cmp['cost_match_same']}, "
                f"max rel gap {cmp['max_rel_gap_same']}), different {cmp['different_optimum']} "
                f"(ours lower {cmp['lower_than_ref']}, higher {cmp['higher_than_ref']}; IPOPT "
                f"started at ours stays {stays}/{len(diff)})",
                flush=True,
            )
        except ImportError as e:
            print(f"  IPOPT skipped: casadi not importable ({e})", flush=True)
            rows.append({**base, "solver": "CasADi+IPOPT", "note": f"not run: {e}"})
        except Exception as e:  # noqa: BLE001
            traceback.print_exc()
            rows.append({**base, "solver": "CasADi+IPOPT", "note": f"{type(e).__name__}: {e}"})
    if "trajax" in args.peers:
        try:
            tj = run_trajax(spec, args.trajax)
            tev = spec.evaluate(tj["u"])
            ok = tj["own_violation"] <= 1e-6
            trow = {
                **base,
                "solver": "trajax constrained_ilqr (jit(vmap))",
                "time_s": tj["time"],
                "compile_s": tj["compile"],
                "outer": stats(tj["outer"]),
                "inner": stats(tj["inner"]),
                "converged": int(ok.sum()),
                "max_violation": float(tev["viol"].max()),
                "mean_cost": float(tev["J"].mean()),
                "ratio_vs_torchslq": tj["time"] / ours["time"],
            }
            if ipopt_ev is not None:
                c = compare(tev, ipopt_ev)
                trow.update(
                    {
                        "vs_ipopt_same_optimum": c["same_optimum"],
                        "vs_ipopt_cost_match": c["cost_match_same"],
                        "vs_ipopt_max_rel_gap_same": c["max_rel_gap_same"],
                        "vs_ipopt_different_optimum": c["different_optimum"],
                    }
                )
            rows.append(trow)
            row["trajax_over_torchslq"] = trow["ratio_vs_torchslq"]
            save()
            print(
                f"  trajax: {tj['time']:.2f} s (compile {tj['compile']:.1f} s), "
                f"ratio trajax/torchslq {trow['ratio_vs_torchslq']:.2f}, violation <= 1e-6 on "
                f"{int(ok.sum())}/{B}, outer {trow['outer']} inner {trow['inner']}",
                flush=True,
            )
        except ImportError as e:
            msg = f"trajax/jax not importable ({e}); give its checkout with --trajax"
            print(f"  trajax skipped: {msg}", flush=True)
            rows.append({**base, "solver": "trajax constrained_ilqr", "note": f"not run: {msg}"})
        except Exception as e:  # noqa: BLE001
            traceback.print_exc()
            rows.append(
                {**base, "solver": "trajax constrained_ilqr", "note": f"{type(e).__name__}: {e}"}
            )


# ---------------------------------------------------------------------------- report
def _f(v, fmt=".3g") -> str:
    return "-" if v is None else format(v, fmt)


def markdown(meta: dict, rows: list) -> str:
    out = [
        "# Constrained solves: torchslq vs CasADi + IPOPT and trajax",
        "",
        "```",
        meta["command"],
        "```",
        "",
        f"{meta['date']}, {meta['machine']}; threads 1, float64; load average at start "
        f"{meta['load_start']}, at end {meta['load_end']} (**a shared 2-core machine: absolute "
        "times are noisy, ratios are from the same run**). Versions: "
        + ", ".join(f"{k} {v}" for k, v in meta["versions"].items())
        + f". torchslq options: {meta['options']}.",
        "",
        *([meta["note"], ""] if meta.get("note") else []),
        "Problems, solvers and settings: the docstring of `benchmarks/constrained.py`. Costs "
        "and violations are recomputed for every solver on the rollout of its controls "
        "through torchslq's model. `same optimum`: state trajectories within "
        f"{SAME_TOL:g} of IPOPT's (cold start); `cost match`: among those, cost within "
        f"{RTOL:g} relative. `IPOPT stays`: of the instances at a different optimum, how "
        "many IPOPT, warm started from ours, keeps (cost within 1e-6): ours is then a local "
        "optimum too.",
        "",
        "| problem | B | solver | time [s] | iterations outer mean/max, inner mean/max | "
        "converged | max violation (converged) | mean cost | same optimum as IPOPT | "
        "cost match (same optimum) | max rel gap (same) | different optimum | note |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "time_s" not in r:
            out.append(
                f"| {r['problem']} | {r['B']} | {r['solver']} | - | - | - | - | - | - | - | - "
                f"| - | {r.get('note', '')} |"
            )
            continue
        if "outer" in r:
            it = (
                f"{r['outer']['mean']:.1f}/{r['outer']['max']:.0f}, "
                f"{r['inner']['mean']:.0f}/{r['inner']['max']:.0f}"
            )
        else:
            it = f"{r['iters']['mean']:.0f}/{r['iters']['max']:.0f} (IPOPT)"
        viol = _f(r["max_violation"], ".1e")
        if r.get("max_violation_converged") is not None:
            viol += f" ({r['max_violation_converged']:.1e})"
        note = []
        if "warmup_s" in r:
            note.append(f"status {r['status']}; first B=2 solve {r['warmup_s']:.1f} s")
        if "ipopt_warm_from_ours_stays" in r:
            note.append(
                f"ours lower {r['vs_ipopt_ours_lower']}, higher {r['vs_ipopt_ours_higher']}; "
                f"IPOPT stays {r['ipopt_warm_from_ours_stays']}/"
                f"{r['vs_ipopt_different_optimum']}"
            )
        if "compile_s" in r:
            note.append(
                f"compile {r['compile_s']:.1f} s excluded; converged = own violation <= 1e-6; "
                f"**{r['ratio_vs_torchslq']:.2f}x torchslq's time**"
            )
        same = r.get("vs_ipopt_same_optimum")
        out.append(
            f"| {r['problem']} | {r['B']} | {r['solver']} | {r['time_s']:.2f} | {it} | "
            f"{r.get('converged', '-')}/{r['B']} | {viol} | {r['mean_cost']:.8g} | "
            f"{_f(same, 'd')} | {_f(r.get('vs_ipopt_cost_match'), 'd')} | "
            f"{_f(r.get('vs_ipopt_max_rel_gap_same'), '.1e')} | "
            f"{_f(r.get('vs_ipopt_different_optimum'), 'd')} | {'; '.join(note)} |"
        )
    out += [
        "",
        "## Targets (issue 22)",
        "",
        "| problem | B | solver | converged with violation <= 1e-6 | same optimum as IPOPT: cost within "
        "1e-6 | different optimum: ours lower / higher (IPOPT from ours stays) | "
        "t_trajax / t_torchslq (>= 3 wanted) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if not r["solver"].startswith("torchslq"):
            continue
        same = r.get("vs_ipopt_same_optimum")
        cost = "-" if same is None else f"{r['vs_ipopt_cost_match']}/{same}"
        diff = (
            "-"
            if same is None
            else f"{r['vs_ipopt_ours_lower']} / {r['vs_ipopt_ours_higher']} "
            f"({r['ipopt_warm_from_ours_stays']}/{r['vs_ipopt_different_optimum']})"
        )
        ratio = _f(r.get("trajax_over_torchslq"), ".2f")
        out.append(
            f"| {r['problem']} | {r['B']} | {r['solver'].split()[1]}, {r.get('model', 'zoo')} model | "
            f"{r['converged_violation_ok']}/{r['converged']} "
            f"(of {r['B']}) | {cost} | {diff} | {ratio} |"
        )
    return "\n".join(out) + "\n"


def versions() -> dict[str, str]:
    return package_versions("torch", "casadi", "jax", "jaxlib", "numpy")


def merge(paths: list[str], out: Path, name: str, note: str | None = None) -> int:
    runs = [json.loads(Path(p).read_text()) for p in paths]
    meta = dict(runs[0]["meta"])
    for k in ("command", "date", "load_start", "load_end"):
        meta[k] = "; ".join(str(r["meta"][k]) for r in runs) if k != "command" else ""
    meta["command"] = "\n".join(r["meta"]["command"] for r in runs)
    meta["merged_from"] = [r["meta"] for r in runs]
    if note:
        meta["note"] = note
    rows = [{"model": r["meta"].get("model", "zoo"), **row} for r in runs for row in r["rows"]]
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(
        json.dumps({"meta": meta, "rows": rows}, indent=1, default=float)
    )
    (out / f"{name}.md").write_text(markdown(meta, rows))
    print(f"wrote {out / (name + '.json')} and {out / (name + '.md')}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batches", default="512")
    ap.add_argument("--problems", default="cartpole,unicycle")
    ap.add_argument("--peers", default="ipopt,trajax")
    ap.add_argument("--trajax", default="/tmp/trajax", help="path of a trajax checkout")
    ap.add_argument(
        "--model",
        choices=("zoo", "user"),
        default="zoo",
        help="zoo: the library's models; user: the same equations written as plain modules",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--solver",
        choices=("ilqr", "ddp"),
        default="ilqr",
        help="torchslq solver of the AL loop (ddp: exact constraint Hessian)",
    )
    ap.add_argument(
        "--option",
        action="append",
        default=[],
        help="a torchslq solver option NAME=VALUE (e.g. penalty_factor=100), repeatable",
    )
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--name", default="constrained")
    ap.add_argument(
        "--merge",
        nargs="+",
        default=None,
        help="only write <out>/<name>.{json,md} from these result files' rows (runs of "
        "one problem each)",
    )
    ap.add_argument("--note", default=None, help="with --merge: a line for the report")
    args = ap.parse_args(argv)
    if args.merge:
        return merge(args.merge, Path(args.out), args.name, args.note)
    args.peers = set(args.peers.split(","))
    args.options = {k: float(v) for k, v in (o.split("=", 1) for o in args.option)}
    for k in ("max_iter", "al_max_iter"):
        if k in args.options:
            args.options[k] = int(args.options[k])
    args.options["solver"] = args.solver
    torch.set_num_threads(1)
    meta = {
        "command": "python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *sys.argv[1:]]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "versions": versions(),
        "load_start": load(),
        "options": args.options,
        "model": args.model,
    }
    print(meta["command"], "| load", meta["load_start"], flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []

    def save():
        meta["load_end"] = load()
        (out / f"{args.name}.json").write_text(
            json.dumps({"meta": meta, "rows": rows}, indent=1, default=float)
        )
        (out / f"{args.name}.md").write_text(markdown(meta, rows))

    for name in args.problems.split(","):
        for B in (int(b) for b in args.batches.split(",")):
            bench(args, Spec(name, B, args.seed, args.model), B, rows, save)
    save()
    print(f"wrote {out / (args.name + '.json')} and {out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
