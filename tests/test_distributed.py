"""More than one process (``torchslq.distributed``), 2 local CPU processes with gloo:

* DDP training through the MPC layer (``examples/mpc_ddp_training.py``): the gradients
  after DDP's all-reduce equal the gradients of the full-batch loss in one process;
* ``solve_sharded``: the assembled shards equal the one-process solve of the whole batch;
  a worker killed mid-job loses nothing: the rerun solves exactly the missing shards,
  leaves the finished shard files untouched, and the result has every row once;
* the CLI's sharded ``solve`` against the one-process solve of the same task.

Workers start by ``fork`` (the spawn start method re-imports torch in every worker) and
every launch has a wall-clock timeout, so a hang fails the test instead of blocking.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from torchslq import ILQR, SolverResult
from torchslq.distributed import launch, load_sharded, shard_bounds, shard_path, solve_sharded
from torchslq.tasks import pendulum_swingup

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "mpc_ddp_training.py"
TIMEOUT = 120
START = "fork" if sys.platform.startswith("linux") else "spawn"


def _example():
    name = "_example_mpc_ddp_training"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# ----------------------------------------------------------------------------- DDP

BATCH, HORIZON, DT = 5, 8, 0.05  # 5 rows: the ranks get 3 and 2


def _ddp_worker(rank: int, world: int, out: str) -> None:
    mod = _example()
    x0, xe, ue = mod.expert_data(BATCH, HORIZON, DT, seed=0)
    model = mod.wrap(mod.Learner(DT, HORIZON), world)
    assert isinstance(model, torch.nn.parallel.DistributedDataParallel)
    loss = mod.local_loss(model, x0, xe, ue, rank, world)
    loss.backward()
    grads = {k: p.grad.detach().clone() for k, p in model.module.named_parameters()}
    torch.save({"grads": grads, "loss": loss.detach()}, os.path.join(out, f"rank{rank}.pt"))


def test_ddp_gradients_equal_single_process(tmp_path):
    # the one-process reference first (forked workers then start with its warm caches)
    mod = _example()
    x0, xe, ue = mod.expert_data(BATCH, HORIZON, DT, seed=0)
    model = mod.Learner(DT, HORIZON)
    loss = mod.local_loss(model, x0, xe, ue, 0, 1)
    loss.backward()
    ref = {k: p.grad for k, p in model.named_parameters()}
    launch(_ddp_worker, 2, (str(tmp_path),), timeout_s=TIMEOUT, start_method=START)
    ranks = [torch.load(tmp_path / f"rank{r}.pt") for r in (0, 1)]
    # the ranks' loss shares (each times world_size) average to the full-batch loss
    full = loss.item()
    assert abs(sum(float(r["loss"]) for r in ranks) / 2 - full) <= 1e-12 * abs(full)
    assert set(ref) == set(ranks[0]["grads"]) and len(ref) == 4
    for name, g in ref.items():
        assert float(g.abs().max()) > 1e-6, name  # a real gradient, not zeros
        for r in ranks:
            err = float((r["grads"][name] - g).abs().max() / g.abs().max())
            assert err < 1e-9, (name, err)


# ----------------------------------------------------------------------------- sharded solves

N, T_SOLVE, SHARD = 10, 10, 3  # 4 shards, the last of 1 row


def _task():
    problem, x0 = pendulum_swingup(batch=N, horizon=T_SOLVE, seed=3)
    return problem, x0, ILQR(max_iter=100, tol=1e-8, progress=False)


class _DiesAfter:
    """A solver that solves ``n_ok`` shards, then kills its process in the next solve
    (``os._exit``: no cleanup, like a killed worker)."""

    def __init__(self, solver, n_ok: int):
        self.solver, self.n_ok, self.calls = solver, n_ok, 0

    def solve(self, problem, x0, u_init=None):
        if self.calls >= self.n_ok:
            os._exit(3)
        self.calls += 1
        return self.solver.solve(problem, x0, u_init)


def _shard_worker(rank: int, world: int, out: str, die_rank: int, n_ok: int) -> None:
    problem, x0, solver = _task()
    if rank == die_rank:
        solver = _DiesAfter(solver, n_ok)
    report = solve_sharded(solver, problem, x0, out, shard_size=SHARD)
    torch.save(
        {"computed": report.computed, "skipped": report.skipped}, os.path.join(out, f"r{rank}.rep")
    )


def _compare(res: SolverResult, ref: SolverResult) -> None:
    assert res.x.shape == ref.x.shape and res.u.shape == ref.u.shape
    for name in ("x", "u", "cost", "K", "k", "grad_norm"):
        a, b = getattr(res, name), getattr(ref, name)
        err = float((a - b).abs().max() / b.abs().max().clamp_min(1.0))
        assert err < 1e-9, (name, err)
    assert torch.equal(res.status, ref.status)
    assert torch.equal(res.iterations, ref.iterations)


def test_sharded_solve_equals_one_process_and_resumes_after_a_kill(tmp_path):
    out = tmp_path / "job"
    problem, x0, solver = _task()
    ref = solver.solve(problem, x0)
    nshards = len(shard_bounds(N, SHARD))
    assert nshards == 4

    # run 1: rank 1 is killed in its second shard (it finished one)
    with pytest.raises(mp.ProcessExitedException):
        launch(_shard_worker, 2, (str(out), 1, 1), timeout_s=TIMEOUT, start_method=START)
    done = {i: os.stat(shard_path(out, i)) for i in range(nshards) if shard_path(out, i).exists()}
    missing = sorted(set(range(nshards)) - set(done))
    assert missing, "the killed worker left no shard undone"
    # a partial write left behind by a killed worker is never mistaken for a shard
    (out / ".shard_000003.pt.junk.tmp").write_bytes(b"partial")
    for i in missing:
        assert not shard_path(out, i).exists()

    # run 2: the same job again; only the missing shards are solved
    launch(_shard_worker, 2, (str(out), -1, 0), timeout_s=TIMEOUT, start_method=START)
    reps = [torch.load(out / f"r{r}.rep") for r in (0, 1)]
    computed = sorted(reps[0]["computed"] + reps[1]["computed"])
    assert computed == missing  # each missing shard once, nothing else recomputed
    assert sorted(reps[0]["skipped"]) == sorted(done)
    for i, st in done.items():  # the finished files are untouched
        now = os.stat(shard_path(out, i))
        assert (now.st_ino, now.st_mtime_ns) == (st.st_ino, st.st_mtime_ns), i
    assert not list(out.glob(".*.tmp"))

    # every row once, in order, equal to the one-process solve
    res = load_sharded(out)
    _compare(res, ref)
    # a shard file is a SolverResult file
    one = SolverResult.load(shard_path(out, 1))
    assert torch.equal(one.x, res.x[SHARD : 2 * SHARD])


def test_sharded_solve_one_process_and_manifest_mismatch(tmp_path):
    problem, x0, solver = _task()
    report = solve_sharded(solver, problem, x0, tmp_path, shard_size=4)
    assert report.computed == [0, 1, 2] and report.skipped == []
    _compare(load_sharded(tmp_path), solver.solve(problem, x0))
    again = solve_sharded(solver, problem, x0, tmp_path, shard_size=4)
    assert again.computed == [] and again.skipped == [0, 1, 2]
    with pytest.raises(ValueError, match="x0_sha256"):
        solve_sharded(solver, problem, x0 + 1, tmp_path, shard_size=4)
    with pytest.raises(ValueError, match="shard_size"):
        solve_sharded(solver, problem, x0, tmp_path, shard_size=0)
    shard_path(tmp_path, 1).unlink()
    with pytest.raises(FileNotFoundError, match="shard_000001"):
        load_sharded(tmp_path)


def test_sharded_solve_cuts_per_element_problem_data_like_x0(tmp_path):
    """A goal per row (``x_ref (N, T+1, n)``) is cut into shards with ``x0``: the
    assembled result equals the one-batch solve (no sub-batching there)."""
    import torchslq as ts

    problem, x0, solver = _task()
    n = problem.state_dim
    x_ref = torch.zeros(N, T_SOLVE + 1, n, dtype=x0.dtype)
    x_ref[:, :, 0] = torch.linspace(2.5, 3.5, N, dtype=x0.dtype)[:, None]
    c = problem.cost
    cost = ts.QuadraticCost(c.Q, c.R, c.Qf, x_ref=x_ref)
    goals = ts.Problem(problem.dynamics, cost, problem.horizon)
    solve_sharded(solver, goals, x0, tmp_path, shard_size=4)
    res, ref = load_sharded(tmp_path), solver.solve(goals, x0)
    _compare(res, ref)
    # the goals matter (a misaligned cut could not match the one-batch solve)
    shared = solver.solve(problem, x0)
    assert float((res.u - shared.u).abs().amax()) > 1e-2


def test_cli_sharded_solve_with_two_workers(tmp_path, capsys):
    from torchslq.cli import main

    problem, x0 = pendulum_swingup(batch=7, horizon=12, seed=2)
    ref = ILQR(max_iter=40, tol=1e-6, progress=False, compact=True).solve(problem, x0)
    out = tmp_path / "cli"
    argv = ["solve", "pendulum", "--batch", "7", "--seed", "2", "--solver", "ilqr"]
    argv += ["--max-iter", "40", "--no-progress", "--horizon", "12", "--out-dir", str(out)]
    argv += ["--shard-size", "3", "--workers", "2", "--start-method", START]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "7 problems in 3 shards of 3" in printed and "3 shards solved now, 0 were" in printed
    _compare(load_sharded(out), ref)
    # the same command again: nothing left to solve
    assert main(argv) == 0
    assert "0 shards solved now, 3 were already on disk" in capsys.readouterr().out
    # command-line errors: one line, exit status 2
    assert main(["solve", "pendulum", "--workers", "2"]) == 2
    assert main([*argv[:-6], "--shard-size", "0"]) == 2


# ----------------------------------------------------------------------------- launch

_SLEEPER = """
import os, sys, time
from torchslq.distributed import launch

def sleeper(rank, world, path):
    with open(path + f".{rank}", "w") as f:
        f.write(str(os.getpid()))
    time.sleep(120)

if __name__ == "__main__":
    launch(sleeper, 2, (sys.argv[1],), timeout_s=120, start_method="fork")
"""


def test_sigterm_to_the_launcher_stops_its_workers(tmp_path):
    import signal
    import subprocess
    import time

    script = tmp_path / "sleeper.py"
    script.write_text(_SLEEPER)
    mark = str(tmp_path / "pid")
    proc = subprocess.Popen([sys.executable, str(script), mark])
    try:
        deadline = time.monotonic() + 60
        while not all(os.path.exists(f"{mark}.{r}") for r in (0, 1)):
            assert time.monotonic() < deadline and proc.poll() is None, "workers did not start"
            time.sleep(0.1)
        time.sleep(0.2)  # the pid files are complete
        pids = [int(Path(f"{mark}.{r}").read_text()) for r in (0, 1)]
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) != 0
        for pid in pids:  # gone (reaped by the launcher), not orphaned
            with pytest.raises(ProcessLookupError):
                os.kill(pid, 0)
    finally:
        if proc.poll() is None:
            proc.kill()
