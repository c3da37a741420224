"""The complementary prior turning about one axis (``about``) and gated (``gate``): a heading
correction from a magnetometer that cannot tilt the estimate and stops where the field is
disturbed, nested after a tilt correction. The AHRS-shaped observer of
``test_complementary_prior.py``: SO(3) x R^3 reading ``y = (acc, mag)`` and a gyro ``u``."""

from __future__ import annotations

import math

import pytest
import torch

from groups import SO3
from manifold_nets.builders import build_piece
from manifold_nets.checkpoint import load_weights, save_checkpoint
from manifold_nets.observer import ComplementaryPrior, KinematicPrior, Measurement

from test_complementary_prior import DT, TAU, UP, G, observer, states

NORTH = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
DIP = 69.5  # degrees below the horizon: the field points north and down
FIELD = 44.0 * torch.tensor([0.0, math.cos(math.radians(DIP)), -math.sin(math.radians(DIP))],
                            dtype=torch.float64)  # fmt: skip
GATE = {"norm": 44.0, "norm_tol": 0.1, "elevation": -DIP, "elevation_tol": 10.0}


def heading(tau=TAU, gate=None, inner=None):
    return ComplementaryPrior("R", (3, 6), tau, DT, reference=(0.0, 1.0, 0.0), about=(0, 0, 1),
                              gate=gate, inner=inner)  # fmt: skip


def bound(p):
    return p.bind(G, Measurement(6, 3).bind(G))


def readings(R, world_mag, acc=None, g=None):
    """Body-frame (acc, mag, gyro) for attitudes ``R`` that see ``world_mag`` in the world."""
    mag = (R.transpose(-1, -2) @ world_mag[..., None])[..., 0]
    acc = (R.transpose(-1, -2) @ (9.81 * UP))[..., None][..., 0] if acc is None else acc
    gyro = torch.randn(R.shape[0], 3, generator=g, dtype=torch.float64)
    return torch.cat((acc, mag, gyro), -1)


def yaw(angle):
    return SO3().exp(angle[:, None] * UP)


def test_the_turn_is_about_up_only_and_leaves_every_vertical_component():
    """For any attitude and any reading the corrected ``R`` differs from ``R`` by a turn about up:
    the world-frame vertical component of every body vector is unchanged (no tilt)."""
    g = torch.Generator().manual_seed(0)
    R = SO3().random((128,), generator=g, dtype=torch.float64)
    ys = torch.randn(128, 9, generator=g, dtype=torch.float64) * 20
    out = bound(heading())(states(R), ys, ys)
    R2 = out[:, :9].unflatten(-1, (3, 3))
    SO3().check_member(R2)
    turn = SO3().log(R2 @ R.transpose(-1, -2))
    assert torch.allclose(turn[:, :2], torch.zeros(128, 2, dtype=torch.float64), atol=1e-12)
    body = torch.randn(128, 3, generator=g, dtype=torch.float64)
    assert torch.allclose((R2 @ body[..., None])[:, 2], (R @ body[..., None])[:, 2], atol=1e-12)


def test_a_heading_error_shrinks_by_dt_over_tau_of_its_sine_whatever_the_tilt():
    """The estimate off the truth by a yaw ``e`` (and the truth tilted anyhow): the magnetometer's
    horizontal part is ``e`` from north, and the yaw error goes to ``e - (dt / tau) sin e``."""
    g = torch.Generator().manual_seed(1)
    truth = SO3().random((64,), generator=g, dtype=torch.float64)
    e = (torch.rand(64, generator=g, dtype=torch.float64) - 0.5) * 3
    R = yaw(e) @ truth
    ys = readings(truth, FIELD, g=g)
    R2 = bound(heading())(states(R), ys, ys)[:, :9].unflatten(-1, (3, 3))
    left = SO3().log(R2 @ truth.transpose(-1, -2))
    assert torch.allclose(left[:, 2], e - DT / TAU * torch.sin(e), atol=1e-12)
    assert torch.allclose(left[:, :2], torch.zeros(64, 2, dtype=torch.float64), atol=1e-12)
    # the reference counts by its part normal to about: north and up is north
    slanted = ComplementaryPrior("R", (3, 6), TAU, DT, reference=(0.0, 2.0, 5.0), about=(0, 0, 3))
    assert torch.allclose(bound(slanted)(states(R), ys, ys)[:, :9], R2.flatten(-2), atol=1e-13)


def test_the_gate_passes_the_undisturbed_field_and_stops_a_disturbed_one():
    g = torch.Generator().manual_seed(2)
    truth = SO3().random((6,), generator=g, dtype=torch.float64)
    R = yaw(torch.full((6,), 0.2, dtype=torch.float64)) @ truth
    x = states(R)
    gated, free = bound(heading(gate=GATE)), bound(heading())
    ok = readings(truth, FIELD, g=g)
    assert torch.equal(gated(x, ok, ok), free(x, ok, ok))  # inside every band: the same turn
    assert not torch.allclose(gated(x, ok, ok), x)
    dip = math.radians(DIP + 15.0)  # the strength right, the dip 15 deg off
    tipped = 44.0 * torch.tensor([0.0, math.cos(dip), -math.sin(dip)], dtype=torch.float64)
    for world in (FIELD * 1.2, FIELD * 0.85, tipped):
        bad = readings(truth, world, g=g)
        assert torch.equal(gated(x, bad, bad), x), world
    # strength alone: the dip is not looked at
    strength = bound(heading(gate={"norm": 44.0, "norm_tol": 0.1}))
    tip = readings(truth, tipped, g=g)
    assert torch.equal(strength(x, tip, tip), free(x, tip, tip))
    # per sample: one disturbed row of a batch stops only that row
    mixed = torch.cat((ok[:3], readings(truth[3:], FIELD * 1.5, g=g)))
    out = gated(x, mixed, mixed)
    assert torch.equal(out[:3], free(x, ok, ok)[:3]) and torch.equal(out[3:], x[3:])


def test_nested_after_a_tilt_correction_builds_saves_and_widens(tmp_path):
    block = {"type": "complementary", "factor": "R", "vector": [3, 6], "tau": 10.0,
             "reference": [0, 1, 0], "about": [0, 0, 1], "gate": dict(GATE),
             "inner": {"type": "complementary", "factor": "R", "vector": [0, 3], "tau": TAU,
                       "inner": {"type": "kinematic", "velocities": {"R": [6, 9]}}}}
    built = build_piece("prior", block, "model.prior", {"dt": DT})
    tilt = ComplementaryPrior("R", (0, 3), TAU, DT, inner=KinematicPrior({"R": (6, 9)}, DT))
    made = heading(10.0, GATE, tilt)
    assert built.signature() == made.signature()
    assert made.signature()["gate"] == GATE and made.signature()["about"] == [0.0, 0.0, 1.0]
    # a trained observer with the tilt correction starts one with the heading correction added
    old = observer(tilt, seed=3)
    path = save_checkpoint(tmp_path / "old.pt", {"model": old.state_dict(), "config": {},
                                                 "signature": old.signature(), "epoch": 1})
    new = observer(made, seed=4)
    load_weights(new, path, widen=True)
    for (k, a), b in zip(old.state_dict().items(), new.state_dict().values()):
        assert torch.equal(a, b), k
    # nested, the tilt goes first, then the heading: the same as the two applied by hand
    g = torch.Generator().manual_seed(5)
    R = SO3().random((16,), generator=g, dtype=torch.float64)
    ys = readings(SO3().random((16,), generator=g, dtype=torch.float64), FIELD, g=g)
    x = states(R)
    by_hand = bound(heading(10.0, GATE))(bound(tilt)(x, ys, ys), ys, ys)
    assert torch.equal(bound(made)(x, ys, ys), by_hand)


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"about": (0, 0, 0)}, r"about must be 3 finite numbers, not all zero"),
        ({"about": (0, 1, 0)}, r"reference is along about"),
        ({"gate": {"norm": 44.0}}, r"gate needs norm and norm_tol"),
        ({"gate": {"norm": 44.0, "norm_tol": 0.1, "dip": 3}}, r"gate must be a mapping of"),
        ({"gate": [44.0, 0.1]}, r"gate must be a mapping of"),
        ({"gate": {"norm": -1.0, "norm_tol": 0.1}}, r"gate.norm must be a number"),
        ({"gate": {"norm": 44.0, "norm_tol": 0.1, "elevation": -69.5}},
         r"elevation and elevation_tol go together"),
        ({"gate": {"norm": 44.0, "norm_tol": 0.1, "elevation": -100, "elevation_tol": 5}},
         r"gate.elevation must be a number in \[-90, 90\]"),
        ({"about": None, "gate": GATE}, r"give about"),
    ],
)
def test_bad_settings_say_what_is_wrong(kw, message):
    args = {"reference": (0.0, 1.0, 0.0), "about": (0, 0, 1), **kw}
    with pytest.raises(ValueError, match=message):
        ComplementaryPrior("R", (3, 6), TAU, DT, **args)


def test_rollout_online_step_and_exported_step_agree_with_the_gate_opening_and_closing(tmp_path):
    """The nested, gated prior in every code path: the rollout, ``step`` and the exported step
    (``torch.export``) give the same estimates over readings whose field is disturbed at every
    third step, so the gate opens and closes within one sequence."""
    from manifold_nets import export_observer
    from manifold_nets.deploy import load_exported_step

    tilt = ComplementaryPrior("R", (0, 3), TAU, DT, inner=KinematicPrior({"R": (6, 9)}, DT))
    obs = observer(heading(0.2, GATE, tilt), seed=1)
    g = torch.Generator().manual_seed(6)
    n, t = 3, 24
    truth = SO3().random((n,), generator=g, dtype=torch.float64)
    ys = torch.stack([readings(truth, FIELD * (1.4 if k % 3 == 0 else 1.0), g=g)
                      for k in range(t)], 1)  # fmt: skip
    ys[..., 6:] *= 0.1
    y, u = ys[..., :6], ys[..., 6:]
    start = obs.init_state(n)._replace(estimate=states(yaw(torch.full((n,), 0.5)) @ truth))
    with torch.no_grad():
        est = obs(y, u, start)
        state = start
        for k in range(t):
            state = obs.step(state, y[:, k], u[:, k])
            torch.testing.assert_close(state.estimate, est[:, k + 1], rtol=0, atol=1e-12)
    strength = y[..., 3:6].norm(dim=-1) / GATE["norm"]  # 1.4 at every third step: closed there
    assert ((strength - 1).abs() > GATE["norm_tol"]).sum() == n * (t // 3)
    export_observer(obs, tmp_path / "step.pt2")
    step = load_exported_step(tmp_path / "step.pt2")
    x, *hidden = step.initial_state(n)
    x = start.estimate.reshape(n, -1)
    for k in range(t):
        x, *hidden = step(x, *hidden, y[:, k], u[:, k].to(obs.net_dtype))
        torch.testing.assert_close(x, est[:, k + 1].flatten(1), rtol=0, atol=1e-10)
