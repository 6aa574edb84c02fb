"""The ``torchslq`` command: ``demo``, ``solve`` and ``reproduce``.

Defaults of ``demo`` and ``solve`` (each overridden by its option):

* ``--solver``: per system, one that converges every problem of the default batch
  (:data:`DEFAULT_SOLVER`: iLQR for the pendulum and the drag vehicle, DDP for the
  cart-pole and the hopper, whose iLQR/SLQ iterations converge slowly or not at all);
* ``--max-iter``: :data:`DEFAULT_MAX_ITER`;
* ``--tol`` (on the gradient norm): the solvers' own default (1e-6) in float64, the
  float32 tolerance of :class:`torchslq.MPC` (:data:`torchslq.mpc.layer.DEFAULT_TOL`,
  1e-4) in float32. Some float32 solves still end ``stalled``: where the gradient
  with respect to the controls is very sensitive (the swing-ups' open-loop rollouts
  through the unstable upright, the drag vehicle's terminal weight 1e6), float32
  rounding alone puts its norm above 1e-4 at the minimum;
* every solve iterates only on the problems still running (``compact=True``).

The printed summary counts the converged problems and, for each other status, says in
one line why those problems stopped (e.g. at the float32 round-off floor).

Errors in the command line (unknown system, solver or option) print one line and exit
with status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from .mpc.layer import DEFAULT_TOL
from .solvers.options import DescentOptions

SOLVERS = ("slq", "ilqr", "ddp")
#: the solver of ``demo``/``solve SYSTEM`` without ``--solver``: one that converges every
#: problem of the default batch, the faster where several do (measured on one CPU
#: thread). iLQR where its cheap iterations converge; DDP where iLQR's and SLQ's converge
#: linearly or not at all: the cart-pole needs up to 340 iLQR iterations against 55 of
#: DDP, and a third of the hopper's iLQR/SLQ solves are still running after 500.
DEFAULT_SOLVER = {"pendulum": "ilqr", "cartpole": "ddp", "drag-vehicle": "ilqr", "hopper": "ddp"}
#: ``--max-iter`` when not given (the slowest default solve, the pendulum's iLQR, needs
#: about 170 iterations for its worst starting states)
DEFAULT_MAX_ITER = 500
REPRODUCTIONS = (
    "sideris-table1",
    "sideris-hopper",
    "gopronto-fig5",
    "lqdo-small",
    "continuous-ilqr",
)
DTYPES = {"float64": torch.float64, "float32": torch.float32}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one clear line, exit code 2
        self.exit(2, f"torchslq: error: {message}\n")


def _fail(message: str) -> int:
    print(f"torchslq: error: {message}", file=sys.stderr)
    return 2


def _device(name: str) -> torch.device:
    try:
        dev = torch.device(name)
    except RuntimeError as err:
        raise ValueError(f"invalid device {name!r}") from err
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} requested but CUDA is not available")
    return dev


def _resolve_defaults(args: argparse.Namespace, system: str) -> None:
    """Fill in the options left at None: ``solver``, ``max_iter``, ``tol`` (see the module
    docstring)."""
    if args.solver is None:
        args.solver = DEFAULT_SOLVER.get(system, "ilqr")
    if args.max_iter is None:
        args.max_iter = DEFAULT_MAX_ITER
    if args.tol is None and DTYPES[args.dtype] != torch.float64:
        # float32 resolves no gradient norm near the solvers' 1e-6: they would end
        # "stalled"; use the tolerance the MPC layer uses for float32
        args.tol = DEFAULT_TOL[torch.float32]


def _make_solver(name: str, args: argparse.Namespace, compact: bool = True):
    """The solver ``name`` with the command's options (``tol=None``: the solver's own
    default). ``compact``: iterate only on the running problems (the per-element data
    of the paper tasks, a beta or a target per problem, follow the running subset)."""
    from .solvers import DDP, ILQR, SLQ

    common = {
        "max_iter": args.max_iter,
        "progress": not args.no_progress,
        "compact": compact,
    }
    if args.tol is not None:
        common["tol"] = args.tol
    if name == "slq":
        return SLQ(line_search=args.line_search, rollout=args.rollout, **common)
    if name in ("ilqr", "ddp"):  # closed-loop rollout and Armijo on the expected improvement
        return (ILQR if name == "ilqr" else DDP)(**common)
    raise ValueError(f"unknown solver {name!r}; choose from {', '.join(SOLVERS)}")


#: why the problems of each status other than ``converged`` stopped ({g}: their largest
#: final gradient norm; {tol}, {max_iter}, {dtype}: the solve's)
_WHY = {
    "max_iter": "reached --max-iter {max_iter} with grad_norm up to {g:.2g} > tol {tol:g}; "
    "raise --max-iter or try another --solver",
    "stalled": "at the {dtype} round-off floor: the cost stopped changing beyond rounding "
    "with grad_norm up to {g:.2g} > tol {tol:g}; use float64 or a --tol above that",
    "line_search_failed": "no step decreased the cost (grad_norm up to {g:.2g} > tol "
    "{tol:g}): a round-off floor or a poor local model; try another --solver",
    "non_finite": "a NaN or infinity in the trajectory, cost or derivatives",
    "diverged": "the iterates left the finite range",
    "not_positive_definite": "the LQ subproblem has no minimum (Quu not positive "
    "definite even at the largest regularisation); try --solver ilqr or slq",
    "infeasible": "constraint violation above constraint_tol at the largest penalty",
}


def status_report(result, tol: float, max_iter: int) -> list[str]:
    """Lines for the summary: ``converged: k/B``, then one line per other status saying
    how many problems ended so and why."""
    from .status import Status, status_names

    names = status_names(result.status)
    g = result.grad_norm.reshape(-1).double()
    dtype = str(result.x.dtype).removeprefix("torch.")
    done = names.count("converged")
    lines = [f"converged: {done}/{len(names)}"]
    for st in Status:
        idx = [i for i, name in enumerate(names) if name == st.label]
        if not idx or st.label == "converged":
            continue
        why = _WHY.get(st.label)
        gmax = float(g[idx].max())
        why = (
            ""
            if why is None
            else ": " + why.format(g=gmax, tol=tol, max_iter=max_iter, dtype=dtype)
        )
        lines.append(f"  {len(idx)} {st.label}{why}")
    return lines


def _run(system: str, args: argparse.Namespace, title: str) -> int:
    from .logging import TensorBoardLogger, _goal
    from .plotting import convergence_figure, state_control_names, trajectory_figure
    from .tasks import TASKS, make_task, swingup_success

    if system not in TASKS:
        return _fail(f"unknown system {system!r}; choose from {', '.join(TASKS)}")
    _resolve_defaults(args, system)
    try:
        device = _device(args.device)
        solver = _make_solver(args.solver, args)
    except ValueError as err:
        return _fail(str(err))
    if args.batch < 1:
        return _fail(f"--batch must be >= 1, got {args.batch}")
    if args.threads is not None and args.threads < 0:
        return _fail(f"--threads must be >= 0 (0: torch's default), got {args.threads}")
    torch.set_num_threads(args.threads) if args.threads else None
    problem, x0 = make_task(
        system, batch=args.batch, seed=args.seed, device=device, dtype=DTYPES[args.dtype]
    )
    logdir = Path(args.logdir) / time.strftime("%Y%m%d-%H%M%S")
    try:
        logdir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        return _fail(f"cannot write --logdir {str(args.logdir)!r}: {err.strerror or err}")
    dt = getattr(problem.dynamics, "dt", None)
    t0 = time.perf_counter()
    with TensorBoardLogger(logdir, dt=dt) as logger:
        result = solver.solve(problem, x0, logger=logger)
    elapsed = time.perf_counter() - t0
    png = logdir / "trajectories.png"
    s_names, c_names = state_control_names(problem.dynamics)
    trajectory_figure(
        result.x, result.u, dt=dt, max_elements=8, title=title, state_labels=s_names,
        control_labels=c_names, x_ref=_goal(problem, result.x),
    ).savefig(png, dpi=110)  # fmt: skip
    conv_png = logdir / "convergence.png"
    convergence_figure(
        {args.solver: result.history}, title=f"{title}: cost and gradient norm over the batch"
    ).savefig(conv_png, dpi=110)

    print(f"# {title}")
    if args.solver == "slq":
        how = f"{args.line_search} line search, {args.rollout} rollout"
    else:
        how = "closed-loop rollout, Armijo on the expected improvement"
    print(
        f"solver: {args.solver} ({how}), tol {solver.options.tol:g} on grad_norm, "
        f"max_iter {args.max_iter}, device {device}, {args.dtype}"
    )
    print(result.summary())
    for line in status_report(result, solver.options.tol, args.max_iter):
        print(line)
    if system in ("pendulum", "cartpole"):
        ok = swingup_success(result.x, angle_index=0 if system == "pendulum" else 1)
        print(f"swung up (final angle within 0.1 rad of upright): {int(ok.sum())}/{ok.numel()}")
    print(
        f"wall time: {elapsed:.2f} s for {x0.shape[0]} problems ({elapsed / x0.shape[0] * 1e3:.2f} ms per problem)"
    )
    print(f"TensorBoard logs: {logdir}   (view: tensorboard --logdir {args.logdir})")
    print(f"plots: {png}, {conv_png}")
    return 0


def _reproductions():
    """The checkout's ``reproductions`` package (not installed with torchslq), or None.

    Found on ``sys.path`` (running from the repository root) or beside this package's
    folder when torchslq is installed from a checkout (``pip install -e .``)."""
    import importlib

    try:
        return importlib.import_module("reproductions")
    except ImportError:
        pass
    root = Path(__file__).resolve().parents[1]
    if (root / "reproductions" / "__init__.py").is_file():
        sys.path.insert(0, str(root))
        try:
            return importlib.import_module("reproductions")
        except ImportError:
            return None
    return None


def _reproduce(name: str, args: argparse.Namespace) -> int:
    if name not in REPRODUCTIONS:
        return _fail(f"unknown reproduction {name!r}; choose from {', '.join(REPRODUCTIONS)}")
    if _reproductions() is None:
        return _fail(
            "the paper reproductions are not part of the installed package: they live in "
            "the repository's reproductions/ folder; run this command from a checkout of "
            "the repository (its root directory)"
        )
    if name == "lqdo-small":  # Herber & Sundarrajan 2020, the small rows of Tables 1-3
        from reproductions import lqdo

        rows = lqdo.table1(("TR20", "PS10"), ipopt=False) + lqdo.table3(("PS10",), ipopt=False)
        print(lqdo.format_rows(rows, lqdo.TABLE_COLUMNS))
        return 0
    if name == "continuous-ilqr":
        from reproductions import continuous_ilqr

        print(continuous_ilqr.format_rows(continuous_ilqr.reproduce(rtol=1e-4)[0]))
        return 0
    if name == "gopronto-fig5":
        from reproductions import gopronto

        print(gopronto.format_rows(gopronto.reproduce_figure5()))
        return 0
    from reproductions import sideris

    if name == "sideris-table1":
        rows = sideris.reproduce_table1(line_search=args.line_search)
    else:
        rows = sideris.reproduce_hopper(line_search=args.line_search)
    print(sideris.format_table(rows))
    return 0


def _add_solve_options(
    p: argparse.ArgumentParser, batch: int, logdir: str, rollout: str, solver_help: str
) -> None:
    p.add_argument("--solver", default=None, choices=SOLVERS, help=solver_help)
    p.add_argument("--batch", type=int, default=batch, help="number of problems solved at once")
    p.add_argument("--device", default="cpu")
    p.add_argument("--dtype", default="float64", choices=tuple(DTYPES))
    p.add_argument("--logdir", default=logdir, help="TensorBoard log root")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--max-iter", type=int, default=None, help=f"iteration limit (default {DEFAULT_MAX_ITER})"
    )
    p.add_argument(
        "--tol",
        type=float,
        default=None,
        help=f"gradient-norm tolerance (default: {DescentOptions.tol:g} in float64, "
        f"{DEFAULT_TOL[torch.float32]:g} in float32)",
    )
    p.add_argument("--line-search", default="exact", choices=("exact", "armijo"), help="slq only")
    p.add_argument(
        "--rollout", default=rollout, choices=("open_loop", "closed_loop"), help="slq only"
    )
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _sharded_job(rank: int, world_size: int, opts: dict) -> None:
    """One process of ``torchslq solve --out-dir``: its shards of the task's batch."""
    from .distributed import solve_sharded
    from .tasks import make_task

    args = argparse.Namespace(**opts)
    kw = {} if args.horizon is None else {"horizon": args.horizon}
    problem, x0 = make_task(
        args.system,
        batch=args.batch,
        seed=args.seed,
        device=_device(args.device),
        dtype=DTYPES[args.dtype],
        **kw,
    )
    solver = _make_solver(args.solver, args)
    solve_sharded(solver, problem, x0, args.out_dir, shard_size=args.shard_size)


def _solve_sharded(args: argparse.Namespace) -> int:
    """``torchslq solve SYSTEM --out-dir DIR``: the batch in shards of ``--shard-size``,
    solved by ``--workers`` local processes (or torchrun's), one SolverResult file per
    shard, resumable (:func:`torchslq.distributed.solve_sharded`)."""
    import os

    from .distributed import init_from_env, iter_shards, launch, shard_bounds, shard_path
    from .status import status_names
    from .tasks import TASKS

    if args.system not in TASKS:
        return _fail(f"unknown system {args.system!r}; choose from {', '.join(TASKS)}")
    _resolve_defaults(args, args.system)
    if args.horizon is not None and args.system not in ("pendulum", "cartpole"):
        return _fail("--horizon applies to the pendulum and cartpole tasks")
    for name, value in (("--batch", args.batch), ("--shard-size", args.shard_size)):
        if value < 1:
            return _fail(f"{name} must be >= 1, got {value}")
    if args.workers < 1:
        return _fail(f"--workers must be >= 1, got {args.workers}")
    if args.horizon is not None and args.horizon < 1:
        return _fail(f"--horizon must be >= 1, got {args.horizon}")
    try:
        _device(args.device)
        _make_solver(args.solver, args)
    except ValueError as err:
        return _fail(str(err))
    out = Path(args.out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        return _fail(f"cannot write --out-dir {str(args.out_dir)!r}: {err.strerror or err}")
    opts = vars(args).copy()
    num = len(shard_bounds(args.batch, args.shard_size))
    t0 = time.perf_counter()
    try:
        if "WORLD_SIZE" in os.environ:  # under torchrun: this process is one rank
            import torch.distributed as dist

            rank, world = init_from_env(backend="gloo")
            try:
                _sharded_job(rank, world, opts)
            finally:
                dist.destroy_process_group()
            if rank != 0:
                return 0
        else:
            before = sum(shard_path(out, i).exists() for i in range(num))
            if args.workers == 1:
                _sharded_job(0, 1, opts)
            else:
                threads = max(1, (args.threads or torch.get_num_threads()) // args.workers)
                launch(
                    _sharded_job,
                    args.workers,
                    (opts,),
                    start_method=args.start_method,
                    threads=threads,
                )
            print(f"{num - before} shards solved now, {before} were already on disk")
    except ValueError as err:
        return _fail(str(err))
    elapsed = time.perf_counter() - t0
    counts: dict[str, int] = {}
    for _, _, res in iter_shards(out):
        for name in status_names(res.status):
            counts[name] = counts.get(name, 0) + 1
    print(f"{args.system}: {args.batch} problems in {num} shards of {args.shard_size} -> {out}")
    print("status: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    print(f"wall time: {elapsed:.2f} s; load with torchslq.distributed.load_sharded({str(out)!r})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="torchslq", description="Batched, differentiable optimal control.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    demo = sub.add_parser(
        "demo", help="256 pendulum swing-ups by iLQR, with TensorBoard logs and plots"
    )
    _add_solve_options(
        demo,
        batch=256,
        logdir="runs/demo",
        rollout="closed_loop",
        solver_help=f"default: {DEFAULT_SOLVER['pendulum']}",
    )
    solve = sub.add_parser("solve", help="solve a batch of a built-in system")
    solve.add_argument("system", help="pendulum | cartpole | drag-vehicle | hopper")
    per_system = ", ".join(f"{k} {v}" for k, v in DEFAULT_SOLVER.items())
    _add_solve_options(
        solve,
        batch=64,
        logdir="runs/solve",
        rollout="closed_loop",
        solver_help=f"default: per system ({per_system})",
    )
    shard = solve.add_argument_group(
        "sharded solve (results streamed to disk, resumable; torchslq.distributed)"
    )
    shard.add_argument(
        "--out-dir", default=None, help="write one SolverResult file per shard into this folder"
    )
    shard.add_argument("--shard-size", type=int, default=1024, help="problems per shard")
    shard.add_argument(
        "--workers",
        type=int,
        default=1,
        help="local worker processes (gloo); under torchrun its processes are used",
    )
    shard.add_argument(
        "--horizon", type=int, default=None, help="pendulum/cartpole horizon (default: the task's)"
    )
    shard.add_argument(
        "--start-method",
        default="spawn",
        choices=("spawn", "fork"),
        help="how --workers start (fork: faster, Linux and CPU only)",
    )
    rep = sub.add_parser("reproduce", help="reproduce a paper's table, ours beside the paper's")
    rep.add_argument("name", help=" | ".join(REPRODUCTIONS))
    rep.add_argument("--line-search", default="armijo", choices=("exact", "armijo"))
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "demo":
        return _run("pendulum", args, "pendulum swing-up demo")
    if args.command == "solve":
        if args.out_dir is not None:
            return _solve_sharded(args)
        if args.horizon is not None or args.workers != 1:
            return _fail("--horizon and --workers go with --out-dir (the sharded solve)")
        return _run(args.system, args, f"{args.system} ({args.batch} problems)")
    return _reproduce(args.name, args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
