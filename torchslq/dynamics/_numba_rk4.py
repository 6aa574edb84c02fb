"""numba kernels for an RK4 step of a model with a compiled right-hand side
(:meth:`torchslq.ContinuousDynamics.compiled_rhs`): the step itself (:func:`rk4_step`)
and its derivatives for a model with compiled derivatives
(:meth:`torchslq.ContinuousDynamics.compiled_derivatives`), imported on first use.

They take the model's functions as arguments. The launchers call them with the functions
as first-class function values (:mod:`torchslq._backend.model_fns`), so each kernel is
compiled once per machine (cached on disk) for every model. The sums follow :mod:`torchslq.dynamics.discretize`
(``DiscretizedDynamics._rk4_chain`` and ``_vhp_from_stages``):

* :func:`rk4_lanes_kernel` (Jacobians, and second derivatives of a model that declares
  its curvature pattern) calls the model row by row but does the chain's sums across
  blocks of :data:`LANES` rows, innermost, so that they compile to SIMD instructions;
  each row's sums are those of the row-by-row kernel in the same order (bitwise equal);
* :func:`rk4_second_derivatives_kernel` scans each point's Hessians for their pattern,
  row by row.
"""

from __future__ import annotations

import numba
import numpy as np

from .._backend import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)
from .._backend._numba_kernels import STEP_RK4, rk4_step_with
from .._backend.model_fns import register_step


# (a_i, w_i) of the classical RK4 scheme: stage i at x + a_i dt k_{i-1}, weight w_i dt / 6
# (as functions: numba indexes a constant tuple with a run-time index slowly, ~0.2 us
# per row of the Jacobian kernel)
@numba.njit(inline="always", _nrt=False)
def _rk4_a(i):
    return 0.0 if i == 0 else (0.5 if i < 3 else 1.0)


@numba.njit(inline="always", _nrt=False)
def _rk4_w(i):
    return 2.0 if (i == 1 or i == 2) else 1.0


_RK4_STEPS: dict = {}


def rk4_step(rhs):
    """A numba RK4 step ``step(x, u, p, out, work)`` (:meth:`torchslq.Dynamics.compiled_step`)
    around a model's ``rhs(x, u, p[1:], out)``
    (:meth:`torchslq.ContinuousDynamics.compiled_rhs`) with ``p[0] = dt``: one function
    per ``rhs``, made once per process and compiled only if called from Python (the
    launchers find ``rhs`` behind it, :func:`torchslq._backend.model_fns.step_source`,
    and run the kernels compiled once per machine with ``rhs`` as an argument)."""
    if rhs in _RK4_STEPS:
        return _RK4_STEPS[rhs]

    @numba.njit(nogil=True)
    def step(x, u, p, out, work):
        rk4_step_with(rhs, x, u, p, out, work)

    _RK4_STEPS[rhs] = step
    register_step(step, rhs, STEP_RK4)
    return step


@numba.njit(nogil=True, _nrt=False)
def _rhs_and_derivs(rhs, derivs, x, u, p, out, fz, H):
    """``derivs(x, u, p, fz, H)`` and ``rhs(x, u, p, out)`` at one point. A generated
    model's module replaces it by one function with both bodies
    (:mod:`torchslq.dynamics.codegen`), where LLVM computes their common terms (a sine,
    a denominator) once; the results are those of the two calls, bit for bit."""
    derivs(x, u, p, fz, H)
    rhs(x, u, p, out)


@numba.njit(nogil=True, _nrt=False)
def _stages(rhs, derivs, p, dt, xr, ur, fz, H, dk, xi, k, with_hessians):
    """Forward sweep over the four stages of one row: ``fz[i] = [f_x | f_u](zeta_i)``,
    ``H[i]`` the per-output Hessians there (when ``with_hessians``), ``dk[i] =
    dk_i/dz = fz[i] + a_i dt f_x(zeta_i) dk[i-1]``."""
    n = xr.shape[0]
    nz = fz.shape[2]
    for i in range(4):
        a = _rk4_a(i)
        if i == 0:
            for j in range(n):
                xi[j] = xr[j]
        else:
            for j in range(n):
                xi[j] = xr[j] + (a * dt) * k[j]
        if i < 3:  # the last stage's k is not needed
            _rhs_and_derivs(rhs, derivs, xi, ur, p, k, fz[i], H[i if with_hessians else 0])
        else:
            derivs(xi, ur, p, fz[i], H[i if with_hessians else 0])
        f = fz[i]
        d = dk[i]
        if i == 0:
            for j in range(n):
                for c in range(nz):
                    d[j, c] = f[j, c]
        else:
            prev = dk[i - 1]
            for j in range(n):
                for c in range(nz):
                    s = 0.0
                    for q in range(n):
                        s += f[j, q] * prev[q, c]
                    d[j, c] = f[j, c] + (a * dt) * s


@numba.njit(nogil=True, _nrt=False)
def _jacobians_from_stages(dk, dt, n, nz, A, B):
    """``A = I + dt/6 sum_i w_i dk_i/dx``, ``B = dt/6 sum_i w_i dk_i/du`` of one row."""
    c = dt / 6.0
    for j in range(n):
        for q in range(nz):
            s = dk[0, j, q] + 2.0 * dk[1, j, q] + 2.0 * dk[2, j, q] + dk[3, j, q]
            if q < n:
                A[j, q] = (1.0 if q == j else 0.0) + c * s
            else:
                B[j, q - n] = c * s


@numba.njit(nogil=True, inline="always", _nrt=False)
def _joint(c, n, m):
    """Index in ``[u; x]`` order of entry ``c`` of ``z = (x, u)``."""
    return c - n if c >= n else m + c


@numba.njit(nogil=True, inline="always", _nrt=False)
def _row_curved(Hi, j, a, nz):
    """Whether row ``a`` of output ``j``'s Hessian has a nonzero (or NaN) entry."""
    for b in range(nz):
        if Hi[j, a, b] != 0.0:
            return True
    return False


@numba.njit(nogil=True, _nrt=False)
def _curvature(Hi, n, nz, outs, sup):
    """The outputs of one stage with a nonzero Hessian (into ``outs``) and the ``z``
    entries where any of them is curved (into ``sup``, ascending); returns their counts.
    NaN entries count as nonzero, so NaNs propagate."""
    no = 0
    for j in range(n):
        for a in range(nz):
            if _row_curved(Hi, j, a, nz):
                outs[no] = j
                no += 1
                break
    ns = 0
    for a in range(nz):
        for jj in range(no):
            if _row_curved(Hi, outs[jj], a, nz):
                sup[ns] = a
                ns += 1
                break
    return no, ns


@numba.njit(nogil=True, cache=True)
def rk4_second_derivatives_kernel(
    r0, r1, rhs, derivs, p, dt, curved_outputs, curved_entries, x, u, S, Hz, A, B
):
    """Hessian blocks of ``s · step(x, u)`` for every weight vector ``s = S[w, r]``:
    ``sum_i Z_i' (mu_i · f_zz(zeta_i)) Z_i`` with ``Z_i = d zeta_i / dz`` and the adjoint
    weights ``mu_3 = c_3 s``, ``mu_{i-1} = c_{i-1} s + a_i dt f_x(zeta_i)' mu_i``
    (``c_i = w_i dt / 6``).

    Only the curved outputs and ``z`` entries enter: the model's static pattern
    (``curved_outputs``, ``curved_entries``, int arrays; the model then fills only those
    entries of ``H``) or, when these are empty, the nonzero entries found per stage.
    With several weight vectors per point (DDP's value mode asks for the output basis)
    each curved output's congruence ``G_ij = Z_i' f_j,zz Z_i`` is computed once and
    weighted; with few, ``mu_i · f_zz`` is formed first and one congruence taken per
    weight (whichever needs fewer products).

    x ``(R, n)``, u ``(R, m)``, S ``(W, R, n)``; output Hz ``(W, R, m+n, m+n)``, the
    Hessians in ``[u; x]`` order; with ``A (R, n, n)``, ``B (R, n, m)`` not
    empty, the step's Jacobians too (from the same stages). Rows ``r0 <= r < r1``.

    ``compiled_rk4`` sends declared patterns to :func:`rk4_lanes_kernel`; this kernel's
    declared-pattern path is the row-by-row reference it is tested against (bitwise)."""
    n = x.shape[1]
    m = u.shape[1]
    nz = n + m
    W = S.shape[0]
    jacobians = A.shape[0] > 0
    static = curved_outputs.shape[0] > 0
    fz = np.empty((4, n, nz), dtype=x.dtype)
    dk = np.empty((4, n, nz), dtype=x.dtype)
    H = np.zeros((4, n, nz, nz), dtype=x.dtype)
    G = np.empty((4, n, nz, nz), dtype=x.dtype)  # upper triangles of Z_i' f_j,zz Z_i
    xi = np.empty(n, dtype=x.dtype)
    k = np.empty(n, dtype=x.dtype)
    outs = np.empty((4, n), dtype=np.int64)  # per stage: the curved outputs
    sup = np.empty((4, nz), dtype=np.int64)  # per stage: the curved z entries
    nout = np.empty(4, dtype=np.int64)
    nsup = np.empty(4, dtype=np.int64)
    Zs = np.empty((4, nz, nz), dtype=x.dtype)  # rows of Z_i at the curved entries
    h = np.empty((nz, nz), dtype=x.dtype)
    T1 = np.empty((nz, nz), dtype=x.dtype)
    acc = np.empty((nz, nz), dtype=x.dtype)
    mu = np.empty(n, dtype=x.dtype)
    mu2 = np.empty(n, dtype=x.dtype)
    if static:
        for i in range(4):
            nout[i] = curved_outputs.shape[0]
            nsup[i] = curved_entries.shape[0]
            for jj in range(nout[i]):
                outs[i, jj] = curved_outputs[jj]
            for a in range(nsup[i]):
                sup[i, a] = curved_entries[a]
    for r in range(r0, r1):
        _stages(rhs, derivs, p, dt, x[r], u[r], fz, H, dk, xi, k, True)
        if jacobians:
            _jacobians_from_stages(dk, dt, n, nz, A[r], B[r])
        work_g = 0
        work_f = 0
        for i in range(4):
            if not static:
                nout[i], nsup[i] = _curvature(H[i], n, nz, outs[i], sup[i])
            no, ns = nout[i], nsup[i]
            if no == 0:
                continue
            scale = _rk4_a(i) * dt
            for a in range(ns):  # Z_i = [[I + a_i dt dk_x, a_i dt dk_u], [0, I]]
                za = sup[i, a]
                for c in range(nz):
                    v = 1.0 if c == za else 0.0
                    if i > 0 and za < n:
                        v += scale * dk[i - 1, za, c]
                    Zs[i, a, c] = v
            cong = ns * ns * nz + (nz * (nz + 1) // 2) * ns
            work_g += no * cong + W * no * (nz * (nz + 1) // 2)
            work_f += W * (no * ns * ns + cong)
        per_output = work_g < work_f
        if per_output:
            for i in range(4):
                no, ns = nout[i], nsup[i]
                for jj in range(no):
                    j = outs[i, jj]
                    Hj = H[i, j]
                    Gj = G[i, j]
                    for a in range(ns):  # T1 = f_j,zz[S, S] Zs
                        for c in range(nz):
                            v = 0.0
                            for b in range(ns):
                                v += Hj[sup[i, a], sup[i, b]] * Zs[i, b, c]
                            T1[a, c] = v
                    for c1 in range(nz):  # G = Zs' T1 (symmetric: upper half)
                        for c2 in range(c1, nz):
                            v = 0.0
                            for a in range(ns):
                                v += Zs[i, a, c1] * T1[a, c2]
                            Gj[c1, c2] = v
        for w in range(W):
            s = S[w, r]
            for a in range(nz):
                for b in range(a, nz):
                    acc[a, b] = 0.0
            for j in range(n):
                mu[j] = (_rk4_w(3) * dt / 6.0) * s[j]
            for i in range(3, -1, -1):
                no, ns = nout[i], nsup[i]
                if per_output:
                    for jj in range(no):
                        j = outs[i, jj]
                        mj = mu[j]
                        if mj != 0.0:
                            Gj = G[i, j]
                            for a in range(nz):
                                for b in range(a, nz):
                                    acc[a, b] += mj * Gj[a, b]
                elif no > 0:
                    for a in range(ns):  # h = mu · f_zz on the curved entries
                        za = sup[i, a]
                        for b in range(ns):
                            zb = sup[i, b]
                            v = 0.0
                            for jj in range(no):
                                j = outs[i, jj]
                                v += mu[j] * H[i, j, za, zb]
                            h[a, b] = v
                    for a in range(ns):  # T1 = h Zs
                        for c in range(nz):
                            v = 0.0
                            for b in range(ns):
                                v += h[a, b] * Zs[i, b, c]
                            T1[a, c] = v
                    for c1 in range(nz):  # acc += Zs' T1 (upper half)
                        for c2 in range(c1, nz):
                            v = 0.0
                            for a in range(ns):
                                v += Zs[i, a, c1] * T1[a, c2]
                            acc[c1, c2] += v
                if i > 0:
                    scale = _rk4_a(i) * dt
                    cw = _rk4_w(i - 1) * dt / 6.0
                    for q in range(n):
                        v = 0.0
                        for j in range(n):
                            v += fz[i, j, q] * mu[j]
                        mu2[q] = cw * s[q] + scale * v
                    for q in range(n):
                        mu[q] = mu2[q]
            Hr = Hz[w, r]
            for c1 in range(nz):
                j1 = _joint(c1, n, m)
                for c2 in range(c1, nz):
                    j2 = _joint(c2, n, m)
                    Hr[j1, j2] = acc[c1, c2]
                    Hr[j2, j1] = acc[c1, c2]


# Rows per block of rk4_lanes_kernel. The block's sums run over the rows innermost; with
# 8 lanes LLVM left them mostly scalar (it must check the scratch arrays for aliasing at
# run time): cart-pole, all four output Hessians and the Jacobians, 2.5 us per row row by
# row, 1.6 (8 lanes), 1.4 (16), 1.25 (32), 0.98 (64), 0.97 (128), 1.09 (256). The helpers
# are left to LLVM to inline (numba's inline="always" measured 10% slower).
LANES = 64


@numba.njit(nogil=True, _nrt=False)
def _lane_stage(rhs, derivs, p, a_dt, i, x, u, rows, fz, H, xi, kr, kL, fzL, HL, outs, ents):
    """Stage ``i`` of every lane, model calls row by row: ``fzL[i] = [f_x | f_u](zeta_i)``,
    ``HL`` the curved outputs' Hessians at the curved entries, ``kL = f(zeta_i)``."""
    n = x.shape[1]
    nz = fz.shape[1]
    for lane in range(LANES):
        xr = x[rows[lane]]
        ur = u[rows[lane]]
        for j in range(n):
            xi[j] = xr[j] if i == 0 else xr[j] + a_dt * kL[j, lane]
        if i < 3:  # the last stage's k is not needed
            _rhs_and_derivs(rhs, derivs, xi, ur, p, kr, fz, H)
            for j in range(n):
                kL[j, lane] = kr[j]
        else:
            derivs(xi, ur, p, fz, H)
        for j in range(n):
            for c in range(nz):
                fzL[i, j, c, lane] = fz[j, c]
        for jj in range(outs.shape[0]):
            Hj = H[outs[jj]]
            for a in range(ents.shape[0]):
                for b in range(ents.shape[0]):
                    HL[jj, a, b, lane] = Hj[ents[a], ents[b]]


@numba.njit(nogil=True, _nrt=False)
def _lane_congruences(i, a_dt, n, fzL, dkL, HL, ents, tri1, tri2, Zs, T1, G):
    """``dkL[i] = dk_i/dz = fz_i + a_i dt f_x(zeta_i) dk_{i-1}`` and, for each curved
    output ``j``, ``G[i, j] = Z_i' f_j,zz Z_i`` (packed upper triangle) with
    ``Z_i = [[I + a_i dt dk_x, a_i dt dk_u], [0, I]]``, across the lanes."""
    nz = fzL.shape[2]
    ns = ents.shape[0]
    L = LANES
    for j in range(n):
        for c in range(nz):
            if i == 0:
                for lane in range(L):
                    dkL[0, j, c, lane] = fzL[0, j, c, lane]
                continue
            for lane in range(L):
                T1[0, 0, lane] = 0.0
            for q in range(n):
                for lane in range(L):
                    T1[0, 0, lane] += fzL[i, j, q, lane] * dkL[i - 1, q, c, lane]
            for lane in range(L):
                dkL[i, j, c, lane] = fzL[i, j, c, lane] + a_dt * T1[0, 0, lane]
    for a in range(ns):
        za = ents[a]
        for c in range(nz):
            v = 1.0 if c == za else 0.0
            if i > 0 and za < n:
                for lane in range(L):
                    Zs[a, c, lane] = v + a_dt * dkL[i - 1, za, c, lane]
            else:
                for lane in range(L):
                    Zs[a, c, lane] = v
    for jj in range(G.shape[1]):
        for a in range(ns):  # T1 = f_j,zz[S, S] Zs
            for c in range(nz):
                for lane in range(L):
                    T1[a, c, lane] = 0.0
                for b in range(ns):
                    for lane in range(L):
                        T1[a, c, lane] += HL[jj, a, b, lane] * Zs[b, c, lane]
        for e in range(tri1.shape[0]):  # G = Zs' T1
            c1 = tri1[e]
            c2 = tri2[e]
            for lane in range(L):
                G[i, jj, e, lane] = 0.0
            for a in range(ns):
                for lane in range(L):
                    G[i, jj, e, lane] += Zs[a, c1, lane] * T1[a, c2, lane]


@numba.njit(nogil=True, _nrt=False)
def _lane_weighted_sum(dt, n, s, fzL, G, outs, mu, mu2, acc):
    """``acc = sum_i sum_j mu_i[j] G[i, j]`` (packed) with the adjoint weights
    ``mu_3 = c_3 s``, ``mu_{i-1} = c_{i-1} s + a_i dt f_x(zeta_i)' mu_i``, across the
    lanes (``s (n, LANES)``); a zero weight adds nothing (as the row kernel's skip)."""
    L = LANES
    for e in range(acc.shape[0]):
        for lane in range(L):
            acc[e, lane] = 0.0
    c3 = _rk4_w(3) * dt / 6.0
    for j in range(n):
        for lane in range(L):
            mu[j, lane] = c3 * s[j, lane]
    for i in range(3, -1, -1):
        for jj in range(outs.shape[0]):
            j = outs[jj]
            for e in range(acc.shape[0]):
                for lane in range(L):
                    mj = mu[j, lane]
                    t = mj * G[i, jj, e, lane]
                    acc[e, lane] += t if mj != 0.0 else 0.0
        if i > 0:
            a_dt = _rk4_a(i) * dt
            cw = _rk4_w(i - 1) * dt / 6.0
            for q in range(n):
                for lane in range(L):
                    mu2[q, lane] = 0.0
                for j in range(n):
                    for lane in range(L):
                        mu2[q, lane] += fzL[i, j, q, lane] * mu[j, lane]
                for lane in range(L):
                    mu2[q, lane] = cw * s[q, lane] + a_dt * mu2[q, lane]
            for q in range(n):
                for lane in range(L):
                    mu[q, lane] = mu2[q, lane]


@numba.njit(nogil=True, cache=True)
def rk4_lanes_kernel(r0, r1, rhs, derivs, p, dt, curved_outputs, curved_entries, x, u, S, Hz, A, B):
    """The RK4 step's Jacobians and the Hessian blocks of ``s · step(x, u)`` for every
    weight vector ``s = S[w, r]``, as :func:`rk4_second_derivatives_kernel` computes
    them with a declared curvature pattern (``curved_outputs``, ``curved_entries``, int
    arrays; may be empty when ``S`` has no weight vectors) and per-output congruences,
    in blocks of :data:`LANES` rows (the last block padded with its last row).

    x ``(R, n)``, u ``(R, m)``, S ``(W, R, n)`` (``W = 0``: Jacobians only, the model
    is then asked for no Hessians); outputs Hz ``(W, R, m+n, m+n)`` (``[u; x]`` order)
    and ``A (R, n, n)``, ``B (R, n, m)`` when not empty. Rows
    ``r0 <= r < r1``."""
    n = x.shape[1]
    m = u.shape[1]
    nz = n + m
    W = S.shape[0]
    L = LANES
    outs = curved_outputs[: curved_outputs.shape[0] if W > 0 else 0]
    ents = curved_entries[: curved_entries.shape[0] if W > 0 else 0]
    no = outs.shape[0]
    ns = ents.shape[0]
    ntri = nz * (nz + 1) // 2
    tri1 = np.empty(ntri, dtype=np.int64)  # packed upper triangle: entry e is (tri1, tri2)
    tri2 = np.empty(ntri, dtype=np.int64)
    e = 0
    for c1 in range(nz):
        for c2 in range(c1, nz):
            tri1[e] = c1
            tri2[e] = c2
            e += 1
    fz = np.empty((n, nz), dtype=x.dtype)  # one row's model output at one point
    H = np.zeros((n if W > 0 else 0, nz, nz), dtype=x.dtype)
    xi = np.empty(n, dtype=x.dtype)
    kr = np.empty(n, dtype=x.dtype)
    kL = np.empty((n, L), dtype=x.dtype)
    fzL = np.empty((4, n, nz, L), dtype=x.dtype)
    dkL = np.empty((4, n, nz, L), dtype=x.dtype)
    HL = np.empty((no, ns, ns, L), dtype=x.dtype)
    Zs = np.empty((max(ns, 1), nz, L), dtype=x.dtype)
    T1 = np.empty((max(ns, 1), nz, L), dtype=x.dtype)
    G = np.empty((4, no, ntri, L), dtype=x.dtype)
    mu = np.empty((n, L), dtype=x.dtype)
    mu2 = np.empty((n, L), dtype=x.dtype)
    sL = np.empty((n, L), dtype=x.dtype)
    acc = np.empty((ntri, L), dtype=x.dtype)
    rows = np.empty(L, dtype=np.int64)
    c6 = dt / 6.0
    for r in range(r0, r1, L):
        nl = min(L, r1 - r)
        for lane in range(L):
            rows[lane] = r + (lane if lane < nl else nl - 1)
        for i in range(4):
            a_dt = _rk4_a(i) * dt
            _lane_stage(rhs, derivs, p, a_dt, i, x, u, rows, fz, H, xi, kr, kL, fzL, HL, outs, ents)
            _lane_congruences(i, a_dt, n, fzL, dkL, HL, ents, tri1, tri2, Zs, T1, G)
        if A.shape[0] > 0:
            for j in range(n):
                for c in range(nz):
                    for lane in range(L):
                        sk = dkL[0, j, c, lane] + 2.0 * dkL[1, j, c, lane]
                        sk = sk + 2.0 * dkL[2, j, c, lane] + dkL[3, j, c, lane]
                        T1[0, 0, lane] = c6 * sk
                    for lane in range(nl):
                        if c < n:
                            A[rows[lane], j, c] = (1.0 if c == j else 0.0) + T1[0, 0, lane]
                        else:
                            B[rows[lane], j, c - n] = T1[0, 0, lane]
        for w in range(W):
            for lane in range(L):
                for q in range(n):
                    sL[q, lane] = S[w, rows[lane], q]
            _lane_weighted_sum(dt, n, sL, fzL, G, outs, mu, mu2, acc)
            for lane in range(nl):
                Hr = Hz[w, rows[lane]]
                for e in range(ntri):
                    j1 = _joint(tri1[e], n, m)
                    j2 = _joint(tri2[e], n, m)
                    Hr[j1, j2] = acc[e, lane]
                    Hr[j2, j1] = acc[e, lane]
