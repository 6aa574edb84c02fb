"""numba kernel of the fused Armijo line search (imported on first use).

iLQR's and DDP's line search tries the steps ``alpha_j = grid[j]`` of the feedback
rollout ``u_t = ū_t + alpha k_t + K_t (x_t - x̄_t)`` and takes the largest whose cost
passes Armijo's test on the expected improvement. On torch ops each pass of trials is a
rollout kernel, a cost kernel and some thirty small ops to choose and gather the steps
(:func:`torchslq.solvers.line_search.armijo_search`); for a few elements that glue is
most of an iteration. Here the whole search of an element is one loop: the trials in
turn, each rolled out (:func:`._numba_kernels._closed_loop_rows`, the rollout
kernel's loop) and costed (:func:`._numba_cost.quadratic_cost_row`) until one passes. The
steps, costs and trajectories are those of ``armijo_search`` (whose batched passes
return what serial backtracking returns), bit for bit: the same operations in the same
order.
"""

from __future__ import annotations

import numba
import numpy as np

from ._numba_cost import quadratic_cost_row
from ._numba_kernels import _closed_loop_rows


@numba.njit(nogil=True, cache=True)
def armijo_rollout_kernel(
    b0, b1, step, rhs, mode, p, xbar, ubar, K, k, lo, hi, grid, J0, slope, curv, quadratic,
    c1, roundoff, active, xr, ur, Q, QT, R, stage_states, x, u, alpha, J, ok,
):  # fmt: skip
    """Armijo backtracking along the feedback rollout, per element ``b0 <= b < b1``.

    Args:
        step, rhs, mode, p: the model's compiled step (as for
            :func:`._numba_kernels.closed_loop_rollout_kernel`).
        xbar ``(B, T+1, n)``, ubar ``(B, T, m)``: the nominal trajectory.
        K ``(B, T, m, n)``, k ``(B, T, m)``: the gains; lo, hi ``(B, T, m)`` control
            bounds or empty.
        grid ``(N,)``: the steps, largest first; J0, slope, curv ``(B,)``: the cost at
            the nominal trajectory and the model decrease ``a slope (+ a^2/2 curv where
            quadratic)``; c1: Armijo's constant; roundoff: ``noise * eps`` of the
            round-off rule (a full step within rounding of ``J0`` is taken when the
            predicted decrease is below it too, :func:`torchslq.solvers.line_search.
            armijo_search`); active ``(B,)`` bool: the elements searched.
        xr, ur, Q, QT, R, stage_states: the quadratic cost's arrays
            (:func:`._numba_cost.quadratic_cost_row`).
        x ``(B, T+1, n)``, u ``(B, T, m)``, alpha, J ``(B,)``, ok ``(B,)`` bool: outputs,
            the accepted trial (alpha 0, J = J0, ok False and the last trial's
            trajectory where none passed; the inactive elements' outputs untouched but
            for those three).
    """
    work = np.empty((8, x.shape[2]), dtype=x.dtype)  # the model step's scratch
    no_skip = np.zeros(0, dtype=np.bool_)
    _armijo_rows(
        b0, b1, step, rhs, mode, p, xbar, ubar, K, k, lo, hi, grid, J0, slope, curv,
        quadratic, c1, roundoff, active, xr, ur, Q, QT, R, stage_states, x, u, alpha, J,
        ok, no_skip, work,
    )  # fmt: skip


@numba.njit(nogil=True, cache=True, _nrt=False)
def _trial(b, a, step, rhs, mode, p, xbar, ubar, K, k, lo, hi, x, u, no_skip, work):
    """The feedback rollout of element ``b`` with step ``a`` into ``x[b]``, ``u[b]``:
    the feedforward ``ū + a k`` written into ``u[b]``, then the rollout kernel's own row
    loop (:func:`._numba_kernels._closed_loop_rows`, ``no_skip`` an empty mask)."""
    for t in range(u.shape[1]):
        for i in range(u.shape[2]):
            u[b, t, i] = ubar[b, t, i] + a * k[b, t, i]
    x0 = xbar[:, 0]
    _closed_loop_rows(b, b + 1, step, rhs, mode, p, x0, xbar, K, lo, hi, no_skip, u, x, work)


@numba.njit(nogil=True, cache=True, _nrt=False)
def _armijo_rows(
    b0, b1, step, rhs, mode, p, xbar, ubar, K, k, lo, hi, grid, J0, slope, curv, quadratic,
    c1, roundoff, active, xr, ur, Q, QT, R, stage_states, x, u, alpha, J, ok, no_skip, work,
):  # fmt: skip
    """The loop of :func:`armijo_rollout_kernel` (no reference counting:
    :mod:`._numba_kernels`' docstring)."""
    inf = np.inf
    for b in range(b0, b1):
        alpha[b] = 0.0
        J[b] = J0[b]
        ok[b] = False
        if not active[b]:
            continue
        J_first = inf
        for j in range(grid.shape[0]):
            a = grid[j]
            _trial(b, a, step, rhs, mode, p, xbar, ubar, K, k, lo, hi, x, u, no_skip, work)
            Jj = quadratic_cost_row(x[b], u[b], b, xr, ur, Q, QT, R, stage_states)
            if np.isnan(Jj):
                Jj = inf  # a trial that blew up is never chosen
            if j == 0:
                J_first = Jj
            model = a * slope[b]
            if quadratic:
                model = model + 0.5 * a * a * curv[b]
            if Jj <= J0[b] + c1 * model:
                alpha[b] = a
                J[b] = Jj
                ok[b] = True
                break
        if not ok[b]:
            # the decrease is below rounding: the full step, if it is no worse than J0
            tol = roundoff * max(abs(J0[b]), 1.0)
            if abs(slope[b]) <= tol and J_first <= J0[b] + tol:
                _trial(
                    b, grid[0], step, rhs, mode, p, xbar, ubar, K, k, lo, hi, x, u, no_skip, work
                )
                alpha[b] = grid[0]
                J[b] = J_first
                ok[b] = True
