"""The derivatives of an RK4 step on CPU kernels, for models with compiled derivatives.

:class:`~torchslq.dynamics.DiscretizedDynamics` chains a continuous model's analytic
Jacobians and Hessians through the four RK4 stages with batched torch products: a dozen
small products on ``(rows, n, n + m)`` tensors per stage, dispatch- and memory-bound.
When the model gives its right-hand side and its derivatives as numba functions
(:meth:`~torchslq.ContinuousDynamics.compiled_rhs`,
:meth:`~torchslq.ContinuousDynamics.compiled_derivatives`) the same chain runs in one kernel
call (:mod:`torchslq.dynamics._numba_rk4`: the model row by row, the chain's sums across
blocks of rows). Call only where
:func:`torchslq._backend.can_use_compiled` holds for ``x``, ``u`` (and ``s``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import ModuleType
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .._backend import _launch
from .._backend.bound import bound_kernels
from .._backend.model_fns import function_value
from .._shapes import broadcast_shapes
from .base import CompiledDerivatives

__all__ = ["rk4_hooks", "rk4_jacobians_compiled", "rk4_vhp_compiled"]

_module: ModuleType | None = None


def _kernels() -> ModuleType:
    global _module
    if _module is None:
        from . import _numba_rk4

        _module = _numba_rk4
    return _module


class RK4Hooks(NamedTuple):
    rhs: Callable
    derivatives: Callable
    params: np.ndarray
    curved_outputs: np.ndarray  # int64, empty: scan each point's Hessians
    curved_entries: np.ndarray
    #: the functions are a discrete model's step and its derivatives (no RK4 chain)
    discrete: bool = False


def rk4_hooks(rhs, derivatives, discrete: bool = False) -> RK4Hooks:
    """The kernels' arguments from a model's :meth:`~torchslq.ContinuousDynamics.compiled_rhs`
    ``(rhs, params)`` and :meth:`~torchslq.ContinuousDynamics.compiled_derivatives` (a
    function or a :class:`~torchslq.dynamics.CompiledDerivatives`); with ``discrete``,
    a discrete model's generated step and its derivatives."""
    fn, params = rhs
    if isinstance(derivatives, CompiledDerivatives):
        outs = np.unique(np.asarray(derivatives.curved_outputs, dtype=np.int64))
        ents = np.unique(np.asarray(derivatives.curved_entries, dtype=np.int64))  # ascending
        if outs.size == 0 or ents.size == 0:
            raise ValueError("a CompiledDerivatives pattern needs curved outputs and entries")
        return RK4Hooks(fn, derivatives.derivatives, params, outs, ents, discrete)
    empty = np.zeros(0, dtype=np.int64)
    return RK4Hooks(fn, derivatives, params, empty, empty, discrete)


def _kernel_and_functions(
    hooks: RK4Hooks, dtype, static: bool, rows: int, jacobians_only: bool = False
):
    """The derivative kernel for ``hooks`` and the model's functions as its first-class
    function arguments (:mod:`torchslq._backend.model_fns`); for a large pass of a
    generated model, its module's kernel with them bound in (:mod:`torchslq._backend.bound`):
    for ``jacobians_only`` (no weights) its straight-line Jacobian kernel where it has
    one (:func:`torchslq.dynamics.codegen._jacobian_rows_source`)."""
    name = "jacobians_kernel" if static else "hessians_kernel"
    if jacobians_only:
        name = "jacobians_only_kernel"
    bound = bound_kernels(hooks.rhs, rows, name, dtype)
    if bound is not None and hasattr(bound, name):
        return getattr(bound, name), ()
    if hooks.discrete:
        from ._numba_step import step_derivatives_kernel as kernel
    else:
        kernels = _kernels()
        kernel = kernels.rk4_lanes_kernel if static else kernels.rk4_second_derivatives_kernel
    fns = (
        function_value(hooks.rhs, "rhs", dtype, hooks.params.dtype),
        function_value(hooks.derivatives, "derivs", dtype, hooks.params.dtype),
    )
    return kernel, fns


def _rows(x: Tensor, u: Tensor, lead=None) -> tuple[torch.Size, int, Tensor, Tensor]:
    """``x``, ``u`` expanded to ``lead`` (default: their broadcast) as ``(R, .)`` rows."""
    if lead is None:
        lead = broadcast_shapes(x.shape[:-1], u.shape[:-1])
    R = math.prod(lead)
    return lead, R, _as_rows(x, lead, R), _as_rows(u, lead, R)


def _as_rows(t: Tensor, lead, R: int) -> Tensor:
    """``t (..., k)`` expanded to ``lead`` as contiguous ``(R, k)`` rows (no op where it
    is one already: the solvers' trajectories are)."""
    if t.requires_grad:
        t = t.detach()
    if t.shape[:-1] != lead:
        t = t.expand(*lead, t.shape[-1])
    if t.ndim != 2:
        t = t.reshape(R, t.shape[-1])
    return t if t.is_contiguous() else t.contiguous()


def rk4_jacobians_compiled(hooks, dt: float, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """``(A (..., n, n), B (..., n, m))`` of the RK4 step of ``dt`` at ``x (..., n)``,
    ``u (..., m)`` (leading dims broadcast); ``hooks`` from :func:`rk4_hooks`."""
    n, m = x.shape[-1], u.shape[-1]
    lead, R, xr, ur = _rows(x, u)
    A = torch.empty(R, n, n, dtype=x.dtype)
    B = torch.empty(R, n, m, dtype=x.dtype)
    xa, ua = xr.numpy(), ur.numpy()
    no_pattern = np.zeros(0, dtype=np.int64)
    no_weights = np.zeros((0, R, n), dtype=xa.dtype)  # W = 0: no Hessians asked
    no_hessians = np.zeros((0, R, n + m, n + m), dtype=xa.dtype)
    kernel, fns = _kernel_and_functions(hooks, xa.dtype, True, R, jacobians_only=True)
    _launch(
        kernel,
        R,
        1,
        *fns,
        hooks.params,
        float(dt),
        no_pattern,
        no_pattern,
        xa,
        ua,
        no_weights,
        no_hessians,
        A.numpy(),
        B.numpy(),
    )
    return A.view(*lead, n, n), B.view(*lead, n, m)


def rk4_vhp_compiled(
    hooks, dt: float, x: Tensor, u: Tensor, s: Tensor, with_jacobians: bool = False
):
    """Hessian blocks ``(Hxx, Huu, Hux)`` of ``s · step(x, u)`` for the RK4 step of
    ``dt``, each ``(*W, *lead, ., .)`` with ``lead`` the broadcast of ``x``'s and ``u``'s
    leading dims and ``W`` the dims ``s`` has beyond them (several weight vectors per
    point, e.g. the output basis for all output Hessians: the stages are computed once
    per point for all of them). With ``with_jacobians`` returns ``((A, B), blocks)``,
    the step's Jacobians (``(*lead, ., .)``) from the same stages."""
    n, m = x.shape[-1], u.shape[-1]
    nl = len(broadcast_shapes(x.shape[:-1], u.shape[:-1]))
    full = broadcast_shapes(s.shape[:-1], x.shape[:-1], u.shape[:-1])
    Wdims = full[: len(full) - nl]
    lead, R, xr, ur = _rows(x, u, full[len(full) - nl :])
    W = math.prod(Wdims)
    S = s.detach().expand(*full, n).reshape(W, R, n).contiguous()
    # one [u; x] block per row and weight: the returned blocks are views of it, and a
    # Riccati pass reads it whole (_backend.joint_hessians)
    Hz = torch.empty(W, R, m + n, m + n, dtype=x.dtype)
    Hxx, Huu, Hux = Hz[:, :, m:, m:], Hz[:, :, :m, :m], Hz[:, :, :m, m:]
    A = torch.empty(R if with_jacobians else 0, n, n, dtype=x.dtype)
    B = torch.empty(R if with_jacobians else 0, n, m, dtype=x.dtype)
    # a declared pattern: the lanes kernel; else each point's Hessians are scanned
    static = hooks.curved_outputs.size > 0
    kernel, fns = _kernel_and_functions(hooks, xr.numpy().dtype, static, R)
    _launch(
        kernel,
        R,
        W,
        *fns,
        hooks.params,
        float(dt),
        hooks.curved_outputs,
        hooks.curved_entries,
        xr.numpy(),
        ur.numpy(),
        S.numpy(),
        Hz.numpy(),
        A.numpy(),
        B.numpy(),
    )
    blocks = (Hxx.view(*full, n, n), Huu.view(*full, m, m), Hux.view(*full, m, n))
    if with_jacobians:
        return (A.view(*lead, n, n), B.view(*lead, n, m)), blocks
    return blocks
