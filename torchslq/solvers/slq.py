"""SLQ: the Sequential Linear Quadratic algorithm of Sideris & Bobrow (2005), batched.

Algorithm 2 of the paper, for every batch element independently:

1. roll out ``x`` under the current controls ``U`` (Step 1);
2. linearise the dynamics along ``(x, u)`` (Step 2, ``A = f_x``, ``B = f_u``) and solve the
   LQ tracking problem with ``x̄(0) = 0`` and targets ``x̄° = x° - x``, ``ū° = u° - u``
   (eq. 29-30) by the shared Riccati kernel (Algorithm 1). For the quadratic cost this
   is exactly the LQ problem with linear terms ``q = Q (x - x°)`` and ``r = R (u - u°)``,
   i.e. the cost's gradient; the cost is *not* linearised (Gauss-Newton, Section 3.3);
3. stop when ``||Ū|| < tol ||U||`` and/or ``||∇_U J|| < tol`` (configurable);
4. otherwise step ``U + α Ū`` (eq. 28) with ``α`` from a line search over ``(0, 1]``:
   "exact" (Theorem 2) or "armijo" with the directional derivative of eq. (34).

It is the direction :class:`~torchslq.solvers.descent.GaussNewtonLQ` with a
:class:`~torchslq.solvers.descent.LineSearch` on the shared loop
(:func:`~torchslq.solvers.core.iterate`).
"""

from __future__ import annotations

from typing import Any, ClassVar

from .base import DescentSolver
from .descent import GaussNewtonLQ, descent_rule
from .options import SLQOptions

__all__ = ["SLQ", "SLQOptions"]


class SLQ(DescentSolver):
    """Sequential Linear Quadratic solver (Sideris & Bobrow 2005, Algorithm 2).

    Args:
        max_iter: iterations per element (default 100).
        tol: tolerance of the stopping rule (default 1e-6).
        line_search: ``"exact"`` (minimise ``J(U + αŪ)`` over ``α ∈ (0, 1]``: a grid of
            steps evaluated as one batched rollout, refined by a quadratic fit) or
            ``"armijo"`` (backtracking from 1 on ``J(U+αŪ) <= J(U) + c1 α D`` with
            ``D = ∇J·Ū = -(Σ x̄'Qx̄ + ū'Rū)``, eq. 34).
        stop: ``"grad"``: ``||∇_U J|| < tol`` (the test of the paper's Section 4);
            ``"step"``: ``||Ū|| < step_tol ||U||`` (Algorithm 2, Step 2); ``"either"`` /
            ``"both"`` combine the two.
        step_tol: tolerance of the step rule (defaults to ``tol``).
        rtol: also stop (as converged) after an accepted step that changes the cost by
            at most ``rtol |J|``; 0 (default) disables this test.
        stall_iters: stop an element with status ``stalled`` (not converged) when this
            many consecutive accepted steps changed its cost by no more than rounding
            noise (``64 eps max(|J|, 1)``, eps of the dtype) and did not halve its
            gradient norm, while the stopping test was still unmet (typically float32
            with a tolerance below what float32 gradients can resolve). Default 10; 0
            disables.
        rollout: ``"open_loop"`` (the paper's ``U + αŪ``) or ``"closed_loop"`` (the line
            search applies the LQ feedback: ``u = u + α k + K (x_new - x)``).
        armijo_c1, armijo_beta, max_backtracks: Armijo constants (``0 < c1 < 1``,
            ``0 < beta < 1``, ``max_backtracks >= 1`` trial steps ``beta^j``).
        armijo_passes: ``(first, then)``: the Armijo trials are rolled out ``first`` at a
            time, then ``then`` at a time (None: all the rest at once) while some element
            has accepted none; the accepted steps are the same for any choice. Default
            (None): ``(1, 3)`` on the CPU (``(2, 2)`` for ILQR/DDP while most elements'
            last steps were shorter than 1), ``(4, None)`` on other devices.
        linearize_method: passed to :func:`torchslq.linearize`.
        progress: show a tqdm bar when a solve takes longer than a second.
        compact: compute each iteration only on the elements still running; per-element
            problem data (a goal per element, a ``(B, 1)`` mass) are indexed with the
            running subset (:meth:`torchslq.Problem.take`, rules in
            :mod:`torchslq.per_element`). Same results; off by default.
    """

    name: ClassVar[str] = "slq"
    options_class: ClassVar[type] = SLQOptions

    def __init__(
        self,
        max_iter: int = 100,
        tol: float = 1e-6,
        line_search: str = "exact",
        *,
        stop: str = "grad",
        step_tol: float | None = None,
        rtol: float = 0.0,
        stall_iters: int = 10,
        rollout: str = "open_loop",
        armijo_c1: float = 1e-4,
        armijo_beta: float = 0.5,
        max_backtracks: int = 20,
        armijo_passes: tuple[int, int | None] | None = None,
        linearize_method: str = "auto",
        progress: bool = True,
        compact: bool = False,
        **unknown: Any,
    ):
        super().__init__(**{k: v for k, v in locals().items() if k not in ("self", "__class__")})

    def rule(self):
        o = self.options
        return descent_rule(GaussNewtonLQ(o.linearize_method), o)
