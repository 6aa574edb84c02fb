"""Tests of the batched LQ kernel (``torchslq.lqr_solve``, ``riccati_backward``,
``rollout_linear``) against independent computations:

* a dense KKT solve of the same QP, assembled here element by element;
* a literal transcription of Algorithm 1 of Sideris & Bobrow (2005), eqs. (21)-(26);
* single solves (batching), float64 (float32 runs), ``gradcheck`` (gradients),
  finite differences of the optimal cost (value function).

Problem of ``lqr_solve`` (per batch element)::

    min  sum_{t<T} [ 1/2 x'Q_t x + 1/2 u'R_t u + u'S_t x + q_t'x + r_t'u ]
         + 1/2 x_T'Q_T x_T + q_T'x_T
    s.t. x_{t+1} = A_t x_t + B_t u_t + c_t,   x_0 = x0
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchslq
from torchslq import Status, lqr_solve, riccati_backward, rollout_linear

F64 = torch.float64


pytestmark = pytest.mark.usefixtures("single_thread")


# ----------------------------------------------------------------------------- helpers


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """Norm-wise relative error of ``a`` w.r.t. the reference ``b`` (floor 1 on |b|)."""
    a = a.detach().to(F64)
    b = b.detach().to(F64)
    assert a.shape == b.shape, (a.shape, b.shape)
    return float((a - b).norm() / max(float(b.norm()), 1.0))


def assert_rel(a: torch.Tensor, b: torch.Tensor, tol: float, what: str = "") -> None:
    err = rel_err(a, b)
    assert err < tol, f"{what}: relative error {err:.3e} >= {tol:.1e}"


def randn(g: torch.Generator, *shape: int, dtype=F64) -> torch.Tensor:
    return torch.randn(*shape, generator=g, dtype=F64).to(dtype)


def spd(g: torch.Generator, prefix: tuple[int, ...], k: int, floor: float) -> torch.Tensor:
    """Symmetric matrices ``(*prefix, k, k)`` with eigenvalues >= ``floor``."""
    L = randn(g, *prefix, k, k) / k**0.5
    return L @ L.mT + floor * torch.eye(k, dtype=F64)


def spectral_scale(M: torch.Tensor, bound: float) -> torch.Tensor:
    """Scale each matrix of ``M`` so that its spectral norm is at most ``bound``."""
    nrm = torch.linalg.matrix_norm(M, ord=2).clamp_min(1e-12)
    return M * (bound / nrm.clamp_min(bound)).unsqueeze(-1).unsqueeze(-1)


def dynamics(g: torch.Generator, prefix: tuple[int, ...], n: int, m: int):
    A = 0.9 * torch.eye(n, dtype=F64) + 0.4 * randn(g, *prefix, n, n) / n**0.5
    B = randn(g, *prefix, n, m) / n**0.5
    return A, B


def full(t: torch.Tensor | None, tail_ndim: int, batch: int, steps: int) -> torch.Tensor | None:
    """Expand an argument given in any accepted layout to ``(batch, steps, *tail)``."""
    if t is None:
        return None
    while t.ndim < tail_ndim + 2:
        t = t.unsqueeze(0)
    return t.expand(batch, steps, *t.shape[-tail_ndim:])


def sym(X: torch.Tensor) -> torch.Tensor:
    return 0.5 * (X + X.mT)


def dense_kkt(A, B, Q, R, x0, q, r, S, c):
    """Solve one LQ problem (unbatched, full time layout) by its dense KKT system.

    Variables ``z = [x_0, ..., x_T, u_0, ..., u_{T-1}]``; constraints ``-x_0 = -x0`` and
    ``A_t x_t + B_t u_t - x_{t+1} = -c_t`` with multipliers ``lam_0 .. lam_T``, so that
    stationarity ``H z + g + G' lam = 0`` gives ``lam_T = Q_T x_T + q_T`` and
    ``lam_t = Q_t x_t + S_t' u_t + q_t + A_t' lam_{t+1}``.

    Returns ``x (T+1, n)``, ``u (T, m)``, ``lam (T+1, n)``, ``cost ()``.
    """
    T, n, m = A.shape[0], A.shape[-1], B.shape[-1]
    nx, nv, nc = (T + 1) * n, (T + 1) * n + T * m, (T + 1) * n
    H = torch.zeros(nv, nv, dtype=F64)
    gvec = torch.zeros(nv, dtype=F64)
    G = torch.zeros(nc, nv, dtype=F64)
    h = torch.zeros(nc, dtype=F64)

    def ix(t):
        return slice(t * n, (t + 1) * n)

    def iu(t):
        return slice(nx + t * m, nx + (t + 1) * m)

    eye = torch.eye(n, dtype=F64)
    for t in range(T + 1):
        H[ix(t), ix(t)] = sym(Q[t])
        gvec[ix(t)] = q[t]
    for t in range(T):
        H[iu(t), iu(t)] = sym(R[t])
        H[iu(t), ix(t)] = S[t]
        H[ix(t), iu(t)] = S[t].T
        gvec[iu(t)] = r[t]
    G[0:n, ix(0)] = -eye
    h[0:n] = -x0
    for t in range(T):
        rows = slice((t + 1) * n, (t + 2) * n)
        G[rows, ix(t)] = A[t]
        G[rows, iu(t)] = B[t]
        G[rows, ix(t + 1)] = -eye
        h[rows] = -c[t]
    K = torch.zeros(nv + nc, nv + nc, dtype=F64)
    K[:nv, :nv] = H
    K[:nv, nv:] = G.T
    K[nv:, :nv] = G
    sol = torch.linalg.solve(K, torch.cat([-gvec, h]))
    z, lam = sol[:nv], sol[nv:]
    cost = 0.5 * z @ H @ z + gvec @ z
    return z[:nx].reshape(T + 1, n), z[nx:].reshape(T, m), lam.reshape(T + 1, n), cost


def random_problem(seed: int, bsz: int, T: int, n: int, m: int, dtype=F64):
    """A fully batched, time-varying, well-conditioned problem (all terms present)."""
    g = torch.Generator().manual_seed(seed)
    A, B = dynamics(g, (bsz, T), n, m)
    Q = spd(g, (bsz, T + 1), n, 0.5)
    R = spd(g, (bsz, T), m, 0.5)
    S = spectral_scale(randn(g, bsz, T, m, n), 0.4)
    args = dict(
        A=A,
        B=B,
        Q=Q,
        R=R,
        x0=randn(g, bsz, n),
        q=randn(g, bsz, T + 1, n),
        r=randn(g, bsz, T, m),
        S=S,
        c=0.5 * randn(g, bsz, T, n),
    )
    return {k: v.to(dtype) for k, v in args.items()}


# ----------------------------------------------------------------------------- 1. dense KKT

TIME_LAYOUTS = ["full", "shared_time", "const", "batch1_const", "batch_const"]


def layout_prefix(layout: str, bsz: int, steps: int) -> tuple[int, ...]:
    return {
        "full": (bsz, steps),
        "shared_time": (steps,),
        "const": (),
        "batch1_const": (1, 1),
        "batch_const": (bsz, 1),
    }[layout]


@st.composite
def lq_problems(draw):
    n = draw(st.integers(1, 5))
    m = draw(st.integers(1, 3))
    T = draw(st.integers(1, 6))
    bsz = draw(st.integers(1, 3))
    seed = draw(st.integers(0, 2**31 - 1))
    joint = draw(st.booleans())
    skew = draw(st.booleans())
    lay = {
        "A": draw(st.sampled_from(["full", "shared_time"])),
        "B": draw(st.sampled_from(["full", "shared_time", "batch1_const", "batch_const"])),
        "Q": draw(st.sampled_from(TIME_LAYOUTS)),
        "R": draw(st.sampled_from(TIME_LAYOUTS)),
        "S": draw(st.sampled_from(TIME_LAYOUTS + ["none"])),
        "q": draw(st.sampled_from(TIME_LAYOUTS + ["none"])),
        "r": draw(st.sampled_from(TIME_LAYOUTS + ["none"])),
        "c": draw(st.sampled_from(TIME_LAYOUTS + ["none"])),
    }
    x0_shared = lay["A"] == "full" and draw(st.booleans())

    g = torch.Generator().manual_seed(seed)
    A, _ = dynamics(g, layout_prefix(lay["A"], bsz, T), n, m)
    _, B = dynamics(g, layout_prefix(lay["B"], bsz, T), n, m)
    if joint:
        # joint stage cost [[R, S], [S', Q]] = L L' + 0.1 I, time-varying and batched
        L = randn(g, bsz, T, n + m, n + m) / (n + m) ** 0.5
        W = L @ L.mT + 0.1 * torch.eye(n + m, dtype=F64)
        R, S = W[..., :m, :m], W[..., :m, m:]
        QT = spd(g, (bsz, 1), n, 0.1)
        Q = torch.cat([W[..., m:, m:], QT], dim=1)
        lay.update(Q="full", R="full", S="full")
    else:
        # Q >= 0.5 I, R >= 0.5 I, ||S|| <= 0.4: Q - S'R^-1 S >= 0.18 I in every layout
        Q = spd(g, layout_prefix(lay["Q"], bsz, T + 1), n, 0.5)
        R = spd(g, layout_prefix(lay["R"], bsz, T), m, 0.5)
        S = None
        if lay["S"] != "none":
            S = spectral_scale(randn(g, *layout_prefix(lay["S"], bsz, T), m, n), 0.4)
    if skew:  # only the symmetric parts of Q and R matter
        Q = Q + (lambda X: X - X.mT)(randn(g, *Q.shape))
        R = R + (lambda X: X - X.mT)(randn(g, *R.shape))
    q = None if lay["q"] == "none" else randn(g, *layout_prefix(lay["q"], bsz, T + 1), n)
    r = None if lay["r"] == "none" else randn(g, *layout_prefix(lay["r"], bsz, T), m)
    c = None if lay["c"] == "none" else 0.5 * randn(g, *layout_prefix(lay["c"], bsz, T), n)
    x0 = randn(g, n) if x0_shared else randn(g, bsz, n)
    args = dict(A=A, B=B, Q=Q, R=R, x0=x0, q=q, r=r, S=S, c=c)
    return args, (bsz, T, n, m), lay


@settings(max_examples=30, deadline=None)
@given(lq_problems())
def test_matches_dense_kkt(problem):
    args, (bsz, T, n, m), _lay = problem
    sol = lqr_solve(**args)
    assert sol.x.shape == (bsz, T + 1, n)
    assert sol.u.shape == (bsz, T, m)
    assert sol.lam.shape == (bsz, T + 1, n)
    assert sol.cost.shape == (bsz,)
    assert (sol.status == Status.CONVERGED).all()

    zeros = torch.zeros((), dtype=F64)
    A = full(args["A"], 2, bsz, T)
    B = full(args["B"], 2, bsz, T)
    Q = full(args["Q"], 2, bsz, T + 1)
    R = full(args["R"], 2, bsz, T)
    S = full(args["S"] if args["S"] is not None else zeros.expand(m, n), 2, bsz, T)
    q = full(args["q"] if args["q"] is not None else zeros.expand(n), 1, bsz, T + 1)
    r = full(args["r"] if args["r"] is not None else zeros.expand(m), 1, bsz, T)
    c = full(args["c"] if args["c"] is not None else zeros.expand(n), 1, bsz, T)
    x0 = args["x0"].expand(bsz, n)
    for b in range(bsz):
        x, u, lam, cost = dense_kkt(A[b], B[b], Q[b], R[b], x0[b], q[b], r[b], S[b], c[b])
        assert_rel(sol.x[b], x, 1e-9, "x")
        assert_rel(sol.u[b], u, 1e-9, "u")
        assert_rel(sol.lam[b], lam, 1e-9, "lam")
        assert abs(float(sol.cost[b]) - float(cost)) < 1e-9 * max(1.0, abs(float(cost)))


# ----------------------------------------------------------------------------- 2. Algorithm 1


def sideris_bobrow_algorithm1(A, B, Q, R, xo, uo, x0):
    """Literal transcription of Algorithm 1 (Sideris & Bobrow 2005), one problem, numpy.

    ``A (N,n,n)``, ``B (N,n,m)``, ``Q (N+1,n,n)``, ``R (N,m,m)``, ``xo (N+1,n)``,
    ``uo (N,m)``, ``x0 (n,)``. Returns ``x, u, lam, P, s``.
    """
    N, n = A.shape[0], A.shape[1]
    I_n = np.eye(n)
    P = [None] * (N + 1)
    s = [None] * (N + 1)
    M = [None] * N
    # Step 1: backward, P_N = Q_N, s_N = -Q_N xo_N   (21)
    P[N] = Q[N]
    s[N] = -Q[N] @ xo[N]
    for k in range(N - 1, -1, -1):
        Rinv = np.linalg.inv(R[k])
        M[k] = np.linalg.inv(I_n + B[k] @ Rinv @ B[k].T @ P[k + 1])  # (23)
        P[k] = Q[k] + A[k].T @ P[k + 1] @ M[k] @ A[k]  # (25)
        s[k] = (
            A[k].T @ (I_n - P[k + 1] @ M[k] @ B[k] @ Rinv @ B[k].T) @ s[k + 1]
            + A[k].T @ P[k + 1] @ M[k] @ B[k] @ uo[k]
            - Q[k] @ xo[k]
        )  # (26)
    # Step 2: forward from x(0) = x0
    x = [x0]
    u = []
    lam = [P[0] @ x0 + s[0]]
    for k in range(N):
        Rinv = np.linalg.inv(R[k])
        v = M[k] @ B[k] @ (uo[k] - Rinv @ B[k].T @ s[k + 1])  # (24)
        x.append(M[k] @ A[k] @ x[k] + v)  # (22)
        lam.append(P[k + 1] @ x[k + 1] + s[k + 1])  # (20)
        u.append(uo[k] - Rinv @ B[k].T @ lam[k + 1])  # (17)
    return np.array(x), np.array(u), np.array(lam), np.array(P), np.array(s)


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 5),
    m=st.integers(1, 3),
    T=st.integers(1, 6),
    bsz=st.integers(1, 3),
    seed=st.integers(0, 2**31 - 1),
)
def test_matches_sideris_bobrow_algorithm1(n, m, T, bsz, seed):
    g = torch.Generator().manual_seed(seed)
    A, B = dynamics(g, (bsz, T), n, m)
    Q = spd(g, (bsz, T + 1), n, 0.1)
    R = spd(g, (bsz, T), m, 0.5)
    xo = randn(g, bsz, T + 1, n)
    uo = randn(g, bsz, T, m)
    x0 = randn(g, bsz, n)
    # tracking cost 1/2 (x-xo)'Q(x-xo) + 1/2 (u-uo)'R(u-uo) == lqr_solve form up to a constant
    q = (Q @ xo.unsqueeze(-1)).squeeze(-1).neg()
    r = (R @ uo.unsqueeze(-1)).squeeze(-1).neg()
    sol = lqr_solve(A, B, Q, R, x0, q=q, r=r)
    for b in range(bsz):
        x, u, lam, P, s = sideris_bobrow_algorithm1(
            *(t[b].numpy() for t in (A, B, Q, R, xo, uo, x0))
        )
        assert_rel(sol.x[b], torch.from_numpy(x), 1e-9, "x")
        assert_rel(sol.u[b], torch.from_numpy(u), 1e-9, "u")
        assert_rel(sol.lam[b], torch.from_numpy(lam), 1e-9, "lam")
        assert_rel(sol.V[b], torch.from_numpy(P), 1e-9, "V vs P")
        assert_rel(sol.v[b], torch.from_numpy(s), 1e-9, "v vs s")


# ----------------------------------------------------------------------------- 3. batching


def _compare_with_single_solves(args, sol, bsz, T, n, m, unbatched: bool):
    for i in range(bsz):
        one = lqr_solve(**{k: (v[i] if unbatched else v[i : i + 1]) for k, v in args.items()})
        lead = () if unbatched else (1,)
        assert one.x.shape == (*lead, T + 1, n)
        assert one.u.shape == (*lead, T, m)
        assert one.K.shape == (*lead, T, m, n)
        assert one.lam.shape == (*lead, T + 1, n)
        assert one.cost.shape == lead
        assert one.status.shape == lead
        assert (one.status == Status.CONVERGED).all()
        for name in ("x", "u", "K", "k", "V", "v", "lam", "cost"):
            ref = getattr(one, name).reshape(getattr(sol, name)[i].shape)
            assert_rel(getattr(sol, name)[i], ref, 1e-12, name)


def test_batch_of_64_equals_unbatched_single_solves():
    bsz, T, n, m = 64, 7, 4, 2
    args = random_problem(1234, bsz, T, n, m)
    sol = lqr_solve(**args)
    _compare_with_single_solves(args, sol, bsz, T, n, m, unbatched=True)


def test_batch_of_64_equals_batch1_single_solves():
    bsz, T, n, m = 64, 7, 4, 2
    args = random_problem(1234, bsz, T, n, m)
    sol = lqr_solve(**args)
    assert sol.x.shape == (bsz, T + 1, n) and sol.u.shape == (bsz, T, m)
    _compare_with_single_solves(args, sol, bsz, T, n, m, unbatched=False)


def test_leading_batch_dims_and_shared_x0():
    """Several leading batch dims broadcast; a shared x0 is used by every element."""
    T, n, m = 4, 3, 2
    args = random_problem(7, 6, T, n, m)
    a2 = {k: v.reshape(2, 3, *v.shape[1:]) for k, v in args.items()}
    sol = lqr_solve(**args)
    sol2 = lqr_solve(**a2)
    assert sol2.x.shape == (2, 3, T + 1, n) and sol2.cost.shape == (2, 3)
    assert_rel(sol2.x.reshape(6, T + 1, n), sol.x, 1e-12, "x")
    assert_rel(sol2.u.reshape(6, T, m), sol.u, 1e-12, "u")
    # shared x0 (n,)
    args["x0"] = args["x0"][0]
    sol3 = lqr_solve(**args)
    ref = lqr_solve(**{**args, "x0": args["x0"].expand(6, n).clone()})
    assert_rel(sol3.x, ref.x, 1e-12, "x shared x0")


# ----------------------------------------------------------------------------- 4. float32


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_float32_agrees_with_float64(seed):
    bsz, T, n, m = 8, 10, 4, 2
    a64 = random_problem(seed, bsz, T, n, m)
    a32 = {k: v.float() for k, v in a64.items()}
    s64 = lqr_solve(**a64)
    s32 = lqr_solve(**a32)
    for name in ("x", "u", "lam", "K", "k", "V", "v", "cost"):
        t32 = getattr(s32, name)
        assert t32.dtype == torch.float32, name
        assert_rel(t32, getattr(s64, name), 1e-4, name)
    assert (s32.status == Status.CONVERGED).all()


# ----------------------------------------------------------------------------- 5. validation


def _bad_inputs():
    T, n, m, bsz = 3, 3, 2, 2
    base = random_problem(5, bsz, T, n, m)

    def with_(**kw):
        return {**base, **kw}

    # faults in data shared by the whole batch (no batch dim) are errors; the same
    # faults in one element's data are that element's status (test_per_element_*)
    nan_A = base["A"][1].clone()
    nan_A[2, 0, 1] = float("nan")
    inf_x0 = base["x0"][0].clone()
    inf_x0[1] = float("inf")
    nan_q = base["q"][0].clone()
    nan_q[T, 0] = float("nan")
    inf_S = base["S"][1].clone()
    inf_S[0, 1, 2] = -float("inf")
    nan_R = base["R"][0].clone()
    nan_R[0, 0, 0] = float("nan")
    nan_c = base["c"][1].clone()
    nan_c[1, 1] = float("nan")
    indef_R = base["R"][1].clone()
    indef_R[2] = torch.diag(torch.tensor([1.0, -1.0], dtype=F64))
    singular_R = base["R"][0].clone()
    singular_R[1] = torch.zeros(m, m, dtype=F64)
    return [
        ("B", with_(B=torch.randn(bsz, T, n + 1, m, dtype=F64))),
        ("B", with_(B=torch.randn(bsz, T + 1, n, m, dtype=F64))),
        ("Q", with_(Q=base["Q"][:, :T])),
        ("Q", with_(Q=torch.eye(n + 1, dtype=F64))),
        ("R", with_(R=torch.eye(m + 1, dtype=F64))),
        ("R", with_(R=base["R"][:, :2])),
        ("x0", with_(x0=torch.randn(bsz, n + 1, dtype=F64))),
        ("q", with_(q=base["q"][:, :T])),
        ("r", with_(r=torch.randn(bsz, T, m + 1, dtype=F64))),
        ("S", with_(S=base["S"].mT.contiguous())),
        ("c", with_(c=torch.randn(bsz, T + 1, n, dtype=F64))),
        ("A", with_(A=torch.randn(bsz, T, n, n + 1, dtype=F64))),
        (
            "A",
            dict(
                A=torch.randn(bsz, 0, n, n, dtype=F64),
                B=torch.randn(bsz, 0, n, m, dtype=F64),
                Q=torch.eye(n, dtype=F64),
                R=torch.eye(m, dtype=F64),
                x0=base["x0"],
            ),
        ),
        ("A", with_(A=nan_A)),
        ("x0", with_(x0=inf_x0)),
        ("q", with_(q=nan_q)),
        ("S", with_(S=inf_S)),
        ("R", with_(R=nan_R)),
        ("c", with_(c=nan_c)),
        ("R", with_(R=-torch.eye(m, dtype=F64))),
        ("R", with_(R=indef_R)),
        ("R", with_(R=singular_R)),
    ]


@pytest.mark.parametrize("name,args", _bad_inputs())
def test_bad_input_raises_value_error_naming_argument(name, args):
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        lqr_solve(**args)


def test_batch_mismatch_raises_value_error():
    args = random_problem(5, 2, 3, 3, 2)
    args["x0"] = torch.randn(3, 3, dtype=F64)
    with pytest.raises(ValueError):
        lqr_solve(**args)


# ----------------------------------------------------------------------------- 6. gradcheck

ARG_NAMES = ("A", "B", "Q", "R", "x0", "q", "r", "S", "c")


def _gradcheck(args):
    inputs = tuple(args[k].detach().clone().requires_grad_(True) for k in ARG_NAMES)

    def f(*xs):
        sol = lqr_solve(**dict(zip(ARG_NAMES, xs, strict=True)))
        return sol.x, sol.u, sol.cost

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_gradcheck_all_arguments():
    _gradcheck(random_problem(11, 2, 3, 3, 2))


def test_gradcheck_all_arguments_broadcast_weights():
    """Gradients of shared/broadcast arguments are summed back to their own shapes."""
    T, n, m = 3, 3, 2
    g = torch.Generator().manual_seed(3)
    args = random_problem(12, 2, T, n, m)
    args.update(
        A=args["A"][0],  # (T, n, n) shared
        B=args["B"][:, :1],  # (B, 1, n, m) constant in time
        Q=spd(g, (), n, 0.5),  # (n, n)
        R=spd(g, (1, T), m, 0.5),  # (1, T, m, m)
        q=randn(g, n),  # (n,)
        S=spectral_scale(randn(g, m, n), 0.4),  # (m, n)
        c=randn(g, 1, 1, n),
    )
    _gradcheck(args)


# ----------------------------------------------------------------------------- 7. failures


def test_per_element_not_positive_definite():
    bsz, T, n, m = 4, 5, 3, 2
    bad = 2
    args = random_problem(21, bsz, T, n, m)
    args["B"] = 0.3 * args["B"]
    args["R"] = args["R"].clone()
    args["R"][bad] = -torch.eye(m, dtype=F64)
    # independent check that the last stage's Quu = R + B'Q_T B of element `bad` is indefinite
    Bl, QT = args["B"][bad, T - 1], sym(args["Q"][bad, T])
    assert float(torch.linalg.eigvalsh(args["R"][bad, T - 1] + Bl.T @ QT @ Bl).min()) < 0

    # with validation the element's R (not positive definite) is its status, the
    # batch goes on; without, the kernel's factorisation finds the same element
    checked = lqr_solve(**args)
    sol = lqr_solve(**args, validate=False)
    assert torch.equal(checked.status, sol.status)
    assert sol.status.dtype == torch.int64 and sol.status.shape == (bsz,)
    expected = [Status.NOT_POSITIVE_DEFINITE if i == bad else Status.CONVERGED for i in range(bsz)]
    assert sol.status.tolist() == [int(s) for s in expected]
    assert torchslq.status_names(sol.status)[bad] == "not_positive_definite"
    for i in range(bsz):
        if i == bad:
            continue
        one = lqr_solve(**{k: v[i : i + 1] for k, v in args.items()})
        assert_rel(sol.x[i], one.x[0], 1e-12, "x")
        assert_rel(sol.u[i], one.u[0], 1e-12, "u")
        assert_rel(sol.lam[i], one.lam[0], 1e-12, "lam")
        assert_rel(sol.cost[i], one.cost[0], 1e-12, "cost")


def test_per_element_non_finite():
    """A non-finite initial state flags only its own element (with or without
    validation)."""
    bsz, T, n, m = 3, 4, 3, 2
    args = random_problem(22, bsz, T, n, m)
    args["x0"] = args["x0"].clone()
    args["x0"][0, 1] = float("nan")
    for validate in (True, False):
        sol = lqr_solve(**args, validate=validate)
        expected = [Status.NON_FINITE] + [Status.CONVERGED] * (bsz - 1)
        assert sol.status.tolist() == [int(s) for s in expected]
        ref = lqr_solve(**{k: v[1:] for k, v in args.items()})
        assert_rel(sol.x[1:], ref.x, 1e-12, "x")
        assert_rel(sol.u[1:], ref.u, 1e-12, "u")


# ----------------------------------------------------------------------------- 8. Riccati API


@pytest.mark.parametrize("with_terms", [True, False])
def test_riccati_backward_and_rollout_match_lqr_solve(with_terms):
    bsz, T, n, m = 3, 6, 4, 2
    args = random_problem(31, bsz, T, n, m)
    if not with_terms:
        for k in ("q", "r", "S", "c"):
            args[k] = None
    sol = lqr_solve(**args)
    A, B, Q, R, x0 = (args[k] for k in ("A", "B", "Q", "R", "x0"))
    q, r, S, c = (args[k] for k in ("q", "r", "S", "c"))
    fac = riccati_backward(A, B, Q, R, q, r, S, c)
    assert not fac.failed.any()
    assert fac.K.shape == (bsz, T, m, n) and fac.k.shape == (bsz, T, m)
    assert fac.V.shape == (bsz, T + 1, n, n) and fac.v.shape == (bsz, T + 1, n)
    x, u = rollout_linear(A, B, fac.K, fac.k, x0, c)
    assert_rel(x, sol.x, 1e-12, "x")
    assert_rel(u, sol.u, 1e-12, "u")
    for name in ("K", "k", "V", "v"):
        assert_rel(getattr(fac, name), getattr(sol, name), 1e-12, name)
    # reg = 0 is the unregularised recursion
    fac0 = riccati_backward(A, B, Q, R, q, r, S, c, reg=0.0)
    assert_rel(fac0.Kk, fac.Kk, 1e-12, "Kk reg=0")
    assert_rel(fac0.Vh, fac.Vh, 1e-12, "Vh reg=0")

    # the controls are u_t = K_t x_t + k_t and the costates lam_t = V_t x_t + v_t
    assert_rel(sol.u, (sol.K @ sol.x[:, :T, :, None])[..., 0] + sol.k, 1e-12, "u = Kx + k")
    assert_rel(sol.lam, (sol.V @ sol.x[..., None])[..., 0] + sol.v, 1e-12, "lam = Vx + v")

    # value function: J*(x0) = 1/2 x0'V_0 x0 + v_0'x0 + 1/2 Vh_0[n, n]
    V0, v0 = fac.V[:, 0], fac.v[:, 0]
    quad = 0.5 * torch.einsum("bi,bij,bj->b", x0, V0, x0) + (v0 * x0).sum(-1)
    assert_rel(sol.cost, quad + 0.5 * fac.Vh[:, 0, n, n], 1e-10, "cost vs value fn")
    # ... and without the constant: J*(x0 + d) - J*(x0) = (V_0 x0 + v_0)'d + 1/2 d'V_0 d
    d = torch.randn(bsz, n, dtype=F64, generator=torch.Generator().manual_seed(0))
    sol_d = lqr_solve(**{**args, "x0": x0 + d})
    lam0 = sol.lam[:, 0]
    pred = (lam0 * d).sum(-1) + 0.5 * torch.einsum("bi,bij,bj->b", d, V0, d)
    assert_rel(sol_d.cost - sol.cost, pred, 1e-10, "cost difference")


def test_costate_is_gradient_of_optimal_cost():
    bsz, T, n, m = 3, 5, 3, 2
    args = random_problem(41, bsz, T, n, m)
    x0 = args["x0"].clone().requires_grad_(True)
    sol = lqr_solve(**{**args, "x0": x0})
    (grad,) = torch.autograd.grad(sol.cost.sum(), x0)
    assert_rel(sol.lam[:, 0], grad, 1e-10, "lam_0 vs dJ*/dx0")
    # central finite difference of the optimal cost (exact for a quadratic up to rounding)
    eps = 1e-4
    for i in range(n):
        e = torch.zeros(n, dtype=F64)
        e[i] = eps
        jp = lqr_solve(**{**args, "x0": args["x0"] + e}).cost
        jm = lqr_solve(**{**args, "x0": args["x0"] - e}).cost
        assert_rel((jp - jm) / (2 * eps), sol.lam[:, 0, i], 1e-8, f"fd d{i}")


def _homogeneous_only(monkeypatch):
    """Make ``lqr_solve`` take the homogeneous path (the gain-form kernels off)."""
    import torchslq.lq.solve as solve_mod

    monkeypatch.setattr(solve_mod, "_solve_gain", lambda *a, **k: None)
    monkeypatch.setattr(solve_mod, "gain_addresses", lambda *a, **k: None)


@pytest.mark.parametrize("grad", [False, True])
@pytest.mark.parametrize("shape", ["batched", "shared_data", "mixed", "unbatched", "broadcast"])
def test_gain_form_kernels_equal_the_homogeneous_path_and_dense_kkt(shape, grad, monkeypatch):
    """On the CPU ``lqr_solve`` runs the gain-form kernels straight from the data, with or
    without a graph. Every output equals the homogeneous path's (the kernels switched
    off) and the dense KKT solution; with a graph, the gradients of every input equal
    the homogeneous path's implicit ones (shared data and time-broadcast weights
    included)."""
    import torchslq.lq.solve as solve_mod

    if not solve_mod.compiled_available():
        pytest.skip("numba kernels not importable")
    args = random_problem(seed=21, bsz=3, T=7, n=4, m=2)
    if shape == "shared_data":  # one problem's data for three initial states
        args = {k: (v if k == "x0" else v[:1]) for k, v in args.items()}
    if shape == "mixed":  # some pieces shared by the batch, the others per element
        args = {k: (v[:1] if k in ("B", "R", "q") else v) for k, v in args.items()}
    if shape == "unbatched":
        args = {k: v[0] for k, v in args.items()}
    if shape == "broadcast":  # no batch dim, a time dim of 1, a constant matrix
        args = {**args, "A": args["A"][0], "R": args["R"][:, :1], "Q": args["Q"][0, 0]}
    calls = []
    for kernel in ("lq_gain_solve", "lq_gain_solve_at"):  # (the arrays' or the addresses')
        real = getattr(solve_mod, kernel)
        monkeypatch.setattr(solve_mod, kernel, lambda *a, real=real: calls.append(1) or real(*a))
    g = torch.Generator().manual_seed(3)

    def run(inputs):
        leaves = {k: v.clone().requires_grad_(grad) for k, v in inputs.items()}
        sol = lqr_solve(**leaves)
        if grad:
            wx = torch.randn(sol.x.shape, generator=g, dtype=F64)
            wu = torch.randn(sol.u.shape, generator=g, dtype=F64)
            ((sol.x * wx).sum() + (sol.u * wu).sum() + sol.cost.sum()).backward()
        return sol, {k: v.grad for k, v in leaves.items()}

    fast, fast_grads = run(args)
    assert calls == [1]
    g.manual_seed(3)
    _homogeneous_only(monkeypatch)
    slow, slow_grads = run(args)
    for name in ("x", "u", "K", "k", "V", "v", "lam", "cost"):
        a, b = getattr(fast, name).detach(), getattr(slow, name).detach()
        assert a.shape == b.shape, name
        torch.testing.assert_close(a, b, rtol=1e-11, atol=1e-11, msg=name)
    assert torch.equal(fast.status, slow.status)
    for name, a in fast_grads.items():
        b = slow_grads[name]
        if not grad:
            assert a is None and b is None
            continue
        assert a.shape == args[name].shape, name
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10, msg=f"d/d{name}")
    if shape == "broadcast":
        return
    one = args if shape == "unbatched" else {k: v[0] for k, v in args.items()}
    x, u, lam, cost = dense_kkt(**one)
    first = (lambda t: t) if shape == "unbatched" else (lambda t: t[0])
    torch.testing.assert_close(first(fast.x).detach(), x, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(first(fast.cost).detach(), cost, rtol=1e-9, atol=1e-10)


def test_one_pass_input_arrays_equal_the_general_path():
    """``lqr_solve``'s common call takes its kernels' arrays in one pass
    (``plain_gain_pieces``): for per-element, shared and mixed data they are the general
    path's (``lq_gain_pieces``, ``_gain_inputs``), with the same data batch; any other
    call (a stride-0 or non-contiguous piece, a batch that is neither 1 nor x0's, mixed
    dtypes, x0 not ``(B, n)``) is left to the general path (None)."""
    import torchslq.lq.solve as solve_mod
    from torchslq._backend import dispatch

    if not dispatch.compiled_available():
        pytest.skip("numba kernels not importable")
    args = random_problem(seed=5, bsz=3, T=4, n=3, m=2)
    order = ("A", "B", "Q", "R", "x0", "q", "r", "S", "c")

    def pieces(a):
        return (a["A"], a["B"], a.get("c"), a["Q"], a["R"], a.get("S"), a.get("q"), a.get("r"))

    shared = {k: (v if k == "x0" else v[:1]) for k, v in args.items()}
    mixed = {k: (v[:1] if k in ("A", "S") else v) for k, v in args.items()}
    no_terms = {k: v for k, v in args.items() if k in ("A", "B", "Q", "R", "x0")}
    grad = {k: v.clone().requires_grad_(True) for k, v in args.items()}
    for case in (args, shared, mixed, no_terms, grad):
        got = dispatch.plain_gain_pieces(pieces(case), case["x0"])
        assert got is not None
        batch = torch.Size([3])
        want = solve_mod._gain_inputs(*(case.get(k) for k in order), batch)
        assert got[1] == want[1]  # the data batch: 1 where shared
        np.testing.assert_array_equal(got[2], want[2])
        for a, b in zip(got[0], want[0], strict=True):
            assert a.shape == b.shape and a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    assert dispatch.plain_gain_pieces(pieces(shared), shared["x0"])[1] == 1
    declined = [
        {**args, "Q": args["Q"][:1].expand(3, -1, -1, -1)},  # stride 0
        {**args, "A": args["A"].transpose(-1, -2)},  # not contiguous
        {**args, "B": args["B"][:2]},  # a batch of 2 against 3
        {**args, "r": args["r"].float()},  # another dtype
        {**args, "x0": args["x0"][0]},  # unbatched x0
    ]
    for case in declined:
        assert dispatch.plain_gain_pieces(pieces(case), case["x0"]) is None


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_kernels_reading_the_data_at_their_addresses_equal_the_array_launchers(dtype):
    """A call without a graph passes the tensors' addresses (``gain_addresses``, the
    ``*_at`` kernels) instead of numpy views. For per-element, shared and mixed data, a
    constant weight, a time dim of 1 and absent terms, the solve equals the array
    launcher's (``lq_gain_solve`` on ``_gain_inputs``) bit for bit, and the data check
    equals ``lq_data_clean`` on a NaN in each piece and an ``R`` that is not positive
    definite. A call the addresses cannot describe exactly (a wrong matrix size, a
    stride-0 or transposed piece, a batch that is neither 1 nor x0's, a time dim that is
    neither 1 nor the horizon, another dtype, a piece that requires grad with grad on)
    is left to the array path (None): the kernels read the memory without bounds
    checks."""
    import torchslq.lq.solve as solve_mod
    from torchslq._backend import dispatch

    if not dispatch.compiled_available():
        pytest.skip("numba kernels not importable")
    T, n, m = 5, 3, 2
    args = random_problem(seed=8, bsz=3, T=T, n=n, m=m, dtype=dtype)
    order = ("A", "B", "Q", "R", "x0", "q", "r", "S", "c")

    def pieces(a):
        return (a["A"], a["B"], a.get("c"), a["Q"], a["R"], a.get("S"), a.get("q"), a.get("r"))

    cases = {
        "per element": args,
        "shared": {k: (v if k == "x0" else v[:1]) for k, v in args.items()},
        "mixed": {k: (v[:1] if k in ("A", "S") else v) for k, v in args.items()},
        "constant Q, R of one step, A without batch": {
            **args, "Q": args["Q"][0, 0].contiguous(), "R": args["R"][:, :1].contiguous(),
            "A": args["A"][0],
        },
        "no terms": {k: v for k, v in args.items() if k in ("A", "B", "Q", "R", "x0")},
    }  # fmt: skip
    for name, case in cases.items():
        at = dispatch.gain_addresses(pieces(case), case["x0"], T, n, m)
        assert at is not None, name
        full = {k: case.get(k) for k in order}
        full["Q"] = solve_mod.with_time(full["Q"], 2, T + 1)
        full["R"] = solve_mod.with_time(full["R"], 2, T)
        arrays, data_batch, x0n = solve_mod._gain_inputs(*full.values(), torch.Size([3]))
        assert at[2] == data_batch, name
        got = dispatch.lq_gain_solve_at(at, T)
        want = dispatch.lq_gain_solve(arrays, data_batch, x0n, T)
        assert got.keys() == want.keys()
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=f"{name}: {key}")
        assert dispatch.lq_data_clean_at(at) and dispatch.lq_data_clean(arrays, x0n)
        for k in order:  # a NaN in each piece, then an R that is not PD
            if case.get(k) is None:
                continue
            bad = {**case, k: case[k].clone()}
            bad[k].view(-1)[-1] = float("nan")
            at = dispatch.gain_addresses(pieces(bad), bad["x0"], T, n, m)
            assert not dispatch.lq_data_clean_at(at), f"{name}: NaN in {k}"
        bad = {**case, "R": -case["R"]}
        assert not dispatch.lq_data_clean_at(
            dispatch.gain_addresses(pieces(bad), bad["x0"], T, n, m)
        )
    declined = {
        "a wrong matrix size": {**args, "Q": args["Q"][..., :2, :2].contiguous()},
        "stride 0": {**args, "Q": args["Q"][:1].expand(3, -1, -1, -1)},
        "transposed": {**args, "A": args["A"].transpose(-1, -2)},
        "a batch of 2 against 3": {**args, "B": args["B"][:2]},
        "a time dim of 2": {**args, "r": args["r"][:, :2].contiguous()},
        "another dtype": {**args, "r": args["r"].to(F64 if dtype != F64 else torch.float32)},
        "unbatched x0": {**args, "x0": args["x0"][0]},
        "requires grad": {**args, "c": args["c"].clone().requires_grad_(True)},
    }
    for name, case in declined.items():
        assert dispatch.gain_addresses(pieces(case), case["x0"], T, n, m) is None, name
    with torch.no_grad():  # no graph is recorded: the addresses serve
        case = declined["requires grad"]
        assert dispatch.gain_addresses(pieces(case), case["x0"], T, n, m) is not None
    seen = []

    def under_vmap(A):  # a transform's tensors have no address: declined, not an error
        case = {k: (A[None] if k == "A" else v[:1]) for k, v in args.items()}
        seen.append(dispatch.gain_addresses(pieces(case), case["x0"], T, n, m))
        return A.sum()

    with torch.no_grad():
        torch.func.vmap(under_vmap)(args["A"])
    assert seen == [None]


@pytest.mark.all_sizes
@pytest.mark.parametrize("n, m", [(4, 1), (7, 4), (8, 2)])
def test_size_specialised_gain_kernels_equal_the_general_ones(n, m, monkeypatch):
    """Up to ``FIXED_MAX_N`` states and ``FIXED_MAX_M`` controls the gain-form kernels
    are compiled for the problem's own sizes (``size_witness``); the same problem solved
    by the kernels that read the sizes at run time (the limits set to zero) gives the
    same solution and gradients, and both equal the dense KKT solution."""
    import torchslq.lq.solve as solve_mod
    from torchslq._backend import _numba_kernels as nk

    if not solve_mod.compiled_available():
        pytest.skip("numba kernels not importable")
    fixed = n <= nk.FIXED_MAX_N and m <= nk.FIXED_MAX_M
    assert (len(nk.size_witness(n, m)[0]) == n) == fixed
    args = random_problem(seed=40 + n, bsz=2, T=6, n=n, m=m)
    g = torch.Generator().manual_seed(4)
    wx = torch.randn(2, 7, n, generator=g, dtype=F64)
    wu = torch.randn(2, 6, m, generator=g, dtype=F64)

    def run():
        leaves = {k: v.clone().requires_grad_(True) for k, v in args.items()}
        sol = lqr_solve(**leaves)
        ((sol.x * wx).sum() + (sol.u * wu).sum() + sol.cost.sum()).backward()
        return sol, {k: v.grad for k, v in leaves.items()}

    spec, spec_grads = run()
    monkeypatch.setattr(nk, "FIXED_MAX_N", 0)
    monkeypatch.setattr(nk, "FIXED_MAX_M", 0)
    assert nk.size_witness(n, m) == ((), ())
    gen, gen_grads = run()
    for name in ("x", "u", "K", "k", "V", "v", "lam", "cost"):
        torch.testing.assert_close(
            getattr(spec, name).detach(), getattr(gen, name).detach(), rtol=1e-12, atol=1e-12
        )
    for name, a in spec_grads.items():
        torch.testing.assert_close(a, gen_grads[name], rtol=1e-11, atol=1e-11, msg=name)
    x, u, lam, cost = dense_kkt(**{k: v[1] for k, v in args.items()})
    torch.testing.assert_close(spec.x[1].detach(), x, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(spec.u[1].detach(), u, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(spec.cost[1].detach(), cost, rtol=1e-9, atol=1e-10)


def test_gain_form_gradient_of_a_non_finite_element_is_zero():
    """Without validation, an element whose affine term is NaN solves to a non-finite
    trajectory on the gain-form path: its status is ``non_finite``, its gradients are
    zero, and the other elements' gradients (of per-element and of shared data) are
    those of the batch without it."""
    args = random_problem(seed=5, bsz=3, T=6, n=3, m=2)
    args["Q"] = args["Q"][:1]  # shared by the batch: its gradient sums over elements
    bad = {**args, "c": args["c"].clone()}
    bad["c"][1, 2, 0] = float("nan")

    def grads(inputs, rows):
        leaves = {k: v.clone().requires_grad_(True) for k, v in inputs.items()}
        sol = lqr_solve(**leaves, validate=False)
        ok = torch.zeros(sol.x.shape[0], dtype=torch.bool)
        ok[rows] = True
        loss = sol.x[ok].sum() + sol.u[ok].sum() + sol.cost[ok].sum()
        loss.backward()
        return sol, {k: v.grad for k, v in leaves.items()}

    sol, g = grads(bad, [0, 2])
    assert sol.status.tolist() == [Status.CONVERGED, Status.NON_FINITE, Status.CONVERGED]
    for name in ("A", "B", "c", "x0", "q"):
        assert torch.equal(g[name][1], torch.zeros_like(g[name][1])), name
    keep = {k: (v if k == "Q" else v[[0, 2]]) for k, v in args.items()}
    _, g_ref = grads(keep, [0, 1])
    for name, ref in g_ref.items():
        got = g[name] if name == "Q" else g[name][[0, 2]]
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12, msg=name)


@pytest.mark.all_sizes
def test_limited_specialisations_run_the_general_kernels_with_the_same_results():
    """``limit_specialised_sizes`` keeps size-specialised kernels (fixed trip counts,
    generated passes) for the sizes it names; another size runs the kernels that read
    their sizes at run time: the same solution as with its own kernels, and the dense
    KKT one. Bad pairs are a ValueError naming them; the previous setting comes back."""
    from torchslq._backend import _numba_kernels as nk
    from torchslq._backend import gain_codegen
    from torchslq._backend.specialisation import limit_specialised_sizes

    args = random_problem(seed=12, bsz=3, T=7, n=3, m=1)
    own = lqr_solve(**args)
    old = limit_specialised_sizes([(4, 1)])
    try:
        assert nk.size_witness(3, 1) == ((), ())
        assert gain_codegen.gain_kernels(3, 1) is None
        assert len(nk.size_witness(4, 1)[0]) == 4
        general = lqr_solve(**args)
        with pytest.raises(ValueError, match="pairs"):
            limit_specialised_sizes([(3, 0)])
    finally:
        assert limit_specialised_sizes(old) == frozenset({(4, 1)})
    assert len(nk.size_witness(3, 1)[0]) == 3
    for name in ("x", "u", "lam", "cost"):
        torch.testing.assert_close(
            getattr(general, name), getattr(own, name), rtol=1e-12, atol=1e-12
        )
    for b in range(3):
        x, u, lam, cost = dense_kkt(**{k: v[b] for k, v in args.items()})
        assert_rel(general.x[b], x, 1e-9, "x")
        assert_rel(general.u[b], u, 1e-9, "u")
