"""DDP: iLQR plus the second-order dynamics terms in the backward pass.

``Q_xx = l_xx + f_x' V'_xx f_x + V'_x · f_xx`` (likewise ``Q_uu``, ``Q_ux``): the last
term is a vector-Hessian product of the dynamics computed with ``torch.func``
(:func:`torchslq.dynamics.dynamics_vhp`, reverse-over-reverse, never the full
``n x n x n`` tensor). Two choices of the vector ``V'_x``:

* ``second_order="value"`` (classic DDP, Mayne 1966 / Tassa et al. 2012): the gradient
  ``v_{t+1}`` of the local value-function model, produced during the backward pass
  itself, so the product is taken step by step inside the Riccati loop (through the
  kernel's ``stage_hook``); ``T`` small autodiff calls per iteration;
* ``second_order="costate"``: the costates ``lam_{t+1}`` of the nominal trajectory
  (eq. 8 of Sideris & Bobrow), known before the backward pass, so all steps are done in
  one batched call. This is Newton's method on ``J(U)``; both variants coincide at a
  stationary point (``v = lam`` there) and converge quadratically nearby.

The regularisation, line search and loop are :class:`torchslq.ILQR`'s; an indefinite
``Quu`` (more likely with the second-order terms) raises ``mu`` for that element.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from torch import Tensor

from .._shapes import broadcast_shapes
from ..dynamics.linearize import dynamics_vhp, linearize_with_hessians, linearize_with_vhp
from ..lq.riccati import StageHook
from .ilqr import ILQR

if TYPE_CHECKING:  # pragma: no cover
    from ..problem import Problem

__all__ = ["DDP"]

_MODES = ("value", "costate")


class DDP(ILQR):
    """Differential dynamic programming (iLQR + dynamics second derivatives).

    Args:
        second_order: ``"value"`` (default, classic DDP) or ``"costate"`` (batched over
            time; see the module docstring).
        vhp_memory_limit: for ``"value"``: when the ``n`` per-output Hessians of all
            steps (``B T n (n+m)^2`` numbers) fit in this many bytes, they are computed
            in one batched call per iteration and contracted with ``v_{t+1}`` in the
            Riccati loop; otherwise (or with None) one vector-Hessian product is taken per
            step inside the loop. Same result, the first is much faster for small ``n``.
        **kwargs: as for :class:`torchslq.ILQR`.
    """

    name = "ddp"

    def __init__(
        self,
        *args: Any,
        second_order: str = "value",
        vhp_memory_limit: int | None = 256 * 2**20,
        **kwargs: Any,
    ):
        super().__init__(*args, **kwargs)
        self.vhp_memory_limit = vhp_memory_limit
        if second_order not in _MODES:
            raise ValueError(f"second_order must be one of {_MODES}, got {second_order!r}")
        self.second_order = second_order

    def _linearize(self, problem: Problem, x: Tensor, u: Tensor):
        method = self.options.linearize_method
        if self.second_order == "costate":
            # the costate mode's VHP at the same steps follows: share what the model allows
            return linearize_with_vhp(problem.transition, x, u, method=method)
        if self._all_hessians(problem, x):
            # every output's Hessians at the same steps follow: one pass where the model
            # allows (the third item is then a function returning them)
            return linearize_with_hessians(problem.transition, x, u, method=method)
        return super()._linearize(problem, x, u)

    def _all_hessians(self, problem: Problem, x: Tensor) -> bool:
        """Whether the value mode takes all ``n`` output Hessians of every step at once
        (they fit in ``vhp_memory_limit``) rather than one product per step."""
        if self.vhp_memory_limit is None:
            return False
        n, m, T = problem.state_dim, problem.control_dim, problem.horizon
        need = x.shape[0] * T * n * (n + m) ** 2 * x.element_size()
        return need <= self.vhp_memory_limit

    def _second_order(
        self, problem: Problem, x: Tensor, u: Tensor, lam: Tensor, e, vhp=None
    ) -> StageHook | None:
        f = problem.transition
        n, T = problem.state_dim, problem.horizon
        if self.second_order == "costate":
            Hxx, Huu, Hux = vhp(lam[:, 1:])  # from _linearize: shares its RK4 stages
            Bsz = x.shape[0]
            e.lxx = e.lxx.expand(Bsz, *e.lxx.shape[1:]).clone()
            e.lxx[:, :T] += Hxx
            e.luu = e.luu.expand(Bsz, *e.luu.shape[1:]) + Huu
            e.lux = Hux if e.lux is None else e.lux.expand_as(Hux) + Hux
            return None

        if vhp is not None:
            # _linearize gave every output's Hessians of all steps (they fit in
            # vhp_memory_limit), possibly from one pass with the Jacobians: contracted
            # with v_{t+1} inside the Riccati loop
            return _HessianHook(*vhp())

        def hook(t: int, Vh_next: Tensor) -> Tensor:
            s = Vh_next[..., :n, n].unsqueeze(-2)  # v_{t+1}, (B, 1, n)
            Hxx, Huu, Hux = dynamics_vhp(f, x[:, t : t + 1], u[:, t : t + 1], s)
            return _block(Hxx, Huu, Hux)[:, 0]  # [u; x] ordering, (B, m+n, m+n)

        return hook


class _HessianHook:
    """Stage hook ``v_{t+1} · f_zz(t)`` from precomputed output Hessians.

    ``Hxx (n, B, T, n, n)``, ``Huu (n, B, T, m, m)``, ``Hux (n, B, T, m, n)``: the
    Hessians of output ``i`` at step ``t`` of element ``b``
    (:func:`~torchslq.dynamics.dynamics_hessians`' layout). The compiled Riccati kernel
    reads them as they are (:attr:`hessians`); the torch path contracts ``Hz (T, n, B,
    m+n, m+n)``, the same in the kernel's ``[u; x]`` ordering, time-major so that each
    step's slice is contiguous, built on its first use. :meth:`subset` restricts them to
    some elements (a Riccati pass repeated for the elements whose factorisation failed).
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
            self._Hz = _block(*(h.movedim(2, 0) for h in self.blocks))
        return self._Hz

    def __call__(self, t: int, Vh_next: Tensor) -> Tensor:
        Hz = self.Hz
        n = Hz.shape[1]
        s = Vh_next[..., :n, n]  # v_{t+1}, (B, n)
        # a broadcast product summed over the outputs: measured 1.6x faster than einsum
        return (s.mT.unsqueeze(-1).unsqueeze(-1) * Hz[t]).sum(0)

    def subset(self, idx: Tensor) -> _HessianHook:
        return _HessianHook(*(h.index_select(1, idx) for h in self.blocks))


def _block(Hxx: Tensor, Huu: Tensor, Hux: Tensor) -> Tensor:
    """``[[Huu, Hux], [Hux', Hxx]]``: the Hessian in the kernel's ``[u; x]`` ordering.

    Written block by block into one new tensor (each entry written once; three
    concatenations wrote most of them twice: 2.6x slower for the unicycle's
    ``(T, n, B, 5, 5)`` blocks)."""
    m, n = Hux.shape[-2], Hux.shape[-1]
    lead = broadcast_shapes(Hxx.shape[:-2], Huu.shape[:-2], Hux.shape[:-2])
    out = Hxx.new_empty(*lead, m + n, m + n)
    out[..., :m, :m] = Huu
    out[..., :m, m:] = Hux
    out[..., m:, :m] = Hux.mT
    out[..., m:, m:] = Hxx
    return out
