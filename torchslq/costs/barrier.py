"""Log barrier for symmetric input bounds ``|u| <= u_max`` (GoPRONTO, Section V.5).

The constraint ``1 - (u / u_max)^2 > 0`` (elementwise) enters the cost as
``eps * b(u)`` with ``b(u) = -sum_{t,i} log(1 - (u_{t,i} / u_max_i)^2)``: the barrier
approach of Hauser & Saccon (2006), ref. [12] of the GoPRONTO paper, with a weight ``eps``
driven to a small value by the solver. Outside the bounds the value is ``+inf``, so a line
search never accepts an infeasible trial and iterates stay strictly feasible.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["box_log_barrier", "box_log_barrier_derivatives"]


def box_log_barrier(u: Tensor, u_max: Tensor) -> Tensor:
    """``b(u) = -sum_{t,i} log(1 - (u_{t,i}/u_max_i)^2)`` of ``u (..., T, m)`` -> ``(...)``.

    ``u_max`` broadcasts against ``u`` (``(m,)``, ``(T, m)`` or ``(B, T, m)``); ``+inf``
    where some ``|u| >= u_max`` (or ``u`` is not finite).
    """
    s = u / u_max
    slack = 1.0 - s * s
    feasible = (slack > 0).flatten(-2).all(-1)
    val = -torch.log(slack.clamp_min(torch.finfo(u.dtype).tiny)).sum(dim=(-1, -2))
    return torch.where(feasible & torch.isfinite(val), val, torch.full_like(val, float("inf")))


def box_log_barrier_derivatives(u: Tensor, u_max: Tensor) -> tuple[Tensor, Tensor]:
    """Gradient and (diagonal) Hessian of :func:`box_log_barrier` per entry: ``(..., T, m)``
    each: ``b' = 2 s / ((1 - s^2) u_max)`` and ``b'' = 2 (1 + s^2) / ((1 - s^2)^2 u_max^2)``
    with ``s = u / u_max`` (meaningful only inside the bounds)."""
    s = u / u_max
    slack = 1.0 - s * s
    grad = 2.0 * s / (slack * u_max)
    hess = 2.0 * (1.0 + s * s) / (slack * slack * u_max * u_max)
    return grad, hess
