"""Damped pendulum driven by a torque."""

from __future__ import annotations

import torch
from torch import Tensor

from ..dynamics import ContinuousDynamics
from ._common import get_param, lead_shape, set_param, stack_matrix, stack_vector

__all__ = ["Pendulum"]


class Pendulum(ContinuousDynamics):
    r"""Point-mass pendulum on a massless rod with viscous joint damping.

    State ``x = [theta, theta_dot]`` (rad, rad/s), ``theta = 0`` hanging straight down,
    ``theta = pi`` upright; control ``u = [tau]``, a joint torque (N m)::

        m l^2 theta_ddot = tau - b theta_dot - m g l sin(theta)

    i.e. ``xdot = [theta_dot, (tau - b theta_dot) / (m l^2) - (g / l) sin(theta)]``.

    Args:
        mass: ``m`` (kg), default 1.
        length: ``l`` (m), default 1.
        g: gravitational acceleration (m/s^2), default 9.81.
        damping: ``b`` (N m s/rad), default 0.1.

    Each parameter is a number or a tensor that broadcasts against the leading dims of
    the inputs (``x[..., 0]``): e.g. shape ``(B, 1)`` for ``x (B, T, 2)`` gives every
    batch element its own value. Tensors are stored as buffers (``nn.Parameter``s stay
    learnable). Analytic Jacobians are provided (:meth:`jacobians`).
    """

    prefer_generated_derivatives = True  # the same equations as jacobians / vhp

    state_dim = 2
    control_dim = 1
    state_names = ("theta [rad]", "theta_dot [rad/s]")
    control_names = ("tau [N m]",)

    def __init__(self, mass=1.0, length=1.0, g=9.81, damping=0.1):
        super().__init__()
        set_param(self, "mass", mass, positive=True)
        set_param(self, "length", length, positive=True)
        set_param(self, "g", g)
        set_param(self, "damping", damping, nonneg=True)

    def _params(self, x: Tensor):
        return tuple(get_param(self, k, x) for k in ("mass", "length", "g", "damping"))

    def forward(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> Tensor:
        m, l, g, b = self._params(x)
        th, thd, tau = x[..., 0], x[..., 1], u[..., 0]
        thdd = (tau - b * thd) / (m * l * l) - (g / l) * torch.sin(th)
        return stack_vector([thd, thdd], lead_shape(x, u, m, l, g, b), x)

    def jacobians(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> tuple[Tensor, Tensor]:
        m, l, g, b = self._params(x)
        th = x[..., 0]
        lead = lead_shape(x, u, m, l, g, b)
        inv_ml2 = 1.0 / (m * l * l)
        A = stack_matrix([[0.0, 1.0], [-(g / l) * torch.cos(th), -b * inv_ml2]], lead, x)
        B = stack_matrix([[0.0], [inv_ml2]], lead, x)
        return A, B

    def energy(self, x: Tensor) -> Tensor:
        """Total mechanical energy ``1/2 m l^2 thd^2 + m g l (1 - cos th)`` (J), ``(...)``."""
        m, l, g, _ = self._params(x)
        th, thd = x[..., 0], x[..., 1]
        return 0.5 * m * l * l * thd**2 + m * g * l * (1.0 - torch.cos(th))
