"""torchslq's iLQR / SLQ / DDP beside peer solvers on the same problems.

Not part of the test suite. Run from the repo root (peers from the ``bench`` extra:
``.venv/bin/pip install -e .[bench]``)::

    .venv/bin/python benchmarks/peers.py                      # B in {1, 64, 512}
    .venv/bin/python benchmarks/peers.py --batches 1 --out /tmp/peers   # a quick check

The committed results are one file per problem and batch range (``--name``)::

    python benchmarks/peers.py --problems cartpole --peers casadi,mpc --batches 64,512 --cap 300 --name peers_cartpole
    python benchmarks/peers.py --problems unicycle --peers crocoddyl --batches 64,512 --repeats 7 --name peers_unicycle
    python benchmarks/peers.py --problems cartpole,unicycle --peers casadi,mpc,crocoddyl --batches 1 --repeats 7 --cap 300 --name peers_b1
    python benchmarks/peers.py --problems unicycle --peers crocoddyl --batches 4096 --name peers_unicycle_4096

Problems (float64, ``torch.set_num_threads(1)``, OMP/MKL threads 1, crocoddyl
``ShootingProblem.nthreads = 1``):

* **cartpole**: :func:`torchslq.tasks.cartpole_swingup` (point-mass cart-pole, cart 1.0,
  tip 0.1, length 0.5, g = 9.81, theta = 0 hanging; one RK4 step per dt = 0.05, T = 50;
  ``J = sum_t 0.01 u_t^2 + 100 |x_T - [0, pi, 0, 0]|^2``; ``u_init = 0``;
  ``x0 = [0, 0.05 N(0, 1), 0, 0]``, seed 0). Solvers:

  - torchslq ``ILQR``, ``SLQ(rollout="closed_loop")`` (exact line search), ``DDP``
    (``second_order="value"``), all with ``tol = 1e-6`` on ``||dJ/dU||``, one batched
    solve per B;
  - CasADi + IPOPT (exact Hessian, ``tol = 1e-12``): direct multiple shooting with the
    same RK4 step, initial guess = the ``u = 0`` rollout; the optimum's reference;
  - crocoddyl ``SolverFDDP`` and ``SolverDDP`` on a Python
    ``DifferentialActionModelAbstract`` (analytic first derivatives of the same model)
    inside ``IntegratedActionModelRK(RKType.four)``, ``th_stop = 1e-14`` (crocoddyl's
    stopping value is a squared gradient-like norm), looped over the batch. Its running
    cost is integrated by the RK4 weights as ``dt * l``, so the differential running
    cost is ``0.01 u^2 / dt`` (state-independent, hence exactly ``0.01 u^2`` per step);
    the terminal model (``dt = 0``) carries ``100 |x - x_ref|^2``;
  - mpc.pytorch (``mpc.mpc.MPC``, its box-DDP/iLQR without bounds) with
    ``GradMethods.AUTO_DIFF`` and with ``GradMethods.ANALYTIC`` where ``grad_input``
    returns ``torch.func`` Jacobians (``vmap(jacrev)``) of the same RK4 step;
    ``eps = 1e-4`` on its full-step norm (max over the batch), ``lqr_iter = 500``. **Cost mapping**:
    mpc.pytorch's cost is ``sum_{t=0}^{T'-1} 1/2 tau_t' C_t tau_t + c_t' tau_t`` on
    ``tau_t = [x_t, u_t]`` with ``x_0 = x_init`` and no separate terminal term, so it is
    given the horizon ``T' = T + 1 = 51``: ``C_t = diag(0, 0, 0, 0, 0.02)`` for
    ``t < 50``; at ``t = 50``, ``C = diag(200 I_4, 0.02)`` and ``c = [-200 x_ref, 0]``
    (= ``100 |x_50 - x_ref|^2`` less the constant ``100 |x_ref|^2``). The extra control
    ``u_50`` only enters ``0.01 u_50^2``, so its optimum is 0 and it is dropped.

* **unicycle**: crocoddyl's built-in C++ ``ActionModelUnicycle`` (dt = 0.1, costWeights
  ``[10, 1]``: ``l = 1/2 (100 |x|^2 + |u|^2)``, terminal ``1/2 100 |x_T|^2``, Euler step
  ``[x + cos(th) v dt, y + sin(th) v dt, th + w dt]``), T = 20, ``x0 ~ U[-1, 1]^3`` (seed
  0), crocoddyl ``SolverDDP`` / ``SolverFDDP`` looped over the batch, beside the same
  model as torchslq's :class:`torchslq.systems.Unicycle` (analytic Jacobians and second
  derivatives) + ``QuadraticCost`` (ILQR, DDP).

Checks and timing: every solver's controls are rolled out through torchslq's model and
costed by torchslq's cost; each instance's cost is compared with the reference
(cartpole: IPOPT; unicycle: crocoddyl DDP) at 1e-6 relative, and the number of
instances that match is reported beside every timing. A solve that does not match is
still timed but marked. Times are wall times of one solve (torchslq: the batched call;
looped peers: the whole loop, model construction excluded). A peer configuration whose
loop passes ``--cap`` seconds is stopped and its time extrapolated linearly from the
instances solved (marked ``extrapolated``); mpc.pytorch (batched) is skipped at B when
its B = 64 time scaled by B / 64 exceeds the cap (it always runs for B <= 64) (marked
``extrapolated`` too). Ratios are ``t_peer / t_torchslq`` from the same run
(> 1: torchslq faster).

The machine this was written for is a shared 2-core box on which other processes run:
the load average at start and end is recorded, and absolute times are noisy.
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

from torchslq import DDP, ILQR, SLQ, Problem, QuadraticCost  # noqa: E402
from torchslq.systems import Unicycle  # noqa: E402
from torchslq.tasks import cartpole_swingup  # noqa: E402

DT, T_CP, MC, MP, L, G = 0.05, 50, 1.0, 0.1, 0.5, 9.81
XREF = np.array([0.0, math.pi, 0.0, 0.0])
RTOL = 1e-6
SAVE = lambda: None  # noqa: E731  (set by main: writes the results so far)
MPC_EPS = 1e-4  # mpc.pytorch: stop when max_b ||du_b|| < MPC_EPS
VERBOSE = int(os.environ.get("PEERS_MPC_VERBOSE", "-1"))
TH_STOP = 1e-12  # crocoddyl: stop when the expected improvement |d1 + d2/2| < TH_STOP


# ---------------------------------------------------------------------------- helpers


def match(J: np.ndarray, Jref: np.ndarray) -> tuple[int, float]:
    """Number of instances within RTOL of the reference and the max relative gap."""
    ok = np.isfinite(J) & np.isfinite(Jref)
    rel = np.full(J.shape, np.inf)
    rel[ok] = np.abs(J[ok] - Jref[ok]) / np.maximum(np.abs(Jref[ok]), 1e-300)
    return int((rel <= RTOL).sum()), float(rel.max()) if rel.size else float("nan")


def true_cost(problem: Problem, x0: torch.Tensor, u: np.ndarray) -> np.ndarray:
    """J(U) by torchslq's rollout and cost (the common yardstick)."""
    ut = torch.as_tensor(u, dtype=torch.float64).reshape(x0.shape[0], problem.horizon, -1)
    with torch.no_grad():
        return problem.total_cost(x0, ut).numpy()


class Looped:
    """Run ``solve_one(i)`` for i < B until ``cap`` seconds; extrapolate the rest."""

    def __init__(self, cap: float):
        self.cap = cap

    def __call__(self, B: int, solve_one):
        us, its, t0 = [], [], time.perf_counter()
        for i in range(B):
            u, it = solve_one(i)
            us.append(u)
            its.append(it)
            if time.perf_counter() - t0 > self.cap and i + 1 < B:
                break
        t = time.perf_counter() - t0
        done = len(us)
        return us, its, (t * B / done), done < B, done


# ---------------------------------------------------------------------------- torchslq
def run_torchslq(solver, problem, x0):
    t0 = time.perf_counter()
    r = solver.solve(problem, x0)
    t = time.perf_counter() - t0
    return {
        "u": r.u.numpy(),
        "time": t,
        "iters_mean": float(r.iterations.double().mean()),
        "iters_max": int(r.iterations.max()),
        "converged": int(r.converged.sum()),
    }


def torchslq_solvers(max_iter: int):
    return {
        # compact=True: finished elements cost nothing more (the problems here have no
        # per-element tensors), so the batch does not pay for its slowest member
        "torchslq ILQR": lambda: ILQR(max_iter=max_iter, tol=1e-6, progress=False, compact=True),
        "torchslq SLQ (closed-loop)": lambda: SLQ(
            max_iter=max_iter, tol=1e-6, rollout="closed_loop", progress=False, compact=True
        ),
        "torchslq DDP": lambda: DDP(max_iter=max_iter, tol=1e-6, progress=False, compact=True),
    }


# ---------------------------------------------------------------------------- cart-pole (numpy)
def cp_f(x, u):
    th, thd = x[1], x[3]
    s, c = math.sin(th), math.cos(th)
    D = MC + MP * s * s
    sdd = (u + MP * s * (L * thd * thd + G * c)) / D
    thdd = (-u * c - MP * L * thd * thd * c * s - (MC + MP) * G * s) / (L * D)
    return np.array([x[2], thd, sdd, thdd]), (s, c, D, sdd, thdd)


def cp_jac(x, u):
    thd = x[3]
    _, (s, c, D, sdd, thdd) = cp_f(x, u)
    dD = 2.0 * MP * s * c
    c2 = c * c - s * s
    Fx = np.zeros((4, 4))
    Fx[0, 2] = Fx[1, 3] = 1.0
    Fx[2, 1] = (MP * (L * thd * thd * c + G * c2) - sdd * dD) / D
    Fx[2, 3] = 2.0 * MP * L * s * thd / D
    Fx[3, 1] = ((u * s - MP * L * thd * thd * c2 - (MC + MP) * G * c) / L - thdd * dD) / D
    Fx[3, 3] = -2.0 * MP * thd * c * s / D
    Fu = np.array([[0.0], [0.0], [1.0 / D], [-c / (L * D)]])
    return Fx, Fu


def cp_rk4_np(x, u):
    k1 = cp_f(x, u)[0]
    k2 = cp_f(x + 0.5 * DT * k1, u)[0]
    k3 = cp_f(x + 0.5 * DT * k2, u)[0]
    k4 = cp_f(x + DT * k3, u)[0]
    return x + DT / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


# ---------------------------------------------------------------------------- CasADi / IPOPT
def casadi_cartpole(x0: np.ndarray, cap: float):
    import casadi as ca

    xs, us_ = ca.SX.sym("x", 4), ca.SX.sym("u", 1)
    th, thd, F = xs[1], xs[3], us_[0]
    s, c = ca.sin(th), ca.cos(th)
    D = MC + MP * s * s
    sdd = (F + MP * s * (L * thd * thd + G * c)) / D
    thdd = (-F * c - MP * L * thd * thd * c * s - (MC + MP) * G * s) / (L * D)
    f = ca.Function("f", [xs, us_], [ca.vertcat(xs[2], thd, sdd, thdd)])
    k1 = f(xs, us_)
    k2 = f(xs + 0.5 * DT * k1, us_)
    k3 = f(xs + 0.5 * DT * k2, us_)
    k4 = f(xs + DT * k3, us_)
    step = ca.Function("step", [xs, us_], [xs + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
    X = ca.SX.sym("X", 4, T_CP + 1)
    U = ca.SX.sym("U", 1, T_CP)
    P = ca.SX.sym("P", 4)
    Xn = step.map(T_CP)(X[:, :T_CP], U)
    g = ca.vertcat(ca.vec(X[:, 0] - P), ca.vec(X[:, 1:] - Xn))
    e = X[:, T_CP] - ca.DM(XREF)
    J = 0.01 * ca.sumsqr(U) + 100 * ca.dot(e, e)
    w = ca.vertcat(ca.vec(X), ca.vec(U))
    opts = {
        "ipopt.tol": 1e-12,
        "ipopt.print_level": 0,
        "print_time": 0,
        "ipopt.sb": "yes",
        "ipopt.max_iter": 1000,
    }
    nlp = ca.nlpsol("nlp", "ipopt", {"x": w, "f": J, "g": g, "p": P}, opts)
    nx = 4 * (T_CP + 1)

    def solve_one(i):
        xg = [x0[i]]
        for _ in range(T_CP):
            xg.append(cp_rk4_np(xg[-1], 0.0))
        w0 = np.concatenate([np.stack(xg, 1).reshape(-1, order="F"), np.zeros(T_CP)])
        sol = nlp(x0=w0, p=x0[i], lbg=0, ubg=0)
        st = nlp.stats()
        it = st["iter_count"] if st["success"] else -1
        return np.array(sol["x"]).reshape(-1)[nx:], it

    return Looped(cap)(x0.shape[0], solve_one)


# ---------------------------------------------------------------------------- crocoddyl
def crocoddyl_cartpole(x0: np.ndarray, cap: float, solver_name: str):
    import crocoddyl

    class DAM(crocoddyl.DifferentialActionModelAbstract):
        def __init__(self, terminal: bool):
            super().__init__(crocoddyl.StateVector(4), 1, 1)
            self.terminal = terminal
            self.wu = 0.01 / DT  # integrated by RK4 as dt * l -> 0.01 u^2 per step

        def calc(self, data, x, u=None):
            uu = 0.0 if u is None else float(u[0])
            data.xout = cp_f(x, uu)[0][2:]
            if self.terminal:
                e = x - XREF
                data.cost = 100.0 * float(e @ e)
            else:
                data.cost = self.wu * uu * uu

        def calcDiff(self, data, x, u=None):
            uu = 0.0 if u is None else float(u[0])
            Fx, Fu = cp_jac(x, uu)
            data.Fx = Fx[2:]
            data.Fu = Fu[2:]
            if self.terminal:
                data.Lx = 200.0 * (x - XREF)
                data.Lxx = 200.0 * np.eye(4)
            else:
                data.Lu = np.array([2 * self.wu * uu])
                data.Luu = np.array([[2 * self.wu]])

    # the DAM's xout is the acceleration of a second-order system [q, v]: q = (s, th)
    run = crocoddyl.IntegratedActionModelRK(DAM(False), crocoddyl.RKType.four, DT)
    term = crocoddyl.IntegratedActionModelRK(DAM(True), crocoddyl.RKType.four, 0.0)
    Solver = {"FDDP": crocoddyl.SolverFDDP, "DDP": crocoddyl.SolverDDP}[solver_name]

    prob = crocoddyl.ShootingProblem(x0[0].copy(), [run] * T_CP, term)
    prob.nthreads = 1  # (crocoddyl's wheel has no multithreading: it says so, once)

    def solve_one(i):
        prob.x0 = x0[i].copy()
        s = Solver(prob)
        s.th_stop = TH_STOP
        us0 = [np.zeros(1)] * T_CP
        xs0 = prob.rollout(us0)
        s.solve(xs0, us0, 1000, True)
        return np.array(s.us).reshape(-1), s.iter

    return Looped(cap)(x0.shape[0], solve_one)


# ---------------------------------------------------------------------------- mpc.pytorch
def mpc_cartpole(problem: Problem, x0: torch.Tensor, method: str):
    from mpc import mpc as mpcmod
    from mpc.mpc import GradMethods, QuadCost

    dyn = problem.dynamics

    class Dx(torch.nn.Module):
        def forward(self, x, u):
            return dyn(x, u)

        def grad_input(self, x, u):  # used by GradMethods.ANALYTIC: torch.func Jacobians
            J = torch.func.vmap(torch.func.jacrev(lambda a, b: dyn(a, b), argnums=(0, 1)))
            return J(x.detach(), u.detach())

    B, n, m, Tp = x0.shape[0], 4, 1, T_CP + 1
    C = torch.zeros(Tp, B, n + m, n + m, dtype=torch.float64)
    c = torch.zeros(Tp, B, n + m, dtype=torch.float64)
    C[:, :, n, n] = 0.02
    C[T_CP, :, :n, :n] = 200.0 * torch.eye(n, dtype=torch.float64)
    c[T_CP, :, :n] = -200.0 * torch.as_tensor(XREF)
    gm = {"AUTO_DIFF": GradMethods.AUTO_DIFF, "ANALYTIC": GradMethods.ANALYTIC}[method]
    ctrl = mpcmod.MPC(
        n,
        m,
        Tp,
        lqr_iter=500,
        grad_method=gm,
        eps=MPC_EPS,
        exit_unconverged=False,
        detach_unconverged=False,
        backprop=False,
        verbose=VERBOSE,
        n_batch=B,
        not_improved_lim=500,
    )
    t0 = time.perf_counter()
    _, u, _ = ctrl(x0, QuadCost(C, c), Dx())
    t = time.perf_counter() - t0
    return u[:T_CP].detach().transpose(0, 1).numpy(), t


# ---------------------------------------------------------------------------- unicycle
# crocoddyl's ActionModelUnicycle step, with analytic Jacobians and second derivatives
# (crocoddyl's own model is analytic C++); kept under its old name for older scripts
TorchUnicycle = Unicycle


def unicycle_problem(B: int, seed: int = 0, T: int = 20):
    import crocoddyl

    m = crocoddyl.ActionModelUnicycle()
    wx, wu = (float(v) for v in m.costWeights)
    kw = {"dtype": torch.float64}
    cost = QuadraticCost(
        wx**2 * torch.eye(3, **kw), wu**2 * torch.eye(2, **kw), Qf=wx**2 * torch.eye(3, **kw)
    )
    g = torch.Generator().manual_seed(seed)
    x0 = torch.rand(B, 3, generator=g, dtype=torch.float64) * 2 - 1
    return Problem(TorchUnicycle(float(m.dt)), cost, T), x0


def crocoddyl_unicycle(x0: np.ndarray, T: int, cap: float, solver_name: str):
    import crocoddyl

    model = crocoddyl.ActionModelUnicycle()
    Solver = {"FDDP": crocoddyl.SolverFDDP, "DDP": crocoddyl.SolverDDP}[solver_name]

    prob = crocoddyl.ShootingProblem(x0[0].copy(), [model] * T, model)
    prob.nthreads = 1

    def solve_one(i):
        prob.x0 = x0[i].copy()
        s = Solver(prob)
        s.th_stop = TH_STOP
        us0 = [np.zeros(2)] * T
        s.solve(prob.rollout(us0), us0, 1000, True)
        return np.array(s.us).reshape(-1), s.iter

    return Looped(cap)(x0.shape[0], solve_one)


# ---------------------------------------------------------------------------- driver
def record(rows, problem_name, B, name, u, t, Jref, problem, x0, **extra):
    J = true_cost(problem, x0, u)
    nm, rel = match(J, Jref) if Jref is not None else (None, None)
    solved = extra.pop("solved", B)
    if Jref is not None and solved < B:
        nm, rel = match(J[:solved], Jref[:solved])
    row = {
        "problem": problem_name,
        "B": B,
        "solver": name,
        "time_s": t,
        "per_problem_ms": 1e3 * t / B,
        "match": nm,
        "checked": solved,
        "max_rel_gap": rel,
        "mean_cost": float(np.mean(J[:solved])),
        **extra,
    }
    rows.append(row)
    SAVE()
    ext = " (extrapolated)" if row.get("extrapolated") else ""
    if nm is None:  # the reference itself (no IPOPT run: the first torchslq solver)
        check = "(reference)"
    else:
        flag = "" if nm == solved else f"  MISMATCH ({nm}/{solved})"
        check = f"match {nm}/{solved}  max rel gap {rel:.1e}{flag}"
    print(f"  {problem_name:9s} B={B:<4d} {name:30s} {t:9.3f} s{ext}  {check}", flush=True)
    return J


def note(rows, problem_name, B, name, text):
    rows.append({"problem": problem_name, "B": B, "solver": name, "note": text})
    SAVE()
    print(f"  {problem_name:9s} B={B:<4d} {name:30s} NOT RUN: {text}", flush=True)


def bench_cartpole(args, rows):
    mpc_prev: dict[str, tuple[int, float]] = {}
    for B in args.batches:
        problem, x0 = cartpole_swingup(B, horizon=T_CP, dt=DT, seed=args.seed)
        x0n = x0.numpy()
        Jref = None
        # reference: IPOPT
        if "casadi" in args.peers:
            try:
                us, its, t, ext, done = casadi_cartpole(x0n, args.cap)
                u = np.full((B, T_CP), np.nan)
                u[:done] = np.stack(us)
                Jc = true_cost(problem, x0, np.nan_to_num(u))
                Jc[done:] = np.nan
                Jref = Jc
                record(
                    rows, "cartpole", B, "CasADi+IPOPT (ref)", u, t, Jref, problem, x0,
                    solved=done, extrapolated=ext, iters_mean=float(np.mean(its)),
                    ipopt_failures=int(sum(i < 0 for i in its)),
                )  # fmt: skip
            except Exception as e:  # noqa: BLE001
                note(rows, "cartpole", B, "CasADi+IPOPT (ref)", f"{type(e).__name__}: {e}")
        for name, mk in torchslq_solvers(args.max_iter).items():
            r = run_torchslq(mk(), problem, x0)
            J = record(
                rows, "cartpole", B, name, r["u"], r["time"], Jref, problem, x0,
                iters_mean=r["iters_mean"], iters_max=r["iters_max"], converged=r["converged"],
            )  # fmt: skip
            if Jref is None:  # no IPOPT: torchslq ILQR is the reference
                Jref = J
        for sname in ("FDDP", "DDP"):
            name = f"crocoddyl {sname} (Python DAM, RK4)"
            if "crocoddyl" not in args.peers:
                continue
            try:
                us, its, t, ext, done = crocoddyl_cartpole(x0n, args.cap, sname)
                u = np.zeros((B, T_CP))
                u[:done] = np.stack(us)
                record(
                    rows, "cartpole", B, name, u, t, Jref, problem, x0, solved=done,
                    extrapolated=ext, iters_mean=float(np.mean(its)), iters_max=int(max(its)),
                )  # fmt: skip
            except Exception as e:  # noqa: BLE001
                traceback.print_exc()
                note(rows, "cartpole", B, name, f"{type(e).__name__}: {e}")
        for method in ("AUTO_DIFF", "ANALYTIC"):
            name = f"mpc.pytorch {method}" + (" (torch.func)" if method == "ANALYTIC" else "")
            if "mpc" not in args.peers:
                continue
            if method in mpc_prev and B > 64:  # batched: always run it up to B = 64
                Bp, tp = mpc_prev[method]
                est = tp * B / Bp
                if est > args.cap:
                    rows.append({
                        "problem": "cartpole", "B": B, "solver": name, "time_s": est,
                        "per_problem_ms": 1e3 * est / B, "extrapolated": True, "match": None,
                        "checked": 0,
                        "note": f"not run: estimated {est:.0f} s > cap (B={Bp} time x {B}/{Bp})",
                    })  # fmt: skip
                    print(f"  cartpole  B={B:<4d} {name:30s} {est:9.1f} s (extrapolated)")
                    continue
            try:
                u, t = mpc_cartpole(problem, x0, method)
                mpc_prev[method] = (B, t)
                record(rows, "cartpole", B, name, u, t, Jref, problem, x0)
            except Exception as e:  # noqa: BLE001
                traceback.print_exc()
                note(rows, "cartpole", B, name, f"{type(e).__name__}: {e}")


def bench_unicycle(args, rows):
    T = 20
    # warm-up on this model (first-call costs of torch.func transforms for a new module),
    # as main() does for the cart-pole
    p, x = unicycle_problem(2, args.seed + 1, T)
    for name, mk in torchslq_solvers(3).items():
        if "SLQ" not in name:
            mk().solve(p, x)
    for B in args.batches:
        problem, x0 = unicycle_problem(B, args.seed, T)
        x0n = x0.numpy()
        # --repeats: every solver runs that many times, in turn (crocoddyl, torchslq,
        # crocoddyl, ...), and the median is reported: this machine's load moves single
        # runs by 20-60%, the peers' as much as ours
        runs: dict[str, dict] = {}
        for _ in range(args.repeats):
            for sname in ("DDP", "FDDP"):
                name = f"crocoddyl {sname} (C++ ActionModelUnicycle)"
                try:
                    us, its, t, ext, done = crocoddyl_unicycle(x0n, T, args.cap, sname)
                except Exception as e:  # noqa: BLE001
                    traceback.print_exc()
                    runs[name] = {"error": f"{type(e).__name__}: {e}"}
                    continue
                if name not in runs:
                    u = np.zeros((B, T, 2))
                    u[:done] = np.stack(us).reshape(done, T, 2)
                    runs[name] = {
                        "u": u, "times": [], "solved": done, "extrapolated": ext,
                        "iters_mean": float(np.mean(its)), "iters_max": int(max(its)),
                    }  # fmt: skip
                runs[name].setdefault("times", []).append(t)
            for name, mk in torchslq_solvers(args.max_iter).items():
                if "SLQ" in name:
                    continue
                r = run_torchslq(mk(), problem, x0)
                if name not in runs:
                    runs[name] = {
                        "u": r["u"], "times": [], "iters_mean": r["iters_mean"],
                        "iters_max": r["iters_max"], "converged": r["converged"],
                    }  # fmt: skip
                runs[name]["times"].append(r["time"])
        Jref = None
        for name, run in runs.items():
            if "error" in run:
                note(rows, "unicycle", B, name, run["error"])
                continue
            u, times = run.pop("u"), run.pop("times")
            t = float(np.median(times))
            extra = dict(run, times=times) if len(times) > 1 else run
            ref = name.startswith("crocoddyl DDP")
            if ref:
                Jref = true_cost(problem, x0, u)
                Jref[run["solved"] :] = np.nan
            J = record(
                rows, "unicycle", B, name + (" (ref)" if ref else ""), u, t, Jref, problem, x0,
                **extra,
            )  # fmt: skip
            if Jref is None:
                Jref = J


def ratios(rows):
    out = []
    timed = [r for r in rows if "time_s" in r]
    for r in timed:
        if not r["solver"].startswith("torchslq"):
            continue
        for p in timed:
            if p["problem"] == r["problem"] and p["B"] == r["B"]:
                if p["solver"].startswith("torchslq"):
                    continue
                out.append({
                    "problem": r["problem"], "B": r["B"], "torchslq": r["solver"],
                    "peer": p["solver"], "ratio": p["time_s"] / r["time_s"],
                    "peer_extrapolated": bool(p.get("extrapolated")),
                    "both_match": p.get("match") == p.get("checked") and r.get("match") == r.get("checked"),
                })  # fmt: skip
    return out


def _note(r: dict) -> str:
    """A row's note, with the times of its repeated runs (``--repeats``)."""
    times = r.get("times")
    runs = "runs " + ", ".join(f"{t:.3f}" for t in times) + " s" if times else ""
    return "; ".join(x for x in (r.get("note", ""), runs) if x)


def markdown(meta, rows, rat) -> str:
    L_ = [
        "# torchslq vs peer solvers",
        "",
        "```",
        meta["command"],
        "```",
        "",
        f"{meta['date']}, {meta['machine']}; torch {meta['torch']}, threads 1, float64. "
        f"Load average at start {meta['load_start']}, at end {meta['load_end']}: "
        "**a shared 2-core box where other processes run**, so absolute times are noisy; "
        "ratios are from the same run. Versions: "
        + ", ".join(f"{k} {v}" for k, v in meta["versions"].items())
        + ".",
        "",
        "`match`: instances whose cost (controls rolled out and costed by torchslq) is "
        f"within {RTOL:g} relative of the reference (cartpole: IPOPT; unicycle: crocoddyl "
        "DDP) / instances checked. `extrapolated`: the loop was stopped at the cap (or not "
        "run) and the time scaled linearly from the instances solved (or from the previous B).",
        "",
        *(
            [
                "Unicycle times: the median of the runs listed in the note (`--repeats`; the "
                "solvers ran in turn: crocoddyl DDP, FDDP, torchslq ILQR, DDP, again).",
                "",
            ]
            if any(r.get("times") for r in rows)
            else []
        ),
        "| problem | B | solver | time [s] | per problem [ms] | iters mean/max | match | "
        "max rel gap | mean cost | note |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "time_s" not in r:
            L_.append(
                f"| {r['problem']} | {r['B']} | {r['solver']} | - | - | - | - | - | - | "
                f"{r.get('note', '')} |"
            )
            continue
        it = f"{r['iters_mean']:.1f}/{r.get('iters_max', '-')}" if "iters_mean" in r else "-"
        ext = " (extrapolated)" if r.get("extrapolated") else ""
        m = "-" if r.get("match") is None else f"{r['match']}/{r['checked']}"
        gap = "-" if r.get("max_rel_gap") is None else f"{r['max_rel_gap']:.1e}"
        cost = "-" if "mean_cost" not in r else f"{r['mean_cost']:.8g}"
        L_.append(
            f"| {r['problem']} | {r['B']} | {r['solver']} | {r['time_s']:.3f}{ext} | "
            f"{r['per_problem_ms']:.2f} | {it} | {m} | {gap} | {cost} | {_note(r)} |"
        )
    L_ += [
        "",
        "## Ratios t_peer / t_torchslq (same run; > 1 means torchslq is faster)",
        "",
        "| problem | B | torchslq | peer | ratio | note |",
        "|---|---|---|---|---|---|",
    ]
    for q in rat:
        n = []
        if q["peer_extrapolated"]:
            n.append("peer extrapolated")
        if not q["both_match"]:
            n.append("costs do not all match")
        L_.append(
            f"| {q['problem']} | {q['B']} | {q['torchslq']} | {q['peer']} | "
            f"{q['ratio']:.2f} | {', '.join(n)} |"
        )
    return "\n".join(L_) + "\n"


def versions() -> dict[str, str]:
    return package_versions("torch", "mpc", "crocoddyl", "casadi", "numpy")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batches", default="1,64,512")
    ap.add_argument("--problems", default="cartpole,unicycle")
    ap.add_argument("--peers", default="casadi,crocoddyl,mpc")
    ap.add_argument("--cap", type=float, default=180.0, help="seconds per peer configuration")
    ap.add_argument("--max-iter", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument(
        "--name",
        default="peers",
        help="results file stem: <out>/<name>.{json,md} (peers_cartpole, peers_unicycle, peers_b1, ...)",
    )
    ap.add_argument(
        "--repeats", type=int, default=1, help="unicycle: runs per solver, median reported"
    )
    args = ap.parse_args(argv)
    args.batches = [int(b) for b in args.batches.split(",")]
    args.peers = set(args.peers.split(","))
    torch.set_num_threads(1)
    torch.set_default_dtype(torch.float64)
    meta = {
        "command": "python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *sys.argv[1:]]),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "torch": torch.__version__,
        "versions": versions(),
        "load_start": load(),
        "cap_s": args.cap,
        "rtol": RTOL,
    }
    print(meta["command"], "| load", meta["load_start"], flush=True)
    # warm-up (first-call overheads of torch.func etc.)
    p, x = cartpole_swingup(2, seed=123)
    for mk in torchslq_solvers(3).values():
        mk().solve(p, x)
    rows: list[dict] = []
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    def save():  # after every configuration, so a stopped run keeps what it measured
        meta["load_end"] = load()
        rat = ratios(rows)
        (out / f"{args.name}.json").write_text(
            json.dumps({"meta": meta, "rows": rows, "ratios": rat}, indent=1, default=float)
        )
        (out / f"{args.name}.md").write_text(markdown(meta, rows, rat))

    global SAVE
    SAVE = save
    probs = args.problems.split(",")
    if "unicycle" in probs:
        bench_unicycle(args, rows)
    if "cartpole" in probs:
        bench_cartpole(args, rows)
    save()
    print(f"wrote {out / (args.name + '.json')} and {out / (args.name + '.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
