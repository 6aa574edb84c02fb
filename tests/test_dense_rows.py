"""The products and tanh of a learned model's derivatives over many rows
(torchslq._backend.dense_rows) against torch's ops, where each way is taken, and a
learned model's graph Jacobians and Hessians through them against torch.func."""

from __future__ import annotations

import pytest
import torch
from test_graph_jacobian import data, reference
from torch import nn
from torch.func import hessian, vmap

import torchslq as ts
from torchslq._backend import dense_rows
from torchslq.dynamics import graph_jacobian as gj

F64 = torch.float64


@pytest.fixture(params=[True, False], ids=["numba-product", "torch-product"])
def forced(request):
    old = dense_rows.set_forced(request.param)
    yield request.param
    dense_rows.set_forced(old)


def _randn(*shape, dtype=F64, seed=0):
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)


@pytest.mark.parametrize("rows", [3, 600, 1601])  # below MIN_WORK, above, odd
@pytest.mark.parametrize("k, c", [(64, 64), (5, 64), (64, 4), (13, 10)])
def test_products_equal_torch(forced, rows, k, c):
    a, b = _randn(rows, k), _randn(k, c, seed=1)
    W, bias = _randn(c, k, seed=2), _randn(c, seed=3)
    torch.testing.assert_close(dense_rows.matmul(a, b), a @ b, rtol=1e-13, atol=1e-13)
    want = torch.nn.functional.linear(a, W, bias)
    torch.testing.assert_close(dense_rows.linear(a, W, bias), want, rtol=1e-13, atol=1e-13)
    want = torch.nn.functional.linear(a, W)
    torch.testing.assert_close(dense_rows.linear(a, W, None), want, rtol=1e-13, atol=1e-13)
    # a strided input (a column slice) and a transposed right factor
    wide = _randn(rows, k + 3, seed=4)
    got = dense_rows.matmul(wide[:, 1 : k + 1], _randn(c, k, seed=5).T)
    torch.testing.assert_close(got, wide[:, 1 : k + 1] @ _randn(c, k, seed=5).T)


def test_what_keeps_torch_ops(forced):
    """float32, tensors that need a graph: torch's ops, bit for bit and differentiable."""
    a, b = _randn(800, 64, dtype=torch.float32), _randn(64, 64, dtype=torch.float32)
    assert torch.equal(dense_rows.matmul(a, b), a @ b)
    assert torch.equal(dense_rows.tanh(a), torch.tanh(a))
    a64 = _randn(800, 64).requires_grad_()
    out = dense_rows.matmul(a64, _randn(64, 64, seed=1))
    assert out.grad_fn is not None
    assert dense_rows.tanh(a64).grad_fn is not None


def test_tanh_equals_torch():
    a = torch.cat([3.0 * _randn(40_000), torch.logspace(-300, 1.5, 2000, dtype=F64)])
    edges = torch.tensor([0.0, -0.0, 30.0, float("inf"), -float("inf"), 0.25], dtype=F64)
    a = torch.cat([a, -a, edges]).view(-1, 2)
    got, want = dense_rows.tanh(a), torch.tanh(a)
    ulp = torch.finfo(F64).eps * want.abs().clamp_min(1e-300)
    assert float(((got - want).abs() / ulp).max()) <= 4.0
    assert torch.equal(torch.signbit(got), torch.signbit(want))  # -0 stays -0
    assert torch.isnan(dense_rows.tanh(torch.full((64, 1024), float("nan"), dtype=F64))).all()


class Residual(ts.Dynamics):
    """``x + net([x, u])``, a 6-64-64-4 tanh network (64-wide: the rows' products are
    large enough for the numba product)."""

    state_dim, control_dim = 4, 2

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.net = nn.Sequential(
            nn.Linear(6, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, 4)
        ).to(F64)  # fmt: skip

    def forward(self, x, u):
        return x + self.net(torch.cat([x, u], -1))


def test_graph_derivatives_through_it_equal_torch_func(forced):
    model = Residual()
    x, u = data(lead=(16, 50), m=2, scale=1.0)
    A, B = gj.graph_jacobians(model, x, u)
    Ar, Br = reference(model, x, u)
    torch.testing.assert_close(A, Ar, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(B, Br, rtol=1e-12, atol=1e-12)
    got = gj.graph_hessians(model, x[:4], u[:4])
    assert got is not None

    def one(z):
        return model(z[:4].unsqueeze(0), z[4:].unsqueeze(0)).squeeze(0)

    H = vmap(hessian(one))(torch.cat([x[:4], u[:4]], -1).reshape(-1, 6))  # (r, n, k, k)
    H = H.reshape(4, 50, 4, 6, 6).movedim(2, 0)
    Hxx, Huu, Hux = got[2]
    torch.testing.assert_close(Hxx, H[..., :4, :4], rtol=1e-11, atol=1e-11)
    torch.testing.assert_close(Huu, H[..., 4:, 4:], rtol=1e-11, atol=1e-11)
    torch.testing.assert_close(Hux, H[..., 4:, :4], rtol=1e-11, atol=1e-11)


def test_split_over_threads_equals_torch(forced):
    """Rows split over two threads (``_backend.dispatch._launch``): the same results."""
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        a, b = _randn(3001, 64), _randn(64, 64, seed=1)
        torch.testing.assert_close(dense_rows.matmul(a, b), a @ b, rtol=1e-13, atol=1e-13)
        torch.testing.assert_close(dense_rows.tanh(a), torch.tanh(a), rtol=1e-15, atol=0.0)
    finally:
        torch.set_num_threads(old)


def test_importing_the_package_does_not_import_numba():
    """The kernels' module is imported on first use (numba's import is about half a
    second of a fresh process's start)."""
    import subprocess
    import sys

    code = "import sys, torchslq; sys.exit('numba' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0
