"""The batched LQ (Riccati) kernel shared by every solver.

The Riccati pass, its rollout and adjoint solve (sequential, or parallel in time by
associative scans: :mod:`.scan`), the box QP and the DARE, with the
Levenberg-Marquardt regularisation schedule and its restarts (:mod:`.regularization`).
Each runs on the CPU as a compiled kernel or as batched torch ops
(:mod:`torchslq._backend`), with the same meaning; :func:`set_compiled` switches the
compiled form off (e.g. to compare the two); :func:`limit_specialised_sizes` names the
problem sizes that get kernels compiled for their own ``(n, m)``.
"""

from .._backend import compiled_available, set_compiled
from .._backend.specialisation import limit_specialised_sizes
from .boxqp import BoxQPResult, box_qp
from .dare import dare, dare_gain, dare_residual
from .regularization import RegularizationSchedule, Restarts
from .riccati import (
    RiccatiFactors,
    homogeneous_cost,
    homogeneous_dynamics,
    riccati_backward,
    riccati_homogeneous,
    rollout_homogeneous,
    rollout_linear,
)
from .scan import (
    associative_scan,
    lq_adjoint_scan,
    riccati_scan,
    riccati_scan_homogeneous,
    rollout_scan,
    rollout_scan_homogeneous,
)
from .solve import (
    LQRSolution,
    choose_method,
    lq_adjoint_solve,
    lq_objective,
    lqr_solve,
    scan_memory_bytes,
)

__all__ = [
    "BoxQPResult",
    "LQRSolution",
    "RegularizationSchedule",
    "Restarts",
    "RiccatiFactors",
    "associative_scan",
    "box_qp",
    "choose_method",
    "scan_memory_bytes",
    "compiled_available",
    "dare",
    "dare_gain",
    "dare_residual",
    "homogeneous_cost",
    "homogeneous_dynamics",
    "limit_specialised_sizes",
    "lq_adjoint_scan",
    "lq_adjoint_solve",
    "lq_objective",
    "lqr_solve",
    "riccati_backward",
    "riccati_homogeneous",
    "riccati_scan",
    "riccati_scan_homogeneous",
    "rollout_homogeneous",
    "rollout_linear",
    "rollout_scan",
    "rollout_scan_homogeneous",
    "set_compiled",
]
