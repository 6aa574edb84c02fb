"""Stage hooks for the Riccati pass's tests: DDP's ``v_{t+1} · f_zz`` term from given
output Hessians, written here independently of the solvers' own hook."""

from __future__ import annotations

import torch
from torch import Tensor


class HessianHook:
    """``hook(t, Vh_next) = sum_i v_{t+1,i} [[Huu, Hux], [Hux', Hxx]]_i(t)`` per element.

    ``Hxx (n, B, T, n, n)``, ``Huu (n, B, T, m, m)``, ``Hux (n, B, T, m, n)``: the
    Hessians of output ``i`` at step ``t`` of element ``b``. :attr:`hessians` lets the
    compiled kernel run the pass; :meth:`subset` restricts the hook to some elements.
    """

    def __init__(self, Hxx: Tensor, Huu: Tensor, Hux: Tensor):
        self.blocks = (Hxx, Huu, Hux)

    @property
    def hessians(self) -> tuple[Tensor, Tensor, Tensor]:
        return self.blocks

    def __call__(self, t: int, Vh_next: Tensor) -> Tensor:
        Hxx, Huu, Hux = (h[:, :, t] for h in self.blocks)  # (n, B, ., .)
        Hz = torch.cat([torch.cat([Huu, Hux], -1), torch.cat([Hux.mT, Hxx], -1)], -2)
        n = Hxx.shape[-1]
        v = Vh_next[..., :n, n]  # (B, n)
        return torch.einsum("bi,ibjk->bjk", v, Hz)

    def subset(self, idx: Tensor) -> HessianHook:
        return HessianHook(*(h.index_select(1, idx) for h in self.blocks))


class PlainHook:
    """The same term as a plain callable (no ``subset``, no ``hessians``): the torch path
    only, and a pass that cannot be restricted to some elements."""

    def __init__(self, hook: HessianHook):
        self._hook = hook

    def __call__(self, t: int, Vh_next: Tensor) -> Tensor:
        return self._hook(t, Vh_next)
