"""The batched Rodas5P integrator (torchslq.ode) against scipy's Radau on stiff problems,
a batch against one-by-one solves, per-element grids and failures, float32."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp as scipy_ivp

from torchslq.ode import PiecewiseCubic, solve_ivp

D = torch.float64
pytestmark = pytest.mark.usefixtures("single_thread")


def robertson(t, y):
    y1, y2, y3 = y.unbind(-1)
    return torch.stack(
        [-0.04 * y1 + 1e4 * y2 * y3, 0.04 * y1 - 1e4 * y2 * y3 - 3e7 * y2**2, 3e7 * y2**2], -1
    )


def robertson_np(t, y):
    y1, y2, y3 = y
    return [-0.04 * y1 + 1e4 * y2 * y3, 0.04 * y1 - 1e4 * y2 * y3 - 3e7 * y2**2, 3e7 * y2**2]


def vdp_np(mu):
    return lambda t, y: [y[1], mu * (1 - y[0] ** 2) * y[1] - y[0]]


def vdp(mu):
    def f(t, y):
        a, b = y.unbind(-1)
        m = mu if not torch.is_tensor(mu) else mu.reshape(-1)
        return torch.stack([b, m * (1 - a**2) * b - a], -1)

    return f


def vdp_jac_np(mu):
    return lambda t, y: [[0.0, 1.0], [-2 * mu * y[0] * y[1] - 1.0, mu * (1 - y[0] ** 2)]]


def radau(f, t1, y0, dense=True, jac=None):
    """scipy's Radau at tight tolerances (``f`` a NumPy right-hand side)."""
    ref = scipy_ivp(
        f,
        (0.0, t1),
        y0,
        method="Radau",
        rtol=1e-10,
        atol=1e-12,
        dense_output=dense,
        jac=jac,
    )
    assert ref.success
    return ref


def test_robertson_against_radau():
    y0 = torch.tensor([[1.0, 0.0, 0.0]], dtype=D)
    sol = solve_ivp(robertson, 0.0, 40.0, y0, rtol=1e-7, atol=1e-11)
    ref = radau(robertson_np, 40.0, [1.0, 0.0, 0.0])
    assert bool(sol.success.all())
    # stiff: a few dozen steps, their sizes spanning orders of magnitude
    assert int(sol.n_steps) < 120
    assert float(sol.h_max / sol.h_min) > 1e3
    np.testing.assert_allclose(sol.y[0, -1].numpy(), ref.y[:, -1], rtol=1e-5, atol=1e-10)
    tq = torch.linspace(0.01, 39.0, 40, dtype=D)
    np.testing.assert_allclose(
        sol(tq[None])[0].numpy(), ref.sol(tq.numpy()).T, rtol=1e-4, atol=1e-9
    )


def test_van_der_pol_stiff_against_radau():
    """mu = 1e3 through its first fast transition (near t = 807)."""
    f = vdp(1e3)
    y0 = torch.tensor([[2.0, 0.0]], dtype=D)
    sol = solve_ivp(f, 0.0, 820.0, y0, rtol=1e-6, atol=1e-8)
    ref = radau(vdp_np(1e3), 820.0, [2.0, 0.0], jac=vdp_jac_np(1e3))
    assert bool(sol.success.all())
    n = int(sol.n_steps)
    assert torch.all(sol.t[0, 1 : n + 1] > sol.t[0, :n])
    assert float(sol.t[0, n]) == 820.0
    assert float(sol.h_max / sol.h_min) > 1e4  # long steps on the slow manifold, tiny in the jump
    np.testing.assert_allclose(sol.y[0, n].numpy(), ref.y[:, -1], rtol=1e-3)
    # before the jump, the grid points and the dense output between them; in and after
    # the jump a phase error of ~1e-6 t moves y2 by O(mu), so compare the jump's time
    slow = sol.t[0, : n + 1] < 800.0
    tg = sol.t[0, : n + 1][slow]
    np.testing.assert_allclose(
        sol.y[0, : n + 1][slow].numpy(), ref.sol(tg.numpy()).T, rtol=1e-4, atol=1e-5
    )
    tq = torch.linspace(0.5, 800.0, 40, dtype=D)
    np.testing.assert_allclose(
        sol(tq[None])[0].numpy(), ref.sol(tq.numpy()).T, rtol=1e-4, atol=1e-5
    )
    fine = torch.linspace(805.0, 810.0, 5001, dtype=D)
    t_jump = fine[int((sol(fine[None])[0, :, 0] < 0).nonzero()[0])]
    t_jump_ref = fine[int(np.nonzero(ref.sol(fine.numpy())[0] < 0)[0][0])]
    assert abs(float(t_jump - t_jump_ref)) < 1e-2


def test_batch_equals_one_by_one_with_own_grids():
    mu = torch.tensor([[10.0], [100.0], [3.0]], dtype=D)
    y0 = torch.tensor([[2.0, 0.0], [1.5, 0.5], [-1.0, 1.0]], dtype=D)
    t1 = torch.tensor([6.0, 8.0, 4.0], dtype=D)
    sol = solve_ivp(vdp(mu), 0.0, t1, y0, rtol=1e-6, atol=1e-8)
    assert bool(sol.success.all())
    assert len(set(sol.n_steps.tolist())) == 3  # each element its own number of steps
    for b in range(3):
        one = solve_ivp(vdp(mu[b : b + 1]), 0.0, t1[b : b + 1], y0[b : b + 1], rtol=1e-6, atol=1e-8)
        n = int(one.n_steps)
        assert int(sol.n_steps[b]) == n and int(sol.n_rejected[b]) == int(one.n_rejected)
        torch.testing.assert_close(sol.t[b, : n + 1], one.t[0], rtol=1e-13, atol=0)
        torch.testing.assert_close(sol.y[b, : n + 1], one.y[0], rtol=1e-12, atol=1e-14)
        assert bool(sol.mask[b, : n + 1].all()) and not bool(sol.mask[b, n + 1 :].any())
        assert float(sol.t[b, n]) == float(t1[b])
        tq = torch.linspace(0.0, float(t1[b]), 33, dtype=D)[None]
        torch.testing.assert_close(sol(tq.expand(3, -1))[b], one(tq)[0], rtol=1e-12, atol=1e-13)
        m = float(mu[b])
        ref = radau(vdp_np(m), float(t1[b]), y0[b].tolist(), dense=False, jac=vdp_jac_np(m))
        np.testing.assert_allclose(one.y[0, -1].numpy(), ref.y[:, -1], rtol=1e-4, atol=1e-5)


def test_failure_is_per_element():
    y0 = torch.tensor([[2.0, 0.0], [float("nan"), 0.0], [1.0, 1.0]], dtype=D)
    sol = solve_ivp(vdp(10.0), 0.0, 2.0, y0, rtol=1e-6, atol=1e-8)
    assert sol.success.tolist() == [True, False, True]
    good = solve_ivp(vdp(10.0), 0.0, 2.0, y0[[0, 2]], rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(sol.y[[0, 2], -1], good.y[:, -1], rtol=1e-12, atol=1e-14)


def test_float32_against_radau():
    f = vdp(10.0)
    y0 = torch.tensor([[2.0, 0.0]], dtype=torch.float32)
    sol = solve_ivp(f, 0.0, 12.0, y0, rtol=1e-4, atol=1e-6)
    assert sol.y.dtype == torch.float32 and bool(sol.success.all())
    ref = radau(vdp_np(10.0), 12.0, [2.0, 0.0], jac=vdp_jac_np(10.0))
    tq = torch.linspace(0.0, 12.0, 25)
    np.testing.assert_allclose(sol(tq[None])[0].numpy(), ref.sol(tq.numpy()).T, atol=2e-2)


def test_accuracy_follows_the_tolerance():
    """Error at t1 against Radau falls with rtol (order-5 method: about 10x per 10x)."""
    f = vdp(5.0)
    y0 = torch.tensor([[2.0, 0.0]], dtype=D)
    ref = radau(vdp_np(5.0), 4.0, [2.0, 0.0], dense=False, jac=vdp_jac_np(5.0)).y[:, -1]
    errs = [
        float(
            np.abs(solve_ivp(f, 0.0, 4.0, y0, rtol=r, atol=r * 1e-2).y[0, -1].numpy() - ref).max()
        )
        for r in (1e-4, 1e-6, 1e-8)
    ]
    assert errs[0] > 10 * errs[1] > 100 * errs[2]
    assert errs[2] < 1e-6


def test_piecewise_cubic_is_exact_on_cubics(backend):
    """On both CPU backends (the kernel and the torch form)."""
    grid = torch.tensor([[0.0, 0.3, 1.0, 2.5], [1.0, 1.5, 1.5, 1.5]], dtype=D)
    n_steps = torch.tensor([3, 1])
    p = lambda t: 1.0 - 2.0 * t + 0.5 * t**2 - 0.25 * t**3  # noqa: E731
    th = torch.tensor([0.0, 1 / 3, 2 / 3, 1.0], dtype=D)
    nodes = grid[:, :-1, None] + th * (grid[:, 1:, None] - grid[:, :-1, None])
    cub = PiecewiseCubic(grid=grid, n_steps=n_steps, values=p(nodes)[..., None])
    tq = torch.stack([torch.linspace(0, 2.5, 17, dtype=D), torch.linspace(1.0, 1.5, 17, dtype=D)])
    torch.testing.assert_close(cub(tq)[..., 0], p(tq), rtol=1e-12, atol=1e-12)


def test_piecewise_cubic_kernel_equals_the_torch_form():
    """The CPU kernel against the torch form on padded per-element grids (queries
    outside the grid, on grid points, matrix values, one query per element)."""
    from torchslq.lq import set_compiled

    g = torch.Generator().manual_seed(0)
    B, N = 5, 7
    h = torch.rand(B, N, generator=g, dtype=D) + 0.1
    grid = torch.cat([torch.zeros(B, 1, dtype=D), h.cumsum(1)], 1)
    n_steps = torch.tensor([7, 3, 1, 7, 5])
    pad = torch.arange(N + 1)[None] > n_steps[:, None]
    grid = torch.where(pad, grid.gather(1, n_steps[:, None]), grid)
    cub = PiecewiseCubic(
        grid=grid, n_steps=n_steps, values=torch.randn(B, N, 4, 2, 3, generator=g, dtype=D)
    )
    tq = torch.cat([torch.rand(B, 9, generator=g, dtype=D) * 8 - 0.5, grid[:, :3]], 1)
    for t in (tq, tq[:, 0]):
        fast = cub(t)
        set_compiled(False)
        try:
            slow = cub(t)
        finally:
            set_compiled(True)
        assert fast.shape == slow.shape == (*t.shape, 2, 3)
        torch.testing.assert_close(fast, slow, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("bad", ["t1", "shape"])
def test_input_errors(bad):
    y0 = torch.zeros(2, 2, dtype=D)
    with pytest.raises(ValueError, match="t1" if bad == "t1" else "y0"):
        if bad == "t1":
            solve_ivp(vdp(1.0), 1.0, 0.5, y0)
        else:
            solve_ivp(vdp(1.0), 0.0, 1.0, y0[0])
