"""numba kernel for the derivatives of a discrete model's compiled step (a user's
:class:`torchslq.Dynamics` whose code :mod:`torchslq.dynamics.codegen` generated):
its Jacobians and the Hessian blocks of ``s · step(x, u)``, with the argument list of
:func:`torchslq.dynamics._numba_rk4.rk4_lanes_kernel` so that one launcher
(:mod:`torchslq.dynamics.compiled_rk4`) serves both, with the model's functions as
first-class function values (:mod:`torchslq._backend.model_fns`)."""

from __future__ import annotations

import numba
import numpy as np

from .._backend import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)


@numba.njit(nogil=True, cache=True)
def step_derivatives_kernel(
    r0, r1, rhs, derivs, p, dt, curved_outputs, curved_entries, x, u, S, Hz, A, B
):
    """``derivs(x, u, p, fz, H)`` per row: ``A (R, n, n)``, ``B (R, n, m)`` from ``fz``
    when not empty, and ``Hz[w, r] = sum_j S[w, r, j] H_j`` in ``[u; x]`` order for the
    ``W`` weight vectors ``S (W, R, n)`` (the model writes only its curved entries of
    ``H``, which starts zero). ``rhs`` and ``dt`` are unused (the step is the model).
    Rows ``r0 <= r < r1``."""
    n = x.shape[1]
    m = u.shape[1]
    nz = n + m
    W = S.shape[0]
    fz = np.empty((n, nz), dtype=x.dtype)
    H = np.zeros((n if W > 0 else 0, nz, nz), dtype=x.dtype)
    jac = A.shape[0] > 0
    for r in range(r0, r1):
        derivs(x[r], u[r], p, fz, H)
        if jac:
            for i in range(n):
                for c in range(n):
                    A[r, i, c] = fz[i, c]
                for c in range(m):
                    B[r, i, c] = fz[i, n + c]
        for w in range(W):
            for a in range(nz):
                ja = a - n if a >= n else m + a  # z = (x, u) -> [u; x]
                for b in range(nz):
                    jb = b - n if b >= n else m + b
                    s = 0.0
                    for j in range(n):
                        s += S[w, r, j] * H[j, a, b]
                    Hz[w, r, ja, jb] = s
