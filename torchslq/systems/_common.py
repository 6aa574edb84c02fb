"""Shared helpers for the example systems: parameters, Jacobian assembly, and the one
source of each model's equations.

A model's equations are written once, as plain functions of its state, control and
parameters that use only arithmetic and :func:`sin` / :func:`cos` (see
:func:`row_source`): ``forward``, ``jacobians`` and ``vhp`` call them with torch tensors
(one tensor per component, :func:`components`: batched, broadcasting), and the model's
compiled hooks (:meth:`torchslq.ContinuousDynamics.compiled_rhs`, ...) are the same
functions compiled by numba for one row (:mod:`torchslq.systems._jit`). The curvature
pattern a compiled hook declares is found from the torch form
(:func:`curvature_pattern`), never kept by hand.

Parameters are stored as python floats (scalars) or tensors. A tensor parameter is
registered as a buffer (or kept as an ``nn.Parameter`` when given as one, so it can be
learned) and must broadcast against the *leading* dims of the inputs, i.e. against
``x[..., 0]``: a ``(B, 1)`` mass for states ``x (B, T, n)`` gives each batch element its
own mass; for ``x (B, n)`` use shape ``(B,)``.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

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


def _is_zero(e) -> bool:
    """Whether ``e`` is the number zero (a structural zero of an equation's source)."""
    return isinstance(e, float | int) and e == 0


# ---------------------------------------------------------------------------------------
# the one source of a model's equations


def sin(a):
    """``torch.sin`` in the torch form of a model's equations, ``math.sin`` in their
    numba form (:mod:`torchslq.systems._jit` registers that)."""
    return torch.sin(a)


def cos(a):
    """``torch.cos`` in the torch form, ``math.cos`` in the numba form (as :func:`sin`)."""
    return torch.cos(a)


_SOURCES: list[Callable] = []


def row_source(fn: Callable) -> Callable:
    """Mark ``fn`` as (part of) a model's equations: a plain function of indexable
    state, control and parameters (``x[i]``, ``u[i]``, ``p[i]``) using only arithmetic,
    :func:`sin`, :func:`cos` and other such functions, returning numbers or tuples of
    them (``0.0`` where an entry is zero whatever the inputs). The torch form calls it
    with tuples of tensors (:func:`components`), the numba form compiles it for one row
    of 1-d arrays (numba is imported only then: :mod:`torchslq.systems._jit` registers
    every marked function as callable from compiled code)."""
    _SOURCES.append(fn)
    jit = sys.modules.get(__package__ + "._jit")
    if jit is not None:
        jit.register(fn)
    return fn


def components(t: Tensor) -> tuple[Tensor, ...]:
    """``t (..., k)`` as ``k`` tensors ``(...)``: what a :func:`row_source` indexes."""
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


_PATTERNS: dict = {}


def curvature_pattern(
    key, make: Callable[[tuple[float, ...]], nn.Module], n_params: int
) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """A model's curvature pattern, found from its torch form: the outputs whose Hessian
    in ``z = (x, u)`` is nonzero and the ``z`` entries where any of them is, by
    automatic differentiation of ``make(params).forward`` at a few random points and random
    positive parameters (float64), so that it holds for every parameter value. Cached
    under ``key`` (the model's class and structural sizes).

    (Autograd's double backward rather than ``torch.func.hessian``: the first call of a
    ``torch.func`` transform imports ``torch._dynamo``, seconds on a busy machine.)"""
    got = _PATTERNS.get(key)
    if got is not None:
        return got
    g = torch.Generator().manual_seed(0)
    curved = None
    with torch.inference_mode(False), torch.enable_grad():
        for _ in range(3):
            params = tuple(float(v) for v in 0.5 + torch.rand(n_params, generator=g))
            model = make(params).double()
            n, m = model.state_dim, model.control_dim
            z = torch.randn(n + m, generator=g, dtype=torch.float64)
            H = _hessians(lambda z, model=model, n=n: model(z[:n], z[n:]), z)
            nonzero = H.detach() != 0  # (NaN counts as nonzero)
            curved = nonzero if curved is None else curved | nonzero
    outs = tuple(int(j) for j in torch.nonzero(curved.flatten(1).any(1)).flatten())
    ents = tuple(int(a) for a in torch.nonzero(curved.any(0).any(0)).flatten())
    _PATTERNS[key] = (outs, ents)
    return outs, ents


def _hessians(f: Callable[[Tensor], Tensor], z: Tensor) -> Tensor:
    """Every output's Hessian ``(n_out, k, k)`` of ``f`` at ``z (k,)``."""
    from torch.autograd.functional import jacobian

    return jacobian(lambda z: jacobian(f, z, create_graph=True), z)
