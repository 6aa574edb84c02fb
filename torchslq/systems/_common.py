"""Shared helpers for the example systems: parameters, Jacobian assembly, and the one
source of each model's equations.

A model's equations are written once, as plain functions of its state, control and
parameters that use only arithmetic and :func:`sin` / :func:`cos`: ``forward``,
``jacobians`` and ``vhp`` call them with torch tensors (one tensor per component,
:func:`components`: batched, broadcasting). On the CPU a model's compiled code is
generated from its ``forward`` (:mod:`torchslq.dynamics.codegen`), as for any user's
model: the zoo has no hand-written compiled code.

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
    if all(_is_zero(e) for row in rows for e in row):
        return like.new_zeros(*lead, r, c)
    flat = [_full(e, lead, like) for row in rows for e in row]
    return torch.stack(flat, dim=-1).reshape(*lead, r, c)


def _full(e: Scalar, lead: torch.Size, like: Tensor) -> Tensor:
    if isinstance(e, Tensor):
        return e.expand(lead)
    return torch.full(lead, float(e), dtype=like.dtype, device=like.device)


def _is_zero(e) -> bool:
    """Whether ``e`` is the number zero (a structural zero of an equation's source)."""
    return isinstance(e, float | int) and e == 0


# ---------------------------------------------------------------------------------------
# the one source of a model's equations


def sin(a):
    """``torch.sin`` (the equations read as plain arithmetic on their components)."""
    return torch.sin(a)


def cos(a):
    """``torch.cos``."""
    return torch.cos(a)


def components(t: Tensor) -> tuple[Tensor, ...]:
    """``t (..., k)`` as ``k`` tensors ``(...)``: what a model's equations index."""
    return t.unbind(-1)


def split_jacobian(J, n: int, lead: torch.Size, like: Tensor) -> tuple[Tensor, Tensor]:
    """``(A (*lead, n, n), B (*lead, n, m))`` from a source's rows of ``[f_x | f_u]``."""
    A = stack_matrix([row[:n] for row in J], lead, like)
    B = stack_matrix([row[n:] for row in J], lead, like)
    return A, B


def weighted_hessians(H, s: Tensor, n: int, lead: torch.Size, like: Tensor):
    """Hessian blocks ``(Hxx, Huu, Hux)`` of ``s · f`` from a source's per-output
    Hessians in ``z = (x, u)`` (``H[j][a][b]``, symmetric; structural zeros ``0.0`` are
    skipped); ``s (..., n)`` may have extra leading dims."""
    w = components(s)
    nz = len(H[0])
    lead = broadcast_shapes(lead, s.shape[:-1])
    E = [[0.0] * nz for _ in range(nz)]
    for a in range(nz):
        for b in range(a, nz):
            acc = 0.0
            for j, Hj in enumerate(H):
                h = Hj[a][b]
                if not _is_zero(h):
                    acc = w[j] * h if _is_zero(acc) else acc + w[j] * h
            E[a][b] = E[b][a] = acc
    Hxx = stack_matrix([row[:n] for row in E[:n]], lead, like)
    Huu = stack_matrix([row[n:] for row in E[n:]], lead, like)
    Hux = stack_matrix([row[:n] for row in E[n:]], lead, like)
    return Hxx, Huu, Hux
