"""Implicit differentiation of an optimal-control solution through its KKT conditions.

At a local solution ``(x*, u*)`` of ``min J(x, u; θ)`` s.t. ``x_{t+1} = f(x_t, u_t; θ)``,
``x_0 = x0`` with costates ``λ*`` (Sideris & Bobrow eqs. 8-9), the KKT conditions of the
Lagrangian ``L = J + Σ λ_{t+1}'(f(x_t, u_t) - x_{t+1})`` hold. Their derivative with
respect to ``θ`` is the KKT system of an LQ problem (Amos et al. 2018, Section 4):

* quadratic terms: the Hessian of ``L`` at the solution,
  ``H_t = ∇²l_t + Σ_i λ_{t+1,i} ∇²f_i`` ("exact") or only ``∇²l_t`` ("gn", what
  mpc.pytorch uses: the dynamics curvature is dropped, an approximation);
* constraint matrices: ``A_t = f_x``, ``B_t = f_u``.

We build that LQ problem *around the solution* so that the solution is its fixed point:
linear terms ``q = ∇l - H z*``, affine dynamics ``c = f(z*) - A x* - B u*``, and solve
it with :func:`torchslq.lqr_solve`. Its minimiser is ``z*`` again (to round-off) and
its implicit-KKT backward pass (one more LQ solve with the same factors) gives exactly
the derivative of ``z*`` with respect to every tensor that ``∇l``, ``f``, ``A``, ``B``
and ``x0`` depend on. The Hessian ``H`` may be detached: its derivative multiplies
``ẑ - z* = 0``. The gradients of the linear terms with respect to the parameters are
second derivatives (``∂²l/∂z∂θ``, ``∂²f/∂z∂θ``), which autograd takes through
``create_graph`` Jacobians.

Control bounds active at the solution are held fixed: those inputs are removed from
the LQ problem (their column of ``B`` is zeroed, their row of the Hessian replaced by
the identity and their linear term by zero), so their sensitivity is zero.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..dynamics.linearize import dynamics_vhp, linearize
from ..lq.solve import lqr_solve
from ..solvers.rollout import costate_gradient
from ..status import Status

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["cost_gradients", "implicit_solution", "lagrangian_hessian"]

_HESSIANS = ("exact", "gn")


def _batched(t: Tensor, Bsz: int, tail: tuple[int, ...]) -> Tensor:
    """``t`` of shape ``(tail)`` / ``(T.., tail)`` / ``(B, T.., tail)`` as ``(B, T.., tail)``."""
    while t.ndim < 2 + len(tail):
        t = t.unsqueeze(0)
    return t.expand(Bsz, *t.shape[1:])


def lagrangian_hessian(
    problem: Problem,
    x: Tensor,
    u: Tensor,
    hessian: str = "exact",
    A: Tensor | None = None,
    B: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Blocks of the Hessian of the Lagrangian at ``(x (B,T+1,n), u (B,T,m))``, detached.

    Returns ``(Q (B,T+1,n,n), R (B,T,m,m), S (B,T,m,n), lx (B,T+1,n), lu (B,T,m))``:
    the cost Hessian blocks plus, for ``hessian="exact"``, the costate-weighted dynamics
    second derivatives ``λ_{t+1}·f_xx``, ``λ_{t+1}·f_uu``, ``λ_{t+1}·f_ux`` (the DDP
    terms, vector-Hessian products with ``torch.func``), and the cost gradients.
    """
    if hessian not in _HESSIANS:
        raise ValueError(f"hessian must be one of {_HESSIANS}, got {hessian!r}")
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
        if hessian == "exact":
            if A is None or B is None:
                A, B = linearize(problem.transition, x[:, :T], u)
            _, lam = costate_gradient(A.detach(), B.detach(), lx, lu)
            Hxx, Huu, Hux = dynamics_vhp(problem.transition, x[:, :T], u, lam[:, 1:])
            Q = torch.cat([Q[:, :T] + Hxx, Q[:, T:]], dim=1)
            R = R + Huu
            S = S + Hux
    return Q, R, S, lx, lu


def cost_gradients(cost, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Partial derivatives ``(l_x (B,T+1,n), l_u (B,T,m))`` of ``cost(x, u)`` that keep
    the autograd graph to the cost's parameters and to ``x``, ``u`` (``torch.func.grad``
    composes with autograd; rows are independent so the sum's gradient is per row)."""
    return torch.func.grad(lambda a, b: cost(a, b).sum(), argnums=(0, 1))(x, u)


def implicit_solution(
    problem: Problem,
    x0: Tensor,
    x: Tensor,
    u: Tensor,
    *,
    hessian: str = "exact",
    active: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Attach implicit-KKT gradients to a solution ``(x, u)`` computed without autograd.

    Args:
        problem: the :class:`torchslq.Problem` that was solved; its dynamics and cost may
            depend on tensors that require grad (module parameters, references, ...).
        x0: ``(B, n)`` initial states (may require grad).
        x: ``(B, T+1, n)``, u: ``(B, T, m)``: the (converged) solution.
        hessian: ``"exact"`` (Hessian of the Lagrangian) or ``"gn"`` (cost Hessian only).
        active: optional ``(B, T, m)`` bool mask of controls at an active bound; they are
            held fixed (zero sensitivity).

    Returns:
        ``(x_out, u_out, lq_status)``: the same values as ``x``, ``u`` (exactly), with a
        backward pass giving ``dx*/dθ``, ``du*/dθ`` by one LQ solve; ``lq_status`` is
        the LQ solve's per-element :class:`torchslq.Status`: ``NOT_POSITIVE_DEFINITE``
        when the Hessian is not positive definite on the constraint null space (not a
        strict local minimum: no derivative), ``NON_FINITE`` for a non-finite solution.
        Those elements get zero gradient and never make other elements' or shared
        parameters' gradients non-finite.
    """
    T = problem.horizon
    xs, us = x.detach(), u.detach()
    # a non-finite solution has no derivative: a finite stand-in (zeros) keeps NaN out of
    # the LQ data, whose adjoint terms are summed into shared parameters
    finite = torch.isfinite(xs).flatten(1).all(1) & torch.isfinite(us).flatten(1).all(1)
    xl = torch.where(finite.view(-1, 1, 1), xs, torch.zeros_like(xs))
    ul = torch.where(finite.view(-1, 1, 1), us, torch.zeros_like(us))
    f = problem.transition
    with torch.enable_grad():
        A, Bm = linearize(problem.dynamics, xl[:, :T], ul, create_graph=True)
        Q, R, S, _, _ = lagrangian_hessian(problem, xl, ul, hessian, A, Bm)
        lx, lu = cost_gradients(problem.cost, xl, ul)
        u_free = ul
        if active is not None:
            keep = (~active).to(xs.dtype)  # (B, T, m)
            Bm = Bm * keep.unsqueeze(-2)
            R = R * keep.unsqueeze(-1) * keep.unsqueeze(-2) + torch.diag_embed(1.0 - keep)
            S = S * keep.unsqueeze(-1)
            u_free = ul * keep
        fx = f(xl[:, :T], ul)
        c = fx - (A @ xl[:, :T].unsqueeze(-1))[..., 0] - (Bm @ u_free.unsqueeze(-1))[..., 0]
        Sx = (S @ xl[:, :T].unsqueeze(-1))[..., 0]
        StU = (S.mT @ u_free.unsqueeze(-1))[..., 0]
        q = lx - (Q @ xl.unsqueeze(-1))[..., 0]
        q = torch.cat([q[:, :T] - StU, q[:, T:]], dim=1)
        r = lu - Sx - (R @ u_free.unsqueeze(-1))[..., 0]
        if active is not None:
            r = r * keep
        sol = lqr_solve(A, Bm, Q, R, x0, q, r, S, c, validate=False)
        status = torch.where(finite, sol.status, torch.full_like(sol.status, Status.NON_FINITE))
        failed = sol.status != Status.CONVERGED
        if bool(failed.any()):
            # no derivative where the Hessian is not positive definite on the null space
            # (not a strict local minimum): those elements get a positive definite stand-in
            # so that their (zero) adjoint stays finite, and zero gradient below
            fm = failed.view(-1, 1, 1, 1)
            n, m = Q.shape[-1], R.shape[-1]
            Q = torch.where(fm, torch.eye(n, dtype=Q.dtype, device=Q.device), Q)
            R = torch.where(fm, torch.eye(m, dtype=R.dtype, device=R.device), R)
            S = torch.where(fm, torch.zeros_like(S), S)
            sol = lqr_solve(A, Bm, Q, R, x0, q, r, S, c, validate=False)
    # exact values of the solver, derivatives of the LQ fixed point (none where undefined)
    good = (finite & ~failed).view(-1, 1, 1)
    x_out = xs + torch.where(good, sol.x - sol.x.detach(), torch.zeros_like(xs))
    u_out = us + torch.where(good, sol.u - sol.u.detach(), torch.zeros_like(us))
    return x_out, u_out, status
