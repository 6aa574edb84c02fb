"""Distil 10,000 batched cart-pole swing-up solves into a policy network.

The task is :func:`torchslq.tasks.cartpole_swingup` (the iLQR benchmark: point-mass
cart-pole, RK4, dt = 0.05 s, T = 50, cost ``sum 0.01 u^2 + 100 |x_T - [0, pi, 0, 0]|^2``,
initial states ``x0 = [0, 0.05 N(0, 1), 0, 0]``), solved for ``--n`` initial states
(default 10,000) in chunks of ``--chunk`` with a batched solver (DDP by default, or
iLQR; ``compact=True`` so finished elements drop out of the working set). Every time
step of every *converged and successful* solution gives a training pair
``(x_t, u_t)`` (50 pairs per solve).

A policy MLP ``pi(x) -> u`` (inputs ``[s, sin theta, cos theta, s_dot, theta_dot]``;
``--time-input`` adds ``t / T``, since the optimal control of a finite-horizon problem
is time-varying, though on a 1,000-solve run the state-only policy did better: 98.7 %
vs 92.3 % success) is fitted by plain regression, then run *closed loop* on the true
dynamics from fresh initial states of the same distribution (a different seed):
``u_t = pi(x_t)``, ``x_{t+1} = f(x_t, u_t)`` for 50 steps, and scored by the task's criterion
(:func:`torchslq.tasks.swingup_success`: final angle within 0.1 rad of upright). The
optimal solutions from the same fresh states are solved too, for comparison.

Reported (printed, and written to ``benchmarks/results/mpc_distill_cartpole.{json,md}``):
solve time (total and per problem), fraction converged and fraction successful of the
dataset solves, the policy's training/held-out regression error, and the policy's
closed-loop success rate and mean cost (beside the optimal solver's). TensorBoard logs
under ``runs/mpc_distill_cartpole/`` (solver convergence of the first chunk, policy
training loss) and a figure of closed-loop policy rollouts vs optimal trajectories.

    python examples/mpc_distill_cartpole.py                 # n = 10,000
    python examples/mpc_distill_cartpole.py --n 2000        # shorter
    python examples/mpc_distill_cartpole.py --quick         # n = 8, tiny policy
    tensorboard --logdir runs/mpc_distill_cartpole
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch
from torch import Tensor, nn

from torchslq import DDP, ILQR, TensorBoardLogger
from torchslq.tasks import cartpole_swingup, swingup_success

LABELS = ["s [m]", "theta [rad]", "s_dot [m/s]", "theta_dot [rad/s]"]


class Policy(nn.Module):
    """MLP ``(x (..., 4), t/T (...)) -> u (..., 1)``; angle as ``sin, cos``; ``t/T`` is
    ignored unless ``use_time``."""

    def __init__(self, hidden: int = 128, use_time: bool = False):
        super().__init__()
        self.use_time = use_time
        d = 6 if use_time else 5
        self.net = nn.Sequential(
            nn.Linear(d, hidden),
            nn.Tanh(),
            nn.Linear(hidden, hidden),
            nn.Tanh(),
            nn.Linear(hidden, hidden),
            nn.Tanh(),
            nn.Linear(hidden, 1),
        )
        self.register_buffer("u_scale", torch.ones(()))

    def features(self, x: Tensor, tau: Tensor) -> Tensor:
        f = [x[..., 0], torch.sin(x[..., 1]), torch.cos(x[..., 1]), x[..., 2] / 3, x[..., 3] / 10]
        if self.use_time:
            f.append(tau)
        return torch.stack(f, -1)

    def forward(self, x: Tensor, tau: Tensor) -> Tensor:
        return self.u_scale * self.net(self.features(x, tau))


def make_solver(name: str, max_iter: int, tol: float):
    cls = {"ddp": DDP, "ilqr": ILQR}[name]
    return cls(max_iter=max_iter, tol=tol, compact=True, progress=False)


def solve_dataset(args, out: Path) -> dict:
    """Solve ``args.n`` swing-ups in chunks; return states, controls, masks and timing."""
    xs, us, conv, succ, costs, iters = [], [], [], [], [], []
    solver = make_solver(args.solver, args.max_iter, args.tol)
    t_total = 0.0
    done = 0
    chunk_id = 0
    while done < args.n:
        b = min(args.chunk, args.n - done)
        # a distinct seed per chunk: the task draws x0 from its own seeded generator
        problem, x0 = cartpole_swingup(b, horizon=args.horizon, seed=args.seed + chunk_id)
        logger = TensorBoardLogger(out / "solver_chunk0", dt=0.05) if chunk_id == 0 else None
        t0 = time.perf_counter()
        res = solver.solve(problem, x0, logger=logger)
        t_total += time.perf_counter() - t0
        if logger is not None:
            logger.close()
        xs.append(res.x)
        us.append(res.u)
        conv.append(res.converged)
        succ.append(swingup_success(res.x, angle_index=1))
        costs.append(res.cost)
        iters.append(res.iterations)
        done += b
        chunk_id += 1
        print(
            f"  solved {done}/{args.n} ({t_total:.1f} s; chunk converged "
            f"{res.converged.double().mean().item():.3f})",
            flush=True,
        )
    return {
        "x": torch.cat(xs),
        "u": torch.cat(us),
        "converged": torch.cat(conv),
        "success": torch.cat(succ),
        "cost": torch.cat(costs),
        "iterations": torch.cat(iters),
        "time_s": t_total,
    }


def pairs(x: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """State-action pairs ``(x_t (N, 4), t/T (N,), u_t (N, 1))`` of trajectories."""
    B, T = u.shape[:2]
    tau = (torch.arange(T, dtype=x.dtype) / T).expand(B, T)
    return x[:, :T].reshape(-1, 4), tau.reshape(-1), u.reshape(-1, 1)


def train_policy(args, X, tau, U, writer) -> tuple[Policy, dict]:
    gen = torch.Generator().manual_seed(args.seed)
    N = X.shape[0]
    perm = torch.randperm(N, generator=gen)
    n_val = max(1, N // 20)
    val, tr = perm[:n_val], perm[n_val:]
    torch.manual_seed(args.seed)
    X, tau, U = X.float(), tau.float(), U.float()
    policy = Policy(args.hidden, use_time=args.time_input)
    policy.u_scale.fill_(U[tr].std().item())
    opt = torch.optim.Adam(policy.parameters(), lr=args.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.iters)
    t0 = time.perf_counter()
    for it in range(args.iters):
        idx = tr[torch.randint(len(tr), (min(args.batch, len(tr)),), generator=gen)]
        loss = ((policy(X[idx], tau[idx]) - U[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if it % 100 == 0 or it == args.iters - 1:
            writer.add_scalar("policy/train_mse", loss.item(), it)
    with torch.no_grad():
        val_mse = ((policy(X[val], tau[val]) - U[val]) ** 2).mean().item()
        tr_sub = tr[:n_val]
        train_mse = ((policy(X[tr_sub], tau[tr_sub]) - U[tr_sub]) ** 2).mean().item()
    writer.add_scalar("policy/val_mse", val_mse, args.iters)
    return policy.double(), {
        "pairs": N,
        "train_mse": train_mse,
        "val_mse": val_mse,
        "u_var": U.var().item(),
        "time_s": time.perf_counter() - t0,
    }


@torch.no_grad()
def closed_loop(policy: Policy, problem, x0: Tensor) -> tuple[Tensor, Tensor]:
    """Roll the policy out on the true dynamics: ``(x (B, T+1, 4), u (B, T, 1))``."""
    T = problem.horizon
    f = problem.dynamics
    x = [x0]
    u = []
    for t in range(T):
        tau = torch.full(x0.shape[:1], t / T, dtype=x0.dtype)
        ut = policy(x[-1], tau)
        u.append(ut)
        x.append(f(x[-1], ut))
    return torch.stack(x, 1), torch.stack(u, 1)


def figure(xp: Tensor, xo: Tensor | None, path: Path, dt: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = torch.arange(xp.shape[1]) * dt
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.5))
    for j, ax in enumerate(axes):
        for i in range(min(4, xp.shape[0])):
            (line,) = ax.plot(t, xp[i, :, j], "--", lw=1.2)
            if xo is not None:
                ax.plot(t, xo[i, :, j], color=line.get_color(), lw=1.5, alpha=0.6)
        ax.set_xlabel("t [s]")
        ax.set_title(LABELS[j])
    axes[0].plot([], [], "k-", label="optimal (DDP/iLQR)")
    axes[0].plot([], [], "k--", label="distilled policy, closed loop")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.1f}%"


def _num(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.4f}"


def write_results(summary: dict, stem: Path) -> None:
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json.dumps(summary, indent=2))
    m, d, p, e = summary["meta"], summary["dataset"], summary["policy"], summary["eval"]
    lines = [
        "# Cart-pole swing-ups distilled into a policy network",
        "",
        f"`{m['command']}` — torch {m['torch']}, {m['threads']} thread(s), float64 solves; "
        "a shared, loaded 2-core box, so times are indicative only.",
        "",
        "## Dataset: batched optimal solves (torchslq.tasks cart-pole swing-up, T = 50)",
        "",
        "| n solved | solver | chunk | time [s] | per problem [ms] | converged | successful "
        "| iters mean/max | cost mean |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {d['n']} | {m['solver']} (compact, tol {m['tol']:g}, max_iter {m['max_iter']}) | "
        f"{m['chunk']} | {d['time_s']:.1f} | {1000 * d['time_s'] / d['n']:.1f} | "
        f"{100 * d['converged']:.2f}% | {100 * d['success']:.2f}% | "
        f"{d['iters_mean']:.1f}/{d['iters_max']} | {d['cost_mean']:.4f} |",
        "",
        f"Training pairs: {p['pairs']} (converged and successful solves x 50 steps).",
        "",
        "## Policy (MLP, closed loop on the true dynamics)",
        "",
        f"Inputs {'[s, sin th, cos th, s_dot, th_dot, t/T]' if m['use_time'] else '[s, sin th, cos th, s_dot, th_dot]'}, "
        f"3 x {m['hidden']} tanh, {m['iters']} Adam steps of batch {m['batch']} "
        f"({p['time_s']:.1f} s). Regression MSE on u: train {p['train_mse']:.3e}, held out "
        f"{p['val_mse']:.3e} (variance of u: {p['u_var']:.3e}).",
        "",
        "| fresh initial states | policy success | policy cost mean | optimal success "
        "| optimal cost mean |",
        "|---|---|---|---|---|",
        f"| {e['n']} (seed {e['seed']}) | {100 * e['policy_success']:.1f}% | "
        f"{e['policy_cost_mean']:.4f} | {_pct(e['optimal_success'])} | "
        f"{_num(e['optimal_cost_mean'])} |",
        "",
        "Success: the task's criterion, final angle within 0.1 rad of upright "
        "(`torchslq.tasks.swingup_success`).",
        "",
    ]
    if m.get("note"):
        lines += [m["note"], ""]
    stem.with_suffix(".md").write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=10_000, help="swing-ups to solve")
    ap.add_argument("--chunk", type=int, default=1000, help="batch size per solve")
    ap.add_argument("--solver", choices=["ddp", "ilqr"], default="ddp")
    ap.add_argument("--max-iter", type=int, default=300)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--horizon", type=int, default=50)
    ap.add_argument("--hidden", type=int, default=128)
    ap.add_argument("--iters", type=int, default=16000, help="policy Adam steps")
    ap.add_argument("--batch", type=int, default=512, help="policy minibatch")
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--time-input", action="store_true", help="policy also takes t/T")
    ap.add_argument("--n-eval", type=int, default=1000, help="fresh initial states")
    ap.add_argument(
        "--no-reference", action="store_true", help="skip the optimal solves of the eval states"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eval-seed", type=int, default=123_456)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="runs/mpc_distill_cartpole")
    ap.add_argument(
        "--results",
        default=None,
        help="results stem (default benchmarks/results/mpc_distill_cartpole; none with --quick)",
    )
    ap.add_argument(
        "--dataset", default="", help="cache file: load the solves from it, or save them to it"
    )
    ap.add_argument("--note", default="", help="a line added to the results file")
    ap.add_argument(
        "--quick", action="store_true", help="n = 8, small policy, 300 steps, no reference solve"
    )
    args = ap.parse_args(argv)
    cmd_args = list(argv) if argv is not None else __import__("sys").argv[1:]
    if args.quick:
        args.n, args.chunk, args.n_eval, args.no_reference = 8, 8, 64, True
        args.hidden, args.iters, args.batch = 32, 300, 256
    torch.set_num_threads(args.threads)
    from torch.utils.tensorboard import SummaryWriter

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    writer = SummaryWriter(log_dir=str(out / "policy"))

    if args.dataset and Path(args.dataset).exists():
        data = torch.load(args.dataset, weights_only=False)
        if data["x"].shape[0] != args.n:
            raise ValueError(f"{args.dataset} holds {data['x'].shape[0]} solves, not --n {args.n}")
        print(f"loaded {args.n} solves from {args.dataset} (solve time {data['time_s']:.1f} s)")
        args.note = (
            f"The {args.n} solves were loaded from the cache `{args.dataset}` written by an "
            "earlier run of this script (same solver settings, --dataset); the solve time "
            "is that run's. " + args.note
        ).strip()
    else:
        print(f"solving {args.n} cart-pole swing-ups ({args.solver}, chunks of {args.chunk})")
        data = solve_dataset(args, out)
        if args.dataset:
            torch.save({k: v for k, v in data.items() if k != "problem"}, args.dataset)
    keep = data["converged"] & data["success"]
    X, tau, U = pairs(data["x"][keep], data["u"][keep])
    policy, pinfo = train_policy(args, X, tau, U, writer)

    problem, x0_eval = cartpole_swingup(args.n_eval, horizon=args.horizon, seed=args.eval_seed)
    xp, up = closed_loop(policy, problem, x0_eval)
    pol_succ = swingup_success(xp, angle_index=1)
    pol_cost = problem.cost(xp, up)
    if args.no_reference:
        ref_x, ref_succ, ref_cost = None, None, None
    else:
        ref = make_solver(args.solver, args.max_iter, args.tol).solve(problem, x0_eval)
        ref_x, ref_cost = ref.x, ref.cost.mean().item()
        ref_succ = swingup_success(ref.x, angle_index=1).double().mean().item()
    writer.add_scalar("eval/policy_success", pol_succ.double().mean().item(), 0)
    writer.close()
    figure(xp[:4], None if ref_x is None else ref_x[:4], out / "rollouts.png", problem.dynamics.dt)

    d = {
        "n": args.n,
        "time_s": data["time_s"],
        "converged": data["converged"].double().mean().item(),
        "success": data["success"].double().mean().item(),
        "converged_and_success": keep.double().mean().item(),
        "iters_mean": data["iterations"].double().mean().item(),
        "iters_max": int(data["iterations"].max()),
        "cost_mean": data["cost"].mean().item(),
    }
    e = {
        "n": args.n_eval,
        "seed": args.eval_seed,
        "policy_success": pol_succ.double().mean().item(),
        "policy_cost_mean": pol_cost.mean().item(),
        "policy_cost_median": pol_cost.median().item(),
        "optimal_success": ref_succ,
        "optimal_cost_mean": ref_cost,
        "final_angle_error_median": (
            (torch.remainder(xp[:, -1, 1], 2 * math.pi) - math.pi).abs().median().item()
        ),
    }
    summary = {
        "meta": {
            "command": "python examples/mpc_distill_cartpole.py " + " ".join(cmd_args),
            "torch": torch.__version__,
            "threads": args.threads,
            "solver": args.solver,
            "tol": args.tol,
            "max_iter": args.max_iter,
            "chunk": args.chunk,
            "hidden": args.hidden,
            "iters": args.iters,
            "batch": args.batch,
            "use_time": args.time_input,
            "note": args.note,
            "dataset_cache": args.dataset,
        },
        "dataset": d,
        "policy": pinfo,
        "eval": e,
    }
    print(
        f"\ndataset: {d['n']} solves in {d['time_s']:.1f} s "
        f"({1000 * d['time_s'] / d['n']:.1f} ms each), converged {100 * d['converged']:.2f}%, "
        f"successful {100 * d['success']:.2f}%"
    )
    print(
        f"policy: {pinfo['pairs']} pairs, MSE train {pinfo['train_mse']:.3e} / held out "
        f"{pinfo['val_mse']:.3e} (var u {pinfo['u_var']:.3e})"
    )
    line = (
        f"closed loop on {e['n']} fresh states: policy success {100 * e['policy_success']:.1f}% "
        f"(cost {e['policy_cost_mean']:.3f})"
    )
    if ref_succ is not None:
        line += f", optimal success {100 * ref_succ:.1f}% (cost {ref_cost:.3f})"
    print(line)
    results = args.results
    if results is None and not args.quick:
        results = "benchmarks/results/mpc_distill_cartpole"
    if results:
        write_results(summary, Path(results))
        print(f"results in {results}.json / .md")
    print(f"TensorBoard logs and figure in {out}/ (tensorboard --logdir {out})")
    return summary


if __name__ == "__main__":
    main()
