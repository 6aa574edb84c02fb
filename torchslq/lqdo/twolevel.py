"""The two-level fixed-parameter method, TLFP (nested co-design; Sec. 4.2.2).

Lower level: for fixed static parameters ``p`` an LQDO-amenable problem is an LQDO
problem in ``w = (u, xi)``; its QP is the transcription's reference QP with ``p``
substituted (:meth:`~torchslq.lqdo.qp.SparseQP.fix`), exact whatever the reference.
Upper level: ``min_p v(p)`` over the parameter bounds.

Beyond the paper (which uses finite differences in the upper level): the exact gradient
``dv/dp`` comes from implicit differentiation of the lower level's KKT conditions. At the
solution ``(w*, lam*, mu*)`` the derivative of ``v(p) = L(w*(p), lam*(p), mu*(p), p)``
reduces to ``dL/dp`` with the KKT terms in ``dw*/dp`` and the multipliers' derivatives
vanishing (stationarity and complementarity), so one reverse pass through the
transcribed Lagrangian ``v(w, p) + lam' h(w, p) + mu' g(w, p)`` gives it for the whole
batch. Every evaluation is batched: many ``p`` (a batch of designs, or all the trial
steps of the upper-level line search) are one lower-level solve.

Upper level: a projected quasi-Newton method (BFGS per element, batched) in the
parameters scaled to ``[0, 1]`` by their bounds, logarithmically where they span two
decades or more (``p`` differ by orders of magnitude in the suspension), Armijo backtracking whose trial steps are evaluated in three batched passes (the full
step, the next three, the last eight); it stops when the projected gradient in the
scaled variables is below ``tol``, when a step no longer changes ``v`` (relative
``1e-12``), or when no step decreases ``v`` while the projected gradient is below
``1e3 tol`` (the accuracy of the lower-level solver is reached).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from torch import Tensor

from ..solvers.options import check_int, check_real
from ..status import Status
from .backends import QPSolution, solve
from .transcription import Transcription

__all__ = ["TwoLevel", "TLFPResult", "LowerLevel"]


@dataclass
class LowerLevel:
    """Lower-level solutions for a batch of parameters.

    Attributes:
        value: ``(B,)`` ``v(p)``; grad: ``(B, np)`` exact ``dv/dp``;
        z: ``(B, n)`` the full transcription variables (``p`` included);
        status: ``(B,)`` QP status; qp: the :class:`QPSolution`.
    """

    value: Tensor
    grad: Tensor
    z: Tensor
    status: Tensor
    qp: QPSolution


@dataclass
class TLFPResult:
    """Outcome of :meth:`TwoLevel.solve`: ``p (B, np)``, ``z (B, n)``, ``objective (B,)``,
    ``iterations (B,)`` upper-level iterations, ``evaluations`` lower-level batched
    solves, ``status (B,)``, ``time`` seconds, ``history`` of ``v`` per iteration."""

    p: Tensor
    z: Tensor
    objective: Tensor
    iterations: Tensor
    evaluations: int
    status: Tensor
    time: float
    history: list


class TwoLevel:
    """TLFP: nested co-design with exact upper-level gradients.

    Args:
        backend: ``"clarabel"``/``"osqp"`` (sparse CPU) or ``"dense"`` (batched torch).
        tol: projected-gradient tolerance in the bound-scaled parameters.
        max_iter: upper-level iteration limit.
        qp_options: passed to the QP backend.
    """

    def __init__(
        self,
        backend: str = "clarabel",
        tol: float = 1e-6,
        max_iter: int = 100,
        qp_options: dict | None = None,
    ) -> None:
        if backend not in ("clarabel", "osqp", "dense"):
            raise ValueError(f"backend must be 'clarabel', 'osqp' or 'dense'; got {backend!r}")
        check_int("max_iter", max_iter, 1)
        check_real("tol", tol, 0.0)
        self.backend, self.tol, self.max_iter = backend, tol, max_iter
        self.qp_options = dict(qp_options or {})

    # ------------------------------------------------------------------ lower level
    def lower(self, tr: Transcription, p: Tensor, gradient: bool = True) -> LowerLevel:
        """Solve the lower-level LQDO QP for every row of ``p (B, np)`` at once and return
        ``v(p)`` with its exact gradient (see the module docstring)."""
        if not isinstance(tr, Transcription):
            raise TypeError(f"tr must be a Transcription; got {type(tr).__name__}")
        P = tr.problem
        if P.np == 0:
            raise ValueError("the problem has no static parameters (np = 0)")
        p = tr.as_batch("p", p, P.np)
        B = p.shape[0]
        mask = torch.zeros(tr.n, dtype=torch.bool, device=p.device)
        mask[tr.idx_p] = True
        zref = torch.zeros(B, tr.n, dtype=tr.dtype, device=p.device)
        zref[:, mask] = p
        red = tr.qp(zref).fix(mask, p)
        sol = solve(red, self.backend, **self.qp_options)
        # the parameters are the last variables of z (eq. 3)
        z = torch.cat([sol.z.detach(), p.detach()], 1)
        grad = p.new_zeros(B, P.np)
        if gradient:
            with torch.enable_grad():
                pp = p.detach().requires_grad_(True)
                zz = torch.cat([z[:, : tr.off_p], pp], 1)
                v = tr.objective(zz)
                L = v + (sol.lam.detach() * tr.equalities(zz)).sum(1)
                if tr.mi:
                    L = L + (sol.mu.detach() * tr.inequalities(zz)).sum(1)
                grad = torch.autograd.grad(L.sum(), pp)[0]
            value = v.detach()  # zz holds the numbers of z
        else:
            value = tr.objective(z).detach()
        return LowerLevel(value=value, grad=grad.detach(), z=z, status=sol.status, qp=sol)

    # ------------------------------------------------------------------ upper level
    def solve(self, tr: Transcription, p0: Tensor) -> TLFPResult:
        """Minimise ``v(p)`` over the parameter bounds from ``p0 (B, np)`` (a batch of
        starting designs, or of problems that differ in ``initial``/``final``)."""
        t0 = time.perf_counter()
        if not isinstance(tr, Transcription):
            raise TypeError(f"tr must be a Transcription; got {type(tr).__name__}")
        P = tr.problem
        if P.np == 0:
            raise ValueError("the problem has no static parameters (np = 0)")
        p0 = tr.as_batch("p0", p0, P.np)
        B, m = p0.shape
        lb = P.p_lb.to(p0).expand(B, m)
        ub = P.p_ub.to(p0).expand(B, m)
        fin = torch.isfinite(lb) & torch.isfinite(ub)
        # scaled variables s in [0, 1] where both bounds are finite: logarithmic when the
        # bounds are positive and span two decades or more (the suspension's damper and
        # spring), linear otherwise; p - lb (one bound) or p itself elsewhere
        logs = fin & (lb > 0) & (ub >= 100 * lb)
        lo = torch.where(torch.isfinite(lb), lb, torch.zeros_like(lb))
        span = torch.where(fin, ub - lb, torch.ones_like(lb))
        lspan = torch.where(logs, torch.log(ub / lb.clamp_min(1e-300)), torch.ones_like(lb))
        s_lo = torch.where(torch.isfinite(lb), 0.0, -float("inf")).to(p0)
        s_hi = torch.where(fin, 1.0, torch.where(torch.isfinite(ub), ub - lo, float("inf"))).to(p0)

        # without logarithmic parameters the maps are affine: the same numbers, fewer ops
        any_log = bool(logs.any())

        def to_p(s):
            if not any_log:
                return lo + span * s
            return torch.where(logs, lb * torch.exp(lspan * s), lo + span * s)

        def dp_ds(s):
            if not any_log:
                return span.expand_as(s)
            return torch.where(logs, to_p(s) * lspan, span)

        def clamp(s):
            return torch.maximum(torch.minimum(s, s_hi), s_lo)

        def to_s(p):
            return torch.where(logs, torch.log(p / lb.clamp_min(1e-300)) / lspan, (p - lo) / span)

        s = clamp(to_s(p0))
        ev = self.lower(tr, to_p(s))
        evaluations = 1
        v, g = ev.value, ev.grad * dp_ds(s)
        Hinv = torch.eye(m, dtype=p0.dtype, device=p0.device).expand(B, m, m).clone()
        status = torch.full((B,), int(Status.RUNNING), dtype=torch.int64, device=p0.device)
        status = status.masked_fill(ev.status != 0, int(Status.NOT_POSITIVE_DEFINITE))
        # a NaN or infinity in a starting design is that element's non_finite (one
        # meaning per status)
        status = status.masked_fill(ev.status == Status.NON_FINITE, int(Status.NON_FINITE))
        iters = torch.zeros(B, dtype=torch.int64, device=p0.device)
        z = ev.z
        hist = [v.clone()]
        alphas = 0.5 ** torch.arange(12, dtype=p0.dtype, device=p0.device)
        K = alphas.numel()
        pg = torch.full_like(v, float("inf"))
        base = torch.arange(B, device=p0.device)
        eye = torch.eye(m, dtype=p0.dtype, device=p0.device)
        # a first step of at most 0.1 in the scaled variables (BFGS has no scale yet)
        first = True
        for _ in range(self.max_iter):
            pg = (clamp(s - g) - s).abs().amax(1)
            status = status.masked_fill((status == -1) & (pg <= self.tol), int(Status.CONVERGED))
            run = status == -1
            if not bool(run.any()):
                break
            # variables at a bound with the gradient pushing outwards stay there; the
            # others take the quasi-Newton step of the free block (a principal block of a
            # positive definite matrix: still a descent direction)
            free = ~(((s <= s_lo) & (g > 0)) | ((s >= s_hi) & (g < 0)))
            Df = free.to(g.dtype)
            d = -((Df[:, :, None] * Hinv * Df[:, None, :]) @ g.unsqueeze(-1)).squeeze(-1)
            if first:
                d = d * (0.1 / d.abs().amax(1, keepdim=True).clamp_min(1e-300)).clamp(max=1.0)
                first = False
            # Armijo trials in passes (the full step first: it is taken in most
            # iterations), each pass one batched lower-level solve of B x (pass size) QPs
            found = torch.zeros(B, dtype=torch.bool, device=p0.device)
            s_new, v_new, g_new, z_new = s, v, g, z
            for lo_k, hi_k in ((0, 1), (1, 4), (4, K)):
                need = run & ~found
                if not bool(need.any()):
                    break
                a = alphas[lo_k:hi_k]
                kk = a.numel()
                trial = clamp(s[None] + a[:, None, None] * d[None])  # (kk, B, m)
                evt = self.lower(tr, to_p(trial).reshape(kk * B, m))
                evaluations += 1
                vt = evt.value.reshape(kk, B)
                ok = vt <= v[None] + 1e-4 * (g[None] * (trial - s[None])).sum(-1)
                ok &= torch.isfinite(vt) & (evt.status.reshape(kk, B) == 0) & need[None]
                hit = ok.any(0)
                k = ok.to(torch.int64).argmax(0)
                tk = trial[k, base]
                s_new = torch.where(hit[:, None], tk, s_new)
                v_new = torch.where(hit, vt[k, base], v_new)
                gt = evt.grad.reshape(kk, B, m)[k, base] * dp_ds(tk)
                g_new = torch.where(hit[:, None], gt, g_new)
                z_new = torch.where(hit[:, None], evt.z.reshape(kk, B, -1)[k, base], z_new)
                found = found | hit
            move = run & found
            # BFGS update of the inverse Hessian (skipped without curvature)
            sk, yk = s_new - s, g_new - g
            sy = (sk * yk).sum(1)
            upd = move & (sy > 1e-12 * (sk.norm(dim=1) * yk.norm(dim=1)).clamp_min(1e-300))
            rho = torch.where(upd, 1.0 / sy.clamp_min(1e-300), torch.zeros_like(sy))
            V = eye - rho[:, None, None] * sk[:, :, None] * yk[:, None, :]
            Hn = V @ Hinv @ V.mT + rho[:, None, None] * sk[:, :, None] * sk[:, None, :]
            Hinv = torch.where(upd[:, None, None], Hn, Hinv)
            small = move & ((v - v_new).abs() <= 1e-12 * v.abs().clamp_min(1e-300))
            s = torch.where(move[:, None], s_new, s)
            g = torch.where(move[:, None], g_new, g)
            v = torch.where(move, v_new, v)
            z = torch.where(move[:, None], z_new, z)
            iters = iters + move.to(torch.int64)
            status = status.masked_fill(small, int(Status.CONVERGED))
            # no decrease found: at the lower level's noise floor when the projected
            # gradient is already small, otherwise a failure
            stuck = run & ~found
            status = status.masked_fill(stuck & (pg <= 1e3 * self.tol), int(Status.CONVERGED))
            status = status.masked_fill(
                stuck & (pg > 1e3 * self.tol), int(Status.LINE_SEARCH_FAILED)
            )
            hist.append(v.clone())
        status = status.masked_fill(status == -1, int(Status.MAX_ITER))
        return TLFPResult(
            p=to_p(s),
            z=z,
            objective=v,
            iterations=iters,
            evaluations=evaluations,
            status=status,
            time=time.perf_counter() - t0,
            history=hist,
        )
