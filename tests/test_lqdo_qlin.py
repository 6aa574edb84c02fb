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
