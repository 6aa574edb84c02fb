"""Quasilinearization (Herber & Sundarrajan 2020, Sec. 4.3.4, Algorithm 1).

Each iteration builds the reference LQDO problem (Prob. 14) about the previous solution
with the chosen transcription, solves its QP, and stops when the objective changes by
no more than ``tol``. The loop is the library's shared solver core
(:func:`torchslq.solvers.core.iterate`): per-element status, masks that freeze a finished
element, the history and logging are the same as for every other solver. Its
``measure`` is the paper's stopping test (cheap), and its ``advance`` builds and solves
the QP for the whole batch at once.

For an OLQ problem (every element OLQ, Sec. 3.1) the first QP is the transcribed problem
itself, and the loop stops after that one iteration.

Safeguards (not in the paper; its conclusion asks for a line search or a trust region),
both on the l1 merit function ``phi(z) = v(z) + rho ||c(z)||_1`` with ``rho`` at least
twice the largest QP multiplier (Nocedal & Wright 2006, Sec. 18.3):

* ``safeguard="merit"``: the QP solution is a direction ``d = z_qp - z``; the step
  ``z + a d`` is chosen among ``a = 1, 1/2, ..., 2^-9`` (all trials evaluated as one
  batch) by Armijo's rule on ``phi``.
* ``safeguard="trust_region"``: the static parameters' step is bounded in the QP,
  ``|p_i - p_ref_i| <= radius max(|p_ref_i|, 1)`` (their products with the states are
  what the linearisation misses on the co-design problems; with ``p`` fixed those are
  linear). The step is accepted where ``phi`` decreases by at least a tenth of the
  decrease the QP predicts; a rejected step is retried once with a second-order
  correction (the QP with its constraints shifted by their linearisation error at the
  trial point, which removes the Maratos effect of those products), and the radius
  shrinks to a quarter of the step where the ratio is below 1/4 and doubles where it is
  above 1/2 with the step on the boundary (ibid., Alg. 4.1 and Sec. 18.5).

With a safeguard an element stops only after a full (accepted) step with
``|dv| <= tol`` and constraint violation ``<= feas_tol`` (with the trust region: a step
inside the region). ``hessian="lagrangian"`` adds the constraints' curvature weighted by
the last QP's multipliers to the subproblem (sequential quadratic programming): Van der
Pol V2 then converges in 6 iterations instead of 15-18.

The result's ``grad_norm`` slot holds the largest nonlinear constraint violation at the
iterate (the quantity QLIN drives to zero besides the objective change).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..solvers.core import Advance, ElementState, LoopSettings, Measure, iterate, shared
from ..solvers.options import check_int, check_real
from ..status import Status
from .backends import IPStart, QPSolution, solve
from .qp import SparseQP
from .transcription import Transcription

__all__ = ["Quasilinearization", "QLINResult", "violation"]


def violation(tr: Transcription, z: Tensor) -> Tensor:
    """``(B, m)`` nonnegative violations of every constraint of Prob. (4) at ``z``:
    equalities (absolute), inequalities and simple bounds (positive parts)."""
    lb, ub = tr._bounds(z.shape[0])  # shared, read only
    return torch.cat(
        [
            tr.equalities(z).abs(),
            tr.inequalities(z).clamp_min(0),
            (lb.to(z) - z).clamp_min(0).nan_to_num(0.0, posinf=0.0),
            (z - ub.to(z)).clamp_min(0).nan_to_num(0.0, posinf=0.0),
        ],
        1,
    )


@dataclass(frozen=True)
class _State(ElementState):
    z: Tensor = None  # (B, n)
    J_prev: Tensor = None  # (B,) objective of the previous iterate (inf at the start)
    viol: Tensor = None  # (B,) largest constraint violation
    full: Tensor = None  # (B,) bool, the last step was the full QP step
    rho: Tensor = None  # (B,) merit penalty
    radius: Tensor = None  # (B,) trust-region radius of the static parameters (relative)
    inside: Tensor = None  # (B,) bool, the last step was inside the trust region
    lam: Tensor = None  # (B, me) the last QP's multipliers (hessian="lagrangian")
    mu: Tensor = None  # (B, mi)
    # the dense backend's warm start for the next QP (backends.IPStart): the bounds'
    # multipliers per variable (B, n) and whether the last QP gave one (B,)
    ip_mu_lb: Tensor = None
    ip_mu_ub: Tensor = None
    ip_ok: Tensor = None
    qp_time: Tensor = shared(None)  # (1,) accumulated QP solve seconds


@dataclass
class QLINResult:
    """Outcome of :meth:`Quasilinearization.solve`.

    Attributes:
        z: ``(B, n)`` final iterate; u, xi, p its parts ``(B, nt, nu)``, ``(B, nt, nx)``,
            ``(B, np)``.
        objective: ``(B,)`` transcribed objective ``v`` (eq. 9) at ``z``.
        violation: ``(B,)`` largest constraint violation at ``z``.
        iterations: ``(B,)`` QP subproblems solved (Algorithm 1's ``k``).
        status: ``(B,)`` :class:`torchslq.Status` (``converged``; ``max_iter`` when the
            iterates keep moving, e.g. oscillate; ``not_positive_definite`` when a QP
            subproblem has no solution; ``line_search_failed`` for the safeguard).
        history: per-iteration ``(B, k+1)`` ``cost``, ``grad_norm`` (the violation),
            ``step``; ``time``.
        time: wall-clock seconds; qp_time: of which in the QP solver.
    """

    z: Tensor
    u: Tensor
    xi: Tensor
    p: Tensor
    objective: Tensor
    violation: Tensor
    iterations: Tensor
    status: Tensor
    history: dict
    time: float
    qp_time: float


class _Rule:
    def __init__(self, owner: Quasilinearization, tr: Transcription):
        self.o, self.tr = owner, tr
        self.olq = tr.is_olq
        self.qp_seconds = 0.0  # in the QP solver, accumulated

    def measure(self, problem, state: _State, running: Tensor, it: int):
        o = self.o
        dv = (state.J - state.J_prev).abs()
        done = dv <= o.tol * state.J.abs().clamp_min(1.0)
        if o.safeguard is not None:
            done = done & state.full & (state.viol <= o.feas_tol)
        if o.safeguard == "trust_region":  # a small change of v on the boundary is not a stop
            done = done & state.inside
        if it >= 1 and self.olq:  # the QP was the problem itself: solved in one iteration
            done = done | state.full
        fail = torch.full_like(state.J, int(Status.RUNNING), dtype=torch.int64)
        return state, Measure(
            grad_norm=state.viol, done=done, fail=fail, cost=state.J, history={"dv": dv}
        )

    def _qp(self, state: _State, radius: Tensor | None = None) -> SparseQP:
        z = state.z
        mult = (state.lam, state.mu) if self.o.hessian == "lagrangian" else None
        qp = self.tr.qp(z, convexify=self.o.convexify, multipliers=mult)
        if radius is not None and self.tr.problem.np:
            # the trust region: |p_i - p_ref_i| <= radius max(|p_ref_i|, 1)
            ip = self.tr.idx_p
            p = z[:, ip]
            half = radius[:, None] * p.abs().clamp_min(1.0)
            lb, ub = qp.lb.clone(), qp.ub.clone()
            lb[:, ip] = torch.maximum(lb[:, ip], p - half)
            ub[:, ip] = torch.minimum(ub[:, ip], p + half)
            qp = replace(qp, lb=lb, ub=ub)
        return qp

    def _solve(self, qp: SparseQP, state: _State | None = None) -> QPSolution:
        """The QP; with ``state`` on the dense backend, warm-started from its iterate and
        its last QP's multipliers where that QP converged (the first QP: the reference, no
        multipliers yet: at the floor) (``backends.IPStart``)."""
        t0 = time.perf_counter()
        options = self.o.qp_options
        if state is not None and self.o.backend == "dense":
            warm = IPStart(
                z=state.z, mu_g=state.mu, mu_lb=state.ip_mu_lb, mu_ub=state.ip_mu_ub,
                ok=state.ip_ok,
            )  # fmt: skip
            options = dict(options, warm=warm)
        sol = solve(qp, self.o.backend, **options)
        self.qp_seconds += time.perf_counter() - t0
        return sol

    def _second_order_correction(self, qp: SparseQP, z_trial: Tensor) -> QPSolution:
        """The QP again with its constraints shifted by their linearisation error at the
        trial point (Nocedal & Wright 2006, Sec. 18.3): ``A z = b - e_E``,
        ``G z <= h - e_I`` with ``e = c(z_trial) - c_lin(z_trial)``. It removes the
        second-order constraint violation that makes an l1 merit reject good steps (the
        Maratos effect; here the products of the parameters and the states)."""
        lin_eq, lin_in = qp.residuals(z_trial)  # the linearised constraints there
        e_eq = self.tr.equalities(z_trial).detach() - lin_eq
        e_in = self.tr.inequalities(z_trial).detach() - lin_in
        return self._solve(replace(qp, b=qp.b - e_eq, h=qp.h - e_in))

    def advance(self, problem, state: _State, m: Measure, running: Tensor) -> Advance:
        tr, o = self.tr, self.o
        before = self.qp_seconds
        trust = o.safeguard == "trust_region"
        qp = self._qp(state, state.radius if trust else None)
        sol = self._solve(qp, state)
        qp_ok = sol.status == int(Status.CONVERGED)
        end = torch.where(
            qp_ok | ~running,
            torch.full_like(sol.status, int(Status.RUNNING)),
            torch.full_like(sol.status, int(Status.NOT_POSITIVE_DEFINITE)),
        )
        d = torch.where(qp_ok[:, None], sol.z - state.z, torch.zeros_like(state.z))
        alpha = torch.ones_like(state.J)
        rho, radius, inside = state.rho, state.radius, state.inside
        if trust:
            rho = self._penalty(state, sol)
            phi0 = self._merit(state.z, rho)
            pred = phi0 - sol.value  # the QP's model: its objective, its constraints met
            ok, ratio = self._ratio_test(phi0, pred, rho, state.z + d)
            retry = qp_ok & running & ~ok
            if bool(retry.any()):  # a second-order correction of the rejected steps
                soc = self._second_order_correction(qp, state.z + d)
                soc_ok = retry & (soc.status == int(Status.CONVERGED))
                d_soc = torch.where(soc_ok[:, None], soc.z - state.z, d)
                ok2, ratio2 = self._ratio_test(phi0, pred, rho, state.z + d_soc)
                use = soc_ok & ok2
                d = torch.where(use[:, None], d_soc, d)
                ok, ratio = ok | use, torch.where(use, ratio2, ratio)
            radius, inside = self._new_radius(state, d, ratio)
            end = torch.where(
                qp_ok & (radius < _MIN_RADIUS) & running,
                torch.full_like(end, int(Status.LINE_SEARCH_FAILED)),
                end,
            )
            alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
        elif o.safeguard == "merit":
            alpha, rho, ok = self._merit_search(state, d, sol)
            end = torch.where(
                qp_ok & ~ok & running, torch.full_like(end, int(Status.LINE_SEARCH_FAILED)), end
            )
            alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
        qp_t = state.qp_time + (self.qp_seconds - before)
        accept = qp_ok & running & (alpha > 0)
        z_new = torch.where(accept[:, None], state.z + alpha[:, None] * d, state.z)
        J_new = tr.objective(z_new).detach()
        viol = violation(tr, z_new).amax(1).detach()
        u, xi, _ = tr.unpack(z_new)
        new = replace(
            state,
            x=xi,
            u=u,
            J=torch.where(accept, J_new, state.J),
            J_prev=torch.where(accept, state.J, state.J_prev),
            z=z_new,
            viol=torch.where(accept, viol, state.viol),
            full=accept & (alpha == 1.0),
            rho=rho,
            radius=radius,
            inside=inside,
            lam=torch.where(qp_ok[:, None], sol.lam, state.lam),
            mu=torch.where(qp_ok[:, None], sol.mu, state.mu),
            qp_time=qp_t,
        )
        if sol.start is not None:  # (the dense backend)
            new = replace(
                new,
                ip_mu_lb=torch.where(qp_ok[:, None], sol.start.mu_lb, state.ip_mu_lb),
                ip_mu_ub=torch.where(qp_ok[:, None], sol.start.mu_ub, state.ip_mu_ub),
                ip_ok=qp_ok & sol.start.ok,
            )
        return Advance(state=new, accept=accept, step=alpha, end=end)

    def _merit(self, z: Tensor, rho: Tensor) -> Tensor:
        """The l1 merit function ``v(z) + rho ||c(z)||_1`` ``(B,)``."""
        return self.tr.objective(z).detach() + rho * violation(self.tr, z).sum(1)

    def _penalty(self, state: _State, sol: QPSolution) -> Tensor:
        """``rho`` at least twice the largest QP multiplier, never decreasing."""
        B = state.J.shape[0]
        mult = torch.cat([sol.lam.abs(), sol.mu.abs(), state.J.new_zeros(B, 1)], 1).amax(1)
        return torch.maximum(state.rho, 2.0 * mult + 1e-8)

    def _ratio_test(self, phi0: Tensor, pred: Tensor, rho: Tensor, z_trial: Tensor):
        """``(ok, ratio)``: the trial point is accepted where the l1 merit (``phi0`` at
        the reference) decreases by at least a tenth of the predicted decrease ``pred``
        (Nocedal & Wright 2006, Alg. 4.1 on the merit function, Sec. 18.5)."""
        phi1 = self._merit(z_trial, rho)
        actual = phi0 - phi1
        ratio = torch.where(pred > 0, actual / pred.clamp_min(1e-300), torch.zeros_like(pred))
        # a step the model predicts no decrease for (at a stationary point) is taken if
        # the merit does not increase
        ok = torch.where(pred > 0, ratio >= 0.1, actual >= 0) & torch.isfinite(phi1)
        return ok, ratio

    def _new_radius(self, state: _State, d: Tensor, ratio: Tensor) -> tuple[Tensor, Tensor]:
        """The parameters' radius shrinks to a quarter of the step where the ratio is
        below 1/4 and doubles where it is above 1/2 with the step on the boundary;
        also whether the step was inside the region."""
        ip = self.tr.idx_p
        if ip.numel():
            p = state.z[:, ip]
            step = (d[:, ip].abs() / p.abs().clamp_min(1.0)).amax(1)
        else:
            step = torch.zeros_like(state.radius)
        radius = state.radius
        inside = step < 0.99 * radius
        radius = torch.where(ratio < 0.25, 0.25 * torch.minimum(step, radius), radius)
        grow = (ratio > 0.5) & ~inside
        radius = torch.where(grow, torch.clamp(2.0 * radius, max=_MAX_RADIUS), radius)
        return radius, inside

    def _merit_search(self, state: _State, d: Tensor, sol: QPSolution):
        tr = self.tr
        B, n = d.shape
        rho = self._penalty(state, sol)
        with torch.enable_grad():
            z = state.z.detach().requires_grad_(True)
            g = torch.autograd.grad(tr.objective(z).sum(), z)[0]
        c0 = violation(tr, state.z).sum(1)
        phi0 = state.J + rho * c0
        slope = (g * d).sum(1) - rho * c0  # directional derivative of the l1 merit
        alphas = 0.5 ** torch.arange(10, dtype=d.dtype, device=d.device)
        K = alphas.numel()
        trial = state.z[None] + alphas[:, None, None] * d[None]  # (K, B, n)
        flat = trial.reshape(K * B, n)
        phi = tr.objective(flat).reshape(K, B) + rho * violation(tr, flat).sum(1).reshape(K, B)
        armijo = phi <= phi0 + 1e-4 * alphas[:, None] * torch.minimum(
            slope, torch.zeros_like(slope)
        )
        armijo &= torch.isfinite(phi)
        first = torch.where(
            armijo.any(0), armijo.to(torch.int64).argmax(0), torch.zeros(B, dtype=torch.int64)
        )
        return alphas[first], rho, armijo.any(0)


_MIN_RADIUS = 1e-10  # a trust region this small: the safeguard has failed
_MAX_RADIUS = 1e3


class Quasilinearization:
    """Quasilinearization, Algorithm 1 (QLIN), with an optional merit line search.

    Args:
        tol: the stopping test ``|v(x^k) - v(x^{k-1})| <= tol max(1, |v|)``.
        max_iter: Algorithm 1's ``k_max``.
        backend: ``"clarabel"`` (default), ``"osqp"`` (sparse CPU solvers) or ``"dense"``
            (the batched torch interior point, CPU or GPU; each QP is warm-started from
            the iterate and the last QP's multipliers, the first from the reference
            ``z0`` with its multipliers at the floor,
            :class:`~torchslq.lqdo.backends.IPStart`).
        safeguard: None (the paper's Algorithm 1) or ``"merit"`` (see the module docstring).
        feas_tol: constraint violation required to stop with the safeguard.
        qp_options: passed to the QP backend (e.g. ``tol``).
        convexify: project each node's objective Hessian onto the positive semidefinite
            cone in the QP subproblems (keeping the objective's value and gradient at the
            reference): the QP is then convex and its step a descent direction of the
            merit function. Off by default: the subproblems of the paper's problems
            are solved as they are (on the suspension, projecting the bilinear blocks
            slowed the trust region from 36 to more than 180 iterations).
        hessian: ``"objective"`` (the paper's subproblem: the objective's Hessian, the
            constraints linearised) or ``"lagrangian"`` (the constraints' curvature
            weighted by the previous QP's multipliers added: sequential quadratic
            programming, which converges where the objective's Hessian alone misses the
            curvature of products of parameters and states).

    Example::

        tr = transcribe(problem, "TR", nodes=20)
        res = Quasilinearization().solve(tr, tr.initial_guess())
    """

    def __init__(
        self,
        tol: float = 1e-6,
        max_iter: int = 50,
        backend: str = "clarabel",
        safeguard: str | None = None,
        feas_tol: float = 1e-6,
        qp_options: dict | None = None,
        convexify: bool = False,
        hessian: str = "objective",
    ) -> None:
        if backend not in ("clarabel", "osqp", "dense"):
            raise ValueError(f"backend must be 'clarabel', 'osqp' or 'dense'; got {backend!r}")
        if safeguard not in (None, "merit", "trust_region"):
            raise ValueError(
                f"safeguard must be None, 'merit' or 'trust_region'; got {safeguard!r}"
            )
        check_real("tol", tol, 0.0)
        check_int("max_iter", max_iter, 1)
        check_real("feas_tol", feas_tol, 0.0)
        self.tol, self.max_iter, self.backend = tol, max_iter, backend
        self.safeguard, self.feas_tol = safeguard, feas_tol
        if not isinstance(convexify, bool):
            raise TypeError(f"convexify must be a bool; got {type(convexify).__name__}")
        self.convexify = convexify
        if hessian not in ("objective", "lagrangian"):
            raise ValueError(f"hessian must be 'objective' or 'lagrangian'; got {hessian!r}")
        self.hessian = hessian
        self.qp_options = dict(qp_options or {})

    def solve(self, tr: Transcription, z0: Tensor) -> QLINResult:
        """Run Algorithm 1 from the initial reference ``z0 (B, n)`` (or ``(n,)``).

        Returns:
            :class:`QLINResult` (batch-first; an unbatched ``z0`` still gives ``B = 1``).
        """
        if not isinstance(tr, Transcription):
            raise TypeError(f"tr must be a Transcription; got {type(tr).__name__}")
        z0 = tr.as_batch("z0", z0, tr.n)
        tr._check_z(z0)
        t0 = time.perf_counter()
        z0 = z0.detach()
        u, xi, _ = tr.unpack(z0)
        B = z0.shape[0]
        J0 = tr.objective(z0).detach()
        state = _State(
            x=xi,
            u=u,
            J=J0,
            z=z0,
            J_prev=torch.full_like(J0, float("inf")),
            viol=violation(tr, z0).amax(1).detach(),
            full=torch.zeros(B, dtype=torch.bool, device=z0.device),
            rho=torch.zeros_like(J0),
            radius=torch.full_like(J0, 1.0),
            inside=torch.ones(B, dtype=torch.bool, device=z0.device),
            lam=z0.new_zeros(B, tr.me),
            mu=z0.new_zeros(B, tr.mi),
            ip_mu_lb=torch.zeros_like(z0),
            ip_mu_ub=torch.zeros_like(z0),
            # the first QP too starts from the reference, its multipliers at the floor
            # (crane PS10 batch: 9.6 iterations and none handed over, against 11.3 and 2
            # from the least-norm point; unit multipliers there: 11.3 and 34)
            ip_ok=torch.ones(B, dtype=torch.bool, device=z0.device),
            qp_time=torch.zeros((), dtype=torch.float64),
        )
        settings = LoopSettings(
            max_iter=self.max_iter, rtol=0.0, stall_iters=0, progress=False, name="QLIN"
        )
        out = iterate(_Rule(self, tr), tr, state, settings)
        s = out.state
        u, xi, p = tr.unpack(s.z)
        return QLINResult(
            z=s.z,
            u=u,
            xi=xi,
            p=p,
            objective=s.J,
            violation=s.viol,
            iterations=out.iterations,
            status=out.status,
            history=out.history,
            time=time.perf_counter() - t0,
            qp_time=float(s.qp_time),
        )
