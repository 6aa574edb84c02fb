"""DDP: second-order dynamics terms (vector-Hessian products) in the backward pass."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import torchslq as ts
from torchslq.dynamics import dynamics_hessians, dynamics_vhp
from torchslq.systems import CartPole
from torchslq.tasks import pendulum_swingup

torch.set_num_threads(1)
F64 = torch.float64
T = 25


@pytest.fixture(scope="module")
def near_optimum():
    problem, x0 = pendulum_swingup(batch=3, horizon=T, seed=1)
    ref = ts.ILQR(progress=False, max_iter=200, tol=1e-10).solve(problem, x0)
    g = torch.Generator().manual_seed(0)
    u = ref.u + 0.03 * torch.randn(ref.u.shape, generator=g, dtype=F64)
    return problem, x0, ref, u


def _dense_newton(problem, x0, u, b):
    def J(U):
        return problem.total_cost(x0[b : b + 1], U.reshape(1, T, -1))[0]

    U = u[b].reshape(-1)
    H = torch.func.hessian(J)(U)
    g = torch.func.grad(J)(U)
    return -torch.linalg.solve(H, g), torch.linalg.eigvalsh(H).min()


def _open_loop_direction(problem, x, u, d):
    A, B = ts.linearize(problem.transition, x[:, :T], u)
    return ts.rollout_linear(A, B, d["K"], d["k"], torch.zeros_like(x[:, 0]))[1]


@pytest.mark.parametrize("method", ["rk4", "euler"])
def test_dynamics_hessians_match_autograd(method):
    """All output Hessians in one batched call == each output's Hessian by autograd."""
    dyn = ts.discretize(CartPole(), 0.05, method)
    g = torch.Generator().manual_seed(2)
    x = torch.randn(3, 5, 4, generator=g, dtype=F64)
    u = torch.randn(3, 5, 1, generator=g, dtype=F64)
    Hxx, Huu, Hux = dynamics_hessians(dyn, x, u)
    assert Hxx.shape == (4, 3, 5, 4, 4) and Huu.shape == (4, 3, 5, 1, 1)
    for b, t in ((0, 0), (2, 4)):
        for i in range(4):

            def fi(z, i=i):
                return dyn(z[:4].reshape(1, 4), z[4:].reshape(1, 1))[0, i]

            H = torch.autograd.functional.hessian(fi, torch.cat([x[b, t], u[b, t]]))
            torch.testing.assert_close(Hxx[i, b, t], H[:4, :4], rtol=1e-9, atol=1e-11)
            torch.testing.assert_close(Huu[i, b, t], H[4:, 4:], rtol=1e-9, atol=1e-11)
            torch.testing.assert_close(Hux[i, b, t], H[4:, :4], rtol=1e-9, atol=1e-11)


def test_dynamics_hessians_in_time_chunks_equal_one_call(monkeypatch):
    """Above HESSIAN_CHUNK_ROWS rows the Hessians (and vector-Hessian products) are
    computed a few time steps at a time; the result equals the single batched call exactly, also with per-element
    model parameters shaped (B, 1) (which a split along the batch dim would misalign)."""
    import sys

    lin = sys.modules["torchslq.dynamics.linearize"]
    mc = torch.tensor([[1.0], [1.5], [0.7]], dtype=F64)  # per element, (B, 1)
    model = ts.discretize(CartPole(mc=mc), 0.05)

    def dyn(x, u):  # a plain callable: the automatic-differentiation path (chunked)
        return model(x, u)

    g = torch.Generator().manual_seed(3)
    x = torch.randn(3, 11, 4, generator=g, dtype=F64)
    u = torch.randn(3, 11, 1, generator=g, dtype=F64)
    s = torch.randn(3, 11, 4, generator=g, dtype=F64)
    whole = dynamics_hessians(dyn, x, u)
    whole_vhp = dynamics_vhp(dyn, x, u, s)
    monkeypatch.setattr(lin, "HESSIAN_CHUNK_ROWS", 7)  # 33 rows -> chunks of 2 steps
    chunked = dynamics_hessians(dyn, x, u)
    chunked_vhp = dynamics_vhp(dyn, x, u, s)
    for a, b in zip(whole + whole_vhp, chunked + chunked_vhp, strict=True):
        assert a.shape == b.shape
        assert torch.equal(a, b)
    # and per element the parameters really differ (the test would catch a misalignment)
    assert not torch.allclose(whole[2][:, 0], whole[2][:, 1])


def test_dynamics_vhp_matches_autograd_hessian():
    problem, _ = pendulum_swingup(batch=2, horizon=T)
    f = problem.transition
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 4, 2, generator=g, dtype=F64)
    u = torch.randn(2, 4, 1, generator=g, dtype=F64)
    s = torch.randn(2, 4, 2, generator=g, dtype=F64)
    Hxx, Huu, Hux = dynamics_vhp(f, x, u, s)
    for b in range(2):
        for t in range(4):

            def sf(z, b=b, t=t):
                return (s[b, t] * f(z[:2].reshape(1, 1, 2), z[2:].reshape(1, 1, 1))[0, 0]).sum()

            H = torch.autograd.functional.hessian(sf, torch.cat([x[b, t], u[b, t]]))
            torch.testing.assert_close(Hxx[b, t], H[:2, :2], rtol=1e-10, atol=1e-12)
            torch.testing.assert_close(Huu[b, t], H[2:, 2:], rtol=1e-10, atol=1e-12)
            torch.testing.assert_close(Hux[b, t], H[2:, :2], rtol=1e-10, atol=1e-12)


def test_costate_ddp_step_is_the_newton_step(near_optimum, backend):
    """With lam-weighted terms and no regularisation the LQ step is -H^-1 g of J(U)."""
    problem, x0, _, u = near_optimum
    x = problem.rollout(x0, u)
    solver = ts.DDP(second_order="costate", mu_init=0.0, mu_min=0.0, progress=False)
    d = solver.direction(problem, x, u)
    du = _open_loop_direction(problem, x, u, d)
    checked = 0
    for b in range(x0.shape[0]):
        newton, min_eig = _dense_newton(problem, x0, u, b)
        if min_eig <= 0 or bool(d["failed"][b]):
            continue
        checked += 1
        torch.testing.assert_close(du[b].reshape(-1), newton, rtol=1e-8, atol=1e-10)
    assert checked >= 1


def test_value_ddp_tensor_and_stepwise_hooks_agree(near_optimum):
    problem, x0, _, u = near_optimum
    x = problem.rollout(x0, u)
    dirs = []
    for limit in (None, 2**30):
        solver = ts.DDP(mu_init=0.0, progress=False, vhp_memory_limit=limit)
        dirs.append(solver.direction(problem, x, u))
    torch.testing.assert_close(dirs[0]["K"], dirs[1]["K"], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(dirs[0]["k"], dirs[1]["k"], rtol=1e-10, atol=1e-12)


def test_ddp_differs_from_ilqr_away_from_optimum(near_optimum):
    """The second-order terms change the step (else the DDP code path would be dead)."""
    problem, x0, _, u = near_optimum
    x = problem.rollout(x0, u)
    ks = []
    for solver in (ts.ILQR(mu_init=0.0, progress=False), ts.DDP(mu_init=0.0, progress=False)):
        ks.append(solver.direction(problem, x, u)["k"])
    assert (ks[0] - ks[1]).abs().max() > 1e-6


@pytest.mark.parametrize("mode", ["value", "costate"])
def test_ddp_converges_quadratically(near_optimum, mode, backend):
    """Near the optimum the gradient-norm ratios g_{k+1}/g_k^2 stay bounded while
    g_k -> 0 (quadratic convergence); iLQR's ratios g_{k+1}/g_k do not go to 0."""
    problem, x0, ref, u = near_optimum
    # tol 1e-10: this problem's gradient reaches its round-off floor near 1e-11 (where
    # steps stop being full and g creeps down by ~2x per iteration, on either kernel)
    res = ts.DDP(second_order=mode, progress=False, max_iter=50, tol=1e-10).solve(problem, x0, u)
    assert bool(res.converged.all())
    torch.testing.assert_close(res.u, ref.u, rtol=1e-6, atol=1e-7)
    for b in range(x0.shape[0]):
        g = res.history["grad_norm"][b, : int(res.iterations[b]) + 1]
        steps = res.history["step"][b, 1 : int(res.iterations[b]) + 1]
        # look at the full-step tail with g below 1e-2
        tail = [
            i
            for i in range(1, g.numel())
            if g[i - 1] < 1e-2 and steps[i - 1] == 1.0 and g[i] > 1e-13
        ]
        assert tail, g
        for i in tail:
            assert g[i] <= 50.0 * g[i - 1] ** 2, (b, g.tolist())
    # the same test fails for iLQR (Gauss-Newton: linear rate), so it tells them apart
    il = ts.ILQR(progress=False, max_iter=200, tol=1e-11).solve(problem, x0, u)
    g = il.history["grad_norm"][0, : int(il.iterations[0]) + 1]
    assert any(g[i] > 50.0 * g[i - 1] ** 2 for i in range(1, g.numel()) if g[i - 1] < 1e-4)


def test_ddp_batch_equals_singles(near_optimum, backend):
    problem, x0, _, u = near_optimum
    solver = ts.DDP(progress=False, max_iter=30)
    batch = solver.solve(problem, x0, u)
    for b in range(x0.shape[0]):
        single = solver.solve(problem, x0[b], u[b])
        torch.testing.assert_close(single.u, batch.u[b], rtol=1e-9, atol=1e-11)
        assert int(single.iterations) == int(batch.iterations[b])


def test_ddp_option_validation():
    with pytest.raises(ValueError, match="second_order"):
        ts.DDP(second_order="hessian")


def test_second_order_failure_falls_back_to_the_ilqr_step():
    """From this cart-pole start the value-mode second-order terms make the backward pass
    non-finite at iteration 2 for every mu (the value function overflows); the element
    then takes the iLQR step instead of stopping as non-finite (found in the 10k
    distillation example), and DDP converges to a stationary point."""
    from torchslq.tasks import cartpole_swingup

    problem, _ = cartpole_swingup(1)
    x0 = torch.tensor([[0, -0.03212286533913405, 0, 0.0]], dtype=F64)
    res = ts.DDP(max_iter=300, tol=1e-6, progress=False).solve(problem, x0)
    assert res.status_names() == ["converged"]
    assert torch.isfinite(res.u).all() and float(res.grad_norm[0]) < 1e-6


def test_mu_retries_repeat_the_pass_for_the_failing_elements_only(monkeypatch):
    """Far from the optimum DDP's second-order terms make some ``Quu`` indefinite; on the
    torch path the pass is then repeated with a larger ``mu`` for those elements only
    (fewer rows per retry, measured by wrapping the pass), and the batch still equals
    one-by-one solves (so the rows put back are the right ones). Trying the next values
    of mu side by side in one pass (the default) gives the same solution bit for bit, in
    fewer passes."""
    import torchslq.lq.riccati as riccati_mod
    from torchslq.lq import set_compiled
    from torchslq.tasks import cartpole_swingup

    problem, x0 = cartpole_swingup(4, seed=3)
    rows_per_pass: list[int] = []
    kernel = riccati_mod._torch_backward

    def counting(A, *args, **kwargs):
        rows_per_pass.append(A.shape[0])
        return kernel(A, *args, **kwargs)

    set_compiled(False)
    try:
        monkeypatch.setattr(riccati_mod, "_torch_backward", counting)
        monkeypatch.setattr(riccati_mod, "RETRY_ROWS", 1)  # one candidate mu per pass
        solver = ts.DDP(progress=False, max_iter=15, tol=1e-8)
        batch = solver.solve(problem, x0)
        assert any(0 < r < x0.shape[0] for r in rows_per_pass), rows_per_pass
        monkeypatch.undo()
        # side by side (the default): the same solution to the last bit, in fewer passes
        passes_one_by_one = len(rows_per_pass)
        rows_per_pass.clear()
        monkeypatch.setattr(riccati_mod, "_torch_backward", counting)
        side_by_side = solver.solve(problem, x0)
        monkeypatch.undo()
        assert torch.equal(side_by_side.u, batch.u) and torch.equal(side_by_side.K, batch.K)
        assert torch.equal(side_by_side.iterations, batch.iterations)
        assert len(rows_per_pass) < passes_one_by_one, (len(rows_per_pass), passes_one_by_one)
        for b in range(x0.shape[0]):
            single = solver.solve(problem, x0[b])
            torch.testing.assert_close(single.u, batch.u[b], rtol=1e-9, atol=1e-11)
            assert int(single.iterations) == int(batch.iterations[b])
    finally:
        set_compiled(True)


@pytest.mark.parametrize("solver_name", ["DDP", "DDP-bounded"])
def test_restarts_inside_the_compiled_kernel_equal_the_repeated_passes(monkeypatch, solver_name):
    """On the CPU the Riccati kernel restarts a failed element itself with the next values
    of the same mu schedule: the solve is the same to the last bit as with the restarts
    made by repeating passes from Python, and no pass is repeated (one per iteration,
    plus none), while the repeated-pass version needed extra passes on this problem."""
    import torchslq.solvers.newton as ilqr_mod  # iLQR/DDP's direction
    from torchslq.tasks import cartpole_swingup

    problem, x0 = cartpole_swingup(6, seed=3)
    kw = dict(progress=False, max_iter=25, tol=1e-8)
    if solver_name == "DDP":
        solver = ts.DDP(**kw)
    else:  # the control-limited pass (box QPs) in the kernel
        solver = ts.DDP(u_min=-3.0, u_max=3.0, **kw)
    passes = []
    kernel = ilqr_mod.riccati_backward

    def counting(*args, **kwargs):
        out = kernel(*args, **kwargs)
        passes.append(out.reg is not None)
        return out

    def repeated_passes(*args, reg, restarts=None, **kwargs):
        """The restarts made from Python: the whole pass repeated, one mu at a time."""
        fac = kernel(*args, reg=reg, **kwargs)
        passes.append(False)
        sched = restarts.schedule
        bad = fac.failed | ~torch.isfinite(fac.Kk).flatten(1).all(1)
        mu, delta = reg.clone(), restarts.delta.clone()
        for _ in range(sched.max_restarts):
            retry = bad & restarts.allowed & (mu <= sched.reg_max)
            if not bool(retry.any()):
                break
            mu, delta = sched.increase(mu, delta, retry)
            fac = kernel(*args, reg=mu, **kwargs)
            passes.append(False)
            bad = fac.failed | ~torch.isfinite(fac.Kk).flatten(1).all(1)
        return dataclasses.replace(fac, failed=bad, reg=mu, reg_delta=delta)

    monkeypatch.setattr(ilqr_mod, "riccati_backward", counting)
    inside = solver.solve(problem, x0)
    n_inside, restarted_inside = len(passes), all(passes)
    passes.clear()
    monkeypatch.setattr(ilqr_mod, "riccati_backward", repeated_passes)
    repeated = solver.solve(problem, x0)
    assert restarted_inside  # every pass ran on the kernel with restarts
    for name in ("u", "x", "K", "cost", "iterations", "status"):
        assert torch.equal(getattr(inside, name), getattr(repeated, name)), name
    assert n_inside <= int(inside.iterations.max()) + 1  # one pass per iteration
    assert len(passes) > n_inside, (len(passes), n_inside)  # restarts were needed
