"""Products and ``tanh`` over many rows (CPU, float64): a learned model's derivatives.

A learned model's Jacobians (:mod:`torchslq.dynamics.graph_jacobian`) spend most of
their time in two kinds of torch op: a network layer's product over every row of a
batch of trajectories (``(rows, 64) @ (64, 64)`` and, in the reverse sweep, ``(rows n,
64) @ (64, 64)``) and its activations. On CPUs other than Intel's, torch's BLAS (MKL)
takes a slow generic path: measured on the AMD EPYC of the benchmarks (1 thread,
``(12800, 64) @ (64, 64)``), torch 6.8-7.9 GFMA/s against 14.2 for the register-blocked
product of the LQ kernels (:func:`~torchslq._backend._numba_gemm.acc_tn`) and 13-16 for
NumPy's OpenBLAS; torch's float64 ``tanh`` 6.2 ns an entry against 2.7 ns for the
branch-free one the compiled network steps inline
(:func:`torchslq.dynamics._numba_net.tanh`).

:func:`matmul` and :func:`linear` therefore run the product in numba where torch's BLAS
is MKL on a CPU that is not Intel's (:func:`blas_is_slow`); :func:`tanh` runs in numba
on any CPU. Both only on CPU float64 tensors that need no autograd graph, outside
``torch.func`` transforms and ``torch.compile`` tracing, and only for at least
:data:`MIN_WORK` multiply-adds or entries (below that a call's overhead decides);
anything else is the torch op. The results differ from torch's by rounding (tanh:
within 3 ulp). The work is split over ``torch.get_num_threads()`` threads by rows.
"""

from __future__ import annotations

import functools
import platform

import numpy as np
import torch
from torch import Tensor

__all__ = ["MIN_WORK", "blas_is_slow", "linear", "matmul", "set_forced", "tanh"]

#: below this many multiply-adds (a product) or entries (tanh), the torch op
MIN_WORK = 1 << 15

# None: decide by the CPU (blas_is_slow); True/False: force the numba product on/off
# (tests of both ways on one machine)
_forced: bool | None = None


def set_forced(value: bool | None) -> bool | None:
    """Force the numba product on (True) or off (False) whatever the CPU, or back to the
    CPU's choice (None); returns the old setting."""
    global _forced
    old, _forced = _forced, value
    return old


@functools.cache
def _cpu_vendor() -> str:
    """``vendor_id`` of ``/proc/cpuinfo`` (Linux); ``""`` where it cannot be read."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("vendor_id"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


@functools.cache
def _mkl_off_intel() -> bool:
    """Whether torch's CPU BLAS is MKL on an x86 CPU that is not Intel's (once a process)."""
    return (
        platform.machine().lower() in ("x86_64", "amd64")
        and torch.backends.mkl.is_available()
        and _cpu_vendor() not in ("", "GenuineIntel")
    )


def blas_is_slow() -> bool:
    """Whether torch's CPU BLAS is MKL on an x86 CPU that is not Intel's (MKL's generic
    code path there runs a float64 product at about half the register-blocked kernel's
    rate); overridden by :func:`set_forced`."""
    return _mkl_off_intel() if _forced is None else _forced


def _eligible(*tensors: Tensor) -> bool:
    from .dispatch import can_use_compiled

    return all(t.dtype == torch.float64 for t in tensors) and can_use_compiled(*tensors)


def _launch(name: str, rows: int, work_per_row: int, *args) -> None:
    # (numba is imported on first use, not with the package)
    from . import _numba_rows
    from ._numba_gemm import with_slp
    from .dispatch import _launch as launch

    # (_launch splits by element-steps; here a row's multiply-adds stand for its steps)
    with_slp(launch, getattr(_numba_rows, name), rows, max(1, work_per_row // 64), *args)


def _takes_product(a: Tensor, b: Tensor, c: int) -> bool:
    """Whether ``a (r, k)`` times a ``(k, c)`` factor ``b`` runs in numba."""
    return a.shape[0] * a.shape[1] * c >= MIN_WORK and blas_is_slow() and _eligible(a, b)


def _product(a: Tensor, b: Tensor, bias: Tensor | None) -> Tensor:
    """``bias + a (r, k) @ b (k, c)`` by the numba kernel (``b`` contiguous)."""
    r, k = a.shape
    c = b.shape[1]
    out = a.new_empty(r, c)
    bias_rows = np.zeros(c) if bias is None else bias.contiguous().numpy()
    _launch("matmul_rows", r, k * c, out.numpy(), a.contiguous().numpy(), b.numpy(), bias_rows)
    return out


def matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a (r, k) @ b (k, c)`` (module docstring: numba or torch)."""
    if not _takes_product(a, b, b.shape[1]):
        return a @ b
    return _product(a, b.contiguous(), None)


def linear(a: Tensor, weight: Tensor, bias: Tensor | None) -> Tensor:
    """``a (r, k) @ weight' + bias``, ``weight (c, k)``, ``bias (c,)`` or None: torch's
    ``F.linear`` (module docstring: numba or torch)."""
    if a.ndim != 2 or not _takes_product(a, weight, weight.shape[0]):
        return torch.nn.functional.linear(a, weight, bias)
    # (the weight's transpose copied: the kernel runs along its factor's rows, contiguous)
    return _product(a, weight.T.contiguous(), bias)


def tanh(a: Tensor) -> Tensor:
    """``torch.tanh(a)`` (module docstring: numba or torch)."""
    if a.numel() < MIN_WORK or not _eligible(a):
        return torch.tanh(a)
    a = a.contiguous()
    out = torch.empty_like(a)
    flat_in, flat_out = a.view(-1).numpy(), out.view(-1).numpy()
    _launch("tanh_rows", flat_in.shape[0], 64, flat_in, flat_out)
    return out
