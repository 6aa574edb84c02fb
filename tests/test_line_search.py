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
