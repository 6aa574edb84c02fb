"""Progress bar shared by the solvers: tqdm, shown only for solves longer than a second."""

from __future__ import annotations

from tqdm.auto import tqdm

__all__ = ["progress_bar"]


def progress_bar(total: int, enabled: bool = True, desc: str = "") -> tqdm:
    """A tqdm bar that stays hidden for the first second (``delay=1``) and when the output
    is not a terminal (``disable=None``: no carriage-return spam in logs and CI)."""
    return tqdm(
        total=total, desc=desc, delay=1.0, disable=None if enabled else True, leave=False, unit="it"
    )
