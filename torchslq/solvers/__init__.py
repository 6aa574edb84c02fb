"""Solvers and their shared pieces: the one iteration loop (:func:`iterate`), the
descent directions and line searches the public solvers are made of, options, results."""

from ..dynamics.rollout import costate_gradient, rollout, rollout_closed_loop
from .base import DescentSolver, Solver
from .continuous import ContinuousILQR, ContinuousILQROptions, ContinuousILQRResult
from .core import Advance, ElementState, Measure, iterate
from .ddp import DDP
from .descent import CostateGradient, DescentRule, DescentState, GaussNewtonLQ, LineSearch
from .gopronto import GoPRONTO, GoPRONTOOptions, GoPRONTOResult, PRONTOOptions
from .gradient import GradientMethod
from .ilqr import ILQR
from .line_search import armijo_search, exact_search
from .newton import RegularizedNewton
from .options import DDPOptions, GradientOptions, ILQROptions
from .pronto import PRONTO
from .result import SolverResult
from .slq import SLQ, SLQOptions

__all__ = [
    "Advance",
    "ContinuousILQR",
    "ContinuousILQROptions",
    "ContinuousILQRResult",
    "CostateGradient",
    "DDP",
    "DDPOptions",
    "DescentRule",
    "DescentSolver",
    "DescentState",
    "ElementState",
    "GaussNewtonLQ",
    "GoPRONTO",
    "GoPRONTOOptions",
    "GoPRONTOResult",
    "GradientMethod",
    "GradientOptions",
    "ILQR",
    "ILQROptions",
    "LineSearch",
    "Measure",
    "PRONTO",
    "PRONTOOptions",
    "RegularizedNewton",
    "SLQ",
    "SLQOptions",
    "Solver",
    "SolverResult",
    "armijo_search",
    "costate_gradient",
    "exact_search",
    "iterate",
    "rollout",
    "rollout_closed_loop",
]
