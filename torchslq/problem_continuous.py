"""``ContinuousProblem``: continuous-time dynamics + cost + time interval.

The input of :class:`torchslq.ContinuousILQR`::

    min  Phi(x(tf)) + int_{t0}^{tf} l(x(t), u(t), t) dt   s.t.  xdot = f(x, u, t),  x(t0) = x0
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .dynamics.base import state_control_dims
from .per_element import per_element_names

__all__ = ["ContinuousProblem"]


class ContinuousProblem(nn.Module):
    """A continuous-time optimal control problem on ``[t0, tf]``.

    Args:
        dynamics: a :class:`torchslq.ContinuousDynamics` (``forward(x, u, t) -> xdot``).
        cost: a :class:`torchslq.Cost` whose stage term is the running cost
            ``l(x, u, t)`` and whose terminal term is ``Phi(x)``. For continuous problems
            the stage's ``t`` is the time (a tensor broadcasting against ``x[..., 0]``),
            not a step index.
        t0, tf: the time interval (``tf > t0``).

    Batch convention: the dynamics and the running cost are called on ``x (B, Q, n)``,
    ``u (B, Q, m)``, ``t (B, Q)`` (``Q = 1`` inside the integrators, ``Q`` sample points
    per element when the nominal trajectory is linearised), so per-element parameters
    shaped ``(B, 1)`` broadcast.
    """

    def __init__(self, dynamics: nn.Module, cost: nn.Module, t0: float, tf: float):
        super().__init__()
        n, m = state_control_dims(dynamics)
        if not callable(dynamics):
            raise TypeError(f"dynamics must be callable, got {type(dynamics).__name__}")
        for name in ("stage", "terminal"):
            if not callable(getattr(cost, name, None)):
                raise TypeError(
                    f"cost must provide {name}() (a torchslq.Cost), got {type(cost).__name__}"
                )
        cn, cm = getattr(cost, "state_dim", n), getattr(cost, "control_dim", m)
        if (cn, cm) != (n, m):
            raise ValueError(
                f"cost is for state/control dims ({cn}, {cm}) but dynamics has ({n}, {m})"
            )
        for name, v in (("t0", t0), ("tf", tf)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v:
                raise TypeError(f"{name} must be a real number, got {v!r}")
            if v in (float("inf"), -float("inf")):  # an endless horizon: no finite solve
                raise ValueError(f"{name} must be finite, got {v!r}")
        if not tf > t0:
            raise ValueError(f"tf must be greater than t0, got t0={t0}, tf={tf}")
        self.dynamics = dynamics
        self.cost = cost
        self.t0, self.tf = float(t0), float(tf)
        self.state_dim, self.control_dim = n, m

    # evaluation on (B, Q, .) --------------------------------------------------------------
    def f(self, x: Tensor, u: Tensor, t: Tensor) -> Tensor:
        """``xdot (B, Q, n)`` at ``x (B, Q, n)``, ``u (B, Q, m)``, ``t (B, Q)``."""
        return self.dynamics(x, u, t)

    def running_cost(self, x: Tensor, u: Tensor, t: Tensor) -> Tensor:
        """``l (B, Q)`` at ``x (B, Q, n)``, ``u (B, Q, m)``, ``t (B, Q)``."""
        return self.cost.stage(x, u, t)

    def terminal_cost(self, x: Tensor) -> Tensor:
        """``Phi (B,)`` at ``x (B, n)``."""
        return self.cost.terminal(x)

    def per_element_tensor(self, batch_size: int) -> str | None:
        """Name of a registered tensor leading with ``batch_size`` (per-element data), or
        None (as :meth:`torchslq.Problem.per_element_tensor`)."""
        names = per_element_names(self, batch_size)
        return names[0] if names else None

    def check_x0(self, x0: Tensor) -> tuple[Tensor, bool]:
        """``x0`` as ``(B, n)`` and whether it was unbatched ``(n,)``."""
        n = self.state_dim
        if not torch.is_tensor(x0) or not x0.is_floating_point():
            raise TypeError("x0 must be a floating-point tensor of shape (B, n) or (n,)")
        if x0.ndim not in (1, 2) or x0.shape[-1] != n:
            raise ValueError(f"x0 must have shape (B, {n}) or ({n},), got {tuple(x0.shape)}")
        for name, t in list(self.named_parameters()) + list(self.named_buffers()):
            if t.is_floating_point() and t.dtype != x0.dtype:
                raise TypeError(
                    f"x0 has dtype {x0.dtype} but the problem's tensor {name!r} has dtype "
                    f"{t.dtype}; convert one of them (e.g. problem.to({x0.dtype}))"
                )
        return x0.reshape(-1, n), x0.ndim == 1
