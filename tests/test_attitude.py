"""The AHRS example on SO(3) x R^3: config, dataset, group membership, exact kinematics against an
ODE solver, the motion and bias laws, the measurement model and its noise law, TRIAD, metrics.
The generic contract (same seed -> same data, rollout against step, shapes, dtypes, batches,
gradients, the noise rule) is checked in tests/test_system_contract.py."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from scipy.integrate import solve_ivp

from manifold_nets_examples.attitude import Attitude
from manifold_nets_examples.attitude.filters import AttitudeEKF
from manifold_nets_examples.attitude.motion import random_sinusoids
from manifold_nets_examples.attitude.triad import triad
from groups import SO3
from manifold_nets.data import load_dataset
from manifold_nets import DatasetConfig, load_or_generate, make_dataset

F64 = torch.float64
CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def rot(x: torch.Tensor) -> torch.Tensor:
    return x[..., :9].unflatten(-1, (3, 3))


def rates_from_states(states: torch.Tensor, dt: float) -> torch.Tensor:
    """The held Omega_k from consecutive states (the inverse of the exact step)."""
    R = rot(states)
    return SO3().log(R[:, :-1].transpose(-1, -2) @ R[:, 1:]) / dt


def test_config_composes_and_generates_a_tiny_dataset(tmp_path):
    with initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        cfg = compose("generate", overrides=["system=attitude", "dataset=attitude_small"])
    system = instantiate(cfg.system)
    assert isinstance(system, Attitude)
    assert system.config() == Attitude().config()  # the yaml restates the defaults
    assert cfg.dataset.name == "attitude_small" and "inference" not in cfg.dataset
    dcfg = DatasetConfig(**dict(cfg.dataset))
    dcfg.num_sequences, dcfg.length, dcfg.cache_dir, dcfg.progress = 10, 6, str(tmp_path), False
    parts = load_or_generate(system, dcfg)
    assert sorted(parts) == ["test", "train", "val"]
    train = parts["train"]
    assert train.states.shape == (8, 7, 12) and train.measurements.shape == (8, 6, 9)
    assert train.inputs.shape == (8, 6, 0)
    ds = load_dataset(parts["train"].meta["path"], group=system.group)  # on the group, validated
    assert ds.meta["system"] == "attitude" and ds.meta["sigma"] == 0.1


def test_every_state_is_on_the_group_after_2000_steps():
    system = Attitude()
    ds = system.simulate(8, 2000, 0.0, gen(1))
    system.group.check_member(ds.states, atol=1e-12)
    # the bias is constant
    assert torch.equal(ds.states[:, :, 9:], ds.states[:, :1, 9:].expand(-1, 2001, -1))


def test_step_matches_an_ode_solver():
    system = Attitude(dt=0.1)
    ds = system.simulate(3, 15, 0.0, gen(2))
    omega = rates_from_states(ds.states, system.dt)
    for i in range(3):
        R = rot(ds.states[i, 0]).numpy()
        for k in range(15):
            w = omega[i, k].numpy()
            wx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
            sol = solve_ivp(lambda _t, y, wx=wx: (y.reshape(3, 3) @ wx).ravel(), (0, system.dt),
                            R.ravel(), method="DOP853", rtol=1e-12, atol=1e-12)
            R = sol.y[:, -1].reshape(3, 3)
            assert np.abs(R - rot(ds.states[i, k + 1]).numpy()).max() < 1e-9
    # and the rates recovered are the drive the simulator drew (same generator order)
    g = gen(2)
    system.sample_initial_state(3, g)
    torch.testing.assert_close(omega, system.sample_drive(3, 15, g), rtol=0, atol=1e-10)


def test_step_overrides_dt_and_checks_the_drive():
    # dtypes and batches: tests/test_system_contract.py
    system = Attitude()
    x = system.sample_initial_state(4, gen(3))
    w = torch.randn(4, 3, generator=gen(4), dtype=F64)
    two = system.step(system.step(x, w, dt=0.05), w, dt=0.05)
    torch.testing.assert_close(two, system.step(x, w), rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match=r"\(\*batch, 3\)"):
        system.step(x, w[:, :2])


def test_measurement_without_noise_is_the_model():
    system = Attitude()
    ds = system.simulate(16, 30, 0.0, gen(5))
    R1, y = rot(ds.states[:, 1:]), ds.measurements
    g, m = torch.tensor(system.gravity, dtype=F64), torch.tensor(system.magnetic, dtype=F64)
    torch.testing.assert_close(y[..., :3], torch.einsum("ntji,j->nti", R1, g), rtol=0, atol=1e-14)
    torch.testing.assert_close(y[..., 3:6], torch.einsum("ntji,j->nti", R1, m), rtol=0, atol=1e-14)
    # the gyro reading of y_{k+1} is the rate applied over k -> k+1, plus the bias
    omega = rates_from_states(ds.states, system.dt)
    torch.testing.assert_close(y[..., 6:], omega + ds.states[:, 1:, 9:], rtol=0, atol=1e-10)
    # unit default directions, 30 deg apart: the measured ones too
    torch.testing.assert_close(y[..., :6].unflatten(-1, (2, 3)).norm(dim=-1),
                               torch.ones(16, 30, 2, dtype=F64))
    angle = torch.acos((y[..., :3] * y[..., 3:6]).sum(-1))
    torch.testing.assert_close(angle, torch.full_like(angle, math.radians(30)))


def test_noise_law_and_per_sensor_scales():
    system = Attitude(gravity_noise=1.0, magnetic_noise=0.5, gyro_noise=2.0)
    sigma = 0.3
    noisy = system.simulate(400, 50, sigma, gen(6))
    clean = system.simulate(400, 50, 0.0, gen(6))
    res = (noisy.measurements - clean.measurements).reshape(-1, 9)
    scale = torch.tensor([1.0] * 3 + [0.5] * 3 + [2.0] * 3, dtype=F64)
    # 20000 samples per component: standard error of the std ~0.5 %, of the mean ~0.7 % of std
    assert (res.std(0) / (sigma * scale) - 1).abs().max() < 0.03
    assert (res.mean(0) / (sigma * scale)).abs().max() < 0.03
    corr = torch.corrcoef(res.T) - torch.eye(9, dtype=F64)
    assert corr.abs().max() < 0.04
    # measure is additive in the explicit noise
    x = system.sample_initial_state(5, gen(7))
    w, nu = torch.randn(5, 3, dtype=F64), torch.randn(5, 9, dtype=F64)
    torch.testing.assert_close(system.measure(x, w, nu) - system.measure(x, w), nu * scale)


def test_motion_law_is_smooth_with_the_stated_rms():
    dt, rms, fmax = 0.1, 1.3, 0.8
    w = random_sinusoids(3000, 60, 3, dt, rms, 0.05, fmax, 3, gen(8))
    assert w.shape == (3000, 60, 3) and w.dtype == F64
    # E[s^2] = rms^2 at every time; random amplitudes: the estimate's relative error ~2-3 %
    ms = w.pow(2).mean(dim=(0, 2))
    assert ((ms / rms**2) - 1).abs().max() < 0.12 and abs(float(ms.mean()) / rms**2 - 1) < 0.05
    assert w.mean().abs() < 0.05
    # smooth: a sum of sinusoids below fmax changes by at most 2 pi fmax sum|a| dt per step,
    # while white noise of the same rms would jump by ~1.4 rms
    jump = (w[:, 1:] - w[:, :-1]).abs().mean()
    assert jump < 2 * math.pi * fmax * dt * rms and jump < 0.5 * rms
    # the AHRS drive is this law
    drive = Attitude(omega_rms=rms, freq_max=fmax).sample_drive(3000, 60, gen(8))
    assert torch.equal(drive, w)


def test_initial_state_and_bias_laws():
    system = Attitude(bias_range=0.3)
    x0 = system.sample_initial_state(4000, gen(9))
    system.group.check_member(x0)
    R0, b = x0[:, :9], x0[:, 9:]
    assert R0.mean(0).abs().max() < 0.05 and (R0.var(0) - 1 / 3).abs().max() < 0.05  # Haar
    assert b.abs().max() <= 0.3 and (b.var(0) / 0.09 - 1 / 3).abs().max() < 0.03


def test_triad_recovers_the_attitude_and_stays_on_so3():
    system = Attitude()
    clean = system.simulate(10, 20, 0.0, gen(10))
    R = rot(clean.states[:, 1:])
    torch.testing.assert_close(system.triad(clean.measurements), R, rtol=0, atol=1e-13)
    errs = system.measurement_errors(clean)
    assert errs["R"].max() < 1e-13 and errs["attitude_deg"].max() < 1e-10
    noisy = system.simulate(10, 20, 0.2, gen(10))
    SO3().check_member(system.triad(noisy.measurements), atol=1e-12)
    # TRIAD keeps the first (gravity) direction exactly: R_triad^T g is the measured direction
    Rt = system.triad(noisy.measurements)
    g = torch.tensor(system.gravity, dtype=F64)
    y_g = torch.nn.functional.normalize(noisy.measurements[..., :3], dim=-1)
    torch.testing.assert_close(torch.einsum("ntji,j->nti", Rt, g), y_g)
    # physical-unit directions give the same rotation (only directions matter)
    torch.testing.assert_close(
        triad(y_g, noisy.measurements[..., 3:6], 9.81 * g, 48.0 * torch.tensor(system.magnetic)), Rt
    )
    err = system.measurement_errors(noisy)
    assert 3 < float(err["attitude_deg"].mean()) < 60  # a real, noisy baseline


def test_metrics_in_degrees_and_per_factor():
    system = Attitude()
    data = system.simulate(3, 8, 0.0, gen(11))
    exact = system.metrics(data.states, data)
    assert set(exact) == {"R", "b_omega", "attitude_deg"}
    assert all(float(v.abs().max()) < 1e-6 for v in exact.values())
    # turn every estimate by 10 deg about a fixed axis and shift the bias by (0.1, 0, 0)
    turn = SO3().exp(torch.tensor([0.0, math.radians(10.0), 0.0], dtype=F64))
    est = data.states.clone()
    est[..., :9] = (rot(est) @ turn).flatten(-2)
    est[..., 9] += 0.1
    m = system.metrics(est, data)
    torch.testing.assert_close(m["attitude_deg"], torch.full((3, 9), 10.0, dtype=F64))
    frob = 2 * math.sqrt(2) * math.sin(math.radians(5.0))  # ||R - R exp(theta)||_F
    torch.testing.assert_close(m["R"], torch.full((3, 9), frob, dtype=F64))
    torch.testing.assert_close(m["b_omega"], torch.full((3, 9), 0.1, dtype=F64))
    short = system.metrics(est[:, 1:].float(), data)  # (N, T) estimates, float32
    assert short["attitude_deg"].shape == (3, 8) and short["attitude_deg"].dtype == torch.float32


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"magnetic": [0.0, 0.0, -2.0]}, "collinear"),
        ({"gravity": [0.0, 0.0]}, "3-vector"),
        ({"freq_max": 6.0}, "Nyquist"),
        ({"dt": 0.0}, "dt"),
        ({"bias_range": -1.0}, "bias_range"),
        ({"num_terms": 0}, "num_terms"),
    ],
)
def test_bad_parameters_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Attitude(**kwargs)


def test_filter_hooks_read_the_state_and_the_drive_off_the_measurement():
    system = Attitude()
    data = system.simulate(4, 25, 0.0, gen(13))
    x0 = system.state_from_measurement(data.measurements)
    system.group.check_member(x0)
    torch.testing.assert_close(x0[..., :9], data.states[:, 1:, :9], rtol=0, atol=1e-13)
    assert torch.equal(x0[..., 9:], torch.zeros_like(x0[..., 9:]))
    # dead reckoning from the true start with the unbiased noise-free readings is the truth
    x = data.states[:, 0]
    for k in range(25):
        w = system.drive_from_measurement(data.measurements[:, k], data.inputs[:, k]) - x[:, 9:]
        x = system.step(x, w)
        torch.testing.assert_close(x, data.states[:, k + 1], rtol=0, atol=1e-12)


def test_ekf_is_consistent_stays_on_the_group_and_beats_triad():
    system = Attitude()
    data = make_dataset(system, 12, 60, sigma=0.1, seed=5)
    ekf = AttitudeEKF(system, 0.1)
    est = ekf.estimate(data)
    assert est.shape == data.states.shape
    system.group.check_member(est, atol=1e-12)
    x1, P1 = ekf.model.triad_prior(data.measurements[:, 0])
    nis = ekf.ekf.filter(data.measurements[:, 1:], x0=x1, P0=P1).nis
    assert 5.0 < float(nis[:, 10:].mean()) < 7.0  # 6 degrees of freedom: the model is right
    ours = system.metrics(est, data)["attitude_deg"][:, 10:].mean()
    triad_deg = system.measurement_errors(data)["attitude_deg"][:, 10:].mean()
    assert ours < 0.5 * triad_deg
    bias = system.metrics(est, data)["b_omega"]
    assert float(bias[:, -1].mean()) < 0.5 * float(data.states[:, 0, 9:].norm(dim=-1).mean())
    with pytest.raises(ValueError, match="sigma > 0"):
        AttitudeEKF(system, 0.0)


def test_experiment_trains_a_few_steps_evaluates_and_compares(tmp_path):
    from manifold_nets_examples.attitude.compare import attitude_estimators, compare_run, load_run
    from manifold_nets.evaluation import rollout
    from manifold_nets.cli.train import run

    tiny = [
        "experiment=attitude", "debug=tiny", f"dataset.cache_dir={tmp_path / 'data'}",
        "eval.plots=false",
    ]
    with initialize_config_dir(config_dir=CONFIGS, version_base="1.3"):
        cfg = compose("train", overrides=tiny)
    assert cfg.system._target_ == "manifold_nets_examples.attitude.system.Attitude"
    (row,) = run(cfg, tmp_path / "run")["table"]
    assert {"R est", "R meas", "b_omega est", "attitude_deg est", "attitude_deg meas"} <= set(row)
    assert row["membership max"] < 1e-12
    _, system, model = load_run(tmp_path / "run")
    data = system.simulate(3, 20, 0.1, gen(15))
    system.group.check_member(rollout(model, data), atol=1e-12)  # the estimates stay on SO(3)
    rows = compare_run(tmp_path / "run", attitude_estimators, plots=False)
    assert [r["method"] for r in rows] == [
        "learned", "ekf", "dead_reckoning", "measurement", "learned / ekf"]
    assert rows[0]["attitude_deg"] == pytest.approx(row["attitude_deg est"])


def test_a_step_that_can_turn_by_pi_is_refused_naming_the_parameters():
    """(Once accepted, with losses of 1e11.) Message: ``Attitude: one step can turn
    by up to sqrt(3) * (4 * omega_rms + bias_range) * dt = sqrt(3) * (4 * 1 + 0.2) * 0.5 =
    3.637 rad, which must be < pi ...; Use a smaller dt, omega_rms or bias_range (dt < 0.4319 s
    for these values).``"""
    with pytest.raises(
        ValueError,
        match=r"^Attitude: one step can turn by up to sqrt\(3\) \* \(4 \* omega_rms \+ "
        r"bias_range\) \* dt = sqrt\(3\) \* \(4 \* 1 \+ 0\.2\) \* 0\.5 = 3\.637 rad, which must "
        r"be < pi .* Use a smaller dt, omega_rms or bias_range \(dt < 0\.4319 s for these "
        r"values\)\.$",
    ):
        Attitude(dt=0.5, freq_max=0.9)
    with pytest.raises(ValueError, match=r"= sqrt\(3\) \* \(4 \* 50 \+ 0\.2\) \* 0\.1 = 34\.68"):
        Attitude(omega_rms=50.0)
    with pytest.raises(ValueError, match=r"\(4 \* 1 \+ 20\) \* 0\.1 = 4\.157 rad"):
        Attitude(bias_range=20.0)
    Attitude(dt=0.4, freq_max=0.9)  # just inside the bound: accepted
