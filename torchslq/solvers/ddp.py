"""DDP: iLQR plus the second-order dynamics terms in the backward pass.

``Q_xx = l_xx + f_x' V'_xx f_x + V'_x · f_xx`` (likewise ``Q_uu``, ``Q_ux``): the last
term is a vector-Hessian product of the dynamics computed with ``torch.func``
(:func:`torchslq.dynamics.dynamics_vhp`, never the full ``n x n x n`` tensor). Two
choices of the vector ``V'_x``:

* ``second_order="value"`` (classic DDP, Mayne 1966 / Tassa et al. 2012): the gradient
  ``v_{t+1}`` of the local value-function model, produced during the backward pass
  itself, so the product is taken step by step inside the Riccati loop (through the
  kernel's ``stage_hook``);
* ``second_order="costate"``: the costates ``lam_{t+1}`` of the nominal trajectory
  (eq. 8 of Sideris & Bobrow), known before the backward pass, so all steps are done in
  one batched call. This is Newton's method on ``J(U)``; both variants coincide at a
  stationary point (``v = lam`` there) and converge quadratically nearby.

The direction is :class:`~torchslq.solvers.newton.RegularizedNewton` with
``second_order`` set; regularisation, line search and loop are iLQR's.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar

from torch import Tensor

from .base import Solver
from .ilqr import ILQR
from .options import DDPOptions

if TYPE_CHECKING:  # pragma: no cover
    from ..constraints import Constraints

__all__ = ["DDP"]


class DDP(ILQR):
    """Differential dynamic programming (iLQR + dynamics second derivatives).

    Args:
        second_order: ``"value"`` (default, classic DDP) or ``"costate"`` (batched over
            time; see the module docstring).
        vhp_memory_limit: for ``"value"``: when the ``n`` per-output Hessians of all
            steps (``B T n (n+m)^2`` numbers) fit in this many bytes, they are computed
            in one batched call per iteration and contracted with ``v_{t+1}`` in the
            Riccati loop; otherwise (or with None) one vector-Hessian product is taken per
            step inside the loop. Same result, the first is much faster for small ``n``.
        the others: as for :class:`torchslq.ILQR`.
    """

    name: ClassVar[str] = "ddp"
    options_class: ClassVar[type] = DDPOptions

    def __init__(
        self,
        max_iter: int = 100,
        tol: float = 1e-6,
        mu_init: float = 0.0,
        mu_min: float = 1e-6,
        mu_max: float = 1e10,
        mu_factor: float = 2.0,
        hessian_floor: float | None = None,
        u_min: float | Tensor | None = None,
        u_max: float | Tensor | None = None,
        *,
        constraints: Constraints | Sequence[Constraints] | None = None,
        constraint_tol: float | None = None,
        penalty_init: float = 1.0,
        penalty_factor: float = 100.0,
        penalty_max: float = 1e10,
        al_max_iter: int = 30,
        polish: bool = False,
        penalty_update: str = "progress",
        constraint_hessian: str = "exact",
        second_order: str = "value",
        vhp_memory_limit: int | None = 256 * 2**20,
        shooting: str = "single",
        defect_tol: float | None = None,
        rtol: float = 0.0,
        stop: str = "grad",
        step_tol: float | None = None,
        stall_iters: int = 10,
        armijo_c1: float = 1e-4,
        armijo_beta: float = 0.5,
        max_backtracks: int = 20,
        armijo_passes: tuple[int, int | None] | None = None,
        linearize_method: str = "auto",
        progress: bool = True,
        compact: bool = False,
        line_search: str = "armijo",
        rollout: str = "closed_loop",
        **unknown: Any,
    ):
        Solver.__init__(
            self, **{k: v for k, v in locals().items() if k not in ("self", "__class__")}
        )

    def rule(self):
        o = self.options
        newton = self._newton(second_order=o.second_order, vhp_memory_limit=o.vhp_memory_limit)
        return self._descent_rule(newton)
