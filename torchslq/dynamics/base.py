"""Base classes for user dynamics: discrete-time :class:`Dynamics` and
continuous-time :class:`ContinuousDynamics`.

Dynamics are ``nn.Module``s called on batched tensors: ``x (..., n)``, ``u (..., m)``
with any leading shape (batch and time together). Each row must depend only on its
own inputs (no mixing across the batch, e.g. no BatchNorm in training mode), which is
what lets :func:`torchslq.linearize` take all Jacobians at once. A per-element
parameter is a tensor that broadcasts against the leading dims, e.g. a ``(B, 1, 1)``
mass for inputs of shape ``(B, T, n)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor, nn

from .._pinned import pinned

__all__ = ["Dynamics", "ContinuousDynamics", "CompiledDerivatives"]


class Dynamics(nn.Module):
    """Discrete-time dynamics ``x_{t+1} = f(x_t, u_t)``.

    Subclasses set ``state_dim`` and ``control_dim`` and implement :meth:`forward`.
    They may override :meth:`jacobians` with analytic derivatives, which
    :func:`torchslq.linearize` then uses instead of automatic differentiation.
    """

    state_dim: int
    control_dim: int

    def forward(self, x: Tensor, u: Tensor) -> Tensor:  # pragma: no cover - abstract
        """Next state ``(..., n)`` from ``x (..., n)`` and ``u (..., m)``."""
        raise NotImplementedError(f"{type(self).__name__} must implement forward(x, u)")

    def jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """Analytic ``(A, B) = (df/dx (..., n, n), df/du (..., n, m))``; optional."""
        raise NotImplementedError

    @property
    def has_analytic_jacobians(self) -> bool:
        return type(self).jacobians is not Dynamics.jacobians

    def vhp(self, x: Tensor, u: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Analytic second derivatives weighted by ``s``: the Hessian blocks of
        ``s · f(x, u)``, ``(Hxx (..., n, n), Huu (..., m, m), Hux (..., m, n))``; optional.

        ``s (..., n)`` may have extra leading dims that broadcast against ``x``'s (e.g.
        ``(k, *lead, n)`` for ``k`` weight vectors at once). When overridden,
        :func:`torchslq.dynamics.dynamics_vhp` and
        :func:`~torchslq.dynamics.dynamics_hessians` (DDP's second-order terms, the MPC
        layer's exact implicit gradients) use it instead of automatic differentiation."""
        raise NotImplementedError

    @property
    def has_analytic_vhp(self) -> bool:
        return type(self).vhp is not Dynamics.vhp

    #: Whether :meth:`compiled_step` and the compiled derivatives may be generated from
    #: :meth:`forward` (:mod:`torchslq.dynamics.codegen`); set False in a subclass to keep
    #: it on torch ops (``TORCHSLQ_CODEGEN=0`` turns generation off for all models).
    generate_compiled_code: bool = True
    #: Whether generated derivatives replace the model's own analytic :meth:`jacobians` /
    #: :meth:`vhp` on the CPU (the zoo's models, whose analytic forms are the same
    #: equations); by default a model's own derivatives are what it is linearised with.
    prefer_generated_derivatives: bool = False

    def compiled_step(self):
        """CPU fast path for rollouts: ``(step, params)`` with ``step`` a numba-compiled
        function ``step(x, u, params, out, work)`` that writes ``f(x, u)`` for one row
        (1-d arrays ``x (n,)``, ``u (m,)``, ``out (n,)``; ``work`` an ``(8, n)`` scratch
        array it may use) and ``params`` a 1-d float64 array; or None where there is none
        (e.g. per-element parameters). Closed-loop rollouts without autograd then run as
        one compiled loop (:func:`torchslq.dynamics.rollout_closed_loop`). It must compute
        what :meth:`forward` computes (up to the last bits of library functions such as
        ``cos``). By default generated from :meth:`forward`
        (:mod:`torchslq.dynamics.codegen`, which says when it cannot be), or for a
        learned model from its traced graph (:mod:`torchslq.dynamics.network_codegen`)."""
        from .codegen import generated_hooks

        hooks = generated_hooks(self)
        if hooks is None:
            from .network_codegen import network_step

            return network_step(self)  # a learned model's, from its traced graph
        return hooks.step, hooks.params(self)

    def compiled_jacobians(self, x: Tensor, u: Tensor) -> tuple[Tensor, Tensor] | None:
        """``(A, B)`` on the CPU kernel from the code generated from :meth:`forward` (for a
        learned model from its traced graph, :mod:`torchslq.dynamics.network_reverse`), or
        None where it does not apply (:func:`torchslq.linearize` then uses
        :meth:`jacobians` or automatic differentiation). Detached."""
        hooks = self._generated_kernel_hooks(x, u)
        if hooks is None:
            from .network_codegen import network_jacobians

            return network_jacobians(self, x, u)  # a learned model's, from its graph
        from .compiled_rk4 import rk4_jacobians_compiled

        return rk4_jacobians_compiled(hooks, 0.0, x, u)

    def compiled_vhp(self, x: Tensor, u: Tensor, s: Tensor):
        """:meth:`vhp` on the CPU kernel from the generated code (``s`` may carry extra
        leading dims), or None where it does not apply. Detached."""
        hooks = self._generated_kernel_hooks(x, u, s)
        if hooks is None:
            return None
        from .compiled_rk4 import rk4_vhp_compiled

        return rk4_vhp_compiled(hooks, 0.0, x, u, s)

    def _generated_kernel_hooks(self, *tensors: Tensor):
        """The generated functions as the derivative kernels' arguments, when ``tensors``
        are CPU float tensors and nothing needs autograd; else None."""
        from .._backend import can_use_compiled, module_needs_grad

        if not can_use_compiled(*tensors) or module_needs_grad(self):
            return None
        if (self.has_analytic_jacobians or self.has_analytic_vhp) and not (
            self.prefer_generated_derivatives
        ):
            return None  # the model's own derivatives (see linearize)
        return pinned(self, "kernel_hooks", self._generated_kernel_hooks_now)

    def _generated_kernel_hooks_now(self):
        from .codegen import generated_hooks

        hooks = generated_hooks(self)
        if hooks is None:
            return None
        from .compiled_rk4 import rk4_hooks

        return rk4_hooks((hooks.rhs, hooks.params(self)), hooks.derivatives, discrete=True)


class CompiledDerivatives(NamedTuple):
    """What :meth:`ContinuousDynamics.compiled_derivatives` may return: the numba
    function and the model's curvature pattern, the same at every point: the outputs
    whose Hessian can be nonzero and the ``z = (x, u)`` entries (rows and columns of
    those Hessians) where it can be; ``derivatives`` writes only those entries of ``H``
    and the kernel reads only those (instead of scanning the whole ``H`` per point)."""

    derivatives: Callable
    curved_outputs: tuple[int, ...]
    curved_entries: tuple[int, ...]


class ContinuousDynamics(nn.Module):
    """Continuous-time dynamics ``xdot = f(x, u, t)``.

    Subclasses set ``state_dim`` and ``control_dim`` and implement :meth:`forward`; they
    may override :meth:`jacobians` (``(df/dx, df/du)``) with analytic derivatives,
    which :func:`torchslq.discretize` chains through its integration scheme.
    """

    state_dim: int
    control_dim: int

    def forward(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> Tensor:  # pragma: no cover
        """Time derivative ``(..., n)``."""
        raise NotImplementedError(f"{type(self).__name__} must implement forward(x, u, t=None)")

    def jacobians(self, x: Tensor, u: Tensor, t: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Analytic ``(df/dx (..., n, n), df/du (..., n, m))``; optional."""
        raise NotImplementedError

    @property
    def has_analytic_jacobians(self) -> bool:
        return type(self).jacobians is not ContinuousDynamics.jacobians

    def vhp(
        self, x: Tensor, u: Tensor, s: Tensor, t: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Analytic Hessian blocks of ``s · f(x, u)`` (as :meth:`Dynamics.vhp`; ``s`` may
        carry extra leading dims); optional. With analytic :meth:`jacobians` too,
        :func:`torchslq.discretize` chains them through its integration scheme."""
        raise NotImplementedError

    @property
    def has_analytic_vhp(self) -> bool:
        return type(self).vhp is not ContinuousDynamics.vhp

    #: Whether :meth:`compiled_rhs` and :meth:`compiled_derivatives` may be generated from
    #: :meth:`forward` (:mod:`torchslq.dynamics.codegen`); set False in a subclass to keep
    #: it on torch ops (``TORCHSLQ_CODEGEN=0`` turns generation off for all models).
    generate_compiled_code: bool = True
    #: Whether generated derivatives replace the model's own analytic :meth:`jacobians` /
    #: :meth:`vhp` in :func:`torchslq.discretize`'s CPU kernels (the zoo's models); by
    #: default a model's own derivatives are chained through the scheme.
    prefer_generated_derivatives: bool = False

    def compiled_rhs(self):
        """Optional: ``(rhs, params)`` with ``rhs(x, u, params, out)`` a numba function
        writing ``f(x, u)`` for one row (time-invariant models; ``params`` a 1-d float64
        array), so that :func:`torchslq.discretize` can give its step as a compiled
        function (:meth:`torchslq.Dynamics.compiled_step`).

        By default it is generated from :meth:`forward` (traced once, differentiated
        symbolically and compiled, see :mod:`torchslq.dynamics.codegen`); None where that
        is not possible (:func:`torchslq.dynamics.codegen.explain` says why)."""
        from .codegen import generated_hooks

        hooks = generated_hooks(self)
        if hooks is None:
            return None
        return hooks.rhs, hooks.params(self)

    def compiled_derivatives(self):
        """Optional, with :meth:`compiled_rhs`: the model's first and second derivatives as
        a numba function ``derivatives(x, u, params, fz, H)`` taking ``compiled_rhs``'s
        ``params``, that writes ``[f_x | f_u]`` at one row into ``fz (n, n + m)`` and,
        unless ``H`` is empty (``H.shape[0] == 0``), every output's Hessian in
        ``z = (x, u)`` into ``H (n, n + m, n + m)``; or a :class:`CompiledDerivatives`
        giving that function with the model's curvature pattern (the function then
        writes only those entries of ``H``; the others are known zeros); or None (the
        default). :func:`torchslq.discretize`'s RK4 step then computes its Jacobians
        and second derivatives on CPU kernels (:mod:`torchslq.dynamics.compiled_rk4`)
        when nothing needs autograd. It must agree with :meth:`jacobians` and
        :meth:`vhp`. By default generated from :meth:`forward` with
        :meth:`compiled_rhs`."""
        if (self.has_analytic_jacobians or self.has_analytic_vhp) and not (
            self.prefer_generated_derivatives
        ):
            return None  # the model's own derivatives, chained by discretize
        from .codegen import generated_hooks

        hooks = generated_hooks(self)
        return None if hooks is None else hooks.derivatives


def state_control_dims(dynamics: nn.Module) -> tuple[int, int]:
    """``(state_dim, control_dim)`` of a dynamics module, with a clear error if missing."""
    n = getattr(dynamics, "state_dim", None)
    m = getattr(dynamics, "control_dim", None)
    if (
        not isinstance(n, int)
        or not isinstance(m, int)
        or isinstance(n, bool)
        or isinstance(m, bool)
    ):
        raise TypeError(
            f"{type(dynamics).__name__} must declare integer attributes state_dim and "
            "control_dim (wrap a plain network with torchslq.LearnedDynamics)"
        )
    if n < 1 or m < 1:
        raise ValueError(
            f"{type(dynamics).__name__} has state_dim {n} and control_dim {m}; both must be >= 1"
        )
    return n, m


def identity_like(x: Tensor, n: int) -> Tensor:
    return torch.eye(n, dtype=x.dtype, device=x.device).expand(*x.shape[:-1], n, n)
