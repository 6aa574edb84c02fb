"""Batched line searches: many step sizes per element in one rollout.

Both searches take ``evaluate(alphas) -> J`` where ``alphas`` is ``(Na, B)`` (a set of
candidate steps for every element, evaluated as an extra batch dimension) and return a
step per element. Non-finite trial costs count as +inf, so a candidate that blows up is
simply never chosen.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from torch import Tensor

from .stopping import ROUNDOFF_NOISE, roundoff_tolerance

__all__ = ["armijo_search", "exact_search", "EXACT_GRID", "TrialRecorder"]

# Candidate steps of the exact search: dense near 1 (the Gauss-Newton step), then halving.
EXACT_GRID = (1.0, 0.85, 0.7, 0.5, 0.35, 0.25) + tuple(0.5**k for k in range(3, 16))


class TrialRecorder:
    """Keeps the trajectories of every trial step so the chosen one need not be re-rolled.

    ``record(alphas (Na, B), *tensors (Na, B, ...))`` is called by the evaluator;
    ``select(alpha (B,))`` returns, per element, the recorded tensors of the trial whose
    step equals ``alpha`` (elements without a matching trial, e.g. ``alpha = 0`` after a
    failed search, get the first trial's values; callers mask those out).
    """

    def __init__(self) -> None:
        self._alphas: list[Tensor] = []
        self._tensors: list[tuple[Tensor, ...]] = []

    def record(self, alphas: Tensor, *tensors: Tensor) -> None:
        self._alphas.append(alphas)
        self._tensors.append(tensors)

    def select(self, alpha: Tensor) -> tuple[Tensor, ...]:
        # per recorded pass, without concatenating the passes' trajectories (a copy of
        # every trial to keep one per element): the first pass with a matching step wins
        out: list[Tensor] = []
        have = None
        for alphas, tensors in zip(self._alphas, self._tensors, strict=True):
            hit = alphas == alpha.unsqueeze(0)  # (Na, B)
            idx = torch.argmax(hit.to(torch.int8), dim=0)  # (B,) first match, else 0
            picked = []
            for t in tensors:
                ix = idx.reshape(1, -1, *([1] * (t.ndim - 2))).expand(1, *t.shape[1:])
                picked.append(t.gather(0, ix)[0])
            found = hit.any(dim=0)
            if have is None:
                out, have = picked, found
                continue
            new = found & ~have
            out = [
                torch.where(new.reshape(-1, *([1] * (o.ndim - 1))), p, o)
                for o, p in zip(out, picked, strict=True)
            ]
            have = have | found
        return tuple(out)


def _finite(J: Tensor) -> Tensor:
    return torch.nan_to_num(J, nan=float("inf"), posinf=float("inf"))


def _within_roundoff(J1: Tensor, J0: Tensor, slope: Tensor | None, noise: float) -> Tensor:
    """True where the predicted decrease ``|slope|`` is below the rounding noise of ``J``
    and the full step ``J(1)`` is no worse than ``J0`` up to that noise.

    Near a minimum of a badly scaled problem the cost change of a (good) Gauss-Newton
    step can be smaller than the rounding error of evaluating ``J``; no comparison of
    costs can then tell a good step from a bad one, so the full step is taken instead of
    declaring failure (the gradient test still decides convergence).
    """
    if slope is None or noise <= 0:
        return torch.zeros_like(J0, dtype=torch.bool)
    tol = roundoff_tolerance(J0, noise)
    return (slope.abs() <= tol) & (J1 <= J0 + tol)


@functools.lru_cache(maxsize=32)
def armijo_steps(
    alpha0: float, beta: float, max_backtracks: int, dtype: torch.dtype, device: torch.device
) -> Tensor:
    """The trial steps ``alpha0 beta^j`` (``j < max_backtracks``) of :func:`armijo_search`
    and of the fused search (:class:`torchslq.solvers.descent.LineSearch`), built once
    per setting; read-only."""
    return alpha0 * beta ** torch.arange(max_backtracks, dtype=dtype, device=device)


def armijo_search(
    evaluate: Callable[[Tensor], Tensor],
    J0: Tensor,
    slope: Tensor,
    *,
    c1: float = 1e-4,
    beta: float = 0.5,
    max_backtracks: int = 20,
    alpha0: float = 1.0,
    roundoff: float = ROUNDOFF_NOISE,
    curvature: Tensor | None = None,
    first_trials: int | None = 4,
    pass_size: int | None = None,
    active: Tensor | None = None,
    skip_settled: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Backtracking on sufficient decrease ``J(a) <= J0 + c1 dJ(a)`` (Armijo).

    The model decrease is ``dJ(a) = a slope`` (first order), or with ``curvature`` given
    ``dJ(a) = a slope + a^2/2 curvature`` (the expected improvement of iLQR/DDP).

    The steps ``alpha0 * beta^j`` (``j < max_backtracks``) are tried as an extra batch
    dimension; the result is the largest that satisfies the condition, i.e. what serial
    backtracking would return. With ``first_trials = k`` the ``k`` largest are tried
    first and the rest (all at once, or ``pass_size`` at a time) only while some
    element has accepted none (one host sync per pass); the result is the same as
    trying all at once, at a fraction of the trial rollouts when (as near convergence)
    the first steps are accepted. None tries all at once. Elements outside ``active``
    (``(B,)`` bool, e.g. finished ones) do not hold up the next pass.

    With ``skip_settled`` the trials that cannot change the result are handed to
    ``evaluate`` as NaN steps (it must then return a non-finite or any cost there; a
    closed-loop rollout with a model's compiled step skips such rows): every step of an
    element outside ``active``, and in a later pass every step of an element that has
    already accepted one. Steps and costs of the elements in ``active`` are the same as
    without it; elements outside get ``alpha = 0`` and ``ok = False`` (callers discard
    them). Later passes then cost in proportion to the elements still searching.

    Args:
        J0: ``(B,)`` current cost; slope ``(B,)`` directional derivative (< 0).
        roundoff: when ``|slope| <= roundoff * eps * |J0|`` the decrease cannot be
            resolved in floating point and the full step is accepted if ``J(alpha0)`` is
            within that noise of ``J0`` (0 disables this).

    Returns:
        ``(alpha (B,), J (B,), ok (B,) bool)``; ``alpha = 0`` where no step was accepted.
    """
    grid = armijo_steps(alpha0, beta, max_backtracks, J0.dtype, J0.device)
    sizes = [max_backtracks]
    if first_trials is not None:
        sizes = [max(1, min(first_trials, max_backtracks))]
        rest = max_backtracks - sizes[0]
        while rest > 0:
            sizes.append(rest if pass_size is None else min(pass_size, rest))
            rest -= sizes[-1]
    Js, oks = [], []
    found = torch.zeros_like(J0, dtype=torch.bool)
    searching = active if skip_settled else None
    for g in torch.split(grid, sizes):
        alphas = g.unsqueeze(-1).expand(-1, J0.shape[0])
        if skip_settled:
            if searching is None:
                searching = ~found
            alphas = torch.where(searching, alphas, torch.full_like(alphas, float("nan")))
        J = _finite(evaluate(alphas))
        model = alphas * slope
        if curvature is not None:
            model = model + 0.5 * alphas * alphas * curvature
        Js.append(J)
        oks.append(J <= J0 + c1 * model)
        found = found | oks[-1].any(dim=0)
        if len(Js) < len(sizes):
            done = found if active is None else found | ~active
            if bool(done.all()):
                break  # every element accepted a step among the largest ones
            searching = ~done
    J, ok = torch.cat(Js, dim=0), torch.cat(oks, dim=0)
    first = torch.argmax(ok.to(torch.int8), dim=0)  # first True (largest alpha)
    found = ok.any(dim=0)
    alpha = torch.where(found, grid[first], torch.zeros_like(J0))
    Jbest = torch.where(found, J.gather(0, first.unsqueeze(0))[0], J0)
    flat = ~found & _within_roundoff(J[0], J0, slope, roundoff)
    alpha = torch.where(flat, grid[0], alpha)
    Jbest = torch.where(flat, J[0], Jbest)
    return alpha, Jbest, found | flat


def exact_search(
    evaluate: Callable[[Tensor], Tensor],
    J0: Tensor,
    *,
    grid: tuple[float, ...] = EXACT_GRID,
    refine: bool = True,
    slope: Tensor | None = None,
    roundoff: float = ROUNDOFF_NOISE,
) -> tuple[Tensor, Tensor, Tensor]:
    """Approximately minimise ``J(a)`` over ``a`` in ``(0, 1]``.

    Evaluates a grid of steps at once, then refines around the best grid point with one
    quadratic fit through it and its two neighbours (clamped to the bracket), keeping
    whichever of the grid point and the fitted point is lower.

    With ``slope`` (the directional derivative) given, a full step is accepted where the
    predicted decrease is below rounding noise (see :func:`armijo_search`).

    Returns:
        ``(alpha (B,), J (B,), ok (B,) bool)``; ``ok`` is False (and ``alpha = 0``) when
        no tried step lowers the cost below ``J0``.
    """
    g = torch.tensor(sorted(grid), dtype=J0.dtype, device=J0.device)  # ascending
    Na, Bsz = g.shape[0], J0.shape[0]
    J = _finite(evaluate(g.unsqueeze(-1).expand(Na, Bsz)))  # (Na, B)
    i = torch.argmin(J, dim=0)  # (B,)
    a_best = g[i]
    J_best = J.gather(0, i.unsqueeze(0))[0]
    if refine and Na >= 3:
        # bracket (lo, mid, hi) in grid order; at the ends use the nearest three points
        mid = i.clamp(1, Na - 2)
        lo, hi = mid - 1, mid + 1
        a0, a1, a2 = g[lo], g[mid], g[hi]
        J0_, J1_, J2_ = (J.gather(0, j.unsqueeze(0))[0] for j in (lo, mid, hi))
        # vertex of the parabola through three points (divided differences)
        d01 = (J1_ - J0_) / (a1 - a0)
        d12 = (J2_ - J1_) / (a2 - a1)
        curv = (d12 - d01) / (a2 - a0)
        vertex = 0.5 * (a0 + a1) - d01 / (2.0 * curv)
        usable = torch.isfinite(vertex) & (curv > 0)
        a_fit = torch.where(usable, vertex, a_best).clamp(min=a0, max=a2).clamp(max=1.0)
        J_fit = _finite(evaluate(a_fit.unsqueeze(0)))[0]
        better = J_fit < J_best
        a_best = torch.where(better, a_fit, a_best)
        J_best = torch.where(better, J_fit, J_best)
    ok = J_best < J0
    flat = ~ok & _within_roundoff(J[-1], J0, slope, roundoff)
    a_best = torch.where(flat, g[-1], a_best)
    J_best = torch.where(flat, J[-1], J_best)
    ok = ok | flat
    alpha = torch.where(ok, a_best, torch.zeros_like(a_best))
    return alpha, torch.where(ok, J_best, J0), ok
