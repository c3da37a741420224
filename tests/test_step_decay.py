"""Step-size decay (``model.step_decay={name: K_f}``): those factors' tangent components of the
step from ``x_k`` are scaled by ``d_k = min(1, K_f / k)``, the others left alone. Pinned: ``d_k``
itself; each step's tangent vector is the undecayed observer's times ``d_k``; the clock runs on
through rollouts in pieces, the online and the exported steps (past a centring ramp's end);
weights load across decays only for fine-tuning; bad settings say what is wrong; the train
command takes it."""

from __future__ import annotations

import pytest
import torch

from manifold_nets import export_observer
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets.deploy import load_exported_step
from manifold_nets.observer import ResidualObserver
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load
from tests.test_centred_update import rigid_observer, save, simulate

DECAY = {"b_omega": 3, "b_v": 5}


def test_the_scale_is_one_then_k_over_k_on_the_named_factors_only():
    obs = rigid_observer(step_decay=DECAY)
    k = torch.arange(0, 12, dtype=torch.float64)
    d = obs.decay_at(k)
    assert d.shape == (12, 12) and d.dtype == torch.float64
    want_bo = [1, 1, 1, 1, 3 / 4, 3 / 5, 3 / 6, 3 / 7, 3 / 8, 3 / 9, 3 / 10, 3 / 11]
    want_bv = [1, 1, 1, 1, 1, 1, 5 / 6, 5 / 7, 5 / 8, 5 / 9, 5 / 10, 5 / 11]
    torch.testing.assert_close(d[:, 6:9], torch.tensor(want_bo)[:, None].expand(12, 3).double())
    torch.testing.assert_close(d[:, 9:12], torch.tensor(want_bv)[:, None].expand(12, 3).double())
    assert bool((d[:, :6] == 1).all())  # R and p
    assert rigid_observer().decay_at(k) is None


def _steps(obs, measurements):
    """The tangent vector ``v_k`` of every step of a rollout, ``(T, N, tangent_dim)``."""
    seen, update = [], obs._update

    def spy(x, v):
        seen.append(v.clone())
        return update(x, v)

    obs._update = spy
    with torch.no_grad():
        obs(measurements)
    del obs._update
    return torch.stack(seen)


@pytest.mark.parametrize("centred", [True, False])
def test_each_step_is_the_undecayed_step_times_d_k(centred):
    """From the same estimates and hidden states (teacher forcing the decayed observer's path),
    the decayed step's tangent vector is the plain one's times ``d_k``, component by component."""
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.2)
    changes = {"centering": 0.8, "centering_ramp": 4} if centred else {"centering": 0.0}
    decayed = rigid_observer(system, seed=3, step_decay=DECAY, **changes)
    plain = rigid_observer(system, seed=3, **changes)
    plain.load_state_dict(decayed.state_dict())
    v_decayed = _steps(decayed, data.measurements)
    with torch.no_grad():
        state = decayed.init_state(3)
        for k in range(12):
            v_plain = []
            plain._update = lambda x, v, keep=v_plain, f=plain._update: keep.append(v) or f(x, v)
            plain.step(state, data.measurements[:, k])
            del plain._update
            d = decayed.decay_at(torch.tensor(float(k), dtype=torch.float64)).float()
            torch.testing.assert_close(v_decayed[k], v_plain[0] * d, rtol=1e-6, atol=1e-7)
            state = decayed.step(state, data.measurements[:, k])
    assert not torch.allclose(v_decayed[-1][:, 6:], v_plain[0][:, 6:])  # the decay mattered


def test_rollout_in_pieces_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=14, sigma=0.3)
    obs = rigid_observer(system, centering=0.85, centering_ramp=4, step_decay=DECAY)
    est = assert_online_matches_rollout(obs, data.measurements, atol=1e-10)
    with torch.no_grad():
        first, state = obs(data.measurements[:, :6], return_state=True)
        rest = obs(data.measurements[:, 6:], state=state)
    assert state.steps == 6
    torch.testing.assert_close(rest[:, -1], est[:, -1], rtol=0, atol=1e-10)
    export_observer(obs, tmp_path / "step.pt2")
    step = load_exported_step(tmp_path / "step.pt2")
    x, *state = step.initial_state(2)
    for k in range(14):
        x, *state = step(x, *state, data.measurements[:, k])
    assert float(state[-1][0]) == 14  # the count runs past the ramp's end (4)
    torch.testing.assert_close(x, est[:, -1].reshape(2, -1), rtol=0, atol=1e-10)


def test_weights_load_across_decays_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    plain = rigid_observer(system, seed=1, centering=0.85)
    path = save(plain, tmp_path / "plain.pt")
    decayed = rigid_observer(system, seed=2, centering=0.85, step_decay=DECAY)
    assert decayed.signature()["step_decay"] == DECAY
    assert "step_decay" not in plain.signature()  # older checkpoints
    with pytest.raises(CheckpointError, match="step_decay"):  # evaluation
        load_weights(decayed, path)
    load_weights(decayed, path, widen_gain=True)  # train.init_from
    assert decayed.step_decay == DECAY
    for a, b in zip(decayed.state_dict().values(), plain.state_dict().values()):
        assert torch.equal(a, b)


def test_bad_decays_say_what_is_wrong():
    with pytest.raises(ValueError, match="names a factor 'q' that"):
        rigid_observer(step_decay={"q": 10})
    for bad in (0, -3):  # through the config
        with pytest.raises(ValueError, match=r"step_decay\['b_v'\] must be an integer >= 1"):
            rigid_observer(step_decay={"b_v": bad})
    group = RigidBody().group
    for bad in (2.5, True, "10", None):
        with pytest.raises(ValueError, match=r"step_decay\['b_v'\] must be an integer >= 1"):
            ResidualObserver(group, 18, hidden_size=4, num_layers=1, step_decay={"b_v": bad})


def test_the_train_command_takes_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path, "model.centering=0.85", "++model.step_decay={b_omega:50}",
    )
    assert observer.step_decay == {"b_omega": 50}
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
