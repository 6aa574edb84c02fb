"""Stopping rules shared by the solver loops (SLQ/iLQR/DDP and GoPRONTO)."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["CURVE_ROUNDOFF_NOISE", "ROUNDOFF_NOISE", "roundoff_tolerance", "stall_update"]

# a cost change below ROUNDOFF_NOISE * eps * max(|J|, 1) cannot be told from rounding
ROUNDOFF_NOISE = 64.0
# the bound of GoPRONTO/PRONTO's line search on the curve (a tighter one: the
# reproductions of the GoPRONTO paper's Figures 5-7 and Table II are measured with it)
CURVE_ROUNDOFF_NOISE = 8.0


def roundoff_tolerance(J: Tensor, noise: float = ROUNDOFF_NOISE) -> Tensor:
    """``noise * eps * max(|J|, 1)`` (eps of ``J``'s dtype): the smallest change of the cost
    ``J`` that rounding cannot explain (used by the line searches and the stall rule)."""
    return noise * torch.finfo(J.dtype).eps * J.abs().clamp_min(1.0)


def stall_update(
    count: Tensor,
    g_ref: Tensor,
    accept: Tensor,
    J_old: Tensor,
    J_new: Tensor,
    grad_norm: Tensor,
    stall_iters: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """One iteration of the round-off stall rule (status ``stalled``).

    An element stalls when ``stall_iters`` consecutive accepted steps changed its cost by
    no more than rounding noise (``64 eps max(|J|, 1)``) and its gradient norm did not
    halve over that window: its line search is accepting noise (e.g. a float32 solve
    asked for a tolerance float32 cannot resolve). The gradient test matters: near a
    minimum the cost change is quadratic in the gradient and reaches the noise first
    while the gradient still falls.

    Args:
        count: ``(B,)`` int, consecutive noise-level accepted steps so far;
        g_ref: ``(B,)`` gradient norm at the start of that run;
        accept: ``(B,)`` bool, the step of this iteration was accepted;
        J_old, J_new: ``(B,)`` costs before and after the step;
        grad_norm: ``(B,)`` gradient norm at the start of this iteration.

    Returns:
        ``(stalled (B,) bool, count, g_ref)`` (the new counters).
    """
    flat = accept & ((J_old - J_new).abs() <= roundoff_tolerance(J_old))
    if flat.is_cpu and stall_iters >= 1 and not bool(flat.any()):
        # no step at noise level (most iterations): every count restarts at 0 and no
        # element stalls; four ops instead of nine (on a GPU the test would be a sync)
        return torch.zeros_like(accept), torch.zeros_like(count), g_ref
    count = torch.where(flat, count + 1, 0)
    g_ref = torch.where(count == 1, grad_norm, g_ref)
    full = count >= stall_iters
    stalled = full & (grad_norm > 0.5 * g_ref)
    return stalled, torch.where(full, 0, count), g_ref
