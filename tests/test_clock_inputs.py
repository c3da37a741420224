"""Clock inputs (``model.clock=[tau, ..]``, ``ObserverInputs.clock``): the core also reads
``tau / (tau + k)``, ``k`` the steps taken. Pinned: the features' values; the core reads them as
its last columns, in the rollout, the online step, a rollout cut in pieces and the exported
step (whose count does not stop at a ramp's end); a checkpoint without them widens for
fine-tuning into an observer that computes exactly what it did (and only for fine-tuning);
truncated BPTT carries the count; bad settings say what is wrong; the train command trains and
reloads it."""

from __future__ import annotations

import pytest
import torch

from manifold_nets import ObserverInputs, export_observer
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets.deploy import load_exported_step
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load
from tests.test_centred_update import rigid_observer, save, simulate

TAUS = [2.0, 30.0]


def test_features_are_tau_over_tau_plus_k():
    inputs = ObserverInputs(clock=(1, 10))
    k = torch.tensor([0.0, 1.0, 10.0, 90.0], dtype=torch.float64)
    want = torch.tensor([[1, 1], [1 / 2, 10 / 11], [1 / 11, 1 / 2], [1 / 91, 1 / 10]])
    assert torch.allclose(inputs.clock_features(k), want.double(), atol=1e-15)
    assert inputs.signature()["clock"] == [1.0, 10.0]
    assert "clock" not in ObserverInputs().signature()  # older checkpoints
    group = RigidBody().group
    assert inputs.core_input_size(group, 18) == ObserverInputs().core_input_size(group, 18) + 2


def test_the_core_reads_the_clock_in_its_last_columns():
    """Only the clock columns' weights differ between two observers: zero there, the clock
    observer is the plain one; non-zero, each step moves as the features say."""
    system = RigidBody()
    data = simulate(system, n=3, t=10, sigma=0.2)
    plain = rigid_observer(system, seed=4, centering=0.8, centering_ramp=3)
    timed = rigid_observer(system, seed=4, centering=0.8, centering_ramp=3, clock=TAUS)
    w = timed.core.gru.weight_ih_l0
    assert w.shape[1] == plain.core.gru.weight_ih_l0.shape[1] + 2
    with torch.no_grad():
        w[:, :-2] = plain.core.gru.weight_ih_l0
        w[:, -2:] = 0
        for name, p in plain.named_parameters():
            if name != "core.gru.weight_ih_l0":
                timed.get_parameter(name).copy_(p)
        assert torch.equal(timed(data.measurements), plain(data.measurements))
        w[:, -2:] = torch.randn(w.shape[0], 2, dtype=w.dtype)
        assert not torch.allclose(timed(data.measurements), plain(data.measurements), atol=1e-6)


def test_rollout_pieces_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=9, sigma=0.3)
    obs = rigid_observer(system, centering=0.9, centering_ramp=4, clock=TAUS)
    with torch.no_grad():  # clock weights that matter
        obs.core.gru.weight_ih_l0[:, -2:] = torch.randn(obs.core.gru.weight_ih_l0.shape[0], 2)
    est = assert_online_matches_rollout(obs, data.measurements)
    system.group.check_member(est)
    with torch.no_grad():
        head, state = obs(data.measurements[:, :4], return_state=True)
        tail = obs(data.measurements[:, 4:], state=state)
    assert torch.allclose(torch.cat([head, tail[:, 1:]], 1), est, atol=1e-12)
    export_observer(obs, tmp_path / "step.pt2")
    step = load_exported_step(tmp_path / "step.pt2")
    assert step.meta["inputs"][-2:] == ["steps", "y"]
    x, *state = step.initial_state(2)
    for k in range(9):
        x, *state = step(x, *state, data.measurements[:, k])
    assert state[-1].tolist() == [9.0, 9.0]  # the clock does not stop at the ramp's end
    assert torch.allclose(x, est[:, -1].reshape(2, -1), atol=1e-10)


def test_a_checkpoint_without_the_clock_widens_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.2)
    plain = rigid_observer(system, seed=1, centering=0.85, centering_ramp=5)
    path = save(plain, tmp_path / "plain.pt")
    timed = rigid_observer(system, seed=2, centering=0.85, centering_ramp=5, clock=TAUS)
    with pytest.raises(CheckpointError, match="clock"):  # evaluation: the same observer
        load_weights(timed, path)
    load_weights(timed, path, widen_gain=True)  # train.init_from
    assert float(timed.core.gru.weight_ih_l0[:, -2:].detach().abs().sum()) == 0
    with torch.no_grad():
        assert torch.equal(timed(data.measurements), plain(data.measurements))
    again = rigid_observer(system, seed=3, centering=0.85, clock=TAUS)
    load_weights(again, save(timed, tmp_path / "timed.pt"), widen_gain=True)  # same clock
    back = rigid_observer(system, seed=3, centering=0.85)
    with pytest.raises(CheckpointError, match="clock"):  # a clock is not dropped silently
        load_weights(back, tmp_path / "timed.pt", widen_gain=True)
    other = rigid_observer(system, seed=3, centering=0.85, clock=[5.0, 50.0])
    with pytest.raises(CheckpointError, match="clock"):
        load_weights(other, tmp_path / "timed.pt", widen_gain=True)


def test_a_gain_head_observer_widens_to_the_clock_and_the_gain_at_once(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=8, sigma=0.2)
    plain = rigid_observer(system, seed=1, centering=0.0)
    both = rigid_observer(system, seed=2, centering=0.0, gain=True, clock=TAUS)
    load_weights(both, save(plain, tmp_path / "plain.pt"), widen_gain=True)
    with torch.no_grad():
        assert torch.allclose(both(data.measurements), plain(data.measurements), atol=1e-12)


def test_bad_clocks_say_what_is_wrong():
    for bad in ([0], [-1.0], ["10"], [True], 10, "10"):
        with pytest.raises(ValueError, match="clock"):
            ObserverInputs(clock=bad)
    with pytest.raises(ValueError, match="clock"):
        rigid_observer(clock=[100, -5])


def test_the_train_command_trains_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path, "model.clock=[10,100]", "train.tbptt=4"
    )
    assert observer.inputs.clock == (10.0, 100.0)
    assert float(observer.core.gru.weight_ih_l0[:, -2:].detach().abs().sum()) > 0  # trained
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
