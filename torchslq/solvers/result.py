"""``SolverResult``: what every solver returns."""

from __future__ import annotations

import pickle
import struct
from dataclasses import MISSING, dataclass, field, fields
from os import PathLike
from pathlib import Path

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
        multipliers: for solves with ``constraints=``, ``{"stage": (B, T, p),
            "terminal": (B, q)}``: the Lagrange multipliers of the constraint rows (``>= 0``
            for inequality rows, zero where inactive); None otherwise.
        max_violation: for solves with ``constraints=``, ``(B,)`` the largest violation
            (``|c|`` of an equality row, ``max(c, 0)`` of an inequality row) at the
            returned trajectory; None otherwise.
        outer_iterations: for solves with ``constraints=``, ``(B,)`` the augmented
            Lagrangian's multiplier updates (``iterations`` then counts the inner
            iLQR/DDP iterations of all subproblems); None otherwise.

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
    multipliers: dict[str, Tensor] | None = None
    max_violation: Tensor | None = None
    outer_iterations: Tensor | None = None

    def to_dict(self) -> dict:
        """Every field by name (tensors as they are): what :meth:`save` writes."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def save(self, path: str | Path) -> None:
        """Write the result to ``path`` (``torch.save`` of :meth:`to_dict` and the result's
        class); :meth:`load` reads it back with every field and status."""
        if not isinstance(path, (str, PathLike)) and not callable(getattr(path, "write", None)):
            raise TypeError(
                f"path must be a str, a path or a writable file, got {type(path).__name__}"
            )
        if isinstance(path, (str, PathLike)) and Path(path).is_dir():
            raise IsADirectoryError(f"path {str(path)!r} is a directory; give a file name")
        torch.save({"class": type(self).__name__, "fields": self.to_dict()}, path)

    @staticmethod
    def load(path: str | Path, map_location: str | torch.device | None = None) -> SolverResult:
        """The result saved at ``path`` by :meth:`save` (of its class: a
        :class:`SolverResult` or a subclass such as :class:`torchslq.GoPRONTOResult`),
        loaded with ``weights_only=True`` (tensors and plain containers only)."""
        if not isinstance(path, (str, PathLike)) and not callable(getattr(path, "read", None)):
            raise TypeError(
                f"path must be a str, a path or a readable file, got {type(path).__name__}"
            )
        if isinstance(map_location, str):
            try:
                torch.device(map_location)
            except RuntimeError as err:
                raise ValueError(f"map_location {map_location!r} is not a device: {err}") from err
        try:
            data = torch.load(path, map_location=map_location, weights_only=True)
        except (
            pickle.UnpicklingError, EOFError, KeyError, IndexError, ValueError, struct.error,
            RuntimeError,
        ) as err:  # fmt: skip
            # torch.load reads a text or corrupt file as a pickle (UnpicklingError,
            # KeyError, struct.error, ...) or a broken zip archive (the PytorchStreamReader)
            if isinstance(err, RuntimeError) and "PytorchStreamReader" not in str(err):
                raise
            raise ValueError(
                f"{path!s} is not a file written by SolverResult.save ({type(err).__name__}: "
                f"{str(err)[:200]})"
            ) from err
        if not isinstance(data, dict) or "class" not in data or "fields" not in data:
            raise ValueError(f"{path!s} is not a file written by SolverResult.save")
        kinds = {k.__name__: k for k in _result_classes()}
        if data["class"] not in kinds:
            raise ValueError(f"{path!s} holds an unknown result class {data['class']!r}")
        cls, given = kinds[data["class"]], data["fields"]
        names = {f.name for f in fields(cls)}
        required = {
            f.name for f in fields(cls) if f.default is MISSING and f.default_factory is MISSING
        }
        if not isinstance(given, dict) or not required <= set(given) or not set(given) <= names:
            have = sorted(given) if isinstance(given, dict) else type(given).__name__
            raise ValueError(
                f"{path!s} is not a file written by SolverResult.save: its fields {have} do "
                f"not match {cls.__name__}'s"
            )
        return cls(**given)

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
            multipliers=None
            if self.multipliers is None
            else {k: sq(v) for k, v in self.multipliers.items()},
            max_violation=None if self.max_violation is None else sq(self.max_violation),
            outer_iterations=None if self.outer_iterations is None else sq(self.outer_iterations),
        )


def _result_classes() -> list[type]:
    """SolverResult and its subclasses (e.g. GoPRONTOResult), for :meth:`SolverResult.load`."""
    out, todo = [], [SolverResult]
    while todo:
        k = todo.pop()
        out.append(k)
        todo.extend(k.__subclasses__())
    return out
