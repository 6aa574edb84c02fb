"""numba kernels of the LQ layer's gain-form solve (imported on first use, as
:mod:`._numba_kernels`).

:func:`torchslq.lqr_solve` solves plain LQ problems: no regularisation, no bounds, no
second-order hooks. For those the homogeneous pass of :mod:`._numba_kernels` (built for
the solvers' regularised, control-limited and DDP passes, on ``(n+1) x (m+n+1)``
blocks) does more than needed. These kernels read the caller's batch-first data
(``A, B, c, Q, R, S, q, r`` with batch and time dims of 1 or full) and run the
recursion in the standard gain form, one element at a time, with ``w = p' + P'c`` and
the primes the next step's value function::

    Qxx = Q + A'P'A,  Quu = R + B'P'B,  Qux = S + B'P'A,  qx = q + A'w,  qu = r + B'w
    Quu = L L'  (Cholesky),  Y = L^{-1} Qux,  y = L^{-1} qu
    K = -L'^{-1} Y,  k = -L'^{-1} y
    P = Qxx - Y'Y,  p = qx - Y'y,  s = s' + p''c + c'P'c / 2 - y'y / 2

(``P = Qxx + Qux'K`` written so that it is symmetric by construction; ``s`` is the
value function's constant, so that the optimal cost is ``x0'P_0 x0 / 2 + p_0'x0 +
s_0``.) The gains are written ``[K, k]`` side by side, as the homogeneous kernel's, so
that the rollout is :func:`._numba_kernels.lq_rollout_kernel`. The backward pass of the
implicit differentiation (:func:`adjoint_gain_kernel`) reuses ``K``, ``L`` and ``P``:
one more LQ solve with the incoming gradients as linear terms, then the gradients of
every datum as outer products of the two trajectories.

The same element pass (:func:`_gain_pass`, with a regularisation of ``Quu`` and DDP's
second-order terms) is the solvers' unconstrained pass of small problems
(:func:`riccati_gain_reg_kernel`, its value functions written into the blocks of the
homogeneous ``Vh``). Up to :data:`._numba_kernels.FIXED_MAX_N` states and
:data:`~._numba_kernels.FIXED_MAX_M` controls the kernels are compiled for the
problem's own sizes (:func:`._numba_kernels.size_witness`).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from . import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)
from ._numba_address import pieces_at
from ._numba_gemm import acc_tn
from ._numba_kernels import (  # noqa: F401 (size_witness re-exported)
    _affine_step,
    _cholesky,
    _controls,
    _idx,
    finite_gains,
    restart_step,
    size_witness,
)

# from this state dimension on, the adjoint pass runs its transposed products in row order
ROW_ORDER_N = 8


@numba.njit(
    cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False, inline="always"
)
def _acc_tn_sized(C, X, Y, sign, upper, fixed, rows, cols, inner):
    """``C += sign X'Y`` as :func:`._numba_gemm.acc_tn` (``X (inner, rows)``, ``Y
    (inner, cols)``); where ``fixed`` (sizes known when compiled), plain loops in row
    order, which LLVM unrolls for those sizes. Inlined, so that the constants reach it."""
    if fixed:
        for k in range(inner):
            xk = X[k]
            yk = Y[k]
            for i in range(rows):
                a = sign * xk[i]
                ci = C[i]
                for j in range(i if upper else 0, cols):
                    ci[j] += a * yk[j]
    else:
        acc_tn(C, X, Y, sign, upper)


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def riccati_gain_kernel(b0, b1, pieces, Kk, P, p, L, s, failed, nt, mt):
    """Gain-form Riccati pass (module docstring) of elements ``b0 <= b < b1``, one
    element at a time, the matrix products register-blocked (:func:`._numba_gemm.acc_tn`;
    compile it inside :func:`._numba_gemm.slp_vectorized`).

    ``pieces = (A, B, c, Q, R, S, q, r)``: ``A (1|B, 1|T, n, n)``, ``B (.., n, m)``,
    ``c (.., n)``, ``Q (1|B, 1|T+1, n, n)``, ``R (.., m, m)``, ``S (.., m, n)``,
    ``q (1|B, 1|T+1, n)``, ``r (.., m)`` (``c, S, q, r`` with a batch dim of 0: zero).
    Outputs ``Kk (B, T, m, n+1)`` (``[K_t, k_t]``), ``P (B, T+1, n, n)``, ``p (B, T+1,
    n)``, ``L (B, T, m, m)`` (lower Cholesky factors of ``Quu``), ``s (B,)`` and
    ``failed (B,)``: some ``Quu`` not positive definite or not finite (the pass of that
    element stops there; its outputs are meaningless). ``nt, mt``: :func:`size_witness`.
    """
    scratch = _gain_scratch(Kk.shape[3] - 1, Kk.shape[2], P.dtype)
    _riccati_gain_rows(b0, b1, pieces, Kk, P, p, L, s, failed, scratch, nt, mt)


@numba.njit(cache=True, nogil=True)
def _gain_scratch(n, m, dt):
    """The scratch arrays of :func:`_riccati_gain_rows` for ``n`` states and ``m``
    controls (allocated by a kernel, which has numba's runtime)."""
    return (
        np.empty((n, n), dtype=dt),
        np.empty((n, m), dtype=dt),
        np.empty(n, dtype=dt),
        np.empty((m, n), dtype=dt),
        np.empty(m, dtype=dt),
        np.zeros((m, m), dtype=dt),
        np.zeros((0, 0), dtype=dt),  # an empty s2 (no per-step constants)
        np.zeros((0, 0, 0, 0, 0), dtype=dt),  # empty Hessians (no second-order terms)
    )


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def _riccati_gain_rows(b0, b1, pieces, Kk, P, p, L, s, failed, scratch, nt, mt):
    """The loop of :func:`riccati_gain_kernel` (without reference counting, see
    :mod:`._numba_kernels`); ``scratch = (PA (n, n), PB (n, m), w (n,), Y (m, n), y (m,),
    Lq (m, m), an empty (0, 0) s2, an empty 5-d array for the absent Hessians)``;
    ``nt, mt``: :func:`size_witness`."""
    none = scratch[7]
    for e in range(b0, b1):
        ok, sv = _gain_pass(
            e, pieces, Kk, P, p, L, scratch[6], 0.0, none, (none, none, none), scratch, nt, mt
        )
        s[e] = sv
        failed[e] = not ok


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def _gain_pass(e, pieces, Kk, P, p, L, s2, reg, Hz, Hb, scratch, nt, mt):
    """The gain-form pass of element ``e`` (module docstring) with ``reg`` added to
    ``Quu``'s diagonal, into ``Kk[e]``, ``P[e]``, ``p[e]``, ``L[e]`` and, where ``s2`` is not
    empty, twice the value function's constant per step into ``s2[e]`` (the corner of
    the homogeneous ``Vh``). Returns ``(ok, s_0)``: whether every ``Quu + reg I`` was
    positive definite (the pass stops at the first that is not, leaving the earlier
    steps as they were) and the constant at ``t = 0``.

    With ``reg > 0`` the gains are the regularised ones and the value function is the
    one of those gains on the true ``Quu`` (Tassa, Erez & Todorov 2012's form, as the
    homogeneous kernel's: ``Qxx + K'Quu K + K'Qux + Qux'K``, exact for any gains), which with ``Y = L^{-1} Qux`` and
    ``Quu + reg I = L L'`` is ``P = Qxx - Y'Y - reg K'K``, ``p = qx - Y'y - reg K'k``,
    ``s = ... - (y'y + reg k'k) / 2``: the homogeneous kernel's values.

    DDP's second-order terms: where ``Hz (T, n, B, m+n, m+n)`` (``[u; x]`` order) or the
    blocks ``Hb = (Hxx (n, B, T, n, n), Huu (n, B, T, m, m), Hux (n, B, T, m, n))`` are
    not empty, ``sum_k p'_k f^k_zz`` (``p'`` the next step's value gradient) is added to
    ``Quu``, ``Qux`` and ``Qxx``, as the homogeneous kernel adds it to its ``M``; the two
    layouts give the same bits."""
    T = Kk.shape[1]
    fixed = len(nt) > 0
    m = len(mt) if fixed else Kk.shape[2]
    n = len(nt) if fixed else Kk.shape[3] - 1
    A, Bm, c, Q, R, S, q, r = pieces
    PA, PB, wv, Y, y, Lq = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5]
    joint = Hz.shape[0] > 0
    second = joint or Hb[0].shape[0] > 0
    has_c, has_S, has_q, has_r = c.shape[0] > 0, S.shape[0] > 0, q.shape[0] > 0, r.shape[0] > 0
    steps = s2.shape[0] > 0
    bq, tq = _idx(Q, e, T)
    Qt = Q[bq, tq]
    Pn = P[e, T]
    pn = p[e, T]
    for i in range(n):
        for j in range(n):
            Pn[i, j] = 0.5 * (Qt[i, j] + Qt[j, i])
        pn[i] = 0.0
    if has_q:
        bl, tl = _idx(q, e, T)
        for i in range(n):
            pn[i] = q[bl, tl, i]
    sv = 0.0
    if steps:
        s2[e, T] = 0.0
    ok = True
    for t in range(T - 1, -1, -1):
        ba, ta = _idx(A, e, t)
        At = A[ba, ta]
        bb, tb = _idx(Bm, e, t)
        Bt = Bm[bb, tb]
        # w = p' + P'c;  s += p''c + c'P'c / 2
        # (row operations over contiguous rows here and below: loops whose inner
        # loop runs down a column, or waits on one running sum, cost several times
        # the register-blocked products of the step at n >= 8)
        for i in range(n):
            wv[i] = pn[i]
        if has_c:
            bc, tc = _idx(c, e, t)
            ct = c[bc, tc]
            # w += P'c as rows of P' (symmetric), s += c'p' + c'P'c / 2
            for j in range(n):
                a = ct[j]
                Pj = Pn[j]
                for i in range(n):
                    wv[i] += a * Pj[i]
            for i in range(n):
                sv += ct[i] * (0.5 * (pn[i] + wv[i]))
        # PA = P'A, PB = P'B (P' symmetric), Quu = R + B'PB (its lower triangle
        # is read), Qux = B'PA (+ S below), qu = B'w (+ r below)
        PA[:] = 0.0
        PB[:] = 0.0
        _acc_tn_sized(PA, Pn, At, 1.0, False, fixed, n, n, n)
        _acc_tn_sized(PB, Pn, Bt, 1.0, False, fixed, n, m, n)
        br, tr = _idx(R, e, t)
        Rt = R[br, tr]
        for i in range(m):
            for j in range(m):
                Lq[i, j] = 0.5 * (Rt[i, j] + Rt[j, i])
            Lq[i, i] += reg
            y[i] = 0.0
        for kk in range(n):  # y = B'w
            a = wv[kk]
            Bk = Bt[kk]
            for i in range(m):
                y[i] += a * Bk[i]
        _acc_tn_sized(Lq, Bt, PB, 1.0, False, fixed, m, m, n)
        Y[:] = 0.0
        _acc_tn_sized(Y, Bt, PA, 1.0, False, fixed, m, n, n)
        if has_S:
            bs, ts = _idx(S, e, t)
            St = S[bs, ts]
            for i in range(m):
                for j in range(n):
                    Y[i, j] += St[i, j]
        if has_r:
            bl, tl = _idx(r, e, t)
            for i in range(m):
                y[i] += r[bl, tl, i]
        if second:  # Quu += sum_k p'_k f^k_uu, Qux += sum_k p'_k f^k_ux
            for k in range(n):
                v = pn[k]
                for i in range(m):
                    for j in range(m):
                        Lq[i, j] += v * (Hz[t, k, e, i, j] if joint else Hb[1][k, e, t, i, j])
                    for j in range(n):
                        Y[i, j] += v * (Hz[t, k, e, i, m + j] if joint else Hb[2][k, e, t, i, j])
        # Cholesky Quu = Lq Lq' in place; Y = Lq^{-1} Qux, y = Lq^{-1} qu
        for j in range(m):
            d = Lq[j, j]
            for kk in range(j):
                d -= Lq[j, kk] * Lq[j, kk]
            if not d > 0.0:  # also NaN
                ok = False
                break
            d = math.sqrt(d)
            Lq[j, j] = d
            for i in range(j + 1, m):
                acc = Lq[i, j]
                for kk in range(j):
                    acc -= Lq[i, kk] * Lq[j, kk]
                Lq[i, j] = acc / d
        if not ok:
            break
        for i in range(m):  # forward substitution, a row of Y at a time
            Yi = Y[i]
            acc = y[i]
            for kk in range(i):
                a = Lq[i, kk]
                Yk = Y[kk]
                for j in range(n):
                    Yi[j] -= a * Yk[j]
                acc -= a * y[kk]
            di = 1.0 / Lq[i, i]
            for j in range(n):
                Yi[j] *= di
            y[i] = acc * di
        # P = Q + A'PA - Y'Y (upper triangle, mirrored), p = q + A'w - Y'y
        Pc = P[e, t]
        pc = p[e, t]
        bq, tq = _idx(Q, e, t)
        Qt = Q[bq, tq]
        for i in range(n):
            for j in range(i, n):
                Pc[i, j] = 0.5 * (Qt[i, j] + Qt[j, i])
            if second:  # Qxx += sum_k p'_k f^k_xx
                for k in range(n):
                    v = pn[k]
                    for j in range(i, n):
                        Pc[i, j] += v * (
                            Hz[t, k, e, m + i, m + j] if joint else Hb[0][k, e, t, i, j]
                        )
            pc[i] = 0.0
        for kk in range(n):  # p = A'w - Y'y (+ q below), by rows of A and Y
            a = wv[kk]
            Ak = At[kk]
            for i in range(n):
                pc[i] += a * Ak[i]
        for kk in range(m):
            a = y[kk]
            Yk = Y[kk]
            for i in range(n):
                pc[i] -= a * Yk[i]
        _acc_tn_sized(Pc, At, PA, 1.0, True, fixed, n, n, n)
        _acc_tn_sized(Pc, Y, Y, -1.0, True, fixed, n, n, m)
        for i in range(n):
            for j in range(i + 1, n):
                Pc[j, i] = Pc[i, j]
        if has_q:
            bl, tl = _idx(q, e, t)
            for i in range(n):
                pc[i] += q[bl, tl, i]
        for kk in range(m):
            sv -= 0.5 * y[kk] * y[kk]
        # [K k] = -Lq'^{-1} [Y y]
        Kt = Kk[e, t]
        Lt = L[e, t]
        # (back substitution a row of [K k] at a time, the sign carried through:
        # -(a - b) = -a + b exactly)
        for i in range(m - 1, -1, -1):
            Ki = Kt[i]
            Yi = Y[i]
            for j in range(n):
                Ki[j] = -Yi[j]
            Ki[n] = -y[i]
            for kk in range(i + 1, m):
                a = Lq[kk, i]
                Kr = Kt[kk]
                for j in range(n + 1):
                    Ki[j] -= a * Kr[j]
            di = 1.0 / Lq[i, i]
            for j in range(n + 1):
                Ki[j] *= di
            for j in range(m):
                Lt[i, j] = Lq[i, j] if j <= i else 0.0
        if reg != 0.0:  # the value of the regularised gains: - reg [K k]'[K k]
            for kk in range(m):
                kr = Kt[kk]
                for i in range(n):
                    a = reg * kr[i]
                    for j in range(i, n):
                        Pc[i, j] -= a * kr[j]
                    pc[i] -= a * kr[n]
                sv -= 0.5 * reg * kr[n] * kr[n]
            for i in range(n):
                for j in range(i + 1, n):
                    Pc[j, i] = Pc[i, j]
        if steps:
            s2[e, t] = 2.0 * sv
        Pn = Pc
        pn = pc
    return ok, sv


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def riccati_gain_reg_kernel(
    b0, b1, pieces, reg, Hz, Hb, Kk, Vh, L, failed, mu_io, delta_io, may_restart, restart_opts,
    nt, mt,
):  # fmt: skip
    """The solvers' unconstrained Riccati pass (:func:`torchslq.lq.riccati_backward`
    without bounds) in gain form, per element ``b0 <= b < b1``:
    :func:`_gain_pass` with ``reg`` (``(1 or B,)``) on ``Quu``'s diagonal and DDP's
    Hessians ``Hz`` or ``Hb`` (see there; empty: none), its value
    functions written into the blocks of the homogeneous ``Vh (B, T+1, n+1, n+1)``
    (``P``, ``p`` and its mirror, twice the constant). Same outputs and restarts as
    :func:`._numba_kernels.riccati_kernel` (``mu_io``, ``delta_io``, ``may_restart``,
    ``restart_opts``: see there; empty: no restarts), for a fraction of its time on small
    problems (no ``(n+1) x (m+n+1)`` blocks assembled, sizes fixed by ``nt, mt``)."""
    n = Kk.shape[3] - 1
    scratch = _gain_scratch(n, Kk.shape[2], Kk.dtype)
    # Hz as a view (layout "A" whether DDP's strided Hessians or iLQR's empty array):
    # one compilation of the callees for both solvers instead of two
    _gain_reg_rows(
        b0, b1, pieces, reg, Hz[:, :, :, :, :], Hb, Kk, Vh[:, :, :n, :n], Vh[:, :, :n, n], L,
        Vh[:, :, n, n], Vh, failed, mu_io, delta_io, may_restart, restart_opts, scratch, nt, mt,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def _gain_reg_rows(
    b0, b1, pieces, reg, Hz, Hb, Kk, P, p, L, s2, Vh, failed, mu_io, delta_io, may_restart,
    restart_opts, scratch, nt, mt,
):  # fmt: skip
    """The loop of :func:`riccati_gain_reg_kernel` (the restart schedule of
    :func:`._numba_kernels.riccati_kernel`); ``P``, ``p``, ``s2`` are views of ``Vh``."""
    T = Kk.shape[1]
    restarting = mu_io.shape[0] > 0
    for b in range(b0, b1):
        r = reg[b if reg.shape[0] > 1 else 0]
        delta = 0.0
        if restarting:
            r = mu_io[b]
            delta = delta_io[b]
        restarts = 0
        while True:
            ok, _ = _gain_pass(b, pieces, Kk, P, p, L, s2, r, Hz, Hb, scratch, nt, mt)
            # non-finite gains count as a failure, as in the homogeneous kernel (where a
            # non-finite linear term reaches Quu through its zero entries of F)
            if ok:
                ok = finite_gains(Kk[b])
            if not restarting:
                break
            stop, r, delta = restart_step(ok, may_restart[b], r, delta, restarts, restart_opts)
            if stop:
                break
            restarts += 1
            # a fresh pass leaves zeros below a failing step: so does a repeated one
            Kk[b] = 0.0
            L[b] = 0.0
            P[b, :T] = 0.0
            p[b, :T] = 0.0
            s2[b, :T] = 0.0
        failed[b] = not ok
        if restarting:
            mu_io[b] = r
            delta_io[b] = delta
        mirror_last_row(Vh, b)


@numba.njit(cache=True, nogil=True, _nrt=False)
def mirror_last_row(Vh, b):
    """``Vh[b]``'s last row set to mirror its last column (every step)."""
    n = Vh.shape[2] - 1
    for t in range(Vh.shape[1]):
        Vt = Vh[b, t]
        for i in range(n):
            Vt[n, i] = Vt[i, n]


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def gain_solve_kernel(pieces, x0, Kk, P, p, L, s, failed, x, u, lam, cost, finite, nt, mt):
    """A whole solve in one call: :func:`riccati_gain_kernel` over the data's batch
    (``Kk.shape[0]`` elements), then :func:`rollout_value_kernel` from ``x0`` over the
    solve's batch (``x.shape[0]`` elements), with the arrays of those two. For a small solve on one thread: each launch of a kernel
    costs 5-10 us of numba's argument typing, as much as the whole (4, 1) pass at
    ``T = 100``."""
    scratch = _gain_scratch(Kk.shape[3] - 1, Kk.shape[2], P.dtype)
    # a literal 0 would type the callees for Literal[int](0): a second compilation of
    # each beside the launchers' int64 one
    first = np.intp(0)
    _riccati_gain_rows(first, Kk.shape[0], pieces, Kk, P, p, L, s, failed, scratch, nt, mt)
    rollout_value_kernel(
        first, x.shape[0], pieces[0], pieces[1], pieces[2], Kk, P, p, s, x0, x, u, lam, cost,
        finite, nt, mt,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def gain_solve_at_kernel(
    addresses, dims, x0_address, Kk, P, p, L, s, failed, x, u, lam, cost, finite, nt, mt
):
    """:func:`gain_solve_kernel` on the data at ``addresses`` and ``x0_address``
    (:func:`._numba_address.pieces_at`; ``x0 (x.shape[0], n)``)."""
    pieces, x0 = pieces_at(addresses, dims, x0_address, x.shape[0], Kk.shape[3] - 1, Kk.shape[2], P)
    gain_solve_kernel(pieces, x0, Kk, P, p, L, s, failed, x, u, lam, cost, finite, nt, mt)


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def rollout_value_kernel(b0, b1, A, Bm, c, Kk, P, p, s, x0, x, u, lam, cost, finite, nt, mt):
    """Per element ``b0 <= e < b1``: the rollout of
    :func:`._numba_kernels.lq_rollout_kernel` (its step, contracted into FMAs here: equal
    to rounding) and, in the same pass over the steps, the costates
    ``lam_t = P_t x_t + p_t``, the optimal cost ``x_0'P_0 x_0 / 2 + p_0'x_0 + s`` (NaN
    where not finite) and whether ``x, u`` are finite. ``P, p, s`` with a batch of 1
    (shared data) or B; outputs ``x, lam (B, T+1, n)``, ``u (B, T, m)``, ``cost (B,)``,
    ``finite (B,)``; ``nt, mt``: :func:`size_witness`. (The costates were a second pass
    that read ``x`` again: at ``(4, 1)``, ``B = 1024``, ``T = 100``, 1.8 + 1.6 ms for
    the two passes.)"""
    T = u.shape[1]
    fixed = len(nt) > 0
    n = len(nt) if fixed else x.shape[2]
    m = len(mt) if fixed else u.shape[2]
    affine = c.shape[0] > 0
    for e in range(b0, b1):
        bk = e if Kk.shape[0] > 1 else 0
        bv = e if P.shape[0] > 1 else 0
        bx = e if x0.shape[0] > 1 else 0
        for i in range(n):
            x[e, 0, i] = x0[bx, i]
        fin = True
        for t in range(T + 1):
            xt = x[e, t]
            lt = lam[e, t]
            Pt = P[bv, t]
            for i in range(n):
                lt[i] = p[bv, t, i]
            # rows for columns (P_t is symmetric): the contiguous inner loop vectorises
            for j in range(n):
                a = xt[j]
                fin = fin and math.isfinite(a)
                Pj = Pt[j]
                for i in range(n):
                    lt[i] += a * Pj[i]
            if t == T:
                break
            ut = u[e, t]
            _controls(Kk[bk, t], xt, ut, True, m, n)
            for i in range(m):
                fin = fin and math.isfinite(ut[i])
            _affine_step(A, Bm, c, affine, e, t, xt, ut, x[e, t + 1], m, n)
        J = s[bv]
        for i in range(n):
            J += x[e, 0, i] * (p[bv, 0, i] + 0.5 * (lam[e, 0, i] - p[bv, 0, i]))
        cost[e] = J if fin else np.nan
        finite[e] = fin


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def adjoint_gain_kernel(
    b0, b1, A, Bm, Kk, L, P, x, u, lam, ok, gx, gu, gJ, vs, ks, gA, gB, gc, gQ, gR, gS, gq, gr,
    gx0, nt, mt,
):  # fmt: skip
    """Backward pass of the implicit differentiation (Amos et al. 2018, Sec. 4.2) for
    elements ``b0 <= b < b1``: the LQ problem with the forward problem's matrices and
    linear terms ``q = gx``, ``r = gu``, ``c = 0``, ``x0 = 0``, solved by the forward
    factors (only the vector recursion ``qu = gu_t + B'v``, ``dk = -Quu^{-1} qu`` by
    ``L``, ``v_t = gx_t + A'v + K'qu``, then the rollout ``du = K dx + dk``,
    ``dx' = A dx + B du``, ``dlam_t = P_t dx_t + v_t``), and the gradients of the data
    as outer products of ``(x, u, lam)`` and ``(dx, du, dlam)``::

        gA_t = dlam_{t+1} x_t' + lam_{t+1} dx_t',   gB_t = dlam_{t+1} u_t' + lam_{t+1} du_t'
        gc_t = dlam_{t+1},   gQ_t = (dx_t x_t' + x_t dx_t') / 2,   gq_t = dx_t
        gR_t = (du_t u_t' + u_t du_t') / 2,   gS_t = du_t x_t' + u_t dx_t',   gr_t = du_t
        gx0 = dlam_0

    and with the optimal cost's incoming gradient ``gJ (B,)`` its own gradient on top
    (envelope theorem: the Lagrangian's partial derivatives at the solution, ``lam_{t+1}
    x_t'`` for ``A_t``, ``x_t x_t' / 2`` for ``Q_t``, ``lam_0`` for ``x0``, ...), folded in
    as ``dlam += gJ lam``, ``dx += gJ x / 2``, ``du += gJ u / 2`` in the products.

    ``A, B`` as in :func:`riccati_gain_kernel`; ``Kk, L (1|B, T, ...)``, ``P (1|B, T+1,
    n, n)``; ``x, u, lam`` the forward solution and ``gx (B, T+1, n)``, ``gu (B, T,
    m)`` the incoming gradients; ``ok (B,)``: elements whose gradients are skipped where
    False (a failed or non-finite solve; the caller zeroes them); ``vs (B, T+1, n)``, ``ks (B, T, m)``
    scratch. Outputs (full batch and time dims; a gradient nobody needs has a batch dim
    of 0 and is skipped): ``gA (B, T, n, n)``, ``gB (B, T, n, m)``, ``gc (B, T, n)``,
    ``gQ (B, T+1, n, n)``, ``gR (B, T, m, m)``, ``gS (B, T, m, n)``, ``gq (B, T+1,
    n)``, ``gr (B, T, m)``, ``gx0 (B, n)``.
    """
    m = u.shape[2]
    n = x.shape[2]
    dt = x.dtype
    scratch = (
        np.empty(n, dtype=dt),
        np.empty(n, dtype=dt),
        np.empty(m, dtype=dt),
        np.empty(n, dtype=dt),
        np.empty(m, dtype=dt),
        np.empty(n, dtype=dt),
        np.empty(n, dtype=dt),
        np.empty(m, dtype=dt),
    )
    _adjoint_gain_rows(
        b0, b1, A, Bm, Kk, L, P, x, u, lam, ok, gx, gu, gJ, vs, ks, gA, gB, gc, gQ, gR, gS,
        gq, gr, gx0, scratch, nt, mt,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def _adjoint_gain_rows(
    b0, b1, A, Bm, Kk, L, P, x, u, lam, ok, gx, gu, gJ, vs, ks, gA, gB, gc, gQ, gR, gS, gq, gr,
    gx0, scratch, nt, mt,
):  # fmt: skip
    """The loop of :func:`adjoint_gain_kernel` (without reference counting, see
    :mod:`._numba_kernels`); ``scratch``: eight vectors, of sizes n, n, m, n, m, n, n, m;
    ``nt, mt``: :func:`size_witness`."""
    T = u.shape[1]
    fixed = len(nt) > 0
    m = len(mt) if fixed else u.shape[2]
    n = len(nt) if fixed else x.shape[2]
    dx, dxn, du, dln, z, dlj, dxj, duj = scratch
    for e in range(b0, b1):
        if not ok[e]:
            continue  # (its gradients are zeroed by the caller)
        bk = e if Kk.shape[0] > 1 else 0
        ve = vs[e]
        ke = ks[e]
        for i in range(n):
            ve[T, i] = gx[e, T, i]
        for t in range(T - 1, -1, -1):
            ba, ta = _idx(A, e, t)
            bb, tb = _idx(Bm, e, t)
            At = A[ba, ta]
            Bt = Bm[bb, tb]
            Kt = Kk[bk, t]
            Lt = L[bk, t]
            vn = ve[t + 1]
            # qu = gu + B'v (then z = L^{-1} qu), v = gx + A'v + K'qu; from n = 8 on the
            # transposed products in row order (contiguous inner loops, no chain of
            # dependent sums: 1.25x faster at (32, 8), 1.3x slower at (4, 1))
            vt = ve[t]
            if n < ROW_ORDER_N:
                for i in range(m):
                    acc = gu[e, t, i]
                    for j in range(n):
                        acc += Bt[j, i] * vn[j]
                    z[i] = acc
                for i in range(n):
                    acc = gx[e, t, i]
                    for j in range(n):
                        acc += At[j, i] * vn[j]
                    for j in range(m):
                        acc += Kt[j, i] * z[j]
                    vt[i] = acc
            else:
                for i in range(m):
                    z[i] = gu[e, t, i]
                for i in range(n):
                    vt[i] = gx[e, t, i]
                for j in range(n):
                    a = vn[j]
                    for i in range(m):
                        z[i] += a * Bt[j, i]
                    for i in range(n):
                        vt[i] += a * At[j, i]
                for j in range(m):
                    a = z[j]
                    for i in range(n):
                        vt[i] += a * Kt[j, i]
            for i in range(m):
                acc = z[i]
                for j in range(i):
                    acc -= Lt[i, j] * z[j]
                z[i] = acc / Lt[i, i]
            kt = ke[t]
            for i in range(m - 1, -1, -1):  # dk = -L'^{-1} z
                acc = z[i]
                for j in range(i + 1, m):
                    acc -= Lt[j, i] * kt[j]
                kt[i] = acc / Lt[i, i]
            for i in range(m):
                kt[i] = -kt[i]
        gj = gJ[e]
        hj = 0.5 * gj
        for i in range(n):
            dx[i] = 0.0
        if gx0.shape[0] > 0:  # dlam_0 = P_0 dx_0 + v_0 with dx_0 = 0
            for i in range(n):
                gx0[e, i] = ve[0, i] + gj * lam[e, 0, i]
        for t in range(T + 1):
            xt = x[e, t]
            if gQ.shape[0] > 0:
                G = gQ[e, t]
                for i in range(n):
                    for j in range(n):
                        G[i, j] = 0.5 * (
                            (dx[i] + hj * xt[i]) * xt[j] + xt[i] * (dx[j] + hj * xt[j])
                        )
            if gq.shape[0] > 0:
                for i in range(n):
                    gq[e, t, i] = dx[i] + gj * xt[i]
            if t == T:
                break
            ut = u[e, t]
            Kt = Kk[bk, t]
            kt = ke[t]
            for i in range(m):
                acc = kt[i]
                for j in range(n):
                    acc += Kt[i, j] * dx[j]
                du[i] = acc
            ba, ta = _idx(A, e, t)
            bb, tb = _idx(Bm, e, t)
            At = A[ba, ta]
            Bt = Bm[bb, tb]
            Pn = P[bk, t + 1]
            vn = ve[t + 1]
            for i in range(n):
                acc = 0.0
                for j in range(n):
                    acc += At[i, j] * dx[j]
                for j in range(m):
                    acc += Bt[i, j] * du[j]
                dxn[i] = acc
            for i in range(n):  # dlam = P dx + v (P symmetric: row order)
                dln[i] = vn[i]
            for j in range(n):
                a = dxn[j]
                for i in range(n):
                    dln[i] += a * Pn[j, i]
            ln = lam[e, t + 1]
            for i in range(n):
                dlj[i] = dln[i] + gj * ln[i]
                dxj[i] = dx[i] + hj * xt[i]
            for i in range(m):
                duj[i] = du[i] + hj * ut[i]
            if gA.shape[0] > 0:
                G = gA[e, t]
                for i in range(n):
                    for j in range(n):
                        G[i, j] = dlj[i] * xt[j] + ln[i] * dx[j]
            if gB.shape[0] > 0:
                G = gB[e, t]
                for i in range(n):
                    for j in range(m):
                        G[i, j] = dlj[i] * ut[j] + ln[i] * du[j]
            if gc.shape[0] > 0:
                for i in range(n):
                    gc[e, t, i] = dlj[i]
            if gR.shape[0] > 0:
                G = gR[e, t]
                for i in range(m):
                    for j in range(m):
                        G[i, j] = 0.5 * (duj[i] * ut[j] + ut[i] * duj[j])
            if gS.shape[0] > 0:
                G = gS[e, t]
                for i in range(m):
                    for j in range(n):
                        G[i, j] = duj[i] * xt[j] + ut[i] * dxj[j]
            if gr.shape[0] > 0:
                for i in range(m):
                    gr[e, t, i] = du[i] + gj * ut[i]
            for i in range(n):
                dx[i] = dxn[i]


@numba.njit(cache=True, nogil=True, _nrt=False, fastmath={"reassoc"})
def _all_finite(a):
    """Whether every entry of the C-contiguous array ``a`` is finite: the sum of
    ``v - v`` is 0 exactly when every ``v`` is finite (NaN for a NaN or an infinity,
    in any order of summation: the sum may be reassociated, so that it vectorises)."""
    flat = a.reshape(a.size)
    acc = 0.0
    for i in range(flat.size):
        v = flat[i]
        acc += v - v
    return acc == 0.0


@numba.njit(cache=True, nogil=True)
def _all_positive_definite(R):
    """Whether the symmetric part of every ``R[b, t] (m, m)`` has a Cholesky factor
    (every pivot positive, as LAPACK's ``potrf`` decides; ``R`` finite)."""
    m = R.shape[2]
    sym = np.empty((m, m), R.dtype)
    L = np.empty((m, m), R.dtype)
    whole = np.zeros(m, dtype=np.bool_)  # (_cholesky's rows to skip: none)
    for b in range(R.shape[0]):
        for t in range(R.shape[1]):
            Rt = R[b, t]
            for i in range(m):
                for j in range(i + 1):
                    sym[i, j] = 0.5 * (Rt[i, j] + Rt[j, i])
            if not _cholesky(sym, 0.0, whole, L):
                return False
    return True


@numba.njit(cache=True, nogil=True)
def data_clean_at_kernel(addresses, dims, x0_address, nb, n, m, like):
    """:func:`data_clean_kernel` on the data at ``addresses`` and ``x0_address``
    (:func:`._numba_address.pieces_at`, in ``like``'s dtype)."""
    pieces, x0 = pieces_at(addresses, dims, x0_address, nb, n, m, like)
    return data_clean_kernel(pieces, x0)


@numba.njit(cache=True, nogil=True)
def data_clean_kernel(pieces, x0):
    """Whether :func:`torchslq.lqr_solve`'s data are clean: every entry of the
    ``pieces`` ``(A, B, c, Q, R, S, q, r)`` and of ``x0`` finite and every ``R``
    positive definite (the quick check of its ``validate``, on the kernels' arrays: a
    pass over the data, a fraction of the solve's cost)."""
    return (
        _all_finite(x0) and _all_finite(pieces[0]) and _all_finite(pieces[1])
        and _all_finite(pieces[2]) and _all_finite(pieces[3]) and _all_finite(pieces[4])
        and _all_finite(pieces[5]) and _all_finite(pieces[6]) and _all_finite(pieces[7])
        and _all_positive_definite(pieces[4])
    )  # fmt: skip
