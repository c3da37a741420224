"""The BROAD calibration command reads a recording the way its observer was trained to: the
pre-filters and the magnetometer setting of the observer's system (``input_settings``), on the
committed excerpt (tests/fixtures/broad/, CC-BY-4.0, see ATTRIBUTION.md)."""

from __future__ import annotations

from pathlib import Path

import torch

from manifold_nets import load_observer
from manifold_nets_examples.broad.calibration import observer_readings
from manifold_nets_examples.broad.data import read_trial
from manifold_nets_examples.broad.evaluate import decimation, input_settings, pad_trials
from manifold_nets_examples.broad.prefilter import prefiltered
from manifold_nets_examples.broad.rate import decimate

FIXTURE = Path(__file__).parent / "fixtures" / "broad" / "excerpt.mat"


def test_the_zoo_observer_is_calibrated_on_the_readings_it_was_trained_on():
    _, system, _ = load_observer("zoo:broad/attitude")
    reads = input_settings(system)
    assert reads["rest_bias"] and reads["acc_lowpass"] > 0  # the shipped entry reads pre-filtered data
    trial = read_trial(FIXTURE)
    k = decimation(system, trial.rate)
    raw = decimate(pad_trials([trial])[0], k, 1.0 / trial.rate)
    want = decimate(
        pad_trials([prefiltered(trial, reads["acc_lowpass"], reads["rest_bias"],
                                reads["acc_lowpass_order"])])[0], k, 1.0 / trial.rate
    )
    got = observer_readings([trial], system)
    assert torch.equal(got.measurements, want.measurements) and torch.equal(got.inputs, want.inputs)
    assert torch.equal(got.states, want.states) and torch.equal(got.mask, want.mask)
    assert not torch.equal(got.measurements, raw.measurements)  # the filter changed the readings


def test_a_6d_observer_is_calibrated_without_the_magnetometer():
    _, system, _ = load_observer("zoo:broad/attitude")
    system.magnetometer = False
    got = observer_readings([read_trial(FIXTURE)], system)
    assert not got.measurements[..., 3:6].any() and got.measurements[..., :3].abs().sum() > 0


def test_the_zoo_ensemble_is_calibrated_by_its_readings_and_a_hidden_readout_is_refused(tmp_path):
    """An ensemble's members have no one core: a hidden-state readout is refused before any
    data is read, naming the two ways that work."""
    import pytest

    from manifold_nets_examples.broad.calibration import main

    with pytest.raises(SystemExit, match="--sources readings, or give one member's run folder"):
        main(["--out", str(tmp_path / "c"), "--sources", "hidden", "--data-dir", str(tmp_path)])
    assert not (tmp_path / "c").exists()


def test_block_spread_reads_the_raw_samples_of_each_observer_step():
    """Step j covers samples jk+1 .. (j+1)k (as decimate's measurement and rate do): a shaken
    block shows in its own step only, on the axis shaken; the pre-filters play no part."""
    import numpy as np

    from manifold_nets_examples.broad.calibration import block_spread
    from manifold_nets_examples.broad.data import Trial

    T, k = 8 * 5 + 3, 8
    acc = np.tile([0.0, 0.0, 9.81], (T, 1))
    gyr = np.zeros((T, 3))
    acc[2 * k + 1 : 3 * k + 1, 0] += np.tile([3.0, -3.0], k // 2)  # step 2's block, +-3 m/s^2
    gyr[4 * k + 1 : 5 * k + 1, 1] = np.linspace(0, 0.7, k)  # step 4's block
    trial = Trial("t", gyr, acc, np.zeros((T, 3)), np.tile([1.0, 0, 0, 0], (T, 1)),
                  np.ones(T, bool), 285.7)
    c = block_spread(trial, k)
    assert c.shape == ((T - 1) // k, 2) and c.dtype == np.float32
    np.testing.assert_allclose(np.exp(c[2, 0]) - 1e-3, 3.0, rtol=1e-6)
    assert np.all(np.delete(c[:, 0], 2) == np.float32(np.log(1e-3)))
    np.testing.assert_allclose(np.exp(c[4, 1]) - 1e-4, np.linspace(0, 0.7, k).std(), rtol=1e-5)
    assert np.all(np.delete(c[:, 1], 4) == np.float32(np.log(1e-4)))
