"""Bad inputs and faults at the public entry points: a clear error naming the problem, or
a per-element status, never a crash or a silent wrong answer."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import textwrap
import warnings

import pytest
import torch

import torchslq as ts
from torchslq.systems import CartPole, Pendulum
from torchslq.tasks import pendulum_swingup

F64 = torch.float64


def _cost(n=2, m=1):
    return ts.QuadraticCost(torch.eye(n, dtype=F64), 0.1 * torch.eye(m, dtype=F64))


def test_problem_refuses_a_continuous_model_that_was_not_discretized():
    """xdot used as x_next would 'converge' to a wrong answer: refused with the fix."""
    with pytest.raises(TypeError, match="discretize"):
        ts.Problem(Pendulum(), _cost(), 10)
    ts.Problem(ts.discretize(Pendulum(), 0.05), _cost(), 10)  # the fix works


class _Float32Step(ts.Dynamics):
    """A float64 pendulum step whose output is cast to float32 (a model that keeps its
    own dtype)."""

    state_dim, control_dim = 2, 1

    def __init__(self):
        super().__init__()
        self.inner = ts.discretize(Pendulum(), 0.05)

    def forward(self, x, u):
        return self.inner(x, u).float()


class _WrongShapeForTrials(ts.Dynamics):
    """Right for (B, 1, n) states, wrong for the line search's (Na, B, 1, n) trials."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.inner = ts.discretize(CartPole(), 0.05)

    def forward(self, x, u):
        out = self.inner(x, u)
        return out[0] if out.ndim == 4 else out


@pytest.mark.parametrize("solver", ["slq", "ilqr", "ddp", "gopronto"])
def test_a_float32_model_in_a_float64_solve_is_an_error(solver):
    make = {
        "slq": ts.SLQ,
        "ilqr": ts.ILQR,
        "ddp": ts.DDP,
        "gopronto": ts.GoPRONTO,
    }[solver]
    problem = ts.Problem(_Float32Step(), _cost(), 10)
    with pytest.raises(ValueError, match="float32"):
        make(max_iter=3, progress=False).solve(problem, torch.zeros(3, 2, dtype=F64))


def test_a_model_with_a_wrong_output_shape_is_an_error_not_a_crash():
    """The wrong shape only for the line search's trial batches used to kill the process
    (SIGSEGV / double free) on the compiled CPU path. Run in a subprocess (one for the
    three solvers: each line printed names the solver done) so that a crash fails the
    test instead of the suite."""
    code = textwrap.dedent(
        f"""
        import sys, torch, torchslq as ts
        sys.path.insert(0, {str(__file__.rsplit("/", 1)[0])!r})
        from test_reliability import _WrongShapeForTrials
        F64 = torch.float64
        cost = ts.QuadraticCost(torch.eye(4, dtype=F64), 0.1 * torch.eye(1, dtype=F64))
        problem = ts.Problem(_WrongShapeForTrials(), cost, 20)
        makers = {{
            "SLQ-closed": lambda: ts.SLQ(rollout="closed_loop", line_search="armijo"),
            "ILQR": lambda: ts.ILQR(),
            "DDP": lambda: ts.DDP(),
        }}
        for name, make in makers.items():
            try:
                make().with_options(progress=False, max_iter=5).solve(
                    problem, 0.1 * torch.ones(3, 4, dtype=F64)
                )
                print(name, "NO_ERROR", flush=True)
            except ValueError as exc:
                print(name, "VALUE_ERROR" if "shape" in str(exc) else repr(exc), flush=True)
        """
    )
    # the torch path's check (generated code would compute each row as traced instead)
    env = {**os.environ, "TORCHSLQ_CODEGEN": "0"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
    )
    assert out.returncode == 0, out.stdout + out.stderr[-2000:]
    assert out.stdout.split("\n")[:3] == [
        "SLQ-closed VALUE_ERROR",
        "ILQR VALUE_ERROR",
        "DDP VALUE_ERROR",
    ], out.stdout


@pytest.mark.parametrize("make", [ts.SLQ, ts.ILQR, ts.GoPRONTO])
def test_an_empty_batch_solves_and_summarises_and_logs(make):
    problem, x0 = pendulum_swingup(batch=2, horizon=10, seed=0)
    with tempfile.TemporaryDirectory() as d, ts.TensorBoardLogger(d) as logger:
        res = make(progress=False).solve(problem, x0[:0], logger=logger)
    assert res.x.shape == (0, 11, 2) and res.status.shape == (0,)
    assert res.summary() == "problems: 0"


def test_mpc_step_warns_when_a_solve_failed():
    """A failed element's action is not an optimal control: MPC.step says so."""

    class NanAbove(ts.Dynamics):
        state_dim, control_dim = 2, 1

        def __init__(self):
            super().__init__()
            self.inner = ts.discretize(Pendulum(), 0.05)

        def forward(self, x, u):
            out = self.inner(x, u)
            return torch.where(x[..., :1] > 2.0, float("nan"), out)

    mpc = ts.MPC(NanAbove(), _cost(), 10, solver=ts.ILQR(max_iter=20, progress=False))
    x = torch.tensor([[0.1, 0.0], [2.5, 0.0]], dtype=F64)
    with pytest.warns(RuntimeWarning, match="1 of 2"):
        action = mpc.step(x)
    assert action.shape == (2, 1)
    assert mpc.last_result.status_names()[1] == "non_finite"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mpc.step(x[:1])  # no failure, no warning


@pytest.mark.parametrize("make", [lambda: ts.ILQR(u_max=2.0), lambda: ts.GoPRONTO(max_iter=5)])
def test_a_result_saves_and_loads_with_every_field(make, tmp_path):
    problem, x0 = pendulum_swingup(batch=3, horizon=10, seed=0)
    res = make().with_options(progress=False).solve(problem, x0)
    res.save(tmp_path / "result.pt")
    back = ts.SolverResult.load(tmp_path / "result.pt")
    assert type(back) is type(res)
    for name, value in res.to_dict().items():
        got = getattr(back, name)
        if torch.is_tensor(value):
            assert torch.equal(got, value), name
        elif isinstance(value, dict):
            assert set(got) == set(value), name
            for k, v in value.items():
                assert torch.equal(got[k], v) if torch.is_tensor(v) else got[k] == v, (name, k)
        else:
            assert got == value, name
    assert back.status_names() == res.status_names()
    with pytest.raises(ValueError, match="SolverResult.save"):
        torch.save({"x": torch.zeros(1)}, tmp_path / "other.pt")
        ts.SolverResult.load(tmp_path / "other.pt")


@pytest.mark.parametrize("compiled", [True, False])
def test_lqr_backward_with_a_failed_element_leaves_the_others_exact(compiled):
    """An element whose Quu is not positive definite (a strongly negative Q) gets a zero
    gradient; the shared A's gradient equals the one of the good elements solved alone
    (it was NaN on the torch path and a ZeroDivisionError on the compiled one)."""
    from torchslq.lq import set_compiled

    g = torch.Generator().manual_seed(3)
    Bsz, T, n, m = 4, 6, 3, 2
    A0 = torch.eye(n, dtype=F64) + 0.1 * torch.randn(n, n, generator=g, dtype=F64)
    Bm = 0.5 * torch.randn(T, n, m, generator=g, dtype=F64)
    Q = torch.eye(n, dtype=F64).expand(Bsz, T + 1, n, n).clone()
    Q[1] = -50.0 * torch.eye(n, dtype=F64)  # element 1: Quu indefinite
    R = torch.eye(m, dtype=F64)
    x0 = torch.randn(Bsz, n, generator=g, dtype=F64)
    good = torch.tensor([0, 2, 3])
    set_compiled(compiled)
    try:
        A = A0.clone().requires_grad_(True)
        sol = ts.lqr_solve(A.expand(Bsz, T, n, n), Bm, Q, R, x0)
        assert sol.status.tolist()[1] == int(ts.Status.NOT_POSITIVE_DEFINITE)
        (sol.x[good].square().sum() + sol.u[good].square().sum()).backward()
        A_ref = A0.clone().requires_grad_(True)
        ref = ts.lqr_solve(A_ref.expand(3, T, n, n), Bm, Q[good], R, x0[good])
        (ref.x.square().sum() + ref.u.square().sum()).backward()
    finally:
        set_compiled(True)
    assert torch.isfinite(A.grad).all()
    torch.testing.assert_close(A.grad, A_ref.grad, rtol=1e-10, atol=1e-12)


class _NanJacobian(ts.Dynamics):
    """A linear model whose analytic Jacobian is NaN where x_0 > 2 (the rollout is finite)."""

    state_dim, control_dim = 2, 1

    def forward(self, x, u):
        return torch.cat([x[..., :1] + 0.1 * x[..., 1:], x[..., 1:] + 0.1 * u], -1)

    def jacobians(self, x, u):
        A = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=x.dtype).expand(*x.shape[:-1], 2, 2)
        B = torch.tensor([[0.0], [0.1]], dtype=x.dtype).expand(*x.shape[:-1], 2, 1)
        bad = (x[..., 0] > 2.0)[..., None, None]
        return torch.where(bad, float("nan"), A), B.clone()


@pytest.mark.parametrize(
    "make",
    [ts.SLQ, ts.ILQR, ts.DDP, lambda **kw: ts.DDP(second_order="costate", **kw), ts.GradientMethod],
)
def test_a_nan_jacobian_is_non_finite_under_every_solver(make):
    """One meaning per status: a NaN Jacobian is non_finite (ILQR/DDP called it
    not_positive_definite); the other element converges."""
    problem = ts.Problem(_NanJacobian(), _cost(), 10)
    x0 = torch.tensor([[0.5, 0.0], [2.5, 0.0]], dtype=F64)
    assert make(progress=False).solve(problem, x0).status_names() == ["converged", "non_finite"]


# ------------------------------------------------------------------ one granularity rule
# A fault confined to some batch elements gives those elements a status and the batch
# goes on; a fault in data shared by the whole batch (or a malformed argument) is an
# error naming the argument.

_SOLVERS = [
    lambda: ts.SLQ(max_iter=40, progress=False),
    lambda: ts.ILQR(max_iter=40, progress=False),
    lambda: ts.DDP(max_iter=40, progress=False, compact=True),
    lambda: ts.GradientMethod(max_iter=5, progress=False),
    lambda: ts.GoPRONTO(max_iter=5, progress=False),
    lambda: ts.ILQR(max_iter=40, progress=False, constraints=ts.Constraints(x_max=20.0)),
]


@pytest.mark.parametrize("make", _SOLVERS)
def test_a_nan_in_one_row_of_x0_is_that_elements_status(make):
    """It used to reject the whole batch (while a NaN in u_init was a status)."""
    problem, x0 = pendulum_swingup(batch=4, horizon=15, seed=1)
    bad = x0.clone()
    bad[1, 0] = float("nan")
    res = make().solve(problem, bad)
    assert res.status_names()[1] == "non_finite"
    ref = make().solve(problem, x0[[0, 2, 3]])
    assert [res.status_names()[i] for i in (0, 2, 3)] == ref.status_names()
    torch.testing.assert_close(res.u[[0, 2, 3]], ref.u, rtol=0, atol=0)


def test_a_per_element_weight_that_is_not_positive_definite_is_that_elements_status():
    """A per-element R (B, T, m, m) not positive definite in one element, a NaN in
    another element's Q: those two get not_positive_definite / non_finite and the others
    equal the solve of the shared weights. A shared R that is not PD is still an error."""
    problem, x0 = pendulum_swingup(batch=4, horizon=15, seed=1)
    c, B, T = problem.cost, 4, 15
    n, m = problem.state_dim, problem.control_dim
    R = c.R.expand(B, T, m, m).clone()
    R[2, 5] = -1.0
    Q = c.Q.expand(B, T, n, n).clone()
    Q[3, 0, 0, 0] = float("nan")
    faulty = ts.Problem(problem.dynamics, ts.QuadraticCost(Q, R, c.Qf, c.x_ref, c.u_ref), T)
    for make in (
        lambda: ts.ILQR(max_iter=40, progress=False),
        lambda: ts.SLQ(max_iter=40, progress=False),
    ):
        res = make().solve(faulty, x0)
        ref = make().solve(problem, x0[:2])
        assert res.status_names()[2:] == ["not_positive_definite", "non_finite"]
        assert res.status_names()[:2] == ref.status_names()
        torch.testing.assert_close(res.u[:2], ref.u, rtol=0, atol=0)
    with pytest.raises(ValueError, match="R must be positive definite"):
        ts.QuadraticCost(c.Q, -c.R)


@pytest.mark.parametrize("compiled", [True, False])
def test_lqr_solve_faults_in_one_element_are_statuses_and_shared_faults_errors(compiled):
    """A NaN in one element's A and an indefinite R in another's: statuses non_finite /
    not_positive_definite, zero gradient for them, and the shared Q's gradient equals the
    good elements solved alone. The same faults in shared data are ValueErrors naming
    the argument."""
    from torchslq.lq import set_compiled

    g = torch.Generator().manual_seed(5)
    Bsz, T, n, m = 4, 6, 3, 2
    A = torch.eye(n, dtype=F64) + 0.1 * torch.randn(Bsz, T, n, n, generator=g, dtype=F64)
    Bm = 0.5 * torch.randn(Bsz, T, n, m, generator=g, dtype=F64)
    R = torch.eye(m, dtype=F64).expand(Bsz, T, m, m).clone()
    x0 = torch.randn(Bsz, n, generator=g, dtype=F64)
    A[1, 3, 0, 0] = float("nan")
    R[2, 1] = torch.diag(torch.tensor([1.0, -1.0], dtype=F64))
    good = torch.tensor([0, 3])
    set_compiled(compiled)
    try:
        Q = torch.eye(n, dtype=F64).requires_grad_(True)
        sol = ts.lqr_solve(A, Bm, Q, R, x0)
        assert ts.status_names(sol.status) == [
            "converged", "non_finite", "not_positive_definite", "converged",
        ]  # fmt: skip
        sol.cost[good].sum().backward()
        Q_ref = torch.eye(n, dtype=F64).requires_grad_(True)
        ref = ts.lqr_solve(A[good], Bm[good], Q_ref, R[good], x0[good])
        ref.cost.sum().backward()
        torch.testing.assert_close(sol.u[good], ref.u, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(Q.grad, Q_ref.grad, rtol=1e-10, atol=1e-12)
        with pytest.raises(ValueError, match=r"^A contains nan or inf \(in data shared"):
            ts.lqr_solve(A[1], Bm, Q, R, x0)
        with pytest.raises(ValueError, match=r"^R must be symmetric positive definite \(in data"):
            ts.lqr_solve(A[0], Bm, Q, R[2, 1], x0)
    finally:
        set_compiled(True)


@pytest.mark.parametrize("compiled", [True, False])
def test_an_overflowing_lq_problem_is_non_finite_not_not_positive_definite(compiled):
    """A = 1e200 (finite data, whose recursion overflows) is non_finite; a Quu that is
    not positive definite with finite numbers stays not_positive_definite. Checked
    independently: element 2's last-stage Quu = R + B'Q_T B is indefinite."""
    from torchslq.lq import set_compiled

    g = torch.Generator().manual_seed(1)
    Bsz, T, n, m = 3, 5, 2, 1
    A = torch.eye(n, dtype=F64).expand(Bsz, T, n, n).clone()
    Bm = torch.randn(Bsz, T, n, m, generator=g, dtype=F64)
    Q = torch.eye(n, dtype=F64).expand(Bsz, T + 1, n, n).clone()
    A[1] *= 1e200
    Q[2, T] = -100.0 * torch.eye(n, dtype=F64)
    Bl = Bm[2, T - 1]
    assert float(1.0 + Bl.T @ Q[2, T] @ Bl) < 0
    set_compiled(compiled)
    try:
        sol = ts.lqr_solve(A, Bm, Q, torch.eye(m, dtype=F64), torch.ones(Bsz, n, dtype=F64))
    finally:
        set_compiled(True)
    assert ts.status_names(sol.status) == ["converged", "non_finite", "not_positive_definite"]


def test_mpc_unroll_with_a_failed_element_gives_it_zero_gradient():
    """backward="unroll": a NaN row of x0 gets a zero gradient (it was NaN) and the shared
    R's gradient equals the batch without that row."""
    problem, x0 = pendulum_swingup(batch=3, horizon=10, seed=2)
    c = problem.cost
    bad = x0.clone()
    bad[1, 0] = float("nan")
    grads = []
    for x, loss_rows in ((bad.clone().requires_grad_(True), [0, 2]), (x0[[0, 2]], [0, 1])):
        R = torch.nn.Parameter(c.R.clone())
        layer = ts.MPC(
            problem.dynamics, ts.QuadraticCost(c.Q, R, c.Qf, c.x_ref, c.u_ref), 10,
            ts.ILQR(max_iter=30, progress=False), backward="unroll", unconverged="zero",
            warm_start=False,
        )  # fmt: skip
        out = layer(x)
        out.u[loss_rows].sum().backward()
        grads.append(R.grad)
        if x.requires_grad:
            assert out.status.tolist()[1] == int(ts.Status.NON_FINITE)
            assert torch.equal(x.grad[1], torch.zeros_like(x.grad[1]))
            assert torch.isfinite(x.grad).all()
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-12, atol=0)


def test_invalid_bounds_of_one_element_are_its_status():
    """Per-element bounds (B, T, m) with a NaN in one element and an empty box in another:
    non_finite / infeasible, and the others equal their solve without them, bit for bit,
    for ILQR, DDP (compact) and the constrained loop (which used to fail on per-element
    bounds once it worked on a sub-batch). Shared bounds with a fault stay errors."""
    problem, x0 = pendulum_swingup(batch=4, horizon=15, seed=1)
    T, m = 15, 1
    lo = torch.full((4, T, m), -3.0, dtype=F64)
    hi = torch.full((4, T, m), 3.0, dtype=F64)
    lo[1, 3, 0] = float("nan")
    lo[2, 5, 0] = 5.0
    makers = [
        lambda **k: ts.ILQR(max_iter=40, progress=False, **k),
        lambda **k: ts.DDP(max_iter=40, progress=False, compact=True, **k),
        lambda **k: ts.ILQR(
            max_iter=40, progress=False, constraints=ts.Constraints(x_max=20.0), **k
        ),
    ]
    good = [0, 3]
    for make in makers:
        res = make(u_min=lo, u_max=hi).solve(problem, x0)
        ref = make(u_min=lo[good], u_max=hi[good]).solve(problem, x0[good])
        assert res.status_names()[1:3] == ["non_finite", "infeasible"]
        assert [res.status_names()[i] for i in good] == ref.status_names()
        torch.testing.assert_close(res.u[good], ref.u, rtol=0, atol=0)
    with pytest.raises(ValueError, match="u_min must be <= u_max"):
        ts.ILQR(u_min=1.0, u_max=0.0, progress=False).solve(problem, x0)
    with pytest.raises(ValueError, match="u_min contains NaN"):
        ts.ILQR(u_min=torch.full((T, m), float("nan"), dtype=F64), progress=False).solve(
            problem, x0
        )


def test_lqr_solve_checks_clean_data_at_once_and_faults_per_element(monkeypatch):
    """Data without faults skip the per-element check (a mask per argument, more than a
    small solve costs) and give what the solve gives without validation; data with a
    fault take it (statuses above). The one-pass check is conservative: finite data
    whose sum overflows are sent to the per-element check, which finds them finite."""
    import sys

    S = sys.modules["torchslq.lq.solve"]
    calls = []
    real = S._input_faults
    monkeypatch.setattr(S, "_input_faults", lambda *a: calls.append(1) or real(*a))
    g = torch.Generator().manual_seed(7)
    Bsz, T, n, m = 3, 8, 3, 2
    A = torch.eye(n, dtype=F64) + 0.1 * torch.randn(Bsz, T, n, n, generator=g, dtype=F64)
    Bm = 0.5 * torch.randn(Bsz, T, n, m, generator=g, dtype=F64)
    Q, R = torch.eye(n, dtype=F64), torch.eye(m, dtype=F64)
    x0 = torch.randn(Bsz, n, generator=g, dtype=F64)
    q = torch.randn(Bsz, T + 1, n, generator=g, dtype=F64)
    sol = ts.lqr_solve(A, Bm, Q, R, x0, q=q)
    ref = ts.lqr_solve(A, Bm, Q, R, x0, q=q, validate=False)
    assert calls == [] and ts.status_names(sol.status) == ["converged"] * Bsz
    assert torch.equal(sol.x, ref.x) and torch.equal(sol.u, ref.u)
    bad = A.clone()
    bad[2, 0, 0, 0] = float("inf")
    assert ts.status_names(ts.lqr_solve(bad, Bm, Q, R, x0, q=q).status)[2] == "non_finite"
    assert calls == [1]
    big = q.clone()
    big[0, 0, 0] = big[1, 0, 0] = 1e308  # finite, but their sum is not
    Qt, Rt = Q.expand(T + 1, n, n), R.expand(T, m, m)  # with time dims, as lqr_solve
    assert not S._data_clean(A, Bm, Qt, Rt, x0, big, None, None, None)
    nonfinite, not_pd = real(A, Bm, Qt, Rt, x0, big, None, None, None, torch.Size([Bsz]))
    assert not bool(nonfinite.any()) and not bool(not_pd.any())
    assert S._data_clean(A, Bm, Qt, Rt, x0, q, None, None, None)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_data_check_agrees_with_the_per_element_check(dtype):
    """On the CPU ``lqr_solve``'s quick check runs compiled on the kernels' arrays
    (:func:`torchslq._backend.dispatch.lq_data_clean`). For a NaN or an infinity in each
    argument in turn, an ``R`` that is not positive definite (indefinite, singular, with
    an asymmetric part that a symmetric-only check would miss) and clean data, it says
    "clean" exactly where the per-element check (``_input_faults``, torch's ``isfinite``
    and LAPACK's Cholesky) finds nothing; and the statuses of the solve are that check's."""
    import sys

    from torchslq._backend import dispatch

    S = sys.modules["torchslq.lq.solve"]
    if not dispatch.compiled_available():
        pytest.skip("numba not installed: the compiled check is not used")
    g = torch.Generator().manual_seed(11)
    Bsz, T, n, m = 3, 6, 3, 2
    data = {
        "A": torch.eye(n) + 0.1 * torch.randn(Bsz, T, n, n, generator=g),
        "B": torch.randn(Bsz, T, n, m, generator=g),
        "Q": torch.eye(n).expand(Bsz, T + 1, n, n),  # broadcast: cut to one step
        "R": torch.eye(m).repeat(Bsz, T, 1, 1),
        "x0": torch.randn(Bsz, n, generator=g),
        "q": torch.randn(Bsz, T + 1, n, generator=g),
        "r": torch.randn(Bsz, T, m, generator=g),
        "S": 0.1 * torch.randn(Bsz, T, m, n, generator=g),
        "c": torch.randn(Bsz, T, n, generator=g),
    }
    data = {k: v.to(dtype) for k, v in data.items()}
    order = ("A", "B", "Q", "R", "x0", "q", "r", "S", "c")
    batch = torch.Size([Bsz])

    def cases():
        yield "clean", data
        for name in order:
            for bad in (float("nan"), float("inf")):
                d = {k: v.clone() for k, v in data.items()}
                d[name].view(-1)[-1] = bad  # the last element's last entry
                yield f"{name}={bad}", d
        for label, Rb in (
            ("indefinite", [[1.0, 2.0], [2.0, 1.0]]),
            ("singular", [[1.0, 1.0], [1.0, 1.0]]),
            ("negative", [[-1.0, 0.0], [0.0, 1.0]]),
            ("asymmetric, PD symmetric part", [[1.0, 3.0], [-3.0, 1.0]]),
        ):
            d = dict(data, R=data["R"].clone())
            d["R"][1, T - 1] = torch.tensor(Rb, dtype=dtype)
            yield label, d

    for label, d in cases():
        args = [d[k] for k in order]
        inputs = S._gain_inputs(*args, batch)
        assert inputs is not None
        nonfinite, not_pd = S._input_faults(*args, batch)
        exact = not bool((nonfinite | not_pd).any())
        assert dispatch.lq_data_clean(inputs[0], inputs[2]) == exact, label
        status = ts.lqr_solve(*args).status
        want = torch.zeros(Bsz, dtype=torch.int64)
        want[not_pd] = int(ts.Status.NOT_POSITIVE_DEFINITE)
        want[nonfinite] = int(ts.Status.NON_FINITE)
        assert torch.equal(status, want), label
        assert label == "clean" or not exact or label.startswith("asymmetric"), label
