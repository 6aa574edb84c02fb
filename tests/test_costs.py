"""QuadraticCost against the paper's eqs. (3)-(4), its expansion, and its validation."""

from __future__ import annotations

import pytest
import torch

from torchslq import QuadraticCost

# torch.func.hessian (forward-mode AD) makes torch load jit-scripted decompositions once
pytestmark = pytest.mark.filterwarnings(
    "ignore:`torch.jit.script` is deprecated:DeprecationWarning"
)

DT = torch.float64
B, T, N, M = 3, 5, 3, 2


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def spd(*lead, k, seed, psd=False):
    g = _gen(seed)
    L = torch.randn(*lead, k, k, dtype=DT, generator=g)
    W = L @ L.mT
    if psd:  # rank deficient: only semidefinite
        v = torch.randn(*lead, k, 1, dtype=DT, generator=g)
        return v @ v.mT
    return W + 0.1 * torch.eye(k, dtype=DT)


def traj(seed=0):
    g = _gen(seed)
    return (
        torch.randn(B, T + 1, N, dtype=DT, generator=g),
        torch.randn(B, T, M, dtype=DT, generator=g),
    )


def _at(W, b, t, time_dims):
    """Weight/reference of batch element b at step t, whatever its layout."""
    if W is None:
        return None
    if W.ndim == time_dims:  # constant
        return W
    if W.ndim == time_dims + 1:  # time-varying
        return W[t] if W.shape[0] > 1 else W[0]
    Wb = W[b]  # per element
    return Wb[t] if Wb.shape[0] > 1 else Wb[0]


def loop_cost(x, u, Q, R, Qf=None, x_ref=None, u_ref=None):
    """Sum over n<N of L(x(n), u(n), n) of eq. (3) plus psi(x(N)) of eq. (4), one element
    and one step at a time."""
    out = []
    for b in range(x.shape[0]):
        J = torch.zeros((), dtype=DT)
        for t in range(T):
            dx = x[b, t] - (0 if x_ref is None else _at(x_ref, b, t, 1))
            du = u[b, t] - (0 if u_ref is None else _at(u_ref, b, t, 1))
            J = J + 0.5 * (dx @ _at(Q, b, t, 2) @ dx + du @ _at(R, b, t, 2) @ du)
        dx = x[b, T] - (0 if x_ref is None else _at(x_ref, b, T, 1))
        if Qf is None:  # default: the last stage weight
            QN = _at(Q, b, T - 1, 2)
        else:
            QN = Qf if Qf.ndim == 2 else Qf[b]
        J = J + 0.5 * dx @ QN @ dx
        out.append(J)
    return torch.stack(out)


CASES = {
    "constant": lambda: dict(Q=spd(k=N, seed=1, psd=True), R=spd(k=M, seed=2)),
    "constant_refs_Qf": lambda: dict(
        Q=spd(k=N, seed=1),
        R=spd(k=M, seed=2),
        Qf=spd(k=N, seed=3),
        x_ref=torch.randn(N, dtype=DT, generator=_gen(4)),
        u_ref=torch.randn(M, dtype=DT, generator=_gen(5)),
    ),
    "time_varying": lambda: dict(
        Q=spd(T, k=N, seed=6),
        R=spd(T, k=M, seed=7),
        x_ref=torch.randn(T + 1, N, dtype=DT, generator=_gen(8)),
        u_ref=torch.randn(T, M, dtype=DT, generator=_gen(9)),
    ),
    "per_element": lambda: dict(
        Q=spd(B, T, k=N, seed=10),
        R=spd(B, T, k=M, seed=11),
        Qf=spd(B, k=N, seed=12),
        x_ref=torch.randn(B, T + 1, N, dtype=DT, generator=_gen(13)),
        u_ref=torch.randn(B, T, M, dtype=DT, generator=_gen(14)),
    ),
    "per_element_constant": lambda: dict(
        Q=spd(B, 1, k=N, seed=15),
        R=spd(B, 1, k=M, seed=16),
        x_ref=torch.randn(B, 1, N, dtype=DT, generator=_gen(17)),
        u_ref=torch.randn(B, 1, M, dtype=DT, generator=_gen(18)),
    ),
    # diagonal weights take the elementwise paths (a diagonal Q with a full Qf does not)
    "diagonal": lambda: dict(
        Q=torch.diag_embed(torch.rand(T, N, dtype=DT, generator=_gen(23))),
        R=torch.diag_embed(1 + torch.rand(M, dtype=DT, generator=_gen(24))),
        Qf=torch.diag_embed(torch.rand(B, N, dtype=DT, generator=_gen(25))),
        x_ref=torch.randn(N, dtype=DT, generator=_gen(26)),
        u_ref=torch.randn(B, T, M, dtype=DT, generator=_gen(27)),
    ),
    "diagonal_Q_full_Qf": lambda: dict(
        Q=torch.diag_embed(torch.rand(N, dtype=DT, generator=_gen(28))),
        R=spd(k=M, seed=29),
        Qf=spd(k=N, seed=30),
    ),
    "mixed": lambda: dict(
        Q=spd(T, k=N, seed=19),
        R=spd(k=M, seed=20),
        Qf=spd(B, k=N, seed=21),
        x_ref=torch.randn(B, T + 1, N, dtype=DT, generator=_gen(22)),
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_value_matches_explicit_loop(case):
    kw = CASES[case]()
    x, u = traj()
    J = QuadraticCost(**kw)(x, u)
    assert J.shape == (B,)
    torch.testing.assert_close(J, loop_cost(x, u, **kw), atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize("case", ["diagonal", "diagonal_Q_full_Qf", "per_element"])
def test_quadratize_gradients_are_the_weights_times_the_deviations(case):
    """lx = Q (x - x°), lu = R (u - u°) as the batched matrix products give them, bit for
    bit (diagonal weights are applied elementwise: the products' other terms are exact
    zeros)."""
    kw = CASES[case]()
    cost = QuadraticCost(**kw)
    x, u = traj(seed=3)
    e = cost.quadratize(x, u)
    Q, R = cost.weights(T)
    xr = kw.get("x_ref", torch.zeros(N, dtype=DT))
    ur = kw.get("u_ref", torch.zeros(M, dtype=DT))
    xr = xr if xr.ndim > 1 else xr.expand(T + 1, N)
    assert torch.equal(e.lx, (Q @ (x - xr).unsqueeze(-1)).squeeze(-1))
    assert torch.equal(e.lu, (R @ (u - ur).unsqueeze(-1)).squeeze(-1))


def test_paper_convention_q0_zero_ignores_initial_state():
    # Sideris & Bobrow take Q(0) = 0 since x(0) is given: then J does not depend on x(0)
    Q = spd(T, k=N, seed=1)
    Q[0] = 0
    cost = QuadraticCost(Q, spd(k=M, seed=2), x_ref=torch.ones(T + 1, N, dtype=DT))
    x, u = traj()
    x2 = x.clone()
    x2[:, 0] += 10.0
    torch.testing.assert_close(cost(x, u), cost(x2, u))


@pytest.mark.parametrize("case", sorted(CASES))
def test_quadratize_matches_autograd(case):
    cost = QuadraticCost(**CASES[case]())
    x, u = traj(seed=1)
    xr, ur = x.clone().requires_grad_(True), u.clone().requires_grad_(True)
    gx, gu = torch.autograd.grad(cost(xr, ur).sum(), (xr, ur))
    e = cost.quadratize(x, u)
    assert e.lx.shape == x.shape and e.lu.shape == u.shape and e.lux is None
    torch.testing.assert_close(e.lx, gx, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(e.lu, gu, atol=1e-12, rtol=1e-12)
    # Hessians: the cost is exactly quadratic, blocks per (element, step)
    b = B - 1

    def with_row(z, zb):
        return torch.cat([z[:b], zb.unsqueeze(0), z[b + 1 :]])

    Hx = torch.func.hessian(lambda xb: cost(with_row(x, xb), u)[b])(x[b])
    Hu = torch.func.hessian(lambda ub: cost(x, with_row(u, ub))[b])(u[b])
    lxx = e.lxx.expand(B, T + 1, N, N)[b]
    luu = e.luu.expand(B, T, M, M)[b]
    for t in range(T + 1):
        torch.testing.assert_close(Hx[t, :, t, :], lxx[t], atol=1e-12, rtol=1e-12)
    for t in range(T):
        torch.testing.assert_close(Hu[t, :, t, :], luu[t], atol=1e-12, rtol=1e-12)
    # and the second-order model is exact for any step
    dx, du = traj(seed=7)
    J1 = cost(x + dx, u + du)
    model = (
        cost(x, u)
        + (e.lx * dx).sum((1, 2))
        + (e.lu * du).sum((1, 2))
        + 0.5 * torch.einsum("bti,btij,btj->b", dx, e.lxx.expand(B, -1, -1, -1), dx)
        + 0.5 * torch.einsum("bti,btij,btj->b", du, e.luu.expand(B, -1, -1, -1), du)
    )
    torch.testing.assert_close(J1, model, atol=1e-10, rtol=1e-10)


def test_learnable_weights_get_gradients():
    q = torch.nn.Parameter(torch.tensor([1.0, 2.0, 3.0], dtype=DT))
    xr = torch.nn.Parameter(torch.zeros(N, dtype=DT))
    cost = QuadraticCost(torch.diag(q), torch.eye(M, dtype=DT), x_ref=xr)
    x, u = traj()
    cost(x, u).sum().backward()
    assert xr.grad is not None and xr.grad.abs().sum() > 0
    # diag(q) is not a leaf parameter of the module, but it stays on the graph
    assert q.grad is not None
    torch.testing.assert_close(q.grad, 0.5 * (x**2).sum((0, 1)))


def test_float32():
    cost = QuadraticCost(torch.eye(N), torch.eye(M))
    x, u = traj()
    J = cost(x.float(), u.float())
    assert J.dtype == torch.float32
    torch.testing.assert_close(
        J, loop_cost(x, u, torch.eye(N, dtype=DT), torch.eye(M, dtype=DT)).float()
    )


# ---------------------------------------------------------------- validation


def test_validation_names_the_argument():
    Q, R = torch.eye(N, dtype=DT), torch.eye(M, dtype=DT)
    asym = Q.clone()
    asym[0, 1] = 0.5
    with pytest.raises(ValueError, match="Q must be symmetric"):
        QuadraticCost(asym, R)
    with pytest.raises(ValueError, match="Qf must be symmetric"):
        QuadraticCost(Q, R, Qf=asym)
    with pytest.raises(ValueError, match="Q must be positive semidefinite"):
        QuadraticCost(-Q, R)
    with pytest.raises(ValueError, match="R must be positive definite"):
        QuadraticCost(Q, torch.diag(torch.tensor([1.0, 0.0], dtype=DT)))
    with pytest.raises(ValueError, match="R must be positive definite"):
        QuadraticCost(Q, -R)
    with pytest.raises(ValueError, match="Q must have shape"):
        QuadraticCost(torch.ones(N, N + 1, dtype=DT), R)
    with pytest.raises(ValueError, match="R must have shape"):
        QuadraticCost(Q, torch.ones(M, dtype=DT))
    with pytest.raises(ValueError, match="Qf must have shape"):
        QuadraticCost(Q, R, Qf=torch.eye(N + 1, dtype=DT))
    with pytest.raises(ValueError, match="x_ref"):
        QuadraticCost(Q, R, x_ref=torch.zeros(T + 1, N + 1, dtype=DT))
    with pytest.raises(ValueError, match="x_ref"):
        QuadraticCost(Q, R, x_ref=torch.zeros(B, 1, T + 1, N, dtype=DT))
    with pytest.raises(ValueError, match="u_ref"):
        QuadraticCost(Q, R, u_ref=torch.zeros(T, M + 1, dtype=DT))
    with pytest.raises(ValueError, match="Q contains non-finite"):
        QuadraticCost(torch.full((N, N), float("nan")), R)


def test_horizon_mismatch_names_the_argument():
    Q, R = torch.eye(N, dtype=DT), torch.eye(M, dtype=DT)
    x, u = traj()
    with pytest.raises(ValueError, match="x_ref"):  # (T, n) where (T+1, n) is needed
        QuadraticCost(Q, R, x_ref=torch.zeros(T, N, dtype=DT))(x, u)
    with pytest.raises(ValueError, match="u_ref"):
        QuadraticCost(Q, R, u_ref=torch.zeros(T + 1, M, dtype=DT))(x, u)
    with pytest.raises(ValueError, match="Q has"):
        QuadraticCost(spd(T + 1, k=N, seed=1), R)(x, u)
    with pytest.raises(ValueError, match="x must be"):
        QuadraticCost(Q, R)(x[0], u[0])
    with pytest.raises(ValueError, match="expected x"):
        QuadraticCost(Q, R)(x[:, :-1], u)


@pytest.mark.parametrize("diagonal", [True, False])
def test_value_is_bitwise_batch_invariant_and_trials_broadcast(diagonal):
    """Every row gets the same bits alone, in the batch, and with extra leading (trial)
    dims; shared diagonal weights take the elementwise path (same value as the dense
    weights up to rounding)."""
    g = _gen(40)
    Qm = torch.diag(torch.rand(N, dtype=DT, generator=g) + 0.1) if diagonal else spd(k=N, seed=41)
    kw = dict(
        Q=Qm, R=spd(k=M, seed=42), Qf=spd(k=N, seed=43), x_ref=torch.randn(N, dtype=DT, generator=g)
    )
    cost = QuadraticCost(**kw)
    x = torch.randn(6, B, T + 1, N, dtype=DT, generator=g)
    u = torch.randn(6, B, T, M, dtype=DT, generator=g)
    J = cost(x, u)
    assert J.shape == (6, B)
    for a, b in ((0, 0), (5, B - 1)):
        assert torch.equal(cost(x[a, b : b + 1], u[a, b : b + 1])[0], J[a, b])
        assert torch.equal(cost(x[a], u[a])[b], J[a, b])
    torch.testing.assert_close(J[0], loop_cost(x[0], u[0], **kw), atol=1e-12, rtol=1e-12)
    assert cost._diagonal("Q") is diagonal
    # an in-place change of the weight is seen (the cache is keyed on the version)
    with torch.no_grad():
        cost.Q[0, 1] = cost.Q[1, 0] = 0.01
    assert cost._diagonal("Q") is False
    torch.testing.assert_close(
        cost(x[0], u[0]), loop_cost(x[0], u[0], **{**kw, "Q": cost.Q}), atol=1e-12, rtol=1e-12
    )
