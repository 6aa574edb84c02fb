"""The case studies of Herber & Sundarrajan (2020), Sec. 6, as :class:`LQDOProblem`\\ s.

Readings (see the module functions): the container crane's lower bound on ``xi5`` is
``-c7`` (as printed, ``c7 <= xi5`` makes ``xi5(0) = -1`` infeasible); the suspension's
road profile (refs. [8, 9]) is not in the paper and is replaced by a documented synthetic
rough road, and its horizon (not stated) is taken as 3 s.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from .problem import LQDOProblem

__all__ = [
    "container_crane",
    "crane_initial_guess",
    "van_der_pol",
    "codesign_transfer",
    "codesign_closed_form",
    "suspension",
    "SyntheticRoad",
]

INF = float("inf")

# eq. (24) constants
C1, C2, C3, C4, C5, C6, C7 = 2.83374, -0.80865, 0.71265, 17.2656, 27.0756, 2.5, 1.0


def container_crane() -> LQDOProblem:
    """Container crane, eq. (24) (``cran`` of Betts [10]): 6 states, 2 controls, t_f = 9."""

    def dyn(t, u, xi, p):
        return torch.stack(
            [
                xi[..., 3],
                xi[..., 4],
                xi[..., 5],
                u[..., 0] + C4 * xi[..., 2],
                u[..., 1],
                -(u[..., 0] + C5 * xi[..., 2] + 2 * xi[..., 4] * xi[..., 5]) / xi[..., 1],
            ],
            -1,
        )

    def lag(t, u, xi, p):
        return 0.5 * (xi[..., 2] ** 2 + xi[..., 5] ** 2 + 0.01 * (u[..., 0] ** 2 + u[..., 1] ** 2))

    return LQDOProblem(
        nu=2,
        nx=6,
        tf=9.0,
        dynamics=dyn,
        lagrange=lag,
        initial=[0.0, 22.0, 0.0, 0.0, -1.0, 0.0],
        final=[10.0, 14.0, 0.0, 2.5, 0.0, 0.0],
        xi_lb=[-INF, -INF, -INF, -C6, -C7, -INF],
        xi_ub=[INF, INF, INF, C6, C7, INF],
        u_lb=[-C1, C2],
        u_ub=[C1, C3],
    )


def crane_initial_guess(tr, B: int = 1) -> Tensor:
    """The paper's initial guess: straight lines between the initial and final states
    and from the maximum to the minimum control values (Sec. 6.1.1, Fig. 1)."""
    return tr.initial_guess(B=B, u0=[C1, C3], uf=[-C1, C2])


def van_der_pol(variant: str = "V2") -> LQDOProblem:
    """Van der Pol oscillator, eq. (25). ``V1``: t_f = 5, no state bound, -0.3 <= u <= 1,
    p = (1, 1) fixed (built with ``np = 0``); ``V2``: xi2 >= -0.4, -0.5 <= u <= 1,
    0.1 <= p <= 5 (two parameters to find)."""
    if variant not in ("V1", "V2"):
        raise ValueError(f"variant must be 'V1' or 'V2'; got {variant!r}")
    v2 = variant == "V2"

    def dyn(t, u, xi, p):
        p1 = p[..., 0] if v2 else 1.0
        p2 = p[..., 1] if v2 else 1.0
        return torch.stack(
            [xi[..., 1], -p1 * xi[..., 0] + xi[..., 1] * (1 - p2 * xi[..., 0] ** 2) + u[..., 0]],
            -1,
        )

    return LQDOProblem(
        nu=1,
        nx=2,
        np=2 if v2 else 0,
        tf=5.0,
        dynamics=dyn,
        lagrange=lambda t, u, xi, p: xi[..., 0] ** 2 + xi[..., 1] ** 2 + u[..., 0] ** 2,
        initial=[1.0, 0.0],
        xi_lb=[-INF, -0.4 if v2 else -INF],
        u_lb=[-0.5 if v2 else -0.3],
        u_ub=[1.0],
        p_lb=[0.1, 0.1] if v2 else None,
        p_ub=[5.0, 5.0] if v2 else None,
    )


def codesign_transfer(x0: float = 1.0, v0: float = 2.0, tf: float = 1.0) -> LQDOProblem:
    """Co-design transfer, eq. (26): ``min int u^2``, ``xi' = (xi2, -p1 xi1 + u)``,
    ``xi(0) = (x0, v0)``, ``xi(tf) = 0``, ``p1 >= 0``."""
    return LQDOProblem(
        nu=1,
        nx=2,
        np=1,
        tf=tf,
        dynamics=lambda t, u, xi, p: torch.stack(
            [xi[..., 1], -p[..., 0] * xi[..., 0] + u[..., 0]], -1
        ),
        lagrange=lambda t, u, xi, p: u[..., 0] ** 2,
        initial=[x0, v0],
        final=[0.0, 0.0],
        p_lb=[0.0],
    )


def codesign_closed_form(p1: float, x0: float = 1.0, v0: float = 2.0, tf: float = 1.0) -> float:
    """Exact optimum of eq. (26) for a fixed ``p1``: the minimum-energy transfer
    ``v = (e^{A tf} xi0)' W^{-1} (e^{A tf} xi0)`` with the controllability Gramian
    ``W = int_0^tf e^{A s} B B' e^{A' s} ds`` (Van Loan's block exponential)."""
    from scipy.linalg import expm

    A = np.array([[0.0, 1.0], [-p1, 0.0]])
    Bm = np.array([[0.0], [1.0]])
    M = np.zeros((4, 4))
    M[:2, :2] = -A
    M[:2, 2:] = Bm @ Bm.T
    M[2:, 2:] = A.T
    E = expm(M * tf)
    Phi = E[2:, 2:].T  # e^{A tf}
    W = Phi @ E[:2, 2:]
    y = Phi @ np.array([x0, v0])
    return float(y @ np.linalg.solve(W, y))


class SyntheticRoad:
    """A synthetic rough road (the paper's profile, refs. [8, 9], is not published with it).

    ``z0(t) = sum_j a_j sin(2 pi f_j t + phi_j)``: 40 components at temporal frequencies
    ``f_j`` log-spaced in [0.5, 8] Hz for a vehicle at 10 m/s (spatial 0.05-0.8 cycles/m),
    amplitudes from the ISO 8608 class C displacement PSD ``G_d(n) = 256e-6 (n / 0.1)^-2``
    m^3 (``a_j = sqrt(2 G_d(n_j) dn_j)``), phases uniform from ``numpy`` seed 0. Its
    derivative ``z0'(t)`` drives the suspension (eq. 27b).
    """

    def __init__(self, speed: float = 10.0, n_components: int = 40, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        f = np.geomspace(0.5, 8.0, n_components)
        n = f / speed
        edges = np.sqrt(n[1:] * n[:-1])
        dn = np.diff(np.concatenate([[n[0] ** 2 / edges[0]], edges, [n[-1] ** 2 / edges[-1]]]))
        Gd = 256e-6 * (n / 0.1) ** -2
        self.f = torch.as_tensor(f)
        self.a = torch.as_tensor(np.sqrt(2 * Gd * dn))
        self.phi = torch.as_tensor(rng.uniform(0, 2 * math.pi, n_components))

    def elevation(self, t: Tensor) -> Tensor:
        w = 2 * math.pi * self.f.to(t)
        return (self.a.to(t) * torch.sin(w * t[..., None] + self.phi.to(t))).sum(-1)

    def rate(self, t: Tensor) -> Tensor:
        w = 2 * math.pi * self.f.to(t)
        return (self.a.to(t) * w * torch.cos(w * t[..., None] + self.phi.to(t))).sum(-1)


def suspension(road: SyntheticRoad | None = None, tf: float = 3.0) -> LQDOProblem:
    """Quarter-car active suspension co-design, eq. (27). States: tyre deflection
    ``zus - z0``, unsprung velocity, suspension deflection ``zs - zus``, sprung velocity;
    control: actuator force; parameters: damper ``p1`` and spring ``p2``.
    ``min int w1 xi1^2 + w2 xi4'^2 + w3 u^2`` with ``|xi3| <= 0.04``,
    ``1e2 <= p1 <= 1e5``, ``1e2 <= p2 <= 1e6``, ``xi(0) = 0``."""
    road = road or SyntheticRoad()
    kt, ct, mus, ms = 232500.0, 0.0, 65.0, 325.0
    w1, w2, w3 = 1e5, 0.5, 1e-5

    def acc_s(u, xi, p):
        return (p[..., 0] * (xi[..., 1] - xi[..., 3]) - p[..., 1] * xi[..., 2] + u[..., 0]) / ms

    def dyn(t, u, xi, p):
        z0d = road.rate(t)
        acc_us = (
            -kt * xi[..., 0]
            - (p[..., 0] + ct) * xi[..., 1]
            + p[..., 1] * xi[..., 2]
            + p[..., 0] * xi[..., 3]
            - u[..., 0]
            + ct * z0d
        ) / mus
        return torch.stack([xi[..., 1] - z0d, acc_us, xi[..., 3] - xi[..., 1], acc_s(u, xi, p)], -1)

    def lag(t, u, xi, p):
        return w1 * xi[..., 0] ** 2 + w2 * acc_s(u, xi, p) ** 2 + w3 * u[..., 0] ** 2

    return LQDOProblem(
        nu=1,
        nx=4,
        np=2,
        tf=tf,
        dynamics=dyn,
        lagrange=lag,
        initial=[0.0, 0.0, 0.0, 0.0],
        xi_lb=[-INF, -INF, -0.04, -INF],
        xi_ub=[INF, INF, 0.04, INF],
        p_lb=[1e2, 1e2],
        p_ub=[1e5, 1e6],
    )
