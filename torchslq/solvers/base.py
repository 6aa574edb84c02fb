"""The front doors' common base: immutable options, capabilities, the descent solve.

A solver object is an immutable set of options (:attr:`Solver.options`, a frozen
dataclass) with a ``solve`` method; per-solve state lives in the loop
(:func:`~torchslq.solvers.core.iterate`), so one object can serve several threads at
once. Capabilities are attributes (``supports_bounds``, ``supports_x_init``) that
callers such as :class:`torchslq.MPC` read instead of testing classes.
"""

from __future__ import annotations

from dataclasses import fields, replace
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from ..costs.quadratic import compiled_cost_evaluation
from ..dynamics.rollout import rollout
from ..problem import check_problem
from ..status import Status
from .core import LoopSettings, check_logger, iterate
from .descent import DescentState
from .options import loggable
from .result import SolverResult

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["DescentSolver", "Solver", "checked_x_init"]


def checked_x_init(x_init: Tensor, x0: Tensor, T: int) -> Tensor:
    """``x_init`` as ``(B, T+1, n)``, checked against ``x0 (B, n)`` (shape, first state)."""
    if not torch.is_tensor(x_init):
        raise TypeError("x_init must be a tensor of shape (B, T+1, n) or (T+1, n)")
    Bsz, n = x0.shape
    x = x_init.reshape(-1, *x_init.shape[-2:]) if x_init.ndim in (2, 3) else x_init
    if x.ndim != 3 or x.shape[1:] != (T + 1, n) or x.shape[0] not in (1, Bsz):
        raise ValueError(
            f"x_init must have shape ({Bsz}, {T + 1}, {n}) or ({T + 1}, {n}), "
            f"got {tuple(x_init.shape)}"
        )
    x = x.to(dtype=x0.dtype, device=x0.device).expand(Bsz, T + 1, n)
    if not bool(((x[:, 0] == x0) | (x[:, 0].isnan() & x0.isnan())).all()):
        raise ValueError("x_init[:, 0] must equal x0 (x_init is the rollout of u_init from x0)")
    return x.detach().clone()


class Solver:
    """Base of the public solvers: an immutable options object and capabilities.

    Attributes:
        name: the solver's name in results and logs.
        options: the frozen options dataclass (every option, recorded in
            ``result.options`` and the TensorBoard hparams).
        supports_bounds: whether ``u_min``/``u_max`` are honoured as hard box
            constraints (:class:`torchslq.ILQR`, :class:`torchslq.DDP`).
        supports_constraints: whether ``constraints=`` (:class:`torchslq.Constraints`)
            are honoured (:class:`torchslq.ILQR`, :class:`torchslq.DDP`).
        supports_x_init: whether ``solve`` accepts the rollout of ``u_init`` as
            ``x_init`` (and ``compact=True``).
    """

    name: ClassVar[str] = "solver"
    options_class: ClassVar[type]
    supports_bounds: ClassVar[bool] = False
    supports_constraints: ClassVar[bool] = False
    supports_x_init: ClassVar[bool] = False

    options: Any

    def __init__(self, unknown: dict[str, Any] | None = None, **options: Any) -> None:
        if unknown:
            valid = ", ".join(f.name for f in fields(self.options_class))
            raise TypeError(
                f"unknown option(s) for {type(self).__name__}: {sorted(unknown)}; "
                f"its options are: {valid}"
            )
        object.__setattr__(self, "options", self.options_class(**options))

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(
            f"{type(self).__name__} is immutable; use solver.with_options({name}=...) "
            "for a solver with other options"
        )

    def __getattr__(self, name: str) -> Any:
        # options read as attributes (solver.mu_init), for convenience
        if name != "options" and "options" in self.__dict__:
            opts = self.__dict__["options"]
            if name in {f.name for f in fields(opts)}:
                return getattr(opts, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def with_options(self, **changes: Any) -> Solver:
        """A new solver of the same kind with some options changed."""
        new = object.__new__(type(self))
        object.__setattr__(new, "options", replace(self.options, **changes))
        return new

    def __repr__(self) -> str:
        opts = ", ".join(
            f"{f.name}={getattr(self.options, f.name)!r}" for f in fields(self.options)
        )
        return f"{type(self).__name__}({opts})"

    def settings(self) -> LoopSettings:
        o = self.options
        return LoopSettings(
            max_iter=o.max_iter,
            rtol=getattr(o, "rtol", 0.0),
            stall_iters=o.stall_iters,
            compact=getattr(o, "compact", False),
            progress=o.progress,
            name=self.name,
        )


class DescentSolver(Solver):
    """A solver whose iteration is a :class:`~torchslq.solvers.descent.DescentRule`
    (SLQ, ILQR, DDP, GradientMethod): one ``solve`` for all of them."""

    supports_x_init: ClassVar[bool] = True

    def rule(self):  # pragma: no cover - every front door defines it
        raise NotImplementedError

    def initial_state(
        self, problem: Problem, x0: Tensor, u: Tensor, x: Tensor, **extra: Any
    ) -> DescentState:
        """The state at the start (the rule's per-element memory at its initial value;
        ``extra`` from :meth:`prepare`)."""
        Bsz, T, n, m = x0.shape[0], problem.horizon, problem.state_dim, problem.control_dim
        return DescentState(
            x=x, u=u, J=problem.cost(x, u), K=x0.new_zeros(Bsz, T, m, n), k=x0.new_zeros(Bsz, T, m)
        )

    def direction(self, problem: Problem, x: Tensor, u: Tensor) -> dict[str, Tensor]:
        """The direction at ``(x (B,T+1,n), u (B,T,m))`` as the first iteration of a solve
        computes it: a dict with ``du``, ``dx``, ``K``, ``k``, ``grad``, ``slope``,
        ``failed`` (and ``curvature`` where the direction has one)."""
        state = self.initial_state(problem, x[:, 0], u, x)
        running = torch.ones(x.shape[0], dtype=torch.bool, device=x.device)
        d, _ = self.rule().direction(problem, state, running, 0)
        return d

    def prepare(
        self, problem: Problem, x0: Tensor, u: Tensor, x_init: Tensor | None
    ) -> tuple[Tensor, Tensor | None, dict]:
        """Controls and ``x_init`` to start from, and extra state (bounds); identity here."""
        return u, x_init, {}

    def solve(
        self,
        problem: Problem,
        x0: Tensor,
        u_init: Tensor | None = None,
        logger: Any = None,
        *,
        x_init: Tensor | None = None,
    ) -> SolverResult:
        """Solve ``problem`` from initial states ``x0 (B, n)`` (or ``(n,)``).

        Args:
            u_init: initial controls ``(B, T, m)`` or ``(T, m)``; zeros by default.
            logger: e.g. :class:`torchslq.TensorBoardLogger`; None costs nothing.
            x_init: optional states ``(B, T+1, n)`` (or ``(T+1, n)``) of ``u_init`` from
                ``x0`` (``x_{t+1} = f(x_t, u_t)``), when the caller has them already (e.g.
                a closed-loop warm start): the initial rollout is then skipped. Only its
                shape and first state are checked.

        Returns:
            :class:`torchslq.SolverResult`.
        """
        o = self.options
        check_problem(problem)
        check_logger(logger)
        x0, u, unbatched = problem.check_inputs(x0, u_init)
        if x_init is not None:
            x_init = checked_x_init(x_init, x0, problem.horizon)
        u, x_init, extra = self.prepare(problem, x0, u, x_init)
        record = o.record(self.name)
        from ..dynamics.codegen import hooks_pinned

        # every cost of the loop is evaluated without autograd, so quadratic costs may use
        # the CPU kernel (whose last bits differ from the torch path's) throughout; the
        # model's generated code is looked up once per solve
        with torch.no_grad(), compiled_cost_evaluation(), hooks_pinned():
            x = rollout(problem.transition, x0, u) if x_init is None else x_init
            state = self.initial_state(problem, x0, u, x, **extra)
            out = iterate(
                self.rule(),
                problem,
                state,
                self.settings(),
                logger=logger,
                options=loggable(record),
                start_status=extra.get("start_status"),
            )
            s = self.final_state(problem, out.state)
        result = SolverResult(
            x=s.x,
            u=s.u,
            cost=s.J,
            grad_norm=out.grad_norm,
            iterations=out.iterations,
            status=out.status,
            converged=out.status == Status.CONVERGED,
            K=s.K,
            k=s.k,
            history=out.history,
            options=record,
        )
        result = self.finish(result, extra)
        if logger is not None:
            logger.log_result(result, problem)
        return result.squeeze_batch() if unbatched else result

    def final_state(self, problem: Problem, state: DescentState) -> DescentState:
        """The state the result is made of (the loop's last state here)."""
        return state

    def finish(self, result: SolverResult, extra: dict) -> SolverResult:
        """The result with solver-specific fields (e.g. ``active_bounds``)."""
        return result
