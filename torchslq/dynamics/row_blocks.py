"""A learned model over many rows, in blocks that stay in cache.

A network's intermediates are ``(rows, width)`` (and a Jacobian pass's sensitivities
``(rows, n, width)``). Over thousands of rows each is megabytes: it leaves the cache,
and the allocator maps fresh pages for it at every call (a page fault per 4 kB, about
as costly as the arithmetic of a 64-wide layer). Where a model's rows are independent
(no per-element data: :mod:`torchslq.per_element`), the same values come from blocks of
rows whose intermediates take at most :data:`BLOCK_BYTES`. On the CPU only (a GPU
wants one large launch).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from .._backend import module_needs_grad
from .._pinned import pinned
from ..per_element import per_element_names

__all__ = ["BLOCK_BYTES", "block_rows", "call_in_blocks", "linear_width", "rows_independent"]

# The most bytes one block's widest intermediate may take. Measured, one thread, the
# cart-pole's RK4 step plus a 5-64-64-4 tanh MLP: its forward at 5,600 / 25,600 rows
# 4.0 / 18.5 ms in one call against 3.2 / 13.8 ms in blocks of 2,048 rows (blocks of
# 256 rows: 4.0 / 19.4 ms, each call's own cost); its Jacobian sweep at 2,400 rows
# (sensitivities 4 x 64 wide) 7.7 ms in one block against 3.7-4.0 ms in blocks of 128 to
# 1,024 rows.
BLOCK_BYTES = 1 << 20


def linear_width(model: Callable) -> int:
    """The widest ``nn.Linear`` output of ``model`` (0 without one, or for a model that
    is not an ``nn.Module``), once per solve."""
    if not isinstance(model, nn.Module):
        return 0

    def widest() -> int:
        return max(
            (mod.out_features for mod in model.modules() if isinstance(mod, nn.Linear)),
            default=0,
        )

    return pinned(model, "linear_width", widest)


def rows_independent(model: nn.Module, lead: torch.Size) -> bool:
    """Whether ``model`` holds no per-element data for inputs with leading dims ``lead``
    (no tensor of its own leads with one of their sizes, see
    :func:`torchslq.per_element.per_element_names`): each row of its output is then a
    function of that row of its inputs alone."""
    for size in set(lead):
        key = ("rows_independent", size)
        if pinned(model, key, lambda size=size: bool(per_element_names(model, size))):
            return False
    return True


def block_rows(values_per_row: int, itemsize: int) -> int:
    """Rows per block when a row's widest intermediate has ``values_per_row`` entries."""
    return max(1, BLOCK_BYTES // max(1, values_per_row * itemsize))


def call_in_blocks(f: Callable[[Tensor, Tensor], Tensor], x: Tensor, u: Tensor) -> Tensor:
    """``f(x, u)`` for ``x (..., n)``, ``u (..., m)`` of the same leading dims; a learned
    model (an ``nn.Module`` with ``nn.Linear`` layers) on the CPU whose rows are
    independent and whose ``(rows, width)`` intermediates would exceed
    :data:`BLOCK_BYTES` is called on blocks of rows and the outputs concatenated (no
    autograd graph is recorded through the blocks: where autograd would record one, ``f``
    is called once)."""
    width = linear_width(f)
    lead = x.shape[:-1]
    rows = lead.numel()
    if width == 0 or not x.is_cpu or x.shape[:-1] != u.shape[:-1]:
        return f(x, u)
    if torch.compiler.is_compiling():
        return f(x, u)
    block = block_rows(width, x.element_size())
    if rows <= block:
        return f(x, u)
    if torch.is_grad_enabled() and (x.requires_grad or u.requires_grad or module_needs_grad(f)):
        return f(x, u)
    if not rows_independent(f, lead):
        return f(x, u)
    xf, uf = x.reshape(rows, x.shape[-1]), u.reshape(rows, u.shape[-1])
    parts = [f(xf[r : r + block], uf[r : r + block]) for r in range(0, rows, block)]
    out = torch.cat(parts)
    return out.reshape(*lead, *out.shape[1:])
