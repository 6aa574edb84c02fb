"""A value's second-order Taylor expansion as an autograd function (the stand-ins of the
Hessian pass, :func:`torchslq.dynamics.linearize.second_order_only`)."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["second_order_taylor"]


class _SecondOrderTaylor(torch.autograd.Function):
    """``J dz + dz' H_i dz / 2`` per output ``i`` for ``dz (*lead, k)``, ``J (*lead, n, k)``,
    ``H (*lead, n, k, k)`` symmetric, differentiable (twice) in ``dz`` only.

    Its backward is written in ops on ``(*lead, k, k)`` (the cotangent contracted with
    ``H`` first), so the Hessian pass's second, batched backward never handles the
    ``(*lead, n, k, k)`` products autograd would record for the plain expression
    (those made a learned residual's Hessians 2x slower than the network's alone)."""

    @staticmethod
    def forward(ctx, dz: Tensor, J: Tensor, H: Tensor) -> Tensor:
        ctx.save_for_backward(dz, J, H)
        if not bool(dz.any()):  # at the expansion point (the stand-ins' case): zero
            return dz.new_zeros(J.shape[:-1])
        Hdz = (H * dz[..., None, None, :]).sum(-1)  # (*lead, n, k)
        return ((J + 0.5 * Hdz) * dz.unsqueeze(-2)).sum(-1)

    @staticmethod
    def backward(ctx, g: Tensor):
        dz, J, H = ctx.saved_tensors
        M = (g[..., :, None, None] * H).sum(-3)  # (*lead, k, k): sum_i g_i H_i
        grad = (g.unsqueeze(-1) * J).sum(-2) + (M * dz.unsqueeze(-2)).sum(-1)
        return grad, None, None


def second_order_taylor(dz: Tensor, J: Tensor, H: Tensor) -> Tensor:
    """``J_i dz + dz' H_i dz / 2`` ``(*lead, n)`` for ``dz (*lead, k)`` (the input's
    offset from the expansion point, zero there), ``J (*lead, n, k)`` and ``H (*lead, n,
    k, k)`` symmetric: the value, first and second derivatives in ``dz`` of the expansion
    (it is differentiable twice in ``dz`` only)."""
    return _SecondOrderTaylor.apply(dz, J, H)
