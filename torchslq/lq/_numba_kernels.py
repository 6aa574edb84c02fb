"""numba kernels of :mod:`torchslq.lq.compiled` (imported on first use: importing
numba and loading the cached machine code takes ~0.5 s, which a GPU-only user should
never pay)."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def riccati_kernel(b0, b1, F, H, VhT, reg, Hz, short_form, Kk, Vh, L, failed):
    """One Riccati pass per element (see riccati_homogeneous for the equations).

    F ``(BF, T, n+1, m+n+1)``, H ``(BH, T, m+n+1, m+n+1)``, VhT ``(BV, n+1, n+1)``
    (each batch 1 or B), reg ``(BR,)`` (1 or B), Hz ``(T, n, B, m+n, m+n)`` or an
    empty array; ``short_form``: the value update ``M_zz + M_uz'Kk`` (no reg, as
    the torch path) instead of the general form; outputs Kk ``(B, T, m, n+1)``, Vh ``(B, T+1, n+1, n+1)``,
    L ``(B, T, m, m)``, failed ``(B,)``. An element whose ``Quu + reg I`` is not
    positive definite (or not finite) at some step is marked failed and its earlier
    steps are left at zero (the torch path's values there are meaningless too).
    Only elements ``b0 <= b < b1`` are computed (see ``compiled._launch``).
    """
    T = Kk.shape[1]
    m = Kk.shape[2]
    n1 = Kk.shape[3]
    n = n1 - 1
    mn1 = m + n1
    use_hz = Hz.shape[0] > 0
    VF = np.empty((n1, mn1), dtype=Vh.dtype)
    M = np.empty((mn1, mn1), dtype=Vh.dtype)
    Lb = np.zeros((m, m), dtype=Vh.dtype)
    for b in range(b0, b1):
        bf = b if F.shape[0] > 1 else 0
        bh = b if H.shape[0] > 1 else 0
        bv = b if VhT.shape[0] > 1 else 0
        r = reg[b if reg.shape[0] > 1 else 0]
        for i in range(n1):
            for j in range(n1):
                Vh[b, T, i, j] = VhT[bv, i, j]
        ok = True
        for t in range(T - 1, -1, -1):
            # 2-d views of this step's matrices (cheaper indexing than 4-d)
            Vn = Vh[b, t + 1]
            Vc = Vh[b, t]
            Ft = F[bf, t]
            Ht = H[bh, t]
            Kt = Kk[b, t]
            # M = H_t + F_t' Vh_{t+1} F_t (symmetric: upper triangle, mirrored)
            for i in range(n1):
                for j in range(mn1):
                    s = 0.0
                    for k in range(n1):
                        s += Vn[i, k] * Ft[k, j]
                    VF[i, j] = s
            for i in range(mn1):
                for j in range(i, mn1):
                    s = Ht[i, j]
                    for k in range(n1):
                        s += Ft[k, i] * VF[k, j]
                    M[i, j] = s
                    M[j, i] = s
            if use_hz:  # DDP: + v_{t+1} . f_zz on the [u; x] block
                for k in range(n):
                    v = Vn[k, n]
                    Hk = Hz[t, k, b]
                    for i in range(mn1 - 1):
                        for j in range(mn1 - 1):
                            M[i, j] += v * Hk[i, j]
            # Cholesky of Quu + reg I
            for j in range(m):
                s = M[j, j] + r
                for k in range(j):
                    s -= Lb[j, k] * Lb[j, k]
                if not (s > 0.0):  # also catches NaN
                    ok = False
                    break
                d = math.sqrt(s)
                Lb[j, j] = d
                for i in range(j + 1, m):
                    s2 = M[i, j]
                    for k in range(j):
                        s2 -= Lb[i, k] * Lb[j, k]
                    Lb[i, j] = s2 / d
            if not ok:
                break
            Lt = L[b, t]
            for i in range(m):
                for j in range(i + 1):
                    Lt[i, j] = Lb[i, j]
            # [K_t, k_t] = -(L L')^{-1} M[:m, m:]
            for c in range(n1):
                for i in range(m):
                    s = -M[i, m + c]
                    for k in range(i):
                        s -= Lb[i, k] * Kt[k, c]
                    Kt[i, c] = s / Lb[i, i]
                for i in range(m - 1, -1, -1):
                    s = Kt[i, c]
                    for k in range(i + 1, m):
                        s -= Lb[k, i] * Kt[k, c]
                    Kt[i, c] = s / Lb[i, i]
            if short_form:  # Vh_t = M_zz + M_uz'Kk, symmetrised
                for i in range(n1):
                    for j in range(i, n1):
                        s = M[m + i, m + j]
                        s2 = M[m + j, m + i]
                        for p in range(m):
                            s += M[p, m + i] * Kt[p, j]
                            s2 += M[p, m + j] * Kt[p, i]
                        Vc[i, j] = 0.5 * (s + s2)
                        Vc[j, i] = 0.5 * (s + s2)
                continue
            # Vh_t = M_zz + Kk'Quu Kk + Kk'M_uz + M_uz'Kk (Tassa et al. 2012's form,
            # exact for any gains, hence also with reg)
            for i in range(n1):
                for j in range(i, n1):
                    s = M[m + i, m + j]
                    for p in range(m):
                        kpi = Kt[p, i]
                        s += kpi * M[p, m + j] + Kt[p, j] * M[p, m + i]
                        acc = 0.0
                        for q in range(m):
                            acc += M[p, q] * Kt[q, j]
                        s += kpi * acc
                    Vc[i, j] = s
                    Vc[j, i] = s
        failed[b] = not ok


@numba.njit(cache=True, nogil=True)
def rollout_kernel(b0, b1, F, Kk, x0, x, u):
    """``u_t = Kk_t [x_t; 1]``, ``x_{t+1} = F_t[:n] [u_t; x_t; 1]`` per element.

    F ``(BF, T, n+1, m+n+1)``, Kk ``(BK, T, m, n+1)``, x0 ``(BX, n)`` (batches 1 or
    B); outputs x ``(B, T+1, n)``, u ``(B, T, m)``.
    """
    T, m = u.shape[1], u.shape[2]
    n = x.shape[2]
    for b in range(b0, b1):
        bf = b if F.shape[0] > 1 else 0
        bk = b if Kk.shape[0] > 1 else 0
        bx = b if x0.shape[0] > 1 else 0
        for i in range(n):
            x[b, 0, i] = x0[bx, i]
        for t in range(T):
            Ft = F[bf, t]
            Kt = Kk[bk, t]
            xt = x[b, t]
            ut = u[b, t]
            for i in range(m):
                s = Kt[i, n]
                for j in range(n):
                    s += Kt[i, j] * xt[j]
                ut[i] = s
            xn = x[b, t + 1]
            for i in range(n):
                s = Ft[i, m + n]
                for j in range(m):
                    s += Ft[i, j] * ut[j]
                for j in range(n):
                    s += Ft[i, m + j] * xt[j]
                xn[i] = s


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
                s = -qu[i]
                for j in range(i):
                    s -= Lt[i, j] * kt[j]
                kt[i] = s / Lt[i, i]
            for i in range(m - 1, -1, -1):
                s = kt[i]
                for j in range(i + 1, m):
                    s -= Lt[j, i] * kt[j]
                kt[i] = s / Lt[i, i]
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
        for t in range(T):
            Ft = F[bf, t]
            Kt = Kk[bk, t]
            xt = dx[b, t]
            ut = du[b, t]
            for i in range(m):
                s = ut[i]
                for j in range(n):
                    s += Kt[i, j] * xt[j]
                ut[i] = s
            xn = dx[b, t + 1]
            for i in range(n):
                s = 0.0
                for j in range(m):
                    s += Ft[i, j] * ut[j]
                for j in range(n):
                    s += Ft[i, m + j] * xt[j]
                xn[i] = s
        # dlam_t = V_t dx_t + v_t
        for t in range(T + 1):
            Vt = Vh[bv, t]
            for i in range(n):
                s = v[t, i]
                for j in range(n):
                    s += Vt[i, j] * dx[b, t, j]
                v[t, i] = s
