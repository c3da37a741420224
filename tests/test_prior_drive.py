"""The prior's drive (``model.prior_drive=true``, ``ObserverInputs.prior_drive``): with a model
prior the core also reads the drive the prior integrates, ``System.compensated_drive`` (the rigid
body's bias-corrected readings), as its last columns. Pinned: each system's prediction steps with
its compensated drive; the columns' values against the readings and the estimate, computed apart,
and the same at the centred update's ``z^0``; the rollout, pieces, the online and the exported
steps agree; a checkpoint without it widens for fine-tuning into an observer that computes exactly
what it did (also with the other appended inputs); bad settings say what is wrong; the train
command trains and reloads it."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf

from manifold_nets import ObserverInputs, build_observer
from manifold_nets.checkpoint import CheckpointError, load_weights
from manifold_nets.config import ModelConfig
from manifold_nets.observer import ResidualObserver
from manifold_nets_examples.attitude import Attitude
from manifold_nets_examples.planar import Planar
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_pieces_and_export_match, train_tiny_and_load
from tests.test_centred_update import rigid_observer, save, simulate
from tests.test_innovation_frame import _core_inputs

FRAME = {"p": "R"}


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


def test_the_rigid_bodys_is_the_readings_less_the_estimated_biases():
    system = RigidBody()
    data = simulate(system, n=3, t=4, sigma=0.1)
    x, y = data.states[:, 1], data.measurements[:, 1]
    want = torch.cat([y[:, 12:15] - x[:, 12:15], y[:, 15:18] - x[:, 15:18]], dim=-1)
    torch.testing.assert_close(system.compensated_drive(x, y, None), want, rtol=0, atol=0)


@pytest.mark.parametrize("centred", [False, True])
def test_the_core_reads_the_drive_from_the_estimate_before_the_prior_last(centred):
    system = RigidBody()
    data = simulate(system, n=3, t=8, sigma=0.3)
    changes = {"centering": 0.8 if centred else 0.0}
    obs = rigid_observer(system, seed=2, prior_drive=True, **changes)
    plain = rigid_observer(system, seed=2, **changes)
    assert obs.core.input_size == plain.core.input_size + 6
    seen, est = _core_inputs(obs, data.measurements)
    n = 3
    for k in range(8):
        y, x = data.measurements[:, k], est[:, k]  # x_k, before the prior moves it
        want = y[:, 12:] - x[:, 12:]
        torch.testing.assert_close(seen[k, :n, -6:], want, rtol=1e-5, atol=1e-5)
        if centred:  # z^0 reads the same drive: it is no innovation
            assert torch.equal(seen[k, n:, -6:], seen[k, :n, -6:])


def test_rollout_pieces_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=9, sigma=0.3)
    obs = rigid_observer(system, centering=0.85, centering_ramp=3, innovation_frame=FRAME,
                         prior_drive=True)
    est = assert_pieces_and_export_match(obs, data.measurements, tmp_path)
    system.group.check_member(est)


def test_a_checkpoint_without_it_widens_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.2)
    settings = dict(centering=0.85, centering_ramp=5, innovation_frame=FRAME)
    framed = rigid_observer(system, seed=1, **settings)
    with torch.no_grad():
        framed.core.gru.weight_ih_l0[:, -3:] = 0.3  # framed weights that matter
    path = save(framed, tmp_path / "framed.pt")
    driven = rigid_observer(system, seed=2, prior_drive=True, **settings)
    with pytest.raises(CheckpointError, match="prior_drive"):  # evaluation
        load_weights(driven, path)
    load_weights(driven, path, widen_gain=True)  # train.init_from
    assert float(driven.core.gru.weight_ih_l0[:, -6:].detach().abs().sum()) == 0
    with torch.no_grad():
        gap = (driven(data.measurements) - framed(data.measurements)).abs().max()
    assert float(gap) < 1e-12  # the same sums but for the zero columns' rounding order
    plain = rigid_observer(system, seed=3, centering=0.85, centering_ramp=5)
    load_weights(driven, save(plain, tmp_path / "plain.pt"), widen_gain=True)  # both missing
    with torch.no_grad():
        gap = (driven(data.measurements) - plain(data.measurements)).abs().max()
    assert float(gap) < 1e-12
    with pytest.raises(CheckpointError, match="prior_drive"):  # not dropped silently
        load_weights(framed, save(driven, tmp_path / "driven.pt"), widen_gain=True)


def test_bad_settings_say_what_is_wrong():
    system = RigidBody()
    inputs = ObserverInputs(innovation={"R": (0, 9), "p": (9, 12)}, prior_drive=6)
    assert inputs.signature()["prior_drive"] == 6
    assert "prior_drive" not in ObserverInputs().signature()  # older checkpoints
    assert inputs.appended()[-1] == ("prior_drive", 6, 6)
    for bad in (True, -1, 2.0):
        with pytest.raises(ValueError, match="prior_drive must be the width"):
            ObserverInputs(prior_drive=bad)
    common = dict(core=None, hidden_size=4, num_layers=1)
    with pytest.raises(ValueError, match="model prior, inputs.prior_drive"):  # no callable
        ResidualObserver(system.group, 18, inputs=inputs, prior=system.predict, **common)
    with pytest.raises(ValueError, match="model prior, inputs.prior_drive"):  # no prior
        ResidualObserver(system.group, 18, inputs=inputs,
                         prior_drive=system.compensated_drive, **common)
    with pytest.raises(TypeError, match="prior_drive must be a callable"):
        ResidualObserver(system.group, 18, inputs=inputs, prior=system.predict,
                         prior_drive=3, **common)
    model = OmegaConf.structured(ModelConfig(hidden_size=4, num_layers=1, prior_drive=True))
    with pytest.raises(ValueError, match="there is no model prior; set model.prior=system"):
        build_observer(system.group, 18, 0, model, system=system)
    model = OmegaConf.to_container(OmegaConf.structured(
        ModelConfig(hidden_size=4, num_layers=1, prior="system")
    ))
    model = OmegaConf.create({**model, "prior_drive": 1})  # a config read from a file
    with pytest.raises(ValueError, match="model.prior_drive must be true or false"):
        build_observer(system.group, 18, 0, model, system=system)


def test_the_train_command_takes_it_and_load_observer_rebuilds_it(tmp_path):
    observer, system, _ = train_tiny_and_load(
        "paper_cpu_prior", tmp_path, "model.centering=0.85", "++model.prior_drive=true",
    )
    assert observer.inputs.prior_drive == 6
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
