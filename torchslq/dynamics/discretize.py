"""Turning :class:`ContinuousDynamics` into discrete-time :class:`Dynamics`."""

from __future__ import annotations

import torch
from torch import Tensor

from .._shapes import broadcast_shapes
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
        # stage i: k_i = f(x + a_i dt k_{i-1}, u), so with z = (x, u) and f_z = [f_x | f_u]
        # dk_i/dz = f_z + a_i dt f_x dk_{i-1}/dz: one product per stage on the joint
        # (n, n + m) block (this chain runs on every linearisation, (rows, n, n + m)
        # tensors, and its cost is the number of tiny batched products and adds)
        n = x.shape[-1]
        k, dk, acc = None, None, None
        stages = ((0.0, 1.0), (0.5, 2.0), (0.5, 2.0), (1.0, 1.0))
        for i, (a, w) in enumerate(stages):
            xi = x if k is None else torch.add(x, k, alpha=a * dt)
            fx, fu = f.jacobians(xi, u)
            lead = broadcast_shapes(fx.shape[:-2], fu.shape[:-2])
            fz = torch.cat([fx.expand(*lead, *fx.shape[-2:]), fu.expand(*lead, *fu.shape[-2:])], -1)
            dk = fz if dk is None else torch.add(fz, fx @ dk, alpha=a * dt)
            acc = dk if acc is None else torch.add(acc, dk, alpha=w)
            if i < len(stages) - 1:  # the last stage's k is not needed
                k = f(xi, u)
        A = torch.add(eye, acc[..., :n], alpha=dt / 6.0)
        return A, acc[..., n:] * (dt / 6.0)


def discretize(dynamics: ContinuousDynamics, dt: float, method: str = "rk4") -> DiscretizedDynamics:
    """Discrete-time :class:`Dynamics` taking one ``method`` step ("rk4" | "euler") of ``dt``."""
    if not isinstance(dynamics, ContinuousDynamics):
        raise TypeError(
            f"dynamics must be a torchslq.ContinuousDynamics, got {type(dynamics).__name__}"
        )
    return DiscretizedDynamics(dynamics, dt, method)
