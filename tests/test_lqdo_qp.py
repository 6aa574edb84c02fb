"""LQDO QP backends: the batched dense interior point against a dense KKT solve, a QP
with a known solution and scipy; the sparse solvers against the same; the implicit
gradients against finite differences; batch against per-element solves."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from torchslq.lqdo import LQDOProblem, transcribe
from torchslq.lqdo.backends import qp_solve, solve_dense, solve_sparse
from torchslq.lqdo.qp import DenseQP

pytestmark = pytest.mark.usefixtures("float64_default")


def known_qp(B=3, n=6, me=2, mi=5, n_act=2, seed=0, dtype=torch.float64, bounds=False):
    """QPs with a known solution (z*, lam*, mu*) and strict complementarity; with
    ``bounds`` also lb <= z <= ub with the lower bound of z_0 active (returned last)."""
    g = torch.Generator().manual_seed(seed)
    M = torch.randn(B, n, n, generator=g)
    H = M @ M.mT / n + torch.eye(n)
    A = torch.randn(B, me, n, generator=g)
    G = torch.randn(B, mi, n, generator=g)
    z = torch.randn(B, n, generator=g)
    lam = torch.randn(B, me, generator=g)
    mu = torch.zeros(B, mi)
    mu[:, :n_act] = 0.5 + torch.rand(B, n_act, generator=g)
    slack = torch.zeros(B, mi)
    slack[:, n_act:] = 0.5 + torch.rand(B, mi - n_act, generator=g)
    b = (A @ z[..., None])[..., 0]
    h = (G @ z[..., None])[..., 0] + slack
    f = -(
        (H @ z[..., None])[..., 0]
        + (A.mT @ lam[..., None])[..., 0]
        + (G.mT @ mu[..., None])[..., 0]
    )
    out = [H, f, A, b, G, h, z, lam, mu]
    if bounds:
        lb, ub = z - 1.0, z + 1.0
        lb[:, 0] = z[:, 0]
        f[:, 0] += 0.7  # the active lower bound's multiplier: -0.7 e_0 in the gradient
        out += [lb, ub]
    return [t.to(dtype) for t in out]


def test_dense_ip_equality_qp_matches_dense_kkt():
    g = torch.Generator().manual_seed(1)
    B, n, me = 4, 7, 3
    M = torch.randn(B, n, n, generator=g)
    H = M @ M.mT + 0.1 * torch.eye(n)
    f = torch.randn(B, n, generator=g)
    A = torch.randn(B, me, n, generator=g)
    b = torch.randn(B, me, generator=g)
    K = torch.cat([torch.cat([H, A.mT], -1), torch.cat([A, torch.zeros(B, me, me)], -1)], -2)
    sol = torch.linalg.solve(K, torch.cat([-f, b], -1))
    z, lam, mu, st = qp_solve(H, f, A, b, torch.zeros(B, 0, n), torch.zeros(B, 0))
    torch.testing.assert_close(z, sol[:, :n], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(lam, sol[:, n:], rtol=1e-9, atol=1e-9)
    assert (st == 0).all()


def test_dense_ip_recovers_a_known_solution_and_matches_scipy():
    from scipy.optimize import minimize

    H, f, A, b, G, h, z_star, lam_star, mu_star = known_qp()
    z, lam, mu, st = qp_solve(H, f, A, b, G, h)
    torch.testing.assert_close(z, z_star, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(lam, lam_star, rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(mu, mu_star, rtol=1e-7, atol=1e-7)
    # scipy's SLSQP on element 0 (an independent solver)
    Hn, fn, An, bn, Gn, hn = (t[0].numpy() for t in (H, f, A, b, G, h))
    res = minimize(
        lambda x: 0.5 * x @ Hn @ x + fn @ x,
        np.zeros(Hn.shape[0]),
        jac=lambda x: Hn @ x + fn,
        constraints=[
            {"type": "eq", "fun": lambda x: An @ x - bn, "jac": lambda x: An},
            {"type": "ineq", "fun": lambda x: hn - Gn @ x, "jac": lambda x: -Gn},
        ],
        method="SLSQP",
        options={"ftol": 1e-14, "maxiter": 500},
    )
    np.testing.assert_allclose(z[0].numpy(), res.x, atol=1e-6)


def test_batch_equals_per_element_solves():
    H, f, A, b, G, h, *_ = known_qp(B=5, seed=4)
    z, lam, mu, _ = qp_solve(H, f, A, b, G, h)
    for i in (0, 3):
        zi, li, mi, _ = qp_solve(*(t[i : i + 1] for t in (H, f, A, b, G, h)))
        torch.testing.assert_close(z[i : i + 1], zi, rtol=1e-9, atol=1e-9)


def test_implicit_gradients_against_finite_differences():
    H, f, A, b, G, h, z_star, _, _, lb, ub = known_qp(
        B=2, n=4, me=1, mi=3, n_act=2, seed=7, bounds=True
    )
    z, *_ = qp_solve(H, f, A, b, G, h, lb, ub)
    torch.testing.assert_close(z, z_star, rtol=1e-8, atol=1e-8)  # the bound is active
    ins = [t.clone().requires_grad_(True) for t in (H, f, A, b, G, h, lb, ub)]

    def fn(H, f, A, b, G, h, lb, ub):
        z, lam, mu, _ = qp_solve(H, f, A, b, G, h, lb, ub, tol=1e-13, max_iter=100)
        return z, lam, mu

    assert torch.autograd.gradcheck(fn, ins, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("bounds", [False, True])
def test_reduced_newton_system_matches_the_known_solution_and_the_full_one(bounds, backend):
    """The null-space (variable reduction) interior point: the same solution and
    multipliers as the known ones and as the full-KKT method, with active general
    inequalities and (``bounds``) an active simple bound; its iterations per element in
    the compiled loop and as batched torch ops."""
    qp = known_qp(B=4, n=9, me=5, mi=4, n_act=2, seed=11, bounds=bounds)
    H, f, A, b, G, h, z_star, lam_star, mu_star = qp[:9]
    lbub = qp[9:] if bounds else []
    out = {k: qp_solve(H, f, A, b, G, h, *lbub, kkt=k) for k in ("reduced", "full")}
    for z, lam, mu, st in out.values():
        assert (st == 0).all()
        torch.testing.assert_close(z, z_star, rtol=1e-8, atol=1e-8)
        torch.testing.assert_close(lam, lam_star, rtol=1e-7, atol=1e-7)
        torch.testing.assert_close(mu, mu_star, rtol=1e-7, atol=1e-7)


@pytest.mark.all_sizes
def test_limited_qp_specialisations_run_the_general_kernels_with_the_same_results():
    """``limit_specialised_qp_sizes`` keeps interior-point kernels compiled for the
    reduced size ``r`` for the sizes it names; another ``r`` runs the kernels that read
    it at run time: the same solution, bit for bit, and the known one. Bad sizes are a
    ValueError; the previous setting comes back."""
    from torchslq._backend import _numba_qp
    from torchslq.lq import compiled_available
    from torchslq.lqdo import limit_specialised_qp_sizes

    if not compiled_available():
        pytest.skip("numba kernels not importable")
    qp = known_qp(B=4, n=9, me=5, mi=4, n_act=2, seed=11, bounds=True)  # r = 4
    H, f, A, b, G, h, z_star = qp[:7]
    assert len(_numba_qp.witness_r(4)) == 4
    own = qp_solve(H, f, A, b, G, h, *qp[9:], kkt="reduced")
    old = limit_specialised_qp_sizes([3])
    try:
        assert _numba_qp.witness_r(4) == () and len(_numba_qp.witness_r(3)) == 3
        general = qp_solve(H, f, A, b, G, h, *qp[9:], kkt="reduced")
        with pytest.raises(ValueError, match="reduced sizes"):
            limit_specialised_qp_sizes([0])
    finally:
        assert limit_specialised_qp_sizes(old) == frozenset({3})
    assert len(_numba_qp.witness_r(4)) == 4
    for a, b_ in zip(general, own, strict=True):
        assert torch.equal(a, b_)
    torch.testing.assert_close(general[0], z_star, rtol=1e-8, atol=1e-8)


def test_reduced_newton_system_gradients_against_finite_differences():
    H, f, A, b, G, h, z_star, _, _, lb, ub = known_qp(
        B=2, n=5, me=2, mi=3, n_act=2, seed=7, bounds=True
    )
    ins = [t.clone().requires_grad_(True) for t in (H, f, A, b, G, h, lb, ub)]

    def fn(H, f, A, b, G, h, lb, ub):
        z, lam, mu, _ = qp_solve(H, f, A, b, G, h, lb, ub, tol=1e-13, max_iter=100, kkt="reduced")
        return z, lam, mu

    assert torch.autograd.gradcheck(fn, ins, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_reduced_newton_system_on_a_transcription_with_active_bounds(backend):
    """A TR transcription (defects and boundary rows leave 10 degrees of freedom of 36)
    with active control and state bounds: the reduced and full methods reach the sparse
    solver's optimum, and ``auto`` picks the reduced one there."""
    from torchslq.lqdo import kkt

    tr = transcribe(lq_problem(bounded=True), "TR", nodes=12)
    qp = tr.qp(tr.initial_guess(B=2))
    ref = solve_sparse(qp, solver="clarabel", tol=1e-10)
    d = qp.dense(bounds=False)
    ineq = kkt.Inequalities(d.G, qp.lb, qp.ub)
    assert isinstance(kkt.newton_system(d.H, d.f, d.A, d.b, ineq), kkt.ReducedKKT)
    for method in ("reduced", "full"):
        sol = solve_dense(qp, kkt=method)
        assert (sol.status == 0).all()
        torch.testing.assert_close(sol.value, ref.value, rtol=1e-8, atol=0)
        torch.testing.assert_close(sol.z, ref.z, rtol=0, atol=1e-6)
        torch.testing.assert_close(sol.lam, ref.lam, rtol=0, atol=1e-5)
        assert float(sol.z[0, tr.idx_x[:, 1]].min()) <= -0.45 + 1e-6  # the bound is active


def test_reduced_newton_system_needs_full_row_rank():
    H, f, A, b, G, h, *_ = known_qp(B=2, n=6, me=3, mi=2, seed=3)
    A = A.clone()
    A[1, 2] = 2.0 * A[1, 0]  # a dependent row in element 1
    b = b.clone()
    b[1, 2] = 2.0 * b[1, 0]
    with pytest.raises(ValueError, match="full row rank"):
        qp_solve(H, f, A, b, G, h, kkt="reduced")
    with pytest.raises(ValueError, match="kkt must be one of"):
        qp_solve(H, f, A, b, G, h, kkt="lu")
    # "auto" falls back to the full KKT matrix, whose dual regularisation copes
    z, _, _, st = qp_solve(H, f, A, b, G, h)
    z0, *_ = qp_solve(*(t[:1] for t in (H, f, A, b, G, h)), kkt="full")
    torch.testing.assert_close(z[:1], z0, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("kkt", ["full", "reduced"])
def test_float32_works(kkt):
    H, f, A, b, G, h, z_star, *_ = known_qp(seed=2, dtype=torch.float32)
    z, _, _, st = qp_solve(H, f, A, b, G, h, kkt=kkt)
    assert z.dtype == torch.float32 and (st == 0).all()
    torch.testing.assert_close(z, z_star, rtol=1e-3, atol=1e-3)


def lq_problem(bounded=False):
    """A double integrator, min int x^2 + v^2 + u^2, from (1, 0) to (0, 0) on [0, 3]."""
    return LQDOProblem(
        nu=1,
        nx=2,
        tf=3.0,
        dynamics=lambda t, u, xi, p: torch.stack([xi[..., 1], u[..., 0]], -1),
        lagrange=lambda t, u, xi, p: xi.pow(2).sum(-1) + u[..., 0] ** 2,
        initial=[1.0, 0.0],
        final=[0.0, 0.0],
        u_lb=[-0.7] if bounded else None,
        u_ub=[0.7] if bounded else None,
        xi_lb=[-float("inf"), -0.45] if bounded else None,
    )


@pytest.mark.parametrize("solver", ["clarabel", "osqp"])
def test_sparse_solvers_against_dense_kkt_and_dense_ip(solver):
    tr = transcribe(lq_problem(), "TR", nodes=12)
    qp = tr.qp(tr.initial_guess(B=2))
    d = qp.dense(bounds=False)
    n, me = qp.n, qp.me
    K = torch.cat([torch.cat([d.H, d.A.mT], -1), torch.cat([d.A, torch.zeros(2, me, me)], -1)], -2)
    ref = torch.linalg.solve(K, torch.cat([-d.f, d.b], -1))[:, :n]
    tol = 1e-6 if solver == "osqp" else 1e-7
    s = solve_sparse(qp, solver=solver)
    torch.testing.assert_close(s.z, ref, rtol=0, atol=tol * 10)
    # without bounds or inequalities the batch is one sparse LU of its KKT matrix, whose
    # structure is kept: a second QP of the same pattern (other values) against the
    # dense KKT solve, multipliers included
    g = torch.Generator().manual_seed(7)
    qp2 = replace(qp, f=torch.randn(2, n, generator=g), A_val=qp.A_val * 1.5)
    d2 = qp2.dense(bounds=False)
    K2 = torch.cat(
        [torch.cat([d2.H, d2.A.mT], -1), torch.cat([d2.A, torch.zeros(2, me, me)], -1)], -2
    )
    ref2 = torch.linalg.solve(K2, torch.cat([-d2.f, d2.b], -1))
    for _ in range(2):
        s2 = solve_sparse(qp2, solver=solver)
        torch.testing.assert_close(s2.z, ref2[:, :n], rtol=0, atol=1e-9)
        torch.testing.assert_close(s2.lam, ref2[:, n:], rtol=0, atol=1e-9)
    # with bounds: the sparse solver and the dense interior point agree, and the
    # solution is feasible
    trb = transcribe(lq_problem(bounded=True), "TR", nodes=12)
    qpb = trb.qp(trb.initial_guess())
    sb, db = solve_sparse(qpb, solver=solver), solve_dense(qpb)
    torch.testing.assert_close(sb.z, db.z, rtol=0, atol=tol * 100)
    assert float(sb.value) == pytest.approx(float(db.value), rel=1e-5)
    assert (sb.status == 0).all() and (db.status == 0).all()
    assert float(db.z[0, trb.idx_u].abs().max()) <= 0.7 + 1e-8
    assert float(db.z[0, trb.idx_x[:, 1]].min()) >= -0.45 - 1e-8
    assert float(db.z[0, trb.idx_x[:, 1]].min()) <= -0.45 + 1e-6  # the bound is active
    assert float(db.value) > float(s.value[0]) + 1e-3  # and costs something


def test_convex_qp_with_an_inactive_bound_is_its_equality_part():
    """The co-design QP (convex; its only bound p >= 0 inactive) is solved as its
    equality-constrained part (one LU: 1 iteration) with the dense interior point's
    solution; with p's upper bound made active the LU's point is infeasible and the
    interior point runs, the bound then holding with equality."""
    from torchslq.lqdo.cases import codesign_transfer

    tr = transcribe(codesign_transfer(), "TR", nodes=30)
    z = torch.ones(1, tr.n)
    qp = tr.qp(z)
    assert qp.convex is True
    s, d = solve_sparse(qp), solve_dense(qp)
    assert s.iterations == 1 and (s.status == 0).all()
    torch.testing.assert_close(s.z, d.z, rtol=0, atol=1e-7)
    torch.testing.assert_close(s.lam, d.lam, rtol=0, atol=1e-6)
    p_free = float(s.z[0, tr.idx_p])
    ub = qp.ub.clone()
    ub[:, tr.idx_p] = 0.5 * p_free
    qpa = replace(qp, ub=ub)
    sa, da = solve_sparse(qpa), solve_dense(qpa)
    assert sa.iterations > 1 and (sa.status == 0).all()
    assert float(sa.z[0, tr.idx_p]) == pytest.approx(0.5 * p_free, abs=1e-7)
    torch.testing.assert_close(sa.z, da.z, rtol=0, atol=1e-6)
    assert float(sa.value) > float(s.value) + 1e-6


def test_stalled_elements_finish_with_the_full_newton_system(monkeypatch):
    """An element that the reduced system hands over (here: element 1, forced) is solved
    again by the full one; the batch then equals the full method's solution. (The torch
    loop's stall test is the one patched here: the compiled loop has its own copy.)"""
    from torchslq.lqdo import kkt

    monkeypatch.setattr("torchslq._backend.dispatch._enabled", False)  # the torch loop

    H, f, A, b, G, h, z_star, lam_star, mu_star, lb, ub = known_qp(
        B=3, n=9, me=5, mi=4, n_act=2, seed=5, bounds=True
    )
    calls = []

    def stalled(self, s, h):
        calls.append(s.shape[0])
        out = torch.zeros(s.shape[0], dtype=torch.bool)
        out[1] = True
        return out

    monkeypatch.setattr(kkt.ReducedKKT, "stalled", stalled)
    z, lam, mu, st = qp_solve(H, f, A, b, G, h, lb, ub, kkt="reduced")
    assert calls and (st == 0).all()
    torch.testing.assert_close(z, z_star, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(lam, lam_star, rtol=1e-7, atol=1e-7)
    torch.testing.assert_close(mu, mu_star, rtol=1e-7, atol=1e-7)


def test_batched_crane_qlin_on_the_reduced_system_equals_per_problem_clarabel(backend):
    """Quasilinearization on a batch of container-crane PS10 problems (other initial
    states) with the dense backend (the reduced Newton system: n = 80, me = 72) reaches
    the objective of each problem solved alone with Clarabel."""
    from torchslq.lqdo import Quasilinearization, cases

    B = 6
    g = torch.Generator().manual_seed(0)
    x0 = torch.tensor([0.0, 22.0, 0.0, 0.0, -1.0, 0.0]).repeat(B, 1)
    x0[:, 0] += 0.5 * (2 * torch.rand(B, generator=g) - 1)
    x0[:, 4] += 0.3 * torch.rand(B, generator=g)
    crane = cases.container_crane()
    crane.initial = x0.clone()
    tr = transcribe(crane, "PS", nodes=10)
    res = Quasilinearization(backend="dense").solve(tr, cases.crane_initial_guess(tr, B))
    assert (res.status == 0).all()
    for i in (0, 3, 5):
        crane.initial = x0[i : i + 1].clone()
        tri = transcribe(crane, "PS", nodes=10)
        ri = Quasilinearization(backend="clarabel").solve(tri, cases.crane_initial_guess(tri))
        assert float(res.objective[i]) == pytest.approx(float(ri.objective[0]), rel=1e-6)


def test_compiled_reduced_iterations_hand_a_nonconvex_element_to_the_full_system():
    """The compiled loop factors the augmented reduced system without pivoting, which
    needs ``Z'HZ`` positive definite. An element that is not convex on the constraints'
    null space (element 1: a negative curvature along a bounded direction) stops there
    and is finished by the full Newton system: the result is a KKT point of each QP
    (checked from the definitions), the convex elements' the known solution."""
    from torchslq._backend.dispatch import reduced_ip_compiled
    from torchslq.lq import compiled_available
    from torchslq.lqdo import kkt

    if not compiled_available():
        pytest.skip("numba kernels not available")
    H, f, A, b, G, h, z_star, lam_star, mu_star, lb, ub = known_qp(
        B=3, n=6, me=2, mi=3, n_act=1, seed=9, bounds=True
    )
    H = H.clone()
    H[1] = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0, 1.0, 1.0]))
    ineq = kkt.Inequalities(G, lb, ub)
    hall = ineq.h_all(h)
    nk = kkt.newton_system(H, f, A, b, ineq, "reduced")
    z = nk.start().contiguous().clone()
    s = (hall - ineq.mv(z)).clamp_min(1.0)
    mu = torch.ones_like(s)
    one = torch.ones(3, dtype=H.dtype)
    args = (f, hall, one, one, 1e-10, 60, kkt._REG, z, s, mu)
    done, handoff, _ = reduced_ip_compiled(nk, ineq, *args)
    assert handoff.tolist() == [False, True, False] and bool(done.all())

    z, lam, mu, st = qp_solve(H, f, A, b, G, h, lb, ub, kkt="reduced")
    assert (st == 0).all()
    for i in (0, 2):
        torch.testing.assert_close(z[i], z_star[i], rtol=1e-8, atol=1e-8)
    # element 1: stationarity with the bounds' multipliers, feasibility, complementarity
    zi, li, mi_ = z[1], lam[1], mu[1]
    g = H[1] @ zi + f[1] + A[1].T @ li + G[1].T @ mi_
    at_lb, at_ub = zi <= lb[1] + 1e-7, zi >= ub[1] - 1e-7
    free = ~(at_lb | at_ub)
    torch.testing.assert_close(g[free], torch.zeros_like(g[free]), rtol=0, atol=1e-7)
    assert bool((g[at_lb] >= -1e-7).all()) and bool((g[at_ub] <= 1e-7).all())
    torch.testing.assert_close(A[1] @ zi, b[1], rtol=0, atol=1e-9)
    assert bool((G[1] @ zi <= h[1] + 1e-9).all()) and bool((mi_ >= -1e-12).all())
    torch.testing.assert_close(mi_ * (h[1] - G[1] @ zi), torch.zeros_like(mi_), rtol=0, atol=1e-7)
    assert bool(((zi >= lb[1] - 1e-9) & (zi <= ub[1] + 1e-9)).all())


@pytest.mark.parametrize("kkt", ["reduced", "full"])
def test_an_element_with_non_finite_data_is_non_finite_and_spares_the_others(kkt, backend):
    """A NaN in one element's Hessian and in another's linear term: those two get the
    status ``non_finite`` (not ``converged``), the third the known solution, on either
    Newton system and either backend of the reduced one's iterations."""
    from torchslq import Status

    H, f, A, b, G, h, z_star, lam_star, mu_star, lb, ub = known_qp(
        B=3, n=9, me=5, mi=4, n_act=2, seed=11, bounds=True
    )
    H, f = H.clone(), f.clone()
    H[1, 2, 3] = float("nan")
    f[2, 0] = float("nan")
    z, lam, mu, st = qp_solve(H, f, A, b, G, h, lb, ub, kkt=kkt)
    assert st.tolist() == [0, int(Status.NON_FINITE), int(Status.NON_FINITE)]
    torch.testing.assert_close(z[0], z_star[0], rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(mu[0], mu_star[0], rtol=1e-7, atol=1e-7)


def test_compiled_reduced_setup_equals_the_torch_setup_and_the_definitions():
    """On the CPU in float64 ``ReducedKKT``'s null-space set-up runs per element in one
    compiled loop. On a batch of random equality- and inequality-constrained QPs with
    bounds (and a transcription's QPs, whose ``H`` is mostly zeros) its fields equal the
    torch set-up's, and they are what they are defined to be: ``A Z = 0`` with ``Z``'s
    free rows the identity, ``A z0 = b`` with ``z0`` orthogonal to ``range(Z)``,
    ``HZ = H Z``, ``Z'HZ``, ``C = [G Z; Z[bidx]]``, ``Hz = H z0``; and the multipliers
    solve the basic rows of ``H z + f + A' lam = 0`` at a point where ``Z'g = 0``."""
    from torchslq.lq import compiled_available, set_compiled
    from torchslq.lqdo import kkt

    if not compiled_available():
        pytest.skip("numba kernels not available")
    H, f, A, b, G, h, *_, lb, ub = known_qp(B=5, n=9, me=4, mi=3, bounds=True)
    tr = transcribe(lq_problem(bounded=True), "TR", nodes=12)
    d = tr.qp(tr.initial_guess(B=3)).dense(bounds=False)
    qp_tr = tr.qp(tr.initial_guess(B=3))
    cases = [
        (H, f, A, b, kkt.Inequalities(G, lb, ub)),
        (d.H, d.f, d.A, d.b, kkt.Inequalities(d.G, qp_tr.lb, qp_tr.ub)),
    ]
    fields = ("Z", "z0", "HZ", "ZHZ", "C", "Hz")
    for H, f, A, b, ineq in cases:
        old = set_compiled(False)
        try:
            ref = kkt.newton_system(H, f, A, b, ineq, "reduced")
        finally:
            set_compiled(old)
        got = kkt.newton_system(H, f, A, b, ineq, "reduced")
        assert got.compiled and not ref.compiled
        for name in fields:
            torch.testing.assert_close(getattr(got, name), getattr(ref, name), rtol=0, atol=1e-12)
        Z, z0 = got.Z, got.z0
        r = Z.shape[-1]
        torch.testing.assert_close(A @ Z, torch.zeros_like(A @ Z), rtol=0, atol=1e-12)
        free = Z.gather(1, got.free.unsqueeze(-1).expand(-1, -1, r))
        torch.testing.assert_close(free, torch.eye(r, dtype=Z.dtype).expand_as(free))
        torch.testing.assert_close((A @ z0[..., None])[..., 0], b, rtol=0, atol=1e-12)
        ztz0 = (Z.mT @ z0[..., None])[..., 0]
        torch.testing.assert_close(ztz0, torch.zeros_like(ztz0), rtol=0, atol=1e-12)
        torch.testing.assert_close(got.HZ, H @ Z, rtol=0, atol=1e-12)
        torch.testing.assert_close(got.ZHZ, Z.mT @ H @ Z, rtol=0, atol=1e-12)
        parts = [ineq.G @ Z, Z[:, ineq.bidx, :]]
        torch.testing.assert_close(got.C, torch.cat(parts, 1), rtol=0, atol=1e-12)
        torch.testing.assert_close(got.Hz, (H @ z0[..., None])[..., 0], rtol=0, atol=1e-12)
        # with a target (a warm start's iterate) z0 is the point of A z = b nearest it
        t = torch.randn(f.shape, generator=torch.Generator().manual_seed(3), dtype=f.dtype)
        old = set_compiled(False)
        try:
            ref_t = kkt.newton_system(H, f, A, b, ineq, "reduced", target=t)
        finally:
            set_compiled(old)
        got_t = kkt.newton_system(H, f, A, b, ineq, "reduced", target=t)
        torch.testing.assert_close(got_t.z0, ref_t.z0, rtol=0, atol=1e-12)
        torch.testing.assert_close((A @ got_t.z0[..., None])[..., 0], b, rtol=0, atol=1e-12)
        ztd = (Z.mT @ (got_t.z0 - t)[..., None])[..., 0]
        torch.testing.assert_close(ztd, torch.zeros_like(ztd), rtol=0, atol=1e-12)
        torch.testing.assert_close(got_t.Hz, (H @ got_t.z0[..., None])[..., 0], rtol=0, atol=1e-12)
        # multipliers at the reduced minimiser z = z0 + Z w, Z'(H z + f) = 0
        w = torch.linalg.solve(Z.mT @ H @ Z, -(Z.mT @ (H @ z0[..., None] + f[..., None])))
        z = z0 + (Z @ w)[..., 0]
        got.Hz = (H @ z[..., None])[..., 0]
        lam = got.multipliers(z, None, None)
        g = (H @ z[..., None])[..., 0] + f + (A.mT @ lam[..., None])[..., 0]
        torch.testing.assert_close(g, torch.zeros_like(g), rtol=0, atol=1e-9)


def test_newton_system_keeps_the_graph_of_inputs_that_require_grad():
    """Built on tensors that require grad, the reduced system is built by torch ops
    that record the graph (the compiled set-up and the LU into preallocated memory are
    for the solver's no-grad forward), with the same values as without a graph; large
    enough (``B n me >= 2^16``) that the no-grad path takes both."""
    from torchslq.lqdo import kkt

    H, f, A, b, G, h, *_, lb, ub = known_qp(B=40, n=48, me=40, mi=3, bounds=True)
    ineq = kkt.Inequalities(G, lb, ub)
    with torch.no_grad():
        ref = kkt.newton_system(H, f, A, b, ineq, "reduced")
    Ag = A.clone().requires_grad_(True)
    got = kkt.newton_system(H, f, Ag, b, ineq, "reduced")
    assert got.z0.requires_grad and not got.compiled
    torch.testing.assert_close(got.z0.detach(), ref.z0, rtol=0, atol=1e-12)
    torch.testing.assert_close(got.ZHZ.detach(), ref.ZHZ, rtol=0, atol=1e-12)
    (gA,) = torch.autograd.grad(got.z0.sum(), Ag)
    assert torch.isfinite(gA).all() and gA.abs().sum() > 0


@pytest.mark.parametrize("kkt_method", ["reduced", "full"])
def test_warm_start_from_a_nearby_qp_reaches_its_solution_in_fewer_iterations(kkt_method, backend):
    """The dense interior point started from the previous quasilinearization QP's
    solution (``IPStart``; the crane PS10 with active bounds, the second QP from the
    first's solution): on both Newton systems and both backends it reaches the solution
    of the cold start and Clarabel's, in fewer iterations; an element given
    ``ok = False`` starts cold and gets exactly the cold start's result."""
    from torchslq.lqdo import cases

    B = 4
    g = torch.Generator().manual_seed(1)
    x0 = torch.tensor([0.0, 22.0, 0.0, 0.0, -1.0, 0.0]).repeat(B, 1)
    x0[:, 0] += 0.5 * (2 * torch.rand(B, generator=g) - 1)
    crane = cases.container_crane()
    crane.initial = x0.clone()
    tr = transcribe(crane, "PS", nodes=10)
    z1 = cases.crane_initial_guess(tr, B)
    first = solve_dense(tr.qp(z1), kkt=kkt_method)
    assert (first.status == 0).all()
    qp2 = tr.qp(first.z.detach())
    cold = solve_dense(qp2, kkt=kkt_method)
    warm = solve_dense(qp2, kkt=kkt_method, warm=first.start)
    ref = solve_sparse(qp2, solver="clarabel", tol=1e-10)
    assert (cold.status == 0).all() and (warm.status == 0).all()
    assert warm.iterations < cold.iterations
    torch.testing.assert_close(warm.value, cold.value, rtol=1e-6, atol=0)
    torch.testing.assert_close(warm.value, ref.value, rtol=1e-6, atol=0)
    torch.testing.assert_close(warm.z, ref.z, rtol=0, atol=1e-2)
    half = replace(first.start, ok=torch.tensor([True, False, True, False]))
    mixed = solve_dense(qp2, kkt=kkt_method, warm=half)
    assert torch.equal(mixed.z[1::2], cold.z[1::2])
    torch.testing.assert_close(mixed.value[::2], warm.value[::2], rtol=1e-6, atol=0)
    H, f, A, b, G, h, *_ = known_qp(B=4)  # another problem: 6 variables
    other = DenseQP(H=H, f=f, A=A, b=b, G=G, h=h, c=torch.zeros(4))
    with pytest.raises(ValueError, match="warm is for QPs of 80 variables"):
        solve_dense(other, warm=first.start)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_scatter_equals_index_add_bit_for_bit_and_keeps_gradients(dtype, monkeypatch):
    """The dense matrices of a QP from its shared pattern: the compiled per-element
    scatter against ``index_add_`` (duplicate positions summed in pattern order), and the
    torch path, with its graph, where the values require grad."""
    import torchslq.lqdo.qp as qp_module

    calls = []
    compiled = qp_module.scatter_compiled
    monkeypatch.setattr(qp_module, "scatter_compiled", lambda *a: calls.append(1) or compiled(*a))
    g = torch.Generator().manual_seed(3)
    m, n, B, nnz = 7, 5, 6, 60  # 60 entries in 35 positions: duplicates
    idx = torch.stack(
        [torch.randint(0, m, (nnz,), generator=g), torch.randint(0, n, (nnz,), generator=g)]
    )
    val = torch.randn(B, nnz, generator=g, dtype=dtype)
    expected = torch.zeros(B, m * n, dtype=dtype).index_add_(1, idx[0] * n + idx[1], val)
    out = qp_module._scatter(idx, val, m, n)
    assert calls, "the compiled scatter was not taken"
    assert out.shape == (B, m, n) and out.dtype == dtype
    assert torch.equal(out.reshape(B, -1), expected)
    # with a graph: the torch path, same values, d(sum w*out)/dval = w at each position
    calls.clear()
    v = val.clone().requires_grad_(True)
    w = torch.randn(B, m, n, generator=g, dtype=dtype)
    out_g = qp_module._scatter(idx, v, m, n)
    assert not calls and torch.equal(out_g.detach(), out)
    (grad,) = torch.autograd.grad((w * out_g).sum(), v)
    assert torch.equal(grad, w.reshape(B, -1)[:, idx[0] * n + idx[1]])


def test_compiled_abs_max_equals_amax_amin_with_zeros_and_nan():
    """The rank test's scale ``max |A|`` per element: the compiled pass against
    ``maximum(amax, -amin)``, rows of zeros (0) and rows with a NaN (NaN) included."""
    from torchslq._backend.dispatch import abs_max_rows_compiled

    g = torch.Generator().manual_seed(5)
    A = torch.randn(6, 4, 7, generator=g)
    A[1] = 0.0
    A[2, 3, 1] = float("nan")
    A[3] = -A[3].abs()  # the largest magnitude negative
    flat = A.reshape(6, -1)
    expected = torch.maximum(flat.amax(-1), -flat.amin(-1))
    out = abs_max_rows_compiled(A)
    assert torch.equal(out[~expected.isnan()], expected[~expected.isnan()])
    assert torch.equal(out.isnan(), expected.isnan()) and bool(out[2].isnan())
    assert float(out[1]) == 0.0 and float(out[3]) == float(A[3].abs().max())
