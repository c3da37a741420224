"""method= selection, the unconstrained ablation and the comparison of methods."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from test_configs import CONFIGS, _compose, _tiny

from manifold_nets_examples.rigid_body import MismatchedRigidBody, RigidBody
from groups import SE3, SO3, Euclidean, Product
from manifold_nets import results
from manifold_nets.cli import compare
from manifold_nets.baselines import DeadReckoning, RawMeasurement, make_estimator
from manifold_nets.evaluation import ObserverEstimator, evaluate
from manifold_nets.relax import relax
from manifold_nets.builders import build_observer
from manifold_nets.cli.train import run
from manifold_nets.config import ModelConfig, RunConfig, TrainSettings
from manifold_nets.training import fit

METHODS = sorted(p.stem for p in (CONFIGS / "method").glob("*.yaml"))


def test_the_methods_of_the_issue_are_there():
    assert {"learned", "untrained", "raw", "dead_reckoning", "ekf", "complementary"} <= set(METHODS)


@pytest.mark.parametrize("method", METHODS)
def test_every_method_composes_and_names_an_estimator_of_the_rigid_body(method):
    cfg = _compose("experiment=default", f"method={method}")
    assert isinstance(OmegaConf.to_object(cfg), RunConfig)
    assert cfg.method.name == method
    if method == "ekf_ar1":  # the correlated-noise oracle: a method of the mismatched body only
        assert method in MismatchedRigidBody().estimators()
        assert method not in RigidBody().estimators()
    elif method not in ("learned", "untrained"):
        assert method in RigidBody().estimators()


@pytest.mark.parametrize("method", ["raw", "dead_reckoning", "untrained", "ekf"])
def test_a_method_runs_through_the_same_evaluation(tmp_path, method):
    cfg = _compose(*_tiny(tmp_path / "data", f"method={method}", "eval.plots=false"))
    metrics = run(cfg, tmp_path / "run")
    assert metrics["method"] == method and "checkpoint" not in metrics
    assert not (tmp_path / "run" / "checkpoints").exists()  # nothing was trained
    (row,) = metrics["table"]
    assert row["method"] == method and row["us/step"] > 0
    assert {"R est", "p est", "b_omega est", "b_v est", "membership max"} <= set(row)
    assert row["membership max"] < 1e-12  # every method stays on the group
    text = (tmp_path / "run" / "results" / "table.md").read_text()
    assert f"method {method}" in text


def test_raw_method_reports_the_measurement_error(tmp_path):
    cfg = _compose(*_tiny(tmp_path / "data", "method=raw", "eval.plots=false"))
    (row,) = run(cfg, tmp_path / "run")["table"]
    assert row["R est"] == pytest.approx(row["R meas"], rel=1e-12)
    assert row["p est"] == pytest.approx(row["p meas"], rel=1e-12)


def test_method_errors_are_clear_and_come_before_any_work(tmp_path):
    cfg = _compose(*_tiny(tmp_path / "data", "method.name=kalman"))
    with pytest.raises(ValueError, match=r"no estimator of that name.*'ekf'.*'raw'"):
        run(cfg, tmp_path / "a")
    assert not (tmp_path / "data").exists()
    cfg = _compose(*_tiny(tmp_path / "data", "method=untrained", "eval.checkpoint=x.pt"))
    with pytest.raises(ValueError, match="untrained.*cannot load"):
        run(cfg, tmp_path / "b")
    cfg = _compose(*_tiny(tmp_path / "data", "method.name=mine", "method.target=no.such.thing"))
    with pytest.raises(ValueError, match="could not be imported"):
        run(cfg, tmp_path / "c")


def test_a_user_factory_with_params_and_label(tmp_path):
    cfg = _compose(
        *_tiny(
            tmp_path / "data",
            "method.name=ekf_autograd",
            "method.target=manifold_nets_examples.rigid_body.filters.RigidBodyEKF",
            "+method.params.jacobians=autograd",
            "method.label=ekf_autograd",
            "eval.plots=false",
        )
    )
    metrics = run(cfg, tmp_path / "run")
    assert metrics["method"] == "ekf_autograd"
    assert metrics["method_params"] == {"jacobians": "autograd"}


def test_make_estimator_passes_sigma_only_to_factories_that_take_it():
    system = RigidBody()
    seen = {}

    def with_sigma(system, sigma, scale=1.0):
        seen["sigma"], seen["scale"] = sigma, scale
        return RawMeasurement(system)

    assert isinstance(make_estimator(system, "raw", 0.3), RawMeasurement)
    assert isinstance(make_estimator(system, DeadReckoning, 0.3), DeadReckoning)
    make_estimator(system, with_sigma, 0.3, scale=2.0)
    assert seen == {"sigma": 0.3, "scale": 2.0}
    with pytest.raises(TypeError, match="not an Estimator"):
        make_estimator(system, lambda system: object(), 0.3)
    with pytest.raises(TypeError, match="params"):
        make_estimator(system, "raw", 0.3, gain=1.0)


# ---------------------------------------------------------------------- the unconstrained ablation


def test_relax_takes_named_factors_off_their_group():
    g = RigidBody().group
    r = relax(g, ["R"])
    assert isinstance(r.factors[0], Euclidean) and r.factors[0].embedding_dim == 9
    assert r.names == g.names and r.element_shape == g.element_shape
    assert relax(g, []) is g
    x = g.random((3,), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert torch.equal(r.embed(x), g.embed(x))  # same layout, same loss and metrics
    with pytest.raises(ValueError, match="does not have"):
        relax(g, ["q"])
    with pytest.raises(ValueError, match="not its flattened element"):
        relax(Product(SE3(), Euclidean(3), names=("T", "b")), ["T"])
    with pytest.raises(ValueError, match="wrap it in a Product"):
        relax(SO3(), ["x"])


def _unconstrained(system, hidden=16, relaxed=True):
    mcfg = OmegaConf.structured(
        ModelConfig(
            hidden_size=hidden,
            num_layers=1,
            updates={"R": "absolute" if relaxed else "residual", "b_omega": "absolute",
                     "b_v": "absolute"},
            measurement={"factors": {"R": [0, 9], "p": [9, 12]}},  # innovation read (features null)
            relax=["R"] if relaxed else [],
        )
    )
    return build_observer(system.group, system.measurement_dim, system.input_dim, mcfg)


def test_the_unconstrained_ablation_really_leaves_so3(tmp_path):
    system = RigidBody()
    gen = torch.Generator().manual_seed(0)
    train = system.simulate(64, 12, 0.1, gen)
    val = system.simulate(16, 12, 0.1, gen)
    test = system.simulate(8, 40, 0.1, gen)
    rows = {}
    for relaxed in (True, False):
        torch.manual_seed(0)
        model = _unconstrained(system, relaxed=relaxed)
        settings = TrainSettings(epochs=3, batch_size=16, lr=3e-3, progress=False)
        fit(model, train, val, settings, out_dir=tmp_path / str(relaxed))
        rows[relaxed] = evaluate(model, test, system, skip=2).row
        est = ObserverEstimator(model).estimate(test)
        R = est[..., :9].unflatten(-1, (3, 3)).double()
        eye = torch.eye(3, dtype=R.dtype)
        off = torch.linalg.matrix_norm(R @ R.transpose(-1, -2) - eye)[:, 2:]
        if relaxed:  # a regression of vec R is not a rotation: far off SO(3), at every step
            assert float(off.min()) > 1e-3
            assert rows[relaxed]["membership mean"] == pytest.approx(
                float(system.group.membership_error(est)[:, 2:].mean()), rel=1e-6
            )
        else:
            assert float(off.max()) < 1e-12
    assert rows[True]["membership mean"] > 1e-2
    assert rows[False]["membership max"] < 1e-12


# ---------------------------------------------------------------------- the comparison


def _fake_run(root: Path, method: str, sigmas, value: float, trained=False, size=(10, 50), seed=0):
    res = root / "results"
    res.mkdir(parents=True)
    table = [
        {"sigma": s, "method": method, "R est": value * s, "R meas": 2 * s, "p est": value,
         "membership mean": 1e-15, "membership max": 1e-14, "sequences": size[0],
         "steps": size[1], "us/step": 3.0}
        for s in sigmas
    ]
    metrics = {"name": "x", "method": method, "table": table, "skip_steps": 2, "seed": seed}
    if trained:
        metrics["checkpoint"] = "best.pt"
    (res / "metrics.json").write_text(json.dumps(metrics))
    curves = {f"{s:g}": {"R est": [None, 1.0, 0.5, 0.4], "R meas": [None, 1, 1, 1],
                         "membership": [0, 1e-15, 1e-15, 1e-15]} for s in sigmas}
    (res / "curves.json").write_text(json.dumps(curves))


def test_comparison_table_ratios_and_figures(tmp_path):
    _fake_run(tmp_path / "sweep" / "0", "ekf", [0.1, 0.2], 1.0)
    _fake_run(tmp_path / "sweep" / "1", "raw", [0.1, 0.2], 4.0)
    _fake_run(tmp_path / "learned", "learned", [0.2, 0.1], 1.5, trained=True)
    out = tmp_path / "cmp"
    assert compare.main([str(tmp_path / "sweep"), str(tmp_path / "learned"), "--out", str(out)]) == 0
    rows = results.comparison_rows(results.collect_runs([tmp_path / "sweep", tmp_path / "learned"]))
    assert [r["method"] for r in rows] == ["ekf", "raw", "learned", "learned / ekf"] * 2
    assert [r["sigma"] for r in rows] == [0.1] * 4 + [0.2] * 4
    ratio = rows[3]
    assert ratio["R"] == pytest.approx(1.5) and ratio["p"] == pytest.approx(1.5)
    for name in ("comparison.csv", "comparison.md", "comparison_vs_sigma.png",
                 "comparison_sigma0.1.png", "comparison_sigma0.2.png"):
        assert (out / name).stat().st_size > 0
    # without a raw run the measurement is a row of its own
    rows = results.comparison_rows(results.collect_runs([tmp_path / "learned"]))
    assert rows[0]["method"] == "measurement" and rows[0]["R"] == pytest.approx(0.2)


def test_comparison_tells_runs_of_one_method_apart(tmp_path):
    _fake_run(tmp_path / "ekf", "ekf", [0.1], 1.0)
    for seed, value in ((0, 1.5), (1, 2.0)):  # a seed sweep of one observer
        _fake_run(tmp_path / "sweep" / str(seed), "learned", [0.1], value, trained=True, seed=seed)
    _fake_run(tmp_path / "again", "learned", [0.1], 3.0, trained=True, seed=1)  # a repeat
    rows = results.comparison_rows(results.collect_runs([tmp_path]))
    assert [r["method"] for r in rows] == [
        "measurement",
        "learned seed 1 #1",  # again/
        "ekf",
        "learned seed 0",  # sweep/0
        "learned seed 1 #2",  # sweep/1
        "learned seed 1 #1 / ekf",
        "learned seed 0 / ekf",
        "learned seed 1 #2 / ekf",
    ]
    by = {r["method"]: r for r in rows}
    assert by["learned seed 0 / ekf"]["R"] == pytest.approx(1.5)
    assert len({r["method"] for r in rows}) == len(rows)  # every row its own name
    curves, _ = results.step_curves(results.collect_runs([tmp_path]), 0.1)
    assert len(curves) == 4  # one line per run in the step figure, none overwritten


def test_comparison_refuses_runs_on_different_sets(tmp_path, capsys):
    _fake_run(tmp_path / "a", "ekf", [0.1], 1.0, size=(10, 50))
    _fake_run(tmp_path / "b", "raw", [0.1], 1.0, size=(10, 60))
    assert compare.main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path)]) == 1
    assert "different sizes" in capsys.readouterr().err
    assert compare.main([str(tmp_path / "nothing"), "--out", str(tmp_path)]) == 1


def test_the_rigid_body_filters_refuse_the_se3_layout():
    from manifold_nets_examples.rigid_body.filters import ComplementaryFilter, RigidBodyEKF

    se3 = RigidBody(pose_group="se3")
    assert set(se3.estimators()) == {"raw", "dead_reckoning"}
    for make in (lambda: RigidBodyEKF(se3, 0.1), lambda: ComplementaryFilter(se3)):
        with pytest.raises(ValueError, match="pose_group='so3_r3'"):
            make()


@pytest.mark.parametrize("experiment", sorted(p.stem for p in (CONFIGS / "experiment").glob("*.yaml")))
def test_no_experiment_pins_a_label_that_would_mislabel_other_methods(experiment):
    # `-m experiment=<e> method=raw,ekf` must give rows labelled raw, ekf: an experiment that set
    # method.label would stamp its own name on every method's rows
    cfg = _compose(f"experiment={experiment}", "method=ekf")
    assert cfg.method.label is None and cfg.method.name == "ekf"


def test_a_trained_observers_rows_say_learned_and_a_comparison_names_its_experiment(tmp_path):
    cfg = _compose(*_tiny(tmp_path / "data", "eval.plots=false", "name=tiny_exp"))
    metrics = run(cfg, tmp_path / "run")
    assert metrics["method"] == "learned" and metrics["table"][0]["method"] == "learned"
    with (tmp_path / "run" / "results" / "table.csv").open() as f:
        assert next(csv.DictReader(f))["method"] == "learned"
    assert metrics["label"] == "tiny_exp"  # what the comparison calls it
    _fake_run(tmp_path / "other", "ekf", [0.1], 1.0, size=(4, 16))  # no label: its method
    rows = results.comparison_rows(results.collect_runs([tmp_path / "run", tmp_path / "other"]))
    assert [r["method"] for r in rows] == ["measurement", "tiny_exp", "ekf", "tiny_exp / ekf"]


def test_horizon_table_gives_the_error_at_chosen_steps_and_its_growth(tmp_path):
    curve = [None] + [0.5] * 150 + [1.0] * 100  # 0.5 up to step 150, 1.0 from step 151
    res = tmp_path / "run" / "results"
    res.mkdir(parents=True)
    table = [{"sigma": 0.1, "method": "learned", "R est": 0.7, "sequences": 2, "steps": 250}]
    (res / "metrics.json").write_text(json.dumps({"method": "learned", "table": table}))
    (res / "curves.json").write_text(json.dumps({"0.1": {"R est": curve, "R meas": curve}}))
    rows = results.horizon_rows(results.collect_runs([tmp_path / "run"]), [100, 200, 9999], window=3)
    assert rows == [{"sigma": 0.1, "method": "learned", "R@100": 0.5, "R@200": 1.0,
                     "R 200/100": 2.0}]
    out = tmp_path / "cmp"
    assert compare.main([str(tmp_path / "run"), "--out", str(out), "--horizon", "100", "200"]) == 0
    assert "R 200/100" in (out / "horizon.md").read_text()
    with pytest.raises(ValueError, match="steps must be step indices >= 0"):
        results.horizon_rows([], [-1])
