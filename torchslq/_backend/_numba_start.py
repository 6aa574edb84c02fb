"""numba's start-up in a process, without importing SciPy's linear algebra.

The first compiled call in a process loads numba's CPU target, which imports
``numba.np.arraymath``; at import that module asks whether a BLAS is available (only to
choose how ``np.correlate`` and ``np.convolve`` are compiled) by importing
``scipy.linalg.cython_blas``, i.e. all of ``scipy.linalg``: measured 0.15 s of the
0.85 s numba takes to start here, where a first small solve takes about 1 s in all.
torchslq's kernels call no BLAS. :func:`prepare` imports ``numba.np.arraymath`` once,
before numba's target does, with that question answered from the installed packages
(SciPy findable) instead of importing them; numba's own check still runs, with its
import, where a compiled function first uses BLAS or LAPACK (``np.dot``,
``np.linalg``), as before.

Called before torchslq first imports numba in a process: by :mod:`._numba_cache`
(imported by every kernel module first) and by
:func:`.source_modules.import_source` (the generated modules).
"""

from __future__ import annotations

import importlib.util
import sys

_prepared = False


def _scipy_findable() -> None:
    """numba's ``ensure_blas`` for the import of ``numba.np.arraymath``: ImportError
    where SciPy is not installed (what the import would raise), nothing otherwise."""
    if importlib.util.find_spec("scipy") is None:
        raise ImportError("scipy 0.16+ is required for linear algebra")


def prepare() -> None:
    """Import ``numba.np.arraymath`` with its BLAS question answered without importing
    SciPy (once per process; nothing where it is imported already)."""
    global _prepared
    if _prepared:
        return
    _prepared = True
    if "numba.np.arraymath" in sys.modules:
        return
    import numba.np.linalg as linalg

    real = linalg.ensure_blas
    linalg.ensure_blas = _scipy_findable
    try:
        import numba.np.arraymath  # noqa: F401 (its BLAS check runs here)
    finally:
        linalg.ensure_blas = real
