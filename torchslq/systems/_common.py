"""Shared helpers for the example systems: parameters and Jacobian assembly.

Parameters are stored as python floats (scalars) or tensors. A tensor parameter is
registered as a buffer (or kept as an ``nn.Parameter`` when given as one, so it can be
learned) and must broadcast against the *leading* dims of the inputs, i.e. against
``x[..., 0]``: a ``(B, 1)`` mass for states ``x (B, T, n)`` gives each batch element its
own mass; for ``x (B, n)`` use shape ``(B,)``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .._shapes import broadcast_shapes

Scalar = float | Tensor


def set_param(module: nn.Module, name: str, value, *, positive: bool = False, nonneg: bool = False):
    """Store ``value`` on ``module`` as a float, buffer or parameter (validated)."""
    if isinstance(value, Tensor):
        if not value.is_floating_point():
            value = value.to(torch.get_default_dtype())
        v = value.detach()
        if not bool(torch.isfinite(v).all()):
            raise ValueError(f"{name} must be finite")
        if positive and not bool((v > 0).all()):
            raise ValueError(f"{name} must be positive")
        if nonneg and not bool((v >= 0).all()):
            raise ValueError(f"{name} must be nonnegative")
        if isinstance(value, nn.Parameter):
            module.register_parameter(name, value)
        else:
            module.register_buffer(name, value)
        return
    try:
        f = float(value)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name} must be a number or a tensor, got {type(value).__name__}") from err
    if not (f == f and abs(f) != float("inf")):
        raise ValueError(f"{name} must be finite, got {f}")
    if positive and not f > 0:
        raise ValueError(f"{name} must be positive, got {f}")
    if nonneg and not f >= 0:
        raise ValueError(f"{name} must be nonnegative, got {f}")
    setattr(module, name, f)


def get_param(module: nn.Module, name: str, like: Tensor) -> Scalar:
    """Parameter ``name`` as a float, or as a tensor in ``like``'s dtype and device."""
    p = getattr(module, name)
    if isinstance(p, Tensor) and (p.dtype != like.dtype or p.device != like.device):
        return p.to(dtype=like.dtype, device=like.device)  # (a no-op .to still costs a dispatch)
    return p


def lead_shape(x: Tensor, u: Tensor, *params: Scalar) -> torch.Size:
    """Broadcast of the leading dims of ``x``, ``u`` and the tensor parameters
    (:func:`torchslq._shapes.broadcast_shapes`, plain Python: ``torch.broadcast_shapes``
    costs ~80 us a call, which dominated rollouts of these small models)."""
    return broadcast_shapes(
        x.shape[:-1], u.shape[:-1], *(p.shape for p in params if isinstance(p, Tensor))
    )


def stack_vector(entries: list[Scalar], lead: torch.Size, like: Tensor) -> Tensor:
    """``(*lead, len(entries))`` from scalars / broadcastable tensors."""
    cols = [_full(e, lead, like) for e in entries]
    return torch.stack(cols, dim=-1)


def stack_matrix(rows: list[list[Scalar]], lead: torch.Size, like: Tensor) -> Tensor:
    """``(*lead, r, c)`` matrix from a nested list of scalars / broadcastable tensors."""
    r, c = len(rows), len(rows[0])
    flat = [_full(e, lead, like) for row in rows for e in row]
    return torch.stack(flat, dim=-1).reshape(*lead, r, c)


def _full(e: Scalar, lead: torch.Size, like: Tensor) -> Tensor:
    if isinstance(e, Tensor):
        return e.expand(lead)
    return torch.full(lead, float(e), dtype=like.dtype, device=like.device)


def scalar_params_array(module: nn.Module, names: tuple[str, ...]):
    """The parameters ``names`` as a 1-d float64 numpy array for a model's compiled
    functions (:meth:`torchslq.ContinuousDynamics.compiled_rhs`), or None when one is a
    tensor with batch dims (per-element parameters)."""
    vals = []
    for name in names:
        p = getattr(module, name)
        if isinstance(p, Tensor):
            if p.ndim > 0:
                return None
            p = float(p.detach())
        vals.append(float(p))
    import numpy as np

    return np.array(vals, dtype=np.float64)
