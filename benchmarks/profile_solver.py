"""cProfile of one torchslq solve of the peers benchmark's cart-pole swing-up.

Prints the functions with the largest cumulative (or own) time, to see where a solve's
time goes (dynamics Hessians, Riccati passes, line-search rollouts, ...)::

    python benchmarks/profile_solver.py --solver ddp --batch 512
    python benchmarks/profile_solver.py --solver ilqr --batch 512 --sort tottime

Same problem and options as ``benchmarks/peers.py`` (float64, one thread, ``compact=True``,
``tol=1e-6``); the profiler adds some overhead to every Python call.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

from torchslq import DDP, ILQR, SLQ  # noqa: E402
from torchslq.tasks import cartpole_swingup  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--solver", choices=("ddp", "ilqr", "slq"), default="ddp")
    ap.add_argument("--batch", type=int, default=512)
    ap.add_argument("--max-iter", type=int, default=500)
    ap.add_argument("--sort", choices=("cumtime", "tottime"), default="cumtime")
    ap.add_argument("--lines", type=int, default=40)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    problem, x0 = cartpole_swingup(args.batch, horizon=peers.T_CP, dt=peers.DT, seed=0)
    kw = dict(max_iter=args.max_iter, tol=1e-6, progress=False, compact=True)
    make = {
        "ddp": lambda: DDP(**kw),
        "ilqr": lambda: ILQR(**kw),
        "slq": lambda: SLQ(rollout="closed_loop", **kw),
    }[args.solver]
    warm, xw = cartpole_swingup(2, horizon=peers.T_CP, dt=peers.DT, seed=1)
    make().solve(warm, xw)  # first-call costs of torch.func transforms
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    r = make().solve(problem, x0)
    prof.disable()
    print(
        f"{args.solver} B={args.batch}: {time.perf_counter() - t0:.2f} s under the profiler, "
        f"iterations mean {r.iterations.double().mean():.1f} max {int(r.iterations.max())}, "
        f"converged {int(r.converged.sum())}/{args.batch}"
    )
    pstats.Stats(prof).sort_stats(args.sort).print_stats(args.lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
