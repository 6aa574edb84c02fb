"""Train of ``N`` inverted pendulums on carts (Sforni et al., GoPRONTO 2022, Section V)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..dynamics import ContinuousDynamics
from ._common import get_param, set_param

__all__ = ["PendulumCartTrain"]

_COUPLINGS = ("paper", "spring")


class PendulumCartTrain(ContinuousDynamics):
    r"""``N`` pendulum-on-cart systems in a row, neighbouring carts coupled by springs.

    State ``x = col(x_1, ..., x_N)`` of size ``4N`` with ``x_i = (theta_i, theta_dot_i,
    w_i, w_dot_i)`` (rad, rad/s, m, m/s), ``theta = 0`` upright; control ``u =
    (u_1, ..., u_N)``, the horizontal force on each cart (N). For every cart ``i``
    (Section V.1, with the erratum of ``shared/PAPER-NOTES.md``: ``cos``, not ``sin``,
    in front of ``w_ddot`` in the first equation)::

        Mp l^2 thdd_i + fp thd_i - Mp l cos(th_i) wdd_i - Mp l g sin(th_i) = 0
        (Mc + Mp) wdd_i + fc wd_i - 1/2 Mp l cos(th_i) thdd_i
                        + 1/2 Mp l sin(th_i) thd_i^2 + s_i(w) = u_i

    solved for ``(thdd_i, wdd_i)`` in closed form (the 2x2 mass matrix has determinant
    ``D = Mp l^2 (Mc + Mp) - 1/2 Mp^2 l^2 cos^2(th) > 0``). The spring term ``s_i``:

    * ``coupling="paper"`` (default): as printed, ``s_i = -ks w_{i+1} + ks w_{i-1}``
      with ``w_0 = w_{N+1} = 0``;
    * ``coupling="spring"``: the physical reading, linear springs between neighbours
      only, ``s_i = ks (w_i - w_{i+1}) [i < N] + ks (w_i - w_{i-1}) [i > 1]``.

    Both leave the upright rest state ``x = 0, u = 0`` an equilibrium.

    Args:
        n_carts: number of carts ``N >= 1``.
        Mp, l, fp: pendulum mass (kg), length (m), damping (N m s / rad); Table I:
            0.2, 1.0, 0.01.
        Mc, ks, fc: cart mass (kg), spring constant (N/m), damping (N s / m); Table I:
            6.0, 0.5, 10.0.
        g: gravitational acceleration, 9.81 m/s^2.
        coupling: ``"paper"`` or ``"spring"`` (see above).

    Parameters are numbers or tensors broadcasting against ``x[..., 0]`` (e.g. ``(B, 1)``
    for ``x (B, T, 4N)``); they are shared by all carts of one element. Analytic
    Jacobians are provided (dense ``(..., 4N, 4N)``; see :meth:`jacobians`).
    """

    control_dim: int
    state_dim: int

    def __init__(
        self,
        n_carts: int,
        Mp=0.2,
        l=1.0,
        fp=0.01,
        Mc=6.0,
        ks=0.5,
        fc=10.0,
        g=9.81,
        coupling: str = "paper",
    ):
        super().__init__()
        if not isinstance(n_carts, int) or isinstance(n_carts, bool) or n_carts < 1:
            raise ValueError(f"n_carts must be a positive int, got {n_carts!r}")
        if coupling not in _COUPLINGS:
            raise ValueError(f"coupling must be one of {_COUPLINGS}, got {coupling!r}")
        self.n_carts = n_carts
        self.state_dim = 4 * n_carts
        self.control_dim = n_carts
        self.coupling = coupling
        set_param(self, "Mp", Mp, positive=True)
        set_param(self, "l", l, positive=True)
        set_param(self, "fp", fp, nonneg=True)
        set_param(self, "Mc", Mc, positive=True)
        set_param(self, "ks", ks, nonneg=True)
        set_param(self, "fc", fc, nonneg=True)
        set_param(self, "g", g)

    # ------------------------------------------------------------------ helpers
    def _params(self, x: Tensor) -> tuple:
        """Parameters with a trailing cart dim so they broadcast against ``(..., N)``."""
        out = []
        for k in ("Mp", "l", "fp", "Mc", "ks", "fc", "g"):
            p = get_param(self, k, x)
            out.append(p.unsqueeze(-1) if isinstance(p, Tensor) else p)
        return tuple(out)

    def _split(self, x: Tensor, u: Tensor) -> tuple[Tensor, ...]:
        N = self.n_carts
        if x.shape[-1] != 4 * N or u.shape[-1] != N:
            raise ValueError(
                f"expected x (..., {4 * N}) and u (..., {N}), got {tuple(x.shape)} and "
                f"{tuple(u.shape)}"
            )
        xs = x.unflatten(-1, (N, 4))
        return xs[..., 0], xs[..., 1], xs[..., 2], xs[..., 3]

    def _neighbours(self, w: Tensor) -> tuple[Tensor, Tensor]:
        """``(w_{i+1}, w_{i-1})`` with zeros beyond the ends, each ``(..., N)``."""
        zero = torch.zeros_like(w[..., :1])
        return torch.cat([w[..., 1:], zero], -1), torch.cat([zero, w[..., :-1]], -1)

    def _ends(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """Indicators ``[i < N]`` and ``[i > 1]``, ``(N,)``."""
        N = self.n_carts
        idx = torch.arange(N, device=like.device)
        return (idx < N - 1).to(like.dtype), (idx > 0).to(like.dtype)

    def _spring_force(self, w: Tensor, ks) -> Tensor:
        """``-s_i(w)``: the spring term moved to the right-hand side, ``(..., N)``."""
        w_next, w_prev = self._neighbours(w)
        if self.coupling == "paper":
            return ks * (w_next - w_prev)
        has_next, has_prev = self._ends(w)
        return ks * ((w_next - w) * has_next + (w_prev - w) * has_prev)

    def _accel(self, x: Tensor, u: Tensor):
        Mp, l, fp, Mc, ks, fc, g = self._params(x)
        th, thd, w, wd = self._split(x, u)
        s, c = torch.sin(th), torch.cos(th)
        r1 = -fp * thd + Mp * l * g * s
        r2 = u - fc * wd - 0.5 * Mp * l * s * thd * thd + self._spring_force(w, ks)
        D = Mp * l * l * (Mc + Mp) - 0.5 * Mp * Mp * l * l * c * c
        thdd = ((Mc + Mp) * r1 + Mp * l * c * r2) / D
        wdd = (0.5 * Mp * l * c * r1 + Mp * l * l * r2) / D
        return thdd, wdd, (Mp, l, fp, Mc, ks, fc, g, th, thd, w, wd, s, c, r1, r2, D)

    # ------------------------------------------------------------------ model
    def forward(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> Tensor:
        """``xdot (..., 4N)`` from ``x (..., 4N)`` and ``u (..., N)``."""
        thdd, wdd, aux = self._accel(x, u)
        thd, wd = aux[8], aux[10]
        thd, wd, thdd, wdd = torch.broadcast_tensors(thd, wd, thdd, wdd)
        return torch.stack([thd, thdd, wd, wdd], -1).flatten(-2)

    def jacobians(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Analytic ``(df/dx (..., 4N, 4N), df/du (..., 4N, N))``.

        Per cart the accelerations depend on the cart's own ``(th, thd, wd, u)`` and on
        the neighbours' positions through the springs; the blocks are assembled into
        dense matrices (the convention of :func:`torchslq.linearize`).
        """
        thdd, wdd, aux = self._accel(x, u)
        Mp, l, fp, Mc, ks, fc, g, th, thd, w, wd, s, c, r1, r2, D = aux
        N = self.n_carts
        lead = torch.broadcast_shapes(thdd.shape, wdd.shape)
        dD = Mp * Mp * l * l * c * s  # dD/dth
        dr2_dth = -0.5 * Mp * l * c * thd * thd
        dr2_dthd = -Mp * l * s * thd
        a_r2 = Mp * l * c / D  # dthdd/dr2
        b_r2 = Mp * l * l / D  # dwdd/dr2
        dN1_dth = (Mc + Mp) * Mp * l * g * c - Mp * l * s * r2 + Mp * l * c * dr2_dth
        dN2_dth = -0.5 * Mp * l * s * r1 + 0.5 * Mp * Mp * l * l * g * c * c + Mp * l * l * dr2_dth
        thdd_th = (dN1_dth - thdd * dD) / D
        thdd_thd = ((Mc + Mp) * (-fp) + Mp * l * c * dr2_dthd) / D
        wdd_th = (dN2_dth - wdd * dD) / D
        wdd_thd = (0.5 * Mp * l * c * (-fp) + Mp * l * l * dr2_dthd) / D
        # spring derivatives of r2 w.r.t. own / next / previous position
        one = torch.ones((), dtype=x.dtype, device=x.device)
        if self.coupling == "paper":
            k_self, k_next, k_prev = 0.0 * one, ks * one, -ks * one
        else:
            has_next, has_prev = self._ends(x)
            k_self = -ks * (has_next + has_prev)
            k_next, k_prev = ks * one, ks * one
        zeros = torch.zeros(lead, dtype=x.dtype, device=x.device)
        ones = torch.ones(lead, dtype=x.dtype, device=x.device)

        def e(v) -> Tensor:
            return (v + zeros) if isinstance(v, Tensor) else zeros + v

        # local 4x4 blocks (..., N, 4, 4), columns (th, thd, w, wd)
        local = torch.stack(
            [
                torch.stack([zeros, ones, zeros, zeros], -1),
                torch.stack([e(thdd_th), e(thdd_thd), e(a_r2 * k_self), e(a_r2 * (-fc))], -1),
                torch.stack([zeros, zeros, zeros, ones], -1),
                torch.stack([e(wdd_th), e(wdd_thd), e(b_r2 * k_self), e(b_r2 * (-fc))], -1),
            ],
            -2,
        )
        A = torch.zeros(*lead[:-1], N, 4, N, 4, dtype=x.dtype, device=x.device)
        idx = torch.arange(N, device=x.device)
        Av = A.movedim((-4, -2), (0, 1))  # (N, N, ..., 4, 4) view
        Av[idx, idx] = local.movedim(-3, 0)
        if N > 1:
            # d(acc_i)/d(w_{i+1}) and d(acc_i)/d(w_{i-1}): column 2 of the neighbour
            nxt = torch.stack([e(a_r2 * k_next), e(b_r2 * k_next)], -1)  # (..., N, 2)
            prv = torch.stack([e(a_r2 * k_prev), e(b_r2 * k_prev)], -1)
            Av[idx[:-1], idx[1:], ..., 1, 2] = nxt[..., :-1, 0].movedim(-1, 0)
            Av[idx[:-1], idx[1:], ..., 3, 2] = nxt[..., :-1, 1].movedim(-1, 0)
            Av[idx[1:], idx[:-1], ..., 1, 2] = prv[..., 1:, 0].movedim(-1, 0)
            Av[idx[1:], idx[:-1], ..., 3, 2] = prv[..., 1:, 1].movedim(-1, 0)
        Bm = torch.zeros(*lead[:-1], N, 4, N, dtype=x.dtype, device=x.device)
        Bv = Bm.movedim((-3, -1), (0, 1))  # (N, N, ..., 4)
        Bv[idx, idx, ..., 1] = e(a_r2).movedim(-1, 0)
        Bv[idx, idx, ..., 3] = e(b_r2).movedim(-1, 0)
        return A.reshape(*lead[:-1], 4 * N, 4 * N), Bm.reshape(*lead[:-1], 4 * N, N)
