"""Active-set polishing of a constrained solution: Newton steps on its KKT conditions.

The augmented-Lagrangian loop converges linearly in its multipliers; near the solution
its active set is settled, and Newton's method on the KKT conditions of the problem
with that active set held as equalities converges quadratically (ALTRO's projection
step plays the same role). One step solves the dense KKT system of
:func:`~torchslq.constraints.kkt.lagrangian_kkt` with the residual

    [∇_u L at the free controls (0 at controls on a bound); c at the active rows]

(the state rows of ``∇_z L`` vanish by the costate recursion, the dynamics rows by the
rollout), then takes the new controls (clipped into the bounds), rolls them out (so the
trajectory stays dynamically exact) and updates the active rows' multipliers. A step
is kept, per element, only where it lowers the KKT error (largest violation over
``constraint_tol``, projected Lagrangian gradient over ``tol``, negative inequality
multipliers over ``tol``); an element whose active set was wrong keeps its input.

Cost: one dense LDL' factorisation per element and step (see :mod:`torchslq.mpc.constrained`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..dynamics.linearize import linearize
from ..dynamics.rollout import costate_gradient, rollout
from .kkt import lagrangian_kkt, symmetric_factor
from .spec import ConstraintSet, max_violation

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["kkt_error", "polish"]


def _at_bounds(u: Tensor, lo: Tensor | None, hi: Tensor | None) -> Tensor:
    if lo is None:
        return torch.zeros_like(u, dtype=torch.bool)
    return (u <= lo) | (u >= hi)


def _solve(K: Tensor, rhs: Tensor) -> tuple[Tensor, Tensor]:
    """``(K^{-1} rhs (B, N), solved (B,))`` for symmetric ``K`` (Bunch-Kaufman LDL'):
    elements whose ``K`` is singular or not finite get zeros."""
    LD, piv, finite = symmetric_factor(K)
    sol = torch.linalg.ldl_solve(LD, piv, torch.where(finite.view(-1, 1), rhs, 0.0).unsqueeze(-1))
    sol = sol[..., 0]
    ok = finite & torch.isfinite(sol).all(1)
    return torch.where(ok.view(-1, 1), sol, 0.0), ok


def kkt_error(
    problem: Problem,
    constraints: ConstraintSet,
    stage_eq: Tensor,
    terminal_eq: Tensor,
    x: Tensor,
    u: Tensor,
    nu_s: Tensor,
    nu_T: Tensor,
    lo: Tensor | None = None,
    hi: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """``(violation, grad_norm, dual)`` ``(B,)`` at ``(x, u)`` with multipliers
    ``nu_s (B,T,p)``, ``nu_T (B,q)``: the largest violation, the norm of the projected
    gradient of the Lagrangian ``J + ν·c`` in ``u`` (costate recursion, bounds
    ``lo``/``hi`` projected as in :class:`torchslq.ILQR`), and the most negative
    inequality multiplier (as a positive number; 0 when none)."""
    T = problem.horizon
    n, m = problem.state_dim, problem.control_dim
    Bsz = x.shape[0]
    with torch.no_grad():
        v = constraints.values(x, u, jacobians=True)
        with torch.enable_grad():
            xg, ug = x.detach().requires_grad_(), u.detach().requires_grad_()
            lx, lu = torch.autograd.grad(problem.cost(xg, ug).sum(), (xg, ug))
        lx = lx.expand(Bsz, T + 1, n).clone()
        lx[:, :T] += (v.cx * nu_s.unsqueeze(-1)).sum(-2)
        lx[:, T] += (v.cxT * nu_T.unsqueeze(-1)).sum(-2)
        lu = lu.expand(Bsz, T, m) + (v.cu * nu_s.unsqueeze(-1)).sum(-2)
        A, B = linearize(problem.transition, x[:, :T], u)
        g, _ = costate_gradient(A, B, lx, lu)
        if lo is not None:
            g = u - torch.minimum(torch.maximum(u - g, lo), hi)
        viol = max_violation(v, stage_eq, terminal_eq)
        neg = torch.cat(
            [
                torch.where(stage_eq, 0.0, -nu_s).reshape(Bsz, -1),
                torch.where(terminal_eq, 0.0, -nu_T),
                x.new_zeros(Bsz, 1),
            ],
            1,
        ).amax(1)
    return viol, g.flatten(1).norm(dim=1), neg


def polish(
    problem: Problem,
    constraints: ConstraintSet,
    stage_eq: Tensor,
    terminal_eq: Tensor,
    x: Tensor,
    u: Tensor,
    nu_s: Tensor,
    nu_T: Tensor,
    lo: Tensor | None,
    hi: Tensor | None,
    *,
    tol: float,
    constraint_tol: float,
    steps: int = 3,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Up to ``steps`` Newton steps (module docstring) from ``(x (B,T+1,n), u (B,T,m))``
    with multipliers ``nu_s``, ``nu_T`` and control bounds ``lo``, ``hi`` ``(B,T,m)``
    (or None). Returns ``(x, u, nu_s, nu_T, ok, violation, grad_norm)``: the polished point
    (the input where no step helped), ``ok (B,)``, whether it meets ``constraint_tol``
    and ``tol`` with nonnegative inequality multipliers, and its largest violation and
    projected Lagrangian gradient norm ``(B,)`` (:func:`kkt_error`)."""
    Bsz, T, m = u.shape
    n = x.shape[-1]
    k = n + m
    N = T * k + n
    p, q = stage_eq.numel(), terminal_eq.numel()
    x0 = x[:, 0]
    dev = x.device
    u_rows = (torch.arange(T, device=dev)[:, None] * k + n + torch.arange(m, device=dev)).reshape(
        -1
    )
    c_rows = N + n + T * n + torch.arange(T * p, device=dev)
    t_rows = N + n + T * n + T * p + torch.arange(q, device=dev)

    def score(xx, uu, ns, nt):
        viol, grad, neg = kkt_error(
            problem, constraints, stage_eq, terminal_eq, xx, uu, ns, nt, lo, hi
        )
        s = torch.maximum(torch.maximum(viol / constraint_tol, grad / tol), neg / tol)
        ok = (viol <= constraint_tol) & (grad <= tol) & (neg <= tol)
        return torch.nan_to_num(s, nan=float("inf")), ok, viol, grad

    best, ok, viol, grad = score(x, u, nu_s, nu_T)
    for _ in range(steps):
        if bool(ok.all()):
            break
        act_s = stage_eq | (nu_s > 0)
        act_T = terminal_eq | (nu_T > 0)
        act_u = _at_bounds(u, lo, hi)
        with torch.no_grad():
            pt = lagrangian_kkt(problem, constraints, x, u, nu_s, nu_T, act_s, act_T, act_u)
            R = x.new_zeros(Bsz, pt.K.shape[-1])
            # bound multipliers absorb the gradient of the controls held at a bound
            R[:, u_rows] = torch.where(act_u, 0.0, pt.grad_u).reshape(Bsz, -1)
            R[:, c_rows] = torch.where(act_s, pt.values.stage, 0.0).reshape(Bsz, -1)
            R[:, t_rows] = torch.where(act_T, pt.values.terminal, 0.0)
            step, solved = _solve(pt.K, -R)
            step = torch.where(solved.view(-1, 1), step, 0.0)
            u_new = u + step[:, u_rows].reshape(Bsz, T, m)
            if lo is not None:
                u_new = torch.minimum(torch.maximum(u_new, lo), hi)
            x_new = rollout(problem.transition, x0, u_new)
            ns_new = torch.where(act_s, nu_s + step[:, c_rows].reshape(Bsz, T, p), 0.0)
            nt_new = torch.where(act_T, nu_T + step[:, t_rows], 0.0)
        s_new, ok_new, viol_new, grad_new = score(x_new, u_new, ns_new, nt_new)
        better = solved & (s_new < best)
        b3 = better.view(-1, 1, 1)
        x, u = torch.where(b3, x_new, x), torch.where(b3, u_new, u)
        nu_s, nu_T = torch.where(b3, ns_new, nu_s), torch.where(better.view(-1, 1), nt_new, nu_T)
        best = torch.where(better, s_new, best)
        ok = torch.where(better, ok_new, ok)
        viol, grad = torch.where(better, viol_new, viol), torch.where(better, grad_new, grad)
        if not bool(better.any()):
            break
    return x, u, nu_s, nu_T, ok, viol, grad
