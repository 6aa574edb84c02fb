"""numba kernel for :class:`torchslq.QuadraticCost`'s value, imported on first use."""

from __future__ import annotations

import numba

from . import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)


@numba.njit(cache=True, nogil=True, _nrt=False)
def quadratic_cost_kernel(r0, r1, B, x, u, xr, ur, Q, QT, R, stage_states, J):
    """``J[r] = 1/2 (sum_t |x_t - xr_t|^2_Q_t + |x_T - xr_T|^2_QT + sum_t |u_t - ur_t|^2_R_t)``
    per row. x ``(Rows, T+1, n)``, u ``(Rows, T, m)``; row ``r`` is batch element
    ``b = r % B``; the weights and references have a batch dim of 1 or ``B`` and a time
    dim of 1 or the horizon: xr ``(., 1|T+1, n)``, ur ``(., 1|T, m)``, Q ``(., 1|T, n,
    n)``, QT ``(., n, n)``, R ``(., 1|T, m, m)``; ``stage_states`` False when ``Q`` is
    zero (only the terminal state is weighted). Rows ``r0 <= r < r1``."""
    for r in range(r0, r1):
        J[r] = quadratic_cost_row(x[r], u[r], r % B, xr, ur, Q, QT, R, stage_states)


@numba.njit(cache=True, nogil=True, _nrt=False)
def quadratic_cost_row(x, u, b, xr, ur, Q, QT, R, stage_states):
    """The cost of one trajectory ``x (T+1, n)``, ``u (T, m)`` of batch element ``b``
    (the weights and references as in :func:`quadratic_cost_kernel`); also the cost of
    the fused line search's trials (:mod:`._numba_search`)."""
    T = u.shape[0]
    xr_t = xr.shape[1] > 1
    ur_t = ur.shape[1] > 1
    Q_t = Q.shape[1] > 1
    R_t = R.shape[1] > 1
    bxr = b if xr.shape[0] > 1 else 0
    bur = b if ur.shape[0] > 1 else 0
    bq = b if Q.shape[0] > 1 else 0
    bqt = b if QT.shape[0] > 1 else 0
    br = b if R.shape[0] > 1 else 0
    s = 0.0
    for t in range(0 if stage_states else T, T + 1):
        W = Q[bq, t if Q_t else 0] if t < T else QT[bqt]
        s = _add_form(s, x[t], xr[bxr, t if xr_t else 0], W)
    for t in range(T):
        s = _add_form(s, u[t], ur[bur, t if ur_t else 0], R[br, t if R_t else 0])
    return 0.5 * s


@numba.njit(cache=True, nogil=True, _nrt=False, inline="always")
def _add_form(s, z, ref, W):
    """``s + (z - ref)' W (z - ref)``, the terms added to ``s`` one row of ``W`` at a
    time (the same sums in the same order for the states' and the controls' forms)."""
    k = z.shape[0]
    for i in range(k):
        di = z[i] - ref[i]
        v = 0.0
        for j in range(k):
            v += W[i, j] * (z[j] - ref[j])
        s += di * v
    return s
