"""A ``torch.fx`` graph of the aten ops a function runs: the tracer behind
:mod:`torchslq.dynamics.codegen`.

:func:`trace` runs the function once on real tensors under
``torch.func.functionalize(..., remove="mutations_and_views")`` (in-place writes become
``*_scatter`` ops, views ``*_copy`` ops) inside a ``TorchDispatchMode`` that records
every aten op reaching it as a ``call_function`` node. Tensors map to nodes by identity
(the recorder keeps each one alive, so an identity is never reused): the inputs are
placeholders, the outputs of recorded ops their nodes, and a tensor the function did
not compute from these (a module's plain tensor attribute, a ``torch.tensor(...)``
literal) a constant, a ``get_attr`` node on a copy of its value, as
``torch.fx.experimental.proxy_tensor.make_fx`` records constants.

It does what ``make_fx(functionalize(fn), tracing_mode="fake")`` does for the small
straight-line functions code generation takes, without importing ``torch._dynamo`` and
``torch._inductor`` (``make_fx`` and fake tensors import both: a second in a fresh
process). A value read back into Python from a tensor computed from the inputs
(``.item()``, ``bool(t)``, ``float(t)``, ``torch.equal``: an op without a tensor
result) raises :class:`DataDependent`, even where the function catches it: the trace
would otherwise hold one branch of the function's control flow, taken on the trace's
values. An in-place op that reaches the recorder (functionalization leaves one only
on a tensor it does not own, e.g. a module attribute) raises :class:`Untraceable`
before it runs. Reads of a tensor's memory that bypass torch's dispatch (``.numpy()``
of a functionalized tensor reads no meaningful value) are not seen: code generation's
numeric check of the generated functions against the forward is what catches those.

``TorchDispatchMode._should_skip_dynamo`` (a private hook of torch) is overridden so
that the mode's ``__torch_dispatch__`` is not wrapped in ``torch._dynamo.disable``,
which would import dynamo on the first op.
"""

from __future__ import annotations

import operator

import torch
from torch import Tensor
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten, tree_map

__all__ = ["DataDependent", "Untraceable", "trace"]


class Untraceable(RuntimeError):
    """The traced function did something its graph cannot hold."""


class DataDependent(Untraceable):
    """The traced function read a value computed from its inputs back into Python."""


class _Recorder(TorchDispatchMode):
    """Records each aten op into ``graph`` (see the module docs)."""

    @classmethod
    def _should_skip_dynamo(cls) -> bool:
        # True wraps __torch_dispatch__ in torch._dynamo.disable, which imports dynamo
        # on the first op: this mode runs eagerly only
        return False

    def __init__(self, graph: torch.fx.Graph, root: torch.nn.Module):
        super().__init__()
        self.graph = graph
        self.root = root
        self.nodes: dict[int, tuple[Tensor, torch.fx.Node]] = {}
        self.derived: set[int] = set()  # ids of tensors computed from the inputs
        self.refused: Untraceable | None = None

    def placeholder(self, t: Tensor, name: str) -> None:
        self.nodes[id(t)] = (t, self.graph.placeholder(name))
        self.derived.add(id(t))

    def node(self, t: Tensor) -> torch.fx.Node:
        """The node of ``t``; a constant (``get_attr`` on a copy) for a tensor first seen
        here."""
        entry = self.nodes.get(id(t))
        if entry is None:
            name = f"_tensor_constant{sum(1 for _ in self.root.buffers())}"
            self.root.register_buffer(name, t.detach().clone())
            entry = self.nodes[id(t)] = (t, self.graph.get_attr(name))
        return entry[1]

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        flat, _ = tree_flatten((args, kwargs))
        tensors = [a for a in flat if isinstance(a, Tensor)]
        from_inputs = any(id(t) in self.derived for t in tensors)
        schema = func._schema
        if schema.is_mutable:
            self.refused = Untraceable(f"in-place {func} on a tensor it does not own")
            raise self.refused
        returns = [str(r.type) for r in schema.returns]
        if not returns or any(r not in ("Tensor", "Tensor[]", "List[Tensor]") for r in returns):
            if from_inputs:  # a value (or nothing) back to Python: control flow on data
                self.refused = DataDependent(f"{func} reads a value computed from the inputs")
                raise self.refused
            return func(*args, **kwargs)  # of constants only: a constant
        node_args, node_kwargs = tree_map(
            lambda a: self.node(a) if isinstance(a, Tensor) else a, (args, kwargs)
        )
        out = func(*args, **kwargs)
        node = self.graph.call_function(func, tuple(node_args), node_kwargs)
        outs = [(out, node)]
        if not isinstance(out, Tensor):  # a tuple or list of tensors
            outs = [(o, self.graph.call_function(operator.getitem, (node, i)))
                    for i, o in enumerate(out)]  # fmt: skip
        for o, n in outs:
            self.nodes[id(o)] = (o, n)
            if from_inputs:
                self.derived.add(id(o))
        return out


def trace(fn, *inputs: Tensor) -> torch.fx.GraphModule:
    """The aten graph of ``fn(*inputs)``: one placeholder per input (in order), the
    functionalized ops, the output as ``fn``'s output structure. Runs ``fn`` once on
    ``inputs`` (real tensors: the graph does not depend on their values, except
    through a read :class:`DataDependent` refuses). Raises :class:`Untraceable` as the
    module docs say, and whatever ``fn`` raises."""
    from torch.func import functionalize

    graph = torch.fx.Graph()
    root = torch.nn.Module()
    recorder = _Recorder(graph, root)
    for i, t in enumerate(inputs):
        recorder.placeholder(t, f"arg{i}_1")
    with recorder:
        result = functionalize(fn, remove="mutations_and_views")(*inputs)
    if recorder.refused is not None:  # raised inside fn, and fn caught it
        raise recorder.refused
    graph.output(tree_map(lambda a: recorder.node(a) if isinstance(a, Tensor) else a, result))
    return torch.fx.GraphModule(root, graph)
