"""Herber & Sundarrajan (2020), small cases against the paper's Tables 1-3: container
crane QLIN-TR20 / QLIN-PS10 / QLIN-PS40, Van der Pol V2 (QLIN does not converge; the safeguarded
variant reaches the interior-point values), co-design transfer QLIN-PS10."""

from __future__ import annotations

import pytest
import torch

from torchslq import Status
from torchslq.lqdo import Quasilinearization, transcribe
from torchslq.lqdo.cases import codesign_transfer, container_crane, crane_initial_guess, van_der_pol

pytestmark = pytest.mark.usefixtures("float64_default")


@pytest.mark.parametrize("method,N,v,iters", [("TR", 20, 0.0380, 3), ("PS", 10, 0.0376, 4)])
def test_container_crane_table1(method, N, v, iters):
    tr = transcribe(container_crane(), method, nodes=N)
    res = Quasilinearization().solve(tr, crane_initial_guess(tr))
    assert res.status.tolist() == [int(Status.CONVERGED)]
    assert round(float(res.objective), 4) == v
    assert int(res.iterations) == iters
    assert float(res.violation) < 1e-6


@pytest.mark.parametrize("method,N,v_ip", [("TR", 20, 1.9809), ("PS", 10, 1.9649)])
def test_van_der_pol_v2_table2_qlin_fails_safeguard_reaches_ip(method, N, v_ip):
    tr = transcribe(van_der_pol("V2"), method, nodes=N)
    z0 = tr.initial_guess(xif=[0.0, 0.0], p=[1.0, 1.0])
    plain = Quasilinearization(max_iter=30).solve(tr, z0)
    assert plain.status.tolist() == [int(Status.MAX_ITER)]  # "did not converge"
    c = plain.history["cost"][0, -6:]
    # it oscillates between two trajectories (Fig. 3): period two, distinct values
    torch.testing.assert_close(c[2:], c[:-2], rtol=1e-6, atol=0)
    assert abs(float(c[-1] - c[-2])) > 1e-2
    safe = Quasilinearization(safeguard="merit", max_iter=100).solve(tr, z0)
    assert safe.status.tolist() == [int(Status.CONVERGED)]
    assert round(float(safe.objective), 4) == v_ip
    assert float(safe.violation) < 1e-6


def test_codesign_transfer_table3_qlin_ps10():
    tr = transcribe(codesign_transfer(), "PS", nodes=10)
    res = Quasilinearization().solve(tr, torch.ones(1, tr.n))  # "a poor initial guess of one"
    assert res.status.tolist() == [int(Status.CONVERGED)]
    assert round(float(res.objective), 4) == 23.6228
    assert abs(int(res.iterations) - 8) <= 1  # the paper: 8


def test_container_crane_table1_ps40_with_clarabel_on_every_qp(monkeypatch):
    """QLIN-PS40: 0.0375 in 3 iterations (Table 1) with every LGL QP solved by Clarabel
    (the dense fallback disabled), and the same value as the dense interior point alone
    (an independent solver) to 1e-6."""
    from torchslq.lqdo import backends

    tr = transcribe(container_crane(), "PS", nodes=40)
    dense = Quasilinearization(backend="dense").solve(tr, crane_initial_guess(tr))

    def no_fallback(*args, **kwargs):
        raise AssertionError("Clarabel failed on a QP: the dense fallback was called")

    monkeypatch.setattr(backends, "solve_dense", no_fallback)
    res = Quasilinearization().solve(tr, crane_initial_guess(tr))
    assert res.status.tolist() == [int(Status.CONVERGED)]
    assert round(float(res.objective), 4) == 0.0375
    assert int(res.iterations) == 3
    assert float(res.violation) < 1e-6
    assert float(res.objective) == pytest.approx(float(dense.objective), rel=1e-6)
