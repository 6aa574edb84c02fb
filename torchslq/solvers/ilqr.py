"""iLQR (and its second-order-dynamics sibling DDP) on the shared LQ kernel.

Background: Li & Todorov (2004), Tassa, Erez & Todorov (2012), and Section III of
Lieskovsky et al. (2025) (``shared/papers/continuous-time-ilqr-2025.md``) whose
discrete counterparts these are:

* backward pass: the LQ subproblem in deviation coordinates with the second-order cost
  expansion (``l_xx, l_uu, l_ux, l_x, l_u``) and linearised dynamics, solved by
  :func:`torchslq.riccati_backward` with a Levenberg-Marquardt term ``mu I`` on ``Quu``
  (per element, adapted: increased on a failed factorisation or line search,
  decreased on success, within ``[mu_min, mu_max]``); optionally the cost Hessian's
  eigenvalues are clipped from below (``lambda := max(lambda, hessian_floor)``);
* forward pass: ``u = ū + α k + K (x - x̄)`` for a set of ``α`` at once (one batched
  rollout), accepted by Armijo on the expected improvement
  ``ΔV(α) = α k'Q_u + α²/2 k'Q_uu k`` (eqs. 14-15 of the paper, discrete form);
* stopping: norm of the gradient of ``J(U)`` (costate pass) below ``tol`` or relative
  cost change below ``rtol``.

Control bounds (``u_min``, ``u_max``): control-limited DDP of Tassa, Mansard & Todorov
(2014). The backward pass solves, per step, the box QP for the feedforward term within
the bounds on the deviation ``δu = u - ū`` (:func:`torchslq.lq.box_qp`, inside the
kernel via its ``u_bounds`` argument), with the clamped controls' feedback rows set to
zero; the line-search rollout clamps ``u`` into the box; the expected improvement is
``α k'Q_u + α²/2 k'Q_uu k`` with the box-QP ``k``; the stopping test uses the norm of the
projected gradient ``u - clip(u - ∇J)`` (reported as ``grad_norm``), and
``SolverResult.active_bounds`` marks the controls at a bound.

The solve loop (batching, per-element masks and status, history, logging) is SLQ's.
"""

from __future__ import annotations

from dataclasses import fields
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from ..costs.general import project_psd
from ..dynamics.linearize import linearize
from ..lq.riccati import Restarts, RiccatiFactors, StageHook, riccati_backward
from .line_search import TrialRecorder
from .rollout import costate_gradient, rollout_closed_loop
from .slq import SLQ, _checked_x_init

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["ILQR", "active_bounds"]


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


def _no_step(x: Tensor, u: Tensor, grad: Tensor) -> dict[str, Tensor]:
    """:meth:`ILQR.direction`'s output when every running element already passes the
    gradient test: no step, and the solve loop keeps the previous gains."""
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


def _merge_factors(mask: Tensor, a: RiccatiFactors, b: RiccatiFactors) -> RiccatiFactors:
    """Per element: ``a``'s factors where ``mask`` (``(B,)`` bool), else ``b``'s."""

    def pick(ta: Tensor | None, tb: Tensor | None) -> Tensor | None:
        if ta is None or tb is None:
            return tb
        return torch.where(mask.view(-1, *([1] * (ta.ndim - 1))), ta, tb)

    return RiccatiFactors(
        **{f.name: pick(getattr(a, f.name), getattr(b, f.name)) for f in fields(RiccatiFactors)}
    )


# restarts of a failed Riccati pass per iteration (Tassa et al.'s regularisation), and the
# most rows one pass of side-by-side restarts may have (failing elements x candidates;
# a constant, so that the passes an element needs do not depend on the batch around it)
MAX_RETRIES = 8
RETRY_ROWS = 2048


def _take_factors(fac: RiccatiFactors, rows: Tensor) -> RiccatiFactors:
    """The factors of the elements ``rows`` (an index tensor)."""

    def take(t: Tensor | None) -> Tensor | None:
        return None if t is None else t.index_select(0, rows)

    return RiccatiFactors(**{f.name: take(getattr(fac, f.name)) for f in fields(RiccatiFactors)})


def _scatter_factors(full: RiccatiFactors, idx: Tensor, part: RiccatiFactors) -> RiccatiFactors:
    """``full`` with rows ``idx`` replaced by ``part`` (a pass repeated for ``idx`` only)."""

    def put(ta: Tensor | None, tb: Tensor | None) -> Tensor | None:
        if ta is None or tb is None:
            return ta
        return ta.index_copy(0, idx, tb.expand(idx.shape[0], *ta.shape[1:]))

    return RiccatiFactors(
        **{
            f.name: put(getattr(full, f.name), getattr(part, f.name))
            for f in fields(RiccatiFactors)
        }
    )


class ILQR(SLQ):
    """Iterative LQR for general costs (any cost with ``quadratize``).

    Args:
        max_iter, tol: iteration limit and gradient-norm tolerance.
        rtol: stop also when ``|J_k - J_{k+1}| <= rtol |J_k|`` after an accepted step
            (0 disables).
        mu_init, mu_min, mu_max, mu_factor: Levenberg-Marquardt regularisation on ``Quu``
            (Tassa et al. 2012 schedule, per element). An element whose ``mu`` would have
            to exceed ``mu_max`` stops: with status ``not_positive_definite`` when
            ``Quu + mu I`` cannot be factorised, ``line_search_failed`` when its line
            searches keep failing.
        hessian_floor: when set, the eigenvalues of every stage cost Hessian (the joint
            ``(n+m)`` block) and of the terminal Hessian are clipped to at least this
            value (the paper uses ``sqrt(eps)``); None leaves them as they are.
        armijo_c1, armijo_beta, max_backtracks: line search on the expected improvement;
            armijo_passes: how many trials each batched pass rolls out (as for
            :class:`torchslq.SLQ`; the accepted steps do not depend on it).
        u_min, u_max: optional control bounds, a float or a tensor of shape ``(m,)``,
            ``(T, m)`` or ``(B, T, m)`` (``-inf``/``+inf`` entries allowed; None: no
            bound on that side). ``u_init`` is clamped into the box. When every bound is
            infinite the solve is exactly the unconstrained one.
        progress, linearize_method: as for :class:`torchslq.SLQ`.
    """

    name = "ilqr"
    _per_element_state = ("_mu", "_delta", "_lo", "_hi")

    def __init__(
        self,
        max_iter: int = 100,
        tol: float = 1e-6,
        mu_init: float = 0.0,
        mu_min: float = 1e-6,
        mu_max: float = 1e10,
        mu_factor: float = 2.0,
        hessian_floor: float | None = None,
        u_min: float | Tensor | None = None,
        u_max: float | Tensor | None = None,
        **kwargs: Any,
    ):
        kwargs.setdefault("line_search", "armijo")
        kwargs.setdefault("rollout", "closed_loop")
        super().__init__(max_iter=max_iter, tol=tol, **kwargs)
        self.options.rtol = float(self.options.rtol)
        if self.options.rollout != "closed_loop" or self.options.line_search != "armijo":
            raise ValueError("ILQR uses rollout='closed_loop' and line_search='armijo'")
        if not (0 <= mu_min <= mu_max) or mu_init < 0 or mu_factor <= 1:
            raise ValueError("need 0 <= mu_min <= mu_max, mu_init >= 0 and mu_factor > 1")
        if self.options.rtol < 0:
            raise ValueError(f"rtol must be >= 0, got {self.options.rtol!r}")
        self.mu_init, self.mu_min, self.mu_max, self.mu_factor = mu_init, mu_min, mu_max, mu_factor
        self.hessian_floor = hessian_floor
        self.u_min, self.u_max = u_min, u_max
        self._lo: Tensor | None = None
        self._hi: Tensor | None = None

    # -------------------------------------------------------------- control bounds
    def _resolve_bounds(self, problem: Problem, x0: Tensor) -> tuple[Tensor, Tensor]:
        """``u_min``/``u_max`` as ``(B, T, m)`` tensors on ``x0``'s device and dtype."""
        Bsz, T, m = x0.shape[0], problem.horizon, problem.control_dim
        out = []
        for name, val, fill in (
            ("u_min", self.u_min, -float("inf")),
            ("u_max", self.u_max, float("inf")),
        ):
            if val is None:
                out.append(x0.new_full((Bsz, T, m), fill))
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
            if bool(torch.isnan(b).any()):
                raise ValueError(f"{name} contains NaN")
            out.append(b.expand(Bsz, T, m))
        lo, hi = out
        if bool((lo > hi).any()):
            raise ValueError("u_min must be <= u_max everywhere")
        if bool((lo == float("inf")).any()) or bool((hi == -float("inf")).any()):
            raise ValueError("u_min cannot be +inf and u_max cannot be -inf")
        return lo, hi

    def solve(
        self,
        problem: Problem,
        x0: Tensor,
        u_init: Tensor | None = None,
        logger: Any = None,
        *,
        x_init: Tensor | None = None,
    ):
        """As :meth:`torchslq.SLQ.solve`; with ``u_min``/``u_max`` the solve is
        control-limited and the result carries ``active_bounds`` (an ``x_init`` is then
        used only if ``u_init`` is within the bounds: clamping changes its rollout)."""
        if self.u_min is None and self.u_max is None:
            return super().solve(problem, x0, u_init, logger, x_init=x_init)
        x0b, u0, unbatched = problem.check_inputs(x0, u_init)
        lo, hi = self._resolve_bounds(problem, x0b)
        u = torch.minimum(torch.maximum(u0, lo), hi)
        if x_init is not None:
            x_init = _checked_x_init(x_init, x0b, problem.horizon)
            if not torch.equal(u, u0):
                x_init = None  # the rollout of other controls
        bounded = not (bool(torch.isinf(lo).all()) and bool(torch.isinf(hi).all()))
        self._lo, self._hi = (lo, hi) if bounded else (None, None)
        try:
            result = super().solve(problem, x0, u, logger, x_init=x_init)
        finally:
            self._lo = self._hi = None
        if unbatched:
            lo, hi = lo[0], hi[0]
        result.active_bounds = active_bounds(result.u, lo, hi)
        return result

    # -------------------------------------------------------------- per-solve state
    def _begin(self, x0: Tensor) -> None:
        Bsz = x0.shape[0]
        self._mu = torch.full((Bsz,), float(self.mu_init), dtype=x0.dtype, device=x0.device)
        self._delta = torch.ones_like(self._mu)

    def _expansion(self, problem: Problem, x: Tensor, u: Tensor):
        e = problem.cost.quadratize(x, u)
        if self.hessian_floor is None:
            return e
        n, m, T = problem.state_dim, problem.control_dim, problem.horizon
        lux = e.lux if e.lux is not None else e.luu.new_zeros(*e.luu.shape[:-1], n)
        lxx = e.lxx.expand(x.shape[0], *e.lxx.shape[1:])
        luu = e.luu.expand(x.shape[0], T, m, m)
        lux = lux.expand(x.shape[0], T, m, n)
        H = torch.cat([torch.cat([lxx[:, :T], lux.mT], -1), torch.cat([lux, luu], -1)], -2)
        H = project_psd(H, self.hessian_floor)
        lxxT = project_psd(lxx[:, T], self.hessian_floor)
        e.lxx = torch.cat([H[..., :n, :n], lxxT.unsqueeze(1)], 1)
        e.luu, e.lux = H[..., n:, n:], H[..., n:, :n]
        return e

    # -------------------------------------------------------------- backward pass
    def direction(self, problem: Problem, x: Tensor, u: Tensor) -> dict[str, Tensor]:
        """Backward pass at ``(x, u)`` with per-element regularisation ``mu``.

        Elements whose ``Quu + mu I`` is not positive definite get a larger ``mu`` and
        the pass is repeated for the batch (at most a few times per iteration); those
        still failing are reported in ``failed``.
        """
        T = problem.horizon
        A, B, vhp = self._linearize(problem, x[:, :T], u)
        e = self._expansion(problem, x, u)
        grad, lam = costate_gradient(A, B, e.lx, e.lu)
        if getattr(self, "_running", None) is None or self._running.shape[0] != x.shape[0]:
            self._running = torch.ones(x.shape[0], dtype=torch.bool, device=x.device)
        mu = getattr(self, "_mu", None)
        if mu is None or mu.shape[0] != x.shape[0]:
            self._begin(x[:, 0])
        lo, hi = getattr(self, "_lo", None), getattr(self, "_hi", None)
        if lo is not None:
            grad = u - torch.minimum(torch.maximum(u - grad, lo), hi)  # projected gradient
        done = self._converged_by_gradient(grad)
        if done is not None and bool((done | ~self._running).all()):
            # every step would be discarded: skip the second-order terms and the pass
            return _no_step(x, u, grad)
        hook = self._second_order(problem, x, u, lam, e, vhp)
        u_bounds = None if lo is None else (lo - u, hi - u)  # bounds on δu at ū = u

        def backward_pass(
            stage_hook,
            idx: Tensor | None = None,
            reg: Tensor | None = None,
            restarts: Restarts | None = None,
        ):
            """The Riccati pass for the whole batch, or for the rows ``idx`` only (a
            retry: the pass costs per element, so only the failing ones repeat it; rows
            may repeat, each with its own ``reg``)."""

            def rows(t: Tensor | None, tail: int) -> Tensor | None:
                if idx is None or t is None or t.ndim <= tail or t.shape[0] == 1:
                    return t  # no batch dim, or one shared by every element
                return t.index_select(0, idx)

            bounds = None if u_bounds is None else tuple(rows(b, 2) for b in u_bounds)
            fac = riccati_backward(
                rows(A, 3),
                rows(B, 3),
                rows(e.lxx, 3),
                rows(e.luu, 3),
                rows(e.lx, 2),
                rows(e.lu, 2),
                rows(e.lux, 3),
                reg=rows(self._mu, 0) if reg is None else reg,
                stage_hook=stage_hook
                if idx is None or stage_hook is None
                else stage_hook.subset(idx),
                u_bounds=bounds,
                restarts=restarts,
            )
            # a factorisation can succeed and still give non-finite gains (DDP's
            # second-order terms can make the value function overflow): a failure too
            return fac, fac.failed | ~torch.isfinite(fac.Kk).flatten(1).all(1)

        fac, bad = backward_pass(hook, restarts=self._restarts())
        if fac.reg is not None:  # the compiled kernel made the restarts itself
            self._mu, self._delta = fac.reg, fac.reg_delta
        elif hook is not None and not hasattr(hook, "subset"):
            for _ in range(MAX_RETRIES):  # a hook that cannot be restricted: whole batch
                retry = bad & self._running & (self._mu <= self.mu_max)
                if not bool(retry.any()):
                    break
                self._increase_mu(retry)
                fac, bad = backward_pass(hook)
        else:
            fac, bad = self._retry_failed(backward_pass, hook, fac, bad)
        if hook is not None and bool((bad & self._running).any()):
            # the second-order terms made the pass fail for good (regularising Quu does
            # not bound an indefinite Qxx): those elements take the iLQR step instead
            fac_gn, bad_gn = backward_pass(None)
            fac, bad = (
                _merge_factors(bad & self._running, fac_gn, fac),
                torch.where(bad & self._running, bad_gn, bad),
            )
        # an element that needed mu > mu_max to factorise stops (status
        # not_positive_definite, set by the solve loop from ``failed``)
        failed = bad | (self._mu > self.mu_max)
        k = fac.k
        if fac.dV is None:
            # k'Quu k = |L'k|^2 with L the Cholesky factor of the (regularised) Quu
            Lk = (fac.chol.mT @ k.unsqueeze(-1))[..., 0]
            curv = Lk.pow(2).sum(dim=(-1, -2))
            slope = -curv  # k'Qu = -k'Quu k
        else:
            slope, curv = fac.dV[..., 0], fac.dV[..., 1]
        return {
            "du": k,  # feedforward direction: the line search adds alpha * k
            "K": fac.K,
            "k": k,
            "grad": grad,
            "slope": slope,
            "curvature": curv,
            "failed": failed,
            "dx": torch.zeros_like(x),
            **({} if fac.clamped is None else {"clamped": fac.clamped}),
            **({} if done is None else {"keep_gains": ~done}),
        }

    def _restarts(self) -> Restarts:
        """The schedule of :meth:`_retry_failed`, for restarts inside the compiled Riccati
        kernel (no pass repeated from Python: for small problems a repeated pass costs
        mostly its dispatch)."""
        return Restarts(
            self._delta,
            self._running,
            float(self.mu_factor),
            self._mu_floor,
            float(self.mu_max),
            MAX_RETRIES,
        )

    def _retry_failed(self, backward_pass, hook, fac: RiccatiFactors, bad: Tensor):
        """Tassa et al.'s restart for the elements whose pass failed: raise ``mu`` (the
        same schedule as :meth:`_increase_mu`) and repeat the pass, up to
        ``MAX_RETRIES`` times, stopping at the first success or once ``mu > mu_max``.

        The next values of the schedule are tried side by side: the failing rows are
        repeated once per candidate ``mu`` in one pass (as many as fit in
        ``RETRY_ROWS_PER_ELEMENT`` times the batch size) and each element takes its first
        candidate that succeeds. The result equals the one-at-a-time restarts (rows are
        independent), but a pass is a dispatch-bound sweep over the horizon whatever its
        number of rows, so this saves most of the repeated passes (e.g. 69 of 100
        Riccati passes of a unicycle DDP solve were restarts).
        """
        tries = 0
        while tries < MAX_RETRIES:
            # retry only elements still iterating whose mu may still grow: a frozen
            # (e.g. non-finite) element must not make the others repeat their pass
            retry = bad & self._running & (self._mu <= self.mu_max)
            if not bool(retry.any()):
                break
            idx = retry.nonzero().squeeze(1)
            r = idx.shape[0]
            n_cand = max(1, min(MAX_RETRIES - tries, RETRY_ROWS // r))
            mu, delta = self._mu[idx], self._delta[idx]
            mus, deltas = [], []
            for _ in range(n_cand):
                mu, delta = self._increased(mu, delta)
                mus.append(mu)
                deltas.append(delta)
            M, D = torch.stack(mus), torch.stack(deltas)  # (n_cand, r)
            fac_r, bad_r = backward_pass(hook, idx.repeat(n_cand), M.reshape(-1))
            bad_r = bad_r.view(n_cand, r)
            # where one-at-a-time restarts stop: first success, or first mu > mu_max
            stop = ~bad_r | (M > self.mu_max)
            first = torch.argmax(stop.to(torch.int8), dim=0)
            c = torch.where(stop.any(0), first, torch.full_like(first, n_cand - 1))
            ar = torch.arange(r, device=idx.device)
            fac = _scatter_factors(fac, idx, _take_factors(fac_r, c * r + ar))
            bad = bad.index_copy(0, idx, bad_r[c, ar])
            self._mu = self._mu.index_copy(0, idx, M[c, ar])
            self._delta = self._delta.index_copy(0, idx, D[c, ar])
            tries += n_cand
        return fac, bad

    def _linearize(self, problem: Problem, x: Tensor, u: Tensor):
        """``(A, B, vhp)`` at the steps ``(x_t, u_t)``; iLQR needs no second derivatives
        (``vhp`` None, see :class:`torchslq.DDP`)."""
        A, B = linearize(problem.transition, x, u, method=self.options.linearize_method)
        return A, B, None

    def _second_order(
        self, problem: Problem, x: Tensor, u: Tensor, lam: Tensor, e, vhp=None
    ) -> StageHook | None:
        """Dynamics second-order terms: none for iLQR (see :class:`torchslq.DDP`)."""
        return None

    # -------------------------------------------------------------- regularisation
    def _increased(self, mu: Tensor, delta: Tensor) -> tuple[Tensor, Tensor]:
        """One increase of Tassa et al.'s schedule: ``delta := max(f, delta f)``,
        ``mu := max(mu_min, mu delta)``."""
        f = self.mu_factor
        delta = torch.maximum(torch.full_like(delta, f), delta * f)
        return torch.maximum(torch.full_like(mu, self._mu_floor), mu * delta), delta

    @property
    def _mu_floor(self) -> float:
        """The smallest ``mu`` an increase gives: ``mu_min``, or 1e-6 when that is zero (a
        zero ``mu`` cannot grow by scaling)."""
        return self.mu_min if self.mu_min > 0 else 1e-6

    def _increase_mu(self, mask: Tensor) -> None:
        mu, delta = self._increased(self._mu, self._delta)
        self._delta = torch.where(mask, delta, self._delta)
        self._mu = torch.where(mask, mu, self._mu)

    def _decrease_mu(self, mask: Tensor) -> None:
        f = self.mu_factor
        delta = torch.minimum(torch.full_like(self._delta, 1.0 / f), self._delta / f)
        mu = self._mu * delta
        mu = torch.where(mu < self.mu_min, torch.zeros_like(mu), mu)
        self._delta = torch.where(mask, delta, self._delta)
        self._mu = torch.where(mask, mu, self._mu)

    def _after_line_search(self, running: Tensor, ok: Tensor) -> Tensor:
        """Adapt ``mu``; returns the elements that failed for good (``mu > mu_max``)."""
        self._decrease_mu(running & ok)
        self._increase_mu(running & ~ok)
        return running & ~ok & (self._mu > self.mu_max)

    # -------------------------------------------------------------- forward pass
    def _line_search(self, f, cost_fn, x0, x, u, J, d) -> tuple[Tensor, ...]:
        trials = TrialRecorder()

        def evaluate(alphas: Tensor) -> Tensor:
            Na = alphas.shape[0]
            xc, uc = rollout_closed_loop(
                f, x0.expand(Na, *x0.shape), x, u, d["K"], d["k"], alphas, self._lo, self._hi
            )
            trials.record(alphas, xc, uc)
            return cost_fn(xc, uc)

        alpha, J_new, ok = self._armijo(evaluate, J, d, curvature=d["curvature"])
        x_new, u_new = trials.select(alpha)
        return alpha, J_new, ok, x_new, u_new
