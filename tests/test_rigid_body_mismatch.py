"""The mismatch benchmark's system and the EKF's tunable noise levels.

MismatchedRigidBody must be the nominal rigid body when every mismatch is off, keep its states
the same at every sigma, and draw each mismatch with the stated law; the EKF's noise levels
(reading_std, pose_std, bias_walk) must change what it does, and the grid search must run the
grid as one batch with the same result as one filter per grid point.
"""

from __future__ import annotations

import math

import pytest
import torch

from manifold_nets_examples.rigid_body import MismatchedRigidBody, RigidBody
from manifold_nets_examples.rigid_body.filters import RigidBodyEKF, tune_ekf_noise


def _sim(system, n=8, t=20, sigma=0.1, seed=3):
    return system.simulate(n, t, sigma, torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("sigma", [0.0, 0.2])
def test_with_every_mismatch_off_the_data_are_the_nominal_rigid_bodys_bit_for_bit(sigma):
    a, b = _sim(RigidBody(), sigma=sigma), _sim(MismatchedRigidBody(), sigma=sigma)
    assert torch.equal(a.states, b.states)
    assert torch.equal(a.measurements, b.measurements)
    assert b.meta["system"] == "rigid_body_mismatch" and b.meta["sigma"] == sigma


ALL_ON = dict(
    scale_factor=0.1, misalignment=0.05, bias_walk=0.05, noise_dof=3, outlier_prob=0.05,
    noise_correlation=0.5,
)


def test_states_and_sensor_errors_are_the_same_at_every_sigma():
    system = MismatchedRigidBody(**ALL_ON)
    quiet, noisy = _sim(system, sigma=0.0), _sim(system, sigma=0.3)
    assert torch.equal(quiet.states, noisy.states)  # what noise_level_mixture needs
    assert not torch.equal(quiet.measurements, noisy.measurements)


def test_the_pose_moves_as_the_nominal_bodys_only_the_readings_and_biases_differ():
    nominal, wrong = _sim(RigidBody(), sigma=0.0), _sim(MismatchedRigidBody(**ALL_ON), sigma=0.0)
    assert torch.equal(nominal.states[..., :12], wrong.states[..., :12])
    assert torch.equal(nominal.measurements[..., :12], wrong.measurements[..., :12])
    assert not torch.allclose(nominal.measurements[..., 12:], wrong.measurements[..., 12:])


def test_scale_factors_are_per_sequence_and_axis_with_the_stated_spread():
    system = MismatchedRigidBody(scale_factor=0.1)
    data = _sim(system, n=2000, t=5, sigma=0.0)
    nominal = _sim(RigidBody(), n=2000, t=5, sigma=0.0)
    drive = nominal.measurements[..., 12:] - nominal.states[:, 1:, 12:]
    ratio = (data.measurements[..., 12:] - data.states[:, 1:, 12:]) / drive  # 1 + s, per axis
    assert torch.allclose(ratio, ratio[:, :1].expand_as(ratio), atol=1e-9)  # constant in time
    s = ratio[:, 0] - 1
    assert abs(float(s.std()) - 0.1) < 0.01 and abs(float(s.mean())) < 0.01


def test_a_misalignment_rotates_the_readings_without_changing_their_length():
    system = MismatchedRigidBody(misalignment=0.05)
    data, nominal = _sim(system, n=200, sigma=0.0), _sim(RigidBody(), n=200, sigma=0.0)
    sensed = (data.measurements[..., 12:] - data.states[:, 1:, 12:]).unflatten(-1, (2, 3))
    true = (nominal.measurements[..., 12:] - nominal.states[:, 1:, 12:]).unflatten(-1, (2, 3))
    assert torch.allclose(sensed.norm(dim=-1), true.norm(dim=-1), atol=1e-12)
    cos = (sensed * true).sum(-1) / (sensed.norm(dim=-1) * true.norm(dim=-1))
    assert float(cos.min()) < 1 - 1e-5  # turned ...
    assert float(cos.min()) > math.cos(0.5)  # ... by a small angle


def test_the_bias_walk_has_independent_increments_of_the_stated_size():
    system = MismatchedRigidBody(bias_walk=0.2)
    data = _sim(system, n=400, t=50, sigma=0.0)
    steps = data.states[:, 1:, 12:] - data.states[:, :-1, 12:]
    assert abs(float(steps.std()) - 0.2 * math.sqrt(system.dt)) < 0.003
    lag1 = float((steps[:, 1:] * steps[:, :-1]).mean() / steps.var())
    assert abs(lag1) < 0.02
    # the readings carry the bias of the state they are taken at
    nominal = _sim(RigidBody(), n=400, t=50, sigma=0.0)
    drive = nominal.measurements[..., 12:] - nominal.states[:, 1:, 12:]
    assert torch.allclose(data.measurements[..., 12:], drive + data.states[:, 1:, 12:], atol=1e-12)


def _kurtosis(x: torch.Tensor) -> float:
    """E[(x - m)^4] / var^2: 3 for Gaussian noise, 3 (1 - p + p k^4) / (1 - p + p k^2)^2 = 42.5
    for 5 % outliers 10x larger, 9 for Student-t with 5 degrees of freedom."""
    x = x.flatten()
    return float(((x - x.mean()) ** 4).mean() / x.var() ** 2)


@pytest.mark.parametrize(
    "law, kurtosis",
    [({}, (2.9, 3.1)), ({"noise_dof": 5}, (5.0, 15.0)), ({"outlier_prob": 0.05}, (38.0, 48.0))],
    ids=["gaussian", "student_t", "outliers"],
)
def test_each_noise_law_has_variance_sigma_squared_or_its_outliers_and_its_tails(law, kurtosis):
    system = MismatchedRigidBody(**law)
    e = system.sample_noise(2000, 100, 0.3, torch.Generator().manual_seed(0))
    assert e.shape == (2000, 100, 12)
    want = 0.09 * (1 + 0.05 * (10.0**2 - 1) if "outlier_prob" in law else 1)
    assert abs(float(e.var()) / want - 1) < 0.1
    lo, hi = kurtosis
    assert lo < _kurtosis(e) < hi


def test_correlated_noise_is_an_ar1_process_of_variance_sigma_squared():
    system = MismatchedRigidBody(noise_correlation=0.8)
    e = system.sample_noise(500, 200, 0.5, torch.Generator().manual_seed(0))
    assert abs(float(e.var()) / 0.25 - 1) < 0.05
    for lag in (1, 3):
        r = float((e[:, lag:] * e[:, :-lag]).mean() / e.var())
        assert abs(r - 0.8**lag) < 0.03


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"scale_factor": -0.1}, "scale_factor must be a finite number >= 0"),
        ({"misalignment": 1.0}, "must be <= 0.25"),
        ({"noise_dof": 2}, "noise_dof must be 0 .* or an integer >= 3"),
        ({"noise_dof": 3.5}, "noise_dof"),
        ({"outlier_prob": 1.0}, r"outlier_prob must be in \[0, 1\)"),
        ({"outlier_scale": 0.5}, "outlier_scale must be >= 1"),
        ({"noise_correlation": 1.0}, r"noise_correlation is an AR\(1\) coefficient"),
        ({"bias_walk": float("nan")}, "bias_walk must be a finite number"),
    ],
)
def test_bad_mismatch_parameters_are_refused_with_their_name(kwargs, match):
    with pytest.raises(ValueError, match=match):
        MismatchedRigidBody(**kwargs)


def test_the_config_names_every_mismatch_so_cached_files_differ():
    a, b = MismatchedRigidBody().config(), MismatchedRigidBody(bias_walk=0.1).config()
    assert set(a) - set(RigidBody().config()) == {
        "scale_factor", "misalignment", "bias_walk", "noise_dof", "outlier_prob",
        "outlier_scale", "noise_correlation",
    }
    assert a != b


# ------------------------------------------------------------------ the EKF's noise levels


def test_the_ekf_defaults_to_the_nominal_noise_and_a_bias_walk_adds_state_noise():
    system = RigidBody()
    nominal = RigidBodyEKF(system, 0.1)
    same = RigidBodyEKF(system, 0.1, reading_std=0.1, pose_std=0.1, bias_walk=0.0)
    data = _sim(system, n=4, t=30)
    assert torch.equal(nominal.estimate(data), same.estimate(data))
    assert nominal.model.state_noise_cov(torch.float64) is None
    Qe = RigidBodyEKF(system, 0.1, bias_walk=0.3).model.state_noise_cov(torch.float64)
    assert torch.allclose(Qe.diagonal()[6:], torch.full((6,), 0.09 * system.dt, dtype=torch.float64))
    assert torch.equal(Qe.diagonal()[:6], torch.zeros(6, dtype=torch.float64))


def test_an_ekf_told_of_the_bias_walk_tracks_drifting_biases_better():
    system = MismatchedRigidBody(bias_walk=0.1)
    data = _sim(system, n=16, t=300)
    err = {}
    for walk in (0.0, 0.1):
        est = RigidBodyEKF(system, 0.1, bias_walk=walk).estimate(data)
        err[walk] = float(system.metrics(est, data)["R"][:, 10:].mean())
    assert err[0.1] < 0.5 * err[0.0]


def test_the_batched_grid_search_equals_one_filter_per_grid_point():
    system = MismatchedRigidBody(noise_correlation=0.8)
    grid = {"reading_scale": (1.0, 4.0), "pose_scale": (1.0, 2.0), "bias_walk": (0.0, 0.03)}
    choice, scores = tune_ekf_noise(system, 0.2, grid=grid, num_sequences=3, length=40, seed=7)
    assert len(scores) == 8
    data = system.simulate(3, 40, 0.2, torch.Generator().manual_seed(7))
    for (r, p, w), score in list(scores.items())[::3]:
        ekf = RigidBodyEKF(system, 0.2, reading_std=r * 0.2, pose_std=p * 0.2, bias_walk=w)
        e = system.metrics(ekf.estimate(data), data)
        assert abs(float((e["R"] + e["p"])[:, 10:].mean()) - score) < 1e-9
    best = min(scores, key=scores.get)
    assert choice == {"reading_std": best[0] * 0.2, "pose_std": best[1] * 0.2, "bias_walk": best[2]}


def test_bad_ekf_noise_levels_are_refused_with_their_name():
    with pytest.raises(ValueError, match="pose_std must be a finite number > 0"):
        RigidBodyEKF(RigidBody(), 0.1, pose_std=0.0)
    with pytest.raises(ValueError, match="bias_walk must be a finite number >= 0"):
        RigidBodyEKF(RigidBody(), 0.1, bias_walk=-1.0)


def test_ekf_tuned_is_a_method_of_the_rigid_body():
    assert "ekf_tuned" in RigidBody().estimators()
    assert "ekf_tuned" in MismatchedRigidBody().estimators()


def test_the_gated_ekf_resists_outliers_and_costs_nothing_on_gaussian_noise():
    """method=ekf_robust, steps >= 60 of 24 x 200 at sigma 0.3: measured R -8 % / p -19 % on the
    outlier law, and +0.03 % / +0.06 % on the nominal body's Gaussian noise."""
    assert "ekf_robust" in RigidBody().estimators()
    outliers = MismatchedRigidBody(noise_dof=3, outlier_prob=0.05, outlier_scale=10.0)
    for system, most in ((outliers, (0.97, 0.9)), (RigidBody(), (1.005, 1.005))):
        data = _sim(system, n=24, t=200, sigma=0.3)
        err = []
        for ekf in (RigidBodyEKF(system, 0.3), RigidBodyEKF.robust(system, 0.3)):
            ekf.ekf.progress = False
            m = system.metrics(ekf.estimate(data), data)
            err.append([float(m[k][:, 60:].mean()) for k in ("R", "p")])
        (r0, p0), (r1, p1) = err
        assert r1 < most[0] * r0 and p1 < most[1] * p0, (type(system).__name__, err)
    assert "gate=16.8119, gate_after=50" in repr(RigidBodyEKF.robust(RigidBody(), 0.1))


def test_the_gate_is_the_chi_square_99_percent_point_for_the_pose():
    from scipy.stats import chi2

    from manifold_nets_examples.rigid_body.filters import CHI2_99_6DOF

    assert abs(chi2.ppf(0.99, 6) - CHI2_99_6DOF) < 1e-4
