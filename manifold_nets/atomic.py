"""Atomic file writes: a temporary file in the same folder, flushed, fsynced, then renamed.

An interrupted run leaves either the old file or the new one, never half of one. Every file the
library writes (data sets, checkpoints, logs, tables) goes through :func:`atomic_open`.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

__all__ = ["atomic_open", "write_text_atomic"]


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator[IO]:
    """``with atomic_open(path, "wb") as f: ...`` writes ``path`` atomically.

    The folder is created if needed; on an exception the temporary file is removed and ``path``
    is left as it was. ``mode`` is ``"w"`` or ``"wb"``; ``kwargs`` go to ``open`` (e.g. ``newline``).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open writes whole files: mode must be 'w' or 'wb', got {mode!r}.")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Writes ``text`` to ``path`` atomically."""
    with atomic_open(path, "w") as f:
        f.write(text)
