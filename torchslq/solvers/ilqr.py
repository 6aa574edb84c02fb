"""iLQR on the shared loop: :class:`~torchslq.solvers.newton.RegularizedNewton` (the
regularised Newton step of the second-order cost expansion, control bounds by the box QP)
with the feedback rollout and Armijo on the expected improvement (eqs. 14-15 of
Lieskovský et al. 2025, discrete form). See :mod:`torchslq.solvers.newton`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from ..dynamics.rollout import rollout
from ..lq.regularization import RegularizationSchedule
from .base import DescentSolver
from .descent import descent_rule
from .newton import RegularizedNewton, active_bounds, bounds_with_faults, resolve_bounds
from .options import ILQROptions
from .shooting import MeritLineSearch, MultipleShootingNewton, node_defects

if TYPE_CHECKING:  # pragma: no cover
    from ..constraints import Constraints
    from ..problem import Problem
    from .result import SolverResult

__all__ = ["ILQR", "active_bounds", "resolve_bounds"]


class ILQR(DescentSolver):
    """Iterative LQR for general costs (any cost with ``quadratize``).

    Args:
        max_iter, tol: iteration limit and gradient-norm tolerance.
        mu_init, mu_min, mu_max, mu_factor: Levenberg-Marquardt regularisation on ``Quu``
            (Tassa et al. 2012 schedule, per element). An element whose ``mu`` would have
            to exceed ``mu_max`` stops: with status ``not_positive_definite`` when
            ``Quu + mu I`` cannot be factorised, ``line_search_failed`` when its line
            searches keep failing.
        hessian_floor: when set, the eigenvalues of every stage cost Hessian (the joint
            ``(n+m)`` block) and of the terminal Hessian are clipped to at least this
            value (the paper uses ``sqrt(eps)``); None leaves them as they are.
        u_min, u_max: optional control bounds, a float or a tensor of shape ``(m,)``,
            ``(T, m)`` or ``(B, T, m)`` (``-inf``/``+inf`` entries allowed; None: no
            bound on that side). ``u_init`` is clamped into the box. When every bound is
            infinite the solve is exactly the unconstrained one.
        constraints: optional :class:`torchslq.Constraints` (or a list): path, terminal
            and state constraints, inequality or equality. The solve is then an
            augmented-Lagrangian outer loop over this solver
            (:mod:`torchslq.solvers.augmented_lagrangian`) with per-element multipliers
            and penalties; ``max_iter``/``tol`` apply to each inner solve, and the
            result has ``multipliers``, ``max_violation`` and ``outer_iterations``
            (``iterations``: the inner iterations of all subproblems). An element that
            cannot reach ``constraint_tol`` ends ``infeasible``; the others go on.
        constraint_tol: the largest violation accepted (None: 1e-6 in float64, 1e-4
            otherwise).
        penalty_init, penalty_factor, penalty_max: the penalty ``ρ`` at the start, its
            growth factor and its limit.
        penalty_update: ``"progress"`` (raise ``ρ`` where the violation did not shrink
            fourfold; Conn, Gould & Toint) or ``"always"`` (wherever still infeasible;
            ALTRO's and trajax's schedule).
        al_max_iter: the limit on multiplier updates (outer iterations).
        polish: finish with Newton steps on the KKT conditions of the active set
            (:mod:`torchslq.constraints.polish`): quadratic instead of linear convergence
            at the end, and KKT conditions met to round-off; the loop then hands over at
            a violation of ``1e-4`` and resumes for an element the steps do not finish.
            One dense LDL' factorisation per element and step (``(T (2n + m + p))^3``).
        constraint_hessian: the constraint terms' Hessian in the subproblems:
            ``"gauss_newton"`` (``ρ c_z' c_z`` on the active rows, positive semidefinite;
            iLQR's default, in the spirit of dropping the dynamics' curvature) or
            ``"exact"`` (plus the rows' curvature weighted by their multipliers; DDP's
            default: with the dynamics' curvature it makes the subproblem steps Newton
            steps, e.g. 4x fewer iterations on a unicycle around an obstacle).
        shooting: ``"single"`` (default: the iterate is ``U``, every trial step a
            feedback rollout of the model) or ``"multiple"`` (every time step a shooting
            node, :mod:`torchslq.solvers.shooting`: the iterate is the node states and
            controls, the LQ step closes their defects and a merit line search accepts
            lifted steps; every model call is one batched call over all ``B T`` nodes,
            no step-by-step rollout, which is what a learned model or any model on the
            torch path needs). With ``"multiple"`` an ``x_init`` may be any state guess
            (its first state must be ``x0``), the result's ``x`` is the rollout of its
            ``u``, and bounds and constraints are not supported.
        defect_tol: ``shooting="multiple"``: the largest defect ``|f(x_t, u_t) -
            x_{t+1}|`` of a converged element (None: ``tol``).
        rtol, stop, step_tol, stall_iters, armijo_c1, armijo_beta, max_backtracks,
            armijo_passes, linearize_method, progress, compact: as for
            :class:`torchslq.SLQ`.
        line_search, rollout: fixed (``"armijo"``, ``"closed_loop"``); accepted for
            symmetry with :class:`torchslq.SLQ`, anything else is a ValueError.
    """

    name: ClassVar[str] = "ilqr"
    options_class: ClassVar[type] = ILQROptions
    supports_bounds: ClassVar[bool] = True
    supports_constraints: ClassVar[bool] = True

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
        constraint_hessian: str = "gauss_newton",
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
        super().__init__(**{k: v for k, v in locals().items() if k not in ("self", "__class__")})

    def solve(
        self,
        problem: Problem,
        x0: Tensor,
        u_init: Tensor | None = None,
        logger: Any = None,
        *,
        x_init: Tensor | None = None,
        multipliers: dict[str, Tensor] | None = None,
    ) -> SolverResult:
        if self.options.constraints is None:
            if multipliers is not None:
                raise ValueError("multipliers are for solves with constraints=")
            return super().solve(problem, x0, u_init, logger, x_init=x_init)
        from .augmented_lagrangian import solve_constrained

        return solve_constrained(self, problem, x0, u_init, logger, x_init, multipliers)

    solve.__doc__ = (DescentSolver.solve.__doc__ or "").replace(
        "        Returns:",
        "            multipliers: with ``constraints=``: initial multipliers\n"
        '                ``{"stage": (B, T, p), "terminal": (B, q)}`` (e.g. a previous\n'
        "                result's ``multipliers``); zeros by default.\n\n        Returns:",
    )

    def _newton(self, **second_order: Any) -> RegularizedNewton:
        o = self.options
        schedule = RegularizationSchedule(o.mu_factor, o.mu_min, o.mu_max)
        common = dict(
            schedule=schedule,
            mu_init=o.mu_init,
            hessian_floor=o.hessian_floor,
            linearize_method=o.linearize_method,
            **second_order,
        )
        if o.shooting == "multiple":
            defect_tol = o.tol if o.defect_tol is None else o.defect_tol
            verify = o.tol if o.stop in ("grad", "either", "both") else None
            return MultipleShootingNewton(defect_tol=defect_tol, verify_tol=verify, **common)
        return RegularizedNewton(skip_tol=o.tol if o.stop in ("grad", "either") else None, **common)

    def _descent_rule(self, newton: RegularizedNewton):
        """The rule of ``newton``: with the feedback rollout, or with multiple shooting's
        merit line search."""
        o = self.options
        search = None
        if o.shooting == "multiple":
            search = MeritLineSearch(
                c1=o.armijo_c1,
                beta=o.armijo_beta,
                max_backtracks=o.max_backtracks,
                passes=o.armijo_passes,
            )
        return descent_rule(newton, o, quadratic_model=True, search=search)

    def rule(self):
        return self._descent_rule(self._newton())

    def initial_state(self, problem, x0, u, x, lo=None, hi=None, bounds=None, start_status=None):
        state = super().initial_state(problem, x0, u, x)
        mu = torch.full_like(state.J, float(self.options.mu_init))
        ones = torch.ones_like(mu)
        state = replace(state, mu=mu, delta=ones, lo=lo, hi=hi, prev_step=ones)
        if self.options.shooting == "multiple":
            gaps = node_defects(problem.transition, x, u)
            state = replace(state, penalty=torch.zeros_like(mu), defects=gaps)
        return state

    def final_state(self, problem, state):
        """With multiple shooting: the rollout of the controls and its cost (the nodes
        differ from it by the remaining defects)."""
        if self.options.shooting != "multiple":
            return state
        x = rollout(problem.transition, state.x[:, 0], state.u)
        return replace(state, x=x, J=problem.cost(x, state.u))

    def prepare(self, problem: Problem, x0: Tensor, u: Tensor, x_init: Tensor | None):
        """Clamp ``u`` into the bounds (an ``x_init`` is then used only if ``u`` was
        within them: clamping changes its rollout)."""
        o = self.options
        if o.u_min is None and o.u_max is None:
            return u, x_init, {}
        lo, hi, faults = bounds_with_faults(problem, x0, o.u_min, o.u_max)
        uc = torch.minimum(torch.maximum(u, lo), hi)
        if x_init is not None and not torch.equal(uc, u):
            x_init = None  # the rollout of other controls
        bounded = not (bool(torch.isinf(lo).all()) and bool(torch.isinf(hi).all()))
        extra = {"lo": lo.contiguous(), "hi": hi.contiguous()} if bounded else {}
        # elements with invalid bounds of their own start with that status (not solved)
        return uc, x_init, extra | {"bounds": (lo, hi), "start_status": faults}

    def finish(self, result, extra):
        if "bounds" in extra:
            lo, hi = extra["bounds"]
            result.active_bounds = active_bounds(result.u, lo, hi)
        return result
