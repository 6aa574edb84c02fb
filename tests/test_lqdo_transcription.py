"""LQDO problem and transcription: quadrature and defects exact on polynomials of the
right degree, the reference QP against automatic differentiation of the nonlinear
program, OLQ detection, the reuse of OLQ pieces and of the data that do not depend on the
reference, and the row-wise derivatives against per-row automatic differentiation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchslq.lqdo import LQDOProblem, detect_olq, lgl, transcribe
from torchslq.lqdo.problem import row_derivatives

pytestmark = pytest.mark.usefixtures("float64_default")


def poly_problem(coef, t0=0.5, tf=2.0, lagrange_deg=None):
    """xi' = d/dt sum_j coef_j t^j (a function of t only), l = t^lagrange_deg."""
    c = torch.as_tensor(coef)
    d = torch.arange(len(coef))

    def dyn(t, u, xi, p):
        dp = (c[1:] * d[1:] * t[..., None] ** (d[1:] - 1)).sum(-1)
        return (dp + 0 * xi[..., 0])[..., None]

    lag = None
    if lagrange_deg is not None:

        def lag(t, u, xi, p):
            return t**lagrange_deg + 0 * u[..., 0]

    return LQDOProblem(nu=1, nx=1, t0=t0, tf=tf, dynamics=dyn, lagrange=lag)


def exact_state(coef, t):
    c = torch.as_tensor(coef)
    return (c * t[:, None] ** torch.arange(len(coef))).sum(-1)


def z_of(tr, xi):
    B = 1
    return tr.pack(torch.zeros(B, tr.nt, 1), xi.reshape(B, -1, 1))


@pytest.mark.parametrize("N", [3, 6, 11])
def test_lgl_quadrature_and_differentiation_exact(N):
    t0, tf = 0.5, 2.0
    for deg in range(2 * N - 2):  # LGL weights exact up to degree 2N - 3
        tr = transcribe(poly_problem([1.0], t0, tf, lagrange_deg=deg), "PS", nodes=N)
        v = tr.objective(z_of(tr, torch.ones(N)))
        exact = (tf ** (deg + 1) - t0 ** (deg + 1)) / (deg + 1)
        assert float(v) == pytest.approx(exact, rel=1e-12, abs=1e-12)
    rng = np.random.default_rng(N)
    coef = rng.normal(size=N).tolist()  # degree N - 1: D is exact
    tr = transcribe(poly_problem(coef, t0, tf), "PS", nodes=N)
    defects = tr.equalities(z_of(tr, exact_state(coef, tr.t)))
    assert defects.abs().max() < 1e-10
    # one degree more is not differentiated exactly: the check above is not vacuous
    coef2 = coef + [1.0]
    tr2 = transcribe(poly_problem(coef2, t0, tf), "PS", nodes=N)
    assert tr2.equalities(z_of(tr2, exact_state(coef2, tr2.t))).abs().max() > 1e-6
    # the nodes and weights against numpy's Gauss-Lobatto construction
    tau, w, _ = lgl(N)
    roots = np.polynomial.legendre.Legendre.basis(N - 1).deriv().roots()
    np.testing.assert_allclose(tau[1:-1], np.sort(roots), atol=1e-12)
    assert w.sum() == pytest.approx(2.0, abs=1e-13)


def test_trapezoid_exact_on_any_mesh():
    mesh = torch.tensor([0.5, 0.6, 0.95, 1.3, 1.31, 2.0])
    # composite trapezoid integrates degree 1 exactly, not degree 2
    for deg, exact_ok in ((0, True), (1, True), (2, False)):
        P = poly_problem([1.0], lagrange_deg=deg)
        tr = transcribe(P, "TR", mesh=mesh)
        v = float(tr.objective(z_of(tr, torch.ones(6))))
        exact = (2.0 ** (deg + 1) - 0.5 ** (deg + 1)) / (deg + 1)
        assert (abs(v - exact) < 1e-13) == exact_ok
    # trapezoidal defects vanish for quadratic states (linear derivative), not for cubic
    for coef, ok in (([0.3, -1.0, 2.0], True), ([0.3, -1.0, 2.0, 1.0], False)):
        tr = transcribe(poly_problem(coef), "TR", mesh=mesh)
        err = tr.equalities(z_of(tr, exact_state(coef, tr.t))).abs().max()
        assert (err < 1e-13) == ok
    with pytest.raises(ValueError, match="mesh"):
        transcribe(poly_problem([1.0]), "TR", mesh=torch.tensor([0.5, 0.4, 2.0]))


def crane():
    c4, c5 = 17.2656, 27.0756

    def dyn(t, u, xi, p):
        return torch.stack(
            [
                xi[..., 3],
                xi[..., 4],
                xi[..., 5],
                u[..., 0] + c4 * xi[..., 2],
                u[..., 1],
                -(u[..., 0] + c5 * xi[..., 2] + 2 * xi[..., 4] * xi[..., 5]) / xi[..., 1],
            ],
            -1,
        )

    return LQDOProblem(
        nu=2,
        nx=6,
        np=1,
        tf=9.0,
        dynamics=dyn,
        lagrange=lambda t, u, xi, p: (
            0.5 * (xi[..., 2] ** 2 + xi[..., 5] ** 2 + 0.01 * u.pow(2).sum(-1))
            + torch.sin(p[..., 0]) * u[..., 0]
        ),
        mayer=lambda p, x0, xf: xf[..., 0] ** 2 * p[..., 0],
        path_ineq=lambda t, u, xi, p: torch.stack(
            [xi[..., 3] * u[..., 1] - 1, t * u[..., 0] - p[..., 0]], -1
        ),
        boundary_eq=lambda p, x0, xf: (x0[..., 1] * xf[..., 1] - p[..., 0] ** 2)[..., None],
        initial=[0, 22, 0, 0, -1, float("nan")],
        final=[10, 14, float("nan"), 2.5, 0, 0],
    )


@pytest.mark.parametrize("method,N", [("TR", 7), ("PS", 6)])
def test_reference_qp_is_the_taylor_model_of_the_program(method, N):
    """A, b, G, h, H, f of the QP about z_ref against torch.autograd.functional
    Jacobians/Hessians of the transcribed nonlinear program."""
    P = crane()
    tr = transcribe(P, method, nodes=N)
    gen = torch.Generator().manual_seed(3)
    z = torch.randn(2, tr.n, generator=gen)
    z[:, tr.idx_x[:, 1].reshape(-1)] += 20.0  # keep xi_2 away from 0
    qp = tr.qp(z)
    d = qp.dense(bounds=False)
    for i in range(2):
        zi = z[i : i + 1]
        Je = torch.autograd.functional.jacobian(lambda x: tr.equalities(x[None])[0], zi[0])
        Jg = torch.autograd.functional.jacobian(lambda x: tr.inequalities(x[None])[0], zi[0])
        torch.testing.assert_close(d.A[i], Je, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(d.G[i], Jg, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(
            d.A[i] @ zi[0] - d.b[i], tr.equalities(zi)[0], atol=1e-10, rtol=0
        )
        torch.testing.assert_close(
            d.G[i] @ zi[0] - d.h[i], tr.inequalities(zi)[0], atol=1e-10, rtol=0
        )
        Hv = torch.autograd.functional.hessian(lambda x: tr.objective(x[None])[0], zi[0])
        gv = torch.autograd.functional.jacobian(lambda x: tr.objective(x[None])[0], zi[0])
        torch.testing.assert_close(d.H[i], Hv, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(d.H[i] @ zi[0] + d.f[i], gv, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(qp.objective(z), tr.objective(z), rtol=1e-12, atol=1e-10)


def test_olq_detection():
    P = crane()
    assert P.olq_rows("dynamics").tolist() == [True] * 5 + [False]
    assert P.olq_rows("lagrange").tolist() == [False]  # sin(p) u1 is not quadratic
    assert P.olq_rows("mayer").tolist() == [False]
    assert P.olq_rows("path_ineq").tolist() == [False, True]  # t u1 - p1: time-varying linear
    assert P.olq_rows("boundary_eq").tolist() == [False]
    Q = LQDOProblem(
        nu=1,
        nx=2,
        dynamics=lambda t, u, xi, p: torch.stack(
            [xi[..., 1], -4 * xi[..., 0] + 2 * u[..., 0] + torch.sin(t)], -1
        ),
        lagrange=lambda t, u, xi, p: xi[..., 1] ** 2 + 1e-3 * u[..., 0] ** 2 + t * xi[..., 0],
        mayer=lambda p, x0, xf: xf[..., 0] ** 2 + torch.sin(xf[..., 1]),
        path_ineq=lambda t, u, xi, p: (xi[..., 0] - 1)[..., None],
    )
    assert detect_olq(Q, "dynamics").tolist() == [True, True]
    assert detect_olq(Q, "lagrange").tolist() == [True]
    assert detect_olq(Q, "mayer").tolist() == [False]
    assert detect_olq(Q, "path_ineq").tolist() == [True]
    Q2 = LQDOProblem(nu=1, nx=2, dynamics=Q.dynamics, olq={"dynamics": [True, False]})
    assert Q2.olq_rows("dynamics").tolist() == [True, False]
    with pytest.raises(ValueError, match="olq"):
        LQDOProblem(nu=1, nx=1, dynamics=Q.dynamics, olq={"dynamic": True})


def test_olq_pieces_reused_and_equal_to_a_fresh_build():
    P = crane()
    tr = transcribe(P, "TR", nodes=9)
    gen = torch.Generator().manual_seed(1)
    z1 = torch.randn(3, tr.n, generator=gen) + 20.0
    z2 = torch.randn(3, tr.n, generator=gen) + 20.0
    tr.qp(z1)
    assert ("dynamics", 3, torch.float64, z1.device) in tr._cache  # OLQ rows kept
    q_reused = tr.qp(z2)
    q_fresh = transcribe(P, "TR", nodes=9).qp(z2)
    for a, b in ((q_reused.dense(), q_fresh.dense()),):
        for name in ("H", "f", "A", "b", "G", "h", "c"):
            torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=1e-12)


def test_fixing_variables_keeps_the_objective_and_constraints():
    P = crane()
    tr = transcribe(P, "TR", nodes=5)
    gen = torch.Generator().manual_seed(2)
    z = torch.randn(2, tr.n, generator=gen) + 20
    qp = tr.qp(z)
    mask = torch.zeros(tr.n, dtype=torch.bool)
    mask[tr.idx_p] = True
    mask[tr.idx_u[2]] = True
    other = torch.zeros(tr.n, dtype=torch.bool)
    other[tr.idx_x[1]] = True
    # the index work is kept per pattern and mask: two masks on one pattern, and the
    # first again at another point
    z2 = z + 0.5
    for m, zz in ((mask, z), (other, z), (mask, z2)):
        red = qp.fix(m, zz[:, m])
        w = zz[:, ~m]
        torch.testing.assert_close(red.objective(w), qp.objective(zz), rtol=1e-12, atol=1e-9)
        for a, b in zip(red.residuals(w), qp.residuals(zz), strict=True):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-9)


def test_validation_names_the_argument():
    with pytest.raises(ValueError, match="tf"):
        LQDOProblem(nu=1, nx=1, tf=0.0, dynamics=lambda t, u, x, p: x)
    with pytest.raises(ValueError, match="initial"):
        LQDOProblem(nu=1, nx=2, dynamics=lambda t, u, x, p: x, initial=[1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="method"):
        transcribe(poly_problem([1.0]), "RK4")
    tr = transcribe(poly_problem([1.0]), "TR", nodes=4)
    with pytest.raises(ValueError, match="z must be"):
        tr.objective(torch.zeros(1, 3))


class _SquareReadingItem(torch.autograd.Function):
    """``x * x`` whose backward reads a Python bool from its incoming gradient: it has no
    batching rule, so a vectorised backward pass over several outputs fails on it."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return x * x

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        if not bool(torch.isfinite(g).all().item()):
            raise FloatingPointError("non-finite gradient")
        return 2 * x * g


@pytest.mark.parametrize("vmappable", [True, False])
def test_row_derivatives_against_per_row_autograd(vmappable):
    """Value, Jacobian (all rows and a subset, a constant row included) and Hessian of a
    row-wise function against torch.autograd.functional on each row alone; with an
    operation that cannot be vectorised, the per-output fallback gives the same."""
    sq = (lambda x: x * x) if vmappable else _SquareReadingItem.apply

    def fn(x):
        return torch.stack(
            [
                sq(x[..., 0]) * x[..., 1],
                torch.sin(x[..., 2]) + x[..., 0],
                torch.ones_like(x[..., 0]),
            ],
            -1,
        )

    def scalar(x):
        return fn(x)[..., :2].prod(-1, keepdim=True)

    gen = torch.Generator().manual_seed(5)
    z = torch.randn(7, 3, generator=gen)
    val, jac, hess = row_derivatives(fn, z)
    assert hess is None
    torch.testing.assert_close(val, fn(z), rtol=0, atol=0)
    _, sub, _ = row_derivatives(fn, z, rows=torch.tensor([2, 0]))
    _, grad, H = row_derivatives(scalar, z, hessian=True)
    for r in range(z.shape[0]):
        Jr = torch.autograd.functional.jacobian(lambda x: fn(x[None])[0], z[r])
        torch.testing.assert_close(jac[r], Jr, rtol=1e-13, atol=1e-13)
        torch.testing.assert_close(sub[r], Jr[[2, 0]], rtol=1e-13, atol=1e-13)
        Hr = torch.autograd.functional.hessian(lambda x: scalar(x[None])[0, 0], z[r])
        torch.testing.assert_close(H[r], Hr, rtol=1e-12, atol=1e-12)
        gr = torch.autograd.functional.jacobian(lambda x: scalar(x[None])[0, 0], z[r])
        torch.testing.assert_close(grad[r, 0], gr, rtol=1e-13, atol=1e-13)
    assert (jac[:, 2] == 0).all()


def test_lgl_qp_has_no_explicit_zeros_and_sees_changed_problem_data():
    """The LGL constraint matrix stores the nonzeros of the Jacobian only (its M2 = I
    has nt^2 pairs and nt nonzeros), counted against the dense autograd Jacobian; the
    bounds and fixed states kept between calls follow a bound changed in place and a
    replaced initial state."""
    P = crane()
    tr = transcribe(P, "PS", nodes=8)
    gen = torch.Generator().manual_seed(4)
    z = torch.randn(1, tr.n, generator=gen)
    z[:, tr.idx_x[:, 1].reshape(-1)] += 20.0
    qp = tr.qp(z)
    Je = torch.autograd.functional.jacobian(lambda x: tr.equalities(x[None])[0], z[0])
    # entries (duplicates summed: D's corner diagonal meets the Jacobian's xi entries)
    positions = torch.unique(qp.A_idx[0] * tr.n + qp.A_idx[1]).numel()
    assert positions == int((Je != 0).sum())
    assert (qp.A_val != 0).all()
    assert torch.isinf(qp.ub).all()
    P.u_ub[1] = 0.5  # in place
    P.initial = torch.tensor([1.0, 21.0, 0.0, 0.0, -1.0, float("nan")])  # replaced
    qp2 = tr.qp(z)
    assert (qp2.ub[0, tr.idx_u[:, 1]] == 0.5).all() and torch.isinf(qp2.ub[0, tr.idx_u[:, 0]]).all()
    eq = tr.equalities(z)[0]
    torch.testing.assert_close(qp2.dense().A[0] @ z[0] - qp2.b[0], eq, rtol=0, atol=1e-10)
    row = tr.nd * P.nx + tr.k["boundary_eq"]  # the first fixed initial state
    assert float(eq[row]) == pytest.approx(float(z[0, tr.idx_x[0, 0]]) - 1.0, abs=1e-12)
    assert float(eq[row + 1]) == pytest.approx(float(z[0, tr.idx_x[0, 1]]) - 21.0, abs=1e-12)
