"""``linearize``: Jacobians of any dynamics over batch and time at once.

This is the single linearisation used by every solver.
"""

from __future__ import annotations

import contextvars
import inspect
import operator
from collections.abc import Callable
from contextlib import nullcontext

import torch
from torch import Tensor, nn
from torch.func import jacfwd, jacrev, vjp, vmap
from torch.nn.modules.module import register_module_forward_hook

from .._backend import can_use_compiled
from .._shapes import broadcast_shapes
from ._mlp import mlp_standin_hook, takes_mlp_standin
from .base import Dynamics, state_control_dims
from .graph_jacobian import graph_hessians, graph_jacobians
from .row_blocks import linear_width

__all__ = [
    "linearize",
    "linearize_with_vhp",
    "linearize_with_hessians",
    "dynamics_vhp",
    "dynamics_hessians",
    "LearnedDynamics",
    "as_transition",
]

_METHODS = ("auto", "vjp", "jacrev", "jacfwd")

_FIRST_ORDER = contextvars.ContextVar("torchslq_first_order", default=False)


def first_order_only() -> bool:
    """Whether the model is being called by :func:`linearize`'s Jacobian pass: only
    first derivatives are taken and no graph is kept, so a submodule may stand in for
    its output by its value plus the linear map of its Jacobians (what
    :class:`torchslq.DiscretizedDynamics` does with generated compiled derivatives)."""
    return _FIRST_ORDER.get()


_SECOND_ORDER = contextvars.ContextVar("torchslq_second_order", default=False)


def second_order_only() -> bool:
    """Whether the model is being called by the Hessian pass of :func:`dynamics_vhp` /
    :func:`dynamics_hessians` on plain autograd: first and second derivatives at the
    point are taken and no graph to the model's parameters is kept, so a submodule may
    stand in for its output by its second-order Taylor expansion at the point (what
    :class:`torchslq.DiscretizedDynamics` does with generated compiled derivatives)."""
    return _SECOND_ORDER.get()


def _has_linear_standins(f: Callable) -> bool:
    """Whether a submodule of ``f`` can stand in by its compiled Jacobians (see
    :func:`first_order_only`); the Jacobian pass then uses plain autograd, where the
    submodule sees real tensors (inside ``torch.func`` transforms it cannot call its
    compiled code)."""
    if not isinstance(f, nn.Module) or torch._C._functorch.peek_interpreter_stack() is not None:
        return False
    return any(getattr(mod, "linear_standin", None) is not None for mod in f.modules())


def _quadratic_standins_apply(f: Callable, x: Tensor, u: Tensor) -> bool:
    """Whether the Hessian pass takes :func:`_vhp_by_autograd`: a submodule of ``f`` (not
    ``f`` itself, whose own derivatives the callers try first) is a flat MLP
    (:func:`~torchslq.dynamics._mlp.takes_mlp_standin`), or has a ``quadratic_standin``
    and the data are where its kernels run (elsewhere, e.g. on a GPU, that stand-in
    declines and the batched ``torch.func`` pass is the faster one)."""
    if not isinstance(f, nn.Module) or torch._C._functorch.peek_interpreter_stack() is not None:
        return False
    kernels = None
    for mod in f.modules():
        if mod is f:  # a stand-in stands in for a submodule called by f, not for f
            continue
        if takes_mlp_standin(mod):
            return True
        if getattr(mod, "quadratic_standin", None) is not None:
            if kernels is None:
                kernels = can_use_compiled(x.detach(), u.detach())
            if kernels:
                return True
    return False


def _output_hessians_by_autograd(
    f: Callable, x: Tensor, u: Tensor, gradients: list | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Every output's Hessian blocks ``(n, ..., ., .)`` (:func:`dynamics_hessians`'
    layout) by :func:`_vhp_by_autograd` with the output basis as weights; ``gradients``
    as there (then the Jacobians' rows)."""
    n = x.shape[-1]
    eye = torch.eye(n, dtype=x.dtype, device=x.device)
    blocks = _vhp_by_autograd(
        f, x.detach(), u.detach(), [eye[i] for i in range(n)], gradients=gradients
    )
    return tuple(torch.stack([b[i] for b in blocks]) for i in range(3))


def _mlp_standin_here(module: nn.Module, args: tuple, output):
    """:func:`~torchslq.dynamics._mlp.mlp_standin_hook` where :func:`second_order_only`."""
    return mlp_standin_hook(module, args, output) if _SECOND_ORDER.get() else None


def _vhp_by_autograd(
    f: Callable, x: Tensor, u: Tensor, weights: list[Tensor], gradients: list | None = None
) -> list[tuple[Tensor, Tensor, Tensor]]:
    """``[(Hxx, Huu, Hux)]``, one per weight ``s`` ``(..., n)`` (``x``'s leading dims):
    the Hessian blocks of ``s · f`` at every row, by double backward through *one* call
    of ``f`` on the whole batch with :func:`second_order_only` set. ``gradients``: a list
    to which the gradients ``(s · f_x, s · f_u)`` of each weight are appended (with the
    output basis as weights: the rows of the Jacobians).

    Per weight: the gradient of ``s · f`` with a graph, then its ``n + m`` rows pulled
    back at once (``is_grads_batched``). (Batching the weights too, a second batched
    backward through a batched one, measured 10x slower on a 5-64-64-4 MLP.)"""
    n, m = x.shape[-1], u.shape[-1]
    k = n + m
    token = _SECOND_ORDER.set(True)
    # flat MLPs inside f stand in by their structured expansion, only during this call
    # and only in this context (the hook is global: another thread's modules pass)
    hook = register_module_forward_hook(_mlp_standin_here)
    try:
        with torch.enable_grad():
            xg, ug = x.detach().requires_grad_(True), u.detach().requires_grad_(True)
            try:
                out = f(xg, ug)
            finally:
                hook.remove()
            basis = torch.eye(k, dtype=x.dtype, device=x.device)
            basis = basis.reshape(k, *([1] * (x.ndim - 1)), k)
            bx, bu = basis[..., :n].expand(k, *x.shape), basis[..., n:].expand(k, *u.shape)
            blocks = []
            for j, s in enumerate(weights):
                last = j == len(weights) - 1
                gx, gu = torch.autograd.grad(
                    out, (xg, ug), s.expand_as(out), create_graph=True, allow_unused=True
                )
                if gradients is not None:
                    gradients.append(
                        tuple(
                            torch.zeros_like(t) if g is None else g.detach()
                            for g, t in ((gx, x), (gu, u))
                        )
                    )
                pairs = [
                    (g, b) for g, b in ((gx, bx), (gu, bu)) if g is not None and g.requires_grad
                ]
                rows_x = rows_u = None
                if pairs:  # else f is linear in (x, u): its second derivatives are 0
                    rows_x, rows_u = torch.autograd.grad(
                        [g for g, _ in pairs],
                        (xg, ug),
                        [b for _, b in pairs],
                        is_grads_batched=True,
                        retain_graph=not last,
                        allow_unused=True,
                    )
                rows_x = x.new_zeros(k, *x.shape) if rows_x is None else rows_x
                rows_u = u.new_zeros(k, *u.shape) if rows_u is None else rows_u
                H = torch.cat([rows_x, rows_u], -1).movedim(0, -2)  # (..., k, k)
                blocks.append((H[..., :n, :n], H[..., n:, n:], H[..., n:, :n]))
    finally:
        _SECOND_ORDER.reset(token)
    return [tuple(b.detach().contiguous() for b in blk) for blk in blocks]


# The output basis is pulled back one vector at a time instead of batched (vmap /
# is_grads_batched) once rows x width reaches this: the batched pass's (n_out, rows,
# width) intermediates then leave the cache, while below it the loop only multiplies the
# op dispatches. "width": the model's widest nn.Linear output, or the state dimension.
# Measured, one thread: a 5-64-64-4 MLP's Jacobian is 1.8x faster one at a time at
# 25,600 rows, 1.15x at 3,200, equal near 500 (rows x width 32,000) and 10% slower at
# 50; the cart-pole's RK4 step on torch ops (width 4) is 12% slower one at a time at
# 3,200 rows and 5-10% faster at 25,600 (whole ILQR(shooting="multiple") solves).
POOL_ELEMENTS = 1 << 16


def _one_at_a_time(rows: int, width: int) -> bool:
    """Whether :func:`_pull_back_basis` pulls the basis back one vector at a time."""
    return rows * width >= POOL_ELEMENTS


def _pull_back_basis(
    one: Callable[[Tensor, bool], tuple],
    out: Tensor,
    batched: Callable[[Tensor], tuple],
    width: int = 0,
) -> tuple:
    """The output basis ``e_i`` pulled back through ``out (..., n_out)``: ``(n_out, ...)``
    stacks of what ``one(e_i expanded like out, last)`` / ``batched(basis)`` return
    (None entries for inputs the output does not depend on), one vector at a time from
    :data:`POOL_ELEMENTS` rows x ``max(width, n_out)`` on."""
    n_out = out.shape[-1]
    eye = torch.eye(n_out, dtype=out.dtype, device=out.device)
    if not _one_at_a_time(out.shape[:-1].numel(), max(width, n_out)):
        basis = eye.reshape(n_out, *([1] * (out.ndim - 1)), n_out).expand(n_out, *out.shape)
        return batched(basis)
    rows = [one(eye[i].expand_as(out), i == n_out - 1) for i in range(n_out)]
    return tuple(
        None if rows[0][k] is None else torch.stack([r[k] for r in rows])
        for k in range(len(rows[0]))
    )


def _jacobians_by_autograd(f: Callable, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """``(Jx (n_out, ..., n), Ju (n_out, ..., m))``: the output basis pulled back through
    one call of ``f`` on the whole batch, by autograd with :func:`first_order_only` set."""
    token = _FIRST_ORDER.set(True)
    try:
        with torch.enable_grad():
            xg, ug = x.detach().requires_grad_(True), u.detach().requires_grad_(True)
            out = f(xg, ug)
            n_out = out.shape[-1]
            Jx, Ju = _pull_back_basis(
                lambda c, last: torch.autograd.grad(
                    out, (xg, ug), c, retain_graph=not last, allow_unused=True
                ),
                out,
                lambda b: torch.autograd.grad(
                    out, (xg, ug), b, is_grads_batched=True, allow_unused=True
                ),
                linear_width(f),
            )
    finally:
        _FIRST_ORDER.reset(token)
    Jx = torch.zeros(n_out, *x.shape, dtype=x.dtype, device=x.device) if Jx is None else Jx
    Ju = torch.zeros(n_out, *u.shape, dtype=u.dtype, device=u.device) if Ju is None else Ju
    return Jx, Ju


class LearnedDynamics(Dynamics):
    """Wraps a network ``net: (..., n+m) -> (..., n)`` (e.g. an ``nn.Sequential`` MLP).

    ``x_next = x + net([x, u])`` when ``residual=True`` (the usual choice for learned
    models), else ``net([x, u])``.
    """

    def __init__(self, net: nn.Module, state_dim: int, control_dim: int, residual: bool = True):
        super().__init__()
        if not callable(net):
            raise TypeError(f"net must be a module or callable on [x, u], got {type(net).__name__}")
        dims = []
        for name, v in (("state_dim", state_dim), ("control_dim", control_dim)):
            try:  # ints (numpy's too), not 2.7 truncated to 2 or True read as 1
                d = operator.index(v) if not isinstance(v, bool) else -1
            except TypeError:
                d = -1
            if d < 1:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
            dims.append(d)
        state_dim, control_dim = dims
        if not isinstance(residual, bool):
            raise TypeError(f"residual must be a bool, got {residual!r}")
        first = net[0] if isinstance(net, nn.Sequential) and len(net) else net
        width = getattr(first, "in_features", None)
        if isinstance(first, nn.Linear) and width != state_dim + control_dim:
            raise ValueError(
                f"net takes {width} input features but [x, u] has state_dim + control_dim = "
                f"{state_dim + control_dim}"
            )
        self.net = net
        self.state_dim = state_dim
        self.control_dim = control_dim
        self.residual = residual

    def per_element_names(self, batch_size: int) -> list[str]:
        """None: a network's weights are shared by the batch whatever their shape (a
        layer as wide as the batch is still one layer); see :mod:`torchslq.per_element`."""
        return []

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        out = self.net(torch.cat([x, u], dim=-1))
        if not torch.is_tensor(out) or out.shape[-1:] != x.shape[-1:]:
            got = tuple(out.shape) if torch.is_tensor(out) else type(out).__name__
            raise ValueError(
                f"LearnedDynamics: net returned {got} for input {tuple(x.shape[:-1])} + "
                f"({self.state_dim + self.control_dim},); its last dim must be state_dim = "
                f"{self.state_dim}"
            )
        return x + out if self.residual else out


def _takes_one_input(module: nn.Module) -> bool:
    try:
        params = [
            p
            for p in inspect.signature(module.forward).parameters.values()
            if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty
        ]
    except (TypeError, ValueError):  # pragma: no cover - builtins without signature
        return False
    return len(params) == 1 or isinstance(module, nn.Sequential)


def as_transition(dynamics: Callable) -> Callable[[Tensor, Tensor], Tensor]:
    """``f(x, u) -> x_next`` for a :class:`Dynamics`, a two-argument callable, or a plain
    network taking the concatenation ``[x, u]`` (such as an ``nn.Sequential``)."""
    if isinstance(dynamics, Dynamics):
        return dynamics
    if isinstance(dynamics, nn.Module) and _takes_one_input(dynamics):
        return lambda x, u: dynamics(torch.cat([x, u], dim=-1))
    if callable(dynamics):
        return dynamics
    raise TypeError(
        f"dynamics must be a Dynamics module or callable, got {type(dynamics).__name__}"
    )


def linearize(
    dynamics: Callable,
    x: Tensor,
    u: Tensor,
    *,
    create_graph: bool = False,
    method: str = "auto",
) -> tuple[Tensor, Tensor]:
    """Jacobians ``A = df/dx (..., n, n)`` and ``B = df/du (..., n, m)`` at ``(x, u)``.

    Args:
        dynamics: a :class:`Dynamics` (its analytic :meth:`~Dynamics.jacobians` are used
            when overridden), a callable ``f(x, u)``, or a network on ``[x, u]``.
        x: ``(..., n)`` states; u: ``(..., m)`` controls. Any leading shape (batch and
            time together); it must be the same for both.
        create_graph: keep the graph from ``A, B`` to the module's parameters (and to
            ``x, u``) so a later layer can differentiate through them. When False the
            Jacobians are returned detached.
        method: ``"vjp"`` calls the dynamics once on the whole batch and pulls back the
            ``n`` output basis vectors (rows must be independent, see
            :mod:`torchslq.dynamics.base`) and supports per-element parameters;
            ``"jacrev"`` / ``"jacfwd"`` use ``vmap(jacrev|jacfwd)`` over per-row calls
            (parameters must then be shared by all rows); ``"auto"`` picks ``"vjp"``.
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if not torch.is_tensor(x) or not torch.is_tensor(u):
        raise TypeError(
            f"x and u must be tensors (..., n) and (..., m), got {type(x).__name__} and "
            f"{type(u).__name__}"
        )
    if x.shape[:-1] != u.shape[:-1]:
        raise ValueError(
            f"x and u must share leading dims, got x {tuple(x.shape)} and u {tuple(u.shape)}"
        )
    fast = None if create_graph else getattr(dynamics, "compiled_jacobians", None)
    if fast is not None:  # a model on the CPU kernels (e.g. generated compiled code)
        with torch.no_grad():
            out = fast(x, u)
        if out is not None:
            return out
    if getattr(dynamics, "has_analytic_jacobians", False):
        ctx = torch.enable_grad() if create_graph else torch.no_grad()
        with ctx:
            out = dynamics.jacobians(x, u)
        return _checked_jacobians(dynamics, out, x, u)
    f = as_transition(dynamics)
    if isinstance(dynamics, Dynamics):
        n, m = state_control_dims(dynamics)
    else:
        n, m = x.shape[-1], u.shape[-1]
    lead = x.shape[:-1]
    if not create_graph:
        x, u = x.detach(), u.detach()
    ctx = nullcontext() if create_graph else torch.no_grad()
    with ctx:
        # a learned model's Jacobians by its traced graph (None where it does not apply)
        graph = None if method != "auto" or create_graph else graph_jacobians(dynamics, x, u)
        if graph is not None:
            A, B = graph
        elif method == "auto" and not create_graph and _has_linear_standins(dynamics):
            # a submodule with compiled derivatives (e.g. a discretised physics model
            # under a learned residual) enters by its Jacobians, not its torch ops
            Jx, Ju = _jacobians_by_autograd(f, x, u)
            A, B = Jx.movedim(0, -2), Ju.movedim(0, -2)
        elif method in ("auto", "vjp"):
            # one call on the full (..., n) batch keeps per-element parameters aligned
            out, pullback = vjp(f, x, u)
            Jx, Ju = _pull_back_basis(  # (n_out, ..., n), (n_out, ..., m)
                lambda c, last: pullback(c), out, vmap(pullback), linear_width(dynamics)
            )
            A, B = Jx.movedim(0, -2), Ju.movedim(0, -2)
        else:
            jac = jacrev if method == "jacrev" else jacfwd
            xf = x.reshape(-1, x.shape[-1])
            uf = u.reshape(-1, u.shape[-1])

            def single(xi: Tensor, ui: Tensor) -> Tensor:
                return f(xi.unsqueeze(0), ui.unsqueeze(0)).squeeze(0)

            A, B = vmap(jac(single, argnums=(0, 1)))(xf, uf)
    n_out = A.shape[-2]
    if n_out != x.shape[-1]:
        raise ValueError(
            f"dynamics returned {n_out} outputs for a state of dimension {x.shape[-1]}"
        )
    del n, m
    return A.reshape(*lead, n_out, x.shape[-1]), B.reshape(*lead, n_out, u.shape[-1])


def _checked_jacobians(dynamics, out, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """The model's analytic ``jacobians(x, u)`` output ``(A, B)``, with a TypeError /
    ValueError naming the model unless they are two tensors of ``x``'s dtype and device
    broadcasting to ``(..., n, n)`` and ``(..., n, m)`` (a wrong shape used to fail deep
    inside the solvers with an IndexError)."""
    name = type(dynamics).__name__
    lead, n, m = x.shape[:-1], x.shape[-1], u.shape[-1]
    if not (isinstance(out, (tuple, list)) and len(out) == 2 and all(map(torch.is_tensor, out))):
        raise TypeError(f"{name}.jacobians(x, u) must return two tensors (A, B), got {out!r:.80}")
    for what, J, tail in (("A = df/dx", out[0], (n, n)), ("B = df/du", out[1], (n, m))):
        ok = J.ndim >= 2 and tuple(J.shape[-2:]) == tail
        try:
            ok = ok and broadcast_shapes(J.shape[:-2], lead) == lead
        except RuntimeError:
            ok = False
        if not ok:
            raise ValueError(
                f"{name}.jacobians(x, u) returned {what} of shape {tuple(J.shape)}; expected "
                f"{(*lead, *tail)} for x {tuple(x.shape)} and u {tuple(u.shape)}"
            )
        if J.dtype != x.dtype or J.device != x.device:
            raise ValueError(
                f"{name}.jacobians(x, u) returned {what} as {J.dtype} on {J.device} for x of "
                f"{x.dtype} on {x.device}; they must match"
            )
    return out[0], out[1]


# rows per call of the batched reverse-over-reverse passes (dynamics_vhp/_hessians)
HESSIAN_CHUNK_ROWS = 4096


def _in_time_chunks(fn: Callable, x: Tensor, *others: Tensor) -> list | None:
    """``fn`` on a few thousand rows at a time, split along the time dim (dim -2), or
    None when ``x`` is small enough (or has no time dim shared with ``others``).

    Split along time, not batch, so that per-element parameters shaped ``(B, 1)`` stay
    aligned; smaller calls keep the reverse-over-reverse intermediates in cache (cart-pole
    RK4 Hessians at 25,600 rows: 278 vs 442 ms, measured when this split was chosen)."""
    rows = x.shape[:-1].numel()
    if x.ndim < 3 or x.shape[-2] <= 1 or rows <= HESSIAN_CHUNK_ROWS:
        return None
    if any(o.ndim != x.ndim or o.shape[-2] != x.shape[-2] for o in others):
        return None
    steps = max(1, HESSIAN_CHUNK_ROWS * x.shape[-2] // rows)
    pieces = zip(x.split(steps, -2), *(o.split(steps, -2) for o in others), strict=True)
    return [fn(*p) for p in pieces]


def dynamics_vhp(
    dynamics: Callable, x: Tensor, u: Tensor, s: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Second-order dynamics terms ``s' f_xx``, ``s' f_uu``, ``s' f_ux`` (the DDP terms).

    The Hessian of ``s · f(x, u)`` for every row: the dynamics' analytic
    :meth:`~torchslq.Dynamics.vhp` when it has one (e.g. a :func:`torchslq.discretize`
    of a model with analytic ``jacobians`` and ``vhp``), else ``n + m`` products of its
    gradient (reverse-over-reverse, ``vmap`` over the basis): the ``n x n x n``
    second-derivative tensor of ``f`` is never formed.

    Args:
        dynamics: as for :func:`linearize`; x ``(..., n)``, u ``(..., m)``, s ``(..., n)``
            (leading dims shared; rows independent).

    Returns:
        ``(Hxx (..., n, n), Huu (..., m, m), Hux (..., m, n))``, detached.
    """
    f = as_transition(dynamics)
    n, m = x.shape[-1], u.shape[-1]
    x, u, s = x.detach(), u.detach(), s.detach()
    fast = getattr(f, "compiled_vhp", None)
    if fast is not None:
        with torch.no_grad():
            out = fast(x, u, s)
        if out is not None:
            return _full_vhp(out, x, u, s)
    if getattr(f, "has_analytic_vhp", False):
        with torch.no_grad():
            return _analytic_vhp(f, x, u, s)
    parts = _in_time_chunks(lambda *t: dynamics_vhp(f, *t), x, u, s)
    if parts is not None:  # outputs (..., T, ., .): time is dim x.ndim - 2
        return tuple(torch.cat([p[i] for p in parts], dim=x.ndim - 2) for i in range(3))
    if s.shape[:-1] == x.shape[:-1] and _quadratic_standins_apply(f, x, u):
        # a submodule with compiled second derivatives (a discretised physics model
        # under a learned residual) enters by its Taylor expansion, not its torch ops
        return _vhp_by_autograd(f, x, u, [s])[0]
    with torch.no_grad():
        g = torch.func.grad(lambda a, b: (s * f(a, b)).sum(), argnums=(0, 1))
        basis = torch.eye(n + m, dtype=x.dtype, device=x.device)
        shape = (n + m, *([1] * (x.ndim - 1)))
        ex = basis[:, :n].reshape(*shape, n).expand(n + m, *x.shape)
        eu = basis[:, n:].reshape(*shape, m).expand(n + m, *u.shape)
        _, pull = vjp(g, x, u)  # reverse-over-reverse: the Hessian is symmetric
        cols_x, cols_u = vmap(lambda dx, du: pull((dx, du)))(ex, eu)
    Hx = cols_x.movedim(0, -1)  # (..., n, n+m): rows of [Hxx | Hxu]
    Hu = cols_u.movedim(0, -1)  # (..., m, n+m): rows of [Hux | Huu]
    return Hx[..., :n], Hu[..., n:], Hu[..., :n]


def linearize_with_vhp(
    dynamics: Callable, x: Tensor, u: Tensor, *, method: str = "auto"
) -> tuple[Tensor, Tensor, Callable[[Tensor], tuple[Tensor, Tensor, Tensor]]]:
    """``(A, B, vhp)``: :func:`linearize` at ``(x, u)`` and ``vhp(s)`` =
    :func:`dynamics_vhp` ``(dynamics, x, u, s)`` at the same point, for a caller that
    needs the second after computing ``s`` from the first (a costate recursion).

    With a model whose second derivatives are chained through its integration stages
    (:meth:`torchslq.DiscretizedDynamics.jacobians_and_vhp`, analytic ``jacobians`` and
    ``vhp``), the stages' Jacobians are computed once for both; otherwise the two are
    computed as by the separate functions. Detached results, as theirs.
    """
    share = getattr(dynamics, "jacobians_and_vhp", None)
    if share is not None and x.shape[:-1] == u.shape[:-1]:
        with torch.no_grad():
            out = share(x.detach(), u.detach())
        if out is not None:
            A, B, vhp = out

            def shared_vhp(s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
                with torch.no_grad():
                    return _full_vhp(vhp(s.detach()), x, u, s)

            return A, B, shared_vhp
    A, B = linearize(dynamics, x, u, method=method)
    return A, B, lambda s: dynamics_vhp(dynamics, x, u, s)


def linearize_with_hessians(
    dynamics: Callable, x: Tensor, u: Tensor, *, method: str = "auto"
) -> tuple[Tensor, Tensor, Callable[[], tuple[Tensor, Tensor, Tensor]]]:
    """``(A, B, hessians)``: :func:`linearize` at ``(x, u)`` and ``hessians()`` =
    :func:`dynamics_hessians` ``(dynamics, x, u)`` at the same point. With a model whose
    Jacobians and Hessians come from one pass of compiled kernels
    (:meth:`torchslq.DiscretizedDynamics.jacobians_and_hessians`) both are computed
    together; otherwise ``hessians`` computes them when called. Detached results."""
    share = getattr(dynamics, "jacobians_and_hessians", None)
    if share is not None and x.shape[:-1] == u.shape[:-1]:
        with torch.no_grad():
            out = share(x.detach(), u.detach())
        if out is not None:
            A, B, blocks = out
            return A, B, lambda: blocks
    if method == "auto" and x.shape[:-1] == u.shape[:-1]:
        # a learned model's by its generated code, else its traced graph (None where
        # they do not apply)
        from .network_codegen import network_hessians

        with torch.no_grad():
            generated = network_hessians(dynamics, x.detach(), u.detach())
        if generated is not None:
            A, B, blocks = generated
            return A, B, lambda: blocks
        graph = graph_hessians(dynamics, x, u)
        if graph is not None:
            A, B, blocks = graph
            return A, B, lambda: blocks
    f = as_transition(dynamics)
    if (
        method == "auto"
        and x.shape[:-1] == u.shape[:-1]
        and x.shape[:-1].numel() <= HESSIAN_CHUNK_ROWS
        and not getattr(f, "has_analytic_jacobians", False)  # its own derivatives first
        and not getattr(f, "has_analytic_vhp", False)
        and _quadratic_standins_apply(f, x, u)
    ):
        fast = getattr(f, "compiled_jacobians", None)  # (code generated for all of f)
        with torch.no_grad():
            own = None if fast is None else fast(x.detach(), u.detach())
        if own is not None:
            return own[0], own[1], lambda: dynamics_hessians(dynamics, x, u)
        # the Hessian pass's first gradients with the output basis are the Jacobians'
        # rows: one pass through the model (and its stand-ins) gives both
        grads: list = []
        hessians = _output_hessians_by_autograd(f, x, u, gradients=grads)
        A = torch.stack([g[0] for g in grads], -2)
        B = torch.stack([g[1] for g in grads], -2)
        return A, B, lambda: hessians
    A, B = linearize(dynamics, x, u, method=method)
    return A, B, lambda: dynamics_hessians(dynamics, x, u)


def _analytic_vhp(f, x: Tensor, u: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The model's own :meth:`~torchslq.Dynamics.vhp`, at full shape ``(*lead, ., .)``
    with ``lead`` the broadcast of ``s``'s and ``x``'s leading dims."""
    return _full_vhp(f.vhp(x, u, s), x, u, s)


def _full_vhp(blocks, x: Tensor, u: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Hessian blocks expanded to ``(*lead, ., .)``, ``lead`` the broadcast of ``s``'s
    and ``x``'s leading dims, contiguous."""
    n, m = x.shape[-1], u.shape[-1]
    lead = broadcast_shapes(s.shape[:-1], x.shape[:-1])
    Hxx, Huu, Hux = blocks
    return (
        Hxx.expand(*lead, n, n).contiguous(),
        Huu.expand(*lead, m, m).contiguous(),
        Hux.expand(*lead, m, n).contiguous(),
    )


def dynamics_hessians(dynamics: Callable, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Second derivatives of every output of ``f``: ``f_i,xx``, ``f_i,uu``, ``f_i,ux``.

    ``n`` vector-Hessian products (:func:`dynamics_vhp`: the analytic ``vhp`` with the
    output basis as one extra leading dim, or reverse-over-reverse batched by ``vmap``)
    with the output basis vectors. (Forward-mode derivatives of analytic
    Jacobians were tried for the RK4-chained cart-pole and measured 1.7x slower.)

    Args:
        dynamics: as for :func:`linearize`; x ``(..., n)``, u ``(..., m)``.

    Returns:
        ``(Hxx (n, ..., n, n), Huu (n, ..., m, m), Hux (n, ..., m, n))``, detached, the
        leading index being the output ``i``.
    """
    n = x.shape[-1]
    f = as_transition(dynamics)
    fast = getattr(f, "compiled_vhp", None)
    if fast is not None:
        basis = torch.eye(n, dtype=x.dtype, device=x.device).reshape(n, *([1] * (x.ndim - 1)), n)
        with torch.no_grad():
            out = fast(x.detach(), u.detach(), basis)
        if out is not None:
            return _full_vhp(out, x, u, basis)
    if getattr(f, "has_analytic_vhp", False):
        # the output basis as n weight vectors at once (an extra leading dim)
        basis = torch.eye(n, dtype=x.dtype, device=x.device)
        basis = basis.reshape(n, *([1] * (x.ndim - 1)), n)
        with torch.no_grad():
            return _analytic_vhp(f, x.detach(), u.detach(), basis)
    parts = _in_time_chunks(lambda *t: dynamics_hessians(f, *t), x, u)
    if parts is not None:  # outputs (n, ..., T, ., .): time is dim x.ndim - 1
        return tuple(torch.cat([p[i] for p in parts], dim=x.ndim - 1) for i in range(3))
    if _quadratic_standins_apply(f, x, u):  # as in dynamics_vhp
        return _output_hessians_by_autograd(f, x, u)
    basis = torch.eye(n, dtype=x.dtype, device=x.device)
    basis = basis.reshape(n, *([1] * (x.ndim - 1)), n).expand(n, *x.shape)
    return vmap(lambda s: dynamics_vhp(f, x, u, s))(basis)
