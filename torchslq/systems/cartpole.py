"""Cart-pole (point mass on a massless pole) pushed by a horizontal force."""

from __future__ import annotations

import torch
from torch import Tensor

from .._shapes import broadcast_shapes
from ..dynamics import ContinuousDynamics
from ._common import (
    get_param,
    lead_shape,
    scalar_params_array,
    set_param,
    stack_matrix,
    stack_vector,
)

__all__ = ["CartPole"]


class CartPole(ContinuousDynamics):
    r"""Frictionless cart with a point mass at the tip of a massless pole.

    State ``x = [s, theta, s_dot, theta_dot]`` (m, rad, m/s, rad/s): cart position and
    pole angle, ``theta = 0`` hanging down, ``theta = pi`` upright. Control ``u = [F]``,
    the horizontal force on the cart (N). With ``D = mc + mp sin^2(theta)``::

        s_ddot     = [F + mp sin(th) (l thd^2 + g cos(th))] / D
        theta_ddot = [-F cos(th) - mp l thd^2 cos(th) sin(th) - (mc + mp) g sin(th)] / (l D)

    (the model of the continuous-time iLQR paper; see ``shared/PAPER-NOTES.md``).

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

    state_dim = 4
    control_dim = 1

    def __init__(self, mc=1.0, mp=0.1, l=0.5, g=9.81):
        super().__init__()
        set_param(self, "mc", mc, positive=True)
        set_param(self, "mp", mp, positive=True)
        set_param(self, "l", l, positive=True)
        set_param(self, "g", g)

    def compiled_rhs(self):
        """``xdot`` as a numba function (see :meth:`torchslq.ContinuousDynamics.compiled_rhs`);
        None when a parameter is a tensor with batch dims."""
        params = scalar_params_array(self, ("mc", "mp", "l", "g"))
        if params is None:
            return None
        from ._numba_steps import cartpole_rhs

        return cartpole_rhs, params

    def compiled_derivatives(self):
        """:meth:`jacobians` and the per-output Hessians of :meth:`vhp` as a numba
        function (see :meth:`torchslq.ContinuousDynamics.compiled_derivatives`)."""
        from ..dynamics import CompiledDerivatives
        from ._numba_steps import CARTPOLE_CURVATURE, cartpole_derivatives

        return CompiledDerivatives(cartpole_derivatives, *CARTPOLE_CURVATURE)

    def _params(self, x: Tensor):
        return tuple(get_param(self, k, x) for k in ("mc", "mp", "l", "g"))

    def _accel(self, x: Tensor, u: Tensor):
        mc, mp, l, g = self._params(x)
        th, thd, F = x[..., 1], x[..., 3], u[..., 0]
        s, c = torch.sin(th), torch.cos(th)
        D = mc + mp * s * s
        sdd = (F + mp * s * (l * thd * thd + g * c)) / D
        thdd = (-F * c - mp * l * thd * thd * c * s - (mc + mp) * g * s) / (l * D)
        return sdd, thdd, (mc, mp, l, g, th, thd, F, s, c, D)

    def forward(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> Tensor:
        sdd, thdd, (mc, mp, l, g, *_) = self._accel(x, u)
        return stack_vector([x[..., 2], x[..., 3], sdd, thdd], lead_shape(x, u, mc, mp, l, g), x)

    def jacobians(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> tuple[Tensor, Tensor]:
        sdd, thdd, (mc, mp, l, g, th, thd, F, s, c, D) = self._accel(x, u)
        lead = lead_shape(x, u, mc, mp, l, g)
        dD = 2.0 * mp * s * c  # dD/dth
        c2 = c * c - s * s  # cos(2 th)
        # sdd = N1 / D
        dN1_dth = mp * (l * thd * thd * c + g * c2)
        dsdd_dth = (dN1_dth - sdd * dD) / D
        dsdd_dthd = 2.0 * mp * l * s * thd / D
        # thdd = N2 / (l D)
        dN2_dth = F * s - mp * l * thd * thd * c2 - (mc + mp) * g * c
        dthdd_dth = (dN2_dth / l - thdd * dD) / D
        dthdd_dthd = -2.0 * mp * thd * c * s / D
        A = stack_matrix(
            [
                [0.0, 0.0, 1.0, 0.0],
                [0.0, 0.0, 0.0, 1.0],
                [0.0, dsdd_dth, 0.0, dsdd_dthd],
                [0.0, dthdd_dth, 0.0, dthdd_dthd],
            ],
            lead,
            x,
        )
        B = stack_matrix([[0.0], [0.0], [1.0 / D], [-c / (l * D)]], lead, x)
        return A, B

    def vhp(
        self, x: Tensor, u: Tensor, s: Tensor, t: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Hessian blocks of ``s · f``: only the accelerations are curved, in ``(th, thd,
        F)``. Each is a quotient ``q = N / D`` (``D`` depends on ``th`` only), so
        ``q_ab = (N_ab - q_a D_b - q_b D_a - q D_ab) / D`` from the numerators' second
        derivatives (``theta_ddot = N2 / (l D)``)."""
        sdd, thdd, (mc, mp, l, g, th, thd, F, sn, c, D) = self._accel(x, u)
        w1, w2 = s[..., 2], s[..., 3]
        dD = 2.0 * mp * sn * c
        ddD = 2.0 * mp * (c * c - sn * sn)
        c2, w2l = c * c - sn * sn, w2 / l
        r = thdd * l  # N2 / D
        # numerator derivatives (a = th, b = thd, F)
        N1a = mp * (l * thd * thd * c + g * c2)
        N1b = 2.0 * mp * l * sn * thd
        N1aa = -mp * (l * thd * thd * sn + 4.0 * g * sn * c)
        N1ab = 2.0 * mp * l * c * thd
        N1bb = 2.0 * mp * l * sn
        N2a = F * sn - mp * l * thd * thd * c2 - (mc + mp) * g * c
        N2b = -2.0 * mp * l * thd * c * sn
        N2aa = F * c + 4.0 * mp * l * thd * thd * sn * c + (mc + mp) * g * sn
        N2ab = -2.0 * mp * l * thd * c2
        N2bb = -2.0 * mp * l * c * sn
        # first derivatives of the quotients (q = sdd, r = N2 / D)
        qa, qb, qF = (N1a - sdd * dD) / D, N1b / D, 1.0 / D
        ra, rb, rF = (N2a - r * dD) / D, N2b / D, -c / D
        # second derivatives (D_b = D_F = 0)
        qaa = (N1aa - 2.0 * qa * dD - sdd * ddD) / D
        qab = (N1ab - qb * dD) / D
        qaF = -qF * dD / D
        qbb = N1bb / D
        raa = (N2aa - 2.0 * ra * dD - r * ddD) / D
        rab = (N2ab - rb * dD) / D
        raF = (sn - rF * dD) / D
        rbb = N2bb / D
        h_aa = w1 * qaa + w2l * raa
        h_ab = w1 * qab + w2l * rab
        h_bb = w1 * qbb + w2l * rbb
        h_aF = w1 * qaF + w2l * raF
        lead = broadcast_shapes(lead_shape(x, u, mc, mp, l, g), s.shape[:-1])
        z = 0.0
        Hxx = stack_matrix(
            [[z, z, z, z], [z, h_aa, z, h_ab], [z, z, z, z], [z, h_ab, z, h_bb]], lead, x
        )
        Huu = x.new_zeros(*lead, 1, 1)
        Hux = stack_matrix([[z, h_aF, z, z]], lead, x)
        return Hxx, Huu, Hux

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
