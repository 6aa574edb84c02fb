"""Direct transcription of an :class:`~torchslq.lqdo.problem.LQDOProblem` (Sec. 2.2).

Variables per batch element, ``z = [vec(U), vec(Xi), p]`` (eq. 3) with ``U (nt, nu)`` and
``Xi (nt, nx)`` stored node-major: ``n = nt (nu + nx) + np``.

Both methods write the defects (eqs. 5-6) as ``M1 Xi - M2 F = 0`` with ``F_k = f(t_k, U_k,
Xi_k, p)`` and two ``(nd, nt)`` operators:

* ``"TR"`` (trapezoidal, single step): ``M1 = [.. -1 1 ..]``, ``M2 = [.. h_k/2 h_k/2 ..]``,
  ``nd = nt - 1``; composite trapezoidal quadrature (eq. 9). Any mesh: ``nodes`` points
  equally spaced, or ``mesh`` a strictly increasing tensor.
* ``"PS"`` (single-interval Legendre pseudospectral on Legendre-Gauss-Lobatto points,
  Herber 2015 [33]): ``M1 = D`` the LGL differentiation matrix scaled by ``2 / (tf - t0)``,
  ``M2 = I``, ``nd = nt``; LGL quadrature weights.

The QP of the reference LQDO problem about ``z_ref`` (Prob. 14: constraints linearised,
eq. 12, objective quadratised, eq. 13) is assembled from per-node Jacobians and
Hessians (:func:`~torchslq.lqdo.problem.row_derivatives`, all nodes and elements at once)
scattered into one shared sparsity pattern: there is no Python loop over nodes or batch
elements. OLQ elements (Sec. 3.1) give the same QP pieces at every reference; they are
built on the first call and reused (Sec. 4.1), and for the dynamics only the non-OLQ
rows are differentiated again.

Equality rows: defects (``nd nx``), path equalities (``nt ke``), boundary equalities,
fixed initial states, fixed final states. Inequality rows: path inequalities
(``nt ki``), boundary inequalities.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .problem import LQDOProblem, row_derivatives
from .qp import SparseQP, few_inequalities

__all__ = ["Transcription", "transcribe", "lgl"]


def lgl(N: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Legendre-Gauss-Lobatto points, weights and differentiation matrix on ``[-1, 1]``.

    Newton iteration on ``(1 - x^2) P'_{N-1}(x)`` from the Chebyshev-Gauss-Lobatto points
    (the classical ``lglnodes`` scheme).

    Returns:
        ``tau (N,)`` increasing, ``w (N,)`` (exact for polynomials of degree ``2N - 3``),
        ``D (N, N)`` (exact derivative at the nodes for degree ``N - 1``).
    """
    if N < 2:
        raise ValueError(f"nodes must be at least 2 for PS; got {N}")
    n = N - 1
    x = np.cos(np.pi * np.arange(N) / n)
    P = np.zeros((N, N))
    xold = 2.0
    for _ in range(100):
        if np.max(np.abs(x - xold)) < 1e-16:
            break
        xold = x
        P[:, 0], P[:, 1] = 1.0, x
        for k in range(2, N):
            P[:, k] = ((2 * k - 1) * x * P[:, k - 1] - (k - 1) * P[:, k - 2]) / k
        x = xold - (x * P[:, n] - P[:, n - 1]) / (N * P[:, n])
    P[:, 0], P[:, 1] = 1.0, x
    for k in range(2, N):
        P[:, k] = ((2 * k - 1) * x * P[:, k - 1] - (k - 1) * P[:, k - 2]) / k
    tau = x[::-1].copy()
    PN = P[::-1, n].copy()
    w = 2.0 / (n * N * PN**2)
    with np.errstate(divide="ignore"):
        D = PN[:, None] / PN[None, :] / (tau[:, None] - tau[None, :])
    np.fill_diagonal(D, 0.0)
    D[0, 0] = -n * N / 4.0
    D[-1, -1] = n * N / 4.0
    return tau, w, D


class Transcription:
    """A transcribed problem: mesh, weights, defect operators, variable layout, and the
    builders of the nonlinear program (Prob. 4) and of the reference LQDO QP (Prob. 14/18).

    Args:
        problem: the NLDO problem.
        method: ``"TR"`` or ``"PS"``.
        nodes: mesh points ``nt`` (ignored when ``mesh`` is given).
        mesh: ``(nt,)`` strictly increasing times from ``t0`` to ``tf`` (TR only).
        dtype, device: of every tensor built.
    """

    def __init__(
        self,
        problem: LQDOProblem,
        method: str = "TR",
        nodes: int = 20,
        mesh: Tensor | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str | None = None,
    ) -> None:
        if not isinstance(problem, LQDOProblem):
            raise TypeError(f"problem must be an LQDOProblem; got {type(problem).__name__}")
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise TypeError(f"dtype must be a floating-point torch.dtype, got {dtype!r}")
        if not isinstance(method, str):
            raise TypeError(f"method must be 'TR' or 'PS'; got {method!r}")
        method = method.upper()
        if method not in ("TR", "PS"):
            raise ValueError(f"method must be 'TR' or 'PS'; got {method!r}")
        self.problem, self.method = problem, method
        self.dtype, self.device = dtype, torch.device(device) if device is not None else None
        kw = dict(dtype=dtype, device=device)
        t0, tf = problem.t0, problem.tf
        if method == "TR":
            if mesh is not None:
                t = torch.as_tensor(mesh, **kw).reshape(-1)
                if t.numel() < 2 or not bool((t[1:] > t[:-1]).all()):
                    raise ValueError("mesh must be strictly increasing with at least 2 points")
                if abs(float(t[0]) - t0) > 1e-12 or abs(float(t[-1]) - tf) > 1e-12:
                    raise ValueError(f"mesh must run from t0={t0} to tf={tf}")
            else:
                if not isinstance(nodes, int) or nodes < 2:
                    raise ValueError(f"nodes must be an int >= 2; got {nodes!r}")
                t = torch.linspace(t0, tf, nodes, **kw)
            nt = t.numel()
            hk = t[1:] - t[:-1]
            w = torch.zeros(nt, **kw)
            w[:-1] += hk / 2
            w[1:] += hk / 2
            i = torch.arange(nt - 1, device=device)
            # pairs (defect row, node) of the two operators' nonzeros
            self.pair_i = torch.cat([i, i])
            self.pair_k = torch.cat([i, i + 1])
            self.pair_m1 = torch.cat([-torch.ones_like(hk), torch.ones_like(hk)])
            self.pair_m2 = torch.cat([hk / 2, hk / 2])
            nd = nt - 1
        else:
            if mesh is not None:
                raise ValueError("mesh is only for method='TR' (PS uses the LGL points)")
            if not isinstance(nodes, int) or nodes < 2:
                raise ValueError(f"nodes must be an int >= 2; got {nodes!r}")
            tau, wn, D = lgl(nodes)
            nt = nodes
            half = (tf - t0) / 2
            t = torch.as_tensor(half * tau + (tf + t0) / 2, **kw)
            w = torch.as_tensor(half * wn, **kw)
            ii, kk = torch.meshgrid(
                torch.arange(nt, device=device), torch.arange(nt, device=device), indexing="ij"
            )
            self.pair_i, self.pair_k = ii.reshape(-1), kk.reshape(-1)
            self.pair_m1 = torch.as_tensor(D / half, **kw).reshape(-1)
            self.pair_m2 = (ii == kk).reshape(-1).to(dtype)
            nd = nt
        self.t, self.w, self.nt, self.nd = t, w, nt, nd
        P = problem
        nu, nx, np_ = P.nu, P.nx, P.np
        self.n = nt * (nu + nx) + np_
        self.off_u, self.off_x, self.off_p = 0, nt * nu, nt * (nu + nx)
        ar = torch.arange(nt, device=device)
        iu = self.off_u + ar[:, None] * nu + torch.arange(nu, device=device)
        ix = self.off_x + ar[:, None] * nx + torch.arange(nx, device=device)
        ip = self.off_p + torch.arange(np_, device=device)
        self.idx_u, self.idx_x, self.idx_p = iu, ix, ip
        # node-local variable maps: path [u_k, xi_k, p], boundary [p, xi_1, xi_nt]
        self.loc_path = torch.cat([iu, ix, ip.expand(nt, np_)], 1)
        self.loc_bnd = torch.cat([ip, ix[0], ix[-1]])
        self.k = {name: P.out_dim(name) for name in ("path_eq", "path_ineq")}
        self.k.update({name: P.out_dim(name) for name in ("boundary_eq", "boundary_ineq")})
        self.fix0 = ~P.initial.isnan().reshape(-1, nx)[0]
        self.fixf = ~P.final.isnan().reshape(-1, nx)[0]
        self.me = (
            nd * nx
            + nt * self.k["path_eq"]
            + self.k["boundary_eq"]
            + int(self.fix0.sum())
            + int(self.fixf.sum())
        )
        self.mi = nt * self.k["path_ineq"] + self.k["boundary_ineq"]
        self._cache: dict = {}
        self._memos: dict = {}  # see _memo
        self._index: dict = {}  # see _pattern_index
        self._loc_path_flat = self.loc_path.reshape(-1)
        self._no_index = torch.zeros(2, 0, dtype=torch.long, device=device)
        # the operators' nonzeros only (M2 = I for PS: its nt^2 pairs hold nt nonzeros,
        # and explicit zeros in the constraint matrix would be fill for the QP solver)
        nz1, nz2 = self.pair_m1 != 0, self.pair_m2 != 0
        self._m1 = (self.pair_i[nz1], self.pair_k[nz1], self.pair_m1[nz1])
        self._m2 = (self.pair_i[nz2], self.pair_k[nz2], self.pair_m2[nz2])

    # ------------------------------------------------------------------ layout
    def pack(self, u: Tensor, xi: Tensor, p: Tensor | None = None) -> Tensor:
        """``z (B, n)`` from ``u (B, nt, nu)``, ``xi (B, nt, nx)``, ``p (B, np)``."""
        B = xi.shape[0]
        parts = [u.reshape(B, -1), xi.reshape(B, -1)]
        if self.problem.np:
            if p is None:
                raise ValueError("p is required: the problem has static parameters")
            parts.append(p.reshape(B, -1))
        return torch.cat(parts, 1)

    def unpack(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``u (B, nt, nu)``, ``xi (B, nt, nx)``, ``p (B, np)`` from ``z (B, n)``."""
        self._check_z(z)
        B, P, nt = z.shape[0], self.problem, self.nt
        return (
            z[:, : self.off_x].reshape(B, nt, P.nu),
            z[:, self.off_x : self.off_p].reshape(B, nt, P.nx),
            z[:, self.off_p :],
        )

    def as_batch(self, name: str, value, width: int) -> Tensor:
        """``value`` (a tensor or array-like ``(B, width)`` or ``(width,)``) as a
        ``(B, width)`` tensor of the transcription's dtype and device; a TypeError /
        ValueError naming ``name`` otherwise (and for an empty batch)."""
        if value is None or isinstance(value, (str, bytes)):
            raise TypeError(f"{name} must be a tensor (B, {width}), got {type(value).__name__}")
        try:
            t = torch.as_tensor(value, dtype=self.dtype, device=self.device)
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(
                f"{name} must be a tensor (B, {width}), got {type(value).__name__}"
            ) from err
        if t.ndim == 1:
            t = t[None]
        if t.ndim != 2 or t.shape[1] != width:
            raise ValueError(f"{name} must be (B, {width}) or ({width},); got {tuple(t.shape)}")
        if t.shape[0] == 0:
            raise ValueError(f"{name} has an empty batch (B = 0); give at least one row")
        return t

    def _check_z(self, z: Tensor) -> None:
        if not torch.is_tensor(z) or z.ndim != 2 or z.shape[1] != self.n:
            raise ValueError(
                f"z must be a (B, {self.n}) tensor; got "
                f"{tuple(z.shape) if torch.is_tensor(z) else type(z).__name__}"
            )

    def initial_guess(
        self,
        B: int = 1,
        u0: Tensor | None = None,
        uf: Tensor | None = None,
        xi0: Tensor | None = None,
        xif: Tensor | None = None,
        p: Tensor | None = None,
    ) -> Tensor:
        """Straight lines from the start to the end values (the paper's initial guess for
        the crane): ``xi0``/``xif`` default to the fixed initial/final states (zero where
        free), ``u0``/``uf`` to zero, ``p`` to zero. Returns ``z (B, n)``."""
        P, kw = self.problem, dict(dtype=self.dtype, device=self.device)

        def v(x, default, dim):
            x = default if x is None else torch.as_tensor(x, **kw)
            return torch.nan_to_num(x.to(**kw), nan=0.0).expand(B, dim)

        s = ((self.t - self.t[0]) / (self.t[-1] - self.t[0]))[None, :, None]
        zu = torch.zeros(P.nu, **kw)
        ua, ub_ = v(u0, zu, P.nu), v(uf, zu, P.nu)
        xa, xb = v(xi0, P.initial, P.nx), v(xif, P.final, P.nx)
        u = ua[:, None] + s * (ub_ - ua)[:, None]
        xi = xa[:, None] + s * (xb - xa)[:, None]
        pp = v(p, torch.zeros(P.np, **kw), P.np)
        return self.pack(u, xi, pp)

    def bounds(self, B: int) -> tuple[Tensor, Tensor]:
        """Simple bounds ``lb, ub (B, n)`` (eq. 4 with the bounds of Prob. 1)."""
        lb, ub = self._bounds(B)
        return lb.clone(), ub.clone()

    def _memo(self, key, deps: tuple, build):
        """``build()`` kept under ``key`` while the tensors ``deps`` (problem data a user may
        replace or modify in place) are the same objects at the same versions: per-call
        data that do not depend on the reference (bounds, fixed states, the constant
        blocks of the QP), built once instead of at every QLIN iteration."""
        hit = self._memos.get(key)
        stamp = tuple(d._version for d in deps)
        if (
            hit is not None
            and hit[1] == stamp
            and all(a is b for a, b in zip(hit[0], deps, strict=True))
        ):
            return hit[2]
        out = build()
        self._memos[key] = (deps, stamp, out)
        return out

    def _bounds(self, B: int) -> tuple[Tensor, Tensor]:
        """:meth:`bounds`, shared between calls (not to be modified in place)."""
        P, nt, kw = self.problem, self.nt, dict(dtype=self.dtype, device=self.device)

        def cat(u, x, p):
            u, x, p = (torch.as_tensor(a).to(**kw) for a in (u, x, p))
            parts = [
                u.expand(B, P.nu)[:, None].expand(B, nt, P.nu).reshape(B, -1),
                x.expand(B, P.nx)[:, None].expand(B, nt, P.nx).reshape(B, -1),
                p.expand(B, P.np),
            ]
            return torch.cat(parts, 1)

        deps = (P.u_lb, P.xi_lb, P.p_lb, P.u_ub, P.xi_ub, P.p_ub)
        return self._memo(
            ("bounds", B),
            deps,
            lambda: (cat(P.u_lb, P.xi_lb, P.p_lb), cat(P.u_ub, P.xi_ub, P.p_ub)),
        )

    def _bound_count(self, B: int) -> int:
        """The most finite simple bounds of an element (both sides counted)."""
        P = self.problem

        def build():
            lb, ub = self._bounds(B)
            return int((torch.isfinite(lb).sum(1) + torch.isfinite(ub).sum(1)).amax())

        deps = (P.u_lb, P.xi_lb, P.p_lb, P.u_ub, P.xi_ub, P.p_ub)
        return self._memo(("bound count", B), deps, build)

    # ------------------------------------------------------------------ node rows
    def _path_rows(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """``t (B nt,)`` and ``[u_k, xi_k, p] (B nt, nu + nx + np)`` at every node."""
        B = z.shape[0]
        zz = z[:, self._loc_path_flat].reshape(B * self.nt, -1)
        t = self._memos.get(("t", B))
        if t is None:
            t = self._memos[("t", B)] = self.t.repeat(B)
        return t, zz

    def _bnd_rows(self, z: Tensor) -> Tensor:
        return z[:, self.loc_bnd]

    def _fixed(self, which: str, B: int) -> Tensor:
        """``(B, nfix)`` the fixed initial or final states (shared between calls)."""
        v0 = getattr(self.problem, which)

        def build():
            v = v0.to(dtype=self.dtype, device=self.device)
            mask = self.fix0 if which == "initial" else self.fixf
            return v.expand(B, -1)[:, mask] if v.ndim == 1 else v[:, mask].expand(B, -1)

        return self._memo(("fixed", which, B), (v0,), build)

    # ------------------------------------------------------------------ nonlinear program
    def objective(self, z: Tensor) -> Tensor:
        """``(B,)`` the transcribed objective, eq. (9): ``sum_k w_k l_k + m``."""
        self._check_z(z)
        P, B = self.problem, z.shape[0]
        v = z.new_zeros(B)
        if P.lagrange is not None:
            t, zz = self._path_rows(z)
            v = v + (P.call("lagrange", t, zz).reshape(B, self.nt) * self.w).sum(1)
        if P.mayer is not None:
            v = v + P.call("mayer", None, self._bnd_rows(z))[:, 0]
        return v

    def equalities(self, z: Tensor) -> Tensor:
        """``(B, me)`` the equality constraints of Prob. (4) (defects, eqs. 5-6; path and
        boundary equalities, eq. 7; fixed initial/final states), ``= 0`` when feasible."""
        self._check_z(z)
        P, B, nt = self.problem, z.shape[0], self.nt
        _, xi, _ = self.unpack(z)
        t, zz = self._path_rows(z)
        F = P.call("dynamics", t, zz).reshape(B, nt, P.nx)
        d = z.new_zeros(B, self.nd, P.nx)
        (i1, k1, m1), (i2, k2, m2) = self._m1, self._m2
        d = d.index_add(1, i1, m1[:, None] * xi[:, k1])
        d = d.index_add(1, i2, -m2[:, None] * F[:, k2])
        out = [d.reshape(B, -1)]
        if self.k["path_eq"]:
            out.append(P.call("path_eq", t, zz).reshape(B, -1))
        if self.k["boundary_eq"]:
            out.append(P.call("boundary_eq", None, self._bnd_rows(z)))
        out.append(xi[:, 0, self.fix0] - self._fixed("initial", B))
        out.append(xi[:, -1, self.fixf] - self._fixed("final", B))
        return torch.cat(out, 1)

    def inequalities(self, z: Tensor) -> Tensor:
        """``(B, mi)`` path and boundary inequalities (eq. 8), ``<= 0`` when feasible."""
        self._check_z(z)
        P, B = self.problem, z.shape[0]
        out = [z.new_zeros(B, 0)]
        if self.k["path_ineq"]:
            t, zz = self._path_rows(z)
            out.append(P.call("path_ineq", t, zz).reshape(B, -1))
        if self.k["boundary_ineq"]:
            out.append(P.call("boundary_ineq", None, self._bnd_rows(z)))
        return torch.cat(out, 1)

    # ------------------------------------------------------------------ the QP
    def _linear(self, name: str, z: Tensor, path: bool) -> tuple[Tensor, Tensor]:
        """Jacobian and offset of element ``name`` linearised at ``z``: ``e(z') ~ J z'_loc
        + r`` with ``r = e(z) - J z_loc`` (eq. 12); rows the problem marks OLQ are
        computed once and reused. Returns ``J (B, R, k, nz)`` and ``r (B, R, k)``
        (``R = nt`` for path elements, 1 for boundary ones)."""
        P, B = self.problem, z.shape[0]
        olq = P.olq_rows(name).to(z.device)
        if path:
            t, zz = self._path_rows(z)
        else:
            t, zz = None, self._bnd_rows(z)
        R = zz.shape[0] // B
        key = (name, B, z.dtype, z.device)
        cached = self._cache.get(key)
        k = olq.numel()

        def fn(x: Tensor) -> Tensor:
            return P.call(name, t, x)

        if cached is not None and bool(olq.all()):
            return cached
        rows = None
        if cached is not None:  # only the rows that are not OLQ are differentiated again
            rows = self._memos.get(("non-OLQ rows", name))
            if rows is None:
                rows = self._memos[("non-OLQ rows", name)] = (~olq).nonzero().squeeze(1)
        val, jac, _ = row_derivatives(fn, zz, rows=rows)
        if cached is not None:
            J = cached[0].index_copy(2, rows, jac.reshape(B, R, -1, zz.shape[1]))
        else:
            J = jac.reshape(B, R, k, zz.shape[1])
        r = val.reshape(B, R, k) - (J * zz.reshape(B, R, 1, -1)).sum(-1)
        if cached is not None:
            r = torch.where(olq, cached[1], r)
        if cached is None and bool(olq.any()):
            self._cache[key] = (J.detach(), r.detach())
        return J, r

    def _quadratic(self, name: str, z: Tensor, path: bool) -> tuple[Tensor, Tensor, Tensor]:
        """Quadratic model of a scalar objective term at ``z`` (eq. 13) in the node-local
        variables: ``Hk (B, R, nz, nz)``, linear ``gk (B, R, nz)``, constant ``ck (B, R)``
        with ``l(z') ~ 1/2 z'Hk z' + gk'z' + ck``; cached when the term is OLQ."""
        P, B = self.problem, z.shape[0]
        key = (name, B, z.dtype, z.device)
        if key in self._cache:
            return self._cache[key]
        if path:
            t, zz = self._path_rows(z)
        else:
            t, zz = None, self._bnd_rows(z)
        R = zz.shape[0] // B

        def fn(x: Tensor) -> Tensor:
            return P.call(name, t, x)

        val, jac, hess = row_derivatives(fn, zz, hessian=True)
        g = jac[:, 0]
        Hz = (hess @ zz.unsqueeze(-1)).squeeze(-1)
        lin = g - Hz
        const = val[:, 0] - (g * zz).sum(-1) + 0.5 * (zz * Hz).sum(-1)
        out = (hess.reshape(B, R, *hess.shape[1:]), lin.reshape(B, R, -1), const.reshape(B, R))
        if bool(P.olq_rows(name).all()):
            self._cache[key] = tuple(o.detach() for o in out)
        return out

    @property
    def is_olq(self) -> bool:
        """Every element is OLQ: the reference QP is the transcribed problem itself
        (an OLQ problem, Sec. 3.1), whatever the reference."""
        P = self.problem
        names = ("dynamics", "lagrange", "mayer", "path_eq", "path_ineq")
        names += ("boundary_eq", "boundary_ineq")
        return all(bool(P.olq_rows(k).all()) for k in names if P.element(k) is not None)

    def _widen(self, name: str, D: Tensor) -> Tensor:
        """The element's derivative pattern, widened by the nonzeros of ``D (B, R, a, b)``
        (a derivative that is zero at the random probe points but not here)."""
        P = self.problem
        pat = (D != 0).any(0).any(0)
        if P.element(name) is None:  # a block of constraint curvature only
            return pat
        pat = P.pattern(name).to(D.device) | pat
        P._pattern[name] = pat
        return pat

    def _curvature(self, name: str, z: Tensor, path: bool, weights: Tensor) -> Tensor:
        """``(B, R, nz, nz)`` the Hessian of ``sum_a weights[b, r, a] e_a`` of element
        ``name`` at each node (path elements) or at the boundary rows, in the node-local
        variables: a constraint's curvature weighted by its multipliers."""
        P, B = self.problem, z.shape[0]
        t, zz = self._path_rows(z) if path else (None, self._bnd_rows(z))
        R = zz.shape[0] // B
        wf = weights.reshape(B * R, -1).to(zz)

        def fn(x: Tensor) -> Tensor:
            return (P.call(name, t, x) * wf).sum(-1, keepdim=True)

        hess = row_derivatives(fn, zz, hessian=True)[2]
        return hess.reshape(B, R, *hess.shape[1:])

    def _constraint_curvature(self, z: Tensor, lam: Tensor, mu: Tensor) -> tuple[Tensor, Tensor]:
        """The constraints' curvature weighted by the multipliers ``lam (B, me)``, ``mu
        (B, mi)`` (the QP's convention ``H z + f + A'lam + G'mu = 0``), summed per node:
        ``(B, nt, nz, nz)`` on the path variables and ``(B, 1, nzb, nzb)`` on the
        boundary variables."""
        B, nt, nx = z.shape[0], self.nt, self.problem.nx
        lam_d = lam[:, : self.nd * nx].reshape(B, self.nd, nx)
        # defect i = sum_k M1[i,k] xi_k - M2[i,k] f(z_k): node k's weights on f
        i2, k2, m2 = self._m2
        w = z.new_zeros(B, nt, nx).index_add(1, k2, -m2[:, None] * lam_d[:, i2])
        Hp = self._curvature("dynamics", z, True, w)
        Hb = None
        row_e, row_i = self.nd * nx, 0
        for name, path, mult, row in (
            ("path_eq", True, lam, "e"),
            ("boundary_eq", False, lam, "e"),
            ("path_ineq", True, mu, "i"),
            ("boundary_ineq", False, mu, "i"),
        ):
            k = self.k[name]
            if not k:
                continue
            R = nt if path else 1
            r0 = row_e if row == "e" else row_i
            wk = mult[:, r0 : r0 + R * k].reshape(B, R, k)
            if row == "e":
                row_e += R * k
            else:
                row_i += R * k
            Hk = self._curvature(name, z, path, wk)
            if path:
                Hp = Hp + Hk
            else:
                Hb = Hk if Hb is None else Hb + Hk
        return Hp, Hb

    def _pattern_index(self, key, pat: Tensor, build):
        """The index tensors of a QP block, ``build(ii, jj)`` from the nonzeros ``(ii, jj)``
        of its derivative pattern ``pat``, kept while the pattern is unchanged (it only
        widens when a derivative is nonzero outside it): the QP's sparsity pattern is then
        one set of tensors across QLIN iterations, not rebuilt at each."""
        hit = self._index.get(key)
        if hit is not None and hit[0].shape == pat.shape and torch.equal(hit[0], pat):
            return hit[1]
        ii, jj = pat.nonzero().T
        out = build(ii, jj)
        self._index[key] = (pat, out)
        return out

    def _joined(self, key, parts: list[Tensor]) -> Tensor:
        """``torch.cat(parts, 1)`` of index tensors, the same tensor while the parts are the
        same tensors (the sparse backend then recognises the pattern without hashing it)."""
        hit = self._index.get(key)
        if (
            hit is not None
            and len(hit[0]) == len(parts)
            and all(a is b for a, b in zip(hit[0], parts, strict=True))
        ):
            return hit[1]
        out = torch.cat(parts, 1)
        self._index[key] = (tuple(parts), out)
        return out

    def qp(
        self,
        z_ref: Tensor,
        convexify: bool = False,
        multipliers: tuple[Tensor, Tensor] | None = None,
    ) -> SparseQP:
        """The QP of the reference LQDO problem about ``z_ref (B, n)`` (Prob. 14 in the
        form of Prob. 18). For an OLQ problem it is the transcribed problem itself.

        Beyond the paper (for the safeguarded quasilinearization):

        * ``multipliers = (lam (B, me), mu (B, mi))``: the constraints' curvature
          weighted by these multipliers is added to the objective's Hessian (the
          Lagrangian's Hessian of sequential quadratic programming, centred at
          ``z_ref``: the QP's value and gradient there are unchanged).
        * ``convexify``: each node's Hessian block projected onto the positive
          semidefinite cone (negative eigenvalues set to zero), keeping the value and
          gradient at ``z_ref``: the QP is then convex, its step a descent direction of
          the l1 merit function.

        What does not depend on the reference is built once per batch size: an OLQ
        objective term's block (values, linear and constant parts), the ``M1 Xi`` block
        and the fixed-state rows, the bounds, and the index tensors of every block while
        its derivative pattern is unchanged."""
        self._check_z(z_ref)
        z = z_ref.detach()
        P, B, nt, nx = self.problem, z.shape[0], self.nt, self.problem.nx
        dev, dt = z.device, z.dtype
        n = self.n
        lb, ub = self.bounds(B)  # copies: a caller may tighten a QP's bounds in place
        # whether H is positive semidefinite (every node's block is) is worth knowing for a
        # QP with few inequalities (see SparseQP.convex)
        few = few_inequalities(n, self.mi + self._bound_count(B))
        convex: bool | None = True
        # ---------------- objective
        H_idx, H_val = [], []
        f = z.new_zeros(B, n)
        c = z.new_zeros(B)
        curv = (None, None) if multipliers is None else self._constraint_curvature(z, *multipliers)
        for name, path, loc, w, Hc in (
            ("lagrange", True, self.loc_path, self.w, curv[0]),
            ("mayer", False, self.loc_bnd[None], None, curv[1]),
        ):
            present = P.element(name) is not None
            if not present and Hc is None and not convexify:
                continue
            # an OLQ term's model is the same at every reference (Sec. 4.1)
            const = present and Hc is None and not convexify and bool(P.olq_rows(name).all())
            key = ("H", name, B, dt, dev)
            blk = self._cache.get(key) if const else None
            if blk is None:
                zz = self._path_rows(z)[1] if path else self._bnd_rows(z)
                zz = zz.reshape(B, loc.shape[0], -1)
                if present:
                    Hk, gk, ck = self._quadratic(name, z, path)
                    if w is not None:
                        Hk, gk, ck = Hk * w[:, None, None], gk * w[:, None], ck * w
                else:  # no objective term here: a zero model
                    Hk = zz.new_zeros(*zz.shape, zz.shape[-1])
                    gk, ck = torch.zeros_like(zz), zz.new_zeros(zz.shape[:2])
                if Hc is not None or convexify:
                    Hk, gk, ck = _recentred(Hk, gk, ck, zz, Hc, convexify)

                def build(ii, jj, loc=loc):
                    return ii, jj, torch.stack([loc[:, ii].reshape(-1), loc[:, jj].reshape(-1)])

                ii, jj, idx = self._pattern_index(("H", name), self._widen(name, Hk), build)
                fk = z.new_zeros(B, n).index_add(1, loc.reshape(-1), gk.reshape(B, -1))
                psd = _is_psd(Hk) if (const or few) else None
                blk = (idx, Hk[:, :, ii, jj].reshape(B, -1), fk, ck.sum(1), psd)
                if const:
                    self._cache[key] = blk
            H_idx.append(blk[0])
            H_val.append(blk[1])
            f = f + blk[2]
            c = c + blk[3]
            convex = None if (convex is None or blk[4] is None) else (convex and blk[4])
        # ---------------- equalities
        A_idx, A_val, b = [], [], []
        Jf, rf = self._linear("dynamics", z, True)  # (B, nt, nx, nz), (B, nt, nx)
        (i1, k1, m1), (i2, k2, m2) = self._m1, self._m2

        def m1_block():  # M1 Xi: rows i nx + a, columns xi_{k, a}
            a = torch.arange(nx, device=dev)
            idx = torch.stack([(i1[:, None] * nx + a).reshape(-1), self.idx_x[k1].reshape(-1)])
            return idx, m1[:, None].expand(-1, nx).reshape(1, -1).expand(B, -1).to(dt)

        idx, val = self._memo(("M1", B, dt, dev), (), m1_block)
        A_idx.append(idx)
        A_val.append(val)
        nzl = Jf.shape[-1]

        def dyn_block(ak, jk):
            # -M2 J_k z_k on the Jacobian's structural nonzeros (rows ak, node-local vars
            # jk): one gather from the flat Jacobians, times -M2
            idx = torch.stack(
                [(i2[:, None] * nx + ak).reshape(-1), self.loc_path[k2][:, jk].reshape(-1)]
            )
            flat = (k2[:, None] * (nx * nzl) + ak * nzl + jk).reshape(-1)
            coef = (-m2[:, None]).expand(-1, ak.numel()).reshape(-1)
            return idx, flat, coef

        idx, flat, coef = self._pattern_index(
            ("A", "dynamics"), self._widen("dynamics", Jf), dyn_block
        )
        A_idx.append(idx)
        A_val.append(coef.to(dt) * Jf.reshape(B, -1)[:, flat])
        bd = z.new_zeros(B, self.nd, nx).index_add(1, i2, m2[:, None] * rf[:, k2])
        b.append(bd.reshape(B, -1))
        row0 = self.nd * nx

        def add_linear(name, path, rows_list, idx_list, val_list, row0):
            J, r = self._linear(name, z, path)  # (B, R, k, nz)
            R, k, _ = J.shape[1:]
            loc = self.loc_path if path else self.loc_bnd[None]

            def build(ak, jk):
                rr = row0 + torch.arange(R, device=dev)[:, None] * k + ak
                return ak, jk, torch.stack([rr.reshape(-1), loc[:, jk].reshape(-1)])

            ak, jk, idx = self._pattern_index(("A", name), self._widen(name, J), build)
            idx_list.append(idx)
            val_list.append(J[:, :, ak, jk].reshape(B, -1))
            rows_list.append(-r.reshape(B, -1))
            return row0 + R * k

        if self.k["path_eq"]:
            row0 = add_linear("path_eq", True, b, A_idx, A_val, row0)
        if self.k["boundary_eq"]:
            row0 = add_linear("boundary_eq", False, b, A_idx, A_val, row0)

        def fixed_rows(row0=row0):
            out = []
            for mask, node in ((self.fix0, 0), (self.fixf, nt - 1)):
                cols = self.idx_x[node][mask]
                m = cols.numel()
                out.append(torch.stack([row0 + torch.arange(m, device=dev), cols]))
                row0 += m
            return out, z.new_ones(B, int(self.fix0.sum()) + int(self.fixf.sum()))

        rows, ones = self._memo(("fixed rows", B, dt, dev), (), fixed_rows)
        A_idx += rows
        A_val.append(ones)
        b += [self._fixed("initial", B), self._fixed("final", B)]
        # ---------------- inequalities
        G_idx, G_val, h = [self._no_index], [z.new_zeros(B, 0)], []
        r0 = 0
        if self.k["path_ineq"]:
            r0 = add_linear("path_ineq", True, h, G_idx, G_val, r0)
        if self.k["boundary_ineq"]:
            r0 = add_linear("boundary_ineq", False, h, G_idx, G_val, r0)
        if not H_idx:
            H_idx, H_val = [self._no_index], [z.new_zeros(B, 0)]
        return SparseQP(
            n=n,
            H_idx=self._joined("H", H_idx),
            H_val=torch.cat(H_val, 1).to(dt),
            f=f,
            c=c,
            A_idx=self._joined("A", A_idx),
            A_val=torch.cat(A_val, 1),
            b=torch.cat(b, 1),
            G_idx=self._joined("G", G_idx),
            G_val=torch.cat(G_val, 1),
            h=torch.cat(h, 1) if h else z.new_zeros(B, 0),
            lb=lb,
            ub=ub,
            convex=convex,
        )


def transcribe(
    problem: LQDOProblem,
    method: str = "TR",
    nodes: int = 20,
    mesh: Tensor | None = None,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Transcription:
    """Transcribe ``problem`` with trapezoidal (``"TR"``) or Legendre-Gauss-Lobatto
    pseudospectral (``"PS"``) defects and quadrature on ``nodes`` points (Sec. 2.2).

    Example::

        tr = transcribe(problem, "PS", nodes=10)
        qp = tr.qp(tr.initial_guess())     # the reference LQDO QP (Prob. 14)
    """
    return Transcription(problem, method=method, nodes=nodes, mesh=mesh, dtype=dtype, device=device)


def _is_psd(H: Tensor) -> bool:
    """Whether every symmetric block ``H (..., k, k)`` is positive semidefinite (its
    smallest eigenvalue at least ``-1e-12`` times its largest magnitude)."""
    if H.numel() == 0:
        return True
    lam = torch.linalg.eigvalsh(0.5 * (H + H.mT))
    scale = lam.abs().amax(-1).clamp_min(1e-300)
    return bool((lam[..., 0] >= -1e-12 * scale).all())


def _psd_part(H: Tensor) -> Tensor:
    """The nearest positive semidefinite matrices (Frobenius norm) to the symmetric
    ``H (..., k, k)``: negative eigenvalues set to zero (matrices without one unchanged)."""
    H = 0.5 * (H + H.mT)
    if H.numel() == 0:
        return H
    lam, V = torch.linalg.eigh(H)
    neg = (lam < 0).any(-1)
    if not bool(neg.any()):
        return H
    proj = (V * lam.clamp_min(0).unsqueeze(-2)) @ V.mT
    return torch.where(neg[..., None, None], proj, H)


def _recentred(
    H: Tensor, g: Tensor, c: Tensor, zz: Tensor, extra: Tensor | None, convexify: bool
) -> tuple[Tensor, Tensor, Tensor]:
    """The quadratic model ``1/2 z'Hz + g'z + c`` (per node, ``H (B, R, k, k)``, ``zz
    (B, R, k)`` the reference) with ``extra`` added to its Hessian and, if
    ``convexify``, the Hessian projected onto the PSD cone, both centred at ``zz``: the
    model's value and gradient at ``zz`` are kept."""
    Hz = (H @ zz.unsqueeze(-1)).squeeze(-1)
    grad = Hz + g
    value = 0.5 * (zz * Hz).sum(-1) + (g * zz).sum(-1) + c
    if extra is not None:
        H = H + extra
    if convexify:
        H = _psd_part(H)
    Hz = (H @ zz.unsqueeze(-1)).squeeze(-1)
    return H, grad - Hz, value - (grad * zz).sum(-1) + 0.5 * (zz * Hz).sum(-1)
