"""The Levenberg-Marquardt regularisation of ``Quu`` and its restarts, written once.

Tassa, Erez & Todorov (2012), Section II.F: each batch element carries a
regularisation ``mu`` (added to ``Quu`` as ``mu I``) and a schedule factor ``delta``;

* increase (a failed factorisation, or a failed line search):
  ``delta := max(f, delta f)``, ``mu := max(mu_floor, mu delta)``;
* decrease (an accepted step): ``delta := min(1/f, delta / f)``, ``mu := mu delta``,
  and 0 once below ``mu_min``.

:class:`RegularizationSchedule` holds the constants and both updates (a solver calls
:meth:`~RegularizationSchedule.increase` / :meth:`~RegularizationSchedule.decrease`
after its line search); :class:`Restarts` hands the schedule and the elements' current
``delta`` to :func:`torchslq.lq.riccati_backward`, which then repeats the pass of every
failed element with increased ``mu`` until it succeeds, with the same meaning on every
backend (the compiled CPU kernel restarts inside its loop, the torch path repeats the
failing rows side by side; see :func:`~torchslq.lq.riccati_backward`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["MAX_RESTARTS", "RegularizationSchedule", "Restarts"]

# restarts of a failed Riccati pass per call (Tassa et al.'s regularisation)
MAX_RESTARTS = 8


def _floor(reg_min: float) -> float:
    """The smallest ``mu`` an increase gives: ``reg_min``, or 1e-6 when that is zero (a
    zero ``mu`` cannot grow by scaling)."""
    return float(reg_min) if reg_min > 0 else 1e-6


@dataclass(frozen=True)
class RegularizationSchedule:
    """Tassa et al.'s (2012) per-element schedule of the regularisation ``mu`` on ``Quu``.

    Attributes:
        factor: the schedule's factor ``f > 1``.
        reg_min: ``mu_min``: a decrease below it gives 0; an increase gives at least
            :attr:`floor`.
        reg_max: ``mu_max``: an element whose ``mu`` exceeds it is not restarted again
            (a solver then stops it).
        max_restarts: the most restarts of one element in one :func:`riccati_backward`.
    """

    factor: float = 2.0
    reg_min: float = 1e-6
    reg_max: float = 1e10
    max_restarts: int = MAX_RESTARTS

    def __post_init__(self):
        if not (self.factor > 1 and 0 <= self.reg_min <= self.reg_max and self.max_restarts >= 0):
            raise ValueError(
                "need factor > 1, 0 <= reg_min <= reg_max and max_restarts >= 0, got "
                f"{self.factor!r}, {self.reg_min!r}, {self.reg_max!r}, {self.max_restarts!r}"
            )

    @property
    def floor(self) -> float:
        """The smallest ``mu`` an increase gives: ``reg_min``, or 1e-6 when that is zero
        (a zero ``mu`` cannot grow by scaling)."""
        return _floor(self.reg_min)

    def increase(
        self, reg: Tensor, delta: Tensor, mask: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``(mu, delta)`` after one increase (``delta := max(f, delta f)``,
        ``mu := max(floor, mu delta)``), where ``mask`` (all elements when None)."""
        f = float(self.factor)
        d = torch.clamp_min(delta * f, f)
        mu = torch.clamp_min(reg * d, self.floor)
        if mask is None:
            return mu, d
        return torch.where(mask, mu, reg), torch.where(mask, d, delta)

    def decrease(
        self, reg: Tensor, delta: Tensor, mask: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """``(mu, delta)`` after one decrease (``delta := min(1/f, delta/f)``,
        ``mu := mu delta``, 0 below ``reg_min``), where ``mask`` (all when None)."""
        f = float(self.factor)
        d = torch.clamp_max(delta / f, 1.0 / f)
        mu = reg * d
        mu = torch.where(mu < self.reg_min, torch.zeros_like(mu), mu)
        if mask is None:
            return mu, d
        return torch.where(mask, mu, reg), torch.where(mask, d, delta)

    def restarts(self, delta: Tensor | None = None, allowed: Tensor | None = None) -> Restarts:
        """The :class:`Restarts` argument of :func:`riccati_backward` for elements with
        schedule factors ``delta`` (``(B,)``; None: ones) of which ``allowed`` (``(B,)``
        bool; None: all) may be restarted."""
        return Restarts(
            delta, allowed, float(self.factor), self.floor, float(self.reg_max), self.max_restarts
        )


@dataclass(frozen=True)
class Restarts:
    """Restarts of failed elements inside :func:`riccati_backward` (Tassa et al.'s
    schedule, :class:`RegularizationSchedule`); build it with
    :meth:`RegularizationSchedule.restarts`.

    An ``allowed`` element whose pass fails (``Quu + mu I`` not positive definite, or
    non-finite gains) repeats it with ``delta := max(factor, delta factor)``,
    ``mu := max(floor, mu delta)``, until it succeeds, ``mu > reg_max`` (that pass is
    still made) or ``max_restarts`` restarts were made.

    Attributes:
        delta: ``(B,)`` the elements' current schedule factors (None: ones).
        allowed: ``(B,)`` bool, the elements that may be restarted (None: all), e.g. the
            ones still iterating.
        factor, floor, reg_max, max_restarts: the schedule (``floor``: the smallest
            ``mu`` an increase gives, > 0).
    """

    delta: Tensor | None = None
    allowed: Tensor | None = None
    factor: float = 2.0
    floor: float = 1e-6
    reg_max: float = 1e10
    max_restarts: int = MAX_RESTARTS

    @property
    def options(self) -> tuple[float, float, float, int]:
        """``(factor, floor, reg_max, max_restarts)`` as plain numbers (the compiled
        kernel's restart options)."""
        return float(self.factor), _floor(self.floor), float(self.reg_max), int(self.max_restarts)

    @property
    def schedule(self) -> RegularizationSchedule:
        """The schedule of the increases (its ``reg_min`` is :attr:`floor`)."""
        return RegularizationSchedule(
            float(self.factor), float(self.floor), float(self.reg_max), int(self.max_restarts)
        )
