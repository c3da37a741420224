"""Streamed training data: fresh simulated sequences every epoch, seeded by (seed, epoch).

The rigid body of the examples on toy sizes (a few sequences of a few steps) and a 1x8 GRU.
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import manifold_nets.cli.train as train_command
from manifold_nets import GRUCore, SimulatedStream, TrainSettings
from manifold_nets.data import TrajectoryDataset
from manifold_nets.observer import GroupUpdate, ResidualObserver
from manifold_nets.streaming import DataStream, stream_seed
from manifold_nets.training import fit
from manifold_nets_examples.rigid_body import RigidBody

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SYSTEM = RigidBody()
BIASES = {"b_omega": "absolute", "b_v": "absolute"}
FIT = {"epochs": 3, "batch_size": 4, "lr": 1e-2, "progress": False}


class RecordingStream(SimulatedStream):
    """A :class:`SimulatedStream` that records the epochs asked for and the data handed out."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.asked: list[int] = []
        self.given: list[TrajectoryDataset] = []

    def epoch(self, epoch: int) -> TrajectoryDataset:
        self.asked.append(epoch)
        self.given.append(super().epoch(epoch))
        return self.given[-1]


def make_model(seed=0) -> ResidualObserver:
    torch.manual_seed(seed)
    return ResidualObserver(
        SYSTEM.group, SYSTEM.measurement_dim,
        functools.partial(GRUCore, hidden_size=8, num_layers=1), update=GroupUpdate(BIASES),
    )


def val_data() -> TrajectoryDataset:
    return SYSTEM.simulate(4, 6, 0.0, torch.Generator().manual_seed(123))


def train_on(data, out_dir, **settings):
    return fit(
        make_model(), data, val_data(), TrainSettings(**{**FIT, **settings}), out_dir=out_dir,
        seed=7,
    )


def test_the_same_epoch_gives_the_same_data_and_other_epochs_and_seeds_differ():
    stream = SimulatedStream(SYSTEM, 5, 6, sigma=0.1, seed=3)
    first = stream.epoch(1)
    assert isinstance(stream, DataStream)
    assert first.states.shape == (5, 7, 18) and first.measurements.shape == (5, 6, 18)
    assert first == stream.epoch(1)  # bit for bit (tensors and meta), asked again ...
    assert first == SimulatedStream(SYSTEM, 5, 6, sigma=0.1, seed=3).epoch(1)  # ... or anew
    assert not torch.equal(first.states, stream.epoch(2).states)
    assert not torch.equal(first.states, SimulatedStream(SYSTEM, 5, 6, sigma=0.1).epoch(1).states)
    meta = first.meta
    assert (meta["stream_seed"], meta["epoch"], meta["sigma"], meta["noise_levels"]) == (
        3, 1, 0.1, []
    )
    assert meta["generator_seed"] == stream_seed(3, 1) < 2**63
    assert "SimulatedStream(RigidBody(" in repr(stream) and "sigma=0.1, seed=3)" in repr(stream)


def test_each_noise_level_is_the_systems_simulation_at_that_sigma():
    levels = [0.0, 0.2, 0.5]
    stream = SimulatedStream(SYSTEM, 7, 6, noise_levels=levels, seed=1)
    assert stream.level_sizes() == [3, 2, 2]
    got = stream.epoch(4)
    # what the brief promises: each level's share by system.simulate, in order, then shuffled
    gen = torch.Generator().manual_seed(stream_seed(1, 4))
    parts = [SYSTEM.simulate(k, 6, s, gen) for s, k in zip(levels, [3, 2, 2])]
    perm = torch.randperm(7, generator=gen)
    for name in ("states", "measurements", "inputs"):
        want = torch.cat([getattr(p, name) for p in parts])[perm]
        assert torch.equal(getattr(got, name), want), name
    assert got.meta["noise_levels"] == levels and got.meta["sigma"] is None
    # the noise is the system's: the measured pose of a sigma-0 sequence is the true pose, and a
    # noisy measured attitude R exp([w1]x) is still a rotation (a Gaussian added on top is not)
    pose_exact = (got.measurements[..., :12] == got.states[:, 1:, :12]).flatten(1).all(1)
    assert int(pose_exact.sum()) == 3
    rot = got.measurements[~pose_exact][..., :9].reshape(-1, 3, 3)
    eye = torch.eye(3, dtype=rot.dtype).expand_as(rot)
    torch.testing.assert_close(rot @ rot.transpose(-1, -2), eye, rtol=0, atol=1e-12)


def test_one_noise_level_is_the_stream_at_that_sigma():
    one = SimulatedStream(SYSTEM, 4, 5, noise_levels=[0.3], seed=2).epoch(1)
    plain = SimulatedStream(SYSTEM, 4, 5, sigma=0.3, seed=2).epoch(1)
    for name in ("states", "measurements", "inputs"):
        assert torch.equal(getattr(one, name), getattr(plain, name)), name


def test_fit_draws_every_epochs_data_from_the_stream(tmp_path):
    stream = RecordingStream(SYSTEM, 8, 6, sigma=0.05, seed=5)
    res = train_on(stream, tmp_path)
    assert stream.asked == [1, 2, 3]
    states = [d.states for d in stream.given]
    assert not torch.equal(states[0], states[1]) and not torch.equal(states[1], states[2])
    losses = [r["train_loss"] for r in res.history[1:]]
    assert len(losses) == 3 and all(torch.isfinite(torch.tensor(losses)))
    assert res.best_path.is_file() and res.last_path.is_file()
    assert [r["epoch"] for r in json.loads((tmp_path / "log.json").read_text())] == [0, 1, 2, 3]


def test_resume_with_a_stream_gives_the_uninterrupted_weights(tmp_path):
    straight = train_on(RecordingStream(SYSTEM, 8, 6, sigma=0.05), tmp_path / "a")
    train_on(RecordingStream(SYSTEM, 8, 6, sigma=0.05), tmp_path / "b", epochs=2)
    later = RecordingStream(SYSTEM, 8, 6, sigma=0.05)
    model = make_model(seed=123)  # another init: everything must come from the checkpoint
    fit(
        model, later, val_data(), TrainSettings(**{**FIT, "resume": str(tmp_path / "b")}),
        out_dir=tmp_path / "c", seed=7,
    )
    assert later.asked == [3]  # the resumed run asks for epoch 3's data, not the first epoch's
    want = torch.load(straight.last_path, weights_only=True)["model"]
    for name, value in model.state_dict().items():
        torch.testing.assert_close(value, want[name], rtol=0, atol=0, msg=name)


def test_fit_refuses_what_is_neither_a_dataset_nor_a_stream(tmp_path):
    with pytest.raises(TypeError, match="TrajectoryDataset or a stream with epoch"):
        train_on([1, 2, 3], tmp_path)
    with pytest.raises(ValueError, match="stream=True, but train_data is a fixed"):
        train_on(val_data(), tmp_path, stream=True)
    assert not (tmp_path / "checkpoints").exists()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"num_sequences": 0}, "num_sequences must be a positive integer, got 0"),
        ({"length": -1}, "length must be a positive integer, got -1"),
        ({"sigma": -0.1}, "sigma is the standard deviation"),
        ({"noise_levels": [0.1, -0.2]}, r"noise_levels\[1\] = -0.2: sigma .* >= 0"),
        ({"noise_levels": [0.0] * 5}, "num_sequences=4 is fewer than the 5 noise_levels"),
        ({"noise_levels": 0.1}, "noise_levels must be a list of sigmas"),
        ({"seed": 1.5}, "seed must be an integer"),
    ],
)
def test_bad_arguments_are_refused_naming_the_parameter(kwargs, match):
    args = {"num_sequences": 4, "length": 5, **kwargs}
    n, t = args.pop("num_sequences"), args.pop("length")
    with pytest.raises(ValueError, match=match) as err:
        SimulatedStream(SYSTEM, n, t, **args)
    assert str(err.value).startswith("SimulatedStream: ")


def _compose(cache: Path, *overrides: str):
    """The tiny run of experiment=default (``configs/debug/tiny.yaml``), its data in ``cache``."""
    tiny = ["experiment=default", "debug=tiny", f"dataset.cache_dir={cache}"]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose("train", overrides=[*tiny, *overrides])


def test_the_config_refuses_a_stream_from_a_data_file_before_any_work(tmp_path):
    cfg = _compose(tmp_path / "data", "train.stream=true", f"data_file={tmp_path / 'x.npz'}")
    with pytest.raises(ValueError, match=r"train.stream=true .* data_file=.*x.npz.*train.stream"):
        train_command.run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists() and not (tmp_path / "data").exists()


def test_a_tiny_run_with_train_stream_trains_on_the_stream(tmp_path, monkeypatch):
    made: list[RecordingStream] = []

    def recording(*args, **kwargs):
        made.append(RecordingStream(*args, **kwargs))
        return made[-1]

    # the module whose run() makes the stream (the command's tasks, wherever they live)
    monkeypatch.setattr(sys.modules[train_command.run.__module__], "SimulatedStream", recording)
    cfg = _compose(tmp_path / "data", "train.stream=true", "train.epochs=2")
    metrics = train_command.run(cfg, tmp_path / "run")
    (stream,) = made
    # the training split's size (32 of 40) and dataset.length, seeded by dataset.seed
    assert (stream.num_sequences, stream.length, stream.seed) == (32, 8, int(cfg.dataset.seed))
    assert stream.asked == [1, 2]
    # the validation data were made in memory: only the inference set (4 x 16) is cached
    assert [f.name for f in (tmp_path / "data").glob("*.npz") if "_40x8_" in f.name] == []
    assert list((tmp_path / "data").glob("*_4x16_*.npz"))
    assert (tmp_path / "run" / "checkpoints" / "best.pt").is_file()
    assert (tmp_path / "run" / "checkpoints" / "last.pt").is_file()
    assert metrics["best_epoch"] in (0, 1, 2)
