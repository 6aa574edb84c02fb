"""A sweep of bad inputs over the public entry points (wrong types, shapes, dtypes,
devices, NaN in shared vs per-element data, empty batches, out-of-range options): each
gives a clear error naming the argument or a per-element status, never an internal
AttributeError / RuntimeError / IndexError from deep inside or a silent wrong answer.
(The cases fixed earlier are in tests/test_reliability.py.)"""

from __future__ import annotations

import math

import pytest
import torch

import torchslq as ts
from torchslq.systems import Pendulum

F64 = torch.float64
T = 6
NAN = float("nan")
INF = float("inf")


def _problem(batch=3, T=T, cost=None, dynamics=None):
    dyn = ts.discretize(Pendulum(), 0.05).to(F64) if dynamics is None else dynamics
    if cost is None:
        cost = ts.QuadraticCost(
            0.05 * torch.diag(torch.tensor([1.0, 0.1], dtype=F64)),
            0.01 * torch.eye(1, dtype=F64),
            Qf=torch.diag(torch.tensor([10.0, 1.0], dtype=F64)),
            x_ref=torch.tensor([math.pi, 0.0], dtype=F64),
        )
    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(batch, 2, generator=g, dtype=F64) * 2 - 1
    return ts.Problem(dyn, cost, T), x0


_SOLVERS = {
    "slq": lambda: ts.SLQ(max_iter=3, progress=False),
    "ilqr": lambda: ts.ILQR(max_iter=3, progress=False),
    "ddp": lambda: ts.DDP(max_iter=3, progress=False),
    "gradient": lambda: ts.GradientMethod(max_iter=3, progress=False),
    "gopronto": lambda: ts.GoPRONTO(max_iter=3, progress=False),
    "pronto": lambda: ts.PRONTO(max_iter=3, progress=False),
    "ilqr-constrained": lambda: ts.ILQR(
        max_iter=3, progress=False, al_max_iter=2, constraints=ts.Constraints(x_max=20.0)
    ),
}


# ------------------------------------------------------------------ solver front doors
@pytest.mark.parametrize("name", list(_SOLVERS))
def test_solve_refuses_a_problem_that_is_not_a_problem(name):
    """It was an AttributeError ('NoneType' object has no attribute 'check_inputs')."""
    _, x0 = _problem()
    for bad in (None, "pendulum"):
        with pytest.raises(TypeError, match="problem must be a torchslq.Problem"):
            _SOLVERS[name]().solve(bad, x0)


@pytest.mark.parametrize("name", ["slq", "ilqr", "gopronto", "ilqr-constrained"])
def test_a_logger_without_the_logger_methods_is_a_type_error(name):
    """It was an AttributeError ('str' object has no attribute 'log_options') after the
    first rollout."""
    problem, x0 = _problem()
    with pytest.raises(TypeError, match="logger must be None or a logger"):
        _SOLVERS[name]().solve(problem, x0, logger="runs/")


@pytest.mark.parametrize("name", ["ilqr", "gopronto"])
def test_x0_on_another_device_than_the_problem_is_an_error_naming_x0(name):
    """(The meta device stands in for a GPU here.) It was a RuntimeError from deep inside."""
    problem, x0 = _problem()
    with pytest.raises(ValueError, match="x0 is on device meta but the problem's tensor"):
        _SOLVERS[name]().solve(problem, x0.to("meta"))


@pytest.mark.parametrize("name", ["slq", "ilqr", "gopronto"])
def test_a_nan_in_u_init_shared_by_the_batch_is_an_error(name):
    """A shared (T, m) or (1, T, m) u_init with a NaN is no element's fault: it made every
    element non_finite, now it is a ValueError naming u_init (the granularity rule)."""
    problem, x0 = _problem()
    bad = torch.zeros(T, 1, dtype=F64)
    bad[2, 0] = NAN
    for u_init in (bad, bad[None]):
        with pytest.raises(ValueError, match="u_init contains nan or inf .in data shared"):
            _SOLVERS[name]().solve(problem, x0, u_init)
    # one element's own row is still that element's status
    rows = torch.zeros(3, T, 1, dtype=F64)
    rows[1, 2, 0] = NAN
    res = _SOLVERS[name]().solve(problem, x0, rows)
    assert res.status_names()[1] == "non_finite"
    ref = _SOLVERS[name]().solve(problem, x0[[0, 2]])
    torch.testing.assert_close(res.u[[0, 2]], ref.u, rtol=0, atol=0)


def test_a_nan_in_one_elements_multipliers_is_that_elements_status():
    """Warm-start multipliers with a NaN in one element rejected the whole batch; now that
    element is non_finite and the others are solved as without it. Shared multipliers
    with a NaN stay an error; a wrong shape names the shape expected."""
    problem, x0 = _problem()
    solver = ts.ILQR(max_iter=20, progress=False, constraints=ts.Constraints(x_max=0.9))
    stage = torch.rand(3, T, 2, dtype=F64, generator=torch.Generator().manual_seed(1))
    terminal = torch.zeros(3, 2, dtype=F64)
    bad = stage.clone()
    bad[1, 3, 0] = NAN
    res = solver.solve(problem, x0, multipliers={"stage": bad, "terminal": terminal})
    assert res.status_names()[1] == "non_finite"
    keep = [0, 2]
    ref = solver.solve(
        problem, x0[keep], multipliers={"stage": stage[keep], "terminal": terminal[keep]}
    )
    assert [res.status_names()[i] for i in keep] == ref.status_names()
    torch.testing.assert_close(res.u[keep], ref.u, rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"multipliers\['stage'\] contains nan or inf \(in data"):
        solver.solve(problem, x0, multipliers={"stage": bad[1], "terminal": terminal})
    with pytest.raises(ValueError, match=rf"multipliers\['stage'\] must have shape \(B, {T}, 2\)"):
        solver.solve(problem, x0, multipliers={"stage": stage[..., :1], "terminal": terminal})


@pytest.mark.parametrize(
    "make, name",
    [
        (lambda: ts.ILQR(mu_init=INF), "mu_init"),
        (lambda: ts.DDP(mu_init=INF), "mu_init"),
        (lambda: ts.ILQR(hessian_floor=INF), "hessian_floor"),
        (lambda: ts.GoPRONTO(step=INF), "step"),
        (lambda: ts.GoPRONTO(step0=INF), "step0"),
        (lambda: ts.PRONTO(step0=INF), "step0"),
    ],
)
def test_an_infinite_option_that_breaks_every_element_is_an_error(make, name):
    """These made every element non_finite / not_positive_definite / diverged /
    line_search_failed: an option shared by the batch, so an error naming it."""
    with pytest.raises(ValueError, match=f"^{name} must be in"):
        make()


@pytest.mark.parametrize("make", [ts.GoPRONTO, ts.PRONTO])
def test_gopronto_progress_must_be_a_bool(make):
    """Any value was accepted (as in the descent solvers, it must be a bool)."""
    with pytest.raises(TypeError, match="progress must be a bool"):
        make(progress="yes")


def test_a_constrained_float16_solve_with_an_overflowing_penalty_is_an_error():
    """penalty_max = 1e10 does not fit in float16: it was a RuntimeError ('value cannot
    be converted to type c10::Half without overflow') from inside the loop."""
    problem, x0 = _problem()
    problem = problem.to(torch.float16)
    solver = ts.ILQR(max_iter=3, progress=False, constraints=ts.Constraints(x_max=20.0))
    with pytest.raises(ValueError, match="penalty_max = 1e\\+10 overflows torch.float16"):
        solver.solve(problem, x0.half())
    res = solver.with_options(penalty_max=1e4).solve(problem, x0.half())  # the fix works
    assert res.status.shape == (3,)


# ------------------------------------------------------------------ lqr_solve
def _lq(Bsz=3, T=5, n=2, m=1):
    g = torch.Generator().manual_seed(0)
    A = torch.eye(n, dtype=F64).expand(Bsz, T, n, n).clone()
    Bm = torch.randn(Bsz, T, n, m, generator=g, dtype=F64)
    return A, Bm, torch.eye(n, dtype=F64), torch.eye(m, dtype=F64), torch.randn(Bsz, n, dtype=F64)


def test_lqr_solve_refuses_missing_mixed_precision_float16_and_other_device_arguments():
    """Q=None was an AttributeError, a float32 x0 or R among float64 data a RuntimeError
    ('expected scalar type Double but found Float'), float16 a NotImplementedError from
    cholesky, data on two devices a RuntimeError."""
    A, Bm, Q, R, x0 = _lq()
    with pytest.raises(TypeError, match="^Q must be a torch.Tensor, got None"):
        ts.lqr_solve(A, Bm, None, R, x0)
    with pytest.raises(TypeError, match="^x0 has dtype torch.float32 but A has torch.float64"):
        ts.lqr_solve(A, Bm, Q, R, x0.float())
    with pytest.raises(TypeError, match="^R has dtype torch.float32 but A has torch.float64"):
        ts.lqr_solve(A, Bm, Q, R.float(), x0)
    with pytest.raises(TypeError, match="^A has dtype torch.float16; lqr_solve needs float32"):
        ts.lqr_solve(*(t.half() for t in (A, Bm, Q, R, x0)))
    with pytest.raises(ValueError, match="^B is on device cpu but A is on meta"):
        ts.lqr_solve(A.to("meta"), Bm, Q, R, x0)
    assert ts.status_names(ts.lqr_solve(A, Bm, Q, R, x0).status) == ["converged"] * 3


# ------------------------------------------------------------------ MPC
def test_mpc_checks_u_init_and_its_options_before_solving():
    problem, x0 = _problem(batch=2)
    dyn, cost = problem.dynamics, problem.cost
    solver = ts.ILQR(max_iter=20, progress=False)
    mpc = ts.MPC(dyn, cost, T, solver=solver)
    # a list u_init was an AttributeError ('list' object has no attribute 'detach')
    with pytest.raises(TypeError, match="u_init must be a tensor"):
        mpc(x0, [[0.0]] * T)
    # 0 and 1 passed the membership tests of True/False; warm_start=0 then warm started
    with pytest.raises(ValueError, match="warm_start must be True, False"):
        ts.MPC(dyn, cost, T, solver=solver, warm_start=0)
    with pytest.raises(ValueError, match="compact must be True, False or 'auto'"):
        ts.MPC(dyn, cost, T, solver=solver, compact=1)
    with pytest.raises(ValueError, match="unroll_iters must be a positive int"):
        ts.MPC(dyn, cost, T, solver=solver, unroll_iters=True)
    # the class instead of an instance failed at the first forward (with_options unbound)
    with pytest.raises(TypeError, match="solver must be a solver object"):
        ts.MPC(dyn, cost, T, solver=ts.ILQR)


def test_mpc_step_in_another_dtype_after_a_warm_start_names_x0():
    """The warm start's rollout ran before the solver's checks and blamed the dynamics
    ('the dynamics returned ... float64 for states of ... float32')."""
    problem, x0 = _problem(batch=2)
    mpc = ts.MPC(problem.dynamics, problem.cost, T, solver=ts.ILQR(max_iter=20, progress=False))
    mpc.step(x0)
    with pytest.raises(TypeError, match="^x0 has dtype torch.float32 but the problem's tensor"):
        mpc.step(x0.float())


# ------------------------------------------------------------------ costs
def test_quadratic_cost_accepts_half_precision_weights_and_still_checks_them():
    """eigvalsh has no float16 kernel: construction was a NotImplementedError (while the
    solvers run float16 problems)."""
    Q, R = torch.eye(2, dtype=torch.float16), torch.eye(1, dtype=torch.float16)
    cost = ts.QuadraticCost(Q, R)
    assert cost.Q.dtype == torch.float16
    with pytest.raises(ValueError, match="R must be positive definite"):
        ts.QuadraticCost(Q, -R)
    with pytest.raises(ValueError, match="Q must be symmetric"):
        ts.QuadraticCost(torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=torch.bfloat16), R)


@pytest.mark.parametrize("field", ["Q", "R", "Qf", "x_ref", "u_ref"])
def test_per_element_cost_data_for_another_batch_size_is_an_error_naming_it(field):
    """It was a RuntimeError ('shapes [(3,), (3,), (4,)] cannot be broadcast together')."""
    Q, R = 0.05 * torch.eye(2, dtype=F64), 0.01 * torch.eye(1, dtype=F64)
    per_element = {
        "Q": Q.expand(4, T, 2, 2),
        "R": R.expand(4, T, 1, 1),
        "Qf": Q.expand(4, 2, 2),
        "x_ref": torch.zeros(4, T + 1, 2, dtype=F64),
        "u_ref": torch.zeros(4, T, 1, dtype=F64),
    }
    kw = {"Q": Q, "R": R, field: per_element[field]}
    problem, x0 = _problem(cost=ts.QuadraticCost(**kw))
    with pytest.raises(ValueError, match=f"cost.{field} is given per element for a batch of 4"):
        ts.ILQR(max_iter=3, progress=False).solve(problem, x0)
    res = ts.ILQR(max_iter=3, progress=False).solve(problem, torch.cat([x0, x0[:1]]))
    assert res.status.shape == (4,)


def test_quadratic_cost_with_an_empty_batch_of_weights_and_non_tensor_trajectories():
    """A (0, T, n, n) weight was a RuntimeError (amax of an empty tensor); cost(x, u) on
    lists an AttributeError."""
    Q, R = torch.eye(2, dtype=F64), torch.eye(1, dtype=F64)
    problem, x0 = _problem(cost=ts.QuadraticCost(Q.expand(0, T, 2, 2), R))
    assert ts.ILQR(progress=False).solve(problem, x0[:0]).x.shape == (0, T + 1, 2)
    with pytest.raises(TypeError, match="x and u must be tensors"):
        problem.cost([[0.0]], [[0.0]])
    with pytest.raises(TypeError, match="x and u must be tensors"):
        problem.cost.quadratize([[0.0]], [[0.0]])


def _pos_cost(**kw):
    def stage(x, u, t):
        return (x * x).sum(-1) + (u * u).sum(-1)

    return ts.Cost(kw.pop("stage", stage), kw.pop("terminal", None), state_dim=2, control_dim=1)


@pytest.mark.parametrize(
    "kw, error, match",
    [
        (
            {"stage": lambda x, u, t: (x * x).sum(-1, keepdim=True)},
            ValueError,
            "stage returned shape",
        ),
        ({"stage": lambda x, u, t: (x * x).sum()}, ValueError, r"stage returned shape \(\)"),
        ({"stage": lambda x, u, t: [1.0]}, TypeError, "stage must return a tensor"),
        ({"terminal": lambda x: x * x}, ValueError, "terminal returned shape"),
    ],
)
def test_a_general_cost_function_with_a_wrong_output_is_an_error_naming_it(kw, error, match):
    """(B, T, 1) and (B, n) outputs were RuntimeErrors from the sum, a list an
    AttributeError, and a scalar (a sum over the batch) a silent wrong cost: every
    element got the whole batch's stage cost."""
    problem, x0 = _problem(cost=_pos_cost(**kw))
    with pytest.raises(error, match=match):
        ts.ILQR(max_iter=3, progress=False).solve(problem, x0)


def test_a_general_cost_keeps_broadcasting_outputs_and_refuses_bool_dims():
    """A stage of t alone ((T,), broadcast over the batch) is still a valid cost."""
    cost = ts.Cost(lambda x, u, t: t.to(x.dtype), lambda x: x[..., 0], state_dim=2, control_dim=1)
    x, u = torch.ones(3, T + 1, 2, dtype=F64), torch.zeros(3, T, 1, dtype=F64)
    torch.testing.assert_close(cost(x, u), torch.full((3,), T * (T - 1) / 2 + 1.0, dtype=F64))
    with pytest.raises(ValueError, match="state_dim and control_dim must be positive ints"):
        ts.Cost(state_dim=2, control_dim=True)


# ------------------------------------------------------------------ dynamics
def test_discretize_and_dynamics_dims_refuse_out_of_range_values():
    """dt = inf made every element non_finite, dt = True was a step of 1.0; state_dim 0
    was reported as a cost mismatch."""
    for dt in (INF, True):
        with pytest.raises(ValueError, match="dt must be a positive finite number"):
            ts.discretize(Pendulum(), dt)

    class NoState(ts.Dynamics):
        state_dim, control_dim = 0, 1

    with pytest.raises(ValueError, match="NoState has state_dim 0 and control_dim 1"):
        ts.Problem(NoState(), ts.Cost(state_dim=1, control_dim=1), T)


def _lin(x, u):
    return torch.cat([x[..., :1] + 0.1 * x[..., 1:], x[..., 1:] + 0.1 * u], -1)


class _Jac(ts.Dynamics):
    """A linear model whose analytic jacobians return ``self.out(x, u)``."""

    state_dim, control_dim = 2, 1

    def __init__(self, out):
        super().__init__()
        self.out = out

    def forward(self, x, u):
        return _lin(x, u)

    def jacobians(self, x, u):
        return self.out(x, u)


_BAD_JACOBIANS = [
    (lambda x, u: (x.new_zeros(*x.shape), x.new_zeros(*x.shape[:-1], 2, 1)), ValueError, "A = df/dx of shape"),
    (lambda x, u: [1, 2], TypeError, "must return two tensors"),
    (
        lambda x, u: (torch.eye(2).expand(*x.shape[:-1], 2, 2), torch.zeros(*x.shape[:-1], 2, 1)),
        ValueError,
        "as torch.float32 on cpu for x of torch.float64",
    ),
]  # fmt: skip


@pytest.mark.parametrize("name", ["slq", "ilqr", "gopronto"])
@pytest.mark.parametrize("out, error, match", _BAD_JACOBIANS)
def test_analytic_jacobians_of_a_wrong_shape_or_dtype_are_an_error_naming_them(
    name, out, error, match
):
    """They were an IndexError ('index 5 is out of bounds'), an AttributeError or a
    RuntimeError from inside the costate pass."""
    problem, x0 = _problem(dynamics=_Jac(out))
    with pytest.raises(error, match="_Jac.jacobians"):
        _SOLVERS[name]().solve(problem, x0)
    with pytest.raises(error, match=match):
        ts.linearize(_Jac(out), x0, torch.zeros(3, 1, dtype=F64))


def test_learned_dynamics_checks_its_network_and_dims():
    """net=None was a TypeError from the first call, dims '2.7' truncated to 2, a Linear
    of the wrong width a RuntimeError ('mat1 and mat2 shapes cannot be multiplied'), a
    wrong output width a RuntimeError from the residual sum."""
    with pytest.raises(TypeError, match="net must be a module or callable"):
        ts.LearnedDynamics(None, 2, 1)
    for dim in (2.7, "2", True, 0):
        with pytest.raises(ValueError, match="state_dim must be a positive int"):
            ts.LearnedDynamics(torch.nn.Linear(3, 2), dim, 1)
    with pytest.raises(TypeError, match="residual must be a bool"):
        ts.LearnedDynamics(torch.nn.Linear(3, 2), 2, 1, residual="no")
    with pytest.raises(ValueError, match="net takes 4 input features but"):
        ts.LearnedDynamics(torch.nn.Sequential(torch.nn.Linear(4, 2)), 2, 1)
    wide = ts.LearnedDynamics(torch.nn.Linear(3, 3).double(), 2, 1)
    problem, x0 = _problem(dynamics=wide)
    with pytest.raises(ValueError, match="its last dim must be state_dim = 2"):
        ts.ILQR(max_iter=3, progress=False).solve(problem, x0)
    assert ts.LearnedDynamics(torch.nn.Linear(3, 2), 2, 1).state_dim == 2


def test_linearize_and_problem_rollout_check_their_arguments():
    problem, x0 = _problem()
    with pytest.raises(TypeError, match="x and u must be tensors"):
        ts.linearize(problem.dynamics, [0.0, 0.0], [0.0])
    with pytest.raises(TypeError, match="x0 must be a floating-point tensor"):
        problem.rollout([0.0, 0.0], torch.zeros(3, T, 1, dtype=F64))
    # u with 2 columns for a 1-control model was rolled out silently (u[..., 0] used)
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., B, T, 1\)"):
        problem.rollout(x0, torch.zeros(3, T, 2, dtype=F64))


# ------------------------------------------------------------------ constraints
def test_constraint_bounds_of_a_wrong_length_or_type_are_errors_naming_them():
    """x_max with 3 entries for n = 2 was a RuntimeError from expand; a str a TypeError
    from torch ('new(): invalid data type'); True was read as 1.0."""
    problem, x0 = _problem()
    solver = ts.ILQR(max_iter=3, progress=False, constraints=ts.Constraints(x_max=torch.ones(3)))
    with pytest.raises(ValueError, match="x_max has 3 entries but the state has n = 2"):
        solver.solve(problem, x0)
    for bad in ("1.0", True):
        with pytest.raises(TypeError, match="x_max must be a float or a tensor"):
            ts.Constraints(x_max=bad)


@pytest.mark.parametrize(
    "kw, error, match",
    [
        ({"stage": lambda x, u, t: u[..., 0] - 1.0}, ValueError, "constraints' stage must return"),
        ({"stage": lambda x, u, t: [1.0]}, TypeError, "constraints' stage must return a tensor"),
        ({"terminal": lambda x: x[..., 0]}, ValueError, "constraints' terminal must return"),
        (
            {"stage": lambda x, u, t: u - 1.0, "stage_jacobian": lambda x, u, t: (x, u)},
            ValueError,
            "constraints' stage_jacobian returned",
        ),
    ],
)
def test_a_constraint_function_with_a_wrong_output_is_an_error_naming_it(kw, error, match):
    """They were RuntimeErrors (expand, index_copy_) and an AttributeError from the loop."""
    problem, x0 = _problem()
    solver = ts.ILQR(max_iter=3, progress=False, al_max_iter=2, constraints=ts.Constraints(**kw))
    with pytest.raises(error, match=match):
        solver.solve(problem, x0)


def test_a_constraint_with_a_per_element_parameter_still_solves():
    """The output check at one row allows a batch from a (B, 1, 1) parameter."""
    problem, x0 = _problem()
    limit = torch.tensor([0.5, 1.0, 2.0], dtype=F64).view(3, 1, 1)
    c = ts.Constraints(stage=lambda x, u, t: u - limit)
    res = ts.ILQR(max_iter=20, progress=False, constraints=c).solve(problem, x0)
    assert bool((res.u <= limit + 1e-5).all())


# ------------------------------------------------------------------ save / load, sharding
def test_solver_result_save_and_load_name_bad_files_and_arguments(tmp_path):
    """A corrupt or text file was an UnpicklingError / KeyError, path None an
    AttributeError, a bad map_location a RuntimeError, missing fields a dataclass
    TypeError, a directory a RuntimeError from the zip writer."""
    problem, x0 = _problem()
    res = ts.ILQR(max_iter=3, progress=False).solve(problem, x0)
    (tmp_path / "text.pt").write_text("hello")
    (tmp_path / "junk.pt").write_bytes(b"\x80\x02junk")
    for name in ("text.pt", "junk.pt"):
        with pytest.raises(ValueError, match="is not a file written by SolverResult.save"):
            ts.SolverResult.load(tmp_path / name)
    torch.save({"class": "SolverResult", "fields": {"x": res.x}}, tmp_path / "partial.pt")
    with pytest.raises(ValueError, match="its fields \\['x'\\] do not match SolverResult"):
        ts.SolverResult.load(tmp_path / "partial.pt")
    with pytest.raises(TypeError, match="path must be a str"):
        ts.SolverResult.load(None)
    res.save(tmp_path / "ok.pt")
    with pytest.raises(ValueError, match="map_location 'nowhere' is not a device"):
        ts.SolverResult.load(tmp_path / "ok.pt", map_location="nowhere")
    with pytest.raises(IsADirectoryError, match="is a directory"):
        res.save(tmp_path)
    with pytest.raises(TypeError, match="path must be a str"):
        res.save(123)
    assert torch.equal(ts.SolverResult.load(tmp_path / "ok.pt").u, res.u)


def test_solve_sharded_checks_its_arguments_and_an_empty_job_loads(tmp_path):
    """shard_size=True and rank=True were read as 1; solver None an AttributeError; an
    empty x0 wrote no shard and load_sharded failed with an IndexError."""
    from torchslq.distributed import load_sharded, solve_sharded

    problem, x0 = _problem()
    solver = ts.ILQR(max_iter=3, progress=False)
    with pytest.raises(ValueError, match="shard_size must be a positive int"):
        solve_sharded(solver, problem, x0, tmp_path / "a", True)
    with pytest.raises(ValueError, match="need 0 <= rank < world_size"):
        solve_sharded(solver, problem, x0, tmp_path / "b", 2, rank=True, world_size=2)
    with pytest.raises(TypeError, match="solver must be a solver object"):
        solve_sharded(None, problem, x0, tmp_path / "c", 2)
    with pytest.raises(TypeError, match="problem must be a torchslq.Problem"):
        solve_sharded(solver, None, x0, tmp_path / "d", 2)
    report = solve_sharded(solver, problem, x0[:0], tmp_path / "empty", 2)
    assert report.num_shards == 1
    empty = load_sharded(tmp_path / "empty")
    assert empty.x.shape == (0, T + 1, 2) and empty.status.shape == (0,)


# ------------------------------------------------------------------ LQDO front door
@pytest.fixture(scope="module")
def codesign():
    from torchslq.lqdo import cases, transcribe

    return transcribe(cases.codesign_transfer(), "TR", nodes=8)


def test_quasilinearization_checks_z0_and_its_options(codesign):
    """z0 None, a list or float32 were RuntimeErrors (index_add_ dtypes, 'Could not infer
    dtype of NoneType'), an empty batch a RuntimeError from a reshape; tol='a' a
    TypeError from a comparison, max_iter=True accepted, feas_tol < 0 accepted."""
    from torchslq.lqdo import Quasilinearization

    tr = codesign
    z0 = tr.initial_guess()
    ref = Quasilinearization(max_iter=2).solve(tr, z0)
    for z in (z0.float(), z0.tolist()):
        res = Quasilinearization(max_iter=2).solve(tr, z)
        torch.testing.assert_close(res.objective, ref.objective, rtol=1e-6, atol=1e-8)
    with pytest.raises(TypeError, match=r"z0 must be a tensor \(B, 25\)"):
        Quasilinearization(max_iter=2).solve(tr, None)
    with pytest.raises(ValueError, match="z0 has an empty batch"):
        Quasilinearization(max_iter=2).solve(tr, z0[:0])
    with pytest.raises(TypeError, match="tol must be a number"):
        Quasilinearization(tol="a")
    with pytest.raises(ValueError, match="max_iter must be an int"):
        Quasilinearization(max_iter=True)
    with pytest.raises(ValueError, match="feas_tol must be in"):
        Quasilinearization(feas_tol=-1.0)


def test_two_level_checks_its_arguments_and_a_nan_design_is_non_finite(codesign):
    """tr None was an AttributeError, p0 (1, 1, 1) a 'too many values to unpack', an
    empty batch a RuntimeError, tol NaN accepted; a NaN starting design was labelled
    not_positive_definite."""
    from torchslq.lqdo import TwoLevel

    tr = codesign
    with pytest.raises(TypeError, match="tr must be a Transcription"):
        TwoLevel(max_iter=2).solve(None, torch.ones(1, 1))
    with pytest.raises(ValueError, match=r"p0 must be \(B, 1\)"):
        TwoLevel(max_iter=2).solve(tr, torch.ones(1, 1, 1))
    with pytest.raises(ValueError, match="p0 has an empty batch"):
        TwoLevel(max_iter=2).solve(tr, torch.ones(0, 1))
    with pytest.raises(ValueError, match="tol must be in"):
        TwoLevel(tol=NAN)
    res = TwoLevel(max_iter=2, backend="dense").solve(tr, torch.tensor([[1.0], [NAN]]))
    assert ts.status_names(res.status)[1] == "non_finite"


def test_qp_solve_and_transcribe_check_their_arguments():
    """f=None and H as a list were AttributeErrors, mixed float32/float64 a RuntimeError,
    transcribe(dtype=int64) a RuntimeError."""
    from torchslq.lqdo import cases, qp_solve, transcribe

    H, f = torch.eye(2, dtype=F64)[None], torch.zeros(1, 2, dtype=F64)
    A, b = torch.zeros(1, 0, 2, dtype=F64), torch.zeros(1, 0, dtype=F64)
    G, h = torch.zeros(1, 0, 2, dtype=F64), torch.zeros(1, 0, dtype=F64)
    with pytest.raises(TypeError, match="^f must be a floating-point tensor"):
        qp_solve(H, None, A, b, G, h)
    with pytest.raises(TypeError, match="^H must be a floating-point tensor"):
        qp_solve([[1.0]], f, A, b, G, h)
    with pytest.raises(TypeError, match="^H is torch.float32 on cpu but f is torch.float64"):
        qp_solve(H.float(), f, A, b, G, h)
    z, _, _, status = qp_solve(H, f + 1.0, A, b, G, h)
    torch.testing.assert_close(z, -torch.ones(1, 2, dtype=F64))
    with pytest.raises(TypeError, match="dtype must be a floating-point torch.dtype"):
        transcribe(cases.codesign_transfer(), "TR", nodes=8, dtype=torch.int64)


# ------------------------------------------------------------------ continuous time
def test_continuous_problem_refuses_an_infinite_horizon_and_a_bad_logger():
    """tf = inf was accepted and ContinuousILQR.solve then ran for minutes (a hang); a
    logger without the logger methods was an AttributeError after the forward pass."""

    class Lin(ts.ContinuousDynamics):
        state_dim, control_dim = 2, 1

        def forward(self, x, u, t=None):
            return torch.stack([x[..., 1], u[..., 0]], -1)

    cost = ts.Cost(lambda x, u, t: (u * u).sum(-1), state_dim=2, control_dim=1)
    for t0, tf in ((0.0, INF), (-INF, 1.0)):
        with pytest.raises(ValueError, match="must be finite"):
            ts.ContinuousProblem(Lin(), cost, t0, tf)
    problem = ts.ContinuousProblem(Lin(), cost, 0.0, 1.0)
    with pytest.raises(TypeError, match="logger must be None or a logger"):
        ts.ContinuousILQR(max_iter=1, progress=False).solve(problem, torch.zeros(2, 2), logger=1)


@pytest.mark.parametrize(
    "kw,match",
    [
        ({"plot_elements": -1}, "plot_elements"),
        ({"plot_elements": "a"}, "plot_elements"),
        ({"dt": -1.0}, "dt"),
        ({"dt": "x"}, "dt"),
        ({"save_png": 1}, "save_png"),
        ({"state_labels": "ab"}, "state_labels"),
        ({"control_labels": [1]}, "control_labels"),
    ],
)
def test_logger_options_are_validated(kw, match, tmp_path):
    """They were accepted and failed (or drew wrong labels) only at log_result."""
    with pytest.raises((ValueError, TypeError), match=match):
        ts.TensorBoardLogger(tmp_path, **kw)
