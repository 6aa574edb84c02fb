"""Shape helpers for hot paths."""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["broadcast_shapes"]


def broadcast_shapes(*shapes: Sequence[int]) -> torch.Size:
    """``torch.broadcast_shapes`` in plain Python on shape tuples.

    Same result and error type (``RuntimeError``) for non-broadcastable shapes;
    ``torch.broadcast_shapes`` goes through the symbolic-shape reference implementation
    and measured 80-900 us a call, which added up in the per-time-step loops (box QP,
    Riccati set-up, line-search cost evaluations).
    """
    if torch.compiler.is_compiling():  # traced code: the symbolic version is the right one
        return torch.broadcast_shapes(*shapes)
    ndim = 0
    for shape in shapes:
        ndim = max(ndim, len(shape))
    out = [1] * ndim
    for shape in shapes:
        offset = ndim - len(shape)
        for i, d in enumerate(shape):
            if d != 1:
                j = offset + i
                if out[j] == 1:
                    out[j] = d
                elif out[j] != d:
                    raise RuntimeError(
                        f"shapes {[tuple(s) for s in shapes]} cannot be broadcast together"
                    )
    return torch.Size(out)
