"""Differentiable MPC: the :class:`MPC` layer and its implicit / unrolled gradients."""

from .implicit import cost_gradients, implicit_solution, lagrangian_hessian
from .layer import MPC, MPCOutput
from .unroll import unrolled_solve

__all__ = [
    "MPC",
    "MPCOutput",
    "cost_gradients",
    "implicit_solution",
    "lagrangian_hessian",
    "unrolled_solve",
]
