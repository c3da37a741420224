"""``train.skip_steps``: the first steps of every sequence left out of the training and validation
loss (10 matches the evaluation's ``eval.skip_steps``). Pinned: the validation loss is the loss
over steps ``k >= skip`` of the same rollout, for both losses; the skipped steps reach neither
the loss nor its gradient, with and without truncated BPTT (only its first piece skips); bad
settings say what is wrong; the train command reads it."""

from __future__ import annotations

import functools
import json
import math

import pytest
import torch

from groups import SO3
from manifold_nets import GRUCore, TrainSettings
from manifold_nets.losses import embedding_log_mse, embedding_mse
from manifold_nets.observer import ResidualObserver
from manifold_nets.training import TrainingDiverged, check_settings, fit, validation_loss
from tests.observer_checks import run_tiny, so3_walk

G = SO3()


@pytest.mark.parametrize(("loss", "fn"), [("mse", embedding_mse), ("log_mse", embedding_log_mse)])
def test_the_validation_loss_leaves_the_first_steps_out(loss, fn):
    data = so3_walk(6, 12, 1)
    torch.manual_seed(0)
    model = ResidualObserver(G, 9, functools.partial(GRUCore, hidden_size=8, num_layers=1))
    with torch.no_grad():
        est = model(data.measurements)
    for skip in (1, 5):
        want = float(fn(G, est, data.states, skip=skip))
        assert validation_loss(model, data, loss=loss, skip=skip) == pytest.approx(want, rel=1e-6)
    assert validation_loss(model, data, loss=loss, skip=5) != pytest.approx(
        validation_loss(model, data, loss=loss), rel=1e-3
    )


def poisoned(n, t, seed, upto):
    """``so3_walk`` with the true states of steps 1 .. upto-1 replaced by NaN: any loss or gradient
    that reads them is NaN."""
    data = so3_walk(n, t, seed)
    data.states[:, 1:upto] = float("nan")
    return data


@pytest.mark.parametrize("tbptt", [None, 4])
def test_the_skipped_steps_reach_neither_the_loss_nor_its_gradient(tmp_path, tbptt):
    train, val = poisoned(8, 12, 1, upto=3), poisoned(4, 12, 2, upto=3)
    torch.manual_seed(0)
    model = ResidualObserver(G, 9, functools.partial(GRUCore, hidden_size=8, num_layers=1))
    settings = dict(epochs=2, batch_size=4, lr=1e-2, progress=False, tbptt=tbptt)
    res = fit(model, train, val, TrainSettings(skip_steps=3, **settings), out_dir=tmp_path / "a")
    assert all(math.isfinite(row["val_loss"]) for row in res.history)
    assert all(math.isfinite(row["train_loss"]) for row in res.history[1:])
    assert all(torch.isfinite(p).all() for p in model.parameters())
    with pytest.raises(TrainingDiverged):  # the same data, the paper's loss: the NaN is read
        fit(model, train, val, TrainSettings(skip_steps=2, **settings), out_dir=tmp_path / "b")


def test_bad_skip_steps_say_what_is_wrong():
    check_settings(TrainSettings(skip_steps=10, tbptt=10))
    with pytest.raises(ValueError, match="skip_steps must be an integer >= 1"):
        check_settings(TrainSettings(skip_steps=0))
    with pytest.raises(ValueError, match="skip_steps must be an integer >= 1"):
        check_settings(TrainSettings(skip_steps=2.5))
    with pytest.raises(ValueError, match=r"skip_steps=10 is longer than a truncated-BPTT piece"):
        check_settings(TrainSettings(skip_steps=10, tbptt=5))


def test_the_train_command_reads_it(tmp_path):
    runs = {}
    for skip in (1, 4):
        cfg = run_tiny("default", tmp_path, tmp_path / str(skip), f"train.skip_steps={skip}")
        assert cfg.train.skip_steps == skip
        runs[skip] = json.loads((tmp_path / str(skip) / "log.json").read_text())
    # the same starting model and validation split, validated over fewer steps
    assert runs[4][0]["val_loss"] != pytest.approx(runs[1][0]["val_loss"], rel=1e-6)
