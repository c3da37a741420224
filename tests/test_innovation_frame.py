"""A framed innovation (``FramedInnovation({p: R})``, ``features: [.., {type: framed_innovation,
frames: {p: R}}]``): the core also reads a 3-vector factor's innovation in a rotation factor's
estimated frame, ``Rhat^T (p^m - phat)``, in the feature's place (here last). Pinned: the columns'
values against the estimate and the measurement, computed apart; zero at the centred update's
``z^0``; the rollout, pieces, the online and the exported steps agree; a checkpoint without it
widens for fine-tuning into an observer that computes exactly what it did (and only for
fine-tuning), also with another added feature before it; bad settings say what is wrong; the
train command trains and reloads it."""

from __future__ import annotations

import pytest
import torch

from manifold_nets.builders import build_piece
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets.observer import (
    CentredHead,
    FramedInnovation,
    Innovation,
    Measurement,
    PlainHead,
    Rotated,
)
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_pieces_and_export_match, train_tiny_and_load
from tests.test_centred_update import (
    MEASURED,
    block_overrides,
    centred,
    rigid_observer,
    save,
    simulate,
)

FRAME = {"p": "R"}
#: The rigid body's body-frame readings (Omega^m, v^m), rotated to the world frame.
READINGS = {"R": [(12, 15), (15, 18)]}


def _core_inputs(obs, measurements):
    """What the core reads at every step of a rollout, ``(T, batch, input_size)`` (the batch
    doubled by a centred update: ``z`` then ``z^0``)."""
    seen, step = [], obs.core.step

    def spy(inp, hidden):
        seen.append(inp.clone())
        return step(inp, hidden)

    obs.core.step = spy
    try:
        with torch.no_grad():
            est = obs(measurements)
    finally:
        del obs.core.step
    return torch.stack(seen), est


@pytest.mark.parametrize("centred_", [False, True])
def test_the_core_reads_rhat_transpose_times_the_innovation_last(centred_):
    system = RigidBody()
    data = simulate(system, n=3, t=8, sigma=0.3)
    head = centred(0.8 if centred_ else 0.0)
    obs = rigid_observer(system, seed=2, head=head, extra=[FramedInnovation(FRAME)])
    plain = rigid_observer(system, seed=2, head=centred(0.8 if centred_ else 0.0))
    assert obs.core.input_size == plain.core.input_size + 3
    assert obs.features[-1].width == 3
    seen, est = _core_inputs(obs, data.measurements)
    n = 3
    for k in range(8):
        # the system prior moves the estimate before the core reads it
        x = system.predict(est[:, k], data.measurements[:, k], None).reshape(n, -1)
        R, p = x[:, :9].reshape(n, 3, 3), x[:, 9:12]
        nu = data.measurements[:, k, 9:12] - p
        want = (R.transpose(-1, -2) @ nu.unsqueeze(-1)).squeeze(-1)
        torch.testing.assert_close(seen[k, :n, -3:], want, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(seen[k, :n, -6:-3], nu, rtol=1e-12, atol=1e-12)  # world frame
        if centred_:  # z^0: the measurement exactly predicted, the innovation zero in any frame
            assert bool((seen[k, n:, -3:] == 0).all())


def test_rollout_pieces_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=9, sigma=0.3)
    obs = rigid_observer(system, head=CentredHead(0.85, ramp=3), extra=[FramedInnovation(FRAME)])
    est = assert_pieces_and_export_match(obs, data.measurements, tmp_path)
    system.group.check_member(est)


def test_a_checkpoint_without_it_widens_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.2)
    plain = rigid_observer(system, seed=1, head=CentredHead(0.85, ramp=5))
    path = save(plain, tmp_path / "plain.pt")
    framed = rigid_observer(system, seed=2, head=CentredHead(0.85, ramp=5),
                            extra=[FramedInnovation(FRAME)])
    with pytest.raises(CheckpointError, match="features"):  # evaluation
        load_weights(framed, path)
    load_weights(framed, path, widen=True)  # train.init_from
    assert float(framed.core.gru.weight_ih_l0[:, -3:].detach().abs().sum()) == 0
    with torch.no_grad():
        gap = (framed(data.measurements) - plain(data.measurements)).abs().max()
    assert float(gap) < 1e-12  # the same sums but for the zero columns' rounding order
    back = rigid_observer(system, seed=3, head=CentredHead(0.85))
    with pytest.raises(CheckpointError, match="only features can be added"):  # not dropped
        load_weights(back, save(framed, tmp_path / "framed.pt"), widen=True)


def test_it_widens_with_and_after_another_added_feature(tmp_path):
    """An observer reading world-frame readings (:class:`Rotated`) and the framed innovation
    starts from one with neither, with the first only, or with the second only (the rotated
    readings' columns then go in the middle of the core's input)."""
    system = RigidBody()
    data = simulate(system, n=2, t=10, sigma=0.2)
    plain = rigid_observer(system, seed=1, head=CentredHead(0.85))
    rotated = rigid_observer(system, seed=4, head=CentredHead(0.85), extra=[Rotated(READINGS)])
    with torch.no_grad():
        rotated.core.gru.weight_ih_l0[:, -6:] = 0.5  # rotated weights that matter
    framed = rigid_observer(system, seed=3, head=CentredHead(0.85),
                            extra=[FramedInnovation(FRAME)])
    with torch.no_grad():
        framed.core.gru.weight_ih_l0[:, -3:] = 0.3  # framed weights that matter
    both = rigid_observer(system, seed=2, head=CentredHead(0.85),
                          extra=[Rotated(READINGS), FramedInnovation(FRAME)])
    for source in (plain, rotated, framed):
        load_weights(both, save(source, tmp_path / "source.pt"), widen=True)
        with torch.no_grad():
            gap = (both(data.measurements) - source(data.measurements)).abs().max()
        assert float(gap) < 1e-12
    reordered = rigid_observer(system, seed=5, head=CentredHead(0.85),
                               extra=[FramedInnovation(FRAME), Rotated(READINGS)])
    with pytest.raises(CheckpointError, match="in order"):  # the checkpoint's order is kept
        load_weights(reordered, save(both, tmp_path / "both.pt"), widen=True)


def test_bad_frames_say_what_is_wrong():
    group = RigidBody().group
    sig = rigid_observer(extra=[FramedInnovation(FRAME)]).signature()
    assert sig["features"][-1] == {"type": "framed_innovation", "frames": FRAME}
    assert "framed_innovation" not in [f["type"] for f in rigid_observer().signature()["features"]]
    measurement = Measurement(18, 0, MEASURED).bind(group)
    assert FramedInnovation(FRAME).bind(group, measurement).width == 3
    assert FramedInnovation({"p": "R", "b_v": "R"}).width == 0  # set by bind
    for frame, match in (
        ({"q": "R"}, "framed_innovation: frames names a factor 'q' that"),
        ({"p": "q"}, "framed_innovation: frames names a factor 'q' that"),
        ({"b_v": "R"}, "framed_innovation: 'b_v' must be a measured 3-vector factor"),
        ({"p": "b_v"}, r"framed_innovation: 'b_v' must be a rotation of R\^3"),
    ):
        with pytest.raises(ValueError, match=match):
            FramedInnovation(frame).bind(group, measurement)
        with pytest.raises(ValueError, match=match):  # and when the observer binds it
            rigid_observer(head=PlainHead(), extra=[FramedInnovation(frame)])
    for bad in ({"p": 3}, {}, None):
        with pytest.raises(ValueError, match="framed_innovation: frames must map vector factors"):
            FramedInnovation(bad)
    with pytest.raises(ValueError, match=r"model.features\[3\] \(framed_innovation\): "
                                         "framed_innovation: frames must map"):
        build_piece("feature", {"type": "framed_innovation", "frames": {"p": 3}},
                    "model.features[3]")
    # p not among the measured factors: no innovation to frame
    with pytest.raises(ValueError, match="'p' must be a measured 3-vector factor"):
        rigid_observer(head=PlainHead(), measurement=Measurement(18, 0, {"R": (0, 9)}),
                       features=[Innovation(), FramedInnovation(FRAME)])


def test_the_train_command_takes_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path,
        *block_overrides(
            head="{type:centred,c:0.85}",
            features="[{type:embedding,drop:[p]},{type:readings,drop:[p]},innovation,"
                     "{type:framed_innovation,frames:{p:R}}]",
        ),
    )
    assert observer.features[-1].frames == FRAME
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
