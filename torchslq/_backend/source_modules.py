"""Generated source files as modules: written atomically, imported by path once per
process (:mod:`torchslq.dynamics.codegen`'s model modules, :mod:`.gain_codegen`'s LQ
passes)."""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType


def cache_root() -> Path:
    """torchslq's cache directory: ``TORCHSLQ_CACHE_DIR``, by default
    ``~/.cache/torchslq`` (generated modules that cannot be written beside the package)."""
    root = os.environ.get("TORCHSLQ_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "torchslq"


def write_atomic(path: Path, text: str) -> None:
    """``text`` into ``path`` through a temporary file and a rename: a concurrent
    process sees all of it or nothing (OSError where the directory is not writable)."""
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def import_source(
    path: Path, name: str, check: Callable[[ModuleType], None] | None = None
) -> ModuleType:
    """The module in ``path`` under ``name`` (``sys.modules[name]`` where already
    imported), compiled from the file's text, not through a ``.pyc``: a file rewritten
    within the same second at the same size would pass the ``.pyc``'s timestamp check.
    ``check(module)`` may raise; then, as for an error in the file, nothing stays in
    ``sys.modules``."""
    if name in sys.modules:
        return sys.modules[name]
    from ._numba_start import prepare

    prepare()  # the generated modules import numba (see _numba_start)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        exec(compile(path.read_text(), str(path), "exec"), module.__dict__)
        if check is not None:
            check(module)
    except Exception:
        del sys.modules[name]
        raise
    return module
