"""The compiled step: :meth:`ResidualObserver.compile_step` (``train.compile=true``).

``torch.compile`` of the one-step function with ``dynamic=False`` (the batch and the sequence
length are fixed within a run) and dynamo's ``allow_rnn``: the paper's core keeps its weights
in a ``torch.nn.GRU`` and calls ``torch.gru_cell`` on them, and without the flag dynamo stops
its graph at the first touch of the module (three graph breaks a step, four graphs), so that
most of the step ran eagerly between compiled pieces. The flag is set only while the compiled
step runs (its first call traces), not for the rest of the program.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["compiled"]


def compiled(step: Callable, **options) -> Callable:
    """``step`` compiled with ``torch.compile(step, dynamic=False, **options)``."""
    fn = torch.compile(step, **{"dynamic": False, **options})

    def run(*args):
        with torch._dynamo.config.patch(allow_rnn=True):
            return fn(*args)

    return run
