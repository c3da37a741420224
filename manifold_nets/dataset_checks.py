"""The checks of a dataset request and of its train/val/test splits, and the error they raise.

:class:`DatasetError` is what every malformed dataset or request raises (in memory, on disk:
:mod:`manifold_nets.data`); the checks of the sizes, the noise level and the split ranges are
shared by the dataset container (:mod:`manifold_nets.trajectory_dataset`), its files and the
generators.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

__all__ = [
    "DatasetError",
    "check_positive_int",
    "check_sigma",
    "check_splits",
    "split_ranges",
]


class DatasetError(ValueError):
    """A dataset (in memory or on disk) or a request for one is malformed."""


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

