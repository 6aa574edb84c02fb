"""Implicit differentiation of a constrained optimal-control solution (dense KKT).

At a local solution ``z* = (x_0, u_0, x_1, ..., u_{T-1}, x_T)`` of
``min J(z; θ)`` s.t. ``x_0 = x0``, ``x_{t+1} = f(x_t, u_t; θ)``, the constraint rows
``c(z; θ)`` (:class:`torchslq.Constraints`) and control bounds, the active set is held:
equality rows, inequality rows with a positive multiplier, and controls at an active
bound become equalities; the others are dropped. The KKT residual of that
equality-constrained problem,

    R(z, μ; θ) = [∇_z J + D(z; θ)' μ ;  r(z; θ)],   r = (x0 - x_0, f - x_next, c_A, u_A - b),

has the symmetric Jacobian ``K = [[H, D'], [D, 0]]`` with ``H = ∇²_z L`` (cost, the
costate-weighted dynamics curvature and the multiplier-weighted constraint curvature;
``hessian="gn"`` keeps the cost's only) and ``D = ∂r/∂z``. By the implicit function
theorem, for a loss ``ℓ(z*)``: solve ``K w = [∂ℓ/∂z; 0]``, then

    dℓ/dθ = -w_z · ∂G/∂θ - w_μ · ∂r/∂θ,   G = ∇_z (J + λ·f + ν·c)  (multipliers fixed),

so the backward pass is one solve with the factorisation made in the forward pass and
one reverse pass through ``G`` and ``r`` evaluated with autograd recording.

The KKT matrix is dense, one per element: ``(T+1) n + T m`` primal and ``(T+1) n + T p
+ q + T m`` dual unknowns (about 560 for the cart-pole with T = 50): an LU of that size
per element costs milliseconds, so this path suits the batch sizes of training
(the unconstrained layer uses the Riccati recursion instead). Inactive rows stay in the
matrix as ``μ_i = 0`` (a unit diagonal), so every element has the same size.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ..constraints.spec import ConstraintSet
from ..costs.general import Cost
from ..dynamics.linearize import linearize_with_vhp
from ..dynamics.rollout import costate_gradient
from ..status import Status

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["constrained_implicit_solution", "kkt_system"]


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


class _ConstrainedKKTSensitivity(torch.autograd.Function):
    """``(Gx, Gu, F, x0, Cs, CT) -> (x*, u*)``; backward by the stored LU of ``K``."""

    @staticmethod
    def forward(ctx, Gx, Gu, F, x0, Cs, CT, x_star, u_star, LU, piv, good):  # noqa: D401
        ctx.save_for_backward(LU, piv, good)
        ctx.dims = (x_star.shape, u_star.shape, Cs.shape, CT.shape)
        return x_star.clone(), u_star.clone()

    @staticmethod
    @once_differentiable
    def backward(ctx, gx, gu):
        LU, piv, good = ctx.saved_tensors
        xs, us, cs, ct = ctx.dims
        Bsz, T1, n = xs
        T, m = us[1], us[2]
        p, q = cs[-1], ct[-1]
        k = n + m
        N = T * k + n
        if gx is None:
            gx = LU.new_zeros(xs)
        if gu is None:
            gu = LU.new_zeros(us)
        g = torch.where(good.view(-1, 1, 1), gx, 0.0), torch.where(good.view(-1, 1, 1), gu, 0.0)
        rhs = LU.new_zeros(Bsz, LU.shape[-1])
        z = torch.cat([g[0][:, :T], g[1]], -1).reshape(Bsz, T * k)
        rhs[:, : T * k] = z
        rhs[:, T * k : N] = g[0][:, T]
        w = torch.linalg.lu_solve(LU, piv, rhs.unsqueeze(-1))[..., 0]
        w = torch.where(good.view(-1, 1), w, 0.0)
        wz = w[:, : T * k].reshape(Bsz, T, k)
        wx = torch.cat([wz[..., :n], w[:, T * k : N].unsqueeze(1)], 1)
        wu = wz[..., n:]
        mu = w[:, N:]
        w_x0 = mu[:, :n]
        w_dyn = mu[:, n : n + T * n].reshape(Bsz, T, n)
        o = n + T * n
        w_c = mu[:, o : o + T * p].reshape(Bsz, T, p)
        w_cT = mu[:, o + T * p : o + T * p + q]
        # dℓ/dθ = -w_z·∂G/∂θ - w_μ·∂r/∂θ; r = (x0 - x_0, f - x_next, c, ...)
        none = (None,) * 5
        return -wx, -wu, -w_dyn, -w_x0, -w_c, -w_cT, *none


def constrained_implicit_solution(
    problem: Problem,
    constraints: ConstraintSet,
    x0: Tensor,
    x: Tensor,
    u: Tensor,
    multipliers: dict[str, Tensor],
    stage_eq: Tensor,
    terminal_eq: Tensor,
    *,
    hessian: str = "exact",
    active_u: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Attach implicit-KKT gradients to a constrained solution (module docstring).

    Args:
        problem: the problem solved (dynamics and cost may hold tensors requiring grad).
        constraints: its :class:`~torchslq.constraints.ConstraintSet` (may too).
        x0 ``(B, n)``; x ``(B, T+1, n)``, u ``(B, T, m)``: the solution.
        multipliers: ``{"stage": (B, T, p), "terminal": (B, q)}`` at the solution.
        stage_eq ``(p,)``, terminal_eq ``(q,)``: the rows' kinds.
        hessian: ``"exact"`` (Hessian of the Lagrangian) or ``"gn"`` (the cost's).
        active_u: ``(B, T, m)`` bool, controls at an active bound (held fixed).

    Returns:
        ``(x_out, u_out, status)``: the solution's values with the implicit backward;
        ``status`` ``(B,)`` is ``CONVERGED`` where the KKT matrix was factorised,
        ``NOT_POSITIVE_DEFINITE`` where it is singular (no derivative: zero gradient),
        ``NON_FINITE`` for a non-finite solution.
    """
    T, n, m = problem.horizon, problem.state_dim, problem.control_dim
    xs, us = x.detach(), u.detach()
    Bsz = xs.shape[0]
    finite = torch.isfinite(xs).flatten(1).all(1) & torch.isfinite(us).flatten(1).all(1)
    xl = torch.where(finite.view(-1, 1, 1), xs, torch.zeros_like(xs))
    ul = torch.where(finite.view(-1, 1, 1), us, torch.zeros_like(us))
    nu_s = torch.nan_to_num(multipliers["stage"].detach())
    nu_T = torch.nan_to_num(multipliers["terminal"].detach())
    act_s = stage_eq | (nu_s > 0)
    act_T = terminal_eq | (nu_T > 0)
    act_u = torch.zeros_like(ul, dtype=torch.bool) if active_u is None else active_u
    f = problem.transition
    with torch.no_grad():
        e = problem.cost.quadratize(xl, ul)
        v = constraints.values(xl, ul, jacobians=True)
        lx = e.lx.expand(Bsz, T + 1, n).clone()
        lx[:, :T] += (v.cx * nu_s.unsqueeze(-1)).sum(-2)
        lx[:, T] += (v.cxT * nu_T.unsqueeze(-1)).sum(-2)
        lu = e.lu.expand(Bsz, T, m) + (v.cu * nu_s.unsqueeze(-1)).sum(-2)
        A, Bm, vhp = linearize_with_vhp(f, xl[:, :T], ul)
        _, lam = costate_gradient(A, Bm, lx, lu)
        Q = e.lxx.expand(Bsz, T + 1, n, n).clone()
        R = e.luu.expand(Bsz, T, m, m).clone()
        S = ul.new_zeros(Bsz, T, m, n) if e.lux is None else e.lux.expand(Bsz, T, m, n).clone()
        if hessian == "exact":
            Hxx, Huu, Hux = vhp(lam[:, 1:])
            Q[:, :T] += Hxx
            R += Huu
            S += Hux
            if nu_s.numel() or nu_T.numel():
                # the multiplier-weighted constraint curvature, by the cost machinery
                curv = Cost(
                    stage=lambda a, b, t: (nu_s * constraints.stage_values(a, b)).sum(-1),
                    terminal=lambda a: (nu_T * constraints.terminal_values(a)).sum(-1),
                    state_dim=n,
                    control_dim=m,
                ).quadratize(xl, ul)
                Q += curv.lxx
                R += curv.luu
                S += curv.lux
        elif hessian != "gn":
            raise ValueError(f"hessian must be 'exact' or 'gn', got {hessian!r}")
        H = torch.cat([torch.cat([Q[:, :T], S.mT], -1), torch.cat([S, R], -1)], -2)
        K = kkt_system(H, Q[:, T], A, Bm, v.cx, v.cu, v.cxT, act_s, act_T, act_u)
        LU, piv, info = torch.linalg.lu_factor_ex(K)
        ok = (info == 0) & torch.isfinite(LU).flatten(1).all(1)
        if not bool(ok.all()):
            eye = torch.eye(K.shape[-1], dtype=K.dtype, device=K.device)
            K = torch.where(ok.view(-1, 1, 1), torch.nan_to_num(K), eye)
            LU, piv, _ = torch.linalg.lu_factor_ex(K)
        good = finite & ok
        status = torch.full((Bsz,), int(Status.CONVERGED), dtype=torch.int64, device=xs.device)
        status = status.masked_fill(~ok, int(Status.NOT_POSITIVE_DEFINITE))
        status = status.masked_fill(~finite, int(Status.NON_FINITE))

    lam_next = lam[:, 1:].detach()

    def lagrangian(a: Tensor, b: Tensor):
        fz = f(a[:, :T], b)
        cv = constraints.values(a, b)
        total = problem.cost(a, b).sum() + (lam_next * fz).sum()
        total = total + (nu_s * cv.stage).sum() + (nu_T * cv.terminal).sum()
        return total, (fz, cv.stage, cv.terminal)

    with torch.enable_grad():
        (Gx, Gu), (Fz, Cs, CT) = torch.func.grad(lagrangian, argnums=(0, 1), has_aux=True)(xl, ul)
        needs = (Gx, Gu, Fz, Cs, CT, x0)
        if not any(t.requires_grad for t in needs):
            return xs, us, status
        x_out, u_out = _ConstrainedKKTSensitivity.apply(
            Gx, Gu, Fz, x0.expand(Bsz, n), Cs, CT, xs, us, LU, piv, good
        )
    return x_out, u_out, status
