"""Figures (torchslq.plotting) and the logger's figures / PNG files, checked on the
matplotlib objects: legend entries, goal and bound lines, batch statistics."""

from __future__ import annotations

import math
import warnings

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch
from matplotlib.collections import PolyCollection

import torchslq as ts
from torchslq import systems
from torchslq.plotting import convergence_figure, state_control_names, trajectory_figure
from torchslq.tasks import pendulum_swingup

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
B, T, N, M = 5, 10, 2, 1


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _traj(batch: int = B):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(batch, T + 1, N, generator=g, dtype=torch.float64)
    u = torch.randn(batch, T, M, generator=g, dtype=torch.float64)
    return x, u


def _legends(fig):
    return [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None] + fig.legends


def _lines(ax, gid):
    return [ln for ln in ax.get_lines() if ln.get_gid() == gid]


# trajectory_figure ----------------------------------------------------------------------
def test_one_legend_names_each_element_once_above_the_curves():
    x, u = _traj()
    fig = trajectory_figure(x, u, max_elements=3, x_ref=torch.tensor([1.0, 0.0]), u_max=2.0)
    legends = _legends(fig)
    assert len(legends) == 1
    assert [t.get_text() for t in legends[0].get_texts()] == ["#0", "#1", "#2", "goal", "bound"]
    # above the first panel, not over its curves
    fig.canvas.draw()
    top_axes = fig.axes[0].get_window_extent()
    assert legends[0].get_window_extent().y0 >= top_axes.y1 - 1.0


def test_legend_has_exactly_k_entries_for_k_elements():
    x, u = _traj()
    for k in (2, 4):
        (legend,) = _legends(trajectory_figure(x, u, max_elements=k))
        assert [t.get_text() for t in legend.get_texts()] == [f"#{b}" for b in range(k)]


def test_element_colours_agree_across_panels():
    x, u = _traj()
    fig = trajectory_figure(x, u, max_elements=3)
    colours = [[ln.get_color() for ln in ax.get_lines()] for ax in fig.axes]
    assert all(c == colours[0] for c in colours) and len(set(colours[0])) == 3


@pytest.mark.parametrize("shape", ["(n,)", "(T+1,n)", "(B,T+1,n)"])
def test_goal_line_ydata_equals_x_ref(shape):
    x, u = _traj()
    k = 3
    ref = {
        "(n,)": torch.tensor([math.pi, -0.5], dtype=torch.float64),
        "(T+1,n)": torch.linspace(0, 1, (T + 1) * N, dtype=torch.float64).reshape(T + 1, N),
        "(B,T+1,n)": torch.randn(B, T + 1, N, dtype=torch.float64),
    }[shape]
    fig = trajectory_figure(x, u, max_elements=k, x_ref=ref)
    for i in range(N):
        goals = _lines(fig.axes[i], "goal")
        if shape == "(n,)":
            (line,) = goals
            np.testing.assert_array_equal(line.get_ydata(), [ref[i].item()] * 2)
            assert line.get_linestyle() == "--"
        elif shape == "(T+1,n)":
            (line,) = goals
            np.testing.assert_array_equal(line.get_ydata(), ref[:, i].numpy())
        else:
            assert len(goals) == k
            for b, line in enumerate(goals):
                np.testing.assert_array_equal(line.get_ydata(), ref[b, :, i].numpy())
    for j in range(M):  # no goal on the control panels
        assert _lines(fig.axes[N + j], "goal") == []


def test_bound_lines_sit_at_the_bounds_and_skip_infinite_entries():
    x, u = _traj()
    fig = trajectory_figure(
        x,
        u,
        u_min=torch.tensor([-math.inf]),
        u_max=2.5,
        x_min=torch.tensor([-1.0, -math.inf]),
        x_max=torch.tensor([math.inf, 4.0]),
    )
    (u_line,) = _lines(fig.axes[N], "bound")
    np.testing.assert_array_equal(u_line.get_ydata(), [2.5, 2.5])
    assert [ln.get_ydata()[0] for ln in _lines(fig.axes[0], "bound")] == [-1.0]
    assert [ln.get_ydata()[0] for ln in _lines(fig.axes[1], "bound")] == [4.0]


def test_labels_are_used_and_validated():
    x, u = _traj()
    fig = trajectory_figure(x, u, state_labels=("a", "b"), control_labels=["F"])
    assert [ax.get_ylabel() for ax in fig.axes] == ["a", "b", "F"]
    with pytest.raises(ValueError, match="state_labels"):
        trajectory_figure(x, u, state_labels=["only one"])
    with pytest.raises(ValueError, match="control_labels"):
        trajectory_figure(x, u, control_labels=["F", "G"])
    with pytest.raises(ValueError, match="x_ref"):
        trajectory_figure(x, u, x_ref=torch.zeros(3))
    with pytest.raises(ValueError, match="u_max"):
        trajectory_figure(x, u, u_max=torch.ones(2))


def test_unbatched_and_empty_trajectories_still_draw():
    x, u = _traj()
    fig = trajectory_figure(x[0], u[0], dt=0.1, title="t")
    assert fig.axes[-1].get_xlabel() == "time [s]"
    assert _legends(fig) == []  # one element and nothing else to explain
    trajectory_figure(x[:0], u[:0])


# convergence_figure ---------------------------------------------------------------------
def _history():
    g = torch.Generator().manual_seed(1)
    h = torch.rand(7, 9, generator=g, dtype=torch.float64) + 0.1
    h[0] = math.nan  # a failed element: ignored
    h[3, 4] = math.inf
    return h


def _expected_quantile(h, q):
    cols = [c[torch.isfinite(c)] for c in h.T]
    return np.array([torch.quantile(c, q).item() for c in cols])


def test_convergence_median_and_band_over_the_finite_batch():
    h = _history()
    fig = convergence_figure({"SLQ": h})
    (ax,) = fig.axes
    (median,) = ax.get_lines()
    assert median.get_label() == "SLQ median"
    np.testing.assert_allclose(median.get_ydata(), _expected_quantile(h, 0.5), rtol=1e-12)
    (band,) = [c for c in ax.collections if isinstance(c, PolyCollection)]
    assert band.get_label() == "SLQ 10-90 percentile"
    verts = band.get_paths()[0].vertices
    lo, hi = _expected_quantile(h, 0.1), _expected_quantile(h, 0.9)
    for it in range(h.shape[1]):
        ys = verts[np.isclose(verts[:, 0], it), 1]
        assert ys.min() == pytest.approx(lo[it]) and ys.max() == pytest.approx(hi[it])
    assert ax.get_yscale() == "log"
    legend_texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend_texts == ["SLQ median", "SLQ 10-90 percentile"]


def test_convergence_min_max_band_and_single_elements():
    h = _history()
    fig = convergence_figure({"a": h}, band=(0.0, 1.0), elements=[2, 99])
    ax = fig.axes[0]
    labels = [ln.get_label() for ln in ax.get_lines()]
    assert labels == ["a median", "a #2"]  # 99 is past the batch: skipped
    np.testing.assert_array_equal(ax.get_lines()[1].get_ydata(), h[2].numpy())
    assert [c.get_label() for c in ax.collections] == ["a min-max"]
    # element= keeps the former one-element view
    (line,) = convergence_figure({"a": h}, element=1).axes[0].get_lines()
    np.testing.assert_array_equal(line.get_ydata(), h[1].numpy())


def test_convergence_of_a_result_history_shows_cost_and_grad_norm():
    h = {"cost": _history(), "grad_norm": _history() * 1e-3, "step": torch.ones(7, 9)}
    fig = convergence_figure({"SLQ": h, "DDP": h}, title="t")
    assert [ax.get_ylabel() for ax in fig.axes] == ["cost", "gradient norm"]
    assert all(ax.get_yscale() == "log" for ax in fig.axes)
    np.testing.assert_allclose(
        fig.axes[1].get_lines()[0].get_ydata(), _expected_quantile(h["grad_norm"], 0.5)
    )


def test_convergence_with_optimum_uses_relative_error_per_element():
    h = _history()
    fig = convergence_figure({"a": h}, optimum=0.5)
    rel = (h - 0.5).abs() / 0.5
    np.testing.assert_allclose(fig.axes[0].get_lines()[0].get_ydata(), _expected_quantile(rel, 0.5))


@pytest.mark.parametrize("h", [torch.empty(0, 6), torch.full((4, 6), math.nan), torch.ones(3, 0)])
def test_convergence_of_empty_or_all_nan_batch_does_not_crash(h):
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        fig = convergence_figure({"a": h})
    assert fig.axes[0].get_xlabel() == "iteration"


# names and the logger -------------------------------------------------------------------
@pytest.mark.parametrize(
    "model",
    [
        systems.Pendulum(),
        systems.CartPole(),
        systems.DragVehicle(),
        systems.Hopper(),
        systems.Unicycle(),
        systems.MassChain(3),
        systems.PendulumCartTrain(2),
    ],
    ids=lambda m: type(m).__name__,
)
def test_zoo_models_name_their_states_and_controls(model):
    s, c = state_control_names(
        ts.discretize(model, 0.1) if isinstance(model, ts.ContinuousDynamics) else model
    )
    assert s is not None and len(s) == model.state_dim
    assert c is not None and len(c) == model.control_dim


def test_logger_passes_names_goal_and_writes_pngs(tmp_path, monkeypatch):
    import torchslq.plotting as plotting

    seen = {}
    real = plotting.trajectory_figure

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(plotting, "trajectory_figure", spy)
    problem, x0 = pendulum_swingup(batch=4, horizon=20)
    with ts.TensorBoardLogger(tmp_path / "png", save_png=True) as logger:
        ts.ILQR(max_iter=3, u_max=30.0, progress=False).solve(problem, x0, logger=logger)
    for name in ("trajectories.png", "convergence.png"):
        assert (tmp_path / "png" / name).read_bytes()[:8] == PNG_MAGIC
    assert tuple(seen["state_labels"]) == systems.Pendulum.state_names
    assert tuple(seen["control_labels"]) == systems.Pendulum.control_names
    assert seen["x_ref"] is problem.cost.x_ref
    assert seen["u_max"] == 30.0 and seen["u_min"] is None

    with ts.TensorBoardLogger(tmp_path / "plain", state_labels=["a", "b"]) as logger:
        ts.SLQ(max_iter=2, progress=False).solve(problem, x0, logger=logger)
    assert not list((tmp_path / "plain").glob("*.png"))  # save_png defaults to False
    assert seen["state_labels"] == ("a", "b")
