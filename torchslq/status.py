"""Per-problem status codes shared by the LQ kernel and every solver.

Each batch element carries its own status as an integer code in a ``(B,)`` int64
tensor (so no host sync is needed to track it). :class:`Status` names the codes and
:func:`status_names` turns a status tensor into a list of strings for display.
"""

from __future__ import annotations

from enum import IntEnum

import torch

__all__ = ["Status", "status_names"]


class Status(IntEnum):
    """Outcome of one batch element.

    * ``CONVERGED``: the stopping test passed (for :func:`torchslq.lqr_solve`: solved,
      the LQ problem is solved exactly in one pass);
    * ``MAX_ITER``: the iteration limit came first;
    * ``LINE_SEARCH_FAILED``: no step decreased the cost (for ILQR/DDP: not even with
      the regularisation at ``mu_max``);
    * ``NON_FINITE``: a NaN or infinity in the element's data, trajectory, cost,
      derivatives (e.g. a NaN Jacobian) or direction, or an LQ recursion that overflowed
      (finite data such as ``A = 1e200``);
    * ``DIVERGED``: a constant-step method's iterate left the finite range;
    * ``NOT_POSITIVE_DEFINITE``: with finite data, the LQ subproblem has no minimum (a
      ``Quu`` not positive definite, for ILQR/DDP even with ``mu_max``);
    * ``STALLED``: accepted steps stopped changing the cost beyond rounding noise while
      the stopping test was unmet (the precision of the dtype is reached);
    * ``INFEASIBLE``: a constrained solve (``constraints=``) could not bring the element's
      largest constraint violation below ``constraint_tol``, even at the largest penalty;
      or the element's own control bounds are empty (``u_min > u_max``: not solved);
    * ``RUNNING`` is only seen inside a solver loop.

    One granularity rule holds at every entry point: a fault confined to some batch
    elements (a NaN in one row of ``x0`` or ``u_init``, a per-element weight that is not
    positive definite, one element's NaN or overflowing data in :func:`torchslq.lqr_solve`)
    gives those elements a status (``NON_FINITE``, ``NOT_POSITIVE_DEFINITE``), the other
    elements are solved exactly as without them, and a failed element gets a zero
    gradient. A fault in data shared by the whole batch, or a malformed argument (shape,
    dtype, type), is an error naming the argument.
    """

    RUNNING = -1
    CONVERGED = 0
    MAX_ITER = 1
    LINE_SEARCH_FAILED = 2
    NON_FINITE = 3
    DIVERGED = 4
    NOT_POSITIVE_DEFINITE = 5
    STALLED = 6  # accepted steps stopped changing the cost beyond rounding noise
    INFEASIBLE = 7  # constraint violation above constraint_tol at the largest penalty

    @property
    def label(self) -> str:
        return self.name.lower()


def status_names(status: torch.Tensor) -> list[str]:
    """Names (``"converged"``, ``"max_iter"``, ...) of a ``(B,)`` status tensor."""
    return [Status(int(s)).label for s in status.reshape(-1).tolist()]
