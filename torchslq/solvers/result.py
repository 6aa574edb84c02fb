"""``SolverResult``: what every solver returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..status import Status, status_names

__all__ = ["SolverResult"]


@dataclass
class SolverResult:
    """Solution of a batch of optimal control problems (all tensors on the solve's device).

    Attributes:
        x: states ``(B, T+1, n)``; u: controls ``(B, T, m)``.
        cost: final cost ``(B,)``.
        grad_norm: ``(B,)`` Euclidean norm of ``dJ/dU`` at the returned ``u`` (costate
            pass, Sideris & Bobrow eqs. 8-11).
        iterations: ``(B,)`` accepted iterations per element.
        status: ``(B,)`` int64 :class:`torchslq.Status` codes; :meth:`status_names` gives
            strings.
        converged: ``(B,)`` bool, ``status == CONVERGED``.
        K: ``(B, T, m, n)`` feedback gains of the last LQ step; k: ``(B, T, m)`` its
            feedforward terms. (iLQR/DDP skip the pass at a point where the gradient
            test stops the element, so there they are the gains of its last step taken,
            at the point before the final one; the same in a batch as alone.)
        history: per-iteration tensors of shape ``(B, iters+1)``: ``"cost"``,
            ``"grad_norm"``, ``"step"`` (step size accepted at that iteration, 0 for
            iteration 0 and for finished elements) and ``"time"`` (``(iters+1,)``
            seconds since the start).
        options: the solver's options, for the record.
        active_bounds: for control-limited solves (iLQR/DDP with ``u_min``/``u_max``),
            ``(B, T, m)`` int8: ``-1`` where ``u`` is at its lower bound, ``+1`` at its
            upper bound, ``0`` elsewhere; None for unconstrained solves.

    Results of an unbatched solve (``x0`` of shape ``(n,)``) drop the batch dim.
    """

    x: Tensor
    u: Tensor
    cost: Tensor
    grad_norm: Tensor
    iterations: Tensor
    status: Tensor
    converged: Tensor
    K: Tensor
    k: Tensor
    history: dict[str, Tensor] = field(default_factory=dict)
    options: dict = field(default_factory=dict)
    active_bounds: Tensor | None = None

    def status_names(self) -> list[str]:
        return status_names(self.status)

    def summary(self) -> str:
        """A few lines: batch size, status counts, cost and iteration statistics."""
        names = status_names(self.status)
        counts = {s.label: names.count(s.label) for s in Status if names.count(s.label)}
        cost = self.cost.reshape(-1).double()
        it = self.iterations.reshape(-1).double()
        if cost.numel() == 0:
            return "problems: 0"
        lines = [
            f"problems: {cost.numel()}  status: "
            + ", ".join(f"{k} {v}" for k, v in counts.items()),
            f"cost: mean {cost.mean().item():.6g}  min {cost.min().item():.6g}  "
            f"max {cost.max().item():.6g}",
            f"iterations: mean {it.mean().item():.1f}  max {int(it.max().item())}  "
            f"grad_norm max {self.grad_norm.reshape(-1).max().item():.3g}",
        ]
        return "\n".join(lines)

    def squeeze_batch(self) -> SolverResult:
        """Drop a batch dim of size 1 (used for unbatched inputs)."""

        def sq(t: Tensor) -> Tensor:
            return t[0] if torch.is_tensor(t) and t.ndim >= 1 else t

        hist = {k: (v if k == "time" else v[0]) for k, v in self.history.items()}
        return SolverResult(
            x=sq(self.x),
            u=sq(self.u),
            cost=sq(self.cost),
            grad_norm=sq(self.grad_norm),
            iterations=sq(self.iterations),
            status=sq(self.status),
            converged=sq(self.converged),
            K=sq(self.K),
            k=sq(self.k),
            history=hist,
            options=self.options,
            active_bounds=None if self.active_bounds is None else sq(self.active_bounds),
        )
