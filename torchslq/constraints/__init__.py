"""State and path constraints (:class:`Constraints`) and the augmented Lagrangian that
:class:`torchslq.ILQR` and :class:`torchslq.DDP` minimise to satisfy them."""

from .augmented import AugmentedLagrangianCost, multiplier_estimate
from .spec import Constraints, ConstraintSet, ConstraintValues, max_violation, violation

__all__ = [
    "AugmentedLagrangianCost",
    "ConstraintSet",
    "ConstraintValues",
    "Constraints",
    "max_violation",
    "multiplier_estimate",
    "violation",
]
