"""The continuous-time iLQR (Lieskovský, Bušek & Vyhlídal 2025): Riccati ODEs in
square-root form and the forward pass, both integrated by a batched Rodas5P with a step
size per element (:mod:`torchslq.ode`), on the shared iteration loop."""

from .passes import Backward, Nominal, Policy, backward_pass, forward_pass, riccati_rhs
from .solver import (
    ContinuousILQR,
    ContinuousILQROptions,
    ContinuousILQRResult,
    ContinuousILQRRule,
    ContinuousState,
)

__all__ = [
    "Backward",
    "ContinuousILQR",
    "ContinuousILQROptions",
    "ContinuousILQRResult",
    "ContinuousILQRRule",
    "ContinuousState",
    "Nominal",
    "Policy",
    "backward_pass",
    "forward_pass",
    "riccati_rhs",
]
