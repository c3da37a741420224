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
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from groups import GroupMembershipError, LieGroup

from .atomic import atomic_open

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

_ARRAYS = ("states", "measurements", "inputs")
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # fixed timestamp: identical datasets give identical bytes
_CHECK_CHUNK = 1 << 18  # values or group elements checked at once (bounds the temporaries)


class DatasetError(ValueError):
    """A dataset (in memory or on disk) or a request for one is malformed."""


# ---------------------------------------------------------------------- argument checks


def _all_finite(t: torch.Tensor) -> bool:
    """Whether every value is finite: ``sum(x * 0) == 0`` exactly then, chunk by chunk (fast)."""
    flat = t.reshape(-1)
    return all(float((c * 0).sum()) == 0.0 for c in flat.split(_CHECK_CHUNK))


def check_positive_int(name: str, value: object) -> int:
    """``value`` as an int, or a :class:`DatasetError` unless it is a positive integer."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise DatasetError(f"{name} must be a positive integer, got {value!r}.")
    return int(value)


def check_sigma(sigma: object) -> float:
    """``sigma`` as a float, or a :class:`DatasetError` unless it is finite and ``>= 0``."""
    if isinstance(sigma, bool) or not isinstance(sigma, (int, float, np.floating)):
        raise DatasetError(f"sigma must be a number >= 0, got {sigma!r}.")
    if not math.isfinite(sigma) or sigma < 0:
        raise DatasetError(
            f"sigma is the standard deviation of the measurement noise and must be finite and "
            f">= 0 (0 for noise-free data), got {sigma!r}."
        )
    return float(sigma)


def split_ranges(num_sequences: int, fractions: Mapping[str, float]) -> dict[str, list[int]]:
    """Contiguous ``{name: [start, stop]}`` ranges of sequences for split ``fractions``.

    The fractions must be positive and sum to 1 (to 1e-9); boundaries are
    ``round(cumulative fraction * N)``, so 80/10/10 of 20000 gives exactly 16000/2000/2000.
    Every split must get at least one sequence.
    """
    n = check_positive_int("num_sequences", num_sequences)
    if not fractions:
        raise DatasetError(
            "splits must name at least one split, e.g. {train: 0.8, val: 0.1, test: 0.1}."
        )
    for name, frac in fractions.items():
        if not isinstance(name, str) or not name:
            raise DatasetError(f"split names must be non-empty strings, got {name!r}.")
        if isinstance(frac, bool) or not isinstance(frac, (int, float)) or not frac > 0:
            raise DatasetError(f"split {name!r} has fraction {frac!r}; fractions must be > 0.")
    total = math.fsum(float(f) for f in fractions.values())
    if abs(total - 1.0) > 1e-9:
        raise DatasetError(
            f"split fractions {dict(fractions)} sum to {total:.12g}, not 1; make them add up "
            "to 1, e.g. {train: 0.8, val: 0.1, test: 0.1}."
        )
    out, acc, start = {}, 0.0, 0
    for i, (name, frac) in enumerate(fractions.items()):
        acc += float(frac)
        stop = n if i == len(fractions) - 1 else int(round(acc * n))
        if stop <= start:
            raise DatasetError(
                f"split {name!r} gets no sequence out of {n}; use more sequences or fewer splits."
            )
        out[name] = [start, stop]
        start = stop
    return out


def check_splits(splits: object, num_sequences: int, where: str = "dataset") -> None:
    """Raises :class:`DatasetError` unless ``splits`` (``meta['splits']``) is sound for ``N``.

    ``None`` (no splits) passes; otherwise a dict ``{name: [start, stop]}`` of integer ranges with
    ``0 <= start < stop <= num_sequences`` (no empty split) that do not overlap. Overlapping
    train and validation ranges would validate on training data silently; an empty one divides
    by zero later. ``where`` (the file) starts every message.
    """
    if splits is None:
        return
    fix = (
        "recompute them with manifold_nets.data.split_ranges(N, {'train': 0.8, 'val': 0.1, "
        "'test': 0.1}) (or regenerate the dataset)"
    )
    if not isinstance(splits, Mapping):
        raise DatasetError(
            f"{where}: meta['splits'] must be a dict {{name: [start, stop]}}, got "
            f"{type(splits).__name__}; {fix}."
        )
    seen: list[tuple[int, int, str]] = []
    for name, rng in splits.items():
        if not isinstance(name, str) or not name:
            raise DatasetError(
                f"{where}: split names must be non-empty strings, got {name!r}; {fix}."
            )
        ok = (
            isinstance(rng, (list, tuple))
            and len(rng) == 2
            and all(
                isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))
                for v in rng
            )
        )
        if not ok:
            raise DatasetError(
                f"{where}: split {name!r} is {rng!r}, not a [start, stop] pair of integers; "
                f"{fix}."
            )
        start, stop = int(rng[0]), int(rng[1])
        if not 0 <= start < stop <= num_sequences:
            what = "is empty" if 0 <= start and start >= stop else "is out of range"
            raise DatasetError(
                f"{where}: split {name!r} = [{start}, {stop}] {what}; a split needs "
                f"0 <= start < stop <= {num_sequences} (the number of sequences); {fix}."
            )
        for s0, s1, other in seen:
            if start < s1 and s0 < stop:
                raise DatasetError(
                    f"{where}: split {name!r} = [{start}, {stop}] overlaps split {other!r} = "
                    f"[{s0}, {s1}]: the same sequences would be in both (e.g. trained on and "
                    f"validated on); {fix}."
                )
        seen.append((start, stop, name))


# ---------------------------------------------------------------------- the dataset


@dataclass(eq=False)
class TrajectoryDataset(torch.utils.data.Dataset):
    """``N`` trajectories of a system on a Lie group; see the module docstring for the shapes.

    A ``torch.utils.data.Dataset`` of ``N`` items, item ``i`` being the one-sequence dataset
    ``ds[i]``; batch it with ``collate_fn=``:func:`collate_trajectories`.
    """

    states: torch.Tensor
    measurements: torch.Tensor
    inputs: torch.Tensor
    meta: dict = field(default_factory=dict)
    mask: torch.Tensor | None = None

    def __post_init__(self) -> None:
        for name in _ARRAYS:
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor) or not t.is_floating_point():
                raise DatasetError(f"{name} must be a floating-point torch.Tensor, got {t!r:.80}.")
        s, m, u = self.states, self.measurements, self.inputs
        if s.dim() < 3 or m.dim() != 3 or u.dim() != 3:
            raise DatasetError(
                "expected states (N, T+1, *element_shape), measurements (N, T, measurement_dim) "
                f"and inputs (N, T, input_dim); got {tuple(s.shape)}, {tuple(m.shape)}, "
                f"{tuple(u.shape)}."
            )
        n, t = m.shape[:2]
        if s.shape[:2] != (n, t + 1) or u.shape[:2] != (n, t):
            raise DatasetError(
                f"inconsistent sizes: states {tuple(s.shape)} must be (N, T+1, ...) and inputs "
                f"{tuple(u.shape)} (N, T, ...) for measurements {tuple(m.shape)} (N={n}, T={t})."
            )
        if not isinstance(self.meta, dict):
            raise DatasetError(f"meta must be a dict, got {type(self.meta).__name__}.")
        if self.mask is not None:
            k = self.mask
            if not isinstance(k, torch.Tensor) or k.dtype != torch.bool:
                raise DatasetError(
                    f"mask must be a bool torch.Tensor (N, T+1) or None, got {k!r:.80}."
                )
            if tuple(k.shape) != (n, t + 1):
                raise DatasetError(
                    f"mask has shape {tuple(k.shape)}; it marks the known states and must be "
                    f"(N, T+1) = ({n}, {t + 1}) like states {tuple(s.shape)}."
                )

    # ------------------------------------------------------------------ sizes and indexing

    def __len__(self) -> int:
        return self.measurements.shape[0]

    @property
    def length(self) -> int:
        """``T``, the number of steps (measurements) per sequence."""
        return self.measurements.shape[1]

    def __getitem__(self, idx) -> TrajectoryDataset:
        """The sequences ``idx`` (an int keeps the sequence dimension: ``ds[3]`` has ``N = 1``).

        ``idx`` may be an int, a slice, or a 1-D index/boolean tensor or list. The subset's
        ``meta`` is the parent's without ``splits`` (those ranges refer to the parent).
        """
        if isinstance(idx, (int, np.integer)):
            n = len(self)
            if not -n <= idx < n:
                raise IndexError(f"sequence {idx} out of range for a dataset of {n} sequences.")
            idx = slice(int(idx) % n, int(idx) % n + 1)
        meta = {k: v for k, v in self.meta.items() if k != "splits"}
        mask = None if self.mask is None else self.mask[idx]
        return TrajectoryDataset(
            self.states[idx], self.measurements[idx], self.inputs[idx], meta, mask
        )

    def split(self, name: str) -> TrajectoryDataset:
        """The split ``name`` (``train``, ``val``, ``test``, ...) recorded in ``meta['splits']``."""
        check_splits(self.meta.get("splits"), len(self))
        ranges = self.meta.get("splits") or {}
        if name not in ranges:
            raise KeyError(f"no split {name!r} in this dataset; its splits: {sorted(ranges)}.")
        start, stop = ranges[name]
        sub = self[start:stop]
        sub.meta["split"] = name
        return sub

    def splits(self) -> dict[str, TrajectoryDataset]:
        """Every split by name, in the recorded order (the whole dataset as ``all`` if none)."""
        names = list(self.meta.get("splits") or {})
        if not names:
            return {"all": self}
        return {name: self.split(name) for name in names}

    def to(self, dtype: torch.dtype | None = None, device=None) -> TrajectoryDataset:
        """A copy with every tensor moved to ``dtype`` / ``device`` (``meta`` is shared)."""
        conv = dict(dtype=dtype, device=device)
        mask = None if self.mask is None else self.mask.to(device=device)
        return TrajectoryDataset(
            self.states.to(**conv), self.measurements.to(**conv), self.inputs.to(**conv),
            self.meta, mask,
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, TrajectoryDataset):
            return NotImplemented
        return all(
            getattr(self, a).dtype == getattr(other, a).dtype
            and torch.equal(getattr(self, a), getattr(other, a))
            for a in _ARRAYS
        ) and _same_mask(self.mask, other.mask) and self.meta == other.meta

    __hash__ = None  # mutable container of tensors

    # ------------------------------------------------------------------ validation

    def validate(
        self, group: LieGroup | None = None, atol: float | None = None, where: str = "dataset"
    ) -> TrajectoryDataset:
        """Raises unless every value is finite and, given ``group``, every state is on it.

        Also checks the states' trailing shape against ``group.element_shape``. Membership is
        checked with ``group.check_member`` (``atol`` defaults to the group's: 1e-9 in float64)
        in chunks, so it needs little memory. Returns ``self``.
        """
        for name in _ARRAYS:
            t = getattr(self, name)
            if not _all_finite(t):
                bad = int((~torch.isfinite(t)).sum())
                raise DatasetError(
                    f"{where}: {name} holds {bad} NaN/Inf value(s); regenerate the data (a "
                    "corrupt file: delete it) or find where the non-finite values come from."
                )
        if group is None:
            return self
        want = tuple(group.element_shape)
        if tuple(self.states.shape[2:]) != want:
            raise DatasetError(
                f"{where}: states have element shape {tuple(self.states.shape[2:])}, but "
                f"{group!r} has elements of shape {want}; load it with the system it was made for."
            )
        flat = self.states.reshape(-1, *want)
        for start in range(0, flat.shape[0], _CHECK_CHUNK):
            try:
                group.check_member(flat[start : start + _CHECK_CHUNK], atol=atol)
            except GroupMembershipError as err:
                raise GroupMembershipError(f"{where}: states are off the group. {err}") from None
        return self


def _same_mask(a: torch.Tensor | None, b: torch.Tensor | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return torch.equal(a, b)


def collate_trajectories(batch) -> TrajectoryDataset:
    """The datasets of ``batch`` (a sequence of :class:`TrajectoryDataset`, e.g. the one-sequence
    items a ``DataLoader`` fetched) concatenated along ``N``: one dataset, ``(B, T+1, ...)``
    states, ``(B, T, l)`` measurements, ``(B, T, m)`` inputs.

    The ``collate_fn`` of a ``torch.utils.data.DataLoader`` over a dataset::

        loader = DataLoader(ds, batch_size=64, shuffle=True, collate_fn=collate_trajectories)
        for batch in loader:
            est = observer(batch.measurements, batch.inputs)

    ``meta`` is the first item's without ``splits`` (the ranges of a parent do not describe a
    batch). All items must have the same length ``T``, element shape and sizes.
    """
    items = list(batch)
    if not items:
        raise DatasetError("collate_trajectories got an empty batch.")
    for i, item in enumerate(items):
        if not isinstance(item, TrajectoryDataset):
            raise TypeError(
                f"collate_trajectories collates TrajectoryDataset items; item {i} is a "
                f"{type(item).__name__}."
            )
    first = items[0]
    for i, item in enumerate(items[1:], 1):
        for name in _ARRAYS:
            a, b = getattr(first, name), getattr(item, name)
            if a.shape[1:] != b.shape[1:]:
                raise DatasetError(
                    f"collate_trajectories: item {i} has {name} of shape {tuple(b.shape)}, item "
                    f"0 {tuple(a.shape)}; a batch needs the same length and sizes (pad or "
                    "crop the sequences, or batch datasets of one length)."
                )
    meta = {k: v for k, v in first.meta.items() if k != "splits"}
    if len(items) == 1:
        return TrajectoryDataset(first.states, first.measurements, first.inputs, meta, first.mask)
    mask = None
    if any(item.mask is not None for item in items):  # an item without one knows every state
        mask = torch.cat([
            item.mask if item.mask is not None
            else torch.ones(item.states.shape[:2], dtype=torch.bool, device=item.states.device)
            for item in items
        ])
    return TrajectoryDataset(
        *(torch.cat([getattr(item, name) for item in items]) for name in _ARRAYS), meta, mask
    )


# ---------------------------------------------------------------------- files


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
