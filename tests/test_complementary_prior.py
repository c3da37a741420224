"""The complementary prior (``ComplementaryPrior``): after another prior, an SO(3) factor turns
``dt / tau`` of the way that aligns a measured direction with its reference (the explicit
complementary filter's correction). Checked on an AHRS-shaped observer on SO(3) x R^3 reading
``y = (acc, mag)`` and a gyro ``u``."""

from __future__ import annotations

import functools
import math

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.builders import build_piece
from manifold_nets.checkpoint import load_weights, save_checkpoint
from manifold_nets.cores import GRUCore
from manifold_nets.observer import (
    ComplementaryPrior,
    Embedding,
    GroupUpdate,
    KinematicPrior,
    Measurement,
    Readings,
    ResidualObserver,
)

G = Product(SO3(), Euclidean(3), names=("R", "b"))
DT, TAU = 0.01, 0.5
UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def observer(prior, seed=0):
    torch.manual_seed(seed)
    return ResidualObserver(
        G, Measurement(6, 3), functools.partial(GRUCore, hidden_size=8, num_layers=1),
        update=GroupUpdate({"R": "left"}), prior=prior, features=[Embedding(), Readings()],
    ).double()


def prior(tau=TAU, inner=True, **kw):
    return ComplementaryPrior("R", (0, 3), tau, DT, inner=KinematicPrior({"R": (6, 9)}, DT)
                              if inner else None, **kw)  # fmt: skip


def states(R):
    x = torch.zeros(R.shape[0], 12, dtype=torch.float64)
    x[:, :9] = R.flatten(-2)
    x[:, 9:] = torch.randn(R.shape[0], 3, dtype=torch.float64)
    return x


def tilt_angle(R, acc):
    """The angle between ``R acc`` and up."""
    v = (R @ acc[..., None])[..., 0]
    return torch.arccos((v @ UP) / v.norm(dim=-1))


@pytest.mark.parametrize("tau", [TAU, DT])
def test_the_correction_shrinks_the_tilt_by_dt_over_tau_of_its_sine(tau):
    """``R acc`` at angle ``t`` from up goes to ``t - (dt / tau) sin t`` (the rotation is about
    ``R acc x up``), the heading about ``R acc`` is not what it moves, ``b`` stays; also at the
    shortest ``tau`` allowed, ``dt``."""
    g = torch.Generator().manual_seed(0)
    R = SO3().random((64,), generator=g, dtype=torch.float64)
    acc = torch.randn(64, 3, generator=g, dtype=torch.float64) * 3
    x = states(R)
    ys = torch.cat((acc, torch.randn(64, 6, generator=g, dtype=torch.float64)), -1)
    out = prior(tau, inner=False).bind(G, Measurement(6, 3).bind(G))(x, ys, ys)
    R2 = out[:, :9].unflatten(-1, (3, 3))
    SO3().check_member(R2)
    t = tilt_angle(R, acc)
    assert torch.allclose(tilt_angle(R2, acc), t - DT / tau * torch.sin(t), atol=1e-12)
    # the correction is a world-frame rotation about an axis perpendicular to up and R acc
    axis = SO3().log(R2 @ R.transpose(-1, -2))
    assert torch.allclose(axis @ UP, torch.zeros(64, dtype=torch.float64), atol=1e-12)
    assert torch.allclose((axis * (R @ acc[..., None])[..., 0]).sum(-1),
                          torch.zeros(64, dtype=torch.float64), atol=1e-12)  # fmt: skip
    assert torch.equal(out[:, 9:], x[:, 9:])


def test_at_tau_equal_to_dt_a_small_tilt_is_gone_in_one_step():
    """``tau = dt`` turns by ``sin t``: a tilt ``t`` of 1e-3 .. 3e-2 rad leaves ``t - sin t``
    (below ``t^3 / 6``), whatever the heading."""
    t = torch.tensor([1e-3, 1e-2, 3e-2], dtype=torch.float64)
    axis = torch.stack((torch.cos(3 * t), torch.sin(3 * t), torch.zeros(3, dtype=torch.float64)), -1)
    R = SO3().exp(axis * t[:, None]) @ SO3().exp(UP * torch.tensor([[0.3], [2.0], [-1.0]]))
    acc = 9.81 * UP.expand(3, 3)
    assert torch.allclose(tilt_angle(R, acc), t, atol=1e-12)
    out = prior(DT, inner=False).bind(G, Measurement(6, 3).bind(G))(
        states(R), torch.cat((acc, torch.ones(3, 6, dtype=torch.float64)), -1),
        torch.cat((acc, torch.ones(3, 6, dtype=torch.float64)), -1))
    v = (out[:, :9].unflatten(-1, (3, 3)) @ acc[..., None])[..., 0]
    left = torch.atan2(torch.linalg.cross(v, UP.expand_as(v)).norm(dim=-1), v @ UP)  # exact near 0
    assert (left <= t**3 / 6).all()
    assert torch.allclose(left, t - torch.sin(t), atol=1e-15, rtol=1e-6)


def test_aligned_or_zero_readings_leave_the_inner_prior_alone():
    g = torch.Generator().manual_seed(1)
    R = SO3().random((8,), generator=g, dtype=torch.float64)
    x = states(R)
    acc = 9.81 * (R.transpose(-1, -2) @ UP)  # exactly up in the world frame: nothing to do
    gyro = torch.randn(8, 3, generator=g, dtype=torch.float64)
    mag = torch.randn(8, 3, generator=g, dtype=torch.float64)
    p = prior(inner=False).bind(G, Measurement(6, 3).bind(G))
    ys = torch.cat((acc, mag, gyro), -1)
    assert torch.allclose(p(x, ys, ys), x, atol=1e-14)
    zero = torch.cat((torch.zeros(8, 3, dtype=torch.float64), mag, gyro), -1)
    assert torch.equal(p(x, zero, zero), x)
    with_inner = prior().bind(G, Measurement(6, 3).bind(G))
    k = KinematicPrior({"R": (6, 9)}, DT).bind(G, Measurement(6, 3).bind(G))
    assert torch.equal(with_inner(x, zero, zero), k(x, zero, zero))


def test_held_still_a_tilted_start_levels_out_at_the_rate_tau_says():
    """Held still with a tilted start and a zero core output, the observer's tilt follows
    ``t <- t - (dt / tau) sin t`` step by step (the Euler step of ``dt/dt = -sin t / tau``, whose
    solution ``tan(t / 2) = tan(t0 / 2) exp(-t / tau)`` it stays within 5 % of over 4 ``tau``)."""
    obs = observer(prior(inner=False))
    t0, steps = 0.3, 200
    x0 = states(SO3().exp(torch.tensor([[t0, 0.0, 0.0]], dtype=torch.float64)))
    reading = torch.cat((UP * 9.81, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)))
    est = obs(reading.expand(1, steps, 6), torch.zeros(1, steps, 3, dtype=torch.float64),
              obs.init_state(1)._replace(estimate=x0))  # fmt: skip
    angle = tilt_angle(est[0, 1:, :9].unflatten(-1, (3, 3)), UP)
    euler, t = [], torch.tensor(t0, dtype=torch.float64)
    for _ in range(steps):
        t = t - DT / TAU * torch.sin(t)
        euler.append(t)
    assert torch.allclose(angle, torch.stack(euler), atol=1e-12)
    time = torch.arange(1, steps + 1, dtype=torch.float64) * DT
    assert torch.allclose(angle, 2 * torch.atan(math.tan(t0 / 2) * torch.exp(-time / TAU)),
                          rtol=5e-2)  # fmt: skip


def test_signature_build_and_widening_from_the_inner_prior(tmp_path):
    sig = observer(prior()).signature()["prior"]
    assert sig == {"type": "complementary", "factor": "R", "vector": [0, 3], "tau": TAU,
                   "dt": DT, "reference": [0.0, 0.0, 1.0],
                   "inner": {"type": "kinematic", "velocities": {"R": [6, 9]}, "dt": DT}}
    built = build_piece("prior", {"type": "complementary", "factor": "R", "vector": [0, 3],
                                  "tau": TAU, "inner": {"type": "kinematic",
                                                        "velocities": {"R": [6, 9]}}},
                        "model.prior", {"dt": DT})  # fmt: skip
    assert built.signature() == sig
    # a trained observer with the kinematic prior starts one with the correction added
    old = observer(KinematicPrior({"R": (6, 9)}, DT), seed=3)
    path = save_checkpoint(tmp_path / "old.pt", {"model": old.state_dict(), "config": {},
                                                 "signature": old.signature(), "epoch": 1})
    new = observer(prior(), seed=4)
    with pytest.raises(ValueError, match="signature"):
        load_weights(new, path)
    load_weights(new, path, widen=True)
    for (k, a), b in zip(old.state_dict().items(), new.state_dict().values()):
        assert torch.equal(a, b), k
    # ... but not one whose inner prior is another
    other = observer(ComplementaryPrior("R", (0, 3), TAU, DT))
    with pytest.raises(ValueError, match="prior is 'kinematic', this observer's 'none'"):
        load_weights(other, path, widen=True)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: ComplementaryPrior("R", (0, 3), 0.0, DT), r"tau must be a number .*seconds"),
        (lambda: observer(ComplementaryPrior("R", (0, 3), 0.4 * DT, DT)),
         r"tau = 0.004 s is shorter than the step dt = 0.01 s, so each step would turn by "
         r"dt / tau = 2.5 times the error .* give tau >= dt"),
        (lambda: ComplementaryPrior("R", (0, 3), TAU, DT, reference=(0, 0, 0)),
         r"reference must be 3 finite numbers, not all zero"),
        (lambda: ComplementaryPrior("R", (0, 3), TAU, DT, reference=(0, 1)),
         r"reference must be 3 finite numbers"),
        (lambda: ComplementaryPrior("R", 3, TAU, DT), r"vector\['v'\] must be \(start, stop\)"),
        (lambda: ComplementaryPrior("R", (0, 3), TAU, DT, inner="kinematic"),
         "inner must be a prior"),
        (lambda: observer(ComplementaryPrior("b", (0, 3), TAU, DT)),
         r"factor 'b' is Euclidean\(3\); it corrects an SO\(3\) factor"),
        (lambda: observer(ComplementaryPrior("q", (0, 3), TAU, DT)), "names a factor 'q'"),
        (lambda: observer(ComplementaryPrior("R", (7, 10), TAU, DT)),
         r"vector = \(7, 10\) must be a span of \(y, u\) \(size 9\) of 3 entries"),
    ],
)
def test_bad_settings_say_what_is_wrong(make, message):
    with pytest.raises(ValueError, match=message):
        make()
