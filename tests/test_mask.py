"""Missing ground truth: a dataset's ``mask`` travels through files, batches, the loss and ``fit``.

Real recordings lose their reference at times (a motion-capture marker hidden). Those steps hold
a placeholder state and ``mask == False``; they must never act as ground truth.
"""

from __future__ import annotations

import functools

import pytest
import torch

from groups import SO3
from manifold_nets import GRUCore, TrainSettings
from manifold_nets.data import (
    DatasetError,
    TrajectoryDataset,
    collate_trajectories,
    load_dataset,
    save_dataset,
)
from manifold_nets.losses import embedding_mse
from manifold_nets.observer import ResidualObserver
from manifold_nets.training import fit, validation_loss

G = SO3()


def make(n=6, t=8, seed=0, masked=True) -> TrajectoryDataset:
    g = torch.Generator().manual_seed(seed)
    states = G.random((n, t + 1), generator=g, dtype=torch.float64)
    meas = states[:, 1:].flatten(-2) + 0.01 * torch.randn(n, t, 9, generator=g, dtype=torch.float64)
    mask = torch.ones(n, t + 1, dtype=torch.bool)
    if masked:
        mask[:, 3:5] = False
        states[:, 3:5] = torch.eye(3, dtype=torch.float64)  # placeholders
    return TrajectoryDataset(
        states, meas, torch.zeros(n, t, 0, dtype=torch.float64), {"sigma": 0.01},
        mask if masked else None,
    )


def test_mask_round_trips_through_a_file_and_indexing(tmp_path):
    ds = make()
    save_dataset(ds, tmp_path / "d.npz")
    back = load_dataset(tmp_path / "d.npz", G)
    assert back == ds and back.mask.dtype == torch.bool
    assert torch.equal(back[2:4].mask, ds.mask[2:4])
    unmasked = make(masked=False)
    save_dataset(unmasked, tmp_path / "u.npz")
    assert load_dataset(tmp_path / "u.npz").mask is None


def test_collate_marks_every_state_of_an_unmasked_item_known():
    a, b = make(2), make(3, masked=False)
    batch = collate_trajectories([a, b])
    assert batch.mask.shape == (5, 9)
    assert torch.equal(batch.mask[:2], a.mask) and bool(batch.mask[2:].all())


def test_a_mask_of_the_wrong_shape_or_dtype_is_refused():
    ds = make()
    with pytest.raises(DatasetError, match=r"mask has shape \(6, 8\); it marks the known states"):
        TrajectoryDataset(ds.states, ds.measurements, ds.inputs, {}, ds.mask[:, 1:])
    with pytest.raises(DatasetError, match="mask must be a bool torch.Tensor"):
        TrajectoryDataset(ds.states, ds.measurements, ds.inputs, {}, ds.mask.float())


def test_masked_steps_do_not_reach_the_loss():
    ds = make()
    est = G.random((6, 9), generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    # wildly wrong placeholders change nothing: only known steps count
    other = ds.states.clone()
    other[:, 3:5] = G.random((6, 2), dtype=torch.float64)
    a = embedding_mse(G, est, ds.states, mask=ds.mask)
    b = embedding_mse(G, est, other, mask=ds.mask)
    assert torch.equal(a, b)
    keep = ds.mask.clone()
    keep[:, 0] = False  # skip=1 leaves x_0 out anyway
    sq = ((G.embed(est) - G.embed(ds.states)) ** 2).sum(-1)
    assert torch.allclose(a, sq[keep].mean() / 9)
    nothing = torch.zeros_like(ds.mask)
    assert float(embedding_mse(G, est, ds.states, mask=nothing)) == 0.0


def test_fit_trains_through_masked_data_from_a_given_start(tmp_path):
    train, val = make(12, seed=1), make(4, seed=2)
    torch.manual_seed(0)
    model = ResidualObserver(G, 9, functools.partial(GRUCore, hidden_size=8, num_layers=1))
    sizes = []

    def start(batch):  # every rollout starts at the true x_0 (a measured start in real use)
        sizes.append(len(batch))
        return batch.states[:, 0]

    before = validation_loss(model, val, start=start)
    assert before != validation_loss(model, val)  # the start is used
    sizes.clear()
    res = fit(
        model, train, val,
        TrainSettings(epochs=3, batch_size=4, lr=1e-2, progress=False),
        out_dir=tmp_path, start=start,
    )
    assert res.best_val_loss <= before
    # epoch 0's validation, then per epoch 3 training batches of 4 and one validation batch
    assert sizes == [4] + [4, 4, 4, 4] * 3


def _fit(tmp_path, name, **settings):
    torch.manual_seed(0)
    model = ResidualObserver(G, 9, functools.partial(GRUCore, hidden_size=8, num_layers=1))
    res = fit(
        model, make(12, t=12, seed=1), make(4, t=12, seed=2),
        TrainSettings(**{"epochs": 2, "batch_size": 4, "lr": 1e-2, "progress": False, **settings}),
        out_dir=tmp_path / name,
    )
    return model, res


def test_truncated_bptt_of_the_whole_length_is_plain_bptt(tmp_path):
    full, res_full = _fit(tmp_path, "full")
    one, res_one = _fit(tmp_path, "one", tbptt=12)
    for a, b in zip(full.parameters(), one.parameters()):
        assert torch.equal(a, b)
    assert [r["train_loss"] for r in res_full.history] == [r["train_loss"] for r in res_one.history]


def test_truncated_bptt_steps_per_piece_and_carries_the_state(tmp_path):
    steps = []
    torch.manual_seed(0)
    model = ResidualObserver(G, 9, functools.partial(GRUCore, hidden_size=8, num_layers=1))
    calls = []
    model.register_forward_pre_hook(lambda m, args, kwargs: calls.append(kwargs.get("state")),
                                    with_kwargs=True)
    opt_step = torch.optim.AdamW.step

    def counting(self, *a, **k):
        steps.append(1)
        return opt_step(self, *a, **k)

    torch.optim.AdamW.step = counting
    try:
        fit(model, make(8, t=12, seed=1), make(4, t=12, seed=2),
            TrainSettings(epochs=1, batch_size=4, lr=1e-2, progress=False, tbptt=5),
            out_dir=tmp_path)
    finally:
        torch.optim.AdamW.step = opt_step
    assert len(steps) == 2 * 3  # 2 batches x pieces of 5, 5, 2 steps
    # training pieces after the first start where the previous one ended (a state is passed)
    train_calls = [c for c in calls if c is not None]
    assert len(train_calls) >= 6 and all(not c.estimate.requires_grad for c in train_calls)
    with pytest.raises(ValueError, match=r"tbptt must be an integer >= 1 or None"):
        fit(model, make(8), make(4), TrainSettings(tbptt=0, progress=False), out_dir=tmp_path)
