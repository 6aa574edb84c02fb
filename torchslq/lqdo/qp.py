"""The quadratic program of a transcribed LQDO problem, Prob. (18), batch-first.

.. math::

    \\min_z \\tfrac12 z^T H z + f^T z + c \\quad\\text{s.t.}\\quad A z = b,\\;
    G z \\le h,\\; lb \\le z \\le ub.

Matrices are stored as one sparsity pattern shared by the batch with per-element values
(``idx (2, nnz)`` rows/columns, ``val (B, nnz)``, duplicates summed), which is how the
transcription builds them without a loop over nodes; :meth:`SparseQP.dense` scatters them
into dense ``(B, m, n)`` tensors (differentiably) for the batched torch solver, and
:meth:`SparseQP.scipy` into one block-diagonal ``scipy.sparse`` matrix for the whole batch
for the sparse CPU solvers.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .._backend.dispatch import NP_FLOAT_DTYPES, can_use_compiled, scatter_compiled
from .kkt import Inequalities

__all__ = ["SparseQP", "DenseQP"]


def _scatter(idx: Tensor, val: Tensor, m: int, n: int) -> Tensor:
    """Dense ``(B, m, n)`` from a shared pattern ``idx (2, nnz)`` and values ``(B, nnz)``."""
    B = val.shape[0]
    if m * n and idx.shape[1] and can_use_compiled(val):
        # one element's row at a time, in cache (index_add_ along dim 1 strides over the
        # batch for every pattern entry): crane PS10, B = 256, 6% of a QLIN solve
        return scatter_compiled(idx[0] * n + idx[1], val, m * n).reshape(B, m, n)
    npd = NP_FLOAT_DTYPES.get(val.dtype) if val.is_cpu else None
    if npd is not None and B * m * n >= 1 << 16:
        # numpy's zeroed memory on the CPU: a large block comes from the system already
        # zero, on huge pages, and is faulted in a page at a time where it is written;
        # torch writes the zeros itself, on small pages (measured at (256, 80, 80): 1.2
        # against 1.5 to 8 ms, the most in a solve's alternation with other large blocks)
        out = torch.from_numpy(np.zeros((B, m * n), npd))
    else:
        out = val.new_zeros(B, m * n)
    # in place (autograd records it too): the out-of-place add copied the zeros once more
    out.index_add_(1, idx[0] * n + idx[1], val)
    return out.reshape(B, m, n)


@dataclass
class DenseQP:
    """Dense batched QP: ``H (B, n, n)``, ``f (B, n)``, ``A (B, me, n)``, ``b (B, me)``,
    ``G (B, mi, n)``, ``h (B, mi)`` (bounds already folded into ``G, h``), constant ``c (B,)``."""

    H: Tensor
    f: Tensor
    A: Tensor
    b: Tensor
    G: Tensor
    h: Tensor
    c: Tensor


@dataclass
class SparseQP:
    """One QP per batch element with a shared sparsity pattern (see the module docstring).

    Attributes:
        n: number of variables.
        H_idx, H_val: the full symmetric Hessian, ``(2, nnz)`` and ``(B, nnz)``.
        f: ``(B, n)``; c: ``(B,)`` constant term.
        A_idx, A_val, b: equality constraints ``A z = b``, ``b (B, me)``.
        G_idx, G_val, h: inequality constraints ``G z <= h``, ``h (B, mi)``.
        lb, ub: ``(B, n)`` simple bounds (``-inf``/``inf`` where absent).
        convex: True when ``H`` is known to be positive semidefinite (the transcription
            knows it from its per-node blocks); None when unknown. A convex QP whose
            inequalities are few may be tried as its equality-constrained part first
            (:func:`~torchslq.lqdo.backends.solve_sparse`).
    """

    n: int
    H_idx: Tensor
    H_val: Tensor
    f: Tensor
    c: Tensor
    A_idx: Tensor
    A_val: Tensor
    b: Tensor
    G_idx: Tensor
    G_val: Tensor
    h: Tensor
    lb: Tensor
    ub: Tensor
    convex: bool | None = None

    @property
    def batch(self) -> int:
        return self.f.shape[0]

    @property
    def me(self) -> int:
        return self.b.shape[1]

    @property
    def mi(self) -> int:
        return self.h.shape[1]

    # ------------------------------------------------------------------ evaluation
    def _matvec(self, idx: Tensor, val: Tensor, z: Tensor, m: int) -> Tensor:
        return z.new_zeros(z.shape[0], m).index_add(1, idx[0], val * z[:, idx[1]])

    def objective(self, z: Tensor) -> Tensor:
        """``(B,)`` value ``1/2 z'Hz + f'z + c`` at ``z (B, n)``."""
        Hz = self._matvec(self.H_idx, self.H_val, z, self.n)
        return 0.5 * (z * Hz).sum(-1) + (self.f * z).sum(-1) + self.c

    def residuals(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """``A z - b (B, me)`` and ``G z - h (B, mi)``."""
        return (
            self._matvec(self.A_idx, self.A_val, z, self.me) - self.b,
            self._matvec(self.G_idx, self.G_val, z, self.mi) - self.h,
        )

    # ------------------------------------------------------------------ conversions
    def dense(self, bounds: bool = True) -> DenseQP:
        """Dense batched tensors (differentiable in every field). With ``bounds`` the
        finite simple bounds become rows of ``G z <= h``: rows ``z_j <= ub_j`` and
        ``-z_j <= -lb_j`` for every ``j`` finite in some element, and an element whose
        bound is infinite gets the always-inactive row ``0 z <= 1``."""
        n = self.n
        H = _scatter(self.H_idx, self.H_val, n, n)
        A = _scatter(self.A_idx, self.A_val, self.me, n)
        G = _scatter(self.G_idx, self.G_val, self.mi, n)
        h = self.h
        if bounds:  # the interior point's own rows
            rows = Inequalities(G, self.lb, self.ub)
            G, h = rows.dense(), rows.h_all(h)
        return DenseQP(H=H, f=self.f, A=A, b=self.b, G=G, h=h, c=self.c)

    def scipy(self):
        """The whole batch as one block-diagonal QP in ``scipy.sparse`` CSC form (float64
        numpy): ``P (Bn, Bn)``, ``q``, ``A (Bme, Bn)``, ``b``, ``G (Bmi, Bn)``, ``h``,
        ``lb``, ``ub``. Block-diagonal, so one call of a sparse solver solves the batch."""
        import numpy as np
        import scipy.sparse as sp

        B, n = self.batch, self.n

        def block(idx: Tensor, val: Tensor, m: int):
            off = torch.arange(B, device=idx.device)
            r = (idx[0][None, :] + m * off[:, None]).reshape(-1)
            c = (idx[1][None, :] + n * off[:, None]).reshape(-1)
            v = val.detach().reshape(-1)
            return sp.csc_matrix(
                (
                    v.cpu().double().numpy(),
                    (r.cpu().numpy(), c.cpu().numpy()),
                ),
                shape=(B * m, B * n),
            )

        def flat(t: Tensor):
            return t.detach().reshape(-1).cpu().double().numpy()

        P = block(self.H_idx, self.H_val, n)
        P.sum_duplicates()
        return dict(
            P=P,
            q=flat(self.f),
            A=block(self.A_idx, self.A_val, self.me),
            b=flat(self.b),
            G=block(self.G_idx, self.G_val, self.mi),
            h=flat(self.h),
            lb=flat(self.lb),
            ub=flat(self.ub),
            np=np,
        )

    # ------------------------------------------------------------------ reduction
    def fix(self, mask: Tensor, values: Tensor) -> SparseQP:
        """The QP in the free variables with ``z[:, mask] = values (B, nfix)`` substituted
        (e.g. the static parameters in the two-level method, Sec. 4.2.2).

        The index work (which entries stay, where they go, which move to the right-hand
        side) depends on the pattern and the mask only: it is kept per pattern (the
        transcription keeps one set of index tensors across calls), so a repeated
        substitution only moves values."""
        n = self.n
        plan = _fix_plan(self, mask)
        full = self.f.new_zeros(self.batch, n)
        full[:, mask] = values.to(full)

        def split(part, val: Tensor, m: int):
            keep, drop, drop_rows, drop_cols, kidx = part
            moved = val[:, drop] * full[:, drop_cols]  # A_p p, moved to the rhs
            rhs = val.new_zeros(self.batch, m).index_add(1, drop_rows, moved)
            return kidx, val[:, keep], rhs

        A_idx, A_val, Ab = split(plan["A"], self.A_val, self.me)
        G_idx, G_val, Gh = split(plan["G"], self.G_val, self.mi)
        ww, wp, r_wp, c_wp, pp, r_pp, c_pp, H_idx = plan["H"]
        free = plan["free"]
        f = self.f.index_add(1, r_wp, self.H_val[:, wp] * full[:, c_wp])
        c = (
            self.c
            + (self.f * full).sum(-1)
            + 0.5 * (self.H_val[:, pp] * full[:, r_pp] * full[:, c_pp]).sum(-1)
        )
        return SparseQP(
            n=plan["nf"],
            H_idx=H_idx,
            H_val=self.H_val[:, ww],
            f=f[:, free],
            c=c,
            A_idx=A_idx,
            A_val=A_val,
            b=self.b - Ab,
            G_idx=G_idx,
            G_val=G_val,
            h=self.h - Gh,
            lb=self.lb[:, free],
            ub=self.ub[:, free],
            convex=self.convex,  # H of the free variables: a principal submatrix
        )


def few_inequalities(n: int, m: int) -> bool:
    """Whether ``m`` inequality rows and finite bounds are few for ``n`` variables: a
    convex QP with that few is tried as its equality-constrained part first (one sparse
    LU, kept if its solution satisfies them), since then they are likely all inactive
    (the co-design problems' only bound ``p >= 0``)."""
    return m <= max(1, n // 20)


class TensorKeyedCache:
    """The last ``size`` values computed from some tensors, found again by the tensors'
    identity and version: the entry holds the tensors, so an id is not reused while it
    lives, and an in-place change of one (a new version) misses. For index tensors that
    a transcription keeps while a QP's pattern is unchanged, instead of hashing their
    bytes per QP; with no tensors (``()``), a plain least-recently-used cache by key.
    Thread-safe."""

    def __init__(self, size: int):
        self.size = size
        self._entries: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key, tensors: tuple[Tensor, ...]):
        """The value stored under ``key`` for ``tensors``, or None."""
        stamp = tuple(t._version for t in tensors)
        with self._lock:
            hit = self._entries.get(key)
            if (
                hit is None
                or hit[1] != stamp
                or not all(a is b for a, b in zip(hit[0], tensors, strict=True))
            ):
                return None
            self._entries.move_to_end(key)
            return hit[2]

    def put(self, key, tensors: tuple[Tensor, ...], value) -> None:
        """Store ``value`` under ``key`` for ``tensors`` (their current versions)."""
        stamp = tuple(t._version for t in tensors)
        with self._lock:
            self._entries[key] = (tensors, stamp, value)
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


_FIX_PLANS = TensorKeyedCache(8)  # see _fix_plan


def _fix_plan(qp: SparseQP, mask: Tensor) -> dict:
    """The index part of :meth:`SparseQP.fix` for ``qp``'s pattern and ``mask``, kept for
    the last few patterns (:class:`TensorKeyedCache`: the index tensors' identity and
    version, and the mask's values)."""
    idx = (qp.H_idx, qp.A_idx, qp.G_idx)
    key = (tuple(id(t) for t in idx), qp.n, qp.me, qp.mi, mask.device, mask.cpu().numpy().tobytes())
    plan = _FIX_PLANS.get(key, idx)
    if plan is not None:
        return plan
    n, dev = qp.n, mask.device
    free = ~mask
    new = torch.full((n,), -1, dtype=torch.long, device=dev)
    nf = int(free.sum())
    new[free] = torch.arange(nf, device=dev)

    def split(i: Tensor):
        keep = free[i[1]]
        drop = ~keep
        kidx = torch.stack([i[0][keep], new[i[1][keep]]])
        return keep.nonzero().squeeze(1), drop.nonzero().squeeze(1), i[0][drop], i[1][drop], kidx

    r, cidx = qp.H_idx
    ww = free[r] & free[cidx]
    wp = free[r] & mask[cidx]
    pp = mask[r] & mask[cidx]
    plan = dict(
        nf=nf,
        free=free.nonzero().squeeze(1),
        A=split(qp.A_idx),
        G=split(qp.G_idx),
        H=(
            ww.nonzero().squeeze(1),
            wp.nonzero().squeeze(1),
            r[wp],
            cidx[wp],
            pp.nonzero().squeeze(1),
            r[pp],
            cidx[pp],
            torch.stack([new[r[ww]], new[cidx[ww]]]),
        ),
    )
    _FIX_PLANS.put(key, idx, plan)
    return plan
