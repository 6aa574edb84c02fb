"""numba forms of some systems' steps (:meth:`torchslq.Dynamics.compiled_step`),
imported on first use (importing numba costs ~0.5 s)."""

from __future__ import annotations

import math

import numba


@numba.njit(cache=True, nogil=True)
def unicycle_step(x, u, p, out, work):
    """:class:`torchslq.systems.Unicycle`'s step; ``p = [dt]``."""
    dt = p[0]
    vdt = u[0] * dt
    th = x[2]
    out[0] = x[0] + math.cos(th) * vdt
    out[1] = x[1] + math.sin(th) * vdt
    out[2] = th + u[1] * dt


@numba.njit(cache=True, nogil=True)
def cartpole_rhs(x, u, p, out):
    """:class:`torchslq.systems.CartPole`'s ``xdot``; ``p = [mc, mp, l, g]``."""
    mc, mp, l, g = p[0], p[1], p[2], p[3]
    th, thd, F = x[1], x[3], u[0]
    s, c = math.sin(th), math.cos(th)
    D = mc + mp * s * s
    out[0] = x[2]
    out[1] = thd
    out[2] = (F + mp * s * (l * thd * thd + g * c)) / D
    out[3] = (-F * c - mp * l * thd * thd * c * s - (mc + mp) * g * s) / (l * D)


_RK4_STEPS: dict = {}


def rk4_step(rhs):
    """A numba RK4 step ``step(x, u, p, out, work)`` around ``rhs(x, u, p[1:], out)``
    with ``p[0] = dt`` (one compiled function per ``rhs``, built once per process; not
    cached on disk, being a closure)."""
    if rhs in _RK4_STEPS:
        return _RK4_STEPS[rhs]

    @numba.njit(nogil=True)
    def step(x, u, p, out, work):
        # the same sums in the same order as DiscretizedDynamics.forward; work rows:
        # k, the stage argument, k1 + 2 k2, k3
        n = x.shape[0]
        dt = p[0]
        q = p[1:]
        k, xi, a, k3 = work[0], work[1], work[2], work[3]
        rhs(x, u, q, k)
        for i in range(n):
            a[i] = k[i]
            xi[i] = x[i] + (0.5 * dt) * k[i]
        rhs(xi, u, q, k)
        for i in range(n):
            a[i] = a[i] + 2.0 * k[i]
            xi[i] = x[i] + (0.5 * dt) * k[i]
        rhs(xi, u, q, k3)
        for i in range(n):
            xi[i] = x[i] + dt * k3[i]
        rhs(xi, u, q, k)
        for i in range(n):
            out[i] = x[i] + (dt / 6.0) * (a[i] + (k[i] + 2.0 * k3[i]))

    _RK4_STEPS[rhs] = step
    return step
