"""The Newton systems of the batched interior point (:func:`backends.qp_solve`).

Every iteration of the interior point solves, for each element of the batch,

    [[K, A'], [A, 0]] [dz; dl] = [r1; r2],     K = H + G_all' W G_all,        (*)

where ``G_all = [G; I; -I]`` stacks the general inequalities and the simple bounds and
``W = diag(mu / s)`` changes every iteration while ``H`` and ``A`` do not. Two
formulations, which converge to the same solution:

* :class:`FullKKT`: a Bunch-Kaufman LDL' factorisation of the ``(n + me)``-square matrix
  every iteration; the iterates need not satisfy ``A z = b`` until convergence.
* :class:`ReducedKKT`, the null-space method with variable reduction (Nocedal & Wright,
  *Numerical Optimization*, 2nd ed., Secs. 15.3 and 16.2): one LU factorisation with
  partial pivoting of ``A'`` per QP gives a basis ``Z`` of ``A``'s null space and a
  point with ``A z0 = b``; the iterates stay on ``z0 + range(Z)`` and an iteration
  factors a system of size ``r + mg + n_b`` (``r = n - me`` degrees of freedom, the
  general inequalities and the bounded variables) and takes ``(n, r)`` products only.
  A transcription's defects and boundary conditions leave few degrees of freedom (the
  container crane PS10: ``n = 80``, ``me = 72``, ``r = 8``, ``n_b = 40``: at most 48
  against 152), and for a batch the ``(n, n)`` matrices' memory traffic is what an
  iteration of the full method costs beyond its factorisation.

:func:`newton_system` picks one by the systems' sizes, the reduced one only where ``A``
has full row rank in every element. Both factor with Bunch-Kaufman LDL', so a nonconvex
QP gets the same kind of (saddle-point) step from either.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .._backend import can_use_compiled
from .._backend.dispatch import (
    abs_max_rows_compiled,
    basic_solve_compiled,
    reduced_setup_compiled,
)

__all__ = ["KKT_METHODS", "Inequalities", "FullKKT", "ReducedKKT", "newton_system"]

KKT_METHODS = ("auto", "full", "reduced")

# primal (+) and dual (-) regularisation of the KKT diagonal: keeps LDL' stable when H is
# singular on the constraints' null space only up to rounding
_REG = 1e-13


def _rowmv(M: Tensor, v: Tensor) -> Tensor:
    """``M v`` for ``M (B, m, k)``, ``v (B, k)``, as the row product ``v' M'``: torch runs
    a batch of row-vector products as one GEMM call, 3-5x faster on the CPU than a batch of
    matrix-vector products (measured at ``(256, 80, 8)``)."""
    return (v.unsqueeze(1) @ M.mT).squeeze(1)


def _rowtmv(M: Tensor, v: Tensor) -> Tensor:
    """``M' v`` for ``M (B, m, k)``, ``v (B, m)`` (see :func:`_rowmv`)."""
    return (v.unsqueeze(1) @ M).squeeze(1)


class Inequalities:
    """The inequality rows ``[G; I_u; -I_l] z <= [h; ub_u; -lb_l]`` of the interior point,
    ``u``/``l`` the variables with a finite upper/lower bound in some element (an element
    where it is infinite gets the row ``0 z <= 1``). The bounds stay diagonal: a bound
    costs a diagonal term in the KKT matrix instead of a row of a dense ``G``, and only
    bounded variables have rows.

    Args:
        G: ``(B, mg, n)``; lb, ub: ``(B, n)``, ``-inf``/``inf`` where absent.
    """

    def __init__(self, G: Tensor, lb: Tensor, ub: Tensor) -> None:
        self.G = G
        self.mg, self.n = G.shape[1], G.shape[2]
        fu, fl = torch.isfinite(ub), torch.isfinite(lb)
        self.uidx = fu.any(0).nonzero().squeeze(1)
        self.lidx = fl.any(0).nonzero().squeeze(1)
        self.eu = fu[:, self.uidx].to(G.dtype)  # (B, nu): 1 where the bound is finite
        self.el = fl[:, self.lidx].to(G.dtype)
        self.ub = torch.where(fu, ub, 1.0)[:, self.uidx]
        self.lb = torch.where(fl, lb, -1.0)[:, self.lidx]
        self.nu, self.nl = self.uidx.numel(), self.lidx.numel()
        self.bounded = bool(self.nu + self.nl)
        self.m = self.mg + self.nu + self.nl
        # the variables with some bound, and each bound row's place among them
        self.bidx, inv = torch.unique(torch.cat([self.uidx, self.lidx]), return_inverse=True)
        self.upos, self.lpos = inv[: self.nu], inv[self.nu :]

    def subset(self, idx: Tensor) -> Inequalities:
        """The rows of the elements ``idx`` (the same row layout)."""
        out = object.__new__(Inequalities)
        out.__dict__.update(self.__dict__)
        out.G = self.G[idx]
        out.eu, out.el, out.ub, out.lb = self.eu[idx], self.el[idx], self.ub[idx], self.lb[idx]
        return out

    def h_all(self, h: Tensor) -> Tensor:
        """The right-hand side ``[h; ub_u; -lb_l]`` (B, m)."""
        return torch.cat([h, self.ub, -self.lb], 1) if self.bounded else h

    def mv(self, z: Tensor, Gz: Tensor | None = None) -> Tensor:
        """``G_all z``; ``Gz``: its first ``mg`` rows when already known."""
        parts = [_rowmv(self.G, z) if Gz is None else Gz]
        if self.bounded:
            parts += [self.eu * z[:, self.uidx], -self.el * z[:, self.lidx]]
        return torch.cat(parts, -1)

    def tmv(self, v: Tensor) -> Tensor:
        """``G_all' v``."""
        out = _rowtmv(self.G, v[:, : self.mg])
        if self.bounded:
            mg, nu = self.mg, self.nu
            out = out.index_add(1, self.uidx, self.eu * v[:, mg : mg + nu])
            out = out.index_add(1, self.lidx, -self.el * v[:, mg + nu :])
        return out

    def bound_weights(self, W: Tensor) -> Tensor:
        """The bounds' part of ``G_all' W G_all`` on the bounded variables ``bidx``:
        ``(B, len(bidx))``, a variable's two bounds summed."""
        mg, nu = self.mg, self.nu
        d = W.new_zeros(W.shape[0], self.bidx.numel())
        d = d.index_add(1, self.upos, self.eu * W[:, mg : mg + nu])
        return d.index_add(1, self.lpos, self.el * W[:, mg + nu :])

    def gwg(self, W: Tensor) -> Tensor:
        """``G_all' W G_all`` (B, n, n)."""
        out = self.G.mT @ (W[:, : self.mg].unsqueeze(-1) * self.G)
        if self.bounded:
            out = out.clone()
            out[:, self.bidx, self.bidx] += self.bound_weights(W)
        return out

    def dense(self) -> Tensor:
        """``G_all`` (B, m, n)."""
        if not self.bounded:
            return self.G
        eye = torch.eye(self.n, dtype=self.G.dtype, device=self.G.device)
        Iu = eye[self.uidx] * self.eu.unsqueeze(-1)
        Il = -eye[self.lidx] * self.el.unsqueeze(-1)
        return torch.cat([self.G, Iu, Il], 1)

    def bound_gradients(self, zm: Tensor) -> tuple[Tensor, Tensor]:
        """The gradients with respect to ``lb`` and ``ub`` (B, n) from the adjoint ``zm``
        of the rows (``h_u = ub``, ``h_l = -lb``)."""
        B, n, mg, nu = zm.shape[0], self.n, self.mg, self.nu
        g_ub = zm.new_zeros(B, n).index_copy(1, self.uidx, -self.eu * zm[:, mg : mg + nu])
        g_lb = zm.new_zeros(B, n).index_copy(1, self.lidx, self.el * zm[:, mg + nu :])
        return g_lb, g_ub


class FullKKT:
    """(*) by an LDL' factorisation of the whole KKT matrix each iteration.

    The matrix ``[[K, A'], [A, 0]]`` lives in one buffer: the constraint blocks are
    written once, ``K`` each iteration (building it with ``cat`` took 15% of a batched
    quasilinearization solve)."""

    def __init__(self, H: Tensor, f: Tensor, A: Tensor, b: Tensor, ineq: Inequalities) -> None:
        B, me, n = A.shape
        self.H, self.f, self.A, self.b, self.ineq, self.n = H, f, A, b, ineq, n
        self.buf = H.new_zeros(B, n + me, n + me)
        self.buf[:, :n, n:] = A.mT
        self.buf[:, n:, :n] = A
        self.buf[:, n:, n:].diagonal(dim1=-2, dim2=-1).fill_(-_REG)
        self.eye = torch.eye(n + me, dtype=H.dtype, device=H.device)

    def start(self) -> Tensor:
        """The first iterate ``z (B, n)``."""
        return torch.zeros_like(self.f)

    def residuals(self, z: Tensor, lam: Tensor, t: Tensor | None) -> tuple[Tensor, Tensor]:
        """``rd = Hz + f + A'lam + t`` (``t = G_all' mu``, None: 0) and ``re = Az - b``."""
        rd = _rowmv(self.H, z) + self.f + _rowtmv(self.A, lam)
        if t is not None:
            rd = rd + t
        return rd, _rowmv(self.A, z) - self.b

    def advance(self, alpha: Tensor) -> None:
        """The loop moved along the last direction by ``alpha (B, 1)`` (nothing kept)."""

    def stalled(self, s: Tensor, h: Tensor) -> Tensor | None:
        """Elements to hand over to :class:`FullKKT` (None: none, this is it)."""
        return None

    def multipliers(self, z: Tensor, lam: Tensor, t: Tensor | None) -> Tensor:
        """The equality multipliers at the end (the iterated ones)."""
        return lam

    def factor(self, W: Tensor | None, done: Tensor) -> None:
        """Factor for the weights ``W (B, mi)`` (None: no inequalities). An element that
        is ``done`` factors the identity (its step is discarded)."""
        n = self.n
        self.buf[:, :n, :n] = self.H + self.ineq.gwg(W) if W is not None else self.H
        self.buf[:, :n, :n].diagonal(dim1=-2, dim2=-1).add_(_REG)
        K = torch.where(done[:, None, None], self.eye, self.buf) if bool(done.any()) else self.buf
        # the KKT matrix is symmetric (indefinite): Bunch-Kaufman LDL'. (Batched LU of
        # larger matrices after torch.set_num_threads has returned invalid pivots with
        # this torch/MKL build; LDL' is also half the work.)
        self.LD, self.piv, _ = torch.linalg.ldl_factor_ex(K)

    def solve(self, r1: Tensor, r2: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """``(dz (B, n), dl (B, me), Gdz)`` of (*) for ``r1 (B, n)``, ``r2 (B, me)``;
        ``Gdz``, the general inequalities' rows of the step, None: ``G dz``."""
        rhs = torch.cat([r1, r2], -1).unsqueeze(-1)
        sol = torch.linalg.ldl_solve(self.LD, self.piv, rhs).squeeze(-1)
        return sol[:, : self.n], sol[:, self.n :], None


class ReducedKKT:
    """(*) on the affine subspace ``A z = b``, by variable reduction.

    ``A' = P L U`` (partial pivoting; ``L = [L1; L2]``, ``L1`` unit lower triangular
    ``me``-square, ``U`` upper triangular): in the permuted variables ``y = P'z`` the
    first ``me`` are basic, and ``A z = 0`` iff ``y1 = -L1^{-T} L2' y2``, so
    ``Z = P [-L1^{-T} L2'; I]`` spans the null space and ``P [L1^{-T} U^{-T} b; 0]`` is
    feasible; the iterates start at the feasible point of least norm (as the full method
    starts at 0) and move by ``dz = Z dw``, so they stay feasible (``r2 = 0``) and

        (Z'KZ) dw = Z' r1,     Z'KZ = Z'HZ + C' diag(w) C,     C = [G Z; Z_b],

    with ``Z_b`` the rows of ``Z`` of the variables with a bound and ``w`` the
    inequalities' weights (a variable's two bounds summed). Near the solution an active
    row's weight grows without bound, and folded into ``Z'KZ`` it would swamp the other
    directions in rounding, so rows with ``w > 1`` are kept as the augmented system

        [[Z'HZ + C_s' diag(w_s) C_s, C_l'], [C_l, -diag(1 / w_l)]] [dw; v] = [Z' r1; 0]

    (``s``/``l``: small/large weights), factored by LDL' like the full KKT matrix but of
    size ``r + k`` instead of ``n + me`` (``k <= mg + n_b`` the most large rows of an
    element: those of the active set near the solution). ``Z'HZ``, ``C`` and ``HZ`` are
    formed once per QP; ``Hz`` is carried along (``H dz = (HZ) dw``), so an iteration
    takes no ``(n, n)`` product.

    The stationarity residual is reported with the multipliers that zero its basic part,
    ``lam = -U^{-1} L1^{-1} (P'g)_1`` for ``g = Hz + f + G_all' mu``: then
    ``P'rd = [0; Z'g]``, so ``Z'g`` is its whole size."""

    def __init__(
        self, H: Tensor, f: Tensor, A: Tensor, b: Tensor, ineq: Inequalities, lu,
        target: Tensor | None = None,
    ) -> None:  # fmt: skip
        B, me, n = A.shape
        r = n - me
        LU, perm = lu
        self.f, self.ineq = f, ineq
        self.basic, self.free = perm[:, :me], perm[:, me:]
        self.LU = LU
        self.mg = ineq.mg
        self.bidx = ineq.bidx  # the variables with a bound in some element
        self.r = r
        self.re = f.new_zeros(B, me)
        # the start z0: the point of A z = b nearest target (0: the least-norm point)
        target = torch.zeros_like(f) if target is None else target
        self.compiled = H.dtype == torch.float64 and B > 0 and can_use_compiled(LU, H, b, ineq.G)
        if self.compiled:
            # the same formulas per element in one compiled loop, reading LU in place
            self.Z, self.z0, self.HZ, self.ZHZ, self.C, self.Hz = reduced_setup_compiled(
                LU, perm, H, b, ineq.G, self.bidx, target
            )
        else:
            self._setup(H, f, b, LU, perm, target)
        self.mc = self.C.shape[1]
        self.eye = torch.eye(r + self.mc, dtype=H.dtype, device=H.device)

    def _setup(
        self, H: Tensor, f: Tensor, b: Tensor, LU: Tensor, perm: Tensor, target: Tensor
    ) -> None:  # fmt: skip
        """``Z``, ``z0``, ``HZ``, ``Z'HZ``, ``C`` and ``H z0`` as batched torch ops."""
        B, n, me = LU.shape
        r = self.r
        ineq = self.ineq
        # the square LU of the basic rows, L1 U, with its pivoting already applied
        # (column-major, as LAPACK takes it: the slice of LU is not, and each solve with
        # it copied it, 6 ms a time at (256, 72, 72))
        self.LU1 = LU[:, :me, :].mT.contiguous().mT
        # Z in the permuted rows, [-L1^{-T} L2'; I], scattered back to z's order, and the
        # basic solution y1 = L1^{-T} U^{-T} b, from one triangular solve
        # (trsm reads only the triangle named: no triu copy)
        c = torch.linalg.solve_triangular(self.LU1.mT, b.unsqueeze(-1), upper=False)
        rhs = torch.cat([LU[:, me:, :].mT, c], -1)
        sol = torch.linalg.solve_triangular(self.LU1.mT, rhs, upper=True, unitriangular=True)
        eye = torch.eye(r, dtype=H.dtype, device=H.device)
        Zy = torch.cat([-sol[:, :, :r], eye.expand(B, r, r)], 1)
        self.Z = torch.empty_like(Zy).scatter_(1, perm.unsqueeze(-1).expand(B, n, r), Zy)
        z0 = torch.zeros_like(f).scatter_(1, self.basic, sol[:, :, r])
        # nearest target on z0 + range(Z): z0 - Z (Z'Z)^{-1} Z'(z0 - target)
        ZtZ = self.Z.mT @ self.Z
        w0 = torch.linalg.solve(ZtZ, self.Z.mT @ (z0 - target).unsqueeze(-1))
        self.z0 = z0 - (self.Z @ w0).squeeze(-1)
        self.HZ = H @ self.Z
        self.ZHZ = self.Z.mT @ self.HZ
        self.Hz = _rowmv(H, self.z0)
        parts = [ineq.G @ self.Z] if ineq.mg else []
        if self.bidx.numel():
            parts.append(self.Z[:, self.bidx, :])
        self.C = torch.cat(parts, 1) if parts else H.new_zeros(B, 0, r)

    def start(self) -> Tensor:
        return self.z0

    def residuals(self, z: Tensor, lam: Tensor, t: Tensor | None) -> tuple[Tensor, Tensor]:
        g = self.Hz + self.f if t is None else self.Hz + self.f + t
        gr = _rowtmv(self.Z, g)
        # rd with the basic multipliers: zero on the basic variables, Z'g on the others
        rd = torch.zeros_like(g).scatter_(1, self.free, gr)
        return rd, self.re

    def factor(self, W: Tensor | None, done: Tensor) -> None:
        r = self.r
        M = self.ZHZ
        self.k = 0
        if self.mc:
            parts = [W[:, : self.mg]] if self.mg else []
            if self.bidx.numel():
                parts.append(self.ineq.bound_weights(W))
            w = torch.cat(parts, 1) if len(parts) > 1 else parts[0]
            large = w > 1.0
            M = M + self.C.mT @ (torch.where(large, 0.0, w).unsqueeze(-1) * self.C)
            # only the rows with large weights are augmented: the k largest per element,
            # k the most any element has (an element's surplus rows are decoupled)
            self.k = k = int(large.sum(-1).max())
            if k:
                wl, self.sel = w.topk(k, dim=-1)
                self.on = wl > 1.0
                self.wl = torch.where(self.on, wl, 1.0)
                Cl = self.C.gather(1, self.sel.unsqueeze(-1).expand(-1, -1, r))
                Cl = torch.where(self.on.unsqueeze(-1), Cl, 0.0)
                d = torch.where(self.on, -1.0 / self.wl, -1.0)
        M = M + _REG * self.eye[:r, :r]
        if self.k:
            K = torch.cat([torch.cat([M, Cl.mT], -1), torch.cat([Cl, torch.diag_embed(d)], -1)], -2)
        else:
            K = M
        if bool(done.any()):
            K = torch.where(done[:, None, None], self.eye[: r + self.k, : r + self.k], K)
        self.LD, self.piv, _ = torch.linalg.ldl_factor_ex(K)

    def solve(self, r1: Tensor, r2: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """``dz`` for ``r2 = 0`` (the iterates are feasible); the multipliers' step is
        not needed (they are recovered at the end), so ``dl`` is returned as 0.

        A row with a large weight takes its step from the augmented solution ``v``
        (``(C dz)_l = v_l / w_l``), not from ``C Z dw``: that difference of ``O(|dw|)``
        terms has an absolute error ``eps |dw|``, which the weight, up to ``1 / tol``,
        would turn into an ``O(1)`` error in the multipliers' step."""
        B, r, k = r1.shape[0], self.r, self.k
        g = _rowtmv(self.Z, r1).unsqueeze(-1)
        if k:
            g = torch.cat([g, g.new_zeros(B, k, 1)], 1)
        sol = torch.linalg.ldl_solve(self.LD, self.piv, g).squeeze(-1)
        dw = sol[:, :r]
        self.Hdz = _rowmv(self.HZ, dw)
        dz = _rowmv(self.Z, dw)
        Gdz = _rowmv(self.C[:, : self.mg], dw) if self.mg else None
        if k:
            # (C dz) of the augmented rows, NaN elsewhere (kept from C Z dw)
            cl = torch.where(self.on, sol[:, r:] / self.wl, float("nan"))
            cdz = torch.full((B, self.mc), float("nan"), dtype=dz.dtype, device=dz.device)
            cdz = cdz.scatter(1, self.sel, cl)
            if self.mg:
                Gdz = torch.where(cdz[:, : self.mg].isnan(), Gdz, cdz[:, : self.mg])
            if self.bidx.numel():
                idx = self.bidx.expand(B, -1)
                cb = cdz[:, self.mg :]
                dz = dz.scatter(1, idx, torch.where(cb.isnan(), dz.gather(1, idx), cb))
        return dz, self.re, Gdz

    def advance(self, alpha: Tensor) -> None:
        self.Hz = self.Hz + alpha * self.Hdz

    def stalled(self, s: Tensor, h: Tensor) -> Tensor | None:
        """Elements with a slack at the rounding level of its row: below it the reduced
        step's error, ``eps |dw|`` in an active row, exceeds the slack, and the Mehrotra
        step inflates that row's multiplier instead of closing the gap (seen on the
        container crane PS10: the gap stalled at 1.4e-10 against a tolerance of 1e-10
        while the multiplier grew to 1e13). They finish with :class:`FullKKT`."""
        if s.shape[-1] == 0:
            return None
        return (s < 10 * torch.finfo(s.dtype).eps * (1 + h.abs())).any(-1)

    def multipliers(self, z: Tensor, lam: Tensor, t: Tensor | None) -> Tensor:
        g = self.Hz + self.f if t is None else self.Hz + self.f + t
        gb = torch.gather(g, 1, self.basic)
        if self.compiled:
            return basic_solve_compiled(self.LU, gb.contiguous())
        B, me = gb.shape
        ident = torch.arange(1, me + 1, dtype=torch.int32, device=g.device).expand(B, me)
        return -torch.linalg.lu_solve(self.LU1, ident, gb.unsqueeze(-1)).squeeze(-1)


def _permutation(piv: Tensor, n: int) -> Tensor:
    """``perm (B, n)`` with row ``i`` of ``L U`` = row ``perm[i]`` of the factored matrix,
    from LAPACK's sequential row interchanges ``piv (B, k)`` (1-based): ``k`` batched
    swaps in numpy (a few microseconds each, where a torch indexing op costs tens)
    instead of building the ``(B, n, n)`` permutation matrix."""
    j = piv.cpu().numpy().astype(np.int64) - 1
    B, k = j.shape
    perm = np.tile(np.arange(n), (B, 1))
    rows = np.arange(B)
    for i in range(k):
        ji = j[:, i]
        pi = perm[:, i].copy()
        perm[:, i] = perm[rows, ji]
        perm[rows, ji] = pi
    return torch.from_numpy(perm).to(piv.device)


def _lu_factor(M: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``torch.linalg.lu_factor_ex(M)``; on the CPU in float64 into numpy's memory (a
    large block from the system, on huge pages: see :func:`.qp._scatter`), column-major
    as LAPACK writes it."""
    graph = torch.is_grad_enabled() and M.requires_grad  # (out= records no graph)
    if M.is_cpu and M.dtype == torch.float64 and M.numel() >= 1 << 16 and not graph:
        B, n, k = M.shape
        LU = torch.from_numpy(np.empty((B, k, n))).mT
        piv = torch.empty(B, min(n, k), dtype=torch.int32)
        info = torch.empty(B, dtype=torch.int32)
        return torch.linalg.lu_factor_ex(M, out=(LU, piv, info))
    return torch.linalg.lu_factor_ex(M)


def newton_system(
    H: Tensor, f: Tensor, A: Tensor, b: Tensor, ineq: Inequalities, method: str = "auto",
    target: Tensor | None = None,
) -> FullKKT | ReducedKKT:  # fmt: skip
    """The solver of (*) for ``H (B, n, n)``, ``f (B, n)``, ``A (B, me, n)``,
    ``b (B, me)``; ``target (B, n)``: where the reduced system's start ``z0`` is the
    point of ``A z = b`` nearest it (None: the least-norm point; a warm start).

    ``method``: ``"full"``, ``"reduced"`` or ``"auto"`` (reduced where ``0 < me < n``,
    ``A`` has full row rank in every element and the reduced system, of size
    ``r + mg + n_b`` (``n_b`` the variables with a bound), is at most 0.6 times the
    size of (*), a fifth of its factorisation's flops; float64 only). ``"reduced"``
    where it does not apply is a ``ValueError``."""
    if method not in KKT_METHODS:
        raise ValueError(f"method must be one of {KKT_METHODS}; got {method!r}")
    B, me, n = A.shape
    r = n - me
    if method == "full" or me == 0 or r <= 0:
        if method == "reduced":
            raise ValueError(f"the reduced method needs 0 < me < n; got me={me}, n={n}")
        return FullKKT(H, f, A, b, ineq)
    nb = ineq.bidx.numel()
    # float32: on the container crane PS10 (more bounds active than degrees of freedom)
    # the reduced method stalled with non-finite weights where the full one converged
    if method == "auto" and (r + ineq.mg + nb > 0.6 * (n + me) or A.dtype != torch.float64):
        return FullKKT(H, f, A, b, ineq)
    LU, piv, info = _lu_factor(A.mT)
    perm = _permutation(piv, n)
    diag = LU.diagonal(dim1=-2, dim2=-1).abs()
    if can_use_compiled(A):  # one pass (crane PS10, B = 256: 2.6 ms -> 1 ms a QP)
        scale = abs_max_rows_compiled(A)
    else:  # (amax and amin: a third of aminmax's time on this CPU build)
        lo, hi = A.reshape(B, -1).amin(-1), A.reshape(B, -1).amax(-1)
        scale = torch.maximum(hi, -lo)
    scale = scale.clamp_min(torch.finfo(A.dtype).tiny)
    # a tiny pivot flags a (nearly) dependent row of A
    deficient = bool((diag.amin(-1) <= 10 * n * torch.finfo(A.dtype).eps * scale).any())
    if deficient or bool((info != 0).any()):
        if method == "reduced":
            raise ValueError("the reduced method needs A of full row rank in every element")
        return FullKKT(H, f, A, b, ineq)
    return ReducedKKT(H, f, A, b, ineq, (LU, perm), target)
