"""Properties every registered piece (:data:`manifold_nets.observer.PIECES`) must have, in a few
observers that together hold each of them, on the rigid body and on a plain SO(3) and SE(3):

* (a) the rollout, the online step loop, the online step module (``OnlineStep``) and, for one
  observer, the exported step agree to 1e-12 (float64), past a centring ramp and a decay start;
* (b) the estimate stays on the group;
* (c) each piece's signature round-trips through a config block (``build_piece``);
* (d) an observer with one piece more (or a wider one in its place) started from the smaller
  one's checkpoint (``load_weights(widen=True)``) computes what the smaller one did;
* (e) an untrained observer whose core the observer made holds still without a prior and
  follows its prior with one;
* (f) a piece defined outside the library (here: :class:`MyFeature`) is registered and a config
  block can name it.
"""

from __future__ import annotations

import functools

import pytest
import torch
from omegaconf import OmegaConf

from groups import SE3, SO3
from manifold_nets import export_observer
from manifold_nets.builders import build_observer, build_piece
from manifold_nets.checkpoint import load_weights, save_checkpoint
from manifold_nets.config import ModelConfig
from manifold_nets.cores import GRUCore
from manifold_nets.deploy import OnlineStep, load_exported_step
from manifold_nets.observer import (
    PIECES,
    CentredHead,
    Embedding,
    Feature,
    FramedInnovation,
    GainHead,
    GroupUpdate,
    Innovation,
    ComplementaryPrior,
    KinematicPrior,
    Measurement,
    NoPrior,
    OutputScale,
    PlainHead,
    Projection,
    Readings,
    ResidualObserver,
    RobustMeasurement,
    RobustSystemPrior,
    RobustWeights,
    Rotated,
    StepDecay,
    SystemPrior,
)
from manifold_nets.system import System
from manifold_nets_examples.rigid_body import RigidBody

CORE = functools.partial(GRUCore, hidden_size=8, num_layers=1)
#: the rigid body's measured factors: y[0:9] is vec R, y[9:12] is p
MEASURED = {"R": (0, 9), "p": (9, 12)}
FRAME = {"p": "R"}
STEPS = 12  # past every ramp (<= 5) and decay start (<= 5) below


# ---------------------------------------------------------------------- a piece of one's own


class MyFeature(Feature):
    """A user's own feature: the measured factors' squared innovation norms, times ``scale``."""

    name = "my_feature"

    def __init__(self, scale: float = 1.0):
        super().__init__()
        self.scale = float(scale)

    def settings(self):
        return {"scale": self.scale} if self.scale != 1.0 else {}

    def bind(self, group, measurement):
        if not measurement.factors:
            raise ValueError("my_feature reads the measured factors' innovations; name some.")
        self.width = len(measurement.factors)
        return self

    def forward(self, view):
        return self.scale * torch.stack([(nu * nu).sum(-1) for nu in view.nu], dim=-1)


# ---------------------------------------------------------------------- a plain SO(3), SE(3) system


class Spinner(System):
    """``x_{k+1} = x_k exp(dt w_k)`` on ``group``, ``w_k`` a random velocity; ``y = embed(x)``
    followed by the velocity reading ``w_k``, or (``as_input``) the velocity as the input ``u``."""

    name, dt = "spinner", 0.1

    def __init__(self, group, as_input: bool = False):
        self.group, self.as_input = group, as_input
        self.embedding_dim = group.embedding_dim
        self.drive_dim = group.tangent_dim
        self.input_dim = self.drive_dim if as_input else 0
        self.measurement_dim = self.noise_dim = self.embedding_dim + (
            0 if as_input else self.drive_dim
        )

    def config(self):
        return {"group": repr(self.group), "as_input": self.as_input}

    def sample_initial_state(self, num_sequences, generator):
        return self.group.random((num_sequences,), generator=generator, dtype=torch.float64)

    def sample_drive(self, num_sequences, length, generator):
        shape = (num_sequences, length, self.drive_dim)
        return torch.randn(shape, generator=generator, dtype=torch.float64)

    def step(self, x, drive, dt=None):
        return self.group.rplus(x, (self.dt if dt is None else dt) * drive)

    def observe(self, x, drive):
        e = self.group.embed(x)
        if self.as_input:
            return e
        return torch.cat([e, drive.expand(*e.shape[:-1], -1)], dim=-1)

    def drive_from_measurement(self, y, u):
        return u if self.as_input else y[..., self.embedding_dim:]


def _data(system, n=3, t=STEPS, sigma=0.2, seed=1):
    return system.simulate(n, t, sigma, torch.Generator().manual_seed(seed))


def _inputs(system, data):
    return data.inputs if system.input_dim else None


def randomise(obs, seed=0, scale=0.3):
    """Weights far from where an observer starts: the core's output layer random (``K`` too) and
    every learned robust weight function shaped away from the identity."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in obs.core.head.parameters():
            p.copy_(scale * (2 * torch.rand(p.shape, generator=g, dtype=torch.float64) - 1))
        for m in obs.modules():
            if isinstance(m, RobustWeights):
                m.amplitude.copy_(-0.3 * torch.rand(m.amplitude.shape, generator=g,
                                                    dtype=torch.float64))
                m.knots.add_(0.2 * torch.randn(m.knots.shape, generator=g, dtype=torch.float64))
    return obs


# ---------------------------------------------------------------------- observers of every piece


def _rigid_centred(system):
    return dict(
        measurement=Measurement(18, 0, MEASURED), prior=SystemPrior(system),
        features=[Embedding(drop=["p"]), Readings(drop=["p"]), Innovation(),
                  Rotated({"R": [(12, 15), (15, 18)]}), FramedInnovation(FRAME), MyFeature(2.0)],
        head=CentredHead(0.8, ramp=4, factors={"b_v": 0.5}, inner=GainHead()),
        scales=[StepDecay({"b_omega": 3, "b_v": 5}), OutputScale(0.5)],
    )


#: name -> (system, pieces of the observer); every registered piece is in one of them at least
COMBOS = {
    "rigid_body_paper": (RigidBody, lambda s: dict(measurement=Measurement(18))),
    "rigid_body_centred_gain": (RigidBody, _rigid_centred),
    "rigid_body_robust": (RigidBody, lambda s: dict(
        measurement=RobustMeasurement(18, 0, MEASURED, width=4, span=2.0),
        prior=RobustSystemPrior(s, width=4, span=2.0),
        features=[Embedding(), Readings(), Innovation(), FramedInnovation(FRAME)],
        head=GainHead(offset=False), scales=[OutputScale(0.3)],
    )),
    "rigid_body_kinematic": (RigidBody, lambda s: dict(
        measurement=Measurement(18, 0, {"R": (0, 9)}),
        prior=KinematicPrior({"R": (12, 15)}, s.dt),  # the gyro reading
        features=[Embedding(), Readings(), Innovation()],
        head=CentredHead(1.0, ramp=3), scales=[StepDecay({"b_omega": 2})],
    )),
    "so3_system": (lambda: Spinner(SO3()), lambda s: dict(
        measurement=Measurement(12, 0, {"x": (0, 9)}), prior=SystemPrior(s),
        features=[Embedding(), Readings(), Innovation(), Rotated({"x": [(9, 12)]}), MyFeature()],
        head=CentredHead(0.9, ramp=5), scales=[StepDecay({"x": 4})],
    )),
    "so3_complementary_left": (lambda: Spinner(SO3(), as_input=True), lambda s: dict(
        measurement=Measurement(9, 3, {"x": (0, 9)}), update=GroupUpdate({"x": "left"}),
        prior=ComplementaryPrior("x", (9, 12), 0.5, s.dt, reference=(0.0, 1.0, 1.0),
                                 inner=KinematicPrior({"x": (9, 12)}, s.dt)),
        features=[Embedding(), Readings(), Innovation()], head=PlainHead(),
        scales=[Projection({"x": [[0.0, 0.0, 1.0], [1.0, 1.0, 0.0]]}), OutputScale(0.5)],
    )),
    "so3_heading_gated_after_tilt": (lambda: Spinner(SO3(), as_input=True), lambda s: dict(
        measurement=Measurement(9, 3, {"x": (0, 9)}), update=GroupUpdate({"x": "left"}),
        prior=ComplementaryPrior(
            "x", (0, 3), 0.5, s.dt, reference=(0.0, 1.0, 0.0), about=(0.0, 0.0, 1.0),
            gate={"norm": 1.0, "norm_tol": 0.3, "elevation": 0.0, "elevation_tol": 30.0},
            inner=ComplementaryPrior("x", (3, 6), 0.5, s.dt,
                                     inner=KinematicPrior({"x": (9, 12)}, s.dt))),
        features=[Embedding(), Readings()], head=PlainHead(), scales=[OutputScale(0.5)],
    )),
    "se3_kinematic_left": (lambda: Spinner(SE3(), as_input=True), lambda s: dict(
        measurement=Measurement(12, 6, {"x": (0, 12)}),
        prior=KinematicPrior({"x": (12, 18)}, s.dt), update=GroupUpdate({"x": "left"}),
        features=[Embedding(), Readings(), Innovation(), MyFeature(0.5)],
        head=GainHead(), scales=[OutputScale(0.5)],
    )),
    "se3_robust_system": (lambda: Spinner(SE3()), lambda s: dict(
        measurement=RobustMeasurement(18, 0, {"x": (0, 12)}, width=3),
        prior=RobustSystemPrior(s, width=3), head=PlainHead(),
        features=[Embedding(), Readings(), Innovation()],
    )),
}


def combo(name, seed=0):
    make_system, pieces = COMBOS[name]
    system = make_system()
    torch.manual_seed(seed)
    obs = ResidualObserver(system.group, core=CORE, **pieces(system)).double()
    return system, randomise(obs, seed)


def _library_pieces():
    """The registered pieces of the library and of this module (other test modules may
    register pieces of their own: they are theirs to test)."""
    return sorted(
        key for key, cls in PIECES.items()
        if cls.__module__.startswith("manifold_nets.") or cls.__module__ == __name__
    )


def test_the_observers_hold_every_registered_piece():
    held = set()
    for name in COMBOS:
        _, obs = combo(name)
        for piece in obs.pieces().values():
            held.add((piece.kind, piece.name))
            inner = getattr(piece, "inner", None)
            if inner is not None:
                held.add((inner.kind, inner.name))
    assert ("feature", "my_feature") in PIECES and PIECES[("feature", "my_feature")] is MyFeature
    missing = set(_library_pieces()) - held
    assert not missing, f"add these pieces to an observer in COMBOS: {sorted(missing)}"


# ---------------------------------------------------------------------- (a), (b)


def _online_step_module(obs, measurements, inputs):
    """The estimates of ``OnlineStep(obs)`` called directly, ``(N, T+1, numel)``, and its final
    state tensors."""
    step = OnlineStep(obs)
    n, t = measurements.shape[:2]
    x, *state = step.initial_state(n)
    xs = [x]
    for k in range(t):
        extra = () if inputs is None else (inputs[:, k].to(obs.net_dtype),)
        x, *state = step(x, *state, measurements[:, k], *extra)
        xs.append(x)
    return torch.stack(xs, 1), state


@pytest.mark.parametrize("name", sorted(COMBOS))
def test_rollout_online_steps_and_the_step_module_agree_and_stay_on_the_group(name):
    system, obs = combo(name)
    data = _data(system)
    y, u = data.measurements, _inputs(system, data)
    with torch.no_grad():
        est = obs(y, u)
        assert est.dtype == torch.float64
        assert est.shape == (3, STEPS + 1, *system.group.element_shape)
        state = obs.init_state(3)
        for k in range(STEPS):
            state = obs.step(state, y[:, k], None if u is None else u[:, k])
            torch.testing.assert_close(state.estimate, est[:, k + 1], rtol=0, atol=1e-12)
        assert state.steps == STEPS
        xs, last = _online_step_module(obs, y, u)
        torch.testing.assert_close(xs, est.flatten(2), rtol=0, atol=1e-12)
        if obs.uses_step_count:  # the count is the steps taken, past every ramp and decay start
            assert last[-1].tolist() == [float(STEPS)] * 3
        # a rollout cut in two carries the state and the clock
        first, mid = obs(y[:, :5], None if u is None else u[:, :5], return_state=True)
        rest = obs(y[:, 5:], None if u is None else u[:, 5:], state=mid)
        torch.testing.assert_close(torch.cat([first, rest[:, 1:]], 1), est, rtol=0, atol=1e-12)
    system.group.check_member(est)
    assert float(est.abs().max()) < 1e6  # the random weights did not blow it up
    assert not torch.allclose(est[:, -1], est[:, 0])  # it moved


def test_the_exported_step_agrees_with_the_rollout(tmp_path):
    system, obs = combo("rigid_body_centred_gain")
    data = _data(system, n=2)
    with torch.no_grad():
        est = obs(data.measurements)
    export_observer(obs, tmp_path / "step.pt2")
    step = load_exported_step(tmp_path / "step.pt2")
    assert step.meta["inputs"][-2:] == ["steps", "y"]
    x, *state = step.initial_state(2)
    for k in range(STEPS):
        x, *state = step(x, *state, data.measurements[:, k])
        torch.testing.assert_close(x, est[:, k + 1].flatten(1), rtol=0, atol=1e-12)
    assert state[-1].tolist() == [float(STEPS)] * 2


# ---------------------------------------------------------------------- (c)


def _pieces_by_key():
    """Every piece of the observers in :data:`COMBOS` (inner heads too), bound, with the system
    it was made for: ``{(kind, name): [(system, piece, measurement), ...]}``."""
    out = {}
    for name in COMBOS:
        system, obs = combo(name)
        for piece in obs.pieces().values():
            for p in (piece, getattr(piece, "inner", None)):
                if p is not None:
                    out.setdefault((p.kind, p.name), []).append((system, p, obs.measurement))
    return out


@pytest.mark.parametrize("key", _library_pieces(), ids=lambda k: f"{k[0]}-{k[1]}")
def test_each_pieces_signature_round_trips_through_a_config_block(key):
    kind, name = key
    found = _pieces_by_key()[key]
    for system, piece, measurement in found:
        sig = piece.signature()
        assert sig == {"type": name, **piece.settings()}
        context = {"system": system, "dt": system.dt, "dim": measurement.dim,
                   "input_dim": measurement.input_dim}
        # the settings a builder supplies (the context's) left to the context ...
        block = {k: v for k, v in piece.settings().items() if k not in context}
        for_context = {k: v for k, v in piece.settings().items() if k in context}
        built = build_piece(kind, {"type": name, **block}, "where", {**context, **for_context})
        assert type(built) is type(piece) and built.signature() == sig
        # ... and the settings as they are: "the piece's arguments (its config block without
        # type)", Piece.settings says
        built = build_piece(kind, {"type": name, **piece.settings()}, "where", context)
        assert type(built) is type(piece)
        assert built.signature() == sig
        if kind == "measurement":
            built.bind(system.group)
        else:
            built.bind(system.group, measurement)
        assert built.signature() == sig  # binding changes nothing of it


# ---------------------------------------------------------------------- (d)


def _rigid(system, seed, **changes):
    pieces = dict(
        measurement=Measurement(18, 0, MEASURED), prior=SystemPrior(system),
        features=[Embedding(drop=["p"]), Readings(drop=["p"]), Innovation()], head=PlainHead(),
    )
    torch.manual_seed(seed)
    obs = ResidualObserver(system.group, core=CORE, **{**pieces, **changes}).double()
    return randomise(obs, seed)


def _features(*more):
    return lambda s: dict(features=[Embedding(drop=["p"]), Readings(drop=["p"]), *more])


#: name -> (the smaller observer's changes, the wider one's), each a function of the system
WIDENINGS = {
    "framed_innovation_added": (
        lambda s: {}, lambda s: _features(Innovation(), FramedInnovation(FRAME))(s)),
    "innovation_added_in_the_middle": (
        _features(FramedInnovation(FRAME)),
        _features(Innovation(), FramedInnovation(FRAME))),
    "robust_system_prior_for_the_system_prior": (
        lambda s: {}, lambda s: dict(prior=RobustSystemPrior(s, width=4))),
    "robust_measurement_for_the_measurement": (
        lambda s: {}, lambda s: dict(measurement=RobustMeasurement(18, 0, MEASURED, width=4))),
    "gain_head_for_the_plain_head": (lambda s: {}, lambda s: dict(head=GainHead())),
    "step_decay_added": (  # d_k = 1 over the sequence (k <= K): the same steps
        lambda s: {}, lambda s: dict(scales=[StepDecay({"b_omega": 70, "b_v": 70})])),
    "several_at_once": (
        _features(FramedInnovation(FRAME)),
        lambda s: dict(measurement=RobustMeasurement(18, 0, MEASURED, width=3),
                       prior=RobustSystemPrior(s, width=3), head=GainHead(),
                       scales=[StepDecay({"b_v": 70})],
                       **_features(Innovation(), MyFeature(), FramedInnovation(FRAME))(s))),
}


def _save(obs, path):
    return save_checkpoint(path, {"model": obs.state_dict(), "signature": obs.signature(),
                                  "config": {}, "epoch": 0})


@pytest.mark.parametrize("case", sorted(WIDENINGS))
def test_a_wider_observer_started_from_a_smaller_ones_checkpoint_computes_what_it_did(
    case, tmp_path
):
    system = RigidBody()
    data = _data(system, t=40)
    small_changes, wide_changes = WIDENINGS[case]
    small = _rigid(system, 1, **small_changes(system))
    wide = _rigid(system, 2, **wide_changes(system))  # its own random weights, overwritten
    load_weights(wide, _save(small, tmp_path / "small.pt"), widen=True)
    with torch.no_grad():
        want, got = small(data.measurements), wide(data.measurements)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_a_centred_head_loads_a_plain_heads_weights_and_starts_from_its_step(tmp_path):
    """The centring adds no weight: the centred observer gets the plain one's weights as they
    are. It subtracts ``c_k T(z^0)``, which no weight cancels, so it computes the plain
    observer's steps only while ``c_k = 0``: the first step of a ramp."""
    system = RigidBody()
    data = _data(system, t=20)
    small = _rigid(system, 1)
    wide = _rigid(system, 2, head=CentredHead(0.7, ramp=5))
    load_weights(wide, _save(small, tmp_path / "small.pt"), widen=True)
    for a, b in zip(wide.state_dict().values(), small.state_dict().values()):
        assert torch.equal(a, b)
    with torch.no_grad():
        want, got = small(data.measurements), wide(data.measurements)
    torch.testing.assert_close(got[:, :2], want[:, :2], rtol=0, atol=1e-12)
    assert not torch.allclose(got[:, -1], want[:, -1], atol=1e-6)


# ---------------------------------------------------------------------- (e)


UNTRAINED = {
    "rigid_body": (RigidBody, lambda s: dict(
        measurement=Measurement(18, 0, MEASURED),
        features=[Embedding(drop=["p"]), Readings(drop=["p"]), Innovation()])),
    "so3": (lambda: Spinner(SO3()), lambda s: dict(
        measurement=Measurement(12, 0, {"x": (0, 9)}),
        features=[Embedding(), Readings(), Innovation()])),
    "se3": (lambda: Spinner(SE3(), as_input=True), lambda s: dict(
        measurement=Measurement(12, 6, {"x": (0, 12)}),
        features=[Embedding(), Readings(), Innovation()])),
}
CORES = {"default": lambda: None, "factory": lambda: CORE}


@pytest.mark.parametrize("core", sorted(CORES))
@pytest.mark.parametrize("where", sorted(UNTRAINED))
@pytest.mark.parametrize("prior, head", [  # a centred head needs a prior
    ("none", "plain"), ("system", "plain"), ("system", "centred"), ("robust_system", "plain"),
    ("robust_system", "centred"),
])
def test_an_untrained_observer_holds_still_or_follows_its_prior(core, where, prior, head):
    make_system, pieces = UNTRAINED[where]
    system = make_system()
    made_prior = {"none": NoPrior, "system": lambda: SystemPrior(system),
                  "robust_system": lambda: RobustSystemPrior(system)}[prior]()
    obs = ResidualObserver(
        system.group, core=CORES[core](), prior=made_prior,
        head=PlainHead() if head == "plain" else CentredHead(0.8, ramp=2), **pieces(system),
    )
    data = _data(system, n=2, t=15)
    u = _inputs(system, data)
    with torch.no_grad():
        est = obs(data.measurements, u)
    x = system.group.identity((2,), dtype=torch.float64)
    torch.testing.assert_close(est[:, 0], x, rtol=0, atol=0)
    for k in range(15):
        if prior != "none":  # the prior's prediction run alone
            x = system.predict(x, data.measurements[:, k], None if u is None else u[:, k])
        torch.testing.assert_close(est[:, k + 1], x, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------- (f)


def test_a_piece_of_ones_own_is_registered_and_a_config_block_names_it():
    assert PIECES[("feature", "my_feature")] is MyFeature
    built = build_piece("feature", {"type": "my_feature", "scale": 2.0}, "model.features[3]")
    assert isinstance(built, MyFeature) and built.scale == 2.0
    with pytest.raises(ValueError, match=r"model.features\[3\] \(my_feature\): unknown key\(s\) "
                                         r"\['width'\]; a my_feature feature takes \['scale'\]"):
        build_piece("feature", {"type": "my_feature", "width": 3}, "model.features[3]")
    with pytest.raises(ValueError, match=r"model.features\[0\].type: 'mine' is not a feature "
                                         r"piece; the features are \[.*'my_feature'"):
        build_piece("feature", {"type": "mine"}, "model.features[0]")
    system = RigidBody()
    model = OmegaConf.structured(ModelConfig(
        hidden_size=8, num_layers=1, measurement={"factors": {"R": [0, 9], "p": [9, 12]}},
        prior={"type": "system"},
        features=["embedding", "readings", "innovation", {"type": "my_feature", "scale": 0.5}],
        head={"type": "centred", "c": 0.9},
    ))
    obs = build_observer(system.group, 18, 0, model, system=system)
    assert isinstance(obs.features[-1], MyFeature) and obs.features[-1].scale == 0.5
    assert obs.signature()["features"][-1] == {"type": "my_feature", "scale": 0.5}
    assert obs.core.input_size == 18 + 18 + 6 + 2
    data = _data(system, n=2, t=6)
    with torch.no_grad():
        est = obs(data.measurements)
    system.group.check_member(est)
