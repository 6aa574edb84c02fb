"""State and path constraints: ``c(x_t, u_t, t) <= 0`` (or ``= 0``) and ``c_T(x_T)``.

A :class:`Constraints` holds a stage function, a terminal function or both, of one kind
(inequality ``c <= 0`` or equality ``c = 0``), or state bounds as a shorthand. Several
are combined into a :class:`ConstraintSet`, which evaluates all of them on the whole
``(B, T)`` grid at once and takes their Jacobians with ``torch.func`` (one forward pass
and ``p`` vector-Jacobian products under ``vmap`` for ``p`` rows; rows ``(b, t)`` are
independent, so the products give every row's Jacobian at once), unless the
constraint gives its own Jacobians.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn
from torch.func import vjp, vmap

__all__ = ["ConstraintSet", "Constraints", "ConstraintValues"]

KINDS = ("inequality", "equality")

StageFn = Callable[[Tensor, Tensor, Tensor], Tensor]
TerminalFn = Callable[[Tensor], Tensor]


class Constraints(nn.Module):
    """Path and terminal constraints of one kind.

    Args:
        stage: ``c(x (..., T, n), u (..., T, m), t (T,)) -> (..., T, p)``, elementwise over
            the leading dims like :class:`torchslq.Cost`'s stage (row ``(b, t)`` may
            depend only on ``x[b, t], u[b, t]``; per-element parameters ``(B, 1, 1)``
            broadcast). ``t`` is the step index. Applied at ``t = 0 .. T-1``.
        terminal: ``c_T(x (..., n)) -> (..., q)`` on the final state ``x_T``.
        kind: ``"inequality"`` (``c <= 0``, the default) or ``"equality"`` (``c = 0``).
        x_min, x_max: state bounds (a float or an ``(n,)`` tensor, ``±inf`` entries
            allowed) as a shorthand: ``x_min <= x_t <= x_max`` for every ``t = 0 .. T``
            (``x_0`` is given, so an ``x0`` outside the bounds makes the element
            infeasible). Only with ``kind="inequality"``; may be combined with
            ``stage``/``terminal``.
        stage_jacobian: optional analytic Jacobians ``(x, u, t) -> (c_x (..., T, p, n),
            c_u (..., T, p, m))`` of ``stage`` (default: ``torch.func``).
        terminal_jacobian: optional ``x -> c_x (..., q, n)`` of ``terminal``.

    A function given as an ``nn.Module`` is registered (its parameters receive gradients
    through :class:`torchslq.MPC`).

    Example (a track limit ``|s| <= 1.5`` and a goal state)::

        track = Constraints(x_min=torch.tensor([-1.5, -inf, -inf, -inf]),
                            x_max=torch.tensor([1.5, inf, inf, inf]))
        goal = Constraints(terminal=lambda x: x - x_goal, kind="equality")
        ILQR(constraints=[track, goal])
    """

    def __init__(
        self,
        stage: StageFn | None = None,
        terminal: TerminalFn | None = None,
        kind: str = "inequality",
        *,
        x_min: float | Tensor | None = None,
        x_max: float | Tensor | None = None,
        stage_jacobian: Callable | None = None,
        terminal_jacobian: Callable | None = None,
    ):
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        for name, fn in (
            ("stage", stage),
            ("terminal", terminal),
            ("stage_jacobian", stage_jacobian),
            ("terminal_jacobian", terminal_jacobian),
        ):
            if fn is not None and not callable(fn):
                raise TypeError(f"{name} must be callable, got {type(fn).__name__}")
        if stage_jacobian is not None and stage is None:
            raise ValueError("stage_jacobian needs stage")
        if terminal_jacobian is not None and terminal is None:
            raise ValueError("terminal_jacobian needs terminal")
        bounded = x_min is not None or x_max is not None
        if bounded and kind != "inequality":
            raise ValueError("x_min/x_max are inequality constraints: use kind='inequality'")
        if stage is None and terminal is None and not bounded:
            raise ValueError("Constraints needs stage, terminal, x_min or x_max")
        self.kind = kind
        self._stage_fn, self._terminal_fn = stage, terminal
        self._stage_jac, self._terminal_jac = stage_jacobian, terminal_jacobian
        self.register_buffer("x_min", _bound("x_min", x_min))
        self.register_buffer("x_max", _bound("x_max", x_max))
        if self.x_min is not None and self.x_max is not None:
            if self.x_min.shape != self.x_max.shape and min(self.x_min.ndim, self.x_max.ndim):
                raise ValueError(
                    f"x_min and x_max must have the same shape, got {tuple(self.x_min.shape)} "
                    f"and {tuple(self.x_max.shape)}"
                )
            if bool((self.x_min > self.x_max).any()):
                raise ValueError("x_min must be <= x_max everywhere")

    @property
    def equality(self) -> bool:
        return self.kind == "equality"

    def __repr__(self) -> str:
        parts = [f"kind={self.kind!r}"]
        for name in ("stage", "terminal"):
            fn = getattr(self, f"_{name}_fn")
            if fn is not None:
                parts.append(f"{name}={getattr(fn, '__name__', type(fn).__name__)}")
        for name in ("x_min", "x_max"):
            if getattr(self, name) is not None:
                parts.append(f"{name}={getattr(self, name).tolist()}")
        return f"Constraints({', '.join(parts)})"

    # the bound rows: x - x_max <= 0 and x_min - x <= 0 for the finite entries
    def _bound_rows(self, n: int, like: Tensor) -> tuple[Tensor, Tensor]:
        """``(sign (r,), index (r,), offset (r,))`` of the finite bound rows:
        ``c = sign * (x[index] - offset)``."""
        signs, idx, offs = [], [], []
        for b, sign in ((self.x_max, 1.0), (self.x_min, -1.0)):
            if b is None:
                continue
            full = b.to(like).expand(n)
            keep = torch.isfinite(full).nonzero().squeeze(1)
            signs.append(torch.full((keep.numel(),), sign, dtype=like.dtype, device=like.device))
            idx.append(keep)
            offs.append(full[keep])
        if not idx:
            z = like.new_zeros(0)
            return z, z.long(), z
        return torch.cat(signs), torch.cat(idx), torch.cat(offs)

    def _bounds(self, x: Tensor) -> Tensor | None:
        if self.x_min is None and self.x_max is None:
            return None
        sign, idx, off = self._bound_rows(x.shape[-1], x)
        return sign * (x.index_select(-1, idx) - off)

    def _bound_jacobian(self, x: Tensor) -> Tensor | None:
        """``(..., r, n)``: the bound rows' (constant) Jacobian at ``x (..., n)``."""
        if self.x_min is None and self.x_max is None:
            return None
        sign, idx, _ = self._bound_rows(x.shape[-1], x)
        rows = torch.zeros(idx.numel(), x.shape[-1], dtype=x.dtype, device=x.device)
        rows[torch.arange(idx.numel(), device=x.device), idx] = sign
        return rows.expand(*x.shape[:-1], *rows.shape)

    def stage_values(self, x: Tensor, u: Tensor, t: Tensor) -> Tensor | None:
        """``(..., T, p)`` at ``x (..., T, n)``, ``u (..., T, m)`` (None: no stage rows)."""
        parts = []
        if self._stage_fn is not None:
            parts.append(self._stage_fn(x, u, t))
        b = self._bounds(x)
        if b is not None:
            parts.append(b)
        if not parts:
            return None
        return _cat(parts, 1)

    def terminal_values(self, x: Tensor) -> Tensor | None:
        """``(..., q)`` at the final state ``x (..., n)`` (None: no terminal rows)."""
        parts = []
        if self._terminal_fn is not None:
            parts.append(self._terminal_fn(x))
        b = self._bounds(x)
        if b is not None:
            parts.append(b)
        if not parts:
            return None
        return _cat(parts, 1)

    def stage_jacobians(self, x: Tensor, u: Tensor, t: Tensor) -> tuple[Tensor, Tensor] | None:
        """``(c_x (..., T, p, n), c_u (..., T, p, m))`` (analytic where given)."""
        if self._stage_fn is None and self._bounds(x[..., :1, :]) is None:
            return None
        parts_x, parts_u = [], []
        if self._stage_fn is not None:
            if self._stage_jac is not None:
                cx, cu = self._stage_jac(x, u, t)
            else:
                cx, cu = _row_jacobians(lambda a, b: self._stage_fn(a, b, t), x, u)
            parts_x.append(cx)
            parts_u.append(cu)
        rows = self._bound_jacobian(x)
        if rows is not None:
            parts_x.append(rows)
            parts_u.append(x.new_zeros(*rows.shape[:-1], u.shape[-1]))
        return _cat(parts_x, 2), _cat(parts_u, 2)

    def terminal_jacobian(self, x: Tensor) -> Tensor | None:
        """``c_x (..., q, n)`` at the final state ``x (..., n)``."""
        parts = []
        if self._terminal_fn is not None:
            if self._terminal_jac is not None:
                parts.append(self._terminal_jac(x))
            else:
                parts.append(_row_jacobians(lambda a: self._terminal_fn(a), x)[0])
        rows = self._bound_jacobian(x)
        if rows is not None:
            parts.append(rows)
        if not parts:
            return None
        return _cat(parts, 2)


def _bound(name: str, v: float | Tensor | None) -> Tensor | None:
    if v is None:
        return None
    if isinstance(v, bool):
        raise TypeError(f"{name} must be a float or a tensor of shape (n,), got {v!r}")
    try:
        b = torch.as_tensor(v, dtype=torch.float64 if not torch.is_tensor(v) else None)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(
            f"{name} must be a float or a tensor of shape (n,), got {type(v).__name__}"
        ) from err
    if not b.is_floating_point():
        b = b.double()
    if b.ndim > 1:
        raise ValueError(f"{name} must be a float or a tensor of shape (n,), got {tuple(b.shape)}")
    if bool(torch.isnan(b).any()):
        raise ValueError(f"{name} contains NaN")
    return b


def _check_rows(name: str, v: object, ndim: int) -> None:
    """``v``, a constraint function's value at one row (``x (1, 1, n)`` for ``stage``,
    ``(1, n)`` for ``terminal``), is a tensor ``(., ., p)`` / ``(., q)``; else a TypeError
    / ValueError naming the function."""
    shape = "(..., T, p)" if name == "stage" else "(..., q)"
    if not torch.is_tensor(v):
        raise TypeError(
            f"the constraints' {name} must return a tensor {shape}, got {type(v).__name__}"
        )
    if v.ndim != ndim:  # (leading dims may be a batch: per-element parameters broadcast)
        raise ValueError(
            f"the constraints' {name} must return {shape} (a last dim of rows); at one row "
            f"of shape {(1, 1, 'n') if ndim == 3 else (1, 'n')} it returned {tuple(v.shape)}"
        )


def _check_jacobian(name: str, J: object, tail: tuple[int, int]) -> None:
    """A Jacobian (analytic ``{name}_jacobian`` or autodiff) ends in ``tail`` =
    ``(rows, n or m)``; else a ValueError naming the function."""
    if not torch.is_tensor(J) or tuple(J.shape[-2:]) != tail:
        got = tuple(J.shape) if torch.is_tensor(J) else type(J).__name__
        raise ValueError(
            f"the constraints' {name}_jacobian returned {got}; expected (..., {tail[0]}, "
            f"{tail[1]}) (rows of the {name} constraint by state or control dims)"
        )


def _cat(parts: list[Tensor], tail: int) -> Tensor:
    """Concatenate along dim ``-tail``, broadcasting the leading dims (all but the last
    ``tail``): 1 for values ``(..., p)``, 2 for Jacobians ``(..., p, k)``."""
    if len(parts) == 1:
        return parts[0]
    lead = torch.broadcast_shapes(*(p.shape[: p.ndim - tail] for p in parts))
    return torch.cat([p.expand(*lead, *p.shape[p.ndim - tail :]) for p in parts], dim=-tail)


def _row_jacobians(fn: Callable[..., Tensor], *args: Tensor) -> tuple[Tensor, ...]:
    """Jacobians of a row-wise function ``fn(*args) -> (..., p)`` for every row at once:
    ``(..., p, k_i)`` per argument ``(..., k_i)`` (one forward pass, ``p`` VJPs)."""
    out, pull = vjp(fn, *args)
    p = out.shape[-1]
    eye = torch.eye(p, dtype=out.dtype, device=out.device)
    basis = eye.reshape(p, *([1] * (out.ndim - 1)), p).expand(p, *out.shape)
    cols = vmap(pull)(basis)  # per argument: (p, ..., k_i)
    return tuple(c.movedim(0, -2) for c in cols)


@dataclass
class ConstraintValues:
    """Constraint values and Jacobians at a trajectory (batch-first).

    ``stage (B, T, p)``, ``terminal (B, q)``; with Jacobians ``cx (B, T, p, n)``,
    ``cu (B, T, p, m)``, ``cxT (B, q, n)`` (None when not computed).
    """

    stage: Tensor
    terminal: Tensor
    cx: Tensor | None = None
    cu: Tensor | None = None
    cxT: Tensor | None = None


class ConstraintSet(nn.Module):
    """Several :class:`Constraints` as one: ``p`` stage rows and ``q`` terminal rows,
    with a per-row kind (``stage_equality (p,)``, ``terminal_equality (q,)`` bool).

    The row counts are known after the first evaluation (:meth:`dims`).
    """

    def __init__(self, constraints: Constraints | Sequence[Constraints]):
        super().__init__()
        if isinstance(constraints, Constraints):
            items = [constraints]
        elif isinstance(constraints, (list, tuple)):
            items = list(constraints)
        else:
            items = []
        if not items or not all(isinstance(c, Constraints) for c in items):
            raise TypeError(
                "constraints must be a torchslq.Constraints or a list of them, got "
                f"{type(constraints).__name__}"
            )
        self.items = nn.ModuleList(items)

    def __repr__(self) -> str:
        return "[" + ", ".join(repr(c) for c in self.items) + "]"

    def _stage_parts(self, x: Tensor, u: Tensor, t: Tensor) -> list[tuple[Tensor, bool]]:
        out = []
        for c in self.items:
            v = c.stage_values(x, u, t)
            if v is not None:
                out.append((v, c.equality))
        return out

    def dims(self, n: int, m: int, like: Tensor) -> tuple[Tensor, Tensor]:
        """``(stage_equality (p,), terminal_equality (q,))`` bool: each row's kind, from
        one evaluation at a zero row of the given dtype/device."""
        x = like.new_zeros(1, 1, n)
        u = like.new_zeros(1, 1, m)
        t = torch.zeros(1, dtype=torch.long, device=like.device)
        se, te = [], []
        for c in self.items:
            for bound in ("x_min", "x_max"):
                b = getattr(c, bound)
                if b is not None and b.ndim == 1 and b.numel() not in (1, n):
                    raise ValueError(
                        f"Constraints {bound} has {b.numel()} entries but the state has n = {n}"
                    )
            # the functions' outputs at one row: (1, 1, p) and (1, q) (a wrong shape used
            # to fail deep inside the solve)
            v = c.stage_values(x, u, t)
            if v is not None:
                _check_rows("stage", v, 3)
                se.append(torch.full((v.shape[-1],), c.equality, device=like.device))
            w = c.terminal_values(x[:, 0])
            if w is not None:
                _check_rows("terminal", w, 2)
                te.append(torch.full((w.shape[-1],), c.equality, device=like.device))
        empty = torch.zeros(0, dtype=torch.bool, device=like.device)
        return (torch.cat(se) if se else empty), (torch.cat(te) if te else empty)

    def stage_values(self, x: Tensor, u: Tensor) -> Tensor:
        """The stage rows ``(..., T, p)`` at ``x (..., T, n)`` (no final state), ``u (..., T, m)``."""
        t = torch.arange(u.shape[-2], device=x.device)
        parts = [v for v, _ in self._stage_parts(x, u, t)]
        if not parts:
            return x.new_zeros(*u.shape[:-1], 0)
        return torch.cat([p.expand(*u.shape[:-1], p.shape[-1]) for p in parts], -1)

    def terminal_values(self, x: Tensor) -> Tensor:
        """The terminal rows ``(..., q)`` at final states ``x (..., n)``."""
        parts = [w for w in (c.terminal_values(x) for c in self.items) if w is not None]
        if not parts:
            return x.new_zeros(*x.shape[:-1], 0)
        return torch.cat([p.expand(*x.shape[:-1], p.shape[-1]) for p in parts], -1)

    def values(self, x: Tensor, u: Tensor, jacobians: bool = False) -> ConstraintValues:
        """All rows at ``x (..., T+1, n)``, ``u (..., T, m)``: stage ``(..., T, p)`` and
        terminal ``(..., q)``; with ``jacobians``, their Jacobians as well."""
        T = u.shape[-2]
        t = torch.arange(T, device=x.device)
        xs, xT = x[..., :T, :], x[..., T, :]
        stage, term, cx, cu, cxT = [], [], [], [], []
        for c in self.items:
            v = c.stage_values(xs, u, t)
            if v is not None:
                stage.append(v.expand(*u.shape[:-1], v.shape[-1]))
                if jacobians:
                    jx, ju = c.stage_jacobians(xs, u, t)
                    _check_jacobian("stage", jx, (v.shape[-1], x.shape[-1]))
                    _check_jacobian("stage", ju, (v.shape[-1], u.shape[-1]))
                    cx.append(jx.expand(*u.shape[:-1], *jx.shape[-2:]))
                    cu.append(ju.expand(*u.shape[:-1], *ju.shape[-2:]))
            w = c.terminal_values(xT)
            if w is not None:
                term.append(w.expand(*xT.shape[:-1], w.shape[-1]))
                if jacobians:
                    jT = c.terminal_jacobian(xT)
                    _check_jacobian("terminal", jT, (w.shape[-1], x.shape[-1]))
                    cxT.append(jT.expand(*xT.shape[:-1], *jT.shape[-2:]))
        n, m = x.shape[-1], u.shape[-1]

        def cat(parts: list[Tensor], shape: tuple[int, ...], dim: int) -> Tensor:
            return torch.cat(parts, dim) if parts else x.new_zeros(shape)

        out = ConstraintValues(
            stage=cat(stage, (*u.shape[:-1], 0), -1), terminal=cat(term, (*xT.shape[:-1], 0), -1)
        )
        if jacobians:
            out.cx = cat(cx, (*u.shape[:-1], 0, n), -2)
            out.cu = cat(cu, (*u.shape[:-1], 0, m), -2)
            out.cxT = cat(cxT, (*xT.shape[:-1], 0, n), -2)
        return out


def violation(
    values: ConstraintValues, stage_eq: Tensor, terminal_eq: Tensor
) -> tuple[Tensor, Tensor]:
    """``(stage (..., T, p), terminal (..., q))`` violations: ``|c|`` for equality rows,
    ``max(c, 0)`` for inequality rows."""

    def v(c: Tensor, eq: Tensor) -> Tensor:
        return torch.where(eq, c.abs(), c.clamp_min(0.0))

    return v(values.stage, stage_eq), v(values.terminal, terminal_eq)


def max_violation(values: ConstraintValues, stage_eq: Tensor, terminal_eq: Tensor) -> Tensor:
    """``(...)``: the largest violation of any row of each element (0 with no rows; NaN
    propagates)."""
    vs, vt = violation(values, stage_eq, terminal_eq)
    lead = vt.shape[:-1]
    parts = [vs.flatten(-2), vt]
    allv = torch.cat(parts, -1)
    if allv.shape[-1] == 0:
        return allv.new_zeros(lead)
    out = allv.amax(-1)
    # amax ignores nothing: a NaN row makes the element's violation NaN
    return torch.where(torch.isnan(allv).any(-1), torch.full_like(out, float("nan")), out)
