"""First-order PRONTO (Algorithm 1 of the GoPRONTO paper, the discrete-time version of
Hauser's PRONTO), batched: the baseline of the paper's Figure 5 and Table III.

Every iteration solves the LQ problem (14) on the linearisation about the current
trajectory ``(x, u)`` for a tangent direction ``(dx, du)`` (``dx_{t+1} = A_t dx_t + B_t du_t``,
``dx_0 = 0``) with the cost's gradients ``a = l_x``, ``b = l_u`` as linear terms and a
weight ``W``: the cost's Hessians (``weights="hessian"``: no second-order dynamics terms,
hence "first order") or the identity (``weights="identity"``). The curve
``(alpha, mu) = (x + gamma dx, u + gamma du)`` (eq. 15) is then projected by the tracking
controller ``u_t = mu_t + K_t (x_t - alpha_t)`` (Step 3), with ``gamma`` from Armijo on
``J(P(x + gamma dx, u + gamma du))``.

It reuses the whole :class:`~torchslq.solvers.gopronto.GoPRONTO` loop (batched Armijo,
per-element status, barrier, history, logger); only the direction differs. The
projection gains come from the same LQ problem with ``(Q_reg, R_reg, Qf_reg)`` and are
recomputed at every iteration by default (``recompute="always"``, as in PRONTO).
``grad_norm`` is the norm of ``grad J(alpha, mu)`` at the curve ``(x, u)`` (eq. 16), the
quantity of Figure 5, so it is comparable with GoPRONTO's. An LQ solve that fails
(``W`` not positive definite on the tangent space, e.g. an indefinite general cost) or a
direction that is not a descent direction fails the line search; with fresh gains at
every iteration the element then ends as ``LINE_SEARCH_FAILED``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from torch import Tensor

from ..lq.riccati import riccati_backward, rollout_linear
from .base import Solver
from .gopronto import GoPRONTO, PRONTOOptions, _chunk_alias, _dot

__all__ = ["PRONTO"]


class PRONTO(GoPRONTO):
    """First-order PRONTO (Algorithm 1). See the module docstring.

    Args:
        order: ``"first"`` (the only one: no second-order dynamics terms in ``W``).
        weights: ``"hessian"`` (default; ``W`` = the cost's Hessians at ``(x, u)``, the
            Gauss-Newton direction) or ``"identity"`` (``W = I``).
        step: ``"armijo"`` (default; first trial ``step0 = 1``, the full LQ step, at every
            iteration) or a constant step.
        recompute: default ``"always"`` (projection gains at every iteration).
        **kwargs: the other options of :class:`GoPRONTO` (``max_iter``, ``tol``,
            ``Q_reg``, ``R_reg``, ``Qf_reg``, ``u_max``, Armijo constants, ...);
            ``variant`` is not accepted.
    """

    name: ClassVar[str] = "pronto"
    options_class: ClassVar[type] = PRONTOOptions

    @property
    def _always_hessians(self) -> bool:
        return self.options.weights == "hessian"

    def __init__(
        self,
        order: str = "first",
        weights: str = "hessian",
        step: Any = "armijo",
        recompute: str = "always",
        *,
        max_iter: int = 200,
        tol: float = 1e-6,
        Q_reg: Any = None,
        R_reg: Any = None,
        Qf_reg: Any = None,
        stability_tol: float = 1e4,
        u_max: Any = None,
        barrier_weight: float = 1.0,
        barrier_decrease: float = 0.2,
        barrier_min: float = 1e-4,
        barrier_margin: float = 0.05,
        armijo_c1: float = 1e-4,
        armijo_beta: float = 0.5,
        max_backtracks: int = 30,
        armijo_passes: tuple[int, int | None] | None = None,
        armijo_chunk: int | None = None,
        step0: float = 1.0,
        armijo_growth: float = 4.0,
        linearize_method: str = "auto",
        progress: bool = True,
        stall_iters: int = 10,
        **unknown: Any,
    ):
        kw = {k: v for k, v in locals().items() if k not in ("self", "__class__")}
        Solver.__init__(self, **_chunk_alias(kw))

    def _direction(self, ctx: dict, problem, x0: Tensor) -> dict[str, Tensor]:
        s = ctx
        A, B, e, x, u = s["A"], s["B"], s["e"], s["x"], s["u"]
        T, n, m = A.shape[-3], A.shape[-1], B.shape[-1]
        if self.options.weights == "hessian":
            Q, R, S = e.lxx, e.luu, e.lux
        else:
            Q = torch.eye(n, dtype=x.dtype, device=x.device)
            R = torch.eye(m, dtype=x.dtype, device=x.device)
            S = None
        fac = riccati_backward(A, B, Q, R, e.lx, e.lu, S)
        dx, du = rollout_linear(A, B, fac.K, fac.k, torch.zeros_like(x0))
        da = dx[:, :T]
        slope = _dot(s["g_a"], da) + _dot(s["g_m"], du)
        bad = fac.failed.reshape(-1).expand(x.shape[0]) | ~(slope < 0)
        nan = torch.full_like(slope, float("nan"))
        return dict(
            base_a=x[:, :T],
            base_m=u,
            da=da,
            dm=du,
            ref=s["J"],
            slope=torch.where(bad, nan, slope),  # a failed LQ solve fails the line search
            plain=torch.ones_like(bad),
        )

    def _first_trial(self, gamma_prev: Tensor) -> Tensor:
        return torch.full_like(gamma_prev, self.options.step0)

    def _on_accept(self, s: dict, accept: Tensor, x: Tensor, u: Tensor) -> None:
        # PRONTO steps from the trajectory, not from the previous curve (eq. 15)
        T = u.shape[-2]
        s["alpha"] = torch.where(accept[:, None, None], x[:, :T], s["alpha"])
        s["mu"] = torch.where(accept[:, None, None], u, s["mu"])
