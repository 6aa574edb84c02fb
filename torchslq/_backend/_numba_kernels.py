"""numba kernels of :mod:`torchslq._backend.dispatch` (imported on first use: importing
numba and loading the cached machine code takes ~0.5 s, which a GPU-only user should
never pay).

**No reference counting in the loops** (``_nrt=False``). numba counts the references of
every array view it creates (a row ``M[i]``, a step's matrix ``Vh[b, t]``, an argument
passed to a helper) with an atomic increment and decrement, about 20 cycles each; LLVM
removes only the pairs it can see in one block. On the small matrices of these loops
that bookkeeping took 30% of a whole ILQR solve of the cart-pole at B = 512 (perf:
``NRT_incref`` / ``NRT_decref``). The loops and helpers are compiled without numba's
runtime: views of the caller's arrays need no count (the caller keeps them alive), and
a kernel that needs scratch allocates it with the runtime on and passes it to its
loop (``riccati_kernel`` -> ``_element_pass``, ``closed_loop_rollout_kernel`` ->
``_closed_loop_rows``). Such a function cannot allocate (numba refuses to compile it).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from . import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)
from ._numba_gemm import acc_tn
from .specialisation import specialised

# Up to these sizes the gain-form LQ kernels (:mod:`._numba_gain`, :func:`lq_rollout_kernel`)
# are compiled for the problem's own (n, m): their loops then have constant trip counts,
# which LLVM unrolls and vectorises. At (4, 1) the Riccati pass takes 117 instead of 194
# ns per element and step, at (6, 2) 294 instead of 535; from n = 8 on the register-blocked
# products (acc_tn) are as fast with the sizes read at run time. Each such size is one
# more specialisation (a few seconds to compile once, then cached on disk); larger
# problems share one compiled pass.
FIXED_MAX_N = 7
FIXED_MAX_M = 4


def small_size(n: int, m: int) -> bool:
    """Whether ``n`` states and ``m`` controls are within the sizes the kernels may be
    compiled for (:func:`size_witness`); the solvers' unconstrained pass of such a
    problem runs in gain form, specialised or not."""
    return n <= FIXED_MAX_N and m <= FIXED_MAX_M


def size_witness(n: int, m: int) -> tuple[tuple, tuple]:
    """``(nt, mt)``, the kernels' size arguments: tuples of ``n`` and ``m`` zeros for a
    problem small enough to get a pass compiled for its sizes (numba types a tuple by
    its length, so ``len(nt)`` is a compile-time constant there), else two empty tuples
    (the sizes are read from the arrays). Sizes left out by
    :func:`.specialisation.limit_specialised_sizes` get the empty tuples too."""
    if small_size(n, m) and specialised(n, m):
        return (0,) * n, (0,) * m
    return (), ()


@numba.njit(cache=True, nogil=True, _nrt=False)
def _feedback_step(Ft, Kt, xt, ut, xn, affine):
    """``u_t = K_t x_t + f``, ``x_{t+1} = B_t u_t + A_t x_t (+ c_t)``: with ``affine`` the
    feedforward ``f`` is ``Kt[:, n]`` and ``c_t = Ft[:n, -1]`` is added (the LQ rollout);
    without, ``f`` is what ``ut`` holds on entry and there is no ``c_t`` (the adjoint
    problem's rollout)."""
    m = ut.shape[0]
    n = xt.shape[0]
    _controls(Kt, xt, ut, affine, m, n)
    for i in range(n):
        s = Ft[i, m + n] if affine else 0.0
        for j in range(m):
            s += Ft[i, j] * ut[j]
        for j in range(n):
            s += Ft[i, m + j] * xt[j]
        xn[i] = s


@numba.njit(cache=True, nogil=True, _nrt=False, inline="always")
def _controls(Kt, xt, ut, affine, m, n):
    """``ut = Kt[:, :n] xt + f`` for ``m`` controls and ``n`` states: ``f = Kt[:, n]``
    with ``affine``, else ``ut`` on entry. Inlined, so that sizes known when the caller
    is compiled (:func:`size_witness`) reach its loops."""
    for i in range(m):
        s = Kt[i, n] if affine else ut[i]
        for j in range(n):
            s += Kt[i, j] * xt[j]
        ut[i] = s


@numba.njit(cache=True, nogil=True, _nrt=False)
def rollout_kernel(b0, b1, F, Kk, x0, x, u):
    """``u_t = Kk_t [x_t; 1]``, ``x_{t+1} = F_t[:n] [u_t; x_t; 1]`` per element.

    F ``(BF, T, n+1, m+n+1)``, Kk ``(BK, T, m, n+1)``, x0 ``(BX, n)`` (batches 1 or
    B); outputs x ``(B, T+1, n)``, u ``(B, T, m)``.
    """
    T = u.shape[1]
    n = x.shape[2]
    for b in range(b0, b1):
        bf = b if F.shape[0] > 1 else 0
        bk = b if Kk.shape[0] > 1 else 0
        bx = b if x0.shape[0] > 1 else 0
        for i in range(n):
            x[b, 0, i] = x0[bx, i]
        for t in range(T):
            _feedback_step(F[bf, t], Kk[bk, t], x[b, t], u[b, t], x[b, t + 1], True)


@numba.njit(cache=True, nogil=True, _nrt=False, inline="always")
def _affine_step(A, Bm, c, affine, b, t, xt, ut, xn, m, n):
    """``xn = A_t xt + B_t ut (+ c_t)`` for element ``b`` (``c`` read where ``affine``),
    summed from ``c``, then ``B u``, then ``A x``. Inlined, as :func:`_controls`."""
    ba, ta = _idx(A, b, t)
    bb, tb = _idx(Bm, b, t)
    bc, tc = _idx(c, b, t) if affine else (0, 0)
    At = A[ba, ta]
    Bt = Bm[bb, tb]
    for i in range(n):
        s = c[bc, tc, i] if affine else 0.0
        for j in range(m):
            s += Bt[i, j] * ut[j]
        for j in range(n):
            s += At[i, j] * xt[j]
        xn[i] = s


@numba.njit(cache=True, nogil=True, _nrt=False)
def lq_rollout_kernel(b0, b1, A, Bm, c, Kk, x0, x, u, nt, mt):
    """``u_t = K_t x_t + k_t``, ``x_{t+1} = A_t x_t + B_t u_t + c_t`` per element, from
    the LQ data itself (no homogeneous ``F``): A ``(1 or B, 1 or T, n, n)``, Bm ``(.., n,
    m)``, c ``(.., n)`` (empty: zero), Kk ``(1 or B, T, m, n+1)``, x0 ``(1 or B, n)``;
    outputs x ``(B, T+1, n)``, u ``(B, T, m)``. The sums in :func:`_feedback_step`'s
    order, so the result is that of :func:`rollout_kernel` on the homogeneous ``F``.
    ``nt, mt``: :func:`size_witness`."""
    T = u.shape[1]
    fixed = len(nt) > 0
    n = len(nt) if fixed else x.shape[2]
    m = len(mt) if fixed else u.shape[2]
    affine = c.shape[0] > 0
    for b in range(b0, b1):
        bk = b if Kk.shape[0] > 1 else 0
        bx = b if x0.shape[0] > 1 else 0
        for i in range(n):
            x[b, 0, i] = x0[bx, i]
        for t in range(T):
            xt = x[b, t]
            ut = u[b, t]
            _controls(Kk[bk, t], xt, ut, True, m, n)
            _affine_step(A, Bm, c, affine, b, t, xt, ut, x[b, t + 1], m, n)


@numba.njit(cache=True, nogil=True)
def adjoint_kernel(b0, b1, F, Kk, Vh, L, gx, gu, dx, du, dlam):
    """The adjoint LQ solve of :func:`torchslq.lq.lq_adjoint_solve` per element.

    F ``(., T, n+1, m+n+1)``, Kk ``(., T, m, n+1)``, Vh ``(., T+1, n+1, n+1)``,
    L ``(., T, m, m)``, gx ``(., T+1, n)``, gu ``(., T, m)`` (each batch 1 or B);
    outputs dx ``(B, T+1, n)``, du ``(B, T, m)``,
    dlam ``(B, T+1, n)`` (dlam holds the linear value terms ``v_t`` until the end).
    """
    T, m = du.shape[1], du.shape[2]
    n = dx.shape[2]
    qu = np.empty(m, dtype=dx.dtype)
    for b in range(b0, b1):
        bf = b if F.shape[0] > 1 else 0
        bk = b if Kk.shape[0] > 1 else 0
        bg = b if gx.shape[0] > 1 else 0
        bgu = b if gu.shape[0] > 1 else 0
        bv = b if Vh.shape[0] > 1 else 0
        bl = b if L.shape[0] > 1 else 0
        v = dlam[b]
        for i in range(n):
            v[T, i] = gx[bg, T, i]
        for t in range(T - 1, -1, -1):
            Ft = F[bf, t]
            Lt = L[bl, t]
            Kt = Kk[bk, t]
            # qu = gu_t + B'v_{t+1};  k_t = -(L L')^{-1} qu (stored in du)
            for i in range(m):
                s = gu[bgu, t, i]
                for j in range(n):
                    s += Ft[j, i] * v[t + 1, j]
                qu[i] = s
            kt = du[b, t]
            for i in range(m):
                kt[i] = -qu[i]
            cholesky_solve(Lt, kt)
            # v_t = gx_t + A'v_{t+1} + K'qu
            for i in range(n):
                s = gx[bg, t, i]
                for j in range(n):
                    s += Ft[j, m + i] * v[t + 1, j]
                for j in range(m):
                    s += Kt[j, i] * qu[j]
                v[t, i] = s
        # forward: dx_0 = 0, du_t = K_t dx_t + k_t, dx_{t+1} = [B A] [du_t; dx_t]
        for i in range(n):
            dx[b, 0, i] = 0.0
        for t in range(T):  # (du holds k_t here)
            _feedback_step(F[bf, t], Kk[bk, t], dx[b, t], du[b, t], dx[b, t + 1], False)
        # dlam_t = V_t dx_t + v_t
        for t in range(T + 1):
            Vt = Vh[bv, t]
            for i in range(n):
                s = v[t, i]
                for j in range(n):
                    s += Vt[i, j] * dx[b, t, j]
                v[t, i] = s


@numba.njit(cache=True, nogil=True, _nrt=False)
def _qp_value(H, g, x):
    """``x'(g + H x / 2)``, the box QP's objective."""
    v = 0.0
    for i in range(x.shape[0]):
        s = 0.0
        for j in range(x.shape[0]):
            s += H[i, j] * x[j]
        v += x[i] * (g[i] + 0.5 * s)
    return v


@numba.njit(cache=True, nogil=True, _nrt=False)
def _box_qp(H, g, lower, upper, x, tol, opts, clamped, Lf, work):
    """Projected-Newton box QP of :func:`torchslq.lq.box_qp` for one element (same
    iteration, same stopping rules, ``min_rel_improve = 0``; ``opts = (max_iter, armijo,
    step_dec, n_steps)``, box_qp's defaults). ``x`` (m,) is the warm start on
    entry (projected here) and the solution on exit; ``clamped`` (m,) bool and ``Lf``
    (m, m), the free-block factor (identity on clamped rows/columns), are outputs;
    ``work`` is scratch of shape (4, m). Returns success."""
    m = g.shape[0]
    for i in range(m):
        x[i] = min(max(x[i], lower[i]), upper[i])
    if m == 1:  # closed form, as _box_qp_scalar
        h = H[0, 0]
        pos = h > 0
        grad0 = g[0] + h * x[0]
        start_clamped = (x[0] <= lower[0] and grad0 > 0) or (x[0] >= upper[0] and grad0 < 0)
        if pos:
            x[0] = min(max(-g[0] / h, lower[0]), upper[0])
        grad = g[0] + h * x[0]
        clamped[0] = (x[0] <= lower[0] and grad > 0) or (x[0] >= upper[0] and grad < 0)
        Lf[0, 0] = math.sqrt(h) if (pos and not clamped[0]) else 1.0
        return (pos or start_clamped) and math.isfinite(x[0])
    grad = work[0]
    newton = work[1]
    xc = work[2]
    rhs = work[3]
    value = _qp_value(H, g, x)
    success = True
    stop = False  # set after an accepted step that did not improve: refresh, then stop
    max_iter, armijo, step_dec, n_steps = opts
    for it in range(max_iter + 1):
        # gradient, clamped set and free-block factor at the current x
        for i in range(m):
            s = g[i]
            for j in range(m):
                s += H[i, j] * x[j]
            grad[i] = s
        n_clamped = 0
        gnorm2 = 0.0
        for i in range(m):
            c = (x[i] <= lower[i] and grad[i] > 0) or (x[i] >= upper[i] and grad[i] < 0)
            clamped[i] = c
            if c:
                n_clamped += 1
            else:
                gnorm2 += grad[i] * grad[i]
        indefinite = not _cholesky(H, 0.0, clamped, Lf)
        if indefinite:
            success = False
            break
        if stop or n_clamped == m or math.sqrt(gnorm2) < tol or it == max_iter:
            break
        # Newton point on the free subspace: x_f = -H_ff^{-1} (g_f + H_fc x_c)
        for ii in range(m):
            if clamped[ii]:
                rhs[ii] = 0.0
                continue
            s = grad[ii]
            for jj in range(m):
                if not clamped[jj]:
                    s -= H[ii, jj] * x[jj]
            rhs[ii] = s
        for ii in range(m):  # L y = rhs
            s = rhs[ii]
            for k in range(ii):
                s -= Lf[ii, k] * newton[k]
            newton[ii] = s / Lf[ii, ii]
        for ii in range(m - 1, -1, -1):  # L' z = y
            s = newton[ii]
            for k in range(ii + 1, m):
                s -= Lf[k, ii] * newton[k]
            newton[ii] = s / Lf[ii, ii]
        sdotg = 0.0
        for ii in range(m):
            newton[ii] = x[ii] if clamped[ii] else -newton[ii]
            sdotg += (newton[ii] - x[ii]) * grad[ii]
        if not (sdotg < 0):
            break  # no descent direction: x is optimal to working precision
        # projected Armijo search, largest step first (the full step is the projected
        # Newton point itself)
        found = False
        v_new = 0.0
        for jstep in range(n_steps):
            step = step_dec**jstep
            for ii in range(m):
                xi = newton[ii] if jstep == 0 else x[ii] + step * (newton[ii] - x[ii])
                xc[ii] = min(max(xi, lower[ii]), upper[ii])
            v = _qp_value(H, g, xc)
            if (v - value) <= armijo * step * sdotg:
                found = True
                v_new = v
                break
        if not found:
            break
        for ii in range(m):
            x[ii] = xc[ii]
        stop = (value - v_new) <= 0.0
        value = v_new
    for i in range(m):
        if not math.isfinite(x[i]):
            return False
    return success


@numba.njit(cache=True, nogil=True, _nrt=False)
def _stage_matrix(Vn, Ft, Ht, Hz, Hb, t, b, VF, M):
    """``M = H_t + F_t' Vh_{t+1} F_t`` (upper triangle, mirrored), plus DDP's
    ``v_{t+1} . f_zz`` on the ``[u; x]`` block when ``Hz`` ``(T, n, B, m+n, m+n)`` or the
    blocks ``Hb = (Hxx (n, B, T, n, n), Huu (n, B, T, m, m), Hux (n, B, T, m, n))`` are
    not empty."""
    n1, mn1 = Ft.shape
    n = n1 - 1
    # register-blocked products (acc_tn); all of H is copied, the upper triangle of
    # F'VF added and mirrored, so that M is exactly symmetric
    VF[:] = 0.0
    acc_tn(VF, Vn.T, Ft, 1.0, False)
    for i in range(mn1):
        mi = M[i]
        hi = Ht[i]
        for j in range(mn1):
            mi[j] = hi[j]
    acc_tn(M, Ft, VF, 1.0, True)
    for i in range(mn1):
        for j in range(i + 1, mn1):
            M[j, i] = M[i, j]
    if Hz.shape[0] > 0:
        for k in range(n):
            v = Vn[k, n]
            Hk = Hz[t, k, b]
            for i in range(mn1 - 1):
                for j in range(mn1 - 1):
                    M[i, j] += v * Hk[i, j]
    Hxx, Huu, Hux = Hb
    if Hxx.shape[0] > 0:
        m = mn1 - n1
        for k in range(n):
            v = Vn[k, n]
            hxx = Hxx[k, b, t]
            huu = Huu[k, b, t]
            hux = Hux[k, b, t]
            for i in range(m):
                mi = M[i]
                for j in range(m):
                    mi[j] += v * huu[i, j]
                for j in range(n):
                    mi[m + j] += v * hux[i, j]
            for i in range(n):
                mi = M[m + i]
                for j in range(m):
                    mi[j] += v * hux[j, i]
                hi = hxx[i]
                for j in range(n):
                    mi[m + j] += v * hi[j]


@numba.njit(cache=True, nogil=True, _nrt=False)
def _cholesky(A, r, cl, Lb):
    """Lower factor of ``A[:m, :m] + r I`` into ``Lb``, with the rows and columns in
    ``cl`` replaced by the identity's (the box QP's free block); False if not positive
    definite (or not finite)."""
    m = Lb.shape[0]
    for j in range(m):
        if cl[j]:
            for i in range(m):  # identity row and column
                Lb[i, j] = 0.0
                Lb[j, i] = 0.0
            Lb[j, j] = 1.0
            continue
        s = A[j, j] + r
        for k in range(j):
            s -= Lb[j, k] * Lb[j, k]
        if not (s > 0.0):  # also catches NaN
            return False
        d = math.sqrt(s)
        Lb[j, j] = d
        for i in range(j):
            Lb[i, j] = 0.0  # upper triangle
        for i in range(j + 1, m):
            if cl[i]:
                Lb[i, j] = 0.0
                continue
            s2 = A[i, j]
            for k in range(j):
                s2 -= Lb[i, k] * Lb[j, k]
            Lb[i, j] = s2 / d
    return True


@numba.njit(cache=True, nogil=True, _nrt=False, inline="always")
def cholesky_solve(Lb, x):
    """``x := (Lb Lb')^{-1} x`` in place, ``Lb (k, k)`` lower (:func:`_cholesky`'s
    factor; its lower triangle is read), ``x (k,)``: forward then back substitution."""
    k = x.shape[0]
    for i in range(k):
        s = x[i]
        for j in range(i):
            s -= Lb[i, j] * x[j]
        x[i] = s / Lb[i, i]
    for i in range(k - 1, -1, -1):
        s = x[i]
        for j in range(i + 1, k):
            s -= Lb[j, i] * x[j]
        x[i] = s / Lb[i, i]


@numba.njit(cache=True, nogil=True, _nrt=False)
def _gains(Lb, M, ncols, cl, Kt):
    """``Kt[:, c] = -(Lb Lb')^{-1} M[:m, m + c]`` for ``c < ncols``, rows in ``cl``
    (clamped controls) given a zero right-hand side. Substitutions on whole rows of
    ``Kt`` (all columns at once: contiguous, vectorised inner loops)."""
    m = Lb.shape[0]
    for i in range(m):  # forward: Lb y = -M[:m, m:]
        ki = Kt[i]
        for c in range(ncols):
            ki[c] = 0.0 if cl[i] else -M[i, m + c]
        for k in range(i):
            _row_update(ki, Lb[i, k], Kt[k], ncols)
        _row_scale(ki, 1.0 / Lb[i, i], ncols)
    for i in range(m - 1, -1, -1):  # backward: Lb' Kt = y
        ki = Kt[i]
        for k in range(i + 1, m):
            _row_update(ki, Lb[k, i], Kt[k], ncols)
        _row_scale(ki, 1.0 / Lb[i, i], ncols)


@numba.njit(cache=True, nogil=True, _nrt=False)
def _row_update(dst, a, src, ncols):
    """``dst[:ncols] -= a * src[:ncols]``."""
    for c in range(ncols):
        dst[c] -= a * src[c]


@numba.njit(cache=True, nogil=True, _nrt=False)
def _row_scale(dst, d, ncols):
    for c in range(ncols):
        dst[c] *= d


@numba.njit(cache=True, nogil=True, _nrt=False)
def _idx(a, b, t):
    """Batch and time index into a piece of shape ``(1 or B, 1 or T, ...)``."""
    return (b if a.shape[0] > 1 else 0), (t if a.shape[1] > 1 else 0)


@numba.njit(cache=True, nogil=True, _nrt=False, inline="always")
def _assemble_stage(pieces, b, t, Fs, Hs):
    """``F_t = [[B, A, c], [0, 0, 1]]`` into ``Fs`` (its last row is set once by the
    caller) and the upper triangle of ``H_t = [[R, S, r], [S', Q, q], [r', q', 0]]``
    into ``Hs`` (all that :func:`_stage_matrix` reads: it mirrors ``M``'s upper
    triangle), with the symmetric parts of ``Q`` and ``R`` (as
    :func:`torchslq.lq.riccati.homogeneous_cost`)."""
    A, Bm, c, Q, R, S, q, r = pieces
    n = A.shape[2]
    m = Bm.shape[3]
    # 2-d views of this step's pieces (no reference counts here: module docstring), read
    # with two indices instead of four
    ba, ta = _idx(A, b, t)
    At = A[ba, ta]
    bb, tb = _idx(Bm, b, t)
    Bt = Bm[bb, tb]
    for i in range(n):
        Fi = Fs[i]
        for j in range(m):
            Fi[j] = Bt[i, j]
        for j in range(n):
            Fi[m + j] = At[i, j]
    if c.shape[0] > 0:
        bc, tc = _idx(c, b, t)
        ct = c[bc, tc]
        for i in range(n):
            Fs[i, m + n] = ct[i]
    bq, tq = _idx(Q, b, t)
    Qt = Q[bq, tq]
    br, tr = _idx(R, b, t)
    Rt = R[br, tr]
    for i in range(m):
        for j in range(m):
            Hs[i, j] = 0.5 * (Rt[i, j] + Rt[j, i])
    for i in range(n):
        for j in range(n):
            Hs[m + i, m + j] = 0.5 * (Qt[i, j] + Qt[j, i])
    if S.shape[0] > 0:
        bs, ts = _idx(S, b, t)
        St = S[bs, ts]
        for i in range(m):
            for j in range(n):
                Hs[i, m + j] = St[i, j]
    if r.shape[0] > 0:
        bl, tl = _idx(r, b, t)
        rt = r[bl, tl]
        for i in range(m):
            Hs[i, m + n] = rt[i]
    if q.shape[0] > 0:
        bl, tl = _idx(q, b, t)
        qt = q[bl, tl]
        for i in range(n):
            Hs[m + i, m + n] = qt[i]


@numba.njit(cache=True, nogil=True, _nrt=False)
def _assemble_terminal(pieces, b, T, Vt):
    """``Vh_T = [[Q_T, q_T], [q_T', 0]]`` (symmetric part of ``Q_T``) into ``Vt``."""
    Q, q = pieces[3], pieces[6]
    n = Q.shape[2]
    bq, tq = _idx(Q, b, T)
    for i in range(n + 1):
        for j in range(n + 1):
            Vt[i, j] = 0.0
    for i in range(n):
        for j in range(n):
            Vt[i, j] = 0.5 * (Q[bq, tq, i, j] + Q[bq, tq, j, i])
    if q.shape[0] > 0:
        bl, tl = _idx(q, b, T)
        for i in range(n):
            Vt[i, n] = q[bl, tl, i]
            Vt[n, i] = q[bl, tl, i]


@numba.njit(cache=True, nogil=True)
def riccati_kernel(
    b0,
    b1,
    F,
    H,
    VhT,
    reg,
    Hz,
    Hb,
    short_form,
    lower,
    upper,
    tol_base,
    box_opts,
    Kk,
    Vh,
    L,
    clamped,
    failed,
    dV,
    pieces,
    restart_opts,
    mu_io,
    delta_io,
    may_restart,
):
    """One Riccati pass per element (see riccati_homogeneous for the equations).

    F ``(BF, T, n+1, m+n+1)``, H ``(BH, T, m+n+1, m+n+1)``, VhT ``(BV, n+1, n+1)``
    (each batch 1 or B), reg ``(BR,)`` (1 or B), Hz ``(T, n, B, m+n, m+n)`` or empty, Hb
    the same Hessians as three blocks ``(n, B, T, ., .)`` (or empty, see _stage_matrix);
    ``short_form``: the value update ``M_zz + M_uz'Kk`` (no reg, as the torch path)
    instead of the general form. Control-limited pass (``riccati._riccati_box``, Tassa,
    Mansard & Todorov 2014) when lower/upper ``(BB, T, m)`` are not empty: the
    feedforward term from the box QP (:func:`_box_qp`, warm-started from the next
    step's, tolerance ``tol_base (1 + |qu|_inf)``, ``box_opts`` as for :func:`_box_qp`), feedback rows of clamped controls
    zero, outputs clamped ``(B, T, m)`` and dV ``(B, 2)`` (``[sum k'qu,
    sum k'(Quu + reg) k]``). Outputs Kk ``(B, T, m, n+1)``, Vh ``(B, T+1, n+1, n+1)``,
    L ``(B, T, m, m)``, failed ``(B,)``. An element whose factorisation fails (not
    positive definite, or not finite) is marked failed and its earlier steps are left
    at zero (the torch path's values there are meaningless too). Only elements
    ``b0 <= b < b1`` are computed (see ``dispatch._launch``).

    ``pieces``: when ``F`` is empty, the LQ data as ``(A, B, c, Q, R, S, q, r)`` (each
    ``(1 or B, 1 or T (T+1 for Q, q), ...)``, ``c, S, q, r`` possibly empty for zero);
    each step's ``F_t``, ``H_t`` and the terminal ``Vh_T`` are then assembled in scratch
    (:func:`_assemble_stage`) instead of being read from tensors built beforehand.

    Restarts (Tassa et al.'s schedule, as ``ILQR._retry_failed``) when ``mu_io`` is not
    empty: element ``b`` starts with ``reg = mu_io[b]``; when its pass fails (not positive
    definite, or non-finite gains) and ``may_restart[b]``, ``delta := max(f, delta f)``,
    ``reg := max(floor, reg delta)`` (``restart_opts = (f, floor, mu_max, max_restarts)``)
    and the pass is repeated, until it succeeds, ``reg > mu_max`` (that pass is still
    made) or ``max_restarts`` restarts were made; the last ``reg``, ``delta`` are written
    back to ``mu_io``, ``delta_io`` (``(B,)``).
    """
    T = Kk.shape[1]
    m = Kk.shape[2]
    n1 = Kk.shape[3]
    n = n1 - 1
    mn1 = m + n1
    boxed = lower.shape[0] > 0
    VF = np.empty((n1, mn1), dtype=Vh.dtype)
    M = np.empty((mn1, mn1), dtype=Vh.dtype)
    Lb = np.zeros((m, m), dtype=Vh.dtype)
    Quu_r = np.empty((m, m), dtype=Vh.dtype)
    qu = np.empty(m, dtype=Vh.dtype)
    k = np.empty(m, dtype=Vh.dtype)
    cl = np.zeros(m, dtype=np.bool_)
    work = np.empty((4, m), dtype=Vh.dtype)
    W = np.empty((m, n1), dtype=Vh.dtype)
    assembled = F.shape[0] == 0
    Fs = np.zeros((n1, mn1), dtype=Vh.dtype)
    Fs[n, mn1 - 1] = 1.0  # the homogeneous row [0 ... 0 1]
    Hs = np.zeros((mn1, mn1), dtype=Vh.dtype)
    restarting = mu_io.shape[0] > 0
    # Hz as a view (layout "A" whether DDP's strided Hessians or iLQR's empty array):
    # one compilation of the element pass for both solvers instead of two
    Hz_view = Hz[:, :, :, :, :]
    for b in range(b0, b1):
        bf = b if F.shape[0] > 1 else 0
        bh = b if H.shape[0] > 1 else 0
        bv = b if VhT.shape[0] > 1 else 0
        bb = b if lower.shape[0] > 1 else 0
        r = reg[b if reg.shape[0] > 1 else 0]
        delta = 0.0
        if restarting:
            r = mu_io[b]
            delta = delta_io[b]
        restarts = 0
        while True:
            ok, slope, curv = _element_pass(
                b, bf, bh, bv, bb, r, F, H, VhT, Hz_view, Hb, short_form, lower, upper, tol_base,
                box_opts, Kk, Vh, L, clamped, pieces, assembled, boxed, VF, M, Lb, Quu_r,
                qu, k, cl, work, W, Fs, Hs,
            )  # fmt: skip
            if not restarting:
                break
            if ok:
                ok = finite_gains(Kk[b])
            stop, r, delta = restart_step(ok, may_restart[b], r, delta, restarts, restart_opts)
            if stop:
                break
            restarts += 1
            # a fresh pass leaves zeros below a failing step: so does a repeated one
            Kk[b] = 0.0
            L[b] = 0.0
            Vh[b, :T] = 0.0
        failed[b] = not ok
        if restarting:
            mu_io[b] = r
            delta_io[b] = delta
        if boxed:
            dV[b, 0] = slope
            dV[b, 1] = curv


@numba.njit(cache=True, nogil=True, _nrt=False)
def finite_gains(Kb):
    """Whether every entry of one element's gains ``(T, m, n+1)`` is finite."""
    for t in range(Kb.shape[0]):
        for i in range(Kb.shape[1]):
            for j in range(Kb.shape[2]):
                if not math.isfinite(Kb[t, i, j]):
                    return False
    return True


@numba.njit(cache=True, nogil=True, _nrt=False)
def restart_step(ok, may_restart, r, delta, restarts, opts):
    """Tassa et al.'s schedule after an element's pass with regularisation ``r``:
    ``(stop, r, delta)``. The pass is repeated (``stop`` False) with ``delta := max(f,
    delta f)``, ``r := max(floor, r delta)`` where it failed, the element may restart,
    ``r <= mu_max`` and fewer than ``max_restarts`` restarts were made (``opts = (f,
    floor, mu_max, max_restarts)``)."""
    if ok or not may_restart or r > opts[2] or restarts >= opts[3]:
        return True, r, delta
    delta = max(opts[0], delta * opts[0])
    return False, max(opts[1], r * delta), delta


@numba.njit(cache=True, nogil=True, _nrt=False)
def _element_pass(
    b, bf, bh, bv, bb, r, F, H, VhT, Hz, Hb, short_form, lower, upper, tol_base, box_opts,
    Kk, Vh, L, clamped, pieces, assembled, boxed, VF, M, Lb, Quu_r, qu, k, cl, work, W,
    Fs, Hs,
):  # fmt: skip
    """The pass of element ``b`` with regularisation ``r`` (the body of
    :func:`riccati_kernel`); returns ``(ok, slope, curv)``."""
    T = Kk.shape[1]
    m = Kk.shape[2]
    n1 = Kk.shape[3]
    n = n1 - 1
    mn1 = m + n1
    if assembled:
        _assemble_terminal(pieces, b, T, Vh[b, T])
    else:
        for i in range(n1):
            for j in range(n1):
                Vh[b, T, i, j] = VhT[bv, i, j]
    for i in range(m):
        k[i] = 0.0
    slope = 0.0
    curv = 0.0
    ok = True
    for t in range(T - 1, -1, -1):
        # 2-d views of this step's matrices (cheaper indexing than 4-d)
        Vn = Vh[b, t + 1]
        Vc = Vh[b, t]
        Kt = Kk[b, t]
        if assembled:
            _assemble_stage(pieces, b, t, Fs, Hs)
            _stage_matrix(Vn, Fs, Hs, Hz, Hb, t, b, VF, M)
        else:
            _stage_matrix(Vn, F[bf, t], H[bh, t], Hz, Hb, t, b, VF, M)
        if boxed:
            for i in range(m):
                for j in range(m):
                    Quu_r[i, j] = M[i, j] + (r if i == j else 0.0)
                qu[i] = M[i, mn1 - 1]
            qmax = 0.0
            for i in range(m):
                qmax = max(qmax, abs(qu[i]))
            tol = tol_base * (1.0 + qmax)
            if not _box_qp(Quu_r, qu, lower[bb, t], upper[bb, t], k, tol, box_opts, cl, Lb, work):
                ok = False
                break
            _gains(Lb, M, n, cl, Kt)
            for i in range(m):
                Kt[i, n] = k[i]
                clamped[b, t, i] = cl[i]
                slope += k[i] * qu[i]
                acc = 0.0
                for j in range(m):
                    acc += Quu_r[i, j] * k[j]
                curv += k[i] * acc
        else:
            if not _cholesky(M, r, cl, Lb):
                ok = False
                break
            _gains(Lb, M, n1, cl, Kt)  # [K_t, k_t] together (cl all False)
        Lt = L[b, t]
        for i in range(m):
            for j in range(i + 1):
                Lt[i, j] = Lb[i, j]
        if short_form:  # Vh_t = M_zz + M_uz'Kk, symmetrised (row order)
            for i in range(n1):
                vi = Vc[i]
                for j in range(n1):
                    vi[j] = M[m + i, m + j]
                for p in range(m):
                    a = M[p, m + i]
                    kp = Kt[p]
                    for j in range(n1):
                        vi[j] += a * kp[j]
            for i in range(n1):
                for j in range(i, n1):
                    s = 0.5 * (Vc[i, j] + Vc[j, i])
                    Vc[i, j] = s
                    Vc[j, i] = s
            continue
        # Vh_t = M_zz + Kk'Quu Kk + Kk'M_uz + M_uz'Kk (Tassa et al. 2012's form,
        # exact for any gains, hence also with reg and with clamped rows), as
        # M_zz + Kk'W + M_uz'Kk with W = Quu Kk + M_uz; row (axpy) order, the upper
        # triangle mirrored
        for p in range(m):
            wp = W[p]
            for j in range(n1):
                wp[j] = M[p, m + j]
            for q in range(m):
                a = M[p, q]
                kq = Kt[q]
                for j in range(n1):
                    wp[j] += a * kq[j]
        for i in range(n1):
            vi = Vc[i]
            for j in range(n1):
                vi[j] = M[m + i, m + j]
            for p in range(m):
                a = Kt[p, i]
                c = M[p, m + i]
                wp = W[p]
                kp = Kt[p]
                for j in range(n1):
                    vi[j] += a * wp[j] + c * kp[j]
        for i in range(n1):
            for j in range(i + 1, n1):
                Vc[j, i] = Vc[i, j]
    return ok, slope, curv


@numba.njit(cache=True, nogil=True)
def stage_congruence_kernel(j0, j1, hxx, huu, hux, dk, scale, Hxx, Huu, Hux):
    """One RK4 stage's term of the chained second derivatives (``discretize``'s vhp):
    with ``P = I + scale dk[:, :n]`` and ``Q = scale dk[:, n:]`` (``Z = [[P, Q], [0, I]]``
    = d zeta / dz of the stage's argument), add ``Z' [[hxx, hux'], [hux, huu]] Z``:

    ``Hxx += P' hxx P``, ``Hux += (hxx Q + hux')' P``,
    ``Huu += huu + Q' (hxx Q + hux') + hux Q``.

    hxx ``(J, n, n)``, huu ``(J, m, m)``, hux ``(J, m, n)`` and the outputs are rows
    ``j = e R + r`` of ``E`` weight vectors times ``R`` points; dk ``(R, n, n+m)`` is
    shared by the ``E`` rows of point ``r``. Rows ``j0 <= j < j1`` (see ``_launch``).
    """
    R = dk.shape[0]
    n = hxx.shape[1]
    m = huu.shape[1]
    P = np.empty((n, n), dtype=hxx.dtype)
    Q = np.empty((n, m), dtype=hxx.dtype)
    HP = np.empty((n, n), dtype=hxx.dtype)
    t1 = np.empty((n, m), dtype=hxx.dtype)
    row_nz = np.zeros(n, dtype=np.bool_)
    t1_nz = np.zeros(n, dtype=np.bool_)
    r_prev = -1
    for j in range(j0, j1):
        r = j % R
        if r != r_prev:
            D = dk[r]
            for a in range(n):
                for b in range(n):
                    P[a, b] = scale * D[a, b]
                P[a, a] += 1.0
                for k in range(m):
                    Q[a, k] = scale * D[a, n + k]
            r_prev = r
        h = hxx[j]
        g = hux[j]
        # HP = hxx P and t1 = hxx Q + hux', row by row. Models' second derivatives are
        # mostly zero (only some states enter nonlinearly): zero entries of hxx are
        # skipped, and so are the rows of HP they leave zero in the next product
        for a in range(n):
            hp = HP[a]
            ta = t1[a]
            for b in range(n):
                hp[b] = 0.0
            for k in range(m):
                ta[k] = g[k, a]
            nz = False
            for c in range(n):
                hac = h[a, c]
                if hac == 0.0:
                    continue
                nz = True
                pc = P[c]
                qc = Q[c]
                for b in range(n):
                    hp[b] += hac * pc[b]
                for k in range(m):
                    ta[k] += hac * qc[k]
            row_nz[a] = nz
            for k in range(m):
                nz = nz or g[k, a] != 0.0
            t1_nz[a] = nz
        # Hxx += P' HP: symmetric (hxx is, and so is every earlier stage's sum), so the
        # upper triangle is computed and mirrored
        O = Hxx[j]
        for c in range(n):
            if not row_nz[c]:
                continue
            pc = P[c]
            hc = HP[c]
            for a in range(n):
                pca = pc[a]
                if pca == 0.0:
                    continue
                oa = O[a]
                for b in range(a, n):
                    oa[b] += pca * hc[b]
        for a in range(n):
            for b in range(a + 1, n):
                O[b, a] = O[a, b]
        # Hux += t1' P, Huu += huu + Q' t1 + hux Q (zero rows of t1, entries of hux
        # skipped)
        G = Hux[j]
        U = Huu[j]
        hu = huu[j]
        for k in range(m):
            uk = U[k]
            for l in range(m):
                uk[l] += hu[k, l]
        for a in range(n):
            if not t1_nz[a]:
                continue
            pa = P[a]
            ta = t1[a]
            qa = Q[a]
            for k in range(m):
                tak = ta[k]
                gk = G[k]
                for b in range(n):
                    gk[b] += tak * pa[b]
                qak = qa[k]
                uk = U[k]
                for l in range(m):
                    uk[l] += qak * ta[l]
        for k in range(m):
            gk_row = g[k]
            uk = U[k]
            for a in range(n):
                gka = gk_row[a]
                if gka == 0.0:
                    continue
                qa = Q[a]
                for l in range(m):
                    uk[l] += gka * qa[l]


@numba.njit(cache=True, nogil=True, _nrt=False)
def feedback_kernel(t, x, xn, K, lo, hi, u):
    """``u[r, t] += K[b, t] (x[r] - xn[b, t])``, then clamped into ``[lo, hi]`` (when
    not empty): the feedback of a closed-loop rollout at step ``t`` for rows ``r`` of
    ``x (R, n)``, ``b = r % B``; ``u (R, T, m)`` holds the feedforward on entry.
    xn ``(B, T, n)``, K ``(B, T, m, n)``, lo, hi ``(B, T, m)`` or empty."""
    R = x.shape[0]
    B = xn.shape[0]
    for r in range(R):
        _feedback_row(x[r], xn, K, lo, hi, r % B, t, u[r, t])


@numba.njit(cache=True, nogil=True, _nrt=False)
def _feedback_row(xr, xn, K, lo, hi, b, t, ur):
    """``ur += K[b, t] (xr - xn[b, t])``, clamped into ``[lo[b, t], hi[b, t]]`` when
    the bounds are not empty (one row of :func:`feedback_kernel`)."""
    Kt = K[b, t]
    xnr = xn[b, t]
    bounded = lo.shape[0] > 0
    for i in range(ur.shape[0]):
        # the feedback summed first, then the feedforward added: the torch path's
        # order of operations (ff + (x - xn) @ K')
        s = 0.0
        Ki = Kt[i]
        for j in range(xr.shape[0]):
            s += Ki[j] * (xr[j] - xnr[j])
        s += ur[i]
        if bounded:
            s = min(max(s, lo[b, t, i]), hi[b, t, i])
        ur[i] = s


@numba.njit(cache=True, nogil=True, _nrt=False)
def costate_kernel(b0, b1, A, B, lx, lu, K, grad, lam):
    """The costate recursion of ``dynamics.rollout.costate_gradient`` per element:
    ``lam_T = lx_T``, ``g_t = lu_t + B_t' lam_{t+1}``, ``lam_t = lx_t + A_t' lam_{t+1}
    (+ K_t' g_t)``. A ``(., T, n, n)``, B ``(., T, n, m)``, lx ``(., T+1, n)``, lu ``(., T,
    m)``, K ``(., T, m, n)`` or empty (each batch 1 or B); outputs grad ``(B, T, m)``,
    lam ``(B, T+1, n)``."""
    T = grad.shape[1]
    m = grad.shape[2]
    n = lam.shape[2]
    feedback = K.shape[0] > 0
    for b in range(b0, b1):
        ba = b if A.shape[0] > 1 else 0
        bb = b if B.shape[0] > 1 else 0
        bx = b if lx.shape[0] > 1 else 0
        bu = b if lu.shape[0] > 1 else 0
        bk = b if K.shape[0] > 1 else 0
        for i in range(n):
            lam[b, T, i] = lx[bx, T, i]
        for t in range(T - 1, -1, -1):
            ln = lam[b, t + 1]
            g = grad[b, t]
            Bt = B[bb, t]
            # the products summed first, then the gradients added (the torch path's order)
            for j in range(m):
                g[j] = 0.0
            for i in range(n):
                li = ln[i]
                Bi = Bt[i]
                for j in range(m):
                    g[j] += Bi[j] * li
            for j in range(m):
                g[j] += lu[bu, t, j]
            lc = lam[b, t]
            At = A[ba, t]
            for j in range(n):
                lc[j] = 0.0
            for i in range(n):
                li = ln[i]
                Ai = At[i]
                for j in range(n):
                    lc[j] += Ai[j] * li
            for j in range(n):
                lc[j] += lx[bx, t, j]
            if feedback:
                Kt = K[bk, t]
                for j in range(n):
                    s = 0.0
                    for i in range(m):
                        s += Kt[i, j] * g[i]
                    lc[j] += s


# How a model's step is given to the rollout kernels (``mode``): its own compiled step
# ``step(x, u, p, out, work)``; the RK4 step of a continuous model's ``rhs(x, u, p[1:],
# out)`` with ``p[0] = dt``; or a discrete model's step written as ``rhs(x, u, p, out)``.
STEP_GIVEN = 0
STEP_RK4 = 1
STEP_DISCRETE = 2


@numba.njit(nogil=True, _nrt=False)
def rk4_step_with(rhs, x, u, p, out, work):
    """One RK4 step of ``rhs(x, u, p[1:], out)`` with ``p[0] = dt`` into ``out``."""
    # the same sums in the same order as DiscretizedDynamics.forward; work rows:
    # k, the stage argument, k1 + 2 k2, k3
    n = x.shape[0]
    dt = p[0]
    q = p[1:]
    k, xi, a, k3 = work[0], work[1], work[2], work[3]
    rhs(x, u, q, k)
    for i in range(n):
        a[i] = k[i]
        xi[i] = x[i] + (0.5 * dt) * k[i]
    rhs(xi, u, q, k)
    for i in range(n):
        a[i] = a[i] + 2.0 * k[i]
        xi[i] = x[i] + (0.5 * dt) * k[i]
    rhs(xi, u, q, k3)
    for i in range(n):
        xi[i] = x[i] + dt * k3[i]
    rhs(xi, u, q, k)
    for i in range(n):
        out[i] = x[i] + (dt / 6.0) * (a[i] + (k[i] + 2.0 * k3[i]))


@numba.njit(nogil=True, _nrt=False)
def _model_step(step, rhs, mode, x, u, p, out, work):
    """``out = f(x, u)`` by the model's step as ``mode`` says (see ``STEP_GIVEN``)."""
    if mode == STEP_RK4:
        rk4_step_with(rhs, x, u, p, out, work)
    elif mode == STEP_DISCRETE:
        rhs(x, u, p, out)
    else:
        step(x, u, p, out, work)


@numba.njit(nogil=True, cache=True, _nrt=False)
def no_rhs(x, u, p, out):
    """Stands in for the ``rhs`` a ``STEP_GIVEN`` kernel call does not use."""


@numba.njit(nogil=True, cache=True, _nrt=False)
def no_step(x, u, p, out, work):
    """Stands in for the ``step`` a ``STEP_RK4`` / ``STEP_DISCRETE`` call does not use."""


@numba.njit(nogil=True, cache=True)
def closed_loop_rollout_kernel(r0, r1, step, rhs, mode, p, x0, xn, K, lo, hi, skip, u, x):
    """A whole closed-loop rollout per row with a model's compiled step: ``u[r, t] +=
    K[b, t] (x[r, t] - xn[b, t])`` (clamped into ``[lo, hi]`` when not empty; the
    feedforward is in ``u`` on entry, the same order of operations as
    :func:`feedback_kernel`), ``x[r, t+1] = f(x[r, t], u[r, t])`` with ``f`` given by
    ``step``, ``rhs`` and ``mode`` (see ``STEP_GIVEN``; ``work`` an ``(8, n)`` scratch
    array). x0 ``(R, n)``, xn ``(B, T, n)``, K ``(B, T, m, n)``, lo/hi ``(B, T, m)`` or
    empty, u ``(R, T, m)``, x ``(R, T+1, n)`` (output); ``b = r % B``. Rows ``r0 <= r <
    r1``; rows with ``skip[r]`` (``(R,)`` bool, or empty for none) are not rolled out:
    their states after ``x0`` are NaN (a line search's trial that no element needs).
    Compiled once per machine with the functions as first-class arguments
    (:mod:`torchslq._backend.model_fns`)."""
    work = np.empty((8, x.shape[2]), dtype=x.dtype)  # the step's scratch
    _closed_loop_rows(r0, r1, step, rhs, mode, p, x0, xn, K, lo, hi, skip, u, x, work)


@numba.njit(nogil=True, cache=True, _nrt=False)
def _closed_loop_rows(r0, r1, step, rhs, mode, p, x0, xn, K, lo, hi, skip, u, x, work):
    """The loop of :func:`closed_loop_rollout_kernel` (no reference counting: module
    docstring)."""
    B = xn.shape[0]
    T = u.shape[1]
    n = x.shape[2]
    skipping = skip.shape[0] > 0
    for r in range(r0, r1):
        for j in range(n):
            x[r, 0, j] = x0[r, j]
        if skipping and skip[r]:
            x[r, 1:, :] = np.nan
            continue
        b = r % B
        for t in range(T):
            xr = x[r, t]
            ur = u[r, t]
            _feedback_row(xr, xn, K, lo, hi, b, t, ur)
            _model_step(step, rhs, mode, xr, ur, p, x[r, t + 1], work)


@numba.njit(nogil=True, cache=True)
def closed_loop_rows_kernel(r0, r1, rows_fn, p, x0, xn, K, lo, hi, skip, u, x):
    """:func:`closed_loop_rollout_kernel` with the model's step on many rows at once
    (``rows_fn(r0, r1, X, U, p, OUT)``, :func:`torchslq._backend.model_fns.register_rows`):
    the rows ``r0 <= r < r1`` rolled out side by side, one call of ``rows_fn`` per time
    step (the same rollouts; the step's values agree with the one-row step's to
    rounding)."""
    nr, n, m = r1 - r0, x.shape[2], u.shape[2]
    rows = np.empty(nr, dtype=np.int64)
    X = np.empty((nr, n), dtype=x.dtype)
    U = np.empty((nr, m), dtype=x.dtype)
    OUT = np.empty((nr, n), dtype=x.dtype)
    count = 0
    for r in range(r0, r1):
        if skip.shape[0] > 0 and skip[r]:
            for j in range(n):
                x[r, 0, j] = x0[r, j]
            x[r, 1:, :] = np.nan
        else:
            rows[count] = r
            count += 1
    _closed_loop_row_set(rows, count, rows_fn, p, x0, xn, K, lo, hi, u, x, X, U, OUT)


@numba.njit(nogil=True, cache=True, _nrt=False)
def _closed_loop_row_set(rows, count, rows_fn, p, x0, xn, K, lo, hi, u, x, X, U, OUT):
    """The closed-loop rollouts of the rows ``rows[:count]`` (as
    :func:`_closed_loop_rows`'s, ``b = r % B``), all of them one time step after
    another: each step's states and controls (the feedback added,
    :func:`_feedback_row`) gathered into ``X``, ``U``, the model's ``rows_fn`` on them,
    ``OUT`` scattered into the next states."""
    B, T, n, m = xn.shape[0], u.shape[1], x.shape[2], u.shape[2]
    for i in range(count):
        r = rows[i]
        for j in range(n):
            x[r, 0, j] = x0[r, j]
    for t in range(T):
        for i in range(count):
            r = rows[i]
            xr = x[r, t]
            ur = u[r, t]
            _feedback_row(xr, xn, K, lo, hi, r % B, t, ur)
            for j in range(n):
                X[i, j] = xr[j]
            for j in range(m):
                U[i, j] = ur[j]
        rows_fn(0, count, X, U, p, OUT)
        for i in range(count):
            r = rows[i]
            for j in range(n):
                x[r, t + 1, j] = OUT[i, j]


@numba.njit(nogil=True, cache=True)
def step_rows_kernel(r0, r1, step, rhs, mode, p, x, u, out):
    """``out[r] = f(x[r], u[r])`` for rows ``r0 <= r < r1`` (``x (R, n)``, ``u (R, m)``,
    ``out (R, n)``; ``f`` as in :func:`closed_loop_rollout_kernel`): one call of a
    model's compiled step on a batch of rows, for a ``forward`` called from Python (e.g.
    inside a user's own model) without autograd."""
    work = np.empty((8, x.shape[1]), dtype=x.dtype)
    _step_rows(r0, r1, step, rhs, mode, p, x, u, out, work)


@numba.njit(nogil=True, cache=True, _nrt=False)
def _step_rows(r0, r1, step, rhs, mode, p, x, u, out, work):
    """The loop of :func:`step_rows_kernel` (no reference counting: module docstring)."""
    for r in range(r0, r1):
        _model_step(step, rhs, mode, x[r], u[r], p, out[r], work)


@numba.njit(cache=True, nogil=True, _nrt=False)
def piecewise_cubic_kernel(b0, b1, grid, n_steps, values, t, out):
    """:class:`torchslq.ode.dense.PiecewiseCubic` at the query times: ``out[b, q] =`` the
    cubic through ``values[b, i, 0..3]`` (at ``theta = 0, 1/3, 2/3, 1``) on the interval
    ``i`` of ``grid[b]`` holding ``t[b, q]`` (the end intervals outside the grid), for
    ``b0 <= b < b1``. grid ``(B, N+1)`` sorted per row, n_steps ``(B,)`` intervals in
    use, values ``(B, N, 4, D)``, t ``(B, Q)``, out ``(B, Q, D)``: the torch form's
    ``searchsorted``, gathers and Lagrange weights in one pass."""
    Q = t.shape[1]
    D = values.shape[3]
    L = grid.shape[1]
    for b in range(b0, b1):
        last = max(n_steps[b] - 1, 0)
        g = grid[b]
        for q in range(Q):
            tq = t[b, q]
            lo, hi = 0, L  # first index with g > tq (searchsorted, right=True)
            while lo < hi:
                mid = (lo + hi) // 2
                if g[mid] > tq:
                    hi = mid
                else:
                    lo = mid + 1
            i = min(max(lo - 1, 0), last)
            h = g[i + 1] - g[i]
            th = (tq - g[i]) / h if h > 0 else 0.0
            a = th - 1.0 / 3.0
            c2 = th - 2.0 / 3.0
            c = th - 1.0
            w0 = -4.5 * a * c2 * c
            w1 = 13.5 * th * c2 * c
            w2 = -13.5 * th * a * c
            w3 = 4.5 * th * a * c2
            v = values[b, i]
            for d in range(D):
                out[b, q, d] = w0 * v[0, d] + w1 * v[1, d] + w2 * v[2, d] + w3 * v[3, d]
