"""Solvers and their shared pieces (rollout, costate gradient, line search, result)."""

from ..dynamics.rollout import costate_gradient, rollout, rollout_closed_loop
from .ddp import DDP
from .gopronto import GoPRONTO, GoPRONTOResult
from .gradient import GradientMethod
from .ilqr import ILQR
from .line_search import armijo_search, exact_search
from .pronto import PRONTO
from .result import SolverResult
from .slq import SLQ, SLQOptions

__all__ = [
    "DDP",
    "GoPRONTO",
    "GoPRONTOResult",
    "GradientMethod",
    "ILQR",
    "PRONTO",
    "SLQ",
    "SLQOptions",
    "SolverResult",
    "armijo_search",
    "costate_gradient",
    "exact_search",
    "rollout",
    "rollout_closed_loop",
]
