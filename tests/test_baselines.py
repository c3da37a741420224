"""Baselines: the raw measurement, dead reckoning (generic), and the rigid body's complementary
filter and its grid search. Every estimator returns (N, T+1, *element_shape) on the group."""

from __future__ import annotations

import pytest
import torch

from manifold_nets_examples.rigid_body import RigidBody
from manifold_nets_examples.rigid_body.filters import (
    ComplementaryFilter,
    ComplementaryGains,
    RigidBodyEKF,
    tune_complementary_gains,
)
from groups import Euclidean
from manifold_nets.baselines import DeadReckoning, Estimator, RawMeasurement
from manifold_nets.data import TrajectoryDataset
from manifold_nets.system import System

F64 = torch.float64


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_raw_measurement_reads_the_measured_pose():
    sys = RigidBody()
    ds = sys.simulate(4, 20, 0.2, gen(0))
    est = RawMeasurement(sys).estimate(ds)
    assert est.shape == (4, 21, 18)
    torch.testing.assert_close(est[:, 0], sys.group.identity((4,), dtype=F64))
    torch.testing.assert_close(est[:, 1:, :12], ds.measurements[..., :12])
    assert float(est[:, 1:, 12:].abs().max()) == 0.0  # biases are not measured
    m, raw = sys.metrics(est, ds), sys.measurement_errors(ds)
    torch.testing.assert_close(m["R"][:, 1:], raw["R"])
    torch.testing.assert_close(m["p"][:, 1:], raw["p"])


def test_dead_reckoning_is_exact_without_noise_and_biases():
    sys = RigidBody(bias_range=0.0)
    ds = sys.simulate(3, 40, 0.0, gen(1))
    est = DeadReckoning(sys).estimate(ds)
    torch.testing.assert_close(est[:, 1:], ds.states[:, 1:], atol=1e-10, rtol=0)


def test_dead_reckoning_drifts_with_biases():
    sys = RigidBody()
    ds = sys.simulate(8, 60, 0.0, gen(2))
    err = sys.metrics(DeadReckoning(sys).estimate(ds), ds)["p"]
    assert float(err[:, 50:].mean()) > 5 * float(err[:, 2:5].mean())


def test_estimators_share_the_interface_and_stay_on_the_group():
    sys = RigidBody()
    ds = sys.simulate(3, 25, 0.3, gen(3)).to(torch.float32)
    for est in (
        RawMeasurement(sys),
        DeadReckoning(sys),
        ComplementaryFilter(sys),
        RigidBodyEKF(sys, 0.3),
    ):
        assert isinstance(est, Estimator)
        x = est.estimate(ds)
        assert x.shape == (3, 26, 18) and x.dtype == torch.float32
        assert torch.isfinite(x).all()
        assert float(sys.group.membership_error(x).max()) < 1e-4, est.name


def test_complementary_filter_learns_the_biases():
    sys = RigidBody()
    ds = sys.simulate(8, 150, 0.05, gen(4))
    est = ComplementaryFilter(
        sys, ComplementaryGains(k_P=4.0, k_I=16.0, k_p=2.0, k_b=4.0)
    ).estimate(ds)
    m, raw = sys.metrics(est, ds), sys.measurement_errors(ds)
    for name in ("b_omega", "b_v"):
        assert float(m[name][:, 120:].mean()) < 0.1 * float(m[name][:, 1].mean()), name
    assert float(m["R"][:, 120:].mean()) < float(raw["R"][:, 119:].mean())


def test_complementary_gains_per_sequence_equal_separate_runs():
    sys = RigidBody()
    ds = sys.simulate(2, 15, 0.2, gen(5))
    cf = ComplementaryFilter(sys)
    y = ds.measurements.repeat(2, 1, 1)
    both = cf.filter(
        y, {"k_P": torch.tensor([1.0, 1.0, 6.0, 6.0]), "k_I": 2.0, "k_p": 2.0, "k_b": 1.0}
    )
    a = cf.filter(ds.measurements, {"k_P": 1.0, "k_I": 2.0, "k_p": 2.0, "k_b": 1.0})
    b = cf.filter(ds.measurements, {"k_P": 6.0, "k_I": 2.0, "k_p": 2.0, "k_b": 1.0})
    torch.testing.assert_close(both, torch.cat((a, b)))


def test_grid_search_picks_the_best_pair():
    sys = RigidBody()
    grid = {"k_P": (1.0, 6.0), "k_I": (0.5, 16.0), "k_p": (1.0, 4.0), "k_b": (0.5, 4.0)}
    gains, scores = tune_complementary_gains(sys, 0.2, grid, num_sequences=4, length=60, seed=6)
    att, pos = scores["attitude"], scores["position"]
    assert len(att) == 4 and len(pos) == 4
    assert (gains.k_P, gains.k_I) == min(att, key=att.get)
    assert (gains.k_p, gains.k_b) == min(pos, key=pos.get)
    again, _ = tune_complementary_gains(sys, 0.2, grid, num_sequences=4, length=60, seed=6)
    assert again == gains  # reproducible from its seed


def test_clear_errors():
    sys = RigidBody()
    ds = sys.simulate(1, 3, 0.1, gen(7))
    other = TrajectoryDataset(ds.states, ds.measurements[..., :12], ds.inputs, dict(ds.meta))
    with pytest.raises(ValueError, match="another system"):
        RawMeasurement(sys).estimate(other)
    with pytest.raises(TypeError, match="TrajectoryDataset"):
        DeadReckoning(sys).estimate(ds.measurements)
    with pytest.raises(TypeError, match="RigidBody"):
        ComplementaryFilter(object())

    walk = RandomWalk()  # a system without state_from_measurement
    with pytest.raises(NotImplementedError, match="state_from_measurement"):
        RawMeasurement(walk).estimate(walk.simulate(1, 2, 0.1, gen(8)))
    u = torch.ones(2, 2, dtype=F64)
    assert torch.equal(walk.drive_from_measurement(torch.zeros(2, 2), u), u)


class RandomWalk(System):
    """``x' = x + w`` on ``R^2`` with the drive as input, ``y = x + nu``; no hooks overridden."""

    name = "walk"
    group = Euclidean(2)
    measurement_dim = input_dim = drive_dim = noise_dim = 2
    dt = 1.0

    def config(self):
        return {}

    def sample_initial_state(self, n, generator):
        return torch.zeros(n, 2, dtype=F64)

    def sample_drive(self, n, length, generator):
        return torch.randn(n, length, 2, generator=generator, dtype=F64)

    def step(self, x, drive, dt=None):
        return x + drive

    def measure(self, x, drive, noise=None):
        return x if noise is None else x + noise
