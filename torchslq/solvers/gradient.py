"""Open-loop costate-gradient (steepest descent) method, the baseline of Sideris & Bobrow's
Figure 2 and the "gradient method" of GoPRONTO (eqs. 5-7).

Every iteration computes the gradient ``∇_U J`` of the reduced cost ``J(U) = J(x(U), U)``
by the costate recursion (Sideris & Bobrow eqs. 8-11) and steps along ``-∇_U J``. It
reuses the whole solve loop of :class:`torchslq.SLQ` (batching, per-element masks and
status, stopping tests, history, logging); only the direction and the range of the
line search differ.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from ..dynamics.linearize import linearize
from ..lq.riccati import rollout_linear
from .result import SolverResult
from .rollout import costate_gradient
from .slq import SLQ

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["GradientMethod"]

_SEARCH_RANGES = ("adaptive", "unit")


class GradientMethod(SLQ):
    """Steepest descent on ``J(U)`` with the costate gradient: ``U <- U - α ∇_U J``.

    Args:
        max_iter, tol, line_search, stop, rollout, armijo_*, linearize_method, progress:
            as for :class:`torchslq.SLQ` (same defaults). ``line_search="exact"`` gives
            the "steepest descent with exact line search" of Sideris & Bobrow (2005),
            Figure 2.
        search_range: ``"adaptive"`` (default): the gradient has an arbitrary scale, so
            the line search runs over ``α ∈ (0, α_max]`` with a per-element
            ``α_max = max(2 α_GN, growth · α_prev)``, where ``α_GN = ||g||² / (g' H g)``
            minimises the Gauss-Newton model of ``J`` along ``-g`` (``H`` built from the
            linear response ``dx`` of the direction) and ``α_prev`` is the element's
            previously accepted step. ``"unit"``: search ``(0, 1]`` like SLQ.
        growth: factor on the previous step in ``α_max`` (default 4).

    :meth:`direction` returns ``du = -grad``, its linear state response ``dx`` (from
    ``x̄(0) = 0``), ``K = 0``, ``k = du`` (so the closed-loop rollout is the same as the
    open-loop one), ``slope = -||grad||²`` and ``curvature = g' H g`` (Gauss-Newton).
    """

    name = "gradient"

    def __init__(
        self,
        max_iter: int = 100,
        tol: float = 1e-6,
        line_search: str = "exact",
        search_range: str = "adaptive",
        growth: float = 4.0,
        **kwargs: Any,
    ):
        super().__init__(max_iter=max_iter, tol=tol, line_search=line_search, **kwargs)
        if search_range not in _SEARCH_RANGES:
            raise ValueError(f"search_range must be one of {_SEARCH_RANGES}, got {search_range!r}")
        if not growth >= 1:
            raise ValueError(f"growth must be >= 1, got {growth!r}")
        if self.options.compact:
            raise ValueError("compact=True is not supported by GradientMethod")
        self.search_range = search_range
        self.growth = float(growth)
        self._prev_alpha: Tensor | None = None

    # ------------------------------------------------------------------ direction
    def direction(self, problem: Problem, x: Tensor, u: Tensor) -> dict[str, Tensor]:
        """Negative costate gradient at ``(x, u)`` (same keys as :meth:`SLQ.direction`,
        plus ``curvature (B,)``)."""
        A, B = linearize(
            problem.transition, x[:, : problem.horizon], u, method=self.options.linearize_method
        )
        e = problem.cost.quadratize(x, u)
        grad, _ = costate_gradient(A, B, e.lx, e.lu)
        du = -grad
        K = du.new_zeros(*du.shape, x.shape[-1])
        dx, _ = rollout_linear(A, B, K, du, torch.zeros_like(x[:, 0]))
        curv = torch.einsum("...ti,...tij,...tj->...", dx, e.lxx, dx)
        curv = curv + torch.einsum("...ti,...tij,...tj->...", du, e.luu, du)
        if e.lux is not None:
            curv = curv + 2.0 * torch.einsum("...ti,...tij,...tj->...", du, e.lux, dx[:, :-1])
        return {
            "dx": dx,
            "du": du,
            "K": K,
            "k": du,
            "grad": grad,
            "slope": -(grad * grad).sum(dim=(-1, -2)),
            "curvature": curv,
            "failed": torch.zeros(du.shape[0], dtype=torch.bool, device=du.device),
        }

    # ------------------------------------------------------------------ solve
    def solve(
        self,
        problem: Problem,
        x0: Tensor,
        u_init: Tensor | None = None,
        logger: Any = None,
    ) -> SolverResult:
        """As :meth:`SLQ.solve`."""
        self._prev_alpha = None
        try:
            return super().solve(problem, x0, u_init=u_init, logger=logger)
        finally:
            self._prev_alpha = None

    def search_scale(self, d: dict[str, Tensor]) -> Tensor:
        """Per-element ``α_max (B,)`` of the line search for direction ``d``."""
        slope = d["slope"]
        if self.search_range == "unit":
            return torch.ones_like(slope)
        g2 = -slope
        a_gn = g2 / d["curvature"]
        fallback = 1.0 / g2.sqrt()  # a step of unit length in U
        good = torch.isfinite(a_gn) & (a_gn > 0)
        scale = torch.where(good, 2.0 * a_gn, fallback)
        if self._prev_alpha is not None:
            scale = torch.maximum(scale, self.growth * self._prev_alpha)
        return torch.where(torch.isfinite(scale) & (scale > 0), scale, torch.ones_like(scale))

    def _line_search(self, f, cost_fn, x0, x, u, J, d) -> tuple[Tensor, ...]:
        # SLQ's search over (0, 1] along the direction scaled by alpha_max; the step is
        # returned in units of the unscaled direction (everything else SLQ's search
        # returns, e.g. the chosen trial trajectories, is passed through unchanged).
        s = self.search_scale(d)
        scaled = dict(d)
        scaled["du"] = s[:, None, None] * d["du"]
        scaled["k"] = s[:, None, None] * d["k"]
        scaled["slope"] = s * d["slope"]
        alpha, J_new, ok, *rest = super()._line_search(f, cost_fn, x0, x, u, J, scaled)
        alpha = alpha * s
        prev = self._prev_alpha
        self._prev_alpha = alpha if prev is None else torch.where(ok, alpha, prev)
        return (alpha, J_new, ok, *rest)
