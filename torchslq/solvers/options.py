"""Options of the solvers: frozen dataclasses, validated on construction.

One options object per solver, recorded whole in ``result.options`` and the TensorBoard
hparams. A solver never changes its options; :meth:`Solver.with_options` returns a new
solver. The same concept has the same name in every solver (e.g. ``armijo_passes``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import torch

__all__ = [
    "DDPOptions",
    "DescentOptions",
    "GradientOptions",
    "ILQROptions",
    "SLQOptions",
    "check_choice",
    "check_int",
    "check_real",
    "options_record",
]


def check_int(name: str, v: Any, lo: int) -> None:
    """``v`` is an int (not a bool) ``>= lo``, or ValueError naming ``name``."""
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        what = "non-negative" if lo == 0 else f">= {lo}"
        raise ValueError(f"{name} must be an int {what}, got {v!r}")


def check_real(
    name: str,
    v: Any,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_closed: bool = False,
    hi_closed: bool = False,
) -> None:
    """``v`` is a real number in the interval given (open ends unless ``*_closed``), or
    TypeError / ValueError naming ``name``."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise TypeError(f"{name} must be a number, got {type(v).__name__}")
    ok = v == v  # not NaN
    if lo is not None:
        ok = ok and (v >= lo if lo_closed else v > lo)
    if hi is not None:
        ok = ok and (v <= hi if hi_closed else v < hi)
    if not ok:
        left = "-inf" if lo is None else f"{lo}"
        right = "inf" if hi is None else f"{hi}"
        interval = f"{'[' if lo_closed else '('}{left}, {right}{']' if hi_closed else ')'}"
        raise ValueError(f"{name} must be in {interval}, got {v!r}")


def check_choice(name: str, v: Any, choices: tuple) -> None:
    if v not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {v!r}")


def check_passes(passes: Any) -> tuple[int, int | None] | None:
    """``armijo_passes`` as a ``(first, then)`` tuple of positive ints (``then`` may be
    None), None, or ValueError."""
    if passes is None:
        return None

    def positive_int(v) -> bool:
        return isinstance(v, int) and not isinstance(v, bool) and v >= 1

    ok = isinstance(passes, (tuple, list)) and len(passes) == 2
    if ok and positive_int(passes[0]) and (passes[1] is None or positive_int(passes[1])):
        return (passes[0], passes[1])
    raise ValueError(
        f"armijo_passes must be (first, then) with positive ints (then may be None), got {passes!r}"
    )


def options_record(name: str, options: Any) -> dict[str, Any]:
    """``{"solver": name, **options}`` with tensors kept as they are (for ``result.options``);
    modules (the ``constraints``) as their description, so that a result can be saved and
    loaded with tensors only."""

    def entry(v: Any) -> Any:
        return repr(v) if isinstance(v, torch.nn.Module) else v

    return {"solver": name, **{f.name: entry(getattr(options, f.name)) for f in fields(options)}}


def loggable(record: dict[str, Any]) -> dict[str, Any]:
    """``record`` with tensors as strings (for the TensorBoard text and hparams)."""
    return {k: str(v) if torch.is_tensor(v) else v for k, v in record.items()}


_STOPS = ("grad", "step", "either", "both")
_LINE_SEARCHES = ("exact", "armijo")
_ROLLOUTS = ("open_loop", "closed_loop")


@dataclass(frozen=True)
class DescentOptions:
    """Options shared by the descent solvers (SLQ, ILQR, DDP, GradientMethod); see
    :class:`torchslq.SLQ` for their meaning."""

    max_iter: int = 100
    tol: float = 1e-6
    stop: str = "grad"
    step_tol: float | None = None
    rtol: float = 0.0
    stall_iters: int = 10
    armijo_c1: float = 1e-4
    armijo_beta: float = 0.5
    max_backtracks: int = 20
    armijo_passes: tuple[int, int | None] | None = None
    linearize_method: str = "auto"
    progress: bool = True
    compact: bool = False

    def __post_init__(self) -> None:
        check_int("max_iter", self.max_iter, 0)
        check_real("tol", self.tol, 0.0)
        check_choice("stop", self.stop, _STOPS)
        if self.step_tol is not None:
            check_real("step_tol", self.step_tol, 0.0)
        check_real("rtol", self.rtol, 0.0, lo_closed=True)
        check_int("stall_iters", self.stall_iters, 0)
        check_real("armijo_c1", self.armijo_c1, 0.0, 1.0)
        check_real("armijo_beta", self.armijo_beta, 0.0, 1.0)
        check_int("max_backtracks", self.max_backtracks, 1)
        object.__setattr__(self, "armijo_passes", check_passes(self.armijo_passes))
        check_choice("linearize_method", self.linearize_method, ("auto", "vjp", "jacrev", "jacfwd"))
        if not isinstance(self.progress, bool):
            raise TypeError(f"progress must be a bool, got {self.progress!r}")
        if not isinstance(self.compact, bool):
            raise TypeError(f"compact must be a bool, got {self.compact!r}")

    def record(self, name: str) -> dict[str, Any]:
        return options_record(name, self)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class SLQOptions(DescentOptions):
    """Options of :class:`torchslq.SLQ`."""

    line_search: str = "exact"
    rollout: str = "open_loop"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("line_search", self.line_search, _LINE_SEARCHES)
        check_choice("rollout", self.rollout, _ROLLOUTS)


@dataclass(frozen=True)
class GradientOptions(SLQOptions):
    """Options of :class:`torchslq.GradientMethod`."""

    search_range: str = "adaptive"
    growth: float = 4.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("search_range", self.search_range, ("adaptive", "unit"))
        check_real("growth", self.growth, 1.0, lo_closed=True)


@dataclass(frozen=True)
class ILQROptions(DescentOptions):
    """Options of :class:`torchslq.ILQR` (``line_search`` and ``rollout`` are fixed: the
    Armijo search on the expected improvement with the feedback rollout)."""

    line_search: str = "armijo"
    rollout: str = "closed_loop"
    mu_init: float = 0.0
    mu_min: float = 1e-6
    mu_max: float = 1e10
    mu_factor: float = 2.0
    hessian_floor: float | None = None
    u_min: Any = None
    u_max: Any = None
    constraints: Any = None
    constraint_tol: float | None = None
    penalty_init: float = 1.0
    penalty_factor: float = 100.0
    penalty_max: float = 1e10
    al_max_iter: int = 30
    polish: bool = False
    constraint_hessian: str = "gauss_newton"
    penalty_update: str = "progress"
    shooting: str = "single"
    defect_tol: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("shooting", self.shooting, ("single", "multiple"))
        if self.defect_tol is not None:
            check_real("defect_tol", self.defect_tol, 0.0)
        if self.shooting == "multiple":
            given = [k for k in ("u_min", "u_max", "constraints") if getattr(self, k) is not None]
            if given:
                raise ValueError(
                    f"shooting='multiple' does not support {', '.join(given)} (bounds and "
                    "constraints need shooting='single')"
                )
        if self.constraints is not None:
            from ..constraints.spec import ConstraintSet

            if not isinstance(self.constraints, ConstraintSet):
                object.__setattr__(self, "constraints", ConstraintSet(self.constraints))
        if self.constraint_tol is not None:
            check_real("constraint_tol", self.constraint_tol, 0.0)
        check_real("penalty_init", self.penalty_init, 0.0)
        check_real("penalty_factor", self.penalty_factor, 1.0)
        check_real("penalty_max", self.penalty_max, 0.0)
        if self.penalty_init > self.penalty_max:
            raise ValueError(
                f"penalty_init ({self.penalty_init}) must not exceed penalty_max ({self.penalty_max})"
            )
        check_int("al_max_iter", self.al_max_iter, 1)
        if not isinstance(self.polish, bool):
            raise TypeError(f"polish must be a bool, got {self.polish!r}")
        check_choice("constraint_hessian", self.constraint_hessian, ("gauss_newton", "exact"))
        check_choice("penalty_update", self.penalty_update, ("progress", "always"))
        if self.rollout != "closed_loop" or self.line_search != "armijo":
            raise ValueError(
                "ILQR/DDP use rollout='closed_loop' and line_search='armijo' "
                f"(got rollout={self.rollout!r}, line_search={self.line_search!r})"
            )
        # an infinite mu_init or hessian_floor makes every element's first step non-finite:
        # an error, not a batch of statuses
        check_real("mu_init", self.mu_init, 0.0, math.inf, lo_closed=True)
        check_real("mu_min", self.mu_min, 0.0, lo_closed=True)
        check_real("mu_max", self.mu_max, 0.0, lo_closed=True)
        if self.mu_min > self.mu_max:
            raise ValueError(f"mu_min ({self.mu_min}) must not exceed mu_max ({self.mu_max})")
        check_real("mu_factor", self.mu_factor, 1.0)
        if self.hessian_floor is not None:
            check_real("hessian_floor", self.hessian_floor, -math.inf, math.inf)
        for name in ("u_min", "u_max"):
            v = getattr(self, name)
            if v is not None and not torch.is_tensor(v):
                check_real(name, v, lo_closed=True, hi_closed=True)


@dataclass(frozen=True)
class DDPOptions(ILQROptions):
    """Options of :class:`torchslq.DDP`."""

    second_order: str = "value"
    vhp_memory_limit: int | None = 256 * 2**20
    constraint_hessian: str = "exact"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("second_order", self.second_order, ("value", "costate"))
        if self.shooting == "multiple":
            raise ValueError(
                "DDP supports shooting='single' only (its dynamics curvature needs the "
                "multipliers at the defects); use ILQR(shooting='multiple')"
            )
        if self.vhp_memory_limit is not None:
            check_int("vhp_memory_limit", self.vhp_memory_limit, 0)
