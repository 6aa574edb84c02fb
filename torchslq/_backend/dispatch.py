"""The compiled CPU backend's dispatch layer: the Riccati pass (and the other dispatch-bound
loops) as compiled numba kernels, for the CPU fast path.

:func:`torchslq.lq.riccati_homogeneous` runs its time loop as a handful of batched torch
ops per step. On the CPU with small matrices (``n, m`` up to a few tens) those ops are
dispatch-bound: each costs a few microseconds whatever the batch, and the two LAPACK
calls per step loop over the batch's tiny matrices one by one. This module runs the same
recursion (same equations, same outputs) as a single numba-compiled loop over batch and
time, with the matrices of one step in registers/L1: 1.5-2.3x faster per pass at
B = 64-1024 and 16-18x at B = 1 (``benchmarks/compiled_riccati.py``, one run).

Used automatically by :func:`riccati_homogeneous` when

* numba is importable and not disabled (``TORCHSLQ_COMPILED=0`` in the environment or
  :func:`set_compiled` ``(False)``),
* the tensors are on the CPU, float32 or float64, and nothing needs autograd (no input
  requires grad while grad mode is on, and no ``torch.func`` transform is active) and
  no ``torch.compile`` tracing is under way,
* the stage hook is None or carries its second-order terms as a dense tensor
  (``stage_hook.hessians``, DDP's precomputed output Hessians).

With control bounds the control-limited pass (a box QP per step, the projected Newton of
:func:`torchslq.lq.box_qp` ported step for step) runs compiled too. Everything else (GPU,
autograd through the pass, callable hooks) takes the torch path.
``tests/test_compiled_riccati.py`` checks the two against each other.

The same module runs a few other dispatch-bound loops of the solvers on the CPU, under
the same conditions and each checked against its torch form in the tests: the feedback
step of closed-loop rollouts (:func:`closed_loop_feedback_compiled`), the costate
recursion (:func:`costate_compiled`), one RK4 stage's congruence of the chained second
derivatives (:func:`stage_congruence_compiled`), and the Riccati kernel's own restarts
of failed elements with a larger regularisation (``restarts``; the torch path of
:func:`torchslq.lq.riccati_backward` makes the same restarts, with the same result).

The kernels live in :mod:`torchslq._backend._numba_kernels`, imported on the first CPU pass
(never by GPU-only use). numba compiles each on first use per dtype and argument layout
and caches the machine code on disk (seconds, once); a new process then pays about
0.5 s to import numba and load it, on its first CPU pass.
"""

from __future__ import annotations

import importlib.util
import math
import os
import warnings
from concurrent.futures import ThreadPoolExecutor
from types import ModuleType

import numpy as np
import torch
from torch import Tensor

from .._shapes import broadcast_shapes
from . import gain_codegen, specialisation
from .gain_codegen import gain_kernels
from .model_fns import function_value, rollout_kernel, rows_step

__all__ = [
    "armijo_rollout_compiled",
    "PIECE_NDIMS",
    "adjoint_compiled",
    "closed_loop_feedback_compiled",
    "closed_loop_rollout_compiled",
    "costate_compiled",
    "can_use_compiled",
    "compiled_available",
    "riccati_compiled",
    "rollout_compiled",
    "set_compiled",
    "stage_congruence_compiled",
]

_enabled = os.environ.get("TORCHSLQ_COMPILED", "1").strip().lower() not in ("0", "false", "no")


_HAVE_NUMBA = importlib.util.find_spec("numba") is not None
_kernels_module: ModuleType | None = None
_kernels_error: str | None = None  # why the kernels could not be loaded, once tried


def compiled_available() -> bool:
    """Whether the compiled CPU kernels are installed (numba), enabled and loadable."""
    return _HAVE_NUMBA and _enabled and _kernels_error is None


def _import_kernels() -> ModuleType:
    from . import _numba_kernels

    return _numba_kernels


def _kernels() -> ModuleType | None:
    """The numba kernels, imported on first use (see :mod:`torchslq._backend._numba_kernels`);
    None (with one warning, and the torch path from then on) if that fails, e.g. when
    numba can neither write nor find a cache directory or its version does not match
    the installed numpy."""
    global _kernels_module, _kernels_error
    if _kernels_module is None and _kernels_error is None:
        try:
            _kernels_module = _import_kernels()
        except Exception as err:  # noqa: BLE001 - any failure means: use the torch path
            _kernels_error = f"{type(err).__name__}: {err}"
            warnings.warn(
                "torchslq: the compiled CPU LQ kernels could not be loaded, using the torch "
                f"path ({_kernels_error})",
                RuntimeWarning,
                stacklevel=3,
            )
    return _kernels_module


def set_compiled(enabled: bool) -> bool:
    """Enable or disable the compiled CPU kernel (process-wide); returns the old value.

    Disabling it makes every Riccati pass take the torch path (e.g. to compare the two).
    """
    global _enabled
    old = _enabled
    _enabled = bool(enabled)
    return old


def can_use_compiled(*tensors: Tensor, differentiable: bool = False) -> bool:
    """Whether the compiled path applies to a pass over ``tensors`` (see module docs);
    ``differentiable``: the caller wraps the pass in its own autograd function, so
    tensors that require grad do not rule it out."""
    if not compiled_available():
        return False
    dtype = tensors[0].dtype
    if dtype not in (torch.float32, torch.float64):
        return False
    grad = torch.is_grad_enabled() and not differentiable
    for t in tensors:  # (is_cpu: t.device.type builds a device object, 6x the cost)
        if not t.is_cpu or t.dtype != dtype or (grad and t.requires_grad):
            return False
    return _kernels_apply_here()


def _kernels_apply_here() -> bool:
    """Whether the compiled kernels can be called in the current context and are
    loadable: inside torch.func transforms tensors are wrappers without storage for
    numpy, and under torch.compile tracing they are fake (the torch path is what gets
    traced)."""
    if torch.compiler.is_compiling():
        return False
    if torch._C._functorch.peek_interpreter_stack() is not None:
        return False
    return _kernels() is not None


def module_needs_grad(module) -> bool:
    """Whether autograd is recording and a parameter or buffer of ``module`` (an
    ``nn.Module``; anything else: False) requires grad: a model's compiled functions,
    which take its parameters as numbers, would then cut the graph. (A tensor given as
    a model parameter may be a buffer that requires grad.)"""
    if not torch.is_grad_enabled() or not isinstance(module, torch.nn.Module):
        return False
    return any(t.requires_grad for t in (*module.parameters(), *module.buffers()))


# Below this many element-steps per thread a pass is not split (thread hand-off costs
# tens of microseconds).
MIN_STEPS_PER_THREAD = 4096
# From this many rows (or elements of a line search) a model's step on many rows at once
# (model_fns.register_rows) runs instead of its one-row step: below it the matrix
# products' calls cost more than they save (the fused search on the 5-64-64-4 residual
# cart-pole: 0.45 against 0.36 ms at 4 elements, even at 12, 1.34x faster at 64).
MIN_BLOCK_ROWS = 12


def _on_rows(step, rows: int):
    """The model's step on many rows at once (``model_fns.register_rows``) for a pass
    over ``rows`` rows (or elements), None below :data:`MIN_BLOCK_ROWS` or where the
    model has none: its one-row step then serves."""
    return rows_step(step) if rows >= MIN_BLOCK_ROWS else None


def _pass_kernel(
    kernel_name: str, rows_kernel_name: str, step, x_dtype, p_dtype, rows: int, size: int, module
) -> tuple:
    """``(kernel, function values)`` for a pass over ``rows`` rows (or line-search
    elements), ``size`` row-steps in all: ``module``'s ``rows_kernel_name`` with the
    model's step on many rows at once where :func:`_on_rows` gives one, else
    :func:`~.model_fns.rollout_kernel`'s ``kernel_name``."""
    rows_fn = _on_rows(step, rows)
    if rows_fn is None:
        return rollout_kernel(kernel_name, step, x_dtype, p_dtype, size, module)
    return getattr(module, rows_kernel_name), (function_value(rows_fn, "rows", x_dtype, p_dtype),)


_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_pid = 0  # a forked child inherits the pool object but not its threads


def _threads(nb: int, T: int) -> int:
    """How many threads :func:`_launch` splits a pass over ``nb`` elements of ``T``
    steps into."""
    return max(1, min(torch.get_num_threads(), nb, (nb * max(T, 1)) // MIN_STEPS_PER_THREAD))


def _one_launch(nb: int, T: int) -> bool:
    """Whether a gain-form solve over ``nb`` elements of ``T`` steps is one launch on the
    calling thread (too small to split over threads, or one thread)."""
    return nb * T < 2 * MIN_STEPS_PER_THREAD or _threads(nb, T) == 1


def _launch(kernel, nb: int, T: int, *args) -> None:
    """Run ``kernel(b0, b1, *args)`` over the batch ``[0, nb)``, split into contiguous
    chunks over ``torch.get_num_threads()`` threads when the pass is large enough.

    The kernels release the GIL and each element is independent, so the chunks run in
    parallel in a plain thread pool, like the torch path's intra-op threads (numba's own
    ``parallel=True`` threading layers were avoided: the default one aborts on
    concurrent launches from several Python threads).
    """
    global _pool, _pool_size, _pool_pid
    threads = _threads(nb, T)
    if threads == 1:
        kernel(0, nb, *args)
        return
    if _pool is None or _pool_size != threads or _pool_pid != os.getpid():
        if _pool is not None and _pool_pid == os.getpid():
            _pool.shutdown(wait=False)
        _pool = ThreadPoolExecutor(threads, thread_name_prefix="torchslq")
        _pool_size, _pool_pid = threads, os.getpid()
    bounds = [nb * i // threads for i in range(threads + 1)]
    futures = [_pool.submit(kernel, bounds[i], bounds[i + 1], *args) for i in range(1, threads)]
    kernel(bounds[0], bounds[1], *args)  # the calling thread takes the first chunk
    for f in futures:
        f.result()


def _np(t: Tensor) -> np.ndarray:
    """``t``'s data as a numpy array (a view where ``t`` is contiguous) without
    autograd's ``detach`` op where ``t`` needs no gradient: each is a dispatch of about
    a microsecond, and the launchers pass a dozen tensors per call."""
    if t.requires_grad:
        t = t.detach()
    return (t if t.is_contiguous() else t.contiguous()).numpy()


def _flat(t: Tensor, batch: torch.Size, tail: int) -> np.ndarray:
    """``t (..., *tail dims)`` as a contiguous ``(1 or prod(batch), *tail)`` array."""
    if t.ndim == tail + 1 and (t.shape[0] in (1, math.prod(batch))) and t.is_contiguous():
        return _np(t)  # already one flat batch dim
    lead = t.shape[: t.ndim - tail]
    if math.prod(lead) == 1:
        t = t.reshape(1, *t.shape[t.ndim - tail :])
    else:
        t = t.expand(*batch, *t.shape[t.ndim - tail :]).reshape(-1, *t.shape[t.ndim - tail :])
    return _np(t)


# array ndims of the kernel's ``pieces`` (A, B, c, Q, R, S, q, r), batch and time dims included
PIECE_NDIMS = (4, 4, 3, 4, 4, 4, 3, 3)


def riccati_compiled(
    F: Tensor | None,
    H: Tensor | None,
    VhT: Tensor | None,
    reg: Tensor | float | None,
    hessians: Tensor | None,
    batch: torch.Size,
    bounds: tuple[Tensor, Tensor] | None = None,
    box_tol: float = 0.0,
    pieces: tuple[Tensor | None, ...] | None = None,
    restarts: tuple[Tensor, Tensor, Tensor, tuple[float, float, float, int]] | None = None,
) -> tuple:
    """The Riccati pass of :func:`riccati_homogeneous` on the CPU kernel.

    Args as for :func:`riccati_homogeneous` (``F (..., T, n+1, m+n+1)``,
    ``H (..., T, m+n+1, m+n+1)``, ``VhT (..., n+1, n+1)``, ``reg`` scalar or batch-shaped),
    ``hessians``: None or ``(T, n, prod(batch), m+n, m+n)``, the dynamics' output Hessians
    in ``[u; x]`` order (added to ``M`` contracted with ``v_{t+1}``), or the same as the
    blocks ``(Hxx, Huu, Hux)``, each ``(n, prod(batch), T, ., .)``; ``batch``: the
    broadcast batch shape; ``bounds``: None, or ``(lower, upper)`` ``(..., T, m)`` on the
    step for the control-limited pass (box QP tolerance ``box_tol (1 + |qu|_inf)``).
    ``pieces``: instead of ``F, H, VhT`` (then None), the LQ data of
    :func:`riccati_backward` ``(A, B, c, Q, R, S, q, r)``, each with a time dim of 1 or
    ``T`` (``T + 1`` for ``Q, q``) and ``c, S, q, r`` possibly None: the kernel assembles
    each step's homogeneous matrices itself, so they are never materialised.
    ``restarts``: None, or ``(mu, delta, allowed, (factor, floor, mu_max, max_restarts))``
    with ``(*batch,)`` tensors: each element starts with ``reg = mu`` and repeats its
    pass with a larger one after a failure (see the kernel's docstring); ``reg`` is then
    ignored. Call only where :func:`can_use_compiled` holds.

    Returns:
        ``Kk (*batch, T, m, n+1)``, ``Vh (*batch, T+1, n+1, n+1)``, ``chol (*batch, T, m, m)``,
        ``failed (*batch,)``, with bounds ``clamped (*batch, T, m)``, ``dV (*batch, 2)``
        (else None, None), and with restarts the final ``mu``, ``delta`` ``(*batch,)``
        (else None, None).
    """
    dtype = F.dtype if pieces is None else pieces[0].dtype
    npd = _np_dtype(dtype)
    if pieces is None:
        T, n1, mn1 = F.shape[-3], F.shape[-2], F.shape[-1]
        arrays = (_flat(F, batch, 3), _flat(H, batch, 3), _flat(VhT, batch, 2))
        piece_arrays = tuple(np.zeros((0,) * d, dtype=npd) for d in PIECE_NDIMS)
    else:
        A, Bm = pieces[0], pieces[1]
        T, n1 = A.shape[-3], A.shape[-1] + 1
        mn1 = n1 + Bm.shape[-1]
        arrays = (
            np.zeros((0, 1, 1, 1), npd),
            np.zeros((0, 1, 1, 1), npd),
            np.zeros((0, 1, 1), npd),
        )
        piece_arrays = _piece_arrays(pieces, batch, dtype)
    m = mn1 - n1
    nb = math.prod(batch)
    # outputs allocated by numpy and shared with torch (cheaper than torch.zeros, which
    # counts at B = 1); zero: a failed element's steps below its failure stay zero
    Kk = torch.from_numpy(np.zeros((nb, T, m, n1), npd))
    Vh = torch.from_numpy(np.zeros((nb, T + 1, n1, n1), npd))
    L = torch.from_numpy(np.zeros((nb, T, m, m), npd))
    failed = torch.from_numpy(np.zeros(nb, np.bool_))
    boxed = bounds is not None
    clamped = torch.from_numpy(np.zeros((nb if boxed else 0, T, m), np.bool_))
    dV = torch.from_numpy(np.zeros((nb if boxed else 0, 2), npd))
    if boxed:
        lower, upper = (_flat(t, batch, 2) for t in bounds)
    else:
        lower = upper = np.zeros((0, 1, 1), dtype=npd)
    if restarts is None:
        mu = delta = None
        restart_arrays = (
            np.zeros(4, dtype=np.float64),
            np.zeros(0, npd),
            np.zeros(0, npd),
            np.zeros(0, np.bool_),
        )
    else:
        # the kernel updates them in place: copies (by numpy, a fraction of torch's cost)
        mu_a, delta_a = (_np(_batch_vector(t, batch, nb)).astype(npd) for t in restarts[:2])
        mu, delta = torch.from_numpy(mu_a), torch.from_numpy(delta_a)
        allowed = _np(_batch_vector(restarts[2], batch, nb))
        opts = np.array(restarts[3], dtype=np.float64)
        restart_arrays = (opts, mu_a, delta_a, allowed)
        reg = mu
    from ._numba_gemm import with_slp

    witness = _kernels().size_witness(n1 - 1, m)
    small = _kernels().small_size(n1 - 1, m)
    if pieces is not None and not boxed and small and (hessians is None or npd == np.float64):
        # the unconstrained pass of a small problem (iLQR's, DDP's with its Hessians): in
        # gain form, its sizes fixed when compiled (riccati_gain_reg_kernel), into the
        # blocks of Vh. (DDP's pass in float32 keeps the homogeneous kernel: in gain form
        # a float32 cart-pole DDP stalled at a gradient of 1.8e-3 instead of 1.7e-4.)
        # (LLVM's SLP switch for its register-blocked products, when first compiled)
        reg_a = restart_arrays[1] if restarts is not None else _reg_array(reg, batch, dtype)
        outs = (Kk.numpy(), Vh.numpy(), L.numpy(), failed.numpy())
        args = (
            piece_arrays, reg_a, *_hessian_arrays(hessians, dtype), *outs,
            *restart_arrays[1:], restart_arrays[0], *witness,
        )  # fmt: skip
        generated = gain_kernels(n1 - 1, m) if hessians is None else None
        if generated is None:
            with_slp(_launch, _gain_kernels().riccati_gain_reg_kernel, nb, T, *args)
        else:
            # the element pass written out for (n, m) (gain_codegen): its first try;
            # an element that fails it runs again on the element kernel, restarts and
            # all, from a fresh pass's zeros
            mu_io = restart_arrays[1]
            _launch(generated.riccati_gain_reg_first, nb, T, piece_arrays, reg_a, *outs, mu_io)
            for b in np.flatnonzero(outs[3]).tolist():
                Kk[b], Vh[b], L[b] = 0.0, 0.0, 0.0
                with_slp(_gain_kernels().riccati_gain_reg_kernel, b, b + 1, *args)
    else:
        with_slp(
            _riccati_homogeneous_launch, arrays, reg, batch, dtype, hessians, boxed, lower,
            upper, box_tol, Kk, Vh, L, clamped, failed, dV, piece_arrays, restart_arrays,
        )  # fmt: skip
    if len(batch) == 1:  # (the outputs have that shape: no views to make)
        return (Kk, Vh, L, failed, clamped if boxed else None, dV if boxed else None, mu, delta)
    return (
        Kk.reshape(*batch, T, m, n1),
        Vh.reshape(*batch, T + 1, n1, n1),
        L.reshape(*batch, T, m, m),
        failed.reshape(batch),
        clamped.reshape(*batch, T, m) if boxed else None,
        dV.reshape(*batch, 2) if boxed else None,
        None if mu is None else mu.reshape(batch),
        None if delta is None else delta.reshape(batch),
    )


def _batch_vector(t: Tensor, batch: torch.Size, nb: int) -> Tensor:
    """``t`` (broadcastable to ``batch``) as a ``(nb,)`` tensor, detached; itself where
    it is one already (each view is a dispatch: this runs at every solver iteration)."""
    if t.requires_grad:
        t = t.detach()
    if t.shape != (nb,):
        t = (t if t.shape == batch else t.expand(batch)).reshape(nb)
    return t


def _riccati_homogeneous_launch(
    arrays, reg, batch, dtype, hessians, boxed, lower, upper, box_tol, Kk, Vh, L, clamped,
    failed, dV, piece_arrays, restart_arrays,
) -> None:  # fmt: skip
    """:func:`riccati_compiled`'s launch of the homogeneous kernel (``riccati_kernel``)."""
    _launch(
        _kernels().riccati_kernel, Kk.shape[0], Kk.shape[1], *arrays,
        _reg_array(reg, batch, dtype), *_hessian_arrays(hessians, dtype),
        reg is None and not boxed, lower, upper, float(box_tol), _box_opts(), Kk.numpy(),
        Vh.numpy(), L.numpy(), clamped.numpy(), failed.numpy(), dV.numpy(), piece_arrays,
        *restart_arrays,
    )  # fmt: skip


def rollout_compiled(F: Tensor, Kk: Tensor, x0: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`torchslq.lq.rollout_homogeneous` on the CPU kernel (same shapes); call
    only where :func:`can_use_compiled` holds."""
    T, n1 = F.shape[-3], F.shape[-2]
    m = Kk.shape[-2]
    n = n1 - 1
    batch = broadcast_shapes(F.shape[:-3], Kk.shape[:-3], x0.shape[:-1])
    nb = math.prod(batch)
    x = torch.empty(nb, T + 1, n, dtype=F.dtype)
    u = torch.empty(nb, T, m, dtype=F.dtype)
    _launch(
        _kernels().rollout_kernel,
        nb,
        T,
        _flat(F, batch, 3),
        _flat(Kk, batch, 3),
        _flat(x0, batch, 1),
        x.numpy(),
        u.numpy(),
    )
    return x.reshape(*batch, T + 1, n), u.reshape(*batch, T, m)


def lq_rollout_compiled(
    A: Tensor, B: Tensor, c: Tensor | None, Kk: Tensor, x0: Tensor
) -> tuple[Tensor, Tensor]:
    """The LQ rollout ``u_t = K_t x_t + k_t``, ``x_{t+1} = A_t x_t + B_t u_t + c_t`` on
    the CPU kernel from the data (``A (..., T, n, n)``, ``B (..., T, n, m)``, ``c (...,
    T, n)`` or None, each with a time dim of ``T``; ``Kk (..., T, m, n+1)``, ``x0 (...,
    n)``). Returns ``x (*batch, T+1, n)``, ``u (*batch, T, m)``; call only where
    :func:`can_use_compiled` holds."""
    T, m, n = Kk.shape[-3], Kk.shape[-2], x0.shape[-1]
    shapes = [A.shape[:-3], B.shape[:-3], Kk.shape[:-3], x0.shape[:-1]]
    if c is not None:
        shapes.append(c.shape[:-2])
    batch = broadcast_shapes(*shapes)
    nb = math.prod(batch)
    x = torch.empty(nb, T + 1, n, dtype=x0.dtype)
    u = torch.empty(nb, T, m, dtype=x0.dtype)
    cn = np.zeros((0, 1, n), dtype=x.numpy().dtype) if c is None else _flat(c, batch, 2)
    _launch(
        _kernels().lq_rollout_kernel,
        nb,
        T,
        _flat(A, batch, 3),
        _flat(B, batch, 3),
        cn,
        _flat(Kk, batch, 3),
        _flat(x0, batch, 1),
        x.numpy(),
        u.numpy(),
        *_kernels().size_witness(n, m),
    )
    return x.reshape(*batch, T + 1, n), u.reshape(*batch, T, m)


def adjoint_compiled(
    F: Tensor, Kk: Tensor, Vh: Tensor, chol: Tensor, gx: Tensor, gu: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`torchslq.lq.lq_adjoint_solve` on the CPU kernel (same shapes and outputs);
    call only where :func:`can_use_compiled` holds."""
    T, m = gu.shape[-2], gu.shape[-1]
    n = gx.shape[-1]
    batch = broadcast_shapes(
        F.shape[:-3], Kk.shape[:-3], Vh.shape[:-3], chol.shape[:-3], gx.shape[:-2], gu.shape[:-2]
    )
    nb = math.prod(batch)
    dx = torch.empty(nb, T + 1, n, dtype=F.dtype)
    du = torch.empty(nb, T, m, dtype=F.dtype)
    dlam = torch.empty(nb, T + 1, n, dtype=F.dtype)
    _launch(
        _kernels().adjoint_kernel,
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


def _bound_arrays(u_min, u_max, shape: tuple[int, int, int], dtype: torch.dtype):
    """Control bounds as ``(B, T, m)`` arrays for the rollout kernels (a missing one
    infinite), or two empty arrays when there are none."""
    if u_min is None and u_max is None:
        empty = np.zeros((0, 1, 1), dtype=_np_dtype(dtype))
        return empty, empty
    inf = torch.tensor(float("inf"), dtype=dtype)
    return tuple(
        ((inf if upper else -inf) if b is None else b).expand(shape).detach().contiguous().numpy()
        for b, upper in ((u_min, False), (u_max, True))
    )


def closed_loop_feedback_compiled(
    x_nom: Tensor, K: Tensor, u: Tensor, u_min: Tensor | None, u_max: Tensor | None
):
    """The feedback step of :func:`torchslq.dynamics.rollout_closed_loop` on the CPU
    kernel: returns ``step(t, x_t)`` which adds ``K_t (x_t - x_nom_t)`` to ``u[..., t, :]``
    in place and clamps it into the bounds.

    ``x_nom (B, T, n)`` (the first ``T`` nominal states), ``K (B, T, m, n)``,
    ``u (..., B, T, m)`` contiguous (the feedforward on entry), bounds None or
    broadcastable to ``(B, T, m)``; ``x_t`` ``(..., B, 1, n)``. One kernel call per step instead of a broadcast batched matmul
    (which copies ``K_t`` for every candidate step) and three elementwise ops. Call only
    where :func:`can_use_compiled` holds for all of them.
    """
    Bsz, T, m, n = K.shape[-4:]
    xn = _np(x_nom)
    Kn = _np(K)
    un = u.view(-1, T, m).numpy()
    lo, hi = _bound_arrays(u_min, u_max, (Bsz, T, m), u.dtype)
    kernel = _kernels().feedback_kernel

    def step(t: int, xt: Tensor) -> None:
        kernel(t, xt.detach().reshape(-1, n).numpy(), xn, Kn, lo, hi, un)

    return step


def closed_loop_rollout_compiled(
    step,
    params: np.ndarray,
    x0: Tensor,
    x_nom: Tensor,
    K: Tensor,
    u: Tensor,
    u_min,
    u_max,
    skip: Tensor | None = None,
) -> Tensor:
    """A whole closed-loop rollout on the CPU kernel with a model's compiled step
    (:meth:`torchslq.Dynamics.compiled_step`): ``x0 (..., B, n)`` (expanded to ``u``'s
    leading dims), ``x_nom (B, T, n)``, ``K (B, T, m, n)``, ``u (..., B, T, m)``
    contiguous holding the feedforward (overwritten with the applied controls), bounds as
    for :func:`closed_loop_feedback_compiled`; ``skip`` (bool, broadcastable to ``u``'s
    leading dims) marks rows not to roll out (their states after ``x0`` are NaN). Returns
    ``x (..., B, T+1, n)``. Call only where :func:`can_use_compiled` holds."""
    Bsz, T, m, n = K.shape[-4:]
    lead = u.shape[:-2]
    R = math.prod(lead)
    un = u.view(R, T, m).numpy()
    lo, hi = _bound_arrays(u_min, u_max, (Bsz, T, m), u.dtype)
    x = torch.empty(*lead, T + 1, n, dtype=u.dtype)
    skip_rows = (
        np.zeros(0, np.bool_)
        if skip is None
        else skip.detach().expand(lead).reshape(R).contiguous().numpy()
    )
    kernel, fns = _pass_kernel(
        "closed_loop_rollout_kernel", "closed_loop_rows_kernel", step, un.dtype, params.dtype,
        R, R * T, _kernels(),
    )  # fmt: skip
    _launch(
        kernel,
        R,
        T,
        *fns,
        params,
        x0.detach().expand(*lead, n).reshape(R, n).contiguous().numpy(),
        _np(x_nom),
        _np(K),
        lo,
        hi,
        skip_rows,
        un,
        x.view(R, T + 1, n).numpy(),
    )
    return x


def armijo_rollout_compiled(
    step,
    params: np.ndarray,
    x: Tensor,
    u: Tensor,
    K: Tensor,
    k: Tensor,
    u_min: Tensor | None,
    u_max: Tensor | None,
    grid: Tensor,
    J0: Tensor,
    slope: Tensor,
    curvature: Tensor | None,
    c1: float,
    roundoff: float,
    active: Tensor,
    cost_terms: tuple,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Armijo backtracking along the feedback rollout, one kernel call for the batch
    (:func:`._numba_search.armijo_rollout_kernel`): a model's compiled step
    (:meth:`torchslq.Dynamics.compiled_step`) and a quadratic cost's kernel arrays
    (:meth:`torchslq.QuadraticCost.compiled_terms`).

    ``x (B, T+1, n)``, ``u (B, T, m)`` the nominal trajectory, ``K (B, T, m, n)``,
    ``k (B, T, m)``, bounds None or broadcastable to ``(B, T, m)``, ``grid (N,)`` the
    steps (largest first), ``J0``, ``slope``, ``curvature`` (None: the linear model)
    and ``active`` ``(B,)``. Returns ``(alpha, J, ok, x_new, u_new)`` as
    :class:`torchslq.solvers.descent.LineSearch` does. Call only where
    :func:`can_use_compiled` holds for all tensors."""
    from . import _numba_search

    Bsz, T, m = u.shape
    n = x.shape[-1]
    lo, hi = _bound_arrays(u_min, u_max, (Bsz, T, m), u.dtype)
    x_new = torch.empty_like(x, memory_format=torch.contiguous_format)
    u_new = torch.empty_like(u, memory_format=torch.contiguous_format)
    alpha, J = torch.empty_like(J0), torch.empty_like(J0)
    ok = torch.empty(Bsz, dtype=torch.bool)
    curv = J0 if curvature is None else curvature  # unread without the quadratic model
    kernel, fns = _pass_kernel(
        "armijo_rollout_kernel", "armijo_rows_kernel", step, _np_dtype(x.dtype), params.dtype,
        Bsz, Bsz * T, _numba_search,
    )  # fmt: skip
    _, (xr, ur, Q, QT, R), stage_states = cost_terms
    arrays = (x, u, K.expand(Bsz, T, m, n), k, grid, J0, slope, curv)
    _launch(
        kernel,
        Bsz,
        T,
        *fns,
        params,
        *(_np(t) for t in arrays[:4]),
        lo,
        hi,
        *(_np(t) for t in arrays[4:]),
        curvature is not None,
        float(c1),
        float(roundoff),
        active.contiguous().numpy(),
        xr,
        ur,
        Q,
        QT,
        R,
        stage_states,
        x_new.numpy(),
        u_new.numpy(),
        alpha.numpy(),
        J.numpy(),
        ok.numpy(),
    )
    return alpha, J, ok, x_new, u_new


def step_rows_compiled(step, params: np.ndarray, x: Tensor, u: Tensor) -> Tensor:
    """``step(x[r], u[r])`` for every row of ``x (R, n)``, ``u (R, m)`` (contiguous) in
    one kernel call with a model's compiled step (:meth:`torchslq.Dynamics.compiled_step`);
    returns ``(R, n)``. Call only where :func:`can_use_compiled` holds."""
    out = torch.empty_like(x)
    xa = _np(x)
    rows_fn = _on_rows(step, x.shape[0])
    if rows_fn is not None:  # the model's own function on many rows
        _launch(rows_fn, x.shape[0], 1, xa, _np(u), params, out.numpy())
        return out
    kernel, fns = rollout_kernel("step_rows_kernel", step, xa.dtype, params.dtype, x.shape[0])
    _launch(
        kernel,
        x.shape[0],
        1,
        *fns,
        params,
        xa,
        _np(u),
        out.numpy(),
    )
    return out


def costate_compiled(
    A: Tensor, B: Tensor, lx: Tensor, lu: Tensor, K: Tensor | None
) -> tuple[Tensor, Tensor] | None:
    """:func:`torchslq.solvers.costate_gradient` on the CPU kernel (same shapes and
    outputs), or None where the shapes are not the plain ``A (..., T, n, n)``, ``B (...,
    T, n, m)``, ``lx (..., T+1, n)``, ``lu (..., T, m)``, ``K (..., T, m, n)`` (the
    caller then takes the torch path). Call only where :func:`can_use_compiled` holds."""
    T, m, n = lu.shape[-2], lu.shape[-1], lx.shape[-1]
    if (
        T == 0
        or A.shape[-3:] != (T, n, n)
        or B.shape[-3:] != (T, n, m)
        or lx.shape[-2] != T + 1
        or (K is not None and K.shape[-3:] != (T, m, n))
    ):
        return None
    leads = [A.shape[:-3], B.shape[:-3], lx.shape[:-2], lu.shape[:-2]]
    if K is not None:
        leads.append(K.shape[:-3])
    batch = broadcast_shapes(*leads)
    nb = math.prod(batch)
    grad = torch.empty(nb, T, m, dtype=lu.dtype)
    lam = torch.empty(nb, T + 1, n, dtype=lu.dtype)
    Ka = np.zeros((0, 1, 1, 1), _np_dtype(lu.dtype)) if K is None else _flat(K, batch, 3)
    _launch(
        _kernels().costate_kernel,
        nb,
        T,
        _flat(A, batch, 3),
        _flat(B, batch, 3),
        _flat(lx, batch, 2),
        _flat(lu, batch, 2),
        Ka,
        grad.numpy(),
        lam.numpy(),
    )
    return grad.reshape(*batch, T, m), lam.reshape(*batch, T + 1, n)


def stage_congruence_compiled(
    acc: tuple[Tensor, Tensor, Tensor],
    h: tuple[Tensor, Tensor, Tensor],
    dk: Tensor,
    scale: float,
) -> None:
    """``acc += Z' h Z`` for one RK4 stage of
    :meth:`torchslq.dynamics.DiscretizedDynamics.vhp` on the CPU kernel (in place).

    ``acc = (Hxx, Huu, Hux)``: contiguous ``(*L, n, n)``, ``(*L, m, m)``, ``(*L, m, n)``;
    ``h``: the stage's Hessian blocks, broadcastable to those; ``dk (*Ld, n, n+m)`` with
    ``Z = [[I + scale dk_x, scale dk_u], [0, I]]``, ``Ld`` a suffix of ``L`` (or
    broadcastable to ``L``). Call only where :func:`can_use_compiled` holds.
    """
    Hxx = acc[0]
    L = Hxx.shape[:-2]
    Ld = dk.shape[:-2]
    if len(Ld) > len(L) or tuple(L[len(L) - len(Ld) :]) != tuple(Ld):
        dk = dk.expand(*L, *dk.shape[-2:])  # not one block per point: one per row
    R = math.prod(dk.shape[:-2])
    J = math.prod(L)
    flat = tuple(
        t.expand(*L, *a.shape[-2:]).reshape(J, *a.shape[-2:]).contiguous().numpy()
        for t, a in zip(h, acc, strict=True)
    )
    outs = tuple(a.view(J, *a.shape[-2:]).numpy() for a in acc)
    d = dk.reshape(R, *dk.shape[-2:]).contiguous().numpy()
    _launch(_kernels().stage_congruence_kernel, J, 1, *flat, d, float(scale), *outs)


def _reg_array(reg: Tensor | float | None, batch: torch.Size, dtype: torch.dtype) -> np.ndarray:
    """``reg`` as a ``(1,)`` or ``(prod(batch),)`` array (zero when None)."""
    if reg is None:
        return np.zeros(1, dtype=_np_dtype(dtype))
    r = torch.as_tensor(reg, dtype=dtype)
    r = r.reshape(1) if r.numel() == 1 else r.expand(batch).reshape(-1)
    return _np(r)


_EMPTY_HESSIANS: dict = {}


def _hessian_arrays(hessians, dtype: torch.dtype) -> tuple:
    """DDP's Hessians for the kernel's ``Hz`` and ``Hb`` arguments: a ``(T, n, B, m+n,
    m+n)`` tensor, or the blocks ``(Hxx, Huu, Hux)`` each ``(n, B, T, ., .)``, or None
    (empty arrays of ``dtype`` for what is not given)."""
    empty = _EMPTY_HESSIANS.get(dtype)
    if empty is None:  # (read-only: the kernels never write an empty array)
        empty = _EMPTY_HESSIANS.setdefault(dtype, np.zeros((0, 1, 1, 1, 1), _np_dtype(dtype)))
    if hessians is None:
        return empty, (empty, empty, empty)
    if isinstance(hessians, Tensor):
        return _np(hessians), (empty, empty, empty)
    joint = joint_hessians(*hessians)
    if joint is not None:  # the kernel reads each step's [u; x] block whole (as Hz)
        return joint.detach().permute(2, 0, 1, 3, 4).numpy(), (empty, empty, empty)
    return empty, tuple(_np(h) for h in hessians)


def joint_hessians(Hxx: Tensor, Huu: Tensor, Hux: Tensor) -> Tensor | None:
    """The ``(..., m+n, m+n)`` tensor in ``[u; x]`` order whose blocks ``Hxx (..., n,
    n)``, ``Huu (..., m, m)``, ``Hux (..., m, n)`` are views (as
    :func:`torchslq.dynamics.compiled_rk4.rk4_vhp_compiled` returns them, its lower-left
    block filled too), or None when they are separate tensors."""
    m, n = Huu.shape[-1], Hxx.shape[-1]
    nz = m + n
    lead, lead_st = Huu.shape[:-2], Huu.stride()[:-2]

    def rows_of_joint(h: Tensor) -> bool:  # rows nz apart, entries adjacent (size 1: any)
        r, c = h.shape[-2:]
        return (r == 1 or h.stride(-2) == nz) and (c == 1 or h.stride(-1) == 1)

    ptr = Huu.untyped_storage().data_ptr()
    same = all(
        h.untyped_storage().data_ptr() == ptr
        and h.shape[:-2] == lead
        and h.stride()[:-2] == lead_st
        and h.dtype == Huu.dtype
        and rows_of_joint(h)
        for h in (Hxx, Huu, Hux)
    )
    o = Huu.storage_offset()
    if not (same and Hux.storage_offset() == o + m and Hxx.storage_offset() == o + m * nz + m):
        return None
    return Huu.as_strided((*lead, nz, nz), (*lead_st, nz, 1), o)


_BOX_OPTS: tuple | None = None


def _box_opts() -> tuple:
    """:func:`torchslq.lq.box_qp`'s defaults ``(MAX_ITER, ARMIJO, STEP_DEC, N_STEPS)`` for
    the kernel's box QPs (read from :mod:`torchslq.lq.boxqp` on first use: ``lq``
    imports this package, not the other way round)."""
    global _BOX_OPTS
    if _BOX_OPTS is None:
        from ..lq import boxqp

        _BOX_OPTS = (boxqp.MAX_ITER, boxqp.ARMIJO, boxqp.STEP_DEC, boxqp.N_STEPS)
    return _BOX_OPTS


def _np_dtype(dtype: torch.dtype) -> np.dtype:
    """The numpy dtype of a torch float dtype (for the kernels' empty placeholders)."""
    return np.float32 if dtype == torch.float32 else np.float64


# ----------------------------------------------------------------------------- gain form


def _gain_kernels() -> ModuleType:
    """The gain-form LQ kernels (:mod:`._numba_gain`); call where :func:`can_use_compiled`
    holds (numba importable)."""
    from . import _numba_gain

    return _numba_gain


def _one_time_step(t: Tensor, tail: int) -> Tensor:
    """``t (..., steps, *tail dims)`` with its time dim cut to 1 where it is a broadcast
    (stride 0): the kernels index a time dim of 1 for every step, and the expanded
    tensor would otherwise be copied ``steps`` times."""
    d = t.ndim - tail - 1
    if t.shape[d] > 1 and t.stride(d) == 0:
        return t.narrow(d, 0, 1)
    return t


#: the numpy dtype of each torch dtype the kernels take (None for the others)
NP_FLOAT_DTYPES = {torch.float64: np.float64, torch.float32: np.float32}

_EMPTY_PIECES: dict = {}  # numpy dtype -> the kernels' (never written) empty pieces


def _empty_pieces(npd) -> tuple[np.ndarray, ...]:
    """The kernels' empty pieces of a numpy dtype (kept: built anew they cost a
    microsecond each at B = 1)."""
    empty = _EMPTY_PIECES[npd] = tuple(np.zeros((0,) * d, dtype=npd) for d in PIECE_NDIMS)
    return empty


def _piece_arrays(pieces: tuple, batch, dtype: torch.dtype) -> tuple[np.ndarray, ...]:
    """The LQ data ``(A, B, c, Q, R, S, q, r)`` (each with a time dim; ``c, S, q, r``
    may be None) as the kernels' ``pieces``: arrays ``(1 or prod(batch), 1 or steps,
    ...)``, an absent piece an empty array."""
    npd = _np_dtype(dtype)
    empty = _EMPTY_PIECES.get(npd) or _empty_pieces(npd)
    nb = math.prod(batch)
    out = []
    for p, d, none in zip(pieces, PIECE_NDIMS, empty, strict=True):
        if p is None:
            out.append(none)
        elif p.ndim == d and p.shape[0] in (1, nb):
            # one flat batch dim already (the common case): numpy's view of it; a time or
            # batch dim broadcast with stride 0 (an expanded weight) cut to 1, copied
            # only where what is left is not contiguous (numpy's slicing and checks cost
            # a fraction of torch's at B = 1)
            a = (p.detach() if p.requires_grad else p).numpy()
            if p.is_contiguous():
                out.append(a)
                continue
            st = a.strides
            if a.shape[1] > 1 and st[1] == 0:
                a = a[:, :1]
            if a.shape[0] > 1 and st[0] == 0:
                a = a[:1]
            out.append(a if a.flags.c_contiguous else np.ascontiguousarray(a))
        else:
            out.append(_flat(_one_time_step(p, d - 2), batch, d - 1))
    return tuple(out)


def lq_gain_pieces(pieces: tuple, batch: torch.Size) -> tuple[tuple[np.ndarray, ...], int]:
    """The LQ data ``(A, B, c, Q, R, S, q, r)`` (time dims given, ``with_time``) as the
    gain kernels' ``pieces`` (:func:`_piece_arrays`) and the data's own batch size: 1
    where every piece is shared by the batch (one Riccati pass serves all), else
    ``prod(batch)``; ``batch`` is the full batch shape (x0's included)."""
    shared = True
    for p, d in zip(pieces, PIECE_NDIMS, strict=True):
        if p is None:
            continue
        k = p.ndim - d + 1  # batch dims (the common case: one, no slice to take)
        if (p.shape[0] != 1) if k == 1 else (k > 1 and math.prod(p.shape[:k]) != 1):
            shared = False
            break
    arrays = _piece_arrays(pieces, (1,) if shared else batch, pieces[0].dtype)
    return arrays, 1 if shared else math.prod(batch)


def plain_gain_pieces(
    pieces: tuple, x0: Tensor
) -> tuple[tuple[np.ndarray, ...], int, np.ndarray] | None:
    """:func:`lq_gain_pieces` and :func:`can_use_compiled` (``differentiable=True``) in
    one pass for the common call, None for any other (the general path then decides):
    ``x0 (B, n)`` and every piece with one batch dim of 1 or ``B`` and its time dim,
    contiguous, on the CPU, in ``x0``'s float dtype. Returns ``(arrays, data_batch,
    x0)`` as numpy arrays. (At ``B = 1`` the general path's separate passes over the
    nine tensors cost about a third of a ``(4, 1)``, ``T = 100`` solve.)"""
    if x0.ndim != 2 or not x0.is_cpu or not compiled_available():
        return None
    dtype = x0.dtype
    npd = NP_FLOAT_DTYPES.get(dtype)
    if npd is None:
        return None
    nb = x0.shape[0]
    empty = _EMPTY_PIECES.get(npd) or _empty_pieces(npd)
    shared = True
    out = []
    for p, d, none in zip(pieces, PIECE_NDIMS, empty, strict=True):
        if p is None:
            out.append(none)
            continue
        if p.ndim != d or p.dtype != dtype or not p.is_cpu or not p.is_contiguous():
            return None
        b = p.shape[0]
        if b != 1:
            if b != nb:
                return None
            shared = False
        out.append((p.detach() if p.requires_grad else p).numpy())
    if not x0.is_contiguous() or not _kernels_apply_here():
        return None
    # data shared by the batch: one Riccati pass serves all
    return tuple(out), 1 if shared else nb, (x0.detach() if x0.requires_grad else x0).numpy()


# per piece (A, B, c, Q, R, S, q, r): its matrix or vector shape in terms of (n, m), and
# whether its time dim has T + 1 steps (else T)
_PIECE_TAILS = ("nn", "nm", "n", "nn", "mm", "mn", "n", "m")
_PIECE_TERMINAL = (False, False, False, True, False, False, True, False)
_ADDRESS_SHAPES: dict = {}  # (n, m, T, B) -> per piece {accepted shape: (batch, time)}


def _address_shapes(n: int, m: int, T: int, nb: int) -> tuple[dict, ...]:
    """Per piece of :func:`gain_addresses`, its accepted shapes and their batch and time
    sizes (one dict lookup a piece: at B = 1 each check of a shape counts)."""
    key = (n, m, T, nb)
    table = _ADDRESS_SHAPES.get(key)
    if table is None:
        if len(_ADDRESS_SHAPES) > 256:
            _ADDRESS_SHAPES.clear()
        sizes = {"n": n, "m": m}
        table = []
        for tail, terminal in zip(_PIECE_TAILS, _PIECE_TERMINAL, strict=True):
            tail = tuple(sizes[k] for k in tail)
            shapes = {tail: (1, 1)}
            for t in (1, T + 1 if terminal else T):
                shapes[(t, *tail)] = (1, t)
                for b in (1, nb):
                    shapes[(b, t, *tail)] = (b, t)
            table.append(shapes)
        table = _ADDRESS_SHAPES[key] = tuple(table)
    return table


def gain_addresses(pieces: tuple, x0: Tensor, T: int, n: int, m: int) -> tuple | None:
    """The LQ data ``pieces`` ``(A, B, c, Q, R, S, q, r)`` (as given to
    :func:`torchslq.lqr_solve`: ``c, S, q, r`` may be None) and ``x0 (B, n)`` as the
    addresses the ``*_at`` kernels read them at (:mod:`._numba_address`), for a call
    that needs no graph and is one launch on one thread; None for any other call (the
    array launchers then decide).

    Each piece is ``(1 or B, 1 or steps, *tail)``, ``(1 or steps, *tail)`` or its
    ``tail`` alone (the same in every step), contiguous, on the CPU, in ``x0``'s float
    dtype, with exactly its tail shape: the kernels read memory at these addresses
    without bounds checks. Returns ``(addresses, dims, data_batch, x0_address, B, n,
    m, numpy dtype)``: ``dims`` each piece's batch and time sizes (``(0, 0)`` absent),
    ``data_batch`` 1 where every piece is shared by the batch (one Riccati pass serves
    all), else ``B``. (At ``B = 1`` a numpy view of each of nine tensors cost more than
    the ``(4, 1)``, ``T = 100`` pass itself.)"""
    if x0.ndim != 2 or not x0.is_cpu or not compiled_available():
        return None
    if not _kernels_apply_here():  # (first: a transform's or a tracer's tensors have no address)
        return None
    dtype = x0.dtype
    npd = NP_FLOAT_DTYPES.get(dtype)
    grad = torch.is_grad_enabled()
    if npd is None or x0.shape[1] != n or not x0.is_contiguous() or (grad and x0.requires_grad):
        return None
    nb = x0.shape[0]
    addresses, dims = [], ()
    shared = True
    for p, shapes in zip(pieces, _address_shapes(n, m, T, nb), strict=True):
        if p is None:
            addresses.append(0)
            dims += (0, 0)
            continue
        bt = shapes.get(p.shape)
        if bt is None or p.dtype != dtype or not p.is_cpu or not p.is_contiguous():
            return None
        if grad and p.requires_grad:
            return None
        if bt[0] != 1:
            shared = False
        addresses.append(p.data_ptr())
        dims += bt
    data_batch = 1 if shared else nb
    if not _one_launch(max(nb, data_batch), T):  # (the array launchers split it)
        return None
    return tuple(addresses), dims, data_batch, x0.data_ptr(), nb, n, m, npd


def lq_data_clean_at(at: tuple) -> bool:
    """:func:`lq_data_clean` on the data of :func:`gain_addresses`."""
    addresses, dims, _, x0_address, nb, n, m, npd = at
    like = _EMPTY_PIECES.get(npd) or _empty_pieces(npd)
    kernel = _gain_kernels().data_clean_at_kernel
    return bool(kernel(addresses, dims, x0_address, nb, n, m, like[0]))


_GAIN_PLANS: dict = {}  # (n, m, switches) -> _gain_plan's tuple


def _gain_plan(n: int, m: int) -> tuple:
    """``(gain, passes, nt, mt, with_slp)`` for ``n`` states and ``m`` controls: the module
    :mod:`._numba_gain`, the element pass written out for ``(n, m)`` where it is
    generated (:func:`.gain_codegen.gain_kernels`; else ``gain``), the size witnesses
    and :func:`._numba_gemm.with_slp` (looked up once: at B = 1 each lookup counts)."""
    # (the switches that decide which kernels a size gets are part of the key)
    key = (n, m, gain_codegen._enabled, specialisation._only)
    plan = _GAIN_PLANS.get(key)
    if plan is None:
        gain = _gain_kernels()
        from ._numba_gemm import with_slp

        passes = gain_kernels(n, m) or gain
        plan = _GAIN_PLANS[key] = (gain, passes, *gain.size_witness(n, m), with_slp)
    return plan


def lq_data_clean(pieces: tuple[np.ndarray, ...], x0: np.ndarray) -> bool:
    """Whether every entry of the kernels' ``pieces`` (:func:`lq_gain_pieces`) and of
    ``x0`` is finite and every ``R`` positive definite: :func:`torchslq.lqr_solve`'s
    quick check of its data, compiled (:func:`._numba_gain.data_clean_kernel`)."""
    return bool(_gain_kernels().data_clean_kernel(pieces, x0))


def lq_gain_solve(
    pieces: tuple[np.ndarray, ...], data_batch: int, x0: np.ndarray, T: int
) -> dict[str, np.ndarray]:
    """:func:`torchslq.lqr_solve` on the gain-form kernels (:mod:`._numba_gain`), without
    autograd: the Riccati pass over the data's batch (``data_batch``, 1 or ``B``), then
    over ``x0 (B, n)``'s batch the rollout (:func:`lq_rollout_kernel`, the one of
    :func:`torchslq.lq.rollout_linear`), costates and optimal cost.

    Returns a dict of numpy arrays (the callers make the tensors they return, from
    numpy's views: cheaper than torch's slicing at B = 1): ``Kk (Bd, T, m, n+1)`` (``[K,
    k]``), ``P (Bd, T+1, n, n)``, ``p (Bd, T+1, n)``, ``L (Bd, T, m, m)`` (``Quu``'s
    Cholesky factors), ``s (Bd,)``, ``failed (Bd,)``; and ``x (B, T+1, n)``, ``u (B, T,
    m)``, ``lam (B, T+1, n)``, ``cost (B,)`` (NaN where not finite), ``finite (B,)``.
    Call only where :func:`can_use_compiled` holds."""
    n, m = pieces[1].shape[-2], pieces[1].shape[-1]
    gain, passes, nt, mt, with_slp = _gain_plan(n, m)
    nb = x0.shape[0]
    out = _gain_outputs(data_batch, nb, T, n, m, x0.dtype)
    Kkn, Pn, pn, Ln, sn, failedn, xn, un, lamn, costn, finiten = out
    work = max(nb, data_batch)
    if _one_launch(work, T):  # one launch, not three
        # (LLVM's SLP switch for its register-blocked products, when first compiled)
        with_slp(passes.gain_solve_kernel, pieces, x0, *out, nt, mt)
    else:
        with_slp(
            _launch, passes.riccati_gain_kernel, data_batch, T, pieces, Kkn, Pn, pn, Ln, sn,
            failedn, nt, mt,
        )  # fmt: skip
        _launch(
            gain.rollout_value_kernel, nb, T, pieces[0], pieces[1], pieces[2], Kkn, Pn, pn, sn,
            x0, xn, un, lamn, costn, finiten, nt, mt,
        )  # fmt: skip
    return _gain_solution_arrays(out)


def lq_gain_solve_at(at: tuple, T: int) -> dict[str, np.ndarray]:
    """:func:`lq_gain_solve` on the data of :func:`gain_addresses`, in one launch."""
    addresses, dims, data_batch, x0_address, nb, n, m, npd = at
    _, passes, nt, mt, with_slp = _gain_plan(n, m)
    out = _gain_outputs(data_batch, nb, T, n, m, npd)
    with_slp(passes.gain_solve_at_kernel, addresses, dims, x0_address, *out, nt, mt)
    return _gain_solution_arrays(out)


def _gain_solution_arrays(out: tuple) -> dict[str, np.ndarray]:
    Kkn, Pn, pn, Ln, sn, failedn, xn, un, lamn, costn, finiten = out
    return {
        "Kk": Kkn, "P": Pn, "p": pn, "L": Ln, "s": sn, "failed": failedn, "x": xn, "u": un,
        "lam": lamn, "cost": costn, "finite": finiten,
    }  # fmt: skip


def _gain_outputs(data_batch: int, nb: int, T: int, n: int, m: int, npd) -> tuple:
    """The gain kernels' outputs (:func:`lq_gain_solve`), uninitialised."""
    return (
        np.empty((data_batch, T, m, n + 1), npd),
        np.empty((data_batch, T + 1, n, n), npd),
        np.empty((data_batch, T + 1, n), npd),
        np.empty((data_batch, T, m, m), npd),
        np.empty(data_batch, npd),
        np.empty(data_batch, np.bool_),
        np.empty((nb, T + 1, n), npd),
        np.empty((nb, T, m), npd),
        np.empty((nb, T + 1, n), npd),
        np.empty(nb, npd),
        np.empty(nb, np.bool_),
    )


def lq_gain_gradients(
    pieces: tuple[np.ndarray, ...], sol: dict[str, np.ndarray], ok: np.ndarray, gx: Tensor,
    gu: Tensor, gJ: Tensor, needs: tuple[bool, ...],
) -> tuple[Tensor | None, ...]:  # fmt: skip
    """Gradients of :func:`lq_gain_solve`'s ``x, u, cost`` (incoming ``gx (B, T+1,
    n)``, ``gu (B, T, m)``, ``gJ (B,)``) with respect to ``(A, B, Q, R, x0, q, r, S, c)``,
    each with full batch and time dims (``(B, T, n, n)``, ...; None where ``needs`` is
    False); zero for elements where ``ok (B,)`` is False. ``sol``: the arrays ``Kk, L,
    P, lam`` of :func:`lq_gain_solve` and its ``x (B, T+1, n)``, ``u (B, T, m)``."""
    kern = _gain_kernels()
    x, u = sol["x"], sol["u"]
    nb, T1, n = x.shape
    T, m = T1 - 1, u.shape[-1]
    npd = x.dtype
    shapes = (
        (T, n, n), (T, n, m), (T + 1, n, n), (T, m, m), (n,), (T + 1, n), (T, m), (T, m, n),
        (T, n),
    )  # fmt: skip
    out = [
        np.empty((nb if need else 0, *shape), npd)
        for shape, need in zip(shapes, needs, strict=True)
    ]
    gA, gB, gQ, gR, gx0, gq, gr, gS, gc = out
    vs = np.empty((nb, T + 1, n), dtype=npd)
    ks = np.empty((nb, T, m), dtype=npd)
    _launch(
        kern.adjoint_gain_kernel, nb, T, pieces[0], pieces[1], sol["Kk"], sol["L"], sol["P"],
        x, u, sol["lam"], ok, _np(gx), _np(gu), _np(gJ), vs, ks,
        gA, gB, gc, gQ, gR, gS, gq, gr, gx0, *kern.size_witness(n, m),
    )  # fmt: skip
    if not ok.all():  # the kernel skipped these elements
        for g, need in zip(out, needs, strict=True):
            if need:
                g[~ok] = 0.0
    return tuple(torch.from_numpy(g) if need else None for g, need in zip(out, needs, strict=True))


def reduced_ip_compiled(
    kkt, ineq, f: Tensor, h: Tensor, scale_d: Tensor, scale_i: Tensor, tol: float,
    max_iter: int, reg: float, z: Tensor, s: Tensor, mu: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """The interior point's iterations on the reduced Newton system, per element in one
    compiled loop (:func:`._numba_qp.reduced_ip_kernel`), for
    :func:`torchslq.lqdo.backends.qp_solve`'s float64 CPU path.

    ``kkt``: a :class:`torchslq.lqdo.kkt.ReducedKKT` (its ``Hz`` is advanced with the
    iterates), ``ineq`` its :class:`~torchslq.lqdo.kkt.Inequalities`; ``reg``: the
    primal regularisation of the reduced matrix's diagonal (``kkt._REG``); ``z (B, n)``,
    ``s``, ``mu (B, mi)``: the start, advanced in place (contiguous float64). Returns
    ``(done, handoff, iters)``, ``(B,)`` each: as the torch loop's flags, and the
    iteration at which each element stopped."""
    from . import _numba_qp

    B = f.shape[0]
    done = torch.empty(B, dtype=torch.bool)
    handoff = torch.empty(B, dtype=torch.bool)
    iters = torch.empty(B, dtype=torch.int64)
    kkt.Hz = kkt.Hz.contiguous().clone()

    def c(t: Tensor) -> np.ndarray:
        return _np(t.contiguous())

    def i64(t: Tensor) -> np.ndarray:
        return _np(t.to(torch.int64).contiguous())

    # an element's solve is a dozen iterations of a few microseconds: weighted as 512
    # steps of an LQ pass when the batch is split over threads
    _launch(
        _numba_qp.reduced_ip_kernel, B, 512, c(kkt.Z), c(kkt.HZ), c(kkt.ZHZ), c(kkt.C),
        c(ineq.G), c(f), c(h), c(ineq.eu), c(ineq.el), i64(ineq.uidx), i64(ineq.lidx),
        i64(ineq.upos), i64(ineq.lpos), i64(ineq.bidx), c(scale_d), c(scale_i), float(tol),
        int(max_iter), float(reg), _np(z), _np(kkt.Hz), _np(s), _np(mu), _np(done), _np(handoff),
        _np(iters), _numba_qp.witness_r(kkt.Z.shape[2]),
    )  # fmt: skip
    return done, handoff, iters


def reduced_setup_compiled(
    LU: Tensor, perm: Tensor, H: Tensor, b: Tensor, G: Tensor, bidx: Tensor, target: Tensor
) -> tuple[Tensor, ...]:
    """``ReducedKKT``'s null-space set-up per element in one compiled loop
    (:func:`._numba_qp.reduced_setup_kernel`), for the float64 CPU path of
    :class:`torchslq.lqdo.kkt.ReducedKKT`: ``(Z, z0, HZ, ZHZ, C, Hz)`` from the LU
    factors ``LU (B, n, me)`` of ``A'`` and their row order ``perm (B, n)``, ``H (B, n,
    n)``, ``b (B, me)``, ``G (B, mg, n)`` and the bounded variables ``bidx``; ``z0`` is
    the point of ``A z = b`` nearest ``target (B, n)``."""
    from . import _numba_qp

    B, n, me = LU.shape
    r, mc = n - me, G.shape[1] + bidx.numel()
    Z, HZ = H.new_empty(B, n, r), H.new_empty(B, n, r)
    z0, Hz = H.new_empty(B, n), H.new_empty(B, n)
    ZHZ, C = H.new_empty(B, r, r), H.new_empty(B, mc, r)
    LUn = LU.detach().numpy()  # (column-major as LAPACK left it: read in place)
    # an element's set-up is some 10^5 multiply-adds: weighted as 512 steps of an LQ pass
    _launch(
        _numba_qp.reduced_setup_kernel, B, 512, LUn, _np(perm.to(torch.int64)), _np(H), _np(b),
        _np(G), _np(bidx.to(torch.int64)), _np(target.contiguous()), _np(Z), _np(z0), _np(HZ),
        _np(ZHZ), _np(C), _np(Hz), _numba_qp.witness_r(r),
    )  # fmt: skip
    return Z, z0, HZ, ZHZ, C, Hz


def scatter_compiled(lin: Tensor, val: Tensor, size: int) -> Tensor:
    """Dense ``(B, size)`` rows from values ``val (B, nnz)`` at the flat positions ``lin
    (nnz,)`` shared by the batch, duplicates summed
    (:func:`._numba_qp.scatter_rows_kernel`); the same sums, in the same order, as
    ``zeros(B, size).index_add_(1, lin, val)``. A float CPU ``val`` without a graph."""
    from . import _numba_qp

    B = val.shape[0]
    # numpy's memory: a large block comes from the system on huge pages (see
    # torchslq.lqdo.qp._scatter); the kernel writes every entry
    out = np.empty((B, size), NP_FLOAT_DTYPES[val.dtype])
    _launch(
        _numba_qp.scatter_rows_kernel, B, max(1, lin.numel() // 64),
        _np(lin.to(torch.int64)), _np(val), out,
    )  # fmt: skip
    return torch.from_numpy(out)


def abs_max_rows_compiled(M: Tensor) -> Tensor:
    """``(B,)`` ``max |M[e]|`` over each element's entries of a float CPU ``M (B, ...)``
    without a graph (:func:`._numba_qp.abs_max_rows_kernel`): the value of
    ``maximum(amax, -amin)``, NaN where an element holds one."""
    from . import _numba_qp

    B = M.shape[0]
    out = M.new_empty(B)
    flat = _np(M.reshape(B, -1))
    _launch(_numba_qp.abs_max_rows_kernel, B, max(1, flat.shape[1] // 64), flat, _np(out))
    return out


def basic_solve_compiled(LU: Tensor, g: Tensor) -> Tensor:
    """``-(L1 U)^{-1} g`` per element (:func:`._numba_qp.basic_solve_kernel`): the
    reduced system's multipliers of ``A z = b`` from ``g (B, me)``, the gradient on the
    basic variables, and ``A'``'s LU factors ``LU (B, n, me)``."""
    from . import _numba_qp

    out = g.new_empty(g.shape)
    _launch(_numba_qp.basic_solve_kernel, g.shape[0], 64, LU.detach().numpy(), _np(g), _np(out))
    return out
