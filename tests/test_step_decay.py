"""Step-size decay (``StepDecay({name: K_f})``, ``scales: [{type: step_decay, factors: ..}]``):
those factors' tangent components of the step from ``x_k`` are scaled by ``d_k = min(1, K_f / k)``,
the others left alone. Pinned: ``d_k`` itself; each step's tangent vector is the undecayed
observer's times ``d_k``; the clock runs on through rollouts in pieces, the online and the
exported steps (past a centring ramp's end); weights load across decays only for fine-tuning;
bad settings say what is wrong; the train command takes it."""

from __future__ import annotations

import pytest
import torch

from manifold_nets import export_observer
from manifold_nets.builders import build_piece
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets.deploy import load_exported_step
from manifold_nets.observer import CentredHead, PlainHead, StepDecay
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load
from tests.test_centred_update import block_overrides, rigid_observer, save, simulate

DECAY = {"b_omega": 3, "b_v": 5}


def test_the_scale_is_one_then_k_over_k_on_the_named_factors_only():
    obs = rigid_observer(scales=[StepDecay(DECAY)])
    k = torch.arange(0, 12, dtype=torch.float64)
    d = obs.scales[0].schedule(k)
    assert d.shape == (12, 12) and d.dtype == torch.float64
    want_bo = [1, 1, 1, 1, 3 / 4, 3 / 5, 3 / 6, 3 / 7, 3 / 8, 3 / 9, 3 / 10, 3 / 11]
    want_bv = [1, 1, 1, 1, 1, 1, 5 / 6, 5 / 7, 5 / 8, 5 / 9, 5 / 10, 5 / 11]
    torch.testing.assert_close(d[:, 6:9], torch.tensor(want_bo)[:, None].expand(12, 3).double())
    torch.testing.assert_close(d[:, 9:12], torch.tensor(want_bv)[:, None].expand(12, 3).double())
    assert bool((d[:, :6] == 1).all())  # R and p
    torch.testing.assert_close(obs.schedule_at(k)[1], d, rtol=0, atol=0)
    plain = rigid_observer(head=PlainHead())
    assert plain.schedule_at(k) == [None] and not plain.uses_step_count
    assert obs.uses_step_count


class UpdateSpy:
    """The observer's group update, keeping each ``v`` it is given (the rest passed through)."""

    def __init__(self, update):
        self.update, self.seen = update, []

    def __call__(self, x, v):
        self.seen.append(v.clone())
        return self.update(x, v)

    def __getattr__(self, name):
        return getattr(self.update, name)


def _steps(obs, measurements):
    """The tangent vector ``v_k`` of every step of a rollout, ``(T, N, tangent_dim)``."""
    update = obs.update
    obs.update = spy = UpdateSpy(update)
    try:
        with torch.no_grad():
            obs(measurements)
    finally:
        obs.update = update
    return torch.stack(spy.seen)


@pytest.mark.parametrize("centred", [True, False])
def test_each_step_is_the_undecayed_step_times_d_k(centred):
    """From the same estimates and hidden states (teacher forcing the decayed observer's path),
    the decayed step's tangent vector is the plain one's times ``d_k``, component by component."""
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.2)
    head = (lambda: CentredHead(0.8, ramp=4)) if centred else PlainHead
    decayed = rigid_observer(system, seed=3, head=head(), scales=[StepDecay(DECAY)])
    plain = rigid_observer(system, seed=3, head=head())
    plain.load_state_dict(decayed.state_dict())
    v_decayed = _steps(decayed, data.measurements)
    update = plain.update
    with torch.no_grad():
        state = decayed.init_state(3)
        for k in range(12):
            plain.update = spy = UpdateSpy(update)
            plain.step(state, data.measurements[:, k])
            plain.update, v_plain = update, spy.seen
            d = decayed.scales[0].schedule(torch.tensor([float(k)], dtype=torch.float64))[0]
            torch.testing.assert_close(v_decayed[k], v_plain[0] * d, rtol=1e-12, atol=1e-14)
            state = decayed.step(state, data.measurements[:, k])
    assert not torch.allclose(v_decayed[-1][:, 6:], v_plain[0][:, 6:])  # the decay mattered


def test_rollout_in_pieces_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=14, sigma=0.3)
    obs = rigid_observer(system, head=CentredHead(0.85, ramp=4), scales=[StepDecay(DECAY)])
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
    plain = rigid_observer(system, seed=1, head=CentredHead(0.85))
    path = save(plain, tmp_path / "plain.pt")
    decayed = rigid_observer(system, seed=2, head=CentredHead(0.85), scales=[StepDecay(DECAY)])
    assert decayed.signature()["scales"] == [{"type": "step_decay", "factors": DECAY}]
    assert plain.signature()["scales"] == []
    with pytest.raises(CheckpointError, match="scales"):  # evaluation
        load_weights(decayed, path)
    load_weights(decayed, path, widen=True)  # train.init_from
    assert decayed.scales[0].factors == DECAY
    for a, b in zip(decayed.state_dict().values(), plain.state_dict().values()):
        assert torch.equal(a, b)
    other = rigid_observer(system, seed=4, head=CentredHead(0.85),
                           scales=[StepDecay({"b_v": 70})])  # across values
    load_weights(other, save(decayed, tmp_path / "decayed.pt"), widen=True)
    assert other.scales[0].factors == {"b_v": 70}


def test_bad_decays_say_what_is_wrong():
    with pytest.raises(ValueError, match="step decay: factors names a factor 'q' that"):
        rigid_observer(scales=[StepDecay({"q": 10})])
    for bad in (0, -3):  # through a config block
        with pytest.raises(ValueError, match=r"model.scales\[0\] \(step_decay\): step decay: "
                                             r"factors\['b_v'\] must be an integer >= 1"):
            build_piece("scale", {"type": "step_decay", "factors": {"b_v": bad}},
                        "model.scales[0]")
    for bad in (2.5, True, "10", None, 0):
        with pytest.raises(ValueError, match=r"step decay: factors\['b_v'\] must be an integer "
                                             ">= 1"):
            StepDecay({"b_v": bad})
    with pytest.raises(ValueError, match="step decay: name at least one factor"):
        StepDecay({})


def test_the_train_command_takes_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path,
        *block_overrides(head="{type:centred,c:0.85}",
                         scales="[{type:step_decay,factors:{b_omega:50}}]"),
    )
    assert observer.scales[0].factors == {"b_omega": 50}
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
