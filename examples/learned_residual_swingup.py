"""Plan on a learned model: a physics step plus a residual network, by multiple shooting.

The "real" cart-pole has viscous friction on both joints that the nominal model lacks.
A 5-64-64-4 tanh MLP learns the difference from random transitions of the real system,
and the model used for planning is ``nominal RK4 step + MLP([x, u])`` (a grey-box
model). Swing-ups from a batch of initial states are then planned on it with ``ILQR``
twice, with the default single shooting and with ``shooting="multiple"``: the same
optimum, but multiple shooting calls the model once per line-search trial over all
``B T`` nodes instead of ``T`` times in a rollout, and inside its Jacobian pass the
nominal step enters by its generated compiled Jacobians. The plans are finally applied
to the real system with their feedback gains.

    python examples/learned_residual_swingup.py            # B = 64
    python examples/learned_residual_swingup.py --quick    # B = 4, a smaller fit
"""

from __future__ import annotations

import argparse
import math
import time

import torch
from torch import nn

import torchslq as ts
from torchslq.systems import CartPole

DT, T = 0.05, 50
FRICTION = torch.tensor([0.0, 0.0, 0.3, 0.05])  # per unit velocity, on s_dot and theta_dot
GOAL = torch.tensor([0.0, math.pi, 0.0, 0.0])


def nominal_step() -> ts.DiscretizedDynamics:
    return ts.discretize(CartPole(mc=1.0, mp=0.1, l=0.5), DT, "rk4").double()


def real_step(x: torch.Tensor, u: torch.Tensor, nominal=None) -> torch.Tensor:
    """The real system: the nominal step with viscous friction on the velocities."""
    nominal = nominal or nominal_step()
    return nominal(x, u) - DT * FRICTION.to(x) * x


class GreyBox(ts.Dynamics):
    """``x_next = nominal_step(x, u) + mlp([x, u])``."""

    state_dim, control_dim = 4, 1

    def __init__(self, width: int = 64):
        super().__init__()
        self.nominal = nominal_step()
        self.mlp = nn.Sequential(
            nn.Linear(5, width), nn.Tanh(), nn.Linear(width, width), nn.Tanh(),
            nn.Linear(width, 4),
        ).double()  # fmt: skip

    def forward(self, x, u):
        return self.nominal(x, u) + self.mlp(torch.cat([x, u], -1))


def fit(model: GreyBox, samples: int, epochs: int, seed: int = 0) -> float:
    """Fit the residual to ``samples`` random transitions of the real system (Adam,
    full batch); returns the final mean squared error of the next state."""
    g = torch.Generator().manual_seed(seed)
    scale = torch.tensor([1.0, math.pi, 3.0, 8.0], dtype=torch.float64)
    x = (2 * torch.rand(samples, 4, generator=g, dtype=torch.float64) - 1) * scale
    u = (2 * torch.rand(samples, 1, generator=g, dtype=torch.float64) - 1) * 10.0
    with torch.no_grad():
        target = real_step(x, u, model.nominal) - model.nominal(x, u)
    opt = torch.optim.Adam(model.mlp.parameters(), lr=3e-3)
    for _ in range(epochs):
        opt.zero_grad()
        loss = (model.mlp(torch.cat([x, u], -1)) - target).pow(2).mean()
        loss.backward()
        opt.step()
    return loss.item()


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--quick", action="store_true", help="B = 4, 1000 samples, 300 epochs")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    B = 4 if args.quick else args.batch
    torch.manual_seed(0)
    model = GreyBox()
    mse = fit(model, 1000 if args.quick else 4000, 300 if args.quick else 1500)
    cost = ts.QuadraticCost(
        Q=torch.zeros(4, 4, dtype=torch.float64),
        R=0.02 * torch.eye(1, dtype=torch.float64),
        Qf=200.0 * torch.eye(4, dtype=torch.float64),
        x_ref=GOAL.double(),
    )
    problem = ts.Problem(model, cost, T)
    x0 = torch.zeros(B, 4, dtype=torch.float64)
    x0[:, 1] = 0.05 * torch.randn(B, generator=torch.Generator().manual_seed(1))
    out = {"fit_mse": mse, "B": B}
    results = {}
    for shooting in ("single", "multiple"):
        options = dict(tol=1e-6, compact=True, progress=False, shooting=shooting)
        # first call (generated code, caches): two iterations build and compile it all
        ts.ILQR(max_iter=2, **options).solve(problem, x0[:2])
        solver = ts.ILQR(max_iter=1000, **options)
        t0 = time.perf_counter()
        res = solver.solve(problem, x0)
        elapsed = time.perf_counter() - t0
        with torch.no_grad():  # the plan on the real system, with its feedback gains
            x = x0
            for t in range(T):
                du = (res.K[:, t] @ (x - res.x[:, t]).unsqueeze(-1)).squeeze(-1)
                x = real_step(x, res.u[:, t] + du, model.nominal)
        miss = (x - GOAL.double()).norm(dim=-1)
        results[shooting] = res
        out[shooting] = {
            "time_s": elapsed,
            "iterations_max": int(res.iterations.max()),
            "converged": int(res.converged.sum()),
            "mean_cost": float(res.cost.mean()),
            "real_final_error_max": float(miss.max()),
        }
        print(
            f"{shooting:8s} shooting: {elapsed:6.2f} s, iterations <= {int(res.iterations.max())}, "
            f"converged {int(res.converged.sum())}/{B}, mean cost {float(res.cost.mean()):.6f}, "
            f"on the real system |x_T - goal| <= {float(miss.max()):.3f}"
        )
    gap = (results["single"].cost - results["multiple"].cost).abs() / results["single"].cost
    out["max_rel_cost_gap"] = float(gap.max())
    print(f"fit MSE {mse:.2e}; costs agree to {float(gap.max()):.1e} relative")
    return out


if __name__ == "__main__":
    main()
