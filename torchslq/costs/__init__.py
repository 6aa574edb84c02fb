"""Costs: the quadratic tracking cost and second-order expansions."""

from .general import Cost, project_psd
from .quadratic import CostExpansion, QuadraticCost

__all__ = ["Cost", "CostExpansion", "QuadraticCost", "project_psd"]
