"""The EKF's lean step against the textbook: a reference filter written plainly in this file
(the model's own drive, step, measure and residual; Jacobians by ``torch.func.jacrev``; the
Joseph form and the reset as printed), on the rigid body and on BROAD's AHRS model, to 1e-12;
the models' one-pass linearisations against their separate methods; the fused SO(3) pieces
against the groups'; the compiled step against the eager one."""

from __future__ import annotations

import math
import shutil

import pytest
import torch

from groups import SO3
from groups import numerics as nx
from groups.so3 import left_jacobian
from manifold_nets.ekf import EKFState, ErrorStateEKF
from manifold_nets.ekf_so3 import exp_and_left_jacobian, so3_coefficients, so3_log
from manifold_nets_examples.broad import filters as broad
from manifold_nets_examples.rigid_body import RigidBody
from manifold_nets_examples.rigid_body.filters import RigidBodyEKF

F64 = torch.float64


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _jacobian(fn, dim: int, like: torch.Tensor) -> torch.Tensor:
    """``d fn(e) / d e`` at ``e = 0`` per sequence, ``(B, out, dim)``: ``fn`` maps ``(B, dim)``
    to ``(B, out)``, sequence by sequence."""
    full = torch.func.jacrev(fn)(like.new_zeros(len(like), dim))  # (B, out, B, dim)
    return torch.diagonal(full, dim1=0, dim2=2).movedim(-1, 0)


def reference_step(model, x, P, y, u, reset=True):
    """One EKF step as the module docstring of ``manifold_nets.ekf`` prints it."""
    g, n = model.group, model.group.tangent_dim
    w = model.drive(x, y, u)
    x_pred = model.step(x, w)
    F = _jacobian(lambda e: g.rminus(model.step(g.rplus(x, e), model.drive(g.rplus(x, e), y, u)),
                                     x_pred), n, x)  # fmt: skip
    G = _jacobian(lambda q: g.rminus(model.step(x, model.drive(x, y, u, q)), x_pred),
                  model.process_noise_dim, x)  # fmt: skip
    Q, Rn = model.process_noise_cov(x.dtype), model.measurement_noise_cov(x.dtype)
    P = F @ P @ F.mT + G @ Q @ G.mT
    Qe = model.state_noise_cov(x.dtype)
    P = 0.5 * (P + P.mT) + (0 if Qe is None else Qe)
    z = model.observation(y)
    z_hat = model.measure(x_pred, w)
    nu = model.residual(z, z_hat)
    H = _jacobian(lambda e: model.residual(model.measure(g.rplus(x_pred, e), w), z_hat), n, x)
    M = _jacobian(lambda r: model.residual(model.measure(x_pred, w, r), z_hat),
                  model.measurement_noise_dim, x)  # fmt: skip
    S = H @ P @ H.mT + M @ Rn @ M.mT
    K = P @ H.mT @ torch.linalg.inv(S)
    nis = (nu.unsqueeze(-2) @ torch.linalg.solve(S, nu.unsqueeze(-1))).flatten()
    delta = (K @ nu.unsqueeze(-1)).squeeze(-1)
    x_new = g.rplus(x_pred, delta)
    A = torch.eye(n, dtype=x.dtype) - K @ H
    P = A @ P @ A.mT + K @ M @ Rn @ M.mT @ K.mT
    if reset:
        J = _jacobian(lambda e: g.rminus(g.rplus(x_pred, delta + e), x_new), n, x)
        P = J @ P @ J.mT
    return x_new, 0.5 * (P + P.mT), nis


def _run_both(ekf: ErrorStateEKF, x, P, ys, us):
    worst = {"x": 0.0, "P": 0.0, "nis": 0.0}
    state, c = EKFState(x, P), ekf.constants(x.dtype)
    for k in range(ys.shape[1]):
        with torch.no_grad():
            state, nis = ekf.step(state, ys[:, k], us[:, k], True, c)
        x, P, nis_ref = reference_step(ekf.model, x, P, ys[:, k], us[:, k], ekf.reset)
        for key, a, b in (("x", state.x, x), ("P", state.P, P), ("nis", nis, nis_ref)):
            worst[key] = max(worst[key], float((a - b).abs().max() / b.abs().max()))
    return worst


@pytest.mark.parametrize("reading_std", [None, "per sequence"])
def test_rigid_body_lean_step_is_the_textbook_filter(reading_std):
    system = RigidBody()
    ds = system.simulate(4, 25, 0.3, gen(0))
    kw = {} if reading_std is None else {
        "reading_std": torch.tensor([0.2, 0.3, 0.5, 1.0], dtype=F64),
        "bias_walk": torch.tensor([0.0, 0.01, 0.1, 0.3], dtype=F64)}  # fmt: skip
    est = RigidBodyEKF(system, 0.3, **kw)
    x, P = est.start_belief(ds.measurements[:, :5])
    y = ds.measurements[:, 5:]
    worst = _run_both(est.ekf, x, P, y, y.new_zeros(4, y.shape[1], 0))
    assert max(worst.values()) < 1e-12, worst


def test_rigid_body_from_the_wide_prior_is_the_textbook_filter():
    """From the prior (rotation std pi / sqrt 3): updates by large angles, the closed forms."""
    system = RigidBody()
    ds = system.simulate(3, 12, 0.3, gen(1))
    ekf = RigidBodyEKF(system, 0.3, init_steps=0).ekf
    x, P = ekf.model.initial_state(3, F64)
    worst = _run_both(ekf, x, P, ds.measurements, ds.measurements.new_zeros(3, 12, 0))
    assert max(worst.values()) < 1e-12, worst


def test_broad_model_lean_step_is_the_textbook_filter():
    g = gen(2)
    m_ref = torch.tensor([0.0, 0.36, -0.93], dtype=F64)
    model = broad.BroadFilterModel(285.7, (m_ref / m_ref.norm()).numpy(),
                                   acc=torch.tensor([0.3, 1.0, 0.5], dtype=F64))  # fmt: skip
    ekf = ErrorStateEKF(model, jacobians="analytic", progress=False)
    x = torch.cat((SO3().random((3,), generator=g, dtype=F64).flatten(-2),
                   0.01 * torch.randn(3, 3, generator=g, dtype=F64)), -1)  # fmt: skip
    P = torch.diag_embed(torch.tensor([0.05] * 3 + [0.01] * 3, dtype=F64) ** 2).expand(3, 6, 6)
    ys = torch.nn.functional.normalize(torch.randn(3, 30, 2, 3, generator=g, dtype=F64), dim=-1)
    us = 2.0 * torch.randn(3, 30, 3, generator=g, dtype=F64)
    worst = _run_both(ekf, x, P, ys.flatten(-2), us)
    assert max(worst.values()) < 1e-12, worst


def test_one_pass_linearisations_equal_the_separate_methods():
    system = RigidBody()
    ds = system.simulate(5, 3, 0.3, gen(3))
    model = RigidBodyEKF(system, 0.3).model
    x, y = ds.states[:, 1], ds.measurements[:, 1]
    u = y.new_zeros(5, 0)
    x_pred, w, F, G = model.linearize_step(x, y, u)
    torch.testing.assert_close(w, model.drive(x, y, u), atol=0, rtol=0)
    torch.testing.assert_close(x_pred, system.step(x, w), atol=1e-14, rtol=0)
    nu, H, M = model.linearize_measurement(x_pred, w, y)
    full = system.measurement_residual(y, system.measure(x_pred, w))
    torch.testing.assert_close(nu, full[:, :6], atol=1e-14, rtol=0)
    assert M is None and torch.equal(H.expand(5, 6, 12), model.measurement_jacobians(x, w)[0])
    delta = 0.5 * torch.randn(5, 12, generator=gen(4), dtype=F64)
    x_new, J = model.linearize_reset(x_pred, delta)
    torch.testing.assert_close(x_new, system.group.rplus(x_pred, delta), atol=1e-14, rtol=0)
    auto = ErrorStateEKF(model).reset_jacobian(x_pred, delta, x_new)
    torch.testing.assert_close(J, auto, atol=1e-12, rtol=0)
    # measured_states = slice(0, 6): H is those rows of the identity, as the filter assumes
    sel = ErrorStateEKF(model, jacobians="analytic")._selection
    assert sel == slice(0, 6) and torch.equal(H, torch.eye(12, dtype=F64)[sel])


def test_measured_states_is_checked():
    model = RigidBodyEKF(RigidBody(), 0.3).model
    for bad in (slice(0, 6, 2), slice(6, 6), (0, 6)):
        model.measured_states = bad
        with pytest.raises(ValueError, match="measured_states"):
            ErrorStateEKF(model, jacobians="analytic")
    model.measured_states = None  # the general H: the same filter (H's rows are exact)
    ekf = ErrorStateEKF(model, jacobians="analytic", progress=False)
    del model.measured_states
    lean = ErrorStateEKF(model, jacobians="analytic", progress=False)
    assert ekf._selection is None and lean._selection == slice(0, 6)
    y = RigidBody().simulate(3, 20, 0.3, gen(5)).measurements
    a, b = ekf.filter(y, return_covariances=True), lean.filter(y, return_covariances=True)
    torch.testing.assert_close(a.estimates, b.estimates, atol=1e-13, rtol=0)
    torch.testing.assert_close(a.covariances, b.covariances, atol=1e-13, rtol=0)


ANGLES = [0.0, 1e-8, 1e-5, 3e-3, 1e-2, 0.3, 1.0, 2.0, math.pi - 1e-7, math.pi, 3.2, 3.3, 7.0]


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_fused_so3_pieces_equal_the_groups(dtype):
    axes = torch.nn.functional.normalize(torch.randn(len(ANGLES), 8, 3, generator=gen(5)), dim=-1)
    phi = (axes.double() * torch.tensor(ANGLES, dtype=F64)[:, None, None]).to(dtype)
    E, Jl, K, co = exp_and_left_jacobian(phi)
    tol = 1e-14 if dtype == F64 else 2e-6
    torch.testing.assert_close(E, SO3().exp(phi), atol=tol, rtol=0)
    torch.testing.assert_close(Jl, left_jacobian(phi), atol=tol, rtol=0)
    torch.testing.assert_close(K, SO3().hat(phi), atol=0, rtol=0)
    t2 = (phi * phi).sum(-1)
    ref = torch.stack((nx.sin_over_t(t2), nx.one_minus_cos_over_t2(t2),
                       nx.t_minus_sin_over_t3(t2)), -1)  # fmt: skip
    torch.testing.assert_close(co[..., :3], ref, atol=tol / 10, rtol=0)
    # B' and C', the derivatives in t^2: the closed forms where they do not cancel, the limits
    t2d = t2.double()
    t = t2d.sqrt()
    dB = (t * torch.sin(t) - 4 * torch.sin(t / 2) ** 2) / (2 * t2d**2)
    dC = (3 * torch.sin(t) - 2 * t - t * torch.cos(t)) / (2 * t2d**2 * t)
    far = t >= 0.3
    got = so3_coefficients(t2d)
    torch.testing.assert_close(got[..., 3:][far], torch.stack((dB, dC), -1)[far], atol=1e-13,
                               rtol=0)  # fmt: skip
    torch.testing.assert_close(got[0, 0, 3:], torch.tensor([-1 / 24, -1 / 120], dtype=F64))
    R = SO3().exp(phi[torch.tensor(ANGLES) <= math.pi])
    torch.testing.assert_close(so3_log(R), SO3().log(R), atol=4 * tol, rtol=0)


@pytest.mark.skipif(shutil.which("g++") is None, reason="torch.compile on the CPU needs a C++ compiler")
def test_compiled_step_equals_the_eager_step():
    system = RigidBody()
    ds = system.simulate(2, 12, 0.3, gen(6))
    eager, compiled = (RigidBodyEKF.robust(system, 0.3, gate_after=0) for _ in range(2))
    compiled.ekf.compile = True
    a, b = eager.estimate(ds), compiled.estimate(ds)
    torch.testing.assert_close(a, b, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="compile=True compiles the analytic step"):
        ErrorStateEKF(eager.model, compile=True)
