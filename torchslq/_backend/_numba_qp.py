"""numba kernel of the batched interior point's iterations on the reduced Newton system
(imported on first use).

:func:`torchslq.lqdo.backends.qp_solve` runs Mehrotra's predictor-corrector method on a
batch of dense QPs. With the null-space method (:class:`torchslq.lqdo.kkt.ReducedKKT`)
an iteration of an element is small work (for the container crane PS10: 8 degrees of
freedom, 40 bounds, an augmented system of 12 to 40 rows), and on torch ops it is some
sixty batched ops and two LAPACK calls padded to the largest element's system, about
35 microseconds per element and iteration at ``B = 256``. Here each element runs its
own loop: the same residuals, convergence and stall tests, weights, augmented system
(rows with a weight above 1 kept out of ``Z'KZ``, see ``ReducedKKT``), predictor and
corrector steps as the torch loop, in the same order; the one difference is the
factorisation of the augmented system, ``LDL'`` without pivoting instead of
Bunch-Kaufman. That system is quasi-definite (``Z'KZ`` positive definite, the
augmented block ``-1/w`` negative definite), so the unpivoted factorisation exists and
its pivots' signs are known; an element whose pivots break that (a QP not convex on the
constraints' null space) stops and is handed over, like a stalled one, to the full
Newton system on torch ops, which continues from its iterate.

The per-QP set-up from the LU factors of ``A'`` (batched LAPACK, on torch) is per
element too (:func:`reduced_setup_kernel`: ``Z``, ``z0``, ``HZ``, ``Z'HZ``, ``C``, ``H
z0``, reading the factors in place where the torch set-up copied ``L1 U`` for its
triangular solves), and so are the multipliers of ``A z = b`` at the end
(:func:`basic_solve_kernel`). The kernels are compiled for the QP's number of degrees
of freedom ``r`` up to :data:`WITNESS_MAX_R` (:func:`witness_r`).
"""

from __future__ import annotations

import numba
import numpy as np

from . import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)
from ._numba_kernels import _cholesky, cholesky_solve
from .specialisation import specialised_qp

# the degrees of freedom up to which the kernels are compiled for their number
WITNESS_MAX_R = 16


def witness_r(r: int) -> tuple:
    """The kernels' ``rt`` argument: ``r`` zeros up to :data:`WITNESS_MAX_R` (numba types
    a tuple by its length, so the kernel is compiled for that ``r``: measured 13% faster
    on the container crane PS10, ``r = 8``, with the same bits), else empty (also for
    sizes left out by :func:`.specialisation.limit_specialised_qp_sizes`)."""
    return (0,) * r if r <= WITNESS_MAX_R and specialised_qp(r) else ()


@numba.njit(nogil=True, cache=True)
def _max_step(v, dv, m):
    """Largest step in (0, 1] keeping ``v + a dv >= 0``."""
    a = 1.0
    for i in range(m):
        if dv[i] < 0.0:
            t = -v[i] / dv[i]
            if t < a:
                a = t
    return a


@numba.njit(nogil=True, cache=True)
def reduced_ip_kernel(
    b0, b1, Z, HZ, ZHZ, C, G, f, h, eu, el, uidx, lidx, upos, lpos, bidx,
    scale_d, scale_i, tol, max_iter, reg, z, Hz, s, mu, done, handoff, iters, rt,
):  # fmt: skip
    """Mehrotra iterations of the elements ``b0 <= b < b1`` on their reduced systems.

    Args:
        Z ``(B, n, r)``, HZ ``(B, n, r)``, ZHZ ``(B, r, r)``: the null-space basis and
            its products with ``H``; C ``(B, mc, r)``: ``[G Z; Z[bidx]]``;
            G ``(B, mg, n)``, f ``(B, n)``, h ``(B, mi)``: the inequality rows'
            right-hand side ``[h; ub_u; -lb_l]``; eu ``(B, nu)``, el ``(B, nl)``: 1
            where an element's bound is finite; uidx, lidx: the bounded variables;
            upos, lpos: their places in bidx (``ReducedKKT``'s fields);
            scale_d, scale_i ``(B,)``: the residuals' scales; tol, max_iter; reg: the
            primal regularisation of ``Z'KZ``'s diagonal (``ReducedKKT``'s).
        z, Hz ``(B, n)``: the start on entry (``z0`` and ``H z0``), the last iterate
            and its carried product on return; s, mu ``(B, mi)`` likewise.
        done, handoff ``(B,)`` bool, iters ``(B,)`` int64: outputs, as the torch
            loop's flags (``handoff``: stalled or not quasi-definite, to finish on the
            full system) and the iteration at which the element stopped (``max_iter``
            where it did not).
        rt: :func:`witness_r` (``r`` zeros, or empty: ``r`` read from ``Z``).
    """
    n = Z.shape[1]
    # r known when compiled where rt has r entries (witness_r): the loops over the
    # degrees of freedom, most of an iteration's, then vectorise without remainders
    r = len(rt) if len(rt) > 0 else Z.shape[2]
    mg, mi, mc = G.shape[1], h.shape[1], C.shape[1]
    nu, nl, nb = uidx.shape[0], lidx.shape[0], bidx.shape[0]
    eps = np.finfo(np.float64).eps
    tiny = np.finfo(np.float64).tiny
    g = np.empty(n)
    gr = np.empty(r)
    ri = np.empty(mi)
    w = np.empty(mc)
    sel = np.empty(mc, dtype=np.int64)
    N = r + mc
    K = np.empty((N, N))
    d = np.empty(N)
    ld = np.empty(N)
    vc = np.empty(mc)
    rhs = np.empty(N)
    dz = np.empty(n)
    Hdz = np.empty(n)
    Gdz = np.empty(mg)
    ds = np.empty(mi)
    dm = np.empty(mi)
    rc = np.empty(mi)
    for b in range(b0, b1):
        done[b] = False
        handoff[b] = False
        iters[b] = max_iter
        zb, Hzb, sb, mub = z[b], Hz[b], s[b], mu[b]
        Zb, HZb, Cb = Z[b], HZ[b], C[b]
        for it in range(1, max_iter + 1):
            # residuals: g = Hz + f + G_all' mu, its reduced part Z'g; ri = G_all z + s - h
            for j in range(n):
                g[j] = Hzb[j] + f[b, j]
            for i in range(mg):
                for j in range(n):
                    g[j] += G[b, i, j] * mub[i]
            for u in range(nu):
                g[uidx[u]] += eu[b, u] * mub[mg + u]
            for q in range(nl):
                g[lidx[q]] -= el[b, q] * mub[mg + nu + q]
            rdmax = 0.0
            finite = True
            for k in range(r):
                acc = 0.0
                for j in range(n):
                    acc += Zb[j, k] * g[j]
                gr[k] = acc
                if not np.isfinite(acc):
                    finite = False
                elif abs(acc) > rdmax:
                    rdmax = abs(acc)
            for i in range(mg):
                acc = 0.0
                for j in range(n):
                    acc += G[b, i, j] * zb[j]
                ri[i] = acc
            for u in range(nu):
                ri[mg + u] = eu[b, u] * zb[uidx[u]]
            for q in range(nl):
                ri[mg + nu + q] = -el[b, q] * zb[lidx[q]]
            rimax = 0.0
            gap = 0.0
            for i in range(mi):
                ri[i] += sb[i] - h[b, i]
                rimax = max(rimax, abs(ri[i]))
                gap += sb[i] * mub[i]
            if mi:
                gap /= mi
            conv = rdmax <= tol * scale_d[b] and gap <= tol and rimax <= tol * scale_i[b]
            if conv or not finite:
                done[b] = True
                iters[b] = it
                if not finite:  # non-finite data: reported as such (status non_finite)
                    for j in range(n):
                        zb[j] = np.nan
                break
            stalled = False
            for i in range(mi):
                if sb[i] < 10.0 * eps * (1.0 + abs(h[b, i])):
                    stalled = True
            if stalled:
                done[b] = handoff[b] = True
                iters[b] = it
                break
            # the weights of the rows of C (a variable's two bounds summed)
            for i in range(mg):
                w[i] = mub[i] / sb[i]
            for i in range(mg, mc):
                w[i] = 0.0
            for u in range(nu):
                w[mg + upos[u]] += eu[b, u] * (mub[mg + u] / sb[mg + u])
            for q in range(nl):
                w[mg + lpos[q]] += el[b, q] * (mub[mg + nu + q] / sb[mg + nu + q])
            # K = [[Z'HZ + C_s' W_s C_s + reg I, C_l'], [C_l, -1/w_l]], in its lower triangle
            k = 0
            for i in range(mc):
                if w[i] > 1.0:
                    sel[k] = i
                    k += 1
            m = r + k
            for a in range(r):
                for c in range(a + 1):
                    K[a, c] = ZHZ[b, a, c]
            for i in range(mc):
                wi = w[i]
                if wi > 1.0 or wi == 0.0:
                    continue
                for a in range(r):
                    ca = wi * Cb[i, a]
                    for c in range(a + 1):
                        K[a, c] += ca * Cb[i, c]
            for a in range(r):
                K[a, a] += reg
            for p in range(k):
                for c in range(r):
                    K[r + p, c] = Cb[sel[p], c]
                for c in range(r, r + p):
                    K[r + p, c] = 0.0
                K[r + p, r + p] = -1.0 / w[sel[p]]
            # LDL' without pivoting (quasi-definite: d > 0 on the first r, < 0 after)
            ok = True
            for j in range(m):
                dj = K[j, j]
                for p in range(j):
                    ld[p] = K[j, p] * d[p]
                    dj -= K[j, p] * ld[p]
                if not ((j < r and dj > 0.0) or (j >= r and dj < 0.0)) or not np.isfinite(dj):
                    ok = False
                    break
                d[j] = dj
                for i in range(j + 1, m):
                    acc = K[i, j]
                    for p in range(j):
                        acc -= K[i, p] * ld[p]
                    K[i, j] = acc / dj
            if not ok:
                done[b] = handoff[b] = True
                iters[b] = it
                break
            alpha = 1.0
            for phase in range(2 if mi else 1):
                # the complementarity target: the affine step's, then Mehrotra's
                if phase == 0:
                    for i in range(mi):
                        rc[i] = -sb[i] * mub[i]
                else:
                    a_aff = min(_max_step(sb, ds, mi), _max_step(mub, dm, mi))
                    gap_aff = 0.0
                    for i in range(mi):
                        gap_aff += (sb[i] + a_aff * ds[i]) * (mub[i] + a_aff * dm[i])
                    gap_aff /= mi
                    sigma = min(max(gap_aff / max(gap, tiny), 0.0), 1.0) ** 3
                    for i in range(mi):
                        rc[i] = -sb[i] * mub[i] - ds[i] * dm[i] + sigma * gap
                # the right-hand side -(Z'g + C' v), v = (rc + mu ri) / s on C's rows
                for i in range(mg):
                    vc[i] = (rc[i] + mub[i] * ri[i]) / sb[i]
                for i in range(mg, mc):
                    vc[i] = 0.0
                for u in range(nu):
                    vc[mg + upos[u]] += (
                        eu[b, u] * (rc[mg + u] + mub[mg + u] * ri[mg + u]) / sb[mg + u]
                    )
                for q in range(nl):
                    t = nu + mg + q
                    vc[mg + lpos[q]] -= el[b, q] * (rc[t] + mub[t] * ri[t]) / sb[t]
                for a in range(r):
                    acc = gr[a]
                    for i in range(mc):
                        acc += Cb[i, a] * vc[i]
                    rhs[a] = -acc
                for p in range(k):
                    rhs[r + p] = 0.0
                # solve L D L' x = rhs
                for i in range(m):
                    acc = rhs[i]
                    for p in range(i):
                        acc -= K[i, p] * rhs[p]
                    rhs[i] = acc
                for i in range(m):
                    rhs[i] /= d[i]
                for i in range(m - 1, -1, -1):
                    acc = rhs[i]
                    for p in range(i + 1, m):
                        acc -= K[p, i] * rhs[p]
                    rhs[i] = acc
                # dz = Z dw, H dz = (HZ) dw, G dz = (GZ) dw; a large row's step from v / w.
                # The predictor's step is needed on the inequalities' rows only.
                if phase == 0 and mi:
                    for jb in range(nb):
                        acc = 0.0
                        for a in range(r):
                            acc += Cb[mg + jb, a] * rhs[a]
                        dz[bidx[jb]] = acc
                else:
                    for j in range(n):
                        a1 = 0.0
                        a2 = 0.0
                        for a in range(r):
                            a1 += Zb[j, a] * rhs[a]
                            a2 += HZb[j, a] * rhs[a]
                        dz[j] = a1
                        Hdz[j] = a2
                for i in range(mg):
                    acc = 0.0
                    for a in range(r):
                        acc += Cb[i, a] * rhs[a]
                    Gdz[i] = acc
                for p in range(k):
                    i = sel[p]
                    cl = rhs[r + p] / w[i]
                    if i < mg:
                        Gdz[i] = cl
                    else:
                        dz[bidx[i - mg]] = cl
                for i in range(mg):
                    ds[i] = -ri[i] - Gdz[i]
                for u in range(nu):
                    ds[mg + u] = -ri[mg + u] - eu[b, u] * dz[uidx[u]]
                for q in range(nl):
                    t = mg + nu + q
                    ds[t] = -ri[t] + el[b, q] * dz[lidx[q]]
                for i in range(mi):
                    dm[i] = (rc[i] - mub[i] * ds[i]) / sb[i]
            if mi:
                alpha = min(0.99 * min(_max_step(sb, ds, mi), _max_step(mub, dm, mi)), 1.0)
            for j in range(n):
                zb[j] += alpha * dz[j]
                Hzb[j] += alpha * Hdz[j]
            for i in range(mi):
                sb[i] += alpha * ds[i]
                mub[i] += alpha * dm[i]


@numba.njit(nogil=True, cache=True, fastmath={"contract"}, error_model="numpy")
def reduced_setup_kernel(b0, b1, LU, perm, H, rb, G, bidx, target, Z, z0, HZ, ZHZ, C, Hz, rt):
    """The null-space set-up of ``ReducedKKT`` (its formulas, in its order) for the
    elements ``b0 <= e < b1``, from the LU factors of ``A'``.

    Args:
        LU ``(B, n, me)``: ``lu_factor``'s factors of ``A' (n, me)`` (any strides):
            ``L = [L1; L2]`` unit lower below the diagonal, ``U`` on and above it;
            perm ``(B, n)``: row ``i`` of ``L U`` is row ``perm[i]`` of ``A'``;
            H ``(B, n, n)``, rb ``(B, me)``: the QP's Hessian and ``A z = b``'s right
            side; G ``(B, mg, n)``; bidx ``(nb,)``: the bounded variables;
            target ``(B, n)``: the point whose projection onto ``A z = b`` is ``z0``
            (0: the least-norm point; a warm start's iterate).
        Z ``(B, n, r)``, z0 ``(B, n)``, HZ ``(B, n, r)``, ZHZ ``(B, r, r)``,
            C ``(B, mg + nb, r)``, Hz ``(B, n)``: outputs; ``Z`` the basis
            ``[-L1^{-T} L2'; I]`` in ``z``'s order, ``z0`` the point with ``A z0 = b``
            nearest ``target`` (``U'^{-1} b`` then ``L1^{-T}`` on the basic variables,
            minus the part of its difference from ``target`` in ``range(Z)``),
            ``C = [G Z; Z[bidx]]``, ``Hz = H z0``.
        rt: :func:`witness_r`.
    """
    n, me = LU.shape[1], LU.shape[2]
    r = len(rt) if len(rt) > 0 else n - me
    mg, nb = G.shape[1], bidx.shape[0]
    S = np.empty((me, r + 1))
    ZtZ = np.empty((r, r))
    Lz = np.empty((r, r))
    whole = np.zeros(r, dtype=np.bool_)  # (_cholesky's rows to skip: none)
    w = np.empty(r)
    # (the triangular solves right-looking and the products as sums of outer products:
    # every multiply-add in an inner loop goes to another accumulator, where dot
    # products would wait on one running sum)
    for e in range(b0, b1):
        L = LU[e]
        p = perm[e]
        # [L2', c] with c = U'^{-1} b (U'[k, i] = U[i, k] = L[i, k] for i <= k)
        for i in range(me):
            for j in range(r):
                S[i, j] = L[me + j, i]
            S[i, r] = rb[e, i]
        for i in range(me):
            ci = S[i, r] / L[i, i]
            S[i, r] = ci
            for k in range(i + 1, me):
                S[k, r] -= L[i, k] * ci
        # sol = L1'^{-1} [L2', c] (L1'[k, i] = L[i, k] for i > k, unit diagonal)
        for i in range(me - 1, 0, -1):
            for k in range(i):
                a = L[i, k]
                for j in range(r + 1):
                    S[k, j] -= a * S[i, j]
        Ze = Z[e]
        for i in range(me):
            for j in range(r):
                Ze[p[i], j] = -S[i, j]
        for i in range(r):
            for j in range(r):
                Ze[p[me + i], j] = 1.0 if i == j else 0.0
        ze = z0[e]
        for j in range(n):
            ze[j] = 0.0
        for i in range(me):
            ze[p[i]] = S[i, r]
        # nearest target on z0 + range(Z): z0 - Z (Z'Z)^{-1} Z'(z0 - target)
        for a in range(r):
            w[a] = 0.0
            for c in range(r):
                ZtZ[a, c] = 0.0
        for j in range(n):
            zj = ze[j] - target[e, j]
            for a in range(r):
                za = Ze[j, a]
                w[a] += za * zj
                for c in range(a + 1):
                    ZtZ[a, c] += za * Ze[j, c]
        _cholesky(ZtZ, 0.0, whole, Lz)  # (Z has an identity block: Z'Z >= I)
        cholesky_solve(Lz, w)
        for j in range(n):
            acc = 0.0
            for a in range(r):
                acc += Ze[j, a] * w[a]
            ze[j] -= acc
        # HZ = H Z, Hz = H z0 (a row of H at a time), ZHZ = Z'HZ
        He, HZe, ZHZe = H[e], HZ[e], ZHZ[e]
        for i in range(n):
            for a in range(r):
                HZe[i, a] = 0.0
            acc = 0.0
            for j in range(n):
                hij = He[i, j]
                if hij != 0.0:  # (a transcription's H is mostly zeros)
                    for a in range(r):
                        HZe[i, a] += hij * Ze[j, a]
                    acc += hij * ze[j]
            Hz[e, i] = acc
        for a in range(r):
            for c in range(r):
                ZHZe[a, c] = 0.0
        for j in range(n):
            for a in range(r):
                za = Ze[j, a]
                for c in range(r):
                    ZHZe[a, c] += za * HZe[j, c]
        for i in range(mg):
            for a in range(r):
                C[e, i, a] = 0.0
            for j in range(n):
                gij = G[e, i, j]
                for a in range(r):
                    C[e, i, a] += gij * Ze[j, a]
        for q in range(nb):
            for a in range(r):
                C[e, mg + q, a] = Ze[bidx[q], a]


@numba.njit(nogil=True, cache=True, fastmath={"contract"}, error_model="numpy")
def basic_solve_kernel(b0, b1, LU, g, out):
    """``out = -(L1 U)^{-1} g`` for the elements ``b0 <= e < b1``: ``LU (B, n, me)`` as in
    :func:`reduced_setup_kernel` (its first ``me`` rows ``L1 U``), ``g (B, me)``."""
    me = LU.shape[2]
    y = np.empty(me)
    for e in range(b0, b1):
        L = LU[e]
        # right-looking (see reduced_setup_kernel): L1 y = g, unit lower, then U x = y
        for i in range(me):
            y[i] = g[e, i]
        for i in range(me):
            yi = y[i]
            for k in range(i + 1, me):
                y[k] -= L[k, i] * yi
        for i in range(me - 1, -1, -1):
            yi = y[i] / L[i, i]
            y[i] = yi
            for k in range(i):
                y[k] -= L[k, i] * yi
        for i in range(me):
            out[e, i] = -y[i]


@numba.njit(nogil=True, cache=True)
def scatter_rows_kernel(b0, b1, lin, val, out):
    """``out[e] = 0; out[e, lin[k]] += val[e, k]`` for the elements ``b0 <= e < b1``:
    dense ``out (B, m n)`` from a sparsity pattern shared by the batch (``lin (nnz,)``
    flat positions, duplicates summed in pattern order) and ``val (B, nnz)``. One
    element's row is zeroed and filled while in cache; ``Tensor.index_add_`` along
    dim 1 adds each pattern entry to all elements in turn, a stride of ``m n`` apart."""
    nnz = lin.shape[0]
    for e in range(b0, b1):
        row = out[e]
        row[:] = 0.0
        for k in range(nnz):
            row[lin[k]] += val[e, k]


@numba.njit(nogil=True, cache=True)
def abs_max_rows_kernel(b0, b1, M, out):
    """``out[e] = max_j |M[e, j]|`` for the elements ``b0 <= e < b1`` of ``M (B, k)``
    (NaN where a row holds one, as ``amax``; 0 for an empty row): one pass where
    ``max(amax, -amin)`` made two."""
    k = M.shape[1]
    for e in range(b0, b1):
        best = 0.0
        for j in range(k):
            a = abs(M[e, j])
            if a != a:  # NaN: the row's maximum, as amax's
                best = a
                break
            if a > best:
                best = a
        out[e] = best
