"""A learned model's derivatives: generated code, its traced graph and autograd's passes.

Not part of the test suite. Run from the repo root::

    .venv/bin/python benchmarks/learned_derivatives.py            # -> benchmarks/results
    .venv/bin/python benchmarks/learned_derivatives.py --quick    # fewer rows and rounds

Two models (``--models``): ``learned``, ``benchmarks/user_models.py``'s learned model (the
user's cart-pole RK4 step, generated code, plus a 5-64-64-4 tanh residual MLP), and
``features``, a fully learned cart-pole step on features of the state
(:class:`FeatureCartPole`: slices of the state, ``sin`` and ``cos`` of the angle, a
6-64-64-4 tanh MLP; on autograd before the graph path took slices and ``sin``/``cos``),
and ``graybox``, the cart-pole's equations written inline in torch ops (entries of the
state, ``sin``/``cos``, quotients by the state-dependent denominator, ``torch.stack``)
in one RK4 step plus a 5-64-64-4 tanh residual MLP (:class:`GrayBoxCartPole`). Its
131 elementwise nodes are more than the graph path takes
(``graph_jacobian.MAX_ELEMENTWISE``: swept by the graph it ran 0.62x autograd's
Jacobians and 0.46x its Hessians at 3,200 rows), so its graph and autograd columns are
both autograd's pass (the rows check that the choice costs nothing), while the generated
sweep writes its physics as straight-line code.
float64, one thread. For each
number of rows ``B x 50`` (random states and controls), the ways alternate in one
process, ``--rounds`` times, and the minimum is reported:

* ``jacobians``: :func:`torchslq.linearize` (the generated reverse sweep beside the
  model's compiled step, ``torchslq/dynamics/network_reverse.py``) against the same call
  with that off (the graph path, ``torchslq/dynamics/graph_jacobian.py``) and with the
  graph path off too (autograd through one call of the model, its step standing in by
  its kernels);
* ``hessians``: :func:`torchslq.dynamics.linearize_with_hessians` and its Hessians (DDP's
  value mode) the same three ways (the generated forward tangents and second-order
  terms).

A graph of more elementwise nodes than ``network_codegen.MAX_DERIVATIVE_NODES`` has no
generated derivatives (``graybox``: 131): its generated column is then the next way's
pass.

Every call runs inside a solve's scope (``torchslq._pinned.solve_scope``: the model's
compiled functions looked up once, as in a solve). The largest difference between the
ways' results is printed beside the times.
Results go to ``--out`` (``learned_derivatives.{json,md}``).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from pathlib import Path

import torch
from torch import nn

from torchslq._pinned import solve_scope
from torchslq.dynamics import network_codegen

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _env import load, run_meta, write_report  # noqa: E402
from user_models import LearnedCartPole  # noqa: E402

import torchslq as ts  # noqa: E402

linearize_module = importlib.import_module("torchslq.dynamics.linearize")
COMMAND = "python benchmarks/learned_derivatives.py"


def tanh_mlp(inputs: int, seed: int) -> nn.Sequential:
    """An ``inputs``-64-64-4 tanh MLP in float64, initialised after ``manual_seed(seed)``."""
    torch.manual_seed(seed)
    return nn.Sequential(
        nn.Linear(inputs, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, 4)
    ).double()


class FeatureCartPole(ts.Dynamics):
    """A fully learned cart-pole step on features of the state, as such models are often
    written: ``x + 0.05 net([s, sin th, cos th, s_dot, th_dot, u])``, ``net`` a 6-64-64-4
    tanh MLP (seed 2)."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.net = tanh_mlp(6, seed=2)

    def forward(self, x, u):
        th = x[..., 1:2]
        z = torch.cat([x[..., :1], torch.sin(th), torch.cos(th), x[..., 2:], u], -1)
        return x + 0.05 * self.net(z)


class GrayBoxCartPole(ts.Dynamics):
    """The cart-pole's equations (mc = 1, mp = 0.1, l = 0.5) written inline in torch ops,
    one RK4 step of dt = 0.05, plus a 5-64-64-4 tanh residual MLP (seed 3)."""

    state_dim, control_dim = 4, 1

    def __init__(self):
        super().__init__()
        self.net = tanh_mlp(5, seed=3)

    @staticmethod
    def rhs(x, f):
        th, sd, thd = x[..., 1], x[..., 2], x[..., 3]
        s, c = torch.sin(th), torch.cos(th)
        D = 1.0 + 0.1 * s * s
        sdd = (f + 0.1 * s * (0.5 * thd * thd + 9.81 * c)) / D
        thdd = (-f * c - 0.05 * thd * thd * c * s - 1.1 * 9.81 * s) / (0.5 * D)
        return torch.stack([sd, thd, sdd, thdd], -1)

    def forward(self, x, u):
        f, dt = u[..., 0], 0.05
        k1 = self.rhs(x, f)
        k2 = self.rhs(x + 0.5 * dt * k1, f)
        k3 = self.rhs(x + 0.5 * dt * k2, f)
        k4 = self.rhs(x + dt * k3, f)
        step = x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return step + 1e-3 * self.net(torch.cat([x, u], -1))


MODELS = {"learned": LearnedCartPole, "features": FeatureCartPole, "graybox": GrayBoxCartPole}


def _jacobians(model, x, u):
    return linearize_module.linearize(model, x, u)


def _hessians(model, x, u):
    A, B, hessians = linearize_module.linearize_with_hessians(model, x, u)
    return (A, B, *hessians())


def _none(*args):
    return None


# pass -> way -> the functions switched off: (module, attribute)
_GENERATED = (network_codegen, "network_jacobians")
_GENERATED_HESSIANS = (network_codegen, "network_hessians")
PASSES = {
    "jacobians": (
        _jacobians,
        {
            "generated": (),
            "graph": (_GENERATED,),
            "autograd": (_GENERATED, (linearize_module, "graph_jacobians")),
        },
    ),
    "hessians": (
        _hessians,
        {
            "generated": (),
            "graph": (_GENERATED_HESSIANS,),
            "autograd": (_GENERATED_HESSIANS, (linearize_module, "graph_hessians")),
        },
    ),
}


def _time(fn, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def measure(name: str, kind: str, batch: int, rounds: int) -> dict:
    """Minimum times (ms) of the pass's ways, alternating; ratios to the first way."""
    fn, ways = PASSES[kind]
    model = MODELS[name]()
    g = torch.Generator().manual_seed(batch)
    x = torch.randn(batch, 50, 4, generator=g, dtype=torch.float64)
    u = torch.randn(batch, 50, 1, generator=g, dtype=torch.float64)
    reals = {sw: getattr(*sw) for off in ways.values() for sw in off}
    times = {k: float("inf") for k in ways}
    outs = {}
    try:
        for _ in range(rounds):
            for way, off in ways.items():
                for sw, real in reals.items():
                    setattr(*sw, _none if sw in off else real)
                with solve_scope():
                    outs[way] = fn(model, x, u)  # (a warm-up in the first round)
                    times[way] = min(times[way], _time(lambda: fn(model, x, u)) * 1e3)
    finally:
        for sw, real in reals.items():
            setattr(*sw, real)
    first = next(iter(ways))
    row = {"model": name, "pass": kind, "rows": batch * 50}
    row |= {f"{way}_ms": round(t, 3) for way, t in times.items()}
    row |= {
        f"{way} / {first}": round(t / times[first], 2) for way, t in times.items() if way != first
    }
    row["max_abs_diff"] = max(
        float((a - b).abs().max())
        for way in ways
        for a, b in zip(outs[first], outs[way], strict=True)
    )
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="B = 1, 64 and 2 rounds, to /tmp")
    ap.add_argument("--models", default=",".join(MODELS), help="of " + ",".join(MODELS))
    ap.add_argument("--batches", default="1,10,64,256,512")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    if args.quick:
        args.batches, args.rounds, args.out = "1,64", 2, "/tmp"
    torch.set_num_threads(1)
    load0 = load()
    rows = []
    for name in args.models.split(","):
        for kind in PASSES:
            for batch in (int(b) for b in args.batches.split(",")):
                row = measure(name, kind, batch, args.rounds)
                print(json.dumps(row), flush=True)
                rows.append(row)
    write_report(
        args.out,
        "learned_derivatives",
        "A learned model's derivatives: generated code, traced graph and autograd "
        "(`benchmarks/learned_derivatives.py`)",
        run_meta(COMMAND, argv, load0),
        rows,
        "`learned`: the cart-pole RK4 step plus a 5-64-64-4 tanh residual MLP; `features`: a "
        "6-64-64-4 tanh MLP on slices of the state and sin/cos of its angle "
        "(`FeatureCartPole`); `graybox`: the cart-pole's equations inline in torch ops, one "
        "RK4 step, plus a 5-64-64-4 tanh residual MLP (`GrayBoxCartPole`). `B x 50` random "
        f"rows; the ways alternate in one process (inside a solve's scope), {args.rounds} "
        "rounds, minimum of 3 calls each: generated code, traced graph, autograd (ratios to "
        "the generated; > 1: generated faster; `graybox`'s 131 elementwise nodes are more "
        "than derivatives are generated for, so its generated column is the graph's, in "
        "turn autograd's). `max |diff|`: the largest difference between the ways' "
        "Jacobians (and Hessians).",
        ["model", "pass", "rows", "generated [ms]", "graph [ms]", "autograd [ms]",
         "graph / generated", "autograd / generated", "max abs diff"],
        lambda r: [
            r["model"], r["pass"], str(r["rows"]), str(r["generated_ms"]),
            str(r["graph_ms"]), str(r["autograd_ms"]), f"{r['graph / generated']}x",
            f"{r['autograd / generated']}x", f"{r['max_abs_diff']:.1e}",
        ],
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
