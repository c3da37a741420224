"""The dataset container and its file format: round trip, reproducible bytes, splits, and every
malformed input refused with a clear error."""

from __future__ import annotations

import hashlib
import json
import zipfile

import numpy as np
import pytest
import torch

from manifold_nets_examples.rigid_body import RigidBody
from groups import GroupMembershipError
from manifold_nets import data as data_mod
from manifold_nets.data import (
    FORMAT_VERSION,
    DatasetError,
    TrajectoryDataset,
    load_dataset,
    save_dataset,
    split_ranges,
)
from manifold_nets.datasets import make_dataset
from manifold_nets.progress import progress

F64 = torch.float64


@pytest.fixture(scope="module")
def body() -> RigidBody:
    return RigidBody()


@pytest.fixture(scope="module")
def ds(body) -> TrajectoryDataset:
    splits = {"train": 0.5, "val": 0.25, "test": 0.25}
    return make_dataset(body, 20, 7, sigma=0.1, seed=3, splits=splits)


def sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def rewrite(path, **changes) -> None:
    """Rewrites the arrays of an npz file with ``changes`` (a corrupt or foreign file)."""
    with np.load(path, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    arrays.update(changes)
    np.savez(path, **arrays)


def test_shapes_and_meta(ds, body):
    assert ds.states.shape == (20, 8, 18) and ds.measurements.shape == (20, 7, 18)
    assert ds.inputs.shape == (20, 7, 0) and len(ds) == 20 and ds.length == 7
    m = ds.meta
    assert m["system"] == "rigid_body" and m["seed"] == 3 and m["sigma"] == 0.1
    assert m["group"] == repr(body.group) and m["config"]["system"]["config"]["dt"] == 0.1
    assert m["splits"] == {"train": [0, 10], "val": [10, 15], "test": [15, 20]}
    json.dumps(m)  # JSON-able


def test_round_trip(ds, body, tmp_path):
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    back = load_dataset(path, group=body.group)
    assert back == ds
    assert list(back.splits()) == ["train", "val", "test"]  # the order survives the file
    assert back.states.dtype == F64
    assert not (back == ds[1:])


def test_same_seed_same_bytes_other_seed_other_bytes(body, tmp_path):
    paths = []
    for i, seed in enumerate((5, 5, 6)):
        paths.append(tmp_path / f"{i}.npz")
        save_dataset(make_dataset(body, 6, 9, sigma=0.2, seed=seed), paths[-1])
    assert sha(paths[0]) == sha(paths[1])
    assert sha(paths[0]) != sha(paths[2])
    a, c = load_dataset(paths[0]), load_dataset(paths[2])
    assert not torch.equal(a.states, c.states)


def test_the_file_is_a_plain_npz_without_pickle(ds, tmp_path):
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    with np.load(path, allow_pickle=False) as f:
        assert set(f.files) == {"states", "measurements", "inputs", "format_version", "meta"}
        assert int(f["format_version"]) == FORMAT_VERSION
        assert json.loads(str(f["meta"]))["seed"] == 3


def test_indexing_splits_and_to(ds):
    one = ds[3]
    assert len(one) == 1 and torch.equal(one.states[0], ds.states[3])
    assert len(ds[-1]) == 1 and len(ds[2:5]) == 3
    assert len(ds[torch.tensor([0, 4, 4])]) == 3
    assert "splits" not in ds[2:5].meta
    parts = ds.splits()
    assert list(parts) == ["train", "val", "test"]
    assert [len(p) for p in parts.values()] == [10, 5, 5]
    assert torch.equal(parts["val"].states, ds.states[10:15])
    assert parts["val"].meta["split"] == "val"
    with pytest.raises(KeyError, match="no split 'tune'"):
        ds.split("tune")
    with pytest.raises(IndexError):
        ds[20]
    f32 = ds.to(torch.float32)
    assert f32.states.dtype == f32.measurements.dtype == torch.float32


def test_split_ranges():
    assert split_ranges(20000, {"train": 0.8, "val": 0.1, "test": 0.1}) == {
        "train": [0, 16000], "val": [16000, 18000], "test": [18000, 20000]
    }
    assert split_ranges(7, {"a": 0.5, "b": 0.5}) == {"a": [0, 4], "b": [4, 7]}


@pytest.mark.parametrize(
    "splits, match",
    [
        ({"train": 0.8, "val": 0.1}, "sum to 0.9"),
        ({"train": 0.9, "val": 0.2}, "sum to 1.1"),
        ({"train": 1.2, "val": -0.2}, "must be > 0"),
        ({}, "at least one split"),
        ({"train": 0.99, "val": 0.01}, "gets no sequence"),
    ],
)
def test_bad_splits(splits, match, body):
    with pytest.raises(DatasetError, match=match):
        split_ranges(10, splits)
    with pytest.raises(DatasetError, match=match):
        make_dataset(body, 10, 3, splits=splits)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(sigma=-0.1), "sigma"),
        (dict(sigma=float("nan")), "sigma"),
        (dict(num_sequences=0), "num_sequences"),
        (dict(num_sequences=-3), "num_sequences"),
        (dict(length=0), "length"),
        (dict(length=2.5), "length"),
        (dict(seed=-1), "seed"),
    ],
)
def test_bad_requests_fail_before_any_work(kwargs, match, body, monkeypatch):
    def boom(*a, **k):
        raise AssertionError("simulated despite a bad request")

    monkeypatch.setattr(RigidBody, "rollout", boom)
    args = dict(num_sequences=4, length=3, sigma=0.0, seed=0) | kwargs
    with pytest.raises(DatasetError, match=match):
        make_dataset(body, **args)
    if "seed" not in kwargs:
        sim = {k: v for k, v in args.items() if k != "seed"}
        with pytest.raises(DatasetError, match=match):
            body.simulate(generator=torch.Generator(), **sim)


def test_wrong_format_version(ds, tmp_path):
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    rewrite(path, format_version=np.asarray(FORMAT_VERSION + 1, dtype=np.int64))
    with pytest.raises(DatasetError, match="format version"):
        load_dataset(path)


@pytest.mark.parametrize("array", ["states", "measurements"])
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_nan_or_inf_in_a_file(ds, tmp_path, array, value):
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    bad = getattr(ds, array).numpy().copy()
    bad[3, 2, 10] = value
    rewrite(path, **{array: bad})
    with pytest.raises(DatasetError, match="NaN/Inf"):
        load_dataset(path)


def test_states_off_the_group(ds, body, tmp_path):
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    bad = ds.states.numpy().copy()
    bad[1, 4, 0] += 1e-3  # R no longer orthonormal
    rewrite(path, states=bad)
    load_dataset(path)  # without a group only the values are checked
    with pytest.raises(GroupMembershipError, match="off the group"):
        load_dataset(path, group=body.group)


def test_other_malformed_files(ds, body, tmp_path):
    with pytest.raises(FileNotFoundError, match="generate it first"):
        load_dataset(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="not a readable dataset"):
        load_dataset(junk)
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    rewrite(path, inputs=np.zeros((20, 6, 0)))
    with pytest.raises(DatasetError, match="inconsistent sizes"):
        load_dataset(path)
    save_dataset(ds, path)
    with pytest.raises(DatasetError, match="element shape"):
        load_dataset(path, group=body.group.factor("R"))


def test_container_refuses_bad_tensors(ds):
    with pytest.raises(DatasetError, match="inconsistent sizes"):
        TrajectoryDataset(ds.states[:, :-1], ds.measurements, ds.inputs, {})
    with pytest.raises(DatasetError, match="floating-point"):
        TrajectoryDataset(ds.states.long(), ds.measurements, ds.inputs, {})
    with pytest.raises(DatasetError, match="JSON-able"):
        save_dataset(TrajectoryDataset(ds.states, ds.measurements, ds.inputs, {"x": object()}),
                     "unused.npz")


def test_interrupted_write_leaves_no_file_and_keeps_the_old_one(ds, tmp_path, monkeypatch):
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    before = sha(path)
    calls = {"n": 0}
    real = np.lib.format.write_array

    def dying(fp, arr, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt  # killed half way through the file
        return real(fp, arr, **kw)

    monkeypatch.setattr(data_mod.np.lib.format, "write_array", dying)
    with pytest.raises(KeyboardInterrupt):
        save_dataset(ds[:5], path)
    new = tmp_path / "new.npz"
    calls["n"] = 0
    with pytest.raises(KeyboardInterrupt):
        save_dataset(ds, new)
    assert sha(path) == before and not new.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npz"]  # no temporary left
    zipfile.ZipFile(path).testzip()


def test_progress_passes_items_through():
    assert list(progress(range(5), desc="x")) == [0, 1, 2, 3, 4]
    assert list(progress(iter("ab"), enabled=False)) == ["a", "b"]
