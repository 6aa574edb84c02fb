"""Batched box-constrained QP by projected Newton (Tassa, Mansard & Todorov 2014).

``min_x 1/2 x'Hx + g'x  s.t.  lower <= x <= upper`` for a batch of small problems
(``H`` positive definite on the free subspace), as used by control-limited DDP
(Tassa, Mansard, Todorov, "Control-limited differential dynamic programming", ICRA
2014, Algorithm 3 "boxQP"). One iteration, for every batch element at once:

1. gradient ``grad = g + Hx``; the *clamped* set is ``{i: x_i = lower_i, grad_i > 0}``
   ``∪ {i: x_i = upper_i, grad_i < 0}``, the rest is *free*;
2. Cholesky factor of the free block ``H_ff``. Batched with masks: the clamped rows and
   columns of ``H`` are replaced by those of the identity, so one batched
   ``cholesky_ex`` factors every element's free block (the factor is the identity on
   the clamped rows/columns and ``chol(H_ff)`` on the free ones);
3. Newton step on the free subspace with the clamped entries held:
   ``x_f <- -H_ff^{-1} (g_f + H_fc x_c)``;
4. projected Armijo line search ``x(s) = clip(x + s d)`` over ``s = step_dec^j``: all
   candidate steps are evaluated at once (one batched evaluation, no serial
   backtracking) and the largest with ``f(x(s)) - f(x) <= armijo s d'grad`` is taken.

An element stops when its free gradient norm is below ``tol``, everything is clamped,
no descent is possible (the Newton direction is not a descent direction or no step
passes the Armijo test: the current point is optimal to working precision), the
relative improvement is at most ``min_rel_improve``, or the free block is not positive
definite (``success = False``). Stopped elements are frozen by masks; the loop over
iterations checks for "all stopped" only every ``check_every`` iterations (one host
synchronisation per check). Bounds may be infinite. A single variable (``m = 1``) is
solved in closed form (``clip(-g/h)``, no loop).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .._shapes import broadcast_shapes

__all__ = ["BoxQPResult", "box_qp"]

# box_qp's defaults; the compiled control-limited Riccati pass (torchslq/_backend/_numba_kernels.py)
# receives the same values
MAX_ITER, ARMIJO, STEP_DEC, N_STEPS = 100, 0.1, 0.6, 32


@dataclass
class BoxQPResult:
    """Output of :func:`box_qp`.

    Attributes:
        x: ``(..., m)`` solution.
        clamped: ``(..., m)`` bool, the clamped set at ``x`` (at a bound, with the
            gradient pointing out of the box).
        chol: ``(..., m, m)`` lower Cholesky factor of the free block of ``H`` (identity
            on the clamped rows and columns), evaluated at ``x``'s clamped set.
        success: ``(...,)`` bool, False where a free block was not positive definite
            (or the result is not finite).
        iterations: ``(...,)`` int64, Newton iterations taken.
    """

    x: Tensor
    clamped: Tensor
    chol: Tensor
    success: Tensor
    iterations: Tensor


def _value(H: Tensor, g: Tensor, x: Tensor) -> Tensor:
    return (x * (g + 0.5 * (H @ x.unsqueeze(-1))[..., 0])).sum(-1)


def _clamped_set(x: Tensor, grad: Tensor, lower: Tensor, upper: Tensor) -> Tensor:
    return ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))


def _free_factor(H: Tensor, free: Tensor, eye: Tensor) -> tuple[Tensor, Tensor]:
    """Cholesky of ``H`` with the clamped rows/columns replaced by the identity's."""
    both = free.unsqueeze(-1) & free.unsqueeze(-2)
    return torch.linalg.cholesky_ex(torch.where(both, H, eye))


def _box_qp_scalar(H: Tensor, g: Tensor, lower: Tensor, upper: Tensor, x0: Tensor) -> BoxQPResult:
    """``m = 1`` in closed form: the projected Newton point ``clip(-g/h)`` is the
    solution (what the iteration reaches in one step), with no loop and no host sync.
    A non-positive ``h`` fails unless the start is clamped (as in the iteration)."""
    h = H[..., 0]  # (..., 1)
    pos = h > 0
    grad0 = g + h * x0
    start_clamped = _clamped_set(x0, grad0, lower, upper)
    newton = -g / torch.where(pos, h, torch.ones_like(h))
    x = torch.where(pos, torch.minimum(torch.maximum(newton, lower), upper), x0)
    grad = g + h * x
    clamped = _clamped_set(x, grad, lower, upper)
    free = ~clamped
    chol = torch.where(free & pos, h.clamp_min(0).sqrt(), torch.ones_like(h)).unsqueeze(-1)
    success = ((pos | start_clamped) & torch.isfinite(x))[..., 0]
    iterations = (pos & (x != x0))[..., 0].to(torch.int64)
    return BoxQPResult(x=x, clamped=clamped, chol=chol, success=success, iterations=iterations)


def box_qp(
    H: Tensor,
    g: Tensor,
    lower: Tensor,
    upper: Tensor,
    x0: Tensor | None = None,
    max_iter: int = MAX_ITER,
    tol: float | Tensor = 1e-10,
    armijo: float = ARMIJO,
    step_dec: float = STEP_DEC,
    n_steps: int = N_STEPS,
    min_rel_improve: float = 0.0,
    check_every: int = 1,
) -> BoxQPResult:
    """Solve ``min 1/2 x'Hx + g'x`` s.t. ``lower <= x <= upper`` for a batch.

    Args:
        H: ``(..., m, m)`` symmetric, positive definite (at least on the free
            subspaces visited).
        g: ``(..., m)``; lower, upper: broadcastable to ``g`` (``-inf``/``+inf``
            allowed; ``lower <= upper`` is not checked).
        x0: optional warm start, projected into the box (default zeros, projected).
        max_iter: Newton iterations at most.
        tol: stop when the norm of the free part of the gradient is below this (float
            or a tensor broadcastable to the batch).
        armijo, step_dec, n_steps: line search constant, step decrease factor and
            number of candidate steps ``step_dec^j, j < n_steps`` (all tried at once).
        min_rel_improve: stop after a step improving the objective by at most this
            fraction of its magnitude (0: only exact stagnation stops).
        check_every: iterations between checks whether every element has stopped
            (each check is one host synchronisation).

    Returns:
        :class:`BoxQPResult` (``x``, ``clamped``, ``chol``, ``success``, ``iterations``).
    """
    m = H.shape[-1]
    batch = broadcast_shapes(H.shape[:-2], g.shape[:-1], lower.shape[:-1], upper.shape[:-1])
    H = H.expand(*batch, m, m)
    g = g.expand(*batch, m)
    lower = lower.expand(*batch, m)
    upper = upper.expand(*batch, m)
    eye = torch.eye(m, dtype=H.dtype, device=H.device)
    x = g.new_zeros(()).expand(*batch, m) if x0 is None else x0.expand(*batch, m)
    x = torch.minimum(torch.maximum(x, lower), upper)
    if m == 1:
        return _box_qp_scalar(H, g, lower, upper, x)
    value = _value(H, g, x)
    active = torch.ones(batch, dtype=torch.bool, device=H.device)
    success = torch.ones_like(active)
    iterations = torch.zeros(batch, dtype=torch.int64, device=H.device)
    steps = step_dec ** torch.arange(n_steps, dtype=H.dtype, device=H.device)
    steps = steps.reshape(n_steps, *([1] * len(batch)))
    for it in range(max_iter + 1):
        # clamped set, free-block factor and stopping tests at the current x
        grad = g + (H @ x.unsqueeze(-1))[..., 0]
        clamped = _clamped_set(x, grad, lower, upper)
        free = ~clamped
        L, info = _free_factor(H, free, eye)
        indefinite = info != 0
        success = success & ~(active & indefinite)
        gnorm = torch.where(free, grad, torch.zeros_like(grad)).norm(dim=-1)
        active = active & ~(indefinite | clamped.all(-1) | (gnorm < tol))
        if it == max_iter or (it > 0 and it % check_every == 0 and not bool(active.any())):
            break
        # Newton point on the free subspace, clamped entries held:
        # x_f = -H_ff^{-1} (g_f + H_fc x_c) = x_f - H_ff^{-1} grad_f
        x_free = torch.where(free, x, torch.zeros_like(x))
        rhs = grad - (H @ x_free.unsqueeze(-1))[..., 0]
        rhs = torch.where(free, rhs, torch.zeros_like(rhs))
        newton = torch.where(free, -torch.cholesky_solve(rhs.unsqueeze(-1), L)[..., 0], x)
        search = newton - x
        sdotg = (search * grad).sum(-1)
        active = active & (sdotg < 0)
        # projected line search: every candidate step at once (the full step is the
        # projected Newton point itself, without the rounding of x + (newton - x))
        xc = x.unsqueeze(0) + steps.unsqueeze(-1) * search.unsqueeze(0)
        xc[0] = newton
        xc = torch.minimum(torch.maximum(xc, lower), upper)
        vc = _value(H, g, xc)
        ok = (vc - value) <= armijo * steps * sdotg
        found = ok.any(0)
        first = torch.argmax(ok.to(torch.int8), dim=0)
        x_new = xc.gather(0, first.reshape(1, *batch, 1).expand(1, *batch, m))[0]
        v_new = vc.gather(0, first.unsqueeze(0))[0]
        take = active & found
        small = (value - v_new) <= min_rel_improve * value.abs()
        x = torch.where(take.unsqueeze(-1), x_new, x)
        value = torch.where(take, v_new, value)
        iterations = iterations + take.to(torch.int64)
        active = take & ~small
    # clamped set and factor are those of the returned x (computed at the loop's exit)
    success = success & ~indefinite & torch.isfinite(x).all(-1)
    return BoxQPResult(x=x, clamped=clamped, chol=L, success=success, iterations=iterations)
