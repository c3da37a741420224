"""Atomic file writes: a temporary file in the same folder, flushed, fsynced, then renamed.

An interrupted run leaves either the old file or the new one, never half of one. Every file the
library writes (data sets, checkpoints, logs, tables) goes through :func:`atomic_open`.

:func:`file_lock` serialises work between processes on one machine (or on a shared file system
with working ``flock``): the dataset cache takes it so that parallel jobs of a sweep that need
the same file make it once.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

try:  # POSIX
    import fcntl
except ImportError:  # Windows: no flock
    fcntl = None

__all__ = ["atomic_open", "file_lock", "write_text_atomic"]

log = logging.getLogger(__name__)


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


@contextlib.contextmanager
def file_lock(path: str | os.PathLike) -> Iterator[Path]:
    """``with file_lock(path): ...`` holds an exclusive lock on ``<path>.lock`` for the block.

    Another process asking for the lock of the same ``path`` waits until the block ends. POSIX
    ``fcntl.flock``: released by the OS if the process dies, so a crash never leaves it stuck.
    The lock file (empty) stays behind: removing it would let a waiting process and a new one
    lock two different files. The folder is created if needed. Where ``fcntl`` is missing
    (Windows) the block runs unlocked: parallel processes may then each do the work, and
    :func:`atomic_open` still keeps every file they write whole. Yields the lock file's path.
    """
    lock_path = Path(f"{os.fspath(path)}.lock")
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    if fcntl is None:
        log.debug("no fcntl on this platform: %s is not locked", path)
        yield lock_path
        return
    with open(lock_path, "a") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield lock_path
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
