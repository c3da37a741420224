"""The system prior (``SystemPrior(system)``, ``prior: {type: system}``): ``System.predict`` moves
the estimate before the learned update. Pinned: each shipped system's ``predict`` is its own
dynamics with the bias-corrected readings (its step with the compensated drive); the observer's
rollout, online step and exported step apply it; the gradient flows through it; the signature
records it; bad settings say what is wrong."""

from __future__ import annotations

import warnings

import pytest
import torch
from omegaconf import OmegaConf

from manifold_nets.builders import build_observer, build_piece
from manifold_nets.checkpoint import CheckpointError, check_signature
from manifold_nets.config import ModelConfig
from manifold_nets.observer import (
    Embedding,
    Measurement,
    ObserverState,
    PlainHead,
    Readings,
    ResidualObserver,
    SystemPrior,
)
from manifold_nets_examples.attitude import Attitude
from manifold_nets_examples.planar import Planar
from manifold_nets_examples.rigid_body import MismatchedRigidBody, RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load
from tests.test_centred_update import block_overrides, rigid_observer, simulate

SYSTEMS = {
    "rigid_body": lambda: RigidBody(),
    "rigid_body_se3": lambda: RigidBody(pose_group="se3"),
    "rigid_body_mismatch_off": lambda: MismatchedRigidBody(),
    "attitude": lambda: Attitude(),
    "planar": lambda: Planar(),
    "planar_so2_r2": lambda: Planar(pose_group="so2_r2"),
}


def prior_observer(system=None, zero=False, seed=0, **changes) -> ResidualObserver:
    """:func:`rigid_observer` with the plain head; ``zero``: the core's output at zero, where a
    core the observer makes starts (only the prior moves the estimate)."""
    return rigid_observer(system, seed, head=changes.pop("head", PlainHead()), untrained=zero,
                          **changes)


def _model(**changes) -> ModelConfig:
    base = dict(hidden_size=16, num_layers=1, updates={})
    return OmegaConf.structured(ModelConfig(**{**base, **changes}))


@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_predict_from_the_true_state_and_noise_free_readings_is_the_next_state(name):
    """The biases the readings carry are the state's, so subtracting the true ones recovers the
    true drive, and the prediction is the system's own step: exact to rounding."""
    system = SYSTEMS[name]()
    data = simulate(system)
    u = data.inputs if system.input_dim else None
    for k in (0, 7, 29):
        uk = None if u is None else u[:, k]
        pred = system.predict(data.states[:, k], data.measurements[:, k], uk)
        assert torch.allclose(pred, data.states[:, k + 1], atol=1e-12), name


@pytest.mark.parametrize("make", [RigidBody, Attitude, Planar])
def test_the_prediction_steps_with_the_compensated_drive(make):
    system = make()
    g = torch.Generator().manual_seed(3)
    data = system.simulate(2, 5, 0.2, g)
    # an estimate whose biases are off, so the compensation shows
    x = data.states[:, 2] + 0.0
    x[..., -2:] += 0.3
    y = data.measurements[:, 2]
    drive = system.compensated_drive(x, y, None)
    assert drive.shape == (2, system.drive_dim)
    torch.testing.assert_close(system.predict(x, y, None), system.step(x, drive), rtol=0, atol=0)
    # the compensated drive is the reading less what the estimate says of its error
    assert not torch.equal(drive, system.drive_from_measurement(y, None))


def test_the_rigid_bodys_compensated_drive_is_the_readings_less_the_estimated_biases():
    system = RigidBody()
    data = simulate(system, n=3, t=4, sigma=0.1)
    x, y = data.states[:, 1], data.measurements[:, 1]
    want = torch.cat([y[:, 12:15] - x[:, 12:15], y[:, 15:18] - x[:, 15:18]], dim=-1)
    torch.testing.assert_close(system.compensated_drive(x, y, None), want, rtol=0, atol=0)


def test_the_rigid_bodys_prediction_subtracts_the_estimates_biases():
    """With wrong bias estimates the prediction is the step with the readings less those."""
    system = RigidBody()
    data = simulate(system, sigma=0.2)
    x, y = data.states[:, 3].clone(), data.measurements[:, 3]
    x[:, -6:] = torch.randn(4, 6, dtype=torch.float64)
    want = system.step(x, y[:, 12:] - x[:, -6:])
    assert torch.equal(system.predict(x, y, None), want)
    raw = system.step(x, y[:, 12:])  # dead reckoning on the biased readings: another state
    assert not torch.allclose(raw[:, :12], want[:, :12], atol=1e-3)


def test_a_zero_correction_started_at_the_truth_follows_it_exactly():
    system = RigidBody()
    data = simulate(system, t=50)
    obs = prior_observer(system, zero=True)
    assert torch.count_nonzero(obs.core.head.weight) == 0  # an untrained observer's
    start = ObserverState(data.states[:, 0].clone(), obs.init_state(4).hidden)
    with torch.no_grad():
        est = obs(data.measurements, state=start)
    assert torch.allclose(est, data.states, atol=1e-12)


def test_the_core_reads_the_prediction():
    system = RigidBody()
    data = simulate(system, n=2, t=1, sigma=0.1)
    obs = prior_observer(system, zero=True)
    seen = []
    obs.core.step = lambda inp, h: (seen.append(inp) or torch.zeros(2, 12, dtype=inp.dtype), h)
    obs(data.measurements)
    x0 = system.group.identity((2,), dtype=torch.float64)
    pred = system.predict(x0, data.measurements[:, 0], None)
    # p dropped: the core reads vec R, the biases, y less p^m, then the innovations
    assert torch.allclose(seen[0][:, :9], pred[:, :9])
    assert torch.allclose(seen[0][:, 9:15], pred[:, 12:])
    innov_R = system.group.factor("R").rminus(
        data.measurements[:, 0, :9].unflatten(-1, (3, 3)), pred[:, :9].unflatten(-1, (3, 3))
    )
    assert torch.allclose(seen[0][:, -6:-3], innov_R)


@pytest.mark.parametrize("pose_group", ["so3_r3", "se3"])
def test_rollout_online_steps_and_the_exported_step_agree(pose_group):
    system = RigidBody(pose_group=pose_group)
    data = simulate(system, n=3, t=12, sigma=0.3)
    obs = prior_observer(system, measurement=Measurement(18), features=[Embedding(), Readings()])
    est = assert_online_matches_rollout(obs, data.measurements)
    system.group.check_member(est)


def test_the_gradient_through_the_prior_is_finite_and_reaches_the_bias_outputs():
    """A loss on the attitude alone reaches the head's ``b_Omega`` outputs (through the prior's
    ``Omega^m - bhat_Omega`` and the core's input); every gradient finite."""
    system = RigidBody()
    data = simulate(system, n=4, t=10, sigma=0.1)
    obs = prior_observer(system)
    est = obs(data.measurements)
    (est[:, 2:, :9] - data.states[:, 2:, :9]).pow(2).mean().backward()
    grads = [p.grad for p in obs.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert float(obs.core.head.bias.grad[6:9].abs().sum()) > 0  # b_omega's outputs


def test_the_signature_records_the_prior_and_a_checkpoint_needs_it():
    with_prior = prior_observer().signature()
    without = prior_observer(prior="none").signature()
    assert with_prior["prior"] == {"type": "system"} and without["prior"] == {"type": "none"}
    check_signature(with_prior, prior_observer(seed=3).signature())
    with pytest.raises(CheckpointError, match="prior.type: checkpoint 'system', model 'none'"):
        check_signature(with_prior, without)


def test_bad_prior_settings_say_what_is_wrong():
    system = RigidBody()
    with pytest.raises(ValueError, match=r"model.prior.type: 'kalman' is not a prior piece; the "
                                         r"priors are \['complementary', 'kinematic', 'none', 'robust_system', "
                                         r"'system'"):
        build_observer(system.group, 18, 0, _model(prior={"type": "kalman"}), system=system)
    with pytest.raises(ValueError, match=r"model.prior \(system\): needs \['system'\] \(pass "
                                         r"build_observer\(\.\.\., system=system\)\)"):
        build_observer(system.group, 18, 0, _model(prior={"type": "system"}))
    with pytest.raises(ValueError, match=r"model.prior \(system\): .*a prior cannot be combined "
                                         "with factors taken off the group"):
        build_observer(system.group, 18, 0, _model(prior={"type": "system"}, relax=["R"]),
                       system=system)
    with pytest.raises(ValueError, match=r"model.prior \(system\): unknown key\(s\) \['dt'\]"):
        build_piece("prior", {"type": "system", "dt": 0.1}, "model.prior", {"system": system})
    with pytest.raises(TypeError, match="SystemPrior needs a System, got str"):
        SystemPrior("system")
    with pytest.raises(ValueError, match="the system prior predicts on .* but the observer's "
                                         "group is"):
        ResidualObserver(RigidBody(pose_group="se3").group, 18, prior=SystemPrior(system))


@pytest.mark.parametrize("prior", ["system", "predict"])
def test_a_prior_that_is_not_a_piece_says_so(prior):
    """``prior=`` takes a Prior piece; the first API's callable (``system.predict``) or name
    must be refused with the type the observer wants, not fail inside the observer."""
    system = RigidBody()
    given = system.predict if prior == "predict" else prior
    with pytest.raises(TypeError, match="prior must be a Prior"):
        ResidualObserver(system.group, 18, prior=given)


def test_an_unknown_first_format_prior_says_so():
    """The first format's ``prior`` is ``none`` or ``system``: another name must be refused,
    as it was ("model.prior='kalman' is not one of ('none', 'system')"), not read as none."""
    system = RigidBody()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        with pytest.raises(ValueError, match="kalman"):
            build_observer(system.group, 18, 0, _model(prior="kalman"), system=system)


def test_the_train_command_trains_with_the_prior_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load("paper_cpu_prior", tmp_path, *block_overrides())
    assert observer.signature()["prior"] == {"type": "system"}
    assert isinstance(observer.prior, SystemPrior) and observer.prior.system is system
    data = simulate(system, n=2, t=5, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
