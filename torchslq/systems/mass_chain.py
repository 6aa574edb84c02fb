"""Chain of point masses joined by nonlinear (cubic, hardening) springs, one force each."""

from __future__ import annotations

import torch
from torch import Tensor

from .._shapes import broadcast_shapes
from ..dynamics import ContinuousDynamics
from ._common import get_param, set_param

__all__ = ["MassChain"]

_PARAMS = ("mass", "k", "k3", "damping")

# The laws, written once: the torch form applies them to every spring and mass at once;
# on the CPU the compiled code is generated from forward (torchslq.dynamics.codegen).


def spring_tension(e, k, k3):
    """Tension ``s(e) = k e + k3 e^3`` of a spring extended by ``e``."""
    return e * (k + k3 * e * e)


def spring_stiffness(e, k, k3):
    """``s'(e)``."""
    return k + 3.0 * k3 * e * e


def spring_curvature(e, k3):
    """``s''(e)``."""
    return 6.0 * k3 * e


def acceleration(net, v, F, m, c):
    """Newton's law for one mass: ``(net spring force - c v + F) / m``."""
    return (net - c * v + F) / m


class MassChain(ContinuousDynamics):
    r"""``N`` equal masses in a line, the first tied to a wall, all pushed by their own force.

    State ``x = [p_1..p_N, v_1..v_N]`` (displacements from the spring rest positions, m,
    and velocities, m/s), control ``u = [F_1..F_N]`` (N). Spring ``i`` joins mass
    ``i - 1`` (``p_0 = 0``, the wall) and mass ``i``; its extension is
    ``e_i = p_i - p_{i-1}`` and its tension ``s(e) = k e + k3 e^3`` (``k3 > 0``: hardening).
    With viscous damping ``c`` on every mass (``s_{N+1} = 0``: the last mass is free)::

        m a_i = s(e_{i+1}) - s(e_i) - c v_i + F_i

    ``n = 2N``, ``m = N``; the default ``N = 4`` gives ``n + m = 12``, the size used to
    compare differentiable MPC solvers. Analytic Jacobians (tridiagonal position block).

    Args:
        n_masses: ``N`` (default 4).
        mass: ``m`` (kg), default 1.
        k: linear stiffness (N/m), default 1.
        k3: cubic stiffness (N/m^3), default 1.
        damping: ``c`` (N s/m), default 0.1.

    Parameters are numbers or tensors broadcasting against ``x[..., 0]`` (e.g. ``(B, 1)``
    for ``x (B, T, n)``); ``nn.Parameter``s stay learnable.
    """

    prefer_generated_derivatives = True  # the same equations as jacobians / vhp

    @property
    def state_names(self) -> tuple[str, ...]:
        """``("p_1 [m]", ..., "p_N [m]", "v_1 [m/s]", ..., "v_N [m/s]")``."""
        idx = range(1, self.n_masses + 1)
        return (*(f"p_{i} [m]" for i in idx), *(f"v_{i} [m/s]" for i in idx))

    @property
    def control_names(self) -> tuple[str, ...]:
        """``("F_1 [N]", ..., "F_N [N]")``."""
        return tuple(f"F_{i} [N]" for i in range(1, self.n_masses + 1))

    def __init__(self, n_masses: int = 4, mass=1.0, k=1.0, k3=1.0, damping=0.1):
        super().__init__()
        if not isinstance(n_masses, int) or n_masses < 1:
            raise ValueError(f"n_masses must be a positive int, got {n_masses!r}")
        self.n_masses = n_masses
        self.state_dim = 2 * n_masses
        self.control_dim = n_masses
        set_param(self, "mass", mass, positive=True)
        set_param(self, "k", k)
        set_param(self, "k3", k3)
        set_param(self, "damping", damping, nonneg=True)

    def _params(self, x: Tensor):
        out = []
        for name in _PARAMS:
            p = get_param(self, name, x)
            out.append(p.unsqueeze(-1) if isinstance(p, Tensor) and p.ndim > 0 else p)
        return out  # tensors broadcast against (..., N)

    def _extensions(self, p: Tensor) -> Tensor:
        return p - torch.cat([torch.zeros_like(p[..., :1]), p[..., :-1]], dim=-1)

    def _matrices(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """``D'`` with ``e = p D'`` (extensions) and ``M`` with ``s M = s_{i+1} - s_i``.

        Cached per dtype and device, but never filled inside a ``torch.func`` transform:
        a tensor made there is wrapped for that transform, and reusing it in a later one
        makes functorch fail ("escaped?"). (Not buffers: the problem's dtype check would
        then demand float64 inputs.)"""
        key = (like.dtype, like.device)
        cache = self.__dict__.setdefault("_mat_cache", {})
        if key in cache:
            return cache[key]
        N = self.n_masses
        eye = torch.eye(N, dtype=like.dtype, device=like.device)
        sub = torch.diag(torch.ones(N - 1, dtype=like.dtype, device=like.device), -1)
        mats = ((eye - sub).T.contiguous(), (sub - eye).contiguous())
        if torch._C._functorch.peek_interpreter_stack() is None:
            cache[key] = mats
        return mats

    def forward(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> Tensor:
        # two small matmuls instead of shifted concatenations: this model is called
        # 4 times per RK4 step in every rollout, so its Python overhead matters
        N = self.n_masses
        m, k, k3, c = self._params(x)
        Dt, M = self._matrices(x)
        p, v = x[..., :N], x[..., N:]
        e = p @ Dt
        a = acceleration(spring_tension(e, k, k3) @ M, v, u, m, c)
        if a.shape != v.shape:
            v, a = torch.broadcast_tensors(v, a)
        return torch.cat([v, a], dim=-1)

    def jacobians(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> tuple[Tensor, Tensor]:
        N = self.n_masses
        m, k, k3, c = self._params(x)
        p = x[..., :N]
        e = self._extensions(p)
        ds = spring_stiffness(e, k, k3) / m  # s'(e_i) / m, (..., N)
        ds_next = torch.cat([ds[..., 1:], torch.zeros_like(ds[..., :1])], dim=-1)
        off = ds[..., 1:]
        Ap = torch.diag_embed(-(ds + ds_next))
        if N > 1:
            Ap = Ap + torch.diag_embed(off, offset=1) + torch.diag_embed(off, offset=-1)
        lead = broadcast_shapes(x.shape[:-1], u.shape[:-1], Ap.shape[:-2])
        ones = x.new_ones(*lead, N)
        Av = torch.diag_embed(-c * ones / m)
        eye = torch.diag_embed(ones)
        zero = torch.zeros_like(eye)
        A = torch.cat(
            [torch.cat([zero, eye], dim=-1), torch.cat([Ap.expand(*lead, N, N), Av], dim=-1)],
            dim=-2,
        )
        B = torch.cat([zero, torch.diag_embed(ones / m)], dim=-2)
        return A, B

    def vhp(
        self, x: Tensor, u: Tensor, s: Tensor, t: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Hessian blocks of ``s · f``. Only the springs are curved: ``s · f`` contains
        ``sum_j c_j s(e_j)`` with ``c_j = (w_{j-1} - w_j) / m`` (``w = s[N:]`` the weights
        of the accelerations, ``w_0 = 0``), so with ``d_j = c_j s''(e_j) = 6 k3 c_j e_j``
        the position block is the tridiagonal ``D' diag(d) D`` (``e = D p``); every other
        entry is zero."""
        N = self.n_masses
        m, _, k3, _ = self._params(x)
        Dt, _ = self._matrices(x)
        e = x[..., :N] @ Dt
        w = s[..., N:]
        w_prev = torch.cat([torch.zeros_like(w[..., :1]), w[..., :-1]], dim=-1)
        d = spring_curvature(e, k3) * (w_prev - w) / m  # (..., N)
        diag = torch.cat([d[..., :-1] + d[..., 1:], d[..., -1:]], dim=-1)
        Hpp = torch.diag_embed(diag)
        if N > 1:
            off = -d[..., 1:]
            Hpp = Hpp + torch.diag_embed(off, offset=1) + torch.diag_embed(off, offset=-1)
        lead = Hpp.shape[:-2]
        Hxx = x.new_zeros(*lead, 2 * N, 2 * N)
        Hxx[..., :N, :N] = Hpp
        return Hxx, x.new_zeros(*lead, N, N), x.new_zeros(*lead, N, 2 * N)
