"""torchslq: batched, differentiable nonlinear optimal control in PyTorch."""

from .constraints import Constraints
from .costs import Cost, CostExpansion, QuadraticCost
from .dynamics import (
    ContinuousDynamics,
    DiscretizedDynamics,
    Dynamics,
    LearnedDynamics,
    discretize,
    linearize,
)
from .logging import TensorBoardLogger
from .lq import LQRSolution, lqr_solve, riccati_backward, rollout_linear
from .mpc import MPC, MPCOutput
from .problem import Problem
from .problem_continuous import ContinuousProblem
from .solvers import DDP, ILQR, PRONTO, SLQ, GoPRONTO, GoPRONTOResult, GradientMethod, SolverResult
from .solvers.continuous import ContinuousILQR, ContinuousILQRResult
from .status import Status, status_names

__version__ = "0.1.0"

__all__ = [
    "Constraints",
    "ContinuousDynamics",
    "ContinuousILQR",
    "ContinuousILQRResult",
    "ContinuousProblem",
    "DDP",
    "Cost",
    "CostExpansion",
    "DiscretizedDynamics",
    "GoPRONTO",
    "GoPRONTOResult",
    "GradientMethod",
    "ILQR",
    "PRONTO",
    "Dynamics",
    "LQRSolution",
    "LearnedDynamics",
    "MPC",
    "MPCOutput",
    "Problem",
    "QuadraticCost",
    "SLQ",
    "SolverResult",
    "Status",
    "TensorBoardLogger",
    "discretize",
    "linearize",
    "lqr_solve",
    "riccati_backward",
    "rollout_linear",
    "status_names",
]
