"""The augmented Lagrangian of a constrained problem, as a cost the unconstrained solvers
minimise (Powell-Hestenes-Rockafellar form, as in ALTRO and trajax's ``constrained_ilqr``).

For rows ``c`` with multipliers ``λ`` and a penalty ``ρ > 0`` (per element)::

    equality   c = 0:   λ'c + ρ/2 |c|²
    inequality c <= 0:  (|max(0, λ + ρ c)|² - |λ|²) / (2ρ)

Both are continuously differentiable with gradient ``λ̂' c_z``, where ``λ̂ = λ + ρ c``
(equality) or ``max(0, λ + ρ c)`` (inequality) is also the first-order multiplier
update. The quadratic model keeps the Gauss-Newton term ``ρ c_z' D c_z`` (``D``: the
rows with ``λ + ρ c > 0``, every equality row), which is positive semidefinite; the
rows' own second derivatives ``Σ λ̂_i ∇²c_i`` are added with ``curvature=True`` (without
them the model is exact for linear rows only; the fixed point is exact either way,
since the gradient is, but curved rows then cost more iterations).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..costs.general import Cost
from ..costs.quadratic import CostExpansion
from .spec import ConstraintSet, ConstraintValues

__all__ = ["AugmentedLagrangianCost", "multiplier_estimate"]


def multiplier_estimate(c: Tensor, lam: Tensor, rho: Tensor, equality: Tensor) -> Tensor:
    """``λ̂ = λ + ρ c`` on equality rows, ``max(0, λ + ρ c)`` on inequality rows
    (``c, lam (..., r)``, ``rho`` broadcastable, ``equality (r,)`` bool)."""
    shifted = lam + rho * c
    return torch.where(equality, shifted, shifted.clamp_min(0.0))


def _penalty(c: Tensor, lam: Tensor, rho: Tensor, equality: Tensor) -> Tensor:
    """Per-row augmented terms (summed by the caller)."""
    eq = lam * c + 0.5 * rho * c * c
    ineq = (torch.clamp_min(lam + rho * c, 0.0).pow(2) - lam * lam) / (2.0 * rho)
    return torch.where(equality, eq, ineq)


class AugmentedLagrangianCost(nn.Module):
    """``J(x, u) + Σ_t AL(c_t, λ_t, ρ) + AL(c_T, λ_T, ρ)`` for a batch of ``B`` elements.

    Args:
        cost: the problem's cost (``cost(x, u)``, ``quadratize(x, u)``).
        constraints: the :class:`~torchslq.constraints.ConstraintSet`.
        lam: stage multipliers ``(B, T, p)``; lam_T: terminal multipliers ``(B, q)``.
        rho: penalties ``(B,)``.
        stage_eq, terminal_eq: ``(p,)``, ``(q,)`` bool, each row's kind.
        curvature: add the rows' curvature ``Σ λ̂_i ∇²c_i`` to the quadratic model (an
            exact Hessian of the augmented terms where the rows are active; it may be
            indefinite, which the solvers' regularisation handles).

    ``forward`` accepts trial batches ``x (..., B, T+1, n)`` (the line search's).
    """

    def __init__(
        self,
        cost: nn.Module,
        constraints: ConstraintSet,
        lam: Tensor,
        lam_T: Tensor,
        rho: Tensor,
        stage_eq: Tensor,
        terminal_eq: Tensor,
        curvature: bool = False,
    ):
        super().__init__()
        self.curvature = curvature
        self.cost = cost
        self.constraints = constraints
        self.lam, self.lam_T, self.rho = lam, lam_T, rho
        self.stage_eq, self.terminal_eq = stage_eq, terminal_eq
        for name in ("state_dim", "control_dim"):  # Problem checks them where the cost has them
            if hasattr(cost, name):
                setattr(self, name, getattr(cost, name))

    def augmentation(self, values: ConstraintValues) -> Tensor:
        """The constraint terms ``(..., B)`` for constraint values at a trajectory."""
        rho = self.rho[:, None, None]
        s = _penalty(values.stage, self.lam, rho, self.stage_eq).sum((-1, -2))
        t = _penalty(values.terminal, self.lam_T, rho[:, 0], self.terminal_eq).sum(-1)
        return s + t

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return self.cost(x, u) + self.augmentation(self.constraints.values(x, u))

    def quadratize(self, x: Tensor, u: Tensor) -> CostExpansion:
        """The cost's expansion plus the constraint terms' gradient ``c_z' λ̂`` and
        Gauss-Newton Hessian ``ρ c_z' D c_z`` (module docstring), all ``(B, ...)``."""
        e = self.cost.quadratize(x, u)
        Bsz, T = u.shape[0], u.shape[1]
        n, m = x.shape[-1], u.shape[-1]
        with torch.no_grad():
            v = self.constraints.values(x.detach(), u.detach(), jacobians=True)
            rho = self.rho[:, None, None]
            lam_hat = multiplier_estimate(v.stage, self.lam, rho, self.stage_eq)
            w = torch.where(self.stage_eq, rho, rho * (self.lam + rho * v.stage > 0))
            lam_hat_T = multiplier_estimate(v.terminal, self.lam_T, rho[:, 0], self.terminal_eq)
            w_T = torch.where(
                self.terminal_eq, rho[:, 0], rho[:, 0] * (self.lam_T + rho[:, 0] * v.terminal > 0)
            )
            wcx = w.unsqueeze(-1) * v.cx  # (B, T, p, n)
            wcu = w.unsqueeze(-1) * v.cu
            lx = e.lx.expand(Bsz, T + 1, n).clone()
            lx[:, :T] += (v.cx * lam_hat.unsqueeze(-1)).sum(-2)
            lx[:, T] += (v.cxT * lam_hat_T.unsqueeze(-1)).sum(-2)
            lu = e.lu.expand(Bsz, T, m) + (v.cu * lam_hat.unsqueeze(-1)).sum(-2)
            lxx = e.lxx.expand(Bsz, T + 1, n, n).clone()
            lxx[:, :T] += v.cx.mT @ wcx
            lxx[:, T] += v.cxT.mT @ (w_T.unsqueeze(-1) * v.cxT)
            luu = e.luu.expand(Bsz, T, m, m) + v.cu.mT @ wcu
            lux = v.cu.mT @ wcx
            if e.lux is not None:
                lux = lux + e.lux
            if self.curvature:
                # the rows' own curvature weighted by λ̂ (the cost machinery's Hessians)
                lam_s, lam_t = lam_hat, lam_hat_T
                cset = self.constraints
                curv = Cost(
                    stage=lambda a, b, t: (lam_s * cset.stage_values(a, b)).sum(-1),
                    terminal=lambda a: (lam_t * cset.terminal_values(a)).sum(-1),
                    state_dim=n,
                    control_dim=m,
                ).quadratize(x.detach(), u.detach())
                lxx = lxx + curv.lxx
                luu = luu + curv.luu
                lux = lux + curv.lux
        return CostExpansion(lxx=lxx, luu=luu, lux=lux, lx=lx, lu=lu)
