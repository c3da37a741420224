"""Torch's CPU threads, set one way by every command: :func:`use_threads`.

The observer's work per step is small (a GRU of tens to hundreds of units over one batch), so a
parallel region costs more to start and join than it saves, and on a machine whose cores other
processes share, the OpenMP workers that wait for the next region (spinning, by libgomp's
default) are the bottleneck: ``broad.apply`` on one BROAD trial took 122 s with torch's default
of one thread per core (2 on a 2-core machine shared with other jobs, load average 2.5-5.5) and
22 s with ``OMP_NUM_THREADS=1`` (docs/real_data.md, "Threads", has the command and more runs).
Hence one thread unless asked:

* ``threads`` given (a command's ``--threads``, a config's ``train.threads``): that many;
* else, when the user set ``OMP_NUM_THREADS`` (torch read it at import), the count it gives;
* else one.

A command calls it once, at the top of ``main`` before any tensor work. The inter-op pool (used
by ``torch.jit.fork`` and a few operators, not by the observer) is sized to one thread too when
it has not started yet (torch refuses to resize it once it has). ``OMP_WAIT_POLICY`` cannot be
set from here: libgomp reads it when ``import torch`` loads it, before any of this runs.
"""

from __future__ import annotations

import os

import torch

__all__ = ["use_threads"]


def use_threads(threads: int | None = None) -> int:
    """Sets torch's intra-op threads by the rule of the module docstring; returns the count.

    ``ValueError`` unless ``threads`` is ``None`` or an integer ``>= 1``."""
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ValueError(
                f"threads must be an integer >= 1 or None (one thread, or OMP_NUM_THREADS), got "
                f"{threads!r}."
            )
        count = threads
    elif os.environ.get("OMP_NUM_THREADS", "").strip():
        count = torch.get_num_threads()
    else:
        count = 1
    if torch.get_num_threads() != count:
        torch.set_num_threads(count)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # the pool has started (or was sized before): leave it
        pass
    return count
