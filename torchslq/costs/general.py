"""General (non-quadratic) costs with derivatives from ``torch.func``.

``J(x, u) = sum_{t<T} l(x_t, u_t, t) + Phi(x_T)``. The stage cost is evaluated on the
whole ``(B, T)`` grid at once, and its gradients and Hessians are taken for all rows
together: one reverse pass gives ``l_x, l_u`` everywhere (rows are independent, so the
gradient of the sum is the per-row gradient), and ``n + m`` forward-mode products of
that gradient (``vmap`` over the basis, reverse-over-reverse) give the Hessian blocks.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn
from torch.func import grad, vjp, vmap

from .quadratic import CostExpansion

__all__ = ["Cost", "project_psd"]

StageFn = Callable[[Tensor, Tensor, Tensor], Tensor]
TerminalFn = Callable[[Tensor], Tensor]


def project_psd(H: Tensor, min_eig: float) -> Tensor:
    """Clip the eigenvalues of symmetric ``H (..., k, k)`` from below: ``lambda := max(lambda,
    min_eig)`` (the regularisation of non-convex cost Hessians in Lieskovsky et al. 2025)."""
    Hs = 0.5 * (H + H.mT)
    w, V = torch.linalg.eigh(Hs)
    return (V * w.clamp_min(min_eig).unsqueeze(-2)) @ V.mT


def _checked_output(name: str, value: object, lead: torch.Size, shape: str) -> Tensor:
    """``value`` of the user's ``stage``/``terminal`` function, with a TypeError /
    ValueError naming it unless it is a tensor that broadcasts to ``lead`` with a full
    last dim (``(..., T)`` for the stage cost, summed over time; ``(..., B)`` for the
    terminal cost). A ``(..., T, 1)`` output or a scalar sum over the batch would
    otherwise misalign or mix the rows silently."""
    if not torch.is_tensor(value):
        raise TypeError(
            f"the cost's {name} must return a tensor {shape}, got {type(value).__name__}"
        )
    k = value.ndim
    ok = 1 <= k <= len(lead) and value.shape[-1] == lead[-1]
    ok = ok and all(a in (1, b) for a, b in zip(value.shape, lead[len(lead) - k :], strict=True))
    if len(lead) == 0:  # a single row (no leading dims): a scalar
        ok = k == 0
    if not ok:
        raise ValueError(
            f"the cost's {name} returned shape {tuple(value.shape)}; expected {shape} = "
            f"{tuple(lead)}"
        )
    return value


class Cost(nn.Module):
    """A general cost ``sum_t l(x_t, u_t, t) + Phi(x_T)``.

    Give the stage and terminal costs as callables, or subclass and override
    :meth:`stage` and :meth:`terminal`.

    Args:
        stage: ``l(x (..., T, n), u (..., T, m), t (T,)) -> (..., T)``; elementwise over
            the leading dims (row ``(b, t)`` may depend only on ``x[b, t], u[b, t]``) and
            broadcasting (so per-element parameters ``(B, 1)`` work). ``t`` is the step index.
        terminal: ``Phi(x (..., n)) -> (...)``; zero when omitted.
        state_dim, control_dim: dimensions, checked against the problem's dynamics.

    A stage/terminal given as an ``nn.Module`` is registered, so its parameters are
    part of this module.
    """

    def __init__(
        self,
        stage: StageFn | None = None,
        terminal: TerminalFn | None = None,
        *,
        state_dim: int,
        control_dim: int,
    ):
        super().__init__()
        if stage is not None and not callable(stage):
            raise TypeError(f"stage must be callable, got {type(stage).__name__}")
        if terminal is not None and not callable(terminal):
            raise TypeError(f"terminal must be callable, got {type(terminal).__name__}")
        if not all(
            isinstance(d, int) and not isinstance(d, bool) and d > 0
            for d in (state_dim, control_dim)
        ):
            raise ValueError(
                f"state_dim and control_dim must be positive ints, got {state_dim}, {control_dim}"
            )
        self._stage_fn = stage
        self._terminal_fn = terminal
        self.state_dim, self.control_dim = state_dim, control_dim

    # user hooks ------------------------------------------------------------------------
    def stage(self, x: Tensor, u: Tensor, t: Tensor) -> Tensor:
        """Running cost ``(..., T)``; override or pass ``stage=``."""
        if self._stage_fn is None:
            return x.new_zeros(x.shape[:-1])
        return self._stage_fn(x, u, t)

    def terminal(self, x: Tensor) -> Tensor:
        """Terminal cost ``(...)``; override or pass ``terminal=``."""
        if self._terminal_fn is None:
            return x.new_zeros(x.shape[:-1])
        return self._terminal_fn(x)

    # evaluation ------------------------------------------------------------------------
    def _check(self, x: Tensor, u: Tensor) -> int:
        if not torch.is_tensor(x) or not torch.is_tensor(u):
            raise TypeError(
                f"x and u must be tensors (B,T+1,n) and (B,T,m), got {type(x).__name__} and "
                f"{type(u).__name__}"
            )
        if x.ndim < 3 or u.ndim < 3 or x.shape[-2] != u.shape[-2] + 1:
            raise ValueError(
                f"x must be (B,T+1,n) and u (B,T,m), got {tuple(x.shape)} and {tuple(u.shape)}"
            )
        if x.shape[-1] != self.state_dim or u.shape[-1] != self.control_dim:
            raise ValueError(
                f"expected state/control dims ({self.state_dim}, {self.control_dim}), "
                f"got x {tuple(x.shape)} and u {tuple(u.shape)}"
            )
        return u.shape[-2]

    def _steps(self, T: int, like: Tensor) -> Tensor:
        return torch.arange(T, device=like.device)

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        """Total cost ``(..., B)`` of ``x (..., B, T+1, n)``, ``u (..., B, T, m)``."""
        T = self._check(x, u)
        t = self._steps(T, x)
        xs = x[..., :T, :]
        stage = _checked_output("stage", self.stage(xs, u, t), xs.shape[:-1], "(..., T)")
        terminal = _checked_output("terminal", self.terminal(x[..., T, :]), x.shape[:-2], "(...)")
        return stage.sum(-1) + terminal

    def quadratize(self, x: Tensor, u: Tensor) -> CostExpansion:
        """Gradients and Hessians at ``(x (B,T+1,n), u (B,T,m))`` by ``torch.func``.

        Returns ``lxx (B,T+1,n,n)`` (index T: terminal), ``luu (B,T,m,m)``,
        ``lux (B,T,m,n)``, ``lx (B,T+1,n)``, ``lu (B,T,m)``, all detached.
        """
        T = self._check(x, u)
        n, m = self.state_dim, self.control_dim
        t = self._steps(T, x)
        xs, xT = x[..., :T, :].detach(), x[..., T, :].detach()
        u = u.detach()
        with torch.no_grad():
            g_stage = grad(lambda a, b: self.stage(a, b, t).sum(), argnums=(0, 1))
            lx, lu = g_stage(xs, u)
            basis = torch.eye(n + m, dtype=x.dtype, device=x.device)
            shape = (n + m, *([1] * (xs.ndim - 1)))
            ex = basis[:, :n].reshape(*shape, n).expand(n + m, *xs.shape)
            eu = basis[:, n:].reshape(*shape, m).expand(n + m, *u.shape)
            # column j of the Hessian of every row: d/ds grad(xs + s ex_j, u + s eu_j)
            # reverse-over-reverse (vjp of the gradient, the Hessian is symmetric): measured
            # ~10x faster than forward-over-reverse jvp under vmap for small models
            _, pull = vjp(g_stage, xs, u)
            cols_x, cols_u = vmap(lambda dx, du: pull((dx, du)))(ex, eu)
            # cols_x: (n+m, B, T, n) -> rows of [l_xx | l_xu]; cols_u likewise for u
            Hx = cols_x.movedim(0, -1)  # (B, T, n, n+m)
            Hu = cols_u.movedim(0, -1)  # (B, T, m, n+m)
            lxx_s, lux = Hx[..., :n], Hu[..., :n]
            luu = Hu[..., n:]
            g_term = grad(lambda a: self.terminal(a).sum())
            lxT = g_term(xT)
            eT = (
                torch.eye(n, dtype=x.dtype, device=x.device)
                .reshape(n, *([1] * (xT.ndim - 1)), n)
                .expand(n, *xT.shape)
            )
            _, pull_T = vjp(g_term, xT)
            lxxT = vmap(lambda d: pull_T(d)[0])(eT).movedim(0, -1)
        lx_full = torch.cat([lx, lxT.unsqueeze(-2)], dim=-2)
        lxx = torch.cat([lxx_s, lxxT.unsqueeze(-3)], dim=-3)
        return CostExpansion(lxx=lxx, luu=luu, lux=lux, lx=lx_full, lu=lu)
