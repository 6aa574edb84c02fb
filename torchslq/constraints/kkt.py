"""The KKT system of a constrained optimal-control problem with its active set held.

Unknowns ``z = (x_0, u_0, ..., x_{T-1}, u_{T-1}, x_T)`` and the multipliers ``μ`` of
``r(z) = (x0 - x_0, f(x_t, u_t) - x_{t+1}, c_A(z), u_A - b)``: the multiple-shooting form,
one dense matrix per element (index tensors, no loop over time). Used by the MPC layer's
implicit gradients (:mod:`torchslq.mpc.constrained`) and by the active-set polishing of
constrained solves (:mod:`torchslq.constraints.polish`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..lagrangian import RowMultipliers, lagrangian_terms
from .spec import ConstraintSet, ConstraintValues

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["KKTPoint", "kkt_system", "lagrangian_kkt", "symmetric_factor"]


def kkt_system(
    H_stage: Tensor,
    Q_T: Tensor,
    A: Tensor,
    Bm: Tensor,
    cx: Tensor,
    cu: Tensor,
    cxT: Tensor,
    active_stage: Tensor,
    active_terminal: Tensor,
    active_u: Tensor,
) -> Tensor:
    """The KKT matrix ``K (B, N + M, N + M)`` of the module docstring.

    Args:
        H_stage: ``(B, T, n+m, n+m)`` Hessian blocks of ``(x_t, u_t)``; Q_T ``(B, n, n)``.
        A ``(B, T, n, n)``, Bm ``(B, T, n, m)``: the dynamics' Jacobians.
        cx ``(B, T, p, n)``, cu ``(B, T, p, m)``, cxT ``(B, q, n)``: constraint Jacobians.
        active_stage ``(B, T, p)``, active_terminal ``(B, q)``, active_u ``(B, T, m)``:
            the rows held (bool).

    Unknowns: ``z = (x_0, u_0, ..., x_{T-1}, u_{T-1}, x_T)``, then the multipliers of
    ``x0 - x_0`` (n), the dynamics (T n), the stage rows (T p), the terminal rows (q) and
    the control bounds (T m). Built with index tensors (no loop over time).
    """
    Bsz, T, n, m = Bm.shape[0], Bm.shape[1], Bm.shape[2], Bm.shape[3]
    p, q = cx.shape[-2], cxT.shape[-2]
    k = n + m
    N = T * k + n
    M = n + T * n + T * p + q + T * m
    dev, dt = A.device, A.dtype
    K = A.new_zeros(Bsz, N + M, N + M)
    ar_t = torch.arange(T, device=dev)
    ar_n, ar_m = torch.arange(n, device=dev), torch.arange(m, device=dev)
    blk = (ar_t[:, None] * k + torch.arange(k, device=dev)).view(T, k)  # rows of (x_t, u_t)
    K[:, blk[:, :, None], blk[:, None, :]] = H_stage
    xT = T * k + ar_n
    K[:, xT[:, None], xT[None, :]] = Q_T
    x_cols = ar_t[:, None] * k + ar_n  # (T, n): x_t
    u_cols = ar_t[:, None] * k + n + ar_m  # (T, m): u_t
    xn_cols = (ar_t[:, None] + 1) * k + ar_n  # (T, n): x_{t+1}
    # D, written into the lower-left block and mirrored
    D = A.new_zeros(Bsz, M, N)
    D[:, ar_n, ar_n] = -1.0  # x0 - x_0
    dyn = n + ar_t[:, None] * n + ar_n  # (T, n)
    D[:, dyn[:, :, None], x_cols[:, None, :]] = A
    D[:, dyn[:, :, None], u_cols[:, None, :]] = Bm
    D[:, dyn, xn_cols] = -1.0
    base = n + T * n
    ar_p = torch.arange(p, device=dev)
    crow = base + ar_t[:, None] * p + ar_p  # (T, p)
    ws = active_stage.to(dt).unsqueeze(-1)
    D[:, crow[:, :, None], x_cols[:, None, :]] = cx * ws
    D[:, crow[:, :, None], u_cols[:, None, :]] = cu * ws
    base += T * p
    trow = base + torch.arange(q, device=dev)
    D[:, trow[:, None], xT[None, :]] = cxT * active_terminal.to(dt).unsqueeze(-1)
    base += q
    brow = base + ar_t[:, None] * m + ar_m  # (T, m)
    D[:, brow, u_cols] = active_u.to(dt)
    K[:, N:, :N] = D
    K[:, :N, N:] = D.mT
    # an inactive row's multiplier is zero: a unit diagonal in place of its equation
    inactive = torch.cat(
        [
            torch.zeros(Bsz, n + T * n, dtype=torch.bool, device=dev),
            ~active_stage.reshape(Bsz, -1),
            ~active_terminal,
            ~active_u.reshape(Bsz, -1),
        ],
        1,
    )
    idx = N + torch.arange(M, device=dev)
    K[:, idx, idx] = inactive.to(dt)
    return K


@dataclass
class KKTPoint:
    """The KKT system at a point, and what it was built from (batch-first).

    ``K (B, N+M, N+M)`` (:func:`kkt_system`); ``lam (B, T+1, n)`` costates of the
    Lagrangian ``J + λ·(f - x_next) + ν·c`` (the multipliers of the dynamics rows);
    ``grad_u (B, T, m)`` its gradient in ``u`` (without bound multipliers);
    ``values``: the constraint rows and Jacobians; ``A, B``: the dynamics' Jacobians.
    """

    K: Tensor
    lam: Tensor
    grad_u: Tensor
    values: ConstraintValues
    A: Tensor
    B: Tensor


def lagrangian_kkt(
    problem: Problem,
    constraints: ConstraintSet,
    x: Tensor,
    u: Tensor,
    nu_s: Tensor,
    nu_T: Tensor,
    act_s: Tensor,
    act_T: Tensor,
    act_u: Tensor,
    hessian: str = "exact",
) -> KKTPoint:
    """:func:`kkt_system` at ``(x (B,T+1,n), u (B,T,m))`` with stage/terminal multipliers
    ``nu_s (B,T,p)``, ``nu_T (B,q)`` and the active rows ``act_*``; ``hessian="exact"``:
    the Hessian of the Lagrangian (cost, ``λ·f_zz`` and ``ν·c_zz``), ``"gn"``: the cost's.
    Detached."""
    xl, ul = x.detach(), u.detach()
    T = problem.horizon
    with torch.no_grad():
        v = constraints.values(xl, ul, jacobians=True)
        lt = lagrangian_terms(
            problem, xl, ul, hessian, rows=RowMultipliers(constraints, v, nu_s, nu_T)
        )
        Q, R, S, A, Bm, lam = lt.Q, lt.R, lt.S, lt.A, lt.B, lt.lam
        H = torch.cat([torch.cat([Q[:, :T], S.mT], -1), torch.cat([S, R], -1)], -2)
        K = kkt_system(H, Q[:, T], A, Bm, v.cx, v.cu, v.cxT, act_s, act_T, act_u)
        grad_u = lt.lu + (Bm.mT @ lam[:, 1:].unsqueeze(-1))[..., 0]
    return KKTPoint(K=K, lam=lam, grad_u=grad_u, values=v, A=A, B=Bm)


def symmetric_factor(K: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Batched LDL' (Bunch-Kaufman) of symmetric ``K (B, N, N)``: ``(LD, pivots, ok (B,))``;
    an element whose ``K`` is not finite or singular is factorised as the identity (so it
    cannot poison the batch) and has ``ok = False``.

    LDL' rather than LU: ``K`` is symmetric indefinite, and in this torch build the first
    batched LU (``lu_factor_ex``) of large matrices after ``torch.set_num_threads`` can
    return invalid pivots (seen with MKL at ``N = 339``, ``B = 8``); the LDL' path is
    unaffected.
    """
    finite = torch.isfinite(K).flatten(1).all(1)
    eye = torch.eye(K.shape[-1], dtype=K.dtype, device=K.device)
    K = torch.where(finite.view(-1, 1, 1), K, eye)
    LD, piv, info = torch.linalg.ldl_factor_ex(K)
    ok = finite & (info == 0) & torch.isfinite(LD).flatten(1).all(1)
    if not bool(ok.all()):
        LD, piv, _ = torch.linalg.ldl_factor_ex(torch.where(ok.view(-1, 1, 1), K, eye))
    return LD, piv, ok
