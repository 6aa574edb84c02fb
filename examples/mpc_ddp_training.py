"""Training through the MPC layer on several processes (``DistributedDataParallel``).

The task of ``examples/mpc_imitation.py`` on more than one process: an expert MPC
(damped pendulum, m = 1, l = 1, b = 0.1, goal angle pi; RK4, dt = 0.05) produced
optimal trajectories ``(x*, u*)`` from ``--batch`` initial states; a learner with the
same structure but unknown mass, length, damping (learned in log space) and goal angle
fits them by minimising the imitation loss

    (1/N) sum_i [ mean_t |u_i - u*_i|^2 + mean_t |x_i - x*_i|^2 ]

of its own :class:`torchslq.MPC` solution (implicit gradients through the solver).

Every process (rank) solves its contiguous shard of the ``N`` problems; the learner is
wrapped in ``torch.nn.parallel.DistributedDataParallel``, which all-reduces (averages)
the parameter gradients after ``backward``. Each rank's loss is its rows' sum times
``world_size / N``, so the averaged gradient is exactly the gradient of the full-batch
loss above, whatever the split (``tests/test_distributed.py`` checks this against one
process). Engine: ``torch.distributed`` with gloo (the model here runs on the CPU; a
model on GPUs would join with NCCL, one device per rank, and ``DistributedDataParallel(
model, device_ids=[local_rank])``).

    torchrun --nproc_per_node 2 examples/mpc_ddp_training.py     # 2 processes
    python examples/mpc_ddp_training.py --local-workers 2        # the same without torchrun
    python examples/mpc_ddp_training.py                          # 1 process
    python examples/mpc_ddp_training.py --quick --local-workers 2

Rank 0 prints the full-batch loss (before the epoch's step) and the learned parameters
every ``--print-every`` epochs and writes ``--out`` (a JSON summary) at the end.
Optimiser: L-BFGS by default (one L-BFGS iteration per epoch, up to ``--max-eval`` solves in its
strong-Wolfe line search; every rank gets the same all-reduced loss and gradient, so
all ranks take the same steps), or Adam (``--optimizer adam``, learning rate ``--lr``
times ``--lr-decay`` per epoch).
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor, nn

from torchslq import ILQR, MPC, QuadraticCost, discretize
from torchslq.distributed import init_from_env, launch, rank_and_world
from torchslq.systems import Pendulum

TRUE = {"mass": 1.0, "length": 1.0, "damping": 0.1, "goal": math.pi}
INIT = {"mass": 1.5, "length": 0.8, "damping": 0.3, "goal": 2.8}
F64 = torch.float64


class LearnablePendulum(Pendulum):
    """``Pendulum`` whose mass, length and damping are ``exp`` of ``nn.Parameter``s."""

    def __init__(self, mass: float, length: float, damping: float, g: float = 9.81):
        nn.Module.__init__(self)
        self.log_mass = nn.Parameter(torch.tensor(math.log(mass), dtype=F64))
        self.log_length = nn.Parameter(torch.tensor(math.log(length), dtype=F64))
        self.log_damping = nn.Parameter(torch.tensor(math.log(damping), dtype=F64))
        self.g = float(g)

    @property
    def mass(self) -> Tensor:
        return self.log_mass.exp()

    @property
    def length(self) -> Tensor:
        return self.log_length.exp()

    @property
    def damping(self) -> Tensor:
        return self.log_damping.exp()


def weights(dt: float) -> tuple[Tensor, Tensor, Tensor]:
    Q = dt * torch.diag(torch.tensor([1.0, 0.1], dtype=F64))
    R = 0.1 * dt * torch.eye(1, dtype=F64)
    Qf = torch.diag(torch.tensor([100.0, 10.0], dtype=F64))
    return Q, R, Qf


class Learner(nn.Module):
    """The learner's MPC; ``forward(x0, u_init) -> (x, u)`` (a plain tuple for DDP)."""

    def __init__(self, dt: float, horizon: int, tol: float = 1e-9):
        super().__init__()
        self.pendulum = LearnablePendulum(INIT["mass"], INIT["length"], INIT["damping"])
        self.goal = nn.Parameter(torch.tensor(INIT["goal"], dtype=F64))
        Q, R, Qf = weights(dt)
        cost = QuadraticCost(Q, R, Qf, x_ref=torch.zeros(2, dtype=F64))
        self.mpc = MPC(
            discretize(self.pendulum, dt, "rk4"),
            cost,
            horizon,
            solver=ILQR(max_iter=200, tol=tol, progress=False),
            warm_start=False,
        )

    def forward(self, x0: Tensor, u_init: Tensor | None = None) -> tuple[Tensor, Tensor]:
        self.mpc.cost.x_ref = torch.stack([self.goal, torch.zeros_like(self.goal)])
        out = self.mpc(x0, u_init=u_init)
        return out.x, out.u

    def values(self) -> dict[str, float]:
        p = self.pendulum
        return {
            "mass": p.mass.item(),
            "length": p.length.item(),
            "damping": p.damping.item(),
            "goal": self.goal.item(),
        }


def expert_data(batch: int, horizon: int, dt: float, seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """``x0 (N, 2)`` and the expert's optimal ``x* (N, T+1, 2)``, ``u* (N, T, 1)``; the
    same on every rank (seeded)."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.rand(batch, 2, generator=g, dtype=F64) * 2 - 1
    dyn = discretize(Pendulum(TRUE["mass"], TRUE["length"], 9.81, TRUE["damping"]), dt, "rk4")
    Q, R, Qf = weights(dt)
    cost = QuadraticCost(Q, R, Qf, x_ref=torch.tensor([TRUE["goal"], 0.0], dtype=F64))
    expert = MPC(dyn, cost, horizon, solver=ILQR(max_iter=500, tol=1e-10, progress=False))
    with torch.no_grad():
        out = expert(x0)
    return x0, out.x, out.u


def shard(batch: int, rank: int, world_size: int) -> slice:
    """The contiguous rows of ``rank`` (sizes differ by at most one)."""
    base, extra = divmod(batch, world_size)
    start = rank * base + min(rank, extra)
    return slice(start, start + base + (1 if rank < extra else 0))


def local_loss(
    model: nn.Module, x0: Tensor, xe: Tensor, ue: Tensor, rank: int, world_size: int
) -> Tensor:
    """This rank's share of the full-batch imitation loss: its rows' sum times
    ``world_size / N`` (DDP averages the ranks' gradients: the sum of the shares' gradients
    over ranks, divided by ``world_size``, is the full loss's gradient)."""
    rows = shard(x0.shape[0], rank, world_size)
    x, u = model(x0[rows], u_init=ue[rows])
    per_row = ((u - ue[rows]) ** 2).mean((1, 2)) + ((x - xe[rows]) ** 2).mean((1, 2))
    return per_row.sum() * (world_size / x0.shape[0])


def wrap(model: nn.Module, world_size: int) -> nn.Module:
    """``DistributedDataParallel(model)`` in a process group of more than one rank."""
    if world_size == 1:
        return model
    return nn.parallel.DistributedDataParallel(model)


def full_loss(share: Tensor, world_size: int) -> Tensor:
    """The full-batch loss from this rank's share (the same value on every rank)."""
    total = share.detach().clone()
    if world_size > 1:
        dist.all_reduce(total)
    return total / world_size


def train(rank: int, world_size: int, args: argparse.Namespace) -> dict:
    torch.manual_seed(args.seed)
    x0, xe, ue = expert_data(args.batch, args.horizon, args.dt, args.seed)
    learner = Learner(args.dt, args.horizon)
    model = wrap(learner, world_size)
    if args.optimizer == "lbfgs":
        # every rank sees the same (all-reduced) loss and gradient, so the line searches
        # of all ranks take the same steps
        opt = torch.optim.LBFGS(
            model.parameters(),
            lr=1.0,
            max_iter=1,
            max_eval=args.max_eval,
            history_size=20,
            line_search_fn="strong_wolfe",
        )
        sched = None
    else:
        opt = torch.optim.Adam(model.parameters(), lr=args.lr)
        sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=args.lr_decay)

    def closure() -> Tensor:
        opt.zero_grad()
        share = local_loss(model, x0, xe, ue, rank, world_size)
        share.backward()  # DDP all-reduces (averages) the gradients here
        return full_loss(share, world_size)

    history = []
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an unconverged learner solve
        for epoch in range(1, args.epochs + 1):
            loss = opt.step(closure)  # the loss before the step
            if sched is not None:
                sched.step()
            history.append(float(loss))
            if rank == 0 and (epoch % args.print_every == 0 or epoch == args.epochs):
                v = learner.values()
                print(
                    f"epoch {epoch:4d}  loss {history[-1]:.3e}  "
                    + "  ".join(f"{k} {v[k]:.4f}" for k in TRUE),
                    flush=True,
                )
        with torch.no_grad():
            final = full_loss(local_loss(model, x0, xe, ue, rank, world_size), world_size)
    summary = {
        "world_size": world_size,
        "batch": args.batch,
        "horizon": args.horizon,
        "epochs": args.epochs,
        "loss_initial": history[0],
        "loss_final": float(final),
        "learned": learner.values(),
        "true": TRUE,
        "init": INIT,
        "time_s": time.perf_counter() - t0,
    }
    if rank == 0 and args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(summary, indent=1))
    return summary


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=32, help="expert trajectories (all ranks)")
    ap.add_argument("--horizon", type=int, default=20)
    ap.add_argument("--dt", type=float, default=0.05)
    ap.add_argument("--epochs", type=int, default=30)
    ap.add_argument("--optimizer", choices=("lbfgs", "adam"), default="lbfgs")
    ap.add_argument("--max-eval", type=int, default=12, help="L-BFGS solves per epoch (max)")
    ap.add_argument("--lr", type=float, default=0.05, help="Adam learning rate")
    ap.add_argument("--lr-decay", type=float, default=0.95, help="learning rate factor per epoch")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--print-every", type=int, default=10)
    ap.add_argument(
        "--local-workers",
        type=int,
        default=0,
        help="start this many local processes (gloo) instead of using torchrun's",
    )
    ap.add_argument("--out", default="runs/mpc_ddp_training/summary.json")
    ap.add_argument("--quick", action="store_true", help="B = 8, T = 10, 3 epochs")
    args = ap.parse_args(argv)
    if args.quick:
        args.batch, args.horizon, args.epochs, args.print_every = 8, 10, 3, 1
    return args


def _local_worker(rank: int, world_size: int, args: argparse.Namespace) -> None:
    train(rank, world_size, args)


def main(argv: list[str] | None = None) -> dict | None:
    args = parse_args(argv)
    if args.local_workers > 1:
        launch(_local_worker, args.local_workers, (args,), timeout_s=3600)
        return None
    init_from_env(backend="gloo")  # torchrun: join its group; plain python: one process
    rank, world_size = rank_and_world()
    torch.set_num_threads(1 if world_size > 1 else torch.get_num_threads())
    try:
        return train(rank, world_size, args)
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


if __name__ == "__main__":
    main()
