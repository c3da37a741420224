"""The centring ramp (``CentredHead(c, ramp=K)``): the centred update's ``c`` rises linearly over
the first ``K`` steps, ``c_k = c min(1, k / K)``, counted by ``ObserverState.steps``. Pinned: each
step of a ramped observer is the step of the constant-centring observer at its ``c_k``; a ramp of
0 is the constant centring; a rollout cut in pieces carries the clock (so does truncated BPTT);
the rollout, the online step and the exported step (which carries the count as a state tensor)
agree; weights load across ramps only for fine-tuning; bad settings say what is wrong; the train
command trains and reloads it."""

from __future__ import annotations

import pytest
import torch

from manifold_nets import TrainSettings, export_observer
from manifold_nets.builders import build_piece
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets.deploy import load_exported_step
from manifold_nets.observer import CentredHead, PlainHead
from manifold_nets.training import fit
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load
from tests.test_centred_update import block_overrides, centred, rigid_observer, save, simulate


def test_c_rises_linearly_over_the_ramp_and_then_stays():
    obs = rigid_observer(head=CentredHead(0.8, ramp=4))
    k = torch.arange(7, dtype=torch.float64)
    c = obs.head.schedule(k)
    assert c.shape == (7, 1) and c.dtype == torch.float64
    assert c[:, 0].tolist() == pytest.approx([0.0, 0.2, 0.4, 0.6, 0.8, 0.8, 0.8])
    assert obs.schedule_at(k)[0][:, 0].tolist() == pytest.approx(c[:, 0].tolist())
    assert [t[0].item() for t in obs.schedule(2, 3)] == pytest.approx([0.4, 0.6, 0.8])
    assert obs.signature()["head"]["ramp"] == 4
    assert "ramp" not in rigid_observer(head=CentredHead(0.8)).signature()["head"]
    # without a ramp c from the first step
    assert CentredHead(0.8).schedule(k)[:, 0].tolist() == pytest.approx([0.8] * 7)


def test_each_step_is_the_constant_centring_step_at_its_c():
    """From the ramped rollout's own state after ``k`` steps (estimate and hidden state), one
    step of the observer with the same weights and constant ``c = c_k`` lands on the ramped
    rollout's next estimate."""
    system = RigidBody()
    data = simulate(system, n=3, t=8, sigma=0.2)
    ramped = rigid_observer(system, seed=3, head=CentredHead(0.9, ramp=5))
    with torch.no_grad():
        est = ramped(data.measurements)
    moved = False
    for k in range(8):
        c = 0.9 * min(1.0, k / 5)
        const = rigid_observer(system, seed=3, head=centred(c))
        const.load_state_dict(ramped.state_dict())
        with torch.no_grad():
            _, state = ramped(data.measurements[:, :k], return_state=True) if k else (
                None, ramped.init_state(3)
            )
            assert state.steps == k
            after = const.step(state._replace(steps=0), data.measurements[:, k]).estimate
        assert torch.allclose(after, est[:, k + 1], atol=1e-12), k
        if k >= 1:  # the same state stepped at the full c lands elsewhere while c_k < c
            full = rigid_observer(system, seed=3, head=CentredHead(0.9))
            full.load_state_dict(ramped.state_dict())
            with torch.no_grad():
                other = full.step(state, data.measurements[:, k]).estimate
            moved |= k < 5 and not torch.allclose(other, est[:, k + 1], atol=1e-8)
    assert moved


def test_a_ramp_of_zero_is_the_constant_centring_and_the_rollout_carries_the_clock():
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.3)
    const = rigid_observer(system, seed=2, head=CentredHead(0.7))
    zero = rigid_observer(system, seed=2, head=CentredHead(0.7, ramp=0))
    ramped = rigid_observer(system, seed=2, head=CentredHead(0.7, ramp=6))
    with torch.no_grad():
        want = const(data.measurements)
        assert torch.equal(zero(data.measurements), want)
        whole = ramped(data.measurements)
        assert not torch.allclose(whole, want, atol=1e-8)
        head, state = ramped(data.measurements[:, :4], return_state=True)
        assert state.steps == 4
        tail, state = ramped(data.measurements[:, 4:], state=state, return_state=True)
        assert state.steps == 12
    assert torch.allclose(torch.cat([head, tail[:, 1:]], 1), whole, atol=1e-12)


def test_rollout_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=9, sigma=0.3)
    obs = rigid_observer(system, head=CentredHead(0.9, ramp=4))
    est = assert_online_matches_rollout(obs, data.measurements)
    system.group.check_member(est)
    export_observer(obs, tmp_path / "step.pt2")
    step = load_exported_step(tmp_path / "step.pt2")
    assert step.meta["inputs"][-2:] == ["steps", "y"]
    x, *state = step.initial_state(2)
    assert float(state[-1].abs().sum()) == 0
    for k in range(9):
        x, *state = step(x, *state, data.measurements[:, k])
    # the count is the steps taken (it no longer stops at the ramp's end: one schedule for all)
    assert state[-1].tolist() == [9.0, 9.0]
    assert torch.allclose(x, est[:, -1].reshape(2, -1), atol=1e-10)


def test_truncated_bptt_carries_the_clock_from_piece_to_piece(tmp_path):
    system = RigidBody()
    train, val = simulate(system, n=4, t=12, sigma=0.1), simulate(system, n=2, t=12, seed=2)
    obs = rigid_observer(system, head=CentredHead(0.9, ramp=8))
    seen, forward = [], obs.forward

    def spy(*args, state=None, **kw):
        seen.append(None if state is None else state.steps)
        return forward(*args, state=state, **kw)

    obs.forward = spy
    settings = TrainSettings(epochs=1, batch_size=4, lr=1e-3, progress=False, tbptt=5)
    fit(obs, train, val, settings, out_dir=tmp_path)
    assert [0, 5, 10] == [s for s in seen if s is not None][:3]


def test_weights_load_across_ramps_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    const = rigid_observer(system, seed=1, head=CentredHead(0.7))
    path = save(const, tmp_path / "const.pt")
    ramped = rigid_observer(system, seed=2, head=CentredHead(0.85, ramp=50))
    with pytest.raises(CheckpointError, match="head.ramp"):  # evaluation: the same observer
        load_weights(ramped, path)
    load_weights(ramped, path, widen=True)  # train.init_from
    assert (ramped.head.c, ramped.head.ramp) == (0.85, 50)
    for a, b in zip(ramped.state_dict().values(), const.state_dict().values()):
        assert torch.equal(a, b)
    back = rigid_observer(system, seed=3, head=PlainHead())
    load_weights(back, save(ramped, tmp_path / "ramped.pt"), widen=True)
    assert back.signature()["head"] == {"type": "plain"}


def test_bad_ramps_say_what_is_wrong():
    for bad in (-1, -2, 2.5, True, "3"):
        with pytest.raises(ValueError, match="centred head: ramp must be an integer >= 0"):
            CentredHead(0.9, ramp=bad)
    with pytest.raises(ValueError, match=r"model.head \(centred\): centred head: ramp must be an "
                                         "integer >= 0"):
        build_piece("head", {"type": "centred", "c": 0.9, "ramp": -1}, "model.head")
    # a ramp without a centring
    with pytest.raises(ValueError, match="c = 0 centres nothing"):
        CentredHead(0.0, ramp=10)
    with pytest.raises(ValueError, match=r"model.head \(plain\): unknown key\(s\) \['ramp'\]"):
        build_piece("head", {"type": "plain", "ramp": 10}, "model.head")


def test_a_block_with_an_unknown_key_lists_what_the_piece_takes():
    """A piece without arguments says so (it has no ``__init__`` of its own: the message must not
    list ``nn.Module.__init__``'s ``*args, **kwargs``)."""
    with pytest.raises(ValueError, match=r"a plain head takes no arguments"):
        build_piece("head", {"type": "plain", "ramp": 10}, "model.head")
    with pytest.raises(ValueError, match=r"a centred head takes \['c', 'ramp', 'factors', 'inner'"):
        build_piece("head", {"type": "centred", "c": 0.5, "gain": True}, "model.head")


def test_a_flat_ramp_without_a_centring_says_so():
    """The first format's ``centering_ramp`` means nothing without ``centering``: the translated
    config must refuse it, as the first format did ("but model.centering is 0"), not drop it."""
    from omegaconf import OmegaConf

    from manifold_nets.builders import build_observer
    from manifold_nets.config import ModelConfig

    system = RigidBody()
    model = OmegaConf.structured(ModelConfig(
        hidden_size=4, num_layers=1, innovation={"R": [0, 9], "p": [9, 12]}, prior="system",
        centering_ramp=10,
    ))
    with pytest.raises(ValueError, match="centering"):
        build_observer(system.group, 18, 0, model, system=system)


def test_the_train_command_trains_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path, *block_overrides(head="{type:centred,c:0.9,ramp:5}")
    )
    assert (observer.head.c, observer.head.ramp) == (0.9, 5)
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
