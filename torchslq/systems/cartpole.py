"""Cart-pole (point mass on a massless pole) pushed by a horizontal force."""

from __future__ import annotations

import torch
from torch import Tensor

from ..dynamics import ContinuousDynamics
from ._common import (
    components,
    cos,
    get_param,
    lead_shape,
    set_param,
    sin,
    split_jacobian,
    stack_vector,
    weighted_hessians,
)

__all__ = ["CartPole"]

_PARAMS = ("mc", "mp", "l", "g")

# The equations, written once: x, u, p indexable (p = (mc, mp, l, g)); forward,
# jacobians and vhp call them with tensors. On the CPU the compiled code is generated
# from forward (torchslq.dynamics.codegen), like a user's model's.


def _terms(x, u, p):
    """The accelerations as quotients ``s_ddot = N1 / D``, ``theta_ddot = N2 / (l D)``."""
    mc, mp, l, g = p[0], p[1], p[2], p[3]
    thd, F = x[3], u[0]
    sn, c = sin(x[1]), cos(x[1])
    D = mc + mp * sn * sn
    N1 = F + mp * sn * (l * thd * thd + g * c)
    N2 = -F * c - mp * l * thd * thd * c * sn - (mc + mp) * g * sn
    return mc, mp, l, g, thd, F, sn, c, D, N1, N2


def cartpole_xdot(x, u, p):
    """``xdot = f(x, u)``."""
    _, _, l, _, thd, _, _, _, D, N1, N2 = _terms(x, u, p)
    return x[2], thd, N1 / D, N2 / (l * D)


def _first(x, u, p):
    """With ``q = N1 / D`` and ``r = N2 / D`` (``= l theta_ddot``): their derivatives in
    ``(a, b, F) = (theta, theta_dot, F)`` (``D`` depends on ``theta`` only), and the terms
    the second derivatives need."""
    mc, mp, l, g, thd, F, sn, c, D, N1, N2 = _terms(x, u, p)
    q, r = N1 / D, N2 / D
    dD = 2.0 * mp * sn * c  # dD / dtheta
    c2 = c * c - sn * sn  # cos(2 theta)
    N1a = mp * (l * thd * thd * c + g * c2)
    N1b = 2.0 * mp * l * sn * thd
    N2a = F * sn - mp * l * thd * thd * c2 - (mc + mp) * g * c
    N2b = -2.0 * mp * l * thd * c * sn
    qa, qb, qF = (N1a - q * dD) / D, N1b / D, 1.0 / D
    ra, rb, rF = (N2a - r * dD) / D, N2b / D, -c / D
    return mc, mp, l, g, thd, F, sn, c, D, c2, dD, q, r, qa, qb, qF, ra, rb, rF


def cartpole_jacobian(x, u, p):
    """The rows of ``[f_x | f_u]``."""
    _, _, l, _, _, _, _, _, _, _, _, _, _, qa, qb, qF, ra, rb, rF = _first(x, u, p)
    z = 0.0
    return (
        (z, z, 1.0, z, z),
        (z, z, z, 1.0, z),
        (z, qa, z, qb, qF),
        (z, ra / l, z, rb / l, rF / l),
    )


def cartpole_hessians(x, u, p):
    """Each output's Hessian in ``z = (x, u)``: only the accelerations are curved, in
    ``(theta, theta_dot, F)``. For a quotient ``q = N / D``, ``q_ab = (N_ab - q_a D_b -
    q_b D_a - q D_ab) / D`` from the numerators' second derivatives."""
    mc, mp, l, g, thd, F, sn, c, D, c2, dD, q, r, qa, qb, qF, ra, rb, rF = _first(x, u, p)
    ddD = 2.0 * mp * c2
    N1aa = -mp * (l * thd * thd * sn + 4.0 * g * sn * c)
    N1ab = 2.0 * mp * l * c * thd
    N1bb = 2.0 * mp * l * sn
    N2aa = F * c + 4.0 * mp * l * thd * thd * sn * c + (mc + mp) * g * sn
    N2ab = -2.0 * mp * l * thd * c2
    N2bb = -2.0 * mp * l * c * sn
    qaa = (N1aa - 2.0 * qa * dD - q * ddD) / D
    qab = (N1ab - qb * dD) / D
    qaF = -qF * dD / D
    qbb = N1bb / D
    raa = (N2aa - 2.0 * ra * dD - r * ddD) / D / l
    rab = (N2ab - rb * dD) / D / l
    raF = (sn - rF * dD) / D / l
    rbb = N2bb / D / l
    z = 0.0
    zr = (z, z, z, z, z)
    flat = (zr, zr, zr, zr, zr)
    return (
        flat,
        flat,
        (
            zr,
            (z, qaa, z, qab, qaF),
            zr,
            (z, qab, z, qbb, z),
            (z, qaF, z, z, z),
        ),
        (
            zr,
            (z, raa, z, rab, raF),
            zr,
            (z, rab, z, rbb, z),
            (z, raF, z, z, z),
        ),
    )


class CartPole(ContinuousDynamics):
    r"""Frictionless cart with a point mass at the tip of a massless pole.

    State ``x = [s, theta, s_dot, theta_dot]`` (m, rad, m/s, rad/s): cart position and
    pole angle, ``theta = 0`` hanging down, ``theta = pi`` upright. Control ``u = [F]``,
    the horizontal force on the cart (N). With ``D = mc + mp sin^2(theta)``::

        s_ddot     = [F + mp sin(th) (l thd^2 + g cos(th))] / D
        theta_ddot = [-F cos(th) - mp l thd^2 cos(th) sin(th) - (mc + mp) g sin(th)] / (l D)

    (the model of Lieskovský, Bušek & Vyhlídal, "Continuous-time iterative
    linear-quadratic regulator", 2025, Section V: ``mc`` the cart, ``mp`` the point mass
    at the tip, the reading that matches the authors' public code).

    Args:
        mc: cart mass (kg), default 1.0.
        mp: tip mass (kg), default 0.1.
        l: pole length (m), default 0.5 as in the common iLQR benchmark; the
            continuous-time iLQR paper (and its public code) uses 0.2.
        g: gravitational acceleration (m/s^2), default 9.81.

    Parameters are numbers or tensors broadcasting against ``x[..., 0]`` (e.g.
    ``(B, 1)`` for ``x (B, T, 4)``). Analytic Jacobians are provided.

    Without force the horizontal momentum :meth:`momentum` is conserved (its rate is
    ``F``) and so is :meth:`energy`.
    """

    prefer_generated_derivatives = True  # the same equations as jacobians / vhp

    state_dim = 4
    control_dim = 1
    state_names = ("s [m]", "theta [rad]", "s_dot [m/s]", "theta_dot [rad/s]")
    control_names = ("F [N]",)

    def __init__(self, mc=1.0, mp=0.1, l=0.5, g=9.81):
        super().__init__()
        set_param(self, "mc", mc, positive=True)
        set_param(self, "mp", mp, positive=True)
        set_param(self, "l", l, positive=True)
        set_param(self, "g", g)

    def _params(self, x: Tensor):
        return tuple(get_param(self, k, x) for k in _PARAMS)

    def forward(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> Tensor:
        p = self._params(x)
        xdot = cartpole_xdot(components(x), components(u), p)
        return stack_vector(list(xdot), lead_shape(x, u, *p), x)

    def jacobians(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> tuple[Tensor, Tensor]:
        p = self._params(x)
        J = cartpole_jacobian(components(x), components(u), p)
        return split_jacobian(J, 4, lead_shape(x, u, *p), x)

    def vhp(
        self, x: Tensor, u: Tensor, s: Tensor, t: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Hessian blocks of ``s · f`` (:func:`cartpole_hessians`): only the
        accelerations are curved, in ``(theta, theta_dot, F)``."""
        p = self._params(x)
        H = cartpole_hessians(components(x), components(u), p)
        return weighted_hessians(H, s, 4, lead_shape(x, u, *p), x)

    def momentum(self, x: Tensor) -> Tensor:
        """Horizontal momentum ``(mc + mp) s_dot + mp l cos(th) th_dot`` (kg m/s)."""
        mc, mp, l, _ = self._params(x)
        return (mc + mp) * x[..., 2] + mp * l * torch.cos(x[..., 1]) * x[..., 3]

    def energy(self, x: Tensor) -> Tensor:
        """Kinetic plus potential energy (J), potential zero at the pivot height."""
        mc, mp, l, g = self._params(x)
        th, sd, thd = x[..., 1], x[..., 2], x[..., 3]
        c = torch.cos(th)
        kin = 0.5 * (mc + mp) * sd**2 + mp * l * c * sd * thd + 0.5 * mp * l * l * thd**2
        return kin - mp * g * l * c
