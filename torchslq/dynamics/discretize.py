"""Turning :class:`ContinuousDynamics` into discrete-time :class:`Dynamics`."""

from __future__ import annotations

import torch
from torch import Tensor

from .._backend import (
    can_use_compiled,
    module_needs_grad,
    stage_congruence_compiled,
    step_rows_compiled,
)
from .._pinned import pinned
from .._shapes import broadcast_shapes
from ._taylor import second_order_taylor
from .base import ContinuousDynamics, Dynamics, identity_like
from .compiled_rk4 import rk4_hooks, rk4_jacobians_compiled, rk4_vhp_compiled
from .graph_jacobian import xu_hessian
from .linearize import first_order_only, second_order_only

__all__ = ["discretize", "DiscretizedDynamics"]

_METHODS = ("euler", "rk4")


class DiscretizedDynamics(Dynamics):
    """One explicit integration step of a continuous model per time step ``dt``.

    ``method="euler"``: ``x + dt f(x, u)``. ``method="rk4"``: the classical
    fourth-order Runge-Kutta step with ``u`` held constant over the step (zero-order
    hold). When the continuous model has analytic Jacobians, :meth:`jacobians` chains
    them through the scheme exactly; otherwise :func:`torchslq.linearize` differentiates
    the step by automatic differentiation.
    """

    def __init__(self, continuous: ContinuousDynamics, dt: float, method: str = "rk4"):
        super().__init__()
        if method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
        if not (
            isinstance(dt, (int, float)) and not isinstance(dt, bool) and 0 < dt < float("inf")
        ):
            raise ValueError(f"dt must be a positive finite number, got {dt!r}")
        self.continuous = continuous
        self.dt = float(dt)
        self.method = method
        self.state_dim = continuous.state_dim
        self.control_dim = continuous.control_dim

    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        f, dt = self.continuous, self.dt
        if x.requires_grad or u.requires_grad:
            out = None
            if first_order_only():
                out = self.linear_standin(x, u)
            elif second_order_only():
                out = self.quadratic_standin(x, u)
            if out is not None:
                return out
        if self.method == "rk4" and can_use_compiled(x, u) and not module_needs_grad(self):
            # called from Python outside the library's kernels (e.g. inside a user's own
            # model, a learned residual on this step): one kernel call for the whole
            # batch instead of the RK4 stages' ~70 small torch ops
            out = self._compiled_forward(x, u)
            if out is not None:
                return out
        if self.method == "euler":
            return x + dt * f(x, u)
        # torch.add(a, b, alpha=c) is a + c b in one op: rollouts are dispatch-bound
        k1 = f(x, u)
        k2 = f(torch.add(x, k1, alpha=0.5 * dt), u)
        k3 = f(torch.add(x, k2, alpha=0.5 * dt), u)
        k4 = f(torch.add(x, k3, alpha=dt), u)
        incr = torch.add(torch.add(k1, k2, alpha=2.0), torch.add(k4, k3, alpha=2.0))
        return torch.add(x, incr, alpha=dt / 6.0)

    def linear_standin(self, x: Tensor, u: Tensor) -> Tensor | None:
        """Inside :func:`torchslq.linearize`'s Jacobian pass of a model that calls this
        step (:func:`~torchslq.dynamics.linearize.first_order_only`): the step's value
        plus ``A (x - x̄) + B (u - ū)`` with its compiled Jacobians at ``(x̄, ū)``, the
        detached inputs. Same value and first derivatives as :meth:`forward` for one
        kernel call each instead of the RK4 stages' torch ops forward and backward; None
        where the compiled path does not apply."""
        point = self._standin_point(x, u)
        jac = None if point is None else self.compiled_jacobians(point[1], point[2])
        if jac is None:
            return None
        value = point[3]
        A, B = jac
        dx, du = (x - x.detach()).unsqueeze(-1), (u - u.detach()).unsqueeze(-1)
        return value + (A @ dx).squeeze(-1) + (B @ du).squeeze(-1)

    def quadratic_standin(self, x: Tensor, u: Tensor) -> Tensor | None:
        """Inside the Hessian pass of :func:`~torchslq.dynamics.dynamics_hessians` /
        :func:`~torchslq.dynamics.dynamics_vhp` of a model that calls this step
        (:func:`~torchslq.dynamics.linearize.second_order_only`): the step's second-order
        Taylor expansion at ``(x̄, ū)``, the detached inputs,

            ``f_i + A_i dx + B_i du + dx' Hxx_i dx / 2 + du' Hux_i dx + du' Huu_i du / 2``

        with ``dx = x - x̄``, ``du = u - ū`` and the compiled Jacobians and Hessians of
        every output ``i``. Same value, first and second derivatives as :meth:`forward`
        at the point, for two kernel calls instead of a double backward through the RK4
        stages' torch ops; None where the compiled path does not apply."""
        point = self._standin_point(x, u)
        both = None if point is None else self.jacobians_and_hessians(point[1], point[2])
        if both is None:
            return None
        lead, _, _, value = point
        n, m = x.shape[-1], u.shape[-1]
        A, B, (Hxx, Huu, Hux) = both  # Hessians (n, *lead, ., .): output first
        H = xu_hessian(Hxx, Huu, Hux)
        dz = torch.cat([(x - x.detach()).expand(*lead, n), (u - u.detach()).expand(*lead, m)], -1)
        return value + second_order_taylor(dz, torch.cat([A, B], -1), H.movedim(0, -3))

    def _standin_point(self, x: Tensor, u: Tensor):
        """``(lead, x̄, ū, value)``: the stand-ins' expansion point (the inputs detached,
        broadcast to their common leading dims ``lead``) and the step's value there by
        the generated kernel; None where the compiled path does not apply."""
        if self.method != "rk4" or module_needs_grad(self):
            return None
        lead = broadcast_shapes(x.shape[:-1], u.shape[:-1])
        xd = x.detach().expand(*lead, x.shape[-1])
        ud = u.detach().expand(*lead, u.shape[-1])
        if not can_use_compiled(xd, ud):
            return None
        value = self._compiled_forward(xd, ud)
        return None if value is None else (lead, xd, ud, value)

    def _compiled_forward(self, x: Tensor, u: Tensor) -> Tensor | None:
        """:meth:`forward` by the compiled step of the code generated from the continuous
        model (None without one: a hand-written step may differ in the last bits)."""
        # looked up once per solve: a learned model around this step calls it at every
        # time step of every rollout
        step = pinned(self, "generated_step", self._generated_step_now)
        if step is None:
            return None
        n, m = x.shape[-1], u.shape[-1]
        if x.shape[:-1] == u.shape[:-1] and x.is_contiguous():
            # (a rollout's (..., 1, n) states: views of the rows, no copies; its
            # controls are a time slice, strided, and copied)
            ur = u.detach().reshape(-1, m)
            ur = ur if ur.is_contiguous() else ur.contiguous()
            out = step_rows_compiled(step[0], step[1], x.detach().view(-1, n), ur)
            return out.view(x.shape)
        lead = broadcast_shapes(x.shape[:-1], u.shape[:-1])
        xr = x.detach().expand(*lead, n).reshape(-1, n).contiguous()
        ur = u.detach().expand(*lead, m).reshape(-1, m).contiguous()
        return step_rows_compiled(step[0], step[1], xr, ur).view(*lead, n)

    def _generated_step_now(self):
        """:meth:`compiled_step` when it wraps generated code, else None."""
        from .._backend.bound import is_generated
        from .._backend.model_fns import step_source

        step = self.compiled_step()
        source = None if step is None else step_source(step[0])
        if source is None or not is_generated(source[0]):
            return None
        return step

    @property
    def has_analytic_jacobians(self) -> bool:
        return self.continuous.has_analytic_jacobians

    def compiled_step(self):
        """The RK4 step as a numba function around the continuous model's
        :meth:`~torchslq.ContinuousDynamics.compiled_rhs` (same sums in the same order
        as :meth:`forward`), or None (no compiled right-hand side, or Euler)."""
        if self.method != "rk4":
            return None
        rhs = self.continuous.compiled_rhs()
        if rhs is None:
            return None
        import numpy as np

        from ._numba_rk4 import rk4_step

        fn, params = rhs
        return rk4_step(fn), np.concatenate([[self.dt], params]).astype(np.float64)

    def jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """Exact Jacobians of the integration step from the continuous model's ones."""
        f, dt = self.continuous, self.dt
        if self.method == "euler":
            fx, fu = f.jacobians(x, u)
            return identity_like(x, x.shape[-1]) + dt * fx, dt * fu
        hooks = self._compiled_derivatives(x, u)
        if hooks is not None:
            return rk4_jacobians_compiled(hooks, dt, x, u)
        A, B, _ = self._rk4_chain(x, u)
        return A, B

    def compiled_jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor] | None:
        """The step's Jacobians ``(A, B)`` on the CPU kernels from the continuous
        model's compiled derivatives (its own or generated from its ``forward``), or None
        where those do not apply (:func:`torchslq.linearize` then differentiates as
        usual). Detached."""
        hooks = self._compiled_derivatives(x, u)
        return None if hooks is None else rk4_jacobians_compiled(hooks, self.dt, x, u)

    def compiled_vhp(self, x: Tensor, u: Tensor, s: Tensor):
        """:meth:`vhp` on the CPU kernels (``s`` may carry extra leading dims), or None
        where the compiled derivatives do not apply. Detached."""
        hooks = self._compiled_derivatives(x, u, s)
        return None if hooks is None else rk4_vhp_compiled(hooks, self.dt, x, u, s)

    def _compiled_derivatives(self, *tensors: Tensor):
        """The continuous model's compiled functions (:func:`~.compiled_rk4.rk4_hooks`) when this RK4 step's
        derivatives can run on the CPU kernels (:mod:`torchslq.dynamics.compiled_rk4`):
        the model has :meth:`~ContinuousDynamics.compiled_rhs` and
        :meth:`~ContinuousDynamics.compiled_derivatives`, ``tensors`` are CPU float
        tensors and nothing (they, or the model's parameters) needs autograd; else None."""
        if self.method != "rk4" or not can_use_compiled(*tensors):
            return None
        # the model's functions and parameter values, once per solve (torchslq._pinned);
        # whether its parameters need autograd depends on the grad mode of the call
        return pinned(self, ("rk4_hooks", torch.is_grad_enabled()), self._rk4_hooks_now)

    def _rk4_hooks_now(self):
        c = self.continuous
        if module_needs_grad(c):
            return None
        derivs = c.compiled_derivatives()
        if derivs is None:
            return None
        rhs = c.compiled_rhs()
        if rhs is None:
            return None
        return rk4_hooks(rhs, derivs)

    def _rk4_chain(
        self, x: Tensor, u: Tensor, keep_stages: bool = False
    ) -> tuple[Tensor, Tensor, list]:
        """RK4 step Jacobians ``(A, B)`` and, with ``keep_stages`` (for :meth:`vhp`), per
        stage ``i`` ``(a_i, xi_i, f_x(xi_i, u), dk_{i-1}/dz)`` (the last None for the
        first stage). (Not kept otherwise: holding every stage's tensors alive made the
        linearisation ~30% slower, the allocator then cannot reuse their memory.)"""
        f, dt = self.continuous, self.dt
        # stage i: k_i = f(x + a_i dt k_{i-1}, u), so with z = (x, u) and f_z = [f_x | f_u]
        # dk_i/dz = f_z + a_i dt f_x dk_{i-1}/dz: one product per stage on the joint
        # (n, n + m) block (this chain runs on every linearisation, (rows, n, n + m)
        # tensors, and its cost is the number of tiny batched products and adds)
        n = x.shape[-1]
        k, dk, acc = None, None, None
        stages = []
        for i, (a, w) in enumerate(_RK4):
            xi = x if k is None else torch.add(x, k, alpha=a * dt)
            fx, fu = f.jacobians(xi, u)
            if keep_stages:
                stages.append((a, xi, fx, dk))
            lead = broadcast_shapes(fx.shape[:-2], fu.shape[:-2])
            fz = torch.cat([fx.expand(*lead, *fx.shape[-2:]), fu.expand(*lead, *fu.shape[-2:])], -1)
            # in place on fresh products where possible: for large row counts each new
            # tensor costs more (allocation, first touch) than the arithmetic on it
            dk = fz if dk is None else (fx @ dk).mul_(a * dt).add_(fz)
            if acc is None:
                acc = dk
            elif i == 1:
                acc = torch.add(acc, dk, alpha=w)  # a new tensor: acc aliased stage 1's dk
            else:
                acc.add_(dk, alpha=w)
            if i < len(_RK4) - 1:  # the last stage's k is not needed
                k = f(xi, u)
        A = torch.add(identity_like(x, n), acc[..., :n], alpha=dt / 6.0)
        return A, acc[..., n:] * (dt / 6.0), stages

    @property
    def has_analytic_vhp(self) -> bool:
        c = self.continuous
        return c.has_analytic_vhp and (self.method == "euler" or c.has_analytic_jacobians)

    def vhp(self, x: Tensor, u: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Hessian blocks of ``s · step(x, u)`` from the continuous model's analytic
        :meth:`~ContinuousDynamics.vhp` and :meth:`~ContinuousDynamics.jacobians`
        (``s (..., n)``, extra leading dims allowed; returns ``(Hxx, Huu, Hux)``).

        RK4 (``step = x + sum_i c_i k_i``, ``k_i = f(zeta_i)``, ``zeta_i = (x + a_i dt
        k_{i-1}, u)``): the second-order chain rule through the stages collapses into
        ``sum_i Z_i' (mu_i · f_zz(zeta_i)) Z_i`` with ``Z_i = d zeta_i / dz`` and adjoint
        weights ``mu_4 = c_4 s``, ``mu_{i-1} = c_{i-1} s + a_i dt f_x(zeta_i)' mu_i``: one
        continuous VHP per stage, never the third-order tensor."""
        f, dt = self.continuous, self.dt
        if not self.has_analytic_vhp:
            raise NotImplementedError(
                f"{type(f).__name__} has no analytic vhp (and jacobians) to chain"
            )
        if self.method == "euler":
            return tuple(dt * h for h in f.vhp(x, u, s))
        hooks = self._compiled_derivatives(x, u, s)
        if hooks is not None:
            return rk4_vhp_compiled(hooks, dt, x, u, s)
        _, _, stages = self._rk4_chain(x, u, keep_stages=True)
        return self._vhp_from_stages(u, s, stages)

    def jacobians_and_vhp(self, x: Tensor, u: Tensor):
        """``(A, B, vhp)``: the step's Jacobians and a function ``s -> vhp(x, u, s)`` that
        reuses their RK4 stages (the Jacobians at each stage, which the second
        derivatives chain through) instead of recomputing them; None when the model has
        no analytic second derivatives to chain (or for Euler, where nothing is shared).
        For callers that need both at the same point, the second after a costate
        recursion on the first (DDP's costate mode, the MPC layer's exact backward)."""
        if self.method == "euler":
            return None
        hooks = self._compiled_derivatives(x, u)
        if hooks is not None:  # the kernel recomputes the stages: cheaper than keeping them
            A, B = rk4_jacobians_compiled(hooks, self.dt, x, u)
            return A, B, lambda s: self._vhp_any(x, u, s)
        if not self.has_analytic_vhp:
            return None
        A, B, stages = self._rk4_chain(x, u, keep_stages=True)
        return A, B, lambda s: self._vhp_from_stages(u, s, stages)

    def _vhp_any(self, x: Tensor, u: Tensor, s: Tensor):
        """:meth:`vhp` on the kernels where they apply, else chained from the continuous
        model's analytic derivatives, else by automatic differentiation of the step."""
        out = self.compiled_vhp(x, u, s)
        if out is not None:
            return out
        if self.has_analytic_vhp:
            return self.vhp(x, u, s)
        from .linearize import dynamics_vhp

        return dynamics_vhp(lambda a, b: self(a, b), x, u, s)

    def jacobians_and_hessians(self, x: Tensor, u: Tensor):
        """``(A, B, (Hxx, Huu, Hux))``: the step's Jacobians and every output's Hessian
        blocks (each ``(n, *lead, ., .)``, :func:`~torchslq.dynamics.dynamics_hessians`'
        layout) from one pass over the RK4 stages on the CPU kernels (DDP's value mode
        needs both at the same points); None where the kernels do not apply."""
        hooks = self._compiled_derivatives(x, u)
        if hooks is None:
            return None
        n = x.shape[-1]
        basis = torch.eye(n, dtype=x.dtype).reshape(n, *([1] * (x.ndim - 1)), n)
        (A, B), blocks = rk4_vhp_compiled(hooks, self.dt, x, u, basis, with_jacobians=True)
        return A, B, blocks

    def _vhp_from_stages(self, u: Tensor, s: Tensor, stages: list):
        """The RK4 chain of :meth:`vhp` from :meth:`_rk4_chain`'s kept stages."""
        f, dt = self.continuous, self.dt
        n = s.shape[-1]
        weights = [dt / 6.0 * w for _, w in _RK4]
        mu = weights[3] * s
        Hxx = Huu = Hux = None
        for i in range(3, -1, -1):
            a, xi, fx, dk_prev = stages[i]
            hxx, huu, hux = f.vhp(xi, u, mu)
            if dk_prev is not None and can_use_compiled(hxx, huu, hux, dk_prev):
                # the congruence on the CPU kernel, added into the running sums: the same
                # products as below, but without ~10 tiny batched matmuls (each
                # broadcasting over the weight vectors by a copy) per stage
                Hxx, Huu, Hux = _accumulator(Hxx, Huu, Hux, hxx, huu, hux, dk_prev)
                stage_congruence_compiled((Hxx, Huu, Hux), (hxx, huu, hux), dk_prev, a * dt)
            else:
                if dk_prev is not None:
                    # Z_i = [[P, Q], [0, I]]: P = I + a dt dk_x, Q = a dt dk_u
                    P = torch.add(identity_like(xi, n), dk_prev[..., :n], alpha=a * dt)
                    Q = dk_prev[..., n:] * (a * dt)
                    t1 = torch.add(hxx @ Q, hux.mT)  # (n, m)
                    hux_i = t1.mT @ P
                    huu = torch.add(huu, torch.add(Q.mT @ t1, hux @ Q))
                    hxx, hux = P.mT @ hxx @ P, hux_i
                Hxx = hxx if Hxx is None else Hxx + hxx
                Huu = huu if Huu is None else Huu + huu
                Hux = hux if Hux is None else Hux + hux
            if i > 0:
                mu = torch.add(weights[i - 1] * s, (fx.mT @ mu.unsqueeze(-1))[..., 0], alpha=a * dt)
        return Hxx, Huu, Hux


def _accumulator(Hxx, Huu, Hux, hxx, huu, hux, dk) -> tuple[Tensor, Tensor, Tensor]:
    """The running sums ``(Hxx, Huu, Hux)`` as fresh contiguous tensors of the full
    broadcast shape of this stage's blocks (zeros, plus the sums so far), to be added
    to in place by :func:`stage_congruence_compiled`."""
    n, m = hxx.shape[-1], huu.shape[-1]
    parts = (hxx, huu, hux, dk) + (() if Hxx is None else (Hxx, Huu, Hux))
    lead = broadcast_shapes(*(p.shape[:-2] for p in parts))
    out = []
    for old, (r, c) in zip((Hxx, Huu, Hux), ((n, n), (m, m), (m, n)), strict=True):
        if old is None:
            out.append(hxx.new_zeros(*lead, r, c))
        elif old.shape == (*lead, r, c) and old.is_contiguous():
            out.append(old)  # the previous stage's accumulator: add to it in place
        else:
            out.append(old.expand(*lead, r, c).clone())
    return tuple(out)


# (a_i, w_i): stage i is evaluated at x + a_i dt k_{i-1}, and weighs w_i dt / 6
_RK4 = ((0.0, 1.0), (0.5, 2.0), (0.5, 2.0), (1.0, 1.0))


def discretize(dynamics: ContinuousDynamics, dt: float, method: str = "rk4") -> DiscretizedDynamics:
    """The discrete-time model ``x_{t+1} = F(x_t, u_t)`` of a continuous one, ``xdot =
    f(x, u)``: one integration step of length ``dt`` per time step, ``u`` held constant
    over the step (zero-order hold). What :class:`torchslq.Problem` needs of a
    :class:`~torchslq.ContinuousDynamics` (passing the continuous model itself is a
    TypeError: its ``xdot`` is no next state).

    Args:
        dynamics: a :class:`~torchslq.ContinuousDynamics` (``state_dim``,
            ``control_dim``, ``forward(x (..., n), u (..., m)) -> xdot (..., n)``,
            batched over any leading dims; optional analytic ``jacobians``/``vhp`` and
            compiled hooks, which the step chains through the scheme exactly).
        dt: the step length (> 0), in the model's time unit.
        method: ``"rk4"`` (default; the classical fourth-order Runge-Kutta step, four
            calls of ``f``) or ``"euler"`` (``x + dt f(x, u)``).

    Returns:
        A :class:`DiscretizedDynamics` (an ``nn.Module``: the continuous model's
        parameters are its parameters, so gradients reach them).

    Example::

        class Pendulum(ts.ContinuousDynamics):
            state_dim, control_dim = 2, 1

            def forward(self, x, u, t=None):
                theta, omega = x[..., :1], x[..., 1:]
                return torch.cat([omega, -9.81 * torch.sin(theta) + u], dim=-1)

        step = ts.discretize(Pendulum(), dt=0.05)      # x_next = step(x, u)
    """
    if not isinstance(dynamics, ContinuousDynamics):
        raise TypeError(
            f"dynamics must be a torchslq.ContinuousDynamics, got {type(dynamics).__name__}"
        )
    return DiscretizedDynamics(dynamics, dt, method)
