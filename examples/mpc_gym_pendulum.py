"""Model-based receding-horizon control of gymnasium's ``Pendulum-v1`` with ``torchslq.MPC``.

The environment is gymnasium's (``pip install gymnasium``), not ours: ``theta = 0`` is
*upright* there, the torque is clipped to ``|u| <= 2``, ``dt = 0.05``, the speed is
clipped to 8 rad/s, and the reward is ``-(angle_normalize(theta)^2 + 0.1 theta_dot^2 +
0.001 u^2)`` per step; an episode is 200 steps from ``theta ~ U(-pi, pi)``,
``theta_dot ~ U(-1, 1)``. The controllers see only the observation
``[cos theta, sin theta, theta_dot]`` and use the state ``x = [atan2(sin, cos), theta_dot]``.

Three controllers, each on the same 20 seeds (``env.reset(seed=s)``):

* ``random``: uniform random torques (the action space seeded with ``s``);
* ``mpc_analytic``: ``torchslq.MPC`` with the pendulum written to match gymnasium's
  equations (semi-implicit Euler, ``theta_dot' = theta_dot + (3 g / (2 l) sin theta +
  3 / (m l^2) u) dt``, ``theta' = theta + theta_dot' dt``, g = 10; the speed clip is left
  out of the model);
* ``mpc_learned``: the same MPC with an MLP dynamics model (``[cos, sin, theta_dot, u]``
  -> ``[dtheta, dtheta_dot]``, residual) trained by plain supervised regression on
  transitions of the environment under a random policy (episodes from the
  environment's own random resets); nothing of the analytic model is used;
* ``mpc_finetuned``: that model fine-tuned *through the MPC layer* on plan consistency
  (:func:`finetune_model`: the environment, started in the planned-from state, is driven
  by the MPC's planned controls, and the squared difference between the planned and the
  real states is backpropagated through ``MPC(backward="implicit_gn")`` into the MLP).

Both MPCs minimise the environment's own cost (the negative reward, with the angle
wrapped) over a horizon of ``T`` steps plus the same terms as a terminal cost, with
``u_min=-2, u_max=2`` (iLQR with box constraints), warm-started by shifting the previous
solution (``MPC.step``); all seeds are controlled in one batched solve per time step.

Output: episode returns (mean ± std over the seeds) beside the random policy, printed
and written to ``benchmarks/results/mpc_gym_pendulum.{json,md}``; TensorBoard logs (model
training loss, per-seed returns) and figures (returns per seed, angle trajectories)
under ``runs/mpc_gym_pendulum/``.

    python examples/mpc_gym_pendulum.py                  # 20 seeds, 200 steps
    python examples/mpc_gym_pendulum.py --quick          # 2 seeds, 60 steps, small model
    tensorboard --logdir runs/mpc_gym_pendulum
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from torchslq import ILQR, MPC, Cost, Dynamics

MAX_TORQUE = 2.0
DT = 0.05
CONTROLLERS = ("random", "mpc_analytic", "mpc_learned", "mpc_finetuned")


def wrap(a: Tensor) -> Tensor:
    """Angle in ``[-pi, pi)`` (gymnasium's ``angle_normalize``)."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


class GymPendulumModel(Dynamics):
    """gymnasium ``Pendulum-v1``'s step (without the 8 rad/s speed clip), ``theta = 0`` up."""

    state_dim = 2
    control_dim = 1

    def __init__(self, g: float = 10.0, m: float = 1.0, l: float = 1.0, dt: float = DT):
        super().__init__()
        self.g, self.m, self.l, self.dt = g, m, l, dt

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        th, thd = x[..., 0], x[..., 1]
        acc = 3 * self.g / (2 * self.l) * torch.sin(th) + 3.0 / (self.m * self.l**2) * u[..., 0]
        thd_next = thd + acc * self.dt
        return torch.stack([th + thd_next * self.dt, thd_next], dim=-1)


class MLPPendulumModel(Dynamics):
    """Learned model ``x' = x + scale * net([cos th, sin th, thd / 8, u / 2])``."""

    state_dim = 2
    control_dim = 1

    def __init__(self, hidden: int = 64):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(4, hidden),
            nn.Tanh(),
            nn.Linear(hidden, hidden),
            nn.Tanh(),
            nn.Linear(hidden, 2),
        ).double()
        self.register_buffer("scale", torch.ones(2, dtype=torch.float64))

    def features(self, x: Tensor, u: Tensor) -> Tensor:
        th, thd = x[..., 0], x[..., 1]
        return torch.stack([torch.cos(th), torch.sin(th), thd / 8.0, u[..., 0] / MAX_TORQUE], -1)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return x + self.scale * self.net(self.features(x, u))


def gym_cost(terminal_weight: float = 1.0) -> Cost:
    """The environment's cost (negative reward) as a stage cost, and its state part
    (times ``terminal_weight``) as the terminal cost."""

    def stage(x: Tensor, u: Tensor, t: Tensor) -> Tensor:
        return wrap(x[..., 0]) ** 2 + 0.1 * x[..., 1] ** 2 + 0.001 * u[..., 0] ** 2

    def terminal(x: Tensor) -> Tensor:
        return terminal_weight * (wrap(x[..., 0]) ** 2 + 0.1 * x[..., 1] ** 2)

    return Cost(stage, terminal, state_dim=2, control_dim=1)


def make_mpc(model: Dynamics, horizon: int, max_iter: int, tol: float) -> MPC:
    return MPC(
        model,
        gym_cost(),
        horizon,
        solver=ILQR(max_iter=max_iter, tol=tol, progress=False),
        u_min=-MAX_TORQUE,
        u_max=MAX_TORQUE,
        warm_start="shift",
    )


def obs_to_state(obs: np.ndarray) -> Tensor:
    """``[cos, sin, thd] (N, 3)`` -> ``[theta, theta_dot] (N, 2)`` float64."""
    th = np.arctan2(obs[:, 1], obs[:, 0])
    return torch.tensor(np.stack([th, obs[:, 2]], -1), dtype=torch.float64)


def run_episodes(controller: str, seeds: list[int], steps: int, mpc: MPC | None = None):
    """Run one episode per seed, all seeds in lockstep (one batched MPC solve per step).

    Returns ``(returns (N,), states (N, steps+1, 2), actions (N, steps), seconds,
    mean solver iterations per step)``."""
    import gymnasium as gym

    envs = [gym.make("Pendulum-v1") for _ in seeds]
    obs = np.stack([env.reset(seed=s)[0] for env, s in zip(envs, seeds, strict=True)])
    for env, s in zip(envs, seeds, strict=True):
        env.action_space.seed(s)
    N = len(seeds)
    returns = np.zeros(N)
    states = [obs_to_state(obs)]
    actions = []
    iters = []
    if mpc is not None:
        mpc.reset()
    t0 = time.perf_counter()
    for _ in range(steps):
        if controller == "random":
            a = np.stack([env.action_space.sample() for env in envs]).astype(np.float32)
        else:
            with torch.no_grad():
                a = mpc.step(states[-1]).numpy().astype(np.float32)
            iters.append(mpc.last_result.iterations.double().mean().item())
        for i, env in enumerate(envs):
            o, r, terminated, truncated, _ = env.step(a[i])
            obs[i] = o
            returns[i] += r
        states.append(obs_to_state(obs))
        actions.append(a[:, 0])
    wall = time.perf_counter() - t0
    for env in envs:
        env.close()
    return (
        returns,
        torch.stack(states, 1).numpy(),
        np.stack(actions, 1),
        wall,
        float(np.mean(iters)) if iters else 0.0,
    )


def collect_transitions(episodes: int, steps: int, seed: int):
    """Random-policy transitions ``(x, u, x_next)`` from the environment's resets."""
    import gymnasium as gym

    env = gym.make("Pendulum-v1")
    env.action_space.seed(seed)
    xs, us, xn = [], [], []
    for e in range(episodes):
        obs, _ = env.reset(seed=seed + e)
        for _ in range(steps):
            a = env.action_space.sample()
            nobs, *_ = env.step(a)
            xs.append(obs)
            us.append(a)
            xn.append(nobs)
            obs = nobs
    env.close()
    x = obs_to_state(np.stack(xs))
    x1 = obs_to_state(np.stack(xn))
    u = torch.tensor(np.stack(us), dtype=torch.float64)
    return x, u, x1


def train_model(args, writer) -> tuple[MLPPendulumModel, dict]:
    """Supervised one-step regression of the MLP on random-policy transitions."""
    t0 = time.perf_counter()
    x, u, x1 = collect_transitions(args.data_episodes, args.data_steps, seed=10_000)
    target = torch.stack([wrap(x1[:, 0] - x[:, 0]), x1[:, 1] - x[:, 1]], -1)
    gen = torch.Generator().manual_seed(args.seed)
    perm = torch.randperm(x.shape[0], generator=gen)
    n_val = max(1, x.shape[0] // 10)
    val, tr = perm[:n_val], perm[n_val:]
    torch.manual_seed(args.seed)
    model = MLPPendulumModel(args.hidden)
    model.scale.copy_(target[tr].std(0))
    opt = torch.optim.Adam(model.net.parameters(), lr=args.model_lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.model_iters)

    def mse(idx: Tensor) -> Tensor:
        pred = model(x[idx], u[idx]) - x[idx]
        return (((pred - target[idx]) / model.scale) ** 2).mean()

    for it in range(args.model_iters):
        idx = tr[torch.randint(len(tr), (min(args.model_batch, len(tr)),), generator=gen)]
        loss = mse(idx)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if it % 50 == 0 or it == args.model_iters - 1:
            writer.add_scalar("model/train_mse_normalized", loss.item(), it)
    with torch.no_grad():
        pred = model(x[val], u[val]) - x[val]
        rmse = ((pred - target[val]) ** 2).mean(0).sqrt()
        analytic = GymPendulumModel()(x[val], u[val]) - x[val]
        rmse_analytic = ((analytic - target[val]) ** 2).mean(0).sqrt()
        val_mse = mse(val).item()
    writer.add_scalar("model/val_mse_normalized", val_mse, args.model_iters)
    info = {
        "transitions": int(x.shape[0]),
        "train_iters": args.model_iters,
        "val_rmse_dtheta": rmse[0].item(),
        "val_rmse_dthetadot": rmse[1].item(),
        "analytic_model_val_rmse_dtheta": rmse_analytic[0].item(),
        "analytic_model_val_rmse_dthetadot": rmse_analytic[1].item(),
        "val_mse_normalized": val_mse,
        "time_s": time.perf_counter() - t0,
    }
    return model, info


def real_rollout(env, x0: Tensor, u: Tensor) -> Tensor:
    """States ``(B, T+1, 2)`` of the environment started in ``x0`` (its ``state`` set
    directly) under the open-loop controls ``u (B, T, 1)``."""
    out = []
    for i in range(x0.shape[0]):
        env.reset(seed=0)
        env.unwrapped.state = x0[i].numpy().copy()
        xs = [x0[i]]
        for t in range(u.shape[1]):
            obs, *_ = env.step(u[i, t].numpy().astype(np.float32))
            xs.append(obs_to_state(obs[None])[0])
        out.append(torch.stack(xs))
    return torch.stack(out)


def finetune_model(model: MLPPendulumModel, args, writer) -> tuple[MLPPendulumModel, dict]:
    """Fine-tune the learned model *through the MPC layer* on plan consistency.

    For a batch of states, the MPC plans ``(x_hat, u_hat)`` with the learned model
    (gradients through the plan); the environment is started in the same states and
    driven open loop by ``u_hat``; the loss is the mean squared (angle-wrapped)
    difference between the planned and the real states, so the model is corrected where
    the planner takes it. ``backward="implicit_gn"``: with the exact Hessian, a plan at
    which the Hessian of the Lagrangian is not positive definite makes the layer's
    output (and every shared gradient) NaN (reported to the MPC layer's owner).
    """
    import copy

    import gymnasium as gym

    model = copy.deepcopy(model).requires_grad_(True)
    mpc = MPC(
        model,
        gym_cost(),
        args.horizon,
        solver=ILQR(max_iter=args.max_iter, tol=args.tol, progress=False),
        u_min=-MAX_TORQUE,
        u_max=MAX_TORQUE,
        backward="implicit_gn",
        warm_start=False,
        unconverged="zero",
    )
    env = gym.make("Pendulum-v1")
    gen = torch.Generator().manual_seed(args.seed + 1)
    opt = torch.optim.Adam(model.net.parameters(), lr=args.finetune_lr)
    losses = []
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # unconverged plans: zero gradient
        for ep in range(args.finetune_epochs):
            xs = torch.stack(
                [
                    (torch.rand(args.finetune_batch, generator=gen, dtype=torch.float64) * 2 - 1)
                    * math.pi,
                    (torch.rand(args.finetune_batch, generator=gen, dtype=torch.float64) * 2 - 1)
                    * 2.0,
                ],
                -1,
            )
            x, u = mpc(xs)
            xr = real_rollout(env, xs, u.detach())
            err = torch.stack([wrap(x[..., 0] - xr[..., 0]), x[..., 1] - xr[..., 1]], -1)
            loss = (err**2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
            writer.add_scalar("finetune/plan_consistency_mse", loss.item(), ep)
    env.close()
    info = {
        "epochs": args.finetune_epochs,
        "batch": args.finetune_batch,
        "loss_first": losses[0] if losses else None,
        "loss_last": losses[-1] if losses else None,
        "loss_first5_mean": float(np.mean(losses[:5])) if losses else None,
        "loss_last5_mean": float(np.mean(losses[-5:])) if losses else None,
        "time_s": time.perf_counter() - t0,
    }
    return model.requires_grad_(False), info


def plot(results: dict, trajs: dict, seeds: list[int], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    fig, axes = plt.subplots(1, 1 + len(names), figsize=(5 * (1 + len(names)), 4))
    w = 0.8 / len(names)
    for j, name in enumerate(names):
        axes[0].bar(np.arange(len(seeds)) + j * w, results[name]["returns"], w, label=name)
    axes[0].set_xlabel("seed")
    axes[0].set_ylabel("episode return")
    axes[0].legend(fontsize=8)
    for ax, name in zip(axes[1:], names, strict=True):
        th = trajs[name][:, :, 0]
        t = np.arange(th.shape[1]) * DT
        for i in range(min(6, th.shape[0])):
            ax.plot(t, np.abs(th[i]), lw=1)
        ax.set_title(f"{name}: |theta| (0 = upright)")
        ax.set_xlabel("t [s]")
        ax.set_ylim(0, math.pi + 0.1)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_results(summary: dict, args, stem: Path) -> None:
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json.dumps(summary, indent=2))
    m = summary["meta"]
    lines = [
        "# gymnasium Pendulum-v1 controlled by torchslq.MPC",
        "",
        f"`{m['command']}` — gymnasium {m['gymnasium']}, {m['n_seeds']} seeds "
        f"({m['seeds'][0]}..{m['seeds'][-1]}), {m['steps']} steps per episode; MPC horizon "
        f"T = {m['horizon']}, iLQR max_iter = {m['max_iter']}, tol = {m['tol']:g}, "
        "|u| <= 2, warm start by shift, one batched solve per step for all seeds.",
        "",
        "| controller | return mean ± std | min | max | time [s] | mean iLQR iters / step |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in summary["controllers"].items():
        ret = np.array(r["returns"])
        lines.append(
            f"| {name} | {ret.mean():.1f} ± {ret.std():.1f} | {ret.min():.1f} | "
            f"{ret.max():.1f} | {r['time_s']:.1f} | "
            + ("-" if name == "random" else f"{r['mean_iters']:.2f}")
            + " |"
        )
    if "model" in summary:
        mi = summary["model"]
        lines += [
            "",
            f"Learned model: MLP 4-{args.hidden}-{args.hidden}-2 (tanh), "
            f"{mi['transitions']} random-policy transitions, {mi['train_iters']} Adam steps "
            f"({mi['time_s']:.1f} s). Held-out one-step RMSE: dtheta "
            f"{mi['val_rmse_dtheta']:.2e}, dtheta_dot {mi['val_rmse_dthetadot']:.2e} (the "
            f"analytic model, which omits the speed clip: {mi['analytic_model_val_rmse_dtheta']:.2e}, "
            f"{mi['analytic_model_val_rmse_dthetadot']:.2e}).",
        ]
    if summary.get("finetune"):
        fi = summary["finetune"]
        lines += [
            "",
            f"Fine-tuning through the MPC layer (`mpc_finetuned`): {fi['epochs']} Adam steps, "
            f"batches of {fi['batch']} random states, backward='implicit_gn'; plan-consistency "
            f"MSE {fi['loss_first5_mean']:.3e} (mean of the first 5 steps) -> "
            f"{fi['loss_last5_mean']:.3e} (last 5) ({fi['time_s']:.1f} s).",
        ]
    lines += [
        "",
        "Mean iLQR iterations per step can be below 1: once the pendulum is balanced, the "
        "shifted warm start already meets the tolerance (0 iterations).",
        "",
        "Per-seed returns are in the JSON file.",
        "",
    ]
    stem.with_suffix(".md").write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=200, help="episode length (gym's is 200)")
    ap.add_argument("--horizon", type=int, default=20)
    ap.add_argument("--max-iter", type=int, default=30)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument(
        "--controllers", default=",".join(CONTROLLERS), help=f"comma list of {CONTROLLERS}"
    )
    ap.add_argument("--data-episodes", type=int, default=100)
    ap.add_argument("--data-steps", type=int, default=50)
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--model-iters", type=int, default=3000)
    ap.add_argument("--model-batch", type=int, default=256)
    ap.add_argument("--model-lr", type=float, default=3e-3)
    ap.add_argument("--seed", type=int, default=0, help="model training seed")
    ap.add_argument("--finetune-epochs", type=int, default=30)
    ap.add_argument("--finetune-batch", type=int, default=32)
    ap.add_argument("--finetune-lr", type=float, default=1e-3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="runs/mpc_gym_pendulum")
    ap.add_argument(
        "--results",
        default=None,
        help="results path stem (default benchmarks/results/mpc_gym_pendulum; none with --quick)",
    )
    ap.add_argument("--quick", action="store_true", help="2 seeds, 60 steps, small model")
    args = ap.parse_args(argv)
    cmd_args = list(argv) if argv is not None else __import__("sys").argv[1:]
    if args.quick:
        args.seeds, args.steps, args.horizon, args.max_iter = 2, 60, 15, 20
        args.data_episodes, args.data_steps, args.model_iters, args.hidden = 20, 50, 300, 32
    torch.set_num_threads(args.threads)
    import gymnasium
    from torch.utils.tensorboard import SummaryWriter

    controllers = [c.strip() for c in args.controllers.split(",") if c.strip()]
    for c in controllers:
        if c not in CONTROLLERS:
            raise ValueError(f"unknown controller {c!r}; choose from {CONTROLLERS}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    writer = SummaryWriter(log_dir=str(out))

    summary: dict = {
        "meta": {
            "command": "python examples/mpc_gym_pendulum.py " + " ".join(cmd_args),
            "gymnasium": gymnasium.__version__,
            "n_seeds": len(seeds),
            "seeds": seeds,
            "steps": args.steps,
            "horizon": args.horizon,
            "max_iter": args.max_iter,
            "tol": args.tol,
        },
        "controllers": {},
    }
    trajs = {}
    for name in controllers:
        mpc = None
        if name == "mpc_analytic":
            mpc = make_mpc(GymPendulumModel(), args.horizon, args.max_iter, args.tol)
        elif name == "mpc_learned":
            model, info = train_model(args, writer)
            summary["model"] = info
            print(
                f"learned model: {info['transitions']} transitions, held-out RMSE "
                f"dtheta {info['val_rmse_dtheta']:.2e}, dtheta_dot "
                f"{info['val_rmse_dthetadot']:.2e} ({info['time_s']:.1f} s)",
                flush=True,
            )
            mpc = make_mpc(model.requires_grad_(False), args.horizon, args.max_iter, args.tol)
        elif name == "mpc_finetuned":
            if "model" not in summary:
                model, summary["model"] = train_model(args, writer)
            tuned, finfo = finetune_model(model, args, writer)
            summary["finetune"] = finfo
            print(
                f"fine-tuned through the MPC layer: plan-consistency MSE "
                f"{finfo['loss_first5_mean']:.3e} (first 5 epochs) -> "
                f"{finfo['loss_last5_mean']:.3e} (last 5) ({finfo['time_s']:.1f} s)",
                flush=True,
            )
            mpc = make_mpc(tuned, args.horizon, args.max_iter, args.tol)
        ret, states, actions, wall, iters = run_episodes(name, seeds, args.steps, mpc)
        trajs[name] = states
        summary["controllers"][name] = {
            "returns": ret.tolist(),
            "mean": float(ret.mean()),
            "std": float(ret.std()),
            "time_s": wall,
            "mean_iters": iters,
            "max_abs_action": float(np.abs(actions).max()),
        }
        for s, r in zip(seeds, ret, strict=True):
            writer.add_scalar(f"return/{name}", r, s)
        writer.add_histogram(f"returns/{name}", ret, 0)
        print(f"{name}: return {ret.mean():.1f} ± {ret.std():.1f} ({wall:.1f} s)", flush=True)
    writer.close()
    plot(summary["controllers"], trajs, seeds, out / "returns.png")

    print(
        f"\ngymnasium Pendulum-v1, {len(seeds)} seeds x {args.steps} steps, MPC T = {args.horizon}"
    )
    print("| controller | return mean ± std | min | max | time [s] |")
    print("|---|---|---|---|---|")
    for name, r in summary["controllers"].items():
        ret = np.array(r["returns"])
        print(
            f"| {name} | {ret.mean():.1f} ± {ret.std():.1f} | {ret.min():.1f} | {ret.max():.1f} | "
            f"{r['time_s']:.1f} |"
        )
    results = args.results
    if results is None and not args.quick:
        results = "benchmarks/results/mpc_gym_pendulum"
    if results:
        write_results(summary, args, Path(results))
        print(f"\nresults in {results}.json / .md")
    print(f"TensorBoard logs and figure in {out}/ (tensorboard --logdir {out})")
    return summary


if __name__ == "__main__":
    main()
