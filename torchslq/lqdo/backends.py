"""QP backends for the LQDO subproblems (Prob. 18).

* :func:`solve_sparse`: a maintained sparse CPU solver on the whole batch as one
  block-diagonal QP (one call, no loop over the batch). Clarabel (an interior-point
  conic solver, accurate to ~1e-8 and robust on the ill-scaled transcriptions) is the
  default; OSQP (ADMM) is available. Imported lazily: the library imports without them.
* :func:`qp_solve` / :func:`solve_dense`: a batched primal-dual interior-point method
  (Mehrotra predictor-corrector) on dense KKT systems in torch, for many small QPs at
  once on the CPU or a GPU, differentiable in every problem tensor by implicit
  differentiation of the KKT conditions at the solution (OptNet, Amos & Kolter 2017):
  the backward pass is one symmetric (LDL') solve with the KKT matrix of the active set.

An equality-constrained batch is one sparse LU of its KKT matrix, and so is a convex
batch with few inequalities whose equality-constrained solution satisfies them (it is then
the QP's solution; otherwise the solver runs).

Both return a :class:`QPSolution` with the multipliers in the convention
``H z + f + A' lam + G' mu = 0`` (``mu >= 0``), which the two-level method uses for its
exact upper-level gradient.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from .._backend import can_use_compiled
from .._backend.dispatch import reduced_ip_compiled
from ..status import Status
from .kkt import _REG, KKT_METHODS, Inequalities, ReducedKKT, newton_system
from .qp import DenseQP, SparseQP, TensorKeyedCache, few_inequalities

__all__ = [
    "IPStart",
    "QPSolution",
    "qp_solve",
    "solve",
    "solve_dense",
    "solve_sparse",
    "SPARSE_SOLVERS",
]

SPARSE_SOLVERS = ("clarabel", "osqp")


@dataclass
class QPSolution:
    """Solution of a batch of QPs.

    Attributes:
        z: ``(B, n)`` primal solution.
        lam: ``(B, me)`` equality multipliers.
        mu: ``(B, mi)`` multipliers of ``G z <= h`` (bounds excluded).
        value: ``(B,)`` objective ``1/2 z'Hz + f'z + c``.
        status: ``(B,)`` int64 :class:`torchslq.Status` codes (``converged``, ``max_iter``,
            ``non_finite``).
        iterations: solver iterations (max over the batch).
        time: wall-clock seconds of the solve.
    """

    z: Tensor
    lam: Tensor
    mu: Tensor
    value: Tensor
    status: Tensor
    iterations: int
    time: float
    start: IPStart | None = None


@dataclass
class IPStart:
    """A warm start of the dense interior point (:func:`solve_dense`) from a nearby QP's
    solution, per element: ``z (B, n)``, the multipliers ``mu_g (B, mg)`` of ``G z <= h``
    and ``mu_lb``, ``mu_ub (B, n)`` of the bounds (0 where a variable has none), and
    ``ok (B,)`` bool: the elements that take it (the others start cold). The start is
    ``z`` moved onto the new ``A z = b`` (on the reduced Newton system; the full one
    starts from ``z``), the slacks ``h - G z`` and the multipliers floored at
    :data:`WARM_SLACK_FLOOR` and :data:`WARM_MU_FLOOR`. :func:`solve_dense` returns the
    next one in :attr:`QPSolution.start`."""

    z: Tensor
    mu_g: Tensor
    mu_lb: Tensor
    mu_ub: Tensor
    ok: Tensor


# the floors of a warm start's slacks and multipliers. On the container crane's QLIN
# QPs (PS10, 256 elements, cold: 12.6 iterations each) these gave 8.7 / 7.4 / 7.4
# iterations for QPs 2-4 and no element handed to the full system; both at 1e-2: 9.0 /
# 6.0 / 6.0 with 9 handed over in QP 2 (each costs more than the iterations saved); 0.1
# and 1e-3: 7.8 / 6.6 / 6.5 with 1
WARM_SLACK_FLOOR = 0.1
WARM_MU_FLOOR = 1e-2


# ---------------------------------------------------------------------- sparse (CPU)
def solve_sparse(
    qp: SparseQP, solver: str = "clarabel", tol: float = 1e-8, max_iter: int | None = None
) -> QPSolution:
    """Solve every QP of the batch with a sparse CPU solver in one call.

    Args:
        qp: the batch (its pattern is replicated block-diagonally).
        solver: ``"clarabel"`` (default) or ``"osqp"``.
        tol: feasibility/optimality tolerance passed to the solver.
        max_iter: iteration limit (solver default when None).
    """
    if solver not in SPARSE_SOLVERS:
        raise ValueError(f"solver must be one of {SPARSE_SOLVERS}; got {solver!r}")
    import numpy as np
    import scipy.sparse as sp

    t0 = time.perf_counter()
    B, n, me, mi = qp.batch, qp.n, qp.me, qp.mi
    N = B * n
    lbn, ubn = (t.detach().cpu().double().numpy().reshape(B, n) for t in (qp.lb, qp.ub))
    fl, fu = np.isfinite(lbn), np.isfinite(ubn)
    no_bounds = not (fl.any() or fu.any())
    inactive = None
    if (B * mi or not no_bounds) and qp.convex:
        nb = int((fl.sum(1) + fu.sum(1)).max())
        if few_inequalities(n, mi + nb):
            inactive = _equality_part(qp, lbn.reshape(-1), ubn.reshape(-1))
    if B * mi == 0 and no_bounds:
        # equality constraints only: the QP is its KKT linear system (one sparse LU)
        with _CLARABEL_LOCK:
            x, lam, ok = _kkt_lu(qp)
        mu, iters = np.zeros(0), 1
    elif inactive is not None:
        (x, lam), mu, ok, iters = inactive, np.zeros(B * mi), True, 1
    elif solver == "clarabel":
        with _CLARABEL_LOCK:
            x, lam, mu, ok, iters = _clarabel(qp, tol, max_iter)
    else:
        try:
            import osqp
        except ImportError as e:  # pragma: no cover
            raise ImportError("solver='osqp' needs the osqp package") from e
        d = qp.scipy()
        P = sp.triu(d["P"], format="csc")
        I = sp.identity(N, format="csc")
        Acon = sp.vstack([d["A"], d["G"], I], format="csc")
        lo = np.concatenate([d["b"], np.full(B * mi, -np.inf), d["lb"]])
        hi = np.concatenate([d["b"], d["h"], d["ub"]])
        m = osqp.OSQP()
        m.setup(
            P,
            d["q"],
            Acon,
            lo,
            hi,
            verbose=False,
            eps_abs=tol,
            eps_rel=tol,
            polishing=True,
            max_iter=max_iter or 200000,
        )
        res = m.solve(raise_error=False)
        x, y = np.asarray(res.x), np.asarray(res.y)
        lam, mu = y[: B * me], y[B * me : B * (me + mi)]
        ok = res.info.status_val == 1
        iters = int(res.info.iter)
    elapsed = time.perf_counter() - t0
    kw = dict(dtype=qp.f.dtype, device=qp.f.device)
    z = torch.as_tensor(x, **kw).reshape(B, n)
    st = Status.CONVERGED if ok else Status.MAX_ITER
    if not np.all(np.isfinite(x)):
        st = Status.NON_FINITE
    return QPSolution(
        z=z,
        lam=torch.as_tensor(lam, **kw).reshape(B, me),
        mu=torch.as_tensor(mu, **kw).reshape(B, mi),
        value=qp.objective(z),
        status=torch.full((B,), int(st), dtype=torch.int64, device=qp.f.device),
        iterations=iters,
        time=elapsed,
    )


# ---------------------------------------------------------------------- dense (torch)
def _default_tol(dtype: torch.dtype) -> float:
    return 1e-10 if dtype == torch.float64 else 1e-5


def _direction(rc, rd, re, ri, s, mu, kkt, ineq, mi):
    """One Newton direction of the interior point for complementarity target ``rc``."""
    rhs1 = -rd - ineq.tmv((rc + mu * ri) / s) if mi else -rd
    dz, dl, Gdz = kkt.solve(rhs1, -re)
    if mi:
        ds = -ri - ineq.mv(dz, Gdz)
        dm = (rc - mu * ds) / s
    else:
        ds = dm = rd.new_zeros(rd.shape[0], 0)
    return dz, dl, ds, dm


def _max_step(v, dv):
    """Largest step in (0, 1] keeping ``v + a dv >= 0`` (per element)."""
    if v.shape[-1] == 0:
        return v.new_ones(v.shape[0])
    ratio = torch.where(dv < 0, -v / dv, torch.full_like(v, float("inf")))
    return ratio.amin(-1).clamp(max=1.0)


# pattern key -> solver structures, the last 8 (no tensors to hold: keyed by value)
_SPARSE_CACHE = TensorKeyedCache(8)
_PATTERN_KEYS = TensorKeyedCache(16)  # see _pattern_key
_CLARABEL_LOCK = threading.RLock()  # the cached solver objects are shared state


def clear_sparse_caches() -> None:
    """Forget the sparse solvers' structures kept per sparsity pattern (a timing that
    should include their set-up calls this first)."""
    with _CLARABEL_LOCK:
        _SPARSE_CACHE.clear()
        _PATTERN_KEYS.clear()


def _pattern_key(qp: SparseQP) -> int:
    """A hash of the QP's index tensors. The transcription keeps one set of them while the
    pattern is unchanged, so they are recognised by identity and version (held here, so
    an id is not reused while its entry lives) instead of hashing their bytes per QP."""
    idx = (qp.H_idx, qp.A_idx, qp.G_idx)
    ids = tuple(id(t) for t in idx)
    key = _PATTERN_KEYS.get(ids, idx)
    if key is None:
        key = hash(tuple(t.detach().cpu().numpy().tobytes() for t in idx))
        _PATTERN_KEYS.put(ids, idx, key)
    return key


def _equality_part(qp: SparseQP, lb, ub):
    """For a convex QP with few inequalities (bounds included; ``lb``, ``ub`` the bounds
    as flat numpy arrays): the solution of its equality-constrained part, ``(x, lam)`` as
    from :func:`_kkt_lu`, if that satisfies every inequality and bound (to ``1e-9``
    relative), else None. Then it is the QP's solution with zero inequality multipliers
    (the KKT conditions hold and the QP is convex), found by one sparse LU instead of an
    interior point (the co-design QPs, whose only bound ``p >= 0`` is inactive)."""
    import numpy as np

    with _CLARABEL_LOCK:
        x, lam, ok = _kkt_lu(qp, check=True)
    if not ok:
        return None
    tol = 1e-9
    with np.errstate(invalid="ignore"):  # inf - inf where a bound is absent
        if np.any(x < lb - tol * (1 + np.abs(lb))) or np.any(x > ub + tol * (1 + np.abs(ub))):
            return None
    if qp.mi:
        z = torch.as_tensor(x, dtype=qp.f.dtype, device=qp.f.device).reshape(qp.batch, qp.n)
        if bool((qp.residuals(z)[1] > tol * (1 + qp.h.abs())).any()):
            return None
    return x, lam


def _kkt_lu(qp: SparseQP, check: bool = False):
    """An equality-constrained batch as one sparse LU of its KKT matrix ``[[H, A'], [A,
    0]]`` (block-diagonal over the batch). The CSC structure of the matrix is kept per
    pattern, so a repeated solve (the two-level lower level) fills in numbers only.
    Returns ``x (B n,)``, ``lam (B me,)`` and whether the solve succeeded."""
    import numpy as np
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    B, n, me = qp.batch, qp.n, qp.me
    N, M = B * n, B * me
    key = ("kkt", B, n, me, _pattern_key(qp))
    entry = _SPARSE_CACHE.get(key, ())
    if entry is None:
        Hi, Ai = qp.H_idx.cpu().numpy(), qp.A_idx.cpu().numpy()
        off = np.arange(B)[:, None]
        hr, hc = (Hi[0][None] + n * off).reshape(-1), (Hi[1][None] + n * off).reshape(-1)
        ar, ac = (Ai[0][None] + me * off).reshape(-1), (Ai[1][None] + n * off).reshape(-1)
        rows = np.concatenate([hr, ac, N + ar])  # H, A' (upper right), A (lower left)
        cols = np.concatenate([hc, N + ar, ac])
        pos, ind, ptr, nnz = _csc_structure(rows, cols, N + M)
        # one matrix object per pattern, its numbers replaced per solve (scipy's
        # constructor checks cost as much as the LU of a small KKT matrix)
        K = sp.csc_matrix((np.zeros(nnz), ind, ptr), shape=(N + M,) * 2)
        entry = (pos, nnz, K)
        _SPARSE_CACHE.put(key, (), entry)
    pos, nnz, K = entry
    Av = qp.A_val.detach().cpu().double().numpy().reshape(-1)
    vals = np.concatenate([qp.H_val.detach().cpu().double().numpy().reshape(-1), Av, Av])
    K.data[:] = np.bincount(pos, weights=vals, minlength=nnz)
    rhs = np.concatenate(
        [
            -qp.f.detach().cpu().double().numpy().reshape(-1),
            qp.b.detach().cpu().double().numpy().reshape(-1),
        ]
    )
    try:
        sol = splu(K).solve(rhs)
        ok = bool(np.all(np.isfinite(sol)))
    except RuntimeError:  # singular KKT matrix
        sol, ok = np.full(N + M, np.nan), False
    if ok and check:  # a nearly singular KKT matrix: the LU's solution is not one
        ok = bool(np.abs(K @ sol - rhs).max() <= 1e-9 * max(1.0, float(np.abs(rhs).max())))
    return sol[:N], sol[N:], ok


def _csc_structure(rows, cols, ncols: int):
    """CSC structure of COO entries (duplicates summed): for each entry its position in
    the compressed data, and the ``indices``/``indptr`` arrays."""
    import numpy as np

    order = np.lexsort((rows, cols))
    r, c = rows[order], cols[order]
    new = np.ones(r.size, dtype=bool)
    new[1:] = (r[1:] != r[:-1]) | (c[1:] != c[:-1])
    pos = np.empty(r.size, dtype=np.int64)
    pos[order] = np.cumsum(new) - 1
    indptr = np.searchsorted(c[new], np.arange(ncols + 1))
    return pos, r[new], indptr, int(new.sum())


def _clarabel(qp: SparseQP, tol: float, max_iter: int | None, fresh: bool = False):
    """The batch as one block-diagonal conic QP for Clarabel. The CSC structures (and the
    solver object, whose KKT symbolic factorisation is the expensive part of its setup)
    are kept per sparsity pattern, so the next QP of a quasilinearization or two-level
    loop only updates the numbers (``DefaultSolver.update``)."""
    import numpy as np
    import scipy.sparse as sp

    try:
        import clarabel
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("solver='clarabel' needs the clarabel package") from e

    B, n, me, mi = qp.batch, qp.n, qp.me, qp.mi
    N = B * n

    def np_(t):
        return t.detach().cpu().numpy()

    Hi, Ai, Gi = np_(qp.H_idx), np_(qp.A_idx), np_(qp.G_idx)
    lb, ub = np_(qp.lb).reshape(-1).astype(np.float64), np_(qp.ub).reshape(-1).astype(np.float64)
    fu, fl = np.isfinite(ub), np.isfinite(lb)
    key = ("clarabel", B, n, me, mi, _pattern_key(qp), fu.tobytes(), fl.tobytes(), tol, max_iter)
    up = Hi[0] <= Hi[1]  # Clarabel takes the upper triangle of P
    off = np.arange(B)[:, None]
    Hv = np_(qp.H_val)[:, up].reshape(-1)
    nfu, nfl = int(fu.sum()), int(fl.sum())
    A_vals = np.concatenate(
        [np_(qp.A_val).reshape(-1), np_(qp.G_val).reshape(-1), np.ones(nfu), -np.ones(nfl)]
    )
    bcon = np.concatenate([np_(qp.b).reshape(-1), np_(qp.h).reshape(-1), ub[fu], -lb[fl]]).astype(
        np.float64
    )
    q = np_(qp.f).reshape(-1).astype(np.float64)
    entry = None if fresh else _SPARSE_CACHE.get(key, ())
    if entry is None:
        pr = (Hi[0][up][None] + n * off).reshape(-1)
        pc = (Hi[1][up][None] + n * off).reshape(-1)
        Ppos, Pind, Pptr, Pnnz = _csc_structure(pr, pc, N)
        m0 = B * (me + mi)
        ar = np.concatenate(
            [
                (Ai[0][None] + me * off).reshape(-1),
                (B * me + Gi[0][None] + mi * off).reshape(-1),
                m0 + np.arange(nfu),
                m0 + nfu + np.arange(nfl),
            ]
        )
        ac = np.concatenate(
            [
                (Ai[1][None] + n * off).reshape(-1),
                (Gi[1][None] + n * off).reshape(-1),
                np.nonzero(fu)[0],
                np.nonzero(fl)[0],
            ]
        )
        Apos, Aind, Aptr, Annz = _csc_structure(ar, ac, N)
        Pd = np.bincount(Ppos, weights=Hv, minlength=Pnnz)
        Ad = np.bincount(Apos, weights=A_vals, minlength=Annz)
        Pm = sp.csc_matrix((Pd, Pind, Pptr), shape=(N, N))
        Am = sp.csc_matrix((Ad, Aind, Aptr), shape=(m0 + nfu + nfl, N))
        cones = [clarabel.ZeroConeT(B * me)] if B * me else []
        if B * mi + nfu + nfl:
            cones.append(clarabel.NonnegativeConeT(B * mi + nfu + nfl))
        st = clarabel.DefaultSettings()
        st.verbose = False
        st.presolve_enable = False  # keeps data updates allowed
        st.tol_gap_abs = st.tol_gap_rel = st.tol_feas = tol
        if max_iter is not None:
            st.max_iter = max_iter
        solver = clarabel.DefaultSolver(Pm, q, Am, bcon, cones, st)
        _SPARSE_CACHE.put(key, (), (solver, Ppos, Pnnz, Apos, Annz))
    else:
        solver, Ppos, Pnnz, Apos, Annz = entry
        solver.update(
            P=np.bincount(Ppos, weights=Hv, minlength=Pnnz),
            q=q,
            A=np.bincount(Apos, weights=A_vals, minlength=Annz),
            b=bcon,
        )
    res = solver.solve()
    x, y = np.asarray(res.x), np.asarray(res.z)
    # AlmostSolved: met Clarabel's reduced tolerances (the LGL transcriptions are
    # ill-conditioned: their differentiation matrices grow like nt^2)
    ok = str(res.status).split(".")[-1] in ("Solved", "AlmostSolved")
    if not ok and entry is not None:
        # a reused solver that fails is set up afresh once (its warm internal state,
        # e.g. equilibration from another QP, can hurt an ill-conditioned update)
        return _clarabel(qp, tol, max_iter, fresh=True)
    return x, y[: B * me], y[B * me : B * (me + mi)], ok, int(res.iterations)


def _iterate(kkt, ineq, f, b, h, tol, max_iter, start, scales):
    """The interior point's iterations as batched torch ops on ``kkt`` from
    ``start = (z, lam, s, mu)``; ``scales``: the residuals' ``(scale_d, scale_e,
    scale_i)``. Returns z, lam, s, mu, done, handoff (to the full system), iterations."""
    z, lam, s, mu = start
    scale_d, scale_e, scale_i = scales
    B, me, mi = f.shape[0], b.shape[1], ineq.m
    dt, dev = f.dtype, f.device
    done = torch.zeros(B, dtype=torch.bool, device=dev)
    handoff = torch.zeros(B, dtype=torch.bool, device=dev)  # to finish with FullKKT
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007 (the count is returned)
        rd, re = kkt.residuals(z, lam, ineq.tmv(mu) if mi else None)
        if mi:
            ri = ineq.mv(z) + s - h
            gap = (s * mu).mean(-1)
        else:
            ri = f.new_zeros(B, 0)
            gap = f.new_zeros(B)
        conv = (rd.abs().amax(-1) <= tol * scale_d) & (gap <= tol)
        if me:
            conv &= re.abs().amax(-1) <= tol * scale_e
        if mi:
            conv &= ri.abs().amax(-1) <= tol * scale_i
        bad = ~torch.isfinite(rd).all(-1)
        done = done | conv | bad
        stalled = kkt.stalled(s, h)
        if stalled is not None:
            stalled &= ~done
            handoff |= stalled
            done |= stalled
        if bool(done.all()):
            break
        kkt.factor(mu / s if mi else None, done)

        def direction(rc, rd=rd, re=re, ri=ri, s=s, mu=mu):
            return _direction(rc, rd, re, ri, s, mu, kkt, ineq, mi)

        if mi:
            dz, dl, ds, dm = direction(-s * mu)
            a_aff = torch.minimum(_max_step(s, ds), _max_step(mu, dm))
            gap_aff = ((s + a_aff[:, None] * ds) * (mu + a_aff[:, None] * dm)).mean(-1)
            sigma = (gap_aff / gap.clamp_min(torch.finfo(dt).tiny)).clamp(0, 1) ** 3
            rc = -s * mu - ds * dm + (sigma * gap)[:, None]
            dz, dl, ds, dm = direction(rc)
            alpha = (0.99 * torch.minimum(_max_step(s, ds), _max_step(mu, dm))).clamp(max=1.0)
        else:
            dz, dl, ds, dm = direction(f.new_zeros(B, 0))
            alpha = f.new_ones(B)
        alpha = torch.where(done, 0.0, alpha)
        a = alpha[:, None]
        z = z + a * dz
        lam = lam + a * dl
        kkt.advance(a)
        if mi:
            s = s + a * ds
            mu = mu + a * dm
    return z, lam, s, mu, done, handoff, it


def _warm(kkt, ineq, z, h, warm: IPStart) -> tuple[Tensor, Tensor, Tensor]:
    """``(z, s, mu)`` of the warm start ``warm`` where ``warm.ok``, else the cold start
    with unit multipliers; ``z = kkt.start()``, which on the reduced system is already
    ``warm.z`` moved onto ``A z = b`` (:func:`_warm_target`), and on the full one is
    replaced by ``warm.z``."""
    ok = warm.ok
    if not isinstance(kkt, ReducedKKT):
        z = torch.where(ok[:, None], warm.z, z)
    mi = ineq.m
    if not mi:
        return z, z.new_ones(z.shape[0], 0), z.new_ones(z.shape[0], 0)
    mu_w = torch.cat([warm.mu_g, warm.mu_ub[:, ineq.uidx], warm.mu_lb[:, ineq.lidx]], 1)
    slack = h - ineq.mv(z)
    s = torch.where(ok[:, None], slack.clamp_min(WARM_SLACK_FLOOR), slack.clamp_min(1.0))
    mu = torch.where(ok[:, None], mu_w.clamp_min(WARM_MU_FLOOR), torch.ones_like(s))
    return z, s, mu


def _warm_target(warm: IPStart | None) -> Tensor | None:
    """The reduced system's ``target`` (:func:`kkt.newton_system`): ``warm.z`` where
    ``warm.ok``, else 0 (the least-norm point of a cold start)."""
    if warm is None:
        return None
    return torch.where(warm.ok[:, None], warm.z, 0.0)


def _bound_multipliers(z: Tensor, mu: Tensor, ineq) -> tuple[Tensor, Tensor]:
    """``(mu_lb, mu_ub)``, ``(B, n)`` each (0 where a variable has no such bound), from
    ``mu (B, mi)`` in the rows of ``ineq``: an :class:`IPStart`'s bound multipliers."""
    mg, nu = ineq.mg, ineq.nu
    mu_ub = torch.zeros_like(z).index_copy(1, ineq.uidx, mu[:, mg : mg + nu])
    mu_lb = torch.zeros_like(z).index_copy(1, ineq.lidx, mu[:, mg + nu :])
    return mu_lb, mu_ub


def _ip(H, f, A, b, ineq, h, tol, max_iter, method="auto", start=None, warm=None):
    """Batched Mehrotra predictor-corrector on the Newton system ``method`` of
    :func:`kkt.newton_system`, from ``start = (z, lam, s, mu)`` if given; elements that
    the reduced system cannot finish (see :meth:`kkt.ReducedKKT.stalled`) continue from
    where they are with the full one; ``warm``: an :class:`IPStart` (where ``start`` is
    None). Returns z, lam, mu, s, status, iterations (of both runs).

    On the CPU in float64 the reduced system's iterations run per element in one
    compiled loop (:func:`torchslq._backend.dispatch.reduced_ip_compiled`, the same
    steps; switched off with :func:`torchslq.lq.set_compiled`), else as batched torch
    ops (:func:`_iterate`)."""
    B = f.shape[0]
    me, mi = A.shape[1], ineq.m
    kkt = newton_system(H, f, A, b, ineq, method, _warm_target(warm))
    if start is not None:
        z, lam, s, mu = start
    else:
        z = kkt.start()
        lam = f.new_zeros(B, me)
        s = f.new_ones(B, mi)
        mu = f.new_ones(B, mi)
        if warm is not None:
            z, s, mu = _warm(kkt, ineq, z, h, warm)
        elif mi:
            s = (h - ineq.mv(z)).clamp_min(1.0)
    scale_d = 1 + f.abs().amax(-1)
    scale_e = 1 + b.abs().amax(-1) if me else f.new_ones(B)
    scale_i = 1 + h.abs().amax(-1) if mi else f.new_ones(B)
    if (
        start is None
        and isinstance(kkt, ReducedKKT)
        and f.dtype == torch.float64
        and B
        and can_use_compiled(f, H, A, h)
    ):
        z, s, mu = z.contiguous().clone(), s.contiguous().clone(), mu.contiguous().clone()
        done, handoff, iters = reduced_ip_compiled(
            kkt, ineq, f, h, scale_d, scale_i, tol, max_iter, _REG, z, s, mu
        )
        it = int(iters.max())
    else:
        z, lam, s, mu, done, handoff, it = _iterate(
            kkt, ineq, f, b, h, tol, max_iter, (z, lam, s, mu), (scale_d, scale_e, scale_i)
        )
    lam = kkt.multipliers(z, lam, ineq.tmv(mu) if mi else None)
    status = torch.full((B,), int(Status.MAX_ITER), dtype=torch.int64, device=f.device)
    status = status.masked_fill(done, int(Status.CONVERGED))
    finite = torch.isfinite(z).all(-1)
    status = status.masked_fill(~finite, int(Status.NON_FINITE))
    if bool(handoff.any()):
        idx = handoff.nonzero().squeeze(1)
        warm = (z[idx], lam[idx], s[idx], mu[idx])
        sub = _ip(
            H[idx], f[idx], A[idx], b[idx], ineq.subset(idx), h[idx], tol, max_iter, "full", warm
        )
        z, lam, mu, s, status = (
            t.index_copy(0, idx, u) for t, u in zip((z, lam, mu, s, status), sub[:5], strict=True)
        )
        it += sub[5]
    return z, lam, mu, s, status, it


class _QPFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, H, f, A, b, G, h, lb, ub, tol, max_iter, kkt, symmetric, warm=None):
        Hs = H if symmetric else 0.5 * (H + H.mT)
        ineq = Inequalities(G, lb, ub)
        h_all = ineq.h_all(h)
        z, lam, mu, s, status, it = _ip(
            Hs, f, A, b, ineq, h_all, tol, max_iter, kkt, warm=warm
        )  # fmt: skip
        ctx.save_for_backward(Hs, A, G, z, lam, mu, s, lb, ub)
        ctx.mg = G.shape[1]
        iters = torch.tensor(it)
        # the bounds' multipliers per variable, for the next QP's warm start
        mu_lb, mu_ub = _bound_multipliers(z.detach(), mu.detach(), ineq)
        ctx.mark_non_differentiable(status, iters, mu_lb, mu_ub)
        return z, lam, mu[:, : G.shape[1]], status, iters, mu_lb, mu_ub

    @staticmethod
    def backward(ctx, gz, glam, gmu, _gst, _git, _gmu_lb, _gmu_ub):
        Hs, A, G, z, lam, mu, s, lb, ub = ctx.saved_tensors
        ineq = Inequalities(G, lb, ub)
        G = ineq.dense()  # with the bounds' rows
        B, n = z.shape
        me, mi, mg = A.shape[1], G.shape[1], ctx.mg
        act = mu > s  # strict complementarity: active rows have mu > 0 = slack
        actf = act.to(z.dtype)
        # K = dF/d(z, lam, mu) of F = [Hz + f + A'lam + G'mu; Az - b; act(Gz - h) + (1-act) mu]
        K = z.new_zeros(B, n + me + mi, n + me + mi)
        K[:, :n, :n] = Hs
        K[:, :n, n : n + me] = A.mT
        # inactive rows' multipliers do not enter the gradients (they are masked below),
        # so their columns in the stationarity rows are dropped: K is symmetric
        K[:, :n, n + me :] = G.mT * actf.unsqueeze(-2)
        K[:, n : n + me, :n] = A
        K[:, n + me :, :n] = actf.unsqueeze(-1) * G
        K[:, n + me :, n + me :] = torch.diag_embed(1.0 - actf)
        gm = z.new_zeros(B, mi)
        if gmu is not None:
            gm[:, :mg] = gmu
        g = torch.cat(
            [
                gz if gz is not None else z.new_zeros(B, n),
                glam if glam is not None else z.new_zeros(B, me),
                gm,
            ],
            -1,
        )
        LD, piv, _ = torch.linalg.ldl_factor_ex(K)
        zeta = -torch.linalg.ldl_solve(LD, piv, g.unsqueeze(-1)).squeeze(-1)
        zz, zl, zm = zeta[:, :n], zeta[:, n : n + me], zeta[:, n + me :]
        zm = zm * actf
        gH = 0.5 * (zz.unsqueeze(-1) * z.unsqueeze(-2) + z.unsqueeze(-1) * zz.unsqueeze(-2))
        gA = lam.unsqueeze(-1) * zz.unsqueeze(-2) + zl.unsqueeze(-1) * z.unsqueeze(-2)
        gG = mu[:, :mg].unsqueeze(-1) * zz.unsqueeze(-2) + zm[:, :mg].unsqueeze(-1) * z.unsqueeze(
            -2
        )
        g_lb, g_ub = ineq.bound_gradients(zm)
        return gH, zz, gA, -zl, gG, -zm[:, :mg], g_lb, g_ub, None, None, None, None, None


def qp_solve(
    H: Tensor,
    f: Tensor,
    A: Tensor,
    b: Tensor,
    G: Tensor,
    h: Tensor,
    lb: Tensor | None = None,
    ub: Tensor | None = None,
    tol: float | None = None,
    max_iter: int = 60,
    kkt: str = "auto",
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Solve ``min 1/2 z'Hz + f'z s.t. A z = b, G z <= h, lb <= z <= ub`` for a batch,
    differentiably.

    Args:
        H: ``(B, n, n)`` (its symmetric part is used); f: ``(B, n)``;
        A: ``(B, me, n)``; b: ``(B, me)``; G: ``(B, mi, n)``; h: ``(B, mi)``;
        lb, ub: ``(B, n)`` simple bounds (``-inf``/``inf`` where absent; None: none),
            kept diagonal in the KKT matrix.
        tol: residual and complementarity tolerance (1e-10 in float64, 1e-5 in float32).
        max_iter: interior-point iteration limit.
        kkt: how each iteration's Newton system is solved (:mod:`torchslq.lqdo.kkt`):
            ``"full"`` (LDL' of the KKT matrix), ``"reduced"`` (one LU of ``A'`` per
            call, then the iterates stay on ``A z = b`` and only the reduced matrix on
            ``A``'s null space is factored) or ``"auto"`` (reduced where it is cheaper).
            On the CPU in float64 the reduced system's iterations run per element in
            one compiled loop (the same steps; ``torchslq.lq.set_compiled(False)``
            keeps batched torch ops, as on a GPU).

    Returns:
        ``z (B, n)``, ``lam (B, me)``, ``mu (B, mi)`` (``Hz + f + A'lam + G'mu = 0``) and
        ``status (B,)``. Gradients flow to every input by implicit differentiation of the
        KKT conditions (strict complementarity assumed at the solution).
    """
    args = {"f": f, "H": H, "A": A, "b": b, "G": G, "h": h, "lb": lb, "ub": ub}
    for name, t in args.items():
        if t is None and name in ("lb", "ub"):
            continue
        if not torch.is_tensor(t) or not t.is_floating_point():
            got = t.dtype if torch.is_tensor(t) else type(t).__name__
            raise TypeError(f"{name} must be a floating-point tensor, got {got}")
        if t.dtype != f.dtype or t.device != f.device:
            raise TypeError(
                f"{name} is {t.dtype} on {t.device} but f is {f.dtype} on {f.device}; all "
                "arguments of qp_solve must have one dtype and device"
            )
    B, n = f.shape if f.ndim == 2 else (None, None)
    if B is None:
        raise ValueError(f"f must be (B, n); got {tuple(f.shape)}")
    for name, t, shape in (("H", H, (B, n, n)), ("A", A, (B, None, n)), ("G", G, (B, None, n))):
        if t.ndim != 3 or t.shape[0] != B or t.shape[2] != n or (shape[1] and t.shape[1] != n):
            raise ValueError(f"{name} must be {shape} (None: any); got {tuple(t.shape)}")
    if b.shape != (B, A.shape[1]):
        raise ValueError(f"b must be ({B}, {A.shape[1]}); got {tuple(b.shape)}")
    if h.shape != (B, G.shape[1]):
        raise ValueError(f"h must be ({B}, {G.shape[1]}); got {tuple(h.shape)}")
    z, lam, mu, status, *_ = _qp_solve_iters(H, f, A, b, G, h, lb, ub, tol, max_iter, kkt)
    return z, lam, mu, status


def _qp_solve_iters(
    H, f, A, b, G, h, lb, ub, tol, max_iter, kkt="auto", symmetric=False, warm=None
):  # fmt: skip
    if kkt not in KKT_METHODS:
        raise ValueError(f"kkt must be one of {KKT_METHODS}; got {kkt!r}")
    tol = _default_tol(f.dtype) if tol is None else tol
    lb = torch.full_like(f, -float("inf")) if lb is None else lb.to(f).expand_as(f)
    ub = torch.full_like(f, float("inf")) if ub is None else ub.to(f).expand_as(f)
    return _QPFunction.apply(H, f, A, b, G, h, lb, ub, tol, max_iter, kkt, symmetric, warm)


def solve_dense(
    qp: SparseQP | DenseQP,
    tol: float | None = None,
    max_iter: int = 60,
    kkt: str = "auto",
    warm: IPStart | None = None,
) -> QPSolution:
    """Solve a batch with the dense interior-point method (:func:`qp_solve`; the simple
    bounds stay diagonal, their multipliers are not returned; ``kkt`` as there), from
    the warm start ``warm`` (:class:`IPStart`) where given; the returned
    :attr:`QPSolution.start` is the warm start its solution gives a nearby QP."""
    t0 = time.perf_counter()
    sparse = isinstance(qp, SparseQP)
    mi = qp.mi if sparse else qp.G.shape[1]
    d = qp.dense(bounds=False) if sparse else qp
    lb, ub = (qp.lb, qp.ub) if sparse else (None, None)
    if warm is not None and (warm.z.shape != d.f.shape or warm.mu_g.shape[1] != mi):
        raise ValueError(
            f"warm is for QPs of {warm.z.shape[1]} variables and {warm.mu_g.shape[1]} "
            f"inequalities (batch {warm.z.shape[0]}); this one has {d.f.shape[1]} and {mi} "
            f"(batch {d.f.shape[0]})"
        )
    # a SparseQP holds the full symmetric Hessian: no symmetrisation of the dense one
    z, lam, mu, status, iters, mu_lb, mu_ub = _qp_solve_iters(
        d.H, d.f, d.A, d.b, d.G, d.h, lb, ub, tol, max_iter, kkt, symmetric=sparse, warm=warm
    )
    ok = status == int(Status.CONVERGED)
    start = IPStart(z=z.detach(), mu_g=mu.detach(), mu_lb=mu_lb, mu_ub=mu_ub, ok=ok)
    if sparse:
        value = qp.objective(z)
    else:
        value = 0.5 * (z * (d.H @ z.unsqueeze(-1)).squeeze(-1)).sum(-1) + (d.f * z).sum(-1) + d.c
    return QPSolution(
        z=z,
        lam=lam,
        mu=mu[:, :mi],
        value=value,
        status=status,
        iterations=int(iters),
        time=time.perf_counter() - t0,
        start=start,
    )


def solve(qp: SparseQP, backend: str = "clarabel", fallback_n: int = 2000, **options) -> QPSolution:
    """Solve with ``backend`` (``"clarabel"``, ``"osqp"`` or ``"dense"``). When a sparse
    solver fails on a QP of at most ``fallback_n`` variables, the batch is solved again by
    the dense interior point (Clarabel stalls on some LGL transcriptions, whose
    differentiation matrices are dense and ill-conditioned)."""
    if backend == "dense":
        return solve_dense(qp, **options)
    sol = solve_sparse(qp, solver=backend, **options)
    if bool((sol.status != int(Status.CONVERGED)).any()) and qp.n <= fallback_n:
        opts = {k: v for k, v in options.items() if k == "max_iter"}
        dense = solve_dense(qp, **opts)
        dense.time += sol.time
        return dense
    return sol
