"""Per-element problem data: which registered tensors lead with the batch, and the
same module tree restricted to a sub-batch.

A problem's dynamics and cost may hold per-element data: a ``(B, 1)`` mass, a
``(B, T+1, n)`` goal per problem, ``(B, T, n, n)`` weights. Solvers that work on a
sub-batch (``compact=True``, the constrained loop, shards) need those tensors indexed
with the sub-batch, and every other tensor left alone.

Which tensors are per element:

* a module may say so itself with a method ``per_element_names(batch_size) ->
  list[str]`` (names relative to the module, submodules included; the search does not
  descend below it). :class:`torchslq.QuadraticCost` does, from each weight's declared
  shape, and :class:`torchslq.LearnedDynamics` declares its network's weights shared;
* layers of ``torch.nn`` (``nn.Linear``, ``nn.Conv1d``, ...) hold weights, never
  per-element data, whatever their width;
* any other module's own tensors are per element when they have two or more dims and
  lead with the batch size (``(B, 1)``, ``(B, T, n)``; not ``(B, B)``).
"""

from __future__ import annotations

import copy

from torch import Tensor, nn

__all__ = ["per_element_names", "take_per_element"]


def _is_torch_layer(module: nn.Module) -> bool:
    return type(module).__module__.startswith("torch.nn")


def _own_tensors(module: nn.Module) -> list[tuple[str, Tensor]]:
    own = list(module._parameters.items()) + list(module._buffers.items())
    return [(k, t) for k, t in own if t is not None]


def looks_per_element(t: Tensor, batch_size: int) -> bool:
    """The shape rule for undeclared tensors: 2-D or more, leading with the batch size."""
    return t.ndim >= 2 and t.shape[0] == batch_size and tuple(t.shape) != (batch_size,) * 2


def per_element_names(module: nn.Module, batch_size: int, prefix: str = "") -> list[str]:
    """Dotted names of ``module``'s per-element tensors for a batch of ``batch_size``
    (empty for ``batch_size <= 1``: then every tensor broadcasts over any sub-batch)."""
    if batch_size <= 1:
        return []
    declared = getattr(module, "per_element_names", None)
    if callable(declared):
        return [prefix + name for name in declared(batch_size)]
    if _is_torch_layer(module):
        return []
    names = [prefix + k for k, t in _own_tensors(module) if looks_per_element(t, batch_size)]
    for child_name, child in module._modules.items():
        if child is not None:
            names += per_element_names(child, batch_size, f"{prefix}{child_name}.")
    return names


def _shallow_copy(module: nn.Module) -> nn.Module:
    new = copy.copy(module)  # a new object sharing the old one's attributes
    for attr in ("_parameters", "_buffers", "_modules"):
        new.__dict__[attr] = dict(module.__dict__[attr])
    return new


def take_per_element(module: nn.Module, idx: Tensor, batch_size: int) -> nn.Module:
    """``module`` with each per-element tensor replaced by its rows ``idx``.

    The module itself is not changed: the result is a shallow copy along the paths to
    those tensors (other submodules and attributes are shared, and the indexed tensors
    stay connected to autograd). Returns ``module`` itself when it has no per-element
    data.
    """
    names = per_element_names(module, batch_size)
    if not names:
        return module
    root = _shallow_copy(module)
    copies = {id(root)}  # modules already copied along an earlier path
    for name in names:
        *path, leaf = name.split(".")
        owner = root
        for part in path:
            child = owner._modules[part]
            if id(child) not in copies:
                child = _shallow_copy(child)
                copies.add(id(child))
                owner._modules[part] = child
            owner = child
        store = owner._parameters if leaf in owner._parameters else owner._buffers
        store[leaf] = store[leaf].index_select(0, idx)
    return root
