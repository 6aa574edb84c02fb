"""Cart-pole swing-up with the continuous-time iLQR (Lieskovský, Bušek & Vyhlídal 2025,
Section V): both variants from the paper's initial state, ours beside the paper's and an
independent optimum, Figures 2 and 3 saved as PNG, the rows as JSON.

    python examples/continuous_ilqr_cartpole.py --rtol 1e-6 --out benchmarks/results

(run from the repository root: the problem definitions live in ``reproductions/``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reproductions import continuous_ilqr as rep  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--variants", nargs="+", default=list(rep.VARIANTS), choices=rep.VARIANTS)
    p.add_argument("--rtol", type=float, default=1e-6, help="integrator rtol (atol = rtol/100)")
    p.add_argument("--max-iter", type=int, default=200)
    p.add_argument("--grids", type=int, nargs="*", default=[2000], help="RK4 grids for ILQR")
    p.add_argument("--out", default="continuous_ilqr_out", help="folder for figures and JSON")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    out = Path(a.out)
    rows, runs = rep.reproduce(
        tuple(a.variants), rtol=a.rtol, grids=tuple(a.grids), max_iter=a.max_iter
    )
    print(rep.format_rows(rows))
    fig = {"convex": 2, "nonconvex": 3}
    for v, run in runs.items():
        tag = f"continuous_ilqr_fig{fig[v]}"
        rep.figure_trajectory(run, out / f"{tag}a.png", f"Fig. {fig[v]}a ({v}): trajectory")
        rep.figure_convergence(run, out / f"{tag}b.png", f"Fig. {fig[v]}b ({v}): convergence")
    cmd = "python " + " ".join([Path(__file__).name, *(argv if argv is not None else sys.argv[1:])])
    (out / "continuous_ilqr_cartpole.json").write_text(
        json.dumps({"command": cmd, "rows": rows}, indent=1)
    )
    (out / "continuous_ilqr_cartpole.md").write_text(
        f"Command: `{cmd}` (1 thread)\n\n" + rep.format_rows(rows) + "\n"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
