"""GoPRONTO: first-order optimal control on a state-input curve with a closed-loop
projection (Sforni, Notarnicola, Notarstefano, "Numerical optimal control via first-order
methods ...", GoPRONTO 2022), batched.

The decision variable is a state-input *curve* ``(alpha, mu)`` (not necessarily a
trajectory). The projection operator ``P`` (eq. 8 / 18) maps it to a trajectory by a
tracking controller about the curve::

    u_t = mu_t + K_t (x_t - alpha_t),   x_{t+1} = f(x_t, u_t),   x_0 = x_init.

**Sign convention.** ``K`` here is the library's feedback-gain convention (the gain of
:func:`torchslq.riccati_backward`, ``u = K x + k``); the paper writes
``u = mu + K_paper (alpha - x)``, so ``K_paper = -K``.

The reduced cost ``J(alpha, mu) = l(P(alpha, mu))`` (eq. 21) is minimised by first-order
methods. Its gradient comes from one costate pass of the *closed-loop* linearisation
(eq. 16; paper signs translated with ``K_paper = -K``)::

    lam_T = l_x(T),
    lam_t = (A_t + B_t K_t)' lam_{t+1} + a_t + K_t' b_t,       (16a)
    grad_mu_t = B_t' lam_{t+1} + b_t          (= -Delta mu_t),  (16b)
    grad_alpha_t = -K_t' grad_mu_t            (= -Delta alpha_t) (16c)

with ``A, B`` the dynamics Jacobians and ``a = l_x``, ``b = l_u`` at the projected
trajectory. ``alpha_0`` is a free variable like every ``alpha_t, t < T`` (Algorithm 2
updates all of them; it enters only through ``u_0``, since ``x_0 = x_init``). Fixing it
instead (one reading of eq. 19b) leaves ``u_0`` with an unpreconditioned gradient and makes
the first step a slow mode (measured: ~100x more iterations on an unstable LQ problem).
The shared :func:`~torchslq.dynamics.rollout.costate_gradient` does
the pass with the gains (``lam_t = a_t + A_t' lam_{t+1} + K_t' grad_mu_t``, the same
recursion without forming ``A + B K``).

Variants (``variant=``):

* ``"gradient"`` (Algorithm 2): ``c_{k+1} = c_k - gamma_k grad J(c_k)`` (eq. 17).
* ``"conjugate"`` (Algorithm 3): ``d_k = -g_k + rho_k d_{k-1}`` with the Polak-Ribiere
  ``rho`` of eq. (23), per time step and per block (``cg_formula="per_step"``, the
  paper's) or one scalar for the whole curve (``"global"``), clipped at 0. Cycles start
  with a gradient step; a cycle restarts when ``|g_k' g_{k-1}| > 0.7 ||g_{k-1}||^2``
  (Section V.4), when ``d_k`` is not a descent direction, and after a gain update.
* ``"heavy_ball"`` (eq. 24): ``c_{k+1} = c_k - gamma_k g_k + gamma_HB (c_k - c_{k-1})``.
* ``"nesterov"`` (Algorithm 4, eqs. 25-27): gradient ``g~`` at the extrapolated curve
  ``c~_k = c_k + k/(k+3) (c_k - c_{k-1})`` (projected, linearised there), then
  ``c_{k+1} = c~_k - gamma_k g~_k``.

Step sizes (``step=``): ``"armijo"`` backtracking (Assumption 3.1), trial steps
evaluated as an extra batch dimension (:func:`torchslq.solvers.armijo_search`: the 4
largest first, the others only if some element accepted none of them);
the first trial of each element is ``step0`` at its first iteration and
``armijo_growth`` times its last accepted step afterwards (``armijo_chunk`` sets the
trials per batched rollout). For heavy-ball the test is
``J(c + m - s g) <= J(c) - c1 s ||g||^2`` with the momentum ``m`` kept fixed; for
Nesterov it is taken at the extrapolated curve (``J(c~ - s g~) <= J(c~) - c1 s ||g~||^2``).
With Armijo, a heavy-ball / Nesterov step that ends above ``J(c_k)`` is rejected, replaced
in the same iteration by a plain gradient step from ``c_k``, and the momentum restarted
(function-value restart, O'Donoghue & Candes 2015), so the cost never increases; with a constant step the paper's iterations are run as they are.
A float gives a constant step (the paper's Figure 7 setting); the step is then
accepted whatever the cost does, as long as the projected trajectory stays finite (and,
with a barrier, feasible: the constant step is then halved until it is).

Projection gains (the rule for recomputing them, ``recompute=``): ``K`` is the LQ gain
of the linearisation about the current trajectory with weights ``(Q_reg, R_reg, Qf_reg)``
(Remark 2.5; Section V.1 uses ``Q_reg = Q``, ``R_reg = I``, ``Qf_reg = Qf``), by the shared
Riccati kernel :func:`torchslq.riccati_backward`. With ``"auto"`` (default) an
element's gains are recomputed only when they stop stabilising, detected by either

1. *closed-loop growth*: the linearisation about the current trajectory under the current
   gains, ``v_{t+1} = (A_t + B_t K_t) v_t``, amplifies fixed probe vectors by more than
   ``stability_tol`` (default ``1e4``) over the horizon (max over ``t`` of
   ``||v_t|| / ||v_0||``; it costs one matrix-vector product per step, like the costate
   pass); or
2. *line-search failure of a plain gradient step*: no trial step was accepted (Armijo),
   or the projected rollout was not finite (constant step). A failed momentum or
   conjugate step only restarts the method (the next step is a plain one).

After a recomputation the element's growth threshold becomes
``max(stability_tol, 10 x`` the fresh gains' own growth``)``, so gains that cannot do better
on this horizon (weak ``R_reg``, short horizon) do not trigger a recomputation at every
iteration. The first gains are computed about the initial curve (see
:meth:`GoPRONTO._initial_curve`).

A recomputation re-linearises nothing: it uses the Jacobians of the current iteration.
Since ``P_K(x, u) = (x, u)`` for any ``K``, the curve is then reset to the current
trajectory (same point, same cost, new coordinates) and momentum / CG memory is
cleared. A failed plain step right after a fresh recomputation ends the element
(``LINE_SEARCH_FAILED``; ``DIVERGED`` for a constant step). ``"always"`` recomputes every iteration (as PRONTO does) and
``"never"`` keeps the first gains. The count (excluding the initial computation) is
``result.recomputations (B,)`` and per iteration ``history["recompute"]``.

Input bounds (``u_max=``): the log barrier of Section V.5 (see
:mod:`torchslq.costs.barrier`): the solver minimises ``J + eps * b(u)`` with a per-element
weight ``eps`` starting at ``barrier_weight``; whenever an element's gradient norm is
below ``max(tol, eps)`` its weight is multiplied by ``barrier_decrease`` until it reaches
``barrier_min``, after which the usual test ``||grad|| < tol`` decides convergence.
*Feasible start:* ``u_init`` is clipped to ``(1 - barrier_margin) u_max``; if the projected
initial curve's inputs are not strictly inside the bounds, the element starts instead from
the open-loop trajectory of the clipped ``u_init``, ``(alpha, mu) = (x(u_init), u_init)``,
which the projection maps to itself: strictly feasible. Every later iterate is an
accepted trial with a finite barrier, so it is strictly feasible too (non-finite or
infeasible trials count as ``+inf`` and are never accepted). ``result.cost`` and
``history["cost"]`` are the problem's cost without the barrier; ``history["objective"]``
includes it; ``grad_norm`` is that of the objective.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, ClassVar

import torch
from torch import Tensor

from .._shapes import broadcast_shapes
from ..costs.barrier import box_log_barrier, box_log_barrier_derivatives
from ..costs.quadratic import CostExpansion
from ..dynamics.linearize import linearize
from ..dynamics.rollout import costate_gradient, rollout, rollout_closed_loop
from ..lq.riccati import riccati_backward
from ..problem import check_problem
from ..status import Status
from .base import Solver
from .core import Advance, ElementState, Measure, check_logger, iterate, shared
from .line_search import TrialRecorder, armijo_search
from .options import check_choice, check_int, check_passes, check_real, loggable, options_record
from .result import SolverResult
from .stopping import CURVE_ROUNDOFF_NOISE, roundoff_tolerance

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = [
    "GoPRONTO",
    "GoPRONTOOptions",
    "GoPRONTOResult",
    "closed_loop_growth",
    "curve_gradient",
    "project",
]

_VARIANTS = ("gradient", "conjugate", "heavy_ball", "nesterov")
_RECOMPUTE = ("auto", "always", "never")
_CG_FORMULAS = ("per_step", "global")


# ---------------------------------------------------------------------------- building blocks
def project(f, x0: Tensor, alpha: Tensor, mu: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """The projection ``P(alpha, mu)`` of eq. (8)/(18): ``u_t = mu_t + K_t (x_t - alpha_t)``,
    ``x_{t+1} = f(x_t, u_t)``, ``x_0 = x0``.

    Args:
        f: transition ``f(x, u)``; x0 ``(B, n)``; alpha ``(B, T, n)`` (``alpha_0`` is not
            used by the dynamics, only through ``u_0``); mu ``(B, T, m)``; K ``(B, T, m, n)``
            (library sign convention, ``K_paper = -K``).

    Returns:
        ``x (B, T+1, n)``, ``u (B, T, m)``.
    """
    zero = x0.new_zeros(x0.shape[:-1])
    return rollout_closed_loop(f, x0, alpha, mu, K, torch.zeros_like(mu), zero)


def curve_gradient(
    A: Tensor, B: Tensor, lx: Tensor, lu: Tensor, K: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Gradient of ``J(alpha, mu)`` by the closed-loop costate pass, eq. (16).

    Args:
        A ``(B, T, n, n)``, B ``(B, T, n, m)``: Jacobians at the projected trajectory;
        lx ``(B, T+1, n)``, lu ``(B, T, m)``: cost gradients there; K ``(B, T, m, n)``.

    Returns:
        ``grad_alpha (B, T, n)``,
        ``grad_mu (B, T, m)`` and the costates ``lam (B, T+1, n)``.
    """
    g_mu, lam = costate_gradient(A, B, lx, lu, K)
    g_alpha = -(K.mT @ g_mu.unsqueeze(-1))[..., 0]
    return g_alpha, g_mu, lam


def closed_loop_growth(A: Tensor, B: Tensor, K: Tensor, probes: int = 2) -> Tensor:
    """``max_t ||v_t|| / ||v_0||`` for ``v_{t+1} = (A_t + B_t K_t) v_t`` (``(B,)``, max over
    ``probes`` fixed, pseudo-random unit start vectors; ``+inf`` where not finite).

    The stability test of the projection gains: a stabilising ``K`` keeps it moderate,
    a gain that has stopped stabilising the current linearisation lets it grow
    geometrically with the horizon.
    """
    n = A.shape[-1]
    g = torch.Generator().manual_seed(1234)
    V = torch.randn(n, probes, generator=g, dtype=torch.float64).to(A.dtype).to(A.device)
    V = V / V.norm(dim=0, keepdim=True)
    v = V.expand(*A.shape[:-3], n, probes)
    growth = torch.ones(A.shape[:-3], dtype=A.dtype, device=A.device)
    for t in range(A.shape[-3]):
        v = A[..., t, :, :] @ v + B[..., t, :, :] @ (K[..., t, :, :] @ v)
        growth = torch.maximum(growth, v.norm(dim=-2).amax(dim=-1))
    return torch.nan_to_num(growth, nan=float("inf"))


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).flatten(1).sum(1)


def _bmask(mask: Tensor, t: Tensor) -> Tensor:
    return mask.reshape(-1, *([1] * (t.ndim - 1)))


def _where(mask: Tensor, a: Tensor, b: Tensor) -> Tensor:
    return torch.where(_bmask(mask, a), a, b)


# ---------------------------------------------------------------------------- options / result
def _check_weight(name: str, w: Any) -> None:
    if w is None or torch.is_tensor(w):
        return
    if isinstance(w, bool) or not isinstance(w, (int, float)):
        raise TypeError(
            f"{name} must be None, a positive number or a tensor, got {type(w).__name__}"
        )
    if not w > 0:
        raise ValueError(f"{name} must be positive, got {w!r}")


@dataclass(frozen=True)
class GoPRONTOOptions:
    """Options of :class:`GoPRONTO` (see its docstring)."""

    variant: str = "gradient"
    step: Any = "armijo"
    max_iter: int = 200
    tol: float = 1e-6
    gamma_hb: float = 0.5
    cg_formula: str = "per_step"
    cg_restart: float = 0.7
    Q_reg: Any = None
    R_reg: Any = None
    Qf_reg: Any = None
    recompute: str = "auto"
    stability_tol: float = 1e4
    u_max: Any = None
    barrier_weight: float = 1.0
    barrier_decrease: float = 0.2
    barrier_min: float = 1e-4
    barrier_margin: float = 0.05
    armijo_c1: float = 1e-4
    armijo_beta: float = 0.5
    max_backtracks: int = 30
    armijo_passes: tuple[int, int | None] | None = None
    step0: float = 1.0
    armijo_growth: float = 4.0
    linearize_method: str = "auto"
    progress: bool = True
    stall_iters: int = 10

    def __post_init__(self) -> None:
        if self.variant not in _VARIANTS:
            raise ValueError(f"variant must be one of {_VARIANTS}, got {self.variant!r}")
        check_int("stall_iters", self.stall_iters, 0)
        if isinstance(self.step, str):
            if self.step != "armijo":
                raise ValueError(f"step must be 'armijo' or a positive float, got {self.step!r}")
        else:
            check_real("step", self.step, 0.0, math.inf)
        check_int("max_iter", self.max_iter, 0)
        check_real("tol", self.tol, 0.0)
        check_real("gamma_hb", self.gamma_hb, 0.0, 1.0, lo_closed=True)
        check_choice("cg_formula", self.cg_formula, _CG_FORMULAS)
        check_real("cg_restart", self.cg_restart, 0.0)
        for name in ("Q_reg", "R_reg", "Qf_reg"):
            _check_weight(name, getattr(self, name))
        check_choice("recompute", self.recompute, _RECOMPUTE)
        check_real("stability_tol", self.stability_tol, 1.0)
        if self.u_max is not None:
            if torch.is_tensor(self.u_max):
                if not self.u_max.is_floating_point() or not bool((self.u_max > 0).all()):
                    raise ValueError("u_max must be positive (a float tensor of shape (m,))")
            else:
                check_real("u_max", self.u_max, 0.0)
        check_real("barrier_weight", self.barrier_weight, 0.0)
        check_real("barrier_decrease", self.barrier_decrease, 0.0, 1.0)
        check_real("barrier_min", self.barrier_min, 0.0)
        if self.barrier_min > self.barrier_weight:
            raise ValueError(
                f"barrier_min ({self.barrier_min}) must not exceed barrier_weight "
                f"({self.barrier_weight})"
            )
        check_real("barrier_margin", self.barrier_margin, 0.0, 1.0)
        check_real("armijo_c1", self.armijo_c1, 0.0, 1.0)
        check_real("armijo_beta", self.armijo_beta, 0.0, 1.0)
        check_int("max_backtracks", self.max_backtracks, 1)
        object.__setattr__(self, "armijo_passes", check_passes(self.armijo_passes))
        check_real("step0", self.step0, 0.0, math.inf)
        if not isinstance(self.progress, bool):
            raise TypeError(f"progress must be a bool, got {self.progress!r}")
        check_real("armijo_growth", self.armijo_growth, 1.0, lo_closed=True)
        check_choice("linearize_method", self.linearize_method, ("auto", "vjp", "jacrev", "jacfwd"))


@dataclass(frozen=True)
class PRONTOOptions(GoPRONTOOptions):
    """Options of :class:`torchslq.PRONTO` (GoPRONTO's, without momentum variants)."""

    recompute: str = "always"
    order: str = "first"
    weights: str = "hessian"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_choice("order", self.order, ("first",))
        check_choice("weights", self.weights, ("hessian", "identity"))


@dataclass(frozen=True)
class CurveState(ElementState):
    """Per-solve state of GoPRONTO/PRONTO (batch-first, besides the shared ``umax``).

    Attributes (besides the trajectory ``x, u`` and the objective ``J`` = cost +
    barrier): ``Jc`` the cost; the curve ``alpha (B,T,n)``, ``mu (B,T,m)``; the barrier
    weight ``eps``; the projection gains ``K``; the variants' memory (``restart``,
    ``prev_*``, ``k_nest``, ``cg_restarts``); the gain rule's flags (``pending``,
    ``fresh``, ``computed``), its ``recomputations`` and growth threshold ``thresh``; the
    last accepted step ``gamma_prev``.
    """

    Jc: Tensor = None
    alpha: Tensor = None
    mu: Tensor = None
    eps: Tensor = None
    K: Tensor = None
    restart: Tensor = None
    prev_a: Tensor = None
    prev_m: Tensor = None
    prev_ga: Tensor = None
    prev_gm: Tensor = None
    prev_da: Tensor = None
    prev_dm: Tensor = None
    k_nest: Tensor = None
    cg_restarts: Tensor = None
    pending: Tensor = None
    fresh: Tensor = None
    computed: Tensor = None
    recomputations: Tensor = None
    thresh: Tensor = None
    gamma_prev: Tensor = None
    umax: Tensor | None = shared()


_STATE_FIELDS = tuple(f.name for f in fields(CurveState))


def _fields(state: CurveState) -> dict[str, Any]:
    return {k: getattr(state, k) for k in _STATE_FIELDS}


@dataclass
class GoPRONTOResult(SolverResult):
    """:class:`SolverResult` plus the curve and the gain bookkeeping of GoPRONTO/PRONTO.

    Attributes (besides those of :class:`SolverResult`; ``K`` are the projection gains in
    the library convention ``u = mu + K (x - alpha)``, ``k`` is zero):
        alpha: ``(B, T, n)`` and mu ``(B, T, m)``: the final state-input curve
            (``P(alpha, mu) = (x, u)``).
        recomputations: ``(B,)`` int64 number of projection-gain recomputations after the
            initial computation.
        barrier_weight: ``(B,)`` final barrier weight (zeros without ``u_max``).
        extra: ``{"cg_restarts": (B,)}``, conjugate cycles restarted (conjugate variant).

    ``history`` adds ``"objective"`` (cost + barrier), ``"recompute"`` (bool, gains
    recomputed at that iteration) and ``"barrier_weight"``.
    """

    alpha: Tensor | None = None
    mu: Tensor | None = None
    recomputations: Tensor | None = None
    barrier_weight: Tensor | None = None
    extra: dict = field(default_factory=dict)

    def squeeze_batch(self) -> GoPRONTOResult:
        base = SolverResult.squeeze_batch(self)

        def sq(t):
            return t[0] if torch.is_tensor(t) and t.ndim >= 1 else t

        return GoPRONTOResult(
            **{k: getattr(base, k) for k in SolverResult.__dataclass_fields__},
            alpha=sq(self.alpha),
            mu=sq(self.mu),
            recomputations=sq(self.recomputations),
            barrier_weight=sq(self.barrier_weight),
            extra={k: sq(v) for k, v in self.extra.items()},
        )


def _chunk_alias(kw: dict[str, Any]) -> dict[str, Any]:
    """``armijo_chunk=c`` (the former name) as ``armijo_passes=(c, c)``."""
    chunk = kw.pop("armijo_chunk", None)
    if chunk is None:
        return kw
    check_int("armijo_chunk", chunk, 1)
    if kw.get("armijo_passes") is not None:
        raise ValueError("give armijo_passes or armijo_chunk, not both")
    return kw | {"armijo_passes": (chunk, chunk)}


# ---------------------------------------------------------------------------- the solver
class GoPRONTO(Solver):
    """GoPRONTO (Algorithms 2-4 of the paper), batched; see the module docstring.

    Args:
        variant: ``"gradient"`` (Alg. 2), ``"conjugate"`` (Alg. 3), ``"heavy_ball"``
            (eq. 24) or ``"nesterov"`` (Alg. 4).
        step: ``"armijo"`` or a positive float (constant step ``gamma``).
        max_iter: iterations per element (default 200); tol: stop when
            ``||grad J(alpha, mu)|| < tol`` (default 1e-6).
        gamma_hb: heavy-ball momentum ``gamma_HB`` in ``[0, 1)`` (default 0.5, Figure 7).
        cg_formula: ``"per_step"`` (eq. 23: one ``rho`` per time step and block) or
            ``"global"``; cg_restart: the conjugacy-test constant (0.7).
        Q_reg, R_reg, Qf_reg: weights of the LQ problem giving the projection gains:
            None (the cost's Hessians at the current trajectory: stage state, control and
            terminal), a positive number (times the identity) or a tensor ``(n, n)`` /
            ``(m, m)`` / ``(n, n)`` (a leading batch/time dim is allowed for Q_reg
            ``(T, n, n)``, ``(B, T, n, n)`` and R_reg likewise).
        recompute: ``"auto"``, ``"always"`` or ``"never"`` (see the module docstring);
            stability_tol: the growth threshold of the ``"auto"`` rule (> 1).
        u_max: None, or the bound of ``|u| <= u_max``: a positive number or a tensor
            ``(m,)``, enforced by the log barrier of the paper's Section V.5 (an interior
            method: iterates stay strictly inside; :class:`torchslq.ILQR` enforces bounds
            as hard box constraints instead). barrier_weight, barrier_decrease,
            barrier_min, barrier_margin: the barrier continuation (initial weight 1,
            factor 0.2 down to 1e-4, start clipped to 95% of the bound).
        armijo_c1, armijo_beta, max_backtracks: Armijo constants (trials
            ``s0 beta^j``, ``j < max_backtracks``); armijo_passes: ``(first, then)``
            trials per batched rollout as for :class:`torchslq.SLQ` (None: the 4 largest
            first, then the rest at once for small problems or 4 at a time for large
            ones, see :meth:`_armijo_passes`); armijo_chunk: ``c`` is ``armijo_passes=(c,
            c)`` (an alias); step0: the first trial step; armijo_growth: later first
            trials are this times the last accepted step.
        linearize_method: passed to :func:`torchslq.linearize`.
        progress: tqdm bar for long solves.
        stall_iters: stop an element with status ``stalled`` after this many consecutive
            accepted steps that changed its objective by no more than rounding noise
            without halving its gradient norm (as for :class:`torchslq.SLQ`); 0 disables.

    ``solve(problem, x0, u_init=None, logger=None)`` returns a :class:`GoPRONTOResult`.
    """

    name: ClassVar[str] = "gopronto"
    options_class: ClassVar[type] = GoPRONTOOptions
    _always_hessians = False  # PRONTO's direction needs them at every iteration

    def __init__(
        self,
        variant: str = "gradient",
        step: Any = "armijo",
        *,
        max_iter: int = 200,
        tol: float = 1e-6,
        gamma_hb: float = 0.5,
        cg_formula: str = "per_step",
        cg_restart: float = 0.7,
        Q_reg: Any = None,
        R_reg: Any = None,
        Qf_reg: Any = None,
        recompute: str = "auto",
        stability_tol: float = 1e4,
        u_max: Any = None,
        barrier_weight: float = 1.0,
        barrier_decrease: float = 0.2,
        barrier_min: float = 1e-4,
        barrier_margin: float = 0.05,
        armijo_c1: float = 1e-4,
        armijo_beta: float = 0.5,
        max_backtracks: int = 30,
        armijo_passes: tuple[int, int | None] | None = None,
        armijo_chunk: int | None = None,
        step0: float = 1.0,
        armijo_growth: float = 4.0,
        linearize_method: str = "auto",
        progress: bool = True,
        stall_iters: int = 10,
        **unknown: Any,
    ):
        kw = {k: v for k, v in locals().items() if k not in ("self", "__class__")}
        super().__init__(**_chunk_alias(kw))

    # ------------------------------------------------------------------ pieces
    def _u_max(self, like: Tensor, m: int) -> Tensor | None:
        um = self.options.u_max
        if um is None:
            return None
        um = torch.as_tensor(um, dtype=like.dtype, device=like.device)
        if um.ndim == 0:
            um = um.expand(m)
        if um.shape != (m,):
            raise ValueError(
                f"u_max must be a number or a tensor of shape ({m},), got {tuple(um.shape)}"
            )
        return um

    def _weights(self, e: CostExpansion, T: int, n: int, m: int, like: Tensor):
        """``Q (.., T+1, n, n)`` and ``R (.., T, m, m)`` of the projection-gain LQ problem."""
        o = self.options

        def as_mat(name, w, k, default):
            if w is None:
                return default
            w = torch.as_tensor(w, dtype=like.dtype, device=like.device)
            if w.ndim == 0:
                return w * torch.eye(k, dtype=like.dtype, device=like.device)
            if w.shape[-2:] != (k, k) or w.ndim > 4:
                raise ValueError(
                    f"{name} must be a number or a tensor of shape ({k}, {k}) (optionally with "
                    f"leading time/batch dims), got {tuple(w.shape)}"
                )
            return w

        lxx = e.lxx
        if lxx is not None and lxx.shape[-3] == 1:
            lxx = lxx.expand(*lxx.shape[:-3], T + 1, n, n)
        Qs = as_mat("Q_reg", o.Q_reg, n, None if lxx is None else lxx[..., :T, :, :])
        Qf = as_mat("Qf_reg", o.Qf_reg, n, None if lxx is None else lxx[..., T, :, :])
        if Qs.ndim == 2:
            Qs = Qs.expand(T, n, n)
        if Qf.ndim == 2:
            Qf = Qf.unsqueeze(0)
        else:
            Qf = Qf.unsqueeze(-3)
        if Qs.ndim == 3 and Qf.ndim == 4:
            Qs = Qs.unsqueeze(0)
        if Qs.ndim == 4 and Qf.ndim == 3:
            Qf = Qf.unsqueeze(0)
        if Qs.ndim == 4:
            bq = broadcast_shapes(Qs.shape[:1], Qf.shape[:1])
            Qs, Qf = Qs.expand(*bq, *Qs.shape[1:]), Qf.expand(*bq, *Qf.shape[1:])
        Q = torch.cat([Qs, Qf], dim=-3)
        R = as_mat("R_reg", o.R_reg, m, e.luu)
        return Q, R

    def projection_gains(self, A: Tensor, B: Tensor, e: CostExpansion) -> tuple[Tensor, Tensor]:
        """Projection gains ``K (B, T, m, n)`` and a failure flag ``(B,)``: the LQ gain of
        the linearisation ``(A, B)`` with the weights ``(Q_reg, R_reg, Qf_reg)`` (the cost's
        Hessians ``e`` where None), by :func:`torchslq.riccati_backward`."""
        T, n, m = A.shape[-3], A.shape[-1], B.shape[-1]
        Q, R = self._weights(e, T, n, m, A)
        fac = riccati_backward(A, B, Q, R)
        K = fac.K.expand(*A.shape[:-3], T, m, n)
        failed = (
            fac.failed.reshape(-1).expand(A.shape[0]) if fac.failed.numel() == 1 else fac.failed
        )
        return K, failed | ~torch.isfinite(K).flatten(1).all(1)

    def _expand(
        self,
        problem: Problem,
        x: Tensor,
        u: Tensor,
        eps: Tensor,
        umax: Tensor | None,
        hessians: bool = False,
    ):
        """Linearisation and cost expansion (with the barrier) at a trajectory."""
        T = problem.horizon
        A, B = linearize(problem.transition, x[:, :T], u, method=self.options.linearize_method)
        return A, B, self._cost_expansion(problem, x, u, eps, umax, hessians)

    def _needs_hessians(self) -> bool:
        """Whether the gain LQ problem uses the cost's Hessians (a weight left None)."""
        o = self.options
        return o.Q_reg is None or o.R_reg is None or o.Qf_reg is None

    def _cost_expansion(self, problem, x, u, eps, umax, hessians: bool) -> CostExpansion:
        """Cost gradients ``lx, lu`` (+ barrier); Hessians too when ``hessians`` (else None).

        The gradient alone (all the costate pass needs) comes from one reverse pass of
        the cost, which for a general :class:`torchslq.Cost` is much cheaper than its
        full :meth:`quadratize`.
        """
        if hessians:
            e = problem.cost.quadratize(x, u)
        else:
            with torch.enable_grad():
                xg = x.detach().requires_grad_(True)
                ug = u.detach().requires_grad_(True)
                lx, lu = torch.autograd.grad(
                    problem.cost(xg, ug).sum(), (xg, ug), allow_unused=True
                )
            lx = torch.zeros_like(x) if lx is None else lx
            lu = torch.zeros_like(u) if lu is None else lu
            e = CostExpansion(lxx=None, luu=None, lux=None, lx=lx, lu=lu)
        if umax is not None:
            bg, bh = box_log_barrier_derivatives(u, umax)
            w = eps[:, None, None]
            luu = None if e.luu is None else e.luu + torch.diag_embed(w * bh)
            e = CostExpansion(lxx=e.lxx, luu=luu, lux=e.lux, lx=e.lx, lu=e.lu + w * bg)
        return e

    def _objective(self, cost_fn, x: Tensor, u: Tensor, eps: Tensor, umax: Tensor | None):
        """``(objective, cost)`` of trajectories ``(..., B, T+1, n)``; ``eps (B,)``."""
        J = cost_fn(x, u)
        if umax is None:
            return J, J
        return J + eps * box_log_barrier(u, umax), J

    # ------------------------------------------------------------------ direction (variants)
    def _direction(self, ctx: dict, problem: Problem, x0: Tensor) -> dict[str, Tensor]:
        """Base curve, direction, slope and reference cost of this iteration.

        Returns ``base_a, base_m`` (the curve at step 0), ``da, dm`` (direction),
        ``ref`` (cost compared against by Armijo) and ``slope`` (``(B,)``, < 0).
        """
        o = self.options
        s = ctx
        g_a, g_m = s["g_a"], s["g_m"]
        alpha, mu = s["alpha"], s["mu"]
        restart = s["restart"]
        ones = torch.ones_like(restart)
        if o.variant == "gradient":
            return dict(
                base_a=alpha, base_m=mu, da=-g_a, dm=-g_m, ref=s["J"], slope=-s["g2"], plain=ones
            )
        if o.variant == "heavy_ball":
            pa = _where(restart, alpha, s["prev_a"])
            pm = _where(restart, mu, s["prev_m"])
            ba = alpha + o.gamma_hb * (alpha - pa)
            bm = mu + o.gamma_hb * (mu - pm)
            return dict(
                base_a=ba, base_m=bm, da=-g_a, dm=-g_m, ref=s["J"], slope=-s["g2"], plain=restart
            )
        if o.variant == "conjugate":
            pga, pgm, pda, pdm = s["prev_ga"], s["prev_gm"], s["prev_da"], s["prev_dm"]
            pg2 = _dot(pga, pga) + _dot(pgm, pgm)
            cross = _dot(g_a, pga) + _dot(g_m, pgm)
            rs = restart | (cross.abs() > o.cg_restart * pg2) | ~(pg2 > 0)
            if o.cg_formula == "global":
                rho = ((s["g2"] - cross) / pg2).clamp_min(0.0)
                rho_a = rho[:, None, None]
                rho_m = rho_a
            else:  # eq. (23): one rho per time step and block

                def rho_of(g, pg):
                    den = (pg * pg).sum(-1, keepdim=True)
                    num = (g * (g - pg)).sum(-1, keepdim=True)
                    r = torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.0)
                    return r.clamp_min(0.0)

                rho_a, rho_m = rho_of(g_a, pga), rho_of(g_m, pgm)
            da = -g_a + rho_a * pda
            dm = -g_m + rho_m * pdm
            slope = _dot(g_a, da) + _dot(g_m, dm)
            rs = rs | ~(slope < 0) | ~torch.isfinite(slope)
            da = _where(rs, -g_a, da)
            dm = _where(rs, -g_m, dm)
            slope = torch.where(rs, -s["g2"], slope)
            s["cg_restarts"] = s["cg_restarts"] + (rs & s["running"]).to(torch.int64)
            return dict(base_a=alpha, base_m=mu, da=da, dm=dm, ref=s["J"], slope=slope, plain=rs)
        # nesterov
        k = s["k_nest"].to(alpha.dtype)
        beta = torch.where(restart, torch.zeros_like(k), k / (k + 3.0))
        if not bool((beta > 0).any()):
            return dict(
                base_a=alpha, base_m=mu, da=-g_a, dm=-g_m, ref=s["J"], slope=-s["g2"], plain=ones
            )
        ta = alpha + beta[:, None, None] * (alpha - s["prev_a"])
        tm = mu + beta[:, None, None] * (mu - s["prev_m"])
        f = problem.transition
        xt, ut = project(f, x0, ta, tm, s["K"])
        Jt, _ = self._objective(problem.cost, xt, ut, s["eps"], s["umax"])
        A, B, e = self._expand(problem, xt, ut, s["eps"], s["umax"])
        ga, gm, _ = curve_gradient(A, B, e.lx, e.lu, s["K"])
        g2 = _dot(ga, ga) + _dot(gm, gm)
        return dict(base_a=ta, base_m=tm, da=-ga, dm=-gm, ref=Jt, slope=-g2, plain=~(beta > 0))

    def _after_step(self, s: dict, accept: Tensor, d: dict) -> None:
        """Variant memory after a step (``accept`` elements moved)."""
        if self.options.variant == "conjugate":
            run = s["running"]
            s["prev_ga"] = _where(run, s["g_a"], s["prev_ga"])
            s["prev_gm"] = _where(run, s["g_m"], s["prev_gm"])
            s["prev_da"] = _where(run, d["da"], s["prev_da"])
            s["prev_dm"] = _where(run, d["dm"], s["prev_dm"])

    # ------------------------------------------------------------------ solve
    def solve(
        self,
        problem: Problem,
        x0: Tensor,
        u_init: Tensor | None = None,
        logger: Any = None,
        *,
        alpha_init: Tensor | None = None,
    ) -> GoPRONTOResult:
        """Solve ``problem`` from ``x0 (B, n)`` (or ``(n,)``).

        Args:
            u_init: initial input curve ``mu_0`` ``(B, T, m)`` or ``(T, m)`` (zeros by
                default).
            alpha_init: initial state curve ``(B, T, n)`` or ``(T, n)``; by default
                ``x0`` held constant (the paper starts from the zero curve at an
                equilibrium). ``alpha_0`` is always set to ``x0``. See
                :meth:`_initial_curve` for how the first gains and trajectory are made.
            logger: e.g. :class:`torchslq.TensorBoardLogger`; None costs nothing.

        Returns:
            :class:`GoPRONTOResult`: trajectory ``x, u`` (the projection of the final curve
            ``alpha, mu``), cost, grad_norm (of ``J(alpha, mu)``), status, iterations,
            projection gains ``K``, recomputations, history.
        """
        o = self.options
        check_problem(problem)
        check_logger(logger)
        x0, u, unbatched = problem.check_inputs(x0, u_init)
        Bsz, T, n, m = x0.shape[0], problem.horizon, problem.state_dim, problem.control_dim
        dev = x0.device
        umax = self._u_max(x0, m)
        if o.Q_reg is not None or o.R_reg is not None or o.Qf_reg is not None:
            # validate the weights' shapes before any work (raises ValueError)
            dummy = CostExpansion(
                lxx=x0.new_zeros(1, T + 1, n, n),
                luu=x0.new_zeros(1, T, m, m),
                lux=None,
                lx=x0.new_zeros(1, T + 1, n),
                lu=x0.new_zeros(1, T, m),
            )
            self._weights(dummy, T, n, m, x0)
        record = options_record(self.name, o)

        with torch.no_grad():
            eps = torch.full(
                (Bsz,), o.barrier_weight if umax is not None else 0.0, dtype=x0.dtype, device=dev
            )
            alpha, mu, x, u, K0, ok0 = self._initial_curve(problem, x0, u, alpha_init, eps, umax)
            J, Jc = self._objective(problem.cost, x, u, eps, umax)
            flags = torch.zeros(Bsz, dtype=torch.bool, device=dev)
            counts = torch.zeros(Bsz, dtype=torch.int64, device=dev)
            state = CurveState(
                x=x,
                u=u,
                J=J,
                Jc=Jc,
                alpha=alpha,
                mu=mu,
                eps=eps,
                K=K0,
                restart=torch.ones_like(flags),
                prev_a=alpha,
                prev_m=mu,
                prev_ga=torch.zeros_like(alpha),
                prev_gm=torch.zeros_like(mu),
                prev_da=torch.zeros_like(alpha),
                prev_dm=torch.zeros_like(mu),
                k_nest=counts,
                cg_restarts=counts,
                pending=~ok0,  # gains to (re)compute at the next iteration
                fresh=flags,  # gains new, no step taken since
                computed=ok0.clone(),  # gains computed about the current curve/trajectory
                recomputations=counts,
                thresh=torch.full((Bsz,), float(o.stability_tol), dtype=x0.dtype, device=dev),
                gamma_prev=torch.full(
                    (Bsz,), o.step0 / o.armijo_growth, dtype=x0.dtype, device=dev
                ),
                umax=umax,
            )
            out = iterate(
                self, problem, state, self.settings(), logger=logger, options=loggable(record)
            )
        s = out.state
        result = GoPRONTOResult(
            x=s.x,
            u=s.u,
            cost=s.Jc,
            grad_norm=out.grad_norm,
            iterations=out.iterations,
            status=out.status,
            converged=out.status == Status.CONVERGED,
            K=s.K,
            k=torch.zeros_like(s.u),
            history=out.history,
            options=record,
            alpha=s.alpha,
            mu=s.mu,
            recomputations=s.recomputations,
            barrier_weight=s.eps,
            extra={"cg_restarts": s.cg_restarts},
        )
        if logger is not None:
            logger.log_result(result, problem)
        return result.squeeze_batch() if unbatched else result

    # ------------------------------------------------------------------ the iteration
    def measure(self, problem: Problem, state: CurveState, running: Tensor, it: int):
        """Gains (recomputed where they stopped stabilising), the curve gradient (eq. 16)
        and the barrier continuation at the current curve."""
        o = self.options
        s = _fields(state)
        x, u, umax = state.x, state.u, state.umax
        T = problem.horizon
        A, Bm, e = self._expand(problem, x, u, s["eps"], umax, self._always_hessians)
        # ---- projection gains: compute / recompute when they stop stabilising
        flag = running & s["pending"]
        if o.recompute == "always":
            flag = running & (s["pending"] | (it > 0))
        elif o.recompute == "auto" and bool(s["computed"].any()):
            growth = closed_loop_growth(A, Bm, s["K"])
            flag = flag | (running & s["computed"] & ~(growth <= s["thresh"]))
        recomp = torch.zeros_like(flag)
        if bool(flag.any()):
            if e.lxx is None and self._needs_hessians():
                e = self._cost_expansion(problem, x, u, s["eps"], umax, True)
            Knew, failed = self.projection_gains(A, Bm, e)
            upd = flag & ~failed
            s["K"] = _where(upd, Knew, s["K"])
            recomp = upd & s["computed"]
            s["recomputations"] = s["recomputations"] + recomp.to(torch.int64)
            s["computed"] = s["computed"] | upd
            if o.recompute == "auto":
                # fresh gains that themselves amplify more than stability_tol / 10
                # (short horizon, weak R_reg) raise the element's threshold, so the
                # test fires on a loss of stability, not every iteration
                g_new = closed_loop_growth(A, Bm, s["K"])
                s["thresh"] = torch.where(
                    upd, torch.clamp(10.0 * g_new, min=o.stability_tol), s["thresh"]
                )
            s["alpha"] = _where(flag, x[:, :T], s["alpha"])
            s["mu"] = _where(flag, u, s["mu"])
            s["restart"] = s["restart"] | flag
            s["k_nest"] = torch.where(flag, 0, s["k_nest"])
            s["fresh"] = s["fresh"] | flag
            s["pending"] = s["pending"] & ~flag
        g_a, g_m, _ = curve_gradient(A, Bm, e.lx, e.lu, s["K"])
        g2 = _dot(g_a, g_a) + _dot(g_m, g_m)
        # ---- barrier continuation
        if umax is not None:
            inner = (
                running
                & (g2.sqrt() < torch.clamp(s["eps"], min=o.tol))
                & (s["eps"] > o.barrier_min * (1 + 1e-9))
            )
            if bool(inner.any()):
                s["eps"] = torch.where(
                    inner, torch.clamp(s["eps"] * o.barrier_decrease, min=o.barrier_min), s["eps"]
                )
                s["J"], s["Jc"] = self._objective(problem.cost, x, u, s["eps"], umax)
                e = self._cost_expansion(problem, x, u, s["eps"], umax, self._always_hessians)
                g_a, g_m, _ = curve_gradient(A, Bm, e.lx, e.lu, s["K"])
                g2 = _dot(g_a, g_a) + _dot(g_m, g_m)
                s["restart"] = s["restart"] | inner
                s["k_nest"] = torch.where(inner, 0, s["k_nest"])
        gn = g2.sqrt()
        done = gn < o.tol
        if umax is not None:
            done = done & (s["eps"] <= o.barrier_min * (1 + 1e-9))
        fail = torch.full_like(s["k_nest"], int(Status.RUNNING))
        fail = fail.masked_fill(~torch.isfinite(gn), int(Status.NON_FINITE))
        state = replace(state, **s)
        scratch = dict(g_a=g_a, g_m=g_m, g2=g2, A=A, B=Bm, e=e, x=x, u=u)
        return state, Measure(
            grad_norm=gn,
            done=done,
            fail=fail,
            cost=state.Jc,
            history={"objective": state.J, "recompute": recomp, "barrier_weight": state.eps},
            direction=scratch,
        )

    def advance(self, problem: Problem, state: CurveState, m: Measure, running: Tensor):
        """Direction of the variant, step (Armijo or constant), momentum restarts and the
        bookkeeping of the gain-recomputation rule."""
        o = self.options
        s = _fields(state) | m.direction
        s["running"] = running
        x0 = state.x[:, 0]
        umax = state.umax
        constant = not isinstance(o.step, str)
        f, cost_fn = problem.transition, problem.cost
        gamma_prev, J = s["gamma_prev"], s["J"]
        d = self._direction(s, problem, x0)
        gamma, Jnew, ok, xn, un = self._line_search(
            f, cost_fn, x0, d, s, gamma_prev, constant, umax
        )
        accept = running & ok
        if not constant and o.variant in ("heavy_ball", "nesterov"):
            # function-value restart (O'Donoghue & Candes): a momentum step that raised
            # the cost is rejected and retried at once with a plain gradient step from c_k
            bump = accept & ~(Jnew <= J) & ~d["plain"]
            if bool(bump.any()):
                d2 = dict(
                    base_a=s["alpha"],
                    base_m=s["mu"],
                    da=-s["g_a"],
                    dm=-s["g_m"],
                    ref=J,
                    slope=-s["g2"],
                    plain=torch.ones_like(bump),
                )
                g2_, J2, ok2, x2, u2 = self._line_search(
                    f, cost_fn, x0, d2, s, gamma_prev, constant, umax
                )
                d = {k: _where(bump, d2[k], v) if torch.is_tensor(v) else v for k, v in d.items()}
                gamma = torch.where(bump, g2_, gamma)
                Jnew = torch.where(bump, J2, Jnew)
                ok = torch.where(bump, ok2, ok)
                xn, un = _where(bump, x2, xn), _where(bump, u2, un)
                accept = running & ok
        else:
            bump = torch.zeros_like(accept)
        na = d["base_a"] + gamma[:, None, None] * d["da"]
        nm = d["base_m"] + gamma[:, None, None] * d["dm"]
        self._after_step(s, accept, d)
        s["prev_a"] = _where(accept, s["alpha"], s["prev_a"])
        s["prev_m"] = _where(accept, s["mu"], s["prev_m"])
        s["alpha"] = _where(accept, na, s["alpha"])
        s["mu"] = _where(accept, nm, s["mu"])
        x = _where(accept, xn, s["x"])
        u = _where(accept, un, s["u"])
        s["J"] = torch.where(accept, Jnew, J)
        Jc_new = cost_fn(x, u) if umax is not None else s["J"]
        s["Jc"] = torch.where(accept, Jc_new, s["Jc"])
        s["x"], s["u"] = x, u
        self._on_accept(s, accept, x, u)
        s["k_nest"] = s["k_nest"] + accept.to(torch.int64)
        s["restart"] = (s["restart"] & ~accept) | bump
        s["k_nest"] = torch.where(bump, 0, s["k_nest"])
        s["gamma_prev"] = torch.where(accept, gamma, gamma_prev)
        # a failed momentum / conjugate step only restarts the method; a failed plain
        # gradient step means the gains stopped stabilising: recompute them, and if they
        # are fresh already, the element has failed
        failed = running & ~ok & d["plain"]
        ended = failed & s["fresh"] if o.recompute != "never" else failed
        if o.recompute != "never":
            s["pending"] = s["pending"] | (failed & ~s["fresh"])
        end_code = int(Status.DIVERGED if constant else Status.LINE_SEARCH_FAILED)
        end = torch.where(ended, end_code, int(Status.RUNNING))
        s["restart"] = s["restart"] | (running & ~ok)
        s["k_nest"] = torch.where(running & ~ok, 0, s["k_nest"])
        s["fresh"] = s["fresh"] & ~accept
        state = replace(state, **{k: s[k] for k in _STATE_FIELDS})
        return Advance(state=state, accept=accept, step=gamma, end=end)

    def _initial_curve(self, problem, x0, u, alpha_init, eps, umax):
        """Initial curve, trajectory and gains.

        The curve ``(alpha, mu) = (alpha_init, u_init)`` is projected with the gains of
        the linearisation *at the curve* (eq. 8 needs gains before there is a
        trajectory; for the paper's zero curve at an equilibrium, curve and trajectory
        coincide). They are not counted as a recomputation. An
        element whose projected start is not finite, or (with ``u_max``) not strictly
        inside the bounds, falls back to the open-loop start: ``u_init`` clipped to
        ``(1 - barrier_margin) u_max`` and its rollout as the curve, which the projection
        maps to itself, so the start is strictly feasible.
        """
        o = self.options
        f = problem.transition
        Bsz, T, n = x0.shape[0], problem.horizon, problem.state_dim
        if alpha_init is None:
            alpha = x0.unsqueeze(1).expand(Bsz, T, n).clone()
        else:
            if not torch.is_tensor(alpha_init):
                raise TypeError("alpha_init must be a tensor of shape (B, T, n) or (T, n)")
            if (
                alpha_init.shape[-2:] != (T, n)
                or alpha_init.ndim not in (2, 3)
                or (alpha_init.ndim == 3 and alpha_init.shape[0] not in (1, Bsz))
            ):
                raise ValueError(
                    f"alpha_init must have shape ({Bsz}, {T}, {n}) or ({T}, {n}), "
                    f"got {tuple(alpha_init.shape)}"
                )
            alpha = alpha_init.to(x0).expand(Bsz, T, n).clone()
        alpha[:, 0] = x0
        if umax is not None:
            lim = (1.0 - o.barrier_margin) * umax
            u = torch.maximum(torch.minimum(u, lim), -lim)
        xa = torch.cat([alpha, alpha[:, -1:]], dim=1)
        A, B, e = self._expand(problem, xa, u, eps, umax, self._needs_hessians())
        K, failed = self.projection_gains(A, B, e)
        K = _where(failed, torch.zeros_like(K), K)
        x, uu = project(f, x0, alpha, u, K)
        bad = ~torch.isfinite(x).flatten(1).all(1) | ~torch.isfinite(uu).flatten(1).all(1)
        if umax is not None:
            bad = bad | ~(uu.abs() < umax).flatten(1).all(1)
        if bool(bad.any()):
            x_ol = rollout(f, x0, u)
            alpha = _where(bad, x_ol[:, :T], alpha)
            x = _where(bad, x_ol, x)
            uu = _where(bad, u, uu)
        # gains about the curve serve the first iteration (the "auto" rule replaces them
        # if they do not stabilise the projected trajectory); elements that fell back to
        # the open-loop start, or whose LQ solve failed, get theirs at iteration 0
        return alpha, u.clone(), x, uu, K, ~(failed | bad)

    def _armijo_passes(self, d: dict) -> tuple[int, int | None]:
        """``(first_trials, pass_size)`` of :func:`armijo_search`: ``armijo_passes`` when
        set; by default the 4 largest trials first (the first trial grows from the last
        accepted step, so one of them is usually accepted), then the rest at once for
        small problems and 4 at a time once a trial rollout is large (``B T n`` above
        2e5 entries), where the rollouts dominate."""
        o = self.options
        if o.armijo_passes is not None:
            return o.armijo_passes
        return 4, (None if d["base_a"].numel() <= 200_000 else 4)

    def _first_trial(self, gamma_prev: Tensor) -> Tensor:
        """First Armijo trial per element: ``armijo_growth`` times the last accepted step
        (``step0`` at the first iteration)."""
        return self.options.armijo_growth * gamma_prev

    def _on_accept(self, s: dict, accept: Tensor, x: Tensor, u: Tensor) -> None:
        """Hook after an accepted step (PRONTO resets its curve to the trajectory)."""

    def _line_search(self, f, cost_fn, x0, d, s, gamma_prev, constant, umax):
        """Steps ``(B,)``, objective, success flags and the chosen trajectories."""
        o = self.options
        K, eps = s["K"], s["eps"]
        ba, bm = d["base_a"], d["base_m"]
        k_ff = d["dm"] - (K @ d["da"].unsqueeze(-1))[..., 0]  # u = bm + a k_ff + K (x - ba)
        trials = TrialRecorder()

        def evaluate(alphas: Tensor) -> Tensor:  # (Na, B) -> (Na, B)
            Na = alphas.shape[0]
            xc, uc = rollout_closed_loop(f, x0.expand(Na, *x0.shape), ba, bm, K, k_ff, alphas)
            trials.record(alphas, xc, uc)
            return self._objective(cost_fn, xc, uc, eps, umax)[0]

        if constant:
            gam = float(o.step)
            n_try = o.max_backtracks if umax is not None else 1
            grid = gam * o.armijo_beta ** torch.arange(n_try, dtype=x0.dtype, device=x0.device)
            alphas = grid.unsqueeze(-1).expand(-1, x0.shape[0])
            Jt = evaluate(alphas)
            okg = torch.isfinite(Jt)
            first = torch.argmax(okg.to(torch.int8), dim=0)
            ok = okg.any(dim=0)
            gamma = torch.where(ok, grid[first], torch.zeros_like(s["J"]))
            Jnew = torch.where(ok, Jt.gather(0, first.unsqueeze(0))[0], s["J"])
        else:
            # first trial: armijo_growth x the element's last accepted step (step0 at first)
            scale = self._first_trial(gamma_prev)
            scale = torch.where(
                torch.isfinite(scale) & (scale > 0), scale, torch.full_like(scale, o.step0)
            )

            def ev_scaled(a: Tensor) -> Tensor:
                return evaluate(a * scale)

            first_trials, pass_size = self._armijo_passes(d)
            a, Jnew, ok = armijo_search(
                ev_scaled,
                d["ref"],
                scale * d["slope"],
                c1=o.armijo_c1,
                beta=o.armijo_beta,
                max_backtracks=o.max_backtracks,
                roundoff=CURVE_ROUNDOFF_NOISE,
                first_trials=first_trials,
                pass_size=pass_size,
                active=s["running"],
            )
            gamma = a * scale
            # near a minimum the predicted decrease of even the first trial can be below
            # the rounding noise of J, and Armijo then passes or fails trials at random
            # (collapsing or inflating the step); there the element keeps its last
            # accepted step if that is no worse than J up to the noise (the gradient test
            # still decides convergence)
            noise = roundoff_tolerance(d["ref"], CURVE_ROUNDOFF_NOISE)
            flat = (scale * d["slope"]).abs() <= noise
            if bool((flat & s["running"]).any()):
                keep = torch.where(gamma_prev > 0, gamma_prev, scale)
                J_keep = evaluate(keep.unsqueeze(0))[0]  # one more batched rollout
                flat = flat & (J_keep <= d["ref"] + noise)
                gamma = torch.where(flat, keep, gamma)
                Jnew = torch.where(flat, J_keep, Jnew)
                ok = ok | flat
            # Armijo compares against the reference (J, or J~ for Nesterov); also never
            # accept a non-finite objective
            ok = ok & torch.isfinite(Jnew)
        xn, un = trials.select(gamma)
        return gamma, Jnew, ok, xn, un
