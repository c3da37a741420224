"""A progress bar for long work (tqdm), shown only on a terminal and only when asked for."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm.auto import tqdm

__all__ = ["progress"]

T = TypeVar("T")


def progress(
    iterable: Iterable[T],
    *,
    desc: str | None = None,
    total: int | None = None,
    enabled: bool = True,
) -> Iterator[T]:
    """``iterable`` wrapped in a tqdm bar when ``enabled`` and stderr is a terminal; else as is."""
    if not enabled:
        return iter(iterable)
    bar = tqdm(iterable, desc=desc, total=total, disable=None, leave=False, dynamic_ncols=True)
    return iter(bar)
