"""Turning :class:`ContinuousDynamics` into discrete-time :class:`Dynamics`."""

from __future__ import annotations

import torch
from torch import Tensor

from .base import ContinuousDynamics, Dynamics, identity_like

__all__ = ["discretize", "DiscretizedDynamics"]

_METHODS = ("euler", "rk4")


class DiscretizedDynamics(Dynamics):
    """One explicit integration step of a continuous model per time step ``dt``.

    ``method="euler"``: ``x + dt f(x, u)``. ``method="rk4"``: the classical
    fourth-order Runge-Kutta step with ``u`` held constant over the step (zero-order
    hold). When the continuous model has analytic Jacobians, :meth:`jacobians` chains
    them through the scheme exactly; otherwise :func:`torchslq.linearize` differentiates
    the step by automatic differentiation.
    """

    def __init__(self, continuous: ContinuousDynamics, dt: float, method: str = "rk4"):
        super().__init__()
        if method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
        if not (isinstance(dt, (int, float)) and dt > 0):
            raise ValueError(f"dt must be a positive number, got {dt!r}")
        self.continuous = continuous
        self.dt = float(dt)
        self.method = method
        self.state_dim = continuous.state_dim
        self.control_dim = continuous.control_dim

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        f, dt = self.continuous, self.dt
        if self.method == "euler":
            return x + dt * f(x, u)
        # torch.add(a, b, alpha=c) is a + c b in one op: rollouts are dispatch-bound
        k1 = f(x, u)
        k2 = f(torch.add(x, k1, alpha=0.5 * dt), u)
        k3 = f(torch.add(x, k2, alpha=0.5 * dt), u)
        k4 = f(torch.add(x, k3, alpha=dt), u)
        incr = torch.add(torch.add(k1, k2, alpha=2.0), torch.add(k4, k3, alpha=2.0))
        return torch.add(x, incr, alpha=dt / 6.0)

    @property
    def has_analytic_jacobians(self) -> bool:
        return self.continuous.has_analytic_jacobians

    def jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """Exact Jacobians of the integration step from the continuous model's ones."""
        f, dt = self.continuous, self.dt
        eye = identity_like(x, x.shape[-1])
        if self.method == "euler":
            fx, fu = f.jacobians(x, u)
            return eye + dt * fx, dt * fu
        # stage i: k_i = f(x + a_i dt k_{i-1}, u); dk_i = f_x (I dx + a_i dt dk_{i-1}) + f_u du
        k, dkx, dku = None, None, None
        acc_x, acc_u = 0.0, 0.0
        for a, w in ((0.0, 1.0), (0.5, 2.0), (0.5, 2.0), (1.0, 1.0)):
            xi = x if k is None else x + a * dt * k
            fx, fu = f.jacobians(xi, u)
            if k is None:
                dkx, dku = fx, fu
            else:
                dkx = fx @ (eye + a * dt * dkx)
                dku = fx @ (a * dt * dku) + fu
            k = f(xi, u)
            acc_x = acc_x + w * dkx
            acc_u = acc_u + w * dku
        return eye + (dt / 6.0) * acc_x, (dt / 6.0) * acc_u


def discretize(dynamics: ContinuousDynamics, dt: float, method: str = "rk4") -> DiscretizedDynamics:
    """Discrete-time :class:`Dynamics` taking one ``method`` step ("rk4" | "euler") of ``dt``."""
    if not isinstance(dynamics, ContinuousDynamics):
        raise TypeError(
            f"dynamics must be a torchslq.ContinuousDynamics, got {type(dynamics).__name__}"
        )
    return DiscretizedDynamics(dynamics, dt, method)
