"""Particle moving through quadratic viscous drag (Sideris & Bobrow 2005, Section 4.1)."""

from __future__ import annotations

from torch import Tensor

from ..dynamics import Dynamics
from ._common import get_param, lead_shape, set_param, stack_matrix, stack_vector

__all__ = ["DragVehicle"]


class DragVehicle(Dynamics):
    r"""Discrete-time (explicit Euler) vehicle under quadratic drag, eqs. (62)-(64).

    Continuous model ``m x_ddot = u - beta sign(x_dot) x_dot^2``; with sampling period
    ``Ts`` the paper's Euler form (63)-(64) is::

        x(n+1) = x(n) + Ts v(n)
        v(n+1) = v(n) + (Ts / m) [u(n) - beta v(n) |v(n)|]

    (``v |v|`` is ``sign(v) v^2`` written so that it is C^1; its derivative is ``2 |v|``).

    State ``[x, v]`` (m, m/s); control ``u``, a force (N).

    Args:
        beta: drag coefficient (kg/m; drag force ``beta v|v|`` in N). Default 0.1, the
            paper's representative case (Table 1 uses 0.01 ... 1).
        m: mass (kg). Default 0.0259: the paper's "m = 25.9 gr" read as grams (with m = 25.9 kg the target
            is never reached and the problem does not get harder with beta,
            contradicting the paper's Table 1).
        Ts: sampling period (s), default 1/500 (``T = 1`` s, ``N = 500``).

    Parameters are numbers or tensors broadcasting against ``x[..., 0]``. Note that the
    Euler step is unstable for ``|v| > m / (beta Ts)`` (where ``|dv(n+1)/dv(n)| > 1``),
    which is why the paper's ``beta = 1`` case does not converge.
    """

    prefer_generated_derivatives = True  # the same equations as jacobians / vhp

    state_dim = 2
    control_dim = 1
    state_names = ("x [m]", "v [m/s]")
    control_names = ("u [N]",)

    def __init__(self, beta=0.1, m=0.0259, Ts=1.0 / 500.0):
        super().__init__()
        set_param(self, "beta", beta, nonneg=True)
        set_param(self, "m", m, positive=True)
        set_param(self, "Ts", Ts, positive=True)

    def _params(self, x: Tensor):
        return tuple(get_param(self, k, x) for k in ("beta", "m", "Ts"))

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        beta, m, Ts = self._params(x)
        p, v, f = x[..., 0], x[..., 1], u[..., 0]
        p_next = p + Ts * v
        v_next = v + (Ts / m) * (f - beta * v * v.abs())
        return stack_vector([p_next, v_next], lead_shape(x, u, beta, m, Ts), x)

    def jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        beta, m, Ts = self._params(x)
        v = x[..., 1]
        lead = lead_shape(x, u, beta, m, Ts)
        A = stack_matrix([[1.0, Ts], [0.0, 1.0 - (2.0 * Ts / m) * beta * v.abs()]], lead, x)
        B = stack_matrix([[0.0], [Ts / m]], lead, x)
        return A, B
