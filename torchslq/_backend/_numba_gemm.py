"""Register-blocked products of the small matrices of the LQ kernels.

A product of ``n x n`` matrices with ``n`` between 4 and 32 is too small for BLAS (the
call costs more than the work) and, written as plain loops, bound by the latency of one
running sum or by a load and a store of ``C`` per multiply-add. :func:`acc_tn` keeps a
``4 x 8`` block of ``C`` in registers (32 independent sums) while it runs down the inner
dimension, so that LLVM's SLP vectoriser turns each row of the block into one or two
vector FMAs. numba leaves SLP vectorisation off by default (numba#8705: miscompilations
in older LLVMs); :func:`slp_vectorized` turns it on while the kernels that call these
helpers are compiled (their results are checked against dense KKT solves and
finite differences in the tests). Measured on one core of the CI machine (Xeon, AVX-512),
``C += X'Y``: 24 / 47 GFLOP/s at 12 x 12 / 32 x 32 against 9 / 13 for the row (axpy)
order the kernels used before.

The loop bodies are written out (generated once, by hand-checked templates): 4 x 8,
4 x 4 and 4 x 1 blocks, then 1 x 8, 1 x 4 and 1 x 1 for the last rows.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numba
import numba.core.config

from . import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)


def with_slp(fn, *args):
    """``fn(*args)`` with LLVM's SLP vectoriser switched on, as :func:`slp_vectorized`:
    the launchers call every kernel that uses these products through it, at every call
    (a generator-based context manager costs microseconds per solver iteration, and
    switching it on only for a kernel's first call missed specialisations compiled
    later)."""
    config = numba.core.config
    old = config.SLP_VECTORIZE
    config.SLP_VECTORIZE = 1
    try:
        return fn(*args)
    finally:
        config.SLP_VECTORIZE = old


@contextlib.contextmanager
def slp_vectorized() -> Iterator[None]:
    """Compile with LLVM's SLP vectoriser inside this block (numba's global switch; the
    kernels are compiled on their first call, so their launchers call them inside it)."""
    old = numba.core.config.SLP_VECTORIZE
    numba.core.config.SLP_VECTORIZE = 1
    try:
        yield
    finally:
        numba.core.config.SLP_VECTORIZE = old


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def acc_tn(C, X, Y, sign, upper):  # noqa: C901, PLR0912, PLR0915
    """``C += sign X'Y`` for ``X (k, r)``, ``Y (k, c)``, ``C (r, c)`` (pass ``X.T`` for
    ``C += sign X Y``); where ``upper``, only the entries ``j >= i`` are needed (some
    below the diagonal are updated too: the callers mirror the upper triangle)."""
    inner, rows, cols = X.shape[0], X.shape[1], Y.shape[1]
    i = 0
    while i + 4 <= rows:
        j = i - i % 8 if upper else 0
        while j + 8 <= cols:
            a00 = a01 = a02 = a03 = a04 = a05 = a06 = a07 = 0.0
            a10 = a11 = a12 = a13 = a14 = a15 = a16 = a17 = 0.0
            a20 = a21 = a22 = a23 = a24 = a25 = a26 = a27 = 0.0
            a30 = a31 = a32 = a33 = a34 = a35 = a36 = a37 = 0.0
            for k in range(inner):
                Yv = Y[k, j : j + 8]
                y0, y1, y2, y3, y4, y5, y6, y7 = (
                    Yv[0],
                    Yv[1],
                    Yv[2],
                    Yv[3],
                    Yv[4],
                    Yv[5],
                    Yv[6],
                    Yv[7],
                )
                Xv = X[k, i : i + 4]
                x0, x1, x2, x3 = Xv[0], Xv[1], Xv[2], Xv[3]
                a00 += x0 * y0
                a01 += x0 * y1
                a02 += x0 * y2
                a03 += x0 * y3
                a04 += x0 * y4
                a05 += x0 * y5
                a06 += x0 * y6
                a07 += x0 * y7
                a10 += x1 * y0
                a11 += x1 * y1
                a12 += x1 * y2
                a13 += x1 * y3
                a14 += x1 * y4
                a15 += x1 * y5
                a16 += x1 * y6
                a17 += x1 * y7
                a20 += x2 * y0
                a21 += x2 * y1
                a22 += x2 * y2
                a23 += x2 * y3
                a24 += x2 * y4
                a25 += x2 * y5
                a26 += x2 * y6
                a27 += x2 * y7
                a30 += x3 * y0
                a31 += x3 * y1
                a32 += x3 * y2
                a33 += x3 * y3
                a34 += x3 * y4
                a35 += x3 * y5
                a36 += x3 * y6
                a37 += x3 * y7
            Cv = C[i + 0, j : j + 8]
            Cv[0] += sign * a00
            Cv[1] += sign * a01
            Cv[2] += sign * a02
            Cv[3] += sign * a03
            Cv[4] += sign * a04
            Cv[5] += sign * a05
            Cv[6] += sign * a06
            Cv[7] += sign * a07
            Cv = C[i + 1, j : j + 8]
            Cv[0] += sign * a10
            Cv[1] += sign * a11
            Cv[2] += sign * a12
            Cv[3] += sign * a13
            Cv[4] += sign * a14
            Cv[5] += sign * a15
            Cv[6] += sign * a16
            Cv[7] += sign * a17
            Cv = C[i + 2, j : j + 8]
            Cv[0] += sign * a20
            Cv[1] += sign * a21
            Cv[2] += sign * a22
            Cv[3] += sign * a23
            Cv[4] += sign * a24
            Cv[5] += sign * a25
            Cv[6] += sign * a26
            Cv[7] += sign * a27
            Cv = C[i + 3, j : j + 8]
            Cv[0] += sign * a30
            Cv[1] += sign * a31
            Cv[2] += sign * a32
            Cv[3] += sign * a33
            Cv[4] += sign * a34
            Cv[5] += sign * a35
            Cv[6] += sign * a36
            Cv[7] += sign * a37
            j += 8
        while j + 4 <= cols:
            a00 = a01 = a02 = a03 = 0.0
            a10 = a11 = a12 = a13 = 0.0
            a20 = a21 = a22 = a23 = 0.0
            a30 = a31 = a32 = a33 = 0.0
            for k in range(inner):
                Yv = Y[k, j : j + 4]
                y0, y1, y2, y3 = Yv[0], Yv[1], Yv[2], Yv[3]
                Xv = X[k, i : i + 4]
                x0, x1, x2, x3 = Xv[0], Xv[1], Xv[2], Xv[3]
                a00 += x0 * y0
                a01 += x0 * y1
                a02 += x0 * y2
                a03 += x0 * y3
                a10 += x1 * y0
                a11 += x1 * y1
                a12 += x1 * y2
                a13 += x1 * y3
                a20 += x2 * y0
                a21 += x2 * y1
                a22 += x2 * y2
                a23 += x2 * y3
                a30 += x3 * y0
                a31 += x3 * y1
                a32 += x3 * y2
                a33 += x3 * y3
            Cv = C[i + 0, j : j + 4]
            Cv[0] += sign * a00
            Cv[1] += sign * a01
            Cv[2] += sign * a02
            Cv[3] += sign * a03
            Cv = C[i + 1, j : j + 4]
            Cv[0] += sign * a10
            Cv[1] += sign * a11
            Cv[2] += sign * a12
            Cv[3] += sign * a13
            Cv = C[i + 2, j : j + 4]
            Cv[0] += sign * a20
            Cv[1] += sign * a21
            Cv[2] += sign * a22
            Cv[3] += sign * a23
            Cv = C[i + 3, j : j + 4]
            Cv[0] += sign * a30
            Cv[1] += sign * a31
            Cv[2] += sign * a32
            Cv[3] += sign * a33
            j += 4
        while j + 1 <= cols:
            a00 = 0.0
            a10 = 0.0
            a20 = 0.0
            a30 = 0.0
            for k in range(inner):
                y0 = Y[k, j]
                Xv = X[k, i : i + 4]
                x0, x1, x2, x3 = Xv[0], Xv[1], Xv[2], Xv[3]
                a00 += x0 * y0
                a10 += x1 * y0
                a20 += x2 * y0
                a30 += x3 * y0
            C[i + 0, j] += sign * a00
            C[i + 1, j] += sign * a10
            C[i + 2, j] += sign * a20
            C[i + 3, j] += sign * a30
            j += 1
        i += 4
    while i + 1 <= rows:
        j = i if upper else 0
        while j + 8 <= cols:
            a00 = a01 = a02 = a03 = a04 = a05 = a06 = a07 = 0.0
            for k in range(inner):
                Yv = Y[k, j : j + 8]
                y0, y1, y2, y3, y4, y5, y6, y7 = (
                    Yv[0],
                    Yv[1],
                    Yv[2],
                    Yv[3],
                    Yv[4],
                    Yv[5],
                    Yv[6],
                    Yv[7],
                )
                x0 = X[k, i]
                a00 += x0 * y0
                a01 += x0 * y1
                a02 += x0 * y2
                a03 += x0 * y3
                a04 += x0 * y4
                a05 += x0 * y5
                a06 += x0 * y6
                a07 += x0 * y7
            Cv = C[i + 0, j : j + 8]
            Cv[0] += sign * a00
            Cv[1] += sign * a01
            Cv[2] += sign * a02
            Cv[3] += sign * a03
            Cv[4] += sign * a04
            Cv[5] += sign * a05
            Cv[6] += sign * a06
            Cv[7] += sign * a07
            j += 8
        while j + 4 <= cols:
            a00 = a01 = a02 = a03 = 0.0
            for k in range(inner):
                Yv = Y[k, j : j + 4]
                y0, y1, y2, y3 = Yv[0], Yv[1], Yv[2], Yv[3]
                x0 = X[k, i]
                a00 += x0 * y0
                a01 += x0 * y1
                a02 += x0 * y2
                a03 += x0 * y3
            Cv = C[i + 0, j : j + 4]
            Cv[0] += sign * a00
            Cv[1] += sign * a01
            Cv[2] += sign * a02
            Cv[3] += sign * a03
            j += 4
        while j + 1 <= cols:
            a00 = 0.0
            for k in range(inner):
                y0 = Y[k, j]
                x0 = X[k, i]
                a00 += x0 * y0
            C[i + 0, j] += sign * a00
            j += 1
        i += 1
