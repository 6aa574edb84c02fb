"""The compiled CPU Riccati kernel (torchslq._backend) against the torch path.

Both implement the same recursion; the torch path is itself checked against dense KKT
solves and a literal transcription of the paper in test_lq_kernel.py.
"""

from __future__ import annotations

import pytest
import torch
from lq_hooks import HessianHook as _HessianHook

import torchslq as ts
from torchslq._backend import dispatch as compiled
from torchslq.lq.riccati import riccati_homogeneous

pytestmark = pytest.mark.codegen  # generated compiled code on (tests/conftest.py)

F64 = torch.float64


@pytest.fixture
def torch_path():
    """Run a block with the compiled kernel disabled (the torch path)."""

    class _Switch:
        def __enter__(self):
            self.old = compiled.set_compiled(False)

        def __exit__(self, *exc):
            compiled.set_compiled(self.old)

    return _Switch()


def test_numba_kernel_is_available():
    # numba is a dependency; if it is missing every CPU pass silently takes the slow path
    assert compiled.compiled_available()


def _problem(batch, T, n, m, dtype=F64, seed=0, shared_cost=True):
    g = torch.Generator().manual_seed(seed)
    mn1 = m + n + 1
    F = 0.4 * torch.randn(*batch, T, n + 1, mn1, generator=g, dtype=dtype)
    F[..., :n, m : m + n] += torch.eye(n, dtype=dtype)
    F[..., n, :] = 0.0
    F[..., n, -1] = 1.0
    cb = (1,) if shared_cost else batch
    G = torch.randn(*cb, T, mn1, mn1, generator=g, dtype=dtype)
    H = G @ G.mT / mn1 + 0.1 * torch.eye(mn1, dtype=dtype)
    H[..., -1, -1] = 0.0
    W = torch.randn(n + 1, n + 1, generator=g, dtype=dtype)
    VhT = W @ W.mT / (n + 1)
    return F, H, VhT


def _both(torch_path, *args, **kwargs):
    fast = riccati_homogeneous(*args, **kwargs)
    with torch_path:
        ref = riccati_homogeneous(*args, **kwargs)
    return fast, ref


def _close(fast, ref, rtol=1e-10):
    assert torch.equal(fast.failed, ref.failed)
    ok = ~ref.failed
    for name in ("Kk", "Vh", "chol"):
        a, b = getattr(fast, name)[ok], getattr(ref, name)[ok]
        assert a.shape == b.shape, name
        scale = b.abs().max().clamp_min(1.0)
        assert float((a - b).abs().max() / scale) < rtol, name


@pytest.mark.parametrize("m", [1, 2, 3])
@pytest.mark.parametrize("reg", [None, 1e-3, "per-element"])
def test_compiled_equals_torch_path(torch_path, m, reg):
    F, H, VhT = _problem((7,), 12, 4, m, seed=m)
    if reg == "per-element":
        reg = torch.linspace(0.0, 0.5, 7, dtype=F64)
    fast, ref = _both(torch_path, F, H, VhT, reg=reg)
    assert not bool(ref.failed.any())
    _close(fast, ref)


def test_compiled_broadcasts_like_the_torch_path(torch_path):
    # per-element F with shared H and VhT, a 2-d batch, and per-element costs
    F, H, VhT = _problem((2, 3), 6, 3, 2)
    fast, ref = _both(torch_path, F, H[0], VhT)
    assert fast.Kk.shape == (2, 3, 6, 2, 4)
    _close(fast, ref)
    F1, Hb, _ = _problem((5,), 6, 3, 2, shared_cost=False)
    fast, ref = _both(torch_path, F1[:1], Hb, VhT.expand(5, 4, 4))
    assert fast.Vh.shape == (5, 7, 4, 4)
    _close(fast, ref)


def _hook(Hz: torch.Tensor, m: int) -> _HessianHook:
    """DDP's hook from ``Hz (T, n, B, m+n, m+n)`` (symmetric, ``[u; x]`` order)."""
    blocks = (Hz[..., m:, m:], Hz[..., :m, :m], Hz[..., :m, m:])
    return _HessianHook(*(b.movedim(0, 2).contiguous() for b in blocks))


class _TensorHook:
    """A hook exposing ``hessians`` as one ``Hz`` tensor (the other accepted form)."""

    def __init__(self, Hz):
        self.hessians = Hz

    def __call__(self, t, Vh_next):
        n = self.hessians.shape[1]
        s = Vh_next[..., :n, n]
        return (s.mT.unsqueeze(-1).unsqueeze(-1) * self.hessians[t]).sum(0)


@pytest.mark.parametrize("form", ["blocks", "tensor"])
def test_compiled_with_ddp_hessian_hook(torch_path, form):
    B, T, n, m = 5, 8, 3, 2
    F, H, VhT = _problem((B,), T, n, m)
    g = torch.Generator().manual_seed(7)
    Hz = torch.randn(T, n, B, m + n, m + n, generator=g, dtype=F64)
    Hz = 0.05 * (Hz + Hz.mT)
    hook = _hook(Hz, m) if form == "blocks" else _TensorHook(Hz)
    fast, ref = _both(torch_path, F, H, VhT, reg=1e-2, stage_hook=hook)
    assert not bool(ref.failed.any())
    _close(fast, ref)
    # the hook changes the pass (a zero-weight hook would pass the comparison above too)
    plain = riccati_homogeneous(F, H, VhT, reg=1e-2)
    assert float((plain.Kk - fast.Kk).abs().max()) > 1e-3


def test_compiled_reports_the_same_failures(torch_path):
    F, H, VhT = _problem((4,), 10, 3, 2)
    H = H.expand(4, *H.shape[1:]).clone()
    H[2, 5, 0, 0] = -50.0  # Quu of element 2 indefinite at step 5
    H[3, 0, 1, 1] = float("nan")  # element 3 non-finite at step 0
    fast, ref = _both(torch_path, F, H, VhT)
    assert fast.failed.tolist() == [False, False, True, True]
    assert torch.equal(fast.failed, ref.failed)
    _close(fast, ref)
    # the failing element's later steps (computed before the failure) agree too
    torch.testing.assert_close(fast.Kk[2, 6:], ref.Kk[2, 6:], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("bounded", [False, True])
def test_compiled_float32(torch_path, bounded):
    F, H, VhT = _problem((6,), 15, 4, 2)
    kw = {"reg": 1e-3}
    if bounded:
        kw["u_bounds"] = (torch.tensor(-0.05, dtype=F64), torch.tensor(0.05, dtype=F64))
    kw32 = dict(kw)
    if bounded:
        kw32["u_bounds"] = tuple(b.float() for b in kw["u_bounds"])
    fast32 = riccati_homogeneous(F.float(), H.float(), VhT.float(), **kw32)
    with torch_path:
        ref64 = riccati_homogeneous(F, H, VhT, **kw)
    assert fast32.Kk.dtype == torch.float32
    if bounded:
        assert bool(ref64.clamped.any())
        assert torch.equal(fast32.clamped, ref64.clamped)
    torch.testing.assert_close(fast32.Kk.double(), ref64.Kk, rtol=1e-3, atol=1e-4)


def test_torch_path_where_autograd_or_transforms_need_it():
    F, H, VhT = _problem((3,), 5, 2, 1)
    assert compiled.can_use_compiled(F, H, VhT)
    Hg = H.clone().requires_grad_()
    assert not compiled.can_use_compiled(F, Hg, VhT)
    with torch.no_grad():
        assert compiled.can_use_compiled(F, Hg, VhT)
    assert not compiled.can_use_compiled(F.float(), H, VhT)  # mixed dtypes
    # gradients through a pass still flow (the torch path records them)
    fac = riccati_homogeneous(F, Hg, VhT)
    fac.Vh[:, 0].sum().backward()
    assert Hg.grad is not None and bool(Hg.grad.abs().sum() > 0)
    # inside torch.func transforms the tensors are wrappers: torch path, same numbers
    out = torch.func.vmap(lambda f: riccati_homogeneous(f, H[0], VhT).Kk)(F)
    torch.testing.assert_close(out, riccati_homogeneous(F, H, VhT).Kk, rtol=1e-12, atol=1e-12)


def test_lqr_solve_matches_with_and_without_compiled(torch_path):
    """The public LQ solve (and its implicit gradient) through either path."""
    g = torch.Generator().manual_seed(3)
    B, T, n, m = 4, 9, 3, 2
    A = torch.eye(n, dtype=F64) + 0.2 * torch.randn(B, T, n, n, generator=g, dtype=F64)
    Bm = torch.randn(B, T, n, m, generator=g, dtype=F64)
    Q = torch.eye(n, dtype=F64).expand(B, T + 1, n, n)
    R = 0.5 * torch.eye(m, dtype=F64).expand(B, T, m, m)
    q = torch.randn(B, T + 1, n, generator=g, dtype=F64).requires_grad_()
    x0 = torch.randn(B, n, generator=g, dtype=F64)
    sol = ts.lqr_solve(A, Bm, Q, R, x0, q=q)
    (gq,) = torch.autograd.grad(sol.u.square().sum(), q)
    with torch_path:
        sol_t = ts.lqr_solve(A, Bm, Q, R, x0, q=q)
        (gq_t,) = torch.autograd.grad(sol_t.u.square().sum(), q)
    torch.testing.assert_close(sol.u, sol_t.u, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(gq, gq_t, rtol=1e-10, atol=1e-12)


def test_ddp_solve_same_with_and_without_compiled(torch_path):
    from torchslq.tasks import pendulum_swingup

    problem, x0 = pendulum_swingup(batch=5, horizon=30, seed=2)
    fast = ts.DDP(max_iter=50, progress=False).solve(problem, x0)
    with torch_path:
        ref = ts.DDP(max_iter=50, progress=False).solve(problem, x0)
    assert bool(fast.converged.all()) and bool(ref.converged.all())
    torch.testing.assert_close(fast.u, ref.u, rtol=1e-6, atol=1e-8)
    torch.testing.assert_close(fast.cost, ref.cost, rtol=1e-10, atol=0.0)


@pytest.mark.parametrize("shared", [False, True])
def test_compiled_rollout_and_adjoint_equal_torch_path(torch_path, shared):
    """rollout_homogeneous and lq_adjoint_solve (the LQ layer's forward rollout and its
    implicit backward) through the compiled kernels and the torch path; ``shared``:
    problem data and factors of batch 1 with per-element x0 and incoming gradients."""
    from torchslq.lq import lq_adjoint_solve, rollout_homogeneous

    B, T, n, m = 6, 11, 4, 2
    F, H, VhT = _problem((1,) if shared else (B,), T, n, m, seed=5)
    fac = riccati_homogeneous(F, H, VhT)
    g = torch.Generator().manual_seed(9)
    x0 = torch.randn(B, n, generator=g, dtype=F64)
    gx = torch.randn(B, T + 1, n, generator=g, dtype=F64)
    gu = torch.randn(B, T, m, generator=g, dtype=F64)
    x, u = rollout_homogeneous(F, fac.Kk, x0)
    adj = lq_adjoint_solve(F, fac.Kk, fac.Vh, fac.chol, gx, gu)
    with torch_path:
        x_t, u_t = rollout_homogeneous(F, fac.Kk, x0)
        adj_t = lq_adjoint_solve(F, fac.Kk, fac.Vh, fac.chol, gx, gu)
    assert x.shape == (B, T + 1, n) and u.shape == (B, T, m)
    torch.testing.assert_close(x, x_t, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(u, u_t, rtol=1e-12, atol=1e-12)
    for a, b in zip(adj, adj_t, strict=True):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def _one_then_three_threads(run, monkeypatch, before_many=None):
    """``(run() on one thread, run() with every pass split over three threads)``
    (``before_many()`` called in between); asserts that the split happened."""
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = run()
        torch.set_num_threads(3)
        monkeypatch.setattr(compiled, "MIN_STEPS_PER_THREAD", 1)
        if before_many is not None:
            before_many()
        many = run()
    finally:
        torch.set_num_threads(old)
    assert compiled._pool_size == 3
    return one, many


def test_threaded_launch_equals_one_thread(torch_path, monkeypatch):
    """Large passes are split over torch.get_num_threads() threads (contiguous chunks of
    the batch); every element's numbers are the same as in one pass."""
    from torchslq.lq import lq_adjoint_solve, rollout_homogeneous

    F, H, VhT = _problem((9,), 7, 3, 2, seed=11)
    g = torch.Generator().manual_seed(2)
    x0 = torch.randn(9, 3, generator=g, dtype=F64)
    gx, gu = (
        torch.randn(9, 8, 3, generator=g, dtype=F64),
        torch.randn(9, 7, 2, generator=g, dtype=F64),
    )
    reg = torch.linspace(0.0, 0.1, 9, dtype=F64)

    def run():
        fac = riccati_homogeneous(F, H, VhT, reg=reg)
        return (
            fac,
            rollout_homogeneous(F, fac.Kk, x0),
            lq_adjoint_solve(F, fac.Kk, fac.Vh, fac.chol, gx, gu),
        )

    calls = []
    orig = compiled._launch

    def spy(kernel, nb, T, *args):
        calls.append(nb)
        return orig(kernel, nb, T, *args)

    one, many = _one_then_three_threads(
        run, monkeypatch, lambda: monkeypatch.setattr(compiled, "_launch", spy)
    )
    assert calls == [9, 9, 9]  # all three kernels ran (split over three threads)
    for name in ("Kk", "Vh", "chol", "failed"):
        assert torch.equal(getattr(one[0], name), getattr(many[0], name)), name
    for a, b in zip((*one[1], *one[2]), (*many[1], *many[2]), strict=True):
        assert torch.equal(a, b)


def test_threaded_gain_form_pass_equals_one_thread(monkeypatch):
    """The solvers' gain-form pass (riccati_backward on a small problem's LQ data, with
    per-element reg and restarts) split over three threads gives every element the same
    bits as one pass."""
    from torchslq.lq import RegularizationSchedule

    g = torch.Generator().manual_seed(5)
    B, T, n, m = 9, 12, 4, 2
    A = torch.eye(n, dtype=F64) + 0.1 * torch.randn(B, T, n, n, generator=g, dtype=F64)
    Bm = torch.randn(B, T, n, m, generator=g, dtype=F64)
    Q = torch.eye(n, dtype=F64).expand(B, T + 1, n, n).contiguous()
    R = torch.eye(m, dtype=F64).expand(B, T, m, m).contiguous()
    R[::3, :, 1, 1] = -0.5  # Quu[1, 1] = -0.5 where the second control does not act:
    Bm[::3, :, :, 1] = 0.0  # these elements need restarts to reg > 0.5
    q, r = (
        torch.randn(B, T + 1, n, generator=g, dtype=F64),
        torch.randn(B, T, m, generator=g, dtype=F64),
    )
    reg = torch.linspace(0.0, 0.3, B, dtype=F64)
    schedule = RegularizationSchedule(factor=2.0, reg_min=1e-6, reg_max=1e10, max_restarts=12)

    def run():
        return ts.riccati_backward(A, Bm, Q, R, q, r, reg=reg, restarts=schedule.restarts())

    one, many = _one_then_three_threads(run, monkeypatch)
    assert not bool(one.failed.any()) and bool((one.reg[::3] > reg[::3]).all())  # restarted
    for name in ("Kk", "Vh", "chol", "failed", "reg", "reg_delta"):
        assert torch.equal(getattr(one, name), getattr(many, name)), name


@pytest.mark.parametrize("m", [1, 2, 3])
@pytest.mark.parametrize("hook", [False, True])
def test_compiled_box_pass_equals_torch_path(torch_path, m, hook):
    """The control-limited pass (box QP per step, Tassa et al. 2014) on both paths, with
    bounds that are active at many steps, per-element reg and (DDP) a Hessian hook."""
    B, T, n = 6, 10, 3
    F, H, VhT = _problem((B,), T, n, m, seed=20 + m)
    g = torch.Generator().manual_seed(30 + m)
    H = H.expand(B, *H.shape[1:]).clone()
    H[..., :m, -1] = 3.0 * torch.randn(B, T, m, generator=g, dtype=F64)  # large r: clamps
    H[..., -1, :m] = H[..., :m, -1]
    lower = -0.3 * torch.rand(B, T, m, generator=g, dtype=F64)
    upper = 0.3 * torch.rand(B, T, m, generator=g, dtype=F64)
    upper[0] = float("inf")  # an element without upper bounds
    reg = torch.linspace(0.0, 0.2, B, dtype=F64)
    kw = {"reg": reg, "u_bounds": (lower, upper)}
    if hook:
        Hz = torch.randn(T, n, B, m + n, m + n, generator=g, dtype=F64)
        kw["stage_hook"] = _hook(0.005 * (Hz + Hz.mT), m)
    fast, ref = _both(torch_path, F, H, VhT, **kw)
    assert not bool(ref.failed.any())
    assert bool(ref.clamped.any()) and not bool(ref.clamped.all())
    assert torch.equal(fast.clamped, ref.clamped)
    _close(fast, ref)
    torch.testing.assert_close(fast.dV, ref.dV, rtol=1e-10, atol=1e-12)


def test_torch_compile_traces_the_torch_path():
    """Under torch.compile the tensors are fake: the traced graph must be the torch
    path's, whole (fullgraph=True fails on a graph break, e.g. a numba call). (Today
    both the is_compiling and the functorch-stack checks route tracing there.)"""
    from torchslq.lq import rollout_homogeneous

    F, H, VhT = _problem((3,), 5, 2, 1)
    Kk = riccati_homogeneous(F, H, VhT).Kk
    x0 = torch.randn(3, 2, generator=torch.Generator().manual_seed(1), dtype=F64)
    f = torch.compile(lambda F, Kk, x0: rollout_homogeneous(F, Kk, x0)[0], fullgraph=True)
    torch.testing.assert_close(f(F, Kk, x0), rollout_homogeneous(F, Kk, x0)[0])


def test_threaded_launch_after_fork(monkeypatch):
    """A forked child (e.g. a DataLoader worker) inherits the parent's thread pool object
    but none of its threads: its threaded passes must still finish (a new pool)."""
    import multiprocessing as mp

    monkeypatch.setattr(compiled, "MIN_STEPS_PER_THREAD", 1)
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        F, H, VhT = _problem((4,), 6, 2, 1)
        ref = riccati_homogeneous(F, H, VhT).Kk  # creates the parent's pool
        assert compiled._pool is not None
        ctx = mp.get_context("fork")
        q = ctx.Queue()
        child = ctx.Process(target=_child_pass, args=(F, H, VhT, q))
        child.start()
        child.join(timeout=60)
        hung = child.is_alive()
        if hung:
            child.kill()
        assert not hung, "threaded pass in a forked child did not finish"
        torch.testing.assert_close(torch.from_numpy(q.get(timeout=5)), ref, rtol=0, atol=0)
    finally:
        torch.set_num_threads(old)


def _child_pass(F, H, VhT, q):
    q.put(riccati_homogeneous(F, H, VhT).Kk.numpy())  # plain pickle, no shared memory


def test_kernels_that_fail_to_load_fall_back_to_torch(torch_path, monkeypatch):
    """If numba cannot load the kernels (no writable cache directory, a numba/numpy
    mismatch, ...), passes warn once and take the torch path instead of failing."""

    def broken():
        raise RuntimeError("cannot cache function: no locator available")

    monkeypatch.setattr(compiled, "_kernels_module", None)
    monkeypatch.setattr(compiled, "_kernels_error", None)
    monkeypatch.setattr(compiled, "_import_kernels", broken)
    F, H, VhT = _problem((3,), 6, 2, 1)
    with pytest.warns(RuntimeWarning, match="could not be loaded"):
        fac = riccati_homogeneous(F, H, VhT)
    assert not compiled.compiled_available()
    with torch_path:
        ref = riccati_homogeneous(F, H, VhT)
    assert torch.equal(fac.Kk, ref.Kk)  # bit-identical: the same (torch) path


def _pieces_cases():
    g = torch.Generator().manual_seed(11)
    B, T, n, m = 5, 7, 4, 2

    def rnd(*s):
        return torch.randn(*s, generator=g, dtype=F64)

    def spd(*lead, k):
        G = rnd(*lead, k, k)
        return G @ G.mT / k + 0.5 * torch.eye(k, dtype=F64)

    return {
        "shared Q R, per-element q r": dict(
            A=0.5 * rnd(B, T, n, n), B=rnd(B, T, n, m), Q=spd(T + 1, k=n), R=spd(T, k=m),
            q=rnd(B, T + 1, n), r=rnd(B, T, m),
        ),
        "per element, with S and c, unsymmetric Q": dict(
            A=0.5 * rnd(B, T, n, n), B=rnd(B, T, n, m), Q=spd(B, T + 1, k=n) + 0.3 * rnd(n, n),
            R=spd(B, T, k=m), q=rnd(B, T + 1, n), r=rnd(B, T, m), S=0.1 * rnd(B, T, m, n),
            c=rnd(B, T, n),
        ),
        "constants without time dims": dict(
            A=0.5 * rnd(B, T, n, n), B=rnd(n, m), Q=spd(k=n), R=spd(k=m)
        ),
        "time dims of 1, 2-d batch": dict(
            A=0.5 * rnd(2, 3, T, n, n), B=rnd(3, 1, n, m), Q=spd(1, k=n), R=spd(1, k=m),
            q=rnd(2, 1, 1, n),
        ),
    }  # fmt: skip


def _small_hessians(batch: torch.Size, T: int, n: int, m: int, joint: bool):
    """DDP's output Hessians for a flat ``batch``, small and symmetric: the blocks as
    separate tensors, or as views of one ``[u; x]`` tensor (the compiled models' form)."""
    g = torch.Generator().manual_seed(11)
    Hz = 0.05 * torch.randn(n, batch.numel(), T, m + n, m + n, generator=g, dtype=F64)
    Hz = Hz + Hz.mT
    if joint:
        return _HessianHook(Hz[..., m:, m:], Hz[..., :m, :m], Hz[..., :m, m:])
    blocks = (Hz[..., m:, m:], Hz[..., :m, :m], Hz[..., :m, m:])
    return _HessianHook(*(b.contiguous() for b in blocks))


@pytest.mark.parametrize("case", list(_pieces_cases()))
@pytest.mark.parametrize("extra", ["none", "reg", "bounds", "hessians", "joint hessians"])
def test_riccati_backward_assembles_the_stages_in_the_kernel(torch_path, monkeypatch, case, extra):
    """riccati_backward on the CPU hands the LQ data to a kernel, and the homogeneous
    tensors are never built: the same factors as the torch path. With bounds the
    homogeneous kernel assembles each step's F_t, H_t itself (bitwise the kernel fed
    with the F, H built by homogeneous_dynamics/_cost); without, this small problem's
    pass runs in gain form (riccati_gain_reg_kernel, or without Hessians the pass
    generated for its size, gain_codegen), equal to within rounding, DDP's Hessian terms
    included (the same bits from separate blocks or one joint tensor)."""
    from torchslq._backend import _numba_gain, gain_codegen
    from torchslq.lq import riccati

    kw = _pieces_cases()[case]
    batch = torch.broadcast_shapes(kw["A"].shape[:-3], kw["B"].shape[:-3])
    T, n, m = kw["A"].shape[-3], kw["A"].shape[-1], kw["B"].shape[-1]
    if "hessians" in extra and len(batch) != 1:
        pytest.skip("the hook's Hessians have one flat batch dim")
    kw |= {
        "none": {},
        "reg": {"reg": torch.linspace(0.0, 0.4, batch.numel(), dtype=F64).reshape(batch)},
        "bounds": {"u_bounds": (-0.3 * torch.ones(1, dtype=F64), 0.3 * torch.ones(1, dtype=F64))},
        "hessians": {"stage_hook": _small_hessians(batch, T, n, m, joint=False)},
        "joint hessians": {"stage_hook": _small_hessians(batch, T, n, m, joint=True)},
    }[extra]
    with torch_path:
        ref = ts.riccati_backward(**kw)

    def forbidden(*a, **k):
        raise AssertionError("homogeneous tensors built on the compiled path")

    gain_calls = []
    gain_kernel = _numba_gain.riccati_gain_reg_kernel
    with monkeypatch.context() as mp:
        mp.setattr(riccati, "homogeneous_cost", forbidden)
        mp.setattr(riccati, "homogeneous_dynamics", forbidden)
        mp.setattr(
            _numba_gain,
            "riccati_gain_reg_kernel",
            lambda *a: gain_calls.append(1) or gain_kernel(*a),
        )
        generated = gain_codegen.gain_kernels(n, m)
        if generated is not None:
            first = generated.riccati_gain_reg_first
            mp.setattr(
                generated, "riccati_gain_reg_first", lambda *a: gain_calls.append(1) or first(*a)
            )
        fast = ts.riccati_backward(**kw)
    assert fast.Kk.shape == ref.Kk.shape == (*batch, T, 2, 5)
    _close(fast, ref)
    assert bool(gain_calls) == (extra != "bounds")
    if extra == "bounds":
        assert torch.equal(fast.clamped, ref.clamped)
        # (without linear terms the feedforward is zero and no bound binds)
        assert bool(fast.clamped.any()) == ("q" in kw or "r" in kw)
    # the kernel fed with the homogeneous tensors gives the same bits
    F = riccati.homogeneous_dynamics(kw["A"], kw["B"], riccati.with_time(kw.get("c"), 1, T))
    H, VhT = riccati.homogeneous_cost(
        riccati.with_time(kw["Q"], 2, T + 1),
        riccati.with_time(kw["R"], 2, T),
        riccati.with_time(kw.get("q"), 1, T + 1),
        riccati.with_time(kw.get("r"), 1, T),
        riccati.with_time(kw.get("S"), 2, T),
    )
    homog = riccati_homogeneous(
        F, H, VhT, kw.get("reg"), kw.get("stage_hook"), u_bounds=kw.get("u_bounds")
    )
    if extra == "bounds":
        assert torch.equal(fast.Kk, homog.Kk) and torch.equal(fast.Vh, homog.Vh)
    else:
        _close(fast, homog, rtol=1e-12)
    if extra == "joint hessians":  # the same bits as from the separate blocks
        blocks = _HessianHook(*(b.contiguous() for b in kw["stage_hook"].blocks))
        sep = ts.riccati_backward(**{**kw, "stage_hook": blocks})
        assert torch.equal(fast.Kk, sep.Kk) and torch.equal(fast.Vh, sep.Vh)


def test_riccati_backward_shape_errors_come_from_the_torch_path():
    A = torch.randn(3, 5, 2, 2, dtype=F64)
    B = torch.randn(3, 5, 2, 1, dtype=F64)
    with pytest.raises(RuntimeError):
        ts.riccati_backward(A, B, torch.eye(2, dtype=F64).expand(4, 2, 2), torch.eye(1, dtype=F64))


def _feedback_data(Na, B, T, n, m, dtype=F64, seed=3):
    g = torch.Generator().manual_seed(seed)

    def r(*s):
        return torch.randn(*s, generator=g, dtype=F64).to(dtype)

    return {
        "x0": r(Na, B, n) if Na else r(B, n),
        "x_nom": r(B, T + 1, n),
        "u_nom": r(B, T, m),
        "K": 0.3 * r(B, T, m, n),
        "k": r(B, T, m),
        "alpha": torch.rand(Na, B, generator=g, dtype=F64).to(dtype) if Na else r(B),
    }


def _rollout_case(case: str, B: int, T: int, n: int, m: int, dtype) -> tuple[dict, dict]:
    """The closed-loop rollout tests' data and bounds for ``case``."""
    d = _feedback_data(0 if case == "one-alpha" else 4, B, T, n, m, dtype)
    kw = {}
    if case == "bounds":
        kw = {
            "u_min": -0.5 * torch.ones(B, T, m, dtype=dtype),
            "u_max": 0.4 * torch.ones(B, T, m, dtype=dtype),
        }
    if case == "time-shared-bounds":  # one (T, m) bound for every element, no upper
        lo = torch.tensor([-0.3, -0.6][:m], dtype=dtype).expand(1, T, m)
        kw = {"u_min": lo, "u_max": None}
    if case == "gopronto-x_nom":
        d["x_nom"] = d["x_nom"][:, :T]
    return d, kw


@pytest.mark.parametrize(
    "case", ["alphas", "one-alpha", "bounds", "time-shared-bounds", "gopronto-x_nom", "float32"]
)
def test_compiled_closed_loop_rollout_equals_torch_path(torch_path, case):
    """rollout_closed_loop with the feedback on the CPU kernel == the torch path (the same
    order of operations, so the same bits), for candidate steps, bounds, a nominal
    trajectory of T states (GoPRONTO's projection) and float32."""
    from torchslq.dynamics.rollout import rollout_closed_loop
    from torchslq.systems import Unicycle

    dtype = torch.float32 if case == "float32" else F64
    B, T, n, m = 5, 7, 3, 2
    d, kw = _rollout_case(case, B, T, n, m, dtype)
    f = Unicycle(0.1).to(dtype)
    f.compiled_step = lambda: None  # the feedback kernel with the torch model (the
    # model's own compiled step is tested below)
    calls = []
    kernel = compiled._kernels().feedback_kernel
    real = compiled.closed_loop_feedback_compiled

    def counting(*a):
        calls.append(1)
        return real(*a)

    import sys

    mod = sys.modules["torchslq.dynamics.rollout"]
    old = mod.closed_loop_feedback_compiled
    mod.closed_loop_feedback_compiled = counting
    try:
        xf, uf = rollout_closed_loop(f, **d, **kw)
    finally:
        mod.closed_loop_feedback_compiled = old
    assert calls and kernel is not None
    with torch_path:
        xr, ur = rollout_closed_loop(f, **d, **kw)
    assert xf.shape == xr.shape and uf.shape == ur.shape
    tol = 0.0 if dtype == F64 else 1e-6
    assert float((xf - xr).abs().max()) <= tol and float((uf - ur).abs().max()) <= tol
    if kw.get("u_min") is not None:
        assert bool((uf >= kw["u_min"] - 1e-12).all()) and bool((uf < -0.29).any())


def test_closed_loop_rollout_keeps_the_graph_of_a_model_that_needs_it(torch_path):
    """A model whose parameters require grad: the rollout falls back to torch ops and
    its output is differentiable, with the torch path's gradient."""
    from torchslq.dynamics.rollout import rollout_closed_loop
    from torchslq.systems import CartPole

    d = _feedback_data(2, 3, 6, 4, 1)
    grads = []
    for ctx in (None, torch_path):
        mc = torch.tensor(1.0, dtype=F64, requires_grad=True)
        f = ts.discretize(CartPole(mc=mc), 0.05)
        if ctx is None:
            x, u = rollout_closed_loop(f, **d)
        else:
            with ctx:
                x, u = rollout_closed_loop(f, **d)
        assert x.requires_grad and u.requires_grad
        grads.append(torch.autograd.grad((x.sum() + u.sum()), mc)[0])
    torch.testing.assert_close(grads[0], grads[1], rtol=0, atol=0)


class _RowCounting(torch.nn.Module):
    """A torch model (the unicycle's step, rows independent) recording how many rows it
    is called on; ``scale`` optional per-element data ``(B, 1, 1)`` multiplying the
    step's increment."""

    def __init__(self, dtype, scale=None):
        super().__init__()
        from torchslq.systems import Unicycle

        self.inner = Unicycle(0.1).to(dtype)
        self.inner.compiled_step = lambda: None
        self.scale = None if scale is None else torch.nn.Parameter(scale, requires_grad=False)
        self.rows = []

    def forward(self, x, u):
        self.rows.append(x.shape[:-1].numel())
        dx = self.inner(x, u) - x
        return x + (dx if self.scale is None else self.scale * dx)


@pytest.mark.parametrize(
    "case", ["alphas", "bounds", "time-shared-bounds", "per-element", "float32"]
)
def test_closed_loop_rollout_of_the_needed_rows_only(torch_path, case):
    """A line search's NaN trial steps (trials no element needs): a torch model whose rows
    are independent is rolled out on the other rows only, and every row equals the torch
    path's, where all rows are rolled out (the kept ones bit for bit; the skipped ones
    NaN after ``x0``, NaN controls). A model with per-element data is called on all rows
    (its data would not line up with a subset). float32: within the tolerance of
    :func:`test_compiled_closed_loop_rollout_equals_torch_path`."""
    from torchslq.dynamics.rollout import rollout_closed_loop

    dtype = torch.float32 if case == "float32" else F64
    Na, B, T, n, m = 4, 5, 7, 3, 2
    d, kw = _rollout_case("alphas" if case == "per-element" else case, B, T, n, m, dtype)
    needed = torch.rand(Na, B, generator=torch.Generator().manual_seed(2)) < 0.4
    d["alpha"] = torch.where(needed, d["alpha"], float("nan"))
    scale = 0.5 + torch.rand(B, 1, 1, dtype=dtype) if case == "per-element" else None
    f = _RowCounting(dtype, scale)
    x, u = rollout_closed_loop(f, **d, **kw)
    with torch_path:
        xr, ur = rollout_closed_loop(f, **d, **kw)
    full = Na * B
    assert f.rows[:T] == [full if case == "per-element" else int(needed.sum())] * T
    assert f.rows[T:] == [full] * T
    tol = 0.0 if dtype == F64 else 1e-6  # (float32: the feedback kernel's rounding)
    torch.testing.assert_close(x, xr, rtol=0, atol=tol, equal_nan=True)
    torch.testing.assert_close(u, ur, rtol=0, atol=tol, equal_nan=True)
    assert bool(x[~needed][:, 1:].isnan().all()) and bool(u[~needed].isnan().all())
    assert bool(x[needed].isfinite().all()) and bool(u[needed].isfinite().all())
    torch.testing.assert_close(x[..., 0, :], d["x0"], rtol=0, atol=0)


@pytest.mark.parametrize("case", ["plain", "feedback", "shared-dynamics", "float32"])
def test_compiled_costate_gradient_equals_torch_path(torch_path, case):
    """costate_gradient on the CPU kernel == the torch recursion (same order of
    operations: the same bits), with GoPRONTO's feedback term, dynamics shared by the
    batch and float32; and the gradient is dJ/dU (checked against autograd)."""
    from torchslq.dynamics.rollout import costate_gradient

    dtype = torch.float32 if case == "float32" else F64
    g = torch.Generator().manual_seed(11)
    Bsz, T, n, m = 4, 6, 3, 2

    def r(*s):
        return torch.randn(*s, generator=g, dtype=F64).to(dtype)

    A = r(1 if case == "shared-dynamics" else Bsz, T, n, n)
    B = r(1 if case == "shared-dynamics" else Bsz, T, n, m)
    lx, lu = r(Bsz, T + 1, n), r(Bsz, T, m)
    K = r(Bsz, T, m, n) if case == "feedback" else None
    fast = costate_gradient(A, B, lx, lu, K)
    with torch_path:
        ref = costate_gradient(A, B, lx, lu, K)
    for a, b in zip(fast, ref, strict=True):
        assert a.shape == b.shape and a.dtype == dtype
        assert torch.equal(a, b)
    if case == "plain":  # J = sum lx'x + lu'u along x_{t+1} = A x_t + B u_t
        u = torch.zeros(Bsz, T, m, dtype=dtype, requires_grad=True)
        x, xs = torch.zeros(Bsz, n, dtype=dtype), []
        for t in range(T):
            xs.append(x)
            x = (A[:, t] @ x.unsqueeze(-1))[..., 0] + (B[:, t] @ u[:, t].unsqueeze(-1))[..., 0]
        xs.append(x)
        J = (torch.stack(xs, 1) * lx).sum() + (u * lu).sum()
        torch.testing.assert_close(fast[0], torch.autograd.grad(J, u)[0])


@pytest.mark.parametrize("model", ["unicycle", "cartpole-rk4"])
@pytest.mark.parametrize("case", ["alphas", "one-alpha", "bounds", "gopronto-x_nom", "float32"])
def test_whole_closed_loop_rollout_with_the_models_compiled_step(torch_path, case, model):
    """A model with a compiled step (Unicycle; the cart-pole's compiled right-hand side
    under discretize's RK4) rolls out in one kernel call: the same states and controls
    as the torch path up to the last bits of cos/sin, and the controls exactly the
    feedback law applied to those states."""
    import sys

    from torchslq.dynamics.rollout import rollout_closed_loop
    from torchslq.systems import CartPole, Unicycle

    dtype = torch.float32 if case == "float32" else F64
    B, T, m = 5, 7, 2 if model == "unicycle" else 1
    n = 3 if model == "unicycle" else 4
    d, kw = _rollout_case(case, B, T, n, m, dtype)
    if model == "unicycle":
        f = Unicycle(0.1).to(dtype)
    else:
        f = ts.discretize(CartPole(mc=torch.tensor(1.3, dtype=dtype)), 0.05)
    assert f.compiled_step() is not None
    mod = sys.modules["torchslq._backend.dispatch"]
    calls = []
    real = mod.closed_loop_rollout_compiled
    rmod = sys.modules["torchslq.dynamics.rollout"]
    rmod.closed_loop_rollout_compiled = lambda *a: calls.append(1) or real(*a)
    try:
        xf, uf = rollout_closed_loop(f, **d, **kw)
    finally:
        rmod.closed_loop_rollout_compiled = real
    assert calls
    with torch_path:
        xr, ur = rollout_closed_loop(f, **d, **kw)
    assert xf.shape == xr.shape and uf.shape == ur.shape and xf.dtype == dtype
    tol = 1e-12 if dtype == F64 else 5e-5
    assert float((xf - xr).abs().max()) <= tol and float((uf - ur).abs().max()) <= tol
    # the model's step and the feedback law hold exactly on the kernel's own trajectory
    xn = d["x_nom"][:, :T]
    ff = d["u_nom"] + d["alpha"][..., None, None] * d["k"]
    law = ff + ((xf[..., :T, :] - xn).unsqueeze(-2) @ d["K"].mT).squeeze(-2)
    if kw:
        law = law.clamp(kw["u_min"], kw["u_max"])
    torch.testing.assert_close(uf, law, rtol=0, atol=10 * torch.finfo(dtype).eps)
    torch.testing.assert_close(xf[..., 1:, :], f(xf[..., :T, :], uf), rtol=0, atol=tol)


def test_models_without_a_usable_compiled_step_take_the_torch_model():
    """Per-element parameters, Euler steps and models without a compiled right-hand side
    (their own or generated) give no compiled step (their rollouts call the torch model)."""
    from torchslq.systems import CartPole, MassChain, Pendulum

    per_elem = torch.rand(3, 1, dtype=F64) + 0.5
    assert ts.discretize(CartPole(mc=per_elem), 0.05).compiled_step() is None
    assert ts.discretize(MassChain(mass=per_elem), 0.1).compiled_step() is None
    assert ts.discretize(CartPole(), 0.05, "euler").compiled_step() is None

    class OwnCodeOnly(Pendulum):  # no compiled right-hand side of its own, none generated
        generate_compiled_code = False

    assert ts.discretize(OwnCodeOnly(), 0.1).compiled_step() is None
    assert ts.discretize(CartPole(), 0.05).compiled_step() is not None
    assert ts.discretize(MassChain(), 0.1).compiled_step() is not None


@pytest.mark.parametrize("model", ["unicycle", "cartpole-rk4"])
def test_whole_rollout_kernel_skips_rows_with_a_nan_step(torch_path, model):
    """A NaN step (a line-search trial no element needs, armijo_search's skip_settled)
    is not rolled out by the kernel: NaN states after x0 as on the torch path, the other rows the
    same as without NaN steps."""
    from torchslq.dynamics.rollout import rollout_closed_loop
    from torchslq.systems import CartPole, Unicycle

    B, T, m = 5, 7, 2 if model == "unicycle" else 1
    n = 3 if model == "unicycle" else 4
    d, _ = _rollout_case("alphas", B, T, n, m, F64)
    f = Unicycle(0.1).double() if model == "unicycle" else ts.discretize(CartPole(), 0.05)
    assert f.compiled_step() is not None
    full_x, full_u = rollout_closed_loop(f, **d)
    skip = torch.zeros_like(d["alpha"], dtype=torch.bool)
    skip[1:, 2] = True
    skip[3, :] = True
    d["alpha"] = torch.where(skip, torch.full_like(d["alpha"], float("nan")), d["alpha"])
    xs, us = rollout_closed_loop(f, **d)
    with torch_path:
        xr, _ = rollout_closed_loop(f, **d)
    for x in (xs, xr):  # the initial state, then NaN
        assert bool(torch.isnan(x[skip][:, 1:]).all()) and torch.equal(x[..., 0, :], xs[..., 0, :])
    assert torch.equal(xs[~skip], full_x[~skip]) and torch.equal(us[~skip], full_u[~skip])


@pytest.mark.parametrize("model", ["unicycle", "cartpole-rk4"])
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_open_loop_rollout_with_the_models_compiled_step(torch_path, model, dtype):
    """rollout() runs a model with a compiled step in one kernel call where no graph is
    needed: the torch path's states up to the last bits of cos/sin, each state the
    model's step of the previous one, leading dims broadcast (x0 shared, u per
    element), ``u`` left untouched; with ``u`` requiring grad the torch model runs and
    the graph is kept."""
    import sys

    from torchslq.dynamics.rollout import rollout
    from torchslq.systems import CartPole, Unicycle

    if model == "unicycle":
        f, n, m = Unicycle(0.1).to(dtype), 3, 2
    else:
        f, n, m = ts.discretize(CartPole(mc=torch.tensor(1.3, dtype=dtype)), 0.05), 4, 1
    g = torch.Generator().manual_seed(3)
    x0 = torch.randn(n, generator=g, dtype=dtype)
    u = torch.randn(2, 5, 9, m, generator=g, dtype=dtype)
    u_before = u.clone()
    rmod = sys.modules["torchslq.dynamics.rollout"]
    real, calls = rmod.closed_loop_rollout_compiled, []
    rmod.closed_loop_rollout_compiled = lambda *a: calls.append(1) or real(*a)
    try:
        xf = rollout(f, x0, u)
    finally:
        rmod.closed_loop_rollout_compiled = real
    assert calls and torch.equal(u, u_before)
    with torch_path:
        xr = rollout(f, x0, u)
    assert xf.shape == xr.shape == (2, 5, 10, n) and xf.dtype == dtype
    tol = 1e-12 if dtype == F64 else 5e-5
    assert float((xf - xr).abs().max()) <= tol
    torch.testing.assert_close(xf[..., 1:, :], f(xf[..., :-1, :], u), rtol=0, atol=tol)
    ug = u.clone().requires_grad_(True)
    xg = rollout(f, x0, ug)
    assert xg.requires_grad
    (gu,) = torch.autograd.grad(xg.sum(), ug)
    assert torch.isfinite(gu).all() and float(gu.abs().max()) > 0
