"""``torchslq.MPC``: a differentiable model-predictive-control layer (``nn.Module``).

The forward pass solves a batch of optimal control problems with any torchslq solver
(iLQR by default) *without* autograd; the backward pass differentiates the solution:

* ``backward="implicit"`` (default): through the KKT conditions at the solution with the
  exact Hessian of the Lagrangian (cost Hessians + costate-weighted dynamics second
  derivatives), one LQ solve on the shared kernel (:mod:`torchslq.mpc.implicit`);
* ``backward="implicit_gn"``: the same without the dynamics second derivatives (the
  Gauss-Newton Hessian, what mpc.pytorch differentiates): an approximation whenever
  the dynamics are nonlinear and the costates are not zero;
* ``backward="unroll"``: backpropagation through differentiable Newton iterations
  (:mod:`torchslq.mpc.unroll`), for comparison only.

Gradients reach ``x0`` and every tensor that requires grad inside the dynamics and the
cost (module parameters, weights, references, goals). Elements that did not converge
are never silently detached: their status is in the output and ``unconverged``
chooses ``"warn"`` (default: keep the implicit gradient at the returned point and
warn), ``"raise"`` or ``"zero"`` (their gradient is zero).
"""

from __future__ import annotations

import warnings
from typing import Any

import torch
from torch import Tensor, nn

from ..dynamics.rollout import rollout_closed_loop
from ..problem import Problem
from ..solvers.ilqr import ILQR
from ..solvers.newton import resolve_bounds
from ..solvers.result import SolverResult
from ..status import Status, status_names
from .constrained import constrained_implicit_solution
from .implicit import implicit_solution
from .unroll import unrolled_solve

__all__ = ["MPC", "MPCOutput"]

_BACKWARDS = ("implicit", "implicit_gn", "unroll")
_UNCONVERGED = ("warn", "raise", "zero")
# gradient-norm tolerance of the default solver by dtype (others: the float32 value)
DEFAULT_TOL = {torch.float64: 1e-8, torch.float32: 1e-4}


class MPCOutput(tuple):
    """``(x, u)`` of an :class:`MPC` solve; unpacks as a pair.

    Attributes:
        x: ``(B, T+1, n)`` states; u: ``(B, T, m)`` controls (differentiable).
        action: ``u[..., 0, :]``, the first control (what receding-horizon control applies).
        status: ``(B,)`` int64 :class:`torchslq.Status` of each solve.
        converged: ``(B,)`` bool.
        result: the solver's :class:`torchslq.SolverResult` (detached).
    """

    x: Tensor
    u: Tensor
    status: Tensor
    converged: Tensor
    result: SolverResult

    def __new__(cls, x: Tensor, u: Tensor, status: Tensor, result: SolverResult):
        out = super().__new__(cls, (x, u))
        out.x, out.u, out.status, out.result = x, u, status, result
        out.converged = status == Status.CONVERGED
        return out

    @property
    def action(self) -> Tensor:
        return self.u[..., 0, :]

    def __reduce__(self):  # pickling a tuple subclass with attributes
        return (MPCOutput, (self.x, self.u, self.status, self.result))


class MPC(nn.Module):
    """Differentiable MPC layer: ``forward(x0) -> (x, u)`` solved for the whole batch.

    Args:
        dynamics: a :class:`torchslq.Dynamics` (analytic or learned ``nn.Module``).
        cost: :class:`torchslq.QuadraticCost` or :class:`torchslq.Cost`.
        horizon: number of steps ``T``.
        solver: any torchslq solver (``ILQR``, ``DDP``, ``SLQ``; default
            ``ILQR(max_iter=200, tol=1e-8, progress=False)``, whose ``tol`` becomes
            ``1e-4`` for a float32 / lower-precision ``x0``: 1e-8 is below the gradient's
            round-off floor there, every element would end ``stalled`` and warn).
            Implicit gradients are exact only at a converged solution: keep ``tol``
            tight.
        u_min, u_max: control bounds (float, ``(m,)``, ``(T, m)`` or ``(B, T, m)``);
            need an :class:`torchslq.ILQR`/:class:`torchslq.DDP` solver. Bounds active
            at the solution are held fixed in the backward pass (zero sensitivity).
        backward: ``"implicit"`` | ``"implicit_gn"`` | ``"unroll"`` (module docstring).
        warm_start: ``True``/``"shift"``: the next solve of a batch of the same size
            starts from the previous solution shifted by one step (receding horizon,
            last control repeated), with the previous feedback gains applied to the
            deviation of the new state from the predicted trajectory; ``"reuse"``: from the previous solution as is (the
            same problems re-solved while their parameters are learned); ``False``: from
            zeros (or ``u_init``). :meth:`reset` forgets the stored solution.
        unconverged: what to do when gradients are needed and some element did not
            converge: ``"warn"``, ``"raise"`` or ``"zero"``.
        unroll_iters: iterations for ``backward="unroll"`` (default: the solver's
            ``max_iter``).
        compact: ``"auto"`` (default) or ``True``: the forward solve iterates only on
            the elements still running (the solver's ``compact=True``; same results, the
            batch does not wait for its slowest member; per-element problem data such
            as a goal per element follow the running subset); ``False``: never.
        constraints: optional :class:`torchslq.Constraints` (or a list): state, path and
            terminal constraints, solved by the solver's augmented-Lagrangian loop
            (needs :class:`torchslq.ILQR`/:class:`torchslq.DDP`). The backward pass holds
            the active set (equality rows, inequality rows with a positive multiplier,
            controls at a bound) and differentiates the KKT conditions of that
            equality-constrained problem (:mod:`torchslq.mpc.constrained`: one dense
            KKT solve per element); gradients also reach the constraints' own tensors.
            Not with ``backward="unroll"``.

    Example::

        mpc = MPC(discretize(Pendulum(), 0.05), QuadraticCost(Q, R, Qf, x_ref=goal), 40)
        x, u = mpc(x0)            # (B, 41, 2), (B, 40, 1)
        loss(x, u).backward()     # gradients w.r.t. x0, goal, pendulum parameters
        a = mpc.step(x_now)       # receding horizon: first action, warm started
    """

    def __init__(
        self,
        dynamics: nn.Module,
        cost: nn.Module,
        horizon: int,
        solver: Any = None,
        u_min: float | Tensor | None = None,
        u_max: float | Tensor | None = None,
        backward: str = "implicit",
        warm_start: bool | str = True,
        unconverged: str = "warn",
        unroll_iters: int | None = None,
        compact: bool | str = "auto",
        constraints: Any = None,
    ):
        super().__init__()
        self.problem = Problem(dynamics, cost, horizon)
        if backward not in _BACKWARDS:
            raise ValueError(f"backward must be one of {_BACKWARDS}, got {backward!r}")
        if not (isinstance(warm_start, bool) or warm_start in ("shift", "reuse")):
            # (0 and 1 compare equal to False and True but would not act as them)
            raise ValueError(
                f"warm_start must be True, False, 'shift' or 'reuse', got {warm_start!r}"
            )
        if unconverged not in _UNCONVERGED:
            raise ValueError(f"unconverged must be one of {_UNCONVERGED}, got {unconverged!r}")
        self._default_solver = solver is None
        if solver is None:
            solver = ILQR(max_iter=200, tol=DEFAULT_TOL[torch.float64], progress=False)
        if isinstance(solver, type) or not callable(getattr(solver, "solve", None)):
            raise TypeError(
                f"solver must be a solver object with a solve(problem, x0, u_init) method "
                f"(e.g. torchslq.ILQR()), got {solver!r}"
            )
        if (u_min is not None or u_max is not None) and not getattr(
            solver, "supports_bounds", False
        ):
            raise ValueError(
                "control bounds need an ILQR or DDP solver (one with supports_bounds), "
                f"got {type(solver).__name__}"
            )
        if not (isinstance(compact, bool) or compact == "auto"):
            raise ValueError(f"compact must be True, False or 'auto', got {compact!r}")
        if unroll_iters is not None and (
            not isinstance(unroll_iters, int) or isinstance(unroll_iters, bool) or unroll_iters < 1
        ):
            raise ValueError(f"unroll_iters must be a positive int, got {unroll_iters!r}")
        if u_min is not None or u_max is not None:
            # a new solver with the bounds: the one given is never changed
            solver = solver.with_options(u_min=u_min, u_max=u_max)
        if constraints is not None:
            if not getattr(solver, "supports_constraints", False):
                raise ValueError(
                    "constraints need an ILQR or DDP solver (one with supports_constraints), "
                    f"got {type(solver).__name__}"
                )
            if backward == "unroll":
                raise ValueError("constraints are differentiated implicitly: not with 'unroll'")
            solver = solver.with_options(constraints=constraints)
        # the constraints' tensors are the layer's (a ConstraintSet module, or None)
        self.constraints = getattr(solver.options, "constraints", None) if constraints else None
        self.solver = solver
        self._solvers: dict[tuple, Any] = {}  # per (tol, compact): the solver a forward uses
        self.compact = compact
        self.u_min, self.u_max = u_min, u_max
        self.backward_mode = backward
        self.warm_start = "shift" if warm_start is True else warm_start
        self.unconverged = unconverged
        self.unroll_iters = unroll_iters
        self._warm: dict[str, Tensor] | None = None
        self.last_result: SolverResult | None = None

    @property
    def dynamics(self) -> nn.Module:
        return self.problem.dynamics

    @property
    def cost(self) -> nn.Module:
        return self.problem.cost

    @property
    def horizon(self) -> int:
        return self.problem.horizon

    def reset(self) -> None:
        """Forget the stored warm start."""
        self._warm = None

    def _initial_guess(
        self, x0: Tensor, u_init: Tensor | None
    ) -> tuple[Tensor | None, Tensor | None]:
        """``(u, x)``: ``u_init``, else the stored warm start for this batch size: the
        previous controls, and for ``"shift"`` with the previous feedback gains applied to
        the deviation from the previous (shifted) trajectory, ``u = u_prev + K_prev (x -
        x_prev)`` rolled out from the new ``x0`` (so a state that drifted from the
        prediction, e.g. under model mismatch, starts from a corrected guess); ``x`` is
        that rollout's states (the solver then skips its own), else None."""
        if u_init is not None:
            return u_init.detach(), None
        w = self._warm
        if self.warm_start is False or w is None or w["u"].shape[0] != x0.shape[0]:
            return None, None
        if "K" not in w:
            return w["u"], None
        lo, hi = self._bounds(x0)
        with torch.no_grad():
            x, u = rollout_closed_loop(
                self.problem.transition,
                x0.detach(),
                w["x"],
                w["u"],
                w["K"],
                torch.zeros_like(w["u"]),
                x0.new_zeros(x0.shape[0]),
                lo,
                hi,
            )
        # a guess that blew up (a gain far from valid) falls back to the plain shift
        ok = torch.isfinite(u).flatten(1).all(1) & torch.isfinite(x).flatten(1).all(1)
        if bool(ok.all()):
            return u, x
        return torch.where(ok.view(-1, 1, 1), u, w["u"]), None

    def _store_warm_start(self, result: SolverResult) -> None:
        if self.warm_start is False:
            return
        u = result.u.detach()
        if self.warm_start == "reuse":
            self._warm = {"u": u}
            if result.multipliers is not None:
                self._warm["multipliers"] = result.multipliers
            return

        def shift(t: Tensor) -> Tensor:
            return torch.cat([t[:, 1:], t[:, -1:]], dim=1)

        warm = {"u": shift(u)}
        if result.multipliers is not None:
            # the constraint multipliers are warm started like the controls
            mult = result.multipliers
            warm["multipliers"] = {"stage": shift(mult["stage"]), "terminal": mult["terminal"]}
        K = getattr(result, "K", None)
        if K is not None and K.shape[:2] == u.shape[:2]:
            # an element without valid gains (e.g. a failed solve) gets the plain shift
            K = K.detach()
            valid = torch.isfinite(K).flatten(1).all(1).view(-1, 1, 1, 1)
            x = torch.nan_to_num(result.x.detach())
            warm.update(x=shift(x), K=shift(torch.where(valid, K, torch.zeros_like(K))))
        self._warm = warm

    def _needs_grad(self, x0: Tensor) -> bool:
        if not torch.is_grad_enabled():
            return False
        if x0.requires_grad:
            return True
        tensors = list(self.parameters()) + list(self.buffers())
        return any(t.requires_grad for t in tensors) or self._has_hidden_graph()

    def _has_hidden_graph(self) -> bool:
        # tensors held as plain attributes (not parameters/buffers) of the cost/dynamics
        for mod in self.modules():
            for v in vars(mod).values():
                if torch.is_tensor(v) and v.requires_grad:
                    return True
        return False

    def forward(self, x0: Tensor, u_init: Tensor | None = None) -> MPCOutput:
        """Solve from ``x0`` ``(B, n)`` (or ``(n,)``); returns :class:`MPCOutput` ``(x, u)``.

        Args:
            x0: initial states; may require grad.
            u_init: optional ``(B, T, m)`` / ``(T, m)`` initial guess (overrides the
                warm start).
        """
        if not torch.is_tensor(x0) or not x0.is_floating_point():
            raise TypeError("x0 must be a floating-point tensor of shape (B, n) or (n,)")
        n = self.problem.state_dim
        if x0.ndim not in (1, 2) or x0.shape[-1] != n:
            raise ValueError(f"x0 must have shape (B, {n}) or ({n},), got {tuple(x0.shape)}")
        unbatched = x0.ndim == 1
        x0b = x0.reshape(-1, n)
        Bsz = x0b.shape[0]
        # u_init, and x0's dtype and device against the problem's, checked before the
        # warm start uses them (the solver checks them again)
        self.problem.check_inputs(x0b.detach(), u_init)
        guess, guess_x = self._initial_guess(x0b, u_init)
        solver = self._solver_for(x0b.dtype, Bsz)
        kw = {"x_init": guess_x} if guess_x is not None and self._supports_compact() else {}
        w = self._warm
        if self.constraints is not None and u_init is None and w and "multipliers" in w:
            if w["u"].shape[0] == Bsz:
                kw["multipliers"] = w["multipliers"]
        with torch.no_grad():
            result = solver.solve(self.problem, x0b.detach(), guess, **kw)
        self.last_result = result
        self._store_warm_start(result)
        x, u, status = result.x, result.u, result.status
        if self._needs_grad(x0b):
            x, u, status = self._attach_gradients(x0b, result, guess)
        if unbatched:
            x, u, status = x[0], u[0], status[0]
            result = result.squeeze_batch()
        return MPCOutput(x, u, status, result)

    def _supports_compact(self) -> bool:
        return getattr(self.solver, "supports_x_init", False)

    def _solver_for(self, dtype: torch.dtype, batch_size: int) -> Any:
        """The solver of a forward pass: the layer's, with the default solver's tolerance
        for ``dtype`` and the ``compact`` choice for this problem (new solver objects,
        made once per combination; the layer's own solver is never changed)."""
        changes: dict[str, Any] = {}
        if self._default_solver:
            changes["tol"] = DEFAULT_TOL.get(dtype, DEFAULT_TOL[torch.float32])
        if self._supports_compact():
            changes["compact"] = self.compact in (True, "auto")
        if not changes:
            return self.solver
        key = tuple(sorted(changes.items()))
        if key not in self._solvers:
            self._solvers[key] = self.solver.with_options(**changes)
        return self._solvers[key]

    def step(self, x: Tensor) -> Tensor:
        """Receding-horizon control: solve from the current state(s) ``x`` and return the
        first action ``(B, m)`` (or ``(m,)``); the next call is warm started.

        An element whose solve failed (``non_finite``, ``not_positive_definite``,
        ``line_search_failed``, ``diverged``) still gets the action of its last iterate,
        which is no optimal control: a ``RuntimeWarning`` names how many and why
        (``last_result.status`` has them per element)."""
        out = self.forward(x)
        status = out.status.reshape(-1)
        ok = (status == Status.CONVERGED) | (status == Status.MAX_ITER)
        ok = ok | (status == Status.STALLED)
        if not bool(ok.all()):
            names = ", ".join(sorted(set(status_names(status[~ok]))))
            warnings.warn(
                f"MPC.step: {int((~ok).sum())} of {status.numel()} solves failed ({names}); "
                "their actions are not optimal controls",
                RuntimeWarning,
                stacklevel=2,
            )
        return out.action

    # ------------------------------------------------------------------ gradients
    def _attach_gradients(self, x0: Tensor, result: SolverResult, guess: Tensor | None):
        status = result.status.clone()
        bad = status != Status.CONVERGED
        if bool(bad.any()):
            names = sorted(set(status_names(status[bad])))
            msg = (
                f"MPC: {int(bad.sum())} of {status.numel()} solves did not converge "
                f"({', '.join(names)}); their implicit gradients are taken at a "
                "non-stationary point"
            )
            if self.unconverged == "raise":
                raise RuntimeError(msg + " (unconverged='raise')")
            if self.unconverged == "warn":
                warnings.warn(
                    msg + " (use unconverged='zero' or 'raise' to change this)",
                    RuntimeWarning,
                    stacklevel=3,
                )
        if self.backward_mode == "unroll":
            lo, hi = self._bounds(x0)
            iters = self.unroll_iters or getattr(self.solver.options, "max_iter", 100)
            u0 = result.u.new_zeros(result.u.shape) if guess is None else guess
            u0 = u0.expand(result.u.shape)
            # elements whose solve met NaN or infinity are not unrolled: a graph through
            # them would send 0 * NaN into x0's and the shared parameters' gradients
            # (they keep the solver's values, with a zero gradient)
            finite = torch.isfinite(result.x).flatten(1).all(1) & torch.isfinite(result.u).flatten(
                1
            ).all(1)
            idx = (finite & (status != Status.NON_FINITE)).nonzero().squeeze(1)
            Bsz = x0.shape[0]

            def take(t: Tensor | None) -> Tensor | None:
                return None if t is None or t.shape[0] != Bsz else t[idx]

            xs, us, _ = unrolled_solve(
                self.problem.take(idx, Bsz),
                x0[idx],
                u0[idx],
                max_iter=iters,
                tol=getattr(self.solver.options, "tol", 1e-8),
                u_min=take(lo),
                u_max=take(hi),
            )
            x = result.x.detach().index_copy(0, idx, xs)
            u = result.u.detach().index_copy(0, idx, us)
        else:
            active = None
            if result.active_bounds is not None:
                active = result.active_bounds != 0
            hessian = "exact" if self.backward_mode == "implicit" else "gn"
            if self.constraints is not None:
                stage_eq, terminal_eq = self.constraints.dims(
                    self.problem.state_dim, self.problem.control_dim, x0
                )
                x, u, lq_status = constrained_implicit_solution(
                    self.problem, self.constraints, x0, result.x, result.u,
                    result.multipliers, stage_eq, terminal_eq, hessian=hessian, active_u=active,
                )  # fmt: skip
            else:
                x, u, lq_status = implicit_solution(
                    self.problem, x0, result.x, result.u, hessian=hessian, active=active
                )
            not_pd = (lq_status == Status.NOT_POSITIVE_DEFINITE) & ~bad
            if bool(not_pd.any()):
                status = torch.where(not_pd, lq_status, status)
                msg = (
                    f"MPC: the Hessian of the Lagrangian is not positive definite for "
                    f"{int(not_pd.sum())} solves (not a strict local minimum; their "
                    "gradient is zero)"
                )
                if self.unconverged == "raise":
                    raise RuntimeError(msg)
                if self.unconverged == "warn":
                    warnings.warn(msg, RuntimeWarning, stacklevel=3)
                bad = bad | not_pd
        if self.unconverged == "zero" and bool(bad.any()):
            keep = (~bad).view(-1, 1, 1)
            x = torch.where(keep, x, x.detach())
            u = torch.where(keep, u, u.detach())
        return x, u, status

    def _bounds(self, x0: Tensor) -> tuple[Tensor | None, Tensor | None]:
        if self.u_min is None and self.u_max is None:
            return None, None
        return resolve_bounds(self.problem, x0, self.u_min, self.u_max)
