"""Per-factor centring (``CentredHead(c, factors={name: c_f})``): those factors' tangent
components are centred by ``c_f``, the others by ``c``, ramped alike. Pinned: each factor's new
estimate is the one of the constant-centring observer at its own ``c_f`` (also inside a ramp, at
``c_f k / K``); ``c_f = c`` everywhere is the plain centred observer bit for bit; the rollout, the
online and the exported steps agree; weights load across per-factor values only for
fine-tuning; bad settings say what is wrong; the train command takes it."""

from __future__ import annotations

import pytest
import torch

from manifold_nets import export_observer
from manifold_nets.builders import build_piece
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets.deploy import load_exported_step
from manifold_nets.observer import CentredHead
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_online_matches_rollout, train_tiny_and_load
from tests.test_centred_update import block_overrides, centred, rigid_observer, save, simulate

FACTORS = {"b_omega": 0.95, "b_v": 0.3}


@pytest.mark.parametrize("ramp, k", [(0, 3), (4, 2)])
def test_each_factor_moves_as_the_constant_centring_at_its_own_c(ramp, k):
    system = RigidBody()
    group = system.group
    data = simulate(system, n=3, t=6, sigma=0.2)
    mixed = rigid_observer(system, seed=3, head=CentredHead(0.6, ramp=ramp, factors=FACTORS))
    with torch.no_grad():
        _, state = mixed(data.measurements[:, :k], return_state=True)
        after = mixed.step(state, data.measurements[:, k]).estimate.flatten(1)
        r = min(1.0, k / ramp) if ramp else 1.0
        for name in group.factor_names:
            c = FACTORS.get(name, 0.6) * r
            const = rigid_observer(system, seed=3, head=centred(c))
            const.load_state_dict(mixed.state_dict())
            want = const.step(state._replace(steps=0), data.measurements[:, k]).estimate
            cols = group.element_slice(name)
            diff = (after[:, cols] - want.flatten(1)[:, cols]).abs().max()
            assert diff < 1e-12, (name, float(diff))
        other = rigid_observer(system, seed=3, head=CentredHead(0.6, ramp=ramp))
        other.load_state_dict(mixed.state_dict())
        assert not torch.allclose(other.step(state, data.measurements[:, k]).estimate.flatten(1),
                                  after, atol=1e-8)  # the factors' own c matter


def test_the_same_c_for_every_factor_is_the_plain_centred_observer():
    system = RigidBody()
    data = simulate(system, n=2, t=10, sigma=0.3)
    plain = rigid_observer(system, seed=1, head=CentredHead(0.8, ramp=3))
    same = rigid_observer(system, seed=1,
                          head=CentredHead(0.8, ramp=3, factors={"R": 0.8, "b_v": 0.8}))
    with torch.no_grad():
        assert torch.equal(same(data.measurements), plain(data.measurements))
    assert same.signature()["head"]["factors"] == {"R": 0.8, "b_v": 0.8}
    assert "factors" not in plain.signature()["head"]


def test_rollout_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=9, sigma=0.3)
    obs = rigid_observer(system, head=CentredHead(0.85, ramp=4, factors=FACTORS))
    est = assert_online_matches_rollout(obs, data.measurements)
    export_observer(obs, tmp_path / "step.pt2")
    step = load_exported_step(tmp_path / "step.pt2")
    x, *state = step.initial_state(2)
    for k in range(9):
        x, *state = step(x, *state, data.measurements[:, k])
    assert torch.allclose(x, est[:, -1].reshape(2, -1), atol=1e-10)


def test_weights_load_across_factor_values_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    plain = rigid_observer(system, seed=1, head=CentredHead(0.85, ramp=5))
    path = save(plain, tmp_path / "plain.pt")
    mixed = rigid_observer(system, seed=2, head=CentredHead(0.85, ramp=5, factors=FACTORS))
    with pytest.raises(CheckpointError, match="head.factors"):  # evaluation
        load_weights(mixed, path)
    load_weights(mixed, path, widen=True)  # train.init_from
    assert mixed.head.factors == FACTORS
    for a, b in zip(mixed.state_dict().values(), plain.state_dict().values()):
        assert torch.equal(a, b)


def test_bad_factor_values_say_what_is_wrong():
    system = RigidBody()
    with pytest.raises(ValueError, match="centred head: factors names a factor 'q' that"):
        rigid_observer(system, head=CentredHead(0.5, factors={"q": 0.5}))
    for bad in (1.5, -0.1):  # through a config block
        with pytest.raises(ValueError, match=r"model.head \(centred\): centred head: "
                                             r"factors\['R'\] must be a number"):
            build_piece("head", {"type": "centred", "c": 0.5, "factors": {"R": bad}},
                        "model.head")
    for bad in (True, "0.9", None, 1.5):
        with pytest.raises(ValueError, match=r"centred head: factors\['R'\] must be a number"):
            CentredHead(0.5, factors={"R": bad})
    with pytest.raises(ValueError, match="c = 0 centres nothing"):  # factors without a centring
        CentredHead(0.0, factors={"R": 0.5})
    with pytest.raises(ValueError, match=r"model.head \(plain\): unknown key\(s\) \['factors'\]"):
        build_piece("head", {"type": "plain", "factors": {"R": 0.5}}, "model.head")


def test_flat_factors_without_a_centring_say_so():
    """The first format's ``centering_factors`` means nothing without ``centering``: the translated
    config must refuse it, as the first format did ("but model.centering is 0"), not drop it."""
    from omegaconf import OmegaConf

    from manifold_nets.builders import build_observer
    from manifold_nets.config import ModelConfig

    system = RigidBody()
    model = OmegaConf.structured(ModelConfig(
        hidden_size=4, num_layers=1, innovation={"R": [0, 9], "p": [9, 12]}, prior="system",
        centering_factors={"R": 0.5},
    ))
    with pytest.raises(ValueError, match="centering"):
        build_observer(system.group, 18, 0, model, system=system)


def test_the_train_command_takes_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path,
        *block_overrides(head="{type:centred,c:0.85,factors:{b_omega:0.95,b_v:0.95}}"),
    )
    assert observer.head.factors == {"b_omega": 0.95, "b_v": 0.95}
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
