"""``benchmarks/calibration_paper_sets.py``'s commands: each case's zoo observer with the readout
fitted on the case's own system (the sensor errors: the nominal entry's ``covariance_sensor.pt``),
or a folder's, with the observer's where the folder has none for the case."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def paper_sets(load_script):
    return load_script("benchmarks/calibration_paper_sets.py")


def _arg(command: list[str], key: str) -> str:
    return next(a.split("=", 1)[1] for a in command if a.startswith(key + "="))


def test_the_zoo_s_readout_of_each_system_is_scored(paper_sets, tmp_path):
    sensor = paper_sets._command("sensor", tmp_path, None, ekf=False)
    assert _arg(sensor, "eval.checkpoint") == "zoo:rigid_body/nominal"
    assert _arg(sensor, "eval.covariance") == "zoo:rigid_body/nominal/covariance_sensor.pt"
    assert _arg(sensor, "eval.baselines") == "[]"
    for case in ("nominal", "outliers"):
        command = paper_sets._command(case, tmp_path, None, ekf=True)
        assert _arg(command, "eval.covariance") == f"zoo:rigid_body/{case}"
        assert _arg(command, "eval.baselines") == "[ekf]"


def test_a_folder_without_the_sensor_readout_scores_the_nominal_one(paper_sets, tmp_path):
    (tmp_path / "nominal_covariance.pt").write_bytes(b"")
    covariance = _arg(paper_sets._command("sensor", tmp_path / "runs", tmp_path, True),
                      "eval.covariance")
    assert covariance == str(tmp_path / "nominal_covariance.pt")
    (tmp_path / "sensor_covariance.pt").write_bytes(b"")
    covariance = _arg(paper_sets._command("sensor", tmp_path / "runs", tmp_path, True),
                      "eval.covariance")
    assert covariance == str(tmp_path / "sensor_covariance.pt")
