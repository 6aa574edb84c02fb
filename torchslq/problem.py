"""``Problem``: dynamics + cost + horizon, the input of every solver."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from .dynamics.base import ContinuousDynamics, state_control_dims
from .dynamics.linearize import as_transition
from .dynamics.rollout import rollout
from .per_element import per_element_names, take_per_element

__all__ = ["Problem", "check_problem"]


def check_problem(problem: object) -> None:
    """TypeError unless ``problem`` is a :class:`Problem` (or a problem-like object with
    ``check_inputs``), for the solvers' front doors."""
    if not callable(getattr(problem, "check_inputs", None)):
        raise TypeError(
            f"problem must be a torchslq.Problem (dynamics, cost, horizon), got "
            f"{type(problem).__name__}"
        )


class Problem(nn.Module):
    """A discrete-time optimal control problem ``min J(x, u)`` s.t. ``x_{t+1} = f(x_t, u_t)``.

    Args:
        dynamics: a :class:`torchslq.Dynamics` (use :func:`torchslq.discretize` for a
            continuous model), or a network on ``[x, u]`` wrapped in
            :class:`torchslq.LearnedDynamics`.
        cost: a cost module with ``cost(x, u) -> (B,)`` and ``quadratize(x, u)``, e.g.
            :class:`torchslq.QuadraticCost`.
        horizon: number of steps ``T``; trajectories are ``x (B, T+1, n)``, ``u (B, T, m)``.

    Batch convention: solvers call the dynamics on ``x (..., B, 1, n)`` during rollouts
    and on ``(B, T, n)`` for linearisation, so a per-element parameter of shape
    ``(B, 1)`` broadcasts against ``x[..., 0]`` in both.
    """

    def __init__(self, dynamics: nn.Module, cost: nn.Module, horizon: int):
        super().__init__()
        if isinstance(dynamics, ContinuousDynamics):
            raise TypeError(
                f"dynamics is a ContinuousDynamics ({type(dynamics).__name__}: xdot = f(x, u)),"
                " but Problem needs x_next = f(x, u): pass discretize(model, dt) "
                "(rk4 by default)"
            )
        n, m = state_control_dims(dynamics)
        if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
            raise ValueError(f"horizon must be a positive int, got {horizon!r}")
        cn, cm = getattr(cost, "state_dim", n), getattr(cost, "control_dim", m)
        if (cn, cm) != (n, m):
            raise ValueError(
                f"cost is for state/control dims ({cn}, {cm}) but dynamics has ({n}, {m})"
            )
        if not callable(getattr(cost, "quadratize", None)):
            raise TypeError(f"cost must provide quadratize(x, u); got {type(cost).__name__}")
        self.dynamics = dynamics
        self.cost = cost
        self.horizon = horizon
        self.state_dim, self.control_dim = n, m

    @property
    def transition(self) -> Callable[[Tensor, Tensor], Tensor]:
        return as_transition(self.dynamics)

    def rollout(self, x0: Tensor, u: Tensor) -> Tensor:
        """States ``(..., B, T+1, n)`` from ``x0 (..., B, n)`` under open-loop ``u (..., B, T, m)``."""
        n, m = self.state_dim, self.control_dim
        checks = (("x0", x0, n, f"(..., B, {n})", 1), ("u", u, m, f"(..., B, T, {m})", 2))
        for name, t, k, shape, min_ndim in checks:
            if not torch.is_tensor(t) or not t.is_floating_point():
                raise TypeError(f"{name} must be a floating-point tensor of shape {shape}")
            if t.ndim < min_ndim or t.shape[-1] != k:
                raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
        return rollout(self.transition, x0, u)

    def total_cost(self, x0: Tensor, u: Tensor) -> Tensor:
        """``J(U)`` ``(..., B)`` of open-loop controls (rollout + cost)."""
        return self.cost(self.rollout(x0, u), u)

    def per_element_tensor(self, batch_size: int) -> str | None:
        """Name of the first registered tensor holding per-element data for a batch of
        ``batch_size`` (``(B, 1)``, ``(B, T+1, n)``, ...; the rule is in
        :mod:`torchslq.per_element`), or None when all problem data are batch-shared."""
        names = per_element_names(self, batch_size)
        return names[0] if names else None

    def element_faults(self, batch_size: int) -> Tensor | None:
        """``(batch_size,)`` int64 status codes of elements whose data are invalid (the
        cost's ``element_faults``, e.g. a per-element ``R`` that is not positive
        definite: ``NOT_POSITIVE_DEFINITE``), ``RUNNING`` elsewhere; None when all are
        valid. Solvers give those elements that status without solving them."""
        faults = getattr(self.cost, "element_faults", None)
        return faults(batch_size) if callable(faults) else None

    def take(self, idx: Tensor, batch_size: int) -> Problem:
        """The problem for the sub-batch ``idx`` of a batch of ``batch_size``: each
        per-element tensor indexed with ``idx`` (a shallow copy; ``self`` itself when
        the data are batch-shared). Solvers use it to work on the running elements only
        (``compact=True``)."""
        return take_per_element(self, idx, batch_size)

    def check_inputs(self, x0: Tensor, u_init: Tensor | None) -> tuple[Tensor, Tensor, bool]:
        """Validate and batch ``x0`` ``(B, n)`` or ``(n,)`` and ``u_init``; returns
        ``(x0 (B,n), u (B,T,m), unbatched)``."""
        n, m, T = self.state_dim, self.control_dim, self.horizon
        if not torch.is_tensor(x0) or not x0.is_floating_point():
            raise TypeError("x0 must be a floating-point tensor of shape (B, n) or (n,)")
        if x0.ndim not in (1, 2) or x0.shape[-1] != n:
            raise ValueError(f"x0 must have shape (B, {n}) or ({n},), got {tuple(x0.shape)}")
        unbatched = x0.ndim == 1
        x0 = x0.reshape(-1, n)
        Bsz = x0.shape[0]
        if u_init is None:
            u = x0.new_zeros(Bsz, T, m)
        else:
            if not torch.is_tensor(u_init):
                raise TypeError("u_init must be a tensor of shape (B, T, m) or (T, m)")
            if u_init.shape[-2:] != (T, m) or u_init.ndim not in (2, 3):
                raise ValueError(
                    f"u_init must have shape (B, {T}, {m}) or ({T}, {m}), got {tuple(u_init.shape)}"
                )
            if u_init.ndim == 3 and u_init.shape[0] not in (1, Bsz):
                raise ValueError(
                    f"u_init has batch size {u_init.shape[0]} but x0 has {Bsz}; expected "
                    f"u_init of shape ({Bsz}, {T}, {m}) or ({T}, {m})"
                )
            if Bsz > 1 and (u_init.ndim == 2 or u_init.shape[0] == 1):
                # initial controls shared by the batch: a NaN there is no element's fault
                if not bool(torch.isfinite(u_init).all()):
                    raise ValueError(
                        "u_init contains nan or inf (in data shared by the whole batch)"
                    )
            u = u_init.to(dtype=x0.dtype, device=x0.device).expand(Bsz, T, m).clone()
        for name, t in list(self.named_parameters()) + list(self.named_buffers()):
            if t.is_floating_point() and t.dtype != x0.dtype:
                raise TypeError(
                    f"x0 has dtype {x0.dtype} but the problem's tensor {name!r} has dtype "
                    f"{t.dtype}; convert one of them (e.g. problem.to({x0.dtype}))"
                )
            if t.device != x0.device:
                raise ValueError(
                    f"x0 is on device {x0.device} but the problem's tensor {name!r} is on "
                    f"{t.device}; move one of them (e.g. problem.to({str(x0.device)!r}))"
                )
        check_batch = getattr(self.cost, "check_batch", None)
        if callable(check_batch):  # per-element weights/targets for another batch size
            check_batch(Bsz)
        # a NaN or infinity in one row of x0 (or u_init) is that element's fault: it
        # starts as non_finite and the others are solved (the granularity rule of
        # torchslq.Status)
        return x0, u, unbatched
