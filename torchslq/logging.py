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

At the end: histogram ``final/cost``, scalar ``final/converged_fraction``, figures
``trajectories`` (the first elements, see :func:`torchslq.plotting.trajectory_figure`)
and ``convergence`` (cost and gradient norm over the batch: median and 10-90 percentile
band, see :func:`torchslq.plotting.convergence_figure`), text ``options`` and the
hparams plugin record. With ``save_png=True`` the two figures are also written to the
log directory as ``trajectories.png`` and ``convergence.png``.

The trajectory figure names the states and controls after the logger's
``state_labels`` / ``control_labels``, else after the model's ``state_names`` /
``control_names`` (:func:`torchslq.plotting.state_control_names`), and draws the
cost's ``x_ref`` as goal lines and the solver's ``u_min`` / ``u_max`` as bound lines
when the problem and the result's options have them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
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


def _goal(problem: Any, x: Tensor) -> Tensor | None:
    """The cost's ``x_ref`` when its shape fits ``x (B, T+1, n)`` (else None)."""
    ref = getattr(getattr(problem, "cost", None), "x_ref", None)
    if not torch.is_tensor(ref) or x.ndim != 3:
        return None
    B, T1, n = x.shape
    return ref if tuple(ref.shape) in ((n,), (T1, n), (1, T1, n), (B, T1, n)) else None


def _bound(value: Any, m: int) -> float | Tensor | None:
    """A solver's ``u_min`` / ``u_max`` option when it is a number or ``(m,)``."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if torch.is_tensor(value) and (value.numel() == 1 or tuple(value.shape) == (m,)):
        return value
    return None


class TensorBoardLogger:
    """Writes a solver's convergence to TensorBoard event files in ``log_dir``.

    Args:
        log_dir: directory for the event files (created if missing).
        plot_elements: how many batch elements the final trajectory figure shows.
        dt: time step for the figure's time axis in seconds (step index when None).
        save_png: when True, :meth:`log_result` also saves its figures as
            ``log_dir/trajectories.png`` and ``log_dir/convergence.png`` (overwritten by
            a later ``log_result`` into the same directory).
        state_labels: ``n`` names for the state panels of the trajectory figure;
            default: the model's ``state_names`` when it has them, else ``x[i]``.
        control_labels: ``m`` names for the control panels; as above
            (``control_names``, else ``u[j]``).

    Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        log_dir: str | Path,
        plot_elements: int = 4,
        dt: float | None = None,
        *,
        save_png: bool = False,
        state_labels: Sequence[str] | None = None,
        control_labels: Sequence[str] | None = None,
    ):
        from torch.utils.tensorboard import SummaryWriter

        if (
            not isinstance(plot_elements, int)
            or isinstance(plot_elements, bool)
            or plot_elements < 0
        ):
            raise ValueError(f"plot_elements must be an int >= 0, got {plot_elements!r}")
        if dt is not None and (
            isinstance(dt, bool)
            or not isinstance(dt, (int, float))
            or not math.isfinite(dt)
            or dt <= 0
        ):
            raise ValueError(f"dt must be a positive finite number or None, got {dt!r}")
        if not isinstance(save_png, bool):
            raise TypeError(f"save_png must be a bool, got {save_png!r}")
        for name, labels in (("state_labels", state_labels), ("control_labels", control_labels)):
            if labels is not None and (
                isinstance(labels, str) or not all(isinstance(s, str) for s in labels)
            ):
                raise TypeError(f"{name} must be a sequence of str (one per dim), got {labels!r}")
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.writer = SummaryWriter(log_dir=str(self.log_dir))
        self.plot_elements = plot_elements
        self.dt = dt
        self.save_png = save_png
        self.state_labels = None if state_labels is None else tuple(state_labels)
        self.control_labels = None if control_labels is None else tuple(control_labels)
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
        """Final records and figures of ``result`` (a :class:`torchslq.SolverResult`
        with batched ``x (B, T+1, n)``, ``u (B, T, m)``, ``cost (B,)`` and ``history``)
        of ``problem`` (optional: names, goal and bounds for the figures)."""
        w = self.writer
        cost = result.cost.detach().reshape(-1)
        finite = cost[torch.isfinite(cost)]
        if finite.numel() > 0:
            w.add_histogram("final/cost", finite.to("cpu", torch.float64), 0)
        conv = result.converged.reshape(-1).double().mean().item()
        w.add_scalar("final/converged_fraction", conv, 0)
        self._log_figures(result, problem)
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

    def _log_figures(self, result: Any, problem: Any) -> None:
        from .plotting import convergence_figure, state_control_names, trajectory_figure

        figures = []
        x, u = result.x, result.u
        if x.ndim < 3 or x.shape[0] > 0:  # an empty batch has nothing to draw
            n, m = x.shape[-1], u.shape[-1]
            s_names, c_names = state_control_names(getattr(problem, "dynamics", None))
            s_names = s_names if s_names is not None and len(s_names) == n else None
            c_names = c_names if c_names is not None and len(c_names) == m else None
            options = getattr(result, "options", None)
            options = options if isinstance(options, dict) else {}
            fig = trajectory_figure(
                x,
                u,
                dt=self.dt,
                max_elements=self.plot_elements,
                state_labels=self.state_labels or s_names,
                control_labels=self.control_labels or c_names,
                x_ref=_goal(problem, x),
                u_min=_bound(options.get("u_min"), m),
                u_max=_bound(options.get("u_max"), m),
            )
            figures.append(("trajectories", fig))
        history = getattr(result, "history", None) or {}
        curves = {k: history[k] for k in ("cost", "grad_norm") if torch.is_tensor(history.get(k))}
        if curves:
            name = str(self._options.get("solver", "solver"))
            figures.append(("convergence", convergence_figure({name: curves})))
        for tag, fig in figures:
            if self.save_png:
                fig.savefig(self.log_dir / f"{tag}.png", dpi=110)
            self.writer.add_figure(tag, fig, 0, close=True)

    # lifecycle ------------------------------------------------------------------------
    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()

    def __enter__(self) -> TensorBoardLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
