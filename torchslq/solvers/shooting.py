"""Multiple shooting for iLQR: every time step is a shooting node.

Giftthaler, Neunert, Stäuble, Buchli & Diehl (2018), "A family of iterative Gauss-Newton
shooting methods for nonlinear optimal control" (GNMS), on the library's Riccati pass.
The iterate is a pair ``(X, U)`` of node states and controls that need not satisfy the
dynamics; its *defects* (gaps) are

    d_t = f(x_t, u_t) - x_{t+1},   t = 0 .. T-1,      x_0 = x0 fixed.

One iteration:

1. **Linearise at every node at once** (one batched call of the model's Jacobians over
   ``B T`` rows) and evaluate the defects (one batched model call).
2. **LQ step with the defects as affine terms**: ``min`` the cost's second-order model
   (its stage Hessians made positive semidefinite) in ``(δx, δu)`` s.t.
   ``δx_{t+1} = A_t δx_t + B_t δu_t + d_t``, ``δx_0 = 0``: :func:`riccati_backward` with
   ``c = d`` and the Levenberg-Marquardt term of iLQR, then the linear rollout of
   ``δu_t = K_t δx_t + k_t``. A full step closes the linearised defects.
3. **Lifted update with a merit line search**: ``(X, U) + α (δX, δU)`` (no nonlinear
   rollout: each trial is one batched model call over all nodes), accepted by Armijo on
   the exact-penalty merit ``φ = J(X, U) + ρ Σ_t |d_t|_1`` with the expected decrease
   ``α ∇J·δz + α²/2 δz'∇²J δz - α ρ Σ|d|_1`` (Nocedal & Wright 2006, Section 18.3).
   The penalty ``ρ`` never decreases and is kept above ``1.1 max|λ|``, the largest
   multiplier of the subproblem's dynamics (``λ_{t+1} = V_{t+1} δx_{t+1} + v_{t+1}``),
   so the step is a descent direction of ``φ`` (Nocedal & Wright, Theorem 18.2).

Why: a single-shooting iteration rolls the model out step by step (``T`` dependent
calls per trial); here every model evaluation is one call over all ``B T`` nodes, which
is what a learned network or any model on the torch path needs to run fast, and
unstable systems need fewer iterations because the defects decouple the horizon.

An element is converged when its gradient test passes *and* its largest defect is at
most ``defect_tol``; the returned trajectory is then the rollout of the returned
controls (the nodes differ from it by the remaining defects, propagated).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..dynamics.rollout import costate_gradient, rollout
from ..dynamics.row_blocks import call_in_blocks
from ..lq.riccati import rollout_linear
from .descent import DescentState, LineSearch, nonfinite_rows
from .line_search import TrialRecorder
from .newton import RegularizedNewton, _floored, _pass

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["MeritLineSearch", "MultipleShootingNewton", "node_defects"]

#: the penalty is kept at least this factor above the largest subproblem multiplier
PENALTY_MARGIN = 1.1


def node_defects(f, x: Tensor, u: Tensor) -> Tensor:
    """``d_t = f(x_t, u_t) - x_{t+1}`` ``(..., T, n)`` for nodes ``x (..., T+1, n)`` and
    controls ``u (..., T, m)``: one model call over all nodes (a learned model's in
    blocks of rows that stay in cache, :func:`~torchslq.dynamics.row_blocks.call_in_blocks`)."""
    T = u.shape[-2]
    return call_in_blocks(f, x[..., :T, :], u) - x[..., 1:, :]


def _quadratic_form(e, dx: Tensor, du: Tensor) -> Tensor:
    """``δz' ∇²J δz`` ``(b,)`` of the cost expansion ``e`` along ``(dx, du)``."""
    T = du.shape[-2]
    # broadcast products, not einsum: its path search costs more than the sums here
    out = ((e.lxx @ dx.unsqueeze(-1)).squeeze(-1) * dx).sum(dim=(-1, -2))
    hu = (e.luu @ du.unsqueeze(-1)).squeeze(-1)
    if e.lux is not None:
        hu = hu + 2.0 * (e.lux @ dx[:, :T].unsqueeze(-1)).squeeze(-1)
    return out + (hu * du).sum(dim=(-1, -2))


def _linear_form(e, dx: Tensor, du: Tensor) -> Tensor:
    """``∇J·δz`` ``(b,)``."""
    return (e.lx * dx).sum(dim=(-1, -2)) + (e.lu * du).sum(dim=(-1, -2))


@dataclass(frozen=True)
class MultipleShootingNewton(RegularizedNewton):
    """iLQR's regularised Newton step (:class:`RegularizedNewton`, without the dynamics'
    curvature) at shooting nodes with defects (module docstring, steps 1-2). Same
    options; ``defect_tol`` is the largest defect a converged element may have. The
    direction adds ``dx`` (the subproblem's state step), ``violation (b,)``
    (``Σ|d|_1``), ``penalty (b,)`` and ``feasible (b,)`` (``max|d| <= defect_tol``) to
    the keys of a direction; ``slope``/``curvature`` are the cost model's along
    ``(δx, δu)``.
    ``verify_tol``: the gradient tolerance of the stopping test (None: no check): an
    element that passes it with its defects within ``defect_tol`` has its nodes replaced
    by the rollout of its controls and is measured there (it goes on from there if the
    rollout's gradient does not pass)."""

    defect_tol: float = 1e-6
    verify_tol: float | None = None

    def _expansion(self, problem: Problem, x: Tensor, u: Tensor):
        """The cost expansion with every stage Hessian projected onto the PSD cone
        (eigenvalues clipped at ``hessian_floor``, or at 0 when it is None): the merit
        line search needs a convex subproblem (along a direction of negative curvature
        of an indefinite one the lifted step is not a descent direction of the merit,
        where single shooting's feedback rollout still makes progress)."""
        e = problem.cost.quadratize(x, u)
        return _floored(problem, e, 0.0 if self.hessian_floor is None else self.hessian_floor)

    def _at_nodes(self, problem: Problem, x: Tensor, u: Tensor):
        """``(A, B, e, grad)`` at the nodes: Jacobians, the convex cost expansion and the
        gradient of ``J(U)`` along the nodes (the rollout's when the defects are 0)."""
        A, B, _ = self._linearize(problem, x[:, : problem.horizon], u)
        e = self._expansion(problem, x, u)
        grad, _ = costate_gradient(A, B, e.lx, e.lu)
        return A, B, e, grad

    def __call__(self, problem: Problem, state: DescentState, running: Tensor, it: int):
        x, u = state.x, state.u
        n = problem.state_dim
        gaps = state.defects  # kept from the line search's trial at the accepted step
        # (an element measured again on its rollout below was feasible: it stays so)
        feasible = gaps.abs().flatten(1).amax(1) <= self.defect_tol
        A, B, e, grad = self._at_nodes(problem, x, u)
        if self.verify_tol is not None:
            # an element that passes the tests at its nodes is measured again on the
            # rollout of its controls (what the result returns): tiny defects, amplified
            # along an unstable horizon, can still move the gradient by a few percent
            near = running & feasible & (grad.flatten(1).norm(dim=1) < self.verify_tol)
            if bool(near.any()):
                idx = near.nonzero().squeeze(1)
                b = x.shape[0]
                sub = problem.take(idx, b)
                xr = rollout(sub.transition, x[idx, 0], u[idx])
                x = x.index_copy(0, idx, xr)
                gaps = gaps.index_fill(0, idx, 0.0)
                state = replace(state, x=x, defects=gaps, J=problem.cost(x, u))
                if idx.numel() == b:
                    A, B, e, grad = self._at_nodes(problem, x, u)
                else:  # only those elements are linearised again
                    A_r, B_r, e_r, grad_r = self._at_nodes(sub, xr, u[idx])
                    A, B, grad = (
                        t.index_copy(0, idx, t_r)
                        for t, t_r in zip((A, B, grad), (A_r, B_r, grad_r), strict=True)
                    )
                    e = _merged_expansion(e, e_r, idx, b)
        restarts = self.schedule.restarts(state.delta, running)
        fac, bad = _pass(A, B, e, None, None, state.mu, restarts=restarts, c=gaps)
        mu, delta = fac.reg, fac.reg_delta
        failed = bad | (mu > self.schedule.reg_max)
        nonfinite = nonfinite_rows(A, B, e.lx, e.lu, gaps) if bool(failed.any()) else None
        dx, du = rollout_linear(A, B, fac.K, fac.k, torch.zeros_like(x[:, 0]), c=gaps)
        V, v = fac.Vh[:, 1:, :n, :n], fac.Vh[:, 1:, :n, n]
        multipliers = (V @ dx[:, 1:].unsqueeze(-1)).squeeze(-1) + v  # λ_{t+1}, (b, T, n)
        lam_max = multipliers.abs().flatten(1).amax(1)
        penalty = torch.maximum(state.penalty, PENALTY_MARGIN * lam_max)
        penalty = torch.where(torch.isfinite(penalty), penalty, state.penalty)
        slope = _linear_form(e, dx, du)
        curv = _quadratic_form(e, dx, du)
        d = {
            "du": du,
            "dx": dx,
            "K": fac.K,
            "k": fac.k,
            "grad": grad,
            "slope": slope,
            "curvature": curv,
            "failed": failed,
            "violation": gaps.abs().flatten(1).sum(1),
            "penalty": penalty,
            "feasible": feasible,
        }
        if nonfinite is not None:
            d["nonfinite"] = nonfinite
        return d, replace(state, mu=mu, delta=delta, penalty=penalty)


def _merged_expansion(e, e_rows, idx: Tensor, b: int):
    """The cost expansion ``e`` of ``b`` elements with the elements ``idx`` replaced by
    ``e_rows`` (their expansion); a term shared by the batch (leading dim 1) stays."""
    for name in ("lxx", "luu", "lux", "lx", "lu"):
        t = getattr(e, name)
        if t is not None and t.shape[0] == b:
            rows = getattr(e_rows, name).expand(idx.numel(), *t.shape[1:])
            setattr(e, name, t.index_copy(0, idx, rows))
    return e


def _on_rows(problem: Problem, live: Tensor, xc: Tensor, uc: Tensor) -> tuple[Tensor, Tensor]:
    """Cost ``(Na, b)`` and defects ``(Na, b, T, n)`` of the trials ``xc (Na, b, T+1, n)``,
    ``uc (Na, b, T, m)`` where ``live (Na, b)``, NaN elsewhere: the live rows only go
    through the model and the cost, with the problem's per-element data taken for them."""
    Na, b = live.shape
    T, n = uc.shape[-2], xc.shape[-1]
    rows = live.reshape(-1).nonzero().squeeze(1)
    J = xc.new_full((Na * b,), float("nan"))
    gaps = xc.new_full((Na * b, T, n), float("nan"))
    if rows.numel() > 0:
        sub = problem.take(rows % b, b)
        xr = xc.reshape(Na * b, *xc.shape[2:]).index_select(0, rows)
        ur = uc.reshape(Na * b, *uc.shape[2:]).index_select(0, rows)
        J = J.index_copy(0, rows, sub.cost(xr, ur))
        gaps = gaps.index_copy(0, rows, node_defects(sub.transition, xr, ur))
    return J.reshape(Na, b), gaps.reshape(Na, b, T, n)


@dataclass(frozen=True)
class MeritLineSearch(LineSearch):
    """Armijo on the exact-penalty merit of multiple shooting (module docstring, step 3):
    the lifted trials ``(X, U) + α (δX, δU)``, each one batched model call over all
    nodes. Same constants as :class:`~torchslq.solvers.descent.LineSearch`; returns the
    accepted steps, the *costs* ``J`` of the new iterates (the merit only decides), the
    success flags, the new nodes and controls, and ``{"defects": ...}`` of the new
    nodes (the state keeps them for the next direction: no model call to recompute)."""

    kind: str = "armijo"
    quadratic_model: bool = True

    def __call__(
        self, problem: Problem, state: DescentState, d: dict[str, Tensor], running: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        f, cost_fn = problem.transition, problem.cost
        x, u = state.x, state.u
        dx, du = d["dx"], d["du"]
        rho = d["penalty"]
        phi0 = state.J + rho * d["violation"]
        trials = TrialRecorder()

        def evaluate(alphas: Tensor) -> Tensor:  # (Na, b) -> merit (Na, b)
            a = alphas[..., None, None]
            xc, uc = x + a * dx, u + a * du
            live = torch.isfinite(alphas)
            if bool(live.all()):
                J, gaps = cost_fn(xc, uc), node_defects(f, xc, uc)
            else:
                # a later pass: only the elements still searching are evaluated (the
                # NaN steps of settled ones would cost a full batch of model calls)
                J, gaps = _on_rows(problem, live, xc, uc)
            trials.record(alphas, xc, uc, J, gaps)
            return J + rho * gaps.abs().flatten(2).sum(2)

        slope = d["slope"] - rho * d["violation"]
        alpha, _, ok = self.armijo(evaluate, phi0, slope, d["curvature"], running, state.prev_step)
        x_new, u_new, J_new, gaps = trials.select(alpha)
        return alpha, torch.where(ok, J_new, state.J), ok, x_new, u_new, {"defects": gaps}
