"""A framed innovation (``model.innovation_frame={p: R}``, ``ObserverInputs.innovation_frame``):
the core also reads a 3-vector factor's innovation in a rotation factor's estimated frame,
``Rhat^T (p^m - phat)``, as its last columns. Pinned: the columns' values against the estimate
and the measurement, computed apart; zero at the centred update's ``z^0``; the rollout, pieces,
the online and the exported steps agree; a checkpoint without it widens for fine-tuning into an
observer that computes exactly what it did (and only for fine-tuning), also with clock inputs;
bad settings say what is wrong; the train command trains and reloads it."""

from __future__ import annotations

import pytest
import torch

from manifold_nets import ObserverInputs
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_pieces_and_export_match, train_tiny_and_load
from tests.test_centred_update import rigid_observer, save, simulate

FRAME = {"p": "R"}


def _core_inputs(obs, measurements):
    """What the core reads at every step of a rollout, ``(T, batch, input_size)`` (the batch
    doubled by a centred update: ``z`` then ``z^0``)."""
    seen, step = [], obs.core.step

    def spy(inp, hidden):
        seen.append(inp.clone())
        return step(inp, hidden)

    obs.core.step = spy
    with torch.no_grad():
        est = obs(measurements)
    del obs.core.step
    return torch.stack(seen), est


@pytest.mark.parametrize("centred", [False, True])
def test_the_core_reads_rhat_transpose_times_the_innovation_last(centred):
    system = RigidBody()
    data = simulate(system, n=3, t=8, sigma=0.3)
    changes = {"centering": 0.8 if centred else 0.0}
    obs = rigid_observer(system, seed=2, innovation_frame=FRAME, **changes)
    plain = rigid_observer(system, seed=2, **changes)
    assert obs.core.input_size == plain.core.input_size + 3
    seen, est = _core_inputs(obs, data.measurements)
    n = 3
    for k in range(8):
        # the model prior moves the estimate before the core reads it
        x = system.predict(est[:, k], data.measurements[:, k], None).reshape(n, -1)
        R, p = x[:, :9].reshape(n, 3, 3), x[:, 9:12]
        nu = data.measurements[:, k, 9:12] - p
        want = (R.transpose(-1, -2) @ nu.unsqueeze(-1)).squeeze(-1)
        torch.testing.assert_close(seen[k, :n, -3:], want, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(seen[k, :n, -6:-3], nu, rtol=1e-5, atol=1e-6)  # world frame
        if centred:  # z^0: the measurement exactly predicted, the innovation zero in any frame
            assert bool((seen[k, n:, -3:] == 0).all())


def test_rollout_pieces_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=9, sigma=0.3)
    obs = rigid_observer(system, centering=0.85, centering_ramp=3, innovation_frame=FRAME)
    est = assert_pieces_and_export_match(obs, data.measurements, tmp_path)
    system.group.check_member(est)


def test_a_checkpoint_without_it_widens_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.2)
    plain = rigid_observer(system, seed=1, centering=0.85, centering_ramp=5)
    path = save(plain, tmp_path / "plain.pt")
    framed = rigid_observer(system, seed=2, centering=0.85, centering_ramp=5,
                            innovation_frame=FRAME)
    with pytest.raises(CheckpointError, match="innovation_frame"):  # evaluation
        load_weights(framed, path)
    load_weights(framed, path, widen_gain=True)  # train.init_from
    assert float(framed.core.gru.weight_ih_l0[:, -3:].detach().abs().sum()) == 0
    with torch.no_grad():
        gap = (framed(data.measurements) - plain(data.measurements)).abs().max()
    assert float(gap) < 1e-12  # the same sums but for the zero columns' rounding order
    back = rigid_observer(system, seed=3, centering=0.85)
    with pytest.raises(CheckpointError, match="innovation_frame"):  # not dropped silently
        load_weights(back, save(framed, tmp_path / "framed.pt"), widen_gain=True)


def test_it_widens_with_and_after_clock_inputs(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=10, sigma=0.2)
    plain = rigid_observer(system, seed=1, centering=0.85)
    timed = rigid_observer(system, seed=4, centering=0.85, clock=[3.0])
    with torch.no_grad():
        timed.core.gru.weight_ih_l0[:, -1] = 0.5  # clock weights that matter
    both = rigid_observer(system, seed=2, centering=0.85, clock=[3.0], innovation_frame=FRAME)
    for source in (plain, timed):  # both missing, or the framed innovation only
        load_weights(both, save(source, tmp_path / "source.pt"), widen_gain=True)
        with torch.no_grad():
            gap = (both(data.measurements) - source(data.measurements)).abs().max()
        assert float(gap) < 1e-12
    framed = rigid_observer(system, seed=3, centering=0.85, innovation_frame=FRAME)
    with pytest.raises(CheckpointError, match="clock"):  # the clock would go in the middle
        load_weights(both, save(framed, tmp_path / "framed.pt"), widen_gain=True)


def test_bad_frames_say_what_is_wrong():
    group = RigidBody().group
    inputs = ObserverInputs(innovation={"R": (0, 9), "p": (9, 12)}, innovation_frame=FRAME)
    assert inputs.signature()["innovation_frame"] == FRAME
    assert "innovation_frame" not in ObserverInputs().signature()  # older checkpoints
    assert inputs.core_input_size(group, 18) == ObserverInputs(
        innovation={"R": (0, 9), "p": (9, 12)}
    ).core_input_size(group, 18) + 3
    for frame, match in (
        ({"q": "R"}, "names a factor 'q' that"),
        ({"p": "q"}, "names a factor 'q' that"),
        ({"b_v": "R"}, r"innovation_frame\['b_v'\]: 'b_v' must be a 3-vector factor with an "
                       "innovation span"),
        ({"p": "b_v"}, r"innovation_frame\['p'\] = 'b_v' must be a rotation"),
    ):
        bad = ObserverInputs(innovation={"R": (0, 9), "p": (9, 12)}, innovation_frame=frame)
        with pytest.raises(ValueError, match=match):
            bad.core_input_size(group, 18)
    with pytest.raises(ValueError, match="innovation_frame must map factor names"):
        ObserverInputs(innovation_frame={"p": 3})


def test_the_train_command_takes_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path, "model.centering=0.85", "++model.innovation_frame={p:R}",
    )
    assert observer.inputs.innovation_frame == FRAME
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
