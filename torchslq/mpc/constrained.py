"""Implicit differentiation of a constrained optimal-control solution (dense KKT).

At a local solution ``z* = (x_0, u_0, x_1, ..., u_{T-1}, x_T)`` of
``min J(z; θ)`` s.t. ``x_0 = x0``, ``x_{t+1} = f(x_t, u_t; θ)``, the constraint rows
``c(z; θ)`` (:class:`torchslq.Constraints`) and control bounds, the active set is held:
equality rows, inequality rows with a positive multiplier, and controls at an active
bound become equalities; the others are dropped. The KKT residual of that
equality-constrained problem,

    R(z, μ; θ) = [∇_z J + D(z; θ)' μ ;  r(z; θ)],   r = (x0 - x_0, f - x_next, c_A, u_A - b),

has the symmetric Jacobian ``K = [[H, D'], [D, 0]]`` with ``H = ∇²_z L`` (cost, the
costate-weighted dynamics curvature and the multiplier-weighted constraint curvature;
``hessian="gn"`` keeps the cost's only) and ``D = ∂r/∂z``. By the implicit function
theorem, for a loss ``ℓ(z*)``: solve ``K w = [∂ℓ/∂z; 0]``, then

    dℓ/dθ = -w_z · ∂G/∂θ - w_μ · ∂r/∂θ,   G = ∇_z (J + λ·f + ν·c)  (multipliers fixed),

so the backward pass is one solve with the factorisation made in the forward pass and
one reverse pass through ``G`` and ``r`` evaluated with autograd recording.

The KKT matrix is dense, one per element: ``(T+1) n + T m`` primal and ``(T+1) n + T p
+ q + T m`` dual unknowns (about 560 for the cart-pole with T = 50): an LDL' of that size
per element costs milliseconds, so this path suits the batch sizes of training
(the unconstrained layer uses the Riccati recursion instead). Inactive rows stay in the
matrix as ``μ_i = 0`` (a unit diagonal), so every element has the same size.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ..constraints.kkt import lagrangian_kkt, symmetric_factor
from ..constraints.spec import ConstraintSet
from ..status import Status

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["constrained_implicit_solution"]


class _ConstrainedKKTSensitivity(torch.autograd.Function):
    """``(Gx, Gu, F, x0, Cs, CT) -> (x*, u*)``; backward by the stored LDL' of ``K``."""

    @staticmethod
    def forward(ctx, Gx, Gu, F, x0, Cs, CT, x_star, u_star, LU, piv, good):  # noqa: D401
        ctx.save_for_backward(LU, piv, good)
        ctx.dims = (x_star.shape, u_star.shape, Cs.shape, CT.shape)
        return x_star.clone(), u_star.clone()

    @staticmethod
    @once_differentiable
    def backward(ctx, gx, gu):
        LU, piv, good = ctx.saved_tensors
        xs, us, cs, ct = ctx.dims
        Bsz, T1, n = xs
        T, m = us[1], us[2]
        p, q = cs[-1], ct[-1]
        k = n + m
        N = T * k + n
        if gx is None:
            gx = LU.new_zeros(xs)
        if gu is None:
            gu = LU.new_zeros(us)
        g = torch.where(good.view(-1, 1, 1), gx, 0.0), torch.where(good.view(-1, 1, 1), gu, 0.0)
        rhs = LU.new_zeros(Bsz, LU.shape[-1])
        z = torch.cat([g[0][:, :T], g[1]], -1).reshape(Bsz, T * k)
        rhs[:, : T * k] = z
        rhs[:, T * k : N] = g[0][:, T]
        w = torch.linalg.ldl_solve(LU, piv, rhs.unsqueeze(-1))[..., 0]
        w = torch.where(good.view(-1, 1), w, 0.0)
        wz = w[:, : T * k].reshape(Bsz, T, k)
        wx = torch.cat([wz[..., :n], w[:, T * k : N].unsqueeze(1)], 1)
        wu = wz[..., n:]
        mu = w[:, N:]
        w_x0 = mu[:, :n]
        w_dyn = mu[:, n : n + T * n].reshape(Bsz, T, n)
        o = n + T * n
        w_c = mu[:, o : o + T * p].reshape(Bsz, T, p)
        w_cT = mu[:, o + T * p : o + T * p + q]
        # dℓ/dθ = -w_z·∂G/∂θ - w_μ·∂r/∂θ; r = (x0 - x_0, f - x_next, c, ...)
        none = (None,) * 5
        return -wx, -wu, -w_dyn, -w_x0, -w_c, -w_cT, *none


def constrained_implicit_solution(
    problem: Problem,
    constraints: ConstraintSet,
    x0: Tensor,
    x: Tensor,
    u: Tensor,
    multipliers: dict[str, Tensor],
    stage_eq: Tensor,
    terminal_eq: Tensor,
    *,
    hessian: str = "exact",
    active_u: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Attach implicit-KKT gradients to a constrained solution (module docstring).

    Args:
        problem: the problem solved (dynamics and cost may hold tensors requiring grad).
        constraints: its :class:`~torchslq.constraints.ConstraintSet` (may too).
        x0 ``(B, n)``; x ``(B, T+1, n)``, u ``(B, T, m)``: the solution.
        multipliers: ``{"stage": (B, T, p), "terminal": (B, q)}`` at the solution.
        stage_eq ``(p,)``, terminal_eq ``(q,)``: the rows' kinds.
        hessian: ``"exact"`` (Hessian of the Lagrangian) or ``"gn"`` (the cost's).
        active_u: ``(B, T, m)`` bool, controls at an active bound (held fixed).

    Returns:
        ``(x_out, u_out, status)``: the solution's values with the implicit backward;
        ``status`` ``(B,)`` is ``CONVERGED`` where the KKT matrix was factorised,
        ``NOT_POSITIVE_DEFINITE`` where it is singular (no derivative: zero gradient),
        ``NON_FINITE`` for a non-finite solution.
    """
    T, n = problem.horizon, problem.state_dim
    xs, us = x.detach(), u.detach()
    Bsz = xs.shape[0]
    finite = torch.isfinite(xs).flatten(1).all(1) & torch.isfinite(us).flatten(1).all(1)
    xl = torch.where(finite.view(-1, 1, 1), xs, torch.zeros_like(xs))
    ul = torch.where(finite.view(-1, 1, 1), us, torch.zeros_like(us))
    nu_s = torch.nan_to_num(multipliers["stage"].detach())
    nu_T = torch.nan_to_num(multipliers["terminal"].detach())
    act_s = stage_eq | (nu_s > 0)
    act_T = terminal_eq | (nu_T > 0)
    act_u = torch.zeros_like(ul, dtype=torch.bool) if active_u is None else active_u
    f = problem.transition
    with torch.no_grad():
        point = lagrangian_kkt(
            problem, constraints, xl, ul, nu_s, nu_T, act_s, act_T, act_u, hessian
        )
        K, lam = point.K, point.lam
        LU, piv, ok = symmetric_factor(K)
        good = finite & ok
        status = torch.full((Bsz,), int(Status.CONVERGED), dtype=torch.int64, device=xs.device)
        status = status.masked_fill(~ok, int(Status.NOT_POSITIVE_DEFINITE))
        status = status.masked_fill(~finite, int(Status.NON_FINITE))

    lam_next = lam[:, 1:].detach()

    def lagrangian(a: Tensor, b: Tensor):
        fz = f(a[:, :T], b)
        cv = constraints.values(a, b)
        total = problem.cost(a, b).sum() + (lam_next * fz).sum()
        total = total + (nu_s * cv.stage).sum() + (nu_T * cv.terminal).sum()
        return total, (fz, cv.stage, cv.terminal)

    with torch.enable_grad():
        (Gx, Gu), (Fz, Cs, CT) = torch.func.grad(lagrangian, argnums=(0, 1), has_aux=True)(xl, ul)
        needs = (Gx, Gu, Fz, Cs, CT, x0)
        if not any(t.requires_grad for t in needs):
            return xs, us, status
        x_out, u_out = _ConstrainedKKTSensitivity.apply(
            Gx, Gu, Fz, x0.expand(Bsz, n), Cs, CT, xs, us, LU, piv, good
        )
    return x_out, u_out, status
