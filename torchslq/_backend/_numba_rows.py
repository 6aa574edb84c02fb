"""The numba kernels of :mod:`.dense_rows` (a module of their own, so that importing
torchslq does not import numba)."""

from __future__ import annotations

import numba

from ..dynamics._numba_net import tanh as _tanh
from . import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)
from ._numba_gemm import acc_tn


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def matmul_rows(r0, r1, C, A, B, bias):
    """``C[r0:r1] = bias + A[r0:r1] @ B`` (``bias (c,)``: zeros for none; ``C`` is
    written, not read, so it need not be zeroed first)."""
    for i in range(r0, r1):
        for j in range(C.shape[1]):
            C[i, j] = bias[j]
    acc_tn(C[r0:r1], A[r0:r1].T, B, 1.0, False)


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", _nrt=False)
def tanh_rows(r0, r1, a, out):
    """``out[r0:r1] = tanh(a[r0:r1])`` (1-d; the loop compiles to SIMD code)."""
    for i in range(r0, r1):
        out[i] = _tanh(a[i])
