"""Quadratic tracking cost of Sideris & Bobrow (2005), eqs. (3)-(4)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .._backend import _launch, can_use_compiled
from .._pinned import pinned
from .._shapes import broadcast_shapes
from ..status import Status

__all__ = ["CostExpansion", "QuadraticCost"]


@dataclass
class CostExpansion:
    """Second-order expansion of a cost about a trajectory ``(x, u)``.

    ``J(x + dx, u + du) ~ J + sum_t [lx'dx + lu'du + 1/2 dx'lxx dx + 1/2 du'luu du +
    du'lux dx]`` with ``lxx (.., T+1, n, n)`` (index T: terminal), ``luu (.., T, m, m)``,
    ``lux (.., T, m, n)`` or None, ``lx (B, T+1, n)``, ``lu (B, T, m)``. The Hessians may
    keep a broadcastable (shared) batch dim. These are exactly the ``Q, R, S, q, r``
    arguments of :func:`torchslq.lqr_solve`.
    """

    lxx: Tensor
    luu: Tensor
    lux: Tensor | None
    lx: Tensor
    lu: Tensor


def _register(module: nn.Module, name: str, value: Tensor | None) -> None:
    if isinstance(value, nn.Parameter):
        module.register_parameter(name, value)
    else:
        module.register_buffer(name, value)


class QuadraticCost(nn.Module):
    """``J = 1/2 sum_{t<T} [|x_t - x°_t|^2_Q_t + |u_t - u°_t|^2_R_t] + 1/2 |x_T - x°_T|^2_Qf``.

    This is the performance index of Sideris & Bobrow eqs. (1), (3), (4).

    Args:
        Q: state weight, ``(n, n)`` constant, ``(T, n, n)`` time-varying, or
            ``(B, T, n, n)`` per batch element (time dim 1 broadcasts: ``(B, 1, n, n)``
            is a per-element constant). Symmetric positive semidefinite.
        R: control weight, ``(m, m)``, ``(T, m, m)`` or ``(B, T, m, m)``; symmetric
            positive definite.
        Qf: terminal weight ``(n, n)`` or ``(B, n, n)``; defaults to the last stage
            weight (``Q`` itself when constant).
        x_ref: state targets ``x°``: ``(n,)``, ``(T+1, n)`` or ``(B, T+1, n)``; default 0.
        u_ref: control targets ``u°``: ``(m,)``, ``(T, m)`` or ``(B, T, m)``; default 0.

    Tensors that require grad (e.g. ``nn.Parameter``) stay connected, so cost
    parameters can be learned through a differentiable solve.
    """

    def __init__(
        self,
        Q: Tensor,
        R: Tensor,
        Qf: Tensor | None = None,
        x_ref: Tensor | None = None,
        u_ref: Tensor | None = None,
    ):
        super().__init__()
        Q = _as_tensor("Q", Q)
        R = _as_tensor("R", R, like=Q)
        if Q.ndim not in (2, 3, 4) or Q.shape[-1] != Q.shape[-2]:
            raise ValueError(f"Q must have shape (n,n), (T,n,n) or (B,T,n,n), got {tuple(Q.shape)}")
        if R.ndim not in (2, 3, 4) or R.shape[-1] != R.shape[-2]:
            raise ValueError(f"R must have shape (m,m), (T,m,m) or (B,T,m,m), got {tuple(R.shape)}")
        n, m = Q.shape[-1], R.shape[-1]
        if Qf is not None:
            Qf = _as_tensor("Qf", Qf, like=Q)
            if Qf.ndim not in (2, 3) or Qf.shape[-2:] != (n, n):
                raise ValueError(
                    f"Qf must have shape ({n},{n}) or (B,{n},{n}), got {tuple(Qf.shape)}"
                )
        if x_ref is not None:
            x_ref = _as_tensor("x_ref", x_ref, like=Q)
            if x_ref.ndim not in (1, 2, 3) or x_ref.shape[-1] != n:
                raise ValueError(
                    f"x_ref must have shape (n,), (T+1,n) or (B,T+1,n) with n={n}, got {tuple(x_ref.shape)}"
                )
        if u_ref is not None:
            u_ref = _as_tensor("u_ref", u_ref, like=Q)
            if u_ref.ndim not in (1, 2, 3) or u_ref.shape[-1] != m:
                raise ValueError(
                    f"u_ref must have shape (m,), (T,m) or (B,T,m) with m={m}, got {tuple(u_ref.shape)}"
                )
        faults = [_check_symmetric("Q", Q, psd=True), _check_symmetric("R", R, psd=False)]
        if Qf is not None:
            faults.append(_check_symmetric("Qf", Qf, psd=True))
        faults = [f for f in faults if f is not None]
        if len({f.shape for f in faults}) > 1:
            raise ValueError(
                f"per-element weights have different batch sizes: {[f.shape[0] for f in faults]}"
            )
        # per element: NOT_POSITIVE_DEFINITE where a weight is not PSD / PD (the element
        # is not solved), else RUNNING; see element_faults
        fault_codes = None
        if faults:
            bad = torch.stack(faults).any(0)
            fault_codes = torch.where(
                bad, int(Status.NOT_POSITIVE_DEFINITE), int(Status.RUNNING)
            ).to(torch.int64)
        self.state_dim, self.control_dim = n, m
        self._diagonal_cache: dict[str, tuple] = {}  # name -> (tensor, version, diagonal?)
        _register(self, "Q", Q)
        _register(self, "R", R)
        _register(self, "Qf", Qf)
        _register(self, "x_ref", x_ref)
        _register(self, "u_ref", u_ref)
        self.register_buffer("fault_codes", fault_codes, persistent=False)

    # ------------------------------------------------------------------ shapes per horizon
    def _time_varying(self, W: Tensor, steps: int, name: str, tail: int) -> Tensor:
        """``W`` as ``(Bw, steps, *tail)`` with broadcastable ``Bw`` (1 or B)."""
        if W.ndim == tail:
            return W.reshape(1, 1, *W.shape)
        if W.ndim == tail + 1:
            W = W.unsqueeze(0)
        if W.shape[1] not in (1, steps):
            raise ValueError(
                f"{name} has {W.shape[1]} time steps but the horizon needs {steps} (or 1)"
            )
        return W

    def weights(self, T: int) -> tuple[Tensor, Tensor]:
        """``Q (Bq, T+1, n, n)`` (index T is ``Qf``) and ``R (Br, T, m, m)``; batch dims 1 or B.

        Within a solve computed once per horizon (:func:`torchslq._pinned.pinned`)."""
        key = ("weights", T, torch.is_grad_enabled())  # (a graph to learnable weights)
        return pinned(self, key, lambda: self._weights(T))

    def _weights(self, T: int) -> tuple[Tensor, Tensor]:
        Qs = self._time_varying(self.Q, T, "Q", 2)
        if self.Qf is not None:
            QT = self.Qf if self.Qf.ndim == 3 else self.Qf.unsqueeze(0)
            QT = QT.unsqueeze(1)
        else:
            QT = Qs[:, -1:]
        bq = broadcast_shapes(Qs.shape[:1], QT.shape[:1])
        n = Qs.shape[-1]
        Qfull = torch.cat([Qs.expand(*bq, T, n, n), QT.expand(*bq, 1, n, n)], dim=1)
        return Qfull, self._time_varying(self.R, T, "R", 2)

    def references(self, T: int, like: Tensor) -> tuple[Tensor, Tensor]:
        """``x° (Bx, T+1, n)`` and ``u° (Bu, T, m)`` (zeros when not given, with
        ``like``'s dtype and device); within a solve computed once per horizon."""
        key = ("references", T, like.dtype, like.device, torch.is_grad_enabled())
        return pinned(self, key, lambda: self._references(T, like))

    def _references(self, T: int, like: Tensor) -> tuple[Tensor, Tensor]:
        n, m = self.state_dim, self.control_dim
        xr = (
            like.new_zeros(1, 1, n)
            if self.x_ref is None
            else self._time_varying(self.x_ref, T + 1, "x_ref", 1)
        )
        ur = (
            like.new_zeros(1, 1, m)
            if self.u_ref is None
            else self._time_varying(self.u_ref, T, "u_ref", 1)
        )
        return xr, ur

    def _check_traj(self, x: Tensor, u: Tensor) -> int:
        if not torch.is_tensor(x) or not torch.is_tensor(u):
            raise TypeError(
                f"x and u must be tensors (B,T+1,n) and (B,T,m), got {type(x).__name__} and "
                f"{type(u).__name__}"
            )
        if x.ndim < 3 or u.ndim < 3:
            raise ValueError(
                f"x must be (B,T+1,n) and u (B,T,m), got {tuple(x.shape)} and {tuple(u.shape)}"
            )
        T = u.shape[-2]
        if x.shape[-2] != T + 1 or x.shape[-1] != self.state_dim or u.shape[-1] != self.control_dim:
            raise ValueError(
                f"expected x (B,T+1,{self.state_dim}) and u (B,T,{self.control_dim}), "
                f"got {tuple(x.shape)} and {tuple(u.shape)}"
            )
        return T

    # ------------------------------------------------------------------ evaluation
    def forward(self, x: Tensor, u: Tensor) -> Tensor:
        """Cost ``(B,)`` of trajectories ``x (B, T+1, n)``, ``u (B, T, m)``.

        Extra leading dims are allowed (``x (..., B, T+1, n)`` gives ``(..., B)``); the
        batch dim of per-element weights aligns with the dim just before time.
        """
        T = self._check_traj(x, u)
        Qs, QT, Rs, xr, ur = self._value_inputs(T, x)
        terms = _compiled_terms(x, u, xr, ur, Qs, QT, Rs)
        if terms is not None:
            return _quadratic_cost_compiled(x, u, terms)
        dx, du = x - xr, u - ur
        # per-row products then a row-wise sum over time: unlike einsum (which may turn
        # into a batched GEMM whose blocking depends on B), this gives every element the
        # same bits whatever the batch it is evaluated in; line searches near the optimum
        # compare costs at that level. Diagonal weights are applied elementwise: the same
        # bits as the matrix product (whose other terms are exact zeros), without
        # broadcasting the weights into every leading dim (matmul would copy Q per trial
        # of a line search: gigabytes at n = 400)
        # (time and state summed in one reduction over each row's contiguous T * k
        # terms: a separate sum over a last dim of 2-4 entries is several times slower)
        Js = _quadratic_terms(Qs, dx[..., :T, :], self._diagonal("Q")).flatten(-2).sum(-1)
        Jf = _quadratic_terms(
            QT, dx[..., T, :], self._diagonal("Qf") if self.Qf is not None else self._diagonal("Q")
        ).sum(-1)
        Ju = _quadratic_terms(Rs, du, self._diagonal("R")).flatten(-2).sum(-1)
        return 0.5 * (Js + Jf + Ju)

    def _diagonal(self, name: str) -> bool:
        """Whether weight ``name`` is diagonal; one host sync per new value (cached on
        the tensor itself and its version, so in-place parameter updates re-check; the
        cache holds the tensor, so its identity cannot pass to another one)."""
        W = getattr(self, name)
        cache = self._diagonal_cache
        held = cache.get(name)
        if held is None or held[0] is not W or held[1] != W._version:
            Wd = W.detach()
            off = Wd - torch.diag_embed(Wd.diagonal(dim1=-2, dim2=-1))
            cache[name] = (W, W._version, not bool(off.any()))
        return cache[name][2]

    def element_faults(self, batch_size: int) -> Tensor | None:
        """``(batch_size,)`` int64 status codes: ``NOT_POSITIVE_DEFINITE`` for elements
        whose per-element weight is not positive (semi)definite, ``RUNNING`` for the
        others; None when every element is fine or the weights are shared (a shared
        weight that is not PD is an error at construction)."""
        f = self.fault_codes
        if f is None or f.shape[0] != batch_size or not bool((f != Status.RUNNING).any()):
            return None
        return f

    def check_batch(self, batch_size: int) -> None:
        """ValueError naming the weight or target given per element for another batch
        size than ``batch_size`` (``Q (B', T, n, n)`` with ``B'`` not 1 or ``B``); called
        by :meth:`torchslq.Problem.check_inputs`."""
        for name, ndim in _PER_ELEMENT_NDIM.items():
            t = getattr(self, name)
            if t is not None and t.ndim == ndim and t.shape[0] not in (1, batch_size):
                raise ValueError(
                    f"cost.{name} is given per element for a batch of {t.shape[0]} "
                    f"(shape {tuple(t.shape)}) but x0 has a batch of {batch_size}"
                )

    def per_element_names(self, batch_size: int) -> list[str]:
        """The weights and targets given per batch element (``(B, T, n, n)`` ``Q``,
        ``(B, T+1, n)`` ``x_ref``, ...) for a batch of ``batch_size``; see
        :mod:`torchslq.per_element`."""
        full = {**_PER_ELEMENT_NDIM, "fault_codes": 1}
        return [
            name
            for name, ndim in full.items()
            if (t := getattr(self, name)) is not None
            and t.ndim == ndim
            and t.shape[0] == batch_size
            and batch_size > 1
        ]

    def quadratize(self, x: Tensor, u: Tensor) -> CostExpansion:
        """Exact second-order expansion (the cost is quadratic): gradients
        ``lx = Q (x - x°)``, ``lu = R (u - u°)`` and Hessians ``Q``, ``R``."""
        T = self._check_traj(x, u)
        Q, R = self.weights(T)
        xr, ur = self.references(T, x)
        # diagonal weights elementwise: the matrix product's bits (its other terms are
        # exact zeros) without a batched product of tiny matrices per row
        if self._diagonal("Q") and (self.Qf is None or self._diagonal("Qf")):
            lx = Q.diagonal(dim1=-2, dim2=-1) * (x - xr)
        else:
            lx = (Q @ (x - xr).unsqueeze(-1)).squeeze(-1)
        if self._diagonal("R"):
            lu = R.diagonal(dim1=-2, dim2=-1) * (u - ur)
        else:
            lu = (R @ (u - ur).unsqueeze(-1)).squeeze(-1)
        return CostExpansion(lxx=Q, luu=R, lux=None, lx=lx, lu=lu)

    def compiled_terms(self, x: Tensor, u: Tensor) -> tuple | None:
        """The weights and references as the CPU cost kernel's arrays for trajectories
        like ``x (B, T+1, n)``, ``u (B, T, m)`` (see :func:`_compiled_terms`), or None
        where the kernel does not apply (outside :func:`compiled_cost_evaluation`, not
        float64 CPU tensors, autograd, dimensions over 32). A fused line search
        (:func:`torchslq.solvers.descent.LineSearch`) evaluates its trials with them."""
        T = self._check_traj(x, u)
        if not _compiled_costs.get():
            return None

        def terms():
            Qs, QT, Rs, xr, ur = self._value_inputs(T, x)
            return _compiled_terms(x, u, xr, ur, Qs, QT, Rs)

        # the same arrays for every trajectory of a solve (one sync for the zero check)
        key = ("compiled_terms", T, x.dtype, u.dtype, x.device, x.requires_grad or u.requires_grad)
        return pinned(self, (*key, torch.is_grad_enabled()), terms)

    def _value_inputs(self, T: int, like: Tensor) -> tuple[Tensor, ...]:
        """``(Qs (Bq, T or 1, n, n), QT (n, n) or (Bq, n, n), Rs (Br, T or 1, m, m), x°,
        u°)``: what the cost's value reads, for a horizon ``T``."""

        def inputs():
            Qs = self._time_varying(self.Q, T, "Q", 2)
            QT = self.Qf if self.Qf is not None else Qs[:, -1]
            Rs = self._time_varying(self.R, T, "R", 2)
            return Qs, QT, Rs

        key = ("value_inputs", T, torch.is_grad_enabled())
        return (*pinned(self, key, inputs), *self.references(T, like))


# the CPU kernel's dense per-row forms are for small weights (diagonal ones of large
# states are cheaper as the torch path's elementwise products)
_COMPILED_MAX_DIM = 32
_compiled_costs: ContextVar[bool] = ContextVar("torchslq_compiled_costs", default=False)


@contextmanager
def compiled_cost_evaluation() -> Iterator[None]:
    """Within this context :class:`QuadraticCost` values are computed on a CPU kernel
    where it applies (float64 CPU tensors, no autograd, dimensions up to 32). Its sums
    run in another order than the torch path's, so the two differ in the last bits: a
    solver enables it only around loops where every cost it compares is evaluated
    without autograd (the SLQ/iLQR/DDP loop), never where costs with and without a
    graph are compared (GoPRONTO's line search)."""
    token = _compiled_costs.set(True)
    try:
        yield
    finally:
        _compiled_costs.reset(token)


def _compiled_terms(x, u, xr, ur, Qs, QT, Rs) -> tuple | None:
    """``(Bw, (xr, ur, Q, QT, R), stage_states)``: the references and weights as the
    arrays of the CPU cost kernel (:func:`~torchslq._backend._numba_cost.quadratic_cost_row`;
    ``Bw`` their broadcast batch, ``stage_states`` False when ``Q`` is zero), inside
    :func:`compiled_cost_evaluation` where the kernel applies to ``x``, ``u``; else None
    (the caller takes the torch path)."""
    if not _compiled_costs.get() or x.dtype != torch.float64:
        return None
    n, m = x.shape[-1], u.shape[-1]
    if n > _COMPILED_MAX_DIM or m > _COMPILED_MAX_DIM:
        return None
    QT = QT if QT.ndim == 3 else QT.unsqueeze(0)
    if not can_use_compiled(x, u, xr, ur, Qs, QT, Rs):
        return None
    Bw = broadcast_shapes(*((t.shape[0],) for t in (xr, ur, Qs, QT, Rs)))[0]
    arrays = tuple(t.detach().contiguous().numpy() for t in (xr, ur, Qs, QT, Rs))
    stage_states = bool(Qs.detach().any())  # (a terminal-only state cost skips T forms)
    return Bw, arrays, stage_states


def _quadratic_cost_compiled(x: Tensor, u: Tensor, terms: tuple) -> Tensor:
    """The cost on the CPU kernel (:mod:`torchslq._backend._numba_cost`) with the arrays
    ``terms`` of :func:`_compiled_terms`: one pass per row instead of a dozen torch ops
    over the whole batch (line searches evaluate it for every trial step); the same
    value per row whatever batch it is evaluated in."""
    Bw, arrays, stage_states = terms
    lead = broadcast_shapes(x.shape[:-2], u.shape[:-2], (Bw,))
    B = lead[-1]
    rows = math.prod(lead)
    J = torch.empty(rows, dtype=x.dtype)
    xs = x.detach().expand(*lead, *x.shape[-2:]).reshape(rows, *x.shape[-2:])
    us = u.detach().expand(*lead, *u.shape[-2:]).reshape(rows, *u.shape[-2:])
    _launch(
        _cost_kernels().quadratic_cost_kernel,
        rows,
        x.shape[-2],
        B,
        xs.contiguous().numpy(),
        us.contiguous().numpy(),
        *arrays,
        stage_states,
        J.numpy(),
    )
    return J.view(lead)


def _cost_kernels():
    from .._backend import _numba_cost

    return _numba_cost


def _quadratic_terms(W: Tensor, d: Tensor, diagonal: bool) -> Tensor:
    """The terms ``d_i (W d)_i`` of ``d' W d`` per row (``d (..., k)``, ``W (..., k, k)``
    broadcasting), ``(..., k)``: the caller sums them (with the time dim, in one go)."""
    if diagonal:
        return d * (W.diagonal(dim1=-2, dim2=-1) * d)
    if W.ndim == 2:
        # a shared matrix: matmul would fold the rows into one GEMM, whose rounding can
        # depend on how many rows there are; a row-wise product cannot
        return d * (W * d.unsqueeze(-2)).sum(-1)
    return d * (W @ d.unsqueeze(-1)).squeeze(-1)


def _as_tensor(name: str, value, like: Tensor | None = None) -> Tensor:
    if isinstance(value, Tensor):
        t = value
    else:
        try:
            t = torch.as_tensor(value, dtype=None if like is None else like.dtype)
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(
                f"{name} must be a tensor or array-like, got {type(value).__name__}"
            ) from err
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype() if like is None else like.dtype)
    # per-element data (a leading batch dim) may hold a NaN in some elements: those
    # start as non_finite and the batch goes on (the granularity rule of Status)
    if not _per_element(name, t) and not bool(torch.isfinite(t.detach()).all()):
        raise ValueError(f"{name} contains non-finite values")
    return t


_PER_ELEMENT_NDIM = {"Q": 4, "R": 4, "Qf": 3, "x_ref": 3, "u_ref": 3}


def _per_element(name: str, t: Tensor) -> bool:
    return t.ndim == _PER_ELEMENT_NDIM[name] and t.shape[0] > 1


def _check_symmetric(name: str, W: Tensor, psd: bool) -> Tensor | None:
    """Raise if a shared weight is not symmetric (or not PSD / PD); for a per-element
    weight ``(B, ...)``, return the ``(B,)`` mask of elements that are not PSD / PD (a
    status for those elements, not an error for the batch). Symmetry is always
    required: a non-symmetric weight is a mistake in the code, not in the data."""
    Wd = W.detach()
    tol = 1e-10 if Wd.dtype == torch.float64 else 1e-6
    if Wd.dtype not in (torch.float32, torch.float64):  # eigvalsh has no float16 kernel
        Wd = Wd.float()
    per_element = _per_element(name, W)
    finite = torch.isfinite(Wd)
    Wd = torch.nan_to_num(Wd, nan=0.0, posinf=0.0, neginf=0.0)
    scale = (Wd.abs().amax() if Wd.numel() else Wd.new_zeros(())).clamp_min(1.0)
    if not bool(((Wd - Wd.mT).abs() <= tol * scale).all()):
        raise ValueError(f"{name} must be symmetric")
    eig = torch.linalg.eigvalsh(Wd)
    bad = (eig < -tol * scale * 10) if psd else (eig <= 0)
    bad = bad.flatten(1).any(1) & finite.flatten(1).all(1) if per_element else bad
    if per_element:
        return bad
    if bool(bad.any()):
        kind = "semidefinite" if psd else "definite"
        raise ValueError(f"{name} must be positive {kind} (min eigenvalue {eig.min().item():.3g})")
    return None
