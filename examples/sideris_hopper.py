"""Sideris & Bobrow (2005), Section 4.2: the gas-actuated hopper (eq. 66, Figure 3).

The target heights y° = 1, 20, 50 are solved as ONE batch (a per-element terminal
reference), then each alone. Our iteration counts are printed beside the paper's (3 for
y° = 1, 166 for y° = 50, none stated for the y° = 20 of Figure 3) and written to
``benchmarks/results/sideris_hopper.md``; Figure 3 goes to ``runs/sideris/``.

    python examples/sideris_hopper.py                      # Armijo and exact searches
    python examples/sideris_hopper.py --line-search exact --max-iter 300
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import torch

# the paper reproductions live in the checkout's reproductions/, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reproductions.sideris import HOPPER_TARGETS, hopper_report  # noqa: E402

NOTES = """\
### Notes

* Eq. (66) is garbled in the paper; this is its literal reading
  (qfin multiplies only the height error, ẏ(N)^2 has weight 1).
* The problem is non-convex (contact switching) and only C^1 (the smoothed spring has a
  jump in its second derivative at e = 0 and e = α), so different line searches can end
  in different local optima and the Gauss-Newton model is poor near the kinks.
* The paper's counts (3 for y° = 1, 166 for y° = 50) were not reproduced by
  independent attempts under any reading or line search (about 100-140 iterations for
  y° = 1; y° = 50 did not meet a 1e-6 gradient test in 1000). Our counts are reported
  as observed; y° = 20 is the case where independent methods agree on the optimum.
* When y° = 50 ends as `stalled` (or, with ``stall_iters=0``, as `line_search_failed`
  some 10-60 iterations later at the same cost) with ‖∇J‖ of 1e-5 to 1e-4, the iteration
  has stalled: the predicted decrease |∇J·Ū| is about 1e-11, the full SLQ step raises J by
  about 1e-9 (J grows like α² along Ū: the Gauss-Newton model misses the curvature from
  the spring's kinks, where a trajectory point sits), and the decrease left for small α
  is at the rounding level of J (eps·J ≈ 1.4e-13). The two line searches also end in
  different local optima (different costs and ẏ(N)).
"""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--line-search", choices=("armijo", "exact", "both"), default="both", help="default both"
    )
    p.add_argument("--targets", type=float, nargs="+", default=list(HOPPER_TARGETS))
    p.add_argument("--max-iter", type=int, default=1000)
    p.add_argument("--tol", type=float, default=1e-6)
    p.add_argument("--no-one-by-one", action="store_true", help="skip the separate solves")
    p.add_argument("--out", default="runs/sideris", help="figure directory")
    p.add_argument("--results", default="benchmarks/results/sideris_hopper.md")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    searches = ("armijo", "exact") if args.line_search == "both" else (args.line_search,)
    command = "python examples/sideris_hopper.py " + shlex.join(
        sys.argv[1:] if argv is None else argv
    )
    t0 = time.perf_counter()
    hopper_report(
        line_searches=searches,
        y_targets=args.targets,
        max_iter=args.max_iter,
        tol=args.tol,
        one_by_one=not args.no_one_by_one,
        out_dir=args.out,
        results_path=args.results or None,
        command=command.strip(),
        notes=NOTES,
    )
    print(f"\nwrote {args.results}; total {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
