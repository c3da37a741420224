"""The System contract (``manifold_nets.testing.check_system``) over every shipped system and
layout, and deliberately broken systems that it must catch, each by the property it breaks.

What is generic lives here (same seed -> same data, states on the group, rollout against step,
measurements against the model, noise entering, shapes, dtypes, batching, gradients); the
per-example test files keep each system's physics."""

from __future__ import annotations

import runpy
from pathlib import Path

import pytest
import torch

from manifold_nets_examples.attitude import Attitude
from manifold_nets_examples.broad.simulator import BroadSimulator
from manifold_nets_examples.planar import Planar
from manifold_nets_examples.rigid_body import MismatchedRigidBody, RigidBody
from manifold_nets.system import System
from manifold_nets.testing import CHECKS, check_rollout_matches_step, check_system

SCRIPT = Path(__file__).resolve().parents[1] / "docs" / "examples" / "minimal_system.py"
Turntable = runpy.run_path(str(SCRIPT), run_name="turntable_contract")["Turntable"]

SHIPPED = {
    "rigid_body-so3_r3": lambda: RigidBody(),
    "rigid_body-se3": lambda: RigidBody(pose_group="se3"),
    "rigid_body-rk45": lambda: RigidBody(integrator="rk45"),
    "rigid_body-mismatch-off": lambda: MismatchedRigidBody(),
    "attitude": lambda: Attitude(),
    "attitude-scaled_noise": lambda: Attitude(magnetic_noise=0.5, gyro_noise=2.0),
    "broad_sim": lambda: BroadSimulator(),
    "planar-se2": lambda: Planar(),
    "planar-so2_r2": lambda: Planar(pose_group="so2_r2"),
    "turntable": lambda: Turntable(),
}


@pytest.mark.parametrize("make", SHIPPED.values(), ids=SHIPPED.keys())
def test_every_shipped_system_keeps_the_contract(make):
    check_system(make())


# ------------------------------------------------------------------ broken systems it must catch


class RolloutOffStep(Turntable):
    """A 'fast' rollout with a slightly wrong step length."""

    def rollout(self, x0, drive, show_progress=False):
        states = [x0]
        for k in range(drive.shape[1]):
            states.append(self.step(states[-1], drive[:, k], dt=self.dt * 1.01))
        return torch.stack(states, dim=1)


class NoiseIgnored(Turntable):
    """apply_noise forgets the noise: every dataset is noise-free whatever sigma says."""

    def apply_noise(self, measurements, noise):
        return measurements


class NoiseDroppedByMeasure(Turntable):
    """The older form, measure written by hand, dropping the noise."""

    def measure(self, x, drive, noise=None):
        return self.observe(x, drive)


class OffTheGroup(Turntable):
    """A step that scales the rotation: R exp(omega dt) * 1.001 is no rotation."""

    def step(self, x, drive, dt=None):
        return super().step(x, drive, dt) * 1.001


class GlobalRandomDrive(Turntable):
    """A sampler that draws from torch's global generator instead of the one it is given."""

    def sample_drive(self, num_sequences, length, generator):
        return (2 * torch.rand(num_sequences, length, 1, dtype=torch.float64) - 1) * self.rate_range


class TensorConfig(Turntable):
    def config(self):
        return {"dt": torch.tensor(self.dt), "rate_range": self.rate_range}


class Float64Constant(Turntable):
    """A float64 constant promotes float32 inputs."""

    def observe(self, x, drive):
        return super().observe(x, drive) * torch.ones(3, dtype=torch.float64)


class NoBroadcast(Turntable):
    def observe(self, x, drive):
        return torch.cat((x[..., :, 0], drive), dim=-1)


class DetachedStep(Turntable):
    """A step a filter cannot linearise: the drive is detached."""

    def step(self, x, drive, dt=None):
        return super().step(x, drive.detach(), dt)


class NoiseAtZero(Turntable):
    """Zero noise is not the noise-free model."""

    def apply_noise(self, measurements, noise):
        return measurements + noise + 1e-3


class ExtraNoiseDims(Turntable):
    """Declares more noise than the measurement uses: noise_dim 3 + 1 unused entry."""

    noise_dim = 4

    def apply_noise(self, measurements, noise):
        return measurements + noise[..., :3]


BROKEN = [
    (RolloutOffStep, "rollout_matches_step", "rollout disagrees with step at k=1"),
    (NoiseIgnored, "noise_enters", "noise component(s) [0, 1, 2] of 3 do not change"),
    (NoiseDroppedByMeasure, "noise_enters", "do not change the measurement"),
    (OffTheGroup, "on_group", "is off the group"),
    (GlobalRandomDrive, "determinism", "simulate drew from torch's global random generator"),
    (TensorConfig, "config", "config() is not JSON-able"),
    (Float64Constant, "dtypes", "in torch.float32 returned torch.float64"),
    (NoBroadcast, "batching", "measure of states (3, 1, 2, 2) and drives (1, 3, 1) raised"),
    (DetachedStep, "gradients", "step fails gradcheck"),
    (NoiseAtZero, "measure_matches_model", "measure(x, w, zeros) differs from measure(x, w)"),
    (ExtraNoiseDims, "noise_enters", "noise component(s) [3] of 4"),
]


@pytest.mark.parametrize("cls, prop, found", BROKEN, ids=[b[0].__name__ for b in BROKEN])
def test_a_broken_system_fails_with_the_property_it_breaks(cls, prop, found):
    with pytest.raises(AssertionError) as info:
        check_system(cls())
    lines = [line for line in str(info.value).splitlines() if line.startswith(f"- {prop}: ")]
    assert lines, f"{prop} not among the failures:\n{info.value}"
    assert cls.__name__ in lines[0] and found in lines[0] and "Fix: " in lines[0]


def test_the_failures_name_the_fix_and_only_the_broken_properties():
    with pytest.raises(AssertionError) as info:
        check_system(RolloutOffStep())
    msg = str(info.value)
    assert msg.startswith("check_system(RolloutOffStep(dt=0.1, rate_range=1.0)): 1 of 11")
    assert "an overridden rollout must agree with step" in msg


def test_one_property_alone_and_a_subset():
    with pytest.raises(AssertionError, match=r"^rollout_matches_step: RolloutOffStep"):
        check_rollout_matches_step(RolloutOffStep())
    check_system(RolloutOffStep(), checks=[c for c in CHECKS if c != "rollout_matches_step"])


def test_an_exception_inside_a_check_is_that_checks_failure():
    class Crashes(Turntable):
        def inputs(self, drive):
            raise RuntimeError("boom")

    with pytest.raises(AssertionError, match=r"- shapes: Crashes.*raised RuntimeError: boom"):
        check_system(Crashes(), checks=["shapes"])


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="unknown checks"):
        check_system(Turntable(), checks=["rollout"])
    with pytest.raises(ValueError, match="sigma must be finite and > 0"):
        check_system(Turntable(), sigma=0.0)
    with pytest.raises(ValueError, match="length must be a positive integer"):
        check_system(Turntable(), length=0)


# ------------------------------------------------------------------ the noise rule of the base


class AdditiveWalk(System):
    """x' = x + w on R^2, y = x + nu: writes observe only; the base adds the noise."""

    name = "walk"
    measurement_dim = drive_dim = input_dim = noise_dim = 2
    dt = 1.0

    def __init__(self):
        from groups import Euclidean

        self.group = Euclidean(2)

    def config(self):
        return {}

    def sample_initial_state(self, n, generator):
        return torch.randn(n, 2, generator=generator, dtype=torch.float64)

    def sample_drive(self, n, length, generator):
        return torch.randn(n, length, 2, generator=generator, dtype=torch.float64)

    def step(self, x, drive, dt=None):
        return x + drive

    def observe(self, x, drive):
        return x.expand(torch.broadcast_shapes(x.shape, drive.shape))


def test_measure_is_derived_from_observe_and_apply_noise():
    walk = AdditiveWalk()
    check_system(walk)
    x, w = torch.ones(3, 2, dtype=torch.float64), torch.zeros(3, 2, dtype=torch.float64)
    nu = torch.full((3, 2), 0.5, dtype=torch.float64)
    assert torch.equal(walk.measure(x, w), x) and torch.equal(walk.measure(x, w, nu), x + nu)
    with pytest.raises(ValueError, match=r"AdditiveWalk expects the noise of shape \(\*batch, 2\)"):
        walk.measure(x, w, nu[:, :1])


def test_the_base_asks_for_apply_noise_when_it_cannot_know_the_noise():
    class Wider(AdditiveWalk):
        noise_dim = 3

    with pytest.raises(NotImplementedError, match=r"noise_dim=3 differs from measurement_dim=2.*"
                       r"write apply_noise\(measurements, noise\)"):
        Wider().measure(torch.ones(2), torch.zeros(2), torch.zeros(3))
    # a system writing measure itself gets observe from it, and no guessed noise rule
    legacy = NoiseDroppedByMeasure()
    assert torch.equal(legacy.observe(torch.eye(2), torch.ones(1)), torch.tensor([1.0, 0.0, 1.0]))
    with pytest.raises(NotImplementedError, match="overrides measure"):
        legacy.apply_noise(torch.zeros(3), torch.zeros(3))

    class Nothing(System):  # writes neither observe nor measure
        config = sample_initial_state = sample_drive = step = None

    with pytest.raises(TypeError, match="observe"):
        Nothing()
