"""iLQR/DDP's direction: the regularised Newton step of the second-order expansion.

Background: Li & Todorov (2004), Tassa, Erez & Todorov (2012), Tassa, Mansard & Todorov
(2014), and Section III of Lieskovský, Bušek & Vyhlídal, "Continuous-time iterative
linear-quadratic regulator" (2025), whose discrete counterparts these are:

* backward pass: the LQ subproblem in deviation coordinates with the second-order cost
  expansion (``l_xx, l_uu, l_ux, l_x, l_u``) and linearised dynamics, solved by
  :func:`torchslq.riccati_backward` with a Levenberg-Marquardt term ``mu I`` on ``Quu``
  (per element, in the solve's state: increased on a failed factorisation or line
  search, decreased on success, within ``[mu_min, mu_max]``); optionally the cost
  Hessian's eigenvalues are clipped from below (``hessian_floor``);
* DDP adds the dynamics' second-order terms ``V'_x · f_zz`` (vector-Hessian products by
  ``torch.func``): with the value gradient ``v_{t+1}`` inside the Riccati pass
  (``second_order="value"``, Mayne 1966) or with the costates ``lam_{t+1}`` of the
  nominal trajectory (``"costate"``: Newton's method on ``J(U)``);
* control bounds: the box QP for the feedforward term within the bounds on
  ``δu = u - ū`` inside the kernel (``u_bounds``), the clamped rows' feedback set to
  zero; the gradient test uses the projected gradient ``u - clip(u - ∇J)``.

The forward pass is :class:`~torchslq.solvers.descent.LineSearch` with the feedback
rollout and Armijo on the expected improvement ``α k'Q_u + α²/2 k'Q_uu k``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .._pinned import pinned
from .._shapes import broadcast_shapes
from ..costs.general import project_psd
from ..dynamics.linearize import (
    dynamics_vhp,
    linearize,
    linearize_with_hessians,
    linearize_with_vhp,
)
from ..dynamics.rollout import costate_gradient
from ..lq.regularization import RegularizationSchedule
from ..lq.riccati import RiccatiFactors, StageHook, failed_or_nonfinite, riccati_backward
from ..status import Status
from .descent import DescentState, nonfinite_rows

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["RegularizedNewton", "active_bounds", "bounds_with_faults", "resolve_bounds"]


def active_bounds(u: Tensor, lo: Tensor, hi: Tensor, rtol: float | None = None) -> Tensor:
    """``int8`` tensor shaped like ``u``: ``-1`` where ``u`` is at ``lo``, ``+1`` at ``hi``
    (within ``rtol (1 + |bound|)``, default ``sqrt(eps)`` of the dtype), ``0`` elsewhere."""
    if rtol is None:
        rtol = torch.finfo(u.dtype).eps ** 0.5
    at_lo = torch.isfinite(lo) & ((u - lo).abs() <= rtol * (1 + lo.abs()))
    at_hi = torch.isfinite(hi) & ((u - hi).abs() <= rtol * (1 + hi.abs()))
    out = torch.zeros(u.shape, dtype=torch.int8, device=u.device)
    out = torch.where(at_lo, torch.full_like(out, -1), out)
    return torch.where(at_hi & ~at_lo, torch.ones_like(out), out)


def bounds_with_faults(
    problem: Problem, x0: Tensor, u_min: float | Tensor | None, u_max: float | Tensor | None
) -> tuple[Tensor, Tensor, Tensor]:
    """``u_min``/``u_max`` (float, ``(m,)``, ``(T, m)`` or ``(B, T, m)``, None: unbounded)
    as ``(B, T, m)`` tensors on ``x0``'s device and dtype, and ``(B,)`` int64 status
    codes of the elements whose own bounds are invalid (the granularity rule of
    :class:`torchslq.Status`): ``NON_FINITE`` for a NaN, ``INFEASIBLE`` for an empty box
    (``u_min > u_max``, ``u_min = +inf`` or ``u_max = -inf``), ``RUNNING`` elsewhere;
    those elements get the unbounded box. A bad shape, or a fault in bounds shared by the
    batch, is a ValueError naming the argument."""
    Bsz, T, m = x0.shape[0], problem.horizon, problem.control_dim
    out, per_element = [], []
    for name, val, fill in (("u_min", u_min, -float("inf")), ("u_max", u_max, float("inf"))):
        if val is None:
            out.append(x0.new_full((Bsz, T, m), fill))
            per_element.append(False)
            continue
        b = torch.as_tensor(val, dtype=x0.dtype, device=x0.device)
        ok = (
            b.ndim == 0
            or (b.ndim == 1 and b.shape == (m,))
            or (b.ndim == 2 and b.shape == (T, m))
            or (b.ndim == 3 and b.shape[1:] == (T, m) and b.shape[0] in (1, Bsz))
        )
        if not ok:
            raise ValueError(
                f"{name} must be a float or a tensor of shape ({m},), ({T}, {m}) or "
                f"({Bsz}, {T}, {m}), got {tuple(b.shape)}"
            )
        own = b.ndim == 3 and b.shape[0] == Bsz and Bsz > 1
        if not own and bool(torch.isnan(b).any()):
            raise ValueError(f"{name} contains NaN")
        out.append(b.expand(Bsz, T, m))
        per_element.append(own)
    lo, hi = out
    nan = (lo.isnan() | hi.isnan()).flatten(1).any(1)
    empty = ((lo > hi) | (lo == float("inf")) | (hi == -float("inf"))).flatten(1).any(1)
    if not any(per_element):  # shared bounds: a fault is an error for the batch
        if bool(empty.any()):
            raise ValueError(
                "u_min must be <= u_max everywhere (u_min cannot be +inf, u_max cannot be -inf)"
            )
    faults = torch.full((Bsz,), int(Status.RUNNING), dtype=torch.int64, device=x0.device)
    faults = faults.masked_fill(empty & ~nan, int(Status.INFEASIBLE))
    faults = faults.masked_fill(nan, int(Status.NON_FINITE))
    bad = (faults != Status.RUNNING).view(-1, 1, 1)
    if bool(bad.any()):
        lo = torch.where(bad, -float("inf"), lo)
        hi = torch.where(bad, float("inf"), hi)
    return lo, hi, faults


def resolve_bounds(
    problem: Problem, x0: Tensor, u_min: float | Tensor | None, u_max: float | Tensor | None
) -> tuple[Tensor, Tensor]:
    """The bounds of :func:`bounds_with_faults`, as ``(B, T, m)`` tensors (elements with
    invalid per-element bounds get the unbounded box: their solve has a status)."""
    lo, hi, _ = bounds_with_faults(problem, x0, u_min, u_max)
    return lo, hi


# ---------------------------------------------------------------------------- factors
def _merge_factors(mask: Tensor, a: RiccatiFactors, b: RiccatiFactors) -> RiccatiFactors:
    """Per element: ``a``'s factors where ``mask`` (``(B,)`` bool), else ``b``'s."""

    def pick(ta: Tensor | None, tb: Tensor | None) -> Tensor | None:
        if ta is None or tb is None:
            return tb
        return torch.where(mask.view(-1, *([1] * (ta.ndim - 1))), ta, tb)

    return RiccatiFactors(
        **{f.name: pick(getattr(a, f.name), getattr(b, f.name)) for f in fields(RiccatiFactors)}
    )


# ---------------------------------------------------------------------------- DDP terms
class HessianHook:
    """Stage hook ``v_{t+1} · f_zz(t)`` from precomputed output Hessians.

    ``Hxx (n, B, T, n, n)``, ``Huu (n, B, T, m, m)``, ``Hux (n, B, T, m, n)``: the
    Hessians of output ``i`` at step ``t`` of element ``b``
    (:func:`~torchslq.dynamics.dynamics_hessians`' layout). The compiled Riccati kernel
    reads them as they are (:attr:`hessians`); the torch path contracts ``Hz (T, n, B,
    m+n, m+n)``, the same in the kernel's ``[u; x]`` ordering, time-major, built on its
    first use. :meth:`subset` restricts them to some elements.
    """

    def __init__(self, Hxx: Tensor, Huu: Tensor, Hux: Tensor):
        self.blocks = (Hxx, Huu, Hux)
        self._Hz: Tensor | None = None

    @property
    def hessians(self) -> tuple[Tensor, Tensor, Tensor]:
        """``(Hxx, Huu, Hux)``, for the compiled Riccati kernel (which contracts them)."""
        return self.blocks

    @property
    def Hz(self) -> Tensor:
        if self._Hz is None:
            self._Hz = hessian_block(*(h.movedim(2, 0) for h in self.blocks))
        return self._Hz

    def __call__(self, t: int, Vh_next: Tensor) -> Tensor:
        Hz = self.Hz
        n = Hz.shape[1]
        s = Vh_next[..., :n, n]  # v_{t+1}, (B, n)
        # a broadcast product summed over the outputs: measured 1.6x faster than einsum
        return (s.mT.unsqueeze(-1).unsqueeze(-1) * Hz[t]).sum(0)

    def subset(self, idx: Tensor) -> HessianHook:
        return HessianHook(*(h.index_select(1, idx) for h in self.blocks))


def hessian_block(Hxx: Tensor, Huu: Tensor, Hux: Tensor) -> Tensor:
    """``[[Huu, Hux], [Hux', Hxx]]``: the Hessian in the kernel's ``[u; x]`` ordering,
    written block by block into one new tensor (each entry written once)."""
    m, n = Hux.shape[-2], Hux.shape[-1]
    lead = broadcast_shapes(Hxx.shape[:-2], Huu.shape[:-2], Hux.shape[:-2])
    out = Hxx.new_empty(*lead, m + n, m + n)
    out[..., :m, :m] = Huu
    out[..., :m, m:] = Hux
    out[..., m:, :m] = Hux.mT
    out[..., m:, m:] = Hxx
    return out


# ---------------------------------------------------------------------------- direction
@dataclass(frozen=True)
class RegularizedNewton:
    """iLQR (``second_order=None``) and DDP (``"value"``/``"costate"``) directions.

    Args:
        schedule: the Levenberg-Marquardt schedule of ``mu`` (Tassa et al. 2012), whose
            restarts of a failed factorisation :func:`riccati_backward` makes.
        mu_init: the regularisation at the start of a solve.
        hessian_floor: clip the cost Hessians' eigenvalues to at least this (None: off).
        second_order: None (iLQR), ``"value"`` or ``"costate"`` (DDP).
        vhp_memory_limit: ``"value"``: take all output Hessians at once when they fit in
            this many bytes, else one product per step inside the pass.
        skip_tol: the gradient tolerance of the loop's stopping test when it stops on the
            gradient alone (None otherwise): when every running element passes it from
            the second iteration on, the pass is skipped (its step would be discarded).
    """

    schedule: RegularizationSchedule = RegularizationSchedule()
    mu_init: float = 0.0
    hessian_floor: float | None = None
    second_order: str | None = None
    vhp_memory_limit: int | None = 256 * 2**20
    skip_tol: float | None = None
    linearize_method: str = "auto"

    # ------------------------------------------------------------------ expansions
    def _expansion(self, problem: Problem, x: Tensor, u: Tensor):
        e = problem.cost.quadratize(x, u)
        if self.hessian_floor is None:
            return e
        return _floored(problem, e, self.hessian_floor)

    def _all_hessians(self, problem: Problem, x: Tensor) -> bool:
        """Whether the value mode takes all ``n`` output Hessians of every step at once."""
        if self.vhp_memory_limit is None:
            return False
        n, m, T = problem.state_dim, problem.control_dim, problem.horizon
        need = x.shape[0] * T * n * (n + m) ** 2 * x.element_size()
        return need <= self.vhp_memory_limit

    def _linearize(self, problem: Problem, x: Tensor, u: Tensor):
        """``(A, B, vhp)`` at the steps ``(x_t, u_t)``: ``vhp`` shares the model's work
        with the Jacobians where the DDP mode needs second derivatives."""
        method = self.linearize_method
        f = problem.transition
        if self.second_order == "costate":
            return linearize_with_vhp(f, x, u, method=method)
        if self.second_order == "value" and self._all_hessians(problem, x):
            return linearize_with_hessians(f, x, u, method=method)
        A, B = linearize(f, x, u, method=method)
        return A, B, None

    def _second_order(self, problem, x, u, lam, e, vhp) -> StageHook | None:
        if self.second_order is None:
            return None
        n, T = problem.state_dim, problem.horizon
        if self.second_order == "costate":
            Hxx, Huu, Hux = vhp(lam[:, 1:])  # shares the linearisation's RK4 stages
            Bsz = x.shape[0]
            e.lxx = e.lxx.expand(Bsz, *e.lxx.shape[1:]).clone()
            e.lxx[:, :T] += Hxx
            e.luu = e.luu.expand(Bsz, *e.luu.shape[1:]) + Huu
            e.lux = Hux if e.lux is None else e.lux.expand_as(Hux) + Hux
            return None
        if vhp is not None:
            # every output's Hessians of all steps: contracted with v_{t+1} in the pass
            return HessianHook(*vhp())
        f = problem.transition

        def hook(t: int, Vh_next: Tensor) -> Tensor:
            s = Vh_next[..., :n, n].unsqueeze(-2)  # v_{t+1}, (B, 1, n)
            Hxx, Huu, Hux = dynamics_vhp(f, x[:, t : t + 1], u[:, t : t + 1], s)
            return hessian_block(Hxx, Huu, Hux)[:, 0]  # [u; x] ordering

        return hook

    # ------------------------------------------------------------------ the step
    def __call__(self, problem: Problem, state: DescentState, running: Tensor, it: int):
        x, u = state.x, state.u
        T = problem.horizon
        A, B, vhp = self._linearize(problem, x[:, :T], u)
        e = self._expansion(problem, x, u)
        grad, lam = costate_gradient(A, B, e.lx, e.lu)
        lo, hi = state.lo, state.hi
        if lo is not None:
            grad = u - torch.minimum(torch.maximum(u - grad, lo), hi)  # projected gradient
        done = grad_norm = None
        if self.skip_tol is not None and it > 0:
            grad_norm = grad.flatten(1).norm(dim=1)
            done = grad_norm < self.skip_tol
            if bool((done | ~running).all()):
                # every step would be discarded: skip the second-order terms and the pass
                return _no_step(x, u, grad) | {"grad_norm": grad_norm}, state
        hook = self._second_order(problem, x, u, lam, e, vhp)
        u_bounds = None if lo is None else (lo - u, hi - u)  # bounds on δu at ū = u
        fac, bad, mu, delta = self._regularized_pass(A, B, e, hook, u_bounds, state, running)
        if hook is not None and bool((bad & running).any()):
            # the second-order terms made the pass fail for good (regularising Quu does
            # not bound an indefinite Qxx): those elements take the iLQR step instead
            fac_gn, bad_gn = _pass(A, B, e, None, u_bounds, mu)
            fac, bad = (
                _merge_factors(bad & running, fac_gn, fac),
                torch.where(bad & running, bad_gn, bad),
            )
        # an element that needed mu > mu_max to factorise stops (not_positive_definite),
        # unless its linearisation or cost expansion is not finite (non_finite)
        failed = bad | (mu > self.schedule.reg_max)
        nonfinite = None
        if bool(failed.any()):
            nonfinite = failed & nonfinite_rows(A, B, e.lx, e.lu)
        k = fac.k
        if fac.dV is None:
            Lk = (fac.chol.mT @ k.unsqueeze(-1))[..., 0]  # k'Quu k = |L'k|^2
            curv = Lk.pow(2).sum(dim=(-1, -2))
            slope = -curv  # k'Qu = -k'Quu k
        else:
            slope, curv = fac.dV[..., 0], fac.dV[..., 1]
        d = {
            "du": k,  # feedforward direction: the line search adds alpha * k
            "K": fac.K,
            "k": k,
            "grad": grad,
            "slope": slope,
            "curvature": curv,
            "failed": failed,
            "dx": torch.zeros_like(x),
        }
        if fac.clamped is not None:
            d["clamped"] = fac.clamped
        if nonfinite is not None:
            d["nonfinite"] = nonfinite
        if done is not None:
            d["keep_gains"] = ~done
            d["grad_norm"] = grad_norm
        return d, state.updated(mu=mu, delta=delta)

    def _regularized_pass(self, A, B, e, hook, u_bounds, state, running):
        """The Riccati pass with Tassa et al.'s restarts of the running elements whose
        factorisation fails (inside :func:`riccati_backward`, the same on every backend):
        ``(factors, failed, mu, delta)``."""
        restarts = self.schedule.restarts(state.delta, running)
        fac, bad = _pass(A, B, e, hook, u_bounds, state.mu, restarts=restarts)
        return fac, bad, fac.reg, fac.reg_delta

    def after_search(self, state: DescentState, running: Tensor, ok: Tensor):
        """Adapt ``mu`` (decrease after an accepted step, increase after a failed search);
        an element whose ``mu`` would exceed ``mu_max`` ends (``line_search_failed``)."""
        sched = self.schedule
        mu, delta = sched.decrease(state.mu, state.delta, running & ok)
        mu, delta = sched.increase(mu, delta, running & ~ok)
        return state.updated(mu=mu, delta=delta), running & ~ok & (mu > sched.reg_max)


def _floored(problem: Problem, e, floor: float):
    """The cost expansion ``e`` with the eigenvalues of every joint stage Hessian
    ``[[l_xx, l_ux'], [l_ux, l_uu]]`` and of the terminal ``l_xx`` clipped to at least
    ``floor`` (a Hessian shared by the batch is projected once; Hessians that are the
    same tensors as at the previous call in the solve, as a quadratic cost's weights
    are, once per solve)."""
    # per solve: the last Hessians projected and their projection (the tensors are held,
    # so an identity test cannot match a later tensor at their address)
    held = pinned(problem.cost, ("psd_floor", floor, problem.horizon), dict)
    inputs = (e.lxx, e.luu, e.lux)
    hit = held.get("last")
    if hit is not None and all(a is b for a, b in zip(hit[0], inputs, strict=True)):
        e.lxx, e.luu, e.lux = hit[1]
        return e
    _project_hessians(problem, e, floor)
    held["last"] = (inputs, (e.lxx, e.luu, e.lux))
    return e


def _project_hessians(problem: Problem, e, floor: float) -> None:
    """:func:`_floored`'s projection, into ``e``."""
    n, m, T = problem.state_dim, problem.control_dim, problem.horizon
    lux = e.lux if e.lux is not None else e.luu.new_zeros(*e.luu.shape[:-1], n)
    nb = broadcast_shapes(e.lxx.shape[:-3], e.luu.shape[:-3], lux.shape[:-3]).numel()
    lxx = e.lxx.expand(nb, *e.lxx.shape[-3:])
    luu = e.luu.expand(nb, T, m, m)
    lux = lux.expand(nb, T, m, n)
    H = torch.cat([torch.cat([lxx[:, :T], lux.mT], -1), torch.cat([lux, luu], -1)], -2)
    H = project_psd(H, floor)
    lxxT = project_psd(lxx[:, T], floor)
    e.lxx = torch.cat([H[..., :n, :n], lxxT.unsqueeze(1)], 1)
    e.luu, e.lux = H[..., n:, n:], H[..., n:, :n]


def _pass(A, B, e, hook, u_bounds, reg, restarts=None, c=None):
    """One Riccati pass: ``(factors, failed)`` (non-finite gains count as a failure);
    ``c (B, T, n)``: affine dynamics terms (multiple shooting's defects)."""
    fac = riccati_backward(
        A, B, e.lxx, e.luu, e.lx, e.lu, e.lux, c,
        reg=reg, stage_hook=hook, u_bounds=u_bounds, restarts=restarts,
    )  # fmt: skip
    if restarts is not None:  # its failures count non-finite gains already (every backend)
        return fac, fac.failed
    return fac, failed_or_nonfinite(fac)


def _no_step(x: Tensor, u: Tensor, grad: Tensor) -> dict[str, Tensor]:
    """The direction when every running element already passes the gradient test: no
    step, and the loop keeps the previous gains."""
    Bsz, T, m = u.shape
    zeros = grad.new_zeros(Bsz)
    return {
        "du": torch.zeros_like(u),
        "K": u.new_zeros(Bsz, T, m, x.shape[-1]),
        "k": torch.zeros_like(u),
        "grad": grad,
        "slope": zeros,
        "curvature": zeros,
        "failed": torch.zeros(Bsz, dtype=torch.bool, device=u.device),
        "dx": torch.zeros_like(x),
        "keep_gains": torch.zeros(Bsz, dtype=torch.bool, device=u.device),
    }
