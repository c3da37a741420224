"""The trained observers shipped for the paper's rigid body and the mismatch benchmark
(examples/rigid_body/pretrained/, docs/comparison.md): each loads from its folder without
executing anything the files name, fits under 5 MB, and is trained: on fresh data of its own
system it beats the raw measurement (an untrained network is as far off as a random
rotation, 2.4)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import manifold_nets_examples.rigid_body  # noqa: F401  registers RigidBody and MismatchedRigidBody
from manifold_nets import load_observer

SHIPPED = Path(__file__).parents[1] / "examples" / "rigid_body" / "pretrained"
NAMES = [
    "paper_cpu_relative_long1000",
    "paper_cpu_prior_long1000",
    "paper_cpu_prior_log_bptt1000",
    "paper_cpu_prior_centred07_skip10_plus4",
    "paper_cpu_prior_centred085_ramp50_cosine2",
    "paper_cpu_prior_centred085_ramp50_cosine24",
    "paper_cpu_prior_centred085_bias097_cosine16",
    "paper_cpu_prior_centred085_bias097_decay16_frame_factor_log",
    "paper_cpu_prior_centred085_low2_bv099_k70",
    "paper_cpu_prior_robust16",
    "mismatch_bias_walk_prior_long1000",
    "mismatch_bias_walk",
    "mismatch_outliers",
    "mismatch_correlated",
    "mismatch_sensor",
    "mismatch_outliers_prior_log_bptt1000",
    "mismatch_correlated_prior_bptt1000_mse",
    "mismatch_correlated_prior_log_cosine2",
    "mismatch_sensor_prior_log_bptt1000",
    "mismatch_outliers_long_bptt1000_log",
    "mismatch_outliers_long_bptt1000_log_skip10",
    "mismatch_outliers_long_bptt1000_log_cosine3",
    "mismatch_outliers_prior_robust16",
    "mismatch_sensor_prior_robust16",
    "mismatch_correlated_prior_robust16_plus8",
]


@pytest.mark.parametrize("name", NAMES)
def test_a_shipped_observer_loads_and_beats_the_raw_measurement_on_its_system(name):
    folder = SHIPPED / name
    assert (folder / "checkpoints" / "best.pt").stat().st_size < 5 * 2**20
    observer, system, config = load_observer(folder)
    assert config.name == name
    data = system.simulate(32, 150, 0.4, torch.Generator().manual_seed(123))
    with torch.no_grad():
        est = observer(data.measurements)
    errors = system.metrics(est, data)
    raw = system.measurement_errors(data)
    for factor in ("R", "p"):
        learned, measured = float(errors[factor][:, 10:].mean()), float(raw[factor][:, 10:].mean())
        assert learned < 0.85 * measured, (name, factor, learned, measured)
    assert float(errors["b_omega"][:, 10:].mean()) < 1.0  # the biases are drawn from +-10
