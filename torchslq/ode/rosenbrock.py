"""Batched Rodas5P with a step size per batch element.

Why our own integrator: the continuous-time iLQR (Lieskovský et al. 2025, Section IV)
needs, in both passes, (1) a stiff-capable method (the Riccati ODEs' stiffness varies
over orders of magnitude), (2) dense output (the policy ``d(t), K(t)`` and the nominal
trajectory are read between grid points) and (3) for a batch, a step size per element
(each element keeps its own grid; none waits for or shares steps with another).
torchdiffeq shares one step across the batch and has only explicit adaptive methods
plus fixed-grid implicit Adams; torchode has per-sample step sizes but only explicit
Runge-Kutta methods (Dopri5, Tsit5) -- neither offers a batched stiff method with dense
output, so this module implements one: Rodas5P (Steinebach, "Construction of
Rosenbrock-Wanner method Rodas5P", BIT 2023), the method the paper used through
DifferentialEquations.jl. It is L-stable and stiffly accurate, has an embedded order-4
error estimate and a continuous (dense) output of order 4.

Stages, in the W-transformed form (``W = I / (h gamma) - J``, ``J = df/dy``,
``f_t = df/dt``, all at the step's start)::

    W k_i = f(t + c_i h, y + sum_j a_ij k_j) + d_i h f_t + sum_j (C_ij / h) k_j
    y_new = y + sum_j a_8j k_j + k_8,   error estimate k_8
    y(t + theta h) = (1 - theta) y + theta (y_new + (1 - theta)(D1 + theta (D2 + theta D3)))

with ``D_r = sum_j H_rj k_j``. The batch runs in lockstep (one loop iteration is one
attempted step of every unfinished element, in one batched call of ``fun``), but each
element has its own time, step size, accept/reject decision and grid; the loop ends when
every element has reached its end time (or failed). Finished elements ride along with a
dummy step that is discarded. The grids are returned padded with a mask.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.func import jvp, vmap

from .dense import RodasDense

__all__ = ["ODESolution", "RODAS5P", "jacobian_by_differences", "jacobian_by_jvp", "solve_ivp"]

# Rodas5P (Steinebach 2023), the coefficients of the W-transformed form.
_GAMMA = 0.21193756319429014
_A = (
    (),
    (3.0,),
    (2.849394379747939, 0.45842242204463923),
    (-6.954028509809101, 2.489845061869568, -10.358996098473584),
    (2.8029986275628964, 0.5072464736228206, -0.3988312541770524, -0.04721187230404641),
    (
        -7.502846399306121,
        2.561846144803919,
        -11.627539656261098,
        -0.18268767659942256,
        0.030198172008377946,
    ),
)
_C = (
    (),
    (-14.155112264123755,),
    (-17.97296035885952, -2.859693295451294),
    (147.12150275711716, -1.41221402718213, 71.68940251302358),
    (165.43517024871676, -0.4592823456491126, 42.90938336958603, -5.961986721573306),
    (
        24.854864614690072,
        -3.0009227002832186,
        47.4931110020768,
        5.5814197821558125,
        -0.6610691825249471,
    ),
    (
        30.91273214028599,
        -3.1208243349937974,
        77.79954646070892,
        34.28646028294783,
        -19.097331116725623,
        -28.087943162872662,
    ),
    (
        37.80277123390563,
        -3.2571969029072276,
        112.26918849496327,
        66.9347231244047,
        -40.06618937091002,
        -54.66780262877968,
        -9.48861652309627,
    ),
)
_CNODES = (
    0.0,
    0.6358126895828704,
    0.4095798393397535,
    0.9769306725060716,
    0.4288403609558664,
    1.0,
    1.0,
    1.0,
)
_D = (
    0.21193756319429014,
    -0.42387512638858027,
    -0.3384627126235924,
    1.8046452872882734,
    2.325825639765069,
    0.0,
    0.0,
    0.0,
)
_H = (
    (
        25.948786856663858,
        -2.5579724845846235,
        10.433815404888879,
        -2.3679251022685204,
        0.524948541321073,
        1.1241088310450404,
        0.4272876194431874,
        -0.17202221070155493,
    ),
    (
        -9.91568850695171,
        -0.9689944594115154,
        3.0438037242978453,
        -24.495224566215796,
        20.176138334709044,
        15.98066361424651,
        -6.789040303419874,
        -6.710236069923372,
    ),
    (
        11.419903575922262,
        2.8879645146136994,
        72.92137995996029,
        80.12511834622643,
        -52.072871366152654,
        -59.78993625266729,
        -0.15582684282751913,
        4.883087185713722,
    ),
)
RODAS5P = {"gamma": _GAMMA, "A": _A, "C": _C, "c": _CNODES, "d": _D, "H": _H}

Fun = Callable[[Tensor, Tensor], Tensor]
Jac = Callable[[Tensor, Tensor], tuple[Tensor, Tensor | None]]


def jacobian_by_jvp(fun: Fun, t: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """``(df/dy (B, n, n), df/dt (B, n))`` of a batched ``fun(t (B,), y (B, n))`` whose rows
    are independent: ``n + 1`` forward-mode products with the basis, all in one
    ``vmap`` (no per-row function is needed, so per-element parameters keep working)."""
    n = y.shape[-1]
    eye = torch.eye(n, dtype=y.dtype, device=y.device)
    basis = eye.unsqueeze(1).expand(n, *y.shape)  # (n, B, n)
    cols = vmap(lambda v: jvp(lambda z: fun(t, z), (y,), (v,))[1])(basis)  # (n, B, n)
    ft = jvp(lambda s: fun(s, y), (t,), (torch.ones_like(t),))[1]
    return cols.permute(1, 2, 0), ft


def jacobian_by_differences(
    fun_rows: Callable[[Tensor, Tensor], Tensor], t: Tensor, y: Tensor, t_step: float
) -> tuple[Tensor, Tensor]:
    """``(df/dy (B, n, n), df/dt (B, n))`` by forward differences, all in ONE call of
    ``fun_rows(t (B, R), y (B, R, n)) -> (B, R, n)`` on ``R = n + 2`` rows per element
    (the point, ``n`` perturbed states, a perturbed time).

    One plain batched call instead of ``n`` forward-mode products: for small models the
    cost is the number of dispatched ops, and ``torch.func`` transforms multiply it.
    Steps ``sqrt(eps) max(|y_j|, 1)`` (relative error of the Jacobian ~``sqrt(eps)``,
    far below the tolerances it is used with); the time step ``t_step`` is taken
    towards smaller ``t`` when negative.
    """
    Bsz, n = y.shape
    eps = torch.finfo(y.dtype).eps
    delta = eps**0.5 * y.abs().clamp_min(1.0)  # (B, n)
    eye = torch.eye(n, dtype=y.dtype, device=y.device)
    ys = torch.cat([y[:, None], y[:, None] + delta[:, None] * eye, y[:, None]], 1)
    ts = torch.cat([t[:, None].expand(Bsz, n + 1), (t + t_step)[:, None]], 1)
    out = fun_rows(ts, ys)  # (B, n + 2, n)
    f0 = out[:, 0]
    J = ((out[:, 1 : n + 1] - f0[:, None]) / delta[:, :, None]).mT
    ft = (out[:, n + 1] - f0) / t_step
    return J, ft


@dataclass
class ODESolution:
    """Solution of a batch of IVPs, each on its own grid.

    Attributes:
        t: ``(B, N+1)`` each element's accepted grid ``t_0 < ... < t_{n_b}``, padded
            after its last point with that point (``N = max_b n_b``).
        y: ``(B, N+1, n)`` the solution on the grid, padded likewise.
        mask: ``(B, N+1)`` bool, True on the element's own grid points.
        n_steps: ``(B,)`` accepted steps ``n_b``; n_rejected: ``(B,)`` rejected ones.
        h_min, h_max: ``(B,)`` smallest and largest accepted step (the last step, cut to
            land on the end time, excluded unless it is the only one).
        success: ``(B,)`` bool, the element reached its end time.
        dense: the continuous output (:class:`RodasDense`); call the solution instead.
    """

    t: Tensor
    y: Tensor
    mask: Tensor
    n_steps: Tensor
    n_rejected: Tensor
    h_min: Tensor
    h_max: Tensor
    success: Tensor
    dense: RodasDense

    def __call__(self, t: Tensor) -> Tensor:
        """The dense output at ``t (B,)`` -> ``(B, n)`` or ``t (B, Q)`` -> ``(B, Q, n)``
        (times outside an element's interval are extrapolated from its end steps)."""
        return self.dense(t)


def _rms(v: Tensor) -> Tensor:
    return v.square().mean(-1).sqrt()


def solve_ivp(
    fun: Fun,
    t0: Tensor | float,
    t1: Tensor | float,
    y0: Tensor,
    *,
    rtol: float = 1e-6,
    atol: float | Tensor = 1e-8,
    jac: Jac | None = None,
    h0: Tensor | float | None = None,
    max_steps: int = 100_000,
    active: Tensor | None = None,
) -> ODESolution:
    """Integrate ``y' = fun(t, y)`` from ``t0`` to ``t1 > t0`` with Rodas5P, a step size per
    batch element.

    Args:
        fun: ``fun(t (B,), y (B, n)) -> (B, n)``; row ``b`` may depend only on ``t[b]``,
            ``y[b]`` (per-element parameters broadcast as ``(B, 1)``).
        t0, t1: start and end times, floats or ``(B,)`` tensors (``t1 > t0``).
        y0: ``(B, n)`` initial states (dtype and device of the solve).
        rtol, atol: error tolerances (``atol`` a float or ``(n,)``); the weighted RMS
            norm ``|err / (atol + rtol max(|y|, |y_new|))|`` of each element's step must be
            at most 1.
        jac: ``jac(t, y) -> (df/dy (B, n, n), df/dt (B, n) or None)``; default
            :func:`jacobian_by_jvp` (``fun`` must then work under ``torch.func``).
        h0: first step (float or ``(B,)``); default from Hairer & Wanner's estimate
            ``0.01 |y0| / |f(t0, y0)|`` in the weighted norm.
        max_steps: limit on loop iterations (attempted steps); elements not at ``t1``
            by then have ``success`` False.
        active: optional ``(B,)`` bool; rows that are False are not integrated (they
            ride along with dummy steps: no steps, ``success`` False).

    Returns:
        :class:`ODESolution`.
    """
    if y0.ndim != 2:
        raise ValueError(f"y0 must have shape (B, n), got {tuple(y0.shape)}")
    Bsz, n = y0.shape
    dt, dev = y0.dtype, y0.device
    t0 = torch.as_tensor(t0, dtype=dt, device=dev).expand(Bsz).clone()
    t1 = torch.as_tensor(t1, dtype=dt, device=dev).expand(Bsz).clone()
    if not bool((t1 > t0).all()):
        raise ValueError("t1 must be greater than t0 for every element")
    atol_t = torch.as_tensor(atol, dtype=dt, device=dev)
    if jac is None:
        jac = lambda t, y: jacobian_by_jvp(fun, t, y)  # noqa: E731
    eps = torch.finfo(dt).eps
    eye = torch.eye(n, dtype=dt, device=dev)
    # coefficient rows as tensors: a stage's combination of the k's is one tensordot
    A = torch.zeros(8, 8, dtype=dt, device=dev)
    C = torch.zeros(8, 8, dtype=dt, device=dev)
    for i, row in enumerate(_A):
        A[i, : len(row)] = torch.tensor(row, dtype=dt)
    for i, row in enumerate(_C):
        C[i, : len(row)] = torch.tensor(row, dtype=dt)
    H = torch.tensor(_H, dtype=dt, device=dev)

    t, y = t0.clone(), y0.clone()
    f0 = fun(t, y)
    if h0 is None:
        scale = atol_t + rtol * y.abs()
        d0, d1 = _rms(y / scale), _rms(f0 / scale)
        h = torch.where((d0 < 1e-5) | (d1 < 1e-5), torch.full_like(d0, 1e-6), 0.01 * d0 / d1)
        h = torch.nan_to_num(h, nan=1e-6)
    else:
        h = torch.as_tensor(h0, dtype=dt, device=dev).expand(Bsz).clone()
    h = torch.minimum(h, t1 - t0)
    done = torch.zeros(Bsz, dtype=torch.bool, device=dev)
    failed = torch.zeros_like(done)
    if active is not None:
        failed = ~active.to(device=dev, dtype=torch.bool)
        done = failed.clone()
    rejected_before = torch.zeros_like(done)
    n_rej = torch.zeros(Bsz, dtype=torch.int64, device=dev)
    rec: list[tuple[Tensor, ...]] = []
    for _ in range(max_steps):
        active = ~done
        hs = torch.where(active, h, torch.ones_like(h))  # dummy step for finished rows
        fy, ft = jac(t, y)
        W = eye / (hs * _GAMMA)[:, None, None] - fy
        LU, piv, _ = torch.linalg.lu_factor_ex(W)
        ks = y.new_zeros(8, Bsz, n)
        ystage = y
        inv_h = (1.0 / hs)[:, None]
        for i in range(8):
            if 0 < i < 6:
                ystage = y + torch.tensordot(A[i, :i], ks[:i], 1)
            elif i >= 6:
                ystage = ystage + ks[i - 1]
            rhs = f0 if i == 0 else fun(t + _CNODES[i] * hs, ystage)
            if _D[i] != 0.0 and ft is not None:
                rhs = rhs + (_D[i] * hs)[:, None] * ft
            if i > 0:
                rhs = rhs + torch.tensordot(C[i, :i], ks[:i], 1) * inv_h
            ks[i] = torch.linalg.lu_solve(LU, piv, rhs.unsqueeze(-1)).squeeze(-1)
        y_new = ystage + ks[7]
        scale = atol_t + rtol * torch.maximum(y.abs(), y_new.abs())
        err = _rms(ks[7] / scale)
        ok = torch.isfinite(err) & torch.isfinite(y_new).all(-1)
        accept = active & ok & (err <= 1.0)
        err_c = torch.where(ok, err, torch.full_like(err, 1e10)).clamp_min(1e-10)
        fac = (0.9 * err_c.pow(-0.2)).clamp(0.2, 6.0)
        # no growth right after a rejection (Hairer & Wanner IV.8)
        fac = torch.where(rejected_before & accept, fac.clamp_max(1.0), fac)
        D = torch.tensordot(H, ks, 1)  # (3, B, n)
        rec.append((accept, t.clone(), hs.clone(), y.clone(), y_new, D[0], D[1], D[2]))
        t_new = torch.where(accept, t + hs, t)
        at_end = accept & (t_new >= t1 - 4 * eps * t1.abs().clamp_min(1.0))
        t_new = torch.where(at_end, t1, t_new)
        y = torch.where(accept[:, None], y_new, y)
        t = t_new
        n_rej = n_rej + (active & ~accept).to(torch.int64)
        rejected_before = active & ~accept
        h_next = hs * fac
        tiny = h_next < 16 * eps * t.abs().clamp_min(1.0)
        failed = failed | (active & ~accept & tiny)
        done = done | at_end | failed
        h = torch.minimum(h_next, t1 - t).clamp_min(0)
        if bool(done.all()):
            break
        f0 = fun(t, y)
    success = done & ~failed
    return _assemble(rec, t0, y0, success, n_rej)


def _assemble(rec, t0: Tensor, y0: Tensor, success: Tensor, n_rejected: Tensor) -> ODESolution:
    """Per-element grids from the lockstep record: each element's accepted steps in order,
    padded to the longest (vectorised: a cumulative count gives each step its slot)."""
    accept = torch.stack([r[0] for r in rec], 1)  # (B, L)
    Bsz, L = accept.shape
    n_steps = accept.sum(1)
    N = max(int(n_steps.max()), 1)
    slot = accept.cumsum(1) - 1
    slot = torch.where(accept, slot, torch.full_like(slot, N))  # rejected -> dropped column
    dt, dev = y0.dtype, y0.device

    def gather(k: int) -> Tensor:
        v = torch.stack([r[k] for r in rec], 1)  # (B, L, ...)
        out = v.new_zeros(Bsz, N + 1, *v.shape[2:])
        idx = slot.reshape(Bsz, L, *([1] * (v.ndim - 2))).expand_as(v)
        return out.scatter(1, idx, v)[:, :N]

    ts, hs, ys, ye = gather(1), gather(2), gather(3), gather(4)
    D = torch.stack([gather(5), gather(6), gather(7)], 2)  # (B, N, 3, n)
    j = torch.arange(N, device=dev)
    valid = j[None, :] < n_steps[:, None]
    last = (n_steps - 1).clamp_min(0)
    ar = torch.arange(Bsz, device=dev)
    t_end = torch.where(n_steps > 0, ts[ar, last] + hs[ar, last], t0)
    y_end = torch.where((n_steps > 0)[:, None], ye[ar, last], y0)
    # pad invalid slots with a zero-length step at the end (keeps the grid sorted)
    ts = torch.where(valid, ts, t_end[:, None])
    hs = torch.where(valid, hs, torch.zeros_like(hs))
    ys = torch.where(valid[..., None], ys, y_end[:, None])
    ye = torch.where(valid[..., None], ye, y_end[:, None])
    D = torch.where(valid[..., None, None], D, torch.zeros_like(D))
    grid = torch.cat([ts, t_end[:, None]], 1)
    grid[:, 0] = torch.where(n_steps > 0, grid[:, 0], t0)
    y = torch.cat([ys, y_end[:, None]], 1)
    mask = torch.arange(N + 1, device=dev)[None, :] <= n_steps[:, None]
    # step-size range, the cut last step left out when there are others
    inner = valid & (j[None, :] < last[:, None])
    inner = torch.where((n_steps > 1)[:, None], inner, valid)
    inf = torch.tensor(float("inf"), dtype=dt, device=dev)
    h_min = torch.where(inner, hs, inf).amin(1)
    h_max = torch.where(inner, hs, -inf).amax(1)
    dense = RodasDense(grid=grid, h=hs, y0=ys, y1=ye, D=D, n_steps=n_steps)
    return ODESolution(
        t=grid,
        y=y,
        mask=mask,
        n_steps=n_steps,
        n_rejected=n_rejected,
        h_min=h_min,
        h_max=h_max,
        success=success,
        dense=dense,
    )
