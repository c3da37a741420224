"""The BROAD simulator (examples/broad/simulator.py): contract, sensor models, disturbances,
parameter errors and TRIAD."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from groups import SO3
from manifold_nets.testing import check_system
from manifold_nets_examples.broad.simulator import G0, M0, BroadSimulator

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "system" / "broad_sim.yaml"
QUIET = dict(hard_iron_probability=0.0, world_disturbance_probability=0.0)
AT_REST = dict(omega_rms=(0.0, 0.0), acc_rms=(0.0, 0.0), **QUIET)
EXACT_GYRO = dict(bias_std=0.0, bias_walk=0.0, gyro_noise=(0.0, 0.0, 0.0))


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def _expected(sim, R):
    """The undisturbed, noise-free (R^T up, R^T m_ref / M0), (..., 6)."""
    up = torch.tensor([0.0, 0.0, 1.0], dtype=R.dtype)
    m = sim.magnetic_field(R.dtype) / M0
    return torch.cat(((up @ R), (m @ R)), dim=-1)


@pytest.mark.parametrize("kwargs", [{}, QUIET, dict(rest_probability=1.0, level_fraction=0.0)],
                         ids=["defaults", "undisturbed", "rest-haar"])
def test_contract(kwargs):
    check_system(BroadSimulator(**kwargs))


def test_config_is_json_and_rebuilds_the_system_and_matches_the_yaml():
    sim = BroadSimulator()
    cfg = json.loads(json.dumps(sim.config()))
    assert BroadSimulator(**cfg).config() == cfg
    yaml = OmegaConf.to_container(OmegaConf.load(CONFIG))
    assert yaml.pop("_target_") == "manifold_nets_examples.broad.simulator.BroadSimulator"
    assert yaml == cfg  # every parameter, at the measured defaults


def test_layout_and_rate():
    sim = BroadSimulator()
    assert (sim.measurement_dim, sim.input_dim, sim.drive_dim, sim.noise_dim) == (6, 3, 18, 6)
    assert sim.dt == pytest.approx(1 / 285.714) and isinstance(sim.group, SO3)
    assert (G0, M0) == (9.81, 44.0)


def test_at_rest_the_sensors_read_up_and_the_field_within_noise():
    sim = BroadSimulator(**AT_REST)
    data = sim.simulate(200, 20, 1.0, _gen())
    R = data.states
    assert torch.allclose(R[:, 1:], R[:, :1].expand_as(R[:, 1:]), atol=1e-12)  # no motion
    resid = data.measurements - _expected(sim, R[:, 1:])
    scale = sim.noise_scale()
    # the noise is the real IMU's at sigma = 1, per axis
    assert torch.allclose(resid.reshape(-1, 6).std(0), scale, rtol=0.05)
    assert float((resid.abs() / scale).max()) < 6.0
    # the field model: |m| 43.7 uT, 69.5 deg dip, horizontal part north (+y)
    m = sim.magnetic_field()
    assert float(m[0]) == 0 and float(m[1]) > 0 and float(m[2]) < 0
    assert math.degrees(math.atan2(-m[2], m[1])) == pytest.approx(69.5)
    # the gyro reads bias + noise at rest
    assert float(data.inputs.abs().max()) < 0.05


def test_the_gyro_input_integrates_to_the_true_rotation_without_bias_and_noise():
    sim = BroadSimulator(**EXACT_GYRO)
    data = sim.simulate(8, 300, 0.0, _gen(1))
    R = data.states[:, 0]
    for k in range(data.length):
        R = R @ SO3().exp(data.inputs[:, k] * sim.dt)
    assert torch.allclose(R, data.states[:, -1], atol=1e-9)
    # with the default bias it drifts away
    biased = BroadSimulator().simulate(8, 300, 0.0, _gen(1))
    assert not torch.allclose(biased.inputs, data.inputs, atol=1e-4)


def test_rates_stay_below_max_rate_and_levels_start_level():
    sim = BroadSimulator(omega_rms=(9.0, 10.0), max_rate=12.0, level_fraction=1.0)
    g = _gen(2)
    R0 = sim.sample_initial_state(500, g)
    tilt = torch.rad2deg(torch.acos(R0[:, 2, 2].clamp(-1, 1)))
    assert float(tilt.max()) <= 3.0 + 1e-9
    heading = torch.atan2(R0[:, 1, 0], R0[:, 0, 0])  # spread over the circle
    assert float(heading.max() - heading.min()) > 5.0
    drive = sim.sample_drive(20, 200, g)
    assert float(drive[..., :3].norm(dim=-1).max()) <= 12.0 + 1e-9


def test_hard_iron_is_a_constant_body_offset_within_the_range():
    sim = BroadSimulator(**{**AT_REST, "hard_iron_probability": 1.0, "hard_iron_range": (0.2, 1.3)})
    data = sim.simulate(50, 30, 0.0, _gen(3))
    offset = data.measurements[..., 3:] - _expected(sim, data.states[:, 1:])[..., 3:]
    size = offset.norm(dim=-1)
    assert float(size.min()) >= 0.2 - 1e-9 and float(size.max()) <= 1.3 + 1e-9
    assert torch.allclose(offset, offset[:, :1].expand_as(offset), atol=1e-12)
    acc = data.measurements[..., :3] - _expected(sim, data.states[:, 1:])[..., :3]
    assert float(acc.abs().max()) < 1e-12  # the accelerometer does not see it


def test_a_world_disturbance_is_fixed_in_the_world_and_changes_over_time():
    sim = BroadSimulator(**{**QUIET, "world_disturbance_probability": 1.0})
    data = sim.simulate(50, 400, 0.0, _gen(4))
    R = data.states[:, 1:]
    world = (R @ data.measurements[..., 3:, None])[..., 0] * M0 - sim.magnetic_field()
    assert float(world.std(dim=1).mean()) > 0.5  # uT, varies in the world frame
    rms = float(world.pow(2).mean().sqrt()) / M0
    assert 0.1 < rms < 0.5  # ~ world_disturbance_rms = 0.25
    off = BroadSimulator(**QUIET).simulate(50, 400, 0.0, _gen(4))
    world = (off.states[:, 1:] @ off.measurements[..., 3:, None])[..., 0] * M0
    assert torch.allclose(world, sim.magnetic_field().expand_as(world), atol=1e-9)


def test_by_default_some_sequences_are_disturbed_and_some_not():
    sim = BroadSimulator()
    drive = sim.sample_drive(400, 10, _gen(5))
    body = drive[:, 0, 12:15].norm(dim=-1) > 0
    world = drive[:, :, 15:18].abs().amax(dim=(1, 2)) > 0
    assert 0.15 < float(body.double().mean()) < 0.35
    assert 0.15 < float(world.double().mean()) < 0.35


def test_linear_acceleration_enters_the_accelerometer_in_the_body_frame():
    sim = BroadSimulator(**QUIET)
    data = sim.simulate(4, 50, 0.0, _gen(6))
    g = _gen(6)  # the same draws as simulate: initial states, then drives
    x0, drive = sim.sample_initial_state(4, g), sim.sample_drive(4, 50, g)
    assert torch.allclose(x0, data.states[:, 0])
    up = torch.tensor([0.0, 0.0, G0], dtype=torch.float64)
    want = ((up + drive[..., 9:12])[..., None, :] @ data.states[:, 1:])[..., 0, :] / G0
    assert torch.allclose(data.measurements[..., :3], want, atol=1e-12)
    assert float(drive[..., 9:12].abs().max()) > 0.1  # it moves: |acc| departs from 1


def test_triad_recovers_the_attitude_from_noise_free_measurements():
    sim = BroadSimulator(**QUIET)
    R = SO3().random((100,), generator=_gen(7), dtype=torch.float64)
    y = _expected(sim, R)
    assert torch.allclose(sim.state_from_measurement(y), R, atol=1e-10)
    data = BroadSimulator(**AT_REST).simulate(20, 20, 1.0, _gen(8))  # the real IMU's noise
    err = sim.measurement_errors(data)["attitude_deg"]
    assert err.shape == (20, 20) and float(err.median()) < 2.5  # about 1 deg


@pytest.mark.parametrize(
    ("kwargs", "quoted"),
    [
        (dict(dt=0.0), "dt (the step length in seconds) must be a finite number > 0"),
        (dict(max_rate=1000.0), "one step must turn by less than pi. Lower max_rate"),
        (dict(omega_rms=(1.0, 30.0)), "exceeds max_rate=20.0; raise max_rate or lower omega_rms"),
        (dict(omega_rms=(2.0, 1.0)), "omega_rms (rad/s per axis) must be a range [lo, hi]"),
        (dict(omega_freq=(0.1, 200.0)), "at or above the Nyquist frequency"),
        (dict(gyro_noise=(0.1, 0.1)), "gyro_noise (rad/s) must be 3 finite numbers >= 0"),
        (dict(hard_iron_probability=1.5), "hard_iron_probability is a probability in [0, 1]"),
        (dict(magnetic_dip_deg=90.0), "magnetic_dip_deg must be in [0, 89]"),
        (dict(tilt_max_deg=200.0), "tilt_max_deg must be in [0, 180]"),
        (dict(num_terms=0), "num_terms must be a positive integer"),
        (dict(bias_std=-1.0), "bias_std (rad/s) must be a finite number >= 0"),
    ],
)
def test_bad_parameters_are_named_with_the_fix(kwargs, quoted):
    with pytest.raises(ValueError) as err:
        BroadSimulator(**kwargs)
    assert str(err.value).startswith("BroadSimulator") and quoted in str(err.value)
