"""Control bounds: the batched box QP (projected Newton), the control-limited Riccati
kernel and control-limited iLQR/DDP (Tassa, Mansard & Todorov 2014).

References are independent: the box QP against a dense enumeration of every active
set, the box-constrained LQ problem against ``scipy.optimize.lsq_linear`` (BVLS, an
exact active-set method) on the condensed quadratic ``J(U)`` built by autograd.
"""

from __future__ import annotations

import itertools
import math

import pytest
import scipy.optimize
import torch

import torchslq as ts
from torchslq.dynamics import Dynamics
from torchslq.dynamics.rollout import rollout, rollout_closed_loop
from torchslq.lq import box_qp, riccati_backward
from torchslq.problem import Problem
from torchslq.tasks import pendulum_swingup

F64 = torch.float64
INF = float("inf")


pytestmark = pytest.mark.usefixtures("single_thread")


# ----------------------------------------------------------------------------- helpers


def random_box_qp(seed: int, B: int, m: int, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(B, m, m, generator=g, dtype=F64)
    H = A @ A.mT + 0.05 * torch.eye(m, dtype=F64)
    q = 3.0 * torch.randn(B, m, generator=g, dtype=F64)
    lo = -torch.rand(B, m, generator=g, dtype=F64) * 1.5
    hi = torch.rand(B, m, generator=g, dtype=F64) * 1.5
    # some infinite bounds, some degenerate boxes
    lo[: B // 4] = -INF
    hi[B // 8 : B // 4 + B // 8] = INF
    lo[-2] = hi[-2] = 0.3  # a point: everything clamped
    return H.to(dtype), q.to(dtype), lo.to(dtype), hi.to(dtype)


def enumerate_box_qp(H, g, lo, hi):
    """Dense reference: for every assignment {lower, free, upper} of the coordinates,
    solve the free block exactly; keep the feasible point of least objective."""
    m = H.shape[-1]
    best, best_x = None, None
    for s in itertools.product((0, 1, 2), repeat=m):
        x = torch.zeros(m, dtype=F64)
        fixed = [i for i in range(m) if s[i] != 1]
        if any(not math.isfinite((lo if s[i] == 0 else hi)[i]) for i in fixed):
            continue
        for i in fixed:
            x[i] = (lo if s[i] == 0 else hi)[i]
        free = [i for i in range(m) if s[i] == 1]
        if free:
            fi, fx = torch.tensor(free), torch.tensor(fixed, dtype=torch.long)
            rhs = g[fi] + (H[fi][:, fx] @ x[fx] if fixed else 0.0)
            x[fi] = -torch.linalg.solve(H[fi][:, fi], rhs)
        if (x < lo - 1e-12).any() or (x > hi + 1e-12).any():
            continue
        v = float(0.5 * x @ H @ x + g @ x)
        if best is None or v < best:
            best, best_x = v, x
    return best_x


class Linear(Dynamics):
    """``x+ = A x + B u + c``."""

    def __init__(self, A, B, c):
        super().__init__()
        self.state_dim, self.control_dim = A.shape[-1], B.shape[-1]
        self.register_buffer("A", A)
        self.register_buffer("B", B)
        self.register_buffer("c", c)

    def forward(self, x, u):
        return x @ self.A.mT + u @ self.B.mT + self.c


def lq_problem(seed: int = 0, n: int = 3, m: int = 2, T: int = 15, B: int = 4):
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(n, dtype=F64) + 0.2 * torch.randn(n, n, generator=g, dtype=F64)
    Bm = torch.randn(n, m, generator=g, dtype=F64)
    c = 0.1 * torch.randn(n, generator=g, dtype=F64)
    L = torch.randn(m, m, generator=g, dtype=F64)
    R = 0.1 * (L @ L.T + torch.eye(m, dtype=F64))
    cost = ts.QuadraticCost(
        torch.eye(n, dtype=F64),
        R,
        Qf=10 * torch.eye(n, dtype=F64),
        x_ref=torch.randn(T + 1, n, generator=g, dtype=F64),
        u_ref=0.3 * torch.randn(T, m, generator=g, dtype=F64),
    )
    x0 = 3.0 * torch.randn(B, n, generator=g, dtype=F64)
    return Problem(Linear(A, Bm, c), cost, T), x0


def condensed_box_lq(problem, x0_b, lo, hi):
    """Independent solve of ``min_U J(U)`` s.t. ``lo <= U <= hi`` for one element: the
    quadratic ``J(U) = 1/2 U'HU + g'U + c`` by autograd (exact for linear dynamics and a
    quadratic cost), written as a bounded least-squares problem
    ``|L'U + L^{-1} g|^2`` (``H = LL'``) and solved by BVLS."""
    T, m = problem.horizon, problem.control_dim

    def J(U):
        return problem.total_cost(x0_b[None], U.reshape(1, T, m))[0]

    U0 = torch.zeros(T * m, dtype=F64)
    H = torch.func.hessian(J)(U0)
    gr = torch.func.grad(J)(U0)
    Lc = torch.linalg.cholesky(H)
    b = -torch.linalg.solve_triangular(Lc, gr[:, None], upper=False)[:, 0]
    res = scipy.optimize.lsq_linear(
        Lc.mT.numpy(),
        b.numpy(),
        bounds=(lo.reshape(-1).numpy(), hi.reshape(-1).numpy()),
        method="bvls",
        tol=1e-15,
    )
    assert res.success
    return torch.from_numpy(res.x).reshape(T, m)


# ----------------------------------------------------------------------------- box QP


@pytest.mark.parametrize("m", [1, 2, 3, 4])
def test_box_qp_matches_active_set_enumeration(m):
    H, g, lo, hi = random_box_qp(m, 64, m)
    res = box_qp(H, g, lo, hi)
    assert res.success.all()
    err = max(
        (enumerate_box_qp(H[b], g[b], lo[b], hi[b]) - res.x[b]).abs().max().item()
        for b in range(H.shape[0])
    )
    assert err < 1e-8, err
    assert ((res.x >= lo) & (res.x <= hi)).all()
    # the all-clamped element (a point box) and a warm start agree
    assert torch.equal(res.x[-2], lo[-2])
    assert res.clamped[-2].all() or (res.x[-2] == lo[-2]).all()
    warm = box_qp(H, g, lo, hi, x0=torch.randn(H.shape[0], m, dtype=F64))
    torch.testing.assert_close(warm.x, res.x, rtol=0, atol=1e-9)


def test_box_qp_clamped_set_and_free_factor():
    H, g, lo, hi = random_box_qp(7, 128, 3)
    res = box_qp(H, g, lo, hi)
    grad = g + (H @ res.x[..., None])[..., 0]
    # KKT: free gradient zero; clamped at a bound with the gradient pointing outwards
    free = ~res.clamped
    assert (grad[free].abs() < 1e-8).all()
    at_lo = res.clamped & (res.x == lo)
    at_hi = res.clamped & (res.x == hi)
    assert (at_lo | at_hi)[res.clamped].all()
    point = lo == hi  # a point box: clamped whatever the gradient's sign
    at_lo, at_hi = at_lo & ~point, at_hi & ~point
    assert (grad[at_lo] > 0).all() and (grad[at_hi] < 0).all()
    assert res.clamped.any() and free.any()
    # chol: factor of the free block, identity on the clamped rows/cols
    LLt = res.chol @ res.chol.mT
    both = free[:, :, None] & free[:, None, :]
    eye = torch.eye(3, dtype=F64).expand_as(H)
    torch.testing.assert_close(LLt, torch.where(both, H, eye), rtol=0, atol=1e-12)


def test_box_qp_infinite_bounds_is_newton_and_all_clamped():
    H, g, _, _ = random_box_qp(3, 16, 3)
    lo = torch.full_like(g, -INF)
    hi = torch.full_like(g, INF)
    res = box_qp(H, g, lo, hi)
    torch.testing.assert_close(res.x, -torch.linalg.solve(H, g), rtol=0, atol=1e-10)
    assert not res.clamped.any()
    # bounds so tight that the gradient pushes out everywhere: all clamped
    lo, hi = torch.full_like(g, -1e-3), torch.full_like(g, 1e-3)
    g_out = 1e3 * torch.sign(g)
    res = box_qp(H, g_out, lo, hi)
    ref = torch.where(g_out > 0, lo, hi)
    assert torch.equal(res.x, ref) and res.clamped.all() and res.success.all()
    torch.testing.assert_close(res.chol, torch.eye(3, dtype=F64).expand_as(H))


def test_box_qp_indefinite_fails_per_element_and_float32():
    H, g, lo, hi = random_box_qp(4, 8, 2)
    H = H.clone()
    H[3] = torch.tensor([[1.0, 0.0], [0.0, -1.0]], dtype=F64)
    lo[3], hi[3] = -INF, INF
    res = box_qp(H, g, lo, hi)
    assert not res.success[3]
    ok = torch.arange(8) != 3
    assert res.success[ok].all()
    ref = box_qp(H[ok], g[ok], lo[ok], hi[ok])
    torch.testing.assert_close(res.x[ok], ref.x)
    H32, g32, lo32, hi32 = random_box_qp(5, 32, 3, dtype=torch.float32)
    r32 = box_qp(H32, g32, lo32, hi32)
    r64 = box_qp(H32.double(), g32.double(), lo32.double(), hi32.double())
    assert r32.x.dtype == torch.float32 and r32.success.all()
    torch.testing.assert_close(r32.x.double(), r64.x, rtol=0, atol=1e-3)


# ----------------------------------------------------------------------------- kernel


def _random_lq(seed=0, B=3, T=8, n=3, m=2):
    g = torch.Generator().manual_seed(seed)
    A = torch.eye(n, dtype=F64) + 0.1 * torch.randn(B, T, n, n, generator=g, dtype=F64)
    Bm = torch.randn(B, T, n, m, generator=g, dtype=F64)
    Q = torch.eye(n, dtype=F64).expand(B, T + 1, n, n)
    R = 0.1 * torch.eye(m, dtype=F64).expand(B, T, m, m)
    q = torch.randn(B, T + 1, n, generator=g, dtype=F64)
    r = torch.randn(B, T, m, generator=g, dtype=F64)
    return A, Bm, Q, R, q, r


def test_kernel_infinite_bounds_match_unbounded_and_clamped_rows():
    A, Bm, Q, R, q, r = _random_lq()
    ref = riccati_backward(A, Bm, Q, R, q, r, reg=0.2)
    assert ref.clamped is None and ref.dV is None
    inf = torch.tensor(INF, dtype=F64)
    box = riccati_backward(A, Bm, Q, R, q, r, reg=0.2, u_bounds=(-inf, inf))
    torch.testing.assert_close(box.Kk, ref.Kk, rtol=0, atol=1e-10)
    torch.testing.assert_close(box.Vh, ref.Vh, rtol=1e-12, atol=1e-10)
    assert not box.clamped.any() and not box.failed.any()
    # tight bounds: clamped rows of K are zero, k within the box, the last step's k is
    # the box QP of the terminal-stage Q function
    lo, hi = torch.tensor(-0.1, dtype=F64), torch.tensor(0.2, dtype=F64)
    box = riccati_backward(A, Bm, Q, R, q, r, u_bounds=(lo, hi))
    assert box.clamped.any() and (~box.clamped).any()
    assert (box.K[box.clamped] == 0).all()
    assert ((box.k >= lo) & (box.k <= hi)).all()
    VT = Q[:, -1]
    Quu = R[:, -1] + Bm[:, -1].mT @ VT @ Bm[:, -1]
    qu = r[:, -1] + (Bm[:, -1].mT @ q[:, -1, :, None])[..., 0]
    for b in range(A.shape[0]):
        ref_k = enumerate_box_qp(Quu[b], qu[b], lo.expand(2), hi.expand(2))
        torch.testing.assert_close(box.k[b, -1], ref_k, rtol=0, atol=1e-10)
    # expected improvement terms: k'Qu + 1/2 k'Quu k <= 0 at every step, summed
    assert (box.dV[:, 0] + 0.5 * box.dV[:, 1] <= 0).all()


# ----------------------------------------------------------------------------- iLQR/DDP


def _ilqr(**kw):
    kw = {"progress": False, "max_iter": 100, "tol": 1e-10, **kw}
    return ts.ILQR(**kw)


@pytest.mark.parametrize("kind", ["per_element", "per_time", "scalar"])
def test_box_lq_matches_condensed_qp(kind):
    problem, x0 = lq_problem(seed=1)
    T, m, B = problem.horizon, problem.control_dim, x0.shape[0]
    g = torch.Generator().manual_seed(2)
    if kind == "scalar":
        u_min, u_max = -0.5, 0.5
    elif kind == "per_element":
        u_min = torch.tensor([-0.5, -INF], dtype=F64)
        u_max = torch.tensor([0.4, 0.8], dtype=F64)
    else:
        u_min = -0.2 - torch.rand(T, m, generator=g, dtype=F64)
        u_max = 0.2 + torch.rand(T, m, generator=g, dtype=F64)
    res = _ilqr(u_min=u_min, u_max=u_max).solve(problem, x0)
    assert res.converged.all(), res.status_names()
    lo = torch.as_tensor(u_min, dtype=F64).expand(T, m)
    hi = torch.as_tensor(u_max, dtype=F64).expand(T, m)
    errs = []
    for b in range(B):
        ref = condensed_box_lq(problem, x0[b], lo, hi)
        errs.append((res.u[b] - ref).abs().max().item())
        # active bounds: exactly where the reference sits on a bound
        exp = torch.zeros(T, m, dtype=torch.int8)
        exp[(ref - lo).abs() < 1e-9] = -1
        exp[(ref - hi).abs() < 1e-9] = 1
        assert torch.equal(res.active_bounds[b], exp)
    assert max(errs) < 1e-6, errs
    assert (res.active_bounds != 0).any()  # the bounds matter
    assert ((res.u >= lo) & (res.u <= hi)).all()


def test_infinite_bounds_equal_unbounded_exactly():
    problem, x0 = lq_problem(seed=3)
    free = _ilqr().solve(problem, x0)
    inf = _ilqr(u_min=-INF, u_max=INF).solve(problem, x0)
    assert torch.equal(inf.u, free.u) and torch.equal(inf.x, free.x)
    assert torch.equal(inf.cost, free.cost)
    assert free.active_bounds is None
    assert inf.active_bounds.shape == free.u.shape and (inf.active_bounds == 0).all()
    # one-sided None bound with the other infinite: the same
    one = _ilqr(u_min=None, u_max=torch.full((2,), INF, dtype=F64)).solve(problem, x0)
    assert torch.equal(one.u, free.u)


def test_per_element_bounds_batch_equals_singles():
    problem, x0 = lq_problem(seed=4, B=3)
    T, m = problem.horizon, problem.control_dim
    g = torch.Generator().manual_seed(5)
    u_min = -0.1 - 0.5 * torch.rand(3, T, m, generator=g, dtype=F64)
    u_max = 0.1 + 0.5 * torch.rand(3, T, m, generator=g, dtype=F64)
    u_max[1] = INF
    batch = _ilqr(u_min=u_min, u_max=u_max).solve(problem, x0)
    for b in range(3):
        one = _ilqr(u_min=u_min[b], u_max=u_max[b]).solve(problem, x0[b])  # unbatched
        assert one.u.shape == (T, m) and one.active_bounds.shape == (T, m)
        torch.testing.assert_close(one.u, batch.u[b], rtol=0, atol=1e-10)
        assert torch.equal(one.active_bounds, batch.active_bounds[b])
        assert one.status == batch.status[b]


def test_u_init_is_clamped_and_rollout_clamp():
    problem, x0 = lq_problem(seed=6, B=2)
    T, m = problem.horizon, problem.control_dim
    u_init = 5.0 * torch.ones(T, m, dtype=F64)
    solver = _ilqr(u_min=-0.3, u_max=0.3, max_iter=0)
    res = solver.solve(problem, x0, u_init)
    assert torch.equal(res.u, torch.full((2, T, m), 0.3, dtype=F64))
    assert (res.active_bounds == 1).all()
    # closed-loop rollout clamp
    x = rollout(problem.transition, x0, res.u)
    K = torch.randn(2, T, m, problem.state_dim, dtype=F64)
    k = 10.0 * torch.randn(2, T, m, dtype=F64)
    lo = torch.full((2, T, m), -0.3, dtype=F64)
    hi = torch.full((2, T, m), 0.3, dtype=F64)
    xc, uc = rollout_closed_loop(
        problem.transition, x0.expand(3, 2, -1), x, res.u, K, k, torch.ones(3, 2), lo, hi
    )
    assert uc.shape == (3, 2, T, m) and (uc.abs() <= 0.3).all()
    torch.testing.assert_close(xc[0], rollout(problem.transition, x0, uc[0]))


def test_bounds_validation():
    problem, x0 = lq_problem(seed=0, B=2)
    with pytest.raises(ValueError, match="u_min"):
        _ilqr(u_min=torch.zeros(3, 3, dtype=F64)).solve(problem, x0)
    with pytest.raises(ValueError, match="u_min must be <= u_max"):
        _ilqr(u_min=1.0, u_max=0.0).solve(problem, x0)
    with pytest.raises(ValueError, match="u_max"):
        _ilqr(u_max=torch.zeros(5, 15, 2, dtype=F64)).solve(problem, x0)
    with pytest.raises(TypeError):
        ts.SLQ(u_min=0.0)


@pytest.mark.parametrize("solver_cls", ["ilqr", "ddp"])
def test_bounded_pendulum_respects_bounds_and_beats_clamping(solver_cls):
    problem, x0 = pendulum_swingup(batch=3, horizon=40, seed=2)
    umax = 2.0
    make = {"ilqr": ts.ILQR, "ddp": ts.DDP}[solver_cls]
    free = make(progress=False, max_iter=200, tol=1e-8).solve(problem, x0)
    assert (free.u.abs() > umax).any()  # the bound is active for the free solution
    box = make(progress=False, max_iter=200, tol=1e-8, u_min=-umax, u_max=umax).solve(problem, x0)
    assert (box.u.abs() <= umax).all()
    assert torch.isfinite(box.cost).all()
    assert set(box.status_names()) <= {"converged", "max_iter"}
    u_clip = free.u.clamp(-umax, umax)
    J_clip = problem.total_cost(x0, u_clip)
    assert (box.cost < J_clip - 1e-6).all(), (box.cost, J_clip)
    torch.testing.assert_close(box.cost, problem.total_cost(x0, box.u))
    # active_bounds marks exactly the saturated controls
    sat = torch.where(box.u >= umax - 1e-12, 1, torch.where(box.u <= -umax + 1e-12, -1, 0))
    assert torch.equal(box.active_bounds, sat.to(torch.int8))
    assert (box.active_bounds != 0).any()
    # the projected gradient is small where the solve converged
    conv = box.converged
    assert (box.grad_norm[conv] < 1e-8).all()
