"""The numba form of the zoo's equations, imported on the first use of a compiled hook
(importing numba costs ~0.5 s).

A model's equations are written once, in its own module, as :func:`~._common.row_source`
functions; this module makes them callable from compiled code (``sin`` / ``cos`` become
``math.sin`` / ``math.cos``) and wraps them into the row functions the kernels call:
:func:`compiled_rhs` (``rhs(x, u, p, out)``), :func:`compiled_step` (``step(x, u, p, out,
work)``) and :func:`compiled_derivatives` (``derivatives(x, u, p, fz, H)``). Each wrapper
is built once per process and source.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numba
from numba import literal_unroll
from numba.extending import overload, register_jitable

from . import _common


@overload(_common.sin, inline="always")
def _sin(a):
    return lambda a: math.sin(a)


@overload(_common.cos, inline="always")
def _cos(a):
    return lambda a: math.cos(a)


_registered: set = set()


def register(fn: Callable) -> None:
    """Make the source ``fn`` callable from compiled code (once)."""
    if fn not in _registered:
        register_jitable(inline="always")(fn)
        _registered.add(fn)


for _fn in _common._SOURCES:
    register(_fn)

_WRAPPERS: dict = {}


@numba.njit(nogil=True)
def _write(values, out):
    """``out[i] = values[i]`` for a tuple ``values`` (its entries may differ in type: an
    entry taken from a float32 state beside a float64 one computed with the parameters)."""
    i = 0
    for v in literal_unroll(values):
        out[i] = v
        i += 1


def jit(fn: Callable) -> Callable:
    """``fn`` (a row function over 1-d arrays that calls sources) compiled by numba."""
    key = ("jit", fn)
    if key not in _WRAPPERS:
        _WRAPPERS[key] = numba.njit(nogil=True)(fn)
    return _WRAPPERS[key]


def compiled_rhs(xdot: Callable) -> Callable:
    """``rhs(x, u, p, out)`` writing the tuple ``xdot(x, u, p)`` into ``out``."""
    key = ("rhs", xdot)
    if key not in _WRAPPERS:

        def rhs(x, u, p, out):
            _write(xdot(x, u, p), out)

        _WRAPPERS[key] = numba.njit(nogil=True)(rhs)
    return _WRAPPERS[key]


def compiled_step(next_state: Callable) -> Callable:
    """``step(x, u, p, out, work)`` writing the tuple ``next_state(x, u, p)`` into ``out``
    (:meth:`torchslq.Dynamics.compiled_step`; ``work`` unused)."""
    key = ("step", next_state)
    if key not in _WRAPPERS:

        def step(x, u, p, out, work):
            _write(next_state(x, u, p), out)

        _WRAPPERS[key] = numba.njit(nogil=True)(step)
    return _WRAPPERS[key]


def compiled_derivatives(
    jacobian: Callable,
    hessians: Callable,
    dims: tuple[int, int, int],
    outs: tuple[int, ...],
    ents: tuple[int, ...],
) -> Callable:
    """``derivatives(x, u, p, fz, H)``
    (:meth:`torchslq.ContinuousDynamics.compiled_derivatives`): the rows of ``[f_x |
    f_u]`` that ``jacobian(x, u, p)`` gives into ``fz`` and, unless ``H`` is empty, the
    entries ``H[j, a, b]`` of ``hessians(x, u, p)`` (per-output Hessians in ``z``) for
    the curved outputs ``j`` in ``outs`` and entries ``a, b`` in ``ents``, the others
    left untouched; ``dims = (n, m, len(p))``.

    Generated code, entry by entry with constant indices, that reads ``x``, ``u``, ``p``
    into tuples of numbers first: a loop over the tuples' entries indexes them at run
    time, and the arrays themselves, which the stores into ``fz`` might alias, made LLVM
    compute the shared terms again for the Hessians (either cost a third per row)."""
    key = ("derivatives", jacobian, hessians, dims, outs, ents)
    if key not in _WRAPPERS:
        n, m, k = dims

        def entries(name, size):
            return "(" + "".join(f"{name}[{i}], " for i in range(size)) + ")"

        lines = [
            "def derivatives(x, u, p, fz, H):",
            f"    xs, us, ps = {entries('x', n)}, {entries('u', m)}, {entries('p', k)}",
            "    J = jacobian(xs, us, ps)",
        ]
        lines += [f"    fz[{i}, {c}] = J[{i}][{c}]" for i in range(n) for c in range(n + m)]
        lines += ["    if H.shape[0] == 0:", "        return", "    Hs = hessians(xs, us, ps)"]
        lines += [
            f"    H[{j}, {a}, {b}] = Hs[{j}][{a}][{b}]" for j in outs for a in ents for b in ents
        ]
        scope = {"jacobian": jacobian, "hessians": hessians}
        exec(compile("\n".join(lines), f"<{jacobian.__qualname__} derivatives>", "exec"), scope)
        _WRAPPERS[key] = numba.njit(nogil=True)(scope["derivatives"])
    return _WRAPPERS[key]
