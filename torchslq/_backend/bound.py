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
iteration instead of 0.73). A large pass also notes the kernel and dtype in a file
beside the module (``.taken``): numba has then cached the compiled kernel with the
module, and a later process loads it for its small passes too (a real-time loop at
B = 1 after any large solve of that model on the machine; where numba's cache has been
removed since, that first small pass compiles the kernel again).
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from types import ModuleType

import numpy as np

#: a pass over fewer rows (points, or rollout element-steps) runs the generic kernels
MIN_ROWS = 1024

_ALWAYS = False  # inline_model_kernels: every pass takes the bound kernels

_BOUND: dict = {}
_TAKEN: set = set()  # (rhs, kernel name, dtype) a large pass has taken in this process
_NOTED: dict = {}  # module -> {(kernel name, dtype)} read from its .taken file


def _taken_file(module: ModuleType) -> Path | None:
    path = getattr(module, "__file__", None)
    return None if path is None else Path(path).with_suffix(".taken")


def _noted(module: ModuleType) -> set:
    """``(kernel, dtype)`` pairs a large pass has taken in any process (the module's
    ``.taken`` file), read once per process."""
    if module not in _NOTED:
        path, pairs = _taken_file(module), set()
        with contextlib.suppress(OSError):
            if path is not None:
                pairs = {tuple(ln.split()) for ln in path.read_text().splitlines() if ln}
        _NOTED[module] = pairs
    return _NOTED[module]


def _note(module: ModuleType, kernel: str, dtype: str) -> None:
    """Add ``(kernel, dtype)`` to the module's ``.taken`` file (nothing where the file
    cannot be written)."""
    pairs = _noted(module)
    if (kernel, dtype) in pairs:
        return
    pairs.add((kernel, dtype))
    path = _taken_file(module)
    with contextlib.suppress(OSError):
        if path is not None:
            with path.open("a") as fh:  # one short line: appends do not interleave
                fh.write(f"{kernel} {dtype}\n")


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


def generated_module(fn) -> ModuleType | None:
    """The generated module whose ``rhs`` is ``fn``, or None."""
    try:
        return _BOUND.get(fn)
    except TypeError:  # unhashable
        return None


def bound_kernels(fn, rows: int, kernel: str, dtype) -> ModuleType | None:
    """The generated module whose ``rhs`` is ``fn`` when a pass of ``rows`` rows over
    arrays of ``dtype`` should run its ``kernel`` (a name): the pass is large enough
    (:data:`MIN_ROWS`), or a large pass has taken that kernel for ``dtype`` in this
    process (it is compiled) or in an earlier one (numba has cached it); else None."""
    try:
        module = _BOUND.get(fn)
    except TypeError:  # unhashable
        return None
    if module is None:
        return None
    key = (fn, kernel, np.dtype(dtype).str)
    if key in _TAKEN:
        return module
    if rows >= MIN_ROWS or _ALWAYS:
        _TAKEN.add(key)
        _note(module, kernel, key[2])
        return module
    if (kernel, key[2]) in _noted(module):
        _TAKEN.add(key)
        return module
    return None


def inline_model_kernels(enabled: bool = True) -> bool:
    """Run every pass of a model whose code is generated (:mod:`torchslq.dynamics.codegen`)
    on the kernels compiled with the model's functions inlined, whatever the pass's
    size; returns the previous setting (process-wide).

    For a real-time loop of small solves: measured on the user cart-pole (RK4, T = 50,
    B = 1, ILQR), about 10% less time per iteration, alternating in one process (the
    same iterates: the two kinds of kernels compute the same bits,
    ``tests/test_codegen.py``). The first pass of each kernel compiles it: seconds per
    model (7 s for the cart-pole's), once per machine (numba caches them with the
    model's module, and later processes take them for small passes too). Off (the
    default), a small solve starts without that compilation and a pass of
    :data:`MIN_ROWS` rows or more takes them."""
    global _ALWAYS
    old, _ALWAYS = _ALWAYS, bool(enabled)
    return old
