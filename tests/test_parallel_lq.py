"""The parallel-in-time LQ backend (``lqr_solve(method="scan")``, :mod:`torchslq.lq.scan`)
against independent computations:

* a dense KKT solve of the same QP (``tests/test_lq_kernel.py``'s, element by element);
* the sequential Riccati kernel (every returned field, the statuses, the gradients);
* plain Python loops for the generic associative scan;
* float64 single solves (batching, failures isolated), float64 for float32 runs.
"""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from test_lq_kernel import (
    assert_rel,
    dense_kkt,
    full,
    lq_problems,
    random_problem,
    sym,
)

from torchslq import Status, lqr_solve
from torchslq.lq import (
    associative_scan,
    choose_method,
    lq_adjoint_scan,
    lq_adjoint_solve,
    riccati_backward,
    riccati_scan,
    rollout_linear,
    rollout_scan,
    scan_memory_bytes,
)

F64 = torch.float64
FIELDS = ("x", "u", "K", "k", "V", "v", "lam", "cost")

pytestmark = pytest.mark.usefixtures("single_thread")


def _dense_check(args, sol, bsz, T, n, m, tol=1e-9):
    zeros = torch.zeros((), dtype=F64)
    A = full(args["A"], 2, bsz, T)
    B = full(args["B"], 2, bsz, T)
    Q = full(args["Q"], 2, bsz, T + 1)
    R = full(args["R"], 2, bsz, T)
    S = full(args["S"] if args.get("S") is not None else zeros.expand(m, n), 2, bsz, T)
    q = full(args["q"] if args.get("q") is not None else zeros.expand(n), 1, bsz, T + 1)
    r = full(args["r"] if args.get("r") is not None else zeros.expand(m), 1, bsz, T)
    c = full(args["c"] if args.get("c") is not None else zeros.expand(n), 1, bsz, T)
    x0 = args["x0"].expand(bsz, n)
    for b in range(bsz):
        x, u, lam, cost = dense_kkt(A[b], B[b], Q[b], R[b], x0[b], q[b], r[b], S[b], c[b])
        assert_rel(sol.x[b], x, tol, "x")
        assert_rel(sol.u[b], u, tol, "u")
        assert_rel(sol.lam[b], lam, tol, "lam")
        assert abs(float(sol.cost[b]) - float(cost)) < tol * max(1.0, abs(float(cost)))


def _same_as_sequential(args, tol=1e-9, **kw):
    seq = lqr_solve(**args, **kw)
    par = lqr_solve(**args, method="scan", **kw)
    for name in FIELDS:
        assert_rel(getattr(par, name), getattr(seq, name), tol, name)
    assert torch.equal(par.status, seq.status)
    return seq, par


# ----------------------------------------------------------------------------- dense KKT


@settings(max_examples=25, deadline=None)
@given(lq_problems())
def test_scan_matches_dense_kkt_all_layouts(problem):
    """Every argument layout of lqr_solve (shared, constant in time, batched, with and
    without cross, linear and affine terms), T = 1 ... 6 (odd and even)."""
    args, (bsz, T, n, m), _lay = problem
    sol = lqr_solve(**args, method="scan")
    assert sol.x.shape == (bsz, T + 1, n) and sol.u.shape == (bsz, T, m)
    assert (sol.status == Status.CONVERGED).all()
    _dense_check(args, sol, bsz, T, n, m)
    _same_as_sequential(args)


@pytest.mark.parametrize("T", [1, 2, 3, 5, 8, 13, 31])
def test_scan_matches_dense_kkt_and_sequential(T):
    bsz, n, m = 3, 4, 2
    args = random_problem(100 + T, bsz, T, n, m)
    seq, par = _same_as_sequential(args)
    _dense_check(args, par, bsz, T, n, m)
    assert (par.status == Status.CONVERGED).all()


def test_long_odd_horizon_matches_sequential():
    """T = 777 (odd, not a power of two; ten levels of the scan)."""
    args = random_problem(7, 2, 777, 3, 1)
    _same_as_sequential(args)


def test_unbatched_and_shared_x0():
    T, n, m = 6, 3, 2
    args = random_problem(3, 1, T, n, m)
    one = {k: v[0] for k, v in args.items()}
    seq, par = _same_as_sequential(one)
    assert par.x.shape == (T + 1, n) and par.cost.shape == ()
    # data shared by the batch (no batch dim) with a batch of initial states
    x0 = torch.randn(5, n, dtype=F64, generator=torch.Generator().manual_seed(0))
    _same_as_sequential({**one, "x0": x0})


# ----------------------------------------------------------------------------- failures


def test_not_positive_definite_element_isolated(backend):
    """An element with R = -I (validate=False): flagged as on the sequential path (both
    CPU backends of it), every output equal to the sequential path's, the others equal
    to their single solves."""
    bsz, T, n, m = 5, 9, 3, 2
    bad = 3
    args = random_problem(21, bsz, T, n, m)
    args["B"] = 0.3 * args["B"]
    args["R"] = args["R"].clone()
    args["R"][bad] = -torch.eye(m, dtype=F64)
    Bl, QT = args["B"][bad, T - 1], sym(args["Q"][bad, T])
    assert float(torch.linalg.eigvalsh(args["R"][bad, T - 1] + Bl.T @ QT @ Bl).min()) < 0
    seq = lqr_solve(**args, validate=False)
    par = lqr_solve(**args, validate=False, method="scan")
    expected = [Status.NOT_POSITIVE_DEFINITE if i == bad else Status.CONVERGED for i in range(bsz)]
    assert par.status.tolist() == [int(s) for s in expected]
    assert torch.equal(par.status, seq.status)
    for name in FIELDS:
        a, b = getattr(par, name)[bad], getattr(seq, name)[bad]
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12, equal_nan=True), name
    for i in range(bsz):
        if i == bad:
            continue
        one = lqr_solve(**{k: v[i : i + 1] for k, v in args.items()})
        for name in FIELDS:
            assert_rel(getattr(par, name)[i], getattr(one, name)[0], 1e-9, name)


def test_indefinite_quu_with_positive_definite_r():
    """R > 0 but an indefinite terminal weight makes Quu indefinite: the scan's own
    factorisation detects it (the element is redone by the recursion); same status."""
    bsz, T, n, m = 3, 4, 2, 1
    args = random_problem(5, bsz, T, n, m)
    args["Q"] = args["Q"].clone()
    args["Q"][0, T] = -50.0 * torch.eye(n, dtype=F64)
    seq = lqr_solve(**args, validate=False)
    par = lqr_solve(**args, validate=False, method="scan")
    assert int(seq.status[0]) == Status.NOT_POSITIVE_DEFINITE
    assert torch.equal(par.status, seq.status)
    for name in FIELDS:
        assert_rel(getattr(par, name)[1:], getattr(seq, name)[1:], 1e-9, name)


def test_non_finite_element_isolated():
    bsz, T, n, m = 3, 6, 3, 2
    args = random_problem(22, bsz, T, n, m)
    args["x0"] = args["x0"].clone()
    args["x0"][0, 1] = float("nan")
    par = lqr_solve(**args, validate=False, method="scan")
    assert par.status.tolist() == [int(Status.NON_FINITE)] + [int(Status.CONVERGED)] * 2
    ref = lqr_solve(**{k: v[1:] for k, v in args.items()})
    assert_rel(par.x[1:], ref.x, 1e-9, "x")
    assert_rel(par.u[1:], ref.u, 1e-9, "u")


# ----------------------------------------------------------------------------- float32


@pytest.mark.parametrize("T", [1, 10, 65])
def test_float32(T):
    bsz, n, m = 4, 4, 2
    a64 = random_problem(T, bsz, T, n, m)
    s64 = lqr_solve(**a64)
    s32 = lqr_solve(**{k: v.float() for k, v in a64.items()}, method="scan")
    assert (s32.status == Status.CONVERGED).all()
    for name in FIELDS:
        t32 = getattr(s32, name)
        assert t32.dtype == torch.float32, name
        assert_rel(t32, getattr(s64, name), 1e-4, name)


# ----------------------------------------------------------------------------- gradients

ARG_NAMES = ("A", "B", "Q", "R", "x0", "q", "r", "S", "c")


def test_gradcheck_scan():
    args = random_problem(11, 1, 3, 2, 2)
    inputs = tuple(args[k].detach().clone().requires_grad_(True) for k in ARG_NAMES)

    def f(*xs):
        sol = lqr_solve(**dict(zip(ARG_NAMES, xs, strict=True)), method="scan")
        return sol.x, sol.u, sol.cost

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_gradients_equal_sequential_with_shared_data_and_bad_element():
    """Shared (batch-1) data, a batch of x0 and one failed element: the same gradients
    as the sequential path (the failed element contributes nothing on either)."""
    bsz, T, n, m = 4, 11, 3, 2
    args = random_problem(12, bsz, T, n, m)
    args["R"] = args["R"].clone()
    args["R"][2] = -torch.eye(m, dtype=F64)
    shared = {k: (v if k in ("R", "x0") else v[:1]) for k, v in args.items()}
    grads = {}
    for method in ("sequential", "scan"):
        ins = {k: v.detach().clone().requires_grad_(True) for k, v in shared.items()}
        sol = lqr_solve(**ins, validate=False, method=method)
        ok = sol.status == Status.CONVERGED
        loss = (sol.x[ok] ** 2).sum() + sol.u[ok].sum() + sol.cost[ok].sum()
        grads[method] = torch.autograd.grad(loss, list(ins.values()))
    for name, a, b in zip(shared, grads["scan"], grads["sequential"], strict=True):
        assert torch.isfinite(a).all(), name
        assert_rel(a, b, 1e-9, f"d/d{name}")


def test_adjoint_scan_matches_adjoint_solve():
    bsz, T, n, m = 3, 14, 4, 2
    args = random_problem(13, bsz, T, n, m)
    A, B, Q, R, q, r, S, c = (args[k] for k in ("A", "B", "Q", "R", "q", "r", "S", "c"))
    fac = riccati_backward(A, B, Q, R, q, r, S, c)
    F = torch.cat(
        [torch.cat([B, A, c.unsqueeze(-1)], -1), torch.zeros(bsz, T, 1, m + n + 1, dtype=F64)],
        -2,
    )
    F[..., n, -1] = 1.0
    g = torch.Generator().manual_seed(1)
    gx = torch.randn(bsz, T + 1, n, generator=g, dtype=F64)
    gu = torch.randn(bsz, T, m, generator=g, dtype=F64)
    ref = lq_adjoint_solve(F, fac.Kk, fac.Vh, fac.chol, gx, gu)
    got = lq_adjoint_scan(F, fac.Kk, fac.Vh, fac.chol, gx, gu)
    for a, b, name in zip(got, ref, ("dx", "du", "dlam"), strict=True):
        assert_rel(a, b, 1e-10, name)


# ----------------------------------------------------------------------------- API


def test_riccati_scan_and_rollout_scan_match_sequential_api():
    bsz, T, n, m = 3, 10, 4, 2
    args = random_problem(31, bsz, T, n, m)
    A, B, Q, R, x0 = (args[k] for k in ("A", "B", "Q", "R", "x0"))
    q, r, S, c = (args[k] for k in ("q", "r", "S", "c"))
    ref = riccati_backward(A, B, Q, R, q, r, S, c)
    fac = riccati_scan(A, B, Q, R, q, r, S, c)
    assert not fac.failed.any()
    for name in ("Kk", "Vh", "chol"):  # the value's constant term Vh[..., n, n] included
        assert_rel(getattr(fac, name), getattr(ref, name), 1e-10, name)
    x, u = rollout_scan(A, B, fac.K, fac.k, x0, c)
    xr, ur = rollout_linear(A, B, ref.K, ref.k, x0, c)
    assert_rel(x, xr, 1e-10, "x")
    assert_rel(u, ur, 1e-10, "u")
    # shared weights (no batch, no time dim) broadcast as in riccati_backward
    fac2 = riccati_scan(A, B, Q[0, 0], R[0, 0])
    ref2 = riccati_backward(A, B, Q[0, 0], R[0, 0])
    assert_rel(fac2.Vh, ref2.Vh, 1e-10, "Vh shared weights")


@pytest.mark.parametrize("T", [1, 2, 5, 8, 9])
@pytest.mark.parametrize("reverse", [False, True])
def test_associative_scan_matches_python_loop(T, reverse):
    """Products of non-commuting matrices (earlier on the right) against a loop."""
    M = torch.randn(2, T, 3, 3, dtype=F64, generator=torch.Generator().manual_seed(T))
    (out,) = associative_scan(lambda a, b: (b[0] @ a[0],), (M,), reverse=reverse)
    for t in range(T):
        idx = range(t, T) if reverse else range(t + 1)
        ref = torch.eye(3, dtype=F64).expand(2, 3, 3)
        for s in idx:
            ref = M[:, s] @ ref
        assert_rel(out[:, t], ref, 1e-12, f"t={t}")


def test_method_argument():
    args = random_problem(1, 2, 4, 3, 2)
    with pytest.raises(ValueError, match="^method"):
        lqr_solve(**args, method="parallel")


def test_auto_follows_the_measured_rule(backend):
    """``auto`` (the default): the sequential kernel, except a single problem with
    T >= 100 on the CPU torch path (where benchmarks/results/parallel_lq.md measured the
    scan faster) and, on a CUDA GPU, T >= 100 with batches up to 2048
    (benchmarks/results/parallel_lq_cuda.md)."""
    cpu = torch.device("cpu")
    scan_one = "scan" if backend == "torch" else "sequential"
    assert choose_method(100, 1, cpu, F64) == scan_one
    assert choose_method(10000, 1, cpu, torch.float32) == scan_one
    assert choose_method(99, 1, cpu, F64) == "sequential"
    assert choose_method(10000, 32, cpu, F64) == "sequential"
    for T, bsz, expected in (
        (4096, 1, "scan"),
        (100, 1024, "scan"),
        (10000, 1024, "scan"),
        (99, 1, "sequential"),
        (1000, 4096, "sequential"),
        (10000, 2049, "sequential"),  # past the crossover
    ):
        for dt in (F64, torch.float32):
            assert choose_method(T, bsz, "cuda", dt) == expected, (T, bsz, dt)
    for bsz, T in ((1, 120), (2, 5)):
        args = random_problem(1, bsz, T, 3, 2)
        auto = lqr_solve(**args)
        ref = lqr_solve(**args, method=choose_method(T, bsz, cpu, F64))
        for name in FIELDS:
            assert torch.equal(getattr(auto, name), getattr(ref, name)), name


def test_auto_keeps_the_scan_within_device_memory(monkeypatch):
    """On a GPU ``auto`` runs the scan only where its estimated memory is at most half of
    what the device has free (the device's free memory is what the test sets)."""
    import torchslq.lq.solve as solve_mod

    need = solve_mod.scan_memory_bytes(4096, 64, 4, F64)
    assert need == 30 * 25 * 8 * 64 * 4096
    for free, expected in ((2 * need, "scan"), (2 * need - 1, "sequential"), (None, "scan")):
        monkeypatch.setattr(solve_mod, "_device_bytes_free", lambda dev, free=free: free)
        assert choose_method(4096, 64, "cuda", F64, n=4) == expected, free
    assert choose_method(4096, 64, "cuda", F64) == "scan"  # no n: no memory test


def test_scan_memory_estimate_bounds_the_measured_peak():
    """``scan_memory_bytes`` against the peak resident memory a scan solve adds, measured
    in a fresh process (the CPU's allocations are the GPU's): an upper bound, and not a
    loose one (within 3x; measured about 0.6 of it)."""
    code = (
        "import torch, sys\n"
        "sys.path.insert(0, 'tests')\n"
        "from test_lq_kernel import random_problem\n"
        "import torchslq as ts\n"
        "torch.set_num_threads(1)\n"
        "args = random_problem(0, 16, 2048, 4, 2)\n"
        "ts.lqr_solve(**random_problem(1, 1, 8, 4, 2), method='scan')  # code loaded\n"
        "def kb(key):\n"
        "    for line in open('/proc/self/status'):\n"
        "        if line.startswith(key):\n"
        "            return int(line.split()[1]) * 1024\n"
        "open('/proc/self/clear_refs', 'w').write('5')\n"
        "base = kb('VmRSS')\n"
        "with torch.no_grad():\n"
        "    ts.lqr_solve(**args, validate=False, method='scan')\n"
        "print(kb('VmHWM') - base)\n"
    )
    import os
    import subprocess
    import sys

    if not os.access("/proc/self/clear_refs", os.W_OK):
        pytest.skip("needs a writable Linux /proc/self/clear_refs to measure a peak")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    peak = int(out.stdout.strip().splitlines()[-1])
    estimate = scan_memory_bytes(2048, 16, 4, F64)
    assert estimate / 3 < peak <= estimate, (peak, estimate)


def test_auto_falls_back_to_the_recursion_when_the_scan_runs_out_of_memory(monkeypatch):
    import torchslq.lq.solve as solve_mod

    args = random_problem(3, 3, 120, 3, 2)
    ref = lqr_solve(**args, method="sequential")

    def out_of_memory(*a, **k):
        raise torch.OutOfMemoryError("the scan's levels do not fit")

    monkeypatch.setattr(solve_mod, "riccati_scan_homogeneous", out_of_memory)
    monkeypatch.setattr(solve_mod, "choose_method", lambda *a, **k: "scan")
    sol = lqr_solve(**args)  # auto: picks the scan, which fails, then the recursion
    for name in FIELDS:
        assert_rel(getattr(sol, name), getattr(ref, name), 1e-12, name)
    assert torch.equal(sol.status, ref.status)
    with pytest.raises(torch.OutOfMemoryError):
        lqr_solve(**args, method="scan")  # asked for by name: the error is the caller's
