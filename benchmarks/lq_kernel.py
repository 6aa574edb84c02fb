"""Benchmark of the batched LQ kernel (``torchslq.lqr_solve``) against two peers.

Not part of the test suite (``pytest`` only collects ``tests/``). Run from the repo root::

    .venv/bin/pip install --no-deps mpc      # mpc 0.0.6 pins numpy<2 but runs on numpy 2
    .venv/bin/python benchmarks/lq_kernel.py --quick
    .venv/bin/python benchmarks/lq_kernel.py    # full grid (slow; see the flags)

(``pip install mpc`` with dependencies would downgrade numpy to 1.x; it leaves torch alone.)
The committed results were produced by::

    .venv/bin/python benchmarks/lq_kernel.py --sizes 4x1,12x4,32x8 --batches 1,64,1024,8192 \
        --dtypes float64,float32 --threads 1,2 --big-threads 1 --repeat 3 --time-budget 6 \
        --single-above 3 --memory-dtypes float64

What is measured
----------------
For every (n, m) in ``--sizes``, batch size B in ``--batches``, dtype in ``--dtypes`` and torch
thread count in ``--threads`` (``torch.set_num_threads``), with horizon T (default 100) and
time-varying, batch-varying problem data (A_t, B_t, c_t, Q_t, R_t, S_t, q_t, r_t, x0 all
random and different per element and per step):

* ``torchslq`` forward: ``lqr_solve(..., validate=False)`` under ``torch.no_grad()``;
* ``torchslq`` forward+backward: the same with every input requiring grad, followed by
  ``loss.backward()`` for ``loss = sum(wx * x) + sum(wu * u)`` (fixed random weights);
* ``numpy``: a plain batched Riccati recursion in the standard gain form written below
  (``numpy_lqr``; ``np.matmul`` / ``np.linalg.solve`` batched over B, Python loop over t,
  time-major arrays, forward only). It gets the same threads setting only through the
  environment: its per-matrix BLAS/LAPACK calls on these tiny matrices are single-threaded
  whatever ``torch.set_num_threads`` says;
* ``mpc.pytorch`` (pip package ``mpc``, Amos et al. 2018): ``mpc.MPC(n, m, T+1, lqr_iter=1,
  exit_unconverged=False, detach_unconverged=False)`` with ``QuadCost(C, c)`` and
  ``LinDx(F, f)`` in its time-major layout. It has no terminal cost, so it is given T+1
  steps: the extra step carries ``C_T = blkdiag(Q_T, I)``, ``c_T = [q_T, 0]``, whose control
  is trivially 0; its states ``x_0..x_T`` and controls ``u_0..u_{T-1}`` are then the same
  as ``lqr_solve``'s. One LQR iteration solves the LQ problem exactly (the step is taken
  around the zero-control rollout with a full line-search step). Forward and forward+backward
  (same loss) are timed.

Each implementation gets its inputs in its own native layout, built before timing (torchslq:
batch-major ``(B, T, ...)``; NumPy and mpc.pytorch: time-major ``(T, B, ...)``).

Correctness before timing: the warm-up output of every implementation is compared with a
float64 NumPy reference solve of the same (dtype-rounded) data; ``rel_err_u`` is
``max|u - u_ref| / max|u_ref|`` (same for x). In float64 the torchslq and mpc errors must be
below 1e-6, in float32 below 1e-2 (T=100 steps in single precision); a failed check is
flagged in the table. For forward+backward against mpc.pytorch in float64 the gradients
with respect to x0, A and B are compared too.

Timing: ``time.perf_counter``; one warm-up call, then up to ``--repeat`` timed calls (stopping
early once ``--time-budget`` seconds are spent, at least one timed call); the best time is
reported, all samples are in the JSON. A call shorter than 2 ms (a probe call after the
warm-up) is timed as the mean of a loop of calls lasting about 20 ms (at most 1000), as
``timeit`` does: each sample is such a mean. A warm-up longer than ``--single-above`` seconds is
the only sample (``warmup_only`` in the JSON; one-time costs are negligible against it).
``time.process_time`` of the same calls is recorded as ``cpu_s`` (CPU seconds of all
threads): on a shared machine it is robust to other processes taking the cores, where the
best-of-N wall time is only the least-disturbed sample. The load average at start and end
is recorded. With 2 threads on an oversubscribed machine the OpenMP workers spin-wait between
parallel regions (``OMP_WAIT_POLICY`` is left at its default), which shows up in both.

Peers (mpc.pytorch) are skipped ("skipped (too slow)") when one call is estimated to take
more than ``--peer-limit`` seconds (default 60): the estimate is 1.5 x the time at the
previous batch size (>= 64) of the same config scaled linearly in B, plus mpc.pytorch's
measured O(B^2) ``torch.diag(alphas)`` term (see ``Runner.estimate``); a SIGALRM watchdog
aborts any peer call that runs past the limit. ``--big-threads`` restricts the thread counts
used for B >= ``--big-batch``. Configurations whose estimated memory exceeds
``--max-mem-gb`` (or 85% of MemAvailable) are skipped ("skipped (memory)").

Peak memory (``--memory``, on by default): measured per (size, B, dtype) in a fresh
subprocess (1 thread) for each implementation in turn: the kernel's peak-RSS counter (VmHWM)
is reset by writing ``5`` to ``/proc/self/clear_refs``, the resident size is read as the
baseline, one call (forward, or forward+backward) is run, and ``VmHWM - baseline`` is
reported, i.e. the extra resident memory at the peak of the call, inputs excluded (input
gradients included for forward+backward). The child runs with
``MALLOC_MMAP_THRESHOLD_=131072`` so that glibc returns every large block to the OS on
free (otherwise reused heap memory makes later measurements read low). Where
``clear_refs`` is not writable each implementation gets its own subprocess and
``ru_maxrss`` deltas are used (an upper-bound-ish number that includes one-time setup).

Throughput: the flop count of one step of the Riccati recursion plus rollout in the
standard gain form (multiply-add = 2 flops, symmetrisation and additions of lower order
ignored)::

    VA, A'VA, VB, B'VB, B'VA          4 n^3 + 4 n^2 m + 2 n m^2
    w = v + V c, A'w, B'w             4 n^2 + 2 n m
    Cholesky of Quu, solve n+1 rhs    m^3 / 3 + 2 m^2 (n + 1)
    V += Qux'K, v += Qux'k            2 n^2 m + 2 n m
    rollout Kx, Ax, Bu                2 n^2 + 4 n m
    ---------------------------------------------------------------
    flops/step = 4n^3 + 6n^2 m + 2n m^2 + m^3/3 + 2m^2(n+1) + 6n^2 + 8nm

and per solve ``B * T * flops/step`` (the forward solve; the homogeneous form torchslq
uses does somewhat more arithmetic, which is not credited). GFLOP/s are reported against
the machine's peak, estimated by the best of five ``torch.mm`` of 2048x2048 matrices in the
same dtype and thread count.

``--compile`` additionally times ``torch.compile`` of the forward solve (compile time and
steady-state time; it unrolls the T-step loops, so compilation takes minutes).
"""

from __future__ import annotations

import argparse
import datetime
import functools
import gc
import json
import math
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import torchslq  # noqa: E402

DTYPES = {"float64": torch.float64, "float32": torch.float32}
TOL = {"float64": 1e-6, "float32": 1e-2}


# ----------------------------------------------------------------------------- problem data


def flops_per_step(n: int, m: int) -> float:
    """Flop count of one Riccati + rollout step in the gain form (see module docstring)."""
    return (
        4 * n**3
        + 6 * n**2 * m
        + 2 * n * m**2
        + m**3 / 3
        + 2 * m**2 * (n + 1)
        + 6 * n**2
        + 8 * n * m
    )


def make_problem(nb: int, T: int, n: int, m: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random time-varying LQ problem, float64, batch-major ``(B, T, ...)``.

    ``A_t = I + 0.1 G / sqrt(n)``, ``B_t = G' / sqrt(n)``; the stage cost matrix
    ``[[Q, S'], [S, R]] = L L' / (n+m) + 0.1 I`` is jointly positive definite (so it is
    also a valid mpc.pytorch cost), the terminal ``Q_T`` its state block.
    """
    g = torch.Generator().manual_seed(seed + 1000 * n + m)
    f64 = torch.float64
    A = torch.randn(nb, T, n, n, generator=g, dtype=f64).mul_(0.1 / math.sqrt(n))
    A += torch.eye(n, dtype=f64)
    Bm = torch.randn(nb, T, n, m, generator=g, dtype=f64).mul_(1 / math.sqrt(n))
    L = torch.randn(nb, T + 1, n + m, n + m, generator=g, dtype=f64)
    C = torch.matmul(L, L.mT).div_(n + m)
    del L
    C += 0.1 * torch.eye(n + m, dtype=f64)
    Q = C[:, :, :n, :n].contiguous()
    R = C[:, :T, n:, n:].contiguous()
    S = C[:, :T, n:, :n].contiguous()
    del C
    return {
        "A": A,
        "B": Bm,
        "Q": Q,
        "R": R,
        "S": S,
        "q": torch.randn(nb, T + 1, n, generator=g, dtype=f64),
        "r": torch.randn(nb, T, m, generator=g, dtype=f64),
        "c": torch.randn(nb, T, n, generator=g, dtype=f64).mul_(0.1),
        "x0": torch.randn(nb, n, generator=g, dtype=f64),
        "wx": torch.randn(nb, T + 1, n, generator=g, dtype=f64),
        "wu": torch.randn(nb, T, m, generator=g, dtype=f64),
    }


def problem_bytes(nb: int, T: int, n: int, m: int, itemsize: int = 8) -> int:
    per = T * (n * n + n * m + m * m + m * n + 3 * n + 2 * m) + n * n + 2 * n
    return nb * per * itemsize


def estimated_peak_bytes(nb: int, T: int, n: int, m: int, itemsize: int) -> int:
    """Rough peak of one config in the timing process: the float64 problem, its copy in the
    timed dtype with gradients, and torchslq's fwd+bwd working set, which is dominated by
    the homogeneous stage matrices, (m+n+1)^2 per step (measured: about 6.7 times their
    size at (12,4), B=1024; 7 is used)."""
    hom = nb * T * (m + n + 1) ** 2 * itemsize
    return problem_bytes(nb, T, n, m, 8) + 2 * problem_bytes(nb, T, n, m, itemsize) + 7 * hom


def to_torchslq(P: dict, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    return {k: v.to(dtype) for k, v in P.items()}


def to_numpy_tm(P: dict, dtype: torch.dtype) -> dict[str, np.ndarray]:
    """Time-major contiguous NumPy arrays ``(T, B, ...)``."""
    out = {}
    for k, v in P.items():
        v = v.to(dtype)
        if k != "x0":
            v = v.transpose(0, 1)
        out[k] = np.ascontiguousarray(v.numpy())
    return out


def to_mpc(P: dict, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """mpc.pytorch layout: C (T+1,B,n+m,n+m), c (T+1,B,n+m), F (T,B,n,n+m), f (T,B,n)."""
    A, Bm, Q, R, S = P["A"], P["B"], P["Q"], P["R"], P["S"]
    nb, T, n, m = *A.shape[:3], Bm.shape[-1]
    C = torch.zeros(T + 1, nb, n + m, n + m, dtype=torch.float64)
    C[:, :, :n, :n] = Q.transpose(0, 1)
    C[:T, :, n:, n:] = R.transpose(0, 1)
    C[T, :, n:, n:] = torch.eye(m, dtype=torch.float64)
    C[:T, :, n:, :n] = S.transpose(0, 1)
    C[:T, :, :n, n:] = S.transpose(0, 1).mT
    c = torch.zeros(T + 1, nb, n + m, dtype=torch.float64)
    c[:, :, :n] = P["q"].transpose(0, 1)
    c[:T, :, n:] = P["r"].transpose(0, 1)
    F = torch.cat([A, Bm], dim=-1).transpose(0, 1)
    return {
        "C": C.to(dtype).contiguous(),
        "c": c.to(dtype).contiguous(),
        "F": F.to(dtype).contiguous(),
        "f": P["c"].transpose(0, 1).to(dtype).contiguous(),
        "x0": P["x0"].to(dtype).contiguous(),
        "wx": P["wx"].transpose(0, 1).to(dtype).contiguous(),
        "wu": P["wu"].transpose(0, 1).to(dtype).contiguous(),
    }


# ----------------------------------------------------------------------------- implementations


def numpy_lqr(d: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Reference: batched Riccati recursion in the standard gain form, time-major arrays.

    ``A (T,B,n,n)``, ``B (T,B,n,m)``, ``Q (T+1,B,n,n)``, ``R (T,B,m,m)``, ``S (T,B,m,n)``,
    ``q (T+1,B,n)``, ``r (T,B,m)``, ``c (T,B,n)``, ``x0 (B,n)``. Returns ``x (T+1,B,n)``,
    ``u (T,B,m)``. Per step::

        w   = v + V c
        Qxx = Q + A'VA,  Quu = R + B'VB,  Qux = S + B'VA,  qx = q + A'w,  qu = r + B'w
        [K, k] = -Quu^{-1} [Qux, qu]
        V = Qxx + Qux'K (symmetrised),  v = qx + Qux'k
    """
    A, Bm, Q, R, S = d["A"], d["B"], d["Q"], d["R"], d["S"]
    q, r, c, x0 = d["q"], d["r"], d["c"], d["x0"]
    T, nb, n, _ = A.shape
    m = Bm.shape[-1]
    K = np.empty((T, nb, m, n), dtype=A.dtype)
    k = np.empty((T, nb, m, 1), dtype=A.dtype)
    V = Q[T]
    v = q[T][..., None]
    for t in range(T - 1, -1, -1):
        At, Bt = A[t], Bm[t]
        AtT, BtT = At.transpose(0, 2, 1), Bt.transpose(0, 2, 1)
        VA = V @ At
        VB = V @ Bt
        w = v + V @ c[t][..., None]
        Qxx = Q[t] + AtT @ VA
        Quu = R[t] + BtT @ VB
        Qux = S[t] + BtT @ VA
        qx = q[t][..., None] + AtT @ w
        qu = r[t][..., None] + BtT @ w
        G = np.linalg.solve(Quu, np.concatenate([Qux, qu], axis=-1))
        K[t] = -G[..., :n]
        k[t] = -G[..., n:]
        QuxT = Qux.transpose(0, 2, 1)
        V = Qxx + QuxT @ K[t]
        V = 0.5 * (V + V.transpose(0, 2, 1))
        v = qx + QuxT @ k[t]
    x = np.empty((T + 1, nb, n, 1), dtype=A.dtype)
    u = np.empty((T, nb, m, 1), dtype=A.dtype)
    x[0] = x0[..., None]
    for t in range(T):
        u[t] = K[t] @ x[t] + k[t]
        x[t + 1] = A[t] @ x[t] + Bm[t] @ u[t] + c[t][..., None]
    return x[..., 0], u[..., 0]


TORCHSLQ_ARGS = ("A", "B", "Q", "R", "x0", "q", "r", "S", "c")


def torchslq_fwd(d: dict[str, torch.Tensor]):
    with torch.no_grad():
        sol = torchslq.lqr_solve(*(d[k] for k in TORCHSLQ_ARGS), validate=False)
    return sol.x, sol.u


def torchslq_fwdbwd(d: dict[str, torch.Tensor]):
    leaves = [d[k] for k in TORCHSLQ_ARGS]
    for t in leaves:
        t.grad = None
    sol = torchslq.lqr_solve(*leaves, validate=False)
    loss = (sol.x * d["wx"]).sum() + (sol.u * d["wu"]).sum()
    loss.backward()
    return sol.x.detach(), sol.u.detach()


MPC_ARGS = ("x0", "C", "c", "F", "f")


def _mpc_call(d: dict[str, torch.Tensor]):
    from mpc import mpc as mpc_mod

    T1, nb, n, _ = d["F"].shape
    m = d["F"].shape[-1] - n
    ctrl = mpc_mod.MPC(
        n,
        m,
        T1 + 1,
        lqr_iter=1,
        exit_unconverged=False,
        detach_unconverged=False,
        n_batch=nb,
        verbose=-1,
    )
    x, u, _ = ctrl(d["x0"], mpc_mod.QuadCost(d["C"], d["c"]), mpc_mod.LinDx(d["F"], d["f"]))
    return x, u[:T1]


def mpc_fwd(d: dict[str, torch.Tensor]):
    with torch.no_grad():
        x, u = _mpc_call(d)
    return x.transpose(0, 1), u.transpose(0, 1)


def mpc_fwdbwd(d: dict[str, torch.Tensor]):
    for k in MPC_ARGS:
        d[k].grad = None
    x, u = _mpc_call(d)
    loss = (x * d["wx"]).sum() + (u * d["wu"]).sum()
    loss.backward()
    return x.detach().transpose(0, 1), u.detach().transpose(0, 1)


# ----------------------------------------------------------------------------- timing helpers


class Watchdog(Exception):
    pass


def _alarm(_signum, _frame):
    raise Watchdog()


SHORT_CALL = 2e-3  # seconds: calls shorter than this are timed in loops ...
LOOP_TIME = 0.02  # ... of about this long (at most MAX_LOOP calls), the mean per call
MAX_LOOP = 1000


def bench(fn, repeat: int, budget: float, single_above: float = math.inf, call_limit=None):
    """One warm-up call, then up to ``repeat`` timed calls (at least one) within ``budget``.

    If the warm-up alone took more than ``single_above`` seconds it is the only sample
    (one-time costs are then negligible; the JSON marks it ``warmup_only``). With
    ``call_limit`` a SIGALRM watchdog raises :class:`Watchdog` in any call running longer.
    Returns ``(best, times, warm, out, warmup_only, best_cpu)``; ``best_cpu`` is the least
    process CPU time (all threads) of the timed calls, a contention-robust companion.
    """
    cpu: list[float] = []

    def call(loop: int = 1):
        """``loop`` calls of ``fn``: the mean wall and CPU time of one, its last result."""
        if call_limit:
            signal.signal(signal.SIGALRM, _alarm)
            signal.setitimer(signal.ITIMER_REAL, call_limit)
        try:
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(loop):
                res = fn()
            cpu.append((time.process_time() - c0) / loop)
            return (time.perf_counter() - t0) / loop, res
        finally:
            if call_limit:
                signal.setitimer(signal.ITIMER_REAL, 0)

    warm, out = call()
    if warm > single_above:
        return warm, [warm], warm, out, True, cpu[0]
    # a call shorter than SHORT_CALL is timed as the mean of a loop of calls lasting
    # about LOOP_TIME (as timeit): one call of ~0.1 ms, timed alone, measures mostly
    # the timer and the cold caches left by the previous configuration
    probe = call()[0]
    loop = 1 if probe >= SHORT_CALL else min(MAX_LOOP, math.ceil(LOOP_TIME / max(probe, 1e-7)))
    cpu.clear()
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < max(1, repeat):
        times.append(call(loop)[0])
        if time.perf_counter() - start + warm > budget:
            break
    return min(times), times, warm, out, False, min(cpu)


def rel_err(a, b) -> float:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    den = float(np.max(np.abs(b))) if b.size else 1.0
    return float(np.max(np.abs(a - b))) / max(den, 1e-300)


def mem_available_bytes() -> int:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 1 << 62


def peak_gflops(dtype: torch.dtype, threads: int, size: int = 2048) -> float:
    torch.set_num_threads(threads)
    a = torch.randn(size, size, dtype=dtype)
    b = torch.randn(size, size, dtype=dtype)
    torch.mm(a, b)
    best = math.inf
    for _ in range(5):
        t0 = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - t0)
    return 2 * size**3 / best / 1e9


def peak_gflops_per_core_cpu(dtype: torch.dtype, size: int = 2048) -> float:
    """1-thread matmul rate from process CPU time: what one core does when it runs."""
    torch.set_num_threads(1)
    a = torch.randn(size, size, dtype=dtype)
    b = torch.randn(size, size, dtype=dtype)
    torch.mm(a, b)
    best = math.inf
    for _ in range(5):
        t0 = time.process_time()
        torch.mm(a, b)
        best = min(best, time.process_time() - t0)
    return 2 * size**3 / best / 1e9


# ----------------------------------------------------------------------------- memory child


def _vm_status(key: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    raise KeyError(key)


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _maxrss_bytes() -> int:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def mem_child(spec: dict) -> list[dict]:
    """Runs in a fresh subprocess: peak extra RSS of one call per implementation."""
    torch.set_num_threads(1)
    n, m, T, nb, dtype_name = spec["n"], spec["m"], spec["T"], spec["B"], spec["dtype"]
    dtype = DTYPES[dtype_name]
    P = make_problem(nb, T, n, m)
    P1 = {k: v[:1].clone() for k, v in P.items()}
    out = []
    for impl, mode in spec["items"]:
        if impl == "torchslq":
            fn = torchslq_fwd if mode == "fwd" else torchslq_fwdbwd

            def prep(PP, mode=mode):
                d = to_torchslq(PP, dtype)
                if mode == "fwdbwd":
                    d = {k: v.clone().requires_grad_(k in TORCHSLQ_ARGS) for k, v in d.items()}
                return d
        elif impl == "numpy":
            fn = numpy_lqr

            def prep(PP):
                return to_numpy_tm(PP, dtype)
        else:
            fn = mpc_fwd if mode == "fwd" else mpc_fwdbwd

            def prep(PP, mode=mode):
                d = to_mpc(PP, dtype)
                if mode == "fwdbwd":
                    d = {k: v.requires_grad_(k in MPC_ARGS) for k, v in d.items()}
                return d

        fn(prep(P1))  # load code paths at B=1
        d = prep(P)
        gc.collect()
        if _reset_hwm():
            base = _vm_status("VmRSS")
            fn(d)
            peak = _vm_status("VmHWM") - base
            method = "VmHWM-after-clear_refs minus VmRSS"
        else:
            base = _maxrss_bytes()
            fn(d)
            peak = _maxrss_bytes() - base
            method = "ru_maxrss delta (fresh process)"
        del d
        gc.collect()
        out.append({"impl": impl, "mode": mode, "peak_mb": peak / 2**20, "method": method})
    return out


def measure_memory(n, m, T, nb, dtype_name, items, timeout=900) -> list[dict]:
    env = dict(os.environ)
    env.update(
        MALLOC_MMAP_THRESHOLD_="131072",
        MALLOC_TRIM_THRESHOLD_="131072",
        OMP_NUM_THREADS="1",
        OPENBLAS_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
    )
    can_reset = _reset_hwm()
    groups = [items] if can_reset else [[it] for it in items]
    res: list[dict] = []
    for group in groups:
        spec = {"n": n, "m": m, "T": T, "B": nb, "dtype": dtype_name, "items": group}
        try:
            proc = subprocess.run(
                [sys.executable, __file__, "--mem-child", json.dumps(spec)],
                capture_output=True,
                text=True,
                env=env,
                timeout=timeout,
            )
            line = [ln for ln in proc.stdout.splitlines() if ln.startswith("MEMRESULT ")]
            if proc.returncode != 0 or not line:
                err = " ".join((proc.stderr or "").strip().splitlines()[-1:])
                if proc.returncode in (-9, 137):
                    err = "killed (SIGKILL: out of memory?) " + err
                err = f"failed (exit {proc.returncode}) {err}".strip()
                res += [{"impl": i, "mode": mo, "error": err} for i, mo in group]
            else:
                res += json.loads(line[-1][len("MEMRESULT ") :])
        except subprocess.TimeoutExpired:
            res += [{"impl": i, "mode": mo, "error": "timeout"} for i, mo in group]
    return res


# ----------------------------------------------------------------------------- main driver


def parse_sizes(s: str) -> list[tuple[int, int]]:
    out = []
    for tok in s.split(","):
        a, b = tok.lower().split("x")
        out.append((int(a), int(b)))
    return out


def parse_ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x]


def git_commit() -> str:
    """Short HEAD hash, with ``+dirty`` when ``torchslq/`` has uncommitted changes."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "torchslq"],
            cwd=ROOT,
            capture_output=True,
            text=True,
        ).stdout.strip()
        return (head or "?") + ("+dirty" if dirty else "")
    except OSError:
        return "?"


class Runner:
    def __init__(self, args):
        self.args = args
        self.records: list[dict] = []
        self.memory: list[dict] = []
        self.peak: dict[str, dict[str, float]] = {}
        self.compiled: dict = {}
        self.peak_cpu: dict[str, float] = {}
        self.meta = {
            "date": datetime.datetime.now().isoformat(timespec="seconds"),
            "command": " ".join([_exe()] + sys.argv),
            "git_commit": git_commit(),
            "torch": torch.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
            "cpu": _cpu_model(),
            "cpu_count": os.cpu_count(),
            "loadavg_start": os.getloadavg(),
            "T": args.T,
            "repeat": args.repeat,
            "time_budget_s": args.time_budget,
            "peer_limit_s": args.peer_limit,
            "single_above_s": args.single_above,
            "big_threads": args.big_threads,
            "big_batch": args.big_batch,
            "flops_formula": "4n^3 + 6n^2 m + 2n m^2 + m^3/3 + 2m^2(n+1) + 6n^2 + 8nm per step",
        }
        try:
            from importlib.metadata import version

            import mpc  # noqa: F401

            self.meta["mpc"] = version("mpc")
            self.have_mpc = True
        except Exception as err:  # pragma: no cover - depends on the environment
            self.meta["mpc"] = f"unavailable: {err}"
            self.have_mpc = False

    # -- helpers
    def log(self, msg: str) -> None:
        print(msg, flush=True)

    def add(self, **rec) -> dict:
        self.records.append(rec)
        return rec

    def prev_time(self, n, m, dtype, threads, impl, mode, nb):
        """Best time of the largest smaller batch measured for the same config."""
        best = None
        for r in self.records:
            if (r["n"], r["m"], r["dtype"], r["threads"], r["impl"], r["mode"]) != (
                n,
                m,
                dtype,
                threads,
                impl,
                mode,
            ):
                continue
            if r.get("time_s") is None or r["B"] >= nb:
                continue
            if best is None or r["B"] > best[0]:
                best = (r["B"], r["time_s"])
        return best

    def estimate(self, n, m, dtype, threads, impl, mode, nb) -> float | None:
        """Seconds for one call, extrapolated linearly in B from the previous batch size, times
        a safety factor of 1.5 (timings on a shared machine fluctuate).

        For mpc.pytorch a measured O(B^2) term is added: its rollout forms the dense
        ``torch.diag(alphas)`` (B x B) and multiplies it by ``k_t`` at every one of its T+1
        steps (twice per step for forward+backward, whose backward re-runs the solver).
        """
        p = self.prev_time(n, m, dtype, threads, impl, mode, nb)
        if p is None or p[0] < 64:
            return None  # tiny batches are overhead-bound; the watchdog guards instead
        est = p[1] * nb / p[0]
        if impl == "mpc" and nb >= 2048:
            a = torch.ones(nb, dtype=DTYPES[dtype])
            kt = torch.ones(nb, m, dtype=DTYPES[dtype])
            t0 = time.perf_counter()
            torch.diag(a).mm(kt)
            t_diag = time.perf_counter() - t0
            est += (1 if mode == "fwd" else 2) * (self.args.T + 1) * t_diag
        return 1.5 * est

    def threads_for(self, nb: int) -> list[int]:
        a = self.args
        return a.big_threads if (a.big_threads and nb >= a.big_batch) else a.threads

    def timed(self, fn, call_limit=None):
        a = self.args
        return bench(fn, a.repeat, a.time_budget, a.single_above, call_limit)

    def record(self, ctx, impl, mode, res, extra=None):
        """Store one timing result after checking its (warm-up) output against the reference."""
        best, times, warm, out, warmup_only, best_cpu = res
        base, dtype_name = ctx["base"], ctx["base"]["dtype"]
        x, u = (np.asarray(o.detach().numpy() if torch.is_tensor(o) else o) for o in out)
        if impl == "numpy":
            x, u = x.transpose(1, 0, 2), u.transpose(1, 0, 2)
        eu, ex = rel_err(u, ctx["u_ref"]), rel_err(x, ctx["x_ref"])
        ok = eu < TOL[dtype_name] and ex < TOL[dtype_name]
        gf = ctx["flops"] / best / 1e9 if mode == "fwd" else None
        peak = ctx["peak"]
        rec = self.add(
            **base,
            impl=impl,
            mode=mode,
            status="ok" if ok else "check failed",
            time_s=best,
            cpu_s=best_cpu,
            times_s=times,
            warmup_s=warm,
            warmup_only=warmup_only,
            rel_err_u=eu,
            rel_err_x=ex,
            check_ok=ok,
            gflops=gf,
            peak_frac=(gf / peak) if (gf and peak) else None,
            **(extra or {}),
        )
        self.log(
            f"  ({base['n']},{base['m']}) B={base['B']:5d} {dtype_name} thr={base['threads']} "
            f"{impl:8s} {mode:6s} {best * 1e3:10.2f} ms  (warm-up {warm * 1e3:.1f} ms, "
            f"n={len(times)}{', warm-up only' if warmup_only else ''}) err_u={eu:.1e} {'' if ok else 'CHECK FAILED'}"
        )
        return rec

    # -- one configuration
    def run_config(self, n, m, nb):
        a = self.args
        T = a.T
        for dtype_name in a.dtypes:
            dtype = DTYPES[dtype_name]
            itemsize = torch.finfo(dtype).bits // 8
            est = estimated_peak_bytes(nb, T, n, m, itemsize)
            limit = min(a.max_mem_gb * 2**30, 0.85 * mem_available_bytes())
            common = {"n": n, "m": m, "T": T, "B": nb, "dtype": dtype_name}
            if est > limit:
                self.log(
                    f"({n},{m}) B={nb} {dtype_name}: skipped (memory): est "
                    f"{est / 2**30:.1f} GiB > {limit / 2**30:.1f} GiB"
                )
                for thr in self.threads_for(nb):
                    for impl, mode in (
                        ("torchslq", "fwd"),
                        ("torchslq", "fwdbwd"),
                        ("numpy", "fwd"),
                        ("mpc", "fwd"),
                        ("mpc", "fwdbwd"),
                    ):
                        self.add(
                            **common, threads=thr, impl=impl, mode=mode, status="skipped (memory)"
                        )
                continue
            P = make_problem(nb, T, n, m)
            # float64 reference on the dtype-rounded data
            Pr = {k: v.to(dtype).to(torch.float64) for k, v in P.items()}
            x_ref, u_ref = numpy_lqr(to_numpy_tm(Pr, torch.float64))
            x_ref, u_ref = x_ref.transpose(1, 0, 2), u_ref.transpose(1, 0, 2)
            del Pr
            fl = flops_per_step(n, m) * T * nb
            for thr in self.threads_for(nb):
                torch.set_num_threads(thr)
                peak = self.peak.get(dtype_name, {}).get(str(thr))
                base = {**common, "threads": thr, "flops": fl}

                ctx = {
                    "base": base,
                    "peak": peak,
                    "x_ref": x_ref,
                    "u_ref": u_ref,
                    "flops": fl,
                }
                record = functools.partial(self.record, ctx)

                # NumPy reference loop
                if not a.no_numpy:
                    dn = to_numpy_tm(P, dtype)
                    record(
                        "numpy",
                        "fwd",
                        self.timed(lambda dn=dn: numpy_lqr(dn)),
                    )
                    del dn
                # torchslq
                dt = to_torchslq(P, dtype)
                record(
                    "torchslq",
                    "fwd",
                    self.timed(lambda dt=dt: torchslq_fwd(dt)),
                )
                dg = {k: v.clone().requires_grad_(k in TORCHSLQ_ARGS) for k, v in dt.items()}
                rec_t = record(
                    "torchslq",
                    "fwdbwd",
                    self.timed(lambda dg=dg: torchslq_fwdbwd(dg)),
                )
                grads_t = {k: dg[k].grad for k in ("x0", "A", "B")}
                del dt, dg
                if a.compile:
                    self.run_compile(n, m, nb, dtype_name, thr, P, base, record)
                # mpc.pytorch
                if self.have_mpc and not a.no_mpc:
                    self.run_mpc(n, m, nb, dtype_name, thr, P, base, record, grads_t, rec_t)
                gc.collect()
            # memory
            if a.memory and dtype_name in a.memory_dtypes:
                items = [("torchslq", "fwd"), ("torchslq", "fwdbwd")]
                if not a.no_numpy:
                    items.append(("numpy", "fwd"))
                ran_mpc = [
                    r
                    for r in self.records
                    if r["impl"] == "mpc"
                    and (r["n"], r["m"], r["B"], r["dtype"]) == (n, m, nb, dtype_name)
                    and r.get("time_s") is not None
                ]
                if ran_mpc:
                    items.append(("mpc", "fwdbwd"))
                t0 = time.perf_counter()
                # the child holds the problem, its copy with gradients and one call's working set
                need = est
                if need > 0.85 * mem_available_bytes():
                    mem = [{"impl": i, "mode": mo, "error": "skipped (memory)"} for i, mo in items]
                else:
                    mem = measure_memory(n, m, T, nb, dtype_name, items)
                for r in mem:
                    self.memory.append({**common, **r})
                self.log(
                    f"  memory ({time.perf_counter() - t0:.1f} s): "
                    + ", ".join(
                        f"{r['impl']}/{r['mode']}="
                        + (f"{r['peak_mb']:.1f} MB" if "peak_mb" in r else r.get("error", "?"))
                        for r in mem
                    )
                )
            del P
            gc.collect()
            self.save()

    def run_mpc(self, n, m, nb, dtype_name, thr, P, base, record, grads_t, rec_t):
        a = self.args
        tag = f"  mpc.pytorch ({n},{m}) B={nb} {dtype_name} thr={thr}"
        todo = []
        for mode in ("fwd", "fwdbwd"):
            est = self.estimate(n, m, dtype_name, thr, "mpc", mode, nb)
            if est is not None and est > a.peer_limit:
                self.log(f"{tag} {mode}: skipped (too slow), estimated {est:.0f} s per call")
                self.add(**base, impl="mpc", mode=mode, status="skipped (too slow)", est_s=est)
            else:
                todo.append(mode)
        if not todo:
            return
        dm = to_mpc(P, DTYPES[dtype_name])
        mode = todo[0]
        try:
            if "fwd" in todo:
                record("mpc", "fwd", self.timed(lambda: mpc_fwd(dm), a.peer_limit))
            if "fwdbwd" in todo:
                mode = "fwdbwd"
                dg = {k: v.clone().requires_grad_(k in MPC_ARGS) for k, v in dm.items()}
                res = self.timed(lambda: mpc_fwdbwd(dg), a.peer_limit)
                extra = {}
                if grads_t.get("x0") is not None and dg["x0"].grad is not None:
                    Fg = dg["F"].grad.transpose(0, 1)
                    extra = {
                        "grad_rel_err_x0": rel_err(grads_t["x0"].numpy(), dg["x0"].grad.numpy()),
                        "grad_rel_err_A": rel_err(grads_t["A"].numpy(), Fg[..., :n].numpy()),
                        "grad_rel_err_B": rel_err(grads_t["B"].numpy(), Fg[..., n:].numpy()),
                    }
                    rec_t.update(extra)
                record("mpc", "fwdbwd", res, extra)
        except Watchdog:
            self.log(f"{tag} {mode}: skipped (too slow), a call exceeded {a.peer_limit:.0f} s")
            for md in todo[todo.index(mode) :]:
                self.add(
                    **base,
                    impl="mpc",
                    mode=md,
                    status="skipped (too slow)",
                    est_s=f">{a.peer_limit:.0f} (watchdog)",
                )
        except Exception as err:  # pragma: no cover - a peer failing is a result, not a crash
            self.log(f"  mpc.pytorch failed: {type(err).__name__}: {err}")
            for mode in ("fwd", "fwdbwd"):
                self.add(
                    **base, impl="mpc", mode=mode, status=f"failed: {type(err).__name__}: {err}"
                )

    def run_compile(self, n, m, nb, dtype_name, thr, P, base, record):
        """``torch.compile`` of the forward solve (static shapes, one compile per problem
        shape, reused across thread counts); the first call's time is the compile time."""
        dt = to_torchslq(P, DTYPES[dtype_name])
        args = [dt[k] for k in TORCHSLQ_ARGS]
        key = (n, m, nb, dtype_name)
        extra = {}
        try:
            if key not in self.compiled:
                for name in ("recompile_limit", "cache_size_limit"):
                    if hasattr(torch._dynamo.config, name):
                        setattr(torch._dynamo.config, name, 256)

                def solve(*xs):
                    sol = torchslq.lqr_solve(*xs, validate=False)
                    return sol.x, sol.u

                cfn = torch.compile(solve, dynamic=False)
                t0 = time.perf_counter()
                with torch.no_grad():
                    cfn(*args)
                self.compiled[key] = cfn
                extra["compile_s"] = time.perf_counter() - t0
            cfn = self.compiled[key]

            def call():
                with torch.no_grad():
                    return cfn(*args)

            record("torchslq-compile", "fwd", self.timed(call), extra)
        except Exception as err:
            msg = f"failed: {type(err).__name__}: {str(err)[:200]}"
            self.log(f"  torch.compile {msg}")
            self.add(**base, impl="torchslq-compile", mode="fwd", status=msg)

    # -- whole run
    def run(self):
        a = self.args
        for dtype_name in a.dtypes:
            self.peak[dtype_name] = {}
            for thr in a.threads:
                self.peak[dtype_name][str(thr)] = peak_gflops(DTYPES[dtype_name], thr)
            self.peak_cpu[dtype_name] = peak_gflops_per_core_cpu(DTYPES[dtype_name])
        self.log(f"peak GFLOP/s (torch.mm 2048^2): {self.peak}")
        t_start = time.perf_counter()
        for n, m in a.sizes:
            for nb in sorted(a.batches):
                self.log(f"== (n,m)=({n},{m}) B={nb} T={a.T}")
                self.run_config(n, m, nb)
        self.meta["wall_s"] = time.perf_counter() - t_start
        self.meta["loadavg_end"] = os.getloadavg()
        self.save()
        self.log(f"wrote {a.out / (a.name + '.json')} and {a.out / (a.name + '.md')}")

    def save(self):
        out = self.args.out
        out.mkdir(parents=True, exist_ok=True)
        payload = {
            "meta": self.meta,
            "peak_gflops": self.peak,
            "peak_gflops_per_core_cpu_time": self.peak_cpu,
            "headline": headline(self.records),
            "results": self.records,
            "memory": self.memory,
        }
        name = self.args.name
        (out / f"{name}.json").write_text(json.dumps(payload, indent=1, default=str))
        (out / f"{name}.md").write_text(markdown(payload))


def _exe() -> str:
    exe = sys.executable
    return os.path.relpath(exe, ROOT) if exe.startswith(str(ROOT) + os.sep) else exe


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


# ----------------------------------------------------------------------------- reporting


def _find(records, **kw):
    for r in records:
        if all(r.get(k) == v for k, v in kw.items()):
            return r
    return None


def _ratio(records, peer, mode, n, m, nb, dtype, thr, key="time_s"):
    t = _find(records, impl="torchslq", mode=mode, n=n, m=m, B=nb, dtype=dtype, threads=thr)
    p = _find(records, impl=peer, mode=mode, n=n, m=m, B=nb, dtype=dtype, threads=thr)
    if not t or not p:
        return None, "not run"
    if p.get(key) is None:
        return None, p.get("status", "?")
    if t.get(key) is None:
        return None, t.get("status", "?")
    return p[key] / t[key], "ok"


TARGETS = [
    # (label, peer, mode, (n, m), B, target ratio peer/torchslq)
    ("B=1024 vs NumPy loop, fwd", "numpy", "fwd", (4, 1), 1024, 10.0),
    ("B=1024 vs NumPy loop, fwd", "numpy", "fwd", (12, 4), 1024, 5.0),
    ("B=1024 vs mpc.pytorch, fwd", "mpc", "fwd", (12, 4), 1024, 20.0),
    ("B=1024 vs mpc.pytorch, fwd+bwd", "mpc", "fwdbwd", (12, 4), 1024, 20.0),
    ("B=1 vs NumPy loop, fwd (within 3x)", "numpy", "fwd", (4, 1), 1, 1 / 3),
    ("B=1 vs NumPy loop, fwd (within 3x)", "numpy", "fwd", (12, 4), 1, 1 / 3),
    ("B=1 vs NumPy loop, fwd (within 3x)", "numpy", "fwd", (32, 8), 1, 1 / 3),
]


def headline(records) -> list[dict]:
    out = []
    combos = sorted(
        {(r["dtype"], r["threads"]) for r in records}, key=lambda c: (c[0] != "float64", c[1])
    )
    for dtype, thr in combos:
        for label, peer, mode, (n, m), nb, target in TARGETS:
            ratio, status = _ratio(records, peer, mode, n, m, nb, dtype, thr)
            cpu_ratio, _ = _ratio(records, peer, mode, n, m, nb, dtype, thr, key="cpu_s")
            if status == "not run":
                continue
            out.append(
                {
                    "target": label,
                    "n": n,
                    "m": m,
                    "B": nb,
                    "dtype": dtype,
                    "threads": thr,
                    "ratio_peer_over_torchslq": ratio,
                    "cpu_time_ratio": cpu_ratio,
                    "target_ratio": target,
                    "met": (ratio >= target) if ratio is not None else None,
                    "status": status,
                }
            )
    return out


def _ms(r) -> str:
    if r is None:
        return "-"
    if r.get("time_s") is None:
        return r.get("status", "-")
    t = r["time_s"]
    s = f"{t * 1e3:.1f}" if t >= 0.01 else f"{t * 1e3:.2f}" if t >= 1e-3 else f"{t * 1e3:.3f}"
    return s + ("" if r.get("check_ok", True) else " (CHECK FAILED)")


def _x(a, b) -> str:
    if not a or not b or a.get("time_s") is None or b.get("time_s") is None:
        return "-"
    return f"{b['time_s'] / a['time_s']:.2f}x"


def markdown(payload) -> str:
    meta, recs, mem, peak = (
        payload["meta"],
        payload["results"],
        payload["memory"],
        payload["peak_gflops"],
    )
    L = []
    L.append("# LQ kernel benchmark (`benchmarks/lq_kernel.py`)\n")
    L.append(
        f"`{meta['command']}` at commit `{meta['git_commit']}` on {meta['date']}; "
        f"{meta['cpu']} ({meta['cpu_count']} cores), torch {meta['torch']}, numpy {meta['numpy']}, "
        f"mpc {meta.get('mpc')}. T={meta['T']}; best of up to {meta['repeat']} timed calls after a "
        f"warm-up (budget {meta['time_budget_s']} s per measurement; a warm-up longer than "
        f"{meta.get('single_above_s')} s is the only sample; a call under {SHORT_CALL * 1e3:g} ms is "
        f"timed as the mean of a loop of about {LOOP_TIME * 1e3:g} ms). Load average at start "
        f"{tuple(round(x, 2) for x in meta['loadavg_start'])}"
        + (
            f", at end {tuple(round(x, 2) for x in meta['loadavg_end'])}"
            if meta.get("loadavg_end")
            else ""
        )
        + " (a shared machine: other processes were competing for the cores).\n"
    )
    L.append(
        "Ratios are `peer time / torchslq time` (>1: torchslq faster). torchslq is timed with "
        "`validate=False`. NumPy is forward only and single-threaded in practice (per-matrix "
        "BLAS/LAPACK calls on tiny matrices); mpc.pytorch solves T+1 steps (no terminal cost "
        "otherwise, see the script docstring).\n"
    )
    for note in meta.get("notes", []):
        L.append(f"Note: {note}\n")
    L.append("## Headline targets\n")
    L.append(
        "| target | (n,m) | B | dtype | threads | ratio (wall) | goal | met | ratio (CPU time) |"
    )
    L.append("|---|---|---|---|---|---|---|---|---|")
    for h in payload["headline"]:
        ratio = (
            f"{h['ratio_peer_over_torchslq']:.2f}x"
            if h["ratio_peer_over_torchslq"]
            else h["status"]
        )
        goal = f">= {h['target_ratio']:.2f}x"
        met = {True: "yes", False: "**no**", None: "-"}[h["met"]]
        cr = f"{h['cpu_time_ratio']:.2f}x" if h.get("cpu_time_ratio") else "-"
        L.append(
            f"| {h['target']} | ({h['n']},{h['m']}) | {h['B']} | {h['dtype']} | {h['threads']} "
            f"| {ratio} | {goal} | {met} | {cr} |"
        )
    L.append(
        "\nRatio (wall): best `perf_counter` time; ratio (CPU time): best `process_time` of the "
        "same calls (CPU seconds of all threads; robust to other processes taking the cores, "
        "but at 2 threads it compares work, not latency). Goals: >= 10x / 5x over the NumPy "
        "loop at B=1024 for (4,1) / (12,4), >= 20x over mpc.pytorch for (12,4), and at B=1 "
        "no more than 3x slower than the NumPy loop.\n"
    )
    L.append("")
    L.append("## Peak (torch.mm 2048x2048, best of 5)\n")
    L.append("| dtype | threads | GFLOP/s (wall) | 1-core GFLOP/s from CPU time |")
    L.append("|---|---|---|---|")
    pc = payload.get("peak_gflops_per_core_cpu_time", {})
    for dt, d in peak.items():
        for thr, g in d.items():
            c = f"{pc[dt]:.1f}" if dt in pc else "-"
            L.append(f"| {dt} | {thr} | {g:.1f} | {c} |")
    L.append(
        "\nThe `% peak` column uses the wall-clock peak of the same dtype and thread count; the "
        "CPU-time rate shows what one core reaches when not preempted.\n"
    )
    L.append("## Times (ms per solve)\n")
    L.append(
        "| (n,m) | B | dtype | thr | torchslq fwd | torchslq fwd+bwd | NumPy fwd | mpc fwd "
        "| mpc fwd+bwd | NumPy/torchslq | mpc/torchslq fwd | mpc/torchslq fwd+bwd "
        "| torchslq GFLOP/s (% peak) | NumPy GFLOP/s | err u (torchslq, mpc) |"
    )
    L.append("|" + "---|" * 15)
    keys = []
    for r in recs:
        k = (r["n"], r["m"], r["B"], r["dtype"], r["threads"])
        if k not in keys:
            keys.append(k)
    for n, m, nb, dt, thr in keys:
        sel = {"n": n, "m": m, "B": nb, "dtype": dt, "threads": thr}
        tf = _find(recs, impl="torchslq", mode="fwd", **sel)
        tb = _find(recs, impl="torchslq", mode="fwdbwd", **sel)
        nf = _find(recs, impl="numpy", mode="fwd", **sel)
        mf = _find(recs, impl="mpc", mode="fwd", **sel)
        mb = _find(recs, impl="mpc", mode="fwdbwd", **sel)
        gf = "-"
        if tf and tf.get("gflops"):
            gf = f"{tf['gflops']:.2f}" + (
                f" ({100 * tf['peak_frac']:.1f}%)" if tf.get("peak_frac") else ""
            )
        ng = f"{nf['gflops']:.2f}" if nf and nf.get("gflops") else "-"
        errs = []
        for r in (tf, mf):
            errs.append(f"{r['rel_err_u']:.0e}" if r and r.get("rel_err_u") is not None else "-")
        L.append(
            f"| ({n},{m}) | {nb} | {dt} | {thr} | {_ms(tf)} | {_ms(tb)} | {_ms(nf)} | {_ms(mf)} "
            f"| {_ms(mb)} | {_x(tf, nf)} | {_x(tf, mf)} | {_x(tb, mb)} | {gf} | {ng} | {', '.join(errs)} |"
        )
    L.append("")
    grads = [r for r in recs if r["impl"] == "mpc" and r.get("grad_rel_err_x0") is not None]
    if grads:
        L.append("## Gradient check against mpc.pytorch (relative max abs difference)\n")
        L.append("| (n,m) | B | dtype | thr | d/dx0 | d/dA | d/dB |")
        L.append("|---|---|---|---|---|---|---|")
        for r in grads:
            L.append(
                f"| ({r['n']},{r['m']}) | {r['B']} | {r['dtype']} | {r['threads']} "
                f"| {r['grad_rel_err_x0']:.1e} | {r['grad_rel_err_A']:.1e} | {r['grad_rel_err_B']:.1e} |"
            )
        L.append("")
    comp = [r for r in recs if r["impl"] == "torchslq-compile"]
    if comp:
        L.append("## torch.compile (forward)\n")
        L.append("| (n,m) | B | dtype | thr | compile s | compiled ms | eager ms | status |")
        L.append("|---|---|---|---|---|---|---|---|")
        for r in comp:
            e = _find(
                recs,
                impl="torchslq",
                mode="fwd",
                n=r["n"],
                m=r["m"],
                B=r["B"],
                dtype=r["dtype"],
                threads=r["threads"],
            )
            cs = f"{r['compile_s']:.1f}" if r.get("compile_s") else "-"
            L.append(
                f"| ({r['n']},{r['m']}) | {r['B']} | {r['dtype']} | {r['threads']} | {cs} | {_ms(r)} "
                f"| {_ms(e)} | {r['status']} |"
            )
        L.append("")
    if mem:
        L.append("## Peak memory (extra resident MB during one call, fresh subprocess, 1 thread)\n")
        L.append(
            "| (n,m) | B | dtype | torchslq fwd | torchslq fwd+bwd | NumPy fwd | mpc fwd+bwd |"
        )
        L.append("|---|---|---|---|---|---|---|")
        mk = []
        for r in mem:
            k = (r["n"], r["m"], r["B"], r["dtype"])
            if k not in mk:
                mk.append(k)
        for n, m, nb, dt in mk:
            cells = []
            for impl, mode in (
                ("torchslq", "fwd"),
                ("torchslq", "fwdbwd"),
                ("numpy", "fwd"),
                ("mpc", "fwdbwd"),
            ):
                r = _find(mem, n=n, m=m, B=nb, dtype=dt, impl=impl, mode=mode)
                if r is None:
                    cells.append("-")
                elif "peak_mb" in r:
                    cells.append(f"{r['peak_mb']:.1f}")
                else:
                    cells.append(r.get("error", "?"))
            L.append(f"| ({n},{m}) | {nb} | {dt} | " + " | ".join(cells) + " |")
        methods = sorted({r["method"] for r in mem if "method" in r})
        L.append(f"\nMethod: {', '.join(methods)}.\n")
    skipped = [r for r in recs if str(r.get("status", "")).startswith("skipped")]
    if skipped:
        L.append("## Skipped\n")
        seen = set()
        for r in skipped:
            k = (r["impl"], r["n"], r["m"], r["B"], r["dtype"], r["threads"], r["status"])
            if k in seen:
                continue
            seen.add(k)
            est = f" (estimated {r['est_s']:.0f} s)" if isinstance(r.get("est_s"), float) else ""
            L.append(
                f"- {r['impl']} ({r['n']},{r['m']}) B={r['B']} {r['dtype']} threads={r['threads']}: "
                f"{r['status']}{est}"
            )
        L.append("")
    return "\n".join(L)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--quick", action="store_true", help="fast subset: 4x1,12x4; B 1,64; float64; 1 thread"
    )
    p.add_argument("--sizes", default="4x1,12x4,32x8", help="comma list of NxM")
    p.add_argument("--batches", default="1,64,1024,8192")
    p.add_argument("--dtypes", default="float64,float32")
    p.add_argument("--threads", default="1,2")
    p.add_argument(
        "--big-threads",
        default=None,
        help="thread counts for batches >= --big-batch (default: --threads), to save time",
    )
    p.add_argument("--big-batch", type=int, default=4096)
    p.add_argument("--T", type=int, default=100)
    p.add_argument(
        "--repeat", type=int, default=5, help="timed calls after the warm-up (best is kept)"
    )
    p.add_argument("--time-budget", type=float, default=20.0, help="seconds per measurement")
    p.add_argument(
        "--peer-limit",
        type=float,
        default=60.0,
        help="skip a peer (mpc.pytorch) whose single call is estimated above this (s)",
    )
    p.add_argument(
        "--single-above",
        type=float,
        default=10.0,
        help="if the warm-up call takes longer than this (s), it is the only sample",
    )
    p.add_argument("--max-mem-gb", type=float, default=20.0)
    p.add_argument("--no-mpc", action="store_true")
    p.add_argument("--no-numpy", action="store_true")
    p.add_argument("--no-memory", dest="memory", action="store_false")
    p.add_argument(
        "--memory-dtypes", default=None, help="dtypes to measure memory for (default: --dtypes)"
    )
    p.add_argument("--compile", action="store_true", help="also time torch.compile of the forward")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    p.add_argument("--name", default="lq_kernel", help="output file stem (e.g. lq_kernel.compile)")
    p.add_argument("--mem-child", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.mem_child:
        print("MEMRESULT " + json.dumps(mem_child(json.loads(args.mem_child))), flush=True)
        return
    if args.quick:
        args.sizes, args.batches, args.dtypes, args.threads = "4x1,12x4", "1,64", "float64", "1"
        args.repeat = min(args.repeat, 3)
    args.sizes = parse_sizes(args.sizes)
    args.batches = parse_ints(args.batches)
    args.dtypes = [d for d in args.dtypes.split(",") if d]
    args.threads = parse_ints(args.threads)
    args.big_threads = parse_ints(args.big_threads) if args.big_threads else None
    args.memory_dtypes = (
        args.dtypes if args.memory_dtypes is None else args.memory_dtypes.split(",")
    )
    for d in args.dtypes:
        if d not in DTYPES:
            p.error(f"unknown dtype {d}")
    Runner(args).run()


if __name__ == "__main__":
    main()
