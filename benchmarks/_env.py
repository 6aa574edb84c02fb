"""What a benchmark records about the machine it ran on: package versions and the load
average (the machines are shared, so absolute times carry it)."""

from __future__ import annotations

import os


def package_versions(*packages: str) -> dict[str, str]:
    """``{package: version}`` (``"not installed"`` for a missing one)."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for p in packages:
        try:
            out[p] = version(p)
        except PackageNotFoundError:
            out[p] = "not installed"
    return out


def load() -> list[float]:
    """The 1, 5 and 15 minute load averages (empty where the OS has none)."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover
        return []
