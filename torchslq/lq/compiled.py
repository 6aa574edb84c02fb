"""The Riccati pass as one compiled CPU kernel (numba), for the CPU fast path.

:func:`torchslq.lq.riccati_homogeneous` runs its time loop as a handful of batched torch
ops per step. On the CPU with small matrices (``n, m`` up to a few tens) those ops are
dispatch-bound: each costs a few microseconds whatever the batch, and the two LAPACK
calls per step loop over the batch's tiny matrices one by one. This module runs the same
recursion (same equations, same outputs) as a single numba-compiled loop over batch and
time, with the matrices of one step in registers/L1. Measured 2-3x faster per pass on
the benchmark shapes (``benchmarks/compiled_riccati.py``).

Used automatically by :func:`riccati_homogeneous` when

* numba is importable and not disabled (``TORCHSLQ_COMPILED=0`` in the environment or
  :func:`set_compiled` ``(False)``),
* the tensors are on the CPU, float32 or float64, and nothing needs autograd (no input
  requires grad while grad mode is on, and no ``torch.func`` transform is active),
* there are no control bounds, and the stage hook is None or carries its second-order
  terms as a dense tensor (``stage_hook.hessians``, DDP's precomputed output Hessians).

Everything else (GPU, autograd through the pass, box QPs, callable hooks) takes the torch
path. ``tests/test_compiled_riccati.py`` checks the two against each other.

The kernel is compiled on first use per dtype (about 1-2 s) and cached on disk by numba.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor

import torch
from torch import Tensor

try:  # numba is a dependency, but the torch path keeps working without it
    import numba
    import numpy as np
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

__all__ = [
    "adjoint_compiled",
    "can_use_compiled",
    "compiled_available",
    "riccati_compiled",
    "rollout_compiled",
    "set_compiled",
]

_enabled = os.environ.get("TORCHSLQ_COMPILED", "1").strip().lower() not in ("0", "false", "no")


def compiled_available() -> bool:
    """Whether the compiled CPU Riccati kernel is importable and enabled."""
    return numba is not None and _enabled


def set_compiled(enabled: bool) -> bool:
    """Enable or disable the compiled CPU kernel (process-wide); returns the old value.

    Disabling it makes every Riccati pass take the torch path (e.g. to compare the two).
    """
    global _enabled
    old = _enabled
    _enabled = bool(enabled)
    return old


def can_use_compiled(*tensors: Tensor) -> bool:
    """Whether the compiled path applies to a pass over ``tensors`` (see module docs)."""
    if not compiled_available():
        return False
    dtype = tensors[0].dtype
    if dtype not in (torch.float32, torch.float64):
        return False
    grad = torch.is_grad_enabled()
    for t in tensors:
        if t.device.type != "cpu" or t.dtype != dtype or (grad and t.requires_grad):
            return False
    # inside torch.func transforms tensors are wrappers without storage for numpy
    return torch._C._functorch.peek_interpreter_stack() is None


if numba is not None:

    @numba.njit(cache=True, nogil=True)
    def _riccati_kernel(
        b0, b1, F, H, VhT, reg, Hz, short_form, Kk, Vh, L, failed
    ):  # pragma: no cover - jit
        """One Riccati pass per element (see riccati_homogeneous for the equations).

        F ``(BF, T, n+1, m+n+1)``, H ``(BH, T, m+n+1, m+n+1)``, VhT ``(BV, n+1, n+1)``
        (each batch 1 or B), reg ``(BR,)`` (1 or B), Hz ``(T, n, B, m+n, m+n)`` or an
        empty array; ``short_form``: the value update ``M_zz + M_uz'Kk`` (no reg, as
        the torch path) instead of the general form; outputs Kk ``(B, T, m, n+1)``, Vh ``(B, T+1, n+1, n+1)``,
        L ``(B, T, m, m)``, failed ``(B,)``. An element whose ``Quu + reg I`` is not
        positive definite (or not finite) at some step is marked failed and its earlier
        steps are left at zero (the torch path's values there are meaningless too).
        Only elements ``b0 <= b < b1`` are computed (see :func:`_launch`).
        """
        T = Kk.shape[1]
        m = Kk.shape[2]
        n1 = Kk.shape[3]
        n = n1 - 1
        mn1 = m + n1
        use_hz = Hz.shape[0] > 0
        VF = np.empty((n1, mn1), dtype=Vh.dtype)
        M = np.empty((mn1, mn1), dtype=Vh.dtype)
        Lb = np.zeros((m, m), dtype=Vh.dtype)
        for b in range(b0, b1):
            bf = b if F.shape[0] > 1 else 0
            bh = b if H.shape[0] > 1 else 0
            bv = b if VhT.shape[0] > 1 else 0
            r = reg[b if reg.shape[0] > 1 else 0]
            for i in range(n1):
                for j in range(n1):
                    Vh[b, T, i, j] = VhT[bv, i, j]
            ok = True
            for t in range(T - 1, -1, -1):
                # 2-d views of this step's matrices (cheaper indexing than 4-d)
                Vn = Vh[b, t + 1]
                Vc = Vh[b, t]
                Ft = F[bf, t]
                Ht = H[bh, t]
                Kt = Kk[b, t]
                # M = H_t + F_t' Vh_{t+1} F_t (symmetric: upper triangle, mirrored)
                for i in range(n1):
                    for j in range(mn1):
                        s = 0.0
                        for k in range(n1):
                            s += Vn[i, k] * Ft[k, j]
                        VF[i, j] = s
                for i in range(mn1):
                    for j in range(i, mn1):
                        s = Ht[i, j]
                        for k in range(n1):
                            s += Ft[k, i] * VF[k, j]
                        M[i, j] = s
                        M[j, i] = s
                if use_hz:  # DDP: + v_{t+1} . f_zz on the [u; x] block
                    for k in range(n):
                        v = Vn[k, n]
                        Hk = Hz[t, k, b]
                        for i in range(mn1 - 1):
                            for j in range(mn1 - 1):
                                M[i, j] += v * Hk[i, j]
                # Cholesky of Quu + reg I
                for j in range(m):
                    s = M[j, j] + r
                    for k in range(j):
                        s -= Lb[j, k] * Lb[j, k]
                    if not (s > 0.0):  # also catches NaN
                        ok = False
                        break
                    d = math.sqrt(s)
                    Lb[j, j] = d
                    for i in range(j + 1, m):
                        s2 = M[i, j]
                        for k in range(j):
                            s2 -= Lb[i, k] * Lb[j, k]
                        Lb[i, j] = s2 / d
                if not ok:
                    break
                Lt = L[b, t]
                for i in range(m):
                    for j in range(i + 1):
                        Lt[i, j] = Lb[i, j]
                # [K_t, k_t] = -(L L')^{-1} M[:m, m:]
                for c in range(n1):
                    for i in range(m):
                        s = -M[i, m + c]
                        for k in range(i):
                            s -= Lb[i, k] * Kt[k, c]
                        Kt[i, c] = s / Lb[i, i]
                    for i in range(m - 1, -1, -1):
                        s = Kt[i, c]
                        for k in range(i + 1, m):
                            s -= Lb[k, i] * Kt[k, c]
                        Kt[i, c] = s / Lb[i, i]
                if short_form:  # Vh_t = M_zz + M_uz'Kk, symmetrised
                    for i in range(n1):
                        for j in range(i, n1):
                            s = M[m + i, m + j]
                            s2 = M[m + j, m + i]
                            for p in range(m):
                                s += M[p, m + i] * Kt[p, j]
                                s2 += M[p, m + j] * Kt[p, i]
                            Vc[i, j] = 0.5 * (s + s2)
                            Vc[j, i] = 0.5 * (s + s2)
                    continue
                # Vh_t = M_zz + Kk'Quu Kk + Kk'M_uz + M_uz'Kk (Tassa et al. 2012's form,
                # exact for any gains, hence also with reg)
                for i in range(n1):
                    for j in range(i, n1):
                        s = M[m + i, m + j]
                        for p in range(m):
                            kpi = Kt[p, i]
                            s += kpi * M[p, m + j] + Kt[p, j] * M[p, m + i]
                            acc = 0.0
                            for q in range(m):
                                acc += M[p, q] * Kt[q, j]
                            s += kpi * acc
                        Vc[i, j] = s
                        Vc[j, i] = s
            failed[b] = not ok

    @numba.njit(cache=True, nogil=True)
    def _rollout_kernel(b0, b1, F, Kk, x0, x, u):  # pragma: no cover - jit
        """``u_t = Kk_t [x_t; 1]``, ``x_{t+1} = F_t[:n] [u_t; x_t; 1]`` per element.

        F ``(BF, T, n+1, m+n+1)``, Kk ``(BK, T, m, n+1)``, x0 ``(BX, n)`` (batches 1 or
        B); outputs x ``(B, T+1, n)``, u ``(B, T, m)``.
        """
        T, m = u.shape[1], u.shape[2]
        n = x.shape[2]
        for b in range(b0, b1):
            bf = b if F.shape[0] > 1 else 0
            bk = b if Kk.shape[0] > 1 else 0
            bx = b if x0.shape[0] > 1 else 0
            for i in range(n):
                x[b, 0, i] = x0[bx, i]
            for t in range(T):
                Ft = F[bf, t]
                Kt = Kk[bk, t]
                xt = x[b, t]
                ut = u[b, t]
                for i in range(m):
                    s = Kt[i, n]
                    for j in range(n):
                        s += Kt[i, j] * xt[j]
                    ut[i] = s
                xn = x[b, t + 1]
                for i in range(n):
                    s = Ft[i, m + n]
                    for j in range(m):
                        s += Ft[i, j] * ut[j]
                    for j in range(n):
                        s += Ft[i, m + j] * xt[j]
                    xn[i] = s

    @numba.njit(cache=True, nogil=True)
    def _adjoint_kernel(b0, b1, F, Kk, Vh, L, gx, gu, dx, du, dlam):  # pragma: no cover - jit
        """The adjoint LQ solve of :func:`torchslq.lq.lq_adjoint_solve` per element.

        F ``(., T, n+1, m+n+1)``, Kk ``(., T, m, n+1)``, Vh ``(., T+1, n+1, n+1)``,
        L ``(., T, m, m)``, gx ``(., T+1, n)``, gu ``(., T, m)`` (each batch 1 or B);
        outputs dx ``(B, T+1, n)``, du ``(B, T, m)``,
        dlam ``(B, T+1, n)`` (dlam holds the linear value terms ``v_t`` until the end).
        """
        T, m = du.shape[1], du.shape[2]
        n = dx.shape[2]
        qu = np.empty(m, dtype=dx.dtype)
        for b in range(b0, b1):
            bf = b if F.shape[0] > 1 else 0
            bk = b if Kk.shape[0] > 1 else 0
            bg = b if gx.shape[0] > 1 else 0
            bgu = b if gu.shape[0] > 1 else 0
            bv = b if Vh.shape[0] > 1 else 0
            bl = b if L.shape[0] > 1 else 0
            v = dlam[b]
            for i in range(n):
                v[T, i] = gx[bg, T, i]
            for t in range(T - 1, -1, -1):
                Ft = F[bf, t]
                Lt = L[bl, t]
                Kt = Kk[bk, t]
                # qu = gu_t + B'v_{t+1};  k_t = -(L L')^{-1} qu (stored in du)
                for i in range(m):
                    s = gu[bgu, t, i]
                    for j in range(n):
                        s += Ft[j, i] * v[t + 1, j]
                    qu[i] = s
                kt = du[b, t]
                for i in range(m):
                    s = -qu[i]
                    for j in range(i):
                        s -= Lt[i, j] * kt[j]
                    kt[i] = s / Lt[i, i]
                for i in range(m - 1, -1, -1):
                    s = kt[i]
                    for j in range(i + 1, m):
                        s -= Lt[j, i] * kt[j]
                    kt[i] = s / Lt[i, i]
                # v_t = gx_t + A'v_{t+1} + K'qu
                for i in range(n):
                    s = gx[bg, t, i]
                    for j in range(n):
                        s += Ft[j, m + i] * v[t + 1, j]
                    for j in range(m):
                        s += Kt[j, i] * qu[j]
                    v[t, i] = s
            # forward: dx_0 = 0, du_t = K_t dx_t + k_t, dx_{t+1} = [B A] [du_t; dx_t]
            for i in range(n):
                dx[b, 0, i] = 0.0
            for t in range(T):
                Ft = F[bf, t]
                Kt = Kk[bk, t]
                xt = dx[b, t]
                ut = du[b, t]
                for i in range(m):
                    s = ut[i]
                    for j in range(n):
                        s += Kt[i, j] * xt[j]
                    ut[i] = s
                xn = dx[b, t + 1]
                for i in range(n):
                    s = 0.0
                    for j in range(m):
                        s += Ft[i, j] * ut[j]
                    for j in range(n):
                        s += Ft[i, m + j] * xt[j]
                    xn[i] = s
            # dlam_t = V_t dx_t + v_t
            for t in range(T + 1):
                Vt = Vh[bv, t]
                for i in range(n):
                    s = v[t, i]
                    for j in range(n):
                        s += Vt[i, j] * dx[b, t, j]
                    v[t, i] = s


# Below this many element-steps per thread a pass is not split (thread hand-off costs
# tens of microseconds).
MIN_STEPS_PER_THREAD = 4096
_pool: ThreadPoolExecutor | None = None
_pool_size = 0


def _launch(kernel, nb: int, T: int, *args) -> None:
    """Run ``kernel(b0, b1, *args)`` over the batch ``[0, nb)``, split into contiguous
    chunks over ``torch.get_num_threads()`` threads when the pass is large enough.

    The kernels release the GIL and each element is independent, so the chunks run in
    parallel in a plain thread pool, like the torch path's intra-op threads (numba's own
    ``parallel=True`` threading layers were avoided: the default one aborts on
    concurrent launches from several Python threads).
    """
    global _pool, _pool_size
    threads = max(1, min(torch.get_num_threads(), nb, (nb * max(T, 1)) // MIN_STEPS_PER_THREAD))
    if threads == 1:
        kernel(0, nb, *args)
        return
    if _pool is None or _pool_size != threads:
        if _pool is not None:
            _pool.shutdown(wait=False)
        _pool, _pool_size = ThreadPoolExecutor(threads, thread_name_prefix="torchslq"), threads
    bounds = [nb * i // threads for i in range(threads + 1)]
    futures = [_pool.submit(kernel, bounds[i], bounds[i + 1], *args) for i in range(1, threads)]
    kernel(bounds[0], bounds[1], *args)  # the calling thread takes the first chunk
    for f in futures:
        f.result()


def _flat(t: Tensor, batch: torch.Size, tail: int) -> np.ndarray:
    """``t (..., *tail dims)`` as a contiguous ``(1 or prod(batch), *tail)`` array."""
    lead = t.shape[: t.ndim - tail]
    if math.prod(lead) == 1:
        t = t.reshape(1, *t.shape[t.ndim - tail :])
    else:
        t = t.expand(*batch, *t.shape[t.ndim - tail :]).reshape(-1, *t.shape[t.ndim - tail :])
    return t.detach().contiguous().numpy()


def riccati_compiled(
    F: Tensor,
    H: Tensor,
    VhT: Tensor,
    reg: Tensor | float | None,
    hessians: Tensor | None,
    batch: torch.Size,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The unconstrained Riccati pass of :func:`riccati_homogeneous` on the CPU kernel.

    Args as for :func:`riccati_homogeneous` (``F (..., T, n+1, m+n+1)``,
    ``H (..., T, m+n+1, m+n+1)``, ``VhT (..., n+1, n+1)``, ``reg`` scalar or batch-shaped),
    ``hessians``: None or ``(T, n, prod(batch), m+n, m+n)``, the dynamics' output Hessians
    in ``[u; x]`` order (added to ``M`` contracted with ``v_{t+1}``); ``batch``: the
    broadcast batch shape. Call only where :func:`can_use_compiled` holds.

    Returns:
        ``Kk (*batch, T, m, n+1)``, ``Vh (*batch, T+1, n+1, n+1)``, ``chol (*batch, T, m, m)``,
        ``failed (*batch,)``.
    """
    T, n1, mn1 = F.shape[-3], F.shape[-2], F.shape[-1]
    m = mn1 - n1
    dtype = F.dtype
    nb = math.prod(batch)
    if reg is None:
        reg_t = torch.zeros(1, dtype=dtype)
    else:
        reg_t = torch.as_tensor(reg, dtype=dtype)
        reg_t = reg_t.reshape(1) if reg_t.numel() == 1 else reg_t.expand(batch).reshape(-1)
    Kk = torch.zeros(nb, T, m, n1, dtype=dtype)
    Vh = torch.zeros(nb, T + 1, n1, n1, dtype=dtype)
    L = torch.zeros(nb, T, m, m, dtype=dtype)
    failed = torch.zeros(nb, dtype=torch.bool)
    Hz = (
        np.zeros((0, 1, 1, 1, 1), dtype=Vh.numpy().dtype)
        if hessians is None
        else hessians.detach().contiguous().numpy()
    )
    _launch(
        _riccati_kernel,
        nb,
        T,
        _flat(F, batch, 3),
        _flat(H, batch, 3),
        _flat(VhT, batch, 2),
        reg_t.detach().contiguous().numpy(),
        Hz,
        reg is None,
        Kk.numpy(),
        Vh.numpy(),
        L.numpy(),
        failed.numpy(),
    )
    return (
        Kk.reshape(*batch, T, m, n1),
        Vh.reshape(*batch, T + 1, n1, n1),
        L.reshape(*batch, T, m, m),
        failed.reshape(batch),
    )


def rollout_compiled(F: Tensor, Kk: Tensor, x0: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`torchslq.lq.rollout_homogeneous` on the CPU kernel (same shapes); call
    only where :func:`can_use_compiled` holds."""
    T, n1 = F.shape[-3], F.shape[-2]
    m = Kk.shape[-2]
    n = n1 - 1
    batch = torch.broadcast_shapes(F.shape[:-3], Kk.shape[:-3], x0.shape[:-1])
    nb = math.prod(batch)
    x = torch.empty(nb, T + 1, n, dtype=F.dtype)
    u = torch.empty(nb, T, m, dtype=F.dtype)
    _launch(
        _rollout_kernel,
        nb,
        T,
        _flat(F, batch, 3),
        _flat(Kk, batch, 3),
        _flat(x0, batch, 1),
        x.numpy(),
        u.numpy(),
    )
    return x.reshape(*batch, T + 1, n), u.reshape(*batch, T, m)


def adjoint_compiled(
    F: Tensor, Kk: Tensor, Vh: Tensor, chol: Tensor, gx: Tensor, gu: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`torchslq.lq.lq_adjoint_solve` on the CPU kernel (same shapes and outputs);
    call only where :func:`can_use_compiled` holds."""
    T, m = gu.shape[-2], gu.shape[-1]
    n = gx.shape[-1]
    batch = torch.broadcast_shapes(
        F.shape[:-3], Kk.shape[:-3], Vh.shape[:-3], chol.shape[:-3], gx.shape[:-2], gu.shape[:-2]
    )
    nb = math.prod(batch)
    dx = torch.empty(nb, T + 1, n, dtype=F.dtype)
    du = torch.empty(nb, T, m, dtype=F.dtype)
    dlam = torch.empty(nb, T + 1, n, dtype=F.dtype)
    _launch(
        _adjoint_kernel,
        nb,
        T,
        _flat(F, batch, 3),
        _flat(Kk, batch, 3),
        _flat(Vh, batch, 3),
        _flat(chol, batch, 3),
        _flat(gx, batch, 2),
        _flat(gu, batch, 2),
        dx.numpy(),
        du.numpy(),
        dlam.numpy(),
    )
    return (
        dx.reshape(*batch, T + 1, n),
        du.reshape(*batch, T, m),
        dlam.reshape(*batch, T + 1, n),
    )
