"""The batched Riccati recursion and linear rollout: the one LQ kernel of torchslq.

Every solver that needs an LQ solve (SLQ, iLQR/DDP, GoPRONTO's projection, the MPC
layer's implicit backward) goes through the two functions here.

Homogeneous form
----------------
Internally a stage is written in homogeneous coordinates ``z_t = [u_t; x_t; 1]``
(``m + n + 1`` entries) and ``xh_t = [x_t; 1]``:

* dynamics ``xh_{t+1} = F_t z_t`` with ``F_t = [[B_t, A_t, c_t], [0, 0, 1]]``,
* stage cost ``1/2 z_t' H_t z_t`` with ``H_t = [[R, S, r], [S', Q, q], [r', q', 0]]``,
* value function ``1/2 xh' Vh_t xh`` with ``Vh_t = [[V_t, v_t], [v_t', 2 c_t]]``.

One backward step is then ``M = H_t + F_t' Vh_{t+1} F_t`` (two matmuls), a Cholesky
factorisation of ``Quu = M[:m, :m]``, one triangular solve for the feedback and
feedforward gains together (``[K_t, k_t] = -Quu^{-1} M[:m, m:]``) and one update
``Vh_t = M[m:, m:] + M[:m, m:]' [K_t, k_t]``. This is the standard gain form of
the Riccati recursion (Quu = R + B'VB, K = -Quu^{-1} Qux, k = -Quu^{-1} qu); without a
cross term it is algebraically Algorithm 1 of Sideris & Bobrow (2005), eqs. (21)-(26),
which ``tests/test_lq_kernel.py`` checks against a literal transcription.

The loop over time is inherent; its body is a handful of batched kernels and has no
host synchronisation. A Cholesky failure (``Quu`` not positive definite) is recorded
per element by ``cholesky_ex`` and never stops the batch.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from .._backend import (
    PIECE_NDIMS,
    can_use_compiled,
    lq_rollout_compiled,
    riccati_compiled,
    rollout_compiled,
)
from .._shapes import broadcast_shapes
from .boxqp import box_qp
from .regularization import RegularizationSchedule, Restarts

StageHook = Callable[[int, Tensor], Tensor]

__all__ = [
    "RegularizationSchedule",
    "Restarts",
    "RiccatiFactors",
    "riccati_backward",
    "rollout_linear",
    "homogeneous_dynamics",
    "homogeneous_cost",
]


@dataclass
class RiccatiFactors:
    """Output of :func:`riccati_backward`.

    Attributes:
        K: feedback gains ``(B, T, m, n)``; the optimal control is ``u_t = K_t x_t + k_t``.
        k: feedforward terms ``(B, T, m)``.
        V: value-function Hessians ``(B, T+1, n, n)``.
        v: value-function gradients ``(B, T+1, n)``.
        chol: lower Cholesky factors of ``Quu`` ``(B, T, m, m)``, reusable for a second
            solve with the same quadratic terms (the implicit backward pass).
        failed: ``(B,)`` bool, True where some ``Quu`` was not positive definite (with
            ``restarts``: where the last pass failed, non-finite gains included).
        Kk: ``(B, T, m, n+1)``, ``[K_t, k_t]`` side by side (what the rollout uses).
        Vh: ``(B, T+1, n+1, n+1)``, homogeneous value matrices (``Vh[..., n, n]`` is
            twice the constant term of the cost-to-go).
        clamped: with control bounds only (else None): ``(B, T, m)`` bool, the controls
            clamped by the box QP of each step (their feedback rows are zero; ``chol``
            then holds the factor of the free block, identity on clamped rows/columns).
        dV: with control bounds only (else None): ``(B, 2)``, the expected-improvement
            terms ``[sum_t k_t'Q_u,t, sum_t k_t'(Q_uu,t + reg) k_t]`` of the step.
        reg, reg_delta: with the ``restarts`` of :func:`riccati_backward` (else None):
            ``(B,)``, the regularisation ``mu`` of each element's last pass and its
            schedule factor ``delta``, on every backend.
    """

    Kk: Tensor
    Vh: Tensor
    chol: Tensor
    failed: Tensor
    clamped: Tensor | None = None
    dV: Tensor | None = None
    reg: Tensor | None = None
    reg_delta: Tensor | None = None

    @property
    def K(self) -> Tensor:
        return self.Kk[..., :-1]

    @property
    def k(self) -> Tensor:
        return self.Kk[..., -1]

    @property
    def V(self) -> Tensor:
        return self.Vh[..., :-1, :-1]

    @property
    def v(self) -> Tensor:
        return self.Vh[..., :-1, -1]


def with_time(t: Tensor | None, tail_ndim: int, steps: int) -> Tensor | None:
    """Expand the time dim of an argument to ``steps``: a constant (no time dim, e.g.
    ``(n, n)``) or a time dim of 1 broadcasts over the horizon."""
    if t is None or (t.ndim > tail_ndim and t.shape[-tail_ndim - 1] == steps):
        return t
    if t.ndim == tail_ndim:
        t = t.unsqueeze(0)
    return t.expand(*t.shape[: -tail_ndim - 1], steps, *t.shape[-tail_ndim:])


def cholesky(A: Tensor) -> tuple[Tensor, Tensor]:
    """``torch.linalg.cholesky_ex`` with a closed form for ``1 x 1`` matrices.

    Batched LAPACK factorisations run one small call per matrix; for a single control
    (``m = 1``, the common case) a square root over the batch is far cheaper. ``info`` is
    non-zero where the matrix is not positive definite (or not finite), as with LAPACK.
    """
    if A.shape[-1] == 1:
        info = (~(A[..., 0, 0] > 0)).to(torch.int32)
        return A.clamp_min(0).sqrt(), info
    return torch.linalg.cholesky_ex(A)


def chol_solve(rhs: Tensor, L: Tensor) -> Tensor:
    """``(L L')^{-1} rhs`` (``torch.cholesky_solve``), with the ``1 x 1`` case in closed form."""
    if L.shape[-1] == 1:
        return rhs / (L * L)
    return torch.cholesky_solve(rhs, L)


def _sym(X: Tensor) -> Tensor:
    return 0.5 * (X + X.mT)


def homogeneous_dynamics(A: Tensor, B: Tensor, c: Tensor | None = None) -> Tensor:
    """``F_t = [[B_t, A_t, c_t], [0, 0, 1]]`` of shape ``(..., T, n+1, m+n+1)``.

    ``A (..., T, n, n)``, ``B (..., T, n, m)`` and ``c (..., T, n)`` broadcast together.
    """
    n, m = A.shape[-1], B.shape[-1]
    if c is None:
        c = A.new_zeros(()).expand(*A.shape[:-1])
    lead = broadcast_shapes(A.shape[:-2], B.shape[:-2], c.shape[:-1])
    top = torch.cat(
        [B.expand(*lead, n, m), A.expand(*lead, n, n), c.expand(*lead, n).unsqueeze(-1)], dim=-1
    )
    bottom = A.new_zeros(*lead, 1, m + n + 1)
    bottom[..., 0, -1] = 1.0
    return torch.cat([top, bottom], dim=-2)


def homogeneous_cost(
    Q: Tensor,
    R: Tensor,
    q: Tensor | None = None,
    r: Tensor | None = None,
    S: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Stage matrices ``H_t (..., T, m+n+1, m+n+1)`` and terminal ``Vh_T (..., n+1, n+1)``.

    ``Q (..., T+1, n, n)`` (index T is the terminal weight), ``R (..., T, m, m)``,
    ``q (..., T+1, n)``, ``r (..., T, m)``, ``S (..., T, m, n)``; all broadcast. ``Q`` and
    ``R`` enter through their symmetric parts.
    """
    n, m = Q.shape[-1], R.shape[-1]
    T = R.shape[-3]
    Q = _sym(Q)
    R = _sym(R)
    if q is None:
        q = Q.new_zeros(()).expand(*Q.shape[:-1])
    if r is None:
        r = R.new_zeros(()).expand(*R.shape[:-1])
    if S is None:
        S = R.new_zeros(()).expand(*R.shape[:-3], T, m, n)
    Qs, qs = Q[..., :T, :, :], q[..., :T, :]
    lead = broadcast_shapes(Qs.shape[:-2], R.shape[:-2], qs.shape[:-1], r.shape[:-1], S.shape[:-2])
    Qs, R, S = Qs.expand(*lead, n, n), R.expand(*lead, m, m), S.expand(*lead, m, n)
    qs, r = qs.expand(*lead, n).unsqueeze(-1), r.expand(*lead, m).unsqueeze(-1)
    corner = Q.new_zeros(*lead, 1, 1)
    H = torch.cat(
        [
            torch.cat([R, S, r], dim=-1),
            torch.cat([S.mT, Qs, qs], dim=-1),
            torch.cat([r.mT, qs.mT, corner], dim=-1),
        ],
        dim=-2,
    )
    QT, qT = Q[..., T, :, :], q[..., T, :]
    lead_T = broadcast_shapes(QT.shape[:-2], qT.shape[:-1])
    QT, qT = QT.expand(*lead_T, n, n), qT.expand(*lead_T, n).unsqueeze(-1)
    VhT = torch.cat(
        [torch.cat([QT, qT], dim=-1), torch.cat([qT.mT, Q.new_zeros(*lead_T, 1, 1)], dim=-1)],
        dim=-2,
    )
    return H, VhT


def riccati_homogeneous(
    F: Tensor,
    H: Tensor,
    VhT: Tensor,
    reg: Tensor | float | None = None,
    stage_hook: StageHook | None = None,
    u_bounds: tuple[Tensor, Tensor] | None = None,
) -> RiccatiFactors:
    """Backward Riccati pass in homogeneous form (see the module docstring).

    Args:
        F: ``(Bf, T, n+1, m+n+1)`` homogeneous dynamics.
        H: ``(Bh, T, m+n+1, m+n+1)`` homogeneous stage costs.
        VhT: ``(Bv, n+1, n+1)`` terminal value matrix.
        reg: optional Levenberg-Marquardt term added to ``Quu`` (scalar or ``(B,)``);
            the value update then uses the regularisation-consistent form of
            Tassa et al. (2012), ``V = Qxx + K'Quu K + K'Qux + Qux'K`` with the
            unregularised ``Quu``.

        stage_hook: optional ``hook(t, Vh_next) -> (B, m+n, m+n)``, a term added to the
            ``[u; x]`` block of the stage Hessian at step ``t`` that may depend on the
            value function of step ``t+1`` (DDP's ``V_x · f_zz`` second-order dynamics
            terms); ``None`` for the plain LQ recursion. A hook whose term is
            ``sum_i v_{t+1,i} Hz[t, i]`` can expose ``Hz (T, n, B, m+n, m+n)``, or the
            same Hessians as blocks ``(Hxx, Huu, Hux)`` each ``(n, B, T, ., .)``, as its
            ``hessians`` attribute, which lets the compiled CPU kernel
            (:mod:`torchslq._backend`) run the pass.
        u_bounds: optional ``(lower, upper)`` bounds on the control ``u_t`` of this LQ
            problem (in deviation coordinates: bounds on ``δu_t``), each broadcastable
            to ``(B, T, m)``, infinite entries allowed, and containing 0 for the
            expected-improvement terms to be meaningful. See
            :func:`_riccati_box` (control-limited DDP, Tassa et al. 2014).

    The batch sizes ``Bf, Bh, Bv`` broadcast (1 or B). On the CPU without autograd the
    pass (with or without bounds) runs as one compiled kernel
    (:mod:`torchslq._backend`, same equations); otherwise as batched torch ops per
    step.
    """
    T = F.shape[-3]
    n = F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    batch = broadcast_shapes(F.shape[:-3], H.shape[:-3], VhT.shape[:-2])
    bounds, batch = _pass_batch(batch, reg, u_bounds, T, m, F.dtype)
    hessians = getattr(stage_hook, "hessians", None)
    if (
        T > 0
        and (stage_hook is None or hessians is not None)
        and can_use_compiled(F, H, VhT, *(bounds or ()), *_tensors(reg, hessians))
    ):
        tol = _box_tol(F.dtype)
        return RiccatiFactors(*riccati_compiled(F, H, VhT, reg, hessians, batch, bounds, tol))
    if bounds is not None:
        return _riccati_box(F, H, VhT, reg, stage_hook, bounds, batch)
    Vh = VhT.expand(*batch, n + 1, n + 1)
    eye_m = torch.eye(m, dtype=F.dtype, device=F.device)
    if reg is not None:
        reg_t = torch.as_tensor(reg, dtype=F.dtype, device=F.device)
        reg_eye = reg_t.reshape(*reg_t.shape, 1, 1) * eye_m
    Vhs: list[Tensor] = [Vh] * (T + 1)
    Kks: list[Tensor] = [Vh] * T
    Ls: list[Tensor] = [Vh] * T
    infos: list[Tensor] = []
    # time-major contiguous copies of F and F': batched matmuls of tiny matrices with
    # strided operands measured 1.8-2.5x slower (B = 1024, T = 100) than contiguous ones
    Fs = F.expand(*batch, *F.shape[-3:]).movedim(-3, 0).contiguous()
    FsT = Fs.mT.contiguous()
    for t in range(T - 1, -1, -1):
        M = H[..., t, :, :] + FsT[t] @ (Vh @ Fs[t])
        if stage_hook is not None:
            M = M + torch.nn.functional.pad(stage_hook(t, Vh), (0, 1, 0, 1))
        Quu = M[..., :m, :m]
        Qu_xh = M[..., :m, m:]
        if reg is None:
            L, info = cholesky(Quu)
            Kk = -chol_solve(Qu_xh, L)
            Vh = M[..., m:, m:] + Qu_xh.mT @ Kk
        else:
            L, info = cholesky(Quu + reg_eye)
            Kk = -chol_solve(Qu_xh, L)
            KtQuu = Kk.mT @ Quu
            cross = Kk.mT @ Qu_xh
            Vh = M[..., m:, m:] + KtQuu @ Kk + cross + cross.mT
        Vh = _sym(Vh)
        Vhs[t], Kks[t], Ls[t] = Vh, Kk, L
        infos.append(info)
    failed = (
        torch.stack(infos, dim=-1).ne(0).any(dim=-1)
        if T > 0
        else Vh.new_zeros(batch, dtype=torch.bool)
    )
    return RiccatiFactors(
        Kk=torch.stack([K.expand(*batch, m, n + 1) for K in Kks], dim=-3),
        Vh=torch.stack(Vhs, dim=-3),
        chol=torch.stack([L.expand(*batch, m, m) for L in Ls], dim=-3),
        failed=failed.expand(batch),
    )


def _riccati_box(
    F: Tensor,
    H: Tensor,
    VhT: Tensor,
    reg: Tensor | float | None,
    stage_hook: StageHook | None,
    u_bounds: tuple[Tensor, Tensor],
    batch: torch.Size,
) -> RiccatiFactors:
    """Control-limited backward pass (Tassa, Mansard & Todorov 2014, Section III), torch
    path (bounds ``u_bounds = (lower, upper)`` already expanded to ``(*batch, T, m)``).

    At each step the feedforward term solves the box QP
    ``k_t = argmin 1/2 k'(Q_uu + reg I)k + k'Q_u`` s.t. ``lower_t <= k <= upper_t``
    (:func:`torchslq.lq.box_qp`, warm-started from ``k_{t+1}`` projected into the box);
    the feedback rows of the clamped controls are zero and the free rows are
    ``K_f = -(Q_uu + reg I)_ff^{-1} Q_ux,f`` from the box QP's free-block factor; the
    value update is the general form ``Vh = Q_zz + Kk'Q_uu Kk + Kk'Q_uz + Q_uz'Kk`` with
    ``Kk = [K, k]`` (which is exact for any gains, so also with ``reg``). A step whose
    free block is not positive definite is reported in ``failed``.

    A host synchronisation every box-QP iteration (every third on an accelerator) ends
    the QP once every element has converged (projected Newton typically needs 1-3
    iterations from the warm start); this is the one place where the kernel's time
    loop synchronises, and only with bounds.
    """
    T = F.shape[-3]
    n = F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    lower, upper = u_bounds  # (*batch, T, m), see riccati_homogeneous
    tol = _box_tol(F.dtype)
    Vh = VhT.expand(*batch, n + 1, n + 1)
    eye_m = torch.eye(m, dtype=F.dtype, device=F.device)
    reg_eye = None
    if reg is not None:
        reg_t = torch.as_tensor(reg, dtype=F.dtype, device=F.device)
        reg_eye = reg_t.reshape(*reg_t.shape, 1, 1) * eye_m
    check_every = 1 if F.device.type == "cpu" else 3  # a host sync is free on the CPU
    Vhs: list[Tensor] = [Vh] * (T + 1)
    Kks: list[Tensor] = [Vh] * T
    Ls: list[Tensor] = [Vh] * T
    clamps: list[Tensor] = [Vh] * T
    oks: list[Tensor] = []
    slope = Vh.new_zeros(batch)
    curv = Vh.new_zeros(batch)
    k = Vh.new_zeros(*batch, m)
    for t in range(T - 1, -1, -1):
        Ft = F[..., t, :, :]
        M = H[..., t, :, :] + Ft.mT @ (Vh @ Ft)
        if stage_hook is not None:
            M = M + torch.nn.functional.pad(stage_hook(t, Vh), (0, 1, 0, 1))
        M = M.expand(*batch, m + n + 1, m + n + 1)
        Quu = M[..., :m, :m]
        Qu_xh = M[..., :m, m:]
        Quu_r = Quu if reg_eye is None else Quu + reg_eye
        qu = Qu_xh[..., -1]
        qp = box_qp(
            Quu_r,
            qu,
            lower[..., t, :],
            upper[..., t, :],
            x0=k,
            tol=tol * (1.0 + qu.abs().amax(-1)),
            check_every=check_every,
        )
        k, L = qp.x, qp.chol
        free = ~qp.clamped
        rhs = torch.where(free.unsqueeze(-1), Qu_xh[..., :n], torch.zeros_like(Qu_xh[..., :n]))
        Kk = torch.cat([-chol_solve(rhs, L), k.unsqueeze(-1)], dim=-1)
        KtQuu = Kk.mT @ Quu
        cross = Kk.mT @ Qu_xh
        Vh = _sym(M[..., m:, m:] + KtQuu @ Kk + cross + cross.mT)
        slope = slope + (k * qu).sum(-1)
        curv = curv + (k * (Quu_r @ k.unsqueeze(-1))[..., 0]).sum(-1)
        Vhs[t], Kks[t], Ls[t], clamps[t] = Vh, Kk, L, qp.clamped
        oks.append(qp.success)
    failed = (
        ~torch.stack(oks, dim=-1).all(dim=-1) if T > 0 else Vh.new_zeros(batch, dtype=torch.bool)
    )
    return RiccatiFactors(
        Kk=torch.stack(Kks, dim=-3) if T > 0 else Vh.new_zeros(*batch, 0, m, n + 1),
        Vh=torch.stack(Vhs, dim=-3),
        chol=torch.stack(Ls, dim=-3) if T > 0 else Vh.new_zeros(*batch, 0, m, m),
        failed=failed,
        clamped=(
            torch.stack(clamps, dim=-2)
            if T > 0
            else torch.zeros(*batch, 0, m, dtype=torch.bool, device=F.device)
        ),
        dV=torch.stack([slope, curv], dim=-1),
    )


def _pass_batch(
    batch, reg, u_bounds: tuple[Tensor, Tensor] | None, T: int, m: int, dtype: torch.dtype
) -> tuple[tuple[Tensor, Tensor] | None, torch.Size]:
    """A pass's batch shape (the data's ``batch`` grown by a per-element ``reg`` and by
    the bounds') and the bounds ``(lower, upper)`` expanded to ``(*batch, T, m)``."""
    if reg is not None and torch.is_tensor(reg) and reg.ndim > 0:
        batch = broadcast_shapes(batch, reg.shape)
    if u_bounds is None:
        return None, batch
    lower, upper = (with_time(b.reshape(1) if b.ndim == 0 else b, 1, T).to(dtype) for b in u_bounds)
    batch = broadcast_shapes(batch, lower.shape[:-2], upper.shape[:-2])
    return (lower.expand(*batch, T, m), upper.expand(*batch, T, m)), batch


def _compiled_pieces_pass(
    A, B, Q, R, q, r, S, c, reg, stage_hook, u_bounds, restarts: Restarts | None = None
) -> RiccatiFactors | None:
    """:func:`riccati_backward` on the compiled kernel straight from the LQ data (its
    homogeneous ``F``, ``H`` are assembled per step inside the kernel, never built), or
    None where the compiled path does not apply (the caller takes the torch path)."""
    T, m = A.shape[-3], B.shape[-1]
    hessians = getattr(stage_hook, "hessians", None)
    if A.device.type != "cpu" or T == 0 or (stage_hook is not None and hessians is None):
        return None  # (the cheap tests first: GPU passes pay nothing here)
    pieces, shapes = [], []
    for p, nd, steps in zip(
        (A, B, c, Q, R, S, q, r), PIECE_NDIMS, (T, T, T, T + 1, T, T, T + 1, T), strict=True
    ):
        if p is not None:
            tail = nd - 2  # the matrix or vector dims
            if p.ndim == tail:
                p = p.unsqueeze(0)  # no time dim: constant over the horizon
            if p.ndim < tail + 1 or p.shape[-tail - 1] not in (1, steps):
                return None  # let the torch path report the shape error
            shapes.append(p.shape[: p.ndim - tail - 1])
        pieces.append(p)
    bounds, batch = _pass_batch(broadcast_shapes(*shapes), reg, u_bounds, T, m, A.dtype)
    extra = _tensors(reg, hessians)
    if not can_use_compiled(*[p for p in pieces if p is not None], *(bounds or ()), *extra):
        return None
    if restarts is not None:
        _check_restart_batch(batch)
        delta, allowed = restarts.delta, restarts.allowed
        restarts = (
            reg,
            torch.ones(batch, dtype=A.dtype) if delta is None else delta,
            torch.ones(batch, dtype=torch.bool) if allowed is None else allowed,
            restarts.options,
        )
    out = riccati_compiled(
        None,
        None,
        None,
        reg,
        hessians,
        batch,
        bounds,
        _box_tol(A.dtype),
        pieces=tuple(pieces),
        restarts=restarts,
    )
    return RiccatiFactors(*out)


# the most rows one torch pass of side-by-side restarts may have (failing elements x
# candidates; a constant, so that the passes an element needs do not depend on the
# batch around it)
RETRY_ROWS = 2048
# dims after the batch dim of (A, B, Q, R, q, r, S, c) in riccati_backward
_DATA_TAILS = (3, 3, 3, 3, 2, 2, 3, 2)


def _check_restart_batch(batch) -> None:
    if len(batch) != 1:
        raise ValueError(f"restarts need one batch dim, got batch shape {tuple(batch)}")


def _ones(t: Tensor | None, batch, dtype: torch.dtype) -> Tensor:
    """``t`` (a restart's ``delta`` or ``allowed``) or ones, broadcast to ``batch``."""
    if t is None:
        return torch.ones(batch, dtype=dtype)
    return t.to(dtype).expand(batch)


def failed_or_nonfinite(fac: RiccatiFactors) -> Tensor:
    """``(B,)``: the pass failed, or its gains are not finite (a factorisation can succeed
    and still give non-finite gains, e.g. DDP's second-order terms overflowing)."""
    return fac.failed | ~torch.isfinite(fac.Kk).flatten(1).all(1)


def _restarted(data: tuple, reg: Tensor, hook, u_bounds, restarts: Restarts) -> RiccatiFactors:
    """:func:`riccati_backward` with ``restarts`` on the torch path (``data = (A, B, Q, R,
    q, r, S, c)``; ``reg`` a tensor): the kernel's restarts, element for element.

    The failing rows repeat the pass for several next values of the schedule side by side
    (as many as fit in :data:`RETRY_ROWS` rows) and each takes its first candidate that
    succeeds (or the first with ``mu > reg_max``): the result equals the one-at-a-time
    restarts (rows are independent), in far fewer dispatch-bound passes. A ``hook``
    without ``subset`` cannot be restricted to rows: the whole batch repeats its pass,
    the failing elements with the increased ``mu``, the others with theirs (which gives
    them the same result again).
    """
    sched = restarts.schedule

    def run(mu: Tensor, idx: Tensor | None = None) -> RiccatiFactors:
        if idx is None:
            return _torch_backward(*data, mu, hook, u_bounds)
        sel = [_select_rows(t, tail, idx) for t, tail in zip(data, _DATA_TAILS, strict=True)]
        bounds = None if u_bounds is None else tuple(_select_rows(b, 2, idx) for b in u_bounds)
        sub = None if hook is None else hook.subset(idx)
        return _torch_backward(*sel, mu, sub, bounds)

    fac = run(reg)
    batch = fac.failed.shape
    _check_restart_batch(batch)
    dev = fac.Kk.device
    mu = reg.expand(batch).clone()
    delta = _ones(restarts.delta, batch, mu.dtype).to(dev)
    allowed = _ones(restarts.allowed, batch, torch.bool).to(dev)
    bad = failed_or_nonfinite(fac)
    if hook is not None and not hasattr(hook, "subset"):
        for _ in range(sched.max_restarts):
            retry = bad & allowed & (mu <= sched.reg_max)
            if not bool(retry.any()):
                break
            mu, delta = sched.increase(mu, delta, retry)
            fac = run(mu)
            bad = failed_or_nonfinite(fac)
        return replace(fac, failed=bad, reg=mu, reg_delta=delta)
    tries = 0
    while tries < sched.max_restarts:
        # only allowed elements whose mu may still grow: a frozen (e.g. non-finite)
        # element must not make the others repeat their pass
        retry = bad & allowed & (mu <= sched.reg_max)
        if not bool(retry.any()):
            break
        idx = retry.nonzero().squeeze(1)
        nr = idx.shape[0]
        n_cand = max(1, min(sched.max_restarts - tries, RETRY_ROWS // nr))
        mu_r, delta_r = mu[idx], delta[idx]
        mus, deltas = [], []
        for _ in range(n_cand):
            mu_r, delta_r = sched.increase(mu_r, delta_r)
            mus.append(mu_r)
            deltas.append(delta_r)
        M, D = torch.stack(mus), torch.stack(deltas)  # (n_cand, nr)
        fac_r = run(M.reshape(-1), idx.repeat(n_cand))
        bad_r = failed_or_nonfinite(fac_r).view(n_cand, nr)
        # where one-at-a-time restarts stop: the first success, or the first mu > reg_max
        stop = ~bad_r | (M > sched.reg_max)
        first = torch.argmax(stop.to(torch.int8), dim=0)
        pick = torch.where(stop.any(0), first, torch.full_like(first, n_cand - 1))
        ar = torch.arange(nr, device=idx.device)
        fac = _scatter_rows(fac, idx, _take_rows(fac_r, pick * nr + ar))
        bad = bad.index_copy(0, idx, bad_r[pick, ar])
        mu = mu.index_copy(0, idx, M[pick, ar])
        delta = delta.index_copy(0, idx, D[pick, ar])
        tries += n_cand
    return replace(fac, failed=bad, reg=mu, reg_delta=delta)


def _select_rows(t: Tensor | None, tail: int, idx: Tensor) -> Tensor | None:
    """The rows ``idx`` of ``t``'s batch dim (the dim before its last ``tail`` dims); ``t``
    itself where it has none or a batch dim of 1 (shared by every element)."""
    if t is None or t.ndim <= tail or t.shape[0] == 1:
        return t
    return t.index_select(0, idx)


def _take_rows(fac: RiccatiFactors, rows: Tensor) -> RiccatiFactors:
    """The factors of the elements ``rows`` (an index tensor)."""

    def take(t: Tensor | None) -> Tensor | None:
        return None if t is None else t.index_select(0, rows)

    return RiccatiFactors(**{f.name: take(getattr(fac, f.name)) for f in fields(RiccatiFactors)})


def _scatter_rows(full: RiccatiFactors, idx: Tensor, part: RiccatiFactors) -> RiccatiFactors:
    """``full`` with the rows ``idx`` replaced by ``part`` (passes repeated for ``idx``)."""

    def put(ta: Tensor | None, tb: Tensor | None) -> Tensor | None:
        if ta is None or tb is None:
            return ta
        return ta.index_copy(0, idx, tb.expand(idx.shape[0], *ta.shape[1:]))

    return RiccatiFactors(
        **{
            f.name: put(getattr(full, f.name), getattr(part, f.name))
            for f in fields(RiccatiFactors)
        }
    )


def _tensors(*args) -> list[Tensor]:
    """The tensors among ``args`` and inside tuples among them (``reg``, a hook's
    ``hessians``), for :func:`can_use_compiled`."""
    out = []
    for a in args:
        if isinstance(a, Tensor):
            out.append(a)
        elif isinstance(a, tuple):
            out.extend(t for t in a if isinstance(t, Tensor))
    return out


def _box_tol(dtype: torch.dtype) -> float:
    """Scale of the box QPs' stopping tolerance (times ``1 + |qu|_inf`` per step)."""
    return max(1e-10, 100 * torch.finfo(dtype).eps)


def rollout_homogeneous(F: Tensor, Kk: Tensor, x0: Tensor) -> tuple[Tensor, Tensor]:
    """Closed-loop rollout ``u_t = K_t x_t + k_t``, ``x_{t+1} = A_t x_t + B_t u_t + c_t``.

    Args:
        F: ``(Bf, T, n+1, m+n+1)`` homogeneous dynamics, Kk ``(B, T, m, n+1)``,
            x0 ``(B, n)``.

    Returns:
        x ``(B, T+1, n)`` and u ``(B, T, m)``.
    """
    T = Kk.shape[-3]
    if T > 0 and can_use_compiled(F, Kk, x0):
        return rollout_compiled(F, Kk, x0)
    xh = torch.cat([x0, x0.new_ones(*x0.shape[:-1], 1)], dim=-1).unsqueeze(-1)
    xs, us = [xh], []
    for t in range(T):
        u = Kk[..., t, :, :] @ xh
        xh = F[..., t, :, :] @ torch.cat([u, xh], dim=-2)
        xs.append(xh)
        us.append(u)
    x = torch.stack(xs, dim=-3)[..., :-1, 0]
    u = torch.stack(us, dim=-3)[..., 0] if T > 0 else x0.new_zeros(*x0.shape[:-1], 0, Kk.shape[-2])
    return x, u


def riccati_backward(
    A: Tensor,
    B: Tensor,
    Q: Tensor,
    R: Tensor,
    q: Tensor | None = None,
    r: Tensor | None = None,
    S: Tensor | None = None,
    c: Tensor | None = None,
    reg: Tensor | float | None = None,
    stage_hook: StageHook | None = None,
    u_bounds: tuple[Tensor, Tensor] | None = None,
    restarts: Restarts | None = None,
) -> RiccatiFactors:
    """Backward Riccati pass of the LQ problem solved by :func:`torchslq.lqr_solve`.

    Shapes as in :func:`torchslq.lqr_solve` (one flat batch dimension, broadcast):
    ``A (B,T,n,n)``, ``B (B,T,n,m)``, ``Q (B,T+1,n,n)``, ``R (B,T,m,m)``, ``q (B,T+1,n)``,
    ``r (B,T,m)``, ``S (B,T,m,n)``, ``c (B,T,n)``; a missing or size-1 time dim
    broadcasts over the horizon ``T = A.shape[-3]``. ``reg`` adds ``reg * I`` to every
    ``Quu`` (scalar or ``(B,)``); ``stage_hook`` and ``u_bounds`` (box bounds
    ``(lower, upper)`` on ``u_t``, each broadcastable to ``(B, T, m)``) are passed to
    :func:`riccati_homogeneous`. No input validation: this is the inner-loop entry point.

    Restarts (Tassa et al. 2012; ``restarts=schedule.restarts(delta, allowed)``, see
    :class:`~torchslq.lq.regularization.RegularizationSchedule`): with one batch dim ``B``
    and ``reg = mu`` (a float or ``(B,)``, None for 0), every element whose pass fails,
    i.e. some ``Quu + mu I`` (with bounds: the free block of a step's box QP) is not
    positive definite *or its gains* ``[K, k]`` *are not finite*, and that is
    ``restarts.allowed``, repeats its pass with ``delta := max(f, delta f)``,
    ``mu := max(floor, mu delta)``, until the pass succeeds, ``mu > reg_max`` (that pass
    is still made) or ``max_restarts`` restarts were made. Elements are independent: the
    result of each is the one of passes repeated for it alone. The result then has

    * ``reg``, ``reg_delta`` ``(B,)``: the ``mu`` and ``delta`` each element ended with
      (its last pass's ``mu``; unchanged where no restart was made);
    * ``failed`` ``(B,)``: the last pass failed (not positive definite, or non-finite
      gains); the factors of a failed element are not meaningful (zeros on the compiled
      path below the failing step);
    * the factors (``Kk``, ``Vh``, ``chol``, ``clamped``, ``dV``) of each element's last
      pass.

    This holds on both backends alike (the compiled CPU kernel restarts an element inside
    its loop; the torch path repeats the failing rows, several candidate ``mu`` side by
    side in one pass, or the whole batch with a ``stage_hook`` that has no
    ``subset(idx)`` to restrict it to some elements); ``tests/test_restarts.py`` checks
    them against each other and against a per-element reference. A hook's
    ``subset(idx)`` returns the hook of the batch rows ``idx`` (an index tensor, rows
    may repeat); its ``hessians`` (see :func:`riccati_homogeneous`) let the compiled
    kernel run the pass. Without ``restarts`` ``reg``, ``reg_delta`` are None and
    ``failed`` flags failed factorisations only.
    """
    if restarts is not None and not (isinstance(reg, Tensor) and reg.dtype == A.dtype):
        reg = torch.as_tensor(0.0 if reg is None else reg, dtype=A.dtype, device=A.device)
    fac = _compiled_pieces_pass(A, B, Q, R, q, r, S, c, reg, stage_hook, u_bounds, restarts)
    if fac is not None:
        return fac
    if restarts is None:
        return _torch_backward(A, B, Q, R, q, r, S, c, reg, stage_hook, u_bounds)
    return _restarted((A, B, Q, R, q, r, S, c), reg, stage_hook, u_bounds, restarts)


def _torch_backward(A, B, Q, R, q, r, S, c, reg, stage_hook, u_bounds) -> RiccatiFactors:
    """:func:`riccati_backward` without restarts through the homogeneous form (the torch
    path, or the compiled kernel on ``F``, ``H`` where the pieces' shapes did not fit)."""
    T = A.shape[-3]
    F = homogeneous_dynamics(A, B, with_time(c, 1, T))
    H, VhT = homogeneous_cost(
        with_time(Q, 2, T + 1),
        with_time(R, 2, T),
        with_time(q, 1, T + 1),
        with_time(r, 1, T),
        with_time(S, 2, T),
    )
    return riccati_homogeneous(F, H, VhT, reg, stage_hook, u_bounds)


def rollout_linear(
    A: Tensor, B: Tensor, K: Tensor, k: Tensor, x0: Tensor, c: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Roll ``x_{t+1} = A_t x_t + B_t u_t + c_t`` forward under ``u_t = K_t x_t + k_t``.

    ``A (B,T,n,n)``, ``B (B,T,n,m)``, ``K (B,T,m,n)``, ``k (B,T,m)``, ``x0 (B,n)``,
    ``c (B,T,n)``. Returns ``x (B,T+1,n)``, ``u (B,T,m)``.
    """
    c = with_time(c, 1, K.shape[-3])
    Kk = torch.cat([K, k.unsqueeze(-1)], dim=-1)
    if can_use_compiled(A, B, Kk, x0, *(() if c is None else (c,))):
        # on the CPU kernel from the data: the homogeneous F is not built
        return lq_rollout_compiled(A, B, c, Kk, x0)
    return rollout_homogeneous(homogeneous_dynamics(A, B, c), Kk, x0)
