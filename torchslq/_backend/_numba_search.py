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
return what serial backtracking returns): the same operations in the same order, so the
same steps, and costs and trajectories equal to the last bit or two (separately
compiled kernels' last bits have been seen to differ between processes). For a model
whose step has a function on many rows at once (a learned model's
wide layers as matrix products, :func:`torchslq._backend.model_fns.register_rows`),
:func:`armijo_rows_kernel` makes the same search with the elements' trials side by
side, one call of that function per time step.
"""

from __future__ import annotations

import numba
import numpy as np

from . import _numba_cache  # noqa: F401 (before any kernel: the library's cache stamp)
from ._numba_cost import quadratic_cost_row
from ._numba_kernels import _closed_loop_row_set, _closed_loop_rows


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
def _armijo_test(b, a, x, u, xr, ur, Q, QT, R, stage_states, J0, slope, curv, quadratic, c1):
    """Element ``b``'s trial of step ``a`` (in ``x[b]``, ``u[b]``): its cost (infinite
    where NaN: a trial that blew up is never chosen) and whether it passes Armijo's test
    on the model decrease ``a slope (+ a^2/2 curv where quadratic)``."""
    Jj = quadratic_cost_row(x[b], u[b], b, xr, ur, Q, QT, R, stage_states)
    if np.isnan(Jj):
        Jj = np.inf
    model = a * slope[b]
    if quadratic:
        model = model + 0.5 * a * a * curv[b]
    return Jj, Jj <= J0[b] + c1 * model


@numba.njit(nogil=True, cache=True, _nrt=False)
def _within_rounding(b, J_first, J0, slope, roundoff):
    """Whether element ``b``, none of whose trials passed, takes the full step anyway:
    its predicted decrease is below rounding and the full step's cost ``J_first`` no
    worse than ``J0`` beyond it (:func:`torchslq.solvers.line_search.armijo_search`'s
    round-off rule)."""
    tol = roundoff * max(abs(J0[b]), 1.0)
    return abs(slope[b]) <= tol and J_first <= J0[b] + tol


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
            Jj, passes = _armijo_test(
                b, a, x, u, xr, ur, Q, QT, R, stage_states, J0, slope, curv, quadratic, c1
            )
            if j == 0:
                J_first = Jj
            if passes:
                alpha[b] = a
                J[b] = Jj
                ok[b] = True
                break
        if not ok[b]:
            if _within_rounding(b, J_first, J0, slope, roundoff):
                _trial(
                    b, grid[0], step, rhs, mode, p, xbar, ubar, K, k, lo, hi, x, u, no_skip, work
                )
                alpha[b] = grid[0]
                J[b] = J_first
                ok[b] = True


@numba.njit(nogil=True, cache=True)
def armijo_rows_kernel(
    b0, b1, rows_fn, p, xbar, ubar, K, k, lo, hi, grid, J0, slope, curv, quadratic, c1,
    roundoff, active, xr, ur, Q, QT, R, stage_states, x, u, alpha, J, ok,
):  # fmt: skip
    """:func:`armijo_rollout_kernel` with the model's step on many rows at once
    (``rows_fn(r0, r1, X, U, p, OUT)``, :func:`torchslq._backend.model_fns.register_rows`:
    a learned model's wide layers as matrix products over the rows): each trial is
    rolled out for all the elements ``b0 <= b < b1`` still searching together, one call
    of ``rows_fn`` per time step, instead of one element after another. The same trials,
    tests and outputs (the step's values agree with the one-row step's to rounding)."""
    nb, n, m = b1 - b0, x.shape[2], u.shape[2]
    X = np.empty((nb, n), dtype=x.dtype)
    U = np.empty((nb, m), dtype=x.dtype)
    OUT = np.empty((nb, n), dtype=x.dtype)
    searching = np.empty(nb, dtype=np.int64)
    J_first = np.empty(nb, dtype=J.dtype)
    _armijo_row_sets(
        b0, b1, rows_fn, p, xbar, ubar, K, k, lo, hi, grid, J0, slope, curv, quadratic, c1,
        roundoff, active, xr, ur, Q, QT, R, stage_states, x, u, alpha, J, ok, X, U, OUT,
        searching, J_first,
    )  # fmt: skip


@numba.njit(nogil=True, cache=True, _nrt=False)
def _armijo_row_sets(
    b0, b1, rows_fn, p, xbar, ubar, K, k, lo, hi, grid, J0, slope, curv, quadratic, c1,
    roundoff, active, xr, ur, Q, QT, R, stage_states, x, u, alpha, J, ok, X, U, OUT,
    searching, J_first,
):  # fmt: skip
    """The loop of :func:`armijo_rows_kernel`: ``searching[:count]`` the elements whose
    search goes on, ``J_first[b - b0]`` an element's cost at the first trial."""
    count = 0
    for b in range(b0, b1):
        alpha[b] = 0.0
        J[b] = J0[b]
        ok[b] = False
        if active[b]:
            searching[count] = b
            count += 1
    for j in range(grid.shape[0]):
        if count == 0:
            break
        a = grid[j]
        _rows_trial(searching, count, a, rows_fn, p, xbar, ubar, K, k, lo, hi, x, u, X, U, OUT)
        left = 0
        for i in range(count):
            b = searching[i]
            Jj, passes = _armijo_test(
                b, a, x, u, xr, ur, Q, QT, R, stage_states, J0, slope, curv, quadratic, c1
            )
            if j == 0:
                J_first[b - b0] = Jj
            if passes:
                alpha[b] = a
                J[b] = Jj
                ok[b] = True
            else:
                searching[left] = b
                left += 1
        count = left
    left = 0
    for i in range(count):
        b = searching[i]
        if _within_rounding(b, J_first[b - b0], J0, slope, roundoff):
            searching[left] = b
            left += 1
    if left > 0:
        _rows_trial(searching, left, grid[0], rows_fn, p, xbar, ubar, K, k, lo, hi, x, u, X, U, OUT)
        for i in range(left):
            b = searching[i]
            alpha[b] = grid[0]
            J[b] = J_first[b - b0]
            ok[b] = True


@numba.njit(nogil=True, cache=True, _nrt=False)
def _rows_trial(searching, count, a, rows_fn, p, xbar, ubar, K, k, lo, hi, x, u, X, U, OUT):
    """The feedback rollouts with step ``a`` of the elements ``searching[:count]`` into
    ``x``, ``u`` (as :func:`_trial`'s): the feedforward ``ū + a k`` written into ``u``,
    then :func:`._numba_kernels._closed_loop_row_set` from ``x̄_0``."""
    T, m = u.shape[1], u.shape[2]
    for i in range(count):
        b = searching[i]
        for t in range(T):
            for q in range(m):
                u[b, t, q] = ubar[b, t, q] + a * k[b, t, q]
    x0 = xbar[:, 0]
    _closed_loop_row_set(searching, count, rows_fn, p, x0, xbar, K, lo, hi, u, x, X, U, OUT)
