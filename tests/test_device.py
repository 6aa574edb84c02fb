"""The library's main paths on an accelerator, each compared with a float64 CPU solve of
the same problem computed in the same test (no stored numbers).

The device is ``TORCHSLQ_TEST_DEVICE`` (default ``"cuda"``). Every test runs on that
device and, in addition, on ``"cpu"`` passed explicitly as a device string, so the
device plumbing (problems built with ``device=``, modules moved by ``.to``, results read
back) is exercised on machines without a GPU too; the accelerator copy of each test is
skipped with a reason where that device is not available (CI has no GPU). With
``TORCHSLQ_TEST_DEVICE=cpu`` the file runs once, on the CPU.

Covered: ``lqr_solve`` forward and implicit backward (gradients w.r.t. ``Q, q, A, B,
x0``), SLQ, ILQR and DDP with control bounds, GoPRONTO (with its input barrier), the MPC
layer forward and implicit backward, float32 against float64, batch == singles, results
staying on the device and the TensorBoard logger fed with device tensors.
"""

from __future__ import annotations

import math
import os

import pytest
import torch

import torchslq as ts
from torchslq import DDP, ILQR, MPC, SLQ, GoPRONTO, QuadraticCost, discretize, lqr_solve
from torchslq.systems import Pendulum
from torchslq.tasks import pendulum_swingup

pytestmark = [
    pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning"),
    pytest.mark.usefixtures("single_thread"),
]

F64 = torch.float64
DEVICE = os.environ.get("TORCHSLQ_TEST_DEVICE", "cuda")


def _unavailable(dev: str) -> str | None:
    """Why ``dev`` cannot be used here, or None when it can."""
    try:
        d = torch.device(dev)
    except (RuntimeError, ValueError) as e:
        return f"TORCHSLQ_TEST_DEVICE={dev!r} is not a torch device ({e})"
    if d.type == "cpu":
        return None
    if d.type == "cuda" and not torch.cuda.is_available():
        return f"device {dev!r} not available: torch.cuda.is_available() is False"
    if d.type == "mps" and not torch.backends.mps.is_available():
        return f"device {dev!r} not available: torch.backends.mps.is_available() is False"
    try:
        torch.zeros(1, device=d)
    except Exception as e:  # noqa: BLE001  (any backend error means: not usable here)
        return f"device {dev!r} not usable: {type(e).__name__}: {e}"
    return None


_DEVICES = ["cpu"] if DEVICE.split(":")[0] == "cpu" else ["cpu", DEVICE]


@pytest.fixture(
    params=[
        pytest.param(
            d, marks=pytest.mark.skipif(_unavailable(d) is not None, reason=str(_unavailable(d)))
        )
        for d in _DEVICES
    ]
)
def device(request) -> torch.device:
    return torch.device(request.param)


# ----------------------------------------------------------------------------- helpers


def on(device: torch.device, t: torch.Tensor) -> bool:
    """``t`` lives on ``device`` (``cuda`` and ``cuda:0`` are the same)."""
    return t.device.type == device.type and (device.index is None or t.device.index == device.index)


def cpu64(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to("cpu", F64)


def assert_close(a: torch.Tensor, b: torch.Tensor, rtol: float, atol: float = 0.0, what=""):
    torch.testing.assert_close(
        cpu64(a), cpu64(b), rtol=rtol, atol=atol, msg=lambda m: f"{what}: {m}"
    )


def assert_result_on(device: torch.device, r) -> None:
    """Every tensor of a SolverResult is on ``device`` (``history["time"]`` holds host
    wall-clock readings and stays on the CPU by design)."""
    for name in ("x", "u", "cost", "grad_norm", "iterations", "status", "converged", "K", "k"):
        t = getattr(r, name)
        assert on(device, t), f"result.{name} is on {t.device}, expected {device}"
    if r.active_bounds is not None:
        assert on(device, r.active_bounds), f"active_bounds on {r.active_bounds.device}"
    for k, v in r.history.items():
        if k != "time" and torch.is_tensor(v):
            assert on(device, v), f"result.history[{k!r}] is on {v.device}, expected {device}"


def spd(g: torch.Generator, shape: tuple[int, ...], k: int, floor: float) -> torch.Tensor:
    M = torch.randn(*shape, k, k, generator=g, dtype=F64)
    return M @ M.mT / k + floor * torch.eye(k, dtype=F64)


def lq_problem(seed: int = 0, bsz: int = 3, T: int = 12, n: int = 4, m: int = 2):
    """A batched, time-varying, well-conditioned LQ problem (all terms present)."""
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(n, dtype=F64) + 0.3 * torch.randn(bsz, T, n, n, generator=g, dtype=F64) / n
    return dict(
        A=A,
        B=torch.randn(bsz, T, n, m, generator=g, dtype=F64),
        Q=spd(g, (bsz, T + 1), n, 0.5),
        R=spd(g, (bsz, T), m, 0.5),
        x0=torch.randn(bsz, n, generator=g, dtype=F64),
        q=torch.randn(bsz, T + 1, n, generator=g, dtype=F64),
        r=torch.randn(bsz, T, m, generator=g, dtype=F64),
        S=0.1 * torch.randn(bsz, T, m, n, generator=g, dtype=F64),
        c=0.5 * torch.randn(bsz, T, n, generator=g, dtype=F64),
    )


def lq_loss_and_grads(
    args: dict, device, dtype=F64, wrt=("Q", "q", "A", "B", "x0"), method: str = "sequential"
):
    """Forward on ``device`` by ``method``; loss = cost + random projections of x and u;
    grads."""
    a = {k: v.to(device, dtype).requires_grad_(k in wrt) for k, v in args.items()}
    sol = lqr_solve(**a, method=method)
    g = torch.Generator().manual_seed(7)
    wx = torch.randn(sol.x.shape, generator=g, dtype=F64).to(device, dtype)
    wu = torch.randn(sol.u.shape, generator=g, dtype=F64).to(device, dtype)
    loss = sol.cost.sum() + (wx * sol.x).sum() + (wu * sol.u).sum()
    grads = torch.autograd.grad(loss, [a[k] for k in wrt])
    return sol, loss, dict(zip(wrt, grads, strict=True))


def pendulum(device, dtype=F64, batch=4, horizon=30, seed=0):
    return pendulum_swingup(batch=batch, horizon=horizon, seed=seed, device=device, dtype=dtype)


# ----------------------------------------------------------------------------- LQ kernel


@pytest.mark.parametrize("method, T", [("sequential", 12), ("scan", 1), ("scan", 37), ("scan", 64)])
def test_lqr_solve_forward_and_backward_match_cpu(device, method, T):
    """Forward and implicit backward on the device by ``method`` (the parallel-in-time
    scan with its scan backward, too; T = 37 is odd and not a power of two) against the
    sequential kernel on the CPU."""
    args = lq_problem(seed=0 if method == "sequential" else 5, T=T)
    ref, ref_loss, ref_g = lq_loss_and_grads(args, "cpu")
    sol, loss, g = lq_loss_and_grads(args, device, method=method)
    rtol, atol = (1e-10, 1e-12) if method == "sequential" else (1e-9, 1e-11)
    for name in ("x", "u", "cost", "K", "k", "lam", "status"):
        assert on(device, getattr(sol, name)), f"sol.{name} on {getattr(sol, name).device}"
    for name in ("x", "u", "cost", "K", "k", "lam"):
        assert_close(getattr(sol, name), getattr(ref, name), rtol, atol, name)
    assert torch.equal(sol.status.cpu(), ref.status)
    assert_close(loss, ref_loss, 1e-10)
    for k in ref_g:
        assert on(device, g[k]), f"grad {k} on {g[k].device}"
        assert_close(g[k], ref_g[k], 1e-9, 1e-11, f"d loss / d {k}")


def test_lqr_solve_float32_close_to_float64(device):
    args = lq_problem(seed=3)
    ref, _, ref_g = lq_loss_and_grads(args, "cpu")
    sol, _, g = lq_loss_and_grads(args, device, dtype=torch.float32)
    assert sol.x.dtype == torch.float32 and on(device, sol.x)
    assert bool(torch.isfinite(sol.x).all()) and bool(torch.isfinite(sol.cost).all())
    assert_close(sol.x, ref.x, 1e-3, 1e-4, "x")
    assert_close(sol.cost, ref.cost, 1e-3, 1e-4, "cost")
    for k in ref_g:
        assert bool(torch.isfinite(g[k]).all()), k
        assert_close(g[k], ref_g[k], 1e-2, 1e-3, f"float32 d loss / d {k}")


def test_lqr_solve_scan_statuses_match_cpu(device):
    """An element whose Quu is indefinite (R > 0, terminal weight -50 I) and one with a
    NaN in x0: the scan on the device reports the CPU sequential kernel's statuses, and
    the other elements' solutions."""
    args = lq_problem(seed=6, bsz=4, T=9)
    args["Q"] = args["Q"].clone()
    args["Q"][1, -1] = -50.0 * torch.eye(args["Q"].shape[-1], dtype=F64)
    args["x0"] = args["x0"].clone()
    args["x0"][2, 0] = float("nan")
    ref = lqr_solve(**args, validate=False)
    sol = lqr_solve(**{k: v.to(device) for k, v in args.items()}, validate=False, method="scan")
    expected = [ts.Status.CONVERGED, ts.Status.NOT_POSITIVE_DEFINITE, ts.Status.NON_FINITE]
    assert ref.status.tolist()[:3] == [int(s) for s in expected]
    assert torch.equal(sol.status.cpu(), ref.status)
    for i in (0, 3):
        for name in ("x", "u", "cost"):
            assert_close(getattr(sol, name)[i], getattr(ref, name)[i], 1e-9, 1e-11, name)


def test_lqr_solve_default_method_on_device(device):
    """T = 120: the default (``auto``) runs what :func:`choose_method` names for the
    device (the scan on a CUDA GPU), bit for bit, and matches the CPU solve."""
    args = lq_problem(seed=9, bsz=2, T=120)
    ref = lqr_solve(**args, method="sequential")
    on_dev = {k: v.to(device) for k, v in args.items()}
    sol = lqr_solve(**on_dev)
    named = lqr_solve(**on_dev, method=ts.lq.choose_method(120, 2, device, F64))
    for name in ("x", "u", "cost", "K", "k", "lam"):
        assert torch.equal(getattr(sol, name), getattr(named, name)), name
        assert_close(getattr(sol, name), getattr(ref, name), 1e-9, 1e-11, name)


def test_lqr_solve_scan_float32_close_to_float64(device):
    args = lq_problem(seed=8, T=50)
    ref = lqr_solve(**args)
    sol = lqr_solve(**{k: v.to(device, torch.float32) for k, v in args.items()}, method="scan")
    assert sol.x.dtype == torch.float32 and on(device, sol.x)
    assert_close(sol.x, ref.x, 1e-3, 1e-4, "x")
    assert_close(sol.cost, ref.cost, 1e-3, 1e-4, "cost")


@pytest.mark.parametrize(("n", "m"), [(4, 2), (1, 1), (3, 1)])
def test_scan_fused_kernels_on_device_match_torch_ops(device, n, m):
    """On a CUDA device with Triton the scan runs the fused kernels (no fallback warning)
    and gives the torch-op scan's results on the same device, forward and gradients (on
    the CPU both are the torch ops: the comparison holds trivially there)."""
    import warnings

    from torchslq.lq import scan_kernels

    args = {k: v.to(device) for k, v in lq_problem(seed=11, bsz=3, T=45, n=n, m=m).items()}
    on_cuda = torch.device(device).type == "cuda"
    if on_cuda and scan_kernels.HAVE_TRITON:
        assert scan_kernels.enabled(args["A"], n, m)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # a kernel that fails to build
        fused, _, g_fused = lq_loss_and_grads(args, device, method="scan")
    with scan_kernels.disabled():
        ref, _, g_ref = lq_loss_and_grads(args, device, method="scan")
    for name in ("x", "u", "cost", "K", "k", "lam"):
        assert_close(getattr(fused, name), getattr(ref, name), 1e-10, 1e-12, name)
    for k in g_ref:
        assert_close(g_fused[k], g_ref[k], 1e-9, 1e-11, f"d loss / d {k}")


# ----------------------------------------------------------------------------- solvers


def test_slq_matches_cpu(device):
    solver = SLQ(max_iter=50, tol=1e-9, rollout="closed_loop", progress=False)
    prob_c, x0_c = pendulum("cpu")
    ref = solver.solve(prob_c, x0_c)
    prob, x0 = pendulum(device)
    assert on(device, x0)
    r = solver.solve(prob, x0)
    assert_result_on(device, r)
    assert r.converged.all(), r.status_names()
    assert ref.converged.all(), ref.status_names()
    assert_close(r.cost, ref.cost, 1e-9, 0, "cost")
    assert_close(r.u, ref.u, 1e-6, 1e-7, "u")
    assert_close(r.x, ref.x, 1e-6, 1e-7, "x")


@pytest.mark.parametrize("solver_cls", [ILQR, DDP], ids=["ilqr", "ddp"])
def test_bounded_ilqr_ddp_match_cpu(device, solver_cls):
    """Control-limited (box-QP) solves: the bound is active on every element.

    tol = 3e-7: element 0 converges linearly under its active bound, and once its
    gradient is below ~1e-7 its accepted steps change the cost by less than rounding, so
    a tighter tol leaves the status to the stall rule's race with the rounding of each
    backend (an H100 run's CPU reference stalled at tol = 1e-9 where CUDA converged).
    At 3e-7 both reach it with a 3x margin on either side of the gradient's decrease."""
    kw = dict(max_iter=100, tol=3e-7, u_min=-1.5, u_max=1.5, progress=False)
    prob_c, x0_c = pendulum("cpu", batch=3, horizon=40)
    ref = solver_cls(**kw).solve(prob_c, x0_c)
    prob, x0 = pendulum(device, batch=3, horizon=40)
    r = solver_cls(**kw).solve(prob, x0)
    assert_result_on(device, r)
    assert r.active_bounds is not None and on(device, r.active_bounds)
    assert bool((r.active_bounds != 0).any(dim=(1, 2)).all())  # the bound matters
    assert float(r.u.abs().max()) <= 1.5 + 1e-12
    assert torch.equal(r.status.cpu(), ref.status), (r.status_names(), ref.status_names())
    assert torch.equal(r.active_bounds.cpu(), ref.active_bounds)
    assert_close(r.cost, ref.cost, 1e-9, 0, "cost")
    assert_close(r.u, ref.u, 1e-6, 1e-7, "u")


def test_gopronto_with_barrier_matches_cpu(device):
    kw = dict(variant="nesterov", max_iter=20, u_max=3.0, progress=False)
    prob_c, x0_c = pendulum("cpu", batch=2)
    ref = GoPRONTO(**kw).solve(prob_c, x0_c)
    prob, x0 = pendulum(device, batch=2)
    r = GoPRONTO(**kw).solve(prob, x0)
    assert_result_on(device, r)
    for name in ("alpha", "mu", "recomputations"):
        assert on(device, getattr(r, name)), f"{name} on {getattr(r, name).device}"
    assert float(r.u.abs().max()) < 3.0
    assert torch.equal(r.iterations.cpu(), ref.iterations)
    assert_close(r.history["cost"], ref.history["cost"], 1e-7, 0, "cost history")
    assert_close(r.u, ref.u, 1e-6, 1e-7, "u")
    hist = r.history["cost"]
    assert bool((hist[:, -1] < 0.9 * hist[:, 0]).all())


def test_ilqr_batch_equals_singles_on_device(device):
    solver = ILQR(max_iter=100, tol=1e-9, progress=False)
    prob, x0 = pendulum(device, batch=3)
    rb = solver.solve(prob, x0)
    assert rb.converged.all(), rb.status_names()
    for i in range(3):
        ri = solver.solve(prob, x0[i])  # unbatched in, unbatched out
        assert ri.x.shape == (31, 2) and on(device, ri.x) and on(device, ri.iterations)
        assert int(ri.iterations) == int(rb.iterations[i])
        assert_close(ri.x, rb.x[i], 1e-9, 1e-10, f"x[{i}]")
        assert_close(ri.u, rb.u[i], 1e-9, 1e-10, f"u[{i}]")


def test_float32_solvers_close_to_float64(device):
    """float32 on the device runs, stays finite and lands near the float64 CPU optimum."""
    prob_c, x0_c = pendulum("cpu")
    prob, x0 = pendulum(device, dtype=torch.float32)
    for solver in (
        SLQ(max_iter=50, tol=1e-4, rollout="closed_loop", progress=False),
        ILQR(max_iter=100, tol=1e-4, progress=False),
    ):
        ref = solver.solve(prob_c, x0_c)
        r = solver.solve(prob, x0)
        assert r.x.dtype == torch.float32 and r.K.dtype == torch.float32
        assert_result_on(device, r)
        for name in ("x", "u", "cost", "K"):
            assert bool(torch.isfinite(getattr(r, name)).all()), name
        assert_close(r.cost, ref.cost, 1e-3, 0, f"{type(solver).__name__} float32 cost")
        assert_close(r.x, ref.x, 0, 5e-2, f"{type(solver).__name__} float32 x")


# ----------------------------------------------------------------------------- MPC layer

DT, T_MPC = 0.05, 15


def mpc_loss(theta: torch.Tensor, x0: torch.Tensor, backward: str = "implicit"):
    """The MPC layer of tests/test_mpc.py: pendulum with learnable mass, damping, cost
    reference and Q diagonal; loss = random projections of the solution."""
    dev, dt = x0.device, x0.dtype
    dyn = discretize(Pendulum(mass=theta[0], damping=theta[1]), DT, method="rk4")
    cost = QuadraticCost(
        Q=torch.diag(theta[4:6]),
        R=0.1 * torch.eye(1, dtype=dt, device=dev),
        Qf=torch.diag(torch.tensor([10.0, 1.0], dtype=dt, device=dev)),
        x_ref=theta[2:4],
    )
    tol = 1e-11 if dt == F64 else 1e-4  # float32: ||dJ/dU|| stalls near 1e-5
    solver = ILQR(max_iter=100, tol=tol, progress=False)
    mpc = MPC(dyn, cost, T_MPC, solver=solver, backward=backward, warm_start=False)
    out = mpc(x0)
    x, u = out
    g = torch.Generator().manual_seed(0)
    wx = torch.randn(x.shape, generator=g, dtype=F64).to(dev, dt)
    wu = torch.randn(u.shape, generator=g, dtype=F64).to(dev, dt)
    return (wx * x).sum() + (wu * u).sum(), out


THETA = torch.tensor([1.2, 0.3, 1.0, 0.2, 1.0, 0.1], dtype=F64)  # m, b, x_ref, Q diag
X0 = torch.tensor([[0.3, 0.0], [-0.5, 0.4], [2.0, -1.0]], dtype=F64)


def mpc_grads(device, dtype=F64, backward="implicit"):
    theta = THETA.to(device, dtype).requires_grad_(True)
    x0 = X0.to(device, dtype).requires_grad_(True)
    loss, out = mpc_loss(theta, x0, backward)
    gt, gx = torch.autograd.grad(loss, (theta, x0))
    return loss, out, gt, gx


def test_mpc_layer_forward_and_implicit_backward_match_cpu(device):
    ref_loss, ref_out, ref_gt, ref_gx = mpc_grads("cpu")
    loss, out, gt, gx = mpc_grads(device)
    x, u = out
    assert on(device, x) and on(device, u) and on(device, out.action)
    assert on(device, gt) and on(device, gx)
    assert bool(out.converged.all())
    assert_close(x, ref_out[0], 1e-8, 1e-10, "mpc x")
    assert_close(u, ref_out[1], 1e-8, 1e-10, "mpc u")
    assert_close(loss, ref_loss, 1e-9)
    assert_close(gt, ref_gt, 1e-7, 1e-9, "d loss / d theta")
    assert_close(gx, ref_gx, 1e-7, 1e-9, "d loss / d x0")


def test_mpc_layer_float32_close_to_float64(device):
    ref_loss, _, ref_gt, ref_gx = mpc_grads("cpu")
    loss, out, gt, gx = mpc_grads(device, dtype=torch.float32)
    assert bool(out.converged.all())
    assert out[0].dtype == torch.float32 and on(device, out[0])
    assert bool(torch.isfinite(gt).all()) and bool(torch.isfinite(gx).all())
    assert_close(loss, ref_loss, 1e-3, 1e-3, "float32 loss")
    assert_close(gt, ref_gt, 5e-2, 5e-2, "float32 d loss / d theta")
    assert_close(gx, ref_gx, 5e-2, 5e-2, "float32 d loss / d x0")


def test_mpc_step_receding_horizon_on_device(device):
    """mpc.step warm starts from its previous solution; the closed loop matches CPU."""

    def closed_loop(dev):
        theta = THETA.to(dev)
        dyn = discretize(Pendulum(mass=theta[0], damping=theta[1]), DT, method="rk4")
        cost = QuadraticCost(
            Q=torch.diag(theta[4:6]),
            R=0.1 * torch.eye(1, dtype=F64, device=dev),
            Qf=torch.diag(torch.tensor([10.0, 1.0], dtype=F64, device=dev)),
            x_ref=torch.tensor([math.pi, 0.0], dtype=F64, device=dev),
        )
        mpc = MPC(dyn, cost, T_MPC, solver=ILQR(max_iter=100, tol=1e-10, progress=False))
        x, xs = X0.to(dev), []
        for _ in range(3):
            a = mpc.step(x)
            assert on(torch.device(dev), a) and a.shape == (3, 1)
            x = dyn(x, a)
            xs.append(x)
        return torch.stack(xs, 1)

    assert_close(closed_loop(device), closed_loop("cpu"), 1e-7, 1e-9, "closed loop")


# ----------------------------------------------------------------------------- logging


def test_tensorboard_logger_with_device_tensors(device, tmp_path):
    pytest.importorskip("tensorboard")
    prob, x0 = pendulum(device, batch=3, horizon=20)
    with ts.TensorBoardLogger(tmp_path / "tb", dt=0.05) as logger:
        r = ILQR(max_iter=10, progress=False).solve(prob, x0, logger=logger)
    assert_result_on(device, r)
    events = list((tmp_path / "tb").rglob("events.out.tfevents.*"))
    assert events and all(e.stat().st_size > 0 for e in events)
