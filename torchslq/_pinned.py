"""Values computed once per solve.

A solver's loop runs inside :func:`solve_scope`. Within it :func:`pinned` computes what a
solve derives from its model and cost at every linearisation, rollout and cost
evaluation (the compiled functions' arguments and parameter arrays, the cost's stacked
weights) once, and :func:`torchslq.dynamics.codegen.generated_hooks` looks a model up
once: neither the model nor the cost changes during a solve, and at B = 1 redoing it cost
a sizeable part of an iteration. Outside a scope every call computes.
"""

from __future__ import annotations

import contextlib
import contextvars
import weakref
from collections.abc import Callable, Hashable, Iterator
from typing import Any

# id(model) -> (model, hooks) for generated_hooks, and "values": a weak dictionary
# owner -> {what: value} for pinned (a subset of a per-element cost or model, made for
# one iteration of a compacting solve, takes its values with it when it goes)
_PINNED: contextvars.ContextVar[dict | None] = contextvars.ContextVar(
    "torchslq_pinned", default=None
)


@contextlib.contextmanager
def solve_scope() -> Iterator[None]:
    """The block within which :func:`pinned` values are kept (nested blocks share the
    outermost one's)."""
    if _PINNED.get() is not None:
        yield
        return
    token = _PINNED.set({"values": weakref.WeakKeyDictionary()})
    try:
        yield
    finally:
        _PINNED.reset(token)


def pinned(owner: object, what: Hashable, compute: Callable[[], Any]) -> Any:
    """``compute()``, computed once per :func:`solve_scope` for ``(owner, what)``;
    outside a scope (or for an owner without weak references), at every call. ``what``
    names the value and whatever else it depends on (a horizon, a dtype, the grad
    mode); the value must not refer to ``owner`` (it would keep it alive)."""
    pins = _PINNED.get()
    if pins is None:
        return compute()
    try:
        values = pins["values"].setdefault(owner, {})
    except TypeError:  # not weakly referenceable
        return compute()
    if what in values:
        return values[what]
    value = values[what] = compute()
    return value
