"""The paper's rigid body: exact kinematics against RK45, states on the group, the random laws,
the measurement model and its noise law, and the velocity pairing of y_{k+1}. The generic
contract (same seed -> same data, states independent of sigma, rollout against step, shapes,
dtypes, gradients) is checked in tests/test_system_contract.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.integrate import quad

from manifold_nets_examples.rigid_body import RigidBody
from manifold_nets_examples.rigid_body.kinematics import (
    exact_rollout,
    exact_step,
    increments,
    rk45_rollout,
)
from groups import SO3
from groups.so3 import left_jacobian, left_jacobian_inverse

F64 = torch.float64


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def velocities_from_states(states: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The held (Omega_k, v_k) from consecutive exact states (the inverse of the exact step)."""
    R = states[..., :9].unflatten(-1, (3, 3))
    p = states[..., 9:12]
    phi = SO3().log(R[:, :-1].transpose(-1, -2) @ R[:, 1:])
    body = (R[:, :-1].transpose(-1, -2) @ (p[:, 1:] - p[:, :-1]).unsqueeze(-1)).squeeze(-1)
    v = (left_jacobian_inverse(phi) @ body.unsqueeze(-1)).squeeze(-1) / dt
    return phi / dt, v


def test_exact_matches_rk45_at_tight_tolerance():
    g = gen(1)
    n, t, dt = 3, 20, 0.1
    R0 = SO3().random((n,), generator=g, dtype=F64)
    p0 = torch.rand(n, 3, generator=g, dtype=F64) * 2 - 1
    w = torch.rand(n, t, 6, generator=g, dtype=F64) * 2 - 1
    R, p = exact_rollout(R0, p0, w[..., :3], w[..., 3:], dt)
    Rr, pr = rk45_rollout(R0, p0, w[..., :3], w[..., 3:], dt, rtol=1e-10, atol=1e-10)
    assert (R - Rr).abs().max() < 1e-8
    assert (p - pr).abs().max() < 1e-8
    # the comparison can fail: dropping J_l (p + R v dt, first order) is off by ~1e-3
    naive = p0.unsqueeze(1) + torch.cumsum((R[:, :-1] @ w[..., 3:, None]).squeeze(-1) * dt, 1)
    assert (naive - pr[:, 1:]).abs().max() > 1e-4


def test_rollout_takes_any_memory_layout_of_the_drive_and_keeps_the_biases():
    # rollout against step: tests/test_system_contract.py
    body = RigidBody(dt=0.07)
    g = gen(2)
    x0 = body.sample_initial_state(4, g)
    w = body.sample_drive(4, 30, g)
    states = body.rollout(x0, w)
    assert torch.equal(body.rollout(x0, w.contiguous()), states)  # any memory layout of the drive
    # the biases never change
    assert torch.equal(states[:, :, 12:], x0[:, None, 12:].expand(-1, 31, -1))


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_fused_increments_equal_the_group_library(dtype):
    g = gen(13)
    axis = torch.nn.functional.normalize(torch.randn(8, 3, generator=g, dtype=F64), dim=-1)
    angles = torch.tensor([0.0, 1e-9, 1e-5, 3e-3, 1e-2, 0.1, 1.0, 3.0], dtype=F64)
    omega = (axis * angles[:, None] / 0.1).to(dtype)
    v = torch.randn(8, 3, generator=g, dtype=F64).to(dtype)
    rot, disp = increments(omega, v, 0.1)
    phi = omega * 0.1
    tol = 1e-15 if dtype == F64 else 1e-6
    torch.testing.assert_close(rot, SO3().exp(phi), rtol=0, atol=tol)
    expected = (left_jacobian(phi) @ v[..., None])[..., 0] * 0.1
    torch.testing.assert_close(disp, expected, rtol=0, atol=tol)
    assert torch.isfinite(rot).all() and torch.isfinite(disp).all()


def test_exact_step_is_the_closed_form():
    g = gen(3)
    R = SO3().random((5,), generator=g, dtype=F64)
    p = torch.randn(5, 3, generator=g, dtype=F64)
    om = torch.randn(5, 3, generator=g, dtype=F64)
    v = torch.randn(5, 3, generator=g, dtype=F64)
    dt = 0.3
    R1, p1 = exact_step(R, p, om, v, dt)
    # exp of the SE(3) twist as a 4x4 matrix exponential
    xi = torch.zeros(5, 4, 4, dtype=F64)
    xi[:, :3, :3] = SO3().hat(om * dt)
    xi[:, :3, 3] = v * dt
    T = torch.linalg.matrix_exp(xi)
    torch.testing.assert_close(R1, R @ T[:, :3, :3], rtol=0, atol=1e-14)
    torch.testing.assert_close(p1, p + (R @ T[:, :3, 3:]).squeeze(-1), rtol=0, atol=1e-14)


@pytest.mark.parametrize("n,t", [(64, 100), (4, 2000)])
def test_every_rotation_is_in_so3_to_1e12(n, t):
    ds = RigidBody().simulate(n, t, 0.0, gen(4))
    R = ds.states[..., :9].unflatten(-1, (3, 3))
    eye = torch.eye(3, dtype=F64)
    assert ds.states.dtype == F64
    assert torch.linalg.matrix_norm(R @ R.transpose(-1, -2) - eye).max() < 1e-12
    assert (torch.linalg.det(R) - 1).abs().max() < 1e-12


def test_rk45_integrator_gives_the_same_data_to_1e8():
    exact = RigidBody().simulate(2, 15, 0.0, gen(5))
    ref = RigidBody(integrator="rk45").simulate(2, 15, 0.0, gen(5))
    assert (exact.states - ref.states).abs().max() < 1e-8
    assert (exact.measurements - ref.measurements).abs().max() < 1e-8
    RigidBody().group.check_member(ref.states)  # projected back onto SO(3) after every step


def test_laws_of_the_initial_state_and_the_velocities():
    body = RigidBody()
    ds = body.simulate(2000, 10, 0.0, gen(6))
    x0 = ds.states[:, 0]
    R0, p0, b = x0[:, :9], x0[:, 9:12], x0[:, 12:]
    # Haar rotations: every entry has mean 0 and variance 1/3 (standard error 0.013 here)
    assert R0.mean(0).abs().max() < 0.06
    assert (R0.var(0) - 1 / 3).abs().max() < 0.06
    assert p0.abs().max() <= 1.0 and (p0.var(0) - 1 / 3).abs().max() < 0.06
    assert b.abs().max() <= 10.0 and (b.var(0) / 100 - 1 / 3).abs().max() < 0.06
    om, v = velocities_from_states(ds.states, body.dt)
    assert om.abs().max() <= 1.0 + 1e-9 and v.abs().max() <= 1.0 + 1e-9
    assert (om.reshape(-1, 3).var(0) - 1 / 3).abs().max() < 0.03


def test_noise_free_measurement_pairs_y_k1_with_the_velocity_of_step_k():
    body = RigidBody(dt=0.05)
    ds = body.simulate(20, 40, 0.0, gen(7))
    x1, y = ds.states[:, 1:], ds.measurements
    assert torch.equal(y[..., :12], x1[..., :12])  # vec R_{k+1}, p_{k+1}
    om, v = velocities_from_states(ds.states, body.dt)
    torch.testing.assert_close(y[..., 12:15], om + x1[..., 12:15], rtol=0, atol=1e-10)
    torch.testing.assert_close(y[..., 15:18], v + x1[..., 15:18], rtol=0, atol=1e-10)


def test_measurement_model_formula():
    body = RigidBody()
    g = gen(8)
    x = body.sample_initial_state(6, g)
    w = body.sample_drive(6, 1, g)[:, 0]
    nu = torch.randn(6, 12, generator=g, dtype=F64)
    y = body.measure(x, w, nu)
    R = x[:, :9].unflatten(-1, (3, 3))
    torch.testing.assert_close(y[:, :9].unflatten(-1, (3, 3)), R @ SO3().exp(nu[:, :3]))
    torch.testing.assert_close(y[:, 9:12], x[:, 9:12] + nu[:, 3:6])
    torch.testing.assert_close(y[:, 12:15], w[:, :3] + x[:, 12:15] + nu[:, 6:9])
    torch.testing.assert_close(y[:, 15:18], w[:, 3:] + x[:, 15:18] + nu[:, 9:12])
    SO3().check_member(y[:, :9].unflatten(-1, (3, 3)))  # R^m is a rotation too


def _mean_rotation_error(sigma: float) -> float:
    """E ||R exp([w]x) - R||_F = E 2 sqrt(2) sin(|w|/2), |w| Maxwell with scale sigma."""
    def pdf(t):
        return math.sqrt(2 / math.pi) * t * t * math.exp(-t * t / (2 * sigma**2)) / sigma**3

    return quad(lambda t: 2 * math.sqrt(2) * math.sin(t / 2) * pdf(t), 0, 20 * sigma)[0]


def test_noise_law_matches_the_papers_measurement_columns():
    sigma = 0.1
    body = RigidBody()
    ds = body.simulate(200, 50, sigma, gen(9))  # 10000 measurements
    err = body.measurement_errors(ds)
    n = err["R"].numel()
    # paper's table, sigma = 0.1: R^m 0.23, p^m 0.16
    mean_R, mean_p = err["R"].mean().item(), err["p"].mean().item()
    exp_R, exp_p = _mean_rotation_error(sigma), sigma * 2 * math.sqrt(2 / math.pi)
    assert round(exp_R, 2) == 0.23 and round(exp_p, 2) == 0.16
    # five standard errors of the mean
    assert abs(mean_R - exp_R) < 5 * err["R"].std().item() / math.sqrt(n)
    assert abs(mean_p - exp_p) < 5 * err["p"].std().item() / math.sqrt(n)
    # the velocity noise: y - (true velocity + bias) is N(0, sigma^2) per component
    om, v = velocities_from_states(ds.states, body.dt)
    x1 = ds.states[:, 1:]
    resid = torch.cat((ds.measurements[..., 12:15] - om - x1[..., 12:15],
                       ds.measurements[..., 15:18] - v - x1[..., 15:18]), -1).reshape(-1, 6)
    se = sigma / math.sqrt(resid.shape[0])
    assert resid.mean(0).abs().max() < 5 * se
    assert (resid.std(0) / sigma - 1).abs().max() < 5 / math.sqrt(2 * resid.shape[0])


def test_metrics_per_factor_frobenius_errors():
    body = RigidBody()
    ds = body.simulate(3, 6, 0.0, gen(11))
    m = body.metrics(ds.states.clone(), ds)
    assert set(m) == {"R", "p", "b_omega", "b_v"} and m["R"].shape == (3, 7)
    assert all(float(e.abs().max()) == 0.0 for e in m.values())
    shifted = ds.states[:, 1:].clone()
    shifted[..., 9] += 0.5
    m = body.metrics(shifted, ds)
    assert m["p"].shape == (3, 6) and torch.allclose(m["p"], torch.full((3, 6), 0.5, dtype=F64))
    with pytest.raises(ValueError, match="estimates must be"):
        body.metrics(ds.states[:, :3], ds)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(dt=0.0), "dt"),
        (dict(dt=-0.1), "dt"),
        (dict(integrator="euler"), "integrator"),
        (dict(rtol=0.0), "rtol"),
        (dict(bias_range=-1.0), "bias_range"),
        (dict(position_range=float("nan")), "position_range"),
        (dict(dt=float("inf")), "dt"),
    ],
)
def test_bad_parameters_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RigidBody(**kwargs)


def test_step_and_measure_check_shapes():
    body = RigidBody()
    x = body.group.identity((4,), dtype=F64)
    with pytest.raises(ValueError, match="18"):
        body.step(torch.zeros(4, 12, dtype=F64), torch.zeros(4, 6, dtype=F64))
    with pytest.raises(ValueError, match=r"drive \(Omega, v\) of shape \(\*batch, 6\)"):
        body.step(x, torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ValueError, match="noise"):
        body.measure(x, torch.zeros(4, 6, dtype=F64), torch.zeros(4, 6, dtype=F64))


def test_step_and_measure_are_differentiable_for_a_filter():
    """An error-state filter needs d step / d x and d measure / d (x, noise) on the group."""
    body = RigidBody()
    g = gen(14)
    x = body.sample_initial_state(1, g)[0]
    w = body.sample_drive(1, 1, g)[0, 0]
    # Jacobians with respect to a right perturbation x exp(delta), at delta = 0
    def f(d):
        return body.group.embed(body.step(body.group.rplus(x, d), w))

    def h(d, nu):
        return body.measure(body.group.rplus(x, d), w, nu)

    zero_d, zero_nu = torch.zeros(12, dtype=F64), torch.zeros(12, dtype=F64)
    Jf = torch.func.jacrev(f)(zero_d)
    Jh, Jn = torch.func.jacrev(h, argnums=(0, 1))(zero_d, zero_nu)
    assert Jf.shape == (18, 12) and Jh.shape == (18, 12) and Jn.shape == (18, 12)
    assert all(bool(torch.isfinite(J).all()) for J in (Jf, Jh, Jn))
    # the position reading depends on p one to one, the rate readings on the biases
    torch.testing.assert_close(Jn[9:12, 3:6], torch.eye(3, dtype=F64))
    torch.testing.assert_close(Jh[12:18, 6:12], torch.eye(6, dtype=F64))


def test_config_and_repr():
    body = RigidBody(dt=0.15)
    assert body.config()["dt"] == 0.15 and "rtol" not in body.config()
    assert "rtol" in RigidBody(integrator="rk45").config()
    assert "dt=0.15" in repr(body)
    assert body.group.embedding_dim == body.measurement_dim == 18 and body.input_dim == 0


def test_rk45_rollout_projects_onto_so3():
    g = gen(12)
    R0 = SO3().random((1,), generator=g, dtype=F64)
    w = torch.rand(1, 5, 6, generator=g, dtype=F64) * 2 - 1
    R, _ = rk45_rollout(R0, torch.zeros(1, 3, dtype=F64), w[..., :3], w[..., 3:], 0.1,
                        rtol=1e-3, atol=1e-6, project=True)
    err = torch.linalg.matrix_norm(R @ R.transpose(-1, -2) - torch.eye(3, dtype=F64))
    assert err.max() < 1e-13
    assert np.isfinite(R.numpy()).all()
