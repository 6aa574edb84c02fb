"""numba's on-disk cache of the library's kernels is invalidated by a change to any of
them (``torchslq._backend._numba_cache``): numba's own stamp covers a function's own
file only, so a kernel whose callee in another module changed would keep running the
callee's old code."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

numba = pytest.importorskip("numba")

ROOT = Path(__file__).resolve().parent.parent

# a kernel module calling a kernel of another module, both cached, as the library's are
CALLER = """
import numba
from callee import inner

@numba.njit(cache=True)
def outer(x):
    return inner(x) + 1.0
"""
CALLEE = """
import numba

@numba.njit(cache=True)
def inner(x):
    return {value} * x
"""
RUN = """
import importlib
import sys
import types
from pathlib import Path
# (the backend's directory as a package of its own: the module and its helpers, without
# importing torch)
backend = types.ModuleType("backend")
backend.__path__ = [str(Path({root!r}) / "torchslq" / "_backend")]
sys.modules["backend"] = backend
_numba_cache = importlib.import_module("backend._numba_cache")
if {library}:  # the two modules as the library's own files
    _numba_cache._DOMAINS[:] = [Path({tmp!r})]
    _numba_cache._DIGEST_ROOTS[:] = [Path({tmp!r})]
else:
    _numba_cache._DOMAINS[:] = []
sys.path.insert(0, {tmp!r})
import caller
print(caller.outer(1.0))
"""


def _run(tmp: Path, library: bool) -> tuple[float, str]:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp / "cache"), "NUMBA_DEBUG_CACHE": "1"}
    script = RUN.format(root=str(ROOT), tmp=str(tmp), library=library)
    out = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    return float(out.stdout.strip().splitlines()[-1]), out.stdout


@pytest.mark.parametrize("library", [True, False])
def test_a_changed_callee_recompiles_its_cached_caller(tmp_path, library):
    """Two cached kernels in two files, the caller's file unchanged and the callee's
    edited between two processes: as the library's files, the second process runs the
    new callee (the caller's cache entry is discarded), and a third, unchanged, loads
    the caller from the cache again. The same files outside the library show what
    numba does alone: the caller keeps the callee's old code."""
    (tmp_path / "caller.py").write_text(textwrap.dedent(CALLER))
    (tmp_path / "callee.py").write_text(textwrap.dedent(CALLEE).format(value="2.0"))
    first, log = _run(tmp_path, library)
    assert first == 3.0
    assert "data saved" in log
    (tmp_path / "callee.py").write_text(textwrap.dedent(CALLEE).format(value="5.0") + "\n")
    second, _ = _run(tmp_path, library)
    third, log = _run(tmp_path, library)
    if library:
        assert second == 6.0
        assert third == 6.0
        assert "data loaded" in log  # the cache still serves an unchanged library
    else:  # numba#1833: the stale code is run (if numba fixes this, the library's
        # stamp is redundant, not wrong)
        assert second in (3.0, 6.0)


def test_library_kernels_carry_the_library_digest():
    """A library kernel's cache locator is the library's (numba's own stamp and the
    digest of the library's kernel files); a function of another file keeps numba's
    locator. The digest changes with the text of any kernel file."""
    from torchslq._backend import _numba_cache, _numba_gain

    locator = _numba_gain.gain_solve_kernel._cache._impl.locator
    assert isinstance(locator, _numba_cache.LibraryCacheLocator)
    stamp = locator.get_source_stamp()
    assert stamp[1] == _numba_cache.library_digest()
    assert len(stamp[1]) == 64

    @numba.njit(cache=True)
    def elsewhere(x):
        return x

    assert not isinstance(elsewhere._cache._impl.locator, _numba_cache.LibraryCacheLocator)


def test_the_digest_follows_the_kernel_files(tmp_path, monkeypatch):
    """The digest covers the files under its roots that define kernels, by path and
    text: editing one changes it, a file without kernels or a generated module does
    not."""
    from torchslq._backend import _numba_cache

    pkg = tmp_path / "pkg"
    (pkg / "_generated").mkdir(parents=True)
    (pkg / "kernels.py").write_text("import numba\nf = numba.njit(lambda x: x)\n")
    (pkg / "plain.py").write_text("import numba\nx = 1\n")
    (pkg / "_generated" / "m.py").write_text("import numba\nf = numba.njit(lambda x: x)\n")
    monkeypatch.setattr(_numba_cache, "_DIGEST_ROOTS", [pkg])

    def digest() -> str:
        monkeypatch.setattr(_numba_cache, "_digest", None)
        return _numba_cache.library_digest()

    base = digest()
    (pkg / "plain.py").write_text("import numba\nx = 2\n")
    (pkg / "_generated" / "m.py").write_text("import numba\nf = numba.njit(lambda x: 2 * x)\n")
    assert digest() == base
    (pkg / "kernels.py").write_text("import numba\nf = numba.njit(lambda x: 2 * x)\n")
    assert digest() != base
