"""Sideris & Bobrow (2005), Section 4.1: Table 1 and Figures 1-2 (viscous-drag vehicle).

All five drag coefficients are solved as ONE batch (beta is a per-element parameter),
then each alone to show that batching does not change any number. Our iteration counts
are printed beside the paper's as a markdown table, which is also written to
``benchmarks/results/sideris_table1.md``; the figures go to ``runs/sideris/``.

    python examples/sideris_table1.py                      # Armijo and exact searches
    python examples/sideris_table1.py --line-search armijo --no-one-by-one
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

from reproductions.sideris import TABLE1_BETAS, table1_report  # noqa: E402

NOTES = """\
### Notes

* Problem readings: m = 25.9 g in kilograms (with m = 25.9 the target is never reached);
  eq. 65 has no 1/2, which does not change the minimiser or the SLQ directions).
* The paper's "quadratic fit" line search is not fully specified. `armijo` is
  backtracking from 1 (c1 = 1e-4, halving); `exact` minimises J(U + αŪ) over a grid
  in (0, 1] refined by one quadratic fit. Counts within about ±10
  of Table 1 are a fair reproduction.
* beta = 1: the paper reports no convergence within 300 iterations, and that is
  the expected outcome: explicit Euler of v' = -(β/m) v|v| is unstable for
  |v| > m/(β Ts) = 12.95 m/s, and the optimal speed exceeds that (column `max speed`),
  so the discrete problem is pathological. Our status for beta = 1 is reported as
  observed, not tuned. When it is `line_search_failed` with ‖∇J‖ about 1e-5, the
  iteration has stalled at a rounding floor: there the predicted decrease |∇J·Ū| is a
  few 1e-9 while J ≈ 1e5 and J(U + αŪ) - J(U) is rounding noise of about 1e-9 for
  every α, so no step can be verified and the 1e-6 gradient test is not reachable in
  float64 (the cost itself has settled to about 1e-14 relative).
* Figure 2's modified Newton method is not implemented here; the steepest-descent
  baseline is `torchslq.GradientMethod` (costate gradient, exact search over an
  adaptive step range).
"""


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--line-search", choices=("armijo", "exact", "both"), default="both", help="default both"
    )
    p.add_argument("--betas", type=float, nargs="+", default=list(TABLE1_BETAS))
    p.add_argument("--max-iter", type=int, default=300)
    p.add_argument("--tol", type=float, default=1e-6)
    p.add_argument("--sd-iters", type=int, default=200, help="steepest-descent iterations")
    p.add_argument("--no-one-by-one", action="store_true", help="skip the separate solves")
    p.add_argument("--out", default="runs/sideris", help="figure directory")
    p.add_argument("--results", default="benchmarks/results/sideris_table1.md")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    searches = ("armijo", "exact") if args.line_search == "both" else (args.line_search,)
    command = "python examples/sideris_table1.py " + shlex.join(
        sys.argv[1:] if argv is None else argv
    )
    t0 = time.perf_counter()
    table1_report(
        line_searches=searches,
        betas=args.betas,
        max_iter=args.max_iter,
        tol=args.tol,
        one_by_one=not args.no_one_by_one,
        sd_max_iter=args.sd_iters,
        out_dir=args.out,
        results_path=args.results or None,
        command=command.strip(),
        notes=NOTES,
    )
    print(f"\nwrote {args.results}; total {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
