"""The fused scan kernels (:mod:`torchslq.lq.scan_kernels`, Triton) against the torch ops
they replace, the sequential kernel and a dense KKT solve.

A GPU runs them; here they run on CPU tensors through Triton's interpreter (the same
kernel source, executed lane by lane with numpy), which checks what they compute.
Whether they compile and how fast they run on a GPU is ``tests/test_device.py``'s and
``benchmarks/parallel_lq.py``'s.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import torch
from test_lq_kernel import assert_rel, random_problem, sym
from test_parallel_lq import FIELDS, _dense_check

from torchslq import Status, lqr_solve
from torchslq.lq import (
    homogeneous_cost,
    homogeneous_dynamics,
    lq_adjoint_scan,
    riccati_backward,
    scan_kernels,
)
from torchslq.lq import scan as scan_module

pytest.importorskip("triton")  # a dev dependency; without it the torch ops serve

F64 = torch.float64

pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.fixture
def fused():
    """The fused kernels on CPU tensors (interpreted). Masked-off lanes of the last
    block divide zeros by zeros, harmlessly: numpy's warnings are silenced."""
    with scan_kernels.interpreted(), np.errstate(all="ignore"):
        yield


def _value_elems(seed: int, bsz: int, T: int, n: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)

    def rn(*s):
        return torch.randn(*s, generator=g, dtype=F64)

    def psd(k):
        X = rn(bsz, T, k, k)
        return X @ X.mT

    return (
        rn(bsz, T, n, n),
        rn(bsz, T, n),
        psd(n),
        rn(bsz, T, n),
        psd(n),
        torch.rand(bsz, T, generator=g) < 0.3,
    )


def _torch_ops(fn, *args):
    with scan_kernels.disabled():
        return fn(*args)


# ----------------------------------------------------------------------------- operators


@pytest.mark.parametrize("n", [1, 2, 4])
def test_value_combination_matches_torch_ops(fused, n):
    """The operator (S2) on random elements (C, J positive semi-definite), strided
    slices as the scan passes them; the bad flags are or-ed."""
    e = _value_elems(n, 2, 11, n)
    e1 = tuple(t[:, 0:10:2] for t in e)
    e2 = tuple(t[:, 1::2] for t in e)
    ref = _torch_ops(scan_module._combine_value, e1, e2)
    got = scan_kernels.combine_value(e1, e2)
    for name, a, b in zip(("A", "b", "C", "eta", "J"), got[:5], ref[:5], strict=True):
        assert a.shape == b.shape, name
        assert_rel(a, b, 1e-12, name)
    assert torch.equal(got[5], ref[5])
    assert torch.equal(got[2], got[2].mT) and torch.equal(got[4], got[4].mT)


def test_value_combination_pivots_and_flags_singular():
    """``I + C1 J2`` with a zero leading entry (C1 = [[1, -1], [-1, 1]], J2 = [[1, 2],
    [2, 4]]: I + C1 J2 = [[0, -2], [1, 3]], non-singular): elimination without row
    exchanges would divide by zero. A singular one (C1 = ones, J2 = diag(-1, 0)) is
    flagged, as LAPACK's info flags it for the torch ops."""
    n = 2
    eye = torch.eye(n, dtype=F64)
    C1 = torch.tensor([[[1.0, -1.0], [-1.0, 1.0]], [[1.0, 1.0], [1.0, 1.0]]], dtype=F64)
    J2 = torch.tensor([[[1.0, 2.0], [2.0, 4.0]], [[-1.0, 0.0], [0.0, 0.0]]], dtype=F64)
    assert float(torch.linalg.det(eye + C1[0] @ J2[0])) == pytest.approx(2.0)
    assert float(torch.linalg.det(eye + C1[1] @ J2[1])) == 0.0
    g = torch.Generator().manual_seed(3)
    e1 = [
        torch.randn(2, 1, *s, generator=g, dtype=F64) for s in ((n, n), (n,), (n, n), (n,), (n, n))
    ]
    e2 = [
        torch.randn(2, 1, *s, generator=g, dtype=F64) for s in ((n, n), (n,), (n, n), (n,), (n, n))
    ]
    e1[2] = C1.unsqueeze(1)
    e2[4] = J2.unsqueeze(1)
    e1[4], e2[2] = sym(e1[4]), sym(e2[2])
    flags = torch.zeros(2, 1, dtype=torch.bool)
    e1, e2 = (*e1, flags), (*e2, flags)
    ref = _torch_ops(scan_module._combine_value, e1, e2)
    with scan_kernels.interpreted(), np.errstate(all="ignore"):
        got = scan_kernels.combine_value(e1, e2)
    assert got[5].tolist() == [[False], [True]] == ref[5].tolist()
    for a, b in zip(got[:5], ref[:5], strict=True):
        assert torch.isfinite(a[0]).all()
        assert_rel(a[0], b[0], 1e-12, "pivoted")


def test_affine_composition_matches_torch_ops(fused):
    g = torch.Generator().manual_seed(0)
    M = torch.randn(3, 7, 4, 4, generator=g, dtype=F64)
    a = torch.randn(3, 7, 4, generator=g, dtype=F64)
    e1, e2 = (M[:, 0:6:2], a[:, 0:6:2]), (M[:, 1::2], a[:, 1::2])
    got = scan_kernels.combine_affine(e1, e2)
    assert_rel(got[0], e2[0] @ e1[0], 1e-13, "M")
    assert_rel(got[1], (e2[0] @ e1[1].unsqueeze(-1))[..., 0] + e2[1], 1e-13, "a")


# ----------------------------------------------------------------------------- passes


def test_riccati_and_adjoint_passes_match_torch_ops(fused):
    """The elements (S1), the value scan, the gains (S4) with an element whose R is not
    positive definite and one whose Quu is indefinite, the closed loop and the adjoint
    scans: every factor equal to the torch ops' (which the sequential kernel checks)."""
    bsz, T, n, m = 4, 9, 4, 2
    args = random_problem(41, bsz, T, n, m)
    args["R"] = args["R"].clone()
    args["R"][1, 3] = -torch.eye(m, dtype=F64)  # an element of the scan is bad
    args["Q"] = args["Q"].clone()
    args["Q"][2, T] = -50.0 * torch.eye(n, dtype=F64)  # Quu indefinite at the end
    F = homogeneous_dynamics(args["A"], args["B"], args["c"])
    H, VhT = homogeneous_cost(args["Q"], args["R"], args["q"], args["r"], args["S"])
    got = scan_module.riccati_scan_homogeneous(F, H, VhT)
    ref = _torch_ops(scan_module.riccati_scan_homogeneous, F, H, VhT)
    assert got.failed.tolist() == ref.failed.tolist() == [False, True, True, False]
    for name in ("Kk", "Vh", "chol"):
        a, b = getattr(got, name), getattr(ref, name)
        assert torch.allclose(a, b, rtol=1e-11, atol=1e-11, equal_nan=True), name
    ok = [0, 3]
    fac = riccati_backward(*(args[k][ok] for k in ("A", "B", "Q", "R", "q", "r", "S", "c")))
    assert_rel(got.Kk[ok], fac.Kk, 1e-10, "Kk against the sequential kernel")
    g = torch.Generator().manual_seed(1)
    gx = torch.randn(2, T + 1, n, generator=g, dtype=F64)
    gu = torch.randn(2, T, m, generator=g, dtype=F64)
    adj = lq_adjoint_scan(F[ok], fac.Kk, fac.Vh, fac.chol, gx, gu)
    adj_ref = _torch_ops(lq_adjoint_scan, F[ok], fac.Kk, fac.Vh, fac.chol, gx, gu)
    for a, b, name in zip(adj, adj_ref, ("dx", "du", "dlam"), strict=True):
        assert_rel(a, b, 1e-11, name)


@pytest.mark.parametrize(("T", "n", "m"), [(1, 4, 2), (2, 1, 1), (6, 3, 1), (33, 4, 2)])
def test_lqr_solve_fused_matches_dense_kkt_and_sequential(fused, T, n, m):
    bsz = 3
    args = random_problem(200 + T, bsz, T, n, m)
    par = lqr_solve(**args, method="scan")
    seq = lqr_solve(**args, method="sequential")
    for name in FIELDS:
        assert_rel(getattr(par, name), getattr(seq, name), 1e-10, name)
    assert (par.status == Status.CONVERGED).all()
    _dense_check(args, par, bsz, T, n, m)


def test_lqr_solve_fused_statuses_and_gradients(fused):
    """A NaN in one x0 and an R that is not positive definite: the sequential kernel's
    statuses; the gradients of the others through the scan's backward (the fused
    closed loop and affine scans) equal the sequential path's."""
    bsz, T, n, m = 4, 12, 4, 2
    args = random_problem(44, bsz, T, n, m)
    args["R"] = args["R"].clone()
    args["R"][1, 5] = -torch.eye(m, dtype=F64)
    args["x0"] = args["x0"].clone()
    args["x0"][3, 0] = float("nan")
    grads, status = {}, {}
    for method in ("sequential", "scan"):
        ins = {k: v.detach().clone().requires_grad_(True) for k, v in args.items()}
        sol = lqr_solve(**ins, validate=False, method=method)
        status[method] = sol.status
        ok = sol.status == Status.CONVERGED
        loss = (sol.x[ok] ** 2).sum() + sol.u[ok].sum() + sol.cost[ok].sum()
        grads[method] = torch.autograd.grad(loss, list(ins.values()))
    assert torch.equal(status["scan"], status["sequential"])
    assert status["scan"].tolist()[1] == int(Status.NOT_POSITIVE_DEFINITE)
    assert status["scan"].tolist()[3] == int(Status.NON_FINITE)
    for name, a, b in zip(args, grads["scan"], grads["sequential"], strict=True):
        assert torch.isfinite(a).all(), name
        assert_rel(a, b, 1e-9, f"d/d{name}")


def test_lqr_solve_fused_float32(fused):
    args = random_problem(45, 3, 20, 4, 2)
    s64 = lqr_solve(**args)
    s32 = lqr_solve(**{k: v.float() for k, v in args.items()}, method="scan")
    for name in FIELDS:
        assert getattr(s32, name).dtype == torch.float32
        assert_rel(getattr(s32, name), getattr(s64, name), 1e-4, name)


# ----------------------------------------------------------------------------- rules


def test_where_the_fused_kernels_serve():
    cpu = torch.zeros(2, dtype=F64)
    assert not scan_kernels.enabled(cpu, 4, 2)  # CPU tensors: the torch ops
    with scan_kernels.interpreted():
        assert scan_kernels.enabled(cpu, 4, 2)
        assert scan_kernels.enabled(cpu.float(), 1, 1)
        assert not scan_kernels.enabled(cpu, scan_kernels.MAX_DIM + 1, 1)
        assert not scan_kernels.enabled(cpu, 2, scan_kernels.MAX_DIM + 1)
        assert not scan_kernels.enabled(cpu.half(), 2, 1)
        with scan_kernels.disabled():
            assert not scan_kernels.enabled(cpu, 4, 2)
        assert scan_kernels.enabled(cpu, 4, 2)


def test_sizes_above_the_limit_run_the_torch_ops(fused):
    n = scan_kernels.MAX_DIM + 1
    args = random_problem(46, 2, 7, n, 1)
    par = lqr_solve(**args, method="scan")
    seq = lqr_solve(**args)
    for name in FIELDS:
        assert_rel(getattr(par, name), getattr(seq, name), 1e-10, name)


def test_gpu_kernels_compile_once_per_dtype():
    """The scan's levels pass slices whose sizes, strides and pointer offsets vary;
    Triton would compile a kernel again for each value it specialises on (a 1, a
    multiple of 16, a 16-byte aligned pointer): every parameter but the block size is
    exempt. (Compiling needs no GPU; launching does.)"""
    fn = scan_kernels._kernel("combine_value", 4, 1, interpret=False)
    params = list(inspect.signature(fn.fn).parameters)
    assert params[-1] == "BLOCK"
    exempt = {fn.arg_names[i] if isinstance(i, int) else i for i in fn.do_not_specialize}
    assert exempt == set(params[:-1])


def test_a_kernel_that_fails_to_build_falls_back_to_torch_ops(fused, monkeypatch):
    """A Triton that cannot compile a kernel: the call warns, its results are the
    torch ops' (equal to the sequential kernel's), and the kernels stay off."""

    def broken(*args, **kwargs):
        raise RuntimeError("no toolchain")

    monkeypatch.setattr(scan_kernels, "_kernel", broken)
    args = random_problem(47, 2, 9, 3, 2)
    with pytest.warns(RuntimeWarning, match="fused scan kernel"):
        par = lqr_solve(**args, method="scan")
    seq = lqr_solve(**args)
    for name in FIELDS:
        assert_rel(getattr(par, name), getattr(seq, name), 1e-10, name)
    assert not scan_kernels.enabled(args["A"], 3, 2)


def test_skipping_the_coalescing_pass_leaves_the_code_unchanged(monkeypatch):
    """The first launch of a kernel compiles it without Triton's coalescing pass (its
    compile time); the PTX for an H100 is the same with and without the pass (compiled
    here, no GPU needed), and the pass is back afterwards."""
    import triton
    from triton._C.libtriton import passes
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    monkeypatch.setattr(triton.knobs.compilation, "always_compile", True)  # no cache hits
    fn = scan_kernels._kernel("combine_affine", 2, 1, interpret=False)
    names = list(inspect.signature(fn.fn).parameters)[:-1]
    sig = {a: "i64" if a in ("N", "Tp") else "i32" if "_s" in a else "*fp64" for a in names}
    sig["BLOCK"] = "constexpr"

    def ptx():
        src = ASTSource(fn, sig, constexprs={"BLOCK": 128})
        opts = scan_kernels._GPU_OPTIONS
        return triton.compile(src, target=GPUTarget("cuda", 90, 32), options=opts).asm["ptx"]

    original = passes.ttgpuir.add_coalesce
    with_pass = ptx()
    asked = []
    with scan_kernels._without_coalescing():
        skip = passes.ttgpuir.add_coalesce
        assert skip is not original
        passes.ttgpuir.add_coalesce = lambda pm: asked.append(skip(pm))
        try:
            without = ptx()
        finally:
            passes.ttgpuir.add_coalesce = skip
    assert asked  # the pipeline was built (compiled, not a cache hit), without the pass
    assert passes.ttgpuir.add_coalesce is original
    assert without == with_pass
