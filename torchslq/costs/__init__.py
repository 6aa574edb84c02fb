"""Costs: the quadratic tracking cost and second-order expansions."""

from .quadratic import CostExpansion, QuadraticCost

__all__ = ["CostExpansion", "QuadraticCost"]
