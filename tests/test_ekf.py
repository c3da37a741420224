"""The error-state EKF: the textbook Kalman filter on a linear system, convergence and consistency
on the rigid body, the covariance's symmetry and definiteness, and its Jacobians (autograd against
finite differences and against the analytic multiplicative-EKF ones)."""

from __future__ import annotations

import math

import pytest
import torch

from manifold_nets_examples.rigid_body import RigidBody
from manifold_nets_examples.rigid_body.filters import (
    RigidBodyEKF,
    RigidBodyFilterModel,
    initialize_from_measurements,
    jl_times_v_derivative,
)
from groups import SO3, Euclidean
from groups.so3 import left_jacobian
from manifold_nets.ekf import (
    BiasedReadingsFilterModel,
    ErrorStateEKF,
    FilterModel,
    SystemFilterModel,
)
from manifold_nets.system import System

F64 = torch.float64


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


class LinearSystem(System):
    """``x' = A x + B w``, ``y = C x + D nu`` on ``R^3``; the drive is the known input."""

    name = "linear"
    measurement_dim = 2
    input_dim = 2
    drive_dim = 2
    noise_dim = 2
    dt = 1.0

    def __init__(self):
        g = gen(0)
        self.group = Euclidean(3)
        self.A = torch.eye(3, dtype=F64) + 0.2 * torch.randn(3, 3, generator=g, dtype=F64)
        self.B = torch.randn(3, 2, generator=g, dtype=F64)
        self.C = torch.randn(2, 3, generator=g, dtype=F64)
        self.D = torch.eye(2, dtype=F64) + 0.3 * torch.randn(2, 2, generator=g, dtype=F64)

    def config(self):
        return {}

    def sample_initial_state(self, n, generator):
        return torch.randn(n, 3, generator=generator, dtype=F64)

    def sample_drive(self, n, length, generator):
        return torch.randn(n, length, 2, generator=generator, dtype=F64)

    def step(self, x, drive, dt=None):
        A, B = self.A.to(x), self.B.to(x)
        return x @ A.T + drive @ B.T

    def measure(self, x, drive, noise=None):
        y = x @ self.C.to(x).T
        return y if noise is None else y + noise @ self.D.to(x).T


def textbook_kalman(sys: LinearSystem, y, u, sigma, q, s0, gate=None):
    """The Kalman filter as printed, one sequence at a time, with the standard covariance update;
    with ``gate``, an innovation whose NIS exceeds it has ``R`` scaled by ``NIS / gate``."""
    A, B, C, D = sys.A, sys.B, sys.C, sys.D
    Q, Rn = q**2 * B @ B.T, sigma**2 * D @ D.T
    out = []
    for i in range(y.shape[0]):
        x, P = torch.zeros(3, dtype=F64), s0**2 * torch.eye(3, dtype=F64)
        xs = [x]
        for k in range(y.shape[1]):
            x = A @ x + B @ u[i, k]
            P = A @ P @ A.T + Q
            S = C @ P @ C.T + Rn
            nu = y[i, k] - C @ x
            nis = float(nu @ torch.linalg.inv(S) @ nu)
            if gate is not None and nis > gate:
                S = C @ P @ C.T + Rn * (nis / gate)
            K = P @ C.T @ torch.linalg.inv(S)
            x = x + K @ (y[i, k] - C @ x)
            P = (torch.eye(3, dtype=F64) - K @ C) @ P
            xs.append(x)
        out.append(torch.stack(xs))
    return torch.stack(out)


def test_linear_system_equals_textbook_kalman_filter():
    sys = LinearSystem()
    sigma, q, s0 = 0.3, 0.2, 2.0
    ds = sys.simulate(3, 25, sigma, gen(1))
    ekf = ErrorStateEKF(SystemFilterModel(sys, sigma, drive_noise_std=q, initial_std=s0))
    res = ekf.filter(ds.measurements, ds.inputs, return_covariances=True)
    ref = textbook_kalman(sys, ds.measurements, ds.inputs, sigma, q, s0)
    assert res.estimates.shape == (3, 26, 3)
    torch.testing.assert_close(res.estimates, ref, atol=1e-10, rtol=0)
    assert float((res.estimates - ds.states).norm(dim=-1)[:, 5:].mean()) < float(
        (ds.states[:, 5:]).norm(dim=-1).mean()
    )


def test_the_gate_inflates_the_measurement_noise_of_large_innovations_like_the_textbook():
    sys = LinearSystem()
    sigma, q, s0 = 0.3, 0.2, 2.0
    ds = sys.simulate(4, 30, sigma, gen(1))
    y = ds.measurements.clone()
    y[:, 10] += 5.0  # an outlier in every sequence at step 11
    y[1, 20] -= 3.0
    model = SystemFilterModel(sys, sigma, drive_noise_std=q, initial_std=s0)
    gated = ErrorStateEKF(model, gate=6.0).filter(y, ds.inputs)
    ref = textbook_kalman(sys, y, ds.inputs, sigma, q, s0, gate=6.0)
    torch.testing.assert_close(gated.estimates, ref, atol=1e-10, rtol=0)
    assert float(gated.nis[:, 10].min()) > 6.0  # the NIS returned is the ungated innovation's
    plain = ErrorStateEKF(model).filter(y, ds.inputs)
    assert not torch.allclose(gated.estimates, plain.estimates)
    wide = ErrorStateEKF(model, gate=1e12).filter(y, ds.inputs)  # never reached: the plain EKF
    assert torch.equal(wide.estimates, plain.estimates)
    err = lambda r: float((r.estimates - ds.states)[:, 11:16].norm(dim=-1).mean())  # noqa: E731
    assert err(gated) < err(plain)  # the outlier moves the gated estimate less


def test_the_gate_waits_gate_after_steps():
    sys = LinearSystem()
    ds = sys.simulate(3, 30, 0.3, gen(2))
    y = ds.measurements.clone()
    y[:, 3] += 5.0  # outliers before and after the gate opens
    y[:, 15] += 5.0
    model = SystemFilterModel(sys, 0.3, drive_noise_std=0.2, initial_std=2.0)
    plain = ErrorStateEKF(model).filter(y, ds.inputs).estimates
    late = ErrorStateEKF(model, gate=6.0, gate_after=10).filter(y, ds.inputs).estimates
    assert torch.equal(late[:, :11], plain[:, :11])  # steps 1-10 ungated, the outlier included
    assert not torch.allclose(late[:, 16], plain[:, 16])
    with pytest.raises(ValueError, match="gate_after is the number of the filter's first steps"):
        ErrorStateEKF(model, gate=6.0, gate_after=-1)


@pytest.mark.parametrize("gate", [0.0, -1.0, math.inf, math.nan, True, "16"])
def test_a_bad_gate_is_refused(gate):
    with pytest.raises(ValueError, match="gate is a threshold on the NIS"):
        ErrorStateEKF(SystemFilterModel(LinearSystem(), 0.3), gate=gate)


def test_float32_follows_float64():
    sys = LinearSystem()
    ds = sys.simulate(2, 15, 0.3, gen(2))
    ekf = ErrorStateEKF(SystemFilterModel(sys, 0.3, drive_noise_std=0.2))
    r64 = ekf.filter(ds.measurements, ds.inputs).estimates
    r32 = ekf.filter(ds.measurements.float(), ds.inputs.float()).estimates
    assert r32.dtype == torch.float32
    torch.testing.assert_close(r32.double(), r64, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_rigid_body_converges_and_covariance_stays_spd(dtype):
    sys = RigidBody()
    sigma = 0.05
    ds = sys.simulate(6, 60, sigma, gen(3)).to(dtype)
    res = ErrorStateEKF(RigidBodyFilterModel(sys, sigma), jacobians="analytic").filter(
        ds.measurements, return_covariances=True
    )
    m = sys.metrics(res.estimates, ds)
    for name in ("R", "p", "b_omega", "b_v"):  # errors shrink over time
        early, late = float(m[name][:, 2:6].mean()), float(m[name][:, 40:].mean())
        assert late < 0.7 * early, (name, early, late)
    raw = sys.measurement_errors(ds)
    assert float(m["R"][:, 40:].mean()) < 0.6 * float(raw["R"][:, 39:].mean())
    P = res.covariances
    assert torch.equal(P, P.transpose(-1, -2))  # symmetrised exactly
    assert float(torch.linalg.eigvalsh(P.double()).min()) > 0
    assert float(sys.group.membership_error(res.estimates).max()) < (
        1e-4 if dtype == torch.float32 else 1e-12
    )
    assert torch.isfinite(res.estimates).all()


def test_nis_is_consistent_and_autograd_filter_equals_analytic():
    sys = RigidBody()
    sigma = 0.2
    ds = sys.simulate(10, 60, sigma, gen(4))
    auto = ErrorStateEKF(RigidBodyFilterModel(sys, sigma)).filter(ds.measurements)
    ana = ErrorStateEKF(RigidBodyFilterModel(sys, sigma), jacobians="analytic").filter(
        ds.measurements
    )
    torch.testing.assert_close(auto.estimates, ana.estimates, atol=1e-10, rtol=0)
    nis = float(ana.nis[:, 10:].mean())  # chi^2 with 6 degrees of freedom when consistent
    assert 5.0 < nis < 7.0, nis


# ------------------------------------------------------------------ Jacobians


def _states_and_readings(n: int, seed: int):
    sys = RigidBody()
    ds = sys.simulate(n, 2, 0.3, gen(seed))
    g = gen(seed + 100)
    x = ds.states[:, 1].clone()
    x[:, 12:] += torch.randn(n, 6, generator=g, dtype=F64)  # an estimate, not the truth
    y = ds.measurements[:, 1].clone()
    y[0, 12:15] = x[0, 12:15]  # phi = 0 exactly: the Taylor branches
    y[1, 12:15] = x[1, 12:15] + 1e-4
    return sys, x, y


def _finite_difference(fn, dim: int, eps: float = 1e-6) -> torch.Tensor:
    cols = []
    for i in range(dim):
        e = torch.zeros(dim, dtype=F64)
        e[i] = eps
        cols.append((fn(e) - fn(-e)) / (2 * eps))
    return torch.stack(cols, dim=-1)


def test_process_jacobians_autograd_finite_differences_and_analytic_agree():
    sys, x, y = _states_and_readings(6, 5)
    model = RigidBodyFilterModel(sys, 0.3)
    g = sys.group
    u = y.new_zeros(len(y), 0)
    F, G = ErrorStateEKF(model).process_jacobians(x, y, u)
    Fa, Ga = model.process_jacobians(x, y, u)
    x_pred = model.step(x, model.drive(x, y, u))
    Ffd = _finite_difference(
        lambda e: g.rminus(
            model.step(
                g.rplus(x, e.expand(len(x), 12)),
                model.drive(g.rplus(x, e.expand(len(x), 12)), y, u),
            ),
            x_pred,
        ),
        12,
    )
    Gfd = _finite_difference(
        lambda q: g.rminus(model.step(x, model.drive(x, y, u, q.expand(len(x), 6))), x_pred), 6
    )
    torch.testing.assert_close(F, Fa, atol=1e-12, rtol=0)
    torch.testing.assert_close(G, Ga, atol=1e-12, rtol=0)
    torch.testing.assert_close(F, Ffd, atol=1e-7, rtol=0)
    torch.testing.assert_close(G, Gfd, atol=1e-7, rtol=0)


def test_measurement_and_reset_jacobians_agree():
    sys, x, y = _states_and_readings(5, 6)
    model = RigidBodyFilterModel(sys, 0.3)
    ekf = ErrorStateEKF(model)
    w = model.drive(x, y, y.new_zeros(5, 0))
    z_hat = model.measure(x, w)
    H, M = ekf.measurement_jacobians(x, w, z_hat, 6)
    Ha, Ma = model.measurement_jacobians(x, w)
    torch.testing.assert_close(H, Ha, atol=1e-12, rtol=0)
    torch.testing.assert_close(M, Ma, atol=1e-12, rtol=0)
    delta = torch.randn(5, 12, generator=gen(7), dtype=F64)
    delta[0] = 0.0
    x_plus = sys.group.rplus(x, delta)
    J = ekf.reset_jacobian(x, delta, x_plus)
    torch.testing.assert_close(J, model.reset_jacobian(x, delta), atol=1e-12, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-3, 0.0999, 0.1001, 0.4999, 0.5001, 1.0, 3.0])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_jl_times_v_derivative_matches_autograd(angle, dtype):
    axis = torch.tensor([0.48, -0.6, 0.64], dtype=F64)
    phi = (angle * axis).to(dtype)
    v = torch.tensor([0.3, -1.2, 0.7], dtype=dtype)
    ref = torch.autograd.functional.jacobian(lambda p: left_jacobian(p) @ v.double(), phi.double())
    got = jl_times_v_derivative(phi, v)
    tol = 1e-10 if dtype == torch.float64 else 2e-5
    torch.testing.assert_close(got.double(), ref, atol=tol, rtol=0)


# ------------------------------------------------------------------ the estimator, initialisation, errors


def test_initialize_from_measurements_recovers_biases_at_small_noise():
    sys = RigidBody()
    ds = sys.simulate(20, 6, 1e-6, gen(8))
    x, P = initialize_from_measurements(sys, ds.measurements[:, :5], 1e-6)
    torch.testing.assert_close(x[:, 12:], ds.states[:, 5, 12:], atol=1e-4, rtol=0)
    assert (
        float(
            SO3()
            .distance(x[:, :9].unflatten(-1, (3, 3)), ds.states[:, 5, :9].unflatten(-1, (3, 3)))
            .max()
        )
        < 1e-5
    )
    assert P.shape == (20, 12, 12) and float(torch.linalg.eigvalsh(P).min()) > 0


def test_rigid_body_ekf_estimator_format_and_starts():
    sys = RigidBody()
    ds = sys.simulate(4, 30, 0.2, gen(9))
    for m in (0, 5):
        est = RigidBodyEKF(sys, 0.2, init_steps=m).estimate(ds)
        assert est.shape == (4, 31, 18)
        torch.testing.assert_close(est[:, 0], sys.group.identity((4,), dtype=F64))
        if m:
            torch.testing.assert_close(
                est[:, 1:m], sys.state_from_measurement(ds.measurements[:, : m - 1])
            )
    with pytest.raises(ValueError, match="init_steps"):
        RigidBodyEKF(sys, 0.2, init_steps=1)


def test_clear_errors():
    sys = RigidBody()
    with pytest.raises(ValueError, match="sigma > 0"):
        RigidBodyFilterModel(sys, 0.0)
    with pytest.raises(ValueError, match="sigma > 0"):
        SystemFilterModel(LinearSystem(), 0.0)
    with pytest.raises(TypeError, match="FilterModel"):
        ErrorStateEKF(sys)
    ekf = ErrorStateEKF(RigidBodyFilterModel(sys, 0.1))
    with pytest.raises(ValueError, match="jacobians"):
        ErrorStateEKF(RigidBodyFilterModel(sys, 0.1), jacobians="numeric")
    with pytest.raises(ValueError, match=r"\(N, T, 18\)"):
        ekf.filter(torch.zeros(2, 5, 12, dtype=F64))

    class Silent(SystemFilterModel):  # a measurement that does not see the state: S = 0
        def measurement_noise_cov(self, dtype, device=None):
            return torch.zeros(self.measurement_noise_dim, self.measurement_noise_dim, dtype=dtype)

    lin = LinearSystem()
    ds = lin.simulate(1, 3, 0.1, gen(10))
    P0 = torch.zeros(1, 3, 3, dtype=F64)
    with pytest.raises(ValueError, match="not positive definite"):
        ErrorStateEKF(Silent(lin, 0.1)).filter(ds.measurements, ds.inputs, P0=P0)


def test_filter_model_without_analytic_jacobians_says_so():
    lin = LinearSystem()
    ds = lin.simulate(1, 2, 0.1, gen(11))
    ekf = ErrorStateEKF(SystemFilterModel(lin, 0.1), jacobians="analytic")
    with pytest.raises(NotImplementedError, match="autograd"):
        ekf.filter(ds.measurements, ds.inputs)
    assert issubclass(SystemFilterModel, FilterModel)


def test_measurement_residual_hook():
    sys = RigidBody()
    ds = sys.simulate(3, 2, 0.0, gen(12))
    y_hat = sys.measure(ds.states[:, 1:], torch.zeros(3, 2, 6, dtype=F64))
    assert float(sys.measurement_residual(y_hat, y_hat).abs().max()) < 1e-14
    noise = 1e-3 * torch.randn(3, 2, 12, generator=gen(13), dtype=F64)
    y = sys.measure(ds.states[:, 1:], torch.zeros(3, 2, 6, dtype=F64), noise)
    r = sys.measurement_residual(y, y_hat)
    assert r.shape == (3, 2, 12)
    torch.testing.assert_close(r, noise, atol=1e-12, rtol=0)  # the noise is a right perturbation
    assert math.isclose(
        float(LinearSystem().measurement_residual(torch.ones(2), torch.zeros(2)).sum()), 2.0
    )


class BiasedOdometer:
    """A cart on a line: position ``p`` and the odometer's bias ``b``, state ``(p, b)`` on
    ``R^2``. ``y_{k+1} = (p_{k+1} + sigma n1, v_k + b + sigma n2)``: a position fix, then the
    biased speed reading that drives the prediction."""

    group = Euclidean(2)
    measurement_dim = 2
    input_dim = 0
    noise_dim = 2
    dt = 0.1

    def step(self, x, drive):
        return torch.cat((x[..., :1] + self.dt * drive, x[..., 1:]), dim=-1)

    def measure(self, x, drive, noise=None):
        y = torch.cat((x[..., :1], drive + x[..., 1:]), dim=-1)
        return y if noise is None else y + noise

    def measurement_residual(self, y, y_hat):
        return y - y_hat

    def drive_from_measurement(self, y, u):
        return y[..., 1:]


class OdometerFilterModel(BiasedReadingsFilterModel):
    system_type = BiasedOdometer
    process_noise_dim = 1
    measurement_noise_dim = 1

    def bias(self, x):
        return x[..., 1:]

    def process_noise_cov(self, dtype, device=None):
        return self.sigma**2 * torch.eye(1, dtype=dtype, device=device)

    def measurement_noise_cov(self, dtype, device=None):
        return self.sigma**2 * torch.eye(1, dtype=dtype, device=device)

    def initial_state(self, batch, dtype, device=None):
        return torch.zeros(batch, 2, dtype=dtype), 4 * torch.eye(2, dtype=dtype).expand(batch, 2, 2)


def test_biased_readings_model_drives_with_readings_and_learns_their_bias():
    """A model of a few lines on BiasedReadingsFilterModel: the reading minus the bias state
    drives the prediction, only the fix updates, and the filter finds the odometer's bias."""
    system, sigma, n, t = BiasedOdometer(), 0.05, 64, 400
    g = gen(5)
    bias = torch.empty(n, 1, dtype=F64).uniform_(-1, 1, generator=g)
    x = torch.cat((torch.zeros(n, 1, dtype=F64), bias), dim=-1)
    ys = []
    for _ in range(t):
        v = torch.randn(n, 1, generator=g, dtype=F64)
        noise = sigma * torch.randn(n, 2, generator=g, dtype=F64)
        ys.append(system.measure(x := system.step(x, v), v, noise))
    model = OdometerFilterModel(system, sigma)
    y = torch.stack(ys, 1)
    # the pieces: drive = reading - bias state - q; the update sees the fix only
    xh = torch.tensor([[3.0, 0.25]], dtype=F64)
    q = torch.tensor([[0.1]], dtype=F64)
    torch.testing.assert_close(model.drive(xh, y[:1, 0], None, q), y[:1, 0, 1:] - 0.25 - 0.1)
    z = model.measure(xh, torch.tensor([[1.0]], dtype=F64), torch.tensor([[0.5]], dtype=F64))
    torch.testing.assert_close(z, torch.tensor([[3.5, 1.25]], dtype=F64))  # reading noise-free
    assert model.residual(y[:1, 0], z).shape == (1, 1)
    est = ErrorStateEKF(model).filter(y).estimates
    err = (est[:, -50:, 1] - bias).abs().mean()
    assert err < 0.05, err  # the bias, never measured, is found from the fixes
    with pytest.raises(
        TypeError, match="OdometerFilterModel needs a BiasedOdometer, got RigidBody"
    ):
        OdometerFilterModel(RigidBody(), sigma)
    with pytest.raises(ValueError, match="sigma > 0"):
        OdometerFilterModel(system, 0.0)
