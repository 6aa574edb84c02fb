"""A traced aten graph evaluated on numpy arrays of ``sympy`` expressions: the
interpreter behind :mod:`torchslq.dynamics.codegen`.

Each tensor of the graph becomes an object array of its shape whose entries are
expressions in the symbols of the inputs; views, copies and factories act on the
arrays, elementwise ops on their entries, products and reductions sum the entries'
products. Branches (``torch.where``, ``clamp``, ``relu``, ``maximum``) become
``Piecewise`` expressions whose derivatives are torch's at the switching points. An op
outside this set raises :class:`Unsupported`, and the model keeps the torch path.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from functools import reduce

import numpy as np
import torch
from torch import Tensor

__all__ = ["Unsupported", "evaluate", "symbols", "as_array"]


class Unsupported(Exception):
    """The model cannot be compiled this way; the message says why."""


def symbols(prefix: str, shape: tuple[int, ...], real: bool = True) -> np.ndarray:
    import sympy

    out = np.empty(shape, dtype=object)
    for idx in np.ndindex(*shape):
        out[idx] = sympy.Symbol(prefix + "_".join(map(str, idx)), real=real)
    return out


def evaluate(gm, inputs: list) -> object:
    """The traced graph's output for symbolic ``inputs`` (object arrays)."""
    from torch.fx.node import map_arg

    env: dict = {}
    it = iter(inputs)
    for node in gm.graph.nodes:
        if node.op == "placeholder":
            env[node] = next(it)
        elif node.op == "get_attr":
            t = getattr(gm, node.target)
            env[node] = _constant(t)
        elif node.op == "call_function":
            args = map_arg(node.args, lambda a: env[a])
            kwargs = map_arg(node.kwargs, lambda a: env[a])
            env[node] = _apply(node.target, args, kwargs)
        elif node.op == "output":
            out = map_arg(node.args[0], lambda a: env[a])
            return out
        else:
            raise Unsupported(f"graph node {node.op} {node.target}")
    raise Unsupported("graph without output")


def _constant(t: Tensor) -> np.ndarray:
    import sympy

    if t.is_floating_point() or t.dtype in (torch.int64, torch.int32, torch.bool):
        vals = t.detach().cpu().to(torch.float64).numpy()
        out = np.empty(vals.shape, dtype=object)
        for idx in np.ndindex(*vals.shape):
            out[idx] = sympy.Float(float(vals[idx]))
        return out
    raise Unsupported(f"a constant tensor of dtype {t.dtype}")


def as_array(a) -> np.ndarray:
    if isinstance(a, np.ndarray):
        return a
    import sympy

    if isinstance(a, (bool, int, float)):
        a = sympy.sympify(a)
    out = np.empty((), dtype=object)
    out[()] = a
    return out


def _ew(fn: Callable) -> Callable:
    vf = np.frompyfunc(fn, 1, 1)

    def apply(a, *rest, **kw):
        return np.asarray(vf(as_array(a)), dtype=object)

    return apply


def _ew2(fn: Callable) -> Callable:
    vf = np.frompyfunc(fn, 2, 1)

    def apply(a, b, *rest, **kw):
        return np.asarray(vf(as_array(a), as_array(b)), dtype=object)

    return apply


def _dim(d: int, ndim: int) -> int:
    return d + ndim if d < 0 else d


def _slice(a, dim=0, start=None, end=None, step=1):
    a = as_array(a)
    dim = _dim(dim, a.ndim)
    size = a.shape[dim]
    start = 0 if start is None else start
    end = size if end is None else min(end, size)
    idx = [slice(None)] * a.ndim
    idx[dim] = slice(start, end, step)
    return a[tuple(idx)]


def _select(a, dim, index):
    a = as_array(a)
    return np.asarray(np.take(a, index, axis=_dim(dim, a.ndim)), dtype=object)


def _expand(a, size, implicit=False):
    a = as_array(a)
    size = list(size)
    off = len(size) - a.ndim
    for i, s in enumerate(size):
        if s == -1:
            size[i] = a.shape[i - off]
    return np.broadcast_to(a, tuple(size))


def _squeeze(a, dim=None):
    a = as_array(a)
    if dim is None:
        return np.squeeze(a)
    dims = [dim] if isinstance(dim, int) else list(dim)
    dims = tuple(_dim(d, a.ndim) for d in dims if a.shape[_dim(d, a.ndim)] == 1)
    return np.squeeze(a, axis=dims) if dims else a


def _sum(a, dim=None, keepdim=False, dtype=None):
    a = as_array(a)
    if dim is None or (isinstance(dim, (list, tuple)) and len(dim) == 0):
        return as_array(reduce(operator.add, a.reshape(-1).tolist(), 0))
    dims = (dim,) if isinstance(dim, int) else tuple(dim)
    dims = tuple(_dim(d, a.ndim) for d in dims)
    return np.asarray(np.sum(a, axis=dims, keepdims=keepdim), dtype=object)


def _mean(a, dim=None, keepdim=False, dtype=None):
    a = as_array(a)
    s = _sum(a, dim, keepdim)
    if dim is None or (isinstance(dim, (list, tuple)) and len(dim) == 0):
        count = a.size
    else:
        dims = (dim,) if isinstance(dim, int) else tuple(dim)
        count = math.prod(a.shape[_dim(d, a.ndim)] for d in dims)
    return s / count


def _matmul(a, b):
    return np.asarray(np.matmul(as_array(a), as_array(b)), dtype=object)


def _full(size, value, **kw):
    return np.asarray(np.full(tuple(size), as_array(value)[()], dtype=object), dtype=object)


def _scatter(a, src, dim, index):
    out = as_array(a).copy()
    idx = [slice(None)] * out.ndim
    idx[_dim(dim, out.ndim)] = index
    out[tuple(idx)] = as_array(src)
    return out


def _slice_scatter(a, src, dim=0, start=None, end=None, step=1):
    out = as_array(a).copy()
    dim = _dim(dim, out.ndim)
    size = out.shape[dim]
    idx = [slice(None)] * out.ndim
    idx[dim] = slice(0 if start is None else start, size if end is None else min(end, size), step)
    out[tuple(idx)] = as_array(src)
    return out


def _binary_alpha(op):
    def apply(a, b, alpha=1):
        b = as_array(b)
        if alpha != 1:
            b = b * alpha
        return np.asarray(op(as_array(a), b), dtype=object)

    return apply


def _handlers() -> dict[str, Callable]:
    import sympy

    def _pow(a, b):
        return np.asarray(as_array(a) ** as_array(b), dtype=object)

    def _identity(a, *rest, **kw):
        return as_array(a)

    def _copy(a, src, non_blocking=False):
        return np.broadcast_to(as_array(src), as_array(a).shape).copy()

    # branches as Piecewise, with torch's derivative at the switching points (a
    # clamp passes the gradient at its bounds, relu does not at 0)
    def _clamp1(a, lo, hi):
        pieces = []
        if lo is not None:
            pieces.append((lo, a < lo))
        if hi is not None:
            pieces.append((hi, a > hi))
        return sympy.Piecewise(*pieces, (a, True))

    def _clamp(a, lo=None, hi=None):
        a, lo_, hi_ = np.broadcast_arrays(as_array(a), as_array(lo), as_array(hi))
        out = np.empty(a.shape, dtype=object)
        for idx in np.ndindex(*a.shape):
            out[idx] = _clamp1(
                a[idx], None if lo is None else lo_[idx], None if hi is None else hi_[idx]
            )
        return out

    def _piecewise(cond, a, b):
        return sympy.Piecewise((a, cond), (b, True))

    def _div(a, b, rounding_mode=None):
        if rounding_mode is not None:
            raise Unsupported(f"division with rounding_mode={rounding_mode!r}")
        return np.asarray(as_array(a) / as_array(b), dtype=object)

    def _addmm(bias, a, b, beta=1, alpha=1):
        prod = _matmul(a, b)
        return np.asarray(beta * as_array(bias) + alpha * prod, dtype=object)

    def _split(a, size, dim=0):
        a = as_array(a)
        dim = _dim(dim, a.ndim)
        total = a.shape[dim]
        sizes = [size] * (total // size) + ([total % size] if total % size else [])
        return _split_sizes(a, sizes, dim)

    def _split_sizes(a, sizes, dim=0):
        a = as_array(a)
        out, start = [], 0
        for s in sizes:
            out.append(_slice(a, dim, start, start + s))
            start += s
        return out

    def _permute(a, dims):
        return np.transpose(as_array(a), [_dim(d, as_array(a).ndim) for d in dims])

    def _reshape(a, shape):
        return as_array(a).reshape(tuple(shape))

    def _unsqueeze(a, dim):
        a = as_array(a)
        return np.expand_dims(a, dim if dim >= 0 else dim + a.ndim + 1)

    def _cat(ts, dim=0):
        arrs = [as_array(t) for t in ts if as_array(t).size > 0 or as_array(t).ndim > 1]
        return np.concatenate(arrs, axis=_dim(dim, arrs[0].ndim))

    def _stack(ts, dim=0):
        arrs = [as_array(t) for t in ts]
        return np.stack(arrs, axis=dim if dim >= 0 else dim + arrs[0].ndim + 1)

    def _unbind(a, dim=0):
        a = as_array(a)
        return [_select(a, dim, i) for i in range(a.shape[_dim(dim, a.ndim)])]

    def _like(value):
        return lambda a, *rest, **kw: _full(as_array(a).shape, value)

    def _full_like(a, value, **kw):
        return _full(as_array(a).shape, value)

    def _new_full(a, size, value, **kw):
        return _full(size, value)

    def _new(value):
        return lambda a, size, **kw: _full(size, value)

    def _eye(n, m=None, **kw):
        m = n if m is None else m
        out = np.empty((n, m), dtype=object)
        for i in range(n):
            for j in range(m):
                out[i, j] = sympy.Integer(1 if i == j else 0)
        return out

    def _pad(a, pad, value=0):
        a = as_array(a)
        width = [(0, 0)] * a.ndim
        for k in range(len(pad) // 2):  # torch: last dim first, (before, after) pairs
            before, after = pad[2 * k], pad[2 * k + 1]
            if before < 0 or after < 0:
                raise Unsupported("negative padding")
            width[a.ndim - 1 - k] = (before, after)
        return np.pad(a, width, mode="constant", constant_values=sympy.sympify(value))

    def _diag_embed(a, offset=0, dim1=-2, dim2=-1):
        a = as_array(a)
        if (dim1, dim2) not in ((-2, -1), (a.ndim - 1, a.ndim)):
            raise Unsupported("diag_embed into other dims than the last two")
        k = a.shape[-1] + abs(offset)
        out = np.full((*a.shape[:-1], k, k), sympy.Integer(0), dtype=object)
        for i in range(a.shape[-1]):
            r, c = (i, i + offset) if offset >= 0 else (i - offset, i)
            out[..., r, c] = a[..., i]
        return out

    def _scalar_tensor(v, **kw):
        return as_array(v)

    def _where(cond, a, b):
        return np.asarray(
            np.frompyfunc(_piecewise, 3, 1)(as_array(cond), as_array(a), as_array(b)), dtype=object
        )

    def _cmp(op):
        return _ew2(lambda a, b: op(sympy.sympify(a), sympy.sympify(b)))

    sigmoid = lambda a: 1 / (1 + sympy.exp(-a))  # noqa: E731
    return {
        # views and copies
        "select": _select,
        "slice": _slice,
        "unsqueeze": _unsqueeze,
        "squeeze": _squeeze,
        "view": _reshape,
        "reshape": _reshape,
        "_unsafe_view": _reshape,
        "expand": _expand,
        "permute": _permute,
        "t": lambda a: as_array(a).T,
        "transpose": lambda a, d0, d1: np.swapaxes(as_array(a), d0, d1),
        "clone": _identity,
        "alias": _identity,
        "detach": _identity,
        "lift_fresh": _identity,
        "contiguous": _identity,
        "_to_copy": _identity,
        "to": _identity,
        "copy": _copy,
        "cat": _cat,
        "stack": _stack,
        "unbind": _unbind,
        "split": _split,
        "split_with_sizes": _split_sizes,
        "select_scatter": _scatter,
        "slice_scatter": _slice_scatter,
        # factories
        "full": _full,
        "zeros": lambda size, **kw: _full(size, 0),
        "ones": lambda size, **kw: _full(size, 1),
        "scalar_tensor": _scalar_tensor,
        "eye": _eye,
        "diag_embed": _diag_embed,
        "constant_pad_nd": _pad,
        "zeros_like": _like(0),
        "ones_like": _like(1),
        "full_like": _full_like,
        "new_zeros": _new(0),
        "new_ones": _new(1),
        "new_full": _new_full,
        "fill": lambda a, v: _full(as_array(a).shape, v),
        # arithmetic
        "add": _binary_alpha(operator.add),
        "sub": _binary_alpha(operator.sub),
        "rsub": lambda a, b, alpha=1: np.asarray(as_array(b) - alpha * as_array(a), dtype=object),
        "mul": lambda a, b: np.asarray(as_array(a) * as_array(b), dtype=object),
        "div": _div,
        "true_divide": _div,
        "neg": lambda a: np.asarray(-as_array(a), dtype=object),
        "pow": _pow,
        "square": lambda a: np.asarray(as_array(a) * as_array(a), dtype=object),
        "reciprocal": lambda a: np.asarray(1 / as_array(a), dtype=object),
        "sin": _ew(sympy.sin),
        "cos": _ew(sympy.cos),
        "tan": _ew(sympy.tan),
        "asin": _ew(sympy.asin),
        "acos": _ew(sympy.acos),
        "atan": _ew(sympy.atan),
        "sinh": _ew(sympy.sinh),
        "cosh": _ew(sympy.cosh),
        "tanh": _ew(sympy.tanh),
        "exp": _ew(sympy.exp),
        "expm1": _ew(lambda a: sympy.exp(a) - 1),
        "log": _ew(sympy.log),
        "log1p": _ew(lambda a: sympy.log(1 + a)),
        "sqrt": _ew(sympy.sqrt),
        "rsqrt": _ew(lambda a: 1 / sympy.sqrt(a)),
        "sigmoid": _ew(sigmoid),
        "abs": _ew(sympy.Abs),
        "atan2": _ew2(sympy.atan2),
        "clamp": _clamp,
        "maximum": _ew2(lambda a, b: _piecewise(a >= b, a, b)),
        "minimum": _ew2(lambda a, b: _piecewise(a <= b, a, b)),
        "relu": _ew(lambda a: _piecewise(a > 0, a, sympy.Integer(0))),
        "sign": _ew(sympy.sign),
        "where": _where,
        "gt": _cmp(operator.gt),
        "lt": _cmp(operator.lt),
        "ge": _cmp(operator.ge),
        "le": _cmp(operator.le),
        "eq": _cmp(sympy.Eq),
        "ne": _cmp(sympy.Ne),
        "logical_and": _ew2(sympy.And),
        "logical_or": _ew2(sympy.Or),
        "logical_not": _ew(sympy.Not),
        # reductions and products
        "sum": _sum,
        "mean": _mean,
        "mm": _matmul,
        "bmm": _matmul,
        "matmul": _matmul,
        "mv": _matmul,
        "dot": _matmul,
        "addmm": _addmm,
    }


_HANDLERS: dict | None = None


def _apply(target, args, kwargs):
    global _HANDLERS
    if _HANDLERS is None:
        _HANDLERS = _handlers()
    name = getattr(getattr(target, "overloadpacket", None), "__name__", None)
    if name is None:
        if target is operator.getitem:
            return args[0][args[1]]
        raise Unsupported(f"call of {target}")
    if name not in _HANDLERS and name.endswith("_copy"):
        name = name[: -len("_copy")]
    fn = _HANDLERS.get(name)
    if fn is None:
        raise Unsupported(f"the op aten.{name} is not supported by the code generator")
    kwargs = {
        k: v
        for k, v in kwargs.items()
        if k not in ("dtype", "layout", "device", "pin_memory", "memory_format")
    }
    return fn(*args, **kwargs)
