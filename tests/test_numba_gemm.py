"""The register-blocked product of the LQ kernels (``torchslq/_backend/_numba_gemm.py``)
against NumPy's matrix product: every block shape (4 x 8, 4 x 4, 4 x 1 rows and the
single-row remainders), transposed (strided) operands, the sign, and the ``upper`` mode
(entries on and above the diagonal exact; the rest left for the caller to mirror)."""

from __future__ import annotations

import numpy as np
import pytest

gemm = pytest.importorskip("torchslq._backend._numba_gemm")

SHAPES = [(1, 1, 1), (3, 5, 2), (4, 4, 4), (5, 6, 5), (12, 12, 12), (7, 9, 13), (32, 8, 33)]


@pytest.mark.parametrize("inner,rows,cols", SHAPES)
@pytest.mark.parametrize("sign", [1.0, -0.5])
def test_acc_tn_equals_numpy(inner, rows, cols, sign):
    rng = np.random.default_rng(inner * 100 + rows * 10 + cols)
    X = rng.standard_normal((inner, rows))
    Y = rng.standard_normal((inner, cols))
    C0 = rng.standard_normal((rows, cols))
    C = C0.copy()
    with gemm.slp_vectorized():
        gemm.acc_tn(C, X, Y, sign, False)
    np.testing.assert_allclose(C, C0 + sign * X.T @ Y, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("inner,n", [(5, 5), (12, 12), (6, 13), (32, 32)])
def test_acc_tn_upper_triangle(inner, n):
    rng = np.random.default_rng(inner + n)
    X = rng.standard_normal((inner, n))
    Y = rng.standard_normal((inner, n))
    C0 = rng.standard_normal((n, n))
    C = C0.copy()
    with gemm.slp_vectorized():
        gemm.acc_tn(C, X, Y, 1.0, True)
    want = C0 + X.T @ Y
    upper = np.triu_indices(n)
    np.testing.assert_allclose(C[upper], want[upper], rtol=1e-13, atol=1e-13)


def test_acc_tn_with_a_transposed_operand():
    # the kernels pass ``Vn.T`` (a strided view) for ``C += Vn Y``
    rng = np.random.default_rng(7)
    V = rng.standard_normal((6, 6))
    Y = rng.standard_normal((6, 7))
    C = np.zeros((6, 7))
    with gemm.slp_vectorized():
        gemm.acc_tn(C, V.T, Y, 1.0, False)
    np.testing.assert_allclose(C, V @ Y, rtol=1e-13, atol=1e-13)


def test_slp_switch_is_restored():
    import numba.core.config as config

    before = config.SLP_VECTORIZE
    with gemm.slp_vectorized():
        assert config.SLP_VECTORIZE == 1
    assert config.SLP_VECTORIZE == before
