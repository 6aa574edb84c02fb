"""Jacobians and Hessians of a learned model by its traced graph, without autograd.

A learned model is mostly ``nn.Linear`` layers, elementwise activations, concatenations
and sums, often around a physics step (a residual network on a discretised model, as
``x_next = rk4_step(x, u) + mlp([x, u])``). Its Jacobians by autograd cost a forward
pass that records every op, then ``n`` backward passes (or one batched pass) through
all of them. Here the model's ``forward`` is traced once by ``torch.fx``; each call then
runs the graph forward on plain tensors, keeping what each node's derivative needs
(an activation's slope ``s'(a)``, a layer's weight, a submodule's Jacobians), and sweeps
the ``n`` output sensitivities ``G (rows, n, width)`` back through it (reverse mode):

* ``nn.Linear``: ``G <- G W``, one matrix product over the rows;
* an elementwise activation, or ``sin``, ``cos``, ``exp``, a square or a power by a
  number of the features: ``G <- G * s'(a)``;
* ``+``, ``-``, ``*`` and ``/`` by a number or by a node of the same shape (a quotient
  by a node adds ``-(a / b^2) db``), negation,
  ``torch.cat`` along the last dim, a slice of the last dim (``z[..., i:j]``);
* a :class:`~torchslq.dynamics.base.Dynamics` submodule called on ``(a, b)`` (e.g. the
  discretised physics under a residual): its own Jacobians, by
  :func:`~torchslq.dynamics.linearize.linearize` (compiled kernels where it has them),
  ``G <- G J_a`` and ``G J_b``.

Every output's Hessian (:func:`graph_hessians`, DDP's value mode) adds the forward
mode: the input basis pushed through the graph gives each node's tangents ``T (rows,
n + m, width)``, and each nonlinear node adds ``T_in' (sum_i G_i d2 node) T_in`` during
the sweep (an activation's ``s''``, a product's two cross terms, a submodule's own
Hessians).

On the CPU the rows go through in blocks whose sensitivities fit in cache
(:data:`~torchslq.dynamics.row_blocks.BLOCK_BYTES`): no intermediate is then large
enough for the allocator to map fresh pages at every call. A model whose graph has
anything else (other indexing, control flow on values, an unknown layer), per-element data,
or data off the CPU keeps autograd: the functions return None (a graph that cannot be
taken is remembered for its module). A trace holds the Python numbers and branches of
``forward`` as they were when it was made; its output is compared with the model's own
``forward`` at one row once per solve, and a model that changed is traced again.
"""

from __future__ import annotations

import operator
import weakref
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, fx, nn

from .._backend import dense_rows
from .._pinned import pinned
from . import _mlp
from .base import Dynamics
from .row_blocks import block_rows, linear_width, rows_independent

__all__ = ["graph_hessians", "graph_jacobians"]


#: the most elementwise nodes (everything but layers and ``Dynamics`` submodules) a graph
#: may have for the sweep to be taken: each costs a round of Python per block of rows,
#: where autograd's engine walks its nodes in C++. Measured at 3,200 rows, a 5-64-64-4
#: tanh MLP with 4 / 10 / 11 / 36 / 131 such nodes around it: Jacobians 1.04 / 0.99 /
#: 0.99 / 0.88 / 0.62x autograd's speed, Hessians 1.37 / 1.57 / 0.88 / 1.15 / 0.46x (the
#: last one the cart-pole's equations written inline in an RK4 step,
#: ``benchmarks/learned_derivatives.py``'s ``graybox``)
MAX_ELEMENTWISE = 32


class _Unsupported(Exception):
    """A node this module cannot differentiate (the caller keeps autograd)."""


def _first(fn) -> Callable[[Tensor, Tensor], Tensor]:
    """``s'(a)`` from :mod:`._mlp`'s ``(a, h) -> (s', s'')`` of an activation (its table
    of activations and their derivatives is the one both passes read)."""
    only = _mlp.FIRST_ONLY.get(fn)  # (not computing s'' where that is extra work)
    return only if only is not None else (lambda a, h: fn(a, h)[0])


def _second(fn) -> Callable[[Tensor, Tensor], Tensor]:
    """``s''(a)`` from :mod:`._mlp`'s ``(a, h) -> (s', s'')`` of an activation."""
    return lambda a, h: fn(a, h)[1]


# the functional and method activations: the function a call's target names (tanh's
# over many rows by :mod:`torchslq._backend.dense_rows`), and the (s', s'') of :mod:`._mlp`
_DERIVATIVES = {
    torch.tanh: (dense_rows.tanh, _mlp._tanh),
    F.tanh: (dense_rows.tanh, _mlp._tanh),
    torch.sigmoid: (torch.sigmoid, _mlp._sigmoid),
    F.sigmoid: (torch.sigmoid, _mlp._sigmoid),
    torch.relu: (torch.relu, _mlp._relu),
    F.relu: (F.relu, _mlp._relu),
    F.silu: (F.silu, _mlp._silu),
    F.gelu: (F.gelu, _mlp._gelu),
    # elementwise functions of the features
    torch.sin: (torch.sin, _mlp._sin),
    torch.cos: (torch.cos, _mlp._cos),
    torch.exp: (torch.exp, _mlp._exp),
    torch.square: (torch.square, _mlp._square),
}
_FUNCTIONS = {k: (f, _first(d)) for k, (f, d) in _DERIVATIVES.items()}
# the same functions called as tensor methods (``z.tanh()``): their values and (s', s'')
_METHOD_NAMES = ("tanh", "sigmoid", "relu", "sin", "cos", "exp", "square")
_METHOD_VALUES = {name: _DERIVATIVES[getattr(torch, name)][0] for name in _METHOD_NAMES}
_METHOD_DERIVATIVES = {name: _DERIVATIVES[getattr(torch, name)][1] for name in _METHOD_NAMES}
_METHODS = {k: _first(d) for k, d in _METHOD_DERIVATIVES.items()}
# second derivatives s''(a) of the functional and method activations (the layers':
# _module_curvature)
_CURVATURE = {k: _second(d) for k, (_, d) in _DERIVATIVES.items()} | {
    k: _second(d) for k, d in _METHOD_DERIVATIVES.items()
}


_POWERS = (operator.pow, torch.pow)  # a node to a number's power: ``z ** p``


def _power_exponent(nd: fx.Node) -> float | None:
    """``p`` of a node ``z ** p`` (``operator.pow``, ``torch.pow`` or ``z.pow(p)``) with
    ``p`` a number (as written: torch takes an integer power by repeated products), else
    None."""
    is_power = nd.target in _POWERS if nd.op == "call_function" else nd.target == "pow"
    if not is_power or len(nd.args) != 2 or not isinstance(nd.args[0], fx.Node):
        return None
    p = nd.args[1]
    return p if _is_number(p) else None


_ARITHMETIC = (operator.add, operator.sub, operator.mul, operator.truediv, operator.neg)


def _is_number(a) -> bool:
    return isinstance(a, (int, float)) and not isinstance(a, bool)


def _is_int(a) -> bool:
    return isinstance(a, int) and not isinstance(a, bool)


def _node_args(args) -> list:
    """A node's arguments, those in lists (a concatenation's pieces) included."""
    out = []
    for a in args:
        out.extend(_node_args(a) if isinstance(a, (list, tuple)) else [a])
    return out


def _last_dim_part(index) -> tuple[slice, bool] | None:
    """``(s, entry)`` for ``z[..., s]`` with ``s`` a slice of step 1 and bounds given as
    numbers (``entry`` False), or for ``z[..., i]`` (``entry`` True, ``s`` the column
    ``i:i+1`` it is held as); None for other indexing, which would reach the rows."""
    if not (isinstance(index, tuple) and len(index) == 2 and index[0] is Ellipsis):
        return None
    key = index[1]
    if _is_int(key):
        return slice(key, key + 1 if key != -1 else None), True
    if not isinstance(key, slice) or key.step not in (None, 1):
        return None
    if not all(b is None or _is_int(b) for b in (key.start, key.stop)):
        return None
    return key, False


def _module_curvature(layer: nn.Module) -> Callable[[Tensor, Tensor], Tensor] | None:
    """``s''(a)`` of an activation layer (None where :mod:`._mlp` does not know it)."""
    fn = _mlp._activation(layer)
    return None if fn is None else _second(fn)


def _module_slope(layer: nn.Module) -> Callable[[Tensor, Tensor], Tensor] | None:
    """``s'(a)`` of an activation layer (None where :mod:`._mlp` does not know it)."""
    fn = _mlp._activation(layer)
    return None if fn is None else _first(fn)


class _Tracer(fx.Tracer):
    """``torch.fx``'s tracer with the model's :class:`Dynamics` submodules as leaves (they
    enter by their own Jacobians)."""

    def is_leaf_module(self, m: nn.Module, module_qualified_name: str) -> bool:
        if isinstance(m, Dynamics):
            return True
        return super().is_leaf_module(m, module_qualified_name)


class _OnConcat(nn.Module):
    """A network on ``[x, u]`` (``nn.Sequential`` and other one-input modules) as a
    two-input model, for tracing."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return self.net(torch.cat([x, u], dim=-1))


class _Residual(nn.Module):
    """:class:`~torchslq.dynamics.linearize.LearnedDynamics`' map without its output
    check (which compares shapes, something a trace cannot do)."""

    def __init__(self, net: nn.Module, residual: bool):
        super().__init__()
        self.net = net
        self.residual = residual

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        out = self.net(torch.cat([x, u], dim=-1))
        return x + out if self.residual else out


def _root(model: nn.Module) -> nn.Module:
    """The module traced for ``model``: itself, or a two-input wrapper."""
    from .linearize import LearnedDynamics

    if isinstance(model, LearnedDynamics):
        return _Residual(model.net, model.residual)
    if isinstance(model, Dynamics):
        return model
    return _OnConcat(model)


class _Program:
    """A traced model: its nodes in order, each checked to be differentiable here. It
    holds no module (the cache of programs must not keep a model alive): the nodes name
    submodules and attributes relative to :func:`_root`, resolved at every call."""

    def __init__(self, root: nn.Module, graph: fx.Graph):
        self.nodes = list(graph.nodes)
        inputs = [nd for nd in self.nodes if nd.op == "placeholder"]
        outputs = [nd for nd in self.nodes if nd.op == "output"]
        if len(inputs) != 2 or len(outputs) != 1:
            raise _Unsupported("a model of (x, u) with one output")
        self.inputs = inputs
        self.output = outputs[0].args[0]
        if not isinstance(self.output, fx.Node):
            raise _Unsupported("the output must be one tensor")
        # the nodes that are one entry of the last dim (``z[..., i]``, which drops it,
        # and elementwise functions of such nodes): held as (rows, 1) columns, they may
        # only meet numbers and each other until ``torch.stack(..., -1)`` or
        # ``unsqueeze(-1)`` makes them a (rows, width) node again
        self.columns: set[fx.Node] = set()
        for nd in self.nodes:
            self._check(root, nd)
        self.elementwise = sum(
            nd.op not in ("placeholder", "output", "get_attr")
            and not (
                nd.op == "call_module"
                and isinstance(root.get_submodule(nd.target), (nn.Linear, Dynamics))
            )
            for nd in self.nodes
        )

    def _check(self, root: nn.Module, nd: fx.Node) -> None:
        if nd.op in ("placeholder", "output", "get_attr"):
            return
        on_column = [a in self.columns for a in _node_args(nd.args) if _var(a)]
        column = any(on_column)  # an elementwise node of columns is one
        if nd.op == "call_module":
            mod = root.get_submodule(nd.target)
            ok = _module_slope(mod) is not None or (
                not column and (isinstance(mod, Dynamics) or type(mod) is nn.Linear)
            )
        elif _power_exponent(nd) is not None:
            ok = True
        elif nd.op == "call_function" and nd.target is operator.getitem:
            part = _last_dim_part(nd.args[1])
            ok = not column and part is not None
            column = ok and part[1]
        elif nd.op == "call_function" and nd.target is torch.stack:
            pieces = nd.args[0]
            dim = nd.kwargs.get("dim", nd.args[1] if len(nd.args) > 1 else 0)
            ok = (
                dim == -1
                and isinstance(pieces, (list, tuple))
                and len(pieces) > 0
                and all(_var(q) and q in self.columns for q in pieces)
            )
            column = False
        elif nd.op == "call_function" and nd.target in _ARITHMETIC:
            # with a column: the other operands columns or numbers (a vector would be
            # broadcast along what is the rows here)
            ok = not column or all(
                (_var(a) and a in self.columns) or _is_number(a) for a in nd.args
            )
        elif nd.op == "call_function":
            ok = nd.target in _FUNCTIONS or (nd.target is torch.cat and not column)
        elif nd.op == "call_method" and nd.target == "unsqueeze":
            dim = nd.kwargs.get("dim", nd.args[1] if len(nd.args) > 1 else None)
            ok = column and dim == -1
            column = False
        elif nd.op == "call_method":
            ok = nd.target in _METHODS
        else:
            ok = False
        # keyword arguments: a concatenation's or stack's dim, a functional activation's
        # inplace=False (an in-place op would overwrite a value the sweep needs)
        kwargs_ok = (
            nd.target in (torch.cat, torch.stack)
            or (nd.target == "unsqueeze" and set(nd.kwargs) <= {"dim"})
            or all(k == "inplace" and v is False for k, v in nd.kwargs.items())
        )
        if not ok or not kwargs_ok or (column and nd is self.output):
            raise _Unsupported(f"{nd.op} {nd.target}")
        if column:
            self.columns.add(nd)


# model -> its program, or None where it cannot be traced or differentiated here
_PROGRAMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _program(model: nn.Module) -> _Program | None:
    """The traced program of ``model``, once per module."""
    try:
        return _PROGRAMS[model]
    except KeyError:
        pass
    root = _root(model)
    try:
        program = _Program(root, _Tracer().trace(root))
    except Exception:  # noqa: BLE001 - any trace failure: autograd is the answer
        program = None
    _PROGRAMS[model] = program
    return program


def _run_forward(model: Callable, x: Tensor, u: Tensor, second: bool = False):
    """``(program, env, local, xf, uf)``: the model's traced program run forward
    (:func:`_forward`) at the rows ``xf (rows, n)``, ``uf (rows, m)`` of ``x``, ``u``;
    None where the graph path does not apply (:func:`graph_jacobians`). A stale trace (a
    Python number or branch of ``forward`` changed since it was made) is traced again
    once; a model that still differs from its trace keeps autograd."""
    if not isinstance(model, nn.Module) or linear_width(model) == 0:
        return None
    if not x.is_cpu or torch._C._functorch.peek_interpreter_stack() is not None:
        return None  # (on a GPU it is unmeasured: autograd's batched pass stays)
    if torch.compiler.is_compiling() or x.shape[:-1] != u.shape[:-1]:
        return None  # (under torch.compile the model's own ops are what gets traced)
    program = _program(model)
    if program is None or program.elementwise > MAX_ELEMENTWISE:
        return None  # (many small nodes: autograd's engine walks them faster)
    root = _root(model)
    lead = x.shape[:-1]
    if not rows_independent(model, lead):
        return None
    n, m = x.shape[-1], u.shape[-1]
    rows = lead.numel()
    xf, uf = x.detach().reshape(rows, n), u.detach().reshape(rows, m)
    env, local = _forward(program, root, xf, uf, second)
    if env[program.output].shape[-1] != n:
        return None  # the model's output is not a state: linearize reports it
    if not _traced_as_called(model, root, env[program.output], xf, uf):
        _PROGRAMS.pop(model, None)
        program = _program(model)
        if program is None:
            return None
        env, local = _forward(program, root, xf, uf, second)
        if not _traced_as_called(model, root, env[program.output], xf, uf):
            _PROGRAMS[model] = None
            return None
    return program, env, local, xf, uf


def graph_jacobians(model: Callable, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor] | None:
    """``A = df/dx (..., n, n)`` and ``B = df/du (..., n, m)`` of a learned model at
    ``x (..., n)``, ``u (..., m)`` by its traced graph (module docstring), detached; None
    where this does not apply: ``model`` is not an ``nn.Module`` with an ``nn.Linear``
    layer, its graph has a node this module does not differentiate, it holds
    per-element data (its rows are then not independent), or the data are not on the
    CPU."""
    n, m = x.shape[-1], u.shape[-1]
    try:
        with torch.no_grad():
            ran = _run_forward(model, x, u)
            if ran is None:
                return None
            program, env, local, xf, uf = ran
            rows = xf.shape[0]
            block = block_rows(max(linear_width(model), n + m) * n, x.element_size())
            if rows <= block:
                Jx, Ju = _reverse(program, env, local, n, slice(None))
            else:
                Jx, Ju = xf.new_empty(rows, n, n), uf.new_empty(rows, n, m)
                for r in range(0, rows, block):
                    part = _reverse(program, env, local, n, slice(r, r + block))
                    Jx[r : r + block], Ju[r : r + block] = part
    except _Unsupported:
        return None
    lead = x.shape[:-1]
    return Jx.reshape(*lead, n, n), Ju.reshape(*lead, n, m)


def graph_hessians(
    model: Callable, x: Tensor, u: Tensor
) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor, Tensor]] | None:
    """``(A, B, (Hxx, Huu, Hux))``: :func:`graph_jacobians` and every output's Hessian
    blocks (:func:`~torchslq.dynamics.dynamics_hessians`' layout, ``(n, ..., ., .)``) by
    the traced graph: the input basis pushed forward through it (the nodes' tangents
    ``T (rows, n + m, width)``) and the output sensitivities swept back, each nonlinear
    node adding ``T_in' (sum_i G_i d2 node) T_in`` (module docstring of
    :mod:`._mlp` for a network's layers). Detached; None where :func:`graph_jacobians`
    does not apply or ``n + m`` exceeds :data:`~torchslq.dynamics._mlp.MAX_INPUT`."""
    n, m = x.shape[-1], u.shape[-1]
    k = n + m
    if k > _mlp.MAX_INPUT:
        return None
    try:
        with torch.no_grad():
            ran = _run_forward(model, x, u, second=True)
            if ran is None:
                return None
            program, env, local, xf, uf = ran
            rows = xf.shape[0]
            # blocks as if only the tangents (rows, k, width) counted: the curvature's
            # (rows, k * k, width) products are then a few megabytes, and each block's
            # graph walk is paid fewer times (measured, 3,200 rows of the 5-64-64-4 MLP
            # on the cart-pole step: 35 ms, against 47 ms in blocks of 4x fewer rows)
            block = block_rows(max(linear_width(model), k) * max(n, k), x.element_size())
            parts = []
            for r in range(0, rows, block):
                sl = slice(r, r + block)
                slopes: dict = {}
                T = _tangents(program, env, local, n, k, sl, slopes)
                parts.append(_reverse(program, env, local, n, sl, T, slopes))
            Jx, Ju, H = (torch.cat([p[i] for p in parts]) for i in range(3))
    except _Unsupported:
        return None
    lead = x.shape[:-1]
    return Jx.reshape(*lead, n, n), Ju.reshape(*lead, n, m), hessian_blocks(H, lead, n)


def hessian_blocks(H: Tensor, lead, n: int) -> tuple[Tensor, Tensor, Tensor]:
    """Every output's Hessians ``H (rows, n_out, k, k)`` (``k = n + m``) as
    :func:`~torchslq.dynamics.dynamics_hessians`' blocks ``(Hxx (n_out, *lead, n, n),
    Huu (n_out, *lead, m, m), Hux (n_out, *lead, m, n))``."""
    n_out, k = H.shape[1], H.shape[-1]
    m = k - n
    H = H.movedim(1, 0)  # (n_out, rows, k, k)
    return (
        H[..., :n, :n].reshape(n_out, *lead, n, n).contiguous(),
        H[..., n:, n:].reshape(n_out, *lead, m, m).contiguous(),
        H[..., n:, :n].reshape(n_out, *lead, m, n).contiguous(),
    )


def xu_hessian(Hxx: Tensor, Huu: Tensor, Hux: Tensor) -> Tensor:
    """The Hessian blocks (:func:`hessian_blocks`' layout: ``Hxx (..., n, n)``, ``Huu
    (..., m, m)``, ``Hux (..., m, n)``) joined into the Hessian in ``z = (x, u)``, ``(...,
    n + m, n + m)``."""
    return torch.cat([torch.cat([Hxx, Hux.mT], -1), torch.cat([Hux, Huu], -1)], -2)


def _traced_as_called(model: nn.Module, root: nn.Module, out: Tensor, x: Tensor, u: Tensor) -> bool:
    """Whether the traced program's output ``out (rows, n)`` equals the model's own
    ``forward`` at the first row (to rounding): a trace holds the Python numbers and
    branches of ``forward`` as they were when it was made. Once per solve (a model does
    not change during one), at every call outside a solve."""

    def check() -> bool:
        real = root(x[:1], u[:1])
        eps = torch.finfo(out.dtype).eps
        scale = 1.0 + float(real.detach().abs().max())
        return torch.allclose(out[:1], real.detach(), rtol=0.0, atol=1e3 * eps * scale)

    return pinned(model, "graph_jacobian_traced_as_called", check)


def _arg(env: dict, a):
    """A node's argument: its value where it is a node, else the constant itself."""
    if isinstance(a, (list, tuple)):
        return [_arg(env, e) for e in a]
    return env[a] if isinstance(a, fx.Node) else a


def _var(a) -> bool:
    """Whether an argument depends on ``(x, u)`` (a node other than a constant)."""
    return isinstance(a, fx.Node) and a.op != "get_attr"


def _forward(
    program: _Program, root: nn.Module, x: Tensor, u: Tensor, second: bool = False
) -> tuple[dict, dict]:
    """The program of ``root`` (see :func:`_root`) run forward at the rows ``x (rows,
    n)``, ``u (rows, m)``: every node's value, and what its reverse rule needs
    (``(kind, data)``: an activation's slope function with its input and output, a
    layer's weight, a submodule's Jacobians, the widths of a concatenation's pieces)."""
    from .linearize import linearize, linearize_with_hessians

    env: dict = {}
    local: dict = {}
    env[program.inputs[0]], env[program.inputs[1]] = x, u
    for nd in program.nodes:
        if nd.op in ("placeholder", "output"):
            continue
        if nd.op == "get_attr":
            obj = root
            for part in nd.target.split("."):
                obj = getattr(obj, part)
            env[nd] = obj.detach() if torch.is_tensor(obj) else obj
            continue
        args = [_arg(env, a) for a in nd.args]
        if nd.op == "call_module":
            mod = root.get_submodule(nd.target)
            if isinstance(mod, Dynamics):
                if len(args) != 2 or not all(torch.is_tensor(a) for a in args):
                    raise _Unsupported("a Dynamics submodule takes (x, u)")
                env[nd] = mod(*args)
                if second:
                    A, B, blocks = linearize_with_hessians(mod, *args)
                    local[nd] = ("jacobians", (A, B), blocks())
                else:
                    local[nd] = ("jacobians", linearize(mod, *args))
            elif type(mod) is nn.Linear:
                env[nd] = dense_rows.linear(args[0], mod.weight.detach(), _detached(mod.bias))
                local[nd] = ("linear", mod.weight.detach())
            else:
                slope = _module_slope(mod)
                if slope is None:  # replaced since the trace
                    raise _Unsupported(type(mod).__name__)
                env[nd] = h = dense_rows.tanh(args[0]) if type(mod) is nn.Tanh else mod(args[0])
                local[nd] = ("slope", (slope, args[0], h, _module_curvature(mod)))
        elif (p := _power_exponent(nd)) is not None:
            env[nd] = h = args[0] ** p
            power = _mlp._power(p)
            local[nd] = ("slope", (_first(power), args[0], h, _second(power)))
        elif nd.target is operator.getitem:
            s = _last_dim_part(nd.args[1])[0]  # z[..., i] as the column z[..., i:i+1]
            env[nd] = args[0][..., s]
            local[nd] = ("slice", (s, args[0].shape[-1]))
        elif nd.target is torch.stack:  # of columns, along the last dim
            env[nd] = torch.cat(args[0], dim=-1)
            local[nd] = ("cat", [1] * len(args[0]))
        elif nd.target == "unsqueeze":  # of a column, at the last dim: held so already
            env[nd] = args[0]
            local[nd] = ("identity", None)
        elif nd.op == "call_method":
            env[nd] = h = _METHOD_VALUES[nd.target](args[0])
            local[nd] = ("slope", (_METHODS[nd.target], args[0], h, _CURVATURE[nd.target]))
        elif nd.target in _FUNCTIONS:
            fn, slope = _FUNCTIONS[nd.target]
            env[nd] = h = fn(args[0])
            local[nd] = ("slope", (slope, args[0], h, _CURVATURE[nd.target]))
        elif nd.target is torch.cat:
            pieces = args[0]
            dim = nd.kwargs.get("dim", args[1] if len(args) > 1 else 0)
            if not all(torch.is_tensor(p) and p.ndim == 2 for p in pieces) or dim not in (-1, 1):
                raise _Unsupported("torch.cat along the last dim")
            env[nd] = torch.cat(pieces, dim=-1)
            local[nd] = ("cat", [p.shape[-1] for p in pieces])
        else:
            for a, v in zip(nd.args, args, strict=True):
                if not _var(a) and torch.is_tensor(v) and v.ndim > 1:
                    raise _Unsupported("a constant operand must be a number or a vector")
            if len({v.shape[-1] for a, v in zip(nd.args, args, strict=True) if _var(a)}) > 1:
                raise _Unsupported("nodes broadcast against each other")
            env[nd] = nd.target(*args)
            local[nd] = ("arith", None)
    out = env[program.output]
    if not torch.is_tensor(out) or out.ndim != 2 or out.shape[0] != x.shape[0]:
        raise _Unsupported("the output must be (rows, n)")
    for nd in program.nodes:  # every node on the way is a row map: (rows, width)
        if (
            _var(nd)
            and nd.op != "output"
            and (
                not torch.is_tensor(env[nd]) or env[nd].ndim != 2 or env[nd].shape[0] != x.shape[0]
            )
        ):
            raise _Unsupported("a node that is not (rows, width)")
    return env, local


def _detached(t: Tensor | None) -> Tensor | None:
    return None if t is None else t.detach()


_IDENTITY = object()  # the output's own sensitivity, not materialised


def _dense(g, value: Tensor, n_out: int) -> Tensor:
    """A sensitivity as a ``(rows, n_out, width)`` tensor, for the rows of ``value
    (rows, width)`` (zeros for None, the identity for :data:`_IDENTITY`)."""
    rows, width = value.shape
    if g is None:
        return value.new_zeros(rows, n_out, width)
    if g is _IDENTITY:
        eye = torch.eye(n_out, width, dtype=value.dtype, device=value.device)
        return eye.expand(rows, n_out, width)
    return g


def _reverse(
    program: _Program,
    env: dict,
    local: dict,
    n_out: int,
    rows: slice,
    tangents: dict | None = None,
    slopes: dict | None = None,
) -> tuple[Tensor, ...]:
    """``(Jx (r, n_out, n), Ju (r, n_out, m))`` at the rows ``rows`` of the forward pass
    ``env``, ``local`` (:func:`_forward`): the output's sensitivities swept back to the
    inputs, ``G = d out / d node (r, n_out, width)`` node by node. With the nodes'
    ``tangents`` (:func:`_tangents`, ``(r, k, width)``: ``d node / d(x, u)``) also every
    output's Hessian ``H (r, n_out, k, k)``, third in the tuple: the sum over the
    nonlinear nodes of ``T_in' (sum_i G_i d2 node) T_in`` (an activation's ``s''``, a
    product's two factors, a submodule's own Hessians); linear nodes add nothing."""
    G: dict = {program.output: _IDENTITY}
    slopes = {} if slopes is None else slopes
    H = None

    def val(a):  # a node's value at these rows (a constant as it is)
        return env[a][rows] if _var(a) else _arg(env, a)

    def add(node, g) -> None:
        if not _var(node):
            return  # a constant
        value = val(node)
        if g is not _IDENTITY and g.shape[-1] != value.shape[-1]:
            raise _Unsupported("broadcasting between nodes")
        have = G.get(node)
        G[node] = g if have is None else _dense(have, value, n_out) + _dense(g, value, n_out)

    def curvature(Ta, c, Tb) -> None:  # H += sum_j c_ij Ta_pj Tb_qj (per row and output i)
        nonlocal H
        if Ta is None or Tb is None:
            return
        r, n_c, w = c.shape
        k = Ta.shape[1]
        if Ta.stride(0) == 0 and Tb.stride(0) == 0:
            # tangents shared by the rows (a layer on the inputs): one product
            outer = (Ta[0].unsqueeze(1) * Tb[0].unsqueeze(0)).reshape(k * k, w)
            term = (c.reshape(r * n_c, w) @ outer.T).view(r, n_c, k, k)
        else:
            outer = (Ta.unsqueeze(2) * Tb.unsqueeze(1)).reshape(r, k * k, w)
            term = (outer @ c.mT).view(r, k, k, n_c).permute(0, 3, 1, 2)
        H = term if H is None else H + term

    for nd in reversed(program.nodes):
        if nd.op in ("placeholder", "output", "get_attr"):
            continue
        g = G.pop(nd, None)
        if g is None:
            continue  # the output does not depend on this node
        kind, data, *extra = local[nd]
        args = nd.args
        if kind == "jacobians":  # a Dynamics submodule on (a, b)
            for a, J in zip(args, data, strict=True):
                add(a, J[rows] if g is _IDENTITY else g @ J[rows])
            if tangents is not None:
                g_d = _dense(g, val(nd), n_out)
                term = _submodule_curvature(nd, g_d, extra[0], rows, tangents, program.inputs)
                H = term if H is None else H + term
        elif kind == "linear":
            W = data
            if g is _IDENTITY:
                add(args[0], W.unsqueeze(0).expand(val(nd).shape[0], *W.shape))
            else:
                GW = dense_rows.matmul(g.reshape(-1, W.shape[0]), W)
                add(args[0], GW.view(g.shape[0], -1, W.shape[1]))
        elif kind == "slope":  # (taken here, on the block's rows, while they are in cache)
            slope = _slope(nd, data, rows, slopes)
            if tangents is not None and _var(args[0]):
                fn, a, h, curv = data
                if curv is None:
                    raise _Unsupported("an activation without a second derivative")
                c = _dense(g, val(nd), n_out) * curv(a[rows], h[rows]).unsqueeze(1)
                T = tangents[args[0]]
                curvature(T, c, T)
            add(args[0], torch.diag_embed(slope) if g is _IDENTITY else g * slope.unsqueeze(1))
        elif kind == "identity":
            add(args[0], g)
        elif kind == "slice":  # zero sensitivity outside the slice
            s, width = data
            g = _dense(g, val(nd), n_out)
            whole = g.new_zeros(*g.shape[:-1], width)
            whole[..., s] = g
            add(args[0], whole)
        elif kind == "cat":
            g = _dense(g, val(nd), n_out)
            start = 0
            for piece, width in zip(args[0], data, strict=True):
                add(piece, g[..., start : start + width])
                start += width
        else:
            if tangents is not None and nd.target is operator.mul:
                a, b = args
                if _var(a) and _var(b):  # a product of two nodes
                    c = _dense(g, val(nd), n_out)
                    curvature(tangents[a], c, tangents[b])
                    curvature(tangents[b], c, tangents[a])
            if tangents is not None and nd.target is operator.truediv and _var(args[1]):
                # a / b: d2/da db = -1 / b^2, d2/db2 = 2 a / b^3
                a, b = args
                c = _dense(g, val(nd), n_out)
                vb = val(b)
                inv2 = 1.0 / (vb * vb)
                if _var(a):
                    cab = c * (-inv2).unsqueeze(1)
                    curvature(tangents.get(a), cab, tangents.get(b))
                    curvature(tangents.get(b), cab, tangents.get(a))
                cbb = c * (2.0 * val(a) * inv2 / vb).unsqueeze(1)
                curvature(tangents.get(b), cbb, tangents.get(b))
            _arithmetic(nd, g, val, n_out, add)
    x, u = program.inputs
    J = (_dense(G.get(x), val(x), n_out), _dense(G.get(u), val(u), n_out))
    if tangents is None:
        return J
    if H is None:
        k = tangents[x].shape[1]
        H = val(x).new_zeros(val(x).shape[0], n_out, k, k)
    return (*J, H)


def _slope(nd: fx.Node, data: tuple, rows: slice, slopes: dict) -> Tensor:
    """An activation node's slope ``s'(a)`` at the rows, once per block."""
    have = slopes.get(nd)
    if have is None:
        fn, a, h = data[:3]
        have = slopes[nd] = fn(a[rows], h[rows])
    return have


def _submodule_curvature(
    nd: fx.Node, g: Tensor, blocks, rows: slice, tangents: dict, inputs: list
) -> Tensor:
    """A :class:`Dynamics` submodule's Hessian term ``T_in' (sum_l G_l H_l) T_in``
    ``(r, n_out, k, k)`` (``H_l`` its outputs' Hessians in its inputs ``(a, b)``, ``T_in
    (r, k, n_a + n_b)`` their tangents; ``g (r, n_out, n_l)`` its sensitivities)."""
    Hxx, Huu, Hux = (blk[:, rows] for blk in blocks)  # (n_l, r, ., .)
    Hl = xu_hessian(Hxx, Huu, Hux).movedim(0, 1)  # (r, n_l, kl, kl)
    r, n_l, kl = Hl.shape[0], Hl.shape[1], Hl.shape[-1]
    M = (g @ Hl.reshape(r, n_l, kl * kl)).view(r, -1, kl, kl)  # (r, n_out, kl, kl)
    a, b = nd.args
    if a is inputs[0] and b is inputs[1]:
        return M  # called on (x, u) itself: its inputs' tangents are the identity
    k = tangents[inputs[0]].shape[1]
    parts = []
    for arg, width in ((a, Hxx.shape[-1]), (b, Huu.shape[-1])):
        T = tangents.get(arg) if _var(arg) else None
        parts.append(g.new_zeros(r, k, width) if T is None else T)
    T_in = torch.cat(parts, -1).unsqueeze(1)  # (r, 1, k, kl)
    return T_in @ M @ T_in.mT


def _tangents(
    program: _Program, env: dict, local: dict, n: int, k: int, rows: slice, slopes: dict
) -> dict:
    """``d node / d(x, u)`` ``(r, k, width)`` of every node that depends on ``(x, u)``, at
    the rows (forward mode: the input basis pushed through the graph)."""
    x, u = program.inputs
    r = env[x][rows].shape[0]
    eye = torch.eye(k, dtype=env[x].dtype, device=env[x].device)
    T: dict = {x: eye[:, :n].expand(r, k, n), u: eye[:, n:].expand(r, k, k - n)}

    def val(a):
        return env[a][rows] if _var(a) else _arg(env, a)

    def tan(a):
        return T.get(a) if _var(a) else None

    for nd in program.nodes:
        if nd.op in ("placeholder", "output", "get_attr"):
            continue
        kind, data, *_ = local[nd]
        args = nd.args
        out = None
        if kind == "jacobians":
            for a, J in zip(args, data, strict=True):
                t = tan(a)
                if t is not None:
                    term = t @ J[rows].mT
                    out = term if out is None else out + term
        elif kind == "linear":
            t = tan(args[0])
            if t is not None and t.stride(0) == 0:  # shared by the rows: once
                out = (t[0] @ data.T).expand(r, k, data.shape[0])
            elif t is not None:
                out = dense_rows.linear(t.reshape(-1, t.shape[-1]), data, None).view(r, k, -1)
        elif kind == "slope":
            t = tan(args[0])
            if t is not None:
                out = t * _slope(nd, data, rows, slopes).unsqueeze(1)
        elif kind == "identity":
            out = tan(args[0])
        elif kind == "slice":
            t = tan(args[0])
            if t is not None:
                out = t[..., data[0]]
        elif kind == "cat":
            pieces = [tan(p) for p in args[0]]
            if all(p is not None and p.stride(0) == 0 for p in pieces):
                out = torch.cat([p[0] for p in pieces], -1).expand(r, k, sum(data))
            elif any(p is not None for p in pieces):
                out = torch.cat(
                    [
                        p if p is not None else val(q).new_zeros(r, k, w)
                        for p, q, w in zip(pieces, args[0], data, strict=True)
                    ],
                    -1,
                )
        else:
            out = _arithmetic_tangent(nd, tan, val)
        if out is not None:
            T[nd] = out
    return T


def _arithmetic_tangent(nd: fx.Node, tan, val):
    """The tangent of ``+``, ``-``, ``*``, ``/``, negation (None: a constant node)."""
    target, args = nd.target, nd.args
    if target is operator.neg:
        t = tan(args[0])
        return None if t is None else -t
    a, b = args
    ta, tb = tan(a), tan(b)
    if target in (operator.add, operator.sub):
        if tb is not None and target is operator.sub:
            tb = -tb
        if ta is None or tb is None:
            return ta if tb is None else tb
        return ta + tb
    if target is operator.truediv:  # d(a / b) = da / b - (a / b^2) db
        vb = val(b)
        if not _var(b):
            return None if ta is None else ta / vb
        vb = vb.unsqueeze(1)
        out = None if ta is None else ta / vb
        if tb is not None:
            va = val(a).unsqueeze(1) if _var(a) else val(a)
            term = tb * (-va / (vb * vb))
            out = term if out is None else out + term
        return out
    # a product
    out = None
    if ta is not None:
        out = ta * (val(b).unsqueeze(1) if _var(b) else val(b))
    if tb is not None:
        term = tb * (val(a).unsqueeze(1) if _var(a) else val(a))
        out = term if out is None else out + term
    return out


def _arithmetic(nd: fx.Node, g, val, n_out: int, add) -> None:
    """The reverse rule of ``+``, ``-``, ``*``, ``/`` and negation (a constant operand
    is a number or a vector along the last dim); ``val``: a node's value at the rows."""
    target, args = nd.target, nd.args
    if target is operator.add:
        for a in args:
            add(a, g)
        return
    g = _dense(g, val(nd), n_out)
    if target is operator.neg:
        add(args[0], -g)
        return
    a, b = args
    if target is operator.sub:
        add(a, g)
        add(b, -g)
        return
    va, vb = val(a), val(b)
    if target is operator.truediv:
        if not _var(b):
            add(a, g / vb)
            return
        add(a, g / vb.unsqueeze(1))
        add(b, g * (-va / (vb * vb)).unsqueeze(1))
        return
    # a product: each factor's sensitivity is g times the other factor
    if _var(a):
        add(a, g * (vb.unsqueeze(1) if _var(b) else vb))
    if _var(b):
        add(b, g * (va.unsqueeze(1) if _var(a) else va))
