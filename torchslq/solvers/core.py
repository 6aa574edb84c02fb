"""The one iteration loop that every solver runs on.

A solver is an *iteration rule* (an :class:`IterationRule`: a descent direction
combined with a globalisation, see :mod:`torchslq.solvers.descent` and
:mod:`torchslq.solvers.gopronto`) run by :func:`iterate`, which owns everything the
solvers share:

* per-element status (:class:`torchslq.Status`) and the masks that freeze a finished or
  failed element without affecting the others;
* compaction (``compact=True``: each iteration runs on the running elements only);
* the stopping tests common to all rules (the rule's own test, the relative cost change
  ``rtol``, the round-off stall rule :func:`~torchslq.solvers.stopping.stall_update`);
* the per-iteration history, the TensorBoard logger and the progress bar;
* the iteration count and the one host synchronisation per iteration that ends the solve.

Per-solve state lives in a typed :class:`ElementState` dataclass created by the rule for
each solve and passed explicitly through the loop, never on the solver object: one
solver object can serve several threads at once.

One iteration on the working set (all elements, or the running ones)::

    state, m = rule.measure(problem, state, running, it)   # direction / gradient at the iterate
    status   <- converged where m.done, m.fail where not     # per element
    history, logging; stop when no element runs (host sync)
    adv      = rule.advance(problem, state, m, running)    # globalisation: the step
    status   <- adv.end, rtol, stall;  iterations += adv.accept
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

import torch
from torch import Tensor

from ..status import Status
from .progress import progress_bar
from .stopping import stall_update

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = [
    "Advance",
    "ElementState",
    "IterationRule",
    "LoopOutcome",
    "LoopSettings",
    "Measure",
    "iterate",
    "shared",
]


def shared(default: Any = None) -> Any:
    """A dataclass field of an :class:`ElementState` that is not per element (it is not
    narrowed by compaction): e.g. a bound shared by the whole batch."""
    return field(default=default, metadata={"shared": True})


def _take(t: Tensor, idx: Tensor | None) -> Tensor:
    return t if idx is None else t.index_select(0, idx)


def _put(full: Tensor, idx: Tensor | None, part: Tensor) -> Tensor:
    return part if idx is None else full.index_copy(0, idx, part)


S = TypeVar("S", bound="ElementState")


@dataclass(frozen=True)
class ElementState:
    """Per-solve state of an iteration rule, batch-first.

    Every field holds a tensor with a leading batch dimension (or None), except those
    declared with :func:`shared`. The loop narrows the state to the working set with
    :meth:`take` and writes it back with :meth:`put`; a rule returns updated copies
    (``dataclasses.replace``), never mutates. Every state has the current trajectory
    ``x (B, T+1, n)``, ``u (B, T, m)`` and the objective ``J (B,)`` the rule decreases.
    """

    x: Tensor
    u: Tensor
    J: Tensor

    def updated(self: S, **changes) -> S:
        """A copy with ``changes`` (field name -> value): ``dataclasses.replace`` without
        its pass through ``__init__`` (about 1 against 8 us for a dozen fields; a rule
        makes several per iteration, which counts at B = 1). States validate nothing on
        construction; a subclass with a ``__post_init__`` gets ``replace`` itself."""
        if hasattr(self, "__post_init__"):
            return replace(self, **changes)
        new = object.__new__(type(self))
        values = new.__dict__
        values.update(self.__dict__)
        values.update(changes)
        return new

    def _batched(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if not f.metadata.get("shared") and torch.is_tensor(v):
                yield f.name, v

    def take(self: S, idx: Tensor | None) -> S:
        """The state of the elements ``idx`` (all of it for None)."""
        if idx is None:
            return self
        return replace(self, **{k: v.index_select(0, idx) for k, v in self._batched()})

    def put(self: S, idx: Tensor | None, part: S) -> S:
        """This state with the elements ``idx`` replaced by ``part`` (``part`` for None);
        the fields that are not per element (:func:`shared`) are ``part``'s, the latest
        (a rule may update them, e.g. an accumulated time)."""
        if idx is None:
            return part
        return replace(
            part, **{k: v.index_copy(0, idx, getattr(part, k)) for k, v in self._batched()}
        )


@dataclass
class Measure:
    """What a rule reports at the current iterate (working set of ``b`` elements).

    Attributes:
        grad_norm: ``(b,)`` the stationarity measure (norm of the gradient the rule uses).
        done: ``(b,)`` bool, the rule's stopping test passes (status ``converged``).
        fail: ``(b,)`` int64 status that ends an element not ``done`` (``RUNNING`` where
            none): e.g. ``not_positive_definite`` for a failed LQ solve.
        cost: ``(b,)`` the problem's cost, as recorded in the history (it differs from
            the state's objective ``J`` when a barrier is added).
        history: extra per-element quantities recorded per iteration (name -> ``(b,)``).
        direction: whatever :meth:`IterationRule.advance` needs of this measurement.
    """

    grad_norm: Tensor
    done: Tensor
    fail: Tensor
    cost: Tensor
    history: dict[str, Tensor] = field(default_factory=dict)
    direction: Any = None


@dataclass
class Advance:
    """The outcome of one step of a rule on the working set.

    Attributes:
        state: the new state (moved where ``accept``).
        accept: ``(b,)`` bool, the element moved.
        step: ``(b,)`` the accepted step size (0 where not accepted).
        end: ``(b,)`` int64 status that ends an element (``RUNNING`` where it goes on),
            e.g. ``line_search_failed``.
    """

    state: ElementState
    accept: Tensor
    step: Tensor
    end: Tensor


class IterationRule(Protocol):
    """A descent direction combined with a globalisation, run by :func:`iterate`."""

    def measure(
        self, problem: Problem, state: ElementState, running: Tensor, it: int
    ) -> tuple[ElementState, Measure]: ...

    def advance(
        self, problem: Problem, state: ElementState, m: Measure, running: Tensor
    ) -> Advance: ...


@dataclass(frozen=True)
class LoopSettings:
    """The loop's own options (a solver's options hold them under the same names)."""

    max_iter: int = 100
    rtol: float = 0.0
    stall_iters: int = 10
    compact: bool = False
    progress: bool = True
    name: str = "solver"


@dataclass
class LoopOutcome:
    """What :func:`iterate` returns: the final state and the loop's per-element record."""

    state: ElementState
    status: Tensor
    iterations: Tensor
    grad_norm: Tensor
    history: dict[str, Tensor]


def _history_row(hist: dict[str, list], key: str, value: Tensor) -> None:
    hist.setdefault(key, []).append(value)


LOGGER_METHODS = ("log_options", "log_iteration", "log_result")


def check_logger(logger: Any) -> None:
    """TypeError unless ``logger`` is None or has the logger methods (``log_options``,
    ``log_iteration``, ``log_result``, as :class:`torchslq.TensorBoardLogger`)."""
    if logger is None:
        return
    missing = [k for k in LOGGER_METHODS if not callable(getattr(logger, k, None))]
    if missing:
        raise TypeError(
            f"logger must be None or a logger such as torchslq.TensorBoardLogger (with "
            f"{', '.join(LOGGER_METHODS)}); got {type(logger).__name__} without "
            f"{', '.join(missing)}"
        )


def iterate(
    rule: IterationRule,
    problem: Problem,
    state: ElementState,
    settings: LoopSettings,
    *,
    logger: Any = None,
    options: dict[str, Any] | None = None,
    start_status: Tensor | None = None,
) -> LoopOutcome:
    """Run ``rule`` from ``state`` until every element has a final status.

    Args:
        rule: the iteration rule (measure / advance).
        problem: the problem (passed through to the rule).
        state: the initial state of the whole batch (``B`` elements). Elements whose
            initial trajectory or objective is not finite start as ``non_finite``.
        settings: iteration limit, ``rtol`` (0: off), ``stall_iters`` (0: off),
            ``compact``, ``progress``.
        logger: e.g. :class:`torchslq.TensorBoardLogger` (``log_options`` with
            ``options``, then ``log_iteration`` per iteration); None costs nothing.
        start_status: optional ``(B,)`` status codes: elements with a code other than
            ``RUNNING`` (e.g. invalid bounds of their own) start with it, not solved.

    Returns:
        :class:`LoopOutcome`; its ``history`` has ``(B, iters+1)`` tensors ``cost``,
        ``grad_norm``, ``step`` and the rule's extra keys, and ``time`` ``(iters+1,)``.
        Elements still running after ``max_iter`` iterations end as ``max_iter``.
    """
    s = settings
    Bsz = state.J.shape[0]
    dev = state.J.device
    finite0 = torch.isfinite(state.J) & torch.isfinite(state.x).flatten(1).all(1)
    status = torch.full((Bsz,), int(Status.RUNNING), dtype=torch.int64, device=dev)
    status = status.masked_fill(~finite0, int(Status.NON_FINITE))
    # elements whose problem data are invalid (e.g. a per-element R that is not positive
    # definite) are not solved; the others are (the granularity rule of Status)
    faults = getattr(problem, "element_faults", None)
    faults = faults(Bsz) if callable(faults) else None
    if faults is not None:
        status = torch.where((faults != Status.RUNNING) & finite0, faults, status)
    if start_status is not None:
        status = torch.where(start_status != Status.RUNNING, start_status, status)
    iterations = torch.zeros(Bsz, dtype=torch.int64, device=dev)
    stalls = torch.zeros_like(iterations)  # consecutive noise-level accepted steps
    stall_grad = torch.zeros_like(state.J)  # gradient norm when that run started
    step = torch.zeros_like(state.J)
    grad_norm = torch.full_like(state.J, float("nan"))
    cost = state.J
    extra: dict[str, Tensor] = {}
    hist: dict[str, list] = {}
    times: list[float] = []
    if logger is not None:
        logger.log_options(s.name, options or {})
    t_start = time.perf_counter()
    bar = progress_bar(s.max_iter, enabled=s.progress, desc=s.name)
    # the working set's state and problem, kept from one iteration to the next while
    # the set is the same (most iterations: an element leaves it once, when it ends);
    # the whole batch's state is written back only when the set shrinks and at the end
    sub, prob, work_idx = state, problem, None
    for it in range(s.max_iter + 1):
        running = status == Status.RUNNING
        # working set: every element, or (compact) only the running ones
        idx = running.nonzero().squeeze(1) if s.compact else None  # one host sync
        if idx is not None and idx.numel() == Bsz:
            idx = None
        size = Bsz if idx is None else idx.numel()
        # an element that ends never runs again: a set of another size is a smaller one
        if size != (Bsz if work_idx is None else work_idx.numel()):
            state = state.put(work_idx, sub)
            sub, work_idx = state.take(idx), idx
            # per-element problem data (a goal per element, (B, 1) masses) follow it
            prob = problem if idx is None else problem.take(idx, Bsz)
        if size == 0:
            # no element runs from the start (all non-finite): record the start and stop
            for key, value in (("cost", cost), ("grad_norm", grad_norm), ("step", step)):
                _history_row(hist, key, value)
            times.append(time.perf_counter() - t_start)
            break
        run = _take(running, idx)
        sub, m = rule.measure(prob, sub, run, it)
        grad_norm = _put(grad_norm, idx, torch.where(run, m.grad_norm, _take(grad_norm, idx)))
        # the rule reports its cost and extra quantities for its whole working set
        cost = _put(cost, idx, m.cost)
        for k, v in m.history.items():
            extra[k] = _put(extra.get(k, torch.zeros(Bsz, dtype=v.dtype, device=dev)), idx, v)
        st = _take(status, idx)
        st = st.masked_fill(run & m.done, int(Status.CONVERGED))
        st = torch.where(run & ~m.done & (m.fail != int(Status.RUNNING)), m.fail, st)
        status = _put(status, idx, st)
        run = st == Status.RUNNING
        _history_row(hist, "cost", cost)
        _history_row(hist, "grad_norm", grad_norm)
        _history_row(hist, "step", step)
        for k, v in extra.items():
            _history_row(hist, k, v)
        times.append(time.perf_counter() - t_start)
        if logger is not None:
            logger.log_iteration(
                it, cost=cost, grad_norm=grad_norm, step=step, status=status, wall_time=times[-1]
            )
        n_running = int(run.sum())  # the host sync that ends the solve
        if n_running == 0 or it == s.max_iter:
            state = state.put(idx, sub)
            break
        J_old = sub.J
        adv = rule.advance(prob, sub, m, run)
        accept = run & adv.accept
        st = torch.where(run & (adv.end != int(Status.RUNNING)), adv.end, st)
        J_new = adv.state.J
        if s.rtol > 0:  # relative cost change after an accepted step
            small = accept & ((J_old - J_new).abs() <= s.rtol * J_old.abs())
            st = st.masked_fill(small & (st == Status.RUNNING), int(Status.CONVERGED))
        if s.stall_iters > 0:
            stalled, ns, g_ref = stall_update(
                _take(stalls, idx), _take(stall_grad, idx), accept, J_old, J_new,
                m.grad_norm, s.stall_iters,
            )  # fmt: skip
            st = st.masked_fill((st == Status.RUNNING) & stalled, int(Status.STALLED))
            stalls, stall_grad = _put(stalls, idx, ns), _put(stall_grad, idx, g_ref)
        status = _put(status, idx, st)
        step = _put(torch.zeros_like(step), idx, torch.where(accept, adv.step, 0.0))
        iterations = _put(iterations, idx, _take(iterations, idx) + accept.to(torch.int64))
        sub = adv.state
        if s.progress:  # (a hidden bar still formats its postfix: ~20 us an iteration)
            bar.update(1)
            bar.set_postfix(running=n_running, refresh=False)
    bar.close()
    status = status.masked_fill(status == Status.RUNNING, int(Status.MAX_ITER))
    history = {k: torch.stack(v, dim=1) for k, v in hist.items()}
    history["time"] = torch.tensor(times, dtype=torch.float64)
    return LoopOutcome(
        state=state, status=status, iterations=iterations, grad_norm=grad_norm, history=history
    )
