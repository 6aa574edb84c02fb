"""Piecewise interpolants on per-element grids (padded ``(B, N+1)`` grids with a count).

* :class:`RodasDense`: Rodas5P's continuous output of order 4 on each step.
* :class:`PiecewiseCubic`: a cubic per interval through four samples at
  ``theta = 0, 1/3, 2/3, 1`` -- used for quantities that are not integrated states but
  functions of them (the control of the forward pass, the feedback terms ``d, K`` of the
  backward pass, the linearisation along the nominal trajectory): sampled once per
  step in one batched evaluation, then read anywhere by tensor arithmetic only.

Both are frozen dataclasses of batch-first tensors with :meth:`take` (rows ``idx``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

__all__ = ["PiecewiseCubic", "RodasDense", "SAMPLE_THETA", "locate"]

SAMPLE_THETA = (0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)


def locate(grid: Tensor, n_steps: Tensor, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The interval of each query: ``grid (B, N+1)`` sorted per row with ``n_steps (B,)``
    valid intervals, ``t (B, Q)`` -> ``(idx (B, Q), theta (B, Q), h (B, Q))`` with
    ``t = grid[idx] + theta h``. Queries outside the grid use the end intervals."""
    idx = torch.searchsorted(grid.contiguous(), t.contiguous(), right=True) - 1
    hi = (n_steps - 1).clamp_min(0)[:, None]
    idx = torch.minimum(idx.clamp_min(0), hi)
    left = grid.gather(1, idx)
    h = grid.gather(1, idx + 1) - left
    theta = torch.where(h > 0, (t - left) / torch.where(h > 0, h, torch.ones_like(h)), 0.0)
    return idx, theta, h


def _gather_steps(v: Tensor, idx: Tensor) -> Tensor:
    """``v (B, N, *rest)`` at ``idx (B, Q)`` -> ``(B, Q, *rest)``."""
    rest = v.shape[2:]
    i = idx.reshape(*idx.shape, *([1] * len(rest))).expand(*idx.shape, *rest)
    return v.gather(1, i)


@dataclass(frozen=True)
class _Piecewise:
    grid: Tensor
    n_steps: Tensor

    def take(self, idx: Tensor):
        """The interpolant of the rows ``idx``."""
        return replace(
            self, **{f.name: getattr(self, f.name).index_select(0, idx) for f in fields(self)}
        )

    def __call__(self, t: Tensor) -> Tensor:
        squeeze = t.ndim == 1
        tq = t[:, None] if squeeze else t
        out = self._at(tq)
        return out[:, 0] if squeeze else out

    def _at(self, t: Tensor) -> Tensor:
        """The interpolant at ``t (B, Q)``."""
        return self._eval(*locate(self.grid, self.n_steps, t))

    def _eval(self, idx: Tensor, theta: Tensor, h: Tensor) -> Tensor:  # pragma: no cover
        raise NotImplementedError


@dataclass(frozen=True)
class RodasDense(_Piecewise):
    """Rodas5P's dense output: on step ``i`` of element ``b``,
    ``y(t_i + theta h_i) = (1-theta) y0 + theta (y1 + (1-theta)(D1 + theta (D2 + theta D3)))``.

    Attributes: grid ``(B, N+1)``, n_steps ``(B,)``, h ``(B, N)``, y0/y1 ``(B, N, n)``
    (step start/end values), D ``(B, N, 3, n)``.
    """

    h: Tensor
    y0: Tensor
    y1: Tensor
    D: Tensor

    def _eval(self, idx, theta, h):
        y0, y1 = _gather_steps(self.y0, idx), _gather_steps(self.y1, idx)
        D = _gather_steps(self.D, idx)
        th = theta[..., None].to(y0.dtype)
        t1 = 1 - th
        return t1 * y0 + th * (y1 + t1 * (D[..., 0, :] + th * (D[..., 1, :] + th * D[..., 2, :])))


@dataclass(frozen=True)
class PiecewiseCubic(_Piecewise):
    """A cubic per interval through samples at ``theta = 0, 1/3, 2/3, 1``.

    Attributes: grid ``(B, N+1)``, n_steps ``(B,)``, values ``(B, N, 4, *shape)``.
    """

    values: Tensor

    def _at(self, t: Tensor) -> Tensor:
        # on the CPU without autograd: one kernel call instead of ~30 small torch ops
        # (the continuous-time solver reads its policy and linearisation this way at
        # every stage of every integration step)
        from .._backend.dispatch import _kernels, _launch, can_use_compiled

        v = self.values
        if not can_use_compiled(v, t, self.grid):
            return super()._at(t)
        B, N, Q = v.shape[0], v.shape[1], t.shape[1]
        vals = v.reshape(B, N, 4, -1).contiguous()
        out = v.new_empty(B, Q, vals.shape[-1])
        grid, steps, tq = self.grid.contiguous(), self.n_steps.contiguous(), t.contiguous()
        args = (grid.numpy(), steps.numpy(), vals.numpy(), tq.numpy(), out.numpy())
        _launch(_kernels().piecewise_cubic_kernel, B, Q, *args)
        return out.reshape(B, Q, *v.shape[3:])

    def _eval(self, idx, theta, h):
        v = _gather_steps(self.values, idx)  # (B, Q, 4, *shape)
        th = theta.to(v.dtype)
        # Lagrange basis on the nodes 0, 1/3, 2/3, 1
        a, b, c = th - 1.0 / 3.0, th - 2.0 / 3.0, th - 1.0
        w = torch.stack(
            [-4.5 * a * b * c, 13.5 * th * b * c, -13.5 * th * a * c, 4.5 * th * a * b], -1
        )
        w = w.reshape(*w.shape, *([1] * (v.ndim - 3)))
        return (w * v).sum(2)
