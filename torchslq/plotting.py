"""Matplotlib figures for trajectories and convergence, used by the logger, CLI and examples.

Every function returns a ``matplotlib.figure.Figure`` (Agg backend, no screen needed);
save it with ``fig.savefig(path)`` or :func:`save_figure`.

* :func:`trajectory_figure`: states and controls of the first elements of a batch, one
  panel per state / control, with optional goal (``x_ref``, dashed) and bound (dotted)
  lines and one legend for the whole figure;
* :func:`convergence_figure`: cost and gradient norm per iteration, for the whole batch
  (median line and a percentile band over the finite values) or for single elements;
* :func:`state_control_names`: the state / control names a dynamics model declares
  (class attributes ``state_names`` / ``control_names``), for the labels above.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from torch import Tensor  # noqa: E402

__all__ = ["trajectory_figure", "convergence_figure", "save_figure", "state_control_names"]

#: Line styles: goal lines dashed, bound lines dotted (also their ``gid``).
GOAL_STYLE = {"ls": "--", "lw": 1.0}
BOUND_STYLE = {"ls": ":", "lw": 1.2, "color": "tab:red"}


def _np(t: Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float64).numpy()


def _color(b: int) -> str:
    return f"C{b % 10}"


def state_control_names(dynamics: Any) -> tuple[tuple[str, ...] | None, tuple[str, ...] | None]:
    """``(state_names, control_names)`` declared by ``dynamics`` (or by the continuous
    model a discretised one wraps, ``dynamics.continuous``), each None when absent or
    when its length differs from the model's ``state_dim`` / ``control_dim``.

    Models declare them as attributes ``state_names`` / ``control_names``: tuples of
    ``n`` / ``m`` strings (the zoo in :mod:`torchslq.systems` does, with units)."""

    def pick(attr: str, dim_attr: str) -> tuple[str, ...] | None:
        for model in (dynamics, getattr(dynamics, "continuous", None)):
            names = getattr(model, attr, None) if model is not None else None
            if names is None or isinstance(names, str):
                continue
            names = tuple(str(s) for s in names)
            dim = getattr(dynamics, dim_attr, None)
            if dim is None or len(names) == dim:
                return names
        return None

    return pick("state_names", "state_dim"), pick("control_names", "control_dim")


def _labels(name: str, labels: Sequence[str] | None, dim: int, what: str) -> list[str] | None:
    if labels is None:
        return None
    if isinstance(labels, str):
        raise ValueError(f"{name} must be a sequence of {dim} strings, got the string {labels!r}")
    labels = [str(s) for s in labels]
    if len(labels) != dim:
        raise ValueError(f"{name} has {len(labels)} names but there are {dim} {what}")
    return labels


def _bound(
    name: str, value: float | Tensor | Sequence[float] | None, dim: int
) -> np.ndarray | None:
    """``value`` as a float64 array ``(dim,)`` (a scalar broadcasts), or None."""
    if value is None:
        return None
    t = torch.as_tensor(value).detach().to("cpu", torch.float64)
    if t.numel() == 1:
        return np.full(dim, t.reshape(()).item())
    if t.ndim != 1 or t.shape[0] != dim:
        raise ValueError(f"{name} must be a float or of shape ({dim},), got {tuple(t.shape)}")
    return t.numpy()


def _draw_bounds(ax, lo: np.ndarray | None, hi: np.ndarray | None, i: int) -> bool:
    drawn = False
    for arr in (lo, hi):
        if arr is not None and math.isfinite(arr[i]):
            ax.axhline(arr[i], gid="bound", **BOUND_STYLE)
            drawn = True
    return drawn


def trajectory_figure(
    x: Tensor,
    u: Tensor,
    dt: float | None = None,
    max_elements: int = 4,
    state_labels: Sequence[str] | None = None,
    control_labels: Sequence[str] | None = None,
    title: str | None = None,
    x_ref: Tensor | None = None,
    u_min: float | Tensor | None = None,
    u_max: float | Tensor | None = None,
    x_min: float | Tensor | None = None,
    x_max: float | Tensor | None = None,
) -> Figure:
    """States and controls of the first ``max_elements`` problems of a batch.

    One panel per state (solid lines) and per control (steps held over each interval);
    element ``b`` has colour ``C{b}`` in every panel, and one legend above the first
    panel names each drawn element once (``#b``) and the goal / bound line styles. The
    legend is left out when it would hold a single element and nothing else.

    Args:
        x: states ``(B, T+1, n)`` or ``(T+1, n)``.
        u: controls ``(B, T, m)`` or ``(T, m)`` (``(B, T+1, m)`` / ``(T+1, m)``, a
            control per knot, is drawn too).
        dt: time step for the horizontal axis in seconds (step index when None).
        max_elements: how many elements (the first ones) to draw.
        state_labels: ``n`` names for the state panels (default ``x[i]``), e.g. a
            model's ``state_names`` (see :func:`state_control_names`).
        control_labels: ``m`` names for the control panels (default ``u[j]``).
        title: figure title.
        x_ref: goal states drawn dashed: ``(n,)`` (one level per state, black),
            ``(T+1, n)`` (a reference trajectory, black) or ``(B, T+1, n)`` (one per
            element, in its colour).
        u_min, u_max: control bounds drawn dotted: a float or ``(m,)``; ``±inf`` (or
            NaN) entries are skipped.
        x_min, x_max: state bounds drawn dotted: a float or ``(n,)``; as above.

    Raises:
        ValueError: shapes that do not fit (``u`` against ``x``, labels of the wrong
            length, ``x_ref`` or a bound of the wrong shape); the message names the
            argument.
    """
    if x.ndim not in (2, 3) or u.ndim != x.ndim:
        raise ValueError(
            f"x and u must be (B, T+1, n) and (B, T, m), or (T+1, n) and (T, m); got "
            f"{tuple(x.shape)} and {tuple(u.shape)}"
        )
    if x.ndim == 2:
        x, u = x.unsqueeze(0), u.unsqueeze(0)
    Bn, T1, n = x.shape
    m = u.shape[-1]
    if u.shape[0] != Bn or u.shape[1] not in (T1 - 1, T1):
        raise ValueError(
            f"u has shape {tuple(u.shape)} but x {tuple(x.shape)} needs u of shape "
            f"({Bn}, {T1 - 1}, m)"
        )
    s_labels = _labels("state_labels", state_labels, n, "states (x.shape[-1])")
    c_labels = _labels("control_labels", control_labels, m, "controls (u.shape[-1])")
    lo_u, hi_u = _bound("u_min", u_min, m), _bound("u_max", u_max, m)
    lo_x, hi_x = _bound("x_min", x_min, n), _bound("x_max", x_max, n)
    ref = None
    if x_ref is not None:
        ref = torch.as_tensor(x_ref).detach().to("cpu", torch.float64)
        if ref.ndim == 3 and ref.shape[0] == 1:
            ref = ref[0]
        ok = (ref.ndim == 1 and ref.shape == (n,)) or (
            ref.ndim in (2, 3)
            and ref.shape[-2:] == (T1, n)
            and (ref.ndim == 2 or ref.shape[0] == Bn)
        )
        if not ok:
            raise ValueError(
                f"x_ref must have shape ({n},), ({T1}, {n}) or ({Bn}, {T1}, {n}), "
                f"got {tuple(ref.shape)}"
            )
        ref = ref.numpy()

    k = max(0, min(max_elements, Bn))
    scale = 1.0 if dt is None else dt
    tx = [i * scale for i in range(T1)]
    tu = tx[: u.shape[1]]
    fig, axes = plt.subplots(n + m, 1, figsize=(7, 1.8 * (n + m) + 0.8), sharex=True, squeeze=False)
    xs, us = _np(x[:k]), _np(u[:k])
    any_goal = any_bound = False
    for i in range(n):
        ax = axes[i, 0]
        for b in range(k):
            ax.plot(tx, xs[b, :, i], lw=1.2, color=_color(b))
        if ref is not None and ref.ndim == 1:
            if math.isfinite(ref[i]):
                ax.axhline(ref[i], color="k", gid="goal", **GOAL_STYLE)
                any_goal = True
        elif ref is not None and ref.ndim == 2:
            ax.plot(tx, ref[:, i], color="k", gid="goal", **GOAL_STYLE)
            any_goal = True
        elif ref is not None:
            for b in range(k):
                ax.plot(tx, ref[b, :, i], color=_color(b), gid="goal", **GOAL_STYLE)
                any_goal = True
        any_bound |= _draw_bounds(ax, lo_x, hi_x, i)
        ax.set_ylabel(s_labels[i] if s_labels else f"x[{i}]")
    for j in range(m):
        ax = axes[n + j, 0]
        for b in range(k):
            ax.step(tu, us[b, :, j], where="post", lw=1.2, color=_color(b))
        any_bound |= _draw_bounds(ax, lo_u, hi_u, j)
        ax.set_ylabel(c_labels[j] if c_labels else f"u[{j}]")
    axes[-1, 0].set_xlabel("time [s]" if dt is not None else "step")

    handles = [Line2D([], [], color=_color(b), lw=1.2, label=f"#{b}") for b in range(k)]
    if any_goal:
        handles.append(Line2D([], [], color="k", label="goal", **GOAL_STYLE))
    if any_bound:
        handles.append(Line2D([], [], label="bound", **BOUND_STYLE))
    if len(handles) > 1:  # above the first panel, over no curve
        axes[0, 0].legend(
            handles=handles,
            loc="lower left",
            bbox_to_anchor=(0.0, 1.02),
            ncol=min(len(handles), 6),
            fontsize=7,
            frameon=False,
            borderaxespad=0.0,
        )
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


_PRETTY = {"cost": "cost", "grad_norm": "gradient norm", "step": "step size"}


def _band_name(band: tuple[float, float]) -> str:
    lo, hi = band
    if (lo, hi) == (0.0, 1.0):
        return "min-max"
    return f"{100 * lo:g}-{100 * hi:g} percentile"


def _batch_quantiles(h: Tensor, q: Sequence[float]) -> Tensor:
    """Quantiles ``(len(q), iters)`` over the batch of ``h (B, iters)``, each over the
    finite entries of its column only (NaN where a column has none, or ``B = 0``);
    linear interpolation as :func:`torch.quantile`."""
    v = h.detach().to("cpu", torch.float64)
    if v.ndim != 2:
        raise ValueError(f"h must have shape (B, iters), got {tuple(v.shape)}")
    qs = torch.tensor(list(q), dtype=torch.float64)
    if v.shape[0] == 0 or v.shape[1] == 0:
        return torch.full((len(qs), v.shape[1]), math.nan, dtype=torch.float64)
    v = torch.where(torch.isfinite(v), v, math.nan)
    return torch.nanquantile(v, qs, dim=0)


def convergence_figure(
    histories: Mapping[str, Tensor | Mapping[str, Tensor]],
    optimum: float | None = None,
    key: str = "cost",
    title: str | None = None,
    element: int | None = None,
    *,
    elements: Sequence[int] = (),
    band: tuple[float, float] | None = (0.1, 0.9),
    keys: Sequence[str] = ("cost", "grad_norm"),
) -> Figure:
    """Convergence per iteration of one or more solvers, over the whole batch.

    For a batch history ``(B, iters+1)`` each solver gets its median (solid line with
    dots, legend ``"<label> median"``) and a shaded band between the ``band``
    quantiles (legend ``"<label> 10-90 percentile"``, or ``"min-max"`` for
    ``band=(0, 1)``), per iteration over the finite values only: non-finite elements
    are ignored, and an iteration with none (or an empty batch) leaves a gap. A single
    element (``(iters+1,)`` or ``B = 1``) is drawn as one line labelled ``<label>``.
    The vertical axis is logarithmic (linear only when nothing positive is drawn).

    Args:
        histories: ``{label: history}``; a history is a tensor ``(B, iters+1)`` or
            ``(iters+1,)`` (e.g. ``result.history["cost"]``, drawn in the panel
            ``key``), or a mapping of such tensors (e.g. ``result.history``), drawn one
            panel per entry of ``keys`` it has.
        optimum: when given, the panel ``key`` shows the relative error
            ``|J_k - J*| / |J*|`` per element (the paper's Figure 2) instead of ``J_k``.
        key: the name of a tensor history's panel (default ``"cost"``).
        title: figure title.
        element: when given, only this batch element of each ``(B, iters+1)``
            history is drawn (one line per solver, the former default ``0``).
        elements: batch elements drawn as thin extra lines over the median and band
            (legend ``"<label> #b"``); indices past ``B`` are skipped.
        band: the quantile levels ``(lo, hi)`` in ``[0, 1]`` of the shaded band;
            None draws the median only.
        keys: the panels drawn from mapping histories, in order (default cost and
            gradient norm); entries no history has are left out.
    """
    if band is not None and not (0.0 <= band[0] <= band[1] <= 1.0):
        raise ValueError(f"band must be (lo, hi) with 0 <= lo <= hi <= 1, got {band!r}")
    normed: dict[str, dict[str, Tensor]] = {}
    for label, h in histories.items():
        if isinstance(h, Mapping):
            normed[label] = {k: v for k, v in h.items() if torch.is_tensor(v)}
        else:
            normed[label] = {key: h}
    panels = [p for p in dict.fromkeys([*keys, key]) if any(p in d for d in normed.values())]
    if not panels:
        panels = [key]
    P = len(panels)
    fig, axes = plt.subplots(
        P, 1, figsize=(6, 4 if P == 1 else 3.2 * P), sharex=True, squeeze=False
    )
    for p, panel in enumerate(panels):
        ax = axes[p, 0]
        positive = False
        for c, (label, d) in enumerate(normed.items()):
            if panel not in d:
                continue
            color = _color(c)
            h = d[panel].detach().to("cpu", torch.float64)
            if h.ndim == 2 and element is not None:
                if not -h.shape[0] <= element < h.shape[0]:
                    raise ValueError(
                        f"element {element} is out of range for a batch of {h.shape[0]}"
                    )
                h = h[element]
            if h.ndim not in (1, 2):
                raise ValueError(
                    f"history {label!r}[{panel!r}] must be (B, iters+1) or (iters+1,), "
                    f"got {tuple(h.shape)}"
                )
            if optimum is not None and panel == key:
                h = (h - optimum).abs() / max(abs(optimum), 1e-300)
            its = np.arange(h.shape[-1])
            if h.ndim == 1 or h.shape[0] == 1:
                vals = _np(h.reshape(-1))
                ax.plot(its, vals, marker=".", color=color, label=label)
                positive |= bool(np.any(np.isfinite(vals) & (vals > 0)))
                continue
            qs = [0.5] if band is None else [0.5, *band]
            stats = _np(_batch_quantiles(h, qs))
            ax.plot(its, stats[0], marker=".", ms=4, color=color, label=f"{label} median")
            shown = stats[0]
            if band is not None:
                ax.fill_between(
                    its, stats[1], stats[2], color=color, alpha=0.25, lw=0,
                    label=f"{label} {_band_name(band)}",
                )  # fmt: skip
                shown = stats
            for b in elements:
                if -h.shape[0] <= b < h.shape[0]:
                    ax.plot(
                        its,
                        _np(h[b]),
                        lw=0.8,
                        alpha=0.7,
                        color=color,
                        ls="-.",
                        label=f"{label} #{b}",
                    )
            positive |= bool(np.any(np.isfinite(shown) & (shown > 0)))
        if positive:
            ax.set_yscale("log")
        if optimum is not None and panel == key:
            ax.set_ylabel("relative cost (J - J*)/J*")
        else:
            ax.set_ylabel(_PRETTY.get(panel, panel))
        ax.grid(True, which="both", alpha=0.3)
    axes[-1, 0].set_xlabel("iteration")
    if axes[0, 0].get_legend_handles_labels()[0]:
        axes[0, 0].legend(fontsize=8)
    if title:
        (axes[0, 0].set_title if P == 1 else fig.suptitle)(title)
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
