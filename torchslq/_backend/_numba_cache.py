"""numba's on-disk cache of the library's kernels, invalidated by any change to them.

numba keys a cached function by its own source file only (its modification time and
size): a kernel that calls a kernel of another module keeps its cached machine code
when only the callee changes (numba/numba#1833), and so do constants read from other
modules. After an upgrade that leaves the old ``__pycache__`` in place, or a change to
the library's source, a kernel could then run its previous version's code without a
warning.

This module puts a locator in front of numba's own (:data:`CacheImpl._locator_classes`)
for the functions of the library's files and of its generated modules: it caches where
numba's own locator would, and its source stamp is numba's stamp together with a digest
of the text of every library file that defines kernels (:func:`library_digest`). Any change to those files discards every index written
before it (numba compiles the kernels again, once); functions outside the library are
left to numba's locators.

Imported by every module that defines kernels, before its first kernel.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from ._numba_start import prepare

prepare()  # (before numba's target loads: see _numba_start)

from numba.core import caching  # noqa: E402

from .source_modules import cache_root  # noqa: E402

_PACKAGE = Path(__file__).resolve().parent.parent  # torchslq/
# the directories whose files' functions get the library's stamp: the package, and
# where generated modules are written (dynamics.codegen._cache_dir, gain_codegen)
_DOMAINS: list[Path] = [_PACKAGE]
# the files whose text makes the digest: every library file that defines kernels, under
# these directories (the generated modules' own text is numba's own stamp)
_DIGEST_ROOTS: list[Path] = [_PACKAGE / "_backend", _PACKAGE / "dynamics"]
_digest: str | None = None


def library_digest() -> str:
    """SHA-256 of the text of every ``.py`` file under :data:`_DIGEST_ROOTS` (generated
    modules excepted) that defines kernels (``njit`` or ``@intrinsic`` in its text:
    the kernel modules and the code generators' templates), in sorted path order
    (computed once per process: about 0.4 MB)."""
    global _digest
    if _digest is None:
        h = hashlib.sha256()
        for root in _DIGEST_ROOTS:
            for path in sorted(root.rglob("*.py")):
                if "_generated" in path.parts or "__pycache__" in path.parts:
                    continue
                text = path.read_bytes()
                if b"njit" in text or b"@intrinsic" in text:
                    h.update(str(path.relative_to(root.parent)).encode() + b"\0" + text)
        _digest = h.hexdigest()
    return _digest


def _in_library(py_file: str) -> bool:
    path = Path(py_file).resolve()
    return any(path.is_relative_to(d) for d in (*_DOMAINS, cache_root().resolve()))


class LibraryCacheLocator(caching._CacheLocator):
    """numba's own locator for the file (the first of its locators that takes it), with
    :func:`library_digest` added to its source stamp."""

    def __init__(self, inner: caching._CacheLocator) -> None:
        self._inner = inner

    def ensure_cache_path(self) -> None:
        self._inner.ensure_cache_path()

    def get_cache_path(self) -> str:
        return self._inner.get_cache_path()

    def get_source_stamp(self):
        return (self._inner.get_source_stamp(), library_digest())

    def get_disambiguator(self) -> str:
        return self._inner.get_disambiguator()

    @classmethod
    def from_function(cls, py_func, py_file):
        if not _in_library(py_file):
            return None
        for inner_cls in caching.CacheImpl._locator_classes:
            if inner_cls is cls:
                continue
            inner = inner_cls.from_function(py_func, py_file)
            if inner is not None:
                return cls(inner)
        return None


def install() -> None:
    """Put :class:`LibraryCacheLocator` first among numba's locators (once; where a
    numba release has no such list, its own locators are left as they are)."""
    classes = getattr(getattr(caching, "CacheImpl", None), "_locator_classes", None)
    if isinstance(classes, list) and LibraryCacheLocator not in classes:
        classes.insert(0, LibraryCacheLocator)


install()
