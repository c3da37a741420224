"""The model prior (``model.prior=system``): ``System.predict`` moves the estimate before the
learned update. Pinned: each shipped system's ``predict`` is its own dynamics with the
bias-corrected readings; the observer's rollout, online step and exported step apply it; the
gradient flows through it; the signature records it; bad settings say what is wrong."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from manifold_nets.builders import build_observer
from manifold_nets.checkpoint import CheckpointError, check_signature
from manifold_nets.config import ModelConfig
from manifold_nets.inputs import ObserverInputs
from manifold_nets.observer import ObserverState, ResidualObserver
from manifold_nets_examples.attitude import Attitude
from manifold_nets_examples.planar import Planar
from manifold_nets_examples.rigid_body import MismatchedRigidBody, RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load

SYSTEMS = {
    "rigid_body": lambda: RigidBody(),
    "rigid_body_se3": lambda: RigidBody(pose_group="se3"),
    "rigid_body_mismatch_off": lambda: MismatchedRigidBody(),
    "attitude": lambda: Attitude(),
    "planar": lambda: Planar(),
    "planar_so2_r2": lambda: Planar(pose_group="so2_r2"),
}


def simulate(system, n=4, t=30, sigma=0.0, seed=1):
    return system.simulate(n, t, sigma, torch.Generator().manual_seed(seed))


def rigid_model(**changes) -> ModelConfig:
    base = dict(
        hidden_size=16, num_layers=1, innovation={"R": [0, 9], "p": [9, 12]},
        relative_only=["p"], prior="system", updates={},
    )
    return OmegaConf.structured(ModelConfig(**{**base, **changes}))


def rigid_observer(system=None, zero=False, seed=0, **changes) -> ResidualObserver:
    system = RigidBody() if system is None else system
    torch.manual_seed(seed)
    obs = build_observer(system.group, 18, 0, rigid_model(**changes), system=system).double()
    if zero:  # the core outputs 0: only the prior moves the estimate
        torch.nn.init.zeros_(obs.core.head.weight)
        torch.nn.init.zeros_(obs.core.head.bias)
    return obs


@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_predict_from_the_true_state_and_noise_free_readings_is_the_next_state(name):
    """The biases the readings carry are the state's, so subtracting the true ones recovers the
    true drive, and the prediction is the system's own step: exact to rounding."""
    system = SYSTEMS[name]()
    data = simulate(system)
    u = data.inputs if system.input_dim else None
    for k in (0, 7, 29):
        pred = system.predict(data.states[:, k], data.measurements[:, k], u if u is None else u[:, k])
        assert torch.allclose(pred, data.states[:, k + 1], atol=1e-12), name


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
    obs = rigid_observer(system, zero=True)
    start = ObserverState(data.states[:, 0].clone(), obs.init_state(4).hidden)
    with torch.no_grad():
        est = obs(data.measurements, state=start)
    assert torch.allclose(est, data.states, atol=1e-12)


def test_the_core_reads_the_prediction():
    system = RigidBody()
    data = simulate(system, n=2, t=1, sigma=0.1)
    obs = rigid_observer(system, zero=True)
    seen = []
    obs.core.step = lambda inp, h: (seen.append(inp) or torch.zeros(2, 12, dtype=inp.dtype), h)
    obs(data.measurements)
    x0 = system.group.identity((2,), dtype=torch.float64)
    pred = system.predict(x0, data.measurements[:, 0], None)
    # relative_only p: the core reads vec R, the biases, y less p^m, then the innovations
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
    obs = rigid_observer(system, innovation={}, relative_only=[])
    est = assert_online_matches_rollout(obs, data.measurements)
    system.group.check_member(est)


def test_the_gradient_through_the_prior_is_finite_and_reaches_the_bias_outputs():
    """A loss on the attitude alone reaches the head's ``b_Omega`` outputs (through the prior's
    ``Omega^m - bhat`` and the core's input); every gradient finite."""
    system = RigidBody()
    data = simulate(system, n=4, t=10, sigma=0.1)
    obs = rigid_observer(system)
    est = obs(data.measurements)
    (est[:, 2:, :9] - data.states[:, 2:, :9]).pow(2).mean().backward()
    grads = [p.grad for p in obs.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert float(obs.core.head.bias.grad[6:9].abs().sum()) > 0  # b_omega's outputs


def test_the_signature_records_the_prior_and_a_checkpoint_needs_it():
    with_prior = rigid_observer().signature()
    without = rigid_observer(prior="none").signature()
    assert with_prior["prior"] == "system" and "prior" not in without
    check_signature(with_prior, rigid_observer(seed=3).signature())
    with pytest.raises(CheckpointError, match="prior"):
        check_signature(with_prior, without)


def test_bad_prior_settings_say_what_is_wrong():
    system = RigidBody()
    with pytest.raises(ValueError, match=r"model.prior='kalman' is not one of \('none', 'system'\)"):
        build_observer(system.group, 18, 0, rigid_model(prior="kalman"), system=system)
    with pytest.raises(ValueError, match="model.prior=system needs the system"):
        build_observer(system.group, 18, 0, rigid_model())
    with pytest.raises(ValueError, match="cannot be combined with model.relax"):
        build_observer(
            system.group, 18, 0, rigid_model(relax=["R"], innovation={}, relative_only=[]),
            system=system,
        )
    with pytest.raises(TypeError, match="prior must be a callable"):
        ResidualObserver(system.group, 18, hidden_size=4, num_layers=1, prior="system")
    with pytest.raises(ValueError, match="prior and inputs.propagate are two kinematic priors"):
        ResidualObserver(
            system.group, 18, hidden_size=4, num_layers=1, prior=system.predict,
            inputs=ObserverInputs(propagate={"R": (12, 15)}, dt=0.1),
        )


def test_the_train_command_trains_with_the_prior_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load("paper_cpu_prior", tmp_path)
    assert observer.signature()["prior"] == "system"
    assert observer.prior == system.predict
    data = simulate(system, n=2, t=5, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
