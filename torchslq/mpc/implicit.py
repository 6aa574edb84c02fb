"""Implicit differentiation of an optimal-control solution through its KKT conditions.

At a local solution ``(x*, u*)`` of ``min J(x, u; θ)`` s.t. ``x_{t+1} = f(x_t, u_t; θ)``,
``x_0 = x0`` with costates ``λ*`` (Sideris & Bobrow eqs. 8-9), the KKT conditions of the
Lagrangian ``L = J + Σ λ_{t+1}'(f(x_t, u_t) - x_{t+1})`` hold. Their derivative with
respect to ``θ`` is the KKT system of an LQ problem (Amos et al. 2018, Section 4):

* quadratic terms: the Hessian of ``L`` at the solution,
  ``H_t = ∇²l_t + Σ_i λ_{t+1,i} ∇²f_i`` ("exact") or only ``∇²l_t`` ("gn", what
  mpc.pytorch uses: the dynamics curvature is dropped, an approximation);
* constraint matrices: ``A_t = f_x``, ``B_t = f_u``.

With ``w = (dz, dλ)`` the solution of that LQ problem whose linear terms are the
incoming gradient ``∂ℓ/∂z*`` (zero initial state, no affine term), the implicit function
theorem gives ``dℓ/dθ = w' ∂r/∂θ`` for the KKT residual ``r``; only two of its parts
depend on ``θ``: the Lagrangian gradient ``G(θ) = ∇_z J(z*; θ) + f_z(z*; θ)'λ*`` and the
dynamics ``f(z*; θ)`` (and ``x0``). So

    dℓ/dθ = Σ_t dz_t·∂G_t/∂θ + Σ_t dλ_{t+1}·∂f(z*_t)/∂θ + dλ_0·∂x0/∂θ.

:func:`implicit_solution` factorises the LQ problem once (forward), evaluates ``G`` and
``f(z*)`` once with autograd recording (one vector-Jacobian product of ``f`` along
``λ*``, kept differentiable), and its backward pass is one linear Riccati sweep with
the stored factors followed by one reverse pass through those evaluations. (Building
the LQ data ``A = f_x``, ``B = f_u`` with ``create_graph`` and differentiating through
them, as a fixed-point LQ layer would, costs ``n`` vector-Jacobian products with graph
instead of one; measured in ``benchmarks/mpc_layer.py``.)

Control bounds active at the solution are held fixed: those inputs are removed from
the LQ problem (their column of ``B`` is zeroed, their row of the Hessian replaced by
the identity and their linear term by zero), so their sensitivity is zero.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ..lagrangian import lagrangian_terms
from ..lq.riccati import homogeneous_cost, homogeneous_dynamics, riccati_homogeneous
from ..lq.solve import lq_adjoint_solve, lq_status

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["cost_gradients", "implicit_solution", "lagrangian_hessian"]


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
    terms, vector-Hessian products with ``torch.func``), and the cost gradients
    (:func:`torchslq.lagrangian.lagrangian_terms`).
    """
    t = lagrangian_terms(problem, x, u, hessian, A, B)
    return t.Q, t.R, t.S, t.lx, t.lu


def cost_gradients(cost, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """Partial derivatives ``(l_x (B,T+1,n), l_u (B,T,m))`` of ``cost(x, u)`` that keep
    the autograd graph to the cost's parameters and to ``x``, ``u`` (``torch.func.grad``
    composes with autograd; rows are independent so the sum's gradient is per row)."""
    return torch.func.grad(lambda a, b: cost(a, b).sum(), argnums=(0, 1))(x, u)


class _KKTSensitivity(torch.autograd.Function):
    """``(Gx, Gu, F, x0) -> (x*, u*)``: the solution's implicit derivative.

    The inputs are the parameter-dependent parts of the KKT residual evaluated at the
    (fixed) solution: the Lagrangian gradient ``G = ∇_z J + f_z'λ*`` (``Gx (B,T+1,n)``,
    ``Gu (B,T,m)``), the dynamics ``F = f(z*) (B,T,n)`` and ``x0 (B,n)``; their values are
    not used, only the autograd graph from them to the parameters. The outputs are the
    solution itself. Backward (implicit function theorem on the KKT conditions,
    Amos et al. 2018, Section 4): the LQ problem with the Lagrangian Hessian as quadratic
    terms and the incoming gradient as linear terms, solved with the factorisation made
    in the forward pass (:func:`torchslq.lq.solve.lq_adjoint_solve`), gives ``dz`` and
    its costates ``dλ``; then ``dℓ/dθ = dz·∂G/∂θ + Σ dλ_{t+1}·∂f_t/∂θ + dλ_0·∂x0/∂θ``.
    """

    @staticmethod
    def forward(ctx, Gx, Gu, F, x0, x_star, u_star, Fh, Kk, Vh, chol, keep_u, good):  # noqa: D401
        ctx.save_for_backward(Fh, Kk, Vh, chol, keep_u, good)
        return x_star.clone(), u_star.clone()

    @staticmethod
    @once_differentiable
    def backward(ctx, gx, gu):
        Fh, Kk, Vh, chol, keep_u, good = ctx.saved_tensors
        if gx is None:
            gx = Vh.new_zeros(Vh.shape[0], Vh.shape[1], Vh.shape[-1] - 1)
        if gu is None:
            gu = Kk.new_zeros(Kk.shape[:-1])
        # no derivative for elements without one (zero gradient, never NaN)
        gx = torch.where(good.view(-1, 1, 1), gx, torch.zeros_like(gx))
        gu = torch.where(good.view(-1, 1, 1) & keep_u, gu, torch.zeros_like(gu))
        dx, du, dlam = lq_adjoint_solve(Fh, Kk, Vh, chol, gx, gu)
        none = (None,) * 8
        return dx, du, dlam[:, 1:], dlam[:, 0], *none


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
        the LQ factorisation's per-element :class:`torchslq.Status`:
        ``NOT_POSITIVE_DEFINITE`` when the Hessian is not positive definite on the
        constraint null space (not a strict local minimum: no derivative), ``NON_FINITE``
        for a non-finite solution or factorisation. Those elements get zero gradient and
        never make other elements' or shared parameters' gradients non-finite.

    Cost: the forward pass factorises the LQ problem (Riccati pass) and evaluates the
    Lagrangian gradient and the dynamics once with autograd recording; the backward pass
    is one linear Riccati sweep plus one reverse pass through those two evaluations (a
    single vector-Jacobian product, not one per state dimension).
    """
    T = problem.horizon
    xs, us = x.detach(), u.detach()
    # a non-finite solution has no derivative: a finite stand-in (zeros) keeps NaN out of
    # the LQ data and of the graph that carries gradients to shared parameters
    finite = torch.isfinite(xs).flatten(1).all(1) & torch.isfinite(us).flatten(1).all(1)
    xl = torch.where(finite.view(-1, 1, 1), xs, torch.zeros_like(xs))
    ul = torch.where(finite.view(-1, 1, 1), us, torch.zeros_like(us))
    with torch.no_grad():
        lt = lagrangian_terms(problem, xl, ul, hessian)
        Q, R, S, lam, A, Bm = lt.Q, lt.R, lt.S, lt.lam, lt.A, lt.B
        keep_u = torch.ones_like(ul, dtype=torch.bool) if active is None else ~active
        if active is not None:
            keep = keep_u.to(xs.dtype)  # (B, T, m)
            Bm = Bm * keep.unsqueeze(-2)
            R = R * keep.unsqueeze(-1) * keep.unsqueeze(-2) + torch.diag_embed(1.0 - keep)
            S = S * keep.unsqueeze(-1)
        Fh = homogeneous_dynamics(A, Bm)
        fac = riccati_homogeneous(Fh, *homogeneous_cost(Q, R, None, None, S))
        ok_fac = torch.isfinite(fac.Kk).flatten(1).all(1) & torch.isfinite(fac.Vh).flatten(1).all(1)
        not_pd = fac.failed  # (a failed factorisation also leaves non-finite gains)
        failed = fac.failed | ~ok_fac
        if bool(failed.any()):
            # no derivative where the Hessian is not positive definite on the null space
            # (not a strict local minimum): those elements get a positive definite stand-in
            # so that their (zero) adjoint stays finite
            fm = failed.view(-1, 1, 1, 1)
            n, m = Q.shape[-1], R.shape[-1]
            Q = torch.where(fm, torch.eye(n, dtype=Q.dtype, device=Q.device), Q)
            R = torch.where(fm, torch.eye(m, dtype=R.dtype, device=R.device), R)
            S = torch.where(fm, torch.zeros_like(S), S)
            fac = riccati_homogeneous(Fh, *homogeneous_cost(Q, R, None, None, S))
        # a non-finite solution is NON_FINITE whatever its factorisation did
        status = lq_status(not_pd & finite, ok_fac & finite)
        good = finite & ~failed

    f, cost = problem.transition, problem.cost
    lam_next = lam[:, 1:].detach()

    def lagrangian(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
        fz = f(a[:, :T], b)
        return cost(a, b).sum() + (lam_next * fz).sum(), fz

    with torch.enable_grad():
        # one evaluation of ∇_z (J + λ*'f) and of f, recording the graph to every
        # parameter (torch.func.grad composes with autograd)
        (Gx, Gu), Fz = torch.func.grad(lagrangian, argnums=(0, 1), has_aux=True)(xl, ul)
        if not (Gx.requires_grad or Gu.requires_grad or Fz.requires_grad or x0.requires_grad):
            return xs, us, status
        x_out, u_out = _KKTSensitivity.apply(
            Gx, Gu, Fz, x0.expand(xs.shape[0], xs.shape[-1]), xs, us,
            Fh, fac.Kk, fac.Vh, fac.chol, keep_u, good,
        )  # fmt: skip
    return x_out, u_out, status
