"""Descent solvers as a direction × a line search on the one loop (:mod:`.core`).

A :class:`DescentRule` combines

* a **direction** (a callable ``(problem, state, running, it) -> (d, state)``): the
  Gauss-Newton LQ step of SLQ (:class:`GaussNewtonLQ`, Sideris & Bobrow Algorithm 2,
  Step 2), the costate gradient (:class:`CostateGradient`, eqs. 8-11), or iLQR/DDP's
  regularised Newton step (:class:`torchslq.solvers.newton.RegularizedNewton`); and
* a **globalisation** (:class:`LineSearch`): the exact search (Theorem 2) or Armijo
  with batched trials, along the open-loop direction ``U + α Ū`` (eq. 28) or through the
  feedback rollout ``u = ū + α k + K (x - x̄)``, with the linear or the quadratic
  (expected-improvement) model of the decrease.

A direction returns a dict ``d`` with ``du (b,T,m)``, ``dx (b,T+1,n)``, ``K``, ``k``,
``grad (b,T,m)`` (``∇_U J``, or the projected gradient with bounds), ``slope (b,)``
(``∇J·Ū``), ``failed (b,)`` and optionally ``grad_norm (b,)`` (the norm of ``grad``,
where the direction computed it), ``curvature (b,)`` (``k'Quu k``), ``scale
(b,)`` (the line search runs over ``(0, scale]``), ``keep_gains (b,)`` (False where the
gains of this iteration were not computed), ``nonfinite (b,)`` (its data were not
finite: status ``non_finite`` rather than ``not_positive_definite``). Its per-element memory (e.g. the
Levenberg-Marquardt ``mu``) lives in the :class:`DescentState`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import torch
from torch import Tensor

from .._backend.dispatch import armijo_rollout_compiled, can_use_compiled
from ..dynamics.linearize import linearize
from ..dynamics.rollout import compiled_step_of, costate_gradient, rollout, rollout_closed_loop
from ..lq.riccati import riccati_backward, rollout_linear
from ..status import Status
from .core import Advance as _Advance
from .core import ElementState, Measure
from .line_search import TrialRecorder, armijo_search, armijo_steps, exact_search
from .options import DescentOptions
from .stopping import ROUNDOFF_NOISE

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = [
    "CostateGradient",
    "DescentRule",
    "DescentState",
    "Direction",
    "GaussNewtonLQ",
    "LineSearch",
]


@dataclass(frozen=True)
class DescentState(ElementState):
    """Per-solve state of a descent solver (batch-first).

    Attributes (besides ``x, u, J``):
        K ``(B, T, m, n)``, k ``(B, T, m)``: the gains of the last LQ step.
        mu, delta ``(B,)``: Levenberg-Marquardt regularisation and its schedule factor
            (iLQR/DDP; None otherwise).
        prev_step ``(B,)``: last accepted step (GradientMethod's search range).
        lo, hi ``(B, T, m)``: control bounds (None: unbounded).
        penalty ``(B,)``, defects ``(B, T, n)``: multiple shooting's merit penalty and
            the defects ``f(x_t, u_t) - x_{t+1}`` of the nodes (None otherwise).
    """

    K: Tensor = None
    k: Tensor = None
    mu: Tensor | None = None
    delta: Tensor | None = None
    prev_step: Tensor | None = None
    lo: Tensor | None = None
    hi: Tensor | None = None
    penalty: Tensor | None = None
    defects: Tensor | None = None


class Direction(Protocol):
    """A descent direction (see the module docstring)."""

    def __call__(
        self, problem: Problem, state: DescentState, running: Tensor, it: int
    ) -> tuple[dict[str, Tensor], DescentState]: ...

    def after_search(
        self, state: DescentState, running: Tensor, ok: Tensor
    ) -> tuple[DescentState, Tensor]:
        """The state after a line search (``ok``: a step was accepted) and the elements
        whose failed search ends their solve."""
        ...


def nonfinite_rows(*tensors: Tensor) -> Tensor:
    """``(b,)`` True where any of the batch-first tensors ``(b, ...)`` has a non-finite
    entry (a NaN Jacobian is ``non_finite``, not a factorisation failure)."""
    out = torch.zeros(tensors[0].shape[0], dtype=torch.bool, device=tensors[0].device)
    for t in tensors:
        if t is not None and t.ndim > 0 and t.shape[0] == out.shape[0]:
            out = out | ~torch.isfinite(t).flatten(1).all(1)
    return out


def _every_failure_ends(
    state: DescentState, running: Tensor, ok: Tensor
) -> tuple[DescentState, Tensor]:
    return state, running & ~ok


@dataclass(frozen=True)
class GaussNewtonLQ:
    """SLQ's direction: linearise at ``(x, u)`` and solve the LQ subproblem with the
    cost's exact quadratic model (Sideris & Bobrow Algorithm 2, Step 2; eqs. 29-30)."""

    linearize_method: str = "auto"

    def __call__(self, problem, state, running, it):
        x, u = state.x, state.u
        T = problem.horizon
        A, B = linearize(problem.transition, x[:, :T], u, method=self.linearize_method)
        e = problem.cost.quadratize(x, u)
        grad, _ = costate_gradient(A, B, e.lx, e.lu)
        fac = riccati_backward(A, B, e.lxx, e.luu, e.lx, e.lu, e.lux)
        dx, du = rollout_linear(A, B, fac.K, fac.k, torch.zeros_like(x[:, 0]))
        slope = (grad * du).sum(dim=(-1, -2))
        d = {"dx": dx, "du": du, "K": fac.K, "k": fac.k, "grad": grad, "slope": slope}
        return d | {"failed": fac.failed}, state

    after_search = staticmethod(_every_failure_ends)


@dataclass(frozen=True)
class CostateGradient:
    """Steepest descent ``-∇_U J`` by the costate recursion (Sideris & Bobrow eqs. 8-11).

    ``search_range="adaptive"``: the gradient has an arbitrary scale, so the search runs
    over ``(0, α_max]`` with ``α_max = max(2 α_GN, growth · α_prev)`` per element, where
    ``α_GN = ||g||² / (g' H g)`` minimises the Gauss-Newton model along ``-g`` and
    ``α_prev`` is the last accepted step; ``"unit"``: over ``(0, 1]``.
    """

    linearize_method: str = "auto"
    search_range: str = "adaptive"
    growth: float = 4.0

    def __call__(self, problem, state, running, it):
        x, u = state.x, state.u
        A, B = linearize(
            problem.transition, x[:, : problem.horizon], u, method=self.linearize_method
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
        slope = -(grad * grad).sum(dim=(-1, -2))
        d = {"dx": dx, "du": du, "K": K, "k": du, "grad": grad, "slope": slope}
        d |= {"curvature": curv, "failed": torch.zeros_like(slope, dtype=torch.bool)}
        d["scale"] = self.search_scale(d, state.prev_step)
        return d, state

    def search_scale(self, d: dict[str, Tensor], prev_step: Tensor | None) -> Tensor:
        """Per-element ``α_max (B,)`` of the line search for direction ``d``."""
        slope = d["slope"]
        if self.search_range == "unit":
            return torch.ones_like(slope)
        g2 = -slope
        a_gn = g2 / d["curvature"]
        fallback = 1.0 / g2.sqrt()  # a step of unit length in U
        good = torch.isfinite(a_gn) & (a_gn > 0)
        scale = torch.where(good, 2.0 * a_gn, fallback)
        if prev_step is not None:
            scale = torch.maximum(scale, self.growth * prev_step)
        return torch.where(torch.isfinite(scale) & (scale > 0), scale, torch.ones_like(scale))

    after_search = staticmethod(_every_failure_ends)


def default_passes(
    device: torch.device, prev_step: Tensor | None = None, running: Tensor | None = None
) -> tuple[int, int | None]:
    """Armijo's pass sizes ``(first_trials, pass_size)`` when the options leave them
    open. Off the CPU ``(4, None)``: each pass costs a host synchronisation. On the CPU
    each trial costs in proportion, so ``(1, 3)``; but ``(2, 2)`` when most running
    elements accepted a step shorter than 1 last time (``prev_step (b,)``): the half
    step is then likely the one accepted again (iLQR on the cart-pole swing-up: 12-15%
    less time at B = 1 and 64; the pendulum, whose full steps pass, keeps ``(1, 3)``).
    The accepted steps do not depend on the pass sizes."""
    if device.type != "cpu":
        return (4, None)
    if prev_step is not None and running is not None:
        if bool(2 * ((prev_step < 1) & running).sum() > running.sum()):  # one host sync
            return (2, 2)
    return (1, 3)


@dataclass(frozen=True)
class LineSearch:
    """The globalisation of a descent solver.

    Args:
        kind: ``"exact"`` (:func:`~torchslq.solvers.line_search.exact_search`) or
            ``"armijo"`` (:func:`~torchslq.solvers.line_search.armijo_search`).
        rollout: ``"open_loop"`` (``U + α Ū``) or ``"closed_loop"`` (the feedback
            rollout, clamped into the state's bounds).
        quadratic_model: Armijo on the expected improvement ``α slope + α²/2 curvature``
            (iLQR/DDP) instead of ``α slope``.
        c1, beta, max_backtracks, passes: Armijo's constants and pass sizes
            ``(first, then)`` (None: :func:`default_passes`).
    """

    kind: str = "exact"
    rollout: str = "open_loop"
    quadratic_model: bool = False
    c1: float = 1e-4
    beta: float = 0.5
    max_backtracks: int = 20
    passes: tuple[int, int | None] | None = None

    def pass_sizes(
        self,
        device: torch.device,
        prev_step: Tensor | None = None,
        running: Tensor | None = None,
    ) -> tuple[int, int | None]:
        """``(first_trials, pass_size)`` of :func:`armijo_search`: the option, or the
        device's default (see :func:`default_passes`)."""
        if self.passes is not None:
            return self.passes
        return default_passes(device, prev_step, running)

    def armijo(
        self,
        evaluate,
        J0: Tensor,
        slope: Tensor,
        curvature: Tensor | None,
        running: Tensor,
        prev_step: Tensor | None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """:func:`armijo_search` with this search's constants and pass sizes, the trials
        of settled elements skipped."""
        first_trials, pass_size = self.pass_sizes(J0.device, prev_step, running)
        return armijo_search(
            evaluate,
            J0,
            slope,
            curvature=curvature,
            c1=self.c1,
            beta=self.beta,
            max_backtracks=self.max_backtracks,
            active=running,
            skip_settled=True,
            first_trials=first_trials,
            pass_size=pass_size,
        )

    def __call__(
        self, problem: Problem, state: DescentState, d: dict[str, Tensor], running: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Step sizes ``(b,)`` (in units of the unscaled direction), new objectives,
        success flags and the chosen trajectories ``x, u``."""
        f, cost_fn = problem.transition, problem.cost
        x, u, J = state.x, state.u, state.J
        x0 = x[:, 0]
        scale = d.get("scale")
        du, k, slope = d["du"], d["k"], d["slope"]
        if scale is not None:
            du, k, slope = scale[:, None, None] * du, scale[:, None, None] * k, scale * slope
        if self.kind == "armijo" and self.rollout == "closed_loop" and scale is None:
            fused = self._fused_armijo(problem, state, d, running)
            if fused is not None:
                return fused
        trials = TrialRecorder()

        def evaluate(alphas: Tensor) -> Tensor:  # alphas (Na, b) -> J (Na, b)
            x0c = x0.expand(alphas.shape[0], *x0.shape)
            if self.rollout == "open_loop":
                uc = u + alphas[..., None, None] * du
                xc = rollout(f, x0c, uc)
            else:
                xc, uc = rollout_closed_loop(f, x0c, x, u, d["K"], k, alphas, state.lo, state.hi)
            trials.record(alphas, xc, uc)
            return cost_fn(xc, uc)

        if self.kind == "exact":
            alpha, J_new, ok = exact_search(evaluate, J, slope=slope)
        else:
            # the last steps hint at this one's (not for a scaled direction, whose
            # steps are in other units)
            prev = state.prev_step if scale is None else None
            curvature = d["curvature"] if self.quadratic_model else None
            alpha, J_new, ok = self.armijo(evaluate, J, slope, curvature, running, prev)
        x_new, u_new = trials.select(alpha)
        if scale is not None:
            alpha = alpha * scale
        return alpha, J_new, ok, x_new, u_new

    def _fused_armijo(
        self, problem: Problem, state: DescentState, d: dict[str, Tensor], running: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor] | None:
        """The Armijo search along the feedback rollout as one CPU kernel call
        (:func:`torchslq._backend.dispatch.armijo_rollout_compiled`) where the model has
        a compiled step and the cost gives its kernel arrays
        (:meth:`torchslq.QuadraticCost.compiled_terms`); None elsewhere. Its steps,
        costs and accepted trajectories are :func:`armijo_search`'s (the trials in
        turn, the same operations in the same order), without the passes' glue: about
        thirty small torch ops per pass, most of a small batch's search."""
        terms_of = getattr(problem.cost, "compiled_terms", None)
        if terms_of is None:
            return None
        x, u, J0 = state.x, state.u, state.J
        curvature = d["curvature"] if self.quadratic_model else None
        tensors = [x, u, J0, d["K"], d["k"], d["slope"]]
        tensors += [t for t in (curvature, state.lo, state.hi) if t is not None]
        if not can_use_compiled(*tensors):
            return None
        compiled = compiled_step_of(problem.transition)
        if compiled is None:
            return None
        terms = terms_of(x, u)
        if terms is None:
            return None
        # armijo_search's steps, the same floats
        grid = armijo_steps(1.0, self.beta, self.max_backtracks, J0.dtype, J0.device)
        return armijo_rollout_compiled(
            *compiled, x, u, d["K"], d["k"], state.lo, state.hi, grid, J0, d["slope"],
            curvature, self.c1, ROUNDOFF_NOISE * torch.finfo(J0.dtype).eps, running, terms,
        )  # fmt: skip


@dataclass(frozen=True)
class DescentRule:
    """Direction × line search: the iteration rule of SLQ, ILQR, DDP and GradientMethod.

    Stopping test (``stop``): ``"grad"``: ``||∇_U J|| < tol``; ``"step"``:
    ``||Ū|| < step_tol ||U||`` (Algorithm 2, Step 2); ``"either"`` / ``"both"``.
    """

    direction: Any
    search: LineSearch
    stop: str = "grad"
    tol: float = 1e-6
    step_tol: float = 1e-6

    def measure(self, problem, state: DescentState, running: Tensor, it: int):
        d, state = self.direction(problem, state, running, it)
        gn = d.get("grad_norm")
        if gn is None:
            gn = d["grad"].flatten(1).norm(dim=1)
        new_gains = running if "keep_gains" not in d else running & d["keep_gains"]
        K = torch.where(new_gains[:, None, None, None], d["K"], state.K)
        k = torch.where(new_gains[:, None, None], d["k"], state.k)
        small_grad = gn < self.tol
        if self.stop == "grad":  # (the step test's two norms only where it is used)
            done = small_grad
        else:
            du_norm = d["du"].flatten(1).norm(dim=1)
            small_step = du_norm < self.step_tol * state.u.flatten(1).norm(dim=1)
            done = {
                "step": small_step,
                "either": small_grad | small_step,
                "both": small_grad & small_step,
            }[self.stop]
        if "feasible" in d:  # multiple shooting: converged only with the defects closed
            done = done & d["feasible"]
        fail = torch.full_like(gn, int(Status.RUNNING), dtype=torch.int64)
        fail = fail.masked_fill(d["failed"], int(Status.NOT_POSITIVE_DEFINITE))
        fail = fail.masked_fill(~torch.isfinite(d["slope"]), int(Status.NON_FINITE))
        if "nonfinite" in d:
            fail = fail.masked_fill(d["nonfinite"], int(Status.NON_FINITE))
        state = state.updated(K=K, k=k)
        return state, Measure(grad_norm=gn, done=done, fail=fail, cost=state.J, direction=d)

    def advance(self, problem, state: DescentState, m: Measure, running: Tensor):
        d = m.direction
        alpha, J_new, ok, x_new, u_new, *extra = self.search(problem, state, d, running)
        accept = running & ok
        # a search may also return per-element state fields of its trials (a dict)
        moved = {
            k: torch.where(accept.view(-1, *([1] * (v.ndim - 1))), v, getattr(state, k))
            for k, v in (extra[0] if extra else {}).items()
        }
        if state.prev_step is not None:
            state = state.updated(prev_step=torch.where(ok, alpha, state.prev_step))
        state, ended = self.direction.after_search(state, running, ok)
        end = torch.where(ended, int(Status.LINE_SEARCH_FAILED), int(Status.RUNNING))
        state = state.updated(
            x=torch.where(accept[:, None, None], x_new, state.x),
            u=torch.where(accept[:, None, None], u_new, state.u),
            J=torch.where(accept, J_new, state.J),
            **moved,
        )
        return _Advance(state=state, accept=accept, step=alpha, end=end)


def descent_rule(
    direction: Any, o: DescentOptions, *, quadratic_model: bool = False, search: Any = None
):
    """The :class:`DescentRule` of ``direction`` with the options ``o`` (an
    :class:`~torchslq.solvers.options.SLQOptions`-like object) and the line search
    ``search`` (by default the :class:`LineSearch` of the options)."""
    search = search or LineSearch(
        kind=o.line_search,
        rollout=o.rollout,
        quadratic_model=quadratic_model,
        c1=o.armijo_c1,
        beta=o.armijo_beta,
        max_backtracks=o.max_backtracks,
        passes=o.armijo_passes,
    )
    step_tol = o.tol if o.step_tol is None else o.step_tol
    return DescentRule(
        direction=direction, search=search, stop=o.stop, tol=o.tol, step_tol=step_tol
    )
