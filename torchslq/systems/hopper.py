"""Gas-actuated one-dimensional hopping machine (Sideris & Bobrow 2005, Section 4.2)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..dynamics import Dynamics
from ._common import get_param, lead_shape, set_param, stack_matrix, stack_vector

__all__ = ["Hopper"]


class Hopper(Dynamics):
    r"""Discrete-time (explicit Euler) hopper with the paper's C^1-smoothed ground spring.

    State ``[y, y_dot, y_p]``: height of the mass, its velocity, and the piston
    (unstretched spring length) position; control ``u = y_p_dot``. Units follow the
    paper (``g = 386.4`` in/s^2): inches and seconds. With spring compression
    ``e = y_p - y`` and the C^1 spring

    ::

        phi(e) = 0                  e < 0          (flight)
                 e^2 / (2 alpha)    0 <= e < alpha
                 e - alpha / 2      e >= alpha     (F(e) = k phi(e))

    the continuous model ``y_ddot = (k/m) phi(e) - g``, ``y_p_dot = u`` is stepped by
    explicit Euler with ``dt = tf / N``::

        y(n+1)    = y(n) + dt y_dot(n)
        ydot(n+1) = y_dot(n) + dt [(k/m) phi(y_p(n) - y(n)) - g]
        y_p(n+1)  = y_p(n) + dt u(n)

    Args:
        k_over_m: spring constant per unit mass (1/s^2), default 500.
        g: gravity (in/s^2), default 386.4.
        alpha: smoothing width of the spring (in), default 0.1; must be positive.
        tf: final time (s), default 1.
        N: number of steps, default 100 (``dt = tf / N``).

    ``k_over_m``, ``g`` and ``alpha`` may be tensors broadcasting against ``x[..., 0]``.
    The branches of ``phi`` are polynomials, finite everywhere, so ``torch.where`` gives
    NaN-free gradients.
    """

    prefer_generated_derivatives = True  # the same equations as jacobians / vhp

    state_dim = 3
    control_dim = 1
    state_names = ("y [in]", "y_dot [in/s]", "y_p [in]")
    control_names = ("y_p_dot [in/s]",)

    def __init__(self, k_over_m=500.0, g=386.4, alpha=0.1, tf=1.0, N=100):
        super().__init__()
        set_param(self, "k_over_m", k_over_m, nonneg=True)
        set_param(self, "g", g)
        set_param(self, "alpha", alpha, positive=True)
        if not (isinstance(N, int) and N > 0):
            raise ValueError(f"N must be a positive integer, got {N!r}")
        if not (isinstance(tf, (int, float)) and tf > 0):
            raise ValueError(f"tf must be a positive number, got {tf!r}")
        self.tf = float(tf)
        self.N = N
        self.dt = self.tf / N

    def _params(self, x: Tensor):
        return tuple(get_param(self, k, x) for k in ("k_over_m", "g", "alpha"))

    @staticmethod
    def _phi(e: Tensor, alpha) -> tuple[Tensor, Tensor]:
        """``phi(e)`` and ``phi'(e)`` of the smoothed spring."""
        zero = torch.zeros_like(e)
        contact = e >= 0
        linear = e >= alpha
        phi = torch.where(linear, e - 0.5 * alpha, e * e / (2.0 * alpha))
        dphi = torch.where(linear, torch.ones_like(e), e / alpha)
        return torch.where(contact, phi, zero), torch.where(contact, dphi, zero)

    def spring_acceleration(self, x: Tensor) -> Tensor:
        """Upward spring force per unit mass ``(k/m) phi(y_p - y)`` (in/s^2), ``(...)``."""
        k, _, alpha = self._params(x)
        return k * self._phi(x[..., 2] - x[..., 0], alpha)[0]

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        k, g, alpha = self._params(x)
        dt = self.dt
        y, yd, yp = x[..., 0], x[..., 1], x[..., 2]
        phi, _ = self._phi(yp - y, alpha)
        return stack_vector(
            [y + dt * yd, yd + dt * (k * phi - g), yp + dt * u[..., 0]],
            lead_shape(x, u, k, g, alpha),
            x,
        )

    def jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        k, g, alpha = self._params(x)
        dt = self.dt
        _, dphi = self._phi(x[..., 2] - x[..., 0], alpha)
        s = dt * k * dphi  # d ydot(n+1) / d y_p ; minus that w.r.t. y
        lead = lead_shape(x, u, k, g, alpha)
        A = stack_matrix([[1.0, dt, 0.0], [-s, 1.0, s], [0.0, 0.0, 1.0]], lead, x)
        B = stack_matrix([[0.0], [0.0], [dt]], lead, x)
        return A, B
