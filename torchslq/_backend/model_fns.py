"""A model's compiled functions as first-class function values for the CPU kernels.

The kernels that run a model's compiled functions (the RK4 derivative passes, the
closed-loop rollout, a step on a batch of rows) take those functions as arguments.
Passed as numba dispatchers, a kernel is compiled again for every model in every
process: numba specialises it on the dispatcher's type and cannot cache the result,
since the callee's address is a dynamic global (a second or more per kernel, most of a
new model's first solve). Passed as *first-class function values*
(``numba.types.FunctionType``: the address of the function, typed by its signature),
the kernel is specialised only on that signature, so it compiles once per machine for
every model and loads from numba's disk cache; a model costs the compilation of its own
functions (a generated model's are cached with its module,
:mod:`torchslq.dynamics.codegen`). The price is a call through a pointer that is not
inlined, and numba's typing of each function argument at every launch (a Python call;
the value's numba type itself is built once, :func:`_function_value_class`).

The functions' signatures follow from the arrays a kernel passes them (``X``: arrays of
the state's dtype, ``P``: the parameters' 1-d array, all C-contiguous):

* ``rhs(x, u, p, out)``: ``X1, X1, P, X1`` (a continuous model's right-hand side, or a
  discrete model's step written without scratch);
* ``derivs(x, u, p, fz, H)``: ``X1, X1, P, X2, X3``;
* ``step(x, u, p, out, work)``: ``X1, X1, P, X1, X2`` (:meth:`torchslq.Dynamics.compiled_step`);
* ``rows(r0, r1, X, U, p, OUT)``: ``intp, intp, X2, X2, P, X2``: the step on the rows
  ``r0 <= r < r1`` of ``X``, ``U`` at once (a learned model's wide layers as matrix
  products over the rows, :func:`torchslq.dynamics.network_chains.step_rows_lines`),
  registered for its step with :func:`register_rows`.

A step function that wraps a model's ``rhs`` (the RK4 step of a continuous model, a
generated discrete model's step) is registered with :func:`register_step`, so the
rollout kernels call ``rhs`` themselves (:data:`~._numba_kernels.STEP_RK4`) instead of a
per-model step that would need its own compilation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .bound import bound_kernels

__all__ = [
    "function_value",
    "register_rows",
    "register_step",
    "rollout_kernel",
    "rows_step",
    "step_source",
]

_VALUES: dict = {}  # (fn, role, x dtype, p dtype) -> first-class function value
_STEPS: dict = {}  # step function -> (rhs, mode)
_ROWS: dict = {}  # step function -> its function on many rows at once


def register_step(step: Any, rhs: Any, mode: int) -> None:
    """Record that ``step(x, u, p, out, work)`` is ``rhs`` taken as ``mode``
    (:data:`~._numba_kernels.STEP_RK4` or :data:`~._numba_kernels.STEP_DISCRETE`)."""
    _STEPS[step] = (rhs, mode)


def step_source(step: Any) -> tuple[Any, int] | None:
    """``(rhs, mode)`` of a registered step function, else None."""
    try:
        return _STEPS.get(step)
    except TypeError:  # unhashable
        return None


def register_rows(step: Any, rows: Any) -> None:
    """Record ``rows(r0, r1, X, U, p, OUT)`` as ``step`` on many rows at once (``OUT[r] =
    step(X[r], U[r])`` up to rounding)."""
    _ROWS[step] = rows


def rows_step(step: Any) -> Any:
    """The function :func:`register_rows` recorded for ``step``, else None."""
    try:
        return _ROWS.get(step)
    except TypeError:  # unhashable
        return None


def _signature(role: str, x_dtype: np.dtype, p_dtype: np.dtype):
    from numba import types
    from numba.np.numpy_support import from_dtype

    x = from_dtype(np.dtype(x_dtype))
    X1, X2, X3 = (types.Array(x, nd, "C") for nd in (1, 2, 3))
    P = types.Array(from_dtype(np.dtype(p_dtype)), 1, "C")
    args = {
        "rhs": (X1, X1, P, X1),
        "derivs": (X1, X1, P, X2, X3),
        "step": (X1, X1, P, X1, X2),
        "rows": (types.intp, types.intp, X2, X2, P, X2),
    }[role]
    return types.void(*args)


def function_value(fn: Any, role: str, x_dtype, p_dtype) -> Any:
    """``fn`` (a numba-compiled function) as a first-class function value of ``role``'s
    signature for arrays of ``x_dtype`` and parameters of ``p_dtype``: compiled for that
    signature once (or found in its cache), then passed to kernels by address. Anything
    that is not a numba dispatcher is returned as it is."""
    key = (fn, role, np.dtype(x_dtype).str, np.dtype(p_dtype).str)
    try:
        return _VALUES[key]
    except KeyError:
        pass
    except TypeError:  # unhashable: pass as it is
        return fn
    from numba.core.dispatcher import Dispatcher

    if not isinstance(fn, Dispatcher):
        return fn
    value = _function_value_class()(fn, _signature(role, x_dtype, p_dtype))
    _VALUES[key] = value
    return value


_CLASS: list = []


def _function_value_class():
    """The :class:`numba.core.types.WrapperAddressProtocol` class (numba imported on
    first use: the library imports without it)."""
    if not _CLASS:
        from numba.core import types
        from numba.core.typing.typeof import typeof_impl
        from numba.experimental.function_type import _get_wrapper_address

        class FunctionValue(types.WrapperAddressProtocol):
            """A compiled function's C-callable address with its signature."""

            def __init__(self, fn, signature) -> None:
                fn.compile(signature.args)  # a function that cannot take them fails here
                self.fn = fn
                self._signature = signature
                self._address = _get_wrapper_address(fn, signature)
                self.numba_type = types.FunctionType(signature)

            def __wrapper_address__(self) -> int:
                return self._address

            def signature(self):
                return self._signature

        # numba types an argument on every launch; for a function value it builds a new
        # FunctionType from the signature each time (~10 us, per argument and launch):
        # the value's own type, built once, instead
        @typeof_impl.register(FunctionValue)
        def _typeof_function_value(val, c):
            return val.numba_type

        _CLASS.append(FunctionValue)
    return _CLASS[0]


def rollout_kernel(kernel_name: str, step: Any, x_dtype, p_dtype, rows: int, module=None):
    """The rollout kernel ``kernel_name`` (``"closed_loop_rollout_kernel"`` or
    ``"step_rows_kernel"`` of :mod:`._numba_kernels`, or a kernel of ``module`` with the
    same leading arguments) for ``step`` and its leading arguments: ``(step, rhs,
    mode)`` with a registered step's ``rhs`` and mode, else the step itself
    (``STEP_GIVEN``) and a stand-in for the unused one, as first-class function values;
    for a large pass of a generated model that defines the kernel, its module's kernel
    and ``(mode,)`` (:mod:`.bound`)."""
    from . import _numba_kernels as K

    source = step_source(step)
    if source is None:
        fn, rhs, mode = step, K.no_rhs, K.STEP_GIVEN
    else:
        fn, (rhs, mode) = K.no_step, source
        bound = bound_kernels(rhs, rows, kernel_name, x_dtype)
        if bound is not None and hasattr(bound, kernel_name):
            return getattr(bound, kernel_name), (mode,)  # the same kernel, functions bound in
    fns = (
        function_value(fn, "step", x_dtype, p_dtype),
        function_value(rhs, "rhs", x_dtype, p_dtype),
        mode,
    )
    return getattr(K if module is None else module, kernel_name), fns
