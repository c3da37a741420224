"""The EKF with the AR(1) noise in its state (method=ekf_ar1), the correlated-noise mismatch's
oracle row: the nominal EKF at rho = 0, analytic Jacobians = autograd, better than the nominal
EKF on correlated data, consistent there, and its errors."""

from __future__ import annotations

import math

import pytest
import torch

from manifold_nets.ekf import ErrorStateEKF
from manifold_nets_examples.rigid_body import MismatchedRigidBody, RigidBody
from manifold_nets_examples.rigid_body.correlated_noise import (
    CorrelatedNoiseEKF,
    CorrelatedNoiseFilterModel,
)
from manifold_nets_examples.rigid_body.filters import RigidBodyEKF


def _quiet(est):
    est.ekf.progress = False
    return est


def _errors(system, est, data, skip=10):
    m = system.metrics(_quiet(est).estimate(data), data)
    return {k: float(v[:, skip:].mean()) for k, v in m.items()}


def test_with_white_noise_it_is_the_nominal_ekf_with_the_floor_added():
    system = MismatchedRigidBody()  # rho = 0
    data = system.simulate(6, 60, 0.2, torch.Generator().manual_seed(2))
    ar = _quiet(CorrelatedNoiseEKF(system, 0.2)).estimate(data)
    floored = RigidBodyEKF(system, 0.2, pose_std=0.2 * math.sqrt(1 + 0.01**2))
    nominal = _quiet(floored).estimate(data)
    assert ar.shape == nominal.shape == data.states.shape
    torch.testing.assert_close(ar, nominal, rtol=0, atol=1e-10)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_analytic_jacobians_are_autograds(seed):
    system = MismatchedRigidBody(noise_correlation=0.8)
    model = CorrelatedNoiseFilterModel(system, 0.3, 0.8)
    g = torch.Generator().manual_seed(seed)
    data = system.simulate(5, 3, 0.3, g)
    base = data.states[:, 1]
    noise = 0.4 * torch.randn(5, 12, generator=g, dtype=torch.float64)
    x = torch.cat((base, noise), dim=-1)
    y = data.measurements[:, 1]
    u = y.new_zeros(5, 0)
    ekf = ErrorStateEKF(model)
    F, G = model.process_jacobians(x, y, u)
    Fa, Ga = ekf.process_jacobians(x, y, u)
    torch.testing.assert_close(F, Fa, rtol=0, atol=1e-10)
    torch.testing.assert_close(G, Ga, rtol=0, atol=1e-10)
    drive = model.drive(x, y, u)
    H, M = model.measurement_jacobians(x, drive)
    Ha, Ma = ekf.measurement_jacobians(x, drive, model.measure(x, drive), 6)
    torch.testing.assert_close(H, Ha, rtol=0, atol=1e-10)
    torch.testing.assert_close(M, Ma, rtol=0, atol=1e-10)
    delta = 0.3 * torch.randn(5, 24, generator=g, dtype=torch.float64)
    J = model.reset_jacobian(x, delta)
    Ja = ekf.reset_jacobian(x, delta, model.group.rplus(x, delta))
    torch.testing.assert_close(J, Ja, rtol=0, atol=1e-10)


def _lag1(nis: torch.Tensor) -> float:
    """The lag-1 autocorrelation of the NIS over the steps (about 0 for white innovations)."""
    c = nis - nis.mean()
    return float((c[:, :-1] * c[:, 1:]).mean() / c.square().mean())


def test_on_correlated_noise_it_beats_the_nominal_ekf_and_its_innovations_are_white():
    system = MismatchedRigidBody(noise_correlation=0.8)
    data = system.simulate(32, 300, 0.2, torch.Generator().manual_seed(4))
    nominal = _errors(system, RigidBodyEKF(system, 0.2), data)
    ar = _errors(system, CorrelatedNoiseEKF(system, 0.2), data)
    assert ar["R"] < 0.97 * nominal["R"] and ar["p"] < 0.97 * nominal["p"], (ar, nominal)
    # it knows the noise's law: its innovations are as large as its covariance says (NIS ~ 6)
    # and white; the nominal EKF's follow the smooth noise (measured: lag-1 0.63 against 0.00)
    y = data.measurements

    def nis_of(est):  # the NIS of the filter as estimate() runs it, from its start at step 5
        x, P = est.start_belief(y[:, :5])
        return _quiet(est).ekf.filter(y[:, 5:], x0=x, P0=P).nis[:, 20:]

    white = nis_of(RigidBodyEKF(system, 0.2))
    nis = nis_of(CorrelatedNoiseEKF(system, 0.2))
    assert 5.5 < float(nis.mean()) < 6.5 and abs(_lag1(nis)) < 0.05
    assert _lag1(white) > 0.4


def test_it_is_a_method_of_the_mismatched_body_and_reads_its_correlation():
    system = MismatchedRigidBody(noise_correlation=0.6)
    est = system.estimators()["ekf_ar1"](system, sigma=0.1)
    assert est.model.rho == 0.6 and est.name == "ekf_ar1" and est.group is system.group
    assert "rho=0.6" in repr(est)
    assert CorrelatedNoiseEKF(system, 0.1, rho=0.3).model.rho == 0.3
    assert "ekf_ar1" not in RigidBody().estimators()
    assert "ekf_ar1" not in MismatchedRigidBody(pose_group="se3").estimators()


def test_bad_arguments_are_refused_with_their_name():
    system = MismatchedRigidBody(noise_correlation=0.8)
    with pytest.raises(ValueError, match="rho is the noise's AR"):
        CorrelatedNoiseEKF(system, 0.1, rho=1.0)
    with pytest.raises(ValueError, match="floor is the pose's white noise"):
        CorrelatedNoiseEKF(system, 0.1, floor=0.0)
    with pytest.raises(ValueError, match="init_steps must be an integer >= 2"):
        CorrelatedNoiseEKF(system, 0.1, init_steps=0)
    with pytest.raises(ValueError, match="noise level sigma > 0"):
        CorrelatedNoiseEKF(system, 0.0)
    with pytest.raises(TypeError, match="needs a RigidBody"):
        CorrelatedNoiseFilterModel(object(), 0.1, 0.5)
    data = system.simulate(2, 3, 0.1, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="shorter than init_steps=5"):
        CorrelatedNoiseEKF(system, 0.1).estimate(data)
