"""The batched LQ (Riccati) kernel shared by every solver."""

from .._backend import compiled_available, set_compiled
from .boxqp import BoxQPResult, box_qp
from .dare import dare, dare_gain, dare_residual
from .riccati import (
    RiccatiFactors,
    homogeneous_cost,
    homogeneous_dynamics,
    riccati_backward,
    riccati_homogeneous,
    rollout_homogeneous,
    rollout_linear,
)
from .solve import LQRSolution, lq_adjoint_solve, lq_objective, lqr_solve

__all__ = [
    "BoxQPResult",
    "LQRSolution",
    "RiccatiFactors",
    "box_qp",
    "compiled_available",
    "dare",
    "dare_gain",
    "dare_residual",
    "homogeneous_cost",
    "homogeneous_dynamics",
    "lq_adjoint_solve",
    "lq_objective",
    "lqr_solve",
    "riccati_backward",
    "riccati_homogeneous",
    "rollout_homogeneous",
    "rollout_linear",
    "set_compiled",
]
