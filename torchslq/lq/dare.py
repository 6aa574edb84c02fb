"""Batched discrete-time algebraic Riccati equation (DARE) by a structured doubling algorithm.

Solves, for the stabilising solution ``X = X' >= 0``::

    X = A' X A - A' X B (R + B' X B)^{-1} B' X A + Q                      (DARE)

with the structured doubling algorithm (SDA) of Chu, Fan and Lin (2005), started from
``A_0 = A``, ``G_0 = B R^{-1} B'``, ``H_0 = Q``::

    W_k     = (I + G_k H_k)^{-1}
    A_{k+1} = A_k W_k A_k
    G_{k+1} = G_k + A_k W_k G_k A_k'
    H_{k+1} = H_k + A_k' H_k W_k A_k

``H_k`` converges quadratically to ``X`` when ``(A, B)`` is stabilisable and
``(Q^{1/2}, A)`` detectable (``H_k`` is the value of the ``2^k``-step LQ problem, so the
doubling is the Riccati recursion iterated ``2^k`` times). The iteration runs on the
whole batch at once; it stops when every element's relative change is below ``tol``
(one host sync per doubling step, never per element) and ``A_k`` (a power of the
closed-loop matrix) has vanished.

Used for the terminal weight ``Qf`` of the GoPRONTO pendulum-train experiments
(Sforni et al. 2022, Section V.1). ``tests/test_pendulum_train.py`` checks it against
``scipy.linalg.solve_discrete_are`` and the DARE residual.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._shapes import broadcast_shapes

__all__ = ["dare", "dare_gain", "dare_residual"]


def dare(
    A: Tensor,
    B: Tensor,
    Q: Tensor,
    R: Tensor,
    *,
    tol: float | None = None,
    max_iter: int = 100,
) -> Tensor:
    """Stabilising solution ``X (..., n, n)`` of the DARE for a batch of systems.

    Args:
        A: ``(..., n, n)`` state matrices.
        B: ``(..., n, m)`` input matrices.
        Q: ``(..., n, n)`` symmetric positive semidefinite state weights.
        R: ``(..., m, m)`` symmetric positive definite input weights.
        tol: relative change ``||H_{k+1} - H_k||_F <= tol ||H_{k+1}||_F`` at which to
            stop; default ``1e-13`` (float64) or ``1e-6`` (float32).
        max_iter: maximum number of doubling steps (each doubles the horizon).

    Leading dims broadcast. Raises ``RuntimeError`` if some element has not converged
    after ``max_iter`` steps or is not finite (e.g. ``(A, B)`` not stabilisable).
    """
    for name, M in (("A", A), ("B", B), ("Q", Q), ("R", R)):
        if not torch.is_tensor(M) or M.ndim < 2:
            raise TypeError(f"{name} must be a tensor with at least 2 dims")
    n, m = A.shape[-1], B.shape[-1]
    if A.shape[-2] != n or B.shape[-2] != n or Q.shape[-2:] != (n, n) or R.shape[-2:] != (m, m):
        raise ValueError(
            f"expected A (..., n, n), B (..., n, m), Q (..., n, n), R (..., m, m); got "
            f"{tuple(A.shape)}, {tuple(B.shape)}, {tuple(Q.shape)}, {tuple(R.shape)}"
        )
    if tol is None:
        tol = 1e-13 if A.dtype == torch.float64 else 1e-6
    lead = broadcast_shapes(A.shape[:-2], B.shape[:-2], Q.shape[:-2], R.shape[:-2])
    Ak = A.expand(*lead, n, n)
    Bx = B.expand(*lead, n, m)
    G = Bx @ torch.linalg.solve(R.expand(*lead, m, m), Bx.mT)
    G = 0.5 * (G + G.mT)
    H = 0.5 * (Q + Q.mT).expand(*lead, n, n)
    eye = torch.eye(n, dtype=A.dtype, device=A.device)
    for _ in range(max_iter):
        W = torch.linalg.solve(eye + G @ H, torch.cat([Ak, G], -1))  # (I + GH)^{-1} [A, G]
        WA, WG = W[..., :n], W[..., n:]
        H_new = H + Ak.mT @ (H @ WA)
        G = G + Ak @ WG @ Ak.mT
        Ak = Ak @ WA
        H_new = 0.5 * (H_new + H_new.mT)
        G = 0.5 * (G + G.mT)
        change = torch.linalg.matrix_norm(H_new - H)
        scale = torch.linalg.matrix_norm(H_new).clamp_min(torch.finfo(A.dtype).tiny)
        H = H_new
        if not bool(torch.isfinite(H).all()):
            raise RuntimeError("dare: non-finite iterate (is (A, B) stabilisable?)")
        # converged: H has stopped changing and A_k (a power of the closed loop) has
        # vanished; an unstabilisable problem grows without bound instead
        if bool(((change <= tol * scale) & (torch.linalg.matrix_norm(Ak) <= 1e-6)).all()):
            return H
    raise RuntimeError(f"dare: no convergence in {max_iter} doubling steps")


def dare_gain(A: Tensor, B: Tensor, X: Tensor, R: Tensor) -> Tensor:
    """The LQR gain ``K = (R + B'XB)^{-1} B'XA`` ``(..., m, n)`` (control ``u = -K x``)."""
    BX = B.mT @ X
    return torch.linalg.solve(R + BX @ B, BX @ A)


def dare_residual(A: Tensor, B: Tensor, Q: Tensor, R: Tensor, X: Tensor) -> Tensor:
    """``A'XA - A'XB (R + B'XB)^{-1} B'XA + Q - X`` ``(..., n, n)``: zero at a solution."""
    AX = A.mT @ X
    return AX @ A - AX @ B @ dare_gain(A, B, X, R) + Q - X
