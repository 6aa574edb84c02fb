"""Reproduction of L. Sforni, S. Spedicato, I. Notarnicola and G. Notarstefano, "GoPRONTO: a
Feedback-based Framework for Nonlinear Optimal Control", 2022, Section V: the
pendulum-on-cart train tracking problem.

The problem follows the paper with these readings (the paper leaves the horizon unstated
and its first pendulum equation has ``sin`` where ``cos`` belongs in front of ``w_ddot``:
as printed, the input cannot reach the pendulum near upright and the Riccati equation
for ``Qf`` has no stabilising solution):

* dynamics :class:`torchslq.systems.PendulumCartTrain` (Section V.1, ``cos`` in front of
  ``w_ddot``) with the Table I parameters, discretised by RK4 with ``delta = 0.05 s``;
* horizon ``T = 10 s`` (200 steps), reference centred at ``T/2``::

      theta_ref(t) = theta_amp f(t - T/2) / max_t f,   f(s) = tanh(s) (1 - tanh^2(s))

  (``max f = 2 / (3 sqrt 3)`` at ``tanh s = 1/sqrt 3``), ``theta_dot_ref`` its exact
  derivative, all other references zero; start at rest upright, ``x0 = 0``;
* stage cost ``|x_t - x_ref,t|^2_Q + |u_t|^2_R`` with ``Q_i = diag(100, 1, 0.1, 0.1)``,
  ``R_i = 0.1``, terminal ``|x_T - x_ref,T|^2_Qf`` with ``Qf`` the stabilising DARE
  solution for the RK4 linearisation at the upright equilibrium; ``|v|^2_W = v'Wv``
  (no 1/2), so the :class:`torchslq.QuadraticCost` (which has a 1/2) gets ``2Q, 2R, 2Qf``
  and its value is the paper's ``J``;
* projection weights for GoPRONTO (``Q_reg = Q``, ``R_reg = I``, ``Qf_reg = Qf``).

A batch of problems with different amplitudes shares the dynamics and weights; only
the reference ``x_ref (B, T+1, 4N)`` differs per element.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchslq.costs import QuadraticCost
from torchslq.dynamics import DiscretizedDynamics, linearize
from torchslq.lq.dare import dare
from torchslq.plotting import save_figure
from torchslq.problem import Problem
from torchslq.systems import PendulumCartTrain, PendulumCartTrainRK4

__all__ = [
    "SOLVER_LABELS",
    "first_below",
    "format_rows",
    "reproduce_figure5",
    "make_solver",
    "plot_grad_norms",
    "run_solver",
    "PAPER_FIG7",
    "PAPER_TABLE1_PARAMS",
    "PAPER_TABLE2",
    "PAPER_TABLE3",
    "DiagonalTrackingCost",
    "PendulumTrainSetup",
    "STAGE_WEIGHTS",
    "CONTROL_WEIGHT",
    "DT",
    "HORIZON_S",
    "pendulum_train_dynamics",
    "pendulum_train_problem",
    "terminal_weight",
    "theta_reference",
    "upright_linearization",
]

#: Table I (pendulum: Mp, l, fp; cart: Mc, ks, fc) and g.
PAPER_TABLE1_PARAMS = {
    "Mp": 0.2,
    "l": 1.0,
    "fp": 0.01,
    "Mc": 6.0,
    "ks": 0.5,
    "fc": 10.0,
    "g": 9.81,
}
#: Sampling period (s) of the RK4 discretisation and horizon (s; not stated in the paper).
DT = 0.05
HORIZON_S = 10.0
#: Per-cart ``Q_i`` diagonal and ``R_i``.
STAGE_WEIGHTS = (100.0, 1.0, 0.1, 0.1)
CONTROL_WEIGHT = 0.1

#: Table II, Gradient GoPRONTO iterations: {(N, amplitude_deg): iterations} (the
#: table's last two columns; partial-condensing HPIPM: 8/9, 14/43, x/x; OSQP: 14/50, x/x,
#: x/x for N = 3/50/100 and 60/80 degrees).
PAPER_TABLE2 = {(3, 60): 30, (3, 80): 34, (50, 60): 35, (50, 80): 39, (100, 60): 40, (100, 80): 42}
#: Table III: seconds per iteration and total seconds, {N: (PRONTO, GoPRONTO)}.
PAPER_TABLE3 = {
    "per_iteration": {
        2: (0.12, 0.05),
        5: (0.24, 0.08),
        10: (0.79, 0.18),
        50: (40.86, 6.73),
        100: (260.29, 33.13),
    },
    "total": {
        2: (0.84, 1.76),
        5: (1.92, 3.36),
        10: (7.9, 9.28),
        50: (449.6, 328.63),
        100: (3123.48, 1807.30),
    },
}
#: Figure 7 setting: N = 50, constant step 1e-3, heavy-ball weight 0.5.
PAPER_FIG7 = {"n_carts": 50, "step": 1e-3, "gamma_hb": 0.5, "iterations": 200}

_FMAX = 2.0 / (3.0 * math.sqrt(3.0))


def theta_reference(t: Tensor, amplitude_rad: Tensor | float, T: float = HORIZON_S):
    """The Section V.1 angle reference and its time derivative.

    Args:
        t: times ``(..., K)`` in seconds.
        amplitude_rad: ``theta_amp`` in radians, a number or a tensor broadcasting
            against ``t[..., :1]`` (e.g. ``(B, 1)`` for ``t (K,)`` gives ``(B, K)``).
        T: horizon (s); the curve is centred at ``T/2``.

    Returns:
        ``(theta_ref, theta_dot_ref)``, each of the broadcast shape. ``theta_ref`` swings
        from ``-theta_amp`` (at ``t = T/2 - atanh(1/sqrt 3)``) to ``+theta_amp``.
    """
    th = torch.tanh(t - 0.5 * T)
    sech2 = 1.0 - th * th
    theta = amplitude_rad * th * sech2 / _FMAX
    theta_dot = amplitude_rad * sech2 * (1.0 - 3.0 * th * th) / _FMAX
    return theta, theta_dot


def pendulum_train_dynamics(
    n_carts: int, dt: float = DT, coupling: str = "paper", **params
) -> DiscretizedDynamics:
    """RK4 discretisation (step ``dt``) of the Table I pendulum train with ``n_carts``.

    A :class:`PendulumCartTrainRK4`: the map of ``discretize(train, dt, "rk4")`` with
    Jacobians chained through the block-tridiagonal structure (same values, faster).
    """
    p = {**PAPER_TABLE1_PARAMS, **params}
    return PendulumCartTrainRK4(PendulumCartTrain(n_carts, coupling=coupling, **p), dt)


def upright_linearization(
    dynamics: DiscretizedDynamics, dtype: torch.dtype = torch.float64, device=None
) -> tuple[Tensor, Tensor]:
    """``(A (n, n), B (n, m))`` of the discrete dynamics at ``x = 0, u = 0``."""
    n, m = dynamics.state_dim, dynamics.control_dim
    x = torch.zeros(n, dtype=dtype, device=device)
    u = torch.zeros(m, dtype=dtype, device=device)
    return linearize(dynamics, x, u)


def paper_weights(
    n_carts: int, dtype: torch.dtype = torch.float64, device=None
) -> tuple[Tensor, Tensor]:
    """``Q = diag(Q_1..Q_N) (4N, 4N)`` and ``R = diag(R_1..R_N) (N, N)`` (paper scale)."""
    q = torch.tensor(STAGE_WEIGHTS, dtype=dtype, device=device).repeat(n_carts)
    r = torch.full((n_carts,), CONTROL_WEIGHT, dtype=dtype, device=device)
    return torch.diag(q), torch.diag(r)


def terminal_weight(dynamics: DiscretizedDynamics, Q: Tensor, R: Tensor) -> Tensor:
    """``Qf (n, n)``: the DARE solution at the upright linearisation (Section V.1)."""
    A, B = upright_linearization(dynamics, Q.dtype, Q.device)
    return dare(A, B, Q, R)


class DiagonalTrackingCost(QuadraticCost):
    """:class:`QuadraticCost` with constant diagonal ``Q (n, n)`` and ``R (m, m)`` and a
    dense terminal ``Qf (n, n)``, whose :meth:`weights` are cached.

    Same value and expansion as :class:`QuadraticCost` (checked in the tests; its value
    uses the elementwise path for diagonal weights, so trials of a batched line search
    do not copy ``Q``). The cache spares rebuilding the ``(T+1, n, n)`` weights
    (257 MB at ``N = 100``) at every expansion.
    """

    def __init__(self, Q: Tensor, R: Tensor, Qf: Tensor, x_ref: Tensor | None = None):
        if Q.ndim != 2 or R.ndim != 2 or Qf.ndim != 2:
            raise ValueError("DiagonalTrackingCost takes constant Q (n, n), R (m, m), Qf (n, n)")
        for name, W in (("Q", Q), ("R", R)):
            if bool((W - torch.diag(W.diagonal())).abs().max() > 0):
                raise ValueError(f"{name} must be diagonal")
        super().__init__(Q, R, Qf, x_ref=x_ref)
        self._weights_cache: dict = {}

    def weights(self, T: int) -> tuple[Tensor, Tensor]:
        key = (T, self.Q.dtype, self.Q.device)
        if key not in self._weights_cache:
            self._weights_cache = {key: super().weights(T)}
        return self._weights_cache[key]


@dataclass
class PendulumTrainSetup:
    """A batch of pendulum-train tracking problems (one per amplitude).

    Attributes:
        problem: the :class:`torchslq.Problem` (RK4 dynamics, a
            :class:`DiagonalTrackingCost` (a :class:`QuadraticCost`) with weights
            ``2Q, 2R, 2Qf`` so that its value is the paper's ``J``).
        x0: ``(B, 4N)`` initial states (zeros: at rest, upright).
        x_ref: ``(B, T+1, 4N)`` references (theta and theta_dot of every cart).
        times: ``(T+1,)`` sample times ``k * dt`` (s).
        amplitudes_deg: ``(B,)``.
        Q, R, Qf: the paper's weights ``(4N, 4N)``, ``(N, N)``, ``(4N, 4N)`` (no 1/2).
        Q_reg, R_reg, Qf_reg: GoPRONTO's projection weights ``Q``, ``I``, ``Qf``.
    """

    problem: Problem
    x0: Tensor
    x_ref: Tensor
    times: Tensor
    amplitudes_deg: Tensor
    Q: Tensor
    R: Tensor
    Qf: Tensor
    Q_reg: Tensor
    R_reg: Tensor
    Qf_reg: Tensor

    @property
    def n_carts(self) -> int:
        return self.problem.control_dim

    @property
    def batch_size(self) -> int:
        return self.x0.shape[0]


def pendulum_train_problem(
    n_carts: int,
    amplitude_deg: float | Sequence[float] | Tensor = 30.0,
    *,
    horizon_s: float = HORIZON_S,
    dt: float = DT,
    dtype: torch.dtype = torch.float64,
    device=None,
    coupling: str = "paper",
) -> PendulumTrainSetup:
    """The Section V tracking problem for ``n_carts`` carts and each amplitude.

    Args:
        n_carts: ``N``; the state has ``4N`` entries, the input ``N``.
        amplitude_deg: ``theta_amp`` in degrees: one number, or ``B`` of them for a
            batch of ``B`` problems (e.g. 30 for Figures 5-7, 60/80 for Table II).
        horizon_s, dt: horizon ``T`` (s) and RK4 step; ``round(horizon_s / dt)`` steps.
        dtype, device: of every tensor (float64 is the reference).
        coupling: spring reading of :class:`PendulumCartTrain`.
    """
    amps = torch.as_tensor(amplitude_deg, dtype=dtype, device=device).reshape(-1)
    if not bool(torch.isfinite(amps).all()):
        raise ValueError("amplitude_deg must be finite")
    steps = int(round(horizon_s / dt))
    if steps < 1 or abs(steps * dt - horizon_s) > 1e-9 * max(1.0, horizon_s):
        raise ValueError(f"horizon_s={horizon_s} must be a positive multiple of dt={dt}")
    dyn = pendulum_train_dynamics(n_carts, dt, coupling).to(dtype)
    Q, R = paper_weights(n_carts, dtype, device)
    Qf = terminal_weight(dyn, Q, R)
    Qf = 0.5 * (Qf + Qf.mT)
    times = torch.arange(steps + 1, dtype=dtype, device=device) * dt
    theta, theta_dot = theta_reference(times, torch.deg2rad(amps).unsqueeze(-1), horizon_s)
    Bsz = amps.shape[0]
    x_ref = torch.zeros(Bsz, steps + 1, n_carts, 4, dtype=dtype, device=device)
    x_ref[..., 0] = theta.unsqueeze(-1)
    x_ref[..., 1] = theta_dot.unsqueeze(-1)
    x_ref = x_ref.flatten(-2)
    cost = DiagonalTrackingCost(2.0 * Q, 2.0 * R, 2.0 * Qf, x_ref=x_ref)
    problem = Problem(dyn, cost, steps)
    x0 = torch.zeros(Bsz, 4 * n_carts, dtype=dtype, device=device)
    eye_m = torch.eye(n_carts, dtype=dtype, device=device)
    return PendulumTrainSetup(
        problem=problem,
        x0=x0,
        x_ref=x_ref,
        times=times,
        amplitudes_deg=amps,
        Q=Q,
        R=R,
        Qf=Qf,
        Q_reg=Q,
        R_reg=eye_m,
        Qf_reg=Qf,
    )


# ---------------------------------------------------------------------------- experiments
#: Solver names of the experiments: GoPRONTO variants, first-order PRONTO, and the
#: open-loop costate gradient method (Section II-B).
SOLVER_LABELS = {
    "gopronto-gradient": "Gradient GoPRONTO",
    "gopronto-conjugate": "Conjugate GoPRONTO",
    "gopronto-heavy_ball": "Heavy-Ball GoPRONTO",
    "gopronto-nesterov": "Nesterov's GoPRONTO",
    "pronto": "First-order PRONTO (W = cost Hessian)",
    "pronto-identity": "First-order PRONTO (W = I)",
    "gradient-method": "Gradient Method",
}


def make_solver(
    name: str,
    setup: PendulumTrainSetup,
    *,
    max_iter: int,
    tol: float,
    step: Any = "armijo",
    gamma_hb: float = 0.5,
    **kwargs: Any,
):
    """A solver of :data:`SOLVER_LABELS` configured as in Section V (projection weights
    ``Q_reg = Q, R_reg = I, Qf_reg = Qf``; Armijo unless ``step`` is a float; no stall
    rule unless ``stall_iters`` is passed)."""
    import torchslq

    # the paper's figures show fixed-length runs (to the iteration cap), so the library's
    # round-off stall rule (status "stalled") is off in these experiments
    kwargs.setdefault("stall_iters", 0)
    if name.startswith("gopronto-"):
        return torchslq.GoPRONTO(
            variant=name.split("-", 1)[1],
            step=step,
            max_iter=max_iter,
            tol=tol,
            gamma_hb=gamma_hb,
            Q_reg=setup.Q_reg,
            R_reg=setup.R_reg,
            Qf_reg=setup.Qf_reg,
            progress=False,
            **kwargs,
        )
    if name in ("pronto", "pronto-identity"):
        if not hasattr(torchslq, "PRONTO"):
            raise RuntimeError("torchslq.PRONTO is not available in this version")
        return torchslq.PRONTO(
            order="first",
            weights="identity" if name == "pronto-identity" else "hessian",
            step=step,
            max_iter=max_iter,
            tol=tol,
            Q_reg=setup.Q_reg,
            R_reg=setup.R_reg,
            Qf_reg=setup.Qf_reg,
            progress=False,
            **kwargs,
        )
    if name == "gradient-method":
        return torchslq.GradientMethod(
            max_iter=max_iter, tol=tol, line_search="armijo", progress=False, **kwargs
        )
    raise ValueError(f"unknown solver {name!r}; expected one of {sorted(SOLVER_LABELS)}")


def first_below(values: Sequence[float], threshold: float) -> int | None:
    """First iteration index whose value is below ``threshold`` (None if never)."""
    for k, v in enumerate(values):
        if v == v and v < threshold:
            return k
    return None


def run_solver(
    name: str, setup: PendulumTrainSetup, *, max_iter: int, tol: float, **kwargs: Any
) -> list[dict[str, Any]]:
    """Solve every problem of ``setup`` (one batch) with solver ``name``.

    Returns one record per batch element: label, amplitude, status, iterations, final
    cost and gradient norm, the histories (``grad_norm``, ``cost``; finite floats or
    None), wall time of the whole batched solve, seconds per iteration (whole batch,
    from the solver's own ``history["time"]``) and, for GoPRONTO, the number of
    projection-gain recomputations.
    """
    solver = make_solver(name, setup, max_iter=max_iter, tol=tol, **kwargs)
    t0 = time.perf_counter()
    res = solver.solve(setup.problem, setup.x0)
    wall = time.perf_counter() - t0
    htime = res.history.get("time")
    n_it = int(res.iterations.max().item())
    per_it = None
    if htime is not None and htime.numel() > 1 and n_it > 0:
        per_it = float(htime[n_it] - htime[0]) / n_it if htime.numel() > n_it else None
    recomp = getattr(res, "recomputations", None)
    out = []
    names = res.status_names()
    for b in range(setup.batch_size):
        it = int(res.iterations[b])
        gn = res.history["grad_norm"][b, : it + 1].tolist()
        J = res.history["cost"][b, : it + 1].tolist()
        out.append(
            {
                "solver": name,
                "label": SOLVER_LABELS[name],
                "n_carts": setup.n_carts,
                "amplitude_deg": float(setup.amplitudes_deg[b]),
                "status": names[b],
                "iterations": it,
                "cost": float(res.cost[b]),
                "grad_norm": float(res.grad_norm[b]),
                "grad_norm_history": [_finite(v) for v in gn],
                "cost_history": [_finite(v) for v in J],
                "wall_s": wall,
                "s_per_iteration": per_it,
                "recomputations": None if recomp is None else int(recomp[b]),
                "max_abs_theta_deg": float(
                    torch.rad2deg(res.x[b, :, 0::4].abs().max()) if res.x is not None else "nan"
                ),
            }
        )
    return out


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def plot_grad_norms(
    runs: Sequence[Mapping[str, Any]], path: str | Path, *, title: str, max_k: int | None = None
) -> Path:
    """``||grad J||`` against iteration (log scale), one line per run (Figures 5-7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for r in runs:
        gn = [float("nan") if v is None else v for v in r["grad_norm_history"]]
        if max_k is not None:
            gn = gn[: max_k + 1]
        ax.semilogy(range(len(gn)), gn, marker="." if len(gn) < 60 else None, label=r["label"])
    ax.set_xlabel("iteration k")
    ax.set_ylabel("||grad J(alpha_k, mu_k)||  (Gradient Method: ||grad_u J||)")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    ax.set_title(title, fontsize=10)
    return save_figure(fig, path)


def reproduce_figure5(max_iter: int = 50, tol: float = 1e-8) -> list[dict[str, Any]]:
    """Figure 5 in numbers (N = 2, +-30 deg, Armijo): one row per solver with the
    gradient norm at a few iterations (the ``torchslq reproduce gopronto-fig5`` table)."""
    setup = pendulum_train_problem(2, 30.0)
    rows = []
    for name in ("gopronto-gradient", "gradient-method", "pronto", "pronto-identity"):
        try:
            r = run_solver(name, setup, max_iter=max_iter, tol=tol)[0]
        except RuntimeError:  # solver not available
            continue
        h = r["grad_norm_history"]

        def at(k: int, h=h) -> str:
            return f"{h[k]:.2e}" if k < len(h) and h[k] is not None else "-"

        rows.append(
            {
                "solver": r["label"],
                "status": r["status"],
                "iterations": r["iterations"],
                "J": f"{r['cost']:.6g}",
                "grad k=0": at(0),
                "grad k=10": at(10),
                "grad k=50": at(50),
                "final grad": f"{r['grad_norm']:.2e}",
            }
        )
    return rows


def format_rows(rows: Sequence[Mapping[str, Any]]) -> str:
    """A markdown table of ``rows`` (the keys of the first row as columns)."""
    if not rows:
        return ""
    cols = list(rows[0])
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in rows]
    return "\n".join(lines)
