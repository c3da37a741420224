"""The dataset container: :class:`TrajectoryDataset` (states, measurements, inputs, meta, mask of
``N`` sequences), its indexing, splits and validation, and :func:`collate_trajectories`.

The shapes and the file format are described in :mod:`manifold_nets.data` (which also saves and
loads these datasets).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from groups import GroupMembershipError, LieGroup

from .dataset_checks import DatasetError, check_splits

__all__ = ["TrajectoryDataset", "collate_trajectories"]

_ARRAYS = ("states", "measurements", "inputs")
_CHECK_CHUNK = 1 << 18  # values or group elements checked at once (bounds the temporaries)


def _all_finite(t: torch.Tensor) -> bool:
    """Whether every value is finite: ``sum(x * 0) == 0`` exactly then, chunk by chunk (fast)."""
    flat = t.reshape(-1)
    return all(float((c * 0).sum()) == 0.0 for c in flat.split(_CHECK_CHUNK))


@dataclass(eq=False)
class TrajectoryDataset(torch.utils.data.Dataset):
    """``N`` trajectories of a system on a Lie group; see :mod:`manifold_nets.data` for the
    shapes.

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

