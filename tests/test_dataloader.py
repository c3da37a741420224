"""``TrajectoryDataset`` with ``torch.utils.data.DataLoader``: batches in the observer's layout,
and a user's own training loop over them.

The system comes from the shipped config (``configs/system/rigid_body.yaml``) rather than an
import of the examples package, so the test follows the config wherever the example lives.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from torch.utils.data import DataLoader, Dataset

import manifold_nets
from manifold_nets import (
    DatasetError,
    ModelConfig,
    TrajectoryDataset,
    build_observer,
    collate_trajectories,
    embedding_mse,
    make_dataset,
)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture(scope="module")
def system():
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=default"])
    return instantiate(cfg.system)


@pytest.fixture(scope="module")
def ds(system) -> TrajectoryDataset:
    return make_dataset(system, 18, 6, sigma=0.05, seed=2, splits={"a": 0.5, "b": 0.5})


def test_a_trajectory_dataset_is_a_torch_dataset(ds):
    assert isinstance(ds, Dataset) and len(ds) == 18
    item = ds[4]
    assert len(item) == 1 and item.length == ds.length and "splits" not in item.meta
    assert manifold_nets.collate_trajectories is collate_trajectories


def test_loader_batches_equal_indexing_by_the_same_permutation(ds):
    def loader(dataset, **kw):
        gen = torch.Generator().manual_seed(7)
        return DataLoader(dataset, batch_size=4, shuffle=True, generator=gen, **kw)

    batches = list(loader(ds, collate_fn=collate_trajectories))
    # the same loader over the indices draws the same permutation (the sampler's, from the seed)
    index_batches = list(loader(list(range(len(ds)))))
    assert [len(b) for b in batches] == [4, 4, 4, 4, 2] == [len(i) for i in index_batches]
    perm = torch.cat(index_batches)
    assert sorted(perm.tolist()) == list(range(len(ds))) and not torch.equal(perm, perm.sort()[0])
    for batch, idx in zip(batches, index_batches):
        assert isinstance(batch, TrajectoryDataset)
        assert batch == ds[idx]  # states (B, T+1, ...), measurements (B, T, l), inputs, meta
        assert batch.states.shape == (len(idx), ds.length + 1, *ds.states.shape[2:])
    assert torch.equal(torch.cat([b.measurements for b in batches]), ds.measurements[perm])


def test_collate_refuses_what_is_not_one_batch(ds, system):
    other = make_dataset(system, 2, 3, seed=0)
    with pytest.raises(DatasetError, match="same length"):
        collate_trajectories([ds[0], other[0]])
    with pytest.raises(DatasetError, match="empty"):
        collate_trajectories([])
    with pytest.raises(TypeError, match="item 1 is a Tensor"):
        collate_trajectories([ds[0], ds.states])


def test_your_own_training_loop_over_a_dataloader_lowers_the_loss(system, ds):
    torch.manual_seed(0)
    model = build_observer(
        system.group, system.measurement_dim, system.input_dim,
        ModelConfig(hidden_size=16, num_layers=1),
    )  # fmt: skip
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    loader = DataLoader(
        ds, batch_size=6, shuffle=True, collate_fn=collate_trajectories,
        generator=torch.Generator().manual_seed(0),
    )  # fmt: skip

    def loss_on(batch: TrajectoryDataset) -> torch.Tensor:
        est = model(batch.measurements, batch.inputs)
        return embedding_mse(model.group, est, batch.states.to(est))

    with torch.no_grad():
        before = float(loss_on(ds))
    for _ in range(4):
        for batch in loader:
            loss = loss_on(batch)
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        after = float(loss_on(ds))
    assert after < 0.9 * before, (before, after)
