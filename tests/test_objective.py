"""The objective a run returns to a sweeper: parsed before any work, read from the results after."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from manifold_nets.cli.train import run
from manifold_nets.objective import Objective, objective_value, parse_objective

CONFIGS = Path(__file__).resolve().parents[1] / "configs"

ROWS = [
    {"sigma": 0.1, "method": "m", "R est": 1.0, "R reduction %": 50.0, "sequences": 4},
    {"sigma": 0.3, "method": "m", "R est": 3.0, "R reduction %": math.nan, "sequences": 4},
]
METRICS = {"best_val_loss": 0.5, "test_loss": 0.7, "table": ROWS}


def _tiny(tmp_path: Path, *more: str):
    cache = f"dataset.cache_dir={tmp_path / 'data'}"
    overrides = ["experiment=default", "debug=tiny", cache, "eval.plots=false"]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose("train", overrides=[*overrides, *more])


@pytest.mark.parametrize(
    "name, want",
    [
        ("best_val_loss", Objective("best_val_loss")),
        ("test_loss", Objective("test_loss")),
        ("R est", Objective("R est", "R est")),
        ("R est@0.1", Objective("R est@0.1", "R est", 0.1)),
        ("b_v reduction % @ 0.3", Objective("b_v reduction % @ 0.3", "b_v reduction %", 0.3)),
        ("membership max", Objective("membership max", "membership max")),
        ("us/step", Objective("us/step", "us/step")),
    ],
)
def test_parse(name, want):
    assert parse_objective(name, sigmas=[0.1, 0.3]) == want


@pytest.mark.parametrize(
    "name, match",
    [
        ("val_loss", "not a loss or a metric column; choose best_val_loss"),
        ("R", "not a loss or a metric column"),
        (" est", "not a loss or a metric column"),
        ("", "names nothing"),
        ("R est@high", "'high' after '@'"),
        ("R est@-1", "finite and >= 0"),
        ("best_val_loss@0.1", "losses have no sigma"),
        ("R est@0.2", r"sigma 0.2, which is not evaluated \(eval.sigmas: 0.1, 0.3\)"),
    ],
)
def test_bad_names_are_refused_with_the_choices(name, match):
    with pytest.raises(ValueError, match=match):
        parse_objective(name, sigmas=[0.1, 0.3])


def test_values():
    assert objective_value("best_val_loss", METRICS) == 0.5
    assert objective_value("test_loss", METRICS) == 0.7
    assert objective_value("R est", METRICS) == 2.0  # the mean over the sigmas
    assert objective_value("R est@0.3", METRICS) == 3.0
    assert objective_value("R reduction %@0.1", METRICS) == 50.0
    assert parse_objective("R reduction %").minimize is False
    assert parse_objective("R est").minimize and parse_objective("test_loss").minimize


def test_missing_values_fail_clearly_never_nan():
    with pytest.raises(ValueError, match=r"no column 'p est'; its metric columns: 'R est', "):
        objective_value("p est", METRICS)
    with pytest.raises(ValueError, match="is nan"):
        objective_value("R reduction %", METRICS)
    with pytest.raises(ValueError, match="this run has no test_loss"):
        objective_value("test_loss", {"table": ROWS})
    with pytest.raises(ValueError, match="no row of the table has sigma 0.5"):
        objective_value("R est@0.5", METRICS)


def test_the_command_returns_the_objective(tmp_path):
    m = run(_tiny(tmp_path), tmp_path / "a")
    assert m["objective"] == m["best_val_loss"] and math.isfinite(m["objective"])
    m = run(_tiny(tmp_path, "objective=R est@0.1", "train.max_batches=1"), tmp_path / "b")
    assert m["objective"] == m["table"][0]["R est"]
    m = run(_tiny(tmp_path, "objective=test_loss", "train.max_batches=1"), tmp_path / "c")
    assert m["objective"] == m["test_loss"]


def test_an_unknown_objective_fails_before_any_work(tmp_path):
    with pytest.raises(ValueError, match="objective='val_loss' is not a loss or a metric column"):
        run(_tiny(tmp_path, "objective=val_loss"), tmp_path / "run")
    with pytest.raises(ValueError, match="not evaluated"):
        run(_tiny(tmp_path, "objective=R est@0.2"), tmp_path / "run")
    assert not (tmp_path / "run").exists() and not (tmp_path / "data").exists()


def test_a_column_the_table_lacks_fails_after_the_evaluation_naming_the_columns(tmp_path):
    with pytest.raises(ValueError, match="no column 'q est'; its metric columns: 'R est'"):
        run(_tiny(tmp_path, "objective=q est", "train.max_batches=1"), tmp_path / "run")
    assert (tmp_path / "run" / "results" / "metrics.json").is_file()  # the work is kept


def test_a_baseline_has_no_loss_to_return_and_a_sweeper_that_needs_one_is_refused(tmp_path):
    assert run(_tiny(tmp_path, "method=raw"), tmp_path / "raw")["objective"] is None
    m = run(_tiny(tmp_path, "method=raw", "objective=R est"), tmp_path / "raw2")
    assert m["objective"] == m["table"][0]["R est"]
    with pytest.raises(ValueError, match="method=raw does not train.*objective='R est'"):
        run(_tiny(tmp_path, "method=raw"), tmp_path / "sweep", objective_required=True)
    assert not (tmp_path / "sweep").exists()
