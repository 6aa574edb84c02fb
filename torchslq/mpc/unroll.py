"""Backpropagation through the iterations of a Newton-type solve ("unroll" gradients).

For comparison with the implicit gradients only: memory grows with the iterations and
the gradient is that of the iterate, which equals the implicit one only at
convergence. Each iteration is a full LQ step ``u <- u + α du`` where ``du`` solves the
LQ subproblem of :func:`torchslq.mpc.implicit.lagrangian_hessian` on the shared kernel
(:func:`torchslq.lqr_solve`, differentiable), the linear terms carry the graph to the
parameters, and the step size ``α`` (per element, chosen by an Armijo test on the
actual cost, several trial steps at once) is treated as a constant. Every element takes
at least one step, so the result always depends on the parameters.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..dynamics.linearize import linearize
from ..dynamics.rollout import costate_gradient, rollout
from ..lq.solve import lqr_solve
from .implicit import cost_gradients, lagrangian_hessian

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["unrolled_solve"]


def unrolled_solve(
    problem: Problem,
    x0: Tensor,
    u: Tensor,
    *,
    max_iter: int,
    tol: float,
    hessian: str = "exact",
    u_min: Tensor | None = None,
    u_max: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Differentiable Newton (``hessian="exact"``) / Gauss-Newton iterations from ``u``.

    Args:
        problem: the problem; x0 ``(B, n)``; u ``(B, T, m)`` the initial guess.
        max_iter: most iterations; tol: stop an element when ``||∇_U J|| < tol``.
        u_min, u_max: ``(B, T, m)`` bounds; the iterate is clamped into the box.

    Returns:
        ``(x, u, iterations)`` with the graph through every iteration.
    """
    T = problem.horizon
    f = problem.transition
    Bsz = x0.shape[0]
    alphas = 0.5 ** torch.arange(12, dtype=x0.dtype, device=x0.device)
    iters = torch.zeros(Bsz, dtype=torch.int64, device=x0.device)
    done = torch.zeros(Bsz, dtype=torch.bool, device=x0.device)

    def clamp(v: Tensor) -> Tensor:
        if u_min is not None:
            v = torch.maximum(v, u_min)
        if u_max is not None:
            v = torch.minimum(v, u_max)
        return v

    u = clamp(u)
    for it in range(max_iter):
        x = rollout(f, x0, u)
        A, Bm = linearize(problem.dynamics, x[:, :T], u, create_graph=True)
        Q, R, S, lxd, lud = lagrangian_hessian(problem, x, u, hessian, A, Bm)
        grad, _ = costate_gradient(A.detach(), Bm.detach(), lxd, lud)
        if it > 0:
            done = done | (grad.flatten(1).norm(dim=1) < tol)
            if bool(done.all()):
                break
        lx, lu = cost_gradients(problem.cost, x, u)
        sol = lqr_solve(A, Bm, Q, R, torch.zeros_like(x0), lx, lu, S, validate=False)
        du = sol.u
        with torch.no_grad():  # Armijo step per element, all trial steps at once
            J0 = problem.total_cost(x0.detach(), u.detach())
            trial_u = clamp(u.detach() + alphas.view(-1, 1, 1, 1) * du.detach())
            J = problem.total_cost(x0.detach().expand(len(alphas), *x0.shape), trial_u)
            slope = (grad * du.detach()).flatten(1).sum(1)
            ok = J <= J0 + 1e-4 * alphas.view(-1, 1) * slope.clamp_max(0.0)
            first = torch.where(ok.any(0), ok.to(torch.int64).argmax(0), len(alphas) - 1)
            alpha = torch.where(done, torch.zeros_like(J0), alphas[first])
        iters = iters + (~done).to(torch.int64)
        u = clamp(u + alpha.view(-1, 1, 1) * du)
    x = rollout(f, x0, u)
    return x, u, iters
