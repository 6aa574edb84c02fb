"""Staged Armijo search (a few large steps first) returns exactly what trying every step
at once returns, and skips the small steps when the large ones are accepted."""

from __future__ import annotations

import torch

from torchslq.solvers.line_search import armijo_search


def _quadratic_evaluator(scale: torch.Tensor, calls: list[int]):
    # J(a) = J0 + slope a + 1/2 scale a^2 per element: elements with a large scale need
    # small steps; one element is non-finite for every step
    def evaluate(alphas: torch.Tensor) -> torch.Tensor:
        calls.append(alphas.shape[0])
        J = 10.0 - alphas + 0.5 * scale * alphas**2
        J[:, -1] = float("nan")
        return J

    return evaluate


def test_staged_search_equals_all_at_once():
    gen = torch.Generator().manual_seed(0)
    scale = torch.cat(
        [
            torch.rand(20, generator=gen, dtype=torch.float64) * 2,
            torch.tensor([50.0, 3000.0, 1.0], dtype=torch.float64),
        ]
    )
    J0 = torch.full_like(scale, 10.0)
    slope = -torch.ones_like(scale)
    ref_calls: list[int] = []
    ref = armijo_search(_quadratic_evaluator(scale, ref_calls), J0, slope, first_trials=None)
    assert ref_calls == [20]
    for k in (1, 2, 4, 19, 20, 50):
        calls: list[int] = []
        out = armijo_search(_quadratic_evaluator(scale, calls), J0, slope, first_trials=k)
        for a, b in zip(out, ref, strict=True):
            assert torch.equal(a, b)
        assert sum(calls) == 20 or k >= 20  # the small-step elements need the rest
    # the hard elements really needed small steps, the non-finite one failed
    alpha, _, ok = ref
    assert float(alpha[-2]) < 1e-3 and not bool(ok[-1]) and float(alpha[-1]) == 0.0


def test_staged_search_skips_small_steps_when_large_ones_are_accepted():
    scale = torch.tensor([0.5, 1.0, 1.5], dtype=torch.float64)
    calls: list[int] = []

    def evaluate(alphas):
        calls.append(alphas.shape[0])
        return 10.0 - alphas + 0.5 * scale * alphas**2

    J0, slope = torch.full_like(scale, 10.0), -torch.ones_like(scale)
    alpha, J, ok = armijo_search(evaluate, J0, slope, first_trials=4)
    assert calls == [4] and bool(ok.all())
    ref = armijo_search(evaluate, J0, slope, first_trials=None)
    assert torch.equal(alpha, ref[0]) and torch.equal(J, ref[1])


def test_passes_of_fixed_size_and_inactive_elements():
    scale = torch.tensor([0.5, 40.0, 1.0], dtype=torch.float64)
    J0, slope = torch.full_like(scale, 10.0), -torch.ones_like(scale)
    calls: list[int] = []
    ref = armijo_search(_quadratic_evaluator(scale, []), J0, slope, first_trials=None)
    out = armijo_search(_quadratic_evaluator(scale, calls), J0, slope, first_trials=2, pass_size=3)
    # element 1 needs alpha <= 1/20 (j >= 5): passes of 2, 3, 3 (the last one is NaN)
    assert calls == [2, 3, 3, 3, 3, 3, 3]  # the non-finite last element never accepts
    for a, b in zip(out, ref, strict=True):
        assert torch.equal(a, b)
    # with the non-finite element inactive the search stops once element 1 has a step
    calls.clear()
    active = torch.tensor([True, True, False])
    out = armijo_search(
        _quadratic_evaluator(scale, calls), J0, slope, first_trials=2, pass_size=3, active=active
    )
    assert calls == [2, 3, 3]
    assert torch.equal(out[0][:2], ref[0][:2])


def test_skip_settled_hands_only_the_needed_trials_to_evaluate():
    """With skip_settled the steps of settled elements arrive as NaN: the first pass for
    every active element, a later pass only for the elements that have accepted no step
    yet; the result for the active elements is the same as trying everything."""
    scale = torch.tensor([0.5, 40.0, 1.0, 3000.0, 0.7], dtype=torch.float64)
    J0, slope = torch.full_like(scale, 10.0), -torch.ones_like(scale)
    active = torch.tensor([True, True, True, True, False])
    seen: list[torch.Tensor] = []

    def evaluate(alphas):
        seen.append(alphas.clone())
        return 10.0 - alphas + 0.5 * scale * alphas**2

    out = armijo_search(evaluate, J0, slope, first_trials=2, pass_size=3, active=active,
                        skip_settled=True)  # fmt: skip
    ref = armijo_search(
        _quadratic_evaluator(scale, []), J0, slope, first_trials=None, active=active
    )
    for a, b in zip(out, ref, strict=True):
        assert torch.equal(a[:3], b[:3])
    # element 3 needs a step <= 1/3000 (j >= 12): it alone is evaluated after the first
    # pass, element 1 (j = 5) until it accepts, the inactive element never
    evaluated = [(~torch.isnan(a)).any(dim=0) for a in seen]
    assert evaluated[0].tolist() == [True, True, True, True, False]
    assert evaluated[1].tolist() == [False, True, False, True, False]
    assert evaluated[2].tolist() == [False, True, False, True, False]
    assert len(evaluated) > 3 and all(
        e.tolist() == [False, False, False, True, False] for e in evaluated[3:]
    )
    assert float(out[0][3]) == float(ref[0][3]) > 0
    assert float(out[0][4]) == 0.0 and not bool(out[2][4])


def test_trial_recorder_selects_each_elements_first_matching_trial():
    """TrialRecorder.select over several recorded passes == a per-element loop: the
    trajectories of the first trial (in recording order) whose step equals the chosen
    one, the very first trial where none does (alpha = 0 after a failed search)."""
    from torchslq.solvers.line_search import TrialRecorder

    g = torch.Generator().manual_seed(1)
    B = 6
    rec = TrialRecorder()
    passes = []
    for Na, steps in ((4, [1.0, 0.5, 0.25, 0.125]), (3, [0.0625, 0.03125, 0.5])):
        alphas = torch.tensor(steps, dtype=torch.float64)[:, None].expand(Na, B).clone()
        alphas[1, 2] = float("nan")  # a skipped trial
        x = torch.randn(Na, B, 5, 2, generator=g, dtype=torch.float64)
        u = torch.randn(Na, B, 4, generator=g, dtype=torch.float64)
        rec.record(alphas, x, u)
        passes.append((alphas, x, u))
    chosen = torch.tensor([1.0, 0.25, 0.5, 0.0625, 0.0, 0.5], dtype=torch.float64)
    xs, us = rec.select(chosen)
    for b in range(B):
        ref = None
        for alphas, x, u in passes:
            for j in range(alphas.shape[0]):
                if ref is None and float(alphas[j, b]) == float(chosen[b]):
                    ref = (x[j, b], u[j, b])
        if ref is None:
            ref = (passes[0][1][0, b], passes[0][2][0, b])
        assert torch.equal(xs[b], ref[0]) and torch.equal(us[b], ref[1])
