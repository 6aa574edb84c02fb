"""Quasilinearization: an LQ problem is solved in one iteration to the QP's (and a dense
KKT solve's) solution; a batch equals per-element solves."""

from __future__ import annotations

import pytest
import torch

from torchslq.lqdo import LQDOProblem, Quasilinearization, transcribe
from torchslq.lqdo.backends import solve_dense

pytestmark = pytest.mark.usefixtures("float64_default")


def lq(bounded: bool) -> LQDOProblem:
    return LQDOProblem(
        nu=1,
        nx=2,
        tf=3.0,
        dynamics=lambda t, u, xi, p: torch.stack([xi[..., 1], -0.5 * xi[..., 0] + u[..., 0]], -1),
        lagrange=lambda t, u, xi, p: xi.pow(2).sum(-1) + u[..., 0] ** 2 + t * xi[..., 0],
        mayer=lambda p, x0, xf: 3.0 * xf[..., 0] ** 2,
        initial=[1.0, 0.0],
        u_lb=[-0.7] if bounded else None,
        u_ub=[0.7] if bounded else None,
    )


def test_lq_problem_converges_in_one_iteration_to_the_kkt_solution():
    tr = transcribe(lq(False), "TR", nodes=15)
    z0 = torch.randn(1, tr.n, generator=torch.Generator().manual_seed(0))
    res = Quasilinearization().solve(tr, z0)
    assert res.iterations.tolist() == [1] and res.status.tolist() == [0]
    # the QP of the transcription (any reference: the problem is OLQ), dense KKT solve
    d = tr.qp(torch.zeros(1, tr.n)).dense(bounds=False)
    n, me = tr.n, d.A.shape[1]
    K = torch.cat([torch.cat([d.H, d.A.mT], -1), torch.cat([d.A, torch.zeros(1, me, me)], -1)], -2)
    z_kkt = torch.linalg.solve(K, torch.cat([-d.f, d.b], -1))[:, :n]
    torch.testing.assert_close(res.z, z_kkt, rtol=0, atol=1e-6)
    torch.testing.assert_close(res.objective, tr.objective(z_kkt), rtol=1e-9, atol=0)


def test_bounded_lq_one_iteration_and_batch_equals_single():
    tr = transcribe(lq(True), "PS", nodes=9)
    g = torch.Generator().manual_seed(1)
    z0 = torch.randn(3, tr.n, generator=g)
    res = Quasilinearization(backend="dense").solve(tr, z0)
    assert res.iterations.tolist() == [1, 1, 1]
    ref = solve_dense(tr.qp(z0[:1]))  # the QP solution, independent of the reference
    for i in range(3):
        torch.testing.assert_close(res.z[i], ref.z[0], rtol=0, atol=1e-7)
    single = Quasilinearization(backend="clarabel").solve(tr, z0[1])
    torch.testing.assert_close(single.z[0], res.z[1], rtol=0, atol=1e-6)


def test_float32_transcription_and_dense_qlin():
    from torchslq.lqdo.cases import container_crane, crane_initial_guess

    tr = transcribe(container_crane(), "PS", nodes=10, dtype=torch.float32)
    res = Quasilinearization(backend="dense").solve(tr, crane_initial_guess(tr))
    assert res.z.dtype == torch.float32 and res.status.tolist() == [0]
    assert round(float(res.objective), 4) == 0.0376  # Table 1, PS10 (float64 test: exact)


# --- safeguards beyond the paper ------------------------------------------------------


def _dense_objective_model(qp, z):
    """Value and gradient of the QP's objective ``1/2 z'Hz + f'z + c`` at ``z``."""
    d = qp.dense(bounds=False)
    Hz = (d.H @ z.unsqueeze(-1)).squeeze(-1)
    return 0.5 * (z * Hz).sum(-1) + (d.f * z).sum(-1) + d.c, Hz + d.f, d.H


def test_lagrangian_hessian_adds_the_multiplier_weighted_constraint_curvature():
    """qp(z, multipliers=(lam, mu)): H minus the plain QP's H equals the Hessian of
    lam' c_E(z) + mu' c_I(z) by autograd on the whole transcription; the value and
    gradient at z are unchanged (a path inequality with curvature included)."""
    from torchslq.lqdo.cases import van_der_pol

    torch.manual_seed(0)
    problem = van_der_pol("V2")
    problem.path_ineq = lambda t, u, xi, p: xi[..., :1] ** 2 - 4.0  # a curved path row
    tr = transcribe(problem, "TR", nodes=8)
    assert tr.mi == 8  # one curved inequality row per node
    z = tr.initial_guess(xif=[0.0, 0.0], p=[1.0, 1.0]) + 0.3 * torch.randn(1, tr.n)
    lam, mu = torch.randn(1, tr.me), torch.rand(1, tr.mi)
    v0, g0, H0 = _dense_objective_model(tr.qp(z), z)
    v1, g1, H1 = _dense_objective_model(tr.qp(z, multipliers=(lam, mu)), z)
    torch.testing.assert_close(v1, v0, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g1, g0, rtol=1e-12, atol=1e-12)

    def weighted(zf):
        zb = zf[None]
        return (lam * tr.equalities(zb)).sum() + (mu * tr.inequalities(zb)).sum()

    want = torch.autograd.functional.hessian(weighted, z[0])
    torch.testing.assert_close(H1[0] - H0[0], want, rtol=1e-10, atol=1e-10)


def test_convexified_qp_is_convex_with_the_objectives_value_and_gradient():
    """qp(z, convexify=True) on the suspension away from the start (its objective's
    node Hessians are indefinite there): positive semidefinite H, and the QP objective's
    value and gradient at z equal the transcribed objective's (autograd)."""
    from torchslq.lqdo.cases import suspension

    torch.manual_seed(1)
    tr = transcribe(suspension(), "TR", nodes=10)
    z = tr.initial_guess(p=[1e3, 1e4]) + 0.1 * torch.randn(1, tr.n)
    _, _, H = _dense_objective_model(tr.qp(z), z)
    assert float(torch.linalg.eigvalsh(H).min()) < -1e-6  # indefinite as it is
    v, g, Hc = _dense_objective_model(tr.qp(z, convexify=True), z)
    assert float(torch.linalg.eigvalsh(Hc).min()) > -1e-9 * float(Hc.abs().max())
    zg = z.clone().requires_grad_(True)
    J = tr.objective(zg)
    (grad,) = torch.autograd.grad(J.sum(), zg)
    torch.testing.assert_close(v, J.detach(), rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(g, grad, rtol=1e-9, atol=1e-9)


def test_trust_region_solves_the_suspension_where_qlin_and_the_line_search_fail():
    """The quarter-car co-design (synthetic road, TR40): Algorithm 1 does not converge,
    the merit line search fails at once (the first QP leaves p free: its step is huge),
    the trust region on p converges to the two-level method's optimum (an independent
    solve: exact QPs in (u, xi) for fixed p, an outer search over p)."""
    from torchslq import Status
    from torchslq.lqdo import TwoLevel
    from torchslq.lqdo.cases import suspension

    tr = transcribe(suspension(), "TR", nodes=40)
    z0 = tr.initial_guess(p=[1e3, 1e4])
    plain = Quasilinearization(max_iter=30).solve(tr, z0)
    assert plain.status.tolist() == [int(Status.MAX_ITER)]
    merit = Quasilinearization(safeguard="merit", max_iter=30).solve(tr, z0)
    assert merit.status.tolist() == [int(Status.LINE_SEARCH_FAILED)]
    res = Quasilinearization(safeguard="trust_region", max_iter=200).solve(tr, z0)
    ref = TwoLevel().solve(tr, torch.tensor([[1e3, 1e4]]))
    assert res.status.tolist() == [int(Status.CONVERGED)]
    assert float(res.violation) < 1e-6
    torch.testing.assert_close(res.objective, ref.objective, rtol=1e-6, atol=0)
    torch.testing.assert_close(res.p, ref.p, rtol=1e-4, atol=0)


@pytest.mark.parametrize("method,N,v_ip", [("TR", 20, 1.9809), ("PS", 10, 1.9649)])
def test_trust_region_and_lagrangian_hessian_on_van_der_pol_v2(method, N, v_ip):
    """Van der Pol V2 (QLIN oscillates, tests/test_lqdo_paper.py): the trust region
    reaches the paper's interior-point value, and with the Lagrangian's Hessian in at
    most 8 iterations (sequential quadratic programming; the paper's IP: 15-17)."""
    from torchslq import Status
    from torchslq.lqdo.cases import van_der_pol

    tr = transcribe(van_der_pol("V2"), method, nodes=N)
    z0 = tr.initial_guess(xif=[0.0, 0.0], p=[1.0, 1.0])
    for hessian, most in (("objective", 40), ("lagrangian", 8)):
        q = Quasilinearization(safeguard="trust_region", hessian=hessian, max_iter=100)
        res = q.solve(tr, z0)
        assert res.status.tolist() == [int(Status.CONVERGED)], hessian
        assert round(float(res.objective), 4) == v_ip, hessian
        assert int(res.iterations) <= most, hessian
        assert float(res.violation) < 1e-6


def test_qlin_options_are_validated():
    with pytest.raises(ValueError, match="safeguard"):
        Quasilinearization(safeguard="trust-region")
    with pytest.raises(ValueError, match="hessian"):
        Quasilinearization(hessian="exact")
    with pytest.raises(TypeError, match="convexify"):
        Quasilinearization(convexify="yes")
