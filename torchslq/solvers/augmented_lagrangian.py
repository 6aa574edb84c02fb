"""Constrained iLQR/DDP: an augmented-Lagrangian outer loop on the shared core.

The outer iteration (one :func:`~torchslq.solvers.core.iterate` step per element) is

1. solve ``min_u J + AL(c; λ, ρ)`` with the unconstrained iLQR/DDP from the current
   trajectory (the inner solve, warm started; control bounds stay in its box QP);
2. update the multipliers ``λ <- λ̂`` (:func:`~torchslq.constraints.multiplier_estimate`);
3. raise the penalty ``ρ <- min(φ ρ, ρ_max)`` of an element whose largest violation did
   not fall below a quarter of the previous one (Conn, Gould & Toint's rule, the default)
   or, with ``penalty_update="always"``, of every element still infeasible (ALTRO's and
   trajax's ``constrained_ilqr``'s schedule).

Every element has its own ``λ``, ``ρ``, outer iteration count and status: it is
``converged`` when its largest violation is at most ``constraint_tol`` and the inner
solve's gradient (the Lagrangian's, with the updated ``λ``) is below ``tol``;
``infeasible`` when the violation stays above ``constraint_tol`` after an inner solve
at ``ρ_max``; an inner ``non_finite`` / ``not_positive_definite`` ends it with that
status. Finished elements are frozen; where the problem data are batch-shared, the
inner solves run on the running elements only.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from ..constraints.augmented import AugmentedLagrangianCost, multiplier_estimate
from ..constraints.polish import polish
from ..constraints.spec import ConstraintSet, max_violation
from ..costs.quadratic import compiled_cost_evaluation
from ..dynamics.rollout import rollout
from ..problem import Problem, check_problem
from ..status import Status
from .base import checked_x_init
from .core import Advance, ElementState, LoopSettings, Measure, check_logger, iterate
from .options import loggable
from .result import SolverResult

if TYPE_CHECKING:  # pragma: no cover
    from .ilqr import ILQR

__all__ = ["ALState", "AugmentedLagrangian", "default_constraint_tol", "solve_constrained"]

# the violation must fall below this fraction of the previous one, or the penalty rises
PROGRESS_RATIO = 0.25
# the subproblems' gradient tolerance: at most INNER_TOL_START, times this per iteration
INNER_TOL_START = 1e-3
INNER_TOL_DECREASE = 0.1
# with polish=True the loop hands over to the Newton steps at this violation
POLISH_FROM = 1e-4


def default_constraint_tol(dtype: torch.dtype) -> float:
    """``constraint_tol`` when not given: 1e-6 in float64, 1e-4 in lower precision."""
    return 1e-6 if dtype == torch.float64 else 1e-4


@dataclass(frozen=True)
class ALState(ElementState):
    """Per-solve state of the augmented-Lagrangian loop (batch-first).

    Attributes (besides ``x, u`` and ``J``, the problem's cost):
        lam ``(B, T, p)``, lam_T ``(B, q)``: multipliers; rho ``(B,)``: penalties.
        violation ``(B,)``: largest violation at ``(x, u)``.
        inner_grad ``(B,)``: the last inner solve's gradient norm (NaN before the first).
        inner_status ``(B,)``: its status; inner_iterations ``(B,)``: their total.
        inner_tol ``(B,)``: the gradient tolerance of the element's next subproblem.
        K ``(B, T, m, n)``, k ``(B, T, m)``: the last inner solve's gains.
        lo, hi ``(B, T, m)``: the control bounds (None: unbounded), carried per element so
        that a subproblem on a sub-batch gets its elements' bounds.
    """

    lam: Tensor = None
    lam_T: Tensor = None
    rho: Tensor = None
    violation: Tensor = None
    inner_grad: Tensor = None
    inner_status: Tensor = None
    inner_iterations: Tensor = None
    inner_tol: Tensor = None
    K: Tensor = None
    k: Tensor = None
    lo: Tensor = None
    hi: Tensor = None


@dataclass(frozen=True)
class AugmentedLagrangian:
    """The outer iteration rule (module docstring).

    Args:
        inner: the unconstrained solver of the subproblems (an ILQR/DDP without
            constraints, no progress bar, no compaction).
        constraints: the rows; stage_eq ``(p,)``, terminal_eq ``(q,)``: their kinds.
        tol: the inner gradient tolerance (the Lagrangian's stationarity).
        constraint_tol: the largest violation accepted.
        penalty_factor, penalty_max: the penalty schedule.
        penalty_update: ``"progress"`` (raise ``ρ`` where the violation did not shrink
            fourfold) or ``"always"`` (wherever it is above ``constraint_tol``: ALTRO's
            and trajax's schedule).
        curvature: the subproblems' quadratic model includes the rows' curvature
            weighted by their multipliers (``constraint_hessian="exact"``).
    """

    inner: Any
    constraints: ConstraintSet
    stage_eq: Tensor
    terminal_eq: Tensor
    tol: float
    constraint_tol: float
    penalty_factor: float
    penalty_max: float
    curvature: bool = False
    penalty_update: str = "progress"

    def _violation(self, x: Tensor, u: Tensor) -> Tensor:
        return max_violation(self.constraints.values(x, u), self.stage_eq, self.terminal_eq)

    def measure(self, problem: Problem, state: ALState, running: Tensor, it: int):
        viol = self._violation(state.x, state.u)
        done = (viol <= self.constraint_tol) & (state.inner_grad < self.tol)
        fail = torch.full_like(state.inner_status, int(Status.RUNNING))
        for code in (Status.NON_FINITE, Status.NOT_POSITIVE_DEFINITE):
            fail = fail.masked_fill(state.inner_status == code, int(code))
        fail = fail.masked_fill(~torch.isfinite(viol), int(Status.NON_FINITE))
        hist = {
            "max_violation": viol,
            "penalty": state.rho,
            "inner_iterations": state.inner_iterations.to(viol.dtype),
        }
        state = replace(state, violation=viol)
        return state, Measure(
            grad_norm=state.inner_grad, done=done, fail=fail, cost=state.J, history=hist
        )

    def advance(self, problem: Problem, state: ALState, m: Measure, running: Tensor):
        idx = running.nonzero().squeeze(1)
        sub = state.take(idx)
        problem = problem.take(idx, state.J.shape[0])  # per-element data follow the subset
        al_cost = AugmentedLagrangianCost(
            problem.cost, self.constraints, sub.lam, sub.lam_T, sub.rho,
            self.stage_eq, self.terminal_eq, curvature=self.curvature,
        )  # fmt: skip
        inner_problem = Problem(problem.dynamics, al_cost, problem.horizon)
        # subproblems far from the solution need not be solved tightly (Conn, Gould &
        # Toint): the tolerance falls tenfold per outer iteration down to ``tol``
        inner = self.inner.with_options(tol=float(sub.inner_tol.max()))
        if sub.lo is not None:  # the sub-batch's own bounds (they may be per element)
            inner = inner.with_options(u_min=sub.lo, u_max=sub.hi)
        r = inner.solve(inner_problem, sub.x[:, 0], sub.u, x_init=sub.x)
        v = self.constraints.values(r.x, r.u)
        viol = max_violation(v, self.stage_eq, self.terminal_eq)
        rho = sub.rho
        lam = multiplier_estimate(v.stage, sub.lam, rho[:, None, None], self.stage_eq)
        lam_T = multiplier_estimate(v.terminal, sub.lam_T, rho[:, None], self.terminal_eq)
        slow = viol > self.constraint_tol
        if self.penalty_update == "progress":
            slow = slow & ~(viol <= PROGRESS_RATIO * sub.violation)
        new_rho = torch.where(slow, (rho * self.penalty_factor).clamp_max(self.penalty_max), rho)
        new = replace(
            sub,
            x=r.x,
            u=r.u,
            J=problem.cost(r.x, r.u),
            lam=lam,
            lam_T=lam_T,
            rho=new_rho,
            violation=viol,
            inner_grad=r.grad_norm,
            inner_status=r.status,
            inner_iterations=sub.inner_iterations + r.iterations,
            # once feasible, only stationarity is left: the next subproblem at ``tol``
            inner_tol=torch.where(
                viol <= self.constraint_tol,
                torch.full_like(sub.inner_tol, self.tol),
                (sub.inner_tol * INNER_TOL_DECREASE).clamp_min(self.tol),
            ),
            K=r.K,
            k=r.k,
        )
        # infeasible: still violated after a subproblem solved at the largest penalty
        infeasible = (rho >= self.penalty_max) & (viol > self.constraint_tol)
        end = torch.full_like(r.status, int(Status.RUNNING))
        end = end.masked_fill(infeasible, int(Status.INFEASIBLE))
        state = state.put(idx, new)
        end = torch.full_like(state.inner_status, int(Status.RUNNING)).index_copy(0, idx, end)
        accept = running.clone()
        return Advance(state=state, accept=accept, step=torch.ones_like(state.J), end=end)


def solve_constrained(
    solver: ILQR,
    problem: Problem,
    x0: Tensor,
    u_init: Tensor | None,
    logger: Any,
    x_init: Tensor | None,
    multipliers: dict[str, Tensor] | None = None,
) -> SolverResult:
    """``solver.solve`` for a solver whose options hold ``constraints`` (module docstring);
    ``multipliers`` (``{"stage": (B, T, p), "terminal": (B, q)}``, e.g. a previous
    solve's, shifted) start the outer loop instead of zeros."""
    o = solver.options
    check_problem(problem)
    check_logger(logger)
    x0, u, unbatched = problem.check_inputs(x0, u_init)
    if x_init is not None:
        x_init = checked_x_init(x_init, x0, problem.horizon)
    Bsz, T = x0.shape[0], problem.horizon
    cset = o.constraints.to(dtype=x0.dtype, device=x0.device)
    stage_eq, terminal_eq = cset.dims(problem.state_dim, problem.control_dim, x0)
    ctol = default_constraint_tol(x0.dtype) if o.constraint_tol is None else o.constraint_tol
    largest = torch.finfo(x0.dtype).max
    for name in ("penalty_init", "penalty_max"):
        if largest < getattr(o, name) < float("inf"):
            raise ValueError(
                f"{name} = {getattr(o, name):g} overflows {x0.dtype} (largest {largest:g}); "
                f"pass a smaller {name}"
            )
    inner = solver.with_options(constraints=None, progress=False, compact=False)
    u, x_init, extra = inner.prepare(problem, x0, u, x_init)  # clamp into the control bounds
    lo, hi = extra.get("lo"), extra.get("hi")
    # with polishing the loop stops at a looser violation and Newton steps on the active
    # set finish; elements they fail resume the loop
    loop_ctol = max(ctol, POLISH_FROM) if o.polish else ctol
    rule = AugmentedLagrangian(
        inner=inner,
        constraints=cset,
        stage_eq=stage_eq,
        terminal_eq=terminal_eq,
        tol=o.tol,
        constraint_tol=loop_ctol,
        penalty_factor=o.penalty_factor,
        penalty_max=o.penalty_max,
        curvature=o.constraint_hessian == "exact",
        penalty_update=o.penalty_update,
    )
    record = o.record(solver.name)
    settings = LoopSettings(
        max_iter=o.al_max_iter,
        rtol=0.0,
        stall_iters=0,
        compact=True,
        progress=o.progress,
        name=solver.name,
    )
    n, m = problem.state_dim, problem.control_dim
    lam, lam_T, bad_lam = _initial_multipliers(multipliers, x0, T, stage_eq, terminal_eq)
    from ..dynamics.codegen import hooks_pinned

    with torch.no_grad(), compiled_cost_evaluation(), hooks_pinned():
        x = rollout(problem.transition, x0, u) if x_init is None else x_init
        zeros = x0.new_zeros(Bsz)
        J0 = problem.cost(x, u)
        if multipliers is not None:  # a non-finite objective: the loop starts it non_finite
            J0 = J0.masked_fill(bad_lam, float("nan"))
        state = ALState(
            x=x,
            u=u,
            J=J0,
            lam=lam,
            lam_T=lam_T,
            rho=torch.full_like(zeros, float(o.penalty_init)),
            violation=torch.full_like(zeros, float("inf")),
            inner_grad=torch.full_like(zeros, float("nan")),
            inner_status=torch.full((Bsz,), int(Status.RUNNING), device=x0.device),
            inner_iterations=torch.zeros(Bsz, dtype=torch.int64, device=x0.device),
            # warm-started multipliers: near the solution, subproblems at ``tol`` at once
            inner_tol=torch.full_like(
                zeros,
                o.tol if multipliers is not None else max(o.tol, min(INNER_TOL_START, o.tol**0.5)),
            ),
            K=x0.new_zeros(Bsz, T, m, n),
            k=x0.new_zeros(Bsz, T, m),
            lo=lo,
            hi=hi,
        )
        out = iterate(
            rule, problem, state, settings, logger=logger, options=loggable(record),
            start_status=extra.get("start_status"),
        )  # fmt: skip
        s, status, grad_norm, outer = out.state, out.status, out.grad_norm, out.iterations
        if o.polish:
            s, status, grad_norm, outer = _polish_and_resume(
                problem, replace(rule, constraint_tol=ctol), settings, s, status, grad_norm,
                outer, lo, hi,
            )  # fmt: skip
    result = SolverResult(
        x=s.x,
        u=s.u,
        cost=s.J,
        grad_norm=grad_norm,
        iterations=s.inner_iterations,
        status=status,
        converged=status == Status.CONVERGED,
        K=s.K,
        k=s.k,
        history=out.history,
        options=record,
        multipliers={"stage": s.lam, "terminal": s.lam_T},
        max_violation=s.violation,
        outer_iterations=outer,
    )
    result = solver.finish(result, extra)
    if logger is not None:
        logger.log_result(result, problem)
    return result.squeeze_batch() if unbatched else result


def _initial_multipliers(
    given: dict[str, Tensor] | None, x0: Tensor, T: int, stage_eq: Tensor, terminal_eq: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """``(lam (B, T, p), lam_T (B, q), bad (B,))``: zeros, or ``given`` checked (shapes,
    ``>= 0`` on inequality rows) and broadcast over the batch. ``bad`` flags the elements
    whose own multipliers contain NaN or infinity (they start ``non_finite``, with zero
    multipliers); in multipliers shared by the batch that is a ValueError."""
    Bsz, p, q = x0.shape[0], stage_eq.numel(), terminal_eq.numel()
    bad = torch.zeros(Bsz, dtype=torch.bool, device=x0.device)
    if given is None:
        return x0.new_zeros(Bsz, T, p), x0.new_zeros(Bsz, q), bad
    if not isinstance(given, dict) or set(given) != {"stage", "terminal"}:
        raise TypeError("multipliers must be a dict with keys 'stage' and 'terminal'")
    out = []
    for key, shape, eq in (("stage", (T, p), stage_eq), ("terminal", (q,), terminal_eq)):
        t = given[key]
        if (
            not torch.is_tensor(t)
            or t.shape[-len(shape) :] != shape
            or t.ndim
            not in (
                len(shape),
                len(shape) + 1,
            )
        ):
            got = tuple(t.shape) if torch.is_tensor(t) else type(t).__name__
            want = ", ".join(map(str, shape))
            raise ValueError(f"multipliers[{key!r}] must have shape (B, {want}), got {got}")
        if t.ndim == len(shape) + 1 and t.shape[0] not in (1, Bsz):
            raise ValueError(f"multipliers[{key!r}] has batch size {t.shape[0]} but x0 has {Bsz}")
        shared = Bsz > 1 and (t.ndim == len(shape) or t.shape[0] == 1)
        t = t.detach().to(dtype=x0.dtype, device=x0.device).expand(Bsz, *shape).clone()
        finite = torch.isfinite(t).flatten(1).all(1)
        if not bool(finite.all()):
            if shared:
                raise ValueError(
                    f"multipliers[{key!r}] contains nan or inf (in data shared by the whole batch)"
                )
            # one element's fault: that element starts non_finite (granularity rule)
            bad = bad | ~finite
            t = torch.where(finite.view(-1, *([1] * (t.ndim - 1))), t, 0.0)
        out.append(torch.where(eq, t, t.clamp_min(0.0)))  # inequality multipliers are >= 0
    return out[0], out[1], bad


def _polish_and_resume(
    problem: Problem,
    rule: AugmentedLagrangian,
    settings: LoopSettings,
    s: ALState,
    status: Tensor,
    grad_norm: Tensor,
    outer: Tensor,
    lo: Tensor | None,
    hi: Tensor | None,
) -> tuple[ALState, Tensor, Tensor, Tensor]:
    """Polish the converged elements (:func:`~torchslq.constraints.polish.polish`) to
    ``rule``'s tolerances; the elements it fails go back to the loop (their multipliers
    and penalties as they were), the others keep the polished point."""
    Bsz = s.J.shape[0]
    idx = (status == Status.CONVERGED).nonzero().squeeze(1)
    if idx.numel() == 0:
        return s, status, grad_norm, outer
    sub = s.take(idx)

    def take(t: Tensor | None) -> Tensor | None:  # the bounds lead with the batch
        return None if t is None else t[idx]

    sub_problem = problem.take(idx, Bsz)
    x, u, lam, lam_T, ok, viol, gnorm = polish(
        sub_problem, rule.constraints, rule.stage_eq, rule.terminal_eq, sub.x, sub.u, sub.lam,
        sub.lam_T, take(lo), take(hi), tol=rule.tol, constraint_tol=rule.constraint_tol,
    )  # fmt: skip
    keep = ok.view(-1, 1, 1)
    polished = replace(
        sub,
        x=torch.where(keep, x, sub.x),
        u=torch.where(keep, u, sub.u),
        J=torch.where(ok, sub_problem.cost(x, u), sub.J),
        lam=torch.where(keep, lam, sub.lam),
        lam_T=torch.where(ok.view(-1, 1), lam_T, sub.lam_T),
        violation=torch.where(ok, viol, sub.violation),
        inner_grad=torch.where(ok, gnorm, sub.inner_grad),
    )
    s = s.put(idx, polished)
    grad_norm = grad_norm.index_copy(0, idx, torch.where(ok, gnorm, grad_norm[idx]))
    redo = idx[~ok]
    if redo.numel() == 0:
        return s, status, grad_norm, outer
    # the elements the Newton steps could not finish: the loop at the strict tolerances
    again = replace(s.take(redo), inner_tol=torch.full_like(s.J[redo], rule.tol))
    out = iterate(rule, problem.take(redo, Bsz), again, replace(settings, progress=False))
    s = s.put(redo, out.state)
    status = status.index_copy(0, redo, out.status)
    grad_norm = grad_norm.index_copy(0, redo, out.grad_norm)
    outer = outer.index_copy(0, redo, outer[redo] + out.iterations)
    return s, status, grad_norm, outer
