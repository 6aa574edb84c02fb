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


@numba.njit(cache=True, nogil=True)
def cartpole_derivatives(x, u, p, fz, H):
    """:class:`torchslq.systems.CartPole`'s ``[f_x | f_u]`` into ``fz (4, 5)`` and, when
    ``H`` is not empty, the Hessians of the accelerations (outputs 2, 3) in
    ``(theta, theta_dot, F)`` (entries 1, 3, 4 of ``z = (x, u)``) into ``H (4, 5, 5)``,
    the other entries untouched (zero everywhere: ``CARTPOLE_CURVATURE``); the formulas
    of ``CartPole.jacobians`` and ``CartPole.vhp``. ``p = [mc, mp, l, g]``."""
    mc, mp, l, g = p[0], p[1], p[2], p[3]
    th, thd, F = x[1], x[3], u[0]
    sn, c = math.sin(th), math.cos(th)
    D = mc + mp * sn * sn
    sdd = (F + mp * sn * (l * thd * thd + g * c)) / D
    r = (-F * c - mp * l * thd * thd * c * sn - (mc + mp) * g * sn) / D  # l theta_ddot
    dD = 2.0 * mp * sn * c
    c2 = c * c - sn * sn
    # numerator derivatives (a = th, b = thd, F); sdd = N1 / D, r = N2 / D
    N1a = mp * (l * thd * thd * c + g * c2)
    N1b = 2.0 * mp * l * sn * thd
    N2a = F * sn - mp * l * thd * thd * c2 - (mc + mp) * g * c
    N2b = -2.0 * mp * l * thd * c * sn
    qa, qb, qF = (N1a - sdd * dD) / D, N1b / D, 1.0 / D
    ra, rb, rF = (N2a - r * dD) / D, N2b / D, -c / D
    for i in range(4):
        for j in range(5):
            fz[i, j] = 0.0
    fz[0, 2] = 1.0
    fz[1, 3] = 1.0
    fz[2, 1], fz[2, 3], fz[2, 4] = qa, qb, qF
    fz[3, 1], fz[3, 3], fz[3, 4] = ra / l, rb / l, rF / l
    if H.shape[0] == 0:
        return
    ddD = 2.0 * mp * c2
    N1aa = -mp * (l * thd * thd * sn + 4.0 * g * sn * c)
    N1ab = 2.0 * mp * l * c * thd
    N1bb = 2.0 * mp * l * sn
    N2aa = F * c + 4.0 * mp * l * thd * thd * sn * c + (mc + mp) * g * sn
    N2ab = -2.0 * mp * l * thd * c2
    N2bb = -2.0 * mp * l * c * sn
    for o in range(2):
        if o == 0:
            haa = (N1aa - 2.0 * qa * dD - sdd * ddD) / D
            hab = (N1ab - qb * dD) / D
            haF = -qF * dD / D
            hbb = N1bb / D
        else:
            haa = (N2aa - 2.0 * ra * dD - r * ddD) / D / l
            hab = (N2ab - rb * dD) / D / l
            haF = (sn - rF * dD) / D / l
            hbb = N2bb / D / l
        Ho = H[2 + o]  # the entries (th, thd, F) of the pattern, zeros included
        Ho[1, 1] = haa
        Ho[1, 3] = hab
        Ho[3, 1] = hab
        Ho[1, 4] = haF
        Ho[4, 1] = haF
        Ho[3, 3] = hbb
        Ho[3, 4] = 0.0
        Ho[4, 3] = 0.0
        Ho[4, 4] = 0.0


@numba.njit(cache=True, nogil=True)
def mass_chain_rhs(x, u, p, out):
    """:class:`torchslq.systems.MassChain`'s ``xdot``; ``p = [mass, k, k3, damping]``,
    ``N = len(u)`` masses."""
    N = u.shape[0]
    m, k, k3, c = p[0], p[1], p[2], p[3]
    s_next = 0.0  # the tension of spring i + 1 (none beyond the last mass)
    for i in range(N - 1, -1, -1):
        e = x[i] - x[i - 1] if i > 0 else x[0]
        si = e * (k + k3 * e * e)
        out[N + i] = ((s_next - si) - c * x[N + i] + u[i]) / m
        out[i] = x[N + i]
        s_next = si


@numba.njit(cache=True, nogil=True)
def mass_chain_derivatives(x, u, p, fz, H):
    """:class:`torchslq.systems.MassChain`'s ``[f_x | f_u]`` into ``fz (2N, 3N)`` and,
    when ``H`` is not empty, the Hessians of the accelerations (outputs ``N..2N-1``) in
    the positions (entries ``0..N-1``), the other entries untouched (zero everywhere:
    ``mass_chain_curvature(N)``): the formulas of ``MassChain.jacobians`` and ``vhp``."""
    N = u.shape[0]
    m, k, k3, c = p[0], p[1], p[2], p[3]
    for a in range(2 * N):
        for b in range(3 * N):
            fz[a, b] = 0.0
    for i in range(N):
        fz[i, N + i] = 1.0
        fz[N + i, N + i] = -c / m
        fz[N + i, 2 * N + i] = 1.0 / m
        e = x[i] - x[i - 1] if i > 0 else x[0]
        ds = (k + 3.0 * k3 * e * e) / m  # s'(e_i) / m
        fz[N + i, i] -= ds
        if i > 0:  # spring i pulls masses i - 1 and i
            fz[N + i, i - 1] += ds
            fz[N + i - 1, i - 1] -= ds
            fz[N + i - 1, i] += ds
    if H.shape[0] == 0:
        return
    for i in range(N):
        for a in range(N):
            for b in range(N):
                H[N + i, a, b] = 0.0
    for i in range(N):
        e = x[i] - x[i - 1] if i > 0 else x[0]
        d = 6.0 * k3 * e / m  # s''(e_i) / m: in a_i with sign -, in a_{i-1} with +
        H[N + i, i, i] -= d
        if i > 0:
            H[N + i, i - 1, i - 1] -= d
            H[N + i, i, i - 1] += d
            H[N + i, i - 1, i] += d
            H[N + i - 1, i, i] += d
            H[N + i - 1, i - 1, i - 1] += d
            H[N + i - 1, i, i - 1] -= d
            H[N + i - 1, i - 1, i] -= d


def mass_chain_curvature(N: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The outputs and ``z`` entries where mass_chain_derivatives' Hessians can be
    nonzero: the accelerations, in the positions."""
    return tuple(range(N, 2 * N)), tuple(range(N))


# the outputs and z entries where cartpole_derivatives' Hessians can be nonzero
CARTPOLE_CURVATURE = ((2, 3), (1, 3, 4))

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
