"""Parallel-in-time LQ: the Riccati recursion and the rollouts as associative scans.

Särkkä & García-Fernández, "Temporal parallelization of dynamic programming and linear
quadratic control", IEEE TAC 68(2), 2023 (arXiv:2104.03186). The sequential kernel
(:mod:`torchslq.lq.riccati`) runs ``T`` dependent steps; here the same quantities come
from ``O(log T)`` levels of batched torch ops over ``(B, T)``, so the span of a solve no
longer grows linearly with the horizon (what matters on a GPU for ``T`` in the
thousands; on the CPU the compiled sequential kernel does less work and stays faster,
see ``docs/scale.md``).

The problem is the one of :func:`torchslq.lqr_solve` (per batch element)::

    min  sum_{t<T} [ 1/2 x'Q_t x + 1/2 u'R_t u + u'S_t x + q_t'x + r_t'u ]
         + 1/2 x_T'Q_T x_T + q_T'x_T
    s.t. x_{t+1} = A_t x_t + B_t u_t + c_t,   x_0 = x0

Backward pass (the value functions)
-----------------------------------
(Equation labels (S1)-(S5) are this module's; the paper's constructs are named, not
numbered.) Step ``t`` is the paper's conditional value function element of the LQ
tracking problem, ``V_{t->t+1}(x, y) = max_lam 1/2 x'J x - eta'x + lam'(A~ x + b - y)
- 1/2 lam'C lam`` (plus a constant), obtained by eliminating ``u`` (here with the cross
term ``S`` and the linear term ``r`` of our cost)::  (S1)

    A~_t = A_t - B_t R_t^{-1} S_t        b_t  = c_t - B_t R_t^{-1} r_t
    C_t  = B_t R_t^{-1} B_t'             eta_t = S_t' R_t^{-1} r_t - q_t
    J_t  = Q_t - S_t' R_t^{-1} S_t

and the terminal element is ``(0, 0, 0, -q_T, Q_T)``. Two consecutive segments
``i->j`` and ``j->k`` combine by the paper's associative operator for these elements
(with ``W = (I + C_ij J_jk)^{-1}``)::  (S2)

    A_ik = A_jk W A_ij                 b_ik = A_jk W (b_ij + C_ij eta_jk) + b_jk
    C_ik = A_jk W C_ij A_jk' + C_jk    eta_ik = A_ij' W' (eta_jk - J_jk b_ij) + eta_ij
    J_ik = A_ij' W' J_jk A_ij + J_ij

(``W' = (I + J_jk C_ij)^{-1}`` since ``C`` and ``J`` are symmetric, so one LU serves
both). The suffix combination ``a_t ⊗ a_{t+1} ⊗ ... ⊗ a_T`` (a reverse associative scan)
is the value function of step ``t``: ``V_t = J``, ``v_t = -eta`` (S3). The gains then
follow at every step at once (``Quu = R + B'V_{t+1} B``, ``K = -Quu^{-1} Qux``, ``k =
-Quu^{-1} qu``, a batched Cholesky over ``(B, T)``) (S4), and so does the value's constant
term (a reverse cumulative sum).

Forward pass (the states)
-------------------------
The closed loop ``x_{t+1} = (A_t + B_t K_t) x_t + (B_t k_t + c_t)`` is a composition of
affine maps (the paper's parallel forward pass), a prefix scan of ``(M, a)`` pairs with
``(M_2, a_2) ∘ (M_1, a_1) = (M_2 M_1, M_2 a_1 + a_2)``; ``x_0`` is folded into the first
element (S5). The implicit backward pass of :func:`torchslq.lqr_solve` (one more LQ solve
with the same quadratic terms, :func:`lq_adjoint_scan`) is two more affine scans.

The scan (:func:`associative_scan`) is the odd-even recursion of Blelloch (1990) as in
``jax.lax.associative_scan``: ``O(T)`` combinations in ``2 log2 T`` levels, each level a
handful of batched ops over ``(B, T / 2^level)``; the Python loop runs over the levels,
never over the batch or the time steps.

On a GPU with Triton (and ``n, m <= 4``) the per-element work of each level, the
elements, the gains and the closed loop run in fused kernels generated from the same
equations (:mod:`.scan_kernels`); elsewhere, and for larger sizes, as the torch ops below.

Per-element failures: a ``Quu`` (or ``R``) that is not positive definite, a singular
``I + C J`` or non-finite numbers make the element's scan result meaningless; such
elements (and only they: a host synchronisation to find them) are recomputed by the
sequential kernel, so the factors, ``failed`` flags and statuses are exactly those of
the sequential path for them, and the other elements are untouched.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .._shapes import broadcast_shapes
from . import scan_kernels
from .riccati import (
    RiccatiFactors,
    chol_solve,
    cholesky,
    homogeneous_cost,
    homogeneous_dynamics,
    riccati_homogeneous,
    with_time,
)

__all__ = [
    "associative_scan",
    "lq_adjoint_scan",
    "riccati_scan",
    "riccati_scan_homogeneous",
    "rollout_scan",
    "rollout_scan_homogeneous",
]

Elems = tuple[Tensor, ...]
Combine = Callable[[Elems, Elems], Elems]


# ----------------------------------------------------------------------------- the scan


def _fused_or_torch_ops(fn):
    """Runs ``fn`` again (as torch ops) if one of its fused kernels fails to build: the
    failure switches them off for the process (:mod:`.scan_kernels`)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except scan_kernels.FusedKernelError:
            return fn(*args, **kwargs)

    return wrapper


def associative_scan(combine: Combine, elems: Sequence[Tensor], reverse: bool = False) -> Elems:
    """Inclusive associative scan along dim 1 (time) of a tuple of batch-first tensors.

    Args:
        combine: ``combine(earlier, later) -> combined``, associative, batched over the
            leading dims ``(B, T')`` of every tensor of the tuples.
        elems: tensors ``(B, T, ...)`` with the same ``B`` and ``T`` (the elements).
        reverse: False: ``out_t = e_0 ⊗ ... ⊗ e_t`` (prefix); True:
            ``out_t = e_t ⊗ ... ⊗ e_{T-1}`` (suffix), still with ``combine(earlier,
            later)``.

    Returns:
        a tuple of tensors shaped as ``elems``. ``O(T)`` calls of ``combine`` on slices
        in ``2 ceil(log2 T)`` levels (odd-even recursion, Blelloch 1990).
    """
    elems = tuple(elems)
    # the suffix scan runs on the elements in place, not on flipped copies (a flip copies
    # every element twice, a sixth of the scan's peak memory); same pairs, same order
    return _suffix(combine, elems) if reverse else _prefix(combine, elems)


def _prefix(combine: Combine, elems: Elems) -> Elems:
    T = elems[0].shape[1]
    if T < 2:
        return elems
    pairs = combine(tuple(e[:, 0 : T - 1 : 2] for e in elems), tuple(e[:, 1::2] for e in elems))
    odd = _prefix(combine, pairs)  # the results at positions 1, 3, 5, ...
    n_even = (T - 1) // 2  # positions 2, 4, ... (position 0 is its own result)
    if n_even > 0:
        rest = combine(tuple(o[:, :n_even] for o in odd), tuple(e[:, 2::2] for e in elems))
    out = []
    for i, e in enumerate(elems):
        full = torch.empty_like(e)
        full[:, 0] = e[:, 0]
        full[:, 1::2] = odd[i]
        if n_even > 0:
            full[:, 2::2] = rest[i]
        out.append(full)
    return tuple(out)


def _suffix(combine: Combine, elems: Elems) -> Elems:
    """``out_t = e_t ⊗ ... ⊗ e_{T-1}``: :func:`_prefix` mirrored. The pairs are the last
    two elements, the two before them, ...: ``(s + 2k, s + 2k + 1)`` with ``s = T mod 2``
    (element 0 alone when ``T`` is odd), all ascending slices."""
    T = elems[0].shape[1]
    if T < 2:
        return elems
    s = T % 2
    pairs = combine(tuple(e[:, s::2] for e in elems), tuple(e[:, s + 1 :: 2] for e in elems))
    head = _suffix(combine, pairs)  # the results at positions s, s + 2, ...
    n_odd = (T - s) // 2 - 1  # positions s + 1, s + 3, ..., T - 3 (T - 1 is its own)
    if n_odd > 0:
        rest = combine(tuple(e[:, s + 1 : T - 2 : 2] for e in elems), tuple(h[:, 1:] for h in head))
    if s:
        first = combine(tuple(e[:, :1] for e in elems), tuple(h[:, :1] for h in head))
    out = []
    for i, e in enumerate(elems):
        full = torch.empty_like(e)
        full[:, T - 1] = e[:, T - 1]
        full[:, s::2] = head[i]
        if n_odd > 0:
            full[:, s + 1 : T - 2 : 2] = rest[i]
        if s:
            full[:, :1] = first[i]
        out.append(full)
    return tuple(out)


# ----------------------------------------------------------------------------- operators


def _combine_value(e1: Elems, e2: Elems) -> Elems:
    """The paper's associative operator (S2): ``e1`` is the segment
    ``i->j`` (earlier), ``e2`` the segment ``j->k``; each is ``(A, b, C, eta, J, bad)``
    with ``A, C, J (B, T', n, n)``, ``b, eta (B, T', n)`` and ``bad (B, T')`` bool (a
    singular ``I + C J`` met on the way)."""
    A1, b1, C1, eta1, J1, bad1 = e1
    A2, b2, C2, eta2, J2, bad2 = e2
    n = A1.shape[-1]
    if scan_kernels.enabled(A1, n):
        return scan_kernels.combine_value(e1, e2)
    eye = torch.eye(n, dtype=A1.dtype, device=A1.device)
    CX = C1 @ torch.cat([J2, eta2.unsqueeze(-1), A2.mT], -1)  # C1 [J2, eta2, A2']
    LU, piv, info = torch.linalg.lu_factor_ex(eye + CX[..., :n])
    rhs = torch.cat([A1, (b1 + CX[..., n]).unsqueeze(-1), CX[..., n + 1 :]], -1)
    AX = A2 @ torch.linalg.lu_solve(LU, piv, rhs)  # A2 W [A1, b1 + C1 eta2, C1 A2']
    A = AX[..., :n]
    b = AX[..., n] + b2
    C = AX[..., n + 1 :] + C2
    JX = J2 @ torch.cat([A1, b1.unsqueeze(-1)], -1)  # J2 [A1, b1]
    rhs2 = torch.cat([JX[..., :n], (eta2 - JX[..., n]).unsqueeze(-1)], -1)
    AY = A1.mT @ torch.linalg.lu_solve(LU, piv, rhs2, adjoint=True)  # A1' W' [..]
    J = AY[..., :n] + J1
    eta = AY[..., n] + eta1
    bad = bad1 | bad2 | (info != 0)
    return A, b, 0.5 * (C + C.mT), eta, 0.5 * (J + J.mT), bad


def _combine_affine(e1: Elems, e2: Elems) -> Elems:
    """Composition of affine maps ``y = M x + a``: ``e2 ∘ e1`` (``e1`` applied first);
    ``M (B, T', p, p)``, ``a (B, T', p)``."""
    M1, a1 = e1
    M2, a2 = e2
    if scan_kernels.enabled(M1, M1.shape[-1]):
        return scan_kernels.combine_affine(e1, e2)
    return M2 @ M1, (M2 @ a1.unsqueeze(-1))[..., 0] + a2


def _affine_recursion(M: Tensor, a: Tensor, start: Tensor, reverse: bool = False) -> Tensor:
    """All states of ``y_{t+1} = M_t y_t + a_t`` from ``y_0 = start`` (forward) or of
    ``y_t = M_t y_{t+1} + a_t`` from ``y_T = start`` (``reverse``), by one scan.

    ``M (B, T, p, p)``, ``a (B, T, p)``, ``start (B, p)`` (batches broadcast). Returns
    ``(B, T+1, p)``, ``start`` included (at index 0, or ``T`` when ``reverse``).
    """
    T = M.shape[1]
    batch = broadcast_shapes(M.shape[:1], a.shape[:1], start.shape[:1])
    M = M.expand(*batch, *M.shape[1:])
    a = a.expand(*batch, *a.shape[1:])
    start = start.expand(*batch, start.shape[-1])
    i = T - 1 if reverse else 0
    # fold the known end into the element next to it: that element maps anything to
    # its result, so every scan result is a state
    first = (M[:, i] @ start.unsqueeze(-1))[..., 0] + a[:, i]
    a = torch.cat([a[:, :i], first.unsqueeze(1), a[:, i + 1 :]], 1)
    M = torch.cat([M[:, :i], torch.zeros_like(M[:, i : i + 1]), M[:, i + 1 :]], 1)
    if reverse:
        _, y = associative_scan(lambda e1, e2: _combine_affine(e2, e1), (M, a), reverse=True)
        return torch.cat([y, start.unsqueeze(1)], 1)
    _, y = associative_scan(_combine_affine, (M, a))
    return torch.cat([start.unsqueeze(1), y], 1)


# ----------------------------------------------------------------------------- the kernel


def _split(F: Tensor, H: Tensor, VhT: Tensor):
    """Views of the LQ data inside the homogeneous ``F``, ``H``, ``VhT``."""
    n = F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    Bm, A, c = F[..., :n, :m], F[..., :n, m : m + n], F[..., :n, -1]
    R, S, r = H[..., :m, :m], H[..., :m, m : m + n], H[..., :m, -1]
    Q, q = H[..., m : m + n, m : m + n], H[..., m : m + n, -1]
    QT, qT = VhT[..., :n, :n], VhT[..., :n, n]
    return A, Bm, c, Q, R, S, q, r, QT, qT


def _value_scan(F: Tensor, H: Tensor, VhT: Tensor, batch: torch.Size) -> tuple[Tensor, ...]:
    """Value functions ``V (B, T+1, n, n)``, ``v (B, T+1, n)`` by the reverse scan of
    the paper's elements (S1)-(S3), and ``(B,)`` bool: some ``R`` not
    positive definite or some ``I + C J`` singular in the element."""
    n = F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    fused = scan_kernels.enabled(F, n, m)
    elems = (_value_elements_fused if fused else _value_elements)(F, H, VhT, batch[0])
    _, _, _, eta_s, J_s, bad_s = associative_scan(_combine_value, elems, reverse=True)
    return J_s, -eta_s, bad_s.any(1)


def _value_elements(F: Tensor, H: Tensor, VhT: Tensor, nb: int) -> Elems:
    """The elements (S1) of every step and the terminal one, ``(B, T+1, ...)``."""
    A, Bm, c, Q, R, S, q, r, QT, qT = _split(F, H, VhT)
    n = A.shape[-1]
    A, Bm, c, Q, R, S, q, r = (t.expand(nb, *t.shape[1:]) for t in (A, Bm, c, Q, R, S, q, r))
    Lr, info_r = cholesky(R)
    # R^{-1} [B', S, r]: the control eliminated from each step (S1)
    W = chol_solve(torch.cat([Bm.mT, S, r.unsqueeze(-1)], -1), Lr)
    WB, WS, Wr = W[..., :n], W[..., n : 2 * n], W[..., 2 * n]
    At = A - Bm @ WS
    b = c - (Bm @ Wr.unsqueeze(-1))[..., 0]
    C = Bm @ WB
    eta = (S.mT @ Wr.unsqueeze(-1))[..., 0] - q
    J = Q - S.mT @ WS
    bad = info_r != 0  # (B, T)
    # the terminal element (0, 0, 0, -q_T, Q_T)
    QT = QT.expand(nb, n, n).unsqueeze(1)
    qT = qT.expand(nb, n).unsqueeze(1)
    zero = torch.zeros_like(QT)
    return (
        torch.cat([At, zero], 1),
        torch.cat([b, torch.zeros_like(qT)], 1),
        torch.cat([0.5 * (C + C.mT), zero], 1),
        torch.cat([eta, -qT], 1),
        torch.cat([0.5 * (J + J.mT), 0.5 * (QT + QT.mT)], 1),
        torch.cat([bad, bad.new_zeros(nb, 1)], 1),
    )


def _value_elements_fused(F: Tensor, H: Tensor, VhT: Tensor, nb: int) -> Elems:
    """:func:`_value_elements` by one fused kernel (:mod:`.scan_kernels`)."""
    T, n = F.shape[1], F.shape[-2] - 1
    QT, qT = VhT[..., :n, :n], VhT[..., :n, n]
    kw = {"dtype": F.dtype, "device": F.device}
    elems = (
        torch.empty(nb, T + 1, n, n, **kw),
        torch.empty(nb, T + 1, n, **kw),
        torch.empty(nb, T + 1, n, n, **kw),
        torch.empty(nb, T + 1, n, **kw),
        torch.empty(nb, T + 1, n, n, **kw),
        torch.empty(nb, T + 1, dtype=torch.bool, device=F.device),
    )
    scan_kernels.value_elements(
        F.expand(nb, *F.shape[1:]), H.expand(nb, *H.shape[1:]), [e[:, :T] for e in elems]
    )
    # the terminal element (0, 0, 0, -q_T, Q_T)
    for e in (elems[0], elems[1], elems[2], elems[5]):
        e[:, T] = 0
    elems[3][:, T] = -qT
    elems[4][:, T] = 0.5 * (QT + QT.mT)  # the kernels read the upper triangles of C and J
    return elems


@_fused_or_torch_ops
def riccati_scan_homogeneous(F: Tensor, H: Tensor, VhT: Tensor) -> RiccatiFactors:
    """The factors of :func:`torchslq.lq.riccati_homogeneous` (no regularisation, hook or
    bounds) by the parallel-in-time backward pass.

    Args:
        F: ``(Bf, T, n+1, m+n+1)`` homogeneous dynamics.
        H: ``(Bh, T, m+n+1, m+n+1)`` homogeneous stage costs (symmetric).
        VhT: ``(Bv, n+1, n+1)`` terminal value matrix.

    Returns:
        :class:`~torchslq.lq.RiccatiFactors` ``(Kk, Vh, chol, failed)`` with the batch
        ``B`` of the broadcast ``Bf, Bh, Bv``: the same quantities as the sequential
        pass (``tests/test_parallel_lq.py`` checks them against it and a dense KKT
        solve). Elements whose scan failed are recomputed by the sequential pass (module
        docstring), so ``failed`` is the sequential pass's.
    """
    T = F.shape[-3]
    n = F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    batch = broadcast_shapes(F.shape[:-3], H.shape[:-3], VhT.shape[:-2])
    if len(batch) != 1:
        raise ValueError(f"F, H, VhT must have one batch dim, got batch shape {tuple(batch)}")
    nb = batch[0]
    if T == 0:
        return riccati_homogeneous(F, H, VhT)
    V, v, bad = _value_scan(F, H, VhT, batch)
    Vh_top = torch.cat([V, v.unsqueeze(-1)], -1)  # (B, T+1, n, n+1): rows :n of Vh
    Kk, L, failed, inc = _gains(F, H, V, v, Vh_top, nb)
    cornerT = VhT[..., n, n].expand(nb)
    corner = cornerT.unsqueeze(1) + inc.flip(1).cumsum(1).flip(1)  # (B, T)
    corner = torch.cat([corner, cornerT.unsqueeze(1)], 1)
    bottom = torch.cat([v, corner.unsqueeze(-1)], -1).unsqueeze(-2)  # (B, T+1, 1, n+1)
    Vh = torch.cat([Vh_top, bottom], -2)
    redo = (
        bad | failed | ~torch.isfinite(Kk).flatten(1).all(1) | ~torch.isfinite(Vh).flatten(1).all(1)
    )
    fac = RiccatiFactors(Kk=Kk, Vh=Vh, chol=L.expand(nb, T, m, m), failed=failed)
    if bool(redo.any()):  # one host sync; rare: failed elements only
        fac = _sequential_rows(F, H, VhT, fac, redo.nonzero().squeeze(1))
    return fac


def _gains(F: Tensor, H: Tensor, V: Tensor, v: Tensor, Vh_top: Tensor, nb: int):
    """Gains at every step at once (S4), the Cholesky factors of ``Quu``, ``(B,)`` failed
    flags and the value constant's increments ``(B, T)``."""
    T, n = F.shape[-3], F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    if scan_kernels.enabled(F, n, m):
        Fb, Hb = F.expand(nb, *F.shape[1:]), H.expand(nb, *H.shape[1:])
        Kk, L, fail, inc = scan_kernels.gains(V[:, 1:], v[:, 1:], Fb, Hb)
        return Kk, L, fail.any(1), inc
    # [Quu, Qu_xh] = H[:m] + B' Vh_{t+1}[:n] F
    P = Vh_top[:, 1:] @ F  # (B, T, n, m+n+1)
    Qu = H[..., :m, :] + F[..., :n, :m].mT @ P
    Quu, Qu_xh = Qu[..., :m], Qu[..., m:]
    L, info = cholesky(0.5 * (Quu + Quu.mT))
    Kk = -chol_solve(Qu_xh, L)
    # the value's constant: Vh_t[n, n] = Vh_{t+1}[n, n] + c'V c + 2 v'c + qu'k
    cvec = F[..., :n, -1].expand(nb, T, n)
    Vn, vn = V[:, 1:], v[:, 1:]
    inc = (
        torch.einsum("bti,btij,btj->bt", cvec, Vn, cvec)
        + 2 * (vn * cvec).sum(-1)
        + (Qu_xh[..., -1] * Kk[..., -1]).sum(-1)
    )
    return Kk, L, (info != 0).any(1), inc


def _sequential_rows(F, H, VhT, fac: RiccatiFactors, idx: Tensor) -> RiccatiFactors:
    """``fac`` with the rows ``idx`` replaced by the sequential pass's factors."""

    def rows(t: Tensor) -> Tensor:
        return t if t.shape[0] == 1 else t.index_select(0, idx)

    seq = riccati_homogeneous(rows(F), rows(H), rows(VhT))
    k = idx.shape[0]

    def put(full: Tensor, part: Tensor) -> Tensor:
        return full.index_copy(0, idx, part.expand(k, *full.shape[1:]).to(full.dtype))

    return RiccatiFactors(
        Kk=put(fac.Kk, seq.Kk),
        Vh=put(fac.Vh, seq.Vh),
        chol=put(fac.chol.contiguous(), seq.chol),
        failed=put(fac.failed, seq.failed),
    )


def _closed_loop(F: Tensor, Kk: Tensor) -> tuple[Tensor, Tensor]:
    """``(A + B K, B k + c)`` of every step: ``(B, T, n, n)``, ``(B, T, n)``."""
    n = F.shape[-2] - 1
    m = F.shape[-1] - n - 1
    if scan_kernels.enabled(Kk, n, m):
        nb = max(F.shape[0], Kk.shape[0])
        return scan_kernels.closed_loop(F.expand(nb, *F.shape[1:]), Kk.expand(nb, *Kk.shape[1:]))
    G = F[..., :n, :m] @ Kk + F[..., :n, m:]
    return G[..., :n], G[..., n]


@_fused_or_torch_ops
def rollout_scan_homogeneous(F: Tensor, Kk: Tensor, x0: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`torchslq.lq.rollout_homogeneous` by one prefix scan (S5).

    Args:
        F: ``(Bf, T, n+1, m+n+1)``, Kk ``(Bk, T, m, n+1)``, x0 ``(B, n)`` (batches
            broadcast).

    Returns:
        x ``(B, T+1, n)`` and u ``(B, T, m)``.
    """
    T = Kk.shape[-3]
    n = F.shape[-2] - 1
    if T == 0:
        return x0.unsqueeze(-2), x0.new_zeros(*x0.shape[:-1], 0, Kk.shape[-2])
    M, a = _closed_loop(F, Kk)  # x_{t+1} = M_t x_t + a_t: (A + BK, Bk + c)
    x = _affine_recursion(M, a, x0)
    u = (Kk[..., :n] @ x[:, :T].unsqueeze(-1))[..., 0] + Kk[..., n]
    return x, u


@_fused_or_torch_ops
def lq_adjoint_scan(
    F: Tensor, Kk: Tensor, Vh: Tensor, chol: Tensor, gx: Tensor, gu: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`torchslq.lq.lq_adjoint_solve` (the implicit backward pass's LQ solve) by two
    affine scans: the linear value term ``v_t = gx_t + K_t'gu_t + (A_t + B_t K_t)'v_{t+1}``
    (suffix), ``k_t = -Quu_t^{-1}(gu_t + B_t'v_{t+1})`` at every step at once, and
    ``dx_{t+1} = (A_t + B_t K_t) dx_t + B_t k_t`` from ``dx_0 = 0`` (prefix).

    Shapes as :func:`~torchslq.lq.lq_adjoint_solve`: ``F (Bf,T,n+1,m+n+1)``,
    ``Kk (B,T,m,n+1)``, ``Vh (B,T+1,n+1,n+1)``, ``chol (B,T,m,m)``, ``gx (B,T+1,n)``,
    ``gu (B,T,m)``. Returns ``dx (B,T+1,n)``, ``du (B,T,m)``, ``dlam (B,T+1,n)``.
    """
    T, n = Kk.shape[-3], gx.shape[-1]
    m = gu.shape[-1]
    K = Kk[..., :n]
    Bm = F[..., :n, :m]
    Acl, _ = _closed_loop(F, Kk)  # (B, T, n, n)
    a = gx[:, :T] + (K.mT @ gu.unsqueeze(-1))[..., 0]
    v = _affine_recursion(Acl.mT, a, gx[:, T], reverse=True)  # (B, T+1, n)
    qu = gu + (Bm.mT @ v[:, 1:].unsqueeze(-1))[..., 0]
    k = -chol_solve(qu.unsqueeze(-1), chol)[..., 0]
    Bk = (Bm @ k.unsqueeze(-1))[..., 0]
    dx = _affine_recursion(Acl, Bk, torch.zeros_like(gx[:, 0]))
    du = (K @ dx[:, :T].unsqueeze(-1))[..., 0] + k
    dlam = (Vh[..., :n, :n] @ dx.unsqueeze(-1))[..., 0] + v
    return dx, du, dlam


# ----------------------------------------------------------------------------- public API


def riccati_scan(
    A: Tensor,
    B: Tensor,
    Q: Tensor,
    R: Tensor,
    q: Tensor | None = None,
    r: Tensor | None = None,
    S: Tensor | None = None,
    c: Tensor | None = None,
) -> RiccatiFactors:
    """:func:`torchslq.lq.riccati_backward` (without ``reg``, hooks, bounds or restarts)
    by the parallel-in-time pass: same arguments, same :class:`RiccatiFactors`.

    ``A (B,T,n,n)``, ``B (B,T,n,m)``, ``Q (B,T+1,n,n)``, ``R (B,T,m,m)``, ``q (B,T+1,n)``,
    ``r (B,T,m)``, ``S (B,T,m,n)``, ``c (B,T,n)``; one flat batch dim (or none, shared),
    a missing or size-1 time dim broadcasts over ``T = A.shape[-3]``.
    """
    T = A.shape[-3]
    F = homogeneous_dynamics(A, B, with_time(c, 1, T))
    H, VhT = homogeneous_cost(
        with_time(Q, 2, T + 1),
        with_time(R, 2, T),
        with_time(q, 1, T + 1),
        with_time(r, 1, T),
        with_time(S, 2, T),
    )
    F, H = (t.unsqueeze(0) if t.ndim == 3 else t for t in (F, H))
    VhT = VhT.unsqueeze(0) if VhT.ndim == 2 else VhT
    return riccati_scan_homogeneous(F, H, VhT)


def rollout_scan(
    A: Tensor, B: Tensor, K: Tensor, k: Tensor, x0: Tensor, c: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """:func:`torchslq.lq.rollout_linear` by one prefix scan: ``x_{t+1} = A_t x_t + B_t
    u_t + c_t`` under ``u_t = K_t x_t + k_t``.

    ``A (B,T,n,n)``, ``B (B,T,n,m)``, ``K (B,T,m,n)``, ``k (B,T,m)``, ``x0 (B,n)``,
    ``c (B,T,n)``. Returns ``x (B,T+1,n)``, ``u (B,T,m)``.
    """
    F = homogeneous_dynamics(A, B, with_time(c, 1, K.shape[-3]))
    Kk = torch.cat([K, k.unsqueeze(-1)], dim=-1)
    F = F.unsqueeze(0) if F.ndim == 3 else F
    Kk = Kk.unsqueeze(0) if Kk.ndim == 3 else Kk
    x0 = x0.unsqueeze(0) if x0.ndim == 1 else x0
    return rollout_scan_homogeneous(F, Kk, x0)
