"""Nonlinear rollouts of a model (open loop and with feedback) and the costate (adjoint)
gradient of the reduced cost: what every solver and the problem need of the dynamics."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from .._backend import (
    can_use_compiled,
    closed_loop_feedback_compiled,
    closed_loop_rollout_compiled,
    costate_compiled,
    module_needs_grad,
)
from .._pinned import pinned
from .._shapes import broadcast_shapes
from .row_blocks import rows_independent

__all__ = ["checked_step", "costate_gradient", "rollout", "rollout_closed_loop"]


def checked_step(x_next: Tensor, x: Tensor) -> Tensor:
    """``x_next``, the model's output for the states ``x``, after checking it has their
    shape, dtype and device (metadata only: no host sync). A model that returns another
    shape for some inputs (e.g. the line search's extra trial dimension) would otherwise
    feed the compiled kernels arrays of the wrong size, and a float32 output in a float64
    solve would silently lose precision."""
    if not torch.is_tensor(x_next):
        raise TypeError(f"the dynamics must return a tensor, got {type(x_next).__name__}")
    if x_next.shape != x.shape or x_next.dtype != x.dtype or x_next.device != x.device:
        raise ValueError(
            f"the dynamics returned shape {tuple(x_next.shape)}, {x_next.dtype} on "
            f"{x_next.device} for states of shape {tuple(x.shape)}, {x.dtype} on {x.device}: "
            "the next state must have the shape, dtype and device of the state"
        )
    return x_next


def rollout(f: Callable[[Tensor, Tensor], Tensor], x0: Tensor, u: Tensor) -> Tensor:
    """``x_{t+1} = f(x_t, u_t)`` for ``x0 (..., n)``, ``u (..., T, m)`` -> ``x (..., T+1, n)``
    (the leading dims of ``x0`` and ``u`` broadcast).

    ``f`` is called on ``(..., 1, n)`` slices (a singleton time dim) so that per-element
    parameters shaped ``(B, 1)`` broadcast the same way as in linearisation. A model with
    a compiled step (:meth:`torchslq.Dynamics.compiled_step`) is rolled out in one kernel
    call where no autograd graph is needed (the initial rollout of every solver: for one
    cart-pole problem the torch path's 200 small model calls were a quarter of a DDP
    solve).
    """
    if can_use_compiled(x0, u):
        x = _rollout_compiled(f, x0, u)
        if x is not None:
            return x
    lead = broadcast_shapes(x0.shape[:-1], u.shape[:-2])
    xt = x0.expand(*lead, x0.shape[-1]).unsqueeze(-2)
    xs = [xt]
    for t in range(u.shape[-2]):
        xt = checked_step(f(xt, u[..., t : t + 1, :]), xt)
        xs.append(xt)
    return torch.cat(xs, dim=-2)


def rollout_closed_loop(
    f: Callable[[Tensor, Tensor], Tensor],
    x0: Tensor,
    x_nom: Tensor,
    u_nom: Tensor,
    K: Tensor,
    k: Tensor,
    alpha: Tensor,
    u_min: Tensor | None = None,
    u_max: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Feedback rollout ``u_t = u_nom_t + alpha k_t + K_t (x_t - x_nom_t)``.

    Args:
        x0: ``(..., B, n)``; x_nom ``(B, T+1, n)``; u_nom ``(B, T, m)``; K ``(B, T, m, n)``;
        k ``(B, T, m)``; alpha ``(..., B)`` step sizes (leading dims: candidate steps);
            a NaN step gives NaN states and controls (with a model's compiled step that
            row is not rolled out at all: a line-search trial no element needs).
        u_min, u_max: optional control bounds ``(B, T, m)`` (or broadcastable, with a
            time dim); the control is clamped into ``[u_min, u_max]`` before it is
            applied (control-limited iLQR/DDP).

    Returns:
        ``x (..., B, T+1, n)`` and ``u (..., B, T, m)``.
    """
    bounds = tuple(b for b in (u_min, u_max) if b is not None)
    if can_use_compiled(x0, x_nom, u_nom, K, k, alpha, *bounds):
        out = _rollout_closed_loop_compiled(f, x0, x_nom, u_nom, K, k, alpha, u_min, u_max)
        if out is not None:
            return out
    T = u_nom.shape[-2]
    # everything that does not depend on the new states is formed for all steps at
    # once, time-major, so that each step is a handful of small ops (rollouts are
    # dispatch-bound: ~6 ops per step here besides the model, instead of ~14)
    ff = (u_nom + alpha[..., None, None] * k).unsqueeze(-2).movedim(-3, 0)  # (T, ..., B, 1, m)
    KT = K.mT.movedim(-3, 0)  # (T, B, n, m)
    xn = x_nom.unsqueeze(-2).movedim(-3, 0)  # (T+1, B, 1, n)
    lo = None if u_min is None else u_min.unsqueeze(-2).movedim(-3, 0)
    hi = None if u_max is None else u_max.unsqueeze(-2).movedim(-3, 0)
    xt = x0.unsqueeze(-2)
    xs, us = [xt], []
    for t in range(T):
        ut = ff[t] + (xt - xn[t]) @ KT[t]
        if lo is not None:
            ut = torch.maximum(ut, lo[t])
        if hi is not None:
            ut = torch.minimum(ut, hi[t])
        xt = checked_step(f(xt, ut), xt)
        xs.append(xt)
        us.append(ut)
    return torch.cat(xs, dim=-2), torch.cat(us, dim=-2)


def _rollout_closed_loop_compiled(f, x0, x_nom, u_nom, K, k, alpha, u_min, u_max):
    """:func:`rollout_closed_loop` with the feedback of each step on the CPU kernel
    (:func:`~torchslq._backend.closed_loop_feedback_compiled`): the controls are
    written into one buffer holding the feedforward, so a step is the kernel call and
    the model. None when the model's states need autograd (the kernel would cut the
    graph): the caller then takes the torch path."""
    T, m, n = u_nom.shape[-2], u_nom.shape[-1], x0.shape[-1]
    Bsz = broadcast_shapes(x_nom.shape[:-2], u_nom.shape[:-2], K.shape[:-3], k.shape[:-2])
    if len(Bsz) != 1:
        return None
    (B,) = Bsz
    lead = broadcast_shapes(alpha.shape, x0.shape[:-1], (B,))
    u = (u_nom + alpha[..., None, None] * k).expand(*lead, T, m).contiguous()
    xn, KB = x_nom[..., :T, :].expand(B, T, n), K.expand(B, T, m, n)
    # a NaN step is a line-search trial no element needs (armijo_search's skip_settled):
    # not rolled out, its states are NaN as on the torch path
    skip = torch.isnan(alpha)
    skipping = bool(skip.any())
    compiled = compiled_step_of(f)
    if compiled is not None:  # the model's own compiled step: one kernel call in all
        x = closed_loop_rollout_compiled(
            *compiled, x0, xn, KB, u, u_min, u_max, skip if skipping else None
        )
        return x, u
    x0 = x0.expand(*lead, n)
    if skipping and len(lead) > 1 and _rows_separable(f, B):
        return _rollout_needed_rows(f, x0, xn, KB, u, u_min, u_max, ~skip.expand(lead))
    x = _feedback_loop(f, x0, xn, KB, u, u_min, u_max)
    return None if x is None else (x, u)


def _rows_separable(f, batch_size: int) -> bool:
    """Whether ``f`` may be called on any subset of a batch's rows: a module holding no
    per-element data (:func:`~torchslq.dynamics.row_blocks.rows_independent`; a plain
    callable may hold some out of sight)."""
    return isinstance(f, nn.Module) and rows_independent(f, torch.Size([batch_size]))


def _feedback_loop(f, x0, xn, K, u, u_min, u_max) -> Tensor | None:
    """The closed-loop rollout of a torch model, step by step, with the feedback of each
    step on the CPU kernel (:func:`_rollout_closed_loop_compiled`'s arguments, ``u``
    overwritten with the applied controls); ``x (..., B, T+1, n)``, or None when the
    model's states need autograd."""
    feedback = closed_loop_feedback_compiled(xn, K, u, u_min, u_max)
    grad = torch.is_grad_enabled()
    xt = x0.unsqueeze(-2)
    xs = [xt]
    for t in range(u.shape[-2]):
        if grad and xt.requires_grad:
            return None
        feedback(t, xt)
        xt = checked_step(f(xt, u[..., t : t + 1, :]), xt)
        xs.append(xt)
    return torch.cat(xs, dim=-2)


def _rollout_needed_rows(f, x0, xn, K, u, u_min, u_max, needed):
    """:func:`_feedback_loop` on the rows of ``needed (..., B)`` only: a line search's
    later passes need the trials of the few elements still searching (NaN steps mark the
    others), and a torch model's cost grows with its rows. The other rows' states after
    ``x0`` and their controls are NaN, as a NaN step gives them."""
    B, T, m = u.shape[-3:]
    n = x0.shape[-1]
    rows = needed.reshape(-1).nonzero().squeeze(-1)
    elements = rows % B  # the lead's last dim is the batch
    uf = u.view(-1, T, m)

    def of_elements(b):
        return None if b is None else b.expand(B, T, m)[elements]

    u_rows = uf[rows]
    x_rows = _feedback_loop(
        f, x0.reshape(-1, n)[rows], xn[elements], K[elements], u_rows,
        of_elements(u_min), of_elements(u_max),
    )  # fmt: skip
    if x_rows is None:
        return None
    x = x0.new_full((uf.shape[0], T + 1, n), float("nan"))
    x[:, 0] = x0.reshape(-1, n)
    x[rows] = x_rows
    uf.fill_(float("nan"))
    uf[rows] = u_rows
    return x.view(*u.shape[:-2], T + 1, n), u


def _rollout_compiled(f, x0: Tensor, u: Tensor) -> Tensor | None:
    """:func:`rollout` on the whole-rollout kernel with the model's compiled step (the
    closed-loop kernel with zero gains), or None without one."""
    compiled = compiled_step_of(f)
    if compiled is None or u.ndim < 2:
        return None
    T, m, n = u.shape[-2], u.shape[-1], x0.shape[-1]
    lead = broadcast_shapes(x0.shape[:-1], u.shape[:-2])
    uc = u.detach().expand(*lead, T, m).clone(memory_format=torch.contiguous_format)
    zero_K = u.new_zeros(1, T, m, n)  # u_t + 0 (x_t - 0): the controls as given
    return closed_loop_rollout_compiled(*compiled, x0, u.new_zeros(1, T, n), zero_K, uc, None, None)


def compiled_step_of(f):
    """``f.compiled_step()`` (:meth:`torchslq.Dynamics.compiled_step`: the step function
    and its parameters array) when ``f`` has one and its parameters need no autograd
    here, else None."""
    get = getattr(f, "compiled_step", None)
    if get is None or module_needs_grad(f):
        return None
    return pinned(f, "compiled_step", get)  # once per solve (the parameter array too)


def costate_gradient(
    A: Tensor, B: Tensor, lx: Tensor, lu: Tensor, K: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Gradient of ``J(U)`` by the costate recursion (Sideris & Bobrow eqs. 8-11).

    ``lam_T = l_x(T)``, ``lam_t = l_x(t) + A_t' lam_{t+1}`` (eq. 8-9) and
    ``dJ/du_t = l_u(t) + B_t' lam_{t+1}`` (eq. 10).

    With feedback gains ``K`` (the controls are ``u_t = v_t + K_t x_t``, e.g. GoPRONTO's
    projection, eq. 16) the gradient is taken with respect to the feedforward ``v``:
    ``lam_t = l_x(t) + A_t' lam_{t+1} + K_t' g_t`` with ``g_t = l_u(t) + B_t' lam_{t+1}``,
    i.e. the costate of the closed loop ``A + B K`` with ``l_x + K' l_u``, without forming
    ``A + B K`` (``O(n^2 + nm)`` per step instead of ``O(n^2 m)``).

    Args:
        A ``(B, T, n, n)``, B ``(B, T, n, m)``, lx ``(B, T+1, n)``, lu ``(B, T, m)``,
        K ``(B, T, m, n)`` or None.

    Returns:
        ``grad (B, T, m)`` and costates ``lam (B, T+1, n)``.
    """
    if can_use_compiled(A, B, lx, lu, *(() if K is None else (K,))):
        out = costate_compiled(A, B, lx, lu, K)
        if out is not None:
            return out
    T = lu.shape[-2]
    lam = lx[..., T, :].unsqueeze(-1)
    lams = [lam] * (T + 1)
    grads = [lam] * T
    for t in range(T - 1, -1, -1):
        g = lu[..., t, :].unsqueeze(-1) + B[..., t, :, :].mT @ lam
        grads[t] = g
        lam = lx[..., t, :].unsqueeze(-1) + A[..., t, :, :].mT @ lam
        if K is not None:
            lam = lam + K[..., t, :, :].mT @ g
        lams[t] = lam
    return torch.stack(grads, dim=-3)[..., 0], torch.stack(lams, dim=-3)[..., 0]
