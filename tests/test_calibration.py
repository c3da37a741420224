"""The calibration figures (NEES, ANEES and its band, ellipsoid shares) against scipy and against
errors drawn from the covariance they are scored under."""

from __future__ import annotations

import json
import math

import pytest
import torch
from scipy.stats import chi2

from groups import SO3, Euclidean, Product
from manifold_nets.calibration import (
    anees_band,
    calibration,
    gaussian_share,
    nees,
    tangent_errors,
)

GROUP = Product(SO3(), Euclidean(3), names=("R", "p"))


def _spd(batch, n, gen):
    a = torch.randn(*batch, n, n, generator=gen, dtype=torch.float64)
    return a @ a.transpose(-1, -2) + 0.5 * torch.eye(n, dtype=torch.float64)


def _block_diagonal(gen, batch):
    P = torch.zeros(*batch, 6, 6, dtype=torch.float64)
    P[..., :3, :3] = _spd(batch, 3, gen)
    P[..., 3:, 3:] = 0.01 * _spd(batch, 3, gen)
    return P


def test_nees_is_the_quadratic_form_of_the_inverse():
    gen = torch.Generator().manual_seed(0)
    P = _spd((5, 4), 6, gen)
    e = torch.randn(5, 4, 6, generator=gen, dtype=torch.float64)
    want = (e.unsqueeze(-2) @ torch.linalg.inv(P) @ e.unsqueeze(-1)).squeeze(-1).squeeze(-1)
    torch.testing.assert_close(nees(e, P), want)


def test_a_covariance_that_is_not_positive_definite_is_refused_by_index():
    P = torch.eye(3, dtype=torch.float64).repeat(2, 3, 1, 1)
    P[1, 2] = -P[1, 2]
    with pytest.raises(ValueError, match=r"index \(1, 2\).*not positive definite"):
        nees(torch.zeros(2, 3, 3), P)


def test_the_band_and_the_shares_are_scipy_s():
    lo, hi = anees_band(100, 3)
    assert lo == pytest.approx(chi2.ppf(0.025, 300) / 300)
    assert hi == pytest.approx(chi2.ppf(0.975, 300) / 300)
    assert gaussian_share(3, 3) == pytest.approx(0.9707, abs=1e-4)
    assert gaussian_share(1, 1) == pytest.approx(0.6827, abs=1e-4)


def test_tangent_errors_reach_the_truth_from_the_estimate():
    gen = torch.Generator().manual_seed(1)
    xhat = GROUP.random((4, 7), generator=gen, dtype=torch.float64)
    x = GROUP.random((4, 7), generator=gen, dtype=torch.float64)
    xi = tangent_errors(GROUP, xhat, x)
    torch.testing.assert_close(GROUP.rplus(xhat, xi), x)


@pytest.mark.parametrize("scale", [1.0, 4.0])
def test_errors_drawn_from_the_covariance_are_calibrated_and_scaled_ones_are_not(scale):
    gen = torch.Generator().manual_seed(2)
    n_seq, steps = 400, 50
    P = _block_diagonal(gen, (n_seq, steps))
    L = torch.linalg.cholesky(P)
    e = (L @ torch.randn(n_seq, steps, 6, 1, generator=gen, dtype=torch.float64)).squeeze(-1)
    out = calibration(GROUP, e, P * scale)
    for name, c in out.items():
        assert c.dim == 3
        assert c.anees == pytest.approx(1 / scale, rel=0.03), name
        assert c.band == pytest.approx(anees_band(n_seq, 3))
        if scale == 1.0:
            assert c.in_band >= 0.8, name  # 95 % in expectation over 50 steps
            for s in (1, 2, 3):
                assert c.shares[s] == pytest.approx(gaussian_share(s, 3), abs=0.01), (name, s)
        else:
            assert c.in_band == 0.0, name
            assert c.shares[3] > 0.999, name


def test_the_mask_leaves_steps_out_and_the_shares_count_only_known_ones():
    gen = torch.Generator().manual_seed(3)
    P = torch.eye(6, dtype=torch.float64).repeat(10, 4, 1, 1)
    e = torch.randn(10, 4, 6, generator=gen, dtype=torch.float64)
    e[:, 0] = 100.0  # step 0 unknown everywhere: left out
    mask = torch.ones(10, 4, dtype=torch.bool)
    mask[:, 0] = False
    c = calibration(GROUP, e, P, mask)["R"]
    assert len(c.anees_steps) == 3
    want = (e[:, 1:, :3] ** 2).sum(-1).mean(0) / 3
    torch.testing.assert_close(torch.as_tensor(c.anees_steps), want)
    assert math.isfinite(c.anees) and c.anees < 10


def test_shapes_are_checked():
    with pytest.raises(ValueError, match=r"\(N, T, n\)"):
        calibration(GROUP, torch.zeros(2, 6), torch.zeros(2, 6, 6))
    with pytest.raises(ValueError, match="6 components|components"):
        calibration(GROUP, torch.zeros(2, 3, 5), torch.zeros(2, 3, 5, 5))


@pytest.mark.parametrize("source", ["residual", "residual_size"])
def test_the_rigid_body_calibration_command_writes_its_tables_figure_and_readout(tmp_path, source):
    """The command of docs/calibration.md at a tiny size: the table rows for both estimators,
    the figure, and a readout that loads back onto the zoo entry."""
    import json

    from manifold_nets import load_observer
    from manifold_nets.covariance_training import load_readout
    from manifold_nets_examples.rigid_body import calibration as command

    command.main(["--out", str(tmp_path), "--cases", "nominal", "--sigmas", "0.3", "--train", "2",
                  "--eval", "3", "--length", "30", "--epochs", "1", "--heldout", "2",
                  "--source", source])
    table = (tmp_path / "calibration.md").read_text()
    assert "| 0.3 | learned |" in table and "| 0.3 | ekf |" in table
    rows = json.loads((tmp_path / "calibration.json").read_text())["cases"]["nominal"]["0.3"]
    for estimator in ("learned", "ekf"):
        assert set(rows[estimator]) == {"R", "p", "b_omega", "b_v"}
        assert all(math.isfinite(v) for v in rows[estimator]["R"].values())
    assert (tmp_path / "calibration_nominal.png").stat().st_size > 10_000
    scales = json.loads((tmp_path / "calibration.json").read_text())["history"]["nominal"]["heldout_scales"]
    assert set(scales) == {"R", "p", "b_omega", "b_v"} and all(v > 0 for v in scales.values())
    observer, _, _ = load_observer("zoo:rigid_body/nominal")
    readout = load_readout(tmp_path / "nominal_covariance.pt", observer).readout
    assert readout.clock == command.CLOCK and readout.source == source
    # --readouts: the same readout scored as it is, not fitted again: the same table
    command.main(["--out", str(tmp_path / "again"), "--cases", "nominal", "--sigmas", "0.3",
                  "--eval", "3", "--length", "30", "--readouts", str(tmp_path)])
    again = json.loads((tmp_path / "again" / "calibration.json").read_text())
    assert again["cases"]["nominal"]["0.3"] == rows and "loaded" in again["history"]["nominal"]
    assert not (tmp_path / "again" / "nominal_covariance.pt").exists()


def test_the_calibration_command_scores_a_readout_with_the_level_scale_its_file_holds(tmp_path):
    """``--readouts DIR``: a file with a level scale (the zoo's hold one) is scored with it, as
    ``CalibratedObserver(observer, readout, level_scale)`` gives it, not as the readout alone."""
    import json

    from manifold_nets.covariance_training import save_readout
    from manifold_nets.observer import CalibratedObserver
    from manifold_nets_examples.rigid_body import calibration as command
    from manifold_nets_examples.rigid_body.level_scale import zoo_readout

    cal, system = zoo_readout("nominal")
    assert cal.level_scale is not None and cal.readout.source == "residual_size"
    rows = {}
    for name, scale in (("with", cal.level_scale), ("alone", None)):
        (tmp_path / name).mkdir()
        save_readout(tmp_path / name / "nominal_covariance.pt", cal.readout,
                     "zoo:rigid_body/nominal", scale)
        command.main(["--out", str(tmp_path / name / "out"), "--cases", "nominal", "--sigmas",
                      "0.3", "--eval", "3", "--length", "40", "--readouts", str(tmp_path / name)])
        rows[name] = json.loads((tmp_path / name / "out" / "calibration.json").read_text())[
            "cases"]["nominal"]["0.3"]
    assert rows["with"]["ekf"] == rows["alone"]["ekf"]
    assert rows["with"]["learned"]["R"]["anees"] != rows["alone"]["learned"]["R"]["anees"]
    data = command._sim(system, 3, 40, 0.3, 7)
    with torch.no_grad():
        direct = CalibratedObserver(cal.observer, cal.readout, cal.level_scale).eval()(
            data.measurements)
    assert command._row(system.group, *direct, data.states) == rows["with"]["learned"]


def test_evaluate_scores_the_covariance_of_an_estimator_that_gives_one():
    from functools import partial

    from manifold_nets.cores import GRUCore
    from manifold_nets.evaluation import CalibratedEstimator, evaluate
    from manifold_nets.observer import (
        CalibratedObserver,
        CovarianceReadout,
        Measurement,
        ResidualObserver,
    )
    from manifold_nets_examples.rigid_body import RigidBody

    system = RigidBody()
    obs = ResidualObserver(system.group, Measurement(18, factors={"R": [0, 9], "p": [9, 12]}),
                           core=partial(GRUCore, hidden_size=8, num_layers=1))
    readout = CovarianceReadout(system.group, 6, "factor", memory=4)
    readout.set_scale(torch.full((12,), 0.3, dtype=torch.float64))
    cal = CalibratedObserver(obs, readout)
    data = system.simulate(5, 20, 0.3, torch.Generator().manual_seed(0))
    plain = evaluate(CalibratedEstimator(cal, batch_size=2), data, system, skip=5)
    assert "R ANEES" not in plain.row  # only when asked
    scored = evaluate(CalibratedEstimator(cal, batch_size=2), data, system, skip=5,
                      calibration=True)
    with torch.no_grad():
        est, cov = cal(data.measurements)
    want = calibration(system.group, tangent_errors(system.group, est[:, 5:], data.states[:, 5:]),
                       cov[:, 5:])
    for f in ("R", "p", "b_omega", "b_v"):
        assert scored.row[f"{f} ANEES"] == pytest.approx(want[f].anees)
        assert scored.row[f"{f} in 3 sigma %"] == pytest.approx(100 * want[f].shares[3])
        assert scored.row[f"{f} in band %"] == pytest.approx(100 * want[f].in_band)
    assert scored.row["R est"] == plain.row["R est"]


def test_the_evaluate_command_scores_the_learned_covariance_and_refuses_it_without_calibration(
    tmp_path,
):
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).parents[1]
    base = [sys.executable, "-m", "manifold_nets.cli.evaluate", "experiment=paper_cpu_prior",
            "eval.checkpoint=zoo:rigid_body/nominal", "eval.covariance=zoo:rigid_body/nominal",
            "eval.sigmas=[0.3]", "eval.num_sequences=3", "eval.length=30", "eval.plots=false",
            "eval.baselines=[ekf]", "eval.test_split=false", f"dataset.cache_dir={tmp_path / 'data'}",
            f"hydra.run.dir={tmp_path / 'run'}"]
    env = {**os.environ, "PYTHONPATH": str(root)}
    out = subprocess.run([*base, "eval.calibration=true"], capture_output=True, text=True,
                         env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    metrics = json.loads((tmp_path / "run" / "results" / "metrics.json").read_text())
    for row in (metrics["table"][0], metrics["references"][0]):  # the learned observer, the EKF
        assert math.isfinite(row["R ANEES"]) and 0 <= row["R in 3 sigma %"] <= 100, row
    assert metrics["references"][0]["method"] == "ekf"
    refused = subprocess.run([*base, f"hydra.run.dir={tmp_path / 'run2'}"], capture_output=True,
                             text=True, env=env, timeout=300)
    assert refused.returncode != 0
    assert "is scored only with eval.calibration=true" in refused.stdout + refused.stderr
    assert not (tmp_path / "run2" / "results").exists()  # refused before any work


def test_the_sensor_errors_are_scored_with_their_own_readout_where_there_is_one(tmp_path):
    """The sensor-error system's readout: the zoo's ``covariance_sensor.pt``, a folder's
    ``sensor_covariance.pt``; a folder without one scores the case with its observer's
    (``nominal_covariance.pt``), as the readouts fitted per observer are scored. Fitting the case
    fits its own readout on its own system."""
    import json
    import shutil

    from manifold_nets.plugins import zoo_path
    from manifold_nets_examples.rigid_body import calibration as command

    zoo = zoo_path("rigid_body/nominal")
    assert command.readout_file("sensor") == zoo / "covariance_sensor.pt"
    assert command.readout_file("nominal") == zoo / "covariance.pt"
    assert command.readout_case("sensor") == "sensor"
    assert command.readout_case("outliers") == "outliers"
    folder = tmp_path / "readouts"
    folder.mkdir()
    shutil.copy(zoo / "covariance.pt", folder / "nominal_covariance.pt")
    rows = {}
    for own in (False, True):
        if own:
            shutil.copy(zoo / "covariance_sensor.pt", folder / "sensor_covariance.pt")
        assert command.readout_case("sensor", folder) == ("sensor" if own else "nominal")
        out = tmp_path / f"out_{own}"
        command.main(["--out", str(out), "--cases", "sensor", "--sigmas", "0.1", "--eval", "3",
                      "--length", "30", "--readouts", str(folder)])
        result = json.loads((out / "calibration.json").read_text())
        want = folder / ("sensor_covariance.pt" if own else "nominal_covariance.pt")
        assert result["history"] == {"sensor": {"loaded": str(want)}}
        rows[own] = result["cases"]["sensor"]["0.1"]
    assert rows[True]["ekf"] == rows[False]["ekf"]
    assert rows[True]["learned"]["R"]["anees"] != rows[False]["learned"]["R"]["anees"]
    command.main(["--out", str(tmp_path / "fit"), "--cases", "sensor", "--sigmas", "0.1",
                  "--train", "2", "--eval", "2", "--length", "20", "--epochs", "1",
                  "--heldout", "0"])
    assert sorted(p.name for p in (tmp_path / "fit").glob("*.pt")) == ["sensor_covariance.pt"]


@pytest.mark.parametrize("text, file", [
    ("zoo:rigid_body/nominal", "covariance.pt"),
    ("zoo:rigid_body/nominal/covariance_sensor.pt", "covariance_sensor.pt"),
])
def test_eval_covariance_names_an_entry_s_readout(text, file):
    from omegaconf import OmegaConf

    from manifold_nets.cli.learned_extras import covariance_file
    from manifold_nets.plugins import zoo_path

    cfg = OmegaConf.create({"eval": {"covariance": text}})
    assert covariance_file(cfg) == zoo_path("rigid_body/nominal") / file


@pytest.mark.parametrize("text, match", [
    ("zoo:rigid_body/nominal/config.yaml", "not a readout's file name"),
    ("zoo:rigid_body/nominal/checkpoints/last.pt", "not a readout's file name"),
    ("zoo:rigid_body/nominal/../outliers/covariance.pt", "not an installed zoo entry"),
    ("zoo:rigid_body/nominal/covariance_..pt", "not a readout's file name"),
])
def test_eval_covariance_refuses_what_is_not_an_entry_s_readout(text, match):
    from omegaconf import OmegaConf

    from manifold_nets.cli.learned_extras import covariance_file

    with pytest.raises(ValueError, match=match):
        covariance_file(OmegaConf.create({"eval": {"covariance": text}}))
