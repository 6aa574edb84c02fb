"""TensorBoard logging shared by all solvers.

A solver calls ``logger.log_options`` once, ``logger.log_iteration`` once per iteration
and ``logger.log_result`` at the end. With ``logger=None`` (the default) none of this
runs, so a solve without a logger pays nothing. The logger converts batch statistics to
Python numbers (host syncs), which is why it only runs when asked for.

Tags written (per iteration ``it``):

* ``cost/mean``, ``cost/min``, ``cost/max``: over the batch (non-finite values skipped);
* ``grad_norm/mean``, ``grad_norm/min``, ``grad_norm/max``;
* ``step/mean``, ``step/max``: accepted step sizes (0 for finished elements);
* ``converged_fraction``: share of elements with status ``converged``;
* ``running``: number of elements still iterating;
* ``time/iteration``: wall time of the iteration in seconds.

At the end: histogram ``final/cost``, scalar ``final/converged_fraction``, a figure
``trajectories`` of the first elements, text ``options`` and the hparams plugin record.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .status import Status

__all__ = ["TensorBoardLogger"]


def _finite_stats(t: Tensor) -> tuple[float, float, float]:
    v = t.detach().reshape(-1).to(torch.float64)
    v = v[torch.isfinite(v)]
    if v.numel() == 0:
        return (math.nan, math.nan, math.nan)
    return (v.mean().item(), v.min().item(), v.max().item())


class TensorBoardLogger:
    """Writes a solver's convergence to TensorBoard event files in ``log_dir``.

    Args:
        log_dir: directory for the event files (created if missing).
        plot_elements: how many batch elements the final trajectory figure shows.
        dt: time step for the figure's time axis (step index when None).

    Use as a context manager or call :meth:`close`.
    """

    def __init__(self, log_dir: str | Path, plot_elements: int = 4, dt: float | None = None):
        from torch.utils.tensorboard import SummaryWriter

        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.writer = SummaryWriter(log_dir=str(self.log_dir))
        self.plot_elements = plot_elements
        self.dt = dt
        self._last_time = 0.0
        self._options: dict[str, Any] = {}

    # solver hooks -------------------------------------------------------------------
    def log_options(self, solver_name: str, options: dict[str, Any]) -> None:
        self._options = {"solver": solver_name, **options}
        self._last_time = 0.0
        rows = "\n".join(f"| {k} | {v} |" for k, v in self._options.items())
        self.writer.add_text("options", "| option | value |\n|---|---|\n" + rows, 0)

    def log_iteration(
        self,
        it: int,
        *,
        cost: Tensor,
        grad_norm: Tensor,
        step: Tensor,
        status: Tensor,
        wall_time: float,
    ) -> None:
        w = self.writer
        for name, t in (("cost", cost), ("grad_norm", grad_norm)):
            mean, lo, hi = _finite_stats(t)
            w.add_scalar(f"{name}/mean", mean, it)
            w.add_scalar(f"{name}/min", lo, it)
            w.add_scalar(f"{name}/max", hi, it)
        step_mean, _, step_max = _finite_stats(step)
        w.add_scalar("step/mean", step_mean, it)
        w.add_scalar("step/max", step_max, it)
        w.add_scalar("converged_fraction", (status == Status.CONVERGED).double().mean().item(), it)
        w.add_scalar("running", int((status == Status.RUNNING).sum().item()), it)
        w.add_scalar("time/iteration", wall_time - self._last_time, it)
        self._last_time = wall_time

    def log_result(self, result: Any, problem: Any = None) -> None:
        from .plotting import trajectory_figure

        w = self.writer
        cost = result.cost.detach().reshape(-1)
        finite = cost[torch.isfinite(cost)]
        if finite.numel() > 0:
            w.add_histogram("final/cost", finite.to("cpu", torch.float64), 0)
        conv = result.converged.reshape(-1).double().mean().item()
        w.add_scalar("final/converged_fraction", conv, 0)
        if result.x.ndim < 3 or result.x.shape[0] > 0:  # an empty batch has nothing to draw
            fig = trajectory_figure(result.x, result.u, dt=self.dt, max_elements=self.plot_elements)
            w.add_figure("trajectories", fig, 0, close=True)
        hparams = {
            k: (v if isinstance(v, (int, float, str, bool)) else str(v))
            for k, v in self._options.items()
        }
        hparams = {k: (str(v) if v is None else v) for k, v in hparams.items()}
        metrics = {
            "hparam/converged_fraction": conv,
            "hparam/mean_cost": finite.double().mean().item() if finite.numel() else math.nan,
            "hparam/mean_iterations": result.iterations.double().mean().item(),
        }
        w.add_hparams(hparams, metrics, run_name=".")
        w.flush()

    # lifecycle ------------------------------------------------------------------------
    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()

    def __enter__(self) -> TensorBoardLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
