"""A progress bar for long work (tqdm), shown only on a terminal and only when asked for."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm.auto import tqdm

__all__ = ["progress", "progress_bar"]

T = TypeVar("T")


def progress(
    iterable: Iterable[T],
    *,
    desc: str | None = None,
    total: int | None = None,
    enabled: bool = True,
    delay: float = 0.0,
) -> Iterator[T]:
    """``iterable`` wrapped in a tqdm bar when ``enabled`` and stderr is a terminal; else as is.

    ``delay``: seconds before the bar appears, so that short work shows none.
    """
    if not enabled:
        return iter(iterable)
    bar = tqdm(
        iterable, desc=desc, total=total, disable=None, leave=False, dynamic_ncols=True,
        delay=delay,
    )  # fmt: skip
    return iter(bar)


def progress_bar(
    total: int, *, desc: str | None = None, unit: str = "it", enabled: bool = True,
    delay: float = 0.0,
):  # fmt: skip
    """A tqdm bar of ``total`` advanced by hand (``bar.update(n)``, ``bar.close()``), for work
    done in chunks (sequences in batches); shown only when ``enabled``, on a terminal, after
    ``delay`` seconds."""
    return tqdm(
        total=total, desc=desc, unit=unit, disable=None if enabled else True, leave=False,
        dynamic_ncols=True, delay=delay,
    )  # fmt: skip
