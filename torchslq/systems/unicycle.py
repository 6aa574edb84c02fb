"""Kinematic unicycle (crocoddyl's ``ActionModelUnicycle`` step), discrete time."""

from __future__ import annotations

import torch
from torch import Tensor

from .._shapes import broadcast_shapes
from ..dynamics import Dynamics
from ._common import components, cos, sin

__all__ = ["Unicycle"]


def unicycle_next(x, u, p):
    """The next state (written once: :meth:`Unicycle.forward` calls it with tensors; its
    compiled step is generated from ``forward``); ``p = (dt,)``."""
    dt = p[0]
    vdt = u[0] * dt
    th = x[2]
    return x[0] + cos(th) * vdt, x[1] + sin(th) * vdt, th + u[1] * dt


class Unicycle(Dynamics):
    r"""One explicit Euler step of a kinematic unicycle.

    State ``x = [px, py, theta]`` (m, m, rad), control ``u = [v, w]`` (forward speed
    m/s, turn rate rad/s)::

        px' = px + cos(theta) v dt,   py' = py + sin(theta) v dt,   theta' = theta + w dt

    the step of crocoddyl's ``ActionModelUnicycle`` (``dt = 0.1`` there). Analytic
    Jacobians and second derivatives (:meth:`vhp`): ``s · f`` is curved only in
    ``(theta, v)``.

    Args:
        dt: time step (s), default 0.1.
    """

    prefer_generated_derivatives = True  # the same equations as jacobians / vhp

    state_dim, control_dim = 3, 2
    state_names = ("px [m]", "py [m]", "theta [rad]")
    control_names = ("v [m/s]", "w [rad/s]")

    def __init__(self, dt: float = 0.1):
        super().__init__()
        if not (isinstance(dt, (int, float)) and dt > 0):
            raise ValueError(f"dt must be a positive number, got {dt!r}")
        self.dt = float(dt)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        return torch.stack(unicycle_next(components(x), components(u), (self.dt,)), -1)

    def jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        th, v = x[..., 2], u[..., 0]
        c, s, dt = torch.cos(th), torch.sin(th), self.dt
        lead = broadcast_shapes(x.shape[:-1], u.shape[:-1])
        A = torch.eye(3, dtype=x.dtype, device=x.device).expand(*lead, 3, 3).clone()
        A[..., 0, 2] = -s * v * dt
        A[..., 1, 2] = c * v * dt
        B = x.new_zeros(*lead, 3, 2)
        B[..., 0, 0] = c * dt
        B[..., 1, 0] = s * dt
        B[..., 2, 1] = dt
        return A, B

    def vhp(self, x: Tensor, u: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Hessian blocks of ``s · f``: ``d2/dtheta2 = -(s_x cos + s_y sin) v dt``,
        ``d2/(dv dtheta) = (s_y cos - s_x sin) dt``; every other entry is zero."""
        th, v = x[..., 2], u[..., 0]
        c, sn, dt = torch.cos(th), torch.sin(th), self.dt
        sx, sy = s[..., 0], s[..., 1]
        h_tt = -(sx * c + sy * sn) * v * dt
        h_vt = (sy * c - sx * sn) * dt
        lead = broadcast_shapes(h_tt.shape, h_vt.shape)
        Hxx = x.new_zeros(*lead, 3, 3)
        Hxx[..., 2, 2] = h_tt
        Hux = x.new_zeros(*lead, 2, 3)
        Hux[..., 0, 2] = h_vt
        return Hxx, x.new_zeros(*lead, 2, 2), Hux
