"""Matplotlib figures for trajectories and convergence, used by the logger, CLI and examples.

Every function returns a ``matplotlib.figure.Figure`` (Agg backend, no screen needed);
save it with ``fig.savefig(path)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from torch import Tensor  # noqa: E402

__all__ = ["trajectory_figure", "convergence_figure"]


def _np(t: Tensor):
    return t.detach().to("cpu", torch.float64).numpy()


def trajectory_figure(
    x: Tensor,
    u: Tensor,
    dt: float | None = None,
    max_elements: int = 4,
    state_labels: Sequence[str] | None = None,
    control_labels: Sequence[str] | None = None,
    title: str | None = None,
) -> Figure:
    """States and controls of the first ``max_elements`` problems of a batch.

    Args:
        x: ``(B, T+1, n)`` or ``(T+1, n)``; u: ``(B, T, m)`` or ``(T, m)``.
        dt: time step for the horizontal axis (step index when None).
    """
    if x.ndim == 2:
        x, u = x.unsqueeze(0), u.unsqueeze(0)
    Bn, T1, n = x.shape
    m = u.shape[-1]
    k = min(max_elements, Bn)
    scale = 1.0 if dt is None else dt
    tx = [i * scale for i in range(T1)]
    tu = tx[:-1]
    fig, axes = plt.subplots(n + m, 1, figsize=(7, 1.8 * (n + m) + 0.5), sharex=True, squeeze=False)
    xs, us = _np(x[:k]), _np(u[:k])
    for i in range(n):
        ax = axes[i, 0]
        for b in range(k):
            ax.plot(tx, xs[b, :, i], lw=1.2, label=f"#{b}")
        ax.set_ylabel(state_labels[i] if state_labels else f"x[{i}]")
    for j in range(m):
        ax = axes[n + j, 0]
        for b in range(k):
            ax.step(tu, us[b, :, j], where="post", lw=1.2)
        ax.set_ylabel(control_labels[j] if control_labels else f"u[{j}]")
    axes[-1, 0].set_xlabel("time [s]" if dt is not None else "step")
    if k > 1:
        axes[0, 0].legend(loc="best", fontsize=7, ncol=min(k, 4))
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def convergence_figure(
    histories: dict[str, Tensor],
    optimum: float | None = None,
    key: str = "cost",
    title: str | None = None,
    element: int = 0,
) -> Figure:
    """Convergence of one batch element for several solvers.

    Args:
        histories: ``{label: history_tensor}`` where each tensor is ``(B, iters+1)`` or
            ``(iters+1,)`` (e.g. ``result.history["cost"]``).
        optimum: when given, plots the relative error ``(J_k - J*) / |J*|`` on a log axis
            (the paper's Figure 2); otherwise the raw values on a log axis.
    """
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, h in histories.items():
        h = h[element] if h.ndim == 2 else h
        vals = _np(h)
        if optimum is not None:
            vals = abs(vals - optimum) / max(abs(optimum), 1e-300)
        ax.semilogy(range(len(vals)), vals, marker=".", label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("relative cost (J - J*)/J*" if optimum is not None else key)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig


def save_figure(fig: Figure, path: str | Path) -> Path:
    """``tight_layout``, create the parent folder, save at 120 dpi and close ``fig``;
    returns the path."""
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
