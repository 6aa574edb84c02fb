"""The backends of torchslq's inner loops, behind one interface (private).

Every dispatch-bound loop of the library (the Riccati pass with its box QPs and
restarts, the LQ rollout and adjoint solve, the closed-loop rollout and its feedback
step, the costate recursion, a quadratic cost's value, an RK4 stage's congruence) has a
torch form, written with batched torch ops where the algorithm lives (``torchslq.lq``,
``torchslq.dynamics.rollout``, ...), and a compiled CPU form here: numba kernels over
batch and time (:mod:`._numba_kernels`, :mod:`._numba_cost`; the RK4 derivative
kernels of a model sit beside it in :mod:`torchslq.dynamics._numba_rk4`), run through
the wrappers of :mod:`.dispatch`.

The contract: the two forms have the same meaning (same equations, outputs, statuses,
failure flags and, for the Riccati pass, the same restarts of failed elements with a
larger regularisation, :class:`torchslq.lq.Restarts`); results differ only by
rounding. Which one runs is decided per call by :func:`can_use_compiled` (CPU, float32
or float64, no autograd graph needed, no ``torch.func`` transform or ``torch.compile``
tracing, numba importable and enabled); :func:`set_compiled` (public as
``torchslq.lq.set_compiled``) switches the compiled form off process-wide, e.g. to run
the same test on both (``tests/conftest.py``'s ``backend`` fixture).
"""

from .dispatch import (
    PIECE_NDIMS,
    adjoint_compiled,
    can_use_compiled,
    closed_loop_feedback_compiled,
    closed_loop_rollout_compiled,
    compiled_available,
    costate_compiled,
    joint_hessians,
    lq_rollout_compiled,
    module_needs_grad,
    riccati_compiled,
    rollout_compiled,
    set_compiled,
    stage_congruence_compiled,
    step_rows_compiled,
)
from .dispatch import (
    _launch as _launch,
)

__all__ = [
    "PIECE_NDIMS",
    "adjoint_compiled",
    "can_use_compiled",
    "closed_loop_feedback_compiled",
    "closed_loop_rollout_compiled",
    "compiled_available",
    "costate_compiled",
    "joint_hessians",
    "lq_rollout_compiled",
    "module_needs_grad",
    "riccati_compiled",
    "rollout_compiled",
    "set_compiled",
    "stage_congruence_compiled",
    "step_rows_compiled",
]
