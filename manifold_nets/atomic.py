"""Atomic file writes: a temporary file in the same folder, flushed, fsynced, then renamed.

An interrupted run leaves either the old file or the new one, never half of one. Every file the
library writes (data sets, checkpoints, logs, tables) goes through :func:`atomic_open`.

A process killed mid-write (``kill -9``, out of memory, power loss) cannot remove its temporary
file. Temporaries are therefore named ``.<name>.<host>.<pid>.<random>.tmp`` beside ``<name>``,
and the next :func:`atomic_open` of the same ``<name>`` removes the leftovers of that target:
those of a process of this host that no longer runs, and those that have not been modified for
:data:`STALE_AGE_S` (one hour) whose writer cannot be checked (another host sharing the folder,
Windows, or a temporary from a version without the pid in its name). A temporary of a live
writer of this host is never removed.

:func:`file_lock` serialises work between processes on one machine (or on a shared file system
with working ``flock``): the dataset cache takes it so that parallel jobs of a sweep that need
the same file make it once.
"""

from __future__ import annotations

import contextlib
import logging
import os
import stat
import re
import secrets
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

try:  # POSIX
    import fcntl
except ImportError:  # Windows: no flock
    fcntl = None

__all__ = [
    "STALE_AGE_S",
    "atomic_open",
    "file_lock",
    "remove_stale_temporaries",
    "write_text_atomic",
]

log = logging.getLogger(__name__)


#: Seconds after its last modification that a temporary whose writer cannot be checked (another
#: host, Windows, an old name without pid) counts as abandoned. Generous: writes take seconds.
STALE_AGE_S = 3600.0

_HOST = re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:64] or "host"


def _create_temporary(path: Path) -> tuple[int, str]:
    """Creates ``.<name>.<host>.<pid>.<random>.tmp`` beside ``path`` exclusively; ``(fd, name)``."""
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{_HOST}.{os.getpid()}.{secrets.token_hex(6)}.tmp"
        try:
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0),
                         0o600)
        except FileExistsError:
            continue
        return fd, str(tmp)
    raise FileExistsError(f"could not create a temporary file beside {path}")


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (POSIX ``kill(pid, 0)``; EPERM means yes)."""
    if pid <= 0:
        return True  # not a real writer's pid: never judge it dead
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: it exists, under another user
        return True
    return True


def remove_stale_temporaries(
    path: str | os.PathLike, max_age_s: float = STALE_AGE_S
) -> list[Path]:
    """Removes the temporaries that killed writers of ``path`` left beside it; returns them.

    A temporary ``.<name>.<host>.<pid>.<random>.tmp`` of this host goes when process ``pid`` no
    longer exists; one of another host (or on Windows, where ``os.kill(pid, 0)`` would signal
    the process) goes when unmodified for ``max_age_s``, as does an old-style
    ``.<name>.<8 characters>.tmp`` (from before the pid was in the name). A live writer's
    temporary stays. Failures to list or remove are logged and ignored: cleaning up must never
    break a write.
    """
    path = Path(path)
    name = re.escape(path.name)
    new_style = re.compile(rf"\.{name}\.([A-Za-z0-9-]+)\.(\d+)\.[0-9a-f]{{12}}\.tmp")
    old_style = re.compile(rf"\.{name}\.[a-z0-9_]{{8}}\.tmp")
    removed: list[Path] = []
    try:
        entries = list(os.scandir(path.parent))
    except OSError as err:
        log.debug("cannot list %s for stale temporaries: %s", path.parent, err)
        return removed
    now = time.time()
    for entry in entries:
        m = new_style.fullmatch(entry.name)
        if m is None and old_style.fullmatch(entry.name) is None:
            continue
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            if m is not None and m.group(1) == _HOST and os.name == "posix":
                stale = not _pid_alive(int(m.group(2)))
            else:
                stale = now - entry.stat(follow_symlinks=False).st_mtime > max_age_s
            if stale:
                os.unlink(entry.path)
                removed.append(Path(entry.path))
                log.info("removed %s, left by an interrupted write of %s", entry.path, path)
        except OSError as err:  # gone already (another cleaner), or not ours to remove
            log.debug("could not remove stale temporary %s: %s", entry.path, err)
    return removed


def _umask() -> int:
    """The process's umask, read without changing it where the system says it (Linux), else by
    setting it and back."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _mode_for(path: Path) -> int:
    """The mode of the file that replaces ``path``: the mode ``path`` has (a replaced file keeps
    its permissions), or for a new file what ``open`` would give it under the user's umask."""
    try:
        return stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        return 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator[IO]:
    """``with atomic_open(path, "wb") as f: ...`` writes ``path`` atomically.

    The folder is created if needed; on an exception the temporary file is removed and ``path``
    is left as it was. Temporaries that killed writers of ``path`` left behind are removed first
    (:func:`remove_stale_temporaries`). A new file gets the permissions the user's umask gives;
    a replaced one keeps its own. ``mode`` is ``"w"`` or ``"wb"``; ``kwargs`` go to ``open`` (e.g. ``newline``).
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open writes whole files: mode must be 'w' or 'wb', got {mode!r}.")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    fd, tmp = _create_temporary(path)
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _mode_for(path))
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
