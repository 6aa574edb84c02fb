"""The Lagrangian of an optimal control problem at a trajectory: its Hessian blocks, the
cost gradients and the costates, with optional constraint rows.

One implementation for the MPC layer's implicit gradients
(:mod:`torchslq.mpc.implicit`, :mod:`torchslq.mpc.unroll`) and the constrained KKT
system (:mod:`torchslq.constraints.kkt`: polishing, constrained gradients).

``L = J(x, u) + sum_t λ_{t+1}·(f(x_t, u_t) - x_{t+1}) + ν·c(x, u)``: the costates
``λ`` solve the adjoint recursion of the cost plus the multiplier-weighted constraint
gradients (Sideris & Bobrow eqs. 8-9), and the exact Hessian adds the dynamics'
``λ_{t+1}·f_zz`` (DDP's terms) and the rows' ``ν·c_zz`` to the cost's.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from .costs.general import Cost
from .dynamics.linearize import dynamics_vhp, linearize_with_vhp
from .dynamics.rollout import costate_gradient

if TYPE_CHECKING:  # pragma: no cover
    from .problem import Problem

__all__ = ["HESSIANS", "LagrangianTerms", "RowMultipliers", "lagrangian_terms"]

HESSIANS = ("exact", "gn")


@dataclass(frozen=True)
class RowMultipliers:
    """Constraint rows in the Lagrangian: the set, its values and Jacobians at the
    trajectory (``ConstraintSet.values(x, u, jacobians=True)``) and the multipliers
    ``stage (B, T, p)``, ``terminal (B, q)``."""

    constraints: Any
    values: Any
    stage: Tensor
    terminal: Tensor


@dataclass(frozen=True)
class LagrangianTerms:
    """Blocks at ``(x (B,T+1,n), u (B,T,m))``, detached: ``Q (B,T+1,n,n)`` (index ``T``
    the terminal block), ``R (B,T,m,m)``, ``S (B,T,m,n)`` (the ``u x`` block), the
    gradients ``lx (B,T+1,n)``, ``lu (B,T,m)`` of the cost plus the rows, the costates
    ``lam (B,T+1,n)`` and the dynamics' Jacobians ``A (B,T,n,n)``, ``B (B,T,n,m)``."""

    Q: Tensor
    R: Tensor
    S: Tensor
    lx: Tensor
    lu: Tensor
    lam: Tensor
    A: Tensor
    B: Tensor


def _batched(t: Tensor, Bsz: int, tail: tuple[int, ...]) -> Tensor:
    """``t`` of shape ``(tail)`` / ``(T.., tail)`` / ``(B, T.., tail)`` as ``(B, T.., tail)``."""
    while t.ndim < 2 + len(tail):
        t = t.unsqueeze(0)
    return t.expand(Bsz, *t.shape[1:])


def lagrangian_terms(
    problem: Problem,
    x: Tensor,
    u: Tensor,
    hessian: str = "exact",
    A: Tensor | None = None,
    B: Tensor | None = None,
    rows: RowMultipliers | None = None,
) -> LagrangianTerms:
    """:class:`LagrangianTerms` at ``(x, u)``.

    Args:
        hessian: ``"exact"``: the Hessian of the Lagrangian (cost, ``λ·f_zz`` by
            vector-Hessian products with ``torch.func``, and with ``rows`` their
            ``ν·c_zz``); ``"gn"``: the cost's (Gauss-Newton).
        A, B: the dynamics' Jacobians when the caller has them (else computed here with
            the second derivatives' shared work, :func:`linearize_with_vhp`).
        rows: optional constraint rows with their multipliers.
    """
    if hessian not in HESSIANS:
        raise ValueError(f"hessian must be one of {HESSIANS}, got {hessian!r}")
    T, n, m = problem.horizon, problem.state_dim, problem.control_dim
    Bsz = x.shape[0]
    x, u = x.detach(), u.detach()
    with torch.no_grad():
        e = problem.cost.quadratize(x, u)
        Q = _batched(e.lxx.detach(), Bsz, (n, n)).expand(Bsz, T + 1, n, n)
        R = _batched(e.luu.detach(), Bsz, (m, m)).expand(Bsz, T, m, m)
        if e.lux is None:
            S = x.new_zeros(Bsz, T, m, n)
        else:
            S = _batched(e.lux.detach(), Bsz, (m, n)).expand(Bsz, T, m, n)
        lx = _batched(e.lx.detach(), Bsz, (n,)).expand(Bsz, T + 1, n)
        lu = _batched(e.lu.detach(), Bsz, (m,)).expand(Bsz, T, m)
        if rows is not None:  # the rows' gradients ν·c_z
            v = rows.values
            c_x = (v.cx * rows.stage.unsqueeze(-1)).sum(-2)
            c_xT = (v.cxT * rows.terminal.unsqueeze(-1)).sum(-2)
            lx = lx + torch.cat([c_x, c_xT.unsqueeze(1)], dim=1)
            lu = lu + (v.cu * rows.stage.unsqueeze(-1)).sum(-2)
        if A is None or B is None:
            A, B, vhp = linearize_with_vhp(problem.transition, x[:, :T], u)
        else:
            vhp = partial(dynamics_vhp, problem.transition, x[:, :T], u)
        _, lam = costate_gradient(A.detach(), B.detach(), lx, lu)
        if hessian == "exact":
            Hxx, Huu, Hux = vhp(lam[:, 1:])
            Q = torch.cat([Q[:, :T] + Hxx, Q[:, T:]], dim=1)
            R = R + Huu
            S = S + Hux
            if rows is not None and (rows.stage.numel() or rows.terminal.numel()):
                # the multiplier-weighted constraint curvature, by the cost machinery
                cset, nu_s, nu_T = rows.constraints, rows.stage, rows.terminal
                curv = Cost(
                    stage=lambda a, b, t: (nu_s * cset.stage_values(a, b)).sum(-1),
                    terminal=lambda a: (nu_T * cset.terminal_values(a)).sum(-1),
                    state_dim=n,
                    control_dim=m,
                ).quadratize(x, u)
                Q, R, S = Q + curv.lxx, R + curv.luu, S + curv.lux
    return LagrangianTerms(Q=Q, R=R, S=S, lx=lx, lu=lu, lam=lam, A=A, B=B)
