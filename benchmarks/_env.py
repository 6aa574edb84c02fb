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


def run_meta(command: str, argv: list[str] | None, load_start: list[float]) -> dict:
    """What a benchmark run records: its command line (``command`` with the arguments it
    was given), date, machine, the load average at its start and end, and the versions
    of torch and numba."""
    import datetime
    import platform
    import sys

    import torch

    given = argv if argv is not None else sys.argv[1:]
    return {
        "command": command + ("" if not given else " " + " ".join(given)),
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": f"{platform.processor() or platform.machine()}, "
        f"{torch.get_num_threads()} thread",
        "load_average": {"start": load_start, "end": load()},
        "versions": package_versions("torch", "numba"),
    }


def write_report(
    out: str,
    stem: str,
    title: str,
    meta: dict,
    rows: list[dict],
    description: str,
    header: list[str],
    cells,
) -> None:
    """``<stem>.json`` (``meta`` and ``rows``) and ``<stem>.md`` in the directory ``out``:
    ``title``, the command in a code block, a line of ``meta`` (date, machine, load,
    versions) followed by ``description``, then a table of ``cells(row)`` (a list of
    strings per row) under ``header``."""
    import json
    from pathlib import Path

    path = Path(out)
    path.mkdir(parents=True, exist_ok=True)
    (path / f"{stem}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    load_avg = meta["load_average"]
    lines = [
        f"# {title}",
        "",
        f"```\n{meta['command']}\n```",
        "",
        f"{meta['date']}, {meta['machine']}, float64; load average at start "
        f"{load_avg['start']}, at end {load_avg['end']}; {meta['versions']}. " + description,
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]
    lines += ["| " + " | ".join(cells(r)) + " |" for r in rows]
    (path / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {path / (stem + '.json')} and {path / (stem + '.md')}")
