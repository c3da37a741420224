"""Per-factor centring (``model.centering_factors={name: c_f}``): those factors' tangent
components are centred by ``c_f``, the others by ``centering``, ramped alike. Pinned: each
factor's new estimate is the one of the constant-centring observer at its own ``c_f`` (also
inside a ramp, at ``c_f k / K``); ``c_f = c`` everywhere is the plain centred observer bit for
bit; the rollout, the online and the exported steps agree; weights load across per-factor
values only for fine-tuning; bad settings say what is wrong; the train command takes it."""

from __future__ import annotations

import pytest
import torch

from manifold_nets import export_observer
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets.deploy import load_exported_step
from manifold_nets.inputs import ObserverInputs
from manifold_nets.observer import ResidualObserver
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load
from tests.test_centred_update import rigid_observer, save, simulate

FACTORS = {"b_omega": 0.95, "b_v": 0.3}


@pytest.mark.parametrize("ramp, k", [(0, 3), (4, 2)])
def test_each_factor_moves_as_the_constant_centring_at_its_own_c(ramp, k):
    system = RigidBody()
    group = system.group
    data = simulate(system, n=3, t=6, sigma=0.2)
    mixed = rigid_observer(system, seed=3, centering=0.6, centering_ramp=ramp,
                           centering_factors=FACTORS)
    with torch.no_grad():
        _, state = mixed(data.measurements[:, :k], return_state=True)
        after = mixed.step(state, data.measurements[:, k]).estimate.flatten(1)
        r = min(1.0, k / ramp) if ramp else 1.0
        for name in group.factor_names:
            c = FACTORS.get(name, 0.6) * r
            const = rigid_observer(system, seed=3, centering=c)
            const.load_state_dict(mixed.state_dict())
            want = const.step(state._replace(steps=0), data.measurements[:, k]).estimate
            cols = group.element_slice(name)
            diff = (after[:, cols] - want.flatten(1)[:, cols]).abs().max()
            assert diff < 1e-12, (name, float(diff))
        other = rigid_observer(system, seed=3, centering=0.6, centering_ramp=ramp)
        other.load_state_dict(mixed.state_dict())
        assert not torch.allclose(other.step(state, data.measurements[:, k]).estimate.flatten(1),
                                  after, atol=1e-8)  # the factors' own c matter


def test_the_same_c_for_every_factor_is_the_plain_centred_observer():
    system = RigidBody()
    data = simulate(system, n=2, t=10, sigma=0.3)
    plain = rigid_observer(system, seed=1, centering=0.8, centering_ramp=3)
    same = rigid_observer(system, seed=1, centering=0.8, centering_ramp=3,
                          centering_factors={"R": 0.8, "b_v": 0.8})
    with torch.no_grad():
        assert torch.equal(same(data.measurements), plain(data.measurements))
    assert same.signature()["centering_factors"] == {"R": 0.8, "b_v": 0.8}
    assert "centering_factors" not in plain.signature()  # older checkpoints


def test_rollout_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=9, sigma=0.3)
    obs = rigid_observer(system, centering=0.85, centering_ramp=4, centering_factors=FACTORS)
    est = assert_online_matches_rollout(obs, data.measurements)
    export_observer(obs, tmp_path / "step.pt2")
    step = load_exported_step(tmp_path / "step.pt2")
    x, *state = step.initial_state(2)
    for k in range(9):
        x, *state = step(x, *state, data.measurements[:, k])
    assert torch.allclose(x, est[:, -1].reshape(2, -1), atol=1e-10)


def test_weights_load_across_factor_values_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    plain = rigid_observer(system, seed=1, centering=0.85, centering_ramp=5)
    path = save(plain, tmp_path / "plain.pt")
    mixed = rigid_observer(system, seed=2, centering=0.85, centering_ramp=5,
                           centering_factors=FACTORS)
    with pytest.raises(CheckpointError, match="centering_factors"):  # evaluation
        load_weights(mixed, path)
    load_weights(mixed, path, widen_gain=True)  # train.init_from
    assert mixed.centering_factors == FACTORS
    for a, b in zip(mixed.state_dict().values(), plain.state_dict().values()):
        assert torch.equal(a, b)


def test_bad_factor_values_say_what_is_wrong():
    system = RigidBody()
    with pytest.raises(ValueError, match="'q' that"):
        rigid_observer(system, centering_factors={"q": 0.5})
    for bad in (1.5, -0.1):  # through the config
        with pytest.raises(ValueError, match=r"centering_factors\['R'\] must be a number"):
            rigid_observer(system, centering_factors={"R": bad})
    inputs = ObserverInputs(innovation={"R": (0, 9)})
    for bad in (True, "0.9", None):
        with pytest.raises(ValueError, match=r"centering_factors\['R'\] must be a number"):
            ResidualObserver(system.group, 18, hidden_size=4, num_layers=1, inputs=inputs,
                             prior=system.predict, centering=0.5, centering_factors={"R": bad})
    with pytest.raises(ValueError, match="but centering is 0"):
        ResidualObserver(system.group, 18, hidden_size=4, num_layers=1,
                         centering_factors={"R": 0.5})


def test_the_train_command_takes_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path, "model.centering=0.85",
        "++model.centering_factors={b_omega:0.95,b_v:0.95}",
    )
    assert observer.centering_factors == {"b_omega": 0.95, "b_v": 0.95}
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
