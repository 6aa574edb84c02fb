"""Kernels specialised to one model's compiled functions and cached on disk.

The generic CPU kernels (the RK4 derivative passes, the whole-rollout kernel) take a
model's numba functions as arguments, so numba compiles them again for each model in
each process (seconds). A module generated for a model
(:mod:`torchslq.dynamics.codegen`) also defines those kernels with its functions bound
in, cached on disk like the rest of the module; it registers here under its functions,
and the launchers look their function up here and call the bound kernel when there is
one (the same code, compiled once per machine instead of once per process).
"""

from __future__ import annotations

from types import ModuleType

_BOUND: dict = {}


def register(module: ModuleType) -> None:
    """Register a generated module under its ``rhs`` and ``step``; it defines
    ``step(x, u, p, out, work)`` (the model's discrete step: the RK4 step of a
    continuous model's ``rhs``, or ``rhs`` itself), ``rollout`` (the closed-loop rollout
    kernel with ``step`` bound), ``step_rows`` (``step`` on a batch of rows), and ``jacobians_kernel`` / ``hessians_kernel`` (the
    step's derivatives, with the argument list of
    :func:`torchslq.dynamics._numba_rk4.rk4_lanes_kernel` less ``rhs`` and ``derivs``)."""
    _BOUND[module.rhs] = module
    _BOUND[module.step] = module


def bound_kernels(fn) -> ModuleType | None:
    """The generated module whose ``rhs`` or ``step`` is ``fn``, or None."""
    try:
        return _BOUND.get(fn)
    except TypeError:  # unhashable
        return None
