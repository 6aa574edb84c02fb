"""The nonlinear dynamic optimisation (NLDO) problem of Herber & Sundarrajan (2020), Prob. (1).

.. math::

    \\min_{u, \\xi, p} \\int_{t_0}^{t_f} \\ell(t, u, \\xi, p)\\,dt + m(p, \\xi_0, \\xi_f)
    \\quad\\text{s.t.}\\quad \\dot\\xi = f(t, u, \\xi, p),\\; h = 0,\\; g \\le 0,

with controls ``u (nu)``, states ``xi (nx)`` and static parameters ``p (np)``; path
constraints depend on ``(t, u, xi, p)``, boundary constraints on ``(p, xi0, xif)``
(eqs. 1c-1e), plus simple bounds on ``u``, ``xi``, ``p`` and fixed initial/final states.

Every function is a plain torch function that broadcasts over leading dimensions and
indexes its arguments with ``[..., i]``:

* path functions (``dynamics``, ``lagrange``, ``path_eq``, ``path_ineq``):
  ``fn(t (...), u (..., nu), xi (..., nx), p (..., np)) -> (..., k)`` (``lagrange`` returns
  ``(...)``);
* boundary functions (``mayer``, ``boundary_eq``, ``boundary_ineq``):
  ``fn(p (..., np), xi0 (..., nx), xif (..., nx)) -> (..., k)`` (``mayer`` returns ``(...)``).

The functions must not close over per-element tensors (a batch of problems differs
through ``initial``/``final`` or through ``p``): they are evaluated on rows that mix
nodes and elements.

Ordinary-linear-quadratic elements (OLQ, Sec. 3.1): a constraint whose Jacobian in
``(u, xi, p)`` does not depend on ``(u, xi, p)`` (it may depend on ``t``), an objective term
whose Hessian does not. Each element may be declared with ``olq={"dynamics": [True, False],
"lagrange": True, ...}`` (one flag, or one per output row of a vector element) or detected
by :func:`detect_olq` (autodiff at random points, the "careful numerical procedure at
several diverse points" of Sec. 4.1 made exact by automatic differentiation). The
transcription builds OLQ pieces of the QP once and reuses them (Sec. 4.1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

__all__ = ["LQDOProblem", "PATH_ELEMENTS", "BOUNDARY_ELEMENTS", "detect_olq", "row_derivatives"]

PATH_ELEMENTS = ("dynamics", "lagrange", "path_eq", "path_ineq")
BOUNDARY_ELEMENTS = ("mayer", "boundary_eq", "boundary_ineq")
_SCALAR = ("lagrange", "mayer")


def _vec(x, n: int, name: str, fill: float) -> Tensor:
    """A bound or fixed-value vector as a float64 tensor of shape ``(n,)`` or ``(B, n)``."""
    if x is None:
        return torch.full((n,), fill, dtype=torch.float64)
    t = torch.as_tensor(x, dtype=torch.float64)
    if t.ndim == 0:
        t = t.expand(n)
    if t.shape[-1] != n or t.ndim > 2:
        raise ValueError(f"{name} must have shape ({n},) or (B, {n}); got {tuple(t.shape)}")
    return t.clone()


@dataclass
class LQDOProblem:
    """An NLDO problem, Prob. (1), on the fixed horizon ``[t0, tf]``.

    Args:
        nu, nx, np: numbers of controls, states and static parameters.
        tf, t0: the horizon.
        dynamics: ``f(t, u, xi, p) -> (..., nx)`` (eq. 1b).
        lagrange: ``l(t, u, xi, p) -> (...)``, the integrand of eq. (1a) (None: 0).
        mayer: ``m(p, xi0, xif) -> (...)`` (None: 0).
        path_eq, path_ineq: ``(t, u, xi, p) -> (..., k)``, ``= 0`` / ``<= 0`` at every node.
        boundary_eq, boundary_ineq: ``(p, xi0, xif) -> (..., k)``, ``= 0`` / ``<= 0``.
        initial, final: fixed ``xi(t0)`` / ``xi(tf)``, ``(nx,)`` or ``(B, nx)``; NaN marks a
            free component (same pattern across the batch). None: free.
        u_lb, u_ub, xi_lb, xi_ub, p_lb, p_ub: simple bounds, ``(dim,)`` or ``(B, dim)``
            (infinite where absent).
        olq: declared OLQ flags per element name (``True``/``False`` or one per row);
            elements not named are detected with :func:`detect_olq`.
    """

    nu: int
    nx: int
    np: int = 0
    tf: float = 1.0
    t0: float = 0.0
    dynamics: Callable[..., Tensor] | None = None
    lagrange: Callable[..., Tensor] | None = None
    mayer: Callable[..., Tensor] | None = None
    path_eq: Callable[..., Tensor] | None = None
    path_ineq: Callable[..., Tensor] | None = None
    boundary_eq: Callable[..., Tensor] | None = None
    boundary_ineq: Callable[..., Tensor] | None = None
    initial: Tensor | None = None
    final: Tensor | None = None
    u_lb: Tensor | None = None
    u_ub: Tensor | None = None
    xi_lb: Tensor | None = None
    xi_ub: Tensor | None = None
    p_lb: Tensor | None = None
    p_ub: Tensor | None = None
    olq: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("nu", "nx", "np"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 0:
                raise ValueError(f"{name} must be a non-negative int; got {v!r}")
        if self.nx < 1:
            raise ValueError("nx must be at least 1")
        if not self.tf > self.t0:
            raise ValueError(f"tf must be greater than t0; got t0={self.t0}, tf={self.tf}")
        if self.dynamics is None or not callable(self.dynamics):
            raise TypeError("dynamics must be a callable f(t, u, xi, p) -> (..., nx)")
        for name in PATH_ELEMENTS + BOUNDARY_ELEMENTS:
            fn = getattr(self, name)
            if fn is not None and not callable(fn):
                raise TypeError(f"{name} must be callable or None; got {type(fn).__name__}")
        unknown = set(self.olq) - set(PATH_ELEMENTS + BOUNDARY_ELEMENTS)
        if unknown:
            raise ValueError(
                f"olq names unknown elements {sorted(unknown)}; valid: "
                f"{list(PATH_ELEMENTS + BOUNDARY_ELEMENTS)}"
            )
        inf = float("inf")
        self.u_lb = _vec(self.u_lb, self.nu, "u_lb", -inf)
        self.u_ub = _vec(self.u_ub, self.nu, "u_ub", inf)
        self.xi_lb = _vec(self.xi_lb, self.nx, "xi_lb", -inf)
        self.xi_ub = _vec(self.xi_ub, self.nx, "xi_ub", inf)
        self.p_lb = _vec(self.p_lb, self.np, "p_lb", -inf)
        self.p_ub = _vec(self.p_ub, self.np, "p_ub", inf)
        nan = float("nan")
        self.initial = _vec(self.initial, self.nx, "initial", nan)
        self.final = _vec(self.final, self.nx, "final", nan)
        for name in ("initial", "final"):
            v = getattr(self, name)
            if v.ndim == 2 and not (v.isnan() == v[:1].isnan()).all():
                raise ValueError(f"{name}: the NaN (free) pattern must be the same in every row")
        self._olq_cache: dict[str, Tensor] = {}
        self._pattern: dict[str, Tensor] = {}

    # ------------------------------------------------------------------ element access
    def element(self, name: str) -> Callable[..., Tensor] | None:
        return getattr(self, name)

    def out_dim(self, name: str) -> int:
        """Output rows of an element (1 for the scalar objective terms, 0 when absent)."""
        fn = self.element(name)
        if fn is None:
            return 0
        if name in _SCALAR:
            return 1
        if name == "dynamics":
            return self.nx
        z = torch.zeros(1, self.np + 2 * self.nx + self.nu, dtype=torch.float64)
        if name in PATH_ELEMENTS:
            out = fn(torch.zeros(1, dtype=torch.float64), *self.split_path(z[:, : self.nz_path]))
        else:
            out = fn(*self.split_boundary(z[:, : self.nz_boundary]))
        return int(out.shape[-1])

    @property
    def nz_path(self) -> int:
        """Variables a path function sees at one node: ``[u, xi, p]``."""
        return self.nu + self.nx + self.np

    @property
    def nz_boundary(self) -> int:
        """Variables a boundary function sees: ``[p, xi0, xif]``."""
        return self.np + 2 * self.nx

    def split_path(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        nu, nx = self.nu, self.nx
        return z[..., :nu], z[..., nu : nu + nx], z[..., nu + nx :]

    def split_boundary(self, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        np_, nx = self.np, self.nx
        return z[..., :np_], z[..., np_ : np_ + nx], z[..., np_ + nx :]

    def call(self, name: str, t: Tensor | None, z: Tensor) -> Tensor:
        """Evaluate element ``name`` on rows ``z (R, nz)`` (``t (R,)`` for path elements);
        returns ``(R, k)`` (``k = 1`` for scalar terms)."""
        fn = self.element(name)
        out = fn(t, *self.split_path(z)) if name in PATH_ELEMENTS else fn(*self.split_boundary(z))
        if name in _SCALAR:
            out = out.unsqueeze(-1)
        if out.shape[:-1] != z.shape[:-1]:
            raise ValueError(
                f"{name} returned shape {tuple(out.shape)} for inputs with leading shape "
                f"{tuple(z.shape[:-1])}: it must broadcast over leading dimensions"
            )
        return out

    # ------------------------------------------------------------------ OLQ flags
    def pattern(self, name: str) -> Tensor:
        """Structural nonzeros of element ``name``'s derivative found at random points:
        ``(k, nz)`` Jacobian pattern, ``(nz, nz)`` Hessian pattern for ``lagrange``/``mayer``.
        The transcription widens it whenever a derivative outside it is nonzero."""
        if name not in self._pattern:
            detect_olq(self, name)
        return self._pattern[name]

    def olq_rows(self, name: str) -> Tensor:
        """``(k,)`` bool: which output rows of element ``name`` are OLQ (declared, or
        detected once by :func:`detect_olq` and cached)."""
        if name in self._olq_cache:
            return self._olq_cache[name]
        k = self.out_dim(name)
        if name in self.olq:
            flags = torch.as_tensor(self.olq[name], dtype=torch.bool).reshape(-1)
            if flags.numel() == 1:
                flags = flags.expand(k).clone()
            if flags.numel() != k:
                raise ValueError(f"olq[{name!r}] needs 1 or {k} flags; got {flags.numel()}")
        else:
            flags = detect_olq(self, name)
        self._olq_cache[name] = flags
        return flags


def row_derivatives(
    fn: Callable[[Tensor], Tensor], z: Tensor, rows: Tensor | None = None, hessian: bool = False
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Value, Jacobian (and Hessian) of a row-wise function at every row at once.

    ``fn`` maps ``z (R, nz)`` to ``(R, k)`` and each output row depends only on its own
    input row, so the gradient of one output summed over the rows is that output's
    Jacobian row at every row. All outputs are differentiated in one vectorised
    backward pass (``grad_outputs`` the ``k`` unit vectors, ``is_grads_batched``), and
    the Hessian in one more over the ``nz`` components of the gradient: none per node,
    batch element or output (one pass per output had cost three times as much on the
    crane's 20 nodes, the autograd engine's fixed cost per call dominating).

    Args:
        fn: the row-wise function.
        z: ``(R, nz)``.
        rows: output rows to differentiate (default all ``k``).
        hessian: also the Hessian of output row 0 (scalar terms, ``k = 1``).

    Returns:
        ``value (R, k)``, ``jac (R, len(rows), nz)``, ``hess (R, nz, nz)`` or None.
    """
    with torch.enable_grad():
        zz = z.detach().requires_grad_(True)
        val = fn(zz)
        if rows is not None:
            rows = torch.as_tensor(rows, dtype=torch.long, device=val.device).reshape(-1)
        out = val if rows is None else val.index_select(1, rows)
        jac = _row_vjps(out, zz, hessian)
        hess = _row_vjps(jac[:, 0], zz, False) if hessian else None
    return val.detach(), jac.detach(), None if hess is None else hess.detach()


def _row_vjps(out: Tensor, zz: Tensor, create: bool) -> Tensor:
    """``(R, m, nz)``: the gradient of each column of ``out (R, m)`` summed over the rows
    with respect to ``zz (R, nz)`` (a row's Jacobian, as rows are independent)."""
    R, m = out.shape
    if m == 0 or not out.requires_grad:  # no rows, or constant rows
        return zz.new_zeros(R, m, zz.shape[1])
    if m > 1:
        seeds = torch.eye(m, dtype=out.dtype, device=out.device)[:, None].expand(m, R, m)
        try:
            g = torch.autograd.grad(
                out, zz, seeds, retain_graph=True, create_graph=create, allow_unused=True,
                is_grads_batched=True,
            )[0]  # fmt: skip
            return zz.new_zeros(R, m, zz.shape[1]) if g is None else g.transpose(0, 1)
        except RuntimeError:
            pass  # an operation without a batching rule: one pass per column below
    cols = []
    for r in range(m):
        g = None
        if out[:, r].requires_grad:
            g = torch.autograd.grad(
                out[:, r].sum(), zz, retain_graph=True, create_graph=create, allow_unused=True
            )[0]
        cols.append(torch.zeros_like(zz) if g is None else g)
    return torch.stack(cols, 1)


def detect_olq(problem: LQDOProblem, name: str, samples: int = 4, seed: int = 0) -> Tensor:
    """Detect which output rows of element ``name`` are OLQ (Sec. 3.1, Sec. 4.1).

    Constraints (and the dynamics): the row's Jacobian in ``z`` is the same at
    ``samples`` random points ``z`` drawn at each of several times ``t`` (a time-varying
    linear element is OLQ). Objective terms: the Hessian is the same. Automatic
    differentiation gives the derivatives exactly, so an affine row yields identical
    Jacobians up to rounding; a row whose derivatives are not finite is not OLQ.

    Returns:
        ``(k,)`` bool (``k = 1`` for ``lagrange``/``mayer``).
    """
    fn = problem.element(name)
    if fn is None:
        return torch.zeros(0, dtype=torch.bool)
    gen = torch.Generator().manual_seed(seed)
    path = name in PATH_ELEMENTS
    nz = problem.nz_path if path else problem.nz_boundary
    nt = 3 if path else 1
    span = problem.tf - problem.t0
    t = problem.t0 + span * torch.rand(nt, generator=gen, dtype=torch.float64)
    t = t.repeat_interleave(samples)
    # diverse points: unit normals scaled by 1, 10 and 0.1 so a term like 1e-3 x^2 is caught
    z = torch.randn(nt * samples, nz, generator=gen, dtype=torch.float64)
    scales = torch.tensor([1.0, 7.0, 0.3, 3.0], dtype=torch.float64)
    z = z * scales[torch.arange(samples) % 4].repeat(nt)[:, None]

    def f(zz: Tensor) -> Tensor:
        return problem.call(name, t if path else None, zz)

    scalar = name in _SCALAR
    _, jac, hess = row_derivatives(f, z, hessian=scalar)
    d = hess.unsqueeze(1) if scalar else jac  # (R, k, ...)
    # structural nonzeros of the Jacobian (Hessian for scalar terms) at the random points
    problem._pattern[name] = (d != 0).any(0).reshape(hess.shape[1:] if scalar else jac.shape[1:])
    d = d.reshape(nt, samples, d.shape[1], -1)
    ref = d[:, :1]
    scale = ref.abs().amax(dim=(0, 1, 3), keepdim=True).clamp_min(1.0)
    same = ((d - ref).abs() <= 1e-10 * scale).all(dim=3).all(dim=1).all(dim=0)
    return same & torch.isfinite(d).reshape(-1, d.shape[2], d.shape[3]).all(2).all(0)
