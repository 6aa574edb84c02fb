"""Kernels specialised to one generated model's functions, for large passes.

The generic CPU kernels (the RK4 derivative passes, the rollouts) take a model's
functions as first-class function values (:mod:`.model_fns`): compiled once per machine
for every model, but each call of the model is a call through a pointer that numba
cannot inline. A module generated for a model (:mod:`torchslq.dynamics.codegen`) also
defines those kernels with its functions bound in (the same source, rewritten), where
they are inlined: measured at B = 512, T = 50 on the cart-pole, the closed-loop rollout
takes 6.5-7.0 ms instead of 7.7-7.9 ms and the Jacobian pass ~10% less. Compiling them
costs seconds per model, once per machine (numba caches them with the module), so the
launchers take them for passes of at least :data:`MIN_ROWS` rows (rows x steps for
a rollout): a small solve (real-time MPC, a first try of a new model) starts without
that compilation, a large one repays it. Once a large pass has taken a kernel for a
dtype, the process has it compiled, and smaller passes take it too: a batch whose
working set shrinks to its last slow elements (or a small solve after a large one)
keeps the inlined kernels and skips typing the function values at every launch
(measured on the cart-pole, T = 50: ILQR at B = 1 after a B = 64 solve 0.65 ms per
iteration instead of 0.73).
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

#: a pass over fewer rows (points, or rollout element-steps) runs the generic kernels
MIN_ROWS = 1024

_BOUND: dict = {}
_TAKEN: set = set()  # (rhs, kernel name, dtype) a large pass has taken in this process


def register(module: ModuleType) -> None:
    """Register a generated module under its ``rhs``; it defines ``step``,
    ``ROLLOUT_MODE`` (how its rollout kernels take the model,
    :data:`~._numba_kernels.STEP_RK4` or ``STEP_DISCRETE``),
    :func:`~._numba_kernels.closed_loop_rollout_kernel` and
    :func:`~._numba_kernels.step_rows_kernel` (less ``step`` and ``rhs``), and
    ``jacobians_kernel`` / ``hessians_kernel`` (the step's derivatives, with the
    argument list of :func:`torchslq.dynamics._numba_rk4.rk4_lanes_kernel` less
    ``rhs`` and ``derivs``)."""
    _BOUND[module.rhs] = module


def is_generated(fn) -> bool:
    """Whether ``fn`` is the ``rhs`` of a generated module (whose step reproduces the
    model's ``forward``, so the forward may run it)."""
    try:
        return fn in _BOUND
    except TypeError:  # unhashable
        return False


def bound_kernels(fn, rows: int, kernel: str, dtype) -> ModuleType | None:
    """The generated module whose ``rhs`` is ``fn`` when a pass of ``rows`` rows over
    arrays of ``dtype`` should run its ``kernel`` (a name): the pass is large enough
    (:data:`MIN_ROWS`), or a large pass has taken that kernel for ``dtype`` in this
    process (it is compiled); else None."""
    try:
        module = _BOUND.get(fn)
    except TypeError:  # unhashable
        return None
    if module is None:
        return None
    key = (fn, kernel, np.dtype(dtype).str)
    if rows >= MIN_ROWS:
        _TAKEN.add(key)
        return module
    return module if key in _TAKEN else None
