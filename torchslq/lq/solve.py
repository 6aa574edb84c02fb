"""``lqr_solve``: the batched, differentiable LQ (Riccati) layer.

Solves, for every batch element independently::

    min  sum_{t<T} [ 1/2 x'Q_t x + 1/2 u'R_t u + u'S_t x + q_t'x + r_t'u ]
         + 1/2 x_T'Q_T x_T + q_T'x_T
    s.t. x_{t+1} = A_t x_t + B_t u_t + c_t,   x_0 = x0

Gradients (with respect to every tensor argument) come from implicit differentiation
of the KKT conditions (Amos et al. 2018, "Differentiable MPC", Section 4.2): the
backward pass is one more LQ solve with the same quadratic terms, so it reuses the
forward Cholesky factors and gains and only recomputes the linear terms. Memory is
``O(B T (n^2 + n m))``; nothing is unrolled.

Two backends solve the same problem with the same meaning (``method=``): the sequential
Riccati recursion (:mod:`.riccati`, compiled on the CPU) and the parallel-in-time
associative scan of Särkkä & García-Fernández (2023) (:mod:`.scan`), whose span is
``O(log T)`` instead of ``O(T)``; the backward pass runs on the backend of the forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from .._backend import (
    adjoint_compiled,
    can_use_compiled,
    compiled_available,
)
from .._backend.dispatch import (
    gain_addresses,
    lq_data_clean,
    lq_data_clean_at,
    lq_gain_gradients,
    lq_gain_pieces,
    lq_gain_solve,
    lq_gain_solve_at,
    plain_gain_pieces,
)
from .._shapes import broadcast_shapes
from ..status import Status
from .riccati import (
    chol_solve,
    homogeneous_cost,
    homogeneous_dynamics,
    riccati_homogeneous,
    rollout_homogeneous,
    with_time,
)
from .scan import lq_adjoint_scan, riccati_scan_homogeneous, rollout_scan_homogeneous

__all__ = ["LQRSolution", "choose_method", "lqr_solve"]

METHODS = ("sequential", "scan", "auto")


@dataclass
class LQRSolution:
    """Solution of a batch of LQ problems (leading batch dims as in the inputs).

    Attributes:
        x: optimal states ``(B, T+1, n)``; differentiable.
        u: optimal controls ``(B, T, m)``; differentiable.
        K: feedback gains ``(B, T, m, n)`` with ``u_t = K_t x_t + k_t``.
        k: feedforward ``(B, T, m)``.
        V: value-function Hessians ``(B, T+1, n, n)``.
        v: value-function gradients ``(B, T+1, n)``.
        lam: costates ``(B, T+1, n)``, ``lam_t = V_t x_t + v_t`` (the KKT multipliers of
            the dynamics; ``lam_0`` is the gradient of the optimal cost w.r.t. ``x0``).
        cost: optimal objective ``(B,)``; differentiable.
        status: ``(B,)`` int64 :class:`torchslq.Status` codes: ``CONVERGED`` (solved),
            ``NOT_POSITIVE_DEFINITE`` (some ``Quu`` was not PD: the problem is not
            strictly convex in u), ``NON_FINITE``.

    Only ``x``, ``u`` and ``cost`` carry gradients; the gains, value function and
    costates are returned detached.
    """

    x: Tensor
    u: Tensor
    K: Tensor
    k: Tensor
    V: Tensor
    v: Tensor
    lam: Tensor
    cost: Tensor
    status: Tensor


class _LQRFunction(torch.autograd.Function):
    """(F, H, VhT, x0) -> (x, u) with the implicit-KKT backward pass.

    Inputs have one flat batch dim, of size ``B`` or 1 (shared data, not copied); the
    backward pass sums the gradient of shared inputs over the batch, and autograd maps
    the gradients back through the ``cat`` that built ``F`` and ``H``.
    """

    @staticmethod
    def forward(ctx, F, H, VhT, x0, method="sequential"):  # noqa: D401
        scan = method == "scan"
        fac = (riccati_scan_homogeneous if scan else riccati_homogeneous)(F, H, VhT)
        nb = x0.shape[0]  # the data may all be shared (batch 1) while x0 is not
        Kk = fac.Kk.expand(nb, *fac.Kk.shape[1:])
        Vh = fac.Vh.expand(nb, *fac.Vh.shape[1:])
        chol = fac.chol.expand(nb, *fac.chol.shape[1:])
        failed = fac.failed.expand(nb)
        x, u = (rollout_scan_homogeneous if scan else rollout_homogeneous)(F, Kk, x0)
        ctx.method = method
        # an element whose solve failed (a Quu not positive definite, or non-finite
        # numbers) gets a zero gradient and must not poison the shared inputs' gradients
        bad = failed | ~torch.isfinite(x).flatten(1).all(1) | ~torch.isfinite(u).flatten(1).all(1)
        ctx.save_for_backward(F, Kk, Vh, chol, x, u, bad)
        ctx.H_like = torch.empty(H.shape[0], 0)  # only the batch size is needed
        ctx.VhT_like = torch.empty(VhT.shape[0], 0)
        ctx.mark_non_differentiable(Kk, Vh, chol, failed)
        return x, u, Kk, Vh, chol, failed

    @staticmethod
    @once_differentiable
    def backward(ctx, gx, gu, _gKk, _gVh, _gchol, _gfailed):
        F, Kk, Vh, chol, x, u, bad = ctx.saved_tensors
        T, m = u.shape[-2], u.shape[-1]
        n = x.shape[-1]
        if gx is None:
            gx = torch.zeros_like(x)
        if gu is None:
            gu = torch.zeros_like(u)
        if bool(bad.any()):
            F, Kk, Vh, chol, x, u, gx, gu = _neutral(bad, F, Kk, Vh, chol, x, u, gx, gu)
        adjoint = lq_adjoint_scan if ctx.method == "scan" else lq_adjoint_solve
        dx, du, dlam = adjoint(F, Kk, Vh, chol, gx, gu)
        lam = (Vh[..., :n, :] @ _homog(x).unsqueeze(-1))[..., 0]  # (B, T+1, n)
        one = x.new_ones(*x.shape[:-1], 1)
        z = torch.cat([u, x[..., :T, :], one[..., :T, :]], dim=-1)  # (B, T, m+n+1)
        dz = torch.cat([du, dx[..., :T, :], torch.zeros_like(one[..., :T, :])], dim=-1)
        gH = 0.5 * (dz.unsqueeze(-1) * z.unsqueeze(-2) + z.unsqueeze(-1) * dz.unsqueeze(-2))
        xhT = torch.cat([x[..., T, :], one[..., T, :]], dim=-1)
        dxhT = torch.cat([dx[..., T, :], torch.zeros_like(one[..., T, :])], dim=-1)
        gVhT = 0.5 * (
            dxhT.unsqueeze(-1) * xhT.unsqueeze(-2) + xhT.unsqueeze(-1) * dxhT.unsqueeze(-2)
        )
        zero_row = torch.zeros_like(one[..., 1:, :])
        lam_next = torch.cat([lam[..., 1:, :], zero_row], dim=-1)  # (B, T, n+1)
        dlam_next = torch.cat([dlam[..., 1:, :], zero_row], dim=-1)
        gF = dlam_next.unsqueeze(-1) * z.unsqueeze(-2) + lam_next.unsqueeze(-1) * dz.unsqueeze(-2)
        gx0 = dlam[..., 0, :]
        del m
        gF, gH = _sum_to(gF, F), _sum_to(gH, ctx.H_like)
        return gF, gH, _sum_to(gVhT, ctx.VhT_like), gx0, None


def _neutral(bad: Tensor, F, Kk, Vh, chol, x, u, gx, gu):
    """The backward pass's inputs with the failed elements ``bad (B,)`` replaced by a
    neutral problem (zero data and trajectory, identity Cholesky factors, zero incoming
    gradient): their adjoint solve is then zero, so they get a zero gradient and add
    nothing to the gradient of inputs shared by the batch."""

    def zero(t: Tensor) -> Tensor:
        if t.shape[0] != bad.shape[0]:  # shared by the batch: left as it is
            return t
        return torch.where(bad.view(-1, *([1] * (t.ndim - 1))), torch.zeros_like(t), t)

    eye = torch.eye(chol.shape[-1], dtype=chol.dtype, device=chol.device).expand_as(chol)
    chol = torch.where(bad.view(-1, 1, 1, 1), eye, chol)
    return (zero(F), zero(Kk), zero(Vh), chol, zero(x), zero(u), zero(gx), zero(gu))


def _flat_batch(t: Tensor, batch: torch.Size, nb: int, tail: int) -> Tensor:
    """One flat batch dim: size 1 for data shared by the whole batch (not copied B
    times; the backward pass sums its gradient), else ``nb``."""
    if t.shape[:-tail].numel() == 1:
        return t.reshape(1, *t.shape[-tail:])
    return t.expand(*batch, *t.shape[-tail:]).reshape(nb, *t.shape[-tail:])


def _sum_to(g: Tensor, like: Tensor) -> Tensor:
    return g.sum(0, keepdim=True) if like.shape[0] == 1 and g.shape[0] != 1 else g


def _homog(x: Tensor) -> Tensor:
    return torch.cat([x, x.new_ones(*x.shape[:-1], 1)], dim=-1)


assert int(Status.CONVERGED) == 0  # lq_status relies on it
_NON_FINITE = int(Status.NON_FINITE)


def _finite_status(f: np.ndarray) -> Tensor:
    """``CONVERGED`` where the numpy flags ``f`` are set, else ``NON_FINITE`` (all finite
    the common case: numpy's where costs microseconds)."""
    if f[0] if f.shape[0] == 1 else f.all():
        return torch.zeros(f.shape[0], dtype=torch.int64)
    return torch.from_numpy(np.where(f, 0, _NON_FINITE))


def lq_status(failed: Tensor | None, finite: Tensor) -> Tensor:
    """Per-element :class:`torchslq.Status` of an LQ solve from ``(B,)`` bool masks:
    ``NOT_POSITIVE_DEFINITE`` where ``failed`` (some ``Quu`` not PD; None: nowhere),
    else ``CONVERGED`` where ``finite``, else ``NON_FINITE``."""
    # CONVERGED is 0: one product instead of a where over two scalars (which allocates
    # both as tensors; it counts at B = 1), on the CPU on numpy's flags (cheaper still)
    if finite.is_cpu:
        status = _finite_status(finite.numpy())
    else:
        status = (~finite).long() * int(Status.NON_FINITE)
    return (
        status if failed is None else status.masked_fill(failed, int(Status.NOT_POSITIVE_DEFINITE))
    )


def _batch_shape(A, B, Q, R, x0, q, r, S, c) -> torch.Size:
    """The broadcast batch shape of :func:`lqr_solve`'s arguments (time dims given)."""
    if A.ndim == 4:  # the common case, one batch dim: compared without slicing shapes
        b = x0.shape[0] if x0.ndim == 2 else 1
        b = A.shape[0] if b == 1 else b
        if all(
            t is None or t.ndim == k + 1 and t.shape[0] in (1, b)
            for t, k in ((A, 3), (B, 3), (Q, 3), (R, 3), (x0, 1), (q, 2), (r, 2), (S, 3), (c, 2))
        ):
            return torch.Size((b,))
    return broadcast_shapes(
        A.shape[:-3], B.shape[:-3], Q.shape[:-3], R.shape[:-3], x0.shape[:-1],
        *(t.shape[:-2] for t in (q, r, c) if t is not None),
        *(() if S is None else (S.shape[:-3],)),
    )  # fmt: skip


def lq_adjoint_solve(
    F: Tensor, Kk: Tensor, Vh: Tensor, chol: Tensor, gx: Tensor, gu: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Second LQ solve of the implicit backward pass, reusing the forward factorisation.

    Solves the LQ problem with the forward problem's quadratic terms and dynamics
    matrices but linear cost terms ``q = gx``, ``r = gu``, ``c = 0`` and ``x0 = 0``
    (the KKT system with the incoming gradient as right-hand side). Only the linear
    value term is recomputed: ``qu = gu_t + B'v``, ``k = -Quu^{-1} qu`` (by the stored
    Cholesky factor) and ``v_t = gx_t + A'v + K'qu`` (since ``Qux = -Quu K``).

    Returns ``dx (B,T+1,n)``, ``du (B,T,m)`` and the costates ``dlam (B,T+1,n)``.
    """
    T, m = gu.shape[-2], gu.shape[-1]
    n = gx.shape[-1]
    if T > 0 and can_use_compiled(F, Kk, Vh, chol, gx, gu):
        return adjoint_compiled(F, Kk, Vh, chol, gx, gu)
    K = Kk[..., :n]
    v = gx[..., T, :].unsqueeze(-1)
    ks: list[Tensor] = [v] * T
    vs: list[Tensor] = [v] * (T + 1)
    for t in range(T - 1, -1, -1):
        BA = F[..., t, :n, : m + n]
        g = BA.mT @ v  # [B'v; A'v]
        qu = gu[..., t, :].unsqueeze(-1) + g[..., :m, :]
        k = -chol_solve(qu, chol[..., t, :, :])
        v = gx[..., t, :].unsqueeze(-1) + g[..., m:, :] + K[..., t, :, :].mT @ qu
        ks[t], vs[t] = k, v
    vs[T] = gx[..., T, :].unsqueeze(-1)
    v_all = torch.stack(vs, dim=-3)[..., 0]  # (B, T+1, n)
    # forward pass of the adjoint problem: zero initial state and no affine term c
    dxt = torch.zeros_like(gx[..., 0, :]).unsqueeze(-1)
    dxs, dus = [dxt], []
    for t in range(T):
        dut = K[..., t, :, :] @ dxt + ks[t]
        dxt = F[..., t, :n, : m + n] @ torch.cat([dut, dxt], dim=-2)
        dxs.append(dxt)
        dus.append(dut)
    dx = torch.stack(dxs, dim=-3)[..., 0]
    du = torch.stack(dus, dim=-3)[..., 0]
    dlam = (Vh[..., :n, :n] @ dx.unsqueeze(-1))[..., 0] + v_all
    return dx, du, dlam


def lq_objective(
    x: Tensor,
    u: Tensor,
    Q: Tensor,
    R: Tensor,
    q: Tensor | None = None,
    r: Tensor | None = None,
    S: Tensor | None = None,
) -> Tensor:
    """Value of the LQ objective of :func:`lqr_solve` at ``(x, u)``; shape ``(B,)``."""
    T = u.shape[-2]
    xs = x[..., :T, :]
    J = 0.5 * torch.einsum("...ti,...tij,...tj->...", xs, Q[..., :T, :, :], xs)
    J = J + 0.5 * torch.einsum("...ti,...tij,...tj->...", u, R, u)
    J = J + 0.5 * torch.einsum("...i,...ij,...j->...", x[..., T, :], Q[..., T, :, :], x[..., T, :])
    if S is not None:
        J = J + torch.einsum("...ti,...tij,...tj->...", u, S, xs)
    if q is not None:
        J = J + (q * x).sum((-1, -2))
    if r is not None:
        J = J + (r * u).sum((-1, -2))
    return J


# ----------------------------------------------------------------------------- validation


def _check_tensor(
    name: str, t: Tensor | None, min_ndim: int, tail: tuple[int, ...], time: int | None
):
    if t is None:
        if name in ("Q", "R", "x0"):
            raise TypeError(f"{name} must be a torch.Tensor, got None")
        return
    if not torch.is_tensor(t):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.ndim < min_ndim:
        raise ValueError(
            f"{name} must have shape (..., {', '.join(map(str, tail))}) with at least "
            f"{min_ndim} dims, got {tuple(t.shape)}"
        )
    if tuple(t.shape[-len(tail) :]) != tail:
        raise ValueError(
            f"{name} must end in shape {tail} (n = state dim, m = control dim), got {tuple(t.shape)}"
        )
    if time is not None and t.ndim >= len(tail) + 1:
        tt = t.shape[-len(tail) - 1]
        if tt not in (1, time):
            raise ValueError(
                f"{name} has {tt} time steps, expected {time} (or 1 to broadcast); shape {tuple(t.shape)}"
            )
    if not t.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {t.dtype}")


def _plain_arguments(A, B, Q, R, x0, q, r, S, c, T: int, n: int, m: int) -> bool:
    """Whether every argument is a tensor of the common call's shape (one batch dim and
    the time dim given: ``A (B|1, T, n, n)``, ``x0 (B, n)``, ...), in ``A``'s float
    dtype, on the CPU: what :func:`_check_tensor` and :func:`_check_common_dtype_device`
    pass, decided without their per-argument steps (at ``B = 1`` those cost as much as a
    small solve). False sends a call to them, for their messages."""
    dtype = A.dtype
    if dtype is not torch.float64 and dtype is not torch.float32:
        return False
    if not isinstance(x0, Tensor) or Q is None or R is None:
        return False
    if x0.shape[1:] != (n,) or x0.dtype != dtype or not x0.is_cpu:
        return False
    for t, shape in (
        (A, (T, n, n)), (B, (T, n, m)), (Q, (T + 1, n, n)), (R, (T, m, m)), (q, (T + 1, n)),
        (r, (T, m)), (S, (T, m, n)), (c, (T, n)),
    ):  # fmt: skip
        if t is None:
            continue
        if not isinstance(t, Tensor) or t.shape[1:] != shape or t.dtype != dtype or not t.is_cpu:
            return False
    return True


def _check_common_dtype_device(**args: Tensor | None) -> None:
    """Every given argument has ``A``'s dtype (float32 or float64) and device; TypeError /
    ValueError naming the first that differs (mixed precisions would fail or be promoted
    deep inside the kernels)."""
    A = args["A"]
    if A.dtype not in (torch.float32, torch.float64):
        raise TypeError(
            f"A has dtype {A.dtype}; lqr_solve needs float32 or float64 tensors (convert "
            "all arguments, e.g. .double())"
        )
    for name, t in args.items():
        if t is None:
            continue
        if t.dtype != A.dtype:
            raise TypeError(
                f"{name} has dtype {t.dtype} but A has {A.dtype}; all arguments of "
                "lqr_solve must have one dtype"
            )
        if t.device != A.device:
            raise ValueError(
                f"{name} is on device {t.device} but A is on {A.device}; all arguments of "
                "lqr_solve must be on one device"
            )


def _element_faults(name: str, fault: Tensor, batch: torch.Size, what: str) -> Tensor:
    """``fault`` (one flag per batch entry of argument ``name``, its batch dims only) as a
    mask over ``batch``.

    The granularity rule of :func:`lqr_solve`: a fault confined to some batch elements
    gives those elements a status and the batch goes on; a fault in data shared by the
    whole batch (no batch dims) is an error naming the argument."""
    if fault.numel() <= 1:
        if bool(fault.any()):
            raise ValueError(f"{name} {what} (in data shared by the whole batch)")
        return torch.zeros(batch, dtype=torch.bool, device=fault.device)
    return fault.expand(batch)


# Peak extra memory of the scan, in numbers per element per (n+1)^2: measured 15-23
# (n = 2, 4, 12, 32; float64 and float32; forward, and forward + backward) as resident
# memory on the CPU; a GPU allocates the same tensors (its caching allocator rounds them
# up). Every level's elements and the combinations' temporaries live at once; the
# sequential recursion needs a third of it or less.
SCAN_NUMBERS_PER_ELEMENT = 30


def scan_memory_bytes(T: int, batch: int, n: int, dtype: torch.dtype) -> int:
    """An upper estimate of the extra memory ``lqr_solve(method="scan")`` takes for
    ``batch`` problems of horizon ``T`` and ``n`` states: ``30 (n+1)^2`` numbers of
    ``dtype`` per element (``SCAN_NUMBERS_PER_ELEMENT``, from measurements)."""
    itemsize = torch.empty((), dtype=dtype).element_size()
    return SCAN_NUMBERS_PER_ELEMENT * (n + 1) ** 2 * itemsize * batch * T


def _device_bytes_free(device: torch.device) -> int | None:
    """Memory the allocator can still hand out on ``device`` (CUDA: the driver's free
    memory plus what PyTorch's caching allocator holds unused); None where unknown."""
    if device.type != "cuda" or not torch.cuda.is_available():
        return None
    free, _total = torch.cuda.mem_get_info(device)
    cached = torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)
    return int(free + cached)


def choose_method(
    T: int, batch: int, device: torch.device | str, dtype: torch.dtype, n: int | None = None
) -> str:
    """The backend ``lqr_solve(method="auto")`` runs: ``"scan"`` only where the benchmark
    (``benchmarks/parallel_lq.py``, ``benchmarks/results/parallel_lq.md``) measured it
    faster than the sequential kernel and, on a GPU, where it fits in memory; else
    ``"sequential"``.

    Args:
        T: horizon. batch: number of problems (the flat batch). device, dtype: the data's.
        n: the state dimension; given, a GPU runs the scan only where its estimated
            memory (:func:`scan_memory_bytes`) is at most half of what the device has
            free (``lqr_solve`` passes it; it also falls back to the sequential kernel
            if the scan runs out of memory all the same).

    Measured (``n = 4``, ``m = 2``, float64 and float32, forward):

    * 2-core CPU (``parallel_lq.md``): the compiled sequential kernel beats the scan
      everywhere (3-30x); the sequential recursion as torch ops (the CPU path without
      the compiled kernel) loses to the scan for a single problem (``batch == 1``) at
      T = 100, 1000 and 10000 (1.5-13x) and is as fast or faster from ``batch = 32`` on.
    * H100 (``parallel_lq_cuda.md``): the sequential pass is a chain of ``T`` small
      kernel launches whatever the batch (0.3-0.5 ms per step), the scan's time grows
      with ``batch * T``. The scan is faster at every measured T >= 100 up to
      ``batch = 1024`` (1.8-2.3x at T = 100, 2.4-154x from T = 1000; 40-61x at
      T = 4096, B <= 64) and about as fast at ``batch = 4096`` (0.66-1.32x). Rule:
      ``T >= 100`` and ``batch <= 2048`` (the crossover of the two trends lies between
      1024 and 4096), and the memory test above. These rows measured the scan as torch
      ops; with the fused kernels (:mod:`.scan_kernels`) it took 23 ms instead of 42 at
      T = 4096, batch 1 (``parallel_lq_cuda_fused.md``), and larger batches are not
      measured yet, so the rule stays.
    """
    dev = torch.device(device)
    if dev.type == "cpu" and dtype in (torch.float32, torch.float64) and not compiled_available():
        return "scan" if batch == 1 and T >= 100 else "sequential"
    if dev.type == "cuda" and T >= 100 and batch <= 2048:
        if n is not None:
            free = _device_bytes_free(dev)
            if free is not None and scan_memory_bytes(T, batch, n, dtype) > free // 2:
                return "sequential"
        return "scan"
    return "sequential"


def _input_faults(A, B, Q, R, x0, q, r, S, c, batch: torch.Size) -> tuple[Tensor, Tensor]:
    """``(nonfinite, not_pd)`` masks over ``batch``: elements with a NaN or infinity in
    their data, elements whose ``R`` is not positive definite (the rule is in
    :func:`_element_faults`)."""
    nonfinite = torch.zeros(batch, dtype=torch.bool, device=x0.device)
    core = {"A": 3, "B": 3, "Q": 3, "R": 3, "x0": 1, "q": 2, "r": 2, "S": 3, "c": 2}
    for name, t in zip(core, (A, B, Q, R, x0, q, r, S, c), strict=True):
        if t is not None:
            flags = ~torch.isfinite(t).flatten(t.ndim - core[name]).all(-1)
            nonfinite = nonfinite | _element_faults(name, flags, batch, "contains nan or inf")
    info = _cholesky_info(R).ne(0).any(-1)
    not_pd = _element_faults("R", info, batch, "must be symmetric positive definite")
    return nonfinite, not_pd & ~nonfinite


def _data_clean(A, B, Q, R, x0, q, r, S, c) -> bool:
    """Whether :func:`_input_faults` would find nothing, in a few ops and one host sync:
    every argument's sum is finite (NaN and infinities propagate into a sum, so a finite
    sum means finite entries; finite data whose sum overflows only send the caller to the
    exact check) and every ``R`` is positive definite (the same factorisation as there).
    The per-element check costs more than a small solve (about 130 us at (4, 1), B = 1:
    a mask per argument, broadcast over the batch)."""
    total = sum(t.sum() for t in (A, B, Q, R, x0, q, r, S, c) if t is not None)
    return bool(torch.isfinite(total) & (_cholesky_info(R) == 0).all())


def _cholesky_info(R: Tensor) -> Tensor:
    """``cholesky_ex``'s ``info`` for the symmetric part of every ``R`` (NaN made finite,
    so that a non-finite ``R`` reports what its finite entries give)."""
    return torch.linalg.cholesky_ex(torch.nan_to_num(0.5 * (R + R.mT))).info


def _overflowed(F: Tensor, H: Tensor, Vh: Tensor, m: int) -> Tensor:
    """``(B,)``: elements whose backward recursion overflowed (finite data, but a
    non-finite ``Quu`` at the first failing step) rather than met a ``Quu`` that is not
    positive definite. ``Quu_t`` is recomputed from the returned ``V_{t+1}``, which is
    exact up to the first failure (from the end)."""
    M = H + F.mT @ Vh[..., 1:, :, :] @ F  # (B, T, m+n+1, m+n+1); F, H may be shared
    Quu = M[..., :m, :m]
    finite = torch.isfinite(Quu).flatten(-2).all(-1)
    info = torch.linalg.cholesky_ex(torch.nan_to_num(0.5 * (Quu + Quu.mT))).info
    fails = ~finite | (info != 0)  # (B, T)
    T = fails.shape[-1]
    steps = torch.arange(T, device=fails.device)
    last = torch.where(fails, steps, -1).amax(-1)  # the first failing step from the end
    at = (~finite).gather(-1, last.clamp_min(0).unsqueeze(-1)).squeeze(-1)
    return at & (last >= 0)


def _with_input_faults(status: Tensor, nonfinite: Tensor, not_pd: Tensor) -> Tensor:
    status = status.masked_fill(not_pd, int(Status.NOT_POSITIVE_DEFINITE))
    return status.masked_fill(nonfinite, int(Status.NON_FINITE))


class _GainLQRFunction(torch.autograd.Function):
    """(A, B, Q, R, x0, q, r, S, c) -> (x, u, cost) on the gain-form CPU kernels,
    solved before the call (``sol`` of :func:`lq_gain_solve`, every element's
    factorisation succeeded); the backward pass is the implicit-KKT one of
    :class:`_LQRFunction` written on the data directly (:func:`lq_gain_gradients`): one
    vector recursion with the forward factors and the outer products, no homogeneous
    matrices; the optimal cost's gradient by the envelope theorem."""

    @staticmethod
    def forward(ctx, pieces, sol, batch, A, B, Q, R, x0, q, r, S, c):  # noqa: D401
        data = (A, B, Q, R, x0, q, r, S, c)
        ctx.pieces, ctx.batch = pieces, batch
        ctx.factors = {key: sol[key] for key in ("Kk", "L", "P", "lam", "finite")}
        ctx.shapes = [None if t is None else t.shape for t in data]
        batch = tuple(batch)
        x = torch.from_numpy(sol["x"].reshape(batch + sol["x"].shape[1:]))
        u = torch.from_numpy(sol["u"].reshape(batch + sol["u"].shape[1:]))
        cost = torch.from_numpy(sol["cost"].reshape(batch))
        # the inputs are saved so that autograd reports an in-place change before the
        # backward pass (the kernels read them through ``pieces``)
        ctx.save_for_backward(x, u, *(t for t in data if t is not None))
        return x, u, cost

    @staticmethod
    @once_differentiable
    def backward(ctx, gx, gu, gJ):
        x, u = ctx.saved_tensors[:2]
        nb = max(math.prod(ctx.batch), 1)
        x, u = x.detach().reshape(nb, *x.shape[-2:]), u.detach().reshape(nb, *u.shape[-2:])
        gx = torch.zeros_like(x) if gx is None else gx.reshape(nb, *x.shape[-2:])
        gu = torch.zeros_like(u) if gu is None else gu.reshape(nb, *u.shape[-2:])
        gJ = x.new_zeros(nb) if gJ is None else gJ.reshape(nb)
        # (x and u from the saved tensors: an in-place change of the outputs is
        # reported by autograd, not differentiated through)
        sol = dict(ctx.factors, x=x.numpy(), u=u.numpy())
        needs = tuple(ctx.needs_input_grad[3:])
        grads = lq_gain_gradients(ctx.pieces, sol, sol["finite"], gx, gu, gJ, needs)
        out = []
        for g, shape in zip(grads, ctx.shapes, strict=True):
            if g is not None and g.shape != shape:  # (two tensor ops a gradient, at B = 1 too)
                g = g.reshape(tuple(ctx.batch) + tuple(g.shape[1:])).sum_to_size(shape)
            out.append(g)
        return (None, None, None, *out)


def _gain_inputs(A, B, Q, R, x0, q, r, S, c, batch: torch.Size) -> tuple | None:
    """The data of :func:`lqr_solve` (time dims expanded, ``batch`` their broadcast
    batch shape) as the gain-form CPU kernels' arrays: ``(pieces, data_batch, x0)`` of
    :func:`lq_gain_pieces` and ``x0 (prod(batch), n)``; None where those kernels do not
    apply (not on the CPU, a ``torch.func`` transform)."""
    present = [t for t in (A, B, Q, R, x0, q, r, S, c) if t is not None]
    if not x0.is_cpu or not can_use_compiled(*present, differentiable=True):
        return None
    n = A.shape[-1]
    nb = max(math.prod(batch), 1)
    pieces, data_batch = lq_gain_pieces((A, B, c, Q, R, S, q, r), batch)
    x0d = x0.detach() if x0.requires_grad else x0
    if x0.ndim == 2 and x0.shape[0] == nb and x0.is_contiguous():
        return pieces, data_batch, x0d.numpy()
    return pieces, data_batch, x0d.expand(*batch, n).reshape(nb, n).contiguous().numpy()


def _any_requires_grad(tensors: tuple) -> bool:
    for t in tensors:
        if t is not None and t.requires_grad:
            return True
    return False


def _solve_gain(A, B, Q, R, x0, q, r, S, c, batch: torch.Size, inputs: tuple) -> LQRSolution | None:
    """:func:`lqr_solve` on the gain-form CPU kernels (:func:`lq_gain_solve`), with or
    without autograd (:class:`_GainLQRFunction`); the arguments as given, time dims
    expanded, ``inputs`` the kernels' arrays of them (:func:`_gain_inputs`). For
    ``method`` ``"sequential"`` or ``"auto"``, which is the sequential kernel here
    (:func:`choose_method`'s rule on the CPU with the compiled kernels). None where an
    element's factorisation failed: the homogeneous path then classifies the failures.

    (Written for a small solve's overhead: at ``(n, m) = (4, 1)``, ``B = 1``, ``T = 100``
    the kernel takes about 10 us, and every tensor op here about one: the outputs are
    numpy arrays, sliced and reshaped by numpy, each made a tensor once.)"""
    pieces, data_batch, x0n = inputs
    sol = lq_gain_solve(pieces, data_batch, x0n, A.shape[-3])
    graph = None
    if torch.is_grad_enabled() and _any_requires_grad((A, B, Q, R, x0, q, r, S, c)):
        graph = (pieces, (A, B, Q, R, x0, q, r, S, c))
    return _gain_solution(sol, batch, data_batch, A.shape[-1], graph)


def _gain_solution(
    sol: dict, batch: torch.Size, data_batch: int, n: int, graph: tuple | None = None
) -> LQRSolution | None:
    """The :class:`LQRSolution` of the gain-form kernels' arrays ``sol``
    (:func:`lq_gain_solve`) for the batch shape ``batch``, the data's own batch
    ``data_batch`` (1 or ``prod(batch)``); ``graph``: ``(pieces, data)`` where ``x, u,
    cost`` are to carry gradients to the data (:class:`_GainLQRFunction`). None where an
    element's factorisation failed."""
    nb = max(math.prod(batch), 1)
    failed = sol["failed"]
    if failed[0] if data_batch == 1 else failed.any():
        return None

    shape = tuple(batch)
    t = torch.from_numpy

    def full(a: np.ndarray) -> Tensor:  # (1 or nb, ...) -> (*batch, ...)
        if a.shape[0] != nb:  # shared data: one value function for the batch, expanded
            e = t(a).expand(nb, *a.shape[1:])
            return e if len(shape) == 1 else e.reshape(shape + a.shape[1:])
        return t(a if len(shape) == 1 else a.reshape(shape + a.shape[1:]))

    status = _finite_status(sol["finite"])  # (lq_status's rule, on numpy's flags)
    if len(shape) != 1:  # (unbatched, or several batch dims)
        status = status.reshape(shape)
    if len(shape) == 1 and data_batch == nb:  # (the common case: no reshape, no expand)
        full = t
    if graph is not None:
        x, u, cost = _GainLQRFunction.apply(graph[0], sol, batch, *graph[1])
    else:
        x, u, cost = full(sol["x"]), full(sol["u"]), full(sol["cost"])
    Kk = sol["Kk"]
    return LQRSolution(
        x=x, u=u, K=full(Kk[..., :n]), k=full(Kk[..., n]), V=full(sol["P"]), v=full(sol["p"]),
        lam=full(sol["lam"]), cost=cost, status=status,
    )  # fmt: skip


def lqr_solve(
    A: Tensor,
    B: Tensor,
    Q: Tensor,
    R: Tensor,
    x0: Tensor,
    q: Tensor | None = None,
    r: Tensor | None = None,
    S: Tensor | None = None,
    c: Tensor | None = None,
    *,
    validate: bool = True,
    method: str = "auto",
) -> LQRSolution:
    """Solve a batch of finite-horizon LQ problems (module docstring gives the problem).

    Args:
        A: ``(B, T, n, n)`` state matrices; ``T`` is read from here.
        B: ``(B, T, n, m)`` input matrices.
        Q: ``(B, T+1, n, n)`` state weights, index ``T`` is the terminal weight; a
            ``(n, n)`` matrix means the same weight at every step.
        R: ``(B, T, m, m)`` (or ``(m, m)``) control weights; must be positive definite.
        x0: ``(B, n)`` initial states.
        q: ``(B, T+1, n)`` linear state terms. r: ``(B, T, m)`` linear control terms.
        S: ``(B, T, m, n)`` cross terms (cost ``u'S x``). c: ``(B, T, n)`` affine dynamics.
        validate: check shapes, finiteness and ``R > 0`` (one host sync each); solvers
            calling this in an inner loop pass ``False``. A NaN/infinity or an ``R``
            that is not positive definite in one element's data gives that element the
            status ``non_finite`` / ``not_positive_definite`` (a NaN cost and solution,
            a zero gradient; the others are solved as without it); in data shared by the
            whole batch it is a ``ValueError`` naming the argument.
        method: the backend, the same results either way (up to rounding):
            ``"sequential"`` the Riccati recursion, ``T`` dependent steps (on the CPU
            one compiled loop); ``"scan"`` the parallel-in-time associative scan
            (:mod:`torchslq.lq.scan`; Särkkä & García-Fernández 2023), ``O(log T)``
            levels of batched ops, its backward pass by scans too (an element whose
            scan fails is redone by the recursion, so the statuses are the same); on a
            GPU with Triton and ``n, m <= 4`` its per-element work runs in fused kernels
            (:mod:`torchslq.lq.scan_kernels`), compiled on first use (seconds, then
            cached on disk by Triton);
            ``"auto"`` (default) picks ``"scan"`` only where it measured faster
            (:func:`choose_method`: on a CUDA GPU for ``T >= 100`` and batches up to
            2048 where it fits in half the free memory; on the CPU, with the compiled
            kernel, never), else ``"sequential"``, which it also falls back to when the
            scan runs out of memory (``docs/scale.md``).

    All leading (batch) dims broadcast together, and a time dim of 1 broadcasts over
    time; a fully unbatched problem (``A (T,n,n)``, ``x0 (n,)``) returns unbatched
    results. Weights enter through their symmetric parts.

    Returns:
        :class:`LQRSolution`. ``x``, ``u`` and ``cost`` are differentiable w.r.t. every
        tensor argument (implicit differentiation, one extra LQ solve).
    """
    if validate:
        if not torch.is_tensor(A) or A.ndim < 3:
            raise ValueError(f"A must have shape (B, T, n, n), got {getattr(A, 'shape', type(A))}")
    T, n = A.shape[-3], A.shape[-1]
    if validate:
        if not torch.is_tensor(B) or B.ndim < 2:
            raise ValueError(f"B must have shape (B, T, n, m), got {getattr(B, 'shape', type(B))}")
        m = B.shape[-1]
        if T == 0 or not _plain_arguments(A, B, Q, R, x0, q, r, S, c, T, n, m):
            _check_tensor("A", A, 3, (n, n), None)
            _check_tensor("B", B, 3, (n, m), T)
            _check_tensor("Q", Q, 2, (n, n), T + 1)
            _check_tensor("R", R, 2, (m, m), T)
            _check_tensor("x0", x0, 1, (n,), None)
            _check_tensor("q", q, 1, (n,), T + 1)
            _check_tensor("r", r, 1, (m,), T)
            _check_tensor("S", S, 2, (m, n), T)
            _check_tensor("c", c, 1, (n,), T)
            if T == 0:
                raise ValueError("A has a horizon of T = 0 steps; need T >= 1")
            _check_common_dtype_device(A=A, B=B, Q=Q, R=R, x0=x0, q=q, r=r, S=S, c=c)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    m = B.shape[-1]
    gain_failed = False  # the gain-form kernels ran on clean data and an element failed
    if method != "scan":
        # the common small call (no graph, the data as given): the kernels read the
        # tensors at their addresses (numpy views of nine tensors cost more than a small
        # solve); None where it does not apply, or a fault or failure is to be classified
        at = gain_addresses((A, B, c, Q, R, S, q, r), x0, T, n, m)
        if at is not None and (not validate or lq_data_clean_at(at)):
            sol = _gain_solution(lq_gain_solve_at(at, T), torch.Size((x0.shape[0],)), at[2], n)
            if sol is not None:
                return sol
            # the homogeneous path below classifies the failure; the data are clean
            gain_failed, validate = True, False
    Q = with_time(Q, 2, T + 1)
    R = with_time(R, 2, T)
    R_given = R  # before a not-PD element's R is made NaN (below)
    q = with_time(q, 1, T + 1)
    r = with_time(r, 1, T)
    S = with_time(S, 2, T)
    c = with_time(c, 1, T)

    # on the CPU: the gain-form kernels' arrays of the data (None where they do not apply)
    # (the common call's in one pass: plain_gain_pieces)
    gain_inputs = (
        None if method == "scan" or gain_failed else plain_gain_pieces((A, B, c, Q, R, S, q, r), x0)
    )
    if gain_inputs is not None:
        batch = torch.Size((x0.shape[0],))
    if validate:
        if gain_inputs is None:
            try:
                batch = _batch_shape(A, B, Q, R, x0, q, r, S, c)
            except RuntimeError as err:
                msg = f"batch dimensions of the arguments do not broadcast: {err}"
                raise ValueError(msg) from err
            if method != "scan":
                gain_inputs = _gain_inputs(A, B, Q, R, x0, q, r, S, c, batch)
        if gain_inputs is not None:  # the same check, compiled, on the kernels' arrays
            faulty = not lq_data_clean(gain_inputs[0], gain_inputs[2])
        else:
            faulty = not _data_clean(A, B, Q, R, x0, q, r, S, c)
        if faulty:  # which elements, or an error naming the argument
            nonfinite, not_pd = _input_faults(A, B, Q, R, x0, q, r, S, c, batch)
            # an element with an R that is not positive definite is not solved (NaN data
            # make its factorisation fail: no solution, a zero gradient)
            if bool(not_pd.any()):
                R = torch.where(not_pd.reshape(*not_pd.shape, 1, 1, 1), float("nan"), R)
            faulty = bool((nonfinite | not_pd).any())
        # below, validate means: some element's data have a fault (its status says which)
        validate = faulty
    if method != "scan" and not validate and not gain_failed:
        # on the CPU: the gain-form kernels straight from the data, with or without a
        # graph (None where they do not apply, or an element failed: the homogeneous
        # path below then classifies the failures)
        if gain_inputs is None:
            batch = _batch_shape(A, B, Q, R, x0, q, r, S, c)
            gain_inputs = _gain_inputs(A, B, Q, R, x0, q, r, S, c, batch)
        if gain_inputs is not None:
            sol = _solve_gain(A, B, Q, R, x0, q, r, S, c, batch, gain_inputs)
            if sol is not None:
                return sol
    F = homogeneous_dynamics(A, B, c)
    H, VhT = homogeneous_cost(Q, R, q, r, S)
    batch = broadcast_shapes(F.shape[:-3], H.shape[:-3], VhT.shape[:-2], x0.shape[:-1])
    # one flat batch dim for the kernel
    nb = int(torch.Size(batch).numel())
    Ff = _flat_batch(F, batch, nb, 3)
    Hf = _flat_batch(H, batch, nb, 3)
    VhTf = _flat_batch(VhT, batch, nb, 2)
    x0f = x0.expand(*batch, n).reshape(nb, n)
    chosen = method == "auto"
    if chosen:
        method = choose_method(T, nb, x0.device, x0.dtype, n)
    try:
        x, u, Kk, Vh, _chol, failed = _LQRFunction.apply(Ff, Hf, VhTf, x0f, method)
    except torch.OutOfMemoryError:
        if not (chosen and method == "scan"):
            raise
        # the scan keeps every level in memory (scan_memory_bytes); the recursion needs
        # a third of it or less, so "auto" still solves what fits the device
        if x0.device.type == "cuda":
            torch.cuda.empty_cache()
        method = "sequential"
        x, u, Kk, Vh, _chol, failed = _LQRFunction.apply(Ff, Hf, VhTf, x0f, method)

    finite = torch.isfinite(x).flatten(1).all(1) & torch.isfinite(u).flatten(1).all(1)
    status = lq_status(failed, finite)
    if bool(failed.any()):  # finite data whose recursion overflowed: non_finite
        over = failed & _overflowed(Ff, Hf, Vh, m)
        status = status.masked_fill(over, int(Status.NON_FINITE))
    lam = (Vh[..., :n, :] @ _homog(x).unsqueeze(-1))[..., 0]

    def unflat(t: Tensor) -> Tensor:
        return t.reshape(tuple(batch) + tuple(t.shape[1:]))

    x, u = unflat(x), unflat(u)
    # a failed element's cost is NaN; its NaN trajectory is kept out of the objective's
    # graph, where 0 * NaN would reach the gradients of weights shared by the batch
    ok = unflat(finite & ~failed)
    okx, oku = ok.reshape(*ok.shape, 1, 1), ok.reshape(*ok.shape, 1, 1)
    cost = lq_objective(
        torch.where(okx, x, 0.0), torch.where(oku, u, 0.0), Q, R_given, q, r, S
    ).masked_fill(~ok, float("nan"))
    return LQRSolution(
        x=x,
        u=u,
        K=unflat(Kk[..., :n]),
        k=unflat(Kk[..., n]),
        V=unflat(Vh[..., :n, :n]),
        v=unflat(Vh[..., :n, n]),
        lam=unflat(lam),
        cost=cost,
        status=_with_input_faults(unflat(status), nonfinite, not_pd)
        if validate
        else unflat(status),
    )
