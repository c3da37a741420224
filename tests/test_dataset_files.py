"""Hostile dataset files and unsound split metadata.

Every case builds the bad file in ``tmp_path`` and pins the whole message a user sees: it names
the file, the problem and the fix, and no raw ``EOFError``/``TypeError``/``MemoryError``/
``ZeroDivisionError`` gets through.
"""

from __future__ import annotations

import json
import re
import zipfile

import numpy as np
import pytest

from manifold_nets_examples.rigid_body import RigidBody
from manifold_nets.data import DatasetError, TrajectoryDataset, load_dataset, save_dataset
from manifold_nets.datasets import make_dataset

REGENERATE = "delete it and regenerate it (mn-generate, or rerun with dataset.regenerate=true)."
FIX_SPLITS = (
    "recompute them with manifold_nets.data.split_ranges(N, {'train': 0.8, 'val': 0.1, "
    "'test': 0.1}) (or regenerate the dataset)."
)


@pytest.fixture(scope="module")
def ds() -> TrajectoryDataset:
    return make_dataset(RigidBody(), 10, 3, sigma=0.1, seed=1,
                        splits={"train": 0.6, "val": 0.2, "test": 0.2})


def with_splits(ds: TrajectoryDataset, splits) -> TrajectoryDataset:
    return TrajectoryDataset(ds.states, ds.measurements, ds.inputs, {**ds.meta, "splits": splits})


def rewrite(path, **changes) -> None:
    """Rewrites the arrays of an npz file with ``changes`` (a corrupt or foreign file)."""
    with np.load(path, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    arrays.update(changes)
    np.savez(path, **arrays)


def raises_exactly(message: str):
    return pytest.raises(DatasetError, match=f"^{re.escape(message)}$")


# ---------------------------------------------------------------------- item 4: splits

SPLIT_CASES = [
    pytest.param(
        {"train": [0, 8], "val": [6, 10]},
        "split 'val' = [6, 10] overlaps split 'train' = [0, 8]: the same sequences would be "
        "in both (e.g. trained on and validated on); ",
        id="overlap",
    ),
    pytest.param(
        {"train": [0, 10], "val": [10, 10]},
        "split 'val' = [10, 10] is empty; a split needs 0 <= start < stop <= 10 (the number "
        "of sequences); ",
        id="empty",
    ),
    pytest.param(
        {"train": [0, 8], "val": [8, 12]},
        "split 'val' = [8, 12] is out of range; a split needs 0 <= start < stop <= 10 (the "
        "number of sequences); ",
        id="out-of-range",
    ),
    pytest.param(
        {"train": [0, 8], "val": [8.0, 10]},
        "split 'val' is [8.0, 10], not a [start, stop] pair of integers; ",
        id="not-integers",
    ),
    pytest.param(
        [[0, 8], [8, 10]],
        "meta['splits'] must be a dict {name: [start, stop]}, got list; ",
        id="not-a-dict",
    ),
]


@pytest.mark.parametrize("splits, problem", SPLIT_CASES)
def test_save_refuses_unsound_splits(ds, tmp_path, splits, problem):
    path = tmp_path / "d.npz"
    with raises_exactly(f"{path}: {problem}{FIX_SPLITS}"):
        save_dataset(with_splits(ds, splits), path)
    assert not path.exists()
    save_dataset(with_splits(ds, {"train": [0, 6], "test": [8, 10]}), path)  # gaps are fine
    assert [len(p) for p in load_dataset(path).splits().values()] == [6, 2]


@pytest.mark.parametrize("splits, problem", SPLIT_CASES)
def test_load_refuses_unsound_splits(ds, tmp_path, splits, problem):
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    rewrite(path, meta=np.asarray(json.dumps({**ds.meta, "splits": splits})))
    with raises_exactly(f"{path}: {problem}{FIX_SPLITS}"):
        load_dataset(path)


# ---------------------------------------------------------------------- item 5: hostile files


def test_empty_file(tmp_path):
    path = tmp_path / "d.npz"
    path.write_bytes(b"")
    with raises_exactly(
        f"{path} is empty (0 bytes): an interrupted copy or download; {REGENERATE}"
    ):
        load_dataset(path)


def test_npy_renamed_npz(ds, tmp_path):
    npy = tmp_path / "states.npy"
    np.save(npy, ds.states.numpy())
    path = npy.rename(tmp_path / "d.npz")
    with raises_exactly(
        f"{path} is a single .npy array, not a dataset (.npz archive of states, measurements, "
        f"inputs, format_version and meta); write datasets with "
        f"manifold_nets.data.save_dataset, or {REGENERATE}"
    ):
        load_dataset(path)


def test_header_claiming_128_pib(ds, tmp_path):
    """A 1 KB file whose states header claims 2**54 float64 values: refused before any
    allocation (numpy would try to allocate 128 PiB)."""
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    with np.load(path, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    with zipfile.ZipFile(path, "w") as zf:
        for name, arr in arrays.items():
            with zf.open(f"{name}.npy", "w") as member:
                if name == "states":
                    np.lib.format.write_array_header_1_0(
                        member, {"descr": "<f8", "fortran_order": False, "shape": (2**54,)}
                    )
                    member.write(b"\0" * 64)
                else:
                    np.lib.format.write_array(member, arr, allow_pickle=False)
    with raises_exactly(
        f"{path}: states claims shape ({2**54},) of float64 ({2**57} bytes), but its member "
        f"holds only 64 bytes (a truncated or forged file); {REGENERATE}"
    ):
        load_dataset(path)


@pytest.mark.parametrize("version, dtype", [(np.asarray("abc"), "<U3"), (np.asarray(1.7), "float64")])
def test_format_version_not_an_integer(ds, tmp_path, version, dtype):
    path = tmp_path / "d.npz"
    save_dataset(ds, path)
    rewrite(path, format_version=version)
    with raises_exactly(
        f"{path} has format_version of dtype {dtype} and shape (); it must be the integer "
        f"scalar 1 (this file was not written by save_dataset); {REGENERATE}"
    ):
        load_dataset(path)
