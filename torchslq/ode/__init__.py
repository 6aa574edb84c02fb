"""Batched ODE integration with a step size per batch element (Rodas5P, dense output).

See :mod:`torchslq.ode.rosenbrock` for the method and why it is written here.
"""

from .dense import PiecewiseCubic, RodasDense, locate
from .rosenbrock import RODAS5P, ODESolution, jacobian_by_jvp, solve_ivp

__all__ = [
    "ODESolution",
    "PiecewiseCubic",
    "RODAS5P",
    "RodasDense",
    "jacobian_by_jvp",
    "locate",
    "solve_ivp",
]
