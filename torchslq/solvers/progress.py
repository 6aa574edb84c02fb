"""Progress bar shared by the solvers: tqdm, shown only for solves longer than a second."""

from __future__ import annotations

from tqdm.auto import tqdm

__all__ = ["progress_bar"]


def progress_bar(total: int, enabled: bool = True, desc: str = "") -> tqdm:
    """A tqdm bar that stays hidden for the first second (``delay=1``)."""
    return tqdm(total=total, desc=desc, delay=1.0, disable=not enabled, leave=False, unit="it")
