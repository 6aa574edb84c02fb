"""The numba form of the zoo's equations, imported on the first use of a compiled hook
(importing numba costs ~0.5 s).

A model's equations are written once, in its own module, as :func:`~._common.row_source`
functions; this module makes them callable from compiled code (``sin`` / ``cos`` become
``math.sin`` / ``math.cos``) and wraps them into the row functions the kernels call:
:func:`compiled_rhs` (``rhs(x, u, p, out)``), :func:`compiled_step` (``step(x, u, p, out,
work)``) and :func:`compiled_derivatives` (``derivatives(x, u, p, fz, H)``). Each wrapper
is built once per process and source, and cached on disk (numba's cache, keyed on
the model's file, whose equations it inlines: compiling them takes seconds).
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


def _build(source: Callable, lines: list[str], scope: dict) -> Callable:
    """Compile the function that ``lines`` define (its name is the first line's) with
    numba, cached on disk as if it stood in ``source``'s module: numba drops a cached
    function when its file changes, and the equations it inlines are in that file."""
    name = lines[0].split()[1].split("(")[0]
    scope = {**scope, "__name__": source.__module__}
    exec(compile("\n".join(lines), source.__code__.co_filename, "exec"), scope)
    return numba.njit(nogil=True, cache=True)(scope[name])


@numba.njit(nogil=True, cache=True)
def _write(values, out):
    """``out[i] = values[i]`` for a tuple ``values`` (its entries may differ in type: an
    entry taken from a float32 state beside a float64 one computed with the parameters)."""
    i = 0
    for v in literal_unroll(values):
        out[i] = v
        i += 1


def jit(fn: Callable) -> Callable:
    """``fn`` (a row function over 1-d arrays that calls sources in its own module)
    compiled by numba (cached on disk)."""
    key = ("jit", fn)
    if key not in _WRAPPERS:
        _WRAPPERS[key] = numba.njit(nogil=True, cache=True)(fn)
    return _WRAPPERS[key]


def compiled_rhs(xdot: Callable) -> Callable:
    """``rhs(x, u, p, out)`` writing the tuple ``xdot(x, u, p)`` into ``out``."""
    key = ("rhs", xdot)
    if key not in _WRAPPERS:
        lines = ["def rhs(x, u, p, out):", "    _write(xdot(x, u, p), out)"]
        _WRAPPERS[key] = _build(xdot, lines, {"xdot": xdot, "_write": _write})
    return _WRAPPERS[key]


def compiled_step(next_state: Callable) -> Callable:
    """``step(x, u, p, out, work)`` writing the tuple ``next_state(x, u, p)`` into ``out``
    (:meth:`torchslq.Dynamics.compiled_step`; ``work`` unused)."""
    key = ("step", next_state)
    if key not in _WRAPPERS:
        lines = ["def step(x, u, p, out, work):", "    _write(next_state(x, u, p), out)"]
        _WRAPPERS[key] = _build(next_state, lines, {"next_state": next_state, "_write": _write})
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
        _WRAPPERS[key] = _build(jacobian, lines, scope)
    return _WRAPPERS[key]
