"""compact=True: iterations computed only on the running elements give the same results."""

from __future__ import annotations

import pytest
import torch

import torchslq as ts
from torchslq.systems import DragVehicle
from torchslq.tasks import cartpole_swingup, pendulum_swingup

torch.set_num_threads(1)


def _same(a, b):
    for name in ("x", "u", "cost", "grad_norm", "iterations", "status", "K", "k"):
        torch.testing.assert_close(
            getattr(a, name), getattr(b, name), rtol=0, atol=0, equal_nan=True, msg=name
        )
    for name in ("cost", "grad_norm", "step"):
        torch.testing.assert_close(a.history[name], b.history[name], rtol=0, atol=0, equal_nan=True)


def _same_to_rounding(a, b):
    """The same iterations, statuses and accepted steps; the rest to rounding. The last
    feedforward ``k = -Quu^-1 Qu`` comes from a difference of O(1) terms near the
    solution (``Qu`` about the gradient, below 1e-6), scaled by ``Quu^-1`` (50 here):
    its rounding is absolute, not relative to its small entries, hence its own absolute
    tolerance (1e-9, far below what the solve resolves; a suite run with fresh kernel
    caches once failed 1e-12 on it)."""
    for name in ("iterations", "status"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert torch.equal(a.history["step"], b.history["step"])
    for name in ("x", "u", "cost", "grad_norm", "K", "k"):
        atol = 1e-9 if name == "k" else 1e-12
        torch.testing.assert_close(
            getattr(a, name), getattr(b, name), rtol=1e-9, atol=atol, equal_nan=True, msg=name
        )


@pytest.mark.parametrize(
    "make",
    [
        lambda **kw: ts.SLQ(rollout="closed_loop", max_iter=60, progress=False, **kw),
        lambda **kw: ts.SLQ(line_search="armijo", max_iter=40, progress=False, **kw),
        lambda **kw: ts.ILQR(max_iter=60, progress=False, **kw),
        lambda **kw: ts.ILQR(max_iter=60, progress=False, u_min=-4.0, u_max=4.0, **kw),
        lambda **kw: ts.DDP(max_iter=40, progress=False, **kw),
        # its per-element search range (the last accepted step) is compacted too
        lambda **kw: ts.GradientMethod(
            line_search="armijo", tol=1.0, max_iter=60, progress=False, **kw
        ),
    ],
)
def test_compact_equals_full_batch(make):
    problem, x0 = pendulum_swingup(batch=6, horizon=30, seed=4)
    full = make().solve(problem, x0)
    comp = make(compact=True).solve(problem, x0)
    # the elements finish at different iterations, so the working set really shrinks
    assert len(set(full.iterations.tolist())) > 1
    _same(full, comp)
    if full.active_bounds is not None:
        assert torch.equal(full.active_bounds, comp.active_bounds)


def test_compact_with_a_failing_element():
    problem, x0 = cartpole_swingup(batch=4, seed=1)
    x0 = x0.clone()
    x0[2, 0] = 1e200  # its cost overflows to inf: non-finite from the start, frozen
    full = ts.ILQR(max_iter=30, progress=False).solve(problem, x0)
    comp = ts.ILQR(max_iter=30, progress=False, compact=True).solve(problem, x0)
    assert full.status_names()[2] == "non_finite"
    _same(full, comp)


def _goal_per_element_problem(B: int, width: int | None = None):
    """Cart-pole-free small problem with per-element data: a (B, 1) drag per element and
    a (B, T+1, n) goal per element; with ``width`` the model is a learned MLP instead."""
    torch.manual_seed(0)
    T, n = 15, 2
    x_ref = torch.zeros(B, T + 1, n, dtype=torch.float64)
    x_ref[:, :, 0] = torch.linspace(0.5, 2.0, B, dtype=torch.float64)[:, None]
    cost = ts.QuadraticCost(
        torch.eye(n, dtype=torch.float64), 0.1 * torch.eye(1, dtype=torch.float64), x_ref=x_ref
    )
    if width is None:
        beta = torch.linspace(0.1, 0.9, B, dtype=torch.float64)[:, None]
        model = DragVehicle(beta=beta)
    else:
        net = torch.nn.Sequential(
            torch.nn.Linear(3, width), torch.nn.Tanh(), torch.nn.Linear(width, 2)
        ).double()
        with torch.no_grad():
            for p in net.parameters():
                p.mul_(0.3)
        model = ts.LearnedDynamics(net, 2, 1)
    x0 = 0.3 * torch.randn(B, n, dtype=torch.float64)
    return ts.Problem(model, cost, T), x0


@pytest.mark.parametrize("width", [None, 8])
@pytest.mark.parametrize(
    "make",
    [
        lambda **kw: ts.SLQ(max_iter=60, progress=False, **kw),
        lambda **kw: ts.ILQR(max_iter=60, progress=False, **kw),
        lambda **kw: ts.DDP(max_iter=40, progress=False, **kw),
    ],
)
def test_compact_with_per_element_problem_data(make, width):
    """A goal per element (B, T+1, n) and a drag per element (B, 1) follow the running
    subset; a learned model whose layer is as wide as the batch (8) is not taken for
    per-element data. Each element equals its own solve as a batch of one."""
    B = 8
    problem, x0 = _goal_per_element_problem(B, width)
    assert problem.per_element_tensor(B) == ("cost.x_ref" if width else "dynamics.beta")
    comp = make(compact=True).solve(problem, x0)
    full = make().solve(problem, x0)
    assert len(set(full.iterations.tolist())) > 1  # the working set shrinks
    assert comp.status_names() == full.status_names()
    torch.testing.assert_close(comp.u, full.u, rtol=0, atol=1e-10)
    for i in (0, 5):
        one = make().solve(problem.take(torch.tensor([i]), B), x0[i : i + 1])
        torch.testing.assert_close(comp.u[i : i + 1], one.u, rtol=0, atol=1e-6)
        torch.testing.assert_close(comp.cost[i : i + 1], one.cost, rtol=1e-10, atol=0)


def test_problem_take_indexes_only_per_element_tensors():
    B = 4
    problem, _ = _goal_per_element_problem(B, width=B)
    idx = torch.tensor([3, 1])
    sub = problem.take(idx, B)
    assert torch.equal(sub.cost.x_ref, problem.cost.x_ref[idx])
    assert sub.dynamics.net is problem.dynamics.net  # the network's weights are shared
    assert problem.cost.x_ref.shape[0] == B  # the original is unchanged
    shared, _ = _goal_per_element_problem(1)
    assert shared.take(torch.tensor([0]), 1) is shared


@pytest.mark.parametrize("module", ["ilqr", "slq"])
def test_finished_elements_do_not_hold_up_the_line_search(module, monkeypatch):
    """Without compaction, finished elements ride along in the batch. A converged
    element's trial costs sit at round-off level (``J(a) = J0 + 1 ulp`` fails Armijo at
    every step size), which made every later line search run its second pass of step
    sizes (unicycle B=512: 195 instead of 100 trial rollouts in 100 iterations). The
    search is told which elements are running: an element is active in a prefix of the
    searches (never again once finished) at least as long as its accepted steps."""
    import importlib

    mod = importlib.import_module("torchslq.solvers.descent")  # one line search serves both
    seen = []
    orig = mod.armijo_search

    def spy(*args, **kwargs):
        seen.append(kwargs.get("active"))
        return orig(*args, **kwargs)

    monkeypatch.setattr(mod, "armijo_search", spy)
    problem, x0 = pendulum_swingup(batch=6, horizon=30, seed=4)
    if module == "ilqr":
        solver = ts.ILQR(max_iter=60, progress=False)
    else:
        solver = ts.SLQ(rollout="closed_loop", line_search="armijo", max_iter=60, progress=False)
    res = solver.solve(problem, x0)
    assert seen and all(a is not None for a in seen)
    act = torch.stack(seen)  # (searches, B)
    n_active = act.sum(0)
    for b in range(act.shape[1]):
        assert bool(act[: n_active[b], b].all()) and not bool(act[n_active[b] :, b].any())
    assert bool((n_active >= res.iterations).all())
    assert int(n_active.min()) < act.shape[0]  # someone finished before the last search


def _batched_search_only(monkeypatch) -> None:
    """The batched search on torch ops (armijo_search) for every line search, not the
    fused kernel the CPU takes with a compiled step and a quadratic cost (checked
    against armijo_search in test_fused_line_search.py)."""
    from torchslq.solvers.descent import LineSearch

    monkeypatch.setattr(LineSearch, "_fused_armijo", lambda self, *args: None)


@pytest.mark.codegen
@pytest.mark.parametrize("compact", [False, True])
@pytest.mark.parametrize("solver", ["ddp", "ilqr-bounds", "slq"])
def test_skipping_settled_trials_changes_no_solve(solver, compact, monkeypatch):
    """The solvers hand armijo_search skip_settled=True (the trials of elements that
    accepted a step, or finished, are not rolled out): the same solves to the last bit
    as evaluating every trial. The cart-pole has a compiled RK4 step, so the rollout
    kernel really skips rows."""
    import sys

    _batched_search_only(monkeypatch)
    problem, x0 = cartpole_swingup(batch=6, horizon=25, seed=3)
    assert problem.dynamics.compiled_step() is not None
    make = {
        "ddp": lambda: ts.DDP(max_iter=40, progress=False, compact=compact),
        "ilqr-bounds": lambda: ts.ILQR(
            max_iter=40, progress=False, compact=compact, u_min=-3.0, u_max=3.0
        ),
        "slq": lambda: ts.SLQ(
            line_search="armijo", rollout="closed_loop", max_iter=40, progress=False,
            compact=compact,
        ),
    }[solver]  # fmt: skip
    fast = make().solve(problem, x0)
    module = sys.modules["torchslq.solvers.descent"]  # one line search serves all three
    real = module.armijo_search
    seen = []

    def every_trial(*a, **kw):
        seen.append(kw.pop("skip_settled"))
        return real(*a, **kw, skip_settled=False)

    monkeypatch.setattr(module, "armijo_search", every_trial)
    ref = make().solve(problem, x0)
    assert seen and all(seen)
    assert len(set(ref.iterations.tolist())) > 1  # finished elements during the solve
    _same(fast, ref)


@pytest.mark.parametrize("solver", ["ddp", "ilqr-bounds", "slq"])
def test_armijo_passes_change_no_solve(solver, monkeypatch):
    """How many trials each pass rolls out (``armijo_passes``) changes which trials are
    rolled out, not the solve: for the CPU default ((1, 3), or (2, 2) while most elements
    took short steps), all at once after 4 (the other devices' default) and one at a
    time, the same iterations, statuses and accepted steps, the trajectories to rounding
    (run alone the solves agree to the last bit; in a full suite run with fresh kernel
    caches the DDP solves once differed in the last bits); the option reaches
    armijo_search."""
    import sys

    _batched_search_only(monkeypatch)
    problem, x0 = cartpole_swingup(batch=6, horizon=25, seed=3)
    make = {
        "ddp": lambda **kw: ts.DDP(max_iter=40, progress=False, **kw),
        "ilqr-bounds": lambda **kw: ts.ILQR(
            max_iter=40, progress=False, u_min=-3.0, u_max=3.0, **kw
        ),
        "slq": lambda **kw: ts.SLQ(
            line_search="armijo", rollout="closed_loop", max_iter=40, progress=False, **kw
        ),
    }[solver]  # fmt: skip
    module = sys.modules["torchslq.solvers.descent"]  # one line search serves all three
    real = module.armijo_search
    seen = []

    def spy(*a, **kw):
        seen.append((kw["first_trials"], kw["pass_size"]))
        return real(*a, **kw)

    monkeypatch.setattr(module, "armijo_search", spy)
    default = make().solve(problem, x0)
    assert (1, 3) in seen and set(seen) <= {(1, 3), (2, 2)}
    for passes in [(4, None), (1, 1)]:
        seen.clear()
        _same_to_rounding(make(armijo_passes=passes).solve(problem, x0), default)
        assert set(seen) == {passes}


def test_armijo_passes_default_by_device_and_validation():
    search = ts.ILQR().rule().search
    assert search.pass_sizes(torch.device("cpu")) == (1, 3)
    assert search.pass_sizes(torch.device("meta")) == (4, None)
    # on the CPU two, then two while most running elements' last step was short
    running = torch.tensor([True, True, True, False])
    short = torch.tensor([0.5, 0.25, 1.0, 0.5])
    assert search.pass_sizes(torch.device("cpu"), short, running) == (2, 2)
    full = torch.tensor([1.0, 0.5, 1.0, 0.5])
    assert search.pass_sizes(torch.device("cpu"), full, running) == (1, 3)
    assert search.pass_sizes(torch.device("meta"), short, running) == (4, None)
    search = ts.DDP(armijo_passes=[2, None]).rule().search
    assert search.pass_sizes(torch.device("cpu")) == (2, None)
    for bad in [(0, 3), (1, 0), (1.0, 3), 3, (1, 2, 3), (True, 3)]:
        with pytest.raises(ValueError, match="armijo_passes"):
            ts.SLQ(armijo_passes=bad)


@pytest.mark.parametrize("make", [ts.SLQ, ts.ILQR])
def test_compact_with_every_element_failing_from_the_start(make):
    """A batch whose every element is non-finite from the start (a B=1 MPC loop whose
    state entered a region where the model returns NaN) ends with status non_finite and
    a one-column history, as without compaction (it used to raise on an empty history)."""
    problem, x0 = pendulum_swingup(batch=3, horizon=10, seed=0)
    x0 = x0.clone()
    x0[:, 0] = 1e200
    comp = make(compact=True, progress=False).solve(problem, x0)
    full = make(progress=False).solve(problem, x0)
    assert comp.status_names() == ["non_finite"] * 3 == full.status_names()
    assert comp.history["cost"].shape == (3, 1) and torch.equal(comp.iterations, full.iterations)


def test_the_working_set_is_taken_once_per_set(monkeypatch):
    """The loop narrows the state and the problem when the running set shrinks, not at
    every iteration (each take is an index op per state field): one take per set, the
    same solve as the full batch."""
    from torchslq.solvers.core import ElementState

    problem, x0 = pendulum_swingup(batch=6, horizon=30, seed=4)
    full = ts.ILQR(max_iter=60, progress=False).solve(problem, x0)
    sizes, problem_takes = [], []
    take, problem_take = ElementState.take, type(problem).take

    def counted(self, idx):
        if idx is not None:
            sizes.append(idx.numel())
        return take(self, idx)

    def counted_problem(self, idx, batch_size):
        problem_takes.append(idx.numel())
        return problem_take(self, idx, batch_size)

    monkeypatch.setattr(ElementState, "take", counted)
    monkeypatch.setattr(type(problem), "take", counted_problem)
    comp = ts.ILQR(max_iter=60, progress=False, compact=True).solve(problem, x0)
    _same(full, comp)
    ends = len(set(full.iterations.tolist()))  # the iterations at which elements end
    assert 1 < len(sizes) <= ends and len(set(sizes)) == len(sizes)
    assert problem_takes == sizes
    assert int(full.iterations.max()) > 2 * len(sizes)  # many iterations per set


def test_put_keeps_the_working_sets_shared_fields():
    """A field that is not per element (e.g. an accumulated time) takes the working
    set's latest value when the set is written back, and the batched fields are
    written at their rows only."""
    from dataclasses import dataclass, replace

    from torchslq.solvers.core import ElementState, shared

    @dataclass(frozen=True)
    class Timed(ElementState):
        seconds: torch.Tensor = shared(None)

    x, u, J = torch.zeros(4, 3, 2), torch.zeros(4, 2, 1), torch.arange(4.0)
    full = Timed(x=x, u=u, J=J, seconds=torch.tensor(1.0))
    idx = torch.tensor([1, 3])
    part = full.take(idx)
    assert torch.equal(part.J, torch.tensor([1.0, 3.0])) and part.seconds is full.seconds
    part = replace(part, J=part.J + 10, seconds=torch.tensor(2.5))
    back = full.put(idx, part)
    assert torch.equal(back.J, torch.tensor([0.0, 11.0, 2.0, 13.0]))
    assert float(back.seconds) == 2.5
