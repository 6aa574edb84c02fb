"""The two passes of the continuous-time iLQR (Lieskovský, Bušek & Vyhlídal 2025,
Sections III-IV), each an adaptive Rodas5P integration with a step size per element.

Nominal trajectory (:class:`Nominal`): the forward pass's dense output of ``(x, c)``
(``c`` the accumulated cost) on its own grid per element, and, sampled at
``theta = 0, 1/3, 2/3, 1`` of every step in one batched evaluation, the control and the
linearisation ``f, f_x, f_u, l, l_x, l_u, l_zz`` (and ``f_zz`` for DDP) as piecewise
cubics. The backward pass reads the linearisation at any ``t`` by interpolation, so its
right-hand side is tensor arithmetic only (no model call inside the Riccati
integration) and its Jacobian is exact by forward-mode differentiation.

Backward pass (:func:`backward_pass`), in reversed time ``tau = tf - t``, the state
``z = (sigma, s, P)``::

    d sigma/d tau = l - 1/2 d' Q_u                          (8a)
    d s/d tau     = l_x + f_x' s - K' Q_u                   (8b)
    d P/d tau     = 1/2 (Q_xx - K' Q_uu K) P^-T             (12, S = P P')

with ``Q_u = l_u + f_u' s``, ``Q_ux = l_ux + f_u' S``, ``Q_xx = l_xx + f_x' S + S f_x``,
``Q_uu = l_uu`` (6c-6f; DDP adds ``s · f_zz``), ``d = Q_uu^-1 Q_u``,
``K = Q_uu^-1 Q_ux`` (7a-7b), the joint cost Hessian ``l_zz`` regularised by (11)
(eigenvalues floored at ``sqrt(eps)``), and the boundary conditions (10) with
``P(tf) = V Lambda^1/2`` floored at ``eps^1/4`` (13).

Forward pass (:func:`forward_pass`): ``xdot = f(x, u, t)``, ``cdot = l(x, u, t)`` with the
policy (14) ``u = ubar(t) - alpha d(t) - K(t) (x - xbar(t))``; ``d, K`` are read from a
piecewise cubic sampled on the backward grid. The integrals ``eta = int Q_u' Q_uu^-1 Q_u dt``
(the expected improvement ``Delta V(alpha) = -(alpha - alpha^2/2) eta``) and
``int |Q_u|^2 dt`` (the stopping test) are quadratures of the same samples (Simpson's
3/8 rule per backward step, exact for the cubic through them): integrated as ODE states
they would carry the integrator's absolute error, ~``atol``, which is larger than the
values near convergence.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor

from ...ode import ODESolution, PiecewiseCubic, RodasDense, solve_ivp
from ...ode.dense import SAMPLE_THETA
from ...ode.rosenbrock import jacobian_by_differences
from .expansion import (
    Layout,
    dynamics_derivatives,
    dynamics_second_derivatives,
    stage_derivatives,
    terminal_derivatives,
)

__all__ = [
    "Backward",
    "Nominal",
    "Policy",
    "backward_pass",
    "floor_eigenvalues",
    "forward_pass",
    "riccati_rhs",
]


def floor_eigenvalues(H: Tensor, floor: float) -> Tensor:
    """Eq. (11): ``H = V diag(lambda) V'`` with ``lambda := max(lambda, floor)``."""
    w, V = torch.linalg.eigh(0.5 * (H + H.mT))
    return (V * w.clamp_min(floor).unsqueeze(-2)) @ V.mT


def _take_rows(obj, idx: Tensor):
    return replace(obj, **{f.name: _take_field(getattr(obj, f.name), idx) for f in fields(obj)})


def _take_field(v, idx):
    if torch.is_tensor(v):
        return v.index_select(0, idx)
    if hasattr(v, "take"):
        return v.take(idx)
    return v


def _pad_steps(v: Tensor, N: int, grid: bool) -> Tensor:
    """``v (B, N0(+1), ...)`` padded along dim 1 to ``N`` steps (a grid to ``N + 1``
    points) by repeating its last entry (padded steps are never read: see
    :func:`torchslq.ode.locate`)."""
    target = N + 1 if grid else N
    extra = target - v.shape[1]
    if extra <= 0:
        return v
    return torch.cat([v, v[:, -1:].expand(v.shape[0], extra, *v.shape[2:])], 1)


def _merge(keep_new: Tensor, new, old):
    """Row-wise choice between two structures of the same kind (interpolants or
    dataclasses of batch-first tensors on per-element grids of different padded
    lengths)."""
    if torch.is_tensor(new):
        if new.ndim >= 2 and new.shape[1] != old.shape[1]:
            raise AssertionError("padded to the same length first")
        m = keep_new.reshape(-1, *([1] * (new.ndim - 1)))
        return torch.where(m, new, old)
    if new is None:
        return None
    return replace(
        new,
        **{
            f.name: _merge(keep_new, getattr(new, f.name), getattr(old, f.name))
            for f in fields(new)
        },
    )


def _padded(obj, N: int):
    """An interpolant/dataclass with its step arrays padded to ``N`` steps."""
    out = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        if f.name in ("grid", "t", "x", "u", "c", "mask") and torch.is_tensor(v):
            if f.name == "mask":
                out[f.name] = (
                    torch.cat([v, v.new_zeros(v.shape[0], N + 1 - v.shape[1])], 1)
                    if v.shape[1] < N + 1
                    else v
                )
            else:
                out[f.name] = _pad_steps(v, N, grid=True)
        elif torch.is_tensor(v) and v.ndim >= 2 and f.name not in ("n_steps",):
            out[f.name] = _pad_steps(v, N, grid=False)
        elif hasattr(v, "grid"):
            out[f.name] = _padded(v, N)
        else:
            out[f.name] = v
    return replace(obj, **out)


@dataclass(frozen=True)
class Nominal:
    """A nominal trajectory (per element, on its own forward grid).

    Attributes:
        t: ``(B, N+1)`` forward grid (padded); mask ``(B, N+1)`` its valid points.
        x: ``(B, N+1, n)``, u ``(B, N+1, m)``, c ``(B, N+1)`` (accumulated cost) on the grid.
        J: ``(B,)`` total cost ``c(tf) + Phi(x(tf))``.
        xc: dense output of ``(x, c)`` (:class:`RodasDense`).
        xu: ``(x, u)`` as one piecewise cubic ``(.., n + m)`` (``x`` sampled from ``xc``):
            what the policy (14) reads at every stage, one interpolation for both.
        coef: the packed linearisation (:class:`Layout`), piecewise cubic.
        phi: ``(Phi, Phi_x, Phi_xx)`` at ``x(tf)``.
        n_steps, h_min, h_max: ``(B,)`` the forward pass's statistics; ok ``(B,)`` bool,
            the integration reached ``tf`` with finite values.
    """

    t: Tensor
    mask: Tensor
    x: Tensor
    u: Tensor
    c: Tensor
    J: Tensor
    xc: RodasDense
    xu: PiecewiseCubic
    coef: PiecewiseCubic
    phi: tuple
    n_steps: Tensor
    h_min: Tensor
    h_max: Tensor
    ok: Tensor

    @property
    def N(self) -> int:
        return self.t.shape[1] - 1

    def take(self, idx: Tensor) -> Nominal:
        return replace(_take_rows(self, idx), phi=tuple(p.index_select(0, idx) for p in self.phi))

    def pad(self, N: int) -> Nominal:
        return _padded(self, N)


def merge_nominal(keep_new: Tensor, new: Nominal, old: Nominal) -> Nominal:
    """Row ``b`` from ``new`` where ``keep_new[b]``, else from ``old``."""
    N = max(new.N, old.N)
    a, b = new.pad(N), old.pad(N)
    out = _merge(keep_new, replace(a, phi=None), replace(b, phi=None))
    phi = tuple(_merge(keep_new, p, q) for p, q in zip(a.phi, b.phi, strict=True))
    return replace(out, phi=phi)


@dataclass(frozen=True)
class Policy:
    """The policy (14) of one backward pass: ``u(x, t) = ubar(t) - alpha d(t) - K(t)(x - xbar(t))``.

    Attributes:
        tf: end time; dk: ``(d, K)`` packed ``(.., m + m n)``, piecewise cubic in
            ``tau = tf - t`` on the backward grid; nominal: the nominal it belongs to;
            z: the backward pass's dense output in ``tau``.
    """

    tf: float
    m: int
    n: int
    dk: PiecewiseCubic
    nominal: Nominal
    z: RodasDense

    def terms(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """``(d (B, [Q,] m), K (B, [Q,] m, n))`` at times ``t (B,)`` or ``(B, Q)``."""
        v = self.dk(self.tf - t)
        return v[..., : self.m], v[..., self.m :].reshape(*v.shape[:-1], self.m, self.n)

    def d(self, t: Tensor) -> Tensor:
        """Feedforward ``d(t)`` (7a)."""
        return self.terms(t)[0]

    def K(self, t: Tensor) -> Tensor:
        """Feedback gain ``K(t)`` (7b)."""
        return self.terms(t)[1]

    def xbar(self, t: Tensor) -> Tensor:
        """Nominal state ``xbar(t)`` (Rodas5P's dense output)."""
        return self.nominal.xc(t)[..., : self.n]

    def ubar(self, t: Tensor) -> Tensor:
        """Nominal control ``ubar(t)``."""
        return self.nominal.xu(t)[..., self.n :]

    def S(self, t: Tensor) -> Tensor:
        """Value Hessian ``S(t) = P P'`` (dense output of the square-root factor)."""
        n = self.n
        P = self.z(self.tf - t)[..., 1 + n :].reshape(*t.shape, n, n)
        return P @ P.mT

    def s(self, t: Tensor) -> Tensor:
        """Value gradient ``s(t)``."""
        return self.z(self.tf - t)[..., 1 : 1 + self.n]

    def __call__(self, t: Tensor, x: Tensor, alpha: Tensor | float = 1.0) -> Tensor:
        """``u = ubar(t) - alpha d(t) - K(t) (x - xbar(t))`` at ``t (B,)`` / ``x (B, n)``
        or ``t (B, Q)`` / ``x (B, Q, n)``; ``alpha`` a float or ``(B,)``."""
        d, K = self.terms(t)
        a = torch.as_tensor(alpha, dtype=x.dtype, device=x.device)
        if a.ndim == 1:
            a = a.reshape(-1, *([1] * (d.ndim - 1)))
        xu = self.nominal.xu(t)
        dx = x - xu[..., : self.n]
        return xu[..., self.n :] - a * d - (K @ dx.unsqueeze(-1)).squeeze(-1)

    def take(self, idx: Tensor) -> Policy:
        return replace(
            self, dk=self.dk.take(idx), nominal=self.nominal.take(idx), z=self.z.take(idx)
        )


def merge_policy(keep_new: Tensor, new: Policy, old: Policy) -> Policy:
    """Row ``b`` from ``new`` where ``keep_new[b]``, else from ``old``."""
    N = max(new.dk.grid.shape[1], old.dk.grid.shape[1]) - 1
    dk = _merge(keep_new, _padded(new.dk, N), _padded(old.dk, N))
    z = _merge(keep_new, _padded(new.z, N), _padded(old.z, N))
    return replace(new, dk=dk, z=z, nominal=merge_nominal(keep_new, new.nominal, old.nominal))


@dataclass(frozen=True)
class Backward:
    """One backward pass: the policy, ``eta = int Q_u' Q_uu^-1 Q_u dt`` (so
    ``Delta V(alpha) = -(alpha - alpha^2/2) eta``), ``grad_norm = sqrt(int |Q_u|^2 dt)``,
    ``sigma0`` (predicted cost), statistics ``n_steps, h_min, h_max`` and ``ok``."""

    policy: Policy
    eta: Tensor
    grad_norm: Tensor
    sigma0: Tensor
    n_steps: Tensor
    h_min: Tensor
    h_max: Tensor
    ok: Tensor


# --- backward pass --------------------------------------------------------------------------


def riccati_rhs(
    c: dict[str, Tensor],
    z: Tensor,
    n: int,
    m: int,
    floor: float,
    ddp: bool,
    with_policy: bool = False,
):
    """``dz/dtau (B, 1 + n + n^2)`` of the backward pass (eqs. 8a, 8b, 12 in reversed time)
    at the coefficients ``c`` (:meth:`Layout.unpack`, ``l_zz`` already regularised) and
    ``z = (sigma, s, vec P)``; with ``with_policy`` also ``(d, K, Q_u)``."""
    s = z[..., 1 : 1 + n]
    P = z[..., 1 + n :].reshape(*z.shape[:-1], n, n)
    S = P @ P.mT
    fx, fu = c["fx"], c["fu"]
    lzz = c["lzz"]
    if ddp:
        # the exact second-order terms s . f_zz, and (11b) applied to the whole second-order
        # block: with them Q_zz may be indefinite, and S = P P' could not follow
        lzz = floor_eigenvalues(lzz + (s[..., :, None, None] * c["fzz"]).sum(-3), floor)
    lxx, luu, lux = lzz[..., :n, :n], lzz[..., n:, n:], lzz[..., n:, :n]
    Qu = c["lu"] + (fu.mT @ s.unsqueeze(-1)).squeeze(-1)
    Qux = lux + fu.mT @ S
    SA = S @ fx
    Qxx = lxx + SA + SA.mT
    Quu = luu
    rhs_u = torch.cat([Qu.unsqueeze(-1), Qux], -1)  # (.., m, 1 + n)
    dK = torch.linalg.solve(Quu, rhs_u)
    d, K = dK[..., 0], dK[..., 1:]
    dQu = (d * Qu).sum(-1)
    dsigma = c["l"] - 0.5 * dQu
    ds = c["lx"] + (fx.mT @ s.unsqueeze(-1)).squeeze(-1) - (K.mT @ Qu.unsqueeze(-1)).squeeze(-1)
    M = Qxx - K.mT @ Quu @ K
    M = 0.5 * (M + M.mT)
    dP = 0.5 * torch.linalg.solve(P, M).mT  # M P^-T = (P^-1 M)' for symmetric M
    out = torch.cat([dsigma.unsqueeze(-1), ds, dP.flatten(-2)], -1)
    return (out, d, K, Qu) if with_policy else out


def _coefficients(
    layout: Layout, coef: PiecewiseCubic, t: Tensor, floor: float
) -> dict[str, Tensor]:
    """The linearisation at ``t (B,)`` or ``(B, Q)``, the joint cost Hessian regularised
    by (11a)-(11b) (after interpolation, so that it holds at every ``t``)."""
    c = layout.unpack(coef(t))
    c["lzz"] = floor_eigenvalues(c["lzz"], floor)
    return c


def backward_pass(
    nominal: Nominal,
    tf: float,
    t0: float,
    layout: Layout,
    *,
    rtol: float,
    atol: float,
    eps: float,
    max_steps: int,
    active: Tensor | None = None,
) -> Backward:
    """Integrate the Riccati ODEs backwards along ``nominal`` (see the module docstring)."""
    n, m, ddp = layout.n, layout.m, layout.ddp
    floor = eps**0.5
    phi, phix, phixx = nominal.phi
    Bsz = phi.shape[0]
    dt = phi.dtype
    # (13): P(tf) = V Lambda^1/2 with sqrt(lambda) >= eps^(1/4)
    w, V = torch.linalg.eigh(0.5 * (phixx + phixx.mT))
    P0 = V * w.clamp_min(floor).sqrt().unsqueeze(-2)
    z0 = torch.cat([phi.unsqueeze(-1), phix, P0.flatten(-2)], -1)
    T = tf - t0

    def coef_at(tau: Tensor) -> dict[str, Tensor]:
        return _coefficients(layout, nominal.coef, tf - tau, floor)

    def rows(tau: Tensor, z: Tensor) -> Tensor:  # tau (B, R), z (B, R, k)
        return riccati_rhs(coef_at(tau), z, n, m, floor, ddp)

    fd = (torch.finfo(dt).eps ** 0.5) * T
    sol = solve_ivp(
        lambda tau, z: rows(tau[:, None], z[:, None])[:, 0],
        0.0,
        T,
        z0,
        rtol=rtol,
        atol=atol,
        jac=lambda tau, z: jacobian_by_differences(rows, tau, z, fd),
        max_steps=max_steps,
        active=active,
    )
    # (d, K) sampled on the backward grid, for the forward pass
    dense = sol.dense
    Nb = dense.h.shape[1]
    theta = torch.tensor(SAMPLE_THETA, dtype=dt, device=phi.device)
    taus = (dense.grid[:, :-1, None] + theta * dense.h[..., None]).reshape(Bsz, 4 * Nb)
    idx = torch.arange(Nb, device=phi.device).repeat_interleave(4).expand(Bsz, -1)
    zs = dense._eval(idx, theta.repeat(Nb).expand(Bsz, -1), None)
    _, d, K, Qu = riccati_rhs(coef_at(taus), zs, n, m, floor, ddp, with_policy=True)
    dk = torch.cat([d, K.flatten(-2)], -1).reshape(Bsz, Nb, 4, -1)
    # Simpson's 3/8 rule on each step (padded steps have h = 0)
    w = dense.h[..., None] * torch.tensor([0.125, 0.375, 0.375, 0.125], dtype=dt, device=phi.device)
    eta = (w * (d * Qu).sum(-1).reshape(Bsz, Nb, 4)).sum((1, 2))
    gamma = (w * Qu.square().sum(-1).reshape(Bsz, Nb, 4)).sum((1, 2))
    policy = Policy(
        tf=tf,
        m=m,
        n=n,
        dk=PiecewiseCubic(grid=dense.grid, n_steps=dense.n_steps, values=dk),
        nominal=nominal,
        z=dense,
    )
    zT = sol.y.gather(1, sol.n_steps.reshape(Bsz, 1, 1).expand(Bsz, 1, sol.y.shape[-1]))[:, 0]
    ok = sol.success & torch.isfinite(zT).all(-1) & torch.isfinite(eta) & torch.isfinite(gamma)
    return Backward(
        policy=policy,
        eta=eta,
        grad_norm=gamma.sqrt(),
        sigma0=zT[:, 0],
        n_steps=sol.n_steps,
        h_min=sol.h_min,
        h_max=sol.h_max,
        ok=ok,
    )


# --- forward pass ---------------------------------------------------------------------------

Control = Callable[[Tensor, Tensor], Tensor]  # (t (B, Q), x (B, Q, n)) -> u (B, Q, m)


def forward_pass(
    problem,
    x0: Tensor,
    control: Control,
    layout: Layout,
    *,
    rtol: float,
    atol: float,
    max_steps: int,
    active: Tensor | None = None,
) -> Nominal:
    """Integrate ``xdot = f(x, u)``, ``cdot = l(x, u)`` with ``u = control(t, x)`` from
    ``(x0, 0)`` over ``[t0, tf]``; sample the control and the linearisation on the new grid."""
    n = layout.n
    t0, tf = problem.t0, problem.tf
    Bsz = x0.shape[0]
    dt = x0.dtype

    def rows(t: Tensor, y: Tensor) -> Tensor:  # t (B, R), y (B, R, n + 1)
        x = y[..., :n]
        u = control(t, x)
        return torch.cat([problem.f(x, u, t), problem.running_cost(x, u, t).unsqueeze(-1)], -1)

    # a forward difference backwards in time stays inside [t0, tf]
    fd = -(torch.finfo(dt).eps ** 0.5) * (tf - t0)
    y0 = torch.cat([x0, x0.new_zeros(Bsz, 1)], -1)
    sol = solve_ivp(
        lambda t, y: rows(t[:, None], y[:, None])[:, 0],
        t0,
        tf,
        y0,
        rtol=rtol,
        atol=atol,
        jac=lambda t, y: jacobian_by_differences(rows, t, y, fd),
        max_steps=max_steps,
        active=active,
    )
    return _nominal_from(problem, sol, control, layout)


def _nominal_from(problem, sol: ODESolution, control: Control, layout: Layout) -> Nominal:
    n = layout.n
    dense = sol.dense
    Bsz, N = dense.h.shape
    dt, dev = sol.y.dtype, sol.y.device
    theta = torch.tensor(SAMPLE_THETA, dtype=dt, device=dev)
    ts = (dense.grid[:, :-1, None] + theta * dense.h[..., None]).reshape(Bsz, 4 * N)
    idx = torch.arange(N, device=dev).repeat_interleave(4).expand(Bsz, -1)
    ys = dense._eval(idx, theta.repeat(N).expand(Bsz, -1), None)
    xs = ys[..., :n]
    with torch.no_grad():
        us = control(ts, xs)
        f, fx, fu = dynamics_derivatives(problem.dynamics, xs, us, ts)
        l, lx, lu, lzz = stage_derivatives(problem.running_cost, xs, us, ts)
        fzz = dynamics_second_derivatives(problem.dynamics, xs, us, ts) if layout.ddp else None
    coef = layout.pack(f, fx, fu, l, lx, lu, lzz, fzz).reshape(Bsz, N, 4, -1)
    uv = us.reshape(Bsz, N, 4, -1)
    ar = torch.arange(Bsz, device=dev)
    last = (sol.n_steps - 1).clamp_min(0)
    u_grid = torch.cat([uv[:, :, 0], uv[ar, last, 3].unsqueeze(1)], 1)
    u_grid = torch.where(sol.mask[..., None], u_grid, uv[ar, last, 3].unsqueeze(1))
    yT = sol.y[ar, sol.n_steps]
    xT = yT[:, :n]
    phi = terminal_derivatives(problem.terminal_cost, xT)
    J = yT[:, n] + phi[0]
    ok = sol.success & torch.isfinite(J) & torch.isfinite(coef).flatten(1).all(1)
    return Nominal(
        t=sol.t,
        mask=sol.mask,
        x=sol.y[..., :n],
        u=u_grid,
        c=sol.y[..., n],
        J=torch.where(ok, J, torch.full_like(J, float("inf"))),
        xc=dense,
        xu=PiecewiseCubic(
            grid=dense.grid,
            n_steps=dense.n_steps,
            values=torch.cat([xs, us], -1).reshape(Bsz, N, 4, -1),
        ),
        coef=PiecewiseCubic(grid=dense.grid, n_steps=dense.n_steps, values=coef),
        phi=phi,
        n_steps=sol.n_steps,
        h_min=sol.h_min,
        h_max=sol.h_max,
        ok=ok,
    )
