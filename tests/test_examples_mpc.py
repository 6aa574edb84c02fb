"""Smoke tests of the MPC learning examples (``examples/mpc_*.py``) in ``--quick`` mode.

Each runs the example's ``main`` on a tiny problem and checks a result that a broken
layer, solver or example would get wrong (not only that it runs)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"_example_{name}", EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(autouse=True)
def _restore_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def test_imitation_recovers_parameters(tmp_path):
    mod = _load("mpc_imitation")
    out = mod.main(["--quick", "--out", str(tmp_path)])
    (run,) = out["runs"]
    assert run["backward"] == "implicit"
    # the imitation loss falls by orders of magnitude and the dynamics parameters move
    # towards the truth (quick: 8 L-BFGS epochs from a 60 % / 30 % wrong mass / length)
    assert run["train_loss"] < run["initial_loss"] / 50
    for k in ("mass", "length", "goal"):
        assert run["rel_errors"][k] < run["initial_rel_errors"][k] / 2.5, k
    assert (tmp_path / "imitation.png").exists()


def test_gym_pendulum_mpc_beats_random(tmp_path):
    pytest.importorskip("gymnasium")
    mod = _load("mpc_gym_pendulum")
    out = mod.main(["--quick", "--controllers", "random,mpc_analytic", "--out", str(tmp_path)])
    rnd = out["controllers"]["random"]["returns"]
    mpc = out["controllers"]["mpc_analytic"]["returns"]
    assert len(rnd) == len(mpc) == 2
    # on every seed, the MPC with gymnasium's dynamics beats random torques by a margin
    for r, m in zip(rnd, mpc, strict=True):
        assert m > r + 50, (m, r)
    # it respects the torque limit it was given
    assert out["controllers"]["mpc_analytic"]["max_abs_action"] <= 2.0 + 1e-6


def test_gym_analytic_model_matches_env():
    gym = pytest.importorskip("gymnasium")
    import numpy as np

    mod = _load("mpc_gym_pendulum")
    env = gym.make("Pendulum-v1")
    obs, _ = env.reset(seed=3)
    model = mod.GymPendulumModel()
    for a in (1.5, -2.0, 0.3):
        x = mod.obs_to_state(obs[None])
        obs, *_ = env.step(np.array([a], dtype=np.float32))
        pred = model(x, torch.tensor([[a]], dtype=torch.float64))
        nxt = mod.obs_to_state(obs[None])
        assert abs(float(mod.wrap(pred[0, 0] - nxt[0, 0]))) < 1e-5
        assert abs(float(pred[0, 1] - nxt[0, 1])) < 1e-5
    env.close()


def test_distill_dataset_solves_converge(tmp_path):
    mod = _load("mpc_distill_cartpole")
    out = mod.main(["--quick", "--out", str(tmp_path)])
    d = out["dataset"]
    assert d["n"] == 8
    assert d["converged"] == 1.0 and d["success"] == 1.0
    assert out["policy"]["pairs"] == 8 * 50
    # the policy regression explains most of the variance of the optimal controls
    assert out["policy"]["val_mse"] < 0.2 * out["policy"]["u_var"]
