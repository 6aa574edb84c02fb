"""torchslq: batched, differentiable nonlinear optimal control in PyTorch."""

from .lq import LQRSolution, lqr_solve, riccati_backward, rollout_linear
from .status import Status, status_names

__version__ = "0.1.0"

__all__ = [
    "LQRSolution",
    "Status",
    "lqr_solve",
    "riccati_backward",
    "rollout_linear",
    "status_names",
]
