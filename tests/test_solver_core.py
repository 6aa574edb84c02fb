"""The shared solver core: re-entrant solver objects, every option recorded, immutable
options with clear errors, and a custom direction on the one loop (the example of
docs/architecture.md, executed here)."""

from __future__ import annotations

import re
import threading
from dataclasses import fields
from pathlib import Path

import pytest
import torch

import torchslq as ts
from torchslq.tasks import pendulum_swingup

F64 = torch.float64
SOLVERS = {
    "slq": lambda **kw: ts.SLQ(progress=False, **kw),
    "ilqr": lambda **kw: ts.ILQR(progress=False, **kw),
    "ddp": lambda **kw: ts.DDP(progress=False, **kw),
    "gradient": lambda **kw: ts.GradientMethod(progress=False, **kw),
    "gopronto": lambda **kw: ts.GoPRONTO(progress=False, **kw),
    "pronto": lambda **kw: ts.PRONTO(progress=False, **kw),
}


def _same(a, b):
    for name in ("x", "u", "cost", "grad_norm", "iterations", "status", "K"):
        torch.testing.assert_close(
            getattr(a, name), getattr(b, name), rtol=0, atol=0, equal_nan=True, msg=name
        )


@pytest.mark.parametrize("name", ["ilqr", "ddp", "slq", "gopronto"])
def test_one_solver_object_serves_two_threads_at_once(name):
    """One solver object used from two threads on two problems (B=5 and B=9) at the same
    time gives each the result of a sequential solve (per-solve state is not kept on the
    object; a former version failed with a size mismatch between the two batches)."""
    solver = SOLVERS[name](max_iter=25)
    jobs = [
        pendulum_swingup(batch=5, horizon=20, seed=1),
        pendulum_swingup(batch=9, horizon=20, seed=2),
    ]
    sequential = [solver.solve(p, x0) for p, x0 in jobs]
    results: list = [None, None]
    errors: list = []
    start = threading.Barrier(2)

    def work(i):
        try:
            start.wait()
            for _ in range(2):  # overlap for longer than one solve
                results[i] = solver.solve(*jobs[i])
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    for got, ref in zip(results, sequential, strict=True):
        _same(got, ref)


@pytest.mark.parametrize("name", sorted(SOLVERS))
def test_every_option_is_recorded_in_the_result_and_the_logger(name):
    """result.options and the logger's options hold every field of the solver's options
    with its value (before, ILQR's mu_*, bounds and DDP's second_order were missing)."""
    problem, x0 = pendulum_swingup(batch=2, horizon=10, seed=0)
    solver = SOLVERS[name](max_iter=3)
    logged = {}

    class Recorder:
        def log_options(self, solver_name, options):
            logged.update(options, solver=solver_name)

        def log_iteration(self, *a, **kw):
            pass

        def log_result(self, *a, **kw):
            pass

    res = solver.solve(problem, x0, logger=Recorder())
    names = {f.name for f in fields(solver.options)}
    assert set(res.options) == names | {"solver"}
    assert set(logged) == names | {"solver"}
    assert res.options["solver"] == solver.name == logged["solver"]
    for f in fields(solver.options):
        assert res.options[f.name] is getattr(solver.options, f.name) or (
            res.options[f.name] == getattr(solver.options, f.name)
        )


def test_non_default_options_reach_the_record():
    problem, x0 = pendulum_swingup(batch=2, horizon=10, seed=0)
    res = ts.DDP(
        mu_init=0.5, mu_factor=3.0, second_order="costate", u_max=2.0, max_iter=2, progress=False
    ).solve(problem, x0)
    assert res.options["mu_init"] == 0.5 and res.options["mu_factor"] == 3.0
    assert res.options["second_order"] == "costate" and res.options["u_max"] == 2.0


def test_solvers_are_immutable_and_with_options_makes_a_new_one():
    s = ts.ILQR(tol=1e-6, progress=False)
    with pytest.raises(AttributeError, match="immutable"):
        s.tol = 1e-3
    with pytest.raises(Exception):  # noqa: B017 - a frozen dataclass
        s.options.tol = 1e-3
    t = s.with_options(tol=1e-3, u_max=1.0)
    assert type(t) is ts.ILQR and t.options.tol == 1e-3 and t.options.u_max == 1.0
    assert s.options.tol == 1e-6 and s.options.u_max is None
    assert s.mu_init == 0.0  # options read as attributes
    with pytest.raises(ValueError, match="armijo_beta"):
        s.with_options(armijo_beta=2.0)


def test_mpc_reads_capabilities_and_never_changes_its_solver():
    from torchslq.systems import Pendulum

    solver = ts.ILQR(max_iter=50, tol=1e-8, progress=False)
    cost = ts.QuadraticCost(torch.eye(2, dtype=F64), 0.1 * torch.eye(1, dtype=F64))
    mpc = ts.MPC(ts.discretize(Pendulum(), 0.05), cost, 10, solver=solver, u_min=-1.0, u_max=1.0)
    mpc(torch.tensor([[0.5, 0.0]], dtype=F64))
    assert solver.options.u_min is None and solver.options.compact is False
    assert mpc.solver.options.u_max == 1.0
    assert ts.ILQR.supports_bounds and not ts.SLQ.supports_bounds
    with pytest.raises(ValueError, match="supports_bounds"):
        ts.MPC(ts.discretize(Pendulum(), 0.05), cost, 10, solver=ts.SLQ(), u_max=1.0)


@pytest.mark.parametrize(
    "make, arg",
    [
        (lambda: ts.SLQ(u_min=0.0), "u_min"),
        (lambda: ts.SLQ(armijo_beta=1.5), "armijo_beta"),
        (lambda: ts.SLQ(max_backtracks=-1), "max_backtracks"),
        (lambda: ts.ILQR(armijo_c1=0.0), "armijo_c1"),
        (lambda: ts.DDP(second_order="exact"), "second_order"),
        (lambda: ts.GradientMethod(growth=0.5), "growth"),
        (lambda: ts.GoPRONTO(armijo_passes=(0, 1)), "armijo_passes"),
        (lambda: ts.PRONTO(variant="conjugate"), "variant"),
    ],
)
def test_bad_options_are_refused_naming_the_argument(make, arg):
    with pytest.raises((TypeError, ValueError), match=arg):
        make()


def test_gopronto_armijo_chunk_is_armijo_passes():
    assert ts.GoPRONTO(armijo_chunk=2).options.armijo_passes == (2, 2)


def _architecture_example() -> str:
    text = (Path(__file__).parents[1] / "docs" / "architecture.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    marked = [b for b in blocks if "class HalfGaussNewton" in b]
    assert len(marked) == 1, "docs/architecture.md has the custom-direction example"
    return marked[0]


def test_custom_direction_example_of_the_architecture_page():
    """The example of docs/architecture.md: a custom direction (half the Gauss-Newton
    step) with SLQ's line search on the one loop reaches SLQ's solution."""
    scope: dict = {}
    exec(_architecture_example(), scope)  # noqa: S102 - the documented example
    result, reference = scope["result"], scope["reference"]
    assert result.status_names() == ["converged"] * 4
    torch.testing.assert_close(result.cost, reference.cost, rtol=1e-8, atol=0)
    torch.testing.assert_close(result.u, reference.u, rtol=0, atol=1e-4)


def test_state_updated_equals_dataclasses_replace():
    """ElementState.updated (the loop's copy with some fields changed) makes what
    dataclasses.replace makes: a new frozen state of the same class, the changed fields
    new, the others the same objects, the original untouched."""
    from dataclasses import FrozenInstanceError, replace

    from torchslq.solvers.descent import DescentState

    x, u, J, mu = torch.zeros(2, 3, 1), torch.zeros(2, 2, 1), torch.ones(2), torch.ones(2)
    state = DescentState(x=x, u=u, J=J, mu=mu, delta=mu)
    new_mu = torch.full((2,), 3.0)
    got = state.updated(mu=new_mu, prev_step=J)
    ref = replace(state, mu=new_mu, prev_step=J)
    assert type(got) is DescentState and got is not state
    for f in fields(DescentState):
        assert getattr(got, f.name) is getattr(ref, f.name), f.name
    assert state.mu is mu and state.prev_step is None
    with pytest.raises(FrozenInstanceError):
        got.mu = mu


def test_stall_update_follows_the_rule_per_element():
    """The stall rule's counters against the rule written per element in plain Python
    (a run of noise-level accepted steps counts up, restarts at 0 otherwise; stalled
    after stall_iters of them unless the gradient halved over the run), over iterations
    with and without noise-level steps (the batched form has a shortcut for the latter)."""
    from torchslq.solvers.stopping import ROUNDOFF_NOISE, stall_update

    g = torch.Generator().manual_seed(0)
    B, stall_iters, eps = 6, 3, torch.finfo(torch.float64).eps
    count, g_ref = torch.zeros(B, dtype=torch.int64), torch.zeros(B, dtype=torch.float64)
    ref_count, ref_g = [0] * B, [0.0] * B
    seen = set()
    for it in range(40):
        J_old = 10 * torch.rand(B, generator=g, dtype=torch.float64)
        noise = torch.rand(B, generator=g) < (0.8 if it % 10 < 6 else 0.0)
        change = torch.where(noise, 0.5 * ROUNDOFF_NOISE * eps * J_old.abs().clamp_min(1.0), 0.1)
        J_new = J_old - change
        accept = torch.rand(B, generator=g) < 0.9
        grad = torch.rand(B, generator=g, dtype=torch.float64) * (0.3 if it % 7 == 0 else 1.0)
        stalled, count, g_ref = stall_update(count, g_ref, accept, J_old, J_new, grad, stall_iters)
        for b in range(B):
            flat = bool(accept[b]) and bool(noise[b])
            ref_count[b] = ref_count[b] + 1 if flat else 0
            if ref_count[b] == 1:
                ref_g[b] = float(grad[b])
            full = ref_count[b] >= stall_iters
            assert bool(stalled[b]) == (full and float(grad[b]) > 0.5 * ref_g[b])
            if full:
                ref_count[b] = 0
            assert int(count[b]) == ref_count[b] and float(g_ref[b]) == ref_g[b]
            seen.add((flat, bool(stalled[b])))
        seen.add(("any flat", bool((accept & noise).any())))
    # both paths ran, and elements stalled and did not
    assert {("any flat", True), ("any flat", False), (True, True), (True, False)} <= seen
