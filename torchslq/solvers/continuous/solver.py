"""``ContinuousILQR``: the continuous-time iLQR of Lieskovský, Bušek & Vyhlídal (2025) on
the shared iteration loop (:func:`torchslq.solvers.core.iterate`).

The iteration rule (:class:`ContinuousILQRRule`):

* ``measure``: the backward pass (:func:`~.passes.backward_pass`) along the current
  nominal trajectory: the policy ``d(t), K(t)``, the expected improvement
  ``Delta V(alpha) = -(alpha - alpha^2/2) eta`` and the stationarity measure
  ``sqrt(int |Q_u|^2 dt)`` (``Q_u`` is the gradient of the cost with respect to the
  control function at the solution);
* ``advance``: the backtracking line search on (15), ``J(alpha) - J < beta Delta V(alpha)``
  with ``alpha = 1, rho, rho^2, ...`` down to ``alpha_min``, each trial a forward pass
  (:func:`~.passes.forward_pass`) of the whole batch with each element's own ``alpha``
  (rows are independent, so an element's accepted trajectory does not depend on the
  others'; an element with no acceptable ``alpha >= alpha_min`` ends as
  ``line_search_failed``, the paper's termination).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from ...status import Status
from ..base import Solver
from ..core import Advance, ElementState, LoopSettings, Measure, check_logger, iterate, shared
from ..options import check_int, check_real, loggable, options_record
from ..result import SolverResult
from .expansion import Layout
from .passes import (
    Backward,
    Nominal,
    Policy,
    backward_pass,
    forward_pass,
    merge_nominal,
    merge_policy,
)

if TYPE_CHECKING:  # pragma: no cover
    from ...problem_continuous import ContinuousProblem

__all__ = [
    "ContinuousILQR",
    "ContinuousILQROptions",
    "ContinuousILQRResult",
    "ContinuousILQRRule",
    "ContinuousState",
]

HISTORY_KEYS = ("n_bwd", "n_fwd", "h_bwd_min", "h_bwd_max", "h_fwd_min", "h_fwd_max", "trials")


@dataclass(frozen=True)
class ContinuousILQROptions:
    """Options of :class:`ContinuousILQR` (see there)."""

    max_iter: int = 200
    tol: float = 1e-6
    rtol: float = 1e-6
    atol: float = 1e-8
    ddp: bool = False
    beta: float = 1e-4
    rho: float = 0.5
    alpha_min: float = 2.0**-20
    eps: float | None = None
    cost_rtol: float = 0.0
    stall_iters: int = 10
    max_steps: int = 100_000
    trials_per_pass: int = 4
    progress: bool = True

    def __post_init__(self) -> None:
        check_int("max_iter", self.max_iter, 0)
        check_real("tol", self.tol, 0.0, lo_closed=True)
        check_real("rtol", self.rtol, 0.0, 1.0)
        check_real("atol", self.atol, 0.0)
        if not isinstance(self.ddp, bool):
            raise TypeError(f"ddp must be a bool, got {self.ddp!r}")
        check_real("beta", self.beta, 0.0, 1.0)
        check_real("rho", self.rho, 0.0, 1.0)
        check_real("alpha_min", self.alpha_min, 0.0, 1.0, hi_closed=True)
        if self.eps is not None:
            check_real("eps", self.eps, 0.0, 1.0)
        check_real("cost_rtol", self.cost_rtol, 0.0, lo_closed=True)
        check_int("stall_iters", self.stall_iters, 0)
        check_int("max_steps", self.max_steps, 1)
        check_int("trials_per_pass", self.trials_per_pass, 1)
        if not isinstance(self.progress, bool):
            raise TypeError(f"progress must be a bool, got {self.progress!r}")

    def record(self, name: str) -> dict[str, Any]:
        return options_record(name, self)


@dataclass(frozen=True)
class ContinuousState(ElementState):
    """Per-solve state: ``x, u`` the nominal on its grid, ``J`` its cost, plus the
    nominal itself and the policy of the last backward pass (batch-wide structures,
    not narrowed: the solver has no ``compact`` mode)."""

    nominal: Any = shared(None)
    policy: Any = shared(None)
    n_fwd: Tensor | None = None
    h_fwd_min: Tensor | None = None
    h_fwd_max: Tensor | None = None
    trials: Tensor | None = None
    fresh: Tensor | None = None  # (B,) bool: the policy belongs to the current nominal


@dataclass
class ContinuousILQRResult(SolverResult):
    """:class:`torchslq.SolverResult` of a continuous-time solve.

    Besides those of :class:`SolverResult` (``x (B, N+1, n)``, ``u (B, N+1, m)`` here on
    the grid ``t``; ``K (B, N+1, m, n)`` and ``k (B, N+1, m)`` the policy on that grid in the
    library's convention ``u = ubar + alpha k + K (x - xbar)``, i.e. ``K = -K_paper``,
    ``k = -d``):

    Attributes:
        t: ``(B, N+1)`` each element's forward-pass grid, padded after its last point with
            that point; mask: ``(B, N+1)`` True on the element's own points.
        c: ``(B, N+1)`` the accumulated cost ``int_{t0}^t l dt`` on the grid.
        policy: the final policy (:class:`~torchslq.solvers.continuous.passes.Policy`):
            ``policy(t, x, alpha=1)`` and ``policy.d(t)``, ``policy.K(t)``,
            ``policy.xbar(t)``, ``policy.ubar(t)``, ``policy.S(t)``, ``policy.s(t)`` at
            any ``t (B,)`` or ``(B, Q)`` by dense output.
        expected_decrease: ``(B,)`` ``-Delta V(1) = eta / 2`` of the final backward pass.

    ``history`` adds per iteration ``n_bwd``, ``n_fwd`` (steps of the backward pass at
    the iterate and of the forward pass that produced it), ``h_bwd_min``, ``h_bwd_max``,
    ``h_fwd_min``, ``h_fwd_max`` (their step-size ranges) and ``trials`` (forward passes
    of the line search).
    """

    t: Tensor | None = None
    mask: Tensor | None = None
    c: Tensor | None = None
    policy: Any = None
    expected_decrease: Tensor | None = None

    def squeeze_batch(self) -> ContinuousILQRResult:
        base = SolverResult.squeeze_batch(self)

        def sq(v):
            return v[0] if torch.is_tensor(v) and v.ndim >= 1 else v

        return ContinuousILQRResult(
            **{k: getattr(base, k) for k in SolverResult.__dataclass_fields__},
            t=sq(self.t),
            mask=sq(self.mask),
            c=sq(self.c),
            policy=self.policy,
            expected_decrease=sq(self.expected_decrease),
        )


class ContinuousILQRRule:
    """The continuous-time iLQR as an iteration rule (measure: backward pass; advance:
    line search of forward passes)."""

    def __init__(self, options: ContinuousILQROptions, layout: Layout, x0: Tensor):
        self.o = options
        self.layout = layout
        self.x0 = x0
        self.eps = options.eps if options.eps is not None else torch.finfo(x0.dtype).eps

    def backward(
        self, problem: ContinuousProblem, nominal: Nominal, active: Tensor | None = None
    ) -> Backward:
        o = self.o
        return backward_pass(
            nominal,
            problem.tf,
            problem.t0,
            self.layout,
            rtol=o.rtol,
            atol=o.atol,
            eps=self.eps,
            max_steps=o.max_steps,
            active=active,
        )

    def measure(
        self, problem: ContinuousProblem, state: ContinuousState, running: Tensor, it: int
    ) -> tuple[ContinuousState, Measure]:
        # rows whose last accepted step ended them (cost_rtol, stall) still need the
        # policy of their final nominal
        active = running if state.fresh is None else running | ~state.fresh
        bwd = self.backward(problem, state.nominal, active)
        o = self.o
        finite = bwd.ok & torch.isfinite(bwd.eta) & torch.isfinite(bwd.grad_norm)
        fail = torch.where(finite, int(Status.RUNNING), int(Status.NON_FINITE))
        done = finite & (bwd.grad_norm <= o.tol)
        nan = torch.full_like(bwd.h_min, float("nan"))
        hist = {  # NaN / 0 where no backward pass ran (finished rows)
            "n_bwd": bwd.n_steps,
            "n_fwd": state.n_fwd,
            "h_bwd_min": torch.where(active, bwd.h_min, nan),
            "h_bwd_max": torch.where(active, bwd.h_max, nan),
            "h_fwd_min": state.h_fwd_min,
            "h_fwd_max": state.h_fwd_max,
            "expected_decrease": torch.where(active, 0.5 * bwd.eta, nan),
            "trials": state.trials,
        }
        # the backward pass ran on the running rows only: the others keep their policy
        policy = (
            bwd.policy if state.policy is None else merge_policy(active, bwd.policy, state.policy)
        )
        state = replace(state, policy=policy, fresh=torch.ones_like(running))
        m = Measure(
            grad_norm=bwd.grad_norm,
            done=done,
            fail=fail.to(torch.int64),
            cost=state.J,
            history=hist,
            direction=bwd,
        )
        return state, m

    def advance(
        self, problem: ContinuousProblem, state: ContinuousState, m: Measure, running: Tensor
    ) -> Advance:
        o = self.o
        bwd: Backward = m.direction
        policy: Policy = bwd.policy
        J0 = state.J
        searching = running.clone()
        accepted = torch.zeros_like(running)
        alpha = torch.where(running, torch.ones_like(J0), torch.zeros_like(J0))
        trials = torch.zeros_like(J0, dtype=torch.int64)
        nom = state.nominal
        Bsz = J0.shape[0]
        # after a first pass with alpha = 1, the next candidates are tried k at a time as
        # extra rows of one integration (the passes are dispatch-bound: k rows cost about
        # one); only for batch-shared problem data, whose rows can be repeated
        k_more = o.trials_per_pass if problem.per_element_tensor(Bsz) is None else 1
        # a predicted decrease below the resolution of the integrated cost: if the full
        # step does not pass (15), no smaller one can be told from integration noise
        noise = searching & (0.5 * bwd.eta <= o.rtol * J0.abs().clamp_min(1.0))
        at_noise = torch.zeros_like(searching)
        first = True
        while bool(searching.any()):  # one host sync per pass
            k = 1 if first else k_more
            first = False
            ar = torch.arange(Bsz, device=J0.device)
            rep = ar.repeat(k)
            pw = o.rho ** torch.arange(k, dtype=J0.dtype, device=J0.device)
            a = (alpha[None, :] * pw[:, None]).reshape(-1)  # (k B,): candidate j of row b
            pol = policy if k == 1 else policy.take(rep)
            x0 = self.x0 if k == 1 else self.x0.index_select(0, rep)
            cand = a >= o.alpha_min
            trial = forward_pass(
                problem,
                x0,
                lambda t, x, a=a, pol=pol: pol(t, x, a),
                self.layout,
                rtol=o.rtol,
                atol=o.atol,
                max_steps=o.max_steps,
                active=searching.repeat(k) & cand,  # the other rows ride along
            )
            dV = -(a - 0.5 * a * a) * bwd.eta.repeat(k)
            ok = (
                searching.repeat(k)
                & cand
                & trial.ok
                & torch.isfinite(trial.J)
                & (trial.J - J0.repeat(k) < o.beta * dV)
            ).reshape(k, Bsz)
            # per row the first (largest) candidate that passes
            any_ok = ok.any(0)
            j = torch.where(any_ok, ok.to(torch.int8).argmax(0), 0)
            tried = torch.where(any_ok, j + 1, (cand.reshape(k, Bsz)).sum(0))
            trials = trials + torch.where(searching, tried, 0)
            chosen = trial if k == 1 else trial.take(j * Bsz + ar)
            nom = merge_nominal(any_ok, chosen, nom)
            accepted = accepted | any_ok
            alpha = torch.where(any_ok, a.reshape(k, Bsz).gather(0, j[None])[0], alpha)
            searching = searching & ~any_ok
            if k == 1:
                at_noise = searching & noise
                searching = searching & ~noise
            alpha = torch.where(searching, alpha * o.rho**k, alpha)
            searching = searching & (alpha >= o.alpha_min)
        end = torch.where(
            running & ~accepted, int(Status.LINE_SEARCH_FAILED), int(Status.RUNNING)
        ).to(torch.int64)
        end = end.masked_fill(at_noise, int(Status.CONVERGED))
        st = replace(_state_from(nom, state.policy, trials), fresh=~accepted)
        return Advance(state=st, accept=accepted, step=torch.where(accepted, alpha, 0.0), end=end)


def _state_from(nom: Nominal, policy: Any = None, trials: Tensor | None = None) -> ContinuousState:
    return ContinuousState(
        trials=torch.zeros_like(nom.n_steps) if trials is None else trials,
        x=nom.x,
        u=nom.u,
        J=nom.J,
        nominal=nom,
        policy=policy,
        n_fwd=nom.n_steps,
        h_fwd_min=nom.h_min,
        h_fwd_max=nom.h_max,
    )


def _initial_control(u_init: Any, problem: ContinuousProblem, x0: Tensor):
    """``u_init`` as a control law ``(t (B, Q), x (B, Q, n)) -> (B, Q, m)``: None (zeros),
    a callable of ``t`` (returning ``(B, Q, m)``, ``(Q, m)`` broadcastable, or ``(B, Q)``
    for ``m = 1``), or a tensor of samples ``(K+1, m)`` / ``(B, K+1, m)`` on the uniform grid
    ``linspace(t0, tf, K+1)``, interpolated linearly."""
    Bsz, m = x0.shape[0], problem.control_dim
    if u_init is None:
        return lambda t, x: x.new_zeros(*x.shape[:-1], m)
    if callable(u_init) and not torch.is_tensor(u_init):

        def law(t, x):
            v = torch.as_tensor(u_init(t), dtype=x.dtype, device=x.device)
            if v.shape == t.shape and m == 1:
                v = v.unsqueeze(-1)
            return v.expand(*x.shape[:-1], m)

        return law
    if not torch.is_tensor(u_init):
        raise TypeError("u_init must be None, a callable of t, or a tensor (K+1, m) / (B, K+1, m)")
    v = u_init.to(dtype=x0.dtype, device=x0.device)
    if v.ndim == 2:
        v = v.unsqueeze(0)
    if v.ndim != 3 or v.shape[-1] != m or v.shape[0] not in (1, Bsz) or v.shape[1] < 2:
        raise ValueError(
            f"u_init must have shape (K+1, {m}) or ({Bsz}, K+1, {m}) with K >= 1, got "
            f"{tuple(u_init.shape)}"
        )
    v = v.expand(Bsz, *v.shape[1:])
    K = v.shape[1] - 1
    t0, tf = problem.t0, problem.tf

    def samples(t, x):
        s = ((t - t0) / (tf - t0) * K).clamp(0, K)
        i = s.floor().clamp_max(K - 1).long()
        w = (s - i).unsqueeze(-1)
        lo = v.gather(1, i.unsqueeze(-1).expand(*i.shape, m))
        hi = v.gather(1, (i + 1).unsqueeze(-1).expand(*i.shape, m))
        return (1 - w) * lo + w * hi

    return samples


class ContinuousILQR(Solver):
    """Continuous-time iLQR (Lieskovský, Bušek & Vyhlídal 2025) for a
    :class:`torchslq.ContinuousProblem`, with adaptive stiff integration (Rodas5P, a
    step size per batch element, dense output) in both passes.

    Args:
        max_iter: iteration limit.
        tol: stop when ``sqrt(int |Q_u(t)|^2 dt) <= tol`` (``Q_u = l_u + f_u' s``, the
            gradient of the cost with respect to the control function). Also
            ``converged``: an element whose predicted decrease ``-Delta V(1) = eta / 2``
            is at most ``rtol max(|J|, 1)`` and whose full step fails (15): below the
            accuracy of the integrated cost no line search can verify a decrease (the
            solution is as accurate as the integration allows; the paper's algorithm
            ends there with a failed line search).
        rtol, atol: the integrators' error tolerances (both passes).
        ddp: add the exact second-order dynamics terms ``s · f_zz`` to ``Q_xx, Q_ux,
            Q_uu`` (the full DDP variant of Section III-A).
        beta, rho, alpha_min: the line search on (15): Armijo constant, backtracking
            factor, smallest step (paper: 1e-4, 1/2, 2^-20).
        eps: the regularisation constant of (11) and (13) (eigenvalues of the cost
            Hessian floored at ``sqrt(eps)``, those of ``P(tf)`` at ``eps^(1/4)``);
            default the dtype's machine epsilon, as in the paper.
        cost_rtol: also stop when an accepted step changes the cost by at most
            ``cost_rtol |J|`` (0: off); stall_iters: the loop's round-off stall rule.
        max_steps: limit on each integration's steps.
        trials_per_pass: after a first forward pass with ``alpha = 1``, the line search
            integrates this many candidates ``alpha rho^j`` at once as extra rows (same
            accepted step as one at a time; for problems without per-element tensors,
            otherwise one at a time).
        progress: show a progress bar.

    ``solve(problem, x0, u_init=None, logger=None)`` returns a
    :class:`ContinuousILQRResult`.
    """

    name: ClassVar[str] = "continuous_ilqr"
    options_class: ClassVar[type] = ContinuousILQROptions

    def __init__(
        self,
        max_iter: int = 200,
        tol: float = 1e-6,
        rtol: float = 1e-6,
        atol: float = 1e-8,
        ddp: bool = False,
        *,
        beta: float = 1e-4,
        rho: float = 0.5,
        alpha_min: float = 2.0**-20,
        eps: float | None = None,
        cost_rtol: float = 0.0,
        stall_iters: int = 10,
        max_steps: int = 100_000,
        trials_per_pass: int = 4,
        progress: bool = True,
        **unknown: Any,
    ):
        super().__init__(**{k: v for k, v in locals().items() if k not in ("self", "__class__")})

    def settings(self) -> LoopSettings:
        o = self.options
        return LoopSettings(
            max_iter=o.max_iter,
            rtol=o.cost_rtol,
            stall_iters=o.stall_iters,
            compact=False,
            progress=o.progress,
            name=self.name,
        )

    def solve(
        self,
        problem: ContinuousProblem,
        x0: Tensor,
        u_init: Any = None,
        logger: Any = None,
    ) -> ContinuousILQRResult:
        """Solve ``problem`` from ``x0 (B, n)`` (or ``(n,)``).

        Args:
            u_init: the initial control: None (zero), a callable ``u_init(t)`` of the time
                ``t (B, Q)`` returning ``(B, Q, m)`` (or ``(B, Q)`` for one control), or
                samples ``(K+1, m)`` / ``(B, K+1, m)`` on ``linspace(t0, tf, K+1)``.
            logger: e.g. :class:`torchslq.TensorBoardLogger`; the per-iteration step
                counts and step-size ranges go under ``continuous/``.
        """
        from ...problem_continuous import ContinuousProblem

        if not isinstance(problem, ContinuousProblem):
            raise TypeError(
                f"problem must be a torchslq.ContinuousProblem, got {type(problem).__name__}"
            )
        check_logger(logger)
        o = self.options
        x0, unbatched = problem.check_x0(x0)
        layout = Layout(problem.state_dim, problem.control_dim, o.ddp)
        record = o.record(self.name)
        control = _initial_control(u_init, problem, x0)
        rule = ContinuousILQRRule(o, layout, x0)
        with torch.no_grad():
            nom = forward_pass(
                problem, x0, control, layout, rtol=o.rtol, atol=o.atol, max_steps=o.max_steps
            )
            out = iterate(
                rule,
                problem,
                _state_from(nom),
                self.settings(),
                logger=logger,
                options=loggable(record),
            )
            s = out.state
            policy = s.policy
            nom = s.nominal
            d, K = policy.terms(nom.t)
        hist = out.history
        result = ContinuousILQRResult(
            x=nom.x,
            u=nom.u,
            cost=nom.J,
            grad_norm=out.grad_norm,
            iterations=out.iterations,
            status=out.status,
            converged=out.status == Status.CONVERGED,
            K=-K,
            k=-d,
            history=hist,
            options=record,
            t=nom.t,
            mask=nom.mask,
            c=nom.c,
            policy=policy,
            expected_decrease=hist["expected_decrease"][:, -1]
            if "expected_decrease" in hist
            else None,
        )
        if logger is not None:
            _log_history(logger, hist)
            # the logger's trajectory figure draws u as controls of the steps between the
            # grid points: give it the values at the steps' starts
            logger.log_result(replace(result, u=result.u[:, :-1]), problem)
        return result.squeeze_batch() if unbatched else result


def _log_history(logger: Any, hist: dict[str, Tensor]) -> None:
    """The per-iteration step counts and step-size ranges as TensorBoard scalars
    ``continuous/<key>/{mean,min,max}`` (batch statistics)."""
    writer = getattr(logger, "writer", None)
    if writer is None:
        return
    for key in (*HISTORY_KEYS[:-1], "expected_decrease"):
        if key not in hist:
            continue
        v = hist[key].detach().to("cpu", torch.float64)
        for it in range(v.shape[1]):
            col = v[:, it]
            col = col[torch.isfinite(col)]
            if col.numel() == 0:
                continue
            writer.add_scalar(f"continuous/{key}/mean", col.mean().item(), it)
            writer.add_scalar(f"continuous/{key}/min", col.min().item(), it)
            writer.add_scalar(f"continuous/{key}/max", col.max().item(), it)
    writer.flush()
