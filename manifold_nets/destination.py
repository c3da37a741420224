"""Where a command will write, checked before it does any work: :func:`check_destination`.

A command that finds a bad ``--out`` only when it writes has spent its work (minutes of
estimation or training) for a traceback. The checks here need no work and create nothing: the
name's suffix, what already stands at the path (a folder where a file goes, a file where a
folder goes, a file in the way of the folders above), and whether the folder that would hold it
(or the nearest existing one above, which the write would create folders in) takes a new file,
probed with an anonymous temporary file that disappears when closed. A place can still become
unwritable between the check and the write (a full disk); the write is atomic
(:mod:`manifold_nets.atomic`), so that leaves the old file as it was.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

__all__ = ["check_destination"]


def check_destination(
    path: str | os.PathLike, *, folder: bool = False, suffixes: Sequence[str] = (),
    option: str = "--out",
) -> Path:
    """``path`` as a :class:`~pathlib.Path` if a file (``folder=False``) or a folder
    (``folder=True``) can be written there; else ``ValueError`` naming ``option``, the path, the
    problem and the fix. ``suffixes``: the file's allowed endings (``(".npy", ".csv")``)."""
    path = Path(path)
    where = f"{option} {path}"
    if folder and path.exists() and not path.is_dir():
        raise ValueError(f"{where}: is a file, not a folder; give a new or existing folder.")
    if not folder and path.is_dir():
        raise ValueError(f"{where}: is a folder; give the path of a file in it (a new or "
                         "existing file).")
    if suffixes and path.suffix not in suffixes:
        raise ValueError(
            f"{where}: the name must end in {' or '.join(suffixes)}; give a file name such as "
            f"out{suffixes[0]}."
        )
    existing = path if folder and path.is_dir() else path.parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(
            f"{where}: {existing} is a file, so nothing can be created under it; give a path "
            "in a folder."
        )
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as err:
        raise ValueError(
            f"{where}: cannot write in {existing} ({type(err).__name__}: {err.strerror or err}); "
            "give a path in a folder you can write to."
        ) from None
    return path
