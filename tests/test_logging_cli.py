"""TensorBoard logging (read back from the event files) and the ``torchslq`` command."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

import torchslq as ts
from torchslq.cli import main
from torchslq.tasks import pendulum_swingup


@pytest.fixture(scope="module")
def logged_solve(tmp_path_factory):
    logdir = tmp_path_factory.mktemp("tb")
    problem, x0 = pendulum_swingup(batch=6, horizon=30, seed=3)
    # a mix of outcomes: max_iter small enough that some elements are still running
    solver = ts.SLQ(max_iter=6, rollout="closed_loop", progress=False)
    with ts.TensorBoardLogger(logdir) as logger:
        result = solver.solve(problem, x0, logger=logger)
    acc = EventAccumulator(
        str(logdir), size_guidance={"scalars": 0, "histograms": 0, "images": 0, "tensors": 0}
    )
    acc.Reload()
    return result, acc


def _scalar_series(acc, tag):
    return {e.step: e.value for e in acc.Scalars(tag)}


def test_logged_cost_statistics_equal_history(logged_solve):
    result, acc = logged_solve
    hist = result.history["cost"]  # (B, iters+1)
    for tag, reduce in (
        ("cost/mean", lambda h: h.mean(0)),
        ("cost/min", lambda h: h.min(0).values),
        ("cost/max", lambda h: h.max(0).values),
    ):
        series = _scalar_series(acc, tag)
        expected = reduce(hist)
        assert sorted(series) == list(range(hist.shape[1]))
        for it, value in series.items():
            assert value == pytest.approx(expected[it].item(), rel=1e-6)  # float32 storage


def test_logged_grad_norm_and_steps_equal_history(logged_solve):
    result, acc = logged_solve
    g = result.history["grad_norm"]
    for it, value in _scalar_series(acc, "grad_norm/max").items():
        assert value == pytest.approx(g[:, it].max().item(), rel=1e-6)
    steps = result.history["step"]
    for it, value in _scalar_series(acc, "step/mean").items():
        assert value == pytest.approx(steps[:, it].mean().item(), rel=1e-6, abs=1e-12)


def test_logged_converged_fraction_and_final_records(logged_solve):
    result, acc = logged_solve
    conv = _scalar_series(acc, "converged_fraction")
    last = max(conv)
    assert conv[last] == pytest.approx(result.converged.double().mean().item())
    final = _scalar_series(acc, "final/converged_fraction")
    assert final[0] == pytest.approx(result.converged.double().mean().item())
    hist = acc.Histograms("final/cost")[0].histogram_value
    assert hist.num == result.cost.numel()
    assert hist.min == pytest.approx(result.cost.min().item(), rel=1e-6)
    assert hist.max == pytest.approx(result.cost.max().item(), rel=1e-6)
    assert "trajectories" in acc.Tags()["images"]
    wall = _scalar_series(acc, "time/iteration")
    assert all(v >= 0 for v in wall.values())


def test_no_logger_means_no_event_files(tmp_path):
    problem, x0 = pendulum_swingup(batch=2, horizon=10)
    ts.SLQ(max_iter=2, progress=False).solve(problem, x0)
    assert list(tmp_path.iterdir()) == []


def test_cli_solve_writes_logs_and_plots(tmp_path, capsys):
    rc = main(
        [
            "solve",
            "pendulum",
            "--batch",
            "4",
            "--max-iter",
            "40",
            "--logdir",
            str(tmp_path),
            "--no-progress",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0
    assert "problems: 4" in out and "swung up" in out
    runs = list(tmp_path.iterdir())
    assert len(runs) == 1
    assert (runs[0] / "trajectories.png").stat().st_size > 1000
    assert any(p.name.startswith("events.out.tfevents") for p in runs[0].iterdir())


@pytest.mark.parametrize(
    "args, needle",
    [
        (["solve", "no-such-system"], "unknown system"),
        (["solve", "pendulum", "--solver", "nope"], "--solver"),
        (["demo", "--line-search", "bogus"], "--line-search"),
        (["reproduce", "nothing"], "unknown reproduction"),
        (["solve", "pendulum", "--threads", "-1"], "--threads"),
        (["solve", "pendulum", "--logdir", "/dev/null/runs"], "--logdir"),
    ],
)
def test_cli_errors_are_one_line_exit_2(args, needle, capsys):
    """In process (``main`` returns 2 or argparse exits with 2); the exit status of a
    real process is checked once, below."""
    threads = torch.get_num_threads()
    try:
        rc = main(args)
    except SystemExit as exc:
        rc = exc.code
    finally:
        torch.set_num_threads(threads)
    assert rc == 2
    err = capsys.readouterr().err
    lines = [line for line in err.strip().splitlines() if line]
    assert len(lines) == 1, err
    assert needle in lines[0]


def test_cli_error_of_a_process_is_one_line_exit_2():
    proc = subprocess.run(
        [sys.executable, "-m", "torchslq.cli", "solve", "no-such-system"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.strip().splitlines() if line]
    assert len(lines) == 1, proc.stderr
    assert "unknown system" in lines[0]


def test_cli_reproduce_without_reproductions_says_where_they_are(monkeypatch, capsys):
    """Installed without a checkout, ``reproduce`` names the repository's folder."""
    import torchslq.cli as cli

    monkeypatch.setattr(cli, "_reproductions", lambda: None)
    assert main(["reproduce", "sideris-table1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "reproductions/" in err[0] and "repository" in err[0]


def test_cli_finds_reproductions_from_a_checkout(tmp_path):
    """Run from outside the repository, the command still finds the checkout's package."""
    code = "import torchslq.cli as c, sys; m = c._reproductions(); print(m.__name__, m.sideris.__name__)"
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["reproductions", "reproductions.sideris"]


def test_float32_solve_runs(tmp_path):
    problem, x0 = pendulum_swingup(batch=3, horizon=30, dtype=torch.float32)
    res = ts.SLQ(max_iter=30, tol=1e-3, rollout="closed_loop", progress=False).solve(problem, x0)
    assert res.x.dtype == torch.float32
    assert bool(torch.isfinite(res.cost).all())
    assert bool(res.converged.all())


@pytest.mark.parametrize("solver", ["ilqr", "ddp"])
def test_cli_solve_with_ilqr_and_ddp(tmp_path, capsys, solver):
    rc = main(
        [
            "solve",
            "cartpole",
            "--solver",
            solver,
            "--batch",
            "2",
            "--max-iter",
            "80",
            "--logdir",
            str(tmp_path),
            "--no-progress",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0
    assert f"solver: {solver} " in out
    assert "swung up (final angle within 0.1 rad of upright): 2/2" in out
