"""Ready-made problems used by the CLI, the demo, examples and benchmarks.

Each builder returns ``(problem, x0)`` with ``x0 (B, n)`` drawn from a seeded generator,
so runs are repeatable.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .costs import QuadraticCost
from .dynamics import discretize
from .problem import Problem
from .systems import CartPole, DragVehicle, Hopper, Pendulum

__all__ = [
    "TASKS",
    "pendulum_swingup",
    "cartpole_swingup",
    "drag_vehicle_problem",
    "hopper_problem",
    "make_task",
    "swingup_success",
]


def _gen(seed: int) -> torch.Generator:
    g = torch.Generator()
    g.manual_seed(seed)
    return g


def pendulum_swingup(
    batch: int = 256,
    horizon: int = 100,
    dt: float = 0.05,
    seed: int = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float64,
    control_weight: float = 0.1,
) -> tuple[Problem, Tensor]:
    """Swing a damped pendulum (m = l = 1, g = 9.81, b = 0.1; RK4, ``dt``) up to
    ``theta = pi`` in ``horizon`` steps from random ``theta, theta_dot ~ U(-1, 1)``.

    Cost (1/2 convention): ``Q = dt diag(1, 0.1)``, ``R = control_weight * dt``,
    ``Qf = diag(100, 10)``, target ``[pi, 0]``.
    """
    kw = {"dtype": dtype, "device": device}
    dyn = discretize(Pendulum(), dt, "rk4").to(**kw)
    cost = QuadraticCost(
        dt * torch.diag(torch.tensor([1.0, 0.1], **kw)),
        control_weight * dt * torch.eye(1, **kw),
        Qf=torch.diag(torch.tensor([100.0, 10.0], **kw)),
        x_ref=torch.tensor([math.pi, 0.0], **kw),
    )
    x0 = (torch.rand(batch, 2, generator=_gen(seed), dtype=torch.float64) * 2 - 1).to(**kw)
    return Problem(dyn, cost, horizon), x0


def cartpole_swingup(
    batch: int = 64,
    horizon: int = 50,
    dt: float = 0.05,
    seed: int = 0,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float64,
) -> tuple[Problem, Tensor]:
    """Cart-pole swing-up of the iLQR benchmark: point-mass cart-pole (cart 1.0, tip
    0.1, length 0.5), one RK4 step per ``dt = 0.05``, ``T = 50``; cost
    ``sum 0.01 u^2 + 100 |x_T - [0, pi, 0, 0]|^2`` (i.e. ``R = 0.02``, ``Qf = 200 I`` in
    the 1/2 convention); ``x0 = [0, 0.05 N(0, 1), 0, 0]``."""
    kw = {"dtype": dtype, "device": device}
    dyn = discretize(CartPole(mc=1.0, mp=0.1, l=0.5), dt, "rk4").to(**kw)
    cost = QuadraticCost(
        torch.zeros(4, 4, **kw),
        0.02 * torch.eye(1, **kw),
        Qf=200.0 * torch.eye(4, **kw),
        x_ref=torch.tensor([0.0, math.pi, 0.0, 0.0], **kw),
    )
    x0 = torch.zeros(batch, 4, dtype=torch.float64)
    x0[:, 1] = 0.05 * torch.randn(batch, generator=_gen(seed), dtype=torch.float64)
    return Problem(dyn, cost, horizon), x0.to(**kw)


def swingup_success(x: Tensor, angle_index: int = 0, tol: float = 0.1) -> Tensor:
    """``(B,)`` bool: final angle within ``tol`` rad of upright (``pi`` modulo ``2 pi``)."""
    th = x[..., -1, angle_index]
    err = torch.remainder(th - math.pi + math.pi, 2 * math.pi) - math.pi
    return err.abs() < tol


#: Sideris & Bobrow (2005), Section 4.1 constants (m = 25.9 g read as 0.0259 kg: with
#: m = 25.9 kg the target is never reached and Table 1 cannot be reproduced).
DRAG = {"m": 0.0259, "N": 500, "q": 1.0, "r": 10.0, "qfin": 1e6, "target": 10.0}
#: Sideris & Bobrow (2005), Section 4.2 constants (the gas-actuated hopper).
HOPPER = {
    "k_over_m": 500.0,
    "g": 386.4,
    "alpha": 0.1,
    "tf": 1.0,
    "N": 100,
    "qfin": 1000.0,
    "q": 1000.0,
    "r": 1.0,
}


#: Table 1's drag coefficients and Section 4.2's target heights.
TABLE1_BETAS = (0.01, 0.05, 0.1, 0.5, 1.0)
HOPPER_TARGETS = (1.0, 20.0, 50.0)


def _as_column(values: float | Sequence[float] | Tensor, dtype, device) -> Tensor:
    t = torch.as_tensor(values, dtype=dtype, device=device).reshape(-1, 1)
    if t.numel() == 0:
        raise ValueError("need at least one value")
    return t


def drag_vehicle_problem(
    betas: float | Sequence[float] | Tensor = TABLE1_BETAS,
    *,
    m: float = DRAG["m"],
    N: int = DRAG["N"],
    q: float = DRAG["q"],
    r: float = DRAG["r"],
    qfin: float = DRAG["qfin"],
    target: float = DRAG["target"],
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[Problem, Tensor]:
    """The viscous-drag vehicle of Sideris & Bobrow (2005), Section 4.1, eqs. (63)-(65),
    one batch element per beta; the cost is eq. (65) as printed (no 1/2).

    Returns ``(problem, x0)`` with ``x0 = 0`` of shape ``(B, 2)``; ``beta`` is a ``(B, 1)``
    parameter of :class:`torchslq.systems.DragVehicle`.
    """
    beta = _as_column(betas, dtype, device)
    Ts = 1.0 / N
    dyn = DragVehicle(beta=beta, m=m, Ts=Ts)
    eye = torch.eye(2, dtype=dtype, device=device)
    x_ref = torch.zeros(N + 1, 2, dtype=dtype, device=device)
    x_ref[N, 0] = target
    cost = QuadraticCost(
        Q=2.0 * Ts * q * eye,
        R=torch.full((1, 1), 2.0 * Ts * r, dtype=dtype, device=device),
        Qf=torch.diag(torch.tensor([2.0 * qfin, 0.0], dtype=dtype, device=device)),
        x_ref=x_ref,
    )
    x0 = torch.zeros(beta.shape[0], 2, dtype=dtype, device=device)
    return Problem(dyn, cost, horizon=N), x0


def hopper_problem(
    y_targets: float | Sequence[float] | Tensor = HOPPER_TARGETS,
    *,
    qfin: float = HOPPER["qfin"],
    q: float = HOPPER["q"],
    r: float = HOPPER["r"],
    N: int = HOPPER["N"],
    tf: float = HOPPER["tf"],
    k_over_m: float = HOPPER["k_over_m"],
    g: float = HOPPER["g"],
    alpha: float = HOPPER["alpha"],
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[Problem, Tensor]:
    """The gas-actuated hopper of Sideris & Bobrow (2005), Section 4.2, with the literal
    reading of the garbled eq. (66), one batch element per target height ``y°`` (a
    per-element terminal reference).

    Returns ``(problem, x0)`` with ``x0 = 0`` of shape ``(B, 3)`` (state ``[y, ydot, yp]``).
    """
    yt = _as_column(y_targets, dtype, device)[:, 0]
    Bsz = yt.shape[0]
    dyn = Hopper(k_over_m=k_over_m, g=g, alpha=alpha, tf=tf, N=N)
    w = tf / N
    x_ref = torch.zeros(Bsz, N + 1, 3, dtype=dtype, device=device)
    x_ref[:, N, 0] = yt
    cost = QuadraticCost(
        Q=torch.diag(torch.tensor([0.0, 0.0, q * w], dtype=dtype, device=device)),
        R=torch.full((1, 1), r * w, dtype=dtype, device=device),
        Qf=torch.diag(torch.tensor([qfin, 2.0, 0.0], dtype=dtype, device=device)),
        x_ref=x_ref,
    )
    x0 = torch.zeros(Bsz, 3, dtype=dtype, device=device)
    return Problem(dyn, cost, horizon=N), x0


#: The drag coefficients of the ``drag-vehicle`` task (the CLI's): Table 1's without
#: beta = 1. There the explicit Euler step of the drag is unstable above
#: ``m / (beta Ts) = 12.95`` m/s, below the speed the target needs, so the discrete
#: problem is ill-posed: its minimiser exploits the instability (iLQR "converges" to a
#: cost below beta = 0.5's with speeds of 5e5 m/s; SLQ stops at a round-off floor), and
#: the paper reports no convergence. The reproduction (``reproductions.sideris``) keeps it.
DRAG_TASK_BETAS = tuple(b for b in TABLE1_BETAS if b < 1.0)


def _drag(batch: int = 4, seed: int = 0, device="cpu", dtype=torch.float64, **_):
    betas = list(DRAG_TASK_BETAS)
    betas = (betas * (batch // len(betas) + 1))[:batch]
    problem, x0 = drag_vehicle_problem(betas, dtype=dtype)
    return problem.to(device), x0.to(device)


def _hopper(batch: int = 3, seed: int = 0, device="cpu", dtype=torch.float64, **_):
    targets = list(HOPPER_TARGETS)
    targets = (targets * (batch // len(targets) + 1))[:batch]
    problem, x0 = hopper_problem(targets, dtype=dtype)
    return problem.to(device), x0.to(device)


TASKS: dict[str, Callable[..., tuple[Problem, Tensor]]] = {
    "pendulum": pendulum_swingup,
    "cartpole": cartpole_swingup,
    "drag-vehicle": _drag,
    "hopper": _hopper,
}


def make_task(name: str, **kwargs) -> tuple[Problem, Tensor]:
    """Build a task by name (see :data:`TASKS`)."""
    if name not in TASKS:
        raise ValueError(f"unknown system {name!r}; choose from {', '.join(TASKS)}")
    return TASKS[name](**kwargs)
