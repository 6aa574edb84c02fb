"""Open-loop costate-gradient (steepest descent) method, the baseline of Sideris & Bobrow's
Figure 2 and the "gradient method" of GoPRONTO (eqs. 5-7).

Every iteration computes the gradient ``∇_U J`` of the reduced cost ``J(U) = J(x(U), U)``
by the costate recursion (Sideris & Bobrow eqs. 8-11) and steps along ``-∇_U J``: the
direction :class:`~torchslq.solvers.descent.CostateGradient` with SLQ's line searches on
the shared loop.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, ClassVar

from .base import DescentSolver
from .descent import CostateGradient, descent_rule
from .options import GradientOptions

__all__ = ["GradientMethod"]


class GradientMethod(DescentSolver):
    """Steepest descent on ``J(U)`` with the costate gradient: ``U <- U - α ∇_U J``.

    Args:
        max_iter, tol, line_search, stop, step_tol, rtol, stall_iters, rollout, armijo_*,
            max_backtracks, linearize_method, progress, compact: as for
            :class:`torchslq.SLQ` (same defaults). ``line_search="exact"`` gives the
            "steepest descent with exact line search" of Sideris & Bobrow (2005), Figure 2.
        search_range: ``"adaptive"`` (default): the line search runs over
            ``α ∈ (0, α_max]`` with a per-element ``α_max = max(2 α_GN, growth · α_prev)``,
            where ``α_GN = ||g||² / (g' H g)`` minimises the Gauss-Newton model of ``J``
            along ``-g`` and ``α_prev`` is the element's previously accepted step.
            ``"unit"``: search ``(0, 1]`` like SLQ.
        growth: factor on the previous step in ``α_max`` (default 4, ``>= 1``).

    :meth:`direction` returns ``du = -grad``, its linear state response ``dx`` (from
    ``x̄(0) = 0``), ``K = 0``, ``k = du``, ``slope = -||grad||²`` and ``curvature = g' H g``.
    """

    name: ClassVar[str] = "gradient"
    options_class: ClassVar[type] = GradientOptions

    def __init__(
        self,
        max_iter: int = 100,
        tol: float = 1e-6,
        line_search: str = "exact",
        search_range: str = "adaptive",
        growth: float = 4.0,
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
        return descent_rule(CostateGradient(o.linearize_method, o.search_range, o.growth), o)

    def initial_state(self, problem, x0, u, x, **extra):
        state = super().initial_state(problem, x0, u, x, **extra)
        return replace(state, prev_step=state.J.new_zeros(state.J.shape))

    def search_scale(self, d, prev_step=None):
        """Per-element ``α_max (B,)`` of the line search for direction ``d``."""
        return self.rule().direction.search_scale(d, prev_step)
