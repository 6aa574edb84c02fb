"""numba's start-up without SciPy's linear algebra (``torchslq._backend._numba_start``):
a first solve on the compiled kernels and generated model code imports no
``scipy.linalg``, numba's BLAS answer is the one its own check gives, and a compiled
function that uses BLAS afterwards still compiles and computes (numba's own check and
import then run)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("numba")
pytest.importorskip("scipy")

ROOT = Path(__file__).resolve().parent.parent

CHILD = textwrap.dedent(
    """
    import importlib.util, json, sys
    import numpy as np
    import torch
    import torchslq as ts

    class UserPendulum(ts.ContinuousDynamics):
        state_dim, control_dim = 2, 1

        def forward(self, x, u, t=None):
            return torch.stack([x[..., 1], -9.81 * torch.sin(x[..., 0]) + u[..., 0]], -1)

    f64 = torch.float64
    dyn = ts.discretize(UserPendulum(), 0.05, "rk4").double()
    cost = ts.QuadraticCost(torch.eye(2, dtype=f64), 0.1 * torch.eye(1, dtype=f64), 10 * torch.eye(2, dtype=f64))
    res = ts.ILQR(max_iter=50, progress=False).solve(ts.Problem(dyn, cost, 20), torch.tensor([[0.5, 0.0]], dtype=f64))
    import numba
    import numba.np.arraymath as am
    from torchslq._backend import dispatch
    out = dict(
        converged=bool(res.converged.all()),
        kernels=dispatch.compiled_available(),
        scipy_linalg_after_solve="scipy.linalg" in sys.modules,
        have_blas=bool(am._HAVE_BLAS),
    )

    @numba.njit
    def dot(a, b):
        return np.dot(a, b)

    a, b = np.arange(6.0).reshape(2, 3), np.arange(12.0).reshape(3, 4)
    out["dot_equal"] = bool(np.array_equal(dot(a, b), a @ b))
    out["scipy_linalg_after_dot"] = "scipy.linalg" in sys.modules
    print(json.dumps(out))
    """
)


def test_first_solve_imports_no_scipy_linalg_and_blas_still_works(tmp_path):
    env = dict(os.environ, TORCHSLQ_CACHE_DIR=str(tmp_path), OMP_NUM_THREADS="1")
    run = subprocess.run(
        [sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, cwd=ROOT
    )
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["converged"] and out["kernels"]
    # numba's own check imports scipy.linalg.cython_blas, which succeeds here (scipy is
    # installed): the answer given without the import is the same
    assert out["have_blas"] is True
    assert out["scipy_linalg_after_solve"] is False
    # BLAS use afterwards: numba's own check runs, with its import
    assert out["dot_equal"] and out["scipy_linalg_after_dot"]


def test_prepare_answers_as_numba_where_scipy_is_missing(monkeypatch):
    """Without SciPy the probe raises numba's ImportError (numba then compiles
    ``np.correlate`` without BLAS, as its own check decides)."""
    import importlib.util

    from torchslq._backend import _numba_start

    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ImportError, match="scipy"):
        _numba_start._scipy_findable()
