"""Derivatives of a :class:`~torchslq.ContinuousProblem` at sample points, and the packed
form in which they are interpolated along a nominal trajectory.

All functions take ``x (B, Q, n)``, ``u (B, Q, m)``, ``t (B, Q)`` (``Q`` points per element)
and return detached tensors with the same leading dims.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor
from torch.func import grad, vjp, vmap

from ...dynamics.linearize import dynamics_hessians, linearize

__all__ = ["Layout", "dynamics_derivatives", "stage_derivatives", "terminal_derivatives"]


def dynamics_derivatives(
    dynamics, x: Tensor, u: Tensor, t: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """``(f (B,Q,n), f_x (B,Q,n,n), f_u (B,Q,n,m))``: the model's analytic
    :meth:`~torchslq.ContinuousDynamics.jacobians` when it has them, else ``n``
    vector-Jacobian products of one batched call (:func:`torchslq.linearize`)."""
    with torch.no_grad():
        f = dynamics(x, u, t)
        if getattr(dynamics, "has_analytic_jacobians", False):
            fx, fu = dynamics.jacobians(x, u, t)
        else:
            fx, fu = linearize(lambda a, b: dynamics(a, b, t), x, u)
    return f, fx.expand(*f.shape, x.shape[-1]), fu.expand(*f.shape, u.shape[-1])


def dynamics_second_derivatives(dynamics, x: Tensor, u: Tensor, t: Tensor) -> Tensor:
    """Every output's Hessian in ``z = (x, u)``: ``(B, Q, n, n+m, n+m)`` (for DDP's terms
    ``s · f_zz``)."""
    n, m = x.shape[-1], u.shape[-1]
    with torch.no_grad():
        if getattr(dynamics, "has_analytic_vhp", False):
            basis = torch.eye(n, dtype=x.dtype, device=x.device).reshape(n, 1, 1, n)
            Hxx, Huu, Hux = dynamics.vhp(x, u, basis, t)
            lead = (n, *x.shape[:-1])
            Hxx, Huu, Hux = (
                Hxx.expand(*lead, n, n),
                Huu.expand(*lead, m, m),
                Hux.expand(*lead, m, n),
            )
        else:
            Hxx, Huu, Hux = dynamics_hessians(lambda a, b: dynamics(a, b, t), x, u)
        top = torch.cat([Hxx, Hux.mT], -1)
        bottom = torch.cat([Hux, Huu], -1)
        return torch.cat([top, bottom], -2).movedim(0, -3)


def stage_derivatives(cost_fn, x: Tensor, u: Tensor, t: Tensor) -> tuple[Tensor, ...]:
    """``(l (B,Q), l_x (B,Q,n), l_u (B,Q,m), l_zz (B,Q,n+m,n+m))`` of the running cost
    ``cost_fn(x, u, t) -> (B, Q)``: one reverse pass for the gradients of all rows (rows
    are independent), ``n + m`` vector-Jacobian products of the gradient for the Hessian
    (as :meth:`torchslq.Cost.quadratize`, with the time passed through)."""
    n, m = x.shape[-1], u.shape[-1]
    x, u = x.detach(), u.detach()
    with torch.no_grad():
        l = cost_fn(x, u, t)
        g = grad(lambda a, b: cost_fn(a, b, t).sum(), argnums=(0, 1))
        (lx, lu), pull = vjp(g, x, u)
        eye = torch.eye(n + m, dtype=x.dtype, device=x.device)
        shape = (n + m, *([1] * (x.ndim - 1)))
        ex = eye[:, :n].reshape(*shape, n).expand(n + m, *x.shape)
        eu = eye[:, n:].reshape(*shape, m).expand(n + m, *u.shape)
        cx, cu = vmap(lambda a, b: pull((a, b)))(ex, eu)  # (n+m, B, Q, n), (n+m, B, Q, m)
        H = torch.cat([cx, cu], -1).movedim(0, -1)  # (B, Q, n+m, n+m)
    return l.expand(x.shape[:-1]), lx, lu, 0.5 * (H + H.mT)


def terminal_derivatives(terminal_fn, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``(Phi (B,), Phi_x (B,n), Phi_xx (B,n,n))`` at ``x (B, n)``."""
    n = x.shape[-1]
    x = x.detach()
    with torch.no_grad():
        phi = terminal_fn(x)
        g = grad(lambda a: terminal_fn(a).sum())
        px, pull = vjp(g, x)
        basis = torch.eye(n, dtype=x.dtype, device=x.device).unsqueeze(1).expand(n, *x.shape)
        H = vmap(lambda v: pull(v)[0])(basis).movedim(0, -1)
    return phi.expand(x.shape[:-1]), px, 0.5 * (H + H.mT)


@dataclass(frozen=True)
class Layout:
    """Where each quantity sits in the packed coefficient vector ``(..., F)`` that is
    interpolated along the nominal trajectory: ``f, f_x, f_u, l, l_x, l_u, l_zz`` and,
    for DDP, ``f_zz``."""

    n: int
    m: int
    ddp: bool

    @property
    def sizes(self) -> tuple[int, ...]:
        n, m, z = self.n, self.m, self.n + self.m
        return (n, n * n, n * m, 1, n, m, z * z) + ((n * z * z,) if self.ddp else ())

    @property
    def width(self) -> int:
        return sum(self.sizes)

    def pack(self, f, fx, fu, l, lx, lu, lzz, fzz=None) -> Tensor:
        lead = f.shape[:-1]
        parts = [f, fx, fu, l.unsqueeze(-1), lx, lu, lzz]
        if self.ddp:
            parts.append(fzz)
        return torch.cat([p.reshape(*lead, -1) for p in parts], -1)

    def unpack(self, c: Tensor) -> dict[str, Tensor]:
        n, m, z = self.n, self.m, self.n + self.m
        lead = c.shape[:-1]
        names = ("f", "fx", "fu", "l", "lx", "lu", "lzz") + (("fzz",) if self.ddp else ())
        shapes = ((n,), (n, n), (n, m), (), (n,), (m,), (z, z), (n, z, z))
        out, i = {}, 0
        for name, size, shape in zip(names, self.sizes, shapes[: len(names)], strict=True):
            out[name] = c[..., i : i + size].reshape(*lead, *shape)
            i += size
        return out
