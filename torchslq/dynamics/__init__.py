"""Dynamics models: base classes, discretisation and linearisation."""

from .._backend.bound import inline_model_kernels
from .base import CompiledDerivatives, ContinuousDynamics, Dynamics, state_control_dims
from .discretize import DiscretizedDynamics, discretize
from .linearize import (
    LearnedDynamics,
    as_transition,
    dynamics_hessians,
    dynamics_vhp,
    linearize,
    linearize_with_hessians,
    linearize_with_vhp,
)

__all__ = [
    "CompiledDerivatives",
    "ContinuousDynamics",
    "DiscretizedDynamics",
    "Dynamics",
    "LearnedDynamics",
    "as_transition",
    "discretize",
    "dynamics_hessians",
    "dynamics_vhp",
    "inline_model_kernels",
    "linearize",
    "linearize_with_hessians",
    "linearize_with_vhp",
    "state_control_dims",
]
