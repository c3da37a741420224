"""``benchmarks/calibration_in_band.py``: its ``--level-scale`` file is the one fitted over the
readout that scores the case (the sensor errors' own where ``--readouts`` has one, else the
nominal observer's), and a missing one is refused before any case is scored."""

from __future__ import annotations

import json
import shutil

import pytest


@pytest.fixture(scope="module")
def in_band(load_script):
    return load_script("benchmarks/calibration_in_band.py")


def _folder(path, files):
    from manifold_nets.plugins import zoo_path

    path.mkdir()
    for name, zoo_file in files.items():
        shutil.copy(zoo_path("rigid_body/nominal") / zoo_file, path / name)
    return path


def test_the_level_scale_follows_the_readout_that_scores_the_case(in_band, tmp_path):
    """The zoo's files hold each readout's own level scale, so ``--level-scale`` on a folder of
    them must give, readout by readout, what the file alone gives: the sensor readout with the
    sensor level scale, the nominal one (a folder without a sensor file) with the nominal's."""
    readouts = _folder(tmp_path / "readouts", {"nominal_covariance.pt": "covariance.pt"})
    scales = _folder(tmp_path / "scales", {"nominal_covariance.pt": "covariance.pt",
                                           "sensor_covariance.pt": "covariance_sensor.pt"})

    def row(name, *level_scale):
        out = tmp_path / name
        in_band.main(["--cases", "sensor", "--sigmas", "0.1", "--test", "2", "--readouts",
                      str(readouts), *level_scale, "--write", str(out)])
        return json.loads(out.with_suffix(".json").read_text())["cases"]["sensor"]["R 0.1"]

    for own in (False, True):
        if own:
            shutil.copy(scales / "sensor_covariance.pt", readouts / "sensor_covariance.pt")
        alone = row(f"file_{own}")  # the readout with the level scale its file holds
        beside = row(f"scale_{own}", "--level-scale", str(scales))
        assert beside["level scale anees"] == pytest.approx(alone["anees"], rel=1e-12), own
        assert beside["anees"] != alone["anees"]  # the column beside it: the readout alone


def test_a_missing_level_scale_is_refused_before_any_case_is_scored(in_band, tmp_path):
    scales = _folder(tmp_path / "scales", {"nominal_covariance.pt": "covariance.pt"})
    with pytest.raises(SystemExit, match="sensor_covariance.pt.*--cases sensor"):
        in_band.main(["--cases", "nominal", "sensor", "--test", "2", "--level-scale",
                      str(scales), "--write", str(tmp_path / "never")])
    assert not (tmp_path / "never.json").exists()
