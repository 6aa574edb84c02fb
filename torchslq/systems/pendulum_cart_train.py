"""Train of ``N`` inverted pendulums on carts (Sforni et al., GoPRONTO 2022, Section V)."""

from __future__ import annotations

import torch
from torch import Tensor

from .._shapes import broadcast_shapes
from ..dynamics import ContinuousDynamics, DiscretizedDynamics
from ._common import get_param, set_param

__all__ = ["PendulumCartTrain", "PendulumCartTrainRK4"]

_COUPLINGS = ("paper", "spring")


class PendulumCartTrain(ContinuousDynamics):
    r"""``N`` pendulum-on-cart systems in a row, neighbouring carts coupled by springs.

    State ``x = col(x_1, ..., x_N)`` of size ``4N`` with ``x_i = (theta_i, theta_dot_i,
    w_i, w_dot_i)`` (rad, rad/s, m, m/s), ``theta = 0`` upright; control ``u =
    (u_1, ..., u_N)``, the horizontal force on each cart (N). For every cart ``i``
    (Section V.1, with an erratum found by independent solves: ``cos``, not ``sin``,
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

    prefer_generated_derivatives = True  # the same equations as jacobians / vhp

    control_dim: int
    state_dim: int

    @property
    def state_names(self) -> tuple[str, ...]:
        """``(theta_i, theta_dot_i, w_i, w_dot_i)`` with units, for ``i = 1 .. N``."""
        units = (("theta", "rad"), ("theta_dot", "rad/s"), ("w", "m"), ("w_dot", "m/s"))
        return tuple(f"{s}_{i} [{u}]" for i in range(1, self.n_carts + 1) for s, u in units)

    @property
    def control_names(self) -> tuple[str, ...]:
        """``("u_1 [N]", ..., "u_N [N]")``."""
        return tuple(f"u_{i} [N]" for i in range(1, self.n_carts + 1))

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
            out.append(p.unsqueeze(-1) if isinstance(p, Tensor) and p.ndim > 0 else p)
        return tuple(out)

    def _split(self, x: Tensor, u: Tensor) -> tuple[Tensor, ...]:
        N = self.n_carts
        if x.shape[-1] != 4 * N or u.shape[-1] != N:
            raise ValueError(
                f"expected x (..., {4 * N}) and u (..., {N}), got {tuple(x.shape)} and "
                f"{tuple(u.shape)}"
            )
        return x[..., 0::4], x[..., 1::4], x[..., 2::4], x[..., 3::4]

    def _ends(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """Indicators ``[i < N]`` and ``[i > 1]``, ``(N,)``."""
        N = self.n_carts
        idx = torch.arange(N, device=like.device)
        return (idx < N - 1).to(like.dtype), (idx > 0).to(like.dtype)

    def _spring_force(self, w: Tensor, ks) -> Tensor:
        """``-s_i(w)``: the spring term moved to the right-hand side, ``(..., N)``."""
        if self.n_carts == 1:
            return torch.zeros_like(w)
        wp = torch.nn.functional.pad(w, (1, 1))  # w_0 = w_{N+1} = 0
        w_next, w_prev = wp[..., 2:], wp[..., :-2]
        if self.coupling == "paper":
            return ks * (w_next - w_prev)
        has_next, has_prev = self._ends(w)
        return ks * ((w_next - w) * has_next + (w_prev - w) * has_prev)

    def _accel(self, x: Tensor, u: Tensor):
        # few kernels per call (rollouts call this 4 times per step): scalar parameters
        # are folded in Python, the 2x2 mass matrix is inverted in closed form
        Mp, l, fp, Mc, ks, fc, g = self._params(x)
        th, thd, w, wd = self._split(x, u)
        s, c = torch.sin(th), torch.cos(th)
        Mpl, M = Mp * l, Mc + Mp
        r1 = (Mpl * g) * s - fp * thd
        r2 = u - fc * wd - (0.5 * Mpl) * s * thd * thd + self._spring_force(w, ks)
        D = (Mpl * l * M) - (0.5 * Mpl * Mpl) * c * c
        thdd = (M * r1 + Mpl * c * r2) / D
        wdd = ((0.5 * Mpl) * c * r1 + (Mpl * l) * r2) / D
        return thdd, wdd, (Mp, l, fp, Mc, ks, fc, g, th, thd, w, wd, s, c, r1, r2, D)

    # ------------------------------------------------------------------ model
    def forward(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> Tensor:
        """``xdot (..., 4N)`` from ``x (..., 4N)`` and ``u (..., N)``."""
        thdd, wdd, aux = self._accel(x, u)
        parts = [aux[8], thdd, aux[10], wdd]
        if not (parts[0].shape == thdd.shape == wdd.shape):
            parts = list(torch.broadcast_tensors(*parts))
        return torch.stack(parts, -1).flatten(-2)

    def jacobian_blocks(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The continuous Jacobian in block form (it is block tridiagonal).

        Returns ``(L, Up, Dn, Bu)``: ``L (..., N, 4, 4)`` the diagonal blocks
        ``d xdot_i / d x_i``; ``Up (..., N, 4)`` and ``Dn (..., N, 4)`` the only nonzero
        columns (position ``w``) of ``d xdot_i / d x_{i+1}`` and ``d xdot_i / d x_{i-1}``
        (entries of the last / first cart unused); ``Bu (..., N, 4)`` = ``d xdot_i / d u_i``.
        """
        thdd, wdd, aux = self._accel(x, u)
        Mp, l, fp, Mc, ks, fc, g, th, thd, w, wd, s, c, r1, r2, D = aux
        lead = broadcast_shapes(thdd.shape, wdd.shape)
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
        if self.coupling == "paper":
            k_self, k_next, k_prev = 0.0, ks, -ks
        else:
            has_next, has_prev = self._ends(x)
            k_self = -ks * (has_next + has_prev)
            k_next, k_prev = ks, ks
        zeros = torch.zeros(lead, dtype=x.dtype, device=x.device)
        ones = zeros + 1.0

        def e(v) -> Tensor:
            return zeros + v

        # columns (th, thd, w, wd)
        L = torch.stack(
            [
                torch.stack([zeros, ones, zeros, zeros], -1),
                torch.stack([e(thdd_th), e(thdd_thd), e(a_r2 * k_self), e(a_r2 * (-fc))], -1),
                torch.stack([zeros, zeros, zeros, ones], -1),
                torch.stack([e(wdd_th), e(wdd_thd), e(b_r2 * k_self), e(b_r2 * (-fc))], -1),
            ],
            -2,
        )
        Up = torch.stack([zeros, e(a_r2 * k_next), zeros, e(b_r2 * k_next)], -1)
        Dn = torch.stack([zeros, e(a_r2 * k_prev), zeros, e(b_r2 * k_prev)], -1)
        Bu = torch.stack([zeros, e(a_r2), zeros, e(b_r2)], -1)
        return L, Up, Dn, Bu

    def jacobians(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Analytic ``(df/dx (..., 4N, 4N), df/du (..., 4N, N))``.

        Per cart the accelerations depend on the cart's own ``(th, thd, wd, u)`` and on
        the neighbours' positions through the springs; the blocks of
        :meth:`jacobian_blocks` are assembled into dense matrices (the convention of
        :func:`torchslq.linearize`).
        """
        L, Up, Dn, Bu = self.jacobian_blocks(x, u)
        N = self.n_carts
        lead = L.shape[:-3]
        A = torch.zeros(*lead, N, 4, N, 4, dtype=L.dtype, device=L.device)
        idx = torch.arange(N, device=L.device)
        Av = A.movedim((-4, -2), (0, 1))  # (N, N, ..., 4, 4) view
        Av[idx, idx] = L.movedim(-3, 0)
        if N > 1:
            Av[idx[:-1], idx[1:], ..., :, 2] = Up[..., :-1, :].movedim(-2, 0)
            Av[idx[1:], idx[:-1], ..., :, 2] = Dn[..., 1:, :].movedim(-2, 0)
        Bm = torch.zeros(*lead, N, 4, N, dtype=L.dtype, device=L.device)
        Bv = Bm.movedim((-3, -1), (0, 1))  # (N, N, ..., 4)
        Bv[idx, idx] = Bu.movedim(-2, 0)
        return A.reshape(*lead, 4 * N, 4 * N), Bm.reshape(*lead, 4 * N, N)

    def band_apply(self, blocks: tuple[Tensor, ...], M: Tensor) -> Tensor:
        """``(df/dx) @ M`` in banded form.

        ``M (..., N, 4, 2W+1, c)`` holds the rows of cart ``i`` against the column blocks
        of carts ``i + d``, ``d = -W..W`` (``c`` columns per block: 4 for a state
        Jacobian, 1 for an input Jacobian); entries beyond the band or the train are
        zero. Since ``df/dx`` couples only neighbouring carts, the product widens the
        band of the acceleration rows by one cart (the position rows follow one product
        later); entries beyond ``W`` are dropped, so the caller keeps ``W`` large enough
        (RK4: ``W = 2``, see :class:`PendulumCartTrainRK4`).
        """
        L, Up, Dn, _ = blocks
        N = self.n_carts
        D, c = M.shape[-2], M.shape[-1]
        out = (L @ M.flatten(-2)).unflatten(-1, (D, c))
        if N > 1:
            Mw = M[..., 2, :, :]  # (..., N, D, c) position rows
            zc = torch.zeros_like(Mw[..., :1, :, :])
            zb = torch.zeros_like(Mw[..., :, :1, :])
            nxt = torch.cat([Mw[..., 1:, :, :], zc], -3)  # M[i+1, 2, d', :], d' = d - 1
            nxt = torch.cat([zb, nxt[..., :, :-1, :]], -2)
            prv = torch.cat([zc, Mw[..., :-1, :, :]], -3)  # M[i-1, 2, d', :], d' = d + 1
            prv = torch.cat([prv[..., :, 1:, :], zb], -2)
            out = out + Up[..., :, :, None, None] * nxt.unsqueeze(-3)
            out = out + Dn[..., :, :, None, None] * prv.unsqueeze(-3)
        return out


def _band_to_dense(band: Tensor, N: int) -> Tensor:
    """``(..., N, r, 2W+1, c)`` banded blocks -> dense ``(..., N r, N c)``."""
    r, D, c = band.shape[-3], band.shape[-2], band.shape[-1]
    W = (D - 1) // 2
    lead = band.shape[:-4]
    out = band.new_zeros(*lead, N, r, N, c)
    for d in range(-min(W, N - 1), min(W, N - 1) + 1):
        diag = torch.diagonal(out, offset=d, dim1=-4, dim2=-2)  # (..., r, c, N - |d|)
        src = band[..., :, :, d + W, :]  # (..., N, r, c)
        src = src[..., : N - d, :, :] if d >= 0 else src[..., -d:, :, :]
        diag.copy_(src.movedim(-3, -1))
    return out.reshape(*lead, N * r, N * c)


class PendulumCartTrainRK4(DiscretizedDynamics):
    """RK4 step of a :class:`PendulumCartTrain` with Jacobians chained in banded form.

    The same map and the same (exact) Jacobians as
    ``torchslq.discretize(train, dt, "rk4")``; only :meth:`jacobians` is faster: the
    continuous Jacobian couples neighbouring carts only (accelerations of cart ``i`` on
    positions of carts ``i +- 1``), and a position depends on a neighbour only one RK4
    stage after its acceleration does, so the step's Jacobian couples carts at most
    two apart. The chain ``k_i = f(x + a dt k_{i-1})`` is carried on
    ``(..., N, 4, 5, 4)`` bands (``O(N)`` per row of carts) instead of
    dense ``(4N, 4N)`` matmuls (``O(N^3)``); the dense result is written once at the
    end. At ``N = 100`` (``n = 400``) that is the difference between seconds and a
    fraction of a second per linearisation of a 200-step trajectory.
    """

    continuous: PendulumCartTrain

    def __init__(self, continuous: PendulumCartTrain, dt: float):
        if not isinstance(continuous, PendulumCartTrain):
            raise TypeError("continuous must be a PendulumCartTrain")
        super().__init__(continuous, dt, "rk4")

    def jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """Exact ``(A (..., 4N, 4N), B (..., 4N, N))`` of the RK4 step."""
        f, dt = self.continuous, self.dt
        N, W = f.n_carts, 2
        D = 2 * W + 1
        k = None
        dkx = dku = acc_x = acc_u = None
        for a, wgt in ((0.0, 1.0), (0.5, 2.0), (0.5, 2.0), (1.0, 1.0)):
            xi = x if k is None else x + a * dt * k
            blocks = f.jacobian_blocks(xi, u)
            L, Bu = blocks[0], blocks[3]
            lead = L.shape[:-3]
            # f_u in banded form: block diagonal, (..., N, 4, D, 1)
            Fu = torch.zeros(*lead, N, 4, D, 1, dtype=L.dtype, device=L.device)
            Fu[..., W, 0] = Bu
            if k is None:
                eye = torch.zeros(*lead, N, 4, D, 4, dtype=L.dtype, device=L.device)
                eye[..., W, :] = torch.eye(4, dtype=L.dtype, device=L.device)
                dkx, dku = f.band_apply(blocks, eye), Fu
            else:
                M = (a * dt) * dkx
                M[..., W, :] += torch.eye(4, dtype=L.dtype, device=L.device)
                dkx = f.band_apply(blocks, M)
                dku = f.band_apply(blocks, (a * dt) * dku) + Fu
            k = f(xi, u)
            acc_x = wgt * dkx if acc_x is None else acc_x + wgt * dkx
            acc_u = wgt * dku if acc_u is None else acc_u + wgt * dku
        Ab = (dt / 6.0) * acc_x
        Ab[..., W, :] += torch.eye(4, dtype=Ab.dtype, device=Ab.device)
        return _band_to_dense(Ab, N), _band_to_dense((dt / 6.0) * acc_u, N)
