"""The batched LQ (Riccati) kernel shared by every solver."""

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
    "LQRSolution",
    "RiccatiFactors",
    "homogeneous_cost",
    "homogeneous_dynamics",
    "lq_adjoint_solve",
    "lq_objective",
    "lqr_solve",
    "riccati_backward",
    "riccati_homogeneous",
    "rollout_homogeneous",
    "rollout_linear",
]
