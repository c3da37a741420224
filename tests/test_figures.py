"""The evaluation's figure (``errors_sigma<s>.png``): axes that name their norm, no empty panel,
every curve inside its frame."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from matplotlib.lines import Line2D

from groups import SE2, SO2, SO3, Euclidean, Product
from manifold_nets.evaluation import EvalResult
from manifold_nets.reporting import _panels, metric_label, plot_errors

RIGID_BODY = Product(SO3(), Euclidean(3), Euclidean(3), Euclidean(3),
                     names=("R", "p", "b_omega", "b_v"))  # fmt: skip


def test_each_axis_names_the_norm_of_its_error():
    assert metric_label("R", RIGID_BODY) == "mean ||R_est - R|| (Frobenius)"
    assert metric_label("p", RIGID_BODY) == "mean ||p_est - p||"
    assert metric_label("x", SO2()) == "mean ||x_est - x|| (Frobenius)"
    # SE(2)'s embedding drops the constant row, whose difference is 0: the Frobenius norm still
    assert metric_label("T", Product(SE2(), Euclidean(1), names=("T", "b"))) == (
        "mean ||T_est - T|| (Frobenius)"
    )
    # a vector element embedded otherwise (a quaternion as its rotation matrix, say)
    quaternion = SimpleNamespace(element_shape=(4,), embedding_is_flat=False)
    group = SimpleNamespace(factor_names=("q",), factor=lambda name: quaternion)
    assert metric_label("q", group) == "mean ||pi(q_est) - pi(q)||"
    assert metric_label("attitude_deg", RIGID_BODY) == "mean attitude_deg"  # a system's own
    assert metric_label("R") == "mean R"  # no group given


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_no_panel_is_left_empty(n):
    fig, axes = _panels(n, height=3.0)
    assert len(fig.axes) == len(axes) == n
    cells = sum(len(ax.get_subplotspec().colspan) for ax in axes)
    assert cells == math.ceil(n / 2) * (2 if n > 1 else 1)  # the grid is filled


def _result(names, membership):
    curves = {}
    for i, name in enumerate(names):
        curves[f"{name} est"] = torch.full((17,), float(i + 1))  # flat: at the top of its axis
        curves[f"{name} meas"] = torch.cat((torch.tensor([math.nan]), torch.full((16,), 0.5)))
    curves["membership"] = membership
    return EvalResult({}, curves, skip=1)


def test_the_figure_draws_every_factor_and_the_distance_from_the_group(tmp_path, monkeypatch):
    drawn = {}
    real = _panels

    def keep(n, height):
        drawn["fig"], drawn["axes"] = real(n, height)
        return drawn["fig"], drawn["axes"]

    monkeypatch.setattr("manifold_nets.reporting._panels", keep)
    names = ["R", "p", "b_omega", "b_v"]
    path = plot_errors(_result(names, torch.full((17,), 1e-16)), tmp_path / "f.png", "t",
                       group=RIGID_BODY)  # fmt: skip
    assert path.stat().st_size > 0
    axes = drawn["axes"]
    assert len(axes) == 5 and len(axes[-1].get_subplotspec().colspan) == 2  # membership: a row
    for name, ax in zip(names, axes):
        assert ax.get_ylabel() == metric_label(name, RIGID_BODY)
        top = max(float(line.get_ydata()[-1]) for line in ax.get_lines())
        assert ax.get_ylim()[0] == 0 and ax.get_ylim()[1] > top  # a flat line is not the frame
    assert axes[-1].get_yscale() == "log"


def test_an_estimate_exactly_on_the_group_says_so(tmp_path, monkeypatch):
    drawn = {}
    real = _panels
    monkeypatch.setattr(
        "manifold_nets.reporting._panels",
        lambda n, height: drawn.setdefault("panels", real(n, height)),
    )
    plot_errors(_result(["x"], torch.zeros(17)), tmp_path / "f.png", group=SO2())
    ax = drawn["panels"][1][-1]
    assert [t.get_text() for t in ax.texts] == ["0 at every step"]
    assert ax.get_yscale() == "linear" and isinstance(ax.get_lines()[0], Line2D)
