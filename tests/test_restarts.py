"""``riccati_backward(..., restarts=...)``: the same restarts of failed elements on both
backends (the compiled CPU kernel and the torch path), and equal to a sequential
reference that repeats each element's pass alone with a growing ``mu``.

The problems make some elements need restarts: the second control does not act on the
state (its column of ``B``, row of ``S`` and of the hook's Hessians are zero), so its
entry of ``Quu`` is exactly ``R[1, 1] = s_b`` and ``Quu + mu I`` factorises iff
``mu > -s_b``; the ``s_b`` sit far from the schedule's values of ``mu``.
"""

from __future__ import annotations

import math

import pytest
import torch
from lq_hooks import HessianHook, PlainHook

from torchslq.lq import RegularizationSchedule, Restarts, riccati_backward, set_compiled
from torchslq.lq import riccati as riccati_mod

F64 = torch.float64
pytestmark = pytest.mark.skipif(
    not __import__("torchslq").lq.compiled_available(), reason="numba kernels not available"
)

# s_b = R[1, 1] per element; comments: what the schedule does (mu from 0: 1e-6, 4e-6,
# 3.2e-5, 5.1e-4, 1.6e-2, 1.05, 134, 3.4e4)
S_DIAG = [
    1.0,  # 0: no restart
    -2e-6,  # 1: two restarts (mu = 4e-6)
    -0.3,  # 2: six restarts (mu = 1.05)
    -100.0,  # 3: seven restarts (mu = 134)
    -1e4,  # 4: eight restarts, the last succeeds (mu = 3.4e4)
    -1e6,  # 5: fails after eight restarts
    -1.0,  # 6: not allowed to restart: fails
    -1e11,  # 7: starts at mu = 3e9: one restart to 6e9, one to 2.4e10 > reg_max, fails
    0.5,  # 8: starts at mu = 0.2, delta = 0.25: no restart
    1.0,  # 9: a non-finite q: non-finite gains, restarted eight times, fails
]
MU0 = [0.0] * 7 + [3e9, 0.2, 0.0]
DELTA0 = [1.0] * 8 + [0.25, 1.0]
NOT_ALLOWED = 6
NONFINITE = 9


def _problem(dtype=F64, T=6, n=3, seed=0, hook=False, bounds=False):
    Bsz, m = len(S_DIAG), 2
    g = torch.Generator().manual_seed(seed)

    def rnd(*shape):
        return torch.randn(*shape, generator=g, dtype=F64)

    A = torch.eye(n, dtype=F64) + 0.1 * rnd(Bsz, T, n, n)
    Bm = 0.3 * rnd(Bsz, T, n, m)
    Bm[..., 1] = 0.0
    G = rnd(Bsz, T + 1, n, n)
    Q = G @ G.mT / n + 0.1 * torch.eye(n, dtype=F64)
    R = torch.eye(m, dtype=F64).repeat(Bsz, T, 1, 1)
    R[..., 1, 1] = torch.tensor(S_DIAG, dtype=F64)[:, None]
    S = 0.1 * rnd(Bsz, T, m, n)
    S[..., 1, :] = 0.0
    q = rnd(Bsz, T + 1, n)
    r = rnd(Bsz, T, m)
    q[NONFINITE, 2, 0] = float("inf")
    data = [t.to(dtype) for t in (A, Bm, Q, R, q, r, S)]
    kw = {}
    if hook:
        Hxx, Huu, Hux = (
            0.05 * rnd(n, Bsz, T, n, n),
            0.05 * rnd(n, Bsz, T, m, m),
            0.05 * rnd(n, Bsz, T, m, n),
        )
        Hxx, Huu = Hxx + Hxx.mT, Huu + Huu.mT
        Huu[..., 1, :] = 0.0
        Huu[..., :, 1] = 0.0
        Hux[..., 1, :] = 0.0
        kw["stage_hook"] = HessianHook(*(h.to(dtype) for h in (Hxx, Huu, Hux)))
    if bounds:
        lower = -0.5 - torch.rand(Bsz, T, m, generator=g, dtype=F64)
        upper = 0.5 + torch.rand(Bsz, T, m, generator=g, dtype=F64)
        upper[0] = float("inf")
        lower[3] = -float("inf")
        kw["u_bounds"] = (lower.to(dtype), upper.to(dtype))
    return data, kw


SCHEDULE = RegularizationSchedule(factor=2.0, reg_min=1e-6, reg_max=1e10, max_restarts=8)


def _restarts(dtype):
    allowed = torch.ones(len(S_DIAG), dtype=torch.bool)
    allowed[NOT_ALLOWED] = False
    return torch.tensor(MU0, dtype=dtype), SCHEDULE.restarts(
        torch.tensor(DELTA0, dtype=dtype), allowed
    )


def _run(compiled: bool, data, kw, dtype=F64, hook=None):
    mu, rs = _restarts(dtype)
    if hook is not None:
        kw = {**kw, "stage_hook": hook}
    old = set_compiled(compiled)
    try:
        return riccati_backward(*data, reg=mu, restarts=rs, **kw)
    finally:
        set_compiled(old)


def _reference(data, kw):
    """Each element alone (the torch path), its pass repeated with the schedule written
    out here: ``delta := max(2, 2 delta)``, ``mu := max(1e-6, mu delta)`` while the pass
    fails (or its gains are not finite), it may restart, ``mu <= 1e10`` and fewer than
    eight restarts were made."""
    out = []
    old = set_compiled(False)
    try:
        for b in range(len(S_DIAG)):
            idx = torch.tensor([b])
            one = [t[b : b + 1] for t in data]
            kwb = {}
            if "stage_hook" in kw:
                kwb["stage_hook"] = kw["stage_hook"].subset(idx)
            if "u_bounds" in kw:
                kwb["u_bounds"] = tuple(x[b : b + 1] for x in kw["u_bounds"])
            mu, delta, n_restarts = MU0[b], DELTA0[b], 0
            while True:
                fac = riccati_backward(*one, reg=torch.tensor([mu], dtype=data[0].dtype), **kwb)
                bad = bool(fac.failed[0]) or not bool(torch.isfinite(fac.Kk).all())
                if not bad or b == NOT_ALLOWED or mu > 1e10 or n_restarts >= 8:
                    break
                delta = max(2.0, 2.0 * delta)
                mu = max(1e-6, mu * delta)
                n_restarts += 1
            out.append((fac, bad, mu, delta))
    finally:
        set_compiled(old)
    return out


def _assert_factors_close(a, b, rows, rtol, atol):
    for name in ("Kk", "Vh", "chol", "dV"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None or y is None:
            assert x is None and y is None, name
            continue
        torch.testing.assert_close(x[rows], y[rows], rtol=rtol, atol=atol, msg=name)
    if a.clamped is not None:
        assert torch.equal(a.clamped[rows], b.clamped[rows])


CASES = [
    pytest.param({}, id="plain"),
    pytest.param({"bounds": True}, id="bounds"),
    pytest.param({"hook": True}, id="hook"),
    pytest.param({"hook": True, "bounds": True}, id="hook-bounds"),
]


@pytest.mark.parametrize("case", CASES)
def test_both_backends_restart_like_the_per_element_reference(case):
    data, kw = _problem(**case)
    ref = _reference(data, kw)
    fast, slow = _run(True, data, kw), _run(False, data, kw)
    ref_failed = torch.tensor([r[1] for r in ref])
    ref_mu = torch.tensor([r[2] for r in ref], dtype=F64)
    ref_delta = torch.tensor([r[3] for r in ref], dtype=F64)
    for fac in (fast, slow):
        assert torch.equal(fac.failed, ref_failed)
        assert torch.equal(fac.reg, ref_mu)  # the same float64 operations: exact
        assert torch.equal(fac.reg_delta, ref_delta)
    # the cases cover what they are meant to
    assert bool(ref_failed[[5, NOT_ALLOWED, 7, NONFINITE]].all())
    if not case:
        assert not bool(ref_failed[[0, 1, 2, 3, 4, 8]].any())
        assert ref_mu[4] > 1e4 and ref_mu[2] > 0.3 and ref_mu[0] == 0.0 and ref_mu[8] == 0.2
    ok = ~ref_failed
    assert int(ok.sum()) >= 3
    _assert_factors_close(fast, slow, ok, 1e-9, 1e-11)
    for b in ok.nonzero().flatten().tolist():
        for name in ("Kk", "Vh", "chol"):
            torch.testing.assert_close(
                getattr(fast, name)[b], getattr(ref[b][0], name)[0], rtol=1e-9, atol=1e-11
            )
        if fast.dV is not None:
            torch.testing.assert_close(fast.dV[b], ref[b][0].dV[0], rtol=1e-9, atol=1e-11)
            assert torch.equal(fast.clamped[b], ref[b][0].clamped[0])


@pytest.mark.parametrize("bounds", [False, True])
def test_a_hook_that_cannot_be_restricted_repeats_the_whole_batch(bounds):
    """A plain callable hook (no ``subset``, no ``hessians``: torch path only): the whole
    batch repeats its pass, with the same result as the compiled kernel's per-element
    restarts with the same term."""
    data, kw = _problem(hook=True, bounds=bounds)
    fast = _run(True, data, kw)
    slow = _run(False, data, kw, hook=PlainHook(kw["stage_hook"]))
    assert torch.equal(fast.failed, slow.failed)
    assert torch.equal(fast.reg, slow.reg) and torch.equal(fast.reg_delta, slow.reg_delta)
    assert bool(fast.failed.any()) and bool((fast.reg > 1.0).any())
    _assert_factors_close(fast, slow, ~fast.failed, 1e-9, 1e-11)


def test_side_by_side_candidates_in_several_rounds(monkeypatch):
    """Fewer candidate rows per pass than restarts needed (several rounds of side-by-side
    candidates): the same result as the kernel's one-at-a-time restarts."""
    data, kw = _problem(hook=True)
    fast = _run(True, data, kw)
    monkeypatch.setattr(riccati_mod, "RETRY_ROWS", 4)
    slow = _run(False, data, kw)
    assert torch.equal(fast.failed, slow.failed)
    assert torch.equal(fast.reg, slow.reg) and torch.equal(fast.reg_delta, slow.reg_delta)
    _assert_factors_close(fast, slow, ~fast.failed, 1e-9, 1e-11)


@pytest.mark.parametrize("bounds", [False, True])
def test_float32_restarts_agree(bounds):
    data, kw = _problem(dtype=torch.float32, bounds=bounds)
    fast = _run(True, data, kw, dtype=torch.float32)
    slow = _run(False, data, kw, dtype=torch.float32)
    assert fast.Kk.dtype == torch.float32 and fast.reg.dtype == torch.float32
    assert torch.equal(fast.failed, slow.failed)
    torch.testing.assert_close(fast.reg, slow.reg, rtol=1e-6, atol=0)
    torch.testing.assert_close(fast.reg_delta, slow.reg_delta, rtol=1e-6, atol=0)
    _assert_factors_close(fast, slow, ~fast.failed, 2e-4, 1e-5)


def test_without_restarts_both_backends_flag_the_same_failures():
    data, kw = _problem(bounds=False)
    mu = torch.tensor(MU0, dtype=F64)
    outs = []
    for compiled in (True, False):
        old = set_compiled(compiled)
        try:
            outs.append(riccati_backward(*data, reg=mu))
        finally:
            set_compiled(old)
    fast, slow = outs
    assert fast.reg is None and slow.reg is None and fast.reg_delta is None
    assert torch.equal(fast.failed, slow.failed)
    assert bool(fast.failed[[1, 2, 3, 4, 5, 6, 7]].all()) and not bool(fast.failed[[0, 8]].any())


def test_scalar_reg_defaults_and_batch_errors():
    """``reg`` may be a float (or None) with restarts; ``delta``/``allowed`` default to
    ones / all; restarts need one batch dim, on both backends alike."""
    data, _ = _problem()
    data[4][NONFINITE] = 0.0  # finite q
    for compiled in (True, False):
        old = set_compiled(compiled)
        try:
            fac = riccati_backward(*data, reg=None, restarts=SCHEDULE.restarts())
            fac2 = riccati_backward(*data, reg=0.0, restarts=Restarts())
            assert torch.equal(fac.reg, fac2.reg) and torch.equal(fac.failed, fac2.failed)
            assert fac.reg.shape == (len(S_DIAG),)
            assert not bool(fac.failed[[0, 1, 2, 3, 4, 6, 8, 9]].any())
            assert bool(fac.failed[[5, 7]].all())
            with pytest.raises(ValueError, match="one batch dim"):
                two = [t.unsqueeze(0).expand(2, *t.shape) for t in data]
                riccati_backward(*two, reg=0.0, restarts=SCHEDULE.restarts())
        finally:
            set_compiled(old)


def test_schedule_increase_and_decrease():
    s = RegularizationSchedule(factor=2.0, reg_min=1e-6, reg_max=1e10)
    mu = torch.tensor([0.0, 1.0, 1e-3], dtype=F64)
    delta = torch.tensor([1.0, 4.0, 0.25], dtype=F64)
    up_mu, up_d = s.increase(mu, delta)
    assert torch.equal(up_d, torch.tensor([2.0, 8.0, 2.0], dtype=F64))
    assert torch.equal(up_mu, torch.tensor([1e-6, 8.0, 2e-3], dtype=F64))
    dn_mu, dn_d = s.decrease(mu, delta)
    assert torch.equal(dn_d, torch.tensor([0.5, 0.5, 0.125], dtype=F64))
    assert torch.equal(dn_mu, torch.tensor([0.0, 0.5, 1.25e-4], dtype=F64))
    tiny_mu, _ = s.decrease(torch.tensor([1.5e-6], dtype=F64), torch.tensor([1.0], dtype=F64))
    assert float(tiny_mu) == 0.0  # below reg_min: 0
    mask = torch.tensor([True, False, True])
    m_mu, m_d = s.increase(mu, delta, mask)
    assert torch.equal(m_mu, torch.where(mask, up_mu, mu)) and torch.equal(m_d[1], delta[1])
    assert RegularizationSchedule(reg_min=0.0).floor == 1e-6
    rs = s.restarts(delta)
    assert rs.schedule.floor == 1e-6 and rs.schedule.reg_max == 1e10 and rs.max_restarts == 8
    with pytest.raises(ValueError):
        RegularizationSchedule(factor=1.0)
    assert math.isclose(s.increase(*s.decrease(mu[1:2], delta[1:2]))[0].item(), 1.0)
