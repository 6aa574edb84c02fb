"""numba forms of some systems' steps (:meth:`torchslq.Dynamics.compiled_step`),
imported on first use (importing numba costs ~0.5 s)."""

from __future__ import annotations

import math

import numba


@numba.njit(cache=True, nogil=True)
def unicycle_step(x, u, p, out):
    """:class:`torchslq.systems.Unicycle`'s step; ``p = [dt]``."""
    dt = p[0]
    vdt = u[0] * dt
    th = x[2]
    out[0] = x[0] + math.cos(th) * vdt
    out[1] = x[1] + math.sin(th) * vdt
    out[2] = th + u[1] * dt
