"""Two-level fixed-parameter method: the lower level against the closed-form
minimum-energy transfer (controllability Gramian), the exact dv/dp against that closed
form's derivative and against finite differences with active inequality constraints,
and a batch of designs against one-by-one solves."""

from __future__ import annotations

import pytest
import torch
from scipy.optimize import minimize_scalar

from torchslq.lqdo import transcribe
from torchslq.lqdo.cases import codesign_closed_form, codesign_transfer, suspension
from torchslq.lqdo.twolevel import TwoLevel

pytestmark = pytest.mark.usefixtures("float64_default")


@pytest.mark.parametrize("backend", ["dense", "clarabel"])
def test_lower_level_value_and_gradient_against_the_gramian_closed_form(backend):
    tr = transcribe(codesign_transfer(), "PS", nodes=16)
    p = torch.tensor([[0.0], [2.0], [6.9], [15.0]])
    ll = TwoLevel(backend=backend).lower(tr, p)
    exact = torch.tensor([codesign_closed_form(float(q)) for q in p[:, 0]])
    torch.testing.assert_close(ll.value, exact, rtol=1e-8, atol=0)
    e = 1e-5
    dexact = torch.tensor(
        [
            (codesign_closed_form(float(q) + e) - codesign_closed_form(float(q) - e)) / (2 * e)
            for q in p[1:, 0]
        ]
    )
    torch.testing.assert_close(ll.grad[1:, 0], dexact, rtol=1e-5, atol=1e-6)


def test_tlfp_reaches_the_closed_form_optimum_and_batch_equals_single():
    opt = minimize_scalar(
        codesign_closed_form, bounds=(0, 50), method="bounded", options={"xatol": 1e-10}
    )
    tr = transcribe(codesign_transfer(), "PS", nodes=10)
    tl = TwoLevel(backend="dense")
    res = tl.solve(tr, torch.tensor([[1.0], [12.0], [3.0]]))
    assert (res.status == 0).all()
    torch.testing.assert_close(res.objective, torch.full((3,), opt.fun), rtol=1e-8, atol=0)
    torch.testing.assert_close(res.p[:, 0], torch.full((3,), opt.x), rtol=1e-5, atol=0)
    assert round(float(res.objective[0]), 4) == 23.6228  # Table 3, TLFP-PS10
    one = tl.solve(tr, torch.tensor([[12.0]]))
    torch.testing.assert_close(one.p[0], res.p[1], rtol=1e-9, atol=0)
    assert int(one.iterations[0]) == int(res.iterations[1])


def test_exact_gradient_with_active_rattle_space_bounds_against_finite_differences():
    tr = transcribe(suspension(), "TR", nodes=25)
    tl = TwoLevel(backend="dense")
    p = torch.tensor([[100.0, 500.0], [150.0, 1000.0]])
    ll = tl.lower(tr, p)
    assert (ll.status == 0).all()
    xi3 = ll.z[:, tr.idx_x[:, 2]]
    assert (xi3.abs().amax(1) > 0.04 - 1e-6).all()  # the rattle-space bound is active
    for j, e in ((0, 1e-3), (1, 1e-2)):
        dp = torch.zeros(2, 2)
        dp[:, j] = e * p[:, j]
        fd = (tl.lower(tr, p + dp, False).value - tl.lower(tr, p - dp, False).value) / (
            2 * dp[:, j]
        )
        torch.testing.assert_close(ll.grad[:, j], fd, rtol=1e-4, atol=1e-12)
