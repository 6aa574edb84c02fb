"""The gain-form element pass generated per size (torchslq._backend.gain_codegen)
against the element kernels of torchslq._backend._numba_gain, a dense KKT solve and the
solvers' restarts."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_lq_kernel import dense_kkt, random_problem

from torchslq._backend import _numba_gain, gain_codegen
from torchslq._backend._numba_gemm import with_slp
from torchslq._backend._numba_kernels import size_witness
from torchslq.lq import riccati_backward
from torchslq.lq.regularization import RegularizationSchedule
from torchslq.lq.solve import lqr_solve

pytestmark = pytest.mark.all_sizes  # the generated passes of several sizes

F64 = torch.float64


def _pieces(rng, nb, T, n, m, *, c, S, q, r, shared_time):
    """Random LQ data as the kernels take it: ``A`` a time dim of 1 where
    ``shared_time``, ``Q`` and ``R`` shared by the batch, optional terms empty."""
    e = lambda *s: np.zeros(s)  # noqa: E731
    A = np.eye(n) + 0.3 * rng.standard_normal((nb, 1 if shared_time else T, n, n))
    B = rng.standard_normal((nb, T, n, m))
    Q = rng.standard_normal((1, T + 1, n, n))
    Q = Q @ Q.transpose(0, 1, 3, 2) + 0.1 * np.eye(n) + 0.05 * rng.standard_normal((1, T + 1, n, n))
    R = rng.standard_normal((1, 1, m, m))
    R = R @ R.transpose(0, 1, 3, 2) + np.eye(m)
    return (
        A, B,
        rng.standard_normal((nb, T, n)) if c else e(0, 1, 1),
        Q, R,
        0.2 * rng.standard_normal((nb, T, m, n)) if S else e(0, 1, 1, 1),
        rng.standard_normal((nb, T + 1, n)) if q else e(0, 1, 1),
        rng.standard_normal((nb, T, m)) if r else e(0, 1, 1),
    )  # fmt: skip


def _run(kernels, pieces, nb, T, n, m, slp=False):
    out = (
        np.zeros((nb, T, m, n + 1)), np.zeros((nb, T + 1, n, n)), np.zeros((nb, T + 1, n)),
        np.zeros((nb, T, m, m)), np.zeros(nb), np.zeros(nb, np.bool_),
    )  # fmt: skip
    call = (with_slp, kernels.riccati_gain_kernel) if slp else (kernels.riccati_gain_kernel,)
    call[0](*call[1:], 0, nb, pieces, *out, *size_witness(n, m))
    return out


@pytest.mark.parametrize("n, m", [(1, 1), (2, 1), (4, 1), (3, 2)])
@pytest.mark.parametrize("terms", ["all", "none", "shared_time"])
def test_generated_pass_equals_the_element_pass(n, m, terms):
    """Gains, value functions, Cholesky factors and constants of the generated pass equal
    the element kernel's (its sums in the same order: rounding-level differences only)
    with and without the affine and cross terms, and with a time dim of 1."""
    rng = np.random.default_rng(n * 10 + m)
    nb, T = 5, 9
    full = terms == "all"
    pieces = _pieces(rng, nb, T, n, m, c=full, S=full, q=full, r=full,
                     shared_time=terms == "shared_time")  # fmt: skip
    generated = gain_codegen.gain_kernels(n, m)
    assert generated is not None
    want = _run(_numba_gain, pieces, nb, T, n, m, slp=True)
    got = _run(generated, pieces, nb, T, n, m)
    for name, a, b in zip(("Kk", "P", "p", "L", "s"), got, want, strict=False):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max(), err_msg=name)
    assert not got[5].any() and not want[5].any()


def test_generated_pass_reports_the_failing_elements():
    """An element whose ``Quu`` is not positive definite (an indefinite ``R``) or has a
    NaN fails in the generated pass as in the element pass; the others do not."""
    n, m, nb, T = 3, 2, 6, 8
    rng = np.random.default_rng(0)
    A, B, c, Q, R, S, q, r = _pieces(rng, nb, T, n, m, c=True, S=False, q=True, r=True,
                                     shared_time=False)  # fmt: skip
    R = np.repeat(R, nb, axis=0).repeat(T, axis=1)
    R[1, 3] = np.diag([1.0, -50.0])
    R[4, 0, 0, 0] = np.nan
    pieces = (A, B, c, Q, R, S, q, r)
    got = _run(gain_codegen.gain_kernels(n, m), pieces, nb, T, n, m)
    want = _run(_numba_gain, pieces, nb, T, n, m, slp=True)
    np.testing.assert_array_equal(got[5], [False, True, False, False, True, False])
    np.testing.assert_array_equal(got[5], want[5])
    ok = ~want[5]
    np.testing.assert_allclose(got[0][ok], want[0][ok], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n, m", [(4, 1), (3, 2)])
def test_lqr_solve_on_the_generated_pass_matches_dense_kkt(n, m):
    """``lqr_solve`` (whose CPU path takes the generated pass at these sizes) against
    the dense KKT solution of every element, batched and time-varying, all terms."""
    assert gain_codegen.gain_kernels(n, m) is not None
    args = random_problem(seed=5, bsz=3, T=6, n=n, m=m)
    sol = lqr_solve(**args)
    for b in range(3):
        x, u, lam, cost = dense_kkt(**{k: v[b] for k, v in args.items()})
        torch.testing.assert_close(sol.x[b], x, rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(sol.u[b], u, rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(sol.cost[b], cost, rtol=1e-9, atol=1e-10)


def _restart_pass():
    """A regularised pass with restarts where two elements' ``Quu`` fail at first (an
    indefinite ``R`` that a large enough ``mu`` repairs) and one cannot be repaired (a
    NaN)."""
    g = torch.Generator().manual_seed(1)
    nb, T, n, m = 9, 12, 4, 1
    A = torch.eye(n, dtype=F64) + 0.1 * torch.randn(nb, T, n, n, generator=g, dtype=F64)
    B = torch.randn(nb, T, n, m, generator=g, dtype=F64)
    Q = torch.eye(n, dtype=F64).expand(nb, T + 1, n, n).clone()
    R = torch.ones(nb, T, m, m, dtype=F64)
    R[2, 5] = -40.0
    R[7, 0] = -3.0
    R[5, 2] = float("nan")
    q = torch.randn(nb, T + 1, n, generator=g, dtype=F64)
    r = torch.randn(nb, T, m, generator=g, dtype=F64)
    mu = torch.full((nb,), 1e-6, dtype=F64)
    restarts = RegularizationSchedule().restarts(
        torch.ones(nb, dtype=F64), torch.ones(nb, dtype=torch.bool)
    )
    return riccati_backward(A, B, Q, R, q, r, reg=mu, restarts=restarts)


def test_solvers_pass_with_restarts_equals_the_element_kernels():
    """The solvers' regularised pass with Tassa et al.'s restarts: the generated first
    pass, the failing elements run again on the element kernel, gives the element
    kernel's failures, final ``mu`` and ``delta`` (bitwise: the same code from the
    same zeros) and gains."""
    fac = _restart_pass()
    old = gain_codegen.set_generated(False)
    try:
        ref = _restart_pass()
    finally:
        gain_codegen.set_generated(old)
    assert fac.failed.tolist() == ref.failed.tolist()
    assert fac.failed.tolist() == [False] * 5 + [True] + [False] * 3
    assert torch.equal(fac.reg, ref.reg) and torch.equal(fac.reg_delta, ref.reg_delta)
    assert bool((fac.reg[[2, 7]] > 1e-6).all())  # those two restarted
    for b in (2, 5, 7):  # run on the element kernel: the same bits
        assert torch.equal(fac.K[b], ref.K[b]) and torch.equal(fac.k[b], ref.k[b])
    torch.testing.assert_close(fac.K, ref.K, rtol=1e-12, atol=1e-12, equal_nan=True)
    torch.testing.assert_close(fac.Vh, ref.Vh, rtol=1e-12, atol=1e-12, equal_nan=True)


def test_sizes_and_switch():
    """Sizes above MAX_ENTRIES are not generated; switched off, none is."""
    assert gain_codegen.gain_kernels(7, 1) is None  # 7 (7 + 1) > 48
    assert gain_codegen.gain_kernels(6, 2) is not None
    old = gain_codegen.set_generated(False)
    try:
        assert gain_codegen.gain_kernels(4, 1) is None
    finally:
        gain_codegen.set_generated(old)


def test_no_writable_directory_falls_back_to_the_element_kernels(monkeypatch, tmp_path):
    """Where no directory can take the module, there is none and ``lqr_solve`` runs the
    element kernels (same solution)."""
    blocked = tmp_path / "file"
    blocked.write_text("")
    monkeypatch.setattr(gain_codegen, "_MODULES", {})
    monkeypatch.setattr(gain_codegen, "_directories", lambda: [blocked / "a", blocked / "b"])
    assert gain_codegen.gain_kernels(2, 1) is None
    args = random_problem(seed=2, bsz=2, T=5, n=2, m=1)
    x, u, lam, cost = dense_kkt(**{k: v[0] for k, v in args.items()})
    torch.testing.assert_close(lqr_solve(**args).x[0], x, rtol=1e-9, atol=1e-10)
