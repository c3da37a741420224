"""Trajectory datasets: true states, measurements, inputs and metadata, stored without pickle.

A :class:`TrajectoryDataset` holds ``N`` sequences of ``T`` steps of a system on a Lie group:

* ``states``       ``(N, T+1, *group.element_shape)``: the true ``x_0 .. x_T``;
* ``measurements`` ``(N, T, measurement_dim)``: ``measurements[:, k]`` is ``y_{k+1}``;
* ``inputs``       ``(N, T, input_dim)``: ``inputs[:, k]`` is ``u_k`` (``input_dim`` may be 0);
* ``meta``         a JSON-able dict: system, group, sigma, seed, the resolved config, its hash,
  the train/val/test ``splits`` as ``{name: [start, stop]}`` ranges of sequences;
* ``mask``         optional, bool ``(N, T+1)``: ``True`` where the true state is known. Real
  recordings lose their ground truth at times (a motion-capture marker hidden); there the state
  is a placeholder on the group (finite, e.g. the identity) and ``mask`` is ``False``, and the
  losses and metrics leave those steps out. ``None``: every state is known (simulated data).

On disk (``save_dataset`` / ``load_dataset``) a dataset is one ``.npz`` file read with
``allow_pickle=False``: the float64 arrays ``states``, ``measurements``, ``inputs``, the bool
array ``mask`` when there is one, the int64 scalar ``format_version`` and ``meta`` as a JSON
string. Files are written to a temporary name
and renamed, so an interrupted write never leaves a half file; the zip entries carry a fixed
timestamp, so the same dataset always gives the same bytes.

A :class:`TrajectoryDataset` is a ``torch.utils.data.Dataset`` of sequences: ``ds[i]`` is the
one-sequence dataset ``i`` and :func:`collate_trajectories` stacks such items back along ``N``,
so ``DataLoader(ds, batch_size=B, shuffle=True, collate_fn=collate_trajectories)`` yields
``TrajectoryDataset`` batches in the ``(B, T, ...)`` layout the observer reads.

The code of this module is the file format (:func:`save_dataset`, :func:`load_dataset`); the
other names are gathered here from :mod:`manifold_nets.trajectory_dataset` (the container) and
:mod:`manifold_nets.dataset_checks` (the checks of a request and of the splits, and
:class:`DatasetError`).
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from groups import LieGroup

from .atomic import atomic_open
from .dataset_checks import (
    DatasetError,
    check_positive_int,
    check_sigma,
    check_splits,
    split_ranges,
)
from .trajectory_dataset import (  # noqa: F401  (_-names: importable here as they always were)
    _ARRAYS,
    _CHECK_CHUNK,
    TrajectoryDataset,
    _all_finite,
    _same_mask,
    collate_trajectories,
)

__all__ = [
    "FORMAT_VERSION",
    "DatasetError",
    "TrajectoryDataset",
    "collate_trajectories",
    "save_dataset",
    "load_dataset",
    "split_ranges",
    "check_splits",
    "check_positive_int",
    "check_sigma",
]

#: Version of the on-disk layout; ``load_dataset`` refuses any other.
FORMAT_VERSION = 1

_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # fixed timestamp: identical datasets give identical bytes


def _write_npz(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """An uncompressed ``.npz`` with fixed entry timestamps, written atomically."""
    with atomic_open(path, "wb") as f:
        with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, arr in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_DATE)
                info.external_attr = 0o644 << 16
                with zf.open(info, "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, arr, allow_pickle=False)


def save_dataset(ds: TrajectoryDataset, path: str | os.PathLike) -> None:
    """Writes ``ds`` to ``path`` (``.npz``, float64, no pickle) atomically: temporary file + rename.

    Raises :class:`DatasetError` for non-finite values or a ``meta`` that is not JSON-able.
    """
    if not isinstance(ds, TrajectoryDataset):
        raise TypeError(f"save_dataset expects a TrajectoryDataset, got {type(ds).__name__}.")
    ds.validate(where=str(path))
    check_splits(ds.meta.get("splits"), len(ds), where=str(path))
    try:
        meta = json.dumps(ds.meta, allow_nan=False)  # insertion order: the splits keep theirs
    except (TypeError, ValueError) as err:
        raise DatasetError(f"meta must be JSON-able (str/number/list/dict): {err}") from None
    arrays = {
        name: np.ascontiguousarray(getattr(ds, name).detach().cpu().to(torch.float64).numpy())
        for name in _ARRAYS
    }
    if ds.mask is not None:
        arrays["mask"] = np.ascontiguousarray(ds.mask.detach().cpu().numpy())
    arrays["format_version"] = np.asarray(FORMAT_VERSION, dtype=np.int64)
    arrays["meta"] = np.asarray(meta)
    _write_npz(Path(path), arrays)


_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a local file header, or an empty archive
_DEFLATE_MAX_RATIO = 1032  # deflate never expands data more than ~1032-fold
_REGENERATE = "delete it and regenerate it (mn-generate, or rerun with dataset.regenerate=true)"


def _member_header(path: Path, zf: zipfile.ZipFile, name: str, disk_size: int):
    """The ``.npy`` header ``(shape, fortran_order, dtype)`` of member ``name``, checked against
    the zip directory before any data is read: no array can claim more bytes than it holds."""
    info = zf.getinfo(f"{name}.npy")
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        raise DatasetError(
            f"{path}: member {name}.npy uses zip compression method {info.compress_type}; a "
            f"dataset is a plain (stored or deflated) .npz; {_REGENERATE}."
        )
    limit = info.compress_size * (1 if info.compress_type == zipfile.ZIP_STORED
                                  else _DEFLATE_MAX_RATIO)
    if info.compress_size > disk_size or info.file_size > limit:
        raise DatasetError(
            f"{path}: the zip directory claims {info.file_size} bytes for {name}.npy, more than "
            f"the {disk_size}-byte file can hold (a corrupt or forged file); {_REGENERATE}."
        )
    with zf.open(info) as member:
        try:
            version = np.lib.format.read_magic(member)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(member)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(member)
            else:
                raise ValueError(f"unsupported .npy format version {version}")
        except (ValueError, TypeError, SyntaxError, EOFError) as err:
            raise DatasetError(
                f"{path}: member {name}.npy has no valid .npy header ({err}); {_REGENERATE}."
            ) from None
        header_bytes = member.tell()
    if dtype.hasobject:
        raise DatasetError(
            f"{path}: {name} holds Python objects (dtype {dtype}), which would need pickle; a "
            f"dataset holds only numbers and one string; {_REGENERATE}."
        )
    if any(int(d) < 0 for d in shape):
        raise DatasetError(
            f"{path}: {name} claims the negative shape {tuple(shape)}; {_REGENERATE}."
        )
    nbytes = math.prod(int(d) for d in shape) * dtype.itemsize  # Python ints: no overflow
    available = info.file_size - header_bytes
    if nbytes > available:
        raise DatasetError(
            f"{path}: {name} claims shape {tuple(shape)} of {dtype} ({nbytes} bytes), but its "
            f"member holds only {max(available, 0)} bytes (a truncated or forged file); "
            f"{_REGENERATE}."
        )
    return shape, fortran, dtype


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays of the ``.npz`` at ``path``, each read only after its header and size check.

    Every malformed file (empty, a bare ``.npy``, not a zip, a header claiming more bytes than
    the file holds, a bad ``format_version``) is a :class:`DatasetError` naming ``path``.
    """
    disk_size = path.stat().st_size
    if disk_size == 0:
        raise DatasetError(
            f"{path} is empty (0 bytes): an interrupted copy or download; {_REGENERATE}."
        )
    with open(path, "rb") as f:
        magic = f.read(6)
    if magic == b"\x93NUMPY":
        raise DatasetError(
            f"{path} is a single .npy array, not a dataset (.npz archive of states, "
            f"measurements, inputs, format_version and meta); write datasets with "
            f"manifold_nets.data.save_dataset, or {_REGENERATE}."
        )
    if magic[:4] not in _ZIP_MAGIC:
        raise DatasetError(
            f"{path} is not a readable dataset file (not a zip/.npz archive); {_REGENERATE}."
        )
    contents: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            names = {n[: -len(".npy")] for n in zf.namelist() if n.endswith(".npy")}
            if "format_version" not in names:
                raise DatasetError(
                    f"{path} has no format_version: not a manifold_nets dataset; {_REGENERATE}."
                )
            # the version first: a file of another version may hold anything else
            order = [
                "format_version", *(n for n in (*_ARRAYS, "mask", "meta") if n in names)
            ]
            for name in order:
                shape, _, dtype = _member_header(path, zf, name, disk_size)
                if name == "format_version":
                    if shape != () or dtype.kind not in "iu":
                        raise DatasetError(
                            f"{path} has format_version of dtype {dtype} and shape "
                            f"{tuple(shape)}; it must be the integer scalar {FORMAT_VERSION} "
                            f"(this file was not written by save_dataset); {_REGENERATE}."
                        )
                elif name in _ARRAYS and dtype != np.float64:
                    raise DatasetError(
                        f"{path}: {name} has dtype {dtype}, expected float64; {_REGENERATE}."
                    )
                elif name == "mask" and dtype != np.bool_:
                    raise DatasetError(
                        f"{path}: mask has dtype {dtype}, expected bool (True where the true "
                        f"state is known); {_REGENERATE}."
                    )
                elif name == "meta" and (shape != () or dtype.kind != "U"):
                    raise DatasetError(
                        f"{path}: meta must be one JSON string, got dtype {dtype} and shape "
                        f"{tuple(shape)}; {_REGENERATE}."
                    )
                with zf.open(f"{name}.npy") as member:
                    contents[name] = np.lib.format.read_array(member, allow_pickle=False)
                if name == "format_version" and int(contents[name]) != FORMAT_VERSION:
                    raise DatasetError(
                        f"{path} has format version {contents[name].tolist()}, this code reads "
                        f"version {FORMAT_VERSION}; delete the file and regenerate it."
                    )
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zipfile.LargeZipFile) as err:
        if isinstance(err, DatasetError):
            raise
        raise DatasetError(
            f"{path} is not a readable dataset file ({err}); {_REGENERATE}."
        ) from None
    return contents


def load_dataset(
    path: str | os.PathLike, group: LieGroup | None = None, atol: float | None = None
) -> TrajectoryDataset:
    """Reads a file written by :func:`save_dataset` (``allow_pickle=False``) and validates it.

    Checks, before returning: the format version, the presence and shapes of the arrays,
    NaN/Inf, and (given ``group``) that every state is on the group. Raises
    :class:`DatasetError` (or :class:`groups.GroupMembershipError`) naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no dataset file at {path}; generate it first.")
    contents = _read_npz(path)
    missing = [k for k in (*_ARRAYS, "format_version", "meta") if k not in contents]
    if missing:
        raise DatasetError(f"{path} lacks the arrays {missing}; delete it and regenerate it.")
    try:
        meta = json.loads(str(contents["meta"]))
    except json.JSONDecodeError as err:
        raise DatasetError(
            f"{path}: meta is not valid JSON ({err}); delete the file and regenerate it."
        ) from None
    tensors = {}
    for name in _ARRAYS:
        arr = contents[name]
        if arr.dtype != np.float64:
            raise DatasetError(f"{path}: {name} has dtype {arr.dtype}, expected float64.")
        tensors[name] = torch.from_numpy(arr)
    mask = torch.from_numpy(contents["mask"]) if "mask" in contents else None
    try:
        ds = TrajectoryDataset(**tensors, meta=meta, mask=mask)
    except DatasetError as err:
        raise DatasetError(f"{path}: {err}") from None
    check_splits(ds.meta.get("splits"), len(ds), where=str(path))
    return ds.validate(group, atol=atol, where=str(path))
