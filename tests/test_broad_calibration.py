"""The BROAD calibration command reads a recording the way its observer was trained to: the
pre-filters and the magnetometer setting of the observer's system (``input_settings``), on the
committed excerpt (tests/fixtures/broad/, CC-BY-4.0, see ATTRIBUTION.md)."""

from __future__ import annotations

from pathlib import Path

import torch

from manifold_nets import load_observer
from manifold_nets_examples.broad.calibration import _decimated
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
    got = _decimated([trial], system)
    assert torch.equal(got.measurements, want.measurements) and torch.equal(got.inputs, want.inputs)
    assert torch.equal(got.states, want.states) and torch.equal(got.mask, want.mask)
    assert not torch.equal(got.measurements, raw.measurements)  # the filter changed the readings


def test_a_6d_observer_is_calibrated_without_the_magnetometer():
    _, system, _ = load_observer("zoo:broad/attitude")
    system.magnetometer = False
    got = _decimated([read_trial(FIXTURE)], system)
    assert not got.measurements[..., 3:6].any() and got.measurements[..., :3].abs().sum() > 0
